"""Why a draped cloth costs the solver: the compressed springs' clamped transverse stiffness.

``solver_choice.py`` found that the shared drape at rest on the sphere needs 2.5-3 times the CG iterations of
the same cloth hanging free, with or without its contact constraints: the draped *state* costs, not the
contacts. The likely reason it named: a spring shorter than its rest length has its transverse stiffness
``k (1 - L0 / l) (I - u u^T)`` (negative) clamped to 0 in the system matrix (Baraff & Witkin 1998: the matrix
stays SPD), so a folded, compressed cloth has many mechanisms that only the mass term ``M`` holds, soft modes
that bilinear interpolation on the grid does not reach.

This script checks it. It takes the linear system of a real step (``solver_choice.capture``: the peer scene of
``vs_blender.py`` hanging, and dropped on the sphere, at step ``--step``, one step a frame) and solves it (the
library's filtered PCG, numpy path, tolerance ``--tolerance``, with the numpy V-cycle of ``solver_choice.py``,
the library's hierarchy) as it is and with a positive transverse stiffness ``beta k c_x (I - u u^T)`` added to
the compressed springs of a family (all, structural, shear or bend) at the step's start, or ``abs(k (1 - L0 / l))
c_x (I - u u^T)`` (the absolute value of the true transverse stiffness instead of 0: the negative eigenvalue
reflected, not zeroed, as in Chen et al., "Stabler Neo-Hookean Simulation: Absolute Eigenvalue Filtering for
Projected Newton", SIGGRAPH 2024). If the clamped springs' mechanisms are what costs, the iterations fall towards
the hanging cloth's as ``beta`` grows. Each variant is also used as the preconditioner of the unmodified system
(the V-cycle built from the stiffened matrix, CG on the true one): whether the stiffening could be a
preconditioner-only lever.

The stiffened matrices are *not* the library's system (the step would change): a diagnosis, not a lever.

Usage::

    python benchmarks/studies/soft_modes.py                    # 32², 64² (~2 min on 2 shared cores)
    python benchmarks/studies/soft_modes.py --sizes 32 64 128  # (~10 min)

Writes ``OUT/soft_modes.{json,md}``. Never asserts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, machine, system_table, write_outputs
from solver_choice import VCycle, capture, direct

from implicit_cloth.solvers.multigrid import grid_prolongations
from implicit_cloth.solvers.pcg import filtered_pcg

#: (label, the stiffness of the spring family stiffened (None: every spring), beta: a number, or "abs" for each
#: spring's own ``L0/l - 1``)
VARIANTS = [("as assembled", None, 0.0), ("all, 0.01 k", None, 0.01), ("all, 0.1 k", None, 0.1),
            ("structural, 0.1 k", 1000.0, 0.1), ("shear, 0.1 k", 1000.0 / 3.0, 0.1), ("bend, 0.1 k", 10.0, 0.1),
            ("bend, 1 k", 10.0, 1.0), ("all, abs(k (1 - L0/l))", None, "abs"), ("bend, abs(k (1 - L0/l))", 10.0, "abs")]


def transverse(sysd: dict, family: float | None, beta) -> sp.csr_array:
    """``beta k c_x (I - u u^T)`` of the compressed springs of ``family`` (their stiffness; None: every family)
    as a (3N, 3N) matrix (c_x = h^2); ``beta = "abs"``: each spring's own ``L0/l - 1``."""
    s, x, h = sysd["springs"], sysd["x"], sysd["h"]
    d = x[s.j] - x[s.i]
    l = np.linalg.norm(d, axis=1)
    u = d / l[:, None]
    pick = l < s.L0
    if family is not None:
        pick &= np.isclose(s.k, family)
    scale = s.L0[pick] / l[pick] - 1.0 if beta == "abs" else np.full(int(pick.sum()), float(beta))
    T = h * h * (scale * s.k[pick])[:, None, None] * (np.eye(3)[None] - u[pick, :, None] * u[pick, None, :])
    i, j = s.i[pick], s.j[pick]
    rows, cols, vals = [], [], []
    for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append(np.repeat(3 * a[:, None] + np.arange(3), 3, axis=1).ravel())
        cols.append(np.tile(3 * b[:, None] + np.arange(3), (1, 3)).ravel())
        vals.append(sign * T.ravel())
    n3 = 3 * len(x)
    return sp.csr_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n3, n3))


