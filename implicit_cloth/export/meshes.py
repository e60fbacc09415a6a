"""OBJ (with normals and UVs), PC2 point caches and PLY.

Axes: OBJ and PC2 are written **y-up** (``(x, y, z)_sim -> (x, z, -y)``), the convention of the tools that read
them (Blender's and Houdini's OBJ importers assume it and turn it back to their own up axis); PLY keeps the
simulation's z-up. Units: metres.

PC2 (the format of Blender's *Mesh Cache* modifier and 3ds Max's Point Cache): a 32-byte header
``b"POINTCACHE2\\0"``, int32 version 1, int32 number of points, float32 start frame, float32 sample rate (frames
per sample), int32 number of samples; then the samples' points, float32 little-endian, ``(samples, points, 3)``.
Its points are in the vertex order of the rest-pose OBJ written beside it, which is the run's vertex order.
The start frame and the sample rate count frames at the run's frame rate (the scene's ``frame_rate``, or
``1 / dt`` when every step is kept; :func:`implicit_cloth.export.pc2_timing`): exporting every kept frame gives
start 0 and rate 1. Blender's Mesh Cache modifier, in its default *Frames* time mode, ignores the header's start
and rate and plays sample ``k`` at scene frame ``k`` (plus the modifier's *Frame Start*): set the scene's frame
rate to the run's, and for every n-th frame exported (``--frames``) the modifier's *Frame Scale* to ``1/n``.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ..files import atomic_write
from ..results import vertex_normals
from .staging import write_bytes

#: z-up (simulation) to y-up: (x, y, z) -> (x, z, -y), a rotation of -90 degrees about x.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

PC2_MAGIC = b"POINTCACHE2\0"
PC2_HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                       ("rate", "<f4"), ("samples", "<i4")])


def y_up(points: np.ndarray) -> np.ndarray:
    """Simulation (z-up) coordinates (..., 3) as y-up ones."""
    return np.asarray(points, float) @ Z_UP_TO_Y_UP.T


def obj_text(positions: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None = None, comment: str = "") -> str:
    """An OBJ of one frame (simulation coordinates, written y-up): ``v``, ``vt`` (if given), ``vn``, ``f v/vt/vn``.

    Vertex ``k`` of the run is the file's vertex ``k + 1`` (OBJ counts from 1).
    """
    buf = io.StringIO()
    buf.write("# implicit_cloth: metres, y-up (simulation z-up (x, y, z) written as (x, z, -y))\n")
    if comment:
        buf.write(f"# {comment}\n")
    np.savetxt(buf, y_up(positions), fmt="v %.9g %.9g %.9g")
    if uvs is not None:
        np.savetxt(buf, uvs, fmt="vt %.9g %.9g")
    np.savetxt(buf, y_up(vertex_normals(positions, faces)), fmt="vn %.6f %.6f %.6f")
    f = np.asarray(faces, np.int64) + 1
    if uvs is not None:
        np.savetxt(buf, np.repeat(f, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    else:
        np.savetxt(buf, np.repeat(f, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
    return buf.getvalue()


def write_obj(path: str | os.PathLike[str], positions: np.ndarray, faces: np.ndarray,
              uvs: np.ndarray | None = None, comment: str = "") -> Path:
    text = obj_text(positions, faces, uvs, comment)
    return write_bytes(path, text.encode("ascii"))


def write_pc2(path: str | os.PathLike[str], samples: np.ndarray, start: float = 0.0, rate: float = 1.0) -> Path:
    """A PC2 file of ``samples`` (S, N, 3) in simulation coordinates, written y-up like the rest-pose OBJ.

    ``start`` is the first sample's frame and ``rate`` the frames between samples (both in the scene's frames).
    """
    samples = np.asarray(samples, float)
    header = np.array([(PC2_MAGIC, 1, samples.shape[1], start, rate, samples.shape[0])], PC2_HEADER)

    def write(fh) -> None:
        fh.write(header.tobytes())
        fh.write(np.ascontiguousarray(y_up(samples), dtype="<f4").tobytes())
    return atomic_write(path, write)


def read_pc2(path: str | os.PathLike[str], z_up: bool = True) -> tuple[np.ndarray, float, float]:
    """Points (S, N, 3), start frame and sample rate of a PC2 file; ``z_up`` turns y-up points back to z-up."""
    data = Path(path).read_bytes()
    header = np.frombuffer(data[:PC2_HEADER.itemsize], PC2_HEADER)[0]
    if header["magic"] != PC2_MAGIC.rstrip(b"\0") or header["version"] != 1:
        raise ValueError(f"{path}: not a PC2 file (magic {header['magic']!r}, version {header['version']})")
    s, n = int(header["samples"]), int(header["points"])
    pts = np.frombuffer(data[PC2_HEADER.itemsize:], "<f4", count=s * n * 3).reshape(s, n, 3).astype(float)
    if z_up:
        pts = pts @ Z_UP_TO_Y_UP      # the inverse (transpose) of the rotation, applied to row vectors
    return pts, float(header["start"]), float(header["rate"])


def ply_bytes(positions: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary PLY of one frame (simulation coordinates, z-up) with vertex normals (trimesh's writer)."""
    import trimesh

    mesh = trimesh.Trimesh(positions, faces, vertex_normals=vertex_normals(positions, faces), process=False)
    data = mesh.export(file_type="ply", include_attributes=True)
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)
