"""Plots from a sweep's summary: each health figure against one swept key, one line per group of the others.

Needs matplotlib (the ``render`` extra). Drawn on an Agg canvas, headless.
"""

from __future__ import annotations

import io
import math
import numbers
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .batch import HEALTH_COLUMNS, read_summary
from .errors import SceneError
from .io import atomic_write
from .scene import _fmt

#: Figures plotted by default (those with at least one value).
DEFAULT_METRICS: tuple[str, ...] = ("energy_drift_rel", "max_strain", "mean_iterations", "wall_s")
UNITS = {"energy_drift": "J", "wall_s": "s", "max_penetration": "m"}


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values)


def _label(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def compare_sweep(out: str | os.PathLike[str], x: str | None = None, by: str | None = None,
                  metrics: Sequence[str] | None = None, plots: str | os.PathLike[str] | None = None
                  ) -> list[Path]:
    """Plot a finished (or partly finished) sweep's health figures.

    Parameters
    ----------
    out : path
        The batch output directory (with ``summary.json``).
    x : str, optional
        Swept key on the horizontal axis (numeric values); default
        ``simulation.dt`` if swept, else the first numeric swept key.
    by : str, optional
        Swept key whose values get one line each; default: one line per
        combination of the other swept keys.
    metrics : list of str, optional
        Columns to plot (default those of :data:`DEFAULT_METRICS` that have values).
    plots : path, optional
        Where to write ``<metric>_vs_<x>.png`` (default ``DIR/compare``).

    Returns
    -------
    list of Path
        The PNG files written (atomically). Diverged cases are drawn as red
        crosses at the figures of their partial run; failed and pending ones are left out.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    summary = read_summary(out)
    keys: list[str] = list(summary.get("keys", []))
    rows = [r for r in summary.get("cases", []) if r.get("status") in ("ok", "diverged")]
    if not rows:
        raise SceneError(f"DIR: the summary has no finished case (ok or diverged) to plot, got {_fmt(str(out))}")
    numeric = [k for k in keys if _numeric([r.get(k) for r in rows]) and len({r.get(k) for r in rows}) > 1]
    if x is None:
        if not numeric:
            raise SceneError(f"--x: no swept key has several numeric values to plot against (swept: "
                             f"{', '.join(keys)}), got None")
        x = "simulation.dt" if "simulation.dt" in numeric else numeric[0]
    elif x not in keys:
        raise SceneError(f"--x: must be one of the swept keys {', '.join(keys)}, got {_fmt(x)}")
    elif x not in numeric:
        raise SceneError(f"--x: the values of {x} are not numbers (or all equal), got {_fmt(x)}")
    if by is not None and (by not in keys or by == x):
        raise SceneError(f"--by: must be one of the swept keys other than --x ({', '.join(k for k in keys if k != x)}), "
                         f"got {_fmt(by)}")
    allowed = ("wall_s", *HEALTH_COLUMNS)
    if metrics is None:
        metrics = [m for m in DEFAULT_METRICS if any(r.get(m) is not None for r in rows)]
    for k, m in enumerate(metrics):
        if m not in allowed:
            raise SceneError(f"--metrics[{k}]: must be one of {', '.join(allowed)}, got {_fmt(m)}")

    group_keys = [by] if by is not None else [k for k in keys if k != x]
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(_label(r.get(k)) for k in group_keys), []).append(r)

    target = Path(plots) if plots is not None else Path(out) / "compare"
    target.mkdir(parents=True, exist_ok=True)
    xs_all = np.array([r[x] for r in rows], float)
    log_x = bool(np.all(xs_all > 0) and xs_all.max() / xs_all.min() > 10)
    written = []
    for m in metrics:
        fig = Figure(figsize=(6.4, 4.4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        ys_all = []
        for g, (name, members) in enumerate(sorted(groups.items())):
            pts = sorted((r[x], r.get(m), r["status"]) for r in members if r.get(m) is not None)
            if not pts:
                continue
            px = np.array([p[0] for p in pts], float)
            py = np.array([p[1] for p in pts], float)
            ok = np.array([p[2] == "ok" for p in pts])
            label = ", ".join(f"{k.split('.')[-1]}={v}" for k, v in zip(group_keys, name)) or "all"
            line, = ax.plot(px[ok], py[ok], "o-", label=label, color=f"C{g % 10}")
            if np.any(~ok):
                ax.plot(px[~ok], py[~ok], "x", color="red", markersize=9, mew=2)
            ys_all.extend(py)
        if any("diverged" == r["status"] and r.get(m) is not None for r in rows):
            ax.plot([], [], "x", color="red", mew=2, label="diverged (partial run)")
        ys = np.array(ys_all, float)
        if log_x:
            ax.set_xscale("log")
        if len(ys) and np.all(ys > 0) and ys.max() / ys.min() > 100:
            ax.set_yscale("log")
        elif len(ys) and np.ptp(ys) > 0 and np.max(np.abs(ys)) / max(np.min(np.abs(ys[ys != 0])) if np.any(ys != 0) else 1, 1e-300) > 1e3:
            ax.set_yscale("symlog", linthresh=float(np.percentile(np.abs(ys[ys != 0]), 10)))
        unit = UNITS.get(m)
        ax.set_xlabel(x)
        ax.set_ylabel(m + (f" ({unit})" if unit else ""))
        ax.set_title(f"{m} vs {x}", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        safe = x.replace(".", "_").replace("[", "_").replace("]", "")
        written.append(atomic_write(target / f"{m}_vs_{safe}.png", lambda f, b=buf: f.write(b.getvalue())))
    return written
