"""Running a sweep: the unfinished cases on a local process pool (or a Dask cluster), resumable, with a lock."""

from __future__ import annotations

import os
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from ..config.validate import fmt
from ..errors import InputError
from .case import pin_blas, run_case
from .cluster import run_dask
from .store import STATUSES, clean_case_dir, finished_row, store_result, write_summary
from .sweep import Case, Sweep


def _run_and_store(case: Case, out: str) -> dict[str, Any]:
    """Worker entry point for local runs: simulate and write (in parallel across workers)."""
    return store_result(Path(out), case, run_case(case))


# --------------------------------------------------------------------------- running a sweep
@dataclass
class BatchResult:
    """What a sweep run did.

    Attributes
    ----------
    rows : dict
        case id -> summary row, for every finished case (including skipped ones).
    counts : dict
        Number of cases per status, plus ``pending`` (not finished).
    skipped : int
        Cases already finished before this run.
    unfinished : list of str
        Ids of cases left pending (the run stopped early; run again to resume).
    notes : list of str
        One-line messages about the run (a worker that died, a cluster error).
    """

    rows: dict[str, dict[str, Any]]
    counts: dict[str, int]
    skipped: int
    unfinished: list[str]
    notes: list[str]
    summary: tuple[Path, Path]


class _Lock:
    """An exclusive lock on ``out/.batch.lock`` (flock), so that two runs never share an output directory."""

    def __init__(self, out: Path) -> None:
        self.path = out / ".batch.lock"
        self.fd: int | None = None

    def __enter__(self) -> "_Lock":
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            return self
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            self.fd = None
            raise InputError(f"--out: another batch run is using this output directory, got "
                             f"{fmt(str(self.path.parent))}") from None
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.fd is not None:
            os.close(self.fd)


def _cpus() -> int:
    """CPUs this process may run on (its affinity where the OS tells it), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def worker_init() -> None:
    """Local worker set-up: one BLAS thread; die with the parent (Linux), so no orphan keeps writing."""
    pin_blas()
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # pragma: no cover
            pass


def run_sweep(sweep: Sweep, out: str | os.PathLike[str], *, workers: int | None = None,
              scheduler: str | None = None, client: Any = None, retry_failed: bool = False,
              progress: bool = False, on_note: Callable[[str], None] | None = None,
              max_restarts: int = 3) -> BatchResult:
    """Run every unfinished case of ``sweep`` into ``out`` and write the summary.

    Parameters
    ----------
    sweep : Sweep
        From :func:`load_sweep`.
    out : path
        Output directory (created). Cases already finished there are skipped.
    workers : int, optional
        Local worker processes (default: the CPUs this process may use). Ignored with a cluster.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:port``): run the cases there.
        Workers return their results and this process writes them, so the
        cluster needs no shared file system.
    client : dask.distributed.Client, optional
        An existing client (instead of ``scheduler``).
    retry_failed : bool
        Run again the cases recorded as ``failed`` (diverged and ok ones are kept).
    progress : bool
        Show a tqdm bar over cases with the running counts.
    on_note : callable, optional
        Called with one-line notes (a worker died and the pool was restarted...).
    max_restarts : int
        Local runs: how many times a broken worker pool (a worker killed) is
        restarted before the run stops, leaving the remaining cases pending.

    Raises
    ------
    KeyboardInterrupt
        After stopping the workers and writing the summary (finished cases kept).
    OSError
        If results cannot be written (after writing what can be).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    notes: list[str] = []

    def note(msg: str) -> None:
        notes.append(msg)
        if on_note is not None:
            on_note(msg)

    with _Lock(out):
        rows: dict[str, dict[str, Any]] = {}
        todo: list[Case] = []
        for case in sweep.cases:
            row = finished_row(out, case)
            if row is not None and not (retry_failed and row["status"] == "failed"):
                rows[case.case_id] = row
            else:
                clean_case_dir(out / case.case_id)
                todo.append(case)
        skipped = len(rows)
        last_write = [0.0]

        def summary(force: bool = False) -> None:
            now = time.monotonic()
            if force or now - last_write[0] >= 1.0:
                write_summary(out, sweep, rows)
                last_write[0] = now

        summary(force=True)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(sweep.cases), initial=skipped, unit="case", desc="batch", dynamic_ncols=True)

        def finished(row: dict[str, Any]) -> None:
            rows[row["case_id"]] = row
            summary()
            if bar is not None:
                c = {s: 0 for s in STATUSES}
                for r in rows.values():
                    c[r["status"]] = c.get(r["status"], 0) + 1
                bar.set_postfix(c, refresh=False)
                bar.update(1)

        try:
            if todo:
                if scheduler is not None or client is not None:
                    run_dask(todo, out, scheduler, client, finished, note)
                else:
                    _run_local(todo, out, workers or _cpus(), finished, note, max_restarts)
        finally:
            if bar is not None:
                bar.close()
            paths = write_summary(out, sweep, rows)
    unfinished = [c.case_id for c in sweep.cases if c.case_id not in rows]
    counts = {s: sum(r["status"] == s for r in rows.values()) for s in STATUSES}
    counts["pending"] = len(unfinished)
    return BatchResult(rows, counts, skipped, unfinished, notes, paths)


