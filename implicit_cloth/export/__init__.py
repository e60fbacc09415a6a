"""Export a run for other tools: animated USD, PC2 point cache, animated glTF/GLB, or OBJ/PLY per frame.

=========  ============================================================  ======  =====================
format     files (in ``RUN_DIR/export`` by default)                      up      animation
=========  ============================================================  ======  =====================
``usd``    ``animation.usd`` (binary crate; needs the ``usd`` extra)     Z       time-sampled points,
                                                                                 normals, transforms
``pc2``    ``animation.pc2`` + ``rest.obj`` (its vertex order)           Y       point cache (Blender's
                                                                                 Mesh Cache modifier)
``glb``    ``animation.glb``                                             Y       morph targets + weights
``gltf``   ``animation.gltf`` + ``animation.bin``                        Y       morph targets + weights
``obj``    ``frame_0000.obj`` ... (``v``, ``vt`` for grids, ``vn``)      Y       one file per frame
``ply``    ``frame_0000.ply`` ... (binary, vertex normals)               Z       one file per frame
=========  ============================================================  ======  =====================

Metres throughout. The run's vertex numbering is kept: vertex ``k`` of ``trajectory.npz`` is OBJ vertex
``k + 1``, PC2 point ``k``; USD and glTF store a mesh per connected cloth piece with the run's index of each
point (``primvars:sourceVertexIndex``, ``extras.sourceVertexIndex``). Obstacles of the run's scene (USD and glTF)
are placed at every frame by the collision code's own motion (:mod:`implicit_cloth.results`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..errors import show as _fmt
from ..results import read_run
from .staging import write_bytes

FORMATS: tuple[str, ...] = ("usd", "pc2", "glb", "gltf", "obj", "ply")


def load_run(run_dir: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``positions (F, N, 3)`` m, ``times (F,)`` s and ``faces (T, 3)`` from ``RUN_DIR/trajectory.npz``.

    Raises
    ------
    InputError
        If the file is missing or unreadable (one line naming it).
    """
    run = read_run(run_dir)
    return run.positions, run.times, run.faces


def select_frames(n_frames: int, frames: Sequence[int] | None) -> list[int]:
    """Frame indices (negative ones count from the end) checked against ``n_frames``; all frames by default."""
    if frames is None:
        return list(range(n_frames))
    out = []
    for k, f in enumerate(frames):
        if not -n_frames <= f < n_frames:
            raise InputError(f"--frames[{k}]: frame index out of range (the run has {n_frames} frames, "
                             f"0 to {n_frames - 1}, or negative from the end), got {f}")
        out.append(f % n_frames)
    return out


def pc2_timing(codes: np.ndarray, frames: Sequence[int] | None = None) -> tuple[float, float]:
    """PC2's start frame and sample rate (frames per sample) for the exported frames' time codes ``codes``.

    The frames are counted at the run's frame rate (``Run.fps``: the scene's ``frame_rate``, or ``1 / dt`` when
    every step is kept). A kept frame lies on the step nearest its nominal time ``k / frame_rate``, up to half a
    step (less than half a frame) away, so its time code is rounded to the nominal frame ``k``: the samples of
    the hanging example (``dt`` 0.01 s, 30 frames a second, kept at 0, 0.03, 0.07, 0.1, ... s) are frames 0, 1,
    2, 3, ..., one frame apart: a reader honouring the header plays the 2 s run in 2 s at 30 frames a second.
    PC2 has one sample rate: frames chosen with unequal gaps cannot be written.

    Raises
    ------
    InputError
        If the exported frames are not evenly spaced.
    """
    nominal = np.rint(np.asarray(codes, float))
    if len(nominal) < 2:
        return float(nominal[0]) if len(nominal) else 0.0, 1.0
    gaps = np.diff(nominal)
    if np.any(gaps != gaps[0]):
        raise InputError(f"--frames: a PC2 point cache holds evenly spaced samples (one sample rate), got frames "
                         f"{list(frames) if frames is not None else 'all'} at unequal intervals of time")
    return float(nominal[0]), float(gaps[0])


def export_run(run_dir: str | os.PathLike[str], fmt: str = "usd", out: str | os.PathLike[str] | None = None,
               frames: Sequence[int] | None = None) -> list[Path]:
    """Write the run's frames in one of :data:`FORMATS` (see the module's table).

    Parameters
    ----------
    run_dir : path
        A directory with ``trajectory.npz`` (from ``implicit-cloth run`` or a batch case) and, for the
        obstacles and the frame rate, ``report.json``.
    fmt : str
        One of :data:`FORMATS`.
    out : path, optional
        Output directory (default ``RUN_DIR/export``).
    frames : list of int, optional
        Frame indices to export (default all); the animated formats need them in increasing time order.

    Returns
    -------
    list of Path
        The files written (each atomically).

    Raises
    ------
    InputError
        Unknown format, a frame out of range or out of order (one line).
    ImportError
        ``usd`` without usd-core (``pip install 'implicit_cloth[usd]'``).
    """
    if fmt not in FORMATS:
        raise InputError(f"--format: must be one of {', '.join(FORMATS)}, got {_fmt(fmt)}")
    run = read_run(run_dir)
    idx = select_frames(run.n_frames, frames)
    if fmt in ("usd", "pc2", "glb", "gltf") and any(b <= a for a, b in zip(idx, idx[1:])):
        raise InputError(f"--frames: an animation needs its frames in increasing order without repeats, "
                         f"got {list(frames or [])}")
    target = Path(out) if out is not None else Path(run_dir) / "export"
    target.mkdir(parents=True, exist_ok=True)
    if fmt == "usd":
        from .usd import write_usd

        return [write_usd(run, idx, target / "animation.usd")]
    if fmt in ("glb", "gltf"):
        from .gltf import write_glb, write_gltf

        if fmt == "glb":
            return [write_glb(run, idx, target / "animation.glb")]
        return write_gltf(run, idx, target / "animation.gltf")
    from .meshes import ply_bytes, write_obj, write_pc2

    uvs = run.uvs()
    if fmt == "pc2":
        start, rate = pc2_timing(run.time_codes()[idx], frames)      # before writing: unequal gaps are refused
        rest = write_obj(target / "rest.obj", run.positions[idx[0]], run.faces, uvs,
                         comment=f"rest pose of animation.pc2: frame {idx[0]}, t = {run.times[idx[0]]:g} s")
        return [rest, write_pc2(target / "animation.pc2", run.positions[idx], start=start, rate=rate)]
    width = max(4, len(str(run.n_frames - 1)))
    written: list[Path] = []
    for f in idx:
        name = target / f"frame_{f:0{width}d}.{fmt}"
        if fmt == "obj":
            written.append(write_obj(name, run.positions[f], run.faces, uvs,
                                     comment=f"frame {f}, t = {run.times[f]:.9g} s"))
        else:
            written.append(write_bytes(name, ply_bytes(run.positions[f], run.faces)))
    return written
