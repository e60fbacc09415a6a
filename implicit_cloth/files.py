"""Files: atomic output (write to a temporary file beside the target, then rename) and a run's pair of files.

A killed process or a full disk therefore never leaves a half-written file in
place of a previous good one. :func:`write_run` writes a run's
``trajectory.npz`` and ``report.json`` as a pair; :func:`load_run` reads them back.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Mapping, Protocol

import numpy as np

from .report import RunReport


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object]) -> Path:
    """Call ``write(f)`` on a temporary file in ``path``'s directory, fsync it, and rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())              # mkstemp makes 0600; give a normal file's mode
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npz(path: str | os.PathLike[str], **arrays: np.ndarray) -> Path:
    """Atomically write a compressed ``.npz`` with the given arrays."""
    return atomic_write(path, lambda f: np.savez_compressed(f, **arrays))  # type: ignore[arg-type]  # numpy stubs


def save_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Atomically write ``obj`` as indented JSON (non-finite floats become null)."""
    text = json.dumps(_finite(obj), indent=2, allow_nan=False)
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    return obj


class RunLike(Protocol):
    """What :func:`write_run` needs of a run: a :class:`~implicit_cloth.simulator.Trajectory` is one."""

    @property
    def report(self) -> Mapping[str, Any]: ...

    def save(self, path: str | os.PathLike[str]) -> Path: ...


def write_run(out: str | os.PathLike[str], traj: RunLike, scene: Mapping[str, Any] | None
              ) -> tuple[Path, Path]:
    """Write ``out/trajectory.npz`` and ``out/report.json`` (the report with the normalised ``scene``) as a pair.

    Both are first written completely to temporary files in ``out`` (each
    atomically, see :func:`atomic_write`), then renamed into place, so a failure
    while writing either (a full disk) leaves the previous pair as it was, never
    a new trajectory beside an old report, and removes the temporary files.
    The report is written through :class:`~implicit_cloth.report.RunReport`
    (so a report that lacks a key is refused before anything is written).
    """
    out = Path(out)
    report = RunReport.from_dict(traj.report).for_file(scene)
    targets = (out / "trajectory.npz", out / "report.json")
    writers = (traj.save, lambda p: save_json(p, report))
    staged: list[Path] = []
    try:
        for target, write in zip(targets, writers):
            fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".new", dir=out)
            os.close(fd)
            staged.append(Path(name))
            write(staged[-1])
        for tmp, target in zip(staged, targets):
            os.replace(tmp, target)
    except BaseException:
        for tmp in staged:
            try:
                tmp.unlink()
            except OSError:
                pass
        raise
    return targets


@dataclass
class Run:
    """A run read back from its directory by :func:`load_run`."""

    positions: np.ndarray
    times: np.ndarray
    faces: np.ndarray
    report: RunReport


def load_run(out: str | os.PathLike[str]) -> Run:
    """Read ``out/trajectory.npz`` and ``out/report.json`` (written by :func:`write_run`).

    ``report.scene`` is the normalised scene: ``Scene.from_dict(run.report.scene)`` runs it again.
    """
    out = Path(out)
    with np.load(out / "trajectory.npz") as z:
        positions, times, faces = z["positions"], z["times"], z["faces"]
    report = RunReport.from_dict(json.loads((out / "report.json").read_text()))
    return Run(positions, times, faces, report)
