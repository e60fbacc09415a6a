"""Multigrid levers for an iteration-flat solve: iterations, work and true error on captured real systems.

Scene: the hanging stiff cloth of ``scaling.py`` (k = 1e4 N/m, backward Euler, dt = 1/60 s, fixed steps: one
solve a step, default solver settings). The linear system of steps ``--steps`` (matrix, right-hand side,
prescribed dv, Baraff-Witkin filter, positions) is captured at every size, and each preconditioner variant is
the preconditioner of the library's filtered PCG (``filtered_pcg(compiled=False)``, tolerance ``--tolerance``,
its stopping rule and mass bound unchanged) on the same systems.

Variants (a numpy V-cycle written here on the library's hierarchy: bilinear prolongations, Galerkin coarse
matrices of the filtered fine matrix ``S A S + (I - S)``, dense Cholesky at the coarsest level):

* ``jacobi``: today's V-cycle, one damped (0.7) block-Jacobi sweep pre and post (checked against the library's
  own numpy ``Multigrid``: same iterations);
* ``jacobi2``, ``jacobi3``: two / three sweeps;
* ``gs``: symmetric multicolour block Gauss-Seidel (a greedy colouring of each level's block graph; forward
  colour order pre, backward post, each colour one vectorised block update);
* ``cheb2``, ``cheb3``: Chebyshev polynomial of ``D^-1 A`` of degree 2 / 3 on ``[lmax / 30, lmax]``,
  ``lmax`` 1.1 times a 10-step power estimate per level at setup;
* ``W``, ``W_cheb2``, ``W_gs``: the W-cycle (two coarse corrections at every level but the last two)
  with Jacobi / Chebyshev / Gauss-Seidel smoothing;
* ``vvar``: the variable V-cycle (2^l sweeps on level l); ``Wc`` / ``Wc_gs``: V at the fine level, W below it;
* ``cheb2_safe``: Chebyshev on the guaranteed bound ``||D^-1 A||_inf`` instead of a power estimate;
* diagnostics: ``two_grid`` (an exact coarse solve on the 2h grid, sparse LU), ``V3_direct`` / ``V4_direct`` (the
  V-cycle cut to 3 / 4 levels, sparse LU at the coarsest; its triangular solves counted as work);
* ``sa_rigid``: pyamg's smoothed aggregation of ``S A S + (I - S)`` (3x3 blocks) with the six rigid motions at the
  step's positions as near-null space, its default V-cycle (symmetric block Gauss-Seidel) as preconditioner;
  its setup is pyamg's, per system;
* smoothed prolongations: ``sp`` / ``sp_fine`` / ``sp2``:
  ``P = (I - w D^-1 A_l) P0`` (smoothed aggregation's smoothing on the geometric ``P0``, ``w = 4 / (3 rho)`` from
  a power estimate) on every level / the finest / the first two, untruncated; ``spr`` / ``spr_fine``: kept on
  ``P0``'s block pattern (3x3 blocks); ``spr_sum`` (``_fine``, ``2``): the same with every fine vertex's block
  row sum restored to ``P0``'s (the library's ``multigrid_smoothed``, there with ``w = 0.7``: ``spr_sum_w07``;
  ``spr_sum_w05``, ``spr_sum_inf`` (``w`` from the bound ``||D^-1 A||_inf``), ``spr_sum_w07_raw`` (the finest
  level smoothed with the unfiltered matrix)); ``spr_scalar``: a scalar smoothing of the block traces,
  ``P kron I3`` kept; ``spr_sum_w07_Wc`` / ``spr_sum_w07_W`` / ``spr_sum_w07_K``: ``spr_sum_w07`` with the ``Wc`` /
  ``W`` / ``K`` cycles (the K-cycle the library runs with ``solver.cycle = "K"``). ``galerkin`` (printed) counts the scipy set-up's multiplications, ``block refresh`` those
  of a fixed-pattern refresh with block prolongations, both in fine SpMVs;
* ``K``, ``K2``, ``K_gs``: the K-cycle (Notay & Vassilevski 2008, as in Notay's AGMG): on every coarse level but
  the coarsest, the coarse correction is one or two iterations of flexible CG (FCG(1)) on that level's Galerkin
  matrix, preconditioned by that level's cycle (smoothing around the next level's K-cycle correction); ``K``
  skips the second iteration when the first left ``|r1| <= 0.25 |r0|`` (Notay's threshold), ``K2`` never skips,
  ``K_gs`` is ``K`` with the Gauss-Seidel smoother. The inner FCG's products with its level's matrix count as
  work. A K-cycle is not a fixed linear operator, so these variants run the outer solve with ``flexible_pcg``
  (the library's numpy loop with the FCG(1) / Polak-Ribiere beta, same filter, bound and error estimate);
  ``jacobi_f`` is ``jacobi`` through that flexible outer CG (the fair reference: with a fixed preconditioner it
  is PCG in exact arithmetic).

Work: every product with a level's matrix (CG's own products, residuals, smoothing sweeps, a colour's rows) is
counted at its share of the fine level's stored entries, so "work" is in fine-level SpMVs; block-diagonal
solves, transfers and the coarsest Cholesky solve are not counted (each well under a fine SpMV at these sizes).
True error: ``|dv - dv*| / |dv*|`` against scipy's ``spsolve`` of the filtered system. Times are numpy on a
shared machine: an indication only.

Usage::

    python benchmarks/studies/mg_levers.py --sizes 32 64 128 256
    python benchmarks/studies/mg_levers.py --sizes 32 64 --variants jacobi gs --steps 1 10
    python benchmarks/studies/mg_levers.py --variants jacobi jacobi_f K K2 K_gs --out /tmp/kcycle_run

Writes ``OUT/mg_levers.{json,md}`` (``--merge`` rebuilds them from earlier runs' JSON). Never asserts.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, hanging_stiff, ic, machine, write_outputs
from solver_choice import _bdiag, _diag_blocks, chebyshev, direct, power_bound, rigid_modes

from implicit_cloth.solvers import make_preconditioner
from implicit_cloth.solvers.blocks import inv3
from implicit_cloth.solvers.multigrid import grid_prolongations
from implicit_cloth.solvers.pcg import Filter, SolveResult, current_error_estimate, filtered_pcg

H = 1 / 60

VARIANTS: dict[str, dict] = {
    "jacobi": {}, "jacobi2": {"nu": 2}, "jacobi3": {"nu": 3},
    "gs": {"smoother": "gs"},
    "cheb2": {"smoother": "chebyshev", "degree": 2}, "cheb3": {"smoother": "chebyshev", "degree": 3},
    "W": {"cycle": "W"}, "W_cheb2": {"cycle": "W", "smoother": "chebyshev", "degree": 2},
    "W_gs": {"cycle": "W", "smoother": "gs"},
    "vvar": {"growth": 2}, "vvar_cheb2": {"growth": 2, "smoother": "chebyshev", "degree": 2},
    "two_grid": {"two_grid": True},
    "V3_direct": {"depth": 2}, "V4_direct": {"depth": 3},
    "Wc": {"cycle": "Wc"}, "Wc_gs": {"cycle": "Wc", "smoother": "gs"},
    "cheb2_safe": {"smoother": "chebyshev", "degree": 2, "safe": True},
    "sa_rigid": {},
    "jacobi_f": {"flexible": True},
    "K": {"cycle": "K", "threshold": 0.25}, "K2": {"cycle": "K", "threshold": None},
    "K_gs": {"cycle": "K", "threshold": 0.25, "smoother": "gs"},
    "sp": {"smooth_p": "all"}, "sp_fine": {"smooth_p": "fine"}, "sp2": {"smooth_p": "two"},
    "spr": {"smooth_p": "all", "restrict_p": "pattern"}, "spr_sum": {"smooth_p": "all", "restrict_p": "sum"},
    "spr_fine": {"smooth_p": "fine", "restrict_p": "pattern"},
    "spr_sum_fine": {"smooth_p": "fine", "restrict_p": "sum"}, "spr_scalar": {"smooth_p": "all", "restrict_p": "scalar"},
    "spr_sum_inf": {"smooth_p": "all", "restrict_p": "sum", "p_omega": "inf"},
    "spr_sum_w05": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.5},
    "spr_sum_w07": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.7},
    "spr_sum_w07_raw": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.7, "p_raw_fine": True}, "spr_sum2": {"smooth_p": "two", "restrict_p": "sum"},
    "spr_sum_w07_Wc": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.7, "cycle": "Wc"},
    "spr_sum_w07_W": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.7, "cycle": "W"},
    "spr_sum_w07_K": {"smooth_p": "all", "restrict_p": "sum", "p_omega": 0.7, "cycle": "K", "threshold": 0.25},
}


# ----------------------------------------------------------------------------- capture
def capture(n: int, k: float, steps: list[int]) -> list[dict]:
    """The linear systems of the given steps of a default fixed-step run (one solve a step).

    Also solves each with the library's own numpy ``Multigrid`` (today's V-cycle), for the check of ``jacobi``.
    """
    d = hanging_stiff(n, k)
    d["simulation"]["adaptive"] = {"enabled": False}
    sim = ic.Simulator(ic.Scene.from_dict(d), dt=H)
    integ, model = sim.integrator, sim.model
    lib = make_preconditioner("multigrid", model, "numpy")
    mass3 = np.repeat(model.masses, 3)
    out: list[dict] = []
    orig = integ._solve
    want = set(steps)
    cur = {"step": 0}

    def spy(A, b, z, filt, info, guess=None, tolerance=None, **kw):
        if cur["step"] in want:
            A0, b0, z0 = sp.csr_array(getattr(A, "csr", A), copy=True), b.reshape(-1).copy(), z.reshape(-1).copy()
            f0 = Filter(filt.n, filt.fixed.copy(), filt.partial.copy(), filt.partial_S.copy())
            lib.setup(model.system, f0)
            _, res = filtered_pcg(A0, b0, z0, f0, lib, integ.tolerance, 5000, mass=mass3, compiled=False)
            out.append({"A": A0, "b": b0, "z": z0, "filt": f0, "x": sim.positions.copy(), "step": cur["step"],
                        "library_iterations": res.iterations})
        return orig(A, b, z, filt, info, guess, tolerance, **kw)

    integ._solve = spy
    for s in range(1, max(steps) + 1):
        cur["step"] = s
        sim.step(1)
    for r in out:
        r.update(n=n, grid=model.geometry.grid_shape, mass3=mass3, tol=integ.tolerance)
    return out


# ----------------------------------------------------------------------------- counting
class Counted:
    """A matrix whose products are counted at ``weight`` (its share of the fine level's entries) in ``box``."""

    def __init__(self, A, weight: float, box: list) -> None:
        self.A, self.w, self.box = A, weight, box
        self.shape = A.shape

    def __matmul__(self, x):
        self.box[0] += self.w
        return self.A @ x


def _canonical(A) -> sp.csr_array:
    """A CSR copy with sorted, summed indices and int64 index arrays."""
    A = sp.csr_array(A, copy=True)
    A.sum_duplicates()
    A.sort_indices()
    A.indptr, A.indices = A.indptr.astype(np.int64), A.indices.astype(np.int64)
    return A


def spgemm_work(A, B) -> float:
    """Multiplications of the sparse product ``A @ B``: for every stored ``a_ij`` the entries of row j of B."""
    A, B = sp.csr_array(A), sp.csr_array(B)
    return float(np.diff(B.indptr)[A.indices].sum())


def block_refresh_work(Al, P) -> float:
    """Multiplications of a fixed-pattern refresh with a block-valued prolongation on ``P``'s node pattern
    (3x3 blocks): the restricted smoothing ``P[f, c] = P0[f, c] I - w D_f^-1 sum_j A[f, j] P0[j, c]`` (9 a term,
    27 for ``D_f^-1``), the row-sum restoration (a 3x3 inverse and 27 a block) and the Galerkin sum
    ``A_c[I, J] += P[i, I]^T A[i, j] P[j, J]`` over every pair of prolongation entries of every stored block
    (54 a term; the scalar refresh takes 9)."""
    G = sp.csr_array(sp.csr_array(Al)[::3, ::3] != 0, dtype=float)      # block pattern of the level
    P = sp.csr_array(abs(P) > 0, dtype=float)
    rowp = np.diff(P.indptr).astype(float)
    G = sp.coo_array(G)
    quads = float((rowp[G.row] * rowp[G.col]).sum())
    smooth_terms = float((G @ P).multiply(P).sum()) if hasattr(G @ P, "multiply") else float(((G @ P) * P).sum())
    return 54.0 * quads + 9.0 * smooth_terms + 27.0 * P.nnz + 27.0 * 2 * P.shape[0]


def greedy_colours(A) -> np.ndarray:
    """A greedy colouring of the block graph of ``A`` (3x3 blocks): no two coupled vertices share a colour."""
    B = sp.csr_array(A)
    n = B.shape[0] // 3
    # block row i: CSR rows 3i..3i+2 (the pointers copied: a strided view here corrupted the heap on sum_duplicates)
    G = sp.csr_array((np.ones(B.nnz), B.indices // 3, np.array(B.indptr[::3], dtype=np.int64)), shape=(n, n))
    G.sum_duplicates()
    ptr, idx = G.indptr, G.indices
    col = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        used = set(col[idx[ptr[i]:ptr[i + 1]]].tolist())
        c = 0
        while c in used:
            c += 1
        col[i] = c
    return col


# ----------------------------------------------------------------------------- the numpy V-cycle
class VCycle:
    """The V-/W-cycle of the module docstring on the library's hierarchy, with a choice of smoother."""

    def __init__(self, A, filt: Filter, Ps: list, box: list, nu: int = 1, cycle: str = "V",  # noqa: C901
                 smoother: str = "jacobi", degree: int = 2, omega: float = 0.7, growth: int = 1,
                 two_grid: bool = False, safe: bool = False, depth: int | None = None,
                 threshold: float | None = 0.25, smooth_p: str | None = None,
                 restrict_p: str | None = None, p_omega: str | float | None = None,
                 p_raw_fine: bool = False) -> None:
        t0 = time.perf_counter()
        S = _bdiag(filt.matrices())
        I3 = sp.identity(A.shape[0], format="csr")
        As = [_canonical(S @ A @ S + (I3 - S))]
        self.P: list = []
        if two_grid:
            depth = 1
        self.p_nnz: list[float] = []
        #: the hierarchy's set-up in multiplications (the smoothing of P, its power estimate, the Galerkin triple
        #: products), converted to fine-level SpMVs below
        galerkin = 0.0
        for li, P in enumerate(Ps if depth is None else Ps[:depth]):
            P3 = sp.csr_array(sp.kron(P, sp.identity(3), format="csr"))
            if restrict_p == "scalar" and smooth_p == "all":
                # scalar weights (P kron I3 kept): smooth the node-level P0 with the level's block traces / 3,
                # restrict to P0's pattern, rows rescaled to sum 1
                Al = sp.csr_array(As[-1])
                nn = Al.shape[0] // 3
                tr = sum(Al[a::3, a::3] for a in range(3)) / 3.0
                tr = sp.csr_array(tr)
                ds = tr.diagonal()
                Ds = sp.diags(1.0 / ds)
                v = np.random.default_rng(0).standard_normal(nn)
                for _ in range(10):
                    v = Ds @ (tr @ v)
                    lam = float(np.linalg.norm(v))
                    v /= lam
                w = 4.0 / (3.0 * lam)
                Ps_ = sp.csr_array(P - w * (Ds @ (tr @ P)))
                mask = sp.csr_array((abs(P) > 0).astype(float))
                Ps_ = sp.csr_array(Ps_ * mask)
                rsum = np.asarray(Ps_.sum(axis=1)).ravel()
                Ps_ = sp.csr_array(sp.diags(1.0 / rsum) @ Ps_)
                P3 = sp.csr_array(sp.kron(Ps_, sp.identity(3), format="csr"))
            elif smooth_p == "all" or (smooth_p == "fine" and li == 0) or (smooth_p == "two" and li < 2):
                # smoothed prolongation (smoothed aggregation's P = (I - w D^-1 A) P0 on the geometric P0), with
                # w = 4 / (3 rho(D^-1 A)) from a power estimate: interpolation that relaxes into the level's
                # low-energy modes of the current (curved, wrinkled) configuration
                Asm = _canonical(A) if (p_raw_fine and li == 0) else As[-1]   # raw: the unfiltered fine matrix
                Dl = _bdiag(inv3(_diag_blocks(Asm)))
                if p_omega is None:
                    rho = power_bound(As[-1], Dl, 10) / 1.1
                    galerkin += 10 * As[-1].nnz
                elif p_omega == "inf":      # the guaranteed bound ||D^-1 A||_inf (one pass)
                    rho = float(abs(Dl @ As[-1]).sum(axis=1).max())
                    galerkin += As[-1].nnz
                else:
                    rho = 4.0 / (3.0 * float(p_omega))
                w = 4.0 / (3.0 * rho)
                self.p_rho = getattr(self, "p_rho", []) + [rho]
                galerkin += spgemm_work(As[-1], P3) + 9 * P3.nnz
                Psm = _canonical(P3 - w * (Dl @ (Asm @ P3)))
                if restrict_p is not None:
                    # keep the smoothed values only on the bilinear P0's block pattern (full 3x3 blocks), so that
                    # the coarse matrices keep today's pattern; "sum": then restore each fine block row's sum to
                    # the bilinear one (translations interpolated exactly)
                    mask = sp.csr_array(sp.kron((abs(P) > 0).astype(float), np.ones((3, 3)), format="csr"))
                    Pr = _canonical(Psm * mask)
                    if restrict_p == "sum":
                        # block row sums: (P 1_c)_f per 3x3; scale so the fine block row's sum equals P0's (I or 0)
                        nf = Pr.shape[0] // 3
                        E = sp.csr_array(sp.kron(np.ones((Pr.shape[1] // 3, 1)), np.eye(3), format="csr"))
                        rs = (Pr @ E).toarray().reshape(nf, 3, 3)      # each fine vertex's summed block
                        fix = np.linalg.inv(rs)                         # left-multiply the row's blocks by it
                        Pr = _canonical(_bdiag(fix) @ Pr)
                    galerkin += 2 * Pr.nnz
                    self.block_refresh = getattr(self, "block_refresh", 0.0) + block_refresh_work(As[-1], P)
                    Psm = Pr
                P3 = Psm
            self.p_nnz.append(P3.nnz / P3.shape[0])
            self.P.append(P3)
            AP = As[-1] @ P3
            galerkin += spgemm_work(As[-1], P3) + spgemm_work(P3.T, AP)
            As.append(_canonical(P3.T @ AP))
        nnz0 = As[0].nnz
        self.galerkin_work = galerkin / nnz0
        if hasattr(self, "block_refresh"):      # the fixed-pattern refresh's cost, as a compiled one would do it
            self.block_refresh /= nnz0
        self.level_nnz = [Al.nnz / Al.shape[0] for Al in As]
        self.box = box
        self.A = [Counted(Al, Al.nnz / nnz0, box) for Al in As]
        self.Dblocks = [inv3(_diag_blocks(Al)) for Al in As[:-1]]
        self.D = [_bdiag(B) for B in self.Dblocks]
        #: the coarsest solve: dense Cholesky, or a sparse LU for the two-grid diagnostic (exact coarse solve)
        if depth is not None:    # a sparse LU of the coarsest level; its two triangular solves counted as work
            lu = spla.splu(sp.csc_matrix(As[-1]))
            cw = (lu.L.nnz + lu.U.nnz) / nnz0
            self.coarse_nnz_share = cw

            def coarse(r, lu=lu, cw=cw):
                box[0] += cw
                return lu.solve(r)
            self.coarse = coarse
        else:
            chol = sla.cho_factor(As[-1].toarray())
            self.coarse = lambda r: sla.cho_solve(chol, r)
        self.growth = growth
        #: K-cycle: skip the second inner FCG iteration when ``|r1| <= threshold |r0|`` (``None``: never skip);
        #: ``kcount[l]``: how often level l's inner FCG took one / two iterations
        self.threshold = threshold
        self.kcount = [[0, 0] for _ in self.A]
        self.nu, self.cycle, self.smoother, self.degree, self.omega = nu, cycle, smoother, degree, omega
        self.lmax: list[float] = []
        self.setup_work = 0.0
        if smoother == "chebyshev":
            for Al, D in zip(self.A[:-1], self.D):
                if safe:       # a guaranteed bound: the spectral radius is at most the row-sum norm of D^-1 A
                    self.lmax.append(float(abs(D @ Al.A).sum(axis=1).max()))
                    box[0] += Al.w
                    continue
                self.lmax.append(power_bound(Al, D, 10))
            self.setup_work, box[0] = box[0], 0.0
        if smoother == "gs":      # per level and colour: its dof rows of A, its inverted diagonal blocks
            self.colours = []
            for Al, Db in zip(As[:-1], self.Dblocks):
                c = greedy_colours(Al)
                per = []
                for k in range(int(c.max()) + 1):
                    v = np.flatnonzero(c == k)
                    dofs = (3 * v[:, None] + np.arange(3)).ravel()
                    sel = sp.csr_array((np.ones(len(dofs)), (np.arange(len(dofs)), dofs)), shape=(len(dofs), Al.shape[0]))
                    rows = sp.csr_array(sel @ Al)     # (fancy row indexing of these matrices crashed scipy 1.17)
                    per.append((dofs, Counted(rows, rows.nnz / nnz0, box), _bdiag(Db[v])))
                self.colours.append(per)
        self.setup_s = time.perf_counter() - t0

    def n_colours(self) -> list[int]:
        return [len(c) for c in self.colours] if self.smoother == "gs" else []

    def _smooth(self, l: int, b: np.ndarray, x: np.ndarray | None, backward: bool = False) -> np.ndarray:
        """Smoothing sweeps on level ``l`` from ``x`` (``None``: zero, whose first product is skipped)."""
        A, D = self.A[l], self.D[l]
        if self.smoother == "jacobi":
            for _ in range(self.nu * self.growth ** l):
                x = self.omega * (D @ b) if x is None else x + self.omega * (D @ (b - A @ x))
            return x
        if self.smoother == "gs":
            zero = x is None
            x = np.zeros_like(b) if x is None else x.copy()
            order = self.colours[l][::-1] if backward else self.colours[l]
            for dofs, rows, Dc in order * self.growth ** l:
                if zero:                            # x = 0 so far: no product needed
                    x[dofs] = Dc @ b[dofs]
                    zero = False
                else:
                    x[dofs] += Dc @ (b[dofs] - rows @ x)
            return x
        return chebyshev(A, D, b, x, self.lmax[l], self.degree * self.growth ** l)

    def _cycle(self, l: int, b: np.ndarray) -> np.ndarray:
        if l == len(self.A) - 1:
            return self.coarse(b)
        x = self._smooth(l, b, None)
        if self.cycle == "K":     # the coarse correction: two FCG iterations on level l + 1 (exact at the coarsest)
            x = x + self.P[l] @ self._krylov(l + 1, self.P[l].T @ (b - self.A[l] @ x))
            return self._smooth(l, b, x, backward=True)
        gamma = 2 if (self.cycle == "W" or (self.cycle == "Wc" and l > 0)) and l < len(self.A) - 2 else 1
        for _ in range(gamma):
            x = x + self.P[l] @ self._cycle(l + 1, self.P[l].T @ (b - self.A[l] @ x))
        return self._smooth(l, b, x, backward=True)

    def _krylov(self, l: int, r: np.ndarray) -> np.ndarray:
        """The K-cycle's coarse solve of ``A_l x = r`` (Notay & Vassilevski 2008, Algorithm 2.1): from x = 0, one
        or two iterations of flexible CG (FCG(1): the second direction A-orthogonalised against the first)
        preconditioned by level l's cycle; the exact solve at the coarsest level. Its products with ``A_l`` count."""
        if l == len(self.A) - 1:
            return self.coarse(r)
        A = self.A[l]
        c = self._cycle(l, r)
        v = A @ c
        rho1, alpha1 = float(c @ v), float(c @ r)
        if rho1 <= 0.0:
            raise ValueError(f"K-cycle: c^T A c = {rho1:.3e} <= 0 on level {l}")
        r1 = r - (alpha1 / rho1) * v
        if self.threshold is not None and np.linalg.norm(r1) <= self.threshold * np.linalg.norm(r):
            self.kcount[l][0] += 1
            return (alpha1 / rho1) * c
        self.kcount[l][1] += 1
        d = self._cycle(l, r1)
        w = A @ d
        gamma, beta, alpha2 = float(d @ v), float(d @ w), float(d @ r1)
        rho2 = beta - gamma * gamma / rho1
        if rho2 <= 0.0:          # d in the span of c (to round-off): the first iteration's answer
            return (alpha1 / rho1) * c
        return (alpha1 / rho1 - gamma * alpha2 / (rho1 * rho2)) * c + (alpha2 / rho2) * d

    def apply(self, r: np.ndarray) -> np.ndarray:
        return self._cycle(0, r)


class SmoothedAggregation:
    """pyamg smoothed aggregation of ``S A S + (I - S)`` with the rigid motions as near-null space."""

    def __init__(self, A, filt: Filter, x: np.ndarray, box: list) -> None:
        import pyamg

        S = _bdiag(filt.matrices())
        K = sp.bsr_matrix(S @ A @ S + (sp.identity(A.shape[0], format="csr") - S), blocksize=(3, 3))
        t0 = time.perf_counter()
        state = np.random.get_state()  # noqa: NPY002 (pyamg reads the legacy global generator)
        np.random.seed(0)  # noqa: NPY002
        try:
            self.ml = pyamg.smoothed_aggregation_solver(K, B=rigid_modes(x), max_coarse=100)
        finally:
            np.random.set_state(state)  # noqa: NPY002
        self.setup_s = time.perf_counter() - t0
        self.M = self.ml.aspreconditioner(cycle="V")
        nnz = [lv.A.nnz for lv in self.ml.levels[:-1]]
        #: per V-cycle: on each level a symmetric Gauss-Seidel sweep (2 passes) before and after, and a residual
        self.per_apply = 5.0 * sum(m / nnz[0] for m in nnz)
        self.box = box
        self.setup_work = 0.0

    def apply(self, r: np.ndarray) -> np.ndarray:
        self.box[0] += self.per_apply
        return np.asarray(self.M @ r)


def flexible_pcg(A, b: np.ndarray, z: np.ndarray, filt: Filter, precond, tol: float = 1e-3,
                 max_iterations: int = 1000, mass: np.ndarray | None = None, min_delay: int = 4,
                 delay_fraction: float = 0.25, callback=None) -> tuple[np.ndarray, SolveResult]:
    """The numpy loop of the library's ``filtered_pcg`` (no guess, ``rule="estimate"``) made flexible for a
    preconditioner that is not a fixed linear operator (the K-cycle): FCG(1) (Notay 2000), i.e. CG with the
    Polak-Ribiere beta ``s_new^T (r_new - r_old) / delta_old``, here written as the equivalent explicit
    A-orthogonalisation of the new direction against the last one, ``beta = -s_new^T A p / p^T A p``, and the
    step ``alpha = p^T r / p^T A p``. Same filter handling, same initial residual and round-off / breakdown
    tests, the same guaranteed bound and error estimate (``ad_j = alpha_j p_j^T r_j``, the exact decrease of the
    squared A-norm error of the line search; the Euclidean part assumes global A-orthogonality, which FCG(1) keeps
    only locally). One product with ``A`` an iteration, as in PCG. With a fixed SPD preconditioner this is PCG
    in exact arithmetic. ``callback(it, dv)``, if given, sees every iterate (for the oracle stop)."""
    zc = z - filt.apply(z.copy())
    dv = zc.copy()
    r = filt.apply(b - A @ dv)
    norm0 = float(np.linalg.norm(r))
    if norm0 == 0.0:
        return dv, SolveResult(0, 0.0, True)
    s = filt.apply(precond.apply(r))
    p = s.copy()
    delta = float(r @ s)
    delta0 = delta
    ad = np.zeros(max_iterations)
    pw = np.zeros(max_iterations)
    inv_mass = None if mass is None else 1.0 / mass
    converged, error, it = False, np.inf, 0
    while not converged and delta > 0.0 and it < max_iterations:
        q = filt.apply(A @ p)
        pq = float(p @ q)
        if pq <= 0.0:
            break
        pr = float(p @ r)
        alpha = pr / pq
        dv += alpha * p
        r -= alpha * q
        ad[it] = alpha * pr
        pw[it] = float(p @ p) / pq
        it += 1
        if callback is not None:
            callback(it, dv)
        s = filt.apply(precond.apply(r))
        delta_new = float(r @ s)
        if delta_new < -1e-30 * delta0:
            break
        if delta_new <= 1e-30 * delta0:
            converged, error = True, 0.0
        else:
            if inv_mass is not None:
                error = np.sqrt(float(r @ (inv_mass * r)) / max(float(dv @ (mass * dv)), 1e-300))
                converged = error <= tol
            d = max(min_delay, int(delay_fraction * it))
            if not converged and it >= d:
                error = current_error_estimate(ad, pw, it, float(dv @ dv), d)
                converged = error <= tol
        if not converged:
            beta = -float(s @ q) / pq
            p *= beta
            p += s
        delta = delta_new
    res = float(np.linalg.norm(filt.apply(b - A @ dv))) / norm0
    return dv, SolveResult(it, res, converged, float(error))


def solve_variants(sysd: dict, variants: list[str], tol: float) -> list[dict]:
    A, b, z, filt = sysd["A"], sysd["b"], sysd["z"], sysd["filt"]
    Ps = grid_prolongations(*sysd["grid"])
    t0 = time.perf_counter()
    ref = direct(A, b, z, filt)
    direct_s = time.perf_counter() - t0
    nref = float(np.linalg.norm(ref))
    rows = []
    for name in variants:
        box = [0.0]
        try:
            opts = dict(VARIANTS[name])
            flexible = bool(opts.pop("flexible", False)) or opts.get("cycle") == "K"
            pc = (SmoothedAggregation(A, filt, sysd["x"], box) if name == "sa_rigid"
                  else VCycle(A, filt, Ps, box, **opts))
            Ac = Counted(A, 1.0, box)
            t1 = time.perf_counter()
            errs: list[float] = []       # the true error of every iterate (flexible outer CG only)
            if flexible:
                dv, res = flexible_pcg(Ac, b, z, filt, pc, tol, 2000, mass=sysd["mass3"],
                                       callback=lambda it, x, errs=errs, nref=nref: errs.append(
                                           float(np.linalg.norm(x - ref)) / nref))
            else:
                dv, res = filtered_pcg(Ac, b, z, filt, pc, tol, 2000, mass=sysd["mass3"], compiled=False)
            solve_s = time.perf_counter() - t1
        except (ValueError, np.linalg.LinAlgError, sla.LinAlgError) as e:
            print(f"{sysd['n']:4d}² step {sysd['step']:3d} {name:9s} failed: {type(e).__name__}: {e}", flush=True)
            rows.append({"n": sysd["n"], "step": sysd["step"], "variant": name, "failed": f"{type(e).__name__}: {e}"})
            continue
        work = box[0]
        #: the oracle stop: the first iterate within the tolerance (None: not recorded, or never)
        oracle = next((i + 1 for i, e in enumerate(errs) if e <= tol), None)
        kcount = [list(c) for c in pc.kcount] if isinstance(pc, VCycle) and pc.cycle == "K" else []
        rng = np.random.default_rng(1)       # is the preconditioner SPD on the free space? (r^T M r of filtered r)
        rmr = min(float(r @ pc.apply(r)) / float(r @ r) for r in (filt.apply(rng.standard_normal(len(b)))
                                                                    for _ in range(3)))
        d3, z3 = dv.reshape(-1, 3), z.reshape(-1, 3)
        exact = bool(np.array_equal(d3[filt.fixed], z3[filt.fixed]))
        row = {"n": sysd["n"], "step": sysd["step"], "variant": name, "iterations": res.iterations,
               "converged": res.converged, "true_error": float(np.linalg.norm(dv - ref) / np.linalg.norm(ref)),
               "work": work, "work_per_iteration": work / max(res.iterations, 1), "min_rMr": rmr,
               "setup_work": pc.setup_work, "setup_s": pc.setup_s, "solve_s": solve_s, "direct_s": direct_s,
               "pins_exact": exact, "library_iterations": sysd["library_iterations"],
               "colours": pc.n_colours() if isinstance(pc, VCycle) else [], "flexible": flexible,
               "k_inner": kcount, "estimate_at_stop": res.error, "oracle_iterations": oracle,
               "galerkin_work": getattr(pc, "galerkin_work", None), "block_refresh_work": getattr(pc, "block_refresh", None), "level_nnz_per_row": getattr(pc, "level_nnz", None)}
        rows.append(row)
        print(f"{sysd['n']:4d}² step {sysd['step']:3d} {name:9s} its {res.iterations:4d} (library V {sysd['library_iterations']}"
              f"{'' if oracle is None else f', oracle {oracle}'})"
              f"  true err {row['true_error']:.1e}{'' if rmr > 0 else ' (M INDEFINITE)'}  work {row['work']:6.1f} ({row['work_per_iteration']:.2f}/it"
              f" + setup {pc.setup_work:.0f})  setup {1e3 * pc.setup_s:.0f} ms  solve {1e3 * solve_s:.0f} ms"
              + (f"  colours {row['colours']}" if row["colours"] else "")
              + (f"  inner 1/2 its per level {kcount[1:-1]}" if kcount else "")
              + (f"  rho {[round(x, 2) for x in getattr(pc, 'p_rho', [])]}" if isinstance(pc, VCycle) else "")
              + (f"  block refresh {pc.block_refresh:.1f}" if hasattr(pc, "block_refresh") else "")
              + (f"  galerkin {pc.galerkin_work:.1f}  nnz/row {[round(x) for x in pc.level_nnz]}"
                 if isinstance(pc, VCycle) else ""), flush=True)
    return rows


# ----------------------------------------------------------------------------- report
def summary(rows: list[dict], sizes: list[int]) -> list[dict]:
    out = []
    for v in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == v and not r.get("failed")]
        per = {}
        for n in sizes:
            q = [r for r in rs if r["n"] == n]
            if q:
                per[n] = {"iterations": [r["iterations"] for r in q], "mean_iterations": statistics.mean(
                    r["iterations"] for r in q), "work": statistics.mean(r["work"] + r["setup_work"] for r in q),
                    "work_per_iteration": statistics.mean(r["work_per_iteration"] for r in q),
                    "max_error": max(r["true_error"] for r in q),
                    "setup_ms": 1e3 * statistics.median(r["setup_s"] for r in q),
                    "ms_per_iteration": 1e3 * statistics.median(r["solve_s"] / max(r["iterations"], 1) for r in q),
                    "converged": all(r["converged"] for r in q), "pins_exact": all(r["pins_exact"] for r in q)}
                if all(r.get("oracle_iterations") is not None for r in q):
                    per[n]["oracle_iterations"] = [r["oracle_iterations"] for r in q]
                    per[n]["max_error_over_estimate"] = max(r["true_error"] / max(r["estimate_at_stop"], 1e-300)
                                                            for r in q)
        lo, hi = min(per, default=None), max(per, default=None)
        ratio = per[hi]["mean_iterations"] / per[lo]["mean_iterations"] if per and hi != lo else None
        out.append({"variant": v, "sizes": per, "ratio": ratio, "failed": len([r for r in rows if r["variant"] == v
                                                                               and r.get("failed")])})
    return out


def markdown(res: dict) -> str:
    sizes = res["sizes"]
    lo, hi = min(sizes), max(sizes)
    out = [f"Hanging stiff cloth k = {res['k']:g} N/m, dt = 1/60 s, fixed steps; systems of steps "
           f"{', '.join(map(str, res['steps']))} at each size; filtered PCG (numpy), tolerance {res['tolerance']:g}, "
           "the library's stopping rule.", "",
           "Iterations: mean over the steps (each step's in brackets). Work: fine-level SpMV equivalents of the "
           "whole solve (CG's products plus every level's matrix products in the preconditioner, at their share "
           "of the fine level's entries; Chebyshev's power iterations included), mean over the steps. True error: "
           "the largest over the steps, against a direct solve. Times: numpy on a shared machine, indication only.",
           "", "| variant | " + " | ".join(f"its {n}²" for n in sizes) + f" | ratio {hi}²/{lo}² | "
           + " | ".join(f"work {n}²" for n in sizes) + " | work/it | max true error | setup ms (largest) "
           "| ms/it (largest) |", "|---|" + "---|" * (2 * len(sizes) + 5)]
    for s in res["summary"]:
        p = s["sizes"]
        if not p:
            out.append(f"| {s['variant']} | failed |")
            continue
        its = [f"{p[n]['mean_iterations']:.1f} ({'/'.join(map(str, p[n]['iterations']))})" if n in p else "-"
               for n in sizes]
        work = [f"{p[n]['work']:.0f}" if n in p else "-" for n in sizes]
        big = p[max(p)]
        err = max(q["max_error"] for q in p.values())
        ratio = f"{s['ratio']:.2f}" if s["ratio"] is not None else "-"
        out.append(f"| {s['variant']} | " + " | ".join(its) + f" | {ratio} | " + " | ".join(work)
                   + f" | {big['work_per_iteration']:.2f} | {err:.1e} | {big['setup_ms']:.0f} | "
                   f"{big['ms_per_iteration']:.0f} |")
    out.append("")
    orc = [s for s in res["summary"] if s["sizes"] and all("oracle_iterations" in q for q in s["sizes"].values())]
    if orc:
        out += ["Flexible outer CG only: the oracle stop (the first iterate whose true error is within the tolerance; "
                "mean over the steps, each in brackets) and the stopping rule's read at its stop (largest true error "
                "/ the estimate or bound it stopped on).", "",
                "| variant | " + " | ".join(f"oracle its {n}²" for n in sizes) + f" | oracle ratio {hi}²/{lo}² | "
                "max true error / estimate at stop |", "|---|" + "---|" * (len(sizes) + 2)]
        for s in orc:
            p = s["sizes"]
            cells = [f"{statistics.mean(p[n]['oracle_iterations']):.1f} ({'/'.join(map(str, p[n]['oracle_iterations']))})"
                     if n in p else "-" for n in sizes]
            lo_, hi_ = min(p), max(p)
            ratio = (f"{statistics.mean(p[hi_]['oracle_iterations']) / statistics.mean(p[lo_]['oracle_iterations']):.2f}"
                     if hi_ != lo_ else "-")
            worst = max(q["max_error_over_estimate"] for q in p.values())
            out.append(f"| {s['variant']} | " + " | ".join(cells) + f" | {ratio} | {worst:.2f} |")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--steps", type=int, nargs="+", default=[10, 30, 60])
    p.add_argument("--k", type=float, default=1e4)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--tolerance", type=float, default=None, help="default: the solver's default tolerance")
    p.add_argument("--out", default=default_out('mg_levers'), help="output folder (default out/bench/mg_levers)")
    p.add_argument("--merge", nargs="+", default=[],
                   help="mg_levers.json files of earlier runs (same steps and k) whose rows are merged, no new solves")
    a = p.parse_args(argv)
    if a.merge:
        import json

        runs = [json.loads(Path(f).read_text()) for f in a.merge]
        rows = [r for run in runs for r in run["rows"]]
        sizes = sorted({r["n"] for r in rows})
        variants = list(dict.fromkeys(r["variant"] for r in rows))
        res = {**runs[0], "sizes": sizes, "variants": variants, "rows": rows, "summary": summary(rows, sizes),
               "merged_from": [str(f) for f in a.merge]}
        md = markdown(res)
        write_outputs(Path(a.out), "mg_levers", res, md)
        print(md)
        return 0
    rows, tol = [], a.tolerance
    for n in a.sizes:
        t0 = time.perf_counter()
        systems = capture(n, a.k, a.steps)
        print(f"{n}²: captured steps {[s['step'] for s in systems]} in {time.perf_counter() - t0:.0f} s", flush=True)
        for sysd in systems:
            tol = sysd["tol"] if a.tolerance is None else a.tolerance
            rows += solve_variants(sysd, a.variants, tol)
    res = {"benchmark": "mg_levers", "sizes": a.sizes, "steps": a.steps, "k": a.k, "tolerance": tol,
           "variants": a.variants, "rows": rows, "summary": summary(rows, a.sizes), "machine": machine()}
    md = markdown(res)
    write_outputs(Path(a.out), "mg_levers", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
