"""A run's two output files written as one pair: ``trajectory.npz`` and ``report.json`` that names it.

Both files are first written completely under hidden temporary names in the output directory
(``.trajectory.npz.<pid>.<random>.new``, ``.report.json.<pid>.<random>.new``) and fsynced, then renamed into
place, the trajectory first. The pair shares a random ``run_id`` (the npz's ``run_id`` array; the report's
``outputs`` table, which also holds the trajectory's SHA-256), so a reader tells a matching pair from a mixed
one: a process killed between the two renames leaves the new trajectory beside the previous report, and
:func:`check_pair` (used by ``export`` and ``render``) refuses it with one line. A failure while writing
(a full disk) leaves the previous pair as it was. Temporary files of writers that no longer run (killed
mid-write) are removed by the next write into the same directory.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
from pathlib import Path
from typing import IO, Any, Mapping

import numpy as np

from .errors import SceneError
from .scene import _fmt

TRAJECTORY, REPORT = "trajectory.npz", "report.json"
_STAGED = re.compile(r"^\.{1,2}(?:trajectory\.npz|report\.json)\.(?:(\d+)\.)?[^/]*\.(?:new|tmp)$")


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
    """Remove the hidden temporaries of earlier writes into ``out`` whose writer no longer runs; returns them.

    Names without a process id (written by earlier versions) count as stale."""
    removed = []
    with contextlib.suppress(OSError):
        for p in Path(out).iterdir():
            m = _STAGED.match(p.name)
            if m and not (m.group(1) and _alive(int(m.group(1)))):
                with contextlib.suppress(OSError):
                    p.unlink()
                    removed.append(p)
    return removed


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _create(path: Path) -> IO[bytes]:
    """A new file (never an existing one) opened for writing."""
    return os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb")


def write_pair(out: str | os.PathLike[str], arrays: Mapping[str, np.ndarray], report: Mapping[str, Any]
               ) -> tuple[Path, Path]:
    """Write ``out/trajectory.npz`` (``arrays`` plus ``run_id``) and ``out/report.json`` (``report`` plus its
    ``outputs`` table) as a pair; see the module's docstring."""
    from .io import _finite

    out = Path(out)
    remove_stale(out)
    run_id = secrets.token_hex(8)
    targets = (out / TRAJECTORY, out / REPORT)
    staged = [out / f".{t.name}.{os.getpid()}.{secrets.token_hex(4)}.new" for t in targets]
    try:
        with _create(staged[0]) as f:
            np.savez_compressed(f, run_id=np.array(run_id), **dict(arrays))  # type: ignore[arg-type]
            f.flush()
            os.fsync(f.fileno())
        full = dict(report)
        full["outputs"] = {"run_id": run_id, "trajectory": TRAJECTORY, "trajectory_sha256": _sha256(staged[0])}
        text = json.dumps(_finite(full), indent=2, allow_nan=False)
        with _create(staged[1]) as f:
            f.write(text.encode("utf-8"))
            f.flush()
            os.fsync(f.fileno())
        mask = os.umask(0)
        os.umask(mask)
        for tmp, target in zip(staged, targets):
            os.chmod(tmp, 0o666 & ~mask)
            os.replace(tmp, target)          # the trajectory first: the report names the pair
        _fsync_dir(out)
    except BaseException:
        for tmp in staged:
            with contextlib.suppress(OSError):
                tmp.unlink()
        raise
    return targets


def check_pair(run_dir: str | os.PathLike[str]) -> None:
    """Raise a one-line SceneError if ``report.json`` names another run than ``trajectory.npz`` holds.

    Pairs written before run ids existed (no ``outputs.run_id``) and directories without a report pass."""
    run_dir = Path(run_dir)
    try:
        report = json.loads((run_dir / REPORT).read_text())
        expected = report["outputs"]["run_id"]
    except (OSError, ValueError, KeyError, TypeError):
        return
    try:
        with np.load(run_dir / TRAJECTORY) as z:
            found = str(z["run_id"]) if "run_id" in z.files else None
    except (OSError, ValueError):
        return
    if found != expected:
        raise SceneError(f"RUN_DIR: report.json belongs to another run than trajectory.npz (run {expected!r} "
                         f"and {found!r}: a run was stopped while replacing them; run it again), got "
                         f"{_fmt(str(run_dir))}")
