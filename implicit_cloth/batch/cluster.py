"""Running cases as Dask tasks: the workers return results and this process writes them."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from ..config.validate import fmt
from ..errors import InputError
from .case import run_case
from .store import store_result
from .sweep import Case


def run_dask(todo: Sequence[Case], out: Path, scheduler: str | None, client: Any,
              finished: Callable[[dict[str, Any]], None], note: Callable[[str], None]) -> None:
    """Run cases as Dask tasks; this process writes their results (no shared file system needed)."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError("--scheduler: running on a cluster needs dask.distributed "
                         "(pip install 'implicit_cloth[dask]'), got " + fmt(scheduler)) from None
    own = client is None
    if own:
        try:
            client = Client(scheduler, timeout="15s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"--scheduler: cannot connect to the Dask scheduler ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())}), got {fmt(scheduler)}") from None
    futures: dict[Any, Case] = {}
    try:
        for case in todo:
            futures[client.submit(run_case, case, key=f"implicit-cloth-case-{case.case_id}", pure=False)] = case
        for fut in as_completed(list(futures)):
            case = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:
                note(f"case {case.case_id} not run on the cluster ({type(exc).__name__}: "
                     f"{' '.join(str(exc).split())[:200]}); run the same command again to retry it")
                continue
            finished(store_result(out, case, result))
    finally:
        pending = [f for f in futures if not f.done()]
        if pending:
            client.cancel(pending)
        if own:
            client.close()