def _run_local(todo: Sequence[Case], out: Path, workers: int, finished: Callable[[dict[str, Any]], None],
               note: Callable[[str], None], max_restarts: int) -> None:
    """Run cases on a pool of ``workers`` processes, at most one case in flight per worker."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    queue = deque(todo)
    restarts = 0
    ctx = multiprocessing.get_context("spawn")     # no fork of a process that may hold threads
    while queue:
        inflight: dict[Any, Case] = {}
        lost: list[Case] = []
        pool = ProcessPoolExecutor(max_workers=min(workers, len(queue)), mp_context=ctx, initializer=worker_init)
        broken = False
        try:
            while queue or inflight:
                while queue and len(inflight) < workers and not broken:
                    case = queue.popleft()
                    try:
                        inflight[pool.submit(_run_and_store, case, str(out))] = case
                    except BrokenProcessPool:
                        queue.appendleft(case)
                        broken = True
                if not inflight:
                    break
                done, _ = wait(inflight, return_when=FIRST_COMPLETED)
                for fut in done:
                    try:
                        row = fut.result()     # a KeyboardInterrupt from the worker leaves the case in flight
                    except BrokenProcessPool:
                        broken = True
                        case = inflight.pop(fut)
                        queue.appendleft(case)
                        lost.append(case)
                        continue
                    inflight.pop(fut)
                    finished(row)
                if broken and not inflight:
                    break
            pool.shutdown(wait=True)
        except BaseException:
            _stop_pool(pool)
            salvage([*inflight.values(), *lost], out, finished)
            raise
        for case in salvage(lost, out, finished):
            queue.remove(case)
        if broken:
            restarts += 1
            if restarts > max_restarts:
                note(f"a worker process died {restarts} times (killed or out of memory); stopping with "
                     f"{len(queue)} cases pending: run the same command again to resume")
                return
            note(f"a worker process died (killed or out of memory); restarting the pool, "
                 f"{len(queue)} cases to go")


def salvage(cases: Sequence[Case], out: Path, finished: Callable[[dict[str, Any]], None]) -> list[Case]:
    """After their workers are gone: remove the temporary files of ``cases``; record those that finished.

    A worker may have written a case completely (marker last) and died, or been
    interrupted, before its result reached this process: the marker, checked
    against the files, says so. Returns the cases recorded.
    """
    done = []
    for case in cases:
        clean_case_dir(out / case.case_id, marker=False)
        row = finished_row(out, case)
        if row is not None:
            finished(row)
            done.append(case)
    return done


def _stop_pool(pool: Any) -> None:
    """Stop a ProcessPoolExecutor now: cancel queued work and terminate its workers."""
    procs = list((getattr(pool, "_processes", None) or {}).values())   # no public handle on the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        try:
            p.terminate()
        except (OSError, AttributeError):
            pass
    for p in procs:
        try:
            p.join(timeout=5)
        except (OSError, AttributeError, AssertionError):
            pass
