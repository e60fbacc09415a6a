"""Plots from a sweep's summary: each health figure against one swept key, one line per group of the others.

Needs matplotlib (the ``render`` extra). Drawn on an Agg canvas, headless.
"""

from __future__ import annotations

import io
import numbers
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .batch import HEALTH_COLUMNS, read_summary
from .errors import InputError, show
from .files import atomic_write

#: Figures plotted by default (those with at least one value).
DEFAULT_METRICS: tuple[str, ...] = ("energy_drift_rel", "max_strain", "mean_iterations", "wall_s")
UNITS = {"energy_drift": "J", "wall_s": "s", "max_penetration": "m"}


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values)


def _label(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _choose(out: str | os.PathLike[str], keys: list[str], rows: list[dict[str, Any]], x: str | None,
            by: str | None, metrics: Sequence[str] | None) -> tuple[str, Sequence[str]]:
    """The checked ``--x``, ``--by`` and ``--metrics`` (defaults filled in); a bad one is an InputError naming it."""
    if not rows:
        raise InputError(f"DIR: the summary has no finished case (ok or diverged) to plot, got {show(str(out))}")
    numeric = [k for k in keys if _numeric([r[k] for r in rows]) and len({r[k] for r in rows}) > 1]
    if x is None:
        if not numeric:
            raise InputError(f"--x: no swept key has several numeric values to plot against (swept: "
                             f"{', '.join(keys)}), got None")
        x = "simulation.dt" if "simulation.dt" in numeric else numeric[0]
    elif x not in keys:
        raise InputError(f"--x: must be one of the swept keys {', '.join(keys)}, got {show(x)}")
    elif x not in numeric:
        raise InputError(f"--x: the values of {x} are not numbers (or all equal), got {show(x)}")
    if by is not None and (by not in keys or by == x):
        others = ", ".join(k for k in keys if k != x)
        raise InputError(f"--by: must be one of the swept keys other than --x ({others}), got {show(by)}")
    allowed = ("wall_s", *HEALTH_COLUMNS)
    if metrics is None:
        metrics = [m for m in DEFAULT_METRICS if any(r[m] is not None for r in rows)]
    for k, m in enumerate(metrics):
        if m not in allowed:
            raise InputError(f"--metrics[{k}]: must be one of {', '.join(allowed)}, got {show(m)}")
    return x, metrics


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
    keys = summary.keys
    rows = summary.finished()
    x, metrics = _choose(out, keys, rows, x, by, metrics)

    # one line per combination of the keys other than x (so that a line never mixes cases);
    # with --by, lines share the colour (and the legend entry) of their --by value
    group_keys = ([by] if by is not None else []) + [k for k in keys if k not in (x, by)]
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(_label(r[k]) for k in group_keys), []).append(r)
    colours = {v: n for n, v in enumerate(dict.fromkeys(g[0] for g in sorted(groups)))} if by else {}

    target = Path(plots) if plots is not None else Path(out) / "compare"
    target.mkdir(parents=True, exist_ok=True)
    xs_all = np.array([r[x] for r in rows], float)
    log_x = bool(np.all(xs_all > 0) and xs_all.max() / xs_all.min() > 10)
    written = []
    for m in metrics:
        fig = Figure(figsize=(6.4, 4.4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        labelled: set[str] = set()
        label: str | None
        crosses: list[tuple[np.ndarray, np.ndarray]] = []
        ok_values: list[float] = []
        for g, (name, members) in enumerate(sorted(groups.items())):
            pts = sorted((r[x], r[m], r["status"]) for r in members if r[m] is not None)
            if not pts:
                continue
            px = np.array([p[0] for p in pts], float)
            py = np.array([p[1] for p in pts], float)
            ok = np.array([p[2] in ("ok", "warning") for p in pts])   # finished (a warning is in the summary)
            if by is not None:
                colour = f"C{colours[name[0]] % 10}"
                label = f"{by.split('.')[-1]}={name[0]}"
                label = label if label not in labelled else None
            else:
                colour = f"C{g % 10}"
                label = ", ".join(f"{k.split('.')[-1]}={v}" for k, v in zip(group_keys, name)) or "all"
            if label is not None:
                labelled.add(label)
                if not np.any(ok):          # keep the legend entry even if this line has no ok point
                    ax.plot([], [], "o-", color=colour, label=label)
                    label = None
            ax.plot(px[ok], py[ok], "o-", label=label, color=colour, alpha=0.8)
            ok_values.extend(py[ok])
            if np.any(~ok):
                crosses.append((px[~ok], py[~ok]))
        if log_x:
            ax.set_xscale("log")
        ys = np.array(ok_values, float)
        ys = ys[np.isfinite(ys)]
        clipped = False
        if len(ys):      # the axis fits the ok cases; a diverged case beyond it is drawn at its edge
            log_y = bool(np.all(ys > 0) and ys.max() / ys.min() > 100)
            if log_y:
                ax.set_yscale("log")
                lo, hi = ys.min() / 1.5, ys.max() * 1.5
            else:
                pad = 0.08 * (np.ptp(ys) or max(abs(ys.max()), 1e-12))
                lo, hi = ys.min() - pad, ys.max() + pad
            ax.set_ylim(lo, hi)
            for cx, cy in crosses:
                clipped |= bool(np.any((cy < lo) | (cy > hi)))
                ax.plot(cx, np.clip(cy, lo, hi), "x", color="red", markersize=9, mew=2, clip_on=False)
        else:
            for cx, cy in crosses:
                ax.plot(cx, cy, "x", color="red", markersize=9, mew=2)
        if crosses:
            ax.plot([], [], "x", color="red", mew=2,
                    label="diverged (partial run" + ("; beyond the axis: at its edge)" if clipped else ")"))
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
        written.append(atomic_write(target / f"{m}_vs_{safe}.png", lambda f, b=buf: f.write(b.getvalue())))  # type: ignore[misc]
    return written
