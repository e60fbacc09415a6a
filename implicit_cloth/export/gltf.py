"""glTF 2.0 export (``.glb`` binary or ``.gltf`` + ``.bin``) with the cloth animated by morph targets.

glTF is y-up and in metres: every coordinate is converted from the simulation's z-up, ``(x, y, z) -> (x, z, -y)``
(Blender's importer turns it back). Each cloth piece is one mesh whose base shape is the first exported frame
and which has one morph target per later frame (``POSITION`` and ``NORMAL`` displacements, named
``frame_NNNN`` in ``extras.targetNames``, which Blender reads as shape-key names). One animation,
``simulation``, keys the weights at the frames' times (LINEAR): at frame k's time target k has weight 1 and the
others 0, so the shape is that frame's exactly; between frames it blends the two neighbours linearly. Obstacles
are meshes in their local frame under nodes whose translation and rotation are keyed at every frame when they
move. The glTF mesh of piece ``k`` stores, in ``extras.sourceVertexIndex``, the run's vertex index of each of
its vertices.
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..results import Run, vertex_normals
from .meshes import Z_UP_TO_Y_UP, y_up
from .staging import write_bytes

#: Most morph targets (frames - 1) written: the weights animation stores targets x frames numbers.
MAX_MORPH_FRAMES = 1024

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Builder:
    """Accumulates the binary buffer and the JSON's bufferViews and accessors."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.size = 0
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, array: np.ndarray, kind: str, target: int | None = None, bounds: bool = False) -> int:
        """Append an accessor of ``array`` (float32 or uint32) and return its index."""
        a = np.ascontiguousarray(array, dtype=np.uint32 if kind == "SCALAR_UINT" else np.float32)
        data = a.tobytes()
        view: dict[str, Any] = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.chunks.append(data + b"\0" * (-len(data) % 4))
        self.size += len(data) + (-len(data) % 4)
        width = {"SCALAR": 1, "SCALAR_UINT": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[kind]
        acc: dict[str, Any] = {"bufferView": len(self.views) - 1, "componentType": _UINT if kind == "SCALAR_UINT"
                               else _FLOAT, "count": int(a.size // width), "type": kind.replace("_UINT", "")}
        if bounds:
            flat = a.reshape(-1, width)
            acc["min"] = [float(v) for v in flat.min(0)]
            acc["max"] = [float(v) for v in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.chunks)


def _quaternions(Rs: np.ndarray) -> np.ndarray:
    """glTF quaternions (x, y, z, w) of rotation matrices (K, 3, 3), signs kept continuous for interpolation."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(Rs).as_quat()
    for k in range(1, len(q)):
        if np.dot(q[k], q[k - 1]) < 0:
            q[k] = -q[k]
    return q


def build_gltf(run: Run, frames: list[int]) -> tuple[dict[str, Any], bytes]:
    """The glTF JSON document and its binary buffer for the chosen frames of ``run``."""
    if len(frames) - 1 > MAX_MORPH_FRAMES:
        raise InputError(f"--frames: glTF keeps one morph target per frame and takes at most "
                         f"{MAX_MORPH_FRAMES + 1} frames (use --frames to pick fewer, or --format usd / pc2), "
                         f"got {len(frames)}")
    b = _Builder()
    positions = y_up(run.positions[frames])
    normals = y_up(vertex_normals(run.positions[frames], run.faces))
    times = run.times[frames] - run.times[frames[0]]
    uvs = run.uvs()
    nodes: list[dict[str, Any]] = []
    meshes: list[dict[str, Any]] = []
    channels, samplers = [], []
    time_acc = b.add(times, "SCALAR", bounds=True) if len(frames) > 1 else None
    n_targets = len(frames) - 1
    names = [f"frame_{f:04d}" for f in frames[1:]]
    for k, verts in enumerate(run.pieces()):
        local = np.full(run.positions.shape[1], -1, np.int64)
        local[verts] = np.arange(len(verts))
        faces = local[run.faces[np.isin(run.faces[:, 0], verts)]]
        p, n = positions[:, verts], normals[:, verts]
        attrs = {"POSITION": b.add(p[0], "VEC3", _ARRAY_BUFFER, bounds=True),
                 "NORMAL": b.add(n[0], "VEC3", _ARRAY_BUFFER)}
        if uvs is not None:
            # glTF's v runs down the image: v = 1 - v
            attrs["TEXCOORD_0"] = b.add(np.stack([uvs[verts, 0], 1.0 - uvs[verts, 1]], 1), "VEC2", _ARRAY_BUFFER)
        targets = [{"POSITION": b.add(p[t] - p[0], "VEC3", _ARRAY_BUFFER, bounds=True),
                    "NORMAL": b.add(n[t] - n[0], "VEC3", _ARRAY_BUFFER)} for t in range(1, len(frames))]
        prim: dict[str, Any] = {"attributes": attrs, "indices": b.add(faces.ravel(), "SCALAR_UINT",
                                                                      _ELEMENT_ARRAY_BUFFER), "mode": 4}
        mesh: dict[str, Any] = {"name": f"cloth_piece_{k}", "primitives": [prim],
                                "extras": {"sourceVertexIndex": [int(v) for v in verts]}}
        if n_targets:
            prim["targets"] = targets
            mesh["weights"] = [0.0] * n_targets
            mesh["extras"]["targetNames"] = names
        meshes.append(mesh)
        nodes.append({"name": f"cloth_piece_{k}", "mesh": len(meshes) - 1})
        if n_targets and time_acc is not None:
            weights = np.zeros((len(frames), n_targets))
            weights[np.arange(1, len(frames)), np.arange(n_targets)] = 1.0
            samplers.append({"input": time_acc, "output": b.add(weights.ravel(), "SCALAR"),
                             "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": len(nodes) - 1, "path": "weights"}})
    for ob in run.obstacles():
        prim = {"attributes": {"POSITION": b.add(ob.vertices, "VEC3", _ARRAY_BUFFER, bounds=True),
                               "NORMAL": b.add(vertex_normals(ob.vertices, ob.faces), "VEC3", _ARRAY_BUFFER)},
                "indices": b.add(ob.faces.ravel(), "SCALAR_UINT", _ELEMENT_ARRAY_BUFFER), "mode": 4}
        meshes.append({"name": ob.name, "primitives": [prim]})
        poses = [ob.pose(run.times[f]) for f in frames]
        cs = np.array([c for c, _ in poses]) @ Z_UP_TO_Y_UP.T
        qs = _quaternions(np.array([Z_UP_TO_Y_UP @ R for _, R in poses]))
        nodes.append({"name": ob.name, "mesh": len(meshes) - 1, "translation": [float(v) for v in cs[0]],
                      "rotation": [float(v) for v in qs[0]]})
        if ob.motion.moving and time_acc is not None:
            for path, values in (("translation", cs), ("rotation", qs)):
                samplers.append({"input": time_acc, "output": b.add(values, "VEC3" if path == "translation"
                                                                    else "VEC4"), "interpolation": "LINEAR"})
                channels.append({"sampler": len(samplers) - 1, "target": {"node": len(nodes) - 1, "path": path}})
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "implicit_cloth",
                  "extras": {"units": "metres", "up": "+Y (converted from the simulation's +Z)",
                             "frames": [int(f) for f in frames], "times": [float(t) for t in run.times[frames]]}},
        "scene": 0, "scenes": [{"name": "simulation", "nodes": list(range(len(nodes)))}],
        "nodes": nodes, "meshes": meshes, "accessors": b.accessors, "bufferViews": b.views,
        "buffers": [{"byteLength": b.size}],
    }
    if channels:
        doc["animations"] = [{"name": "simulation", "channels": channels, "samplers": samplers}]
    return doc, b.blob()


def write_glb(run: Run, frames: list[int], path: str | os.PathLike[str]) -> Path:
    """One binary glTF file: a 12-byte header, the JSON chunk, the BIN chunk."""
    doc, blob = build_gltf(run, frames)
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    data = (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(blob), b"BIN\0") + blob)
    return write_bytes(path, data)


def write_gltf(run: Run, frames: list[int], path: str | os.PathLike[str]) -> list[Path]:
    """A text glTF file and its buffer beside it (``NAME.gltf`` + ``NAME.bin``; the buffer is written first)."""
    path = Path(path)
    doc, blob = build_gltf(run, frames)
    bin_path = path.with_suffix(".bin")
    doc["buffers"][0]["uri"] = bin_path.name
    text = json.dumps(doc, indent=1).encode("utf-8")
    return [write_bytes(bin_path, blob), write_bytes(path, text)]
