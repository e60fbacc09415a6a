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
"""

from __future__ import annotations

import copy
import csv
import hashlib
import io
import itertools
import json
import math
import os
import re
import signal
import sys
import time
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from .config.validate import check_keys as _check_keys
from .config.validate import fail as _fail
from .config.validate import fmt as _fmt
from .errors import DivergenceError, SceneError
from .files import atomic_write, save_json, write_run
from .report import RunReport
from .scene import Scene, load_scene, tomllib

#: Columns of summary.csv after the swept keys and ``status``, ``reason``, ``wall_s``.
HEALTH_COLUMNS: tuple[str, ...] = (
    "steps", "energy_drift", "energy_drift_rel", "max_strain",
    "mean_iterations", "max_iterations", "unconverged_steps", "max_penetration",
)
#: Case statuses: a finished case is ok, diverged or failed; ``pending`` in a summary means not run yet.
STATUSES: tuple[str, ...] = ("ok", "diverged", "failed")
MARKER = "done.json"
#: Most cases a sweep may expand to.
MAX_CASES = 1_000_000
_TMP = re.compile(r"^\..+\.(tmp|new)$")
_SEGMENT = re.compile(r"^([^\[\]]+)((?:\[\d+\])*)$")


# --------------------------------------------------------------------------- sweep description
@dataclass
class Case:
    """One case of a sweep.

    Attributes
    ----------
    case_id : str
        Stable id: the first 12 hex digits of the SHA-256 of the case's
        normalised scene as canonical JSON.
    params : dict
        The swept keys' values for this case (dotted path -> value as given;
        a key an explicit case leaves out shows the base scene's value).
    raw : dict
        The case's scene as given (base scene with the overrides applied).
    base_dir : str or None
        Directory that relative paths in the scene are resolved against.
    """

    case_id: str
    params: dict[str, Any]
    raw: dict[str, Any]
    base_dir: str | None


@dataclass
class Sweep:
    """A parsed and validated sweep: the swept keys (summary columns) and the cases in order."""

    path: str
    base: str
    keys: list[str]
    cases: list[Case] = field(default_factory=list)


def _segments(path: str) -> list[str | int]:
    """``"obstacles[0].radius"`` -> ``["obstacles", 0, "radius"]``; ValueError if malformed."""
    out: list[str | int] = []
    for part in path.split("."):
        m = _SEGMENT.match(part)
        if not m:
            raise ValueError(part)
        out.append(m.group(1))
        out.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return out


def _set_path(raw: dict[str, Any], path: str, value: Any) -> None:
    """Set ``raw[a][b]...[z] = value`` for the dotted ``path``, creating missing tables."""
    segs = _segments(path)
    node: Any = raw
    for k, seg in enumerate(segs[:-1]):
        nxt = segs[k + 1]
        if isinstance(seg, int):
            if not isinstance(node, list) or seg >= len(node):
                raise KeyError(seg)
            node = node[seg]
            continue
        if not isinstance(node, dict):
            raise KeyError(seg)
        if seg not in node:
            if isinstance(nxt, int):
                raise KeyError(seg)
            node[seg] = {}
        node = node[seg]
    last = segs[-1]
    if isinstance(last, int):
        if not isinstance(node, list) or last >= len(node):
            raise KeyError(last)
    elif not isinstance(node, dict):
        raise KeyError(last)
    node[last] = copy.deepcopy(value)


def get_path(data: Any, path: str, default: Any = None) -> Any:
    """The value at dotted ``path`` in nested dicts/lists, or ``default``."""
    try:
        node = data
        for seg in _segments(path):
            node = node[seg]
        return node
    except (KeyError, IndexError, TypeError, ValueError):
        return default


def case_id(scene: Scene) -> str:
    """Stable id of a case: SHA-256 (12 hex digits) of its normalised scene as canonical JSON."""
    text = json.dumps(scene.data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]


def _key_only(where: str) -> str:
    """``sweep.k[2]`` -> ``sweep.k``: for an error about the key itself, not one of its values."""
    return re.sub(r"\[\d+\]$", "", where)


def _where_error(where: str, key: str, exc: SceneError) -> SceneError:
    """Re-word a scene error raised by overriding ``key`` so that it names its place in the sweep file.

    Read from the error's fields (``path``, ``message``, ``value``), never from its text.
    """
    if exc.message.startswith("unknown key") and (key == exc.path or key.startswith(exc.path + ".")):
        named = "" if exc.path == key else f" {exc.path!r}"
        return SceneError(_key_only(where), "unknown key" + named + exc.message[len("unknown key"):])
    if exc.path == key or exc.path.startswith((key + "[", key + ".")):
        return SceneError(where + exc.path[len(key):], exc.message, exc.value)
    return SceneError(where, f"makes the scene invalid ({exc})")


def _apply(base_raw: Mapping[str, Any], overrides: Mapping[str, Any], base_dir: Path | None,
           where: Callable[[str], str], label: str | None = None) -> Scene:
    """The base scene with ``overrides`` (dotted key -> value) applied and validated.

    An error about one of the overridden keys is reported at ``where(key)``;
    any other (values fine alone, not together) at ``label``.
    """
    raw = copy.deepcopy(dict(base_raw))
    for key, value in overrides.items():
        try:
            _set_path(raw, key, value)
        except (KeyError, ValueError):
            raise SceneError(f"{_key_only(where(key))}: not a path into the scene (it goes through a value that is "
                             f"not a table, or a list index out of range), got {_fmt(key)}") from None
    try:
        return Scene(raw, base_dir=base_dir)
    except SceneError as exc:
        for key in overrides:          # name the override the error is about, if it is one
            if (exc.path == key or exc.path.startswith((key + "[", key + "."))
                    or (key.startswith(exc.path + ".") and exc.message.startswith("unknown key"))):
                raise _where_error(where(key), key, exc) from None
        if label is None:
            label = where(next(iter(overrides))) if overrides else "base"
        raise SceneError(f"{label}: makes the scene invalid ({exc})") from None


def load_sweep(path: str | os.PathLike[str]) -> Sweep:
    """Read and validate a sweep file; expand it into its cases.

    Raises
    ------
    SceneError
        With a one-line message naming the sweep file's key and the bad value,
        e.g. ``sweep.simulation.dt[2]: must be a finite number > 0, got -1``,
        ``sweep.simulation.dtt: unknown key (did you mean 'dt'?)``,
        ``sweep.simulation.dt: must be a non-empty list of values, got []``,
        ``base: scene file not found, got 'nope.toml'``.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise SceneError(f"{p}: cannot read sweep file ({exc.strerror or exc})") from None
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SceneError(f"{p}: not a valid TOML file ({exc})") from None
    return sweep_from_dict(data, base_dir=p.parent, path=str(p))


