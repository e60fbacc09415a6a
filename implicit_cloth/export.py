"""Export a run's frames as meshes (trimesh): OBJ or PLY per frame, or one GLB with a node per frame."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import SceneError, show
from .files import atomic_write

FORMATS: tuple[str, ...] = ("obj", "ply", "glb")


def load_run(run_dir: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``positions (F, N, 3)`` m, ``times (F,)`` s and ``faces (T, 3)`` from ``RUN_DIR/trajectory.npz``.

    Raises
    ------
    SceneError
        If the file is missing or unreadable (one line naming it).
    """
    p = Path(run_dir) / "trajectory.npz"
    if not p.is_file():
        raise SceneError(f"RUN_DIR: no trajectory.npz (not a run output directory), got {show(str(run_dir))}")
    try:
        with np.load(p) as z:
            return np.asarray(z["positions"], float), np.asarray(z["times"], float), np.asarray(z["faces"], np.int64)
    except (OSError, ValueError, KeyError) as exc:
        raise SceneError(f"RUN_DIR: cannot read {p} ({' '.join(str(exc).split())}), got {show(str(run_dir))}") from None


def select_frames(n_frames: int, frames: Sequence[int] | None) -> list[int]:
    """Frame indices (negative ones count from the end) checked against ``n_frames``; all frames by default."""
    if frames is None:
        return list(range(n_frames))
    out = []
    for k, f in enumerate(frames):
        if not -n_frames <= f < n_frames:
            raise SceneError(f"--frames[{k}]: frame index out of range (the run has {n_frames} frames, "
                             f"0 to {n_frames - 1}, or negative from the end), got {f}")
        out.append(f % n_frames)
    return out


def export_run(run_dir: str | os.PathLike[str], fmt: str = "obj", out: str | os.PathLike[str] | None = None,
               frames: Sequence[int] | None = None) -> list[Path]:
    """Write the run's frames as meshes.

    Parameters
    ----------
    run_dir : path
        A directory with ``trajectory.npz`` (from ``implicit-cloth run`` or a batch case).
    fmt : {"obj", "ply", "glb"}
        ``obj``/``ply``: one file per frame, ``frame_0000.obj`` ...; ``glb``:
        one binary glTF file ``frames.glb`` holding one mesh node per frame
        (named ``frame_0000`` ..., the frame's time in s in the mesh's extras
        as ``time``; trimesh reads it back into ``geometry.metadata["time"]``).
    out : path, optional
        Output directory (default ``RUN_DIR/export``).
    frames : list of int, optional
        Frame indices to export (default all).

    Returns
    -------
    list of Path
        The files written (each atomically). Coordinates are in metres.
    """
    import trimesh

    if fmt not in FORMATS:
        raise SceneError(f"--format: must be one of {', '.join(FORMATS)}, got {show(fmt)}")
    positions, times, faces = load_run(run_dir)
    idx = select_frames(len(positions), frames)
    out = Path(out) if out is not None else Path(run_dir) / "export"
    out.mkdir(parents=True, exist_ok=True)
    width = max(4, len(str(len(positions) - 1)))
    written: list[Path] = []
    if fmt == "glb":
        scene = trimesh.Scene()
        for f in idx:
            name = f"frame_{f:0{width}d}"
            mesh = trimesh.Trimesh(positions[f], faces, process=False)
            mesh.metadata["time"] = float(times[f])
            scene.add_geometry(mesh, node_name=name, geom_name=name)
        data = scene.export(file_type="glb")
        written.append(atomic_write(out / "frames.glb", lambda fh: fh.write(data)))
        return written
    for f in idx:
        mesh = trimesh.Trimesh(positions[f], faces, process=False)
        data = mesh.export(file_type=fmt)
        blob = data.encode("utf-8") if isinstance(data, str) else data
        written.append(atomic_write(out / f"frame_{f:0{width}d}.{fmt}", lambda fh, b=blob: fh.write(b)))
    return written
