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
from .export.staging import write_bytes

#: Figures plotted by default (those with at least one value).
DEFAULT_METRICS: tuple[str, ...] = ("energy_drift_rel", "max_strain", "mean_iterations", "wall_s")
UNITS = {"energy_drift": "J", "wall_s": "s", "max_penetration": "m"}
MARKERS = ("o", "s", "^", "D", "v", "P", "*", "X")


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values)


def _label(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _safe(key: str) -> str:
    return key.replace(".", "_").replace("[", "_").replace("]", "")


def _sort_key(values: tuple[Any, ...]) -> tuple[tuple[int, Any], ...]:
    """Numbers in numeric order (1000 < 5000 < 20000), before strings in their order; None last."""
    return tuple((0, float(v)) if isinstance(v, numbers.Real) and not isinstance(v, bool) else
                 (2, "") if v is None else (1, str(v)) for v in values)


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
        Where to write the plots (default ``DIR/compare``): into ``by_<key>/`` for ``--by key`` (dots as
        underscores), ``per_case/`` without, so that plots by different keys do not replace each other.

    Returns
    -------
    list of Path
        The PNG files written (atomically). Every line is labelled with its whole combination of swept
        values, legends in numeric order. A diverged case has no comparable figure (its run stopped, perhaps
        before its first kept frame): it is marked by a red cross at the top of the plot at its x, never
        plotted as a value; failed and pending ones are left out.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    summary = read_summary(out)
    keys = summary.keys
    rows = summary.finished()
    x, metrics = _choose(out, keys, rows, x, by, metrics)

    # one line per combination of the keys other than x (so that a line never mixes cases), each labelled with
    # its whole combination; with --by, lines share the colour of their --by value and differ in marker
    group_keys = ([by] if by is not None else []) + [k for k in keys if k not in (x, by)]
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in group_keys), []).append(r)
    order = sorted(groups, key=_sort_key)
    colours = {v: n for n, v in enumerate(dict.fromkeys(g[0] for g in order))} if by else {}

    base = Path(plots) if plots is not None else Path(out) / "compare"
    target = base / ("by_" + _safe(by) if by is not None else "per_case")
    target.mkdir(parents=True, exist_ok=True)
    xs_all = np.array([r[x] for r in rows], float)
    log_x = bool(np.all(xs_all > 0) and xs_all.max() / xs_all.min() > 10)
    written = []
    for m in metrics:
        fig = Figure(figsize=(6.4, 4.4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        diverged_x: list[float] = []
        ok_values: list[float] = []
        for g, name in enumerate(order):
            members = groups[name]
            diverged_x.extend(float(r[x]) for r in members if r["status"] == "diverged")
            # finished cases (a warning is in the summary's health column), not diverged ones
            pts = sorted((r[x], r[m]) for r in members if r["status"] in ("ok", "warning") and r[m] is not None)
            label = ", ".join(f"{k.split('.')[-1]}={_label(v)}" for k, v in zip(group_keys, name)) or "all"
            colour = f"C{colours[name[0]] % 10}" if by is not None else f"C{g % 10}"
            marker = MARKERS[g % len(MARKERS)] if by is not None else "o"
            if not pts:             # only diverged cases: the line's legend entry stays, without points
                ax.plot([], [], marker=marker, linestyle="-", color=colour, label=label + " (diverged)")
                continue
            px = np.array([p[0] for p in pts], float)
            py = np.array([p[1] for p in pts], float)
            ax.plot(px, py, marker=marker, linestyle="-", label=label, color=colour, alpha=0.8)
            ok_values.extend(py)
        if log_x:
            ax.set_xscale("log")
        ys = np.array(ok_values, float)
        ys = ys[np.isfinite(ys)]
        if len(ys):
            log_y = bool(np.all(ys > 0) and ys.max() / ys.min() > 100)
            if log_y:
                ax.set_yscale("log")
                lo, hi = ys.min() / 1.5, ys.max() * 1.5
            else:
                pad = 0.08 * (np.ptp(ys) or max(abs(ys.max()), 1e-12))
                lo, hi = ys.min() - pad, ys.max() + pad
            ax.set_ylim(lo, hi)
        if diverged_x:      # a diverged case has no comparable figure (its run stopped): marked, not plotted
            ax.plot(diverged_x, [1.0] * len(diverged_x), "x", color="red", markersize=9, mew=2, clip_on=False,
                    transform=ax.get_xaxis_transform(), label="diverged (no value; marked at the top)")
        unit = UNITS.get(m)
        ax.set_xlabel(x)
        ax.set_ylabel(m + (f" ({unit})" if unit else ""))
        ax.set_title(f"{m} vs {x}", fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        written.append(write_bytes(target / f"{m}_vs_{_safe(x)}.png", buf.getvalue()))
    return written