def sweep_from_dict(data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None = None,
                    path: str = "<dict>") -> Sweep:
    """Validate a sweep given as a dict with the keys of the sweep file (see :func:`load_sweep`)."""
    _check_keys("", data, ("base", "set", "sweep", "cases"))
    if "base" not in data:
        raise SceneError("base: missing (a sweep file names its base scene: base = \"scene.toml\")")
    base = data["base"]
    if not isinstance(base, str) or not base:
        raise _fail("base", "must be the path of a scene file", base)
    base_path = Path(base)
    if not base_path.is_absolute() and base_dir is not None:
        base_path = Path(base_dir) / base_path
    if not base_path.is_file():
        raise _fail("base", f"scene file not found ({base_path})", base)
    try:
        base_scene = load_scene(base_path)
    except SceneError as exc:
        raise _fail("base", f"the base scene is invalid ({exc})", base) from None
    base_raw = base_scene.source
    scene_dir = base_scene.base_dir

    fixed = _flat("set", data.get("set", {}))
    if fixed:
        base_scene = _apply(base_raw, fixed, scene_dir, lambda k: f"set.{k}")
        base_raw = base_scene.source

    sweep = _flat("sweep", data.get("sweep", {}))
    explicit = data.get("cases", [])
    if not isinstance(explicit, list) or not all(isinstance(c, Mapping) for c in explicit):
        raise _fail("cases", "must be a list of tables ([[cases]] with dotted keys)", explicit)
    explicit = [_flat(f"cases[{n}]", c) for n, c in enumerate(explicit)]
    if not sweep and not explicit:
        raise SceneError("sweep: missing (a sweep file needs a [sweep] table of keys and value lists, "
                         "or [[cases]])")

    keys = list(sweep)
    for key, values in sweep.items():
        if not isinstance(values, list) or not values:
            raise _fail(f"sweep.{key}", "must be a non-empty list of values", values)
        for i, v in enumerate(values):            # each value alone: the clearest message
            _apply(base_raw, {key: v}, scene_dir, lambda k, i=i: f"sweep.{k}[{i}]")
    for n, c in enumerate(explicit):
        if not c:
            raise _fail(f"cases[{n}]", "must set at least one key", dict(c))
        keys += [k for k in c if k not in keys]

    n_product = math.prod(len(v) for v in sweep.values()) if sweep else 0
    if n_product + len(explicit) > MAX_CASES:
        raise _fail("sweep", f"expands to {n_product + len(explicit)} cases, more than the limit of "
                    f"{MAX_CASES}", {k: len(v) for k, v in sweep.items()})

    result = Sweep(path=str(path), base=str(base_path), keys=keys)
    seen: dict[str, str] = {}

    def add(params: dict[str, Any], label: str, where: Callable[[str], str]) -> None:
        scene = _apply(base_raw, params, scene_dir, where, label)
        cid = case_id(scene)
        if cid in seen:
            raise SceneError(f"{label}: the same scene as {seen[cid]} (equal after normalisation), "
                             f"got {_fmt(params)}")
        seen[cid] = label
        full = {k: params[k] if k in params else get_path(scene.data, k) for k in keys}
        result.cases.append(Case(cid, full, scene.source, str(scene_dir) if scene_dir is not None else None))

    if sweep:
        for n, combo in enumerate(itertools.product(*sweep.values())):
            params = dict(zip(sweep, combo))
            label = "sweep (case " + ", ".join(f"{k} = {_fmt(v)}" for k, v in params.items()) + ")"
            add(params, label, lambda k: f"sweep.{k}")
    for n, c in enumerate(explicit):
        add(dict(c), f"cases[{n}]", lambda k, n=n: f"cases[{n}].{k}")
    return result


