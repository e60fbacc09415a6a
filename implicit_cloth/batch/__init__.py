"""Batch runs: parameter sweeps over a base scene, run locally or on a Dask cluster.

A sweep file (TOML) names a base scene and the keys to vary::

    base = "hanging.toml"                  # relative to the sweep file
    [set]                                  # optional: fixed overrides for every case
    "cloth.resolution" = [8, 8]
    [sweep]                                # the cases are the product of these lists
    "simulation.dt" = [0.005, 0.01, 0.033]
    "simulation.integrator" = ["backward_euler", "bdf2"]
    [[cases]]                              # optional: explicit cases, for sweeps that are no product
    "simulation.dt" = 0.02
    "simulation.integrator" = "symplectic_euler"

Keys are dotted paths into the scene (``cloth.springs.structural.stiffness``;
a list entry as ``obstacles[0].radius``). Every case is validated before
anything runs; a bad key or value is a :class:`~implicit_cloth.SceneError`
naming its place in the sweep file and the value.

A case's id is a hash of its normalised scene (every default filled in), so
it is stable: the same parameters give the same id in every run of the sweep,
and a change of the base scene changes the ids of the cases it affects.

Output layout (``DIR`` = the output directory)::

    DIR/<case-id>/trajectory.npz   positions, times, faces (diverged: the frames before it)
    DIR/<case-id>/report.json      run report + normalised scene (failed: status, reason, scene)
    DIR/<case-id>/done.json        completion marker: the case's summary row and the sizes and
                                   SHA-256 of the files above; written last
    DIR/summary.csv, summary.json  one row per case, rewritten atomically from the markers

Every file is written atomically (a temporary file renamed into place), and the
marker only after the others, so a case is finished exactly when its marker is
present and the files it vouches for match it. Re-running the same sweep into
the same directory skips finished cases; killing a run (SIGINT, SIGKILL of a
worker or of the whole run) loses no finished case.

The package, by job: :mod:`.sweep` (the sweep file and its cases), :mod:`.case`
(running one case), :mod:`.store` (the output directory: case files, markers, the
summary), :mod:`.runner` (the local process pool and :func:`run_sweep`) and
:mod:`.cluster` (Dask).
"""

from __future__ import annotations

from .case import pin_blas, run_case
from .runner import BatchResult, run_sweep, salvage
from .store import (
                    HEALTH_COLUMNS,
                    MARKER,
                    STATUSES,
                    SweepSummary,
                    clean_case_dir,
                    finished_row,
                    health,
                    read_summary,
                    store_result,
                    summary_columns,
                    write_summary,
)
from .sweep import MAX_CASES, Case, Sweep, case_id, get_path, load_sweep, sweep_from_dict

__all__ = ["HEALTH_COLUMNS", "MARKER", "MAX_CASES", "STATUSES", "BatchResult", "Case", "Sweep", "SweepSummary",
           "case_id", "clean_case_dir", "finished_row", "get_path", "health", "load_sweep", "pin_blas",
           "read_summary", "run_case", "run_sweep", "salvage", "store_result", "summary_columns",
           "sweep_from_dict", "write_summary"]
