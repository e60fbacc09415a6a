"""Files: atomic output (write to a temporary file beside the target, then rename) and a run's pair of files.

A killed process or a full disk therefore never leaves a half-written file in
place of a previous good one. :func:`write_run` writes a run's
``trajectory.npz`` and ``report.json`` as a pair; :func:`load_run` reads them back.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable, Mapping, Protocol

import numpy as np

from .errors import InputError, show
from .report import RunReport


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object]) -> Path:
    """Call ``write(f)`` on a temporary file in ``path``'s directory, fsync it, and rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
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

    Both are first written completely under hidden temporary names in ``out``
    (``.trajectory.npz.<pid>.*.new``, ``.report.json.<pid>.*.new``), then renamed into
    place, the trajectory first; the report's ``outputs`` table names its trajectory
    and that file's SHA-256. So a failure while writing either (a full disk) leaves
    the previous pair as it was and removes the temporary files, and a process
    killed between the two renames leaves a new trajectory beside the old report,
    which :func:`check_pair` (and so :func:`load_run`, ``export`` and ``render``)
    refuses. Temporaries of writers that no longer run are removed first
    (:func:`remove_stale`). The report is written through
    :class:`~implicit_cloth.report.RunReport` (so a report that lacks a key is
    refused before anything is written).
    """
    out = Path(out)
    report = RunReport.from_dict(traj.report).for_file(scene)
    remove_stale(out)
    targets = (out / TRAJECTORY, out / REPORT)
    staged: list[Path] = []
    try:
        for target in targets:
            fd, name = tempfile.mkstemp(prefix=f".{target.name}.{os.getpid()}.", suffix=".new", dir=out)
            os.close(fd)
            staged.append(Path(name))
        traj.save(staged[0])
        report["outputs"] = {"trajectory": TRAJECTORY, "trajectory_sha256": _sha256(staged[0])}
        save_json(staged[1], report)
        for tmp, target in zip(staged, targets):     # the trajectory first: the report names it
            os.replace(tmp, target)
    except BaseException:
        for tmp in staged:
            try:
                tmp.unlink()
            except OSError:
                pass
        raise
    return targets


TRAJECTORY, REPORT = "trajectory.npz", "report.json"
_STAGED = re.compile(r"^\.{1,2}(?:trajectory\.npz|report\.json)\.(?:(\d+)\.)?[^/]*\.(?:new|tmp)$")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale(out: str | os.PathLike[str]) -> list[Path]:
    """Remove the hidden temporaries of earlier :func:`write_run` calls into ``out`` whose process no longer
    runs (killed while writing); names without a process id (earlier versions) count as stale. Returns them."""
    removed: list[Path] = []
    try:
        entries = list(Path(out).iterdir())
    except OSError:
        return removed
    for p in entries:
        m = _STAGED.match(p.name)
        if m and not (m.group(1) and _alive(int(m.group(1)))):
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def check_pair(out: str | os.PathLike[str]) -> None:
    """Raise a one-line :class:`~implicit_cloth.errors.InputError` if ``out/report.json`` names another
    trajectory than ``out/trajectory.npz`` (its SHA-256). Reports written before the ``outputs`` table existed
    and directories without a report or a trajectory pass."""
    out = Path(out)
    try:
        expected = json.loads((out / REPORT).read_text())["outputs"]["trajectory_sha256"]
        found = _sha256(out / TRAJECTORY)
    except (OSError, ValueError, KeyError, TypeError):
        return
    if found != expected:
        raise InputError(f"RUN_DIR: report.json belongs to another run than trajectory.npz (its SHA-256 is not "
                         f"the one the report names: a run was stopped while replacing them; run it again), "
                         f"got {show(str(out))}")


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
    check_pair(out)
    with np.load(out / "trajectory.npz") as z:
        positions, times, faces = z["positions"], z["times"], z["faces"]
    report = RunReport.from_dict(json.loads((out / "report.json").read_text()))
    return Run(positions, times, faces, report)
