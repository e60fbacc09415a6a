"""A coarse space with rotations: rigid-mode aggregation at the finest level, smoothed aggregation below.

``soft_modes.py`` found that the draped cloth's extra CG iterations (and much of the hanging cloth's growth with
the grid) are soft modes of compressed springs, and that an operator-dependent coarse space reaches them where
the library's bilinear interpolation does not. This script measures one that stays sparse, on systems of real
steps (``solver_choice.capture``: the stiff hanging cloth of ``scaling.py`` at step ``--stiff-step``, first
solve; the peer scene of ``vs_blender.py`` hanging and draped on the sphere at step ``--peer-step``, one step a
frame, last solve), each solved by the library's filtered PCG (numpy path, tolerance ``--tolerance``, its
stopping rule) with these preconditioners (numpy V-cycles, one damped block-Jacobi sweep before and after on
every level, a dense Cholesky solve on the coarsest, at most ``COARSEST`` unknowns):

* ``bilinear`` (the library's default hierarchy: bilinear prolongations, 3 unknowns a vertex on every level);
* ``rigid``: 2x2-vertex aggregates on the grid, each a coarse node with 6 unknowns, the aggregate's three
  translations and three rotations about its centre at the step's positions (orthonormalised per aggregate,
  the tentative prolongation of smoothed aggregation, Vanek, Mandel & Brezina 1996), the same on every level
  (the coarse nodes' modes from the QR factors), no smoothing: a sparse coarse space that holds the rotations;
* ``rigid + SA below``: ``rigid`` at the finest level, its coarser prolongations smoothed once by their level's
  matrix (``P - omega D^-1 A P``), where the operators are small;
* ``SA everywhere``: every level's prolongation smoothed, the finest too.

For each: CG iterations, the true error of ``dv`` against a sparse direct solve, the coarse matrices' entries
over the fine matrix's (operator complexity less one: what a V-cycle's coarse levels cost against its fine
one) and a cost estimate in fine-matrix passes for the solve (CG's product, two fine smoothing passes, the
coarse levels by their share, the transfers by the prolongation's entries). Not the library's solver: a study of
a lever, by its iteration counts (the compiled path's ms would decide).

Usage::

    python benchmarks/studies/rigid_coarse.py                 # 32², 64², 128²: stiff, hanging, drape (~5 min)
    python benchmarks/studies/rigid_coarse.py --quick         # seconds (CI smoke)

Writes ``OUT/rigid_coarse.{json,md}``. Never asserts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, machine, system_table, write_outputs
from solver_choice import VCycle, _bdiag, capture, direct

from implicit_cloth.solvers.multigrid import grid_prolongations
from implicit_cloth.solvers.pcg import filtered_pcg

#: most unknowns of the coarsest level (solved densely)
COARSEST = 200
#: the damping of the block-Jacobi sweeps and of the prolongation smoothing
OMEGA = 0.7
LEVERS = ("bilinear", "rigid", "rigid + SA below", "SA everywhere")


def block_inverse(A: sp.csr_array, k: int) -> sp.csr_array:
    """The inverse of the k x k diagonal blocks of ``A`` as a sparse matrix (zero blocks: identity)."""
    n = A.shape[0] // k
    Ab = sp.bsr_array(sp.csr_array(A), blocksize=(k, k))
    Ab.sort_indices()
    rows = np.repeat(np.arange(n), np.diff(Ab.indptr))
    diag = rows == Ab.indices
    D = np.zeros((n, k, k))
    D[rows[diag]] = Ab.data[diag]
    dead = np.abs(np.linalg.det(D)) < 1e-300
    D[dead] = np.eye(k)
    return sp.csr_array(sp.bsr_array((np.linalg.inv(D), np.arange(n), np.arange(n + 1)), shape=A.shape))


def rigid_modes(x: np.ndarray) -> np.ndarray:
    """(3N, 6): the three translations and three rotations (about the centroid) of the positions ``x``."""
    q = x - x.mean(axis=0)
    B = np.zeros((len(x), 3, 6))
    B[:, :, :3] = np.eye(3)
    B[:, 0, 4], B[:, 0, 5] = q[:, 2], -q[:, 1]          # columns 3-5: e_a x q (rotations about x, y, z)
    B[:, 1, 3], B[:, 1, 5] = -q[:, 2], q[:, 0]
    B[:, 2, 3], B[:, 2, 4] = q[:, 1], -q[:, 0]
    return B.reshape(-1, 6)


def tentative(B: np.ndarray, k: int, nx: int, ny: int) -> tuple[sp.csr_array, np.ndarray, tuple[int, int]]:
    """Tentative prolongation of 2x2-node aggregates of an ``nx`` x ``ny`` node grid with ``k`` unknowns a node
    and the near-null modes ``B`` (n k, 6): per aggregate the QR factorisation of its rows of ``B`` (batched,
    missing nodes of edge aggregates as zero rows; a mode an aggregate cannot hold is dropped, its column 0).
    Returns P (n k, 6 n_agg), the coarse modes (6 n_agg, 6) and the coarse grid."""
    ax, ay = np.arange(nx) // 2, np.arange(ny) // 2
    cx, cy = int(ax[-1]) + 1, int(ay[-1]) + 1
    node = np.arange(nx * ny).reshape(ny, nx)
    slots = np.full((cy * cx, 4), -1)
    for dy in range(2):                                       # the aggregate's up to four nodes
        for dx in range(2):
            ys, xs = np.arange(dy, ny, 2), np.arange(dx, nx, 2)
            a = (ys[:, None] // 2) * cx + xs[None, :] // 2
            slots[a.ravel(), 2 * dy + dx] = node[np.ix_(ys, xs)].ravel()
    na = len(slots)
    rows = (k * np.maximum(slots, 0)[:, :, None] + np.arange(k)).reshape(na, 4 * k)
    present = np.repeat(slots >= 0, k, axis=1)
    Bl = np.where(present[:, :, None], B[rows], 0.0)
    Q, R = np.linalg.qr(Bl)                                   # (na, 4k, 6), (na, 6, 6)
    scale = np.abs(R).max(axis=(1, 2), keepdims=True)
    keep = np.abs(np.diagonal(R, axis1=1, axis2=2))[:, None, :] > 1e-10 * scale
    Q = Q * keep
    cols = 6 * np.arange(na)[:, None, None] + np.arange(6)[None, None, :]
    r = np.broadcast_to(rows[:, :, None], Q.shape)[present]
    c = np.broadcast_to(cols, Q.shape)[present]
    P = sp.csr_array((Q[present].ravel(), (r.ravel(), c.ravel())), shape=(B.shape[0], 6 * na))
    P.eliminate_zeros()
    return P, R.reshape(-1, 6), (cx, cy)


class Hierarchy:
    """The V-cycle of a lever (module docstring) on the filtered fine matrix ``Af``."""

    def __init__(self, Af: sp.csr_array, x: np.ndarray, grid: tuple[int, int], lever: str) -> None:
        nx, ny = grid
        self.A, self.D, self.P = [Af], [block_inverse(Af, 3)], []
        B, k = rigid_modes(x), 3
        while self.A[-1].shape[0] > COARSEST and min(nx, ny) > 1:
            P, B, (nx, ny) = tentative(B, k, nx, ny)
            level = len(self.P)
            if lever == "SA everywhere" or (lever == "rigid + SA below" and level > 0):
                P = sp.csr_array(P - OMEGA * (self.D[-1] @ (self.A[-1] @ P)))
            self.P.append(P)
            Ac = sp.csr_array(P.T @ self.A[-1] @ P)
            self.A.append(Ac)
            self.D.append(block_inverse(Ac, 6))
            k = 6
        C = self.A[-1].toarray()
        dead = np.diag(C) == 0.0
        C[dead, dead] = 1.0
        self.chol = sla.cho_factor(C)

    def apply(self, r: np.ndarray, level: int = 0) -> np.ndarray:
        if level == len(self.P):
            return sla.cho_solve(self.chol, r)
        A, D, P = self.A[level], self.D[level], self.P[level]
        x = OMEGA * (D @ r)
        x = x + P @ self.apply(P.T @ (r - A @ x), level + 1)
        return x + OMEGA * (D @ (r - A @ x))



def coarse_share(pc) -> float:
    """The coarse matrices' entries over the fine one's (a hierarchy's level matrices ``pc.A``)."""
    return sum(a.nnz for a in pc.A[1:]) / pc.A[0].nnz


def passes(pc) -> float:
    """Fine-matrix passes per CG iteration of a hierarchy (``pc.A``, ``pc.P``): CG's product, a pre- and
    post-sweep with its residual on every level (by the level's entries), the transfers (each prolongation's
    entries, twice)."""
    fine = pc.A[0].nnz
    return 1.0 + 2.0 * sum(a.nnz for a in pc.A[:-1]) / fine + 2.0 * sum(p.nnz for p in pc.P) / fine


def galerkin_work(pc) -> float:
    """The set-up's Galerkin products ``P^T (A P)`` of a hierarchy (``pc.A``, ``pc.P``), formed in two stages, in
    scalar multiplications over the fine matrix's entries: per level ``nnz(A) nnz(P) / rows(P)`` for ``A P``
    and ``nnz(P) nnz(A P) / rows(A P)`` for ``P^T (A P)`` (each entry of one factor times a row of the other).
    A CG iteration reads the fine matrix's entries about :func:`passes` times."""
    work = 0.0
    for A, P in zip(pc.A[:-1], pc.P):
        AP = sp.csr_array(A @ P)
        work += A.nnz * P.nnz / P.shape[0] + P.nnz * AP.nnz / AP.shape[0]
    return work / pc.A[0].nnz


def solve_all(sysd: dict, tol: float) -> list[dict]:
    A, b, z, filt = sysd["A"], sysd["b"], sysd["z"], sysd["filt"]
    S = _bdiag(filt.matrices())
    Af = sp.csr_array(S @ A @ S + (sp.identity(A.shape[0], format="csr") - S))
    mass = np.repeat(sysd["masses"], 3)
    ref = direct(A, b, z, filt)
    rows = []
    for lever in LEVERS:
        pc = (VCycle(A, filt, grid_prolongations(*sysd["grid"])) if lever == "bilinear"      # the library's
              else Hierarchy(Af, sysd["x"], sysd["grid"], lever))
        dv, res = filtered_pcg(A, b, z, filt, pc, tol, 2000, mass=mass, compiled=False)
        row = {"system": sysd["kind"], "n": sysd["n"], "lever": lever, "iterations": res.iterations,
               "converged": res.converged, "true_error": float(np.linalg.norm(dv - ref) / np.linalg.norm(ref)),
               "coarse_share": coarse_share(pc), "passes_per_iteration": passes(pc),
               "galerkin_work": galerkin_work(pc)}
        row["passes"] = row["passes_per_iteration"] * res.iterations
        rows.append(row)
        print(f"{sysd['kind']:8s} {sysd['n']:4d}² {lever:17s} its {res.iterations:4d}  err {row['true_error']:.1e}  "
              f"coarse/fine {row['coarse_share']:.2f}  {row['passes_per_iteration']:.2f} passes/it = "
              f"{row['passes']:.0f}, set-up {row['galerkin_work']:.0f}", flush=True)
    return rows


def markdown(res: dict) -> str:
    systems = list(dict.fromkeys((r["system"], r["n"]) for r in res["rows"]))
    lines = ["# A coarse space with rotations", "",
             f"CG iterations (tolerance {res['tolerance']:g}, the library's stopping rule) / true error of dv / "
             "fine-matrix passes of the solve; in brackets the coarse matrices' entries over the fine one's and the "
             "set-up's Galerkin products in multiplications over the fine matrix's entries (every solve).", ""]
    lines += system_table(res["rows"], systems, "lever", LEVERS, lambda r: f"{r['iterations']} / {r['true_error']:.0e}"
                          f" / {r['passes']:.0f} ({r['coarse_share']:.2f}, {r['galerkin_work']:.0f})")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--systems", nargs="+", default=["stiff", "hanging", "drape"], choices=["stiff", "hanging", "drape"])
    p.add_argument("--stiff-step", type=int, default=20)
    p.add_argument("--peer-step", type=int, default=120, help="120: the peer scene at 2 s (the drape at rest)")
    p.add_argument("--tolerance", type=float, default=1e-3)
    p.add_argument("--quick", action="store_true", help="tiny run (CI smoke)")
    p.add_argument("--out", type=Path, default=Path(default_out('rigid_coarse')), help="output folder (default out/bench/rigid_coarse)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.systems, a.stiff_step, a.peer_step = [16], ["stiff", "drape"], 3, 30
    res: dict = {"benchmark": "rigid_coarse", "machine": machine(), "quick": a.quick, "tolerance": a.tolerance,
                 "stiff_step": a.stiff_step, "peer_step": a.peer_step, "rows": []}
    for n in a.sizes:
        for kind in a.systems:
            step = a.stiff_step if kind == "stiff" else a.peer_step
            res["rows"] += solve_all(capture(kind, n, step, fixed=kind != "stiff"), a.tolerance)
    md = markdown(res)
    write_outputs(a.out, "rigid_coarse" + ("_quick" if a.quick else ""), res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
