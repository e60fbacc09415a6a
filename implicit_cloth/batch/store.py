"""A sweep's output directory: each case's files and completion marker, and the summary.

See :mod:`implicit_cloth.batch` for the layout. Every file is written atomically and a
case's marker last, so a case is finished exactly when its marker is present and the
files it vouches for match it.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from ..errors import InputError
from ..files import atomic_write, save_json, write_run
from ..report import RunReport
from .sweep import Case, Sweep

#: Columns of summary.csv after the swept keys and ``status``, ``reason``, ``wall_s``.
HEALTH_COLUMNS: tuple[str, ...] = (
    "steps", "energy_drift", "energy_drift_rel", "max_strain",
    "mean_iterations", "max_iterations", "unconverged_steps", "max_penetration", "health",
)
#: Case statuses: a finished case is ok, warning (finished, with the report's health warnings), diverged or
#: failed; ``pending`` in a summary means not run yet.
STATUSES: tuple[str, ...] = ("ok", "warning", "diverged", "failed")
MARKER = "done.json"
_TMP = re.compile(r"^\..+\.(tmp|new)$")


def health(report: RunReport) -> dict[str, Any]:
    """Health figures of a run report (the summary's last columns).

    ``energy_drift`` = E_total(end) - E_total(0) - W_pins(end), J, and
    ``energy_drift_rel`` the same divided by the run's energy scale (see
    docs/scene.md, "Divergence"); ``max_strain`` the largest over kept frames;
    solver figures for implicit methods (empty otherwise);
    ``max_penetration`` (m) from the collision report, 0 without obstacles;
    ``health``: the criteria the run warned about (``energy strain``; empty when ok).
    """
    out: dict[str, Any] = {k: None for k in HEALTH_COLUMNS}
    out["steps"] = report.steps
    drift = report.energy_drift()
    if drift is not None:
        scale = report.divergence_bound.energy_scale
        out["energy_drift"] = drift
        out["energy_drift_rel"] = drift / scale if scale else None
        out["max_strain"] = max(report.frames.max_strain or [math.nan])
    if report.solver:
        out["mean_iterations"] = report.solver.mean_iterations
        out["max_iterations"] = report.solver.max_iterations
        out["unconverged_steps"] = report.solver.unconverged_steps
    out["max_penetration"] = float(report.collision.max_penetration) if report.collision else 0.0
    out["health"] = " ".join(w["criterion"] for w in report.health)
    return out


def clean_case_dir(case_dir: Path, marker: bool = True) -> None:
    """Remove a case directory's stray temporary files (from a killed writer) and, if ``marker``, its marker."""
    if not case_dir.is_dir():
        return
    for p in case_dir.iterdir():
        if (marker and p.name == MARKER) or _TMP.match(p.name):
            try:
                p.unlink()
            except FileNotFoundError:
                pass


def _digest(path: Path) -> dict[str, Any]:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return {"size": path.stat().st_size, "sha256": h.hexdigest()}


def store_result(out: Path, case: Case, result: Mapping[str, Any]) -> dict[str, Any]:
    """Write a case's result to ``out/<case-id>/``: the pair atomically, then the marker. Returns the row."""
    from ..simulator import Trajectory

    case_dir = out / case.case_id
    case_dir.mkdir(parents=True, exist_ok=True)
    clean_case_dir(case_dir)
    report = dict(result["report"])
    scene_data = report.pop("scene", None)
    if "trajectory" in result:
        t = result["trajectory"]
        traj = Trajectory(t["positions"], t["times"], t["faces"], report)
        files: tuple[Path, ...] = write_run(case_dir, traj, scene_data)
    else:   # failed: no trajectory; a stale one from an earlier attempt must not stand beside the report
        try:
            (case_dir / "trajectory.npz").unlink()
        except FileNotFoundError:
            pass
        files = (save_json(case_dir / "report.json", {**report, "scene": scene_data}),)
    marker = {"case_id": case.case_id, "row": result["row"],
              "files": {f.name: _digest(f) for f in files}}
    save_json(case_dir / MARKER, marker)
    return dict(result["row"])