def _flat(path: str, table: Any) -> dict[str, Any]:
    """A table of dotted keys, with nested tables flattened into dotted keys.

    TOML reads an unquoted ``simulation.dt = [...]`` (or a ``[sweep.simulation]``
    table) as nested tables; both mean the same as the quoted ``"simulation.dt"``.
    """
    if not isinstance(table, Mapping):
        raise _fail(path, "must be a table of dotted scene keys", table)
    out: dict[str, Any] = {}

    def walk(prefix: str, node: Mapping[str, Any]) -> None:
        for key, value in node.items():
            full = f"{prefix}.{key}" if prefix else str(key)
            try:
                _segments(full)
            except ValueError:
                raise _fail(f"{path}.{full}", "not a dotted scene key (e.g. simulation.dt, obstacles[0].radius)",
                            full) from None
            if isinstance(value, Mapping) and value:
                walk(full, value)
            elif full in out:
                raise _fail(f"{path}.{full}", "given twice (quoted and as a table)", value)
            else:
                out[full] = value

    walk("", table)
    return out


# --------------------------------------------------------------------------- running one case
def _pin_blas() -> None:
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


def health(report: RunReport) -> dict[str, Any]:
    """Health figures of a run report (the summary's last columns).

    ``energy_drift`` = E_total(end) - E_total(0) - W_pins(end), J, and
    ``energy_drift_rel`` the same divided by the run's energy scale (see the
    README's "Divergence"); ``max_strain`` the largest over kept frames;
    solver figures for implicit methods (empty otherwise);
    ``max_penetration`` (m) from the collision report, 0 without obstacles.
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
    return out


def run_case(case: Case) -> dict[str, Any]:
    """Simulate one case (in whatever process calls it) and return its result, writing nothing.

    Returns
    -------
    dict
        ``row`` (the summary row), ``report`` (with the normalised scene under
        ``"scene"``) and, unless the case failed, ``trajectory`` (positions,
        times, faces).
    """
    from .simulator import Simulator

    _pin_blas()
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
    except Exception as exc:  # noqa: BLE001 - a case that raises is recorded, the sweep goes on
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


def _clean(case_dir: Path, marker: bool = True) -> None:
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
    from .simulator import Trajectory

    case_dir = out / case.case_id
    case_dir.mkdir(parents=True, exist_ok=True)
    _clean(case_dir)
    report = dict(result["report"])
    scene_data = report.pop("scene", None)
    if "trajectory" in result:
        t = result["trajectory"]
        traj = Trajectory(t["positions"], t["times"], t["faces"], report)
        files = write_run(case_dir, traj, scene_data)
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


def _run_and_store(case: Case, out: str) -> dict[str, Any]:
    """Worker entry point for local runs: simulate and write (in parallel across workers)."""
    return store_result(Path(out), case, run_case(case))


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
    """Atomically write ``out/summary.csv`` and ``out/summary.json`` (cases in sweep order, unfinished ones ``pending``)."""
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
            raise SceneError(f"--out: another batch run is using this output directory, got "
                             f"{_fmt(str(self.path.parent))}") from None
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


def _worker_init() -> None:
    """Local worker set-up: one BLAS thread; die with the parent (Linux), so no orphan keeps writing."""
    _pin_blas()
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
                _clean(out / case.case_id)
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
                    _run_dask(todo, out, scheduler, client, finished, note)
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
        pool = ProcessPoolExecutor(max_workers=min(workers, len(queue)), mp_context=ctx, initializer=_worker_init)
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
            _salvage([*inflight.values(), *lost], out, finished)
            raise
        for case in _salvage(lost, out, finished):
            queue.remove(case)
        if broken:
            restarts += 1
            if restarts > max_restarts:
                note(f"a worker process died {restarts} times (killed or out of memory); stopping with "
                     f"{len(queue)} cases pending: run the same command again to resume")
                return
            note(f"a worker process died (killed or out of memory); restarting the pool, "
                 f"{len(queue)} cases to go")


def _salvage(cases: Sequence[Case], out: Path, finished: Callable[[dict[str, Any]], None]) -> list[Case]:
    """After their workers are gone: remove the temporary files of ``cases``; record those that finished.

    A worker may have written a case completely (marker last) and died, or been
    interrupted, before its result reached this process: the marker, checked
    against the files, says so. Returns the cases recorded.
    """
    done = []
    for case in cases:
        _clean(out / case.case_id, marker=False)
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


def _run_dask(todo: Sequence[Case], out: Path, scheduler: str | None, client: Any,
              finished: Callable[[dict[str, Any]], None], note: Callable[[str], None]) -> None:
    """Run cases as Dask tasks; this process writes their results (no shared file system needed)."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise SceneError("--scheduler: running on a cluster needs dask.distributed "
                         "(pip install 'implicit_cloth[dask]'), got " + _fmt(scheduler)) from None
    own = client is None
    if own:
        try:
            client = Client(scheduler, timeout="15s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise SceneError(f"--scheduler: cannot connect to the Dask scheduler ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())}), got {_fmt(scheduler)}") from None
    futures: dict[Any, Case] = {}
    try:
        for case in todo:
            futures[client.submit(run_case, case, key=f"implicit-cloth-case-{case.case_id}", pure=False)] = case
        for fut in as_completed(list(futures)):
            case = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:  # noqa: BLE001 - KilledWorker, a lost scheduler...: leave the case pending
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


# --------------------------------------------------------------------------- reading results
def read_summary(out: str | os.PathLike[str]) -> dict[str, Any]:
    """Read ``out/summary.json`` (see :func:`write_summary`)."""
    p = Path(out) / "summary.json"
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise SceneError(f"DIR: no summary.json (not a batch output directory), got {_fmt(str(out))}") from None
    except (OSError, ValueError) as exc:
        raise SceneError(f"DIR: cannot read {p} ({exc}), got {_fmt(str(out))}") from None
