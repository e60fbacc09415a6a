"""Helpers shared by the benchmark scripts: machine description and atomic output."""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

import numpy as np
import scipy

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import implicit_cloth as ic
from implicit_cloth.files import atomic_write, save_json


def machine() -> dict:
    """Platform, CPU count and library versions, stored with every result."""
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "versions": {"implicit_cloth": ic.__version__, "numpy": np.__version__, "scipy": scipy.__version__},
    }


def default_out(name: str) -> str:
    """Where benchmark ``name`` writes without ``--out``: ``out/bench/NAME`` under the working directory (git
    ignores ``out/``), never over the committed results; ``--out benchmarks/results`` writes there."""
    return str(Path("out") / "bench" / name)


def write_outputs(out: Path, name: str, result: dict, markdown: str) -> None:
    """Write ``OUT/NAME.json`` and ``OUT/NAME.md`` atomically."""
    out = Path(out)
    save_json(out / f"{name}.json", result)
    atomic_write(out / f"{name}.md", lambda f: f.write(markdown.encode("utf-8")))


def series(name: str) -> tuple[str, str]:
    """A benchmark's solver series as ``(solver.preconditioner, solver.cycle)``: a preconditioner's name, or a
    multigrid's with ``+K`` for its K-cycle (``"multigrid_smoothed+K"``)."""
    pc, _, cycle = name.partition("+")
    return pc, cycle or "V"


def hanging_stiff(n: int, k: float = 1e4, preconditioner: str = "multigrid", tolerance: float | None = None) -> dict:
    """The "hanging stiff cloth" of the performance issue: 1 m x 1 m, 0.1 kg, flat at rest, top corners pinned."""
    solver = {"preconditioner": preconditioner, "max_iterations": 20000}
    if tolerance is not None:
        solver["tolerance"] = tolerance
    return {
        "simulation": {"integrator": "backward_euler", "dt": 1 / 60},
        "solver": solver,
        "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xy",
                  "pins": ["top_left", "top_right"],
                  "springs": {"structural": {"stiffness": k, "damping": 0.1},
                              "shear": {"stiffness": k, "damping": 0.1},
                              "bend": {"stiffness": k / 100, "damping": 0.01}}},
        "effects": {"gravity": [0.0, 0.0, -9.81]},
    }


def spmv_seconds(A, repeats: int = 50) -> float:
    """Median time of one ``A @ x``, s."""
    import statistics
    import time

    x = np.random.default_rng(0).standard_normal(A.shape[0])
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        A @ x
        t.append(time.perf_counter() - t0)
    return statistics.median(t)


def progress(iterable=None, total: int | None = None, desc: str | None = None):
    """A tqdm progress bar on stderr when stderr is a terminal, a silent pass-through otherwise."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, disable=not sys.stderr.isatty(), leave=False)


def run_all(fn, items: list, workers: int = 1, desc: str | None = None) -> list:
    """``[fn(item) for item in items]``, in ``workers`` processes when more than one (results in order)."""
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers) as pool:
            return list(progress(pool.map(fn, items), total=len(items), desc=desc))
    return [fn(item) for item in progress(items, desc=desc)]


def save_png(fig, path: Path, dpi: int = 120) -> None:
    """Write a matplotlib figure to ``path`` as PNG, atomically."""
    atomic_write(Path(path), lambda f: fig.savefig(f, format="png", dpi=dpi))


#: ``[simulation.adaptive]`` for benchmarks that measure an integrator itself (its stability region, its numerical
#: damping): adaptive stepping (on by default for the implicit methods) would hide exactly what they measure.
FIXED_STEPS = {"enabled": False}


#: Marker and colour of each integrator in every benchmark plot.
STYLE = {"forward_euler": ("v", "tab:red"), "symplectic_euler": ("o", "tab:blue"), "verlet": ("s", "tab:cyan"),
         "rk4": ("D", "tab:purple"), "backward_euler": ("^", "tab:green"), "bdf2": ("P", "tab:olive")}


def friction_used(speed: float | None, newton: int | None) -> tuple[float, int]:
    """``(friction_speed, friction_newton)`` a run used: the values given (None: not given), the library's
    defaults filled in."""
    from implicit_cloth.collision.context import friction_newton, friction_speed

    given = {k: v for k, v in (("friction_speed", speed), ("friction_newton", newton)) if v is not None}
    return friction_speed(given), friction_newton(given)


def friction_text(res: dict, who: str = "") -> str:
    """How a result's friction reads in its table's header (results of before 2026-12-05 record 0, or nothing,
    for Coulomb's states, then the default); ``who`` prefixes it ("Ours with ")."""
    if not res.get("friction_speed"):
        text = "Coulomb's sticking and sliding states (`collision.friction_speed = 0`)"
    else:
        text = f"smoothed friction, `collision.friction_speed = {res['friction_speed']:g}` m/s"
        if res.get("friction_newton"):
            text += (f", solved within each step by up to `collision.friction_newton = {res['friction_newton']}` "
                     "Newton iterations")
        if res.get("friction_pause"):
            text += (f", paused for `collision.friction_pause = {res['friction_pause']}` steps after two steps in a "
                     "row that missed the law")
    text = who + text
    return f" {text[0].upper()}{text[1:]}."


def system_table(rows: list[dict], columns: list, label_key: str, labels, cell) -> list[str]:
    """Markdown lines of a table with a row per label (``r[label_key]``) and a column per ``(system, n)``, each
    cell ``cell(r)`` of the row ``r`` of that system, size and label."""
    out = [f"| {label_key} | " + " | ".join(f"{k} {n}²" for k, n in columns) + " |",
           "|---|" + "---|" * len(columns)]
    for label in labels:
        cells = [cell(next(r for r in rows if r["system"] == k and r["n"] == n and r[label_key] == label))
                 for k, n in columns]
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    return out