def compressed(sysd: dict) -> dict:
    s, x = sysd["springs"], sysd["x"]
    short = np.linalg.norm(x[s.j] - x[s.i], axis=1) < s.L0
    names = {1000.0: "structural", 1000.0 / 3.0: "shear", 10.0: "bend"}
    out = {"all": float(short.mean())}
    for k, name in names.items():
        fam = np.isclose(s.k, k)
        out[name] = float(short[fam].mean()) if np.any(fam) else 0.0
    return out


def run(sysd: dict, tol: float, only: list[str] | None = None) -> list[dict]:
    A, b, z, filt = sysd["A"], sysd["b"], sysd["z"], sysd["filt"]
    Ps = grid_prolongations(*sysd["grid"])
    mass = np.repeat(sysd["masses"], 3)
    ref = direct(A, b, z, filt)
    rows = []
    for label, family, beta in VARIANTS:
        if only is not None and label not in only and label != "as assembled":
            continue
        stiffened = beta != 0.0
        Am = sp.csr_array(A + transverse(sysd, family, beta)) if stiffened else A
        refm = direct(Am, b, z, filt) if stiffened else ref
        pc = VCycle(Am, filt, Ps)
        dv, res = filtered_pcg(Am, b, z, filt, pc, tol, 2000, mass=mass, compiled=False)
        dv0, res0 = filtered_pcg(A, b, z, filt, pc, tol, 2000, mass=mass, compiled=False)
        rows.append({"system": sysd["kind"], "n": sysd["n"], "variant": label, "iterations": res.iterations,
                     "true_error": float(np.linalg.norm(dv - refm) / np.linalg.norm(refm)),
                     "as_preconditioner_iterations": res0.iterations,
                     "as_preconditioner_true_error": float(np.linalg.norm(dv0 - ref) / np.linalg.norm(ref))})
        print(f"{sysd['kind']:8s} {sysd['n']:4d}² {label:18s} its {res.iterations:4d} (err {rows[-1]['true_error']:.1e});"
              f" as preconditioner of the assembled system {res0.iterations:4d}", flush=True)
    return rows


def markdown(res: dict) -> str:
    lines = ["# Soft modes of the draped cloth: compressed springs' clamped transverse stiffness", "",
             f"Peer scene of `vs_blender.py`, one step a frame, the system of step {res['step']}; CG iterations "
             f"to the library's stopping rule (tolerance {res['tolerance']:g}) with the numpy V-cycle of "
             "`solver_choice.py`, with `beta k h^2 (I - u u^T)` added to the compressed springs named; in brackets "
             "the same stiffened V-cycle as the preconditioner of the assembled system.", ""]
    for (kind, n), frac in res["compressed"].items():
        lines.append(f"- {kind} {n}²: springs shorter than their rest length: " +
                     ", ".join(f"{k} {100 * v:.0f} %" for k, v in frac.items()))
    lines += [""] + system_table(res["rows"], list(res["compressed"]), "variant",
                                 dict.fromkeys(r["variant"] for r in res["rows"]),
                                 lambda r: f"{r['iterations']} ({r['as_preconditioner_iterations']})")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    p.add_argument("--systems", nargs="+", default=["hanging", "drape"], choices=["hanging", "drape"])
    p.add_argument("--step", type=int, default=120, help="the step whose system is taken (120: 2 s)")
    p.add_argument("--tolerance", type=float, default=1e-3)
    p.add_argument("--variants", nargs="+", default=None, help="only these variants (labels; default all)")
    p.add_argument("--quick", action="store_true", help="tiny run (CI smoke)")
    p.add_argument("--out", type=Path, default=Path(default_out('soft_modes')), help="output folder (default out/bench/soft_modes)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.step = [12], 30
    res: dict = {"benchmark": "soft_modes", "machine": machine(), "step": a.step, "tolerance": a.tolerance,
                 "quick": a.quick, "rows": [], "compressed": {}}
    for n in a.sizes:
        for kind in a.systems:
            sysd = capture(kind, n, a.step, fixed=True)
            res["compressed"][(kind, n)] = compressed(sysd)
            res["rows"] += run(sysd, a.tolerance, a.variants)
    md = markdown(res)
    res["compressed"] = {f"{k} {n}": v for (k, n), v in res["compressed"].items()}
    write_outputs(a.out, "soft_modes" + ("_quick" if a.quick else ""), res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