def finished_row(out: Path, case: Case) -> dict[str, Any] | None:
    """The summary row of a finished case, or None: the marker must parse, name the case and match its files."""
    case_dir = out / case.case_id
    try:
        marker = json.loads((case_dir / MARKER).read_text())
        if marker.get("case_id") != case.case_id or marker["row"].get("status") not in STATUSES:
            return None
        files = marker["files"]
        needed = {"report.json"} | ({"trajectory.npz"} if marker["row"]["status"] != "failed" else set())
        if not needed <= set(files):
            return None
        for name, info in files.items():
            p = case_dir / name
            if p.stat().st_size != info["size"] or _digest(p)["sha256"] != info["sha256"]:
                return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    row = dict(marker["row"])
    row.update({k: v for k, v in case.params.items()})   # columns as this sweep names them
    return row


# --------------------------------------------------------------------------- summary
def summary_columns(sweep: Sweep) -> list[str]:
    """``case_id``, the swept keys, ``status``, ``reason``, ``wall_s``, then :data:`HEALTH_COLUMNS`."""
    return ["case_id", *sweep.keys, "status", "reason", "wall_s", *HEALTH_COLUMNS]


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    if isinstance(v, (list, dict, tuple)):
        return json.dumps(v)
    return str(v)


def write_summary(out: Path, sweep: Sweep, rows: Mapping[str, Mapping[str, Any]]) -> tuple[Path, Path]:
    """Atomically write ``out/summary.csv`` and ``out/summary.json``.

    Cases are in sweep order; unfinished ones are ``pending``.
    """
    cols = summary_columns(sweep)
    table = []
    for case in sweep.cases:
        row = rows.get(case.case_id)
        if row is None:
            row = {"case_id": case.case_id, **case.params, "status": "pending", "reason": "", "wall_s": None}
        table.append({c: row.get(c) for c in cols})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in table:
        w.writerow([_cell(r[c]) for c in cols])
    counts = {s: sum(r["status"] == s for r in table) for s in (*STATUSES, "pending")}
    csv_path = atomic_write(out / "summary.csv", lambda f: f.write(buf.getvalue().encode("utf-8")))
    json_path = save_json(out / "summary.json", {
        "sweep": sweep.path, "base": sweep.base, "keys": sweep.keys, "columns": cols,
        "counts": counts, "cases": table})
    return csv_path, json_path


# --------------------------------------------------------------------------- reading results
@dataclass
class SweepSummary:
    """``summary.json`` of a sweep's output directory, checked as it is read (see :func:`write_summary`).

    Every row has every column (``None``: no value, e.g. the solver figures of an explicit method).
    """

    sweep: str
    base: str
    keys: list[str]
    columns: list[str]
    counts: dict[str, int]
    cases: list[dict[str, Any]]

    @classmethod
    def from_dict(cls, data: Any, where: str = "summary.json") -> SweepSummary:
        """Read a parsed ``summary.json``; a missing key or a row without a column is an InputError naming it."""
        if not isinstance(data, Mapping):
            raise InputError(where, "must be a table", data)
        for name in ("sweep", "base", "keys", "columns", "counts", "cases"):
            if name not in data:
                raise InputError(f"{where}.{name}", "missing")
        for n, row in enumerate(data["cases"]):
            missing = [c for c in data["columns"] if not isinstance(row, Mapping) or c not in row]
            if missing:
                raise InputError(f"{where}.cases[{n}].{missing[0]}", "missing")
        return cls(data["sweep"], data["base"], list(data["keys"]), list(data["columns"]), dict(data["counts"]),
                   [dict(r) for r in data["cases"]])

    def finished(self) -> list[dict[str, Any]]:
        """The rows of cases that ran to an end (``ok``, ``warning`` or ``diverged``)."""
        return [r for r in self.cases if r["status"] in ("ok", "warning", "diverged")]


def read_summary(out: str | os.PathLike[str]) -> SweepSummary:
    """Read and check ``out/summary.json`` (see :func:`write_summary`)."""
    p = Path(out) / "summary.json"
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError("DIR", "no summary.json (not a batch output directory)", str(out)) from None
    except (OSError, ValueError) as exc:
        raise InputError("DIR", f"cannot read {p} ({exc})", str(out)) from None
    return SweepSummary.from_dict(data, where=str(p))
