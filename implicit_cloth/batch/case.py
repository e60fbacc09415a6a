"""Running one case of a sweep in whatever process calls it (a local worker or a Dask task)."""

from __future__ import annotations

import time
import warnings
from typing import Any

from ..errors import DivergenceError
from ..report import RunReport
from ..scene import Scene
from .store import HEALTH_COLUMNS, health
from .sweep import Case


# --------------------------------------------------------------------------- running one case
def pin_blas() -> None:
    """Limit every loaded BLAS to one thread for the rest of this (worker) process.

    Results then do not depend on threads, and two workers on two cores do not
    run four BLAS threads. NumPy and SciPy wheels each bring their own OpenBLAS
    and SciPy's is loaded only with ``scipy.linalg`` (measured: it stayed at 2
    threads when the limit was set before that import), so that is imported
    first; repeated for every case, it also catches a library loaded later.
    """
    import scipy.linalg  # noqa: F401 - loads SciPy's BLAS (the package imports it lazily) before the limit
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


def run_case(case: Case) -> dict[str, Any]:
    """Simulate one case (in whatever process calls it) and return its result, writing nothing.

    Returns
    -------
    dict
        ``row`` (the summary row), ``report`` (with the normalised scene under
        ``"scene"``) and, unless the case failed, ``trajectory`` (positions,
        times, faces).
    """
    from ..simulator import Simulator

    pin_blas()
    t0 = time.perf_counter()
    traj = None
    scene_data: Any = None
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scene = Scene(case.raw, base_dir=case.base_dir)
            scene_data = scene.data
            sim = Simulator(scene, blas_threads=1)
            try:
                traj = sim.run()
                status, reason = "ok", ""
            except DivergenceError as exc:
                traj = exc.trajectory
                status, reason = "diverged", " ".join(str(exc.reason).split())
    except Exception as exc:
        status = "failed"
        reason = " ".join(f"{type(exc).__name__}: {exc}".split())
        traj = None
    wall = time.perf_counter() - t0
    report: dict[str, Any] = dict(traj.report) if traj is not None else {"status": status, "reason": reason}
    report["status"], report["reason"] = status, reason
    report["scene"] = scene_data
    report["case_id"] = case.case_id
    report["warnings"] = [" ".join(str(w.message).split()) for w in caught]
    row = {"case_id": case.case_id, **case.params, "status": status, "reason": reason, "wall_s": wall,
           **(health(RunReport.from_dict(report)) if traj is not None else {k: None for k in HEALTH_COLUMNS})}
    result: dict[str, Any] = {"row": row, "report": report}
    if traj is not None:
        result["trajectory"] = {"positions": traj.positions, "times": traj.times, "faces": traj.faces}
    return result
