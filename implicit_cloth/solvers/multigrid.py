"""Multigrid V-cycle preconditioner for the filtered PCG, with a fixed hierarchy and cheap refresh.

The hierarchy is built once per cloth from *node-level* prolongations
``P_l`` (n_l x n_{l+1}) that act on each displacement component alike
(``P_l kron I3``):

* grid cloths: bilinear interpolation between every other grid line
  (geometric multigrid; the last line is kept when the count is even);
* mesh cloths: smoothed aggregation (pyamg) on the graph of structural springs.

Every step the level matrices are refreshed by Galerkin products
``A_{l+1} = P_l^T A_l P_l``, which for ``P kron I3`` are sums of weighted
3x3 blocks::

    A_{l+1}[I, J] = sum_{i, j} P[i, I] P[j, J] A_l[i, j]

Since the block patterns never change, that sum is one sparse matrix ``T_l``
(n_blocks_{l+1} x n_blocks_l), built once, applied to the (n_blocks, 9) block
values: no sparse matrix-matrix product per step.

Constraints: the V-cycle preconditions ``S A S + (I - S)``, which is SPD
whenever A is and leaves constrained components untouched, so the
Baraff-Witkin filter stays exact. (The smoothed multigrid weighs the
constrained directions of its finest prolongation by the vertices' masses,
so that its coarse levels do not take that identity for the cloth's
stiffness: :meth:`SmoothedProlongation.weigh_constrained`.) Smoother: one damped block-Jacobi sweep
before and after the coarse correction (symmetric, so the V-cycle is an SPD
preconditioner, as CG needs). Coarsest level: dense Cholesky, shifted by a
multiple of the identity when round-off makes the matrix numerically
indefinite (see :func:`coarse_cholesky`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .. import backend as _backend
from ..assembly import SystemMatrix, accumulate_product
from ..backend import (
    THREAD_CHUNKS,
    Backend,
    BackendMismatch,
    get_backend,
    set_numba_threads,
    thread_min_vertices,
    threads,
)
from .blocks import block_diagonal_operator, inv3
from .pcg import Filter, SolveResult


# ----------------------------------------------------------------------------- prolongations
def _interp_1d(n: int) -> sp.csr_array:
    """Linear interpolation from every other point (and the last) of n points on a line."""
    coarse = np.arange(0, n, 2)
    if coarse[-1] != n - 1:
        coarse = np.append(coarse, n - 1)
    i = np.arange(n)
    k = np.searchsorted(coarse, i)                  # coarse[k] >= i
    exact = coarse[np.minimum(k, len(coarse) - 1)] == i
    lo = np.where(exact, k, k - 1)
    hi = np.minimum(lo + 1, len(coarse) - 1)
    w = np.where(exact, 0.0, (i - coarse[lo]) / np.maximum(coarse[hi] - coarse[lo], 1))
    rows = np.concatenate([i, i[~exact]])
    cols = np.concatenate([lo, hi[~exact]])
    vals = np.concatenate([1.0 - w, w[~exact]])
    return sp.csr_array((vals, (rows, cols)), shape=(n, len(coarse)))


#: A grid cloth of at most this many vertices is solved directly (a single level: the dense factor); a grid of
#: fewer than :data:`COARSEST_FROM` vertices is coarsened until its coarsest level has at most this many.
DIRECT_VERTICES = 100
#: A grid of :data:`COARSEST_FROM` vertices or more is coarsened until its coarsest level has at most this many
#: (5 x 5 from a square grid), whose dense Cholesky factor the V-cycle solves with. At 81 vertices (the bound
#: of :data:`DIRECT_VERTICES`) the factor and its two triangular solves a cycle (243 unknowns:
#: 0.45 ms and 67 us here) were a quarter of a 32² peer step; at 25 they are 32 us and 6 us, and the extra level
#: of smoothing costs less than it saves (the peer scene, one step a frame, one thread, best of 3 twice:
#: 32² 4.3 -> 3.4 ms, 64² 15.9 -> 14.8, 128² the same within the noise, 256² 443 -> 389; CG iterations
#: -5 % .. +12 %; docs/benchmarks.md, "A coarsest level of 25 vertices").
COARSEST_VERTICES = 30
#: Below this many vertices the coarsest level keeps up to :data:`DIRECT_VERTICES`. The deeper hierarchy is
#: faster there too (16² 1.6 -> 0.9 ms a step), but it re-rolls four chaotic small test scenes (a 16² drape's
#: landing sways longer, a 16² towel folds otherwise, a 12² cloth released from one point overshoots the
#: strain bound, a balance premise): not yet looked into, so those sizes are unchanged for now.
COARSEST_FROM = 1024


def grid_prolongations(nx: int, ny: int, min_vertices: int | None = None,
                       direct_vertices: int = DIRECT_VERTICES) -> list[sp.csr_array]:
    """Bilinear prolongations of a grid cloth (vertex index j*nx + i), coarsened until <= min_vertices
    (default :data:`COARSEST_VERTICES` from :data:`COARSEST_FROM` vertices, else ``direct_vertices``); none (a
    direct solve) for a grid of at most ``direct_vertices``."""
    out: list[sp.csr_array] = []
    if nx * ny <= direct_vertices:
        return out
    if min_vertices is None:
        min_vertices = COARSEST_VERTICES if nx * ny >= COARSEST_FROM else direct_vertices
    while nx * ny > min_vertices and (nx > 2 or ny > 2):
        px, py = _interp_1d(nx) if nx > 2 else sp.identity(nx, format="csr"), \
            _interp_1d(ny) if ny > 2 else sp.identity(ny, format="csr")
        out.append(sp.csr_array(sp.kron(py, px, format="csr")))
        nx, ny = px.shape[1], py.shape[1]
    return out


def aggregation_prolongations(n: int, edges: np.ndarray, min_vertices: int = 100) -> list[sp.csr_array]:
    """Smoothed-aggregation prolongations (pyamg) on the graph of a mesh cloth's edges."""
    import pyamg  # deferred: only mesh cloths with multigrid need it

    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    adj = sp.csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adj = ((adj + adj.T) > 0).astype(float)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    lap = sp.diags(deg + 1e-3 * np.maximum(deg.mean(), 1.0)) - adj   # graph Laplacian, slightly shifted
    # pyamg estimates the smoother's spectral radius from a random start vector (numpy's global generator): a
    # fixed one, so that a mesh cloth (or several pieces) runs bit for bit the same in every process
    state = np.random.get_state()  # noqa: NPY002 (the legacy global generator is the one pyamg reads)
    np.random.seed(0)  # noqa: NPY002
    try:
        ml = pyamg.smoothed_aggregation_solver(lap.tocsr(), max_coarse=min_vertices, keep=False)
    finally:
        np.random.set_state(state)  # noqa: NPY002
    return [sp.csr_array(lvl.P) for lvl in ml.levels[:-1]]


# ----------------------------------------------------------------------------- hierarchy
#: The K-cycle's coarse correction skips its second flexible-CG iteration when the first left the level's
#: residual at most this fraction of its right-hand side (Notay's AGMG: 0.25).
K_THRESHOLD = 0.25


class _Level:
    """One coarse level: its block pattern, Galerkin map from the level above, transfer and smoother."""

    def __init__(self, fine: SystemMatrix, P: sp.csr_array) -> None:
        P = sp.csr_array(P)
        P.sort_indices()
        nb = fine.n_blocks
        br, bc = fine.block_rows, fine.block_cols
        ptr, idx, val = P.indptr, P.indices, P.data
        cr = ptr[br + 1] - ptr[br]
        cc = ptr[bc + 1] - ptr[bc]
        per = cr * cc
        b = np.repeat(np.arange(nb), per)
        k = np.arange(len(b)) - np.repeat(np.cumsum(per) - per, per)
        pr, pc = k // cc[b], k % cc[b]
        I = idx[ptr[br[b]] + pr]
        J = idx[ptr[bc[b]] + pc]
        w = val[ptr[br[b]] + pr] * val[ptr[bc[b]] + pc]
        nc = P.shape[1]
        keys = np.unique(I * nc + J)
        off = keys[keys // nc != keys % nc]
        self.system = SystemMatrix(nc, np.stack([off // nc, off % nc], axis=1), fine.backend)
        rows = self.system.block_index(I, J)
        #: Galerkin map: coarse blocks (nbc, 9) = T @ fine blocks (nb, 9)
        self.T = sp.csr_array((w, (rows, b)), shape=(self.system.n_blocks, nb))
        self.T.sum_duplicates()
        #: vector transfer (3 n_fine, 3 n_coarse)
        self.P3 = sp.csr_array(sp.kron(P, sp.identity(3), format="csr"))
        self.R3 = sp.csr_array(self.P3.T.tocsr())


#: Damping ``w`` of the prolongation smoothing of ``"multigrid_smoothed"`` (:class:`SmoothedProlongation`): fixed,
#: since a power estimate of the spectral radius of ``D^-1 A`` (1.8-2.6 on the stiff hanging cloth's levels,
#: where ``4 / (3 rho)`` is 0.5-0.7) costs ten matrix passes a level a step and gave the same iterations
#: (benchmarks/studies/mg_levers.py, ``spr_sum`` against ``spr_sum_w07``).
SMOOTH_P_OMEGA = 0.7


class SmoothedProlongation:
    """Build-time lists of one level's smoothed prolongation (the kernels' docstring,
    :mod:`implicit_cloth.kernels.smoothed`): ``P[f, c] = F_f (P0[f, c] I - w D_f^-1 sum_j A[f, j] P0[j, c])``
    on ``P0``'s node pattern, refreshed every step from the level's matrix.

    For every entry ``e = (f, c)`` of ``P0`` (sorted CSR) its terms: the level's blocks ``(f, j)`` with
    ``P0[j, c] != 0``, as a position in the level's block list (``t_blk``: the numpy path) and as a code into the
    diagonal + upper storage of the compiled path (``t_code = 3 k + kind``: kind 0 diagonal block ``k``, 1 upper
    block ``k``, 2 upper block ``k`` transposed), with the weight ``t_w = P0[j, c]``.
    """

    def __init__(self, system: SystemMatrix, P0: sp.csr_array, upper: np.ndarray, finest: bool = False) -> None:
        #: whether it prolongs to the finest level, the one that holds the constraints (weigh_constrained)
        self.finest = finest
        P0 = sp.csr_array(P0, copy=True)
        P0.sum_duplicates()
        P0.sort_indices()
        self.ptr = P0.indptr.astype(np.int64)
        self.idx = P0.indices.astype(np.int64)
        self.p0 = P0.data.astype(float)
        nf, nc = P0.shape
        self.shape = (nf, nc)
        self.e_row = np.repeat(np.arange(nf), np.diff(self.ptr))
        #: the row sums to restore: a translation is interpolated as by P0
        self.target = np.bincount(self.e_row, weights=self.p0, minlength=nf)
        br, bc = system.block_rows, system.block_cols
        upos = np.full(system.n_blocks, -1, dtype=np.int64)
        upos[upper] = np.arange(len(upper))
        kind = np.where(br == bc, 0, np.where(br < bc, 1, 2))
        lower = kind == 2
        code_k = np.where(kind == 0, br, upos)
        if lower.any():
            code_k[lower] = upos[system.block_index(bc[lower], br[lower])]
        cnt = self.ptr[bc + 1] - self.ptr[bc]
        src = np.repeat(np.arange(system.n_blocks), cnt)
        k = np.arange(len(src)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        m = self.ptr[bc[src]] + k                       # P0 entry (j, c)
        f, c = br[src], self.idx[m]
        keys = self.e_row * nc + self.idx               # sorted: CSR order
        q = f * nc + c
        pos = np.searchsorted(keys, q)
        ok = pos < len(keys)
        ok[ok] = keys[pos[ok]] == q[ok]
        e = pos[ok]
        order = np.argsort(e, kind="stable")
        self.t_ptr = np.concatenate([[0], np.cumsum(np.bincount(e, minlength=len(keys)))]).astype(np.int64)
        self.t_blk = src[ok][order].astype(np.int64)
        self.t_code = (3 * code_k[self.t_blk] + kind[self.t_blk]).astype(np.int32)
        self.t_w = np.ascontiguousarray(self.p0[m[ok][order]])
        #: P^T's CSR order as positions in P's entries (the restriction's blocks are their transposes)
        self.tperm = np.lexsort((self.e_row, self.idx)).astype(np.int64)

    def blocks_numpy(self, blocks: np.ndarray, dinv: np.ndarray, omega: float) -> np.ndarray:
        """The prolongation blocks (nnz, 3, 3) from a level's (filtered) block values and inverted diagonal
        blocks: the numpy reference of :func:`implicit_cloth.kernels.smoothed.smooth_prolongation`."""
        nnz = len(self.p0)
        terms = self.t_w[:, None] * blocks[self.t_blk].reshape(-1, 9)
        acc = np.zeros((nnz, 9))
        np.add.at(acc, np.repeat(np.arange(nnz), np.diff(self.t_ptr)), terms)
        Pt = self.p0[:, None, None] * np.eye(3) - omega * (dinv[self.e_row] @ acc.reshape(-1, 3, 3))
        rs = np.zeros((self.shape[0], 3, 3))
        np.add.at(rs, self.e_row, Pt)
        det = np.linalg.det(rs)
        scale = np.maximum(np.abs(np.diagonal(rs, axis1=1, axis2=2)).max(axis=1), 1e-300) ** 3
        good = np.isfinite(det) & (np.abs(det) > 1e-12 * scale)
        F = np.zeros_like(rs)
        F[good] = self.target[good, None, None] * np.linalg.inv(rs[good])
        P = F[self.e_row] @ Pt
        bad = ~good[self.e_row]
        P[bad] = self.p0[bad, None, None] * np.eye(3)
        return P

    def weigh_constrained(self, pblocks: np.ndarray, filt: Filter, masses: np.ndarray | None) -> None:
        """Weigh, in place, the constrained directions of the prolongation's rows at the partially constrained
        fine vertices by the square root of the vertex's mass: ``P[f, c] <- (S_f + sqrt(m_f) (I - S_f)) P[f, c]``
        (the finest level's prolongation only; ``masses`` None: not weighed).

        The filtered matrix ``S A S + (I - S)`` the V-cycle preconditions has an identity (1 kg) in the
        constrained directions, where ``A = M + ...`` holds a vertex's mass (6e-6 kg on a 128² cloth of 0.1 kg).
        A coarse function that moves a contact's vertex along its normal paid that identity in the Galerkin
        product ``P^T (S A S + (I - S)) P``: the coarse levels took the motion of a region in contact (a draped
        cloth sliding over a sphere) for 1e5 times stiffer than it is, and corrected it by next to nothing. With
        the weight it pays the vertex's mass, as it would free. Zeroing the rows' normal part instead (``S_f P``)
        leaves a coarse node inside a flat contact without its normal direction (a singular coarse block):
        a sheet on a box blew up. CG and its filter are untouched: only the preconditioner changes.
        """
        if masses is None or not self.finest or not len(filt.partial):
            return
        rows = filt.partial
        cnt = self.ptr[rows + 1] - self.ptr[rows]
        first = np.repeat(self.ptr[rows], cnt)
        ent = first + np.arange(len(first)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        S = np.repeat(filt.partial_S, cnt, axis=0)
        w = np.repeat(np.sqrt(masses[rows]), cnt)
        pblocks[ent] = (S + w[:, None, None] * (np.eye(3) - S)) @ pblocks[ent]

    def csr(self, pblocks: np.ndarray) -> sp.csr_array:
        """The (3 n_f, 3 n_c) prolongation of the given blocks."""
        nf, nc = self.shape
        return sp.csr_array(sp.bsr_array((pblocks, self.idx, self.ptr), shape=(3 * nf, 3 * nc)).tocsr())


class Multigrid:
    """V-cycle preconditioner over a fixed hierarchy (see module docstring).

    Parameters
    ----------
    system : SystemMatrix
        The model's fine-level system (pattern).
    prolongations : list of sparse (n_l, n_{l+1})
        Node-level prolongations, finest first.
    omega : float
        Damping of the block-Jacobi smoother (0 < omega <= 1).
    name : str
        Reported name.
    smoothed : bool
        Smooth the prolongations every step from the level matrices (:class:`SmoothedProlongation`;
        ``solver.preconditioner = "multigrid_smoothed"``) instead of the fixed ``P kron I3``.
    masses : (n,) array, optional
        The fine vertices' masses, kg: with ``smoothed``, the weight of the contacts' constrained directions in
        the coarse levels (:meth:`SmoothedProlongation.weigh_constrained`; None: an identity).
    """

    #: multigrid-preconditioned CG converges steadily: its error estimate is reliable
    stopping_rule = "estimate"

    def __init__(self, system: SystemMatrix, prolongations: list, omega: float = 0.7,
                 name: str = "multigrid", accelerator: str | Backend | None = None, smoothed: bool = False,
                 p_omega: float = SMOOTH_P_OMEGA, masses: np.ndarray | None = None) -> None:
        self.name = name
        self.masses = None if masses is None else np.asarray(masses, dtype=float)
        self.omega = float(omega)
        self.smoothed = bool(smoothed)
        #: the cycle (``solver.cycle``): "V", or "K" (Notay's K-cycle, :func:`implicit_cloth.kernels.pcg.kcycle`:
        #: not a fixed linear operator, so CG runs flexible with it, :attr:`flexible`)
        self.cycle = "V"
        self.p_omega = float(p_omega)
        self.fine = system
        #: the back-end: the system's (the model's) unless one is named; numba runs the packed hierarchy
        #: and the whole PCG compiled (:class:`_FusedHierarchy`), numpy the reference (:class:`_NumpyHierarchy`)
        self.backend = system.backend if accelerator is None else get_backend(accelerator)
        self.levels: list[_Level] = []
        cur = system
        #: per level, with ``smoothed``: the smoothing's term lists (the level's upper blocks as the compiled
        #: storage orders them) and the current blocks
        self.sprol: list[SmoothedProlongation] = []
        for P in prolongations:
            lvl = _Level(cur, P)
            if self.smoothed:
                self.sprol.append(SmoothedProlongation(cur, P, np.flatnonzero(cur.block_rows < cur.block_cols),
                                                       finest=not self.sprol))
            self.levels.append(lvl)
            cur = lvl.system
        #: whether every setup estimates each coarse level's smoother damping (:data:`SMOOTHER_RHO`): off until
        #: a solve breaks down on an indefinite V-cycle (:meth:`protect`), then for the rest of the run
        self.damped = False
        self._filt: Filter | None = None
        #: per level, the smoother's damping of the last setup (the finest level's is ``omega``;
        #: :data:`SMOOTHER_RHO`) and the estimate of ``lambda_max(D^-1 A)`` it came from (nan: not estimated)
        self.level_omega = np.full(len(self.levels) + 1, self.omega)
        self.level_lambda = np.full(len(self.levels) + 1, np.nan)
        #: per coarse level, made at its first estimate: its fixed start vector and its most blocks a row
        self._estimate_data: dict[int, tuple[np.ndarray, float]] = {}
        self._blocks: list[np.ndarray] = []
        self._A: list[sp.csr_array] = []
        self._chol: Any = None
        #: shift added to the coarsest matrix by the last setup (0: none; see coarse_cholesky)
        self.coarse_shift = 0.0
        self.engine: _NumpyHierarchy | _FusedHierarchy = (
            _FusedHierarchy(self, prolongations) if self.backend.compiled else _NumpyHierarchy(self))

    @property
    def flexible(self) -> bool:
        """Whether the preconditioner varies with its argument (the K-cycle): CG's ``beta`` is then Polak-Ribiere's
        (:func:`~implicit_cloth.solvers.pcg.filtered_pcg`)."""
        return self.cycle == "K"

    @property
    def accelerator(self) -> str:
        """The back-end's name, as the run report gives it: "numba" or "numpy"."""
        return self.backend.name

    @property
    def compiled(self) -> bool:
        """Whether the whole filtered PCG runs compiled (:meth:`fused_pcg`) with this preconditioner."""
        return self.backend.compiled

    def _systems(self) -> list[SystemMatrix]:
        return [self.fine] + [lvl.system for lvl in self.levels]

    @property
    def n_levels(self) -> int:
        return len(self.levels) + 1

    def setup(self, system: SystemMatrix | None, filt: Filter) -> None:
        """Refresh every level from the fine system's current values (call after assembly).

        ``system`` is the assembled fine system (the one this hierarchy was built on, read through
        ``self.fine``); it is part of the preconditioner protocol shared with :class:`BlockJacobi`.
        """
        self._filt = filt
        C = self.engine.setup(filt)
        self._chol, self.coarse_shift = coarse_cholesky(C)

    def protect(self) -> bool:
        """After a CG breakdown on this preconditioner (not positive definite: a coarse level's smoother
        amplifying, :data:`SMOOTHER_RHO`): from now on every setup damps each coarse level's smoother to its
        estimated ``lambda_max``, starting with the hierarchy set up again now from the current values. Returns
        whether anything changed (False when already so, or never set up)."""
        if self.damped or self._filt is None:
            return False
        self.damped = True
        self.setup(self.fine, self._filt)
        return True

    def refresh_diagonal(self, system: SystemMatrix | None, filt: Filter) -> None:
        """After a change of the fine system's diagonal blocks only, with the filter of the last setup: the
        fine level's copy and smoother follow, the coarse levels stay (an SPD preconditioner still, for the
        slightly different matrix). Falls back to :meth:`setup` where the engine has no such refresh."""
        if isinstance(self.engine, _FusedHierarchy) and self.engine.filt is filt:
            self.engine.refresh_diagonal()
        else:
            self.setup(system, filt)

    def apply(self, r: np.ndarray) -> np.ndarray:
        """One cycle (:attr:`cycle`, V or K): an approximation of ``(S A S + I - S)^-1 r``."""
        return self.engine.apply(r)

    def fused_pcg(self, A, b: np.ndarray, z: np.ndarray, filt: Filter, **kw) -> tuple[np.ndarray, SolveResult]:
        """The whole filtered PCG compiled (the numba back-end; :func:`~.pcg.filtered_pcg` calls it).

        ``A`` must be the fine system's own CSR matrix unchanged since :meth:`setup` (no
        ``finalize`` in between) and ``filt`` the filter of the last setup: the compiled CG
        multiplies by the blocks packed at setup. Anything else is a
        :class:`~implicit_cloth.backend.BackendMismatch`, never a silent numpy solve.
        """
        if not isinstance(self.engine, _FusedHierarchy):
            raise BackendMismatch(f"fused_pcg: the {self.name} preconditioner runs on the numpy back-end, "
                                  f"which has no compiled PCG")
        return self.engine.pcg(A, b, z, filt, **kw)

    def coarse_solve(self, b: np.ndarray) -> np.ndarray:
        """The coarsest level's exact solve with the factor of the last setup."""
        return sla.cho_solve(self._chol, b, check_finite=False)

    def _level_estimate_data(self, l: int) -> tuple[np.ndarray, float]:
        """Coarse level ``l``'s fixed start vector for its damping's estimate and its most blocks a row (the
        bound of :func:`smoother_damping`), made on first use."""
        if l not in self._estimate_data:
            s = self._systems()[l]
            self._estimate_data[l] = (np.random.default_rng(l).standard_normal(3 * s.n),
                                      float(np.bincount(s.block_rows, minlength=s.n).max()))
        return self._estimate_data[l]

    def _probe(self, l: int) -> np.ndarray:
        """A copy of coarse level ``l``'s fixed start vector (the estimate overwrites it)."""
        return self._level_estimate_data(l)[0].copy()

    def _set_damping(self, l: int, lam: float) -> None:
        """Level ``l``'s smoother damping from its estimated ``lambda_max(D^-1 A)`` (:data:`SMOOTHER_RHO`)."""
        self.level_lambda[l] = lam
        self.level_omega[l] = smoother_damping(self.omega, lam, self._level_estimate_data(l)[1])


class _NumpyHierarchy:
    """The reference path: every level's matrix as CSR, inverted diagonal blocks as block-diagonal CSR."""

    def __init__(self, mg: Multigrid) -> None:
        self.mg = mg
        self._D = [block_diagonal_operator(s.n) for s in mg._systems()]
        #: the transfers: the fixed ``P kron I3``, or with ``smoothed`` the ones of the last setup
        self.P3 = [lvl.P3 for lvl in mg.levels]
        self.R3 = [lvl.R3 for lvl in mg.levels]

    def setup(self, filt: Filter) -> np.ndarray:
        """Refresh the levels; returns the coarsest matrix (dense) to factorise."""
        mg = self.mg
        fine = mg.fine
        blocks = fine.blocks
        if not filt.trivial:
            blocks = _filtered_blocks(fine, blocks, filt)
        systems = mg._systems()
        mg._A, mg._blocks = [], []
        dinv = np.zeros((0, 3, 3))
        for l, sm in enumerate(systems):
            if l > 0 and mg.smoothed:            # P from the level above's matrix, then P^T A P into the pattern
                spl = mg.sprol[l - 1]
                pblocks = spl.blocks_numpy(blocks, dinv, mg.p_omega)
                spl.weigh_constrained(pblocks, filt, mg.masses)
                P3 = spl.csr(pblocks)
                self.P3[l - 1], self.R3[l - 1] = P3, sp.csr_array(P3.T.tocsr())
                Cc = sp.coo_array(P3.T @ mg._A[-1] @ P3)
                sm.reset()
                kb = sm.block_index(Cc.row // 3, Cc.col // 3)
                np.add.at(sm.blocks, (kb, Cc.row % 3, Cc.col % 3), Cc.data)
                blocks = sm.blocks
                A = sm.finalize()
            elif l > 0:
                sm.reset()
                accumulate_product(mg.levels[l - 1].T, blocks.reshape(-1, 9), sm.blocks.reshape(-1, 9))
                blocks = sm.blocks
                A = sm.finalize()
            elif blocks is fine.blocks:
                A = fine.csr
            else:
                A = _csr_from_blocks(fine, blocks)
            mg._A.append(A)
            mg._blocks.append(blocks)
            dinv = inv3(blocks[sm.diag_index])          # the smoother's, and the next level's smoothing of P
            self._D[l].data[:] = dinv.reshape(-1)
            if mg.damped and 0 < l < len(systems) - 1:  # a smoothed coarse level: its damping (SMOOTHER_RHO)
                mg._set_damping(l, self._lanczos(l, blocks[sm.diag_index]))
        return mg._A[-1].toarray()

    def _lanczos(self, l: int, D: np.ndarray) -> float:
        """:func:`implicit_cloth.kernels.pcg.smoother_lanczos` in numpy: level ``l``'s estimate of
        ``lambda_max(D^-1 A)`` (``D`` its diagonal blocks)."""
        A, Dinv = self.mg._A[l], self._D[l]

        def dnorm(x: np.ndarray) -> float:
            return float(np.sqrt(np.einsum("ni,nij,nj->", x.reshape(-1, 3), D, x.reshape(-1, 3))))

        q = self.mg._probe(l)
        nq = dnorm(q)
        if not nq > 0.0:
            return float("nan")
        q /= nq
        qp = np.zeros_like(q)
        alpha, beta = np.zeros(SMOOTHER_LANCZOS_STEPS), np.zeros(SMOOTHER_LANCZOS_STEPS)
        b, steps = 0.0, SMOOTHER_LANCZOS_STEPS
        for s in range(SMOOTHER_LANCZOS_STEPS):
            aq = A @ q
            alpha[s] = float(q @ aq)
            if s == SMOOTHER_LANCZOS_STEPS - 1:
                break
            w = Dinv @ aq - alpha[s] * q - b * qp
            b = dnorm(w)
            if not b > 0.0:
                steps = s + 1
                break
            beta[s] = b
            qp, q = q, w / b
        return ritz_max(alpha, beta, steps)

    def apply(self, r: np.ndarray) -> np.ndarray:
        return self._vcycle(0, r)

    def _vcycle(self, l: int, b: np.ndarray) -> np.ndarray:
        mg = self.mg
        if l == len(mg.levels):
            return mg.coarse_solve(b)
        A, D, w = mg._A[l], self._D[l], mg.level_omega[l]
        x = w * (D @ b)                                   # pre-smooth from x = 0
        rc = self.R3[l] @ (b - A @ x)
        if mg.cycle == "K" and l + 1 < len(mg.levels):
            x += self.P3[l] @ self._kstep(l + 1, rc)
        else:
            x += self.P3[l] @ self._vcycle(l + 1, rc)
        x += w * (D @ (b - A @ x))                        # post-smooth
        return x

    def _kstep(self, m: int, r: np.ndarray) -> np.ndarray:
        """The K-cycle's coarse correction on level ``m`` (Notay & Vassilevski 2008, Algorithm 2.1): one or two
        flexible-CG iterations on ``A_m x = r`` from zero, preconditioned by level ``m``'s cycle; the second is
        skipped when the first leaves ``|r1| <= K_THRESHOLD |r|`` (the compiled :func:`~implicit_cloth.kernels.pcg.
        kcycle` in the same order)."""
        A = self.mg._A[m]
        c1 = self._vcycle(m, r)
        v1 = A @ c1
        rho1 = float(c1 @ v1)
        if not rho1 > 0.0:
            return c1
        a1 = float(c1 @ r)
        r1 = r - (a1 / rho1) * v1
        if float(r1 @ r1) <= K_THRESHOLD ** 2 * float(r @ r):
            return (a1 / rho1) * c1
        c2 = self._vcycle(m, r1)
        v2 = A @ c2
        g = float(c2 @ v1)
        beta = float(c2 @ v2) - g * g / rho1
        a2 = float(c2 @ r1)
        if not beta > 0.0:
            return (a1 / rho1) * c1
        return (a1 / rho1 - g * a2 / (rho1 * beta)) * c1 + (a2 / beta) * c2


def coarse_cholesky(C: np.ndarray, max_tries: int = 40) -> tuple[tuple[np.ndarray, bool], float]:
    """Cholesky factor of the coarsest matrix, or of ``C + tau I`` when ``C`` is numerically indefinite.

    ``C = M + h^2 K + ...`` is SPD in exact arithmetic, but once ``k h^2 / m_i``
    exceeds about ``1 / eps = 4.5e15`` the mass term falls below the round-off
    of the stiffness term, and the rigid modes of ``K`` (eigenvalue ~ ``m_i``)
    come out slightly negative. Then ``tau`` starts at ``n eps max|C_ii|`` (the
    size of that round-off) and grows tenfold until the factorisation succeeds
    (Nocedal & Wright 2006, Algorithm 3.3). ``(C + tau I)^-1`` is still SPD, so
    the V-cycle stays a valid CG preconditioner, only a weaker one for the
    modes below ``tau``; CG then needs more iterations or reports the step
    unconverged, which the run counts.

    Parameters
    ----------
    C : (n, n) array
        The coarsest-level matrix.
    max_tries : int
        Shifts tried after the unshifted factorisation (tau grows by 10 each).

    Returns
    -------
    factor : tuple
        For :func:`scipy.linalg.cho_solve`.
    tau : float
        The shift used (0 when ``C`` itself factorised), in the units of ``C`` (kg).
        A matrix with a non-finite entry (an overflowed assembly) is not
        factorised: the identity stands in and ``tau`` is NaN; the solve then
        produces a non-finite step, which the simulator reports as a divergence.
    """
    if not np.all(np.isfinite(C)):
        return (np.eye(len(C)), False), float("nan")
    try:
        return sla.cho_factor(C, lower=False, check_finite=False), 0.0
    except np.linalg.LinAlgError:
        pass
    scale = float(np.abs(np.diagonal(C)).max()) if len(C) else 1.0
    tau = max(len(C) * np.finfo(float).eps * scale, np.finfo(float).tiny)
    eye = np.eye(len(C))
    for _ in range(max_tries):
        try:
            return sla.cho_factor(C + tau * eye, lower=False, check_finite=False), tau
        except np.linalg.LinAlgError:
            tau *= 10.0
    # unreachable for a finite symmetric C: tau has passed its largest eigenvalue bound n max|C_ij|
    return (np.eye(len(C)), False), float("nan")


def _concat_csr(mats: list) -> tuple:
    """Row pointers (each matrix's own, local), column indices and values of CSR matrices laid end to end,
    and where each matrix's pointers start (for the kernels' per-level slices)."""
    mats = [sp.csr_array(M) for M in mats]
    for M in mats:
        M.sort_indices()
    off = np.zeros(max(len(mats), 1), dtype=np.int64)
    off[1:len(mats)] = np.cumsum([M.shape[0] + 1 for M in mats])[:-1]
    if not mats:
        return np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros(0), off
    return (np.concatenate([M.indptr for M in mats]).astype(np.int64),
            np.concatenate([M.indices for M in mats]).astype(np.int32),
            np.concatenate([M.data for M in mats]).astype(float), off)


def _galerkin_entries(fine: SystemMatrix, coarse: SystemMatrix, fine_up: np.ndarray, coarse_up: np.ndarray,
                      P, entries: bool = False) -> tuple:
    """Entry lists of :func:`implicit_cloth.kernels.pcg.galerkin` for ``coarse = P^T fine P`` (``P kron I3``),
    both levels in
    diagonal + upper-block storage (``*_up``: positions of the upper blocks in each level's block list).
    With ``entries``, each list also carries the two prolongation entries of every term (positions in ``P``'s
    sorted CSR), for a block prolongation on ``P``'s pattern
    (:func:`implicit_cloth.kernels.smoothed.galerkin_blocks`): ``(d_ptr, d_dst, d_w, d_pa, d_pb, u_...)``."""
    P = sp.csr_array(P)
    P.sort_indices()
    ptr, idx, val = P.indptr, P.indices, P.data
    upos = np.full(coarse.n_blocks, -1, dtype=np.int64)
    upos[coarse_up] = np.arange(len(coarse_up))

    def expand(br, bc):
        cr, cc = ptr[br + 1] - ptr[br], ptr[bc + 1] - ptr[bc]
        per = cr * cc
        src = np.repeat(np.arange(len(br)), per)
        k = np.arange(len(src)) - np.repeat(np.cumsum(per) - per, per)
        a, b = ptr[br[src]] + k // cc[src], ptr[bc[src]] + k % cc[src]
        return src, idx[a].astype(np.int64), idx[b].astype(np.int64), val[a] * val[b], a, b

    # diagonal blocks (i, i): pairs (I, J) of row i's entries with I <= J
    i = np.arange(fine.n)
    src, I, J, w, ea, eb = expand(i, i)
    keep = I <= J
    src, I, J, w, ea, eb = src[keep], I[keep], J[keep], w[keep], ea[keep], eb[keep]
    todiag = I == J
    dst = np.where(todiag, I, upos[coarse.block_index(I, J)] if len(I) else I)
    d = _packed_entries(src, fine.n, 4 * dst + 3 * todiag, w, (ea, eb) if entries else ())
    # upper blocks (i, j), i < j
    src, I, J, w, ea, eb = expand(fine.block_rows[fine_up], fine.block_cols[fine_up])
    mode = np.where(I < J, 0, np.where(I > J, 1, 2))
    lo, hi = np.minimum(I, J), np.maximum(I, J)
    off = lo != hi
    dst = lo.copy()
    if off.any():
        dst[off] = upos[coarse.block_index(lo[off], hi[off])]
    u = _packed_entries(src, len(fine_up), 4 * dst + mode, w, (ea, eb) if entries else ())
    return d + u


def _packed_entries(src: np.ndarray, n_src: int, code: np.ndarray, w: np.ndarray, extra: tuple = ()) -> tuple:
    """Entries sorted by source block: (pointer per source, packed destination ``4 t + mode``, weight, and any
    ``extra`` per-entry arrays in the same order, as int32)."""
    if len(code) and (code.min() < 0 or code.max() >= 2**31):
        raise ValueError("Galerkin entry outside the coarse pattern")   # a bug, not a user error
    order = np.argsort(src, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n_src))]).astype(np.int64)
    return (ptr, code[order].astype(np.int32), np.ascontiguousarray(w[order], dtype=float),
            *(np.ascontiguousarray(x[order], dtype=np.int32) for x in extra))


def _filtered_blocks(sm: SystemMatrix, blocks: np.ndarray, filt: Filter) -> np.ndarray:
    """Blocks of ``S A S + (I - S)``: rows and columns of constrained vertices filtered."""
    out = blocks.copy()
    n = sm.n
    if len(filt.fixed):
        fixed = np.zeros(n, dtype=bool)
        fixed[filt.fixed] = True
        out[fixed[sm.block_rows] | fixed[sm.block_cols]] = 0.0
        out[sm.diag_index[filt.fixed]] = np.eye(3)
    if len(filt.partial):
        S = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        S[filt.partial] = filt.partial_S
        part = np.zeros(n, dtype=bool)
        part[filt.partial] = True
        sel = np.flatnonzero(part[sm.block_rows] | part[sm.block_cols])
        out[sel] = S[sm.block_rows[sel]] @ out[sel] @ S[sm.block_cols[sel]]
        out[sm.diag_index[filt.partial]] += np.eye(3) - filt.partial_S
    return out


def _csr_from_blocks(sm: SystemMatrix, blocks: np.ndarray) -> sp.csr_array:
    """A CSR matrix with ``sm``'s pattern and the given block values (a new matrix; sm is untouched)."""
    A = sm.csr.copy()
    np.take(blocks.reshape(-1), sm._perm, out=A.data)
    return A


#: Once a solve has broken down on the hierarchy (:meth:`Multigrid.protect`), a coarse level's block-Jacobi
#: smoother is damped to ``omega_l = min(omega, SMOOTHER_RHO / lambda_l)``, ``lambda_l`` the level's largest
#: eigenvalue of ``D^-1 A`` estimated at every setup (:data:`SMOOTHER_LANCZOS_STEPS` Lanczos steps from a fixed
#: start, the largest Ritz value: from below, within 2.5 % on the levels measured). One damped Jacobi sweep
#: scales an error mode of eigenvalue ``lambda`` by ``1 - omega lambda``: past ``omega lambda_max = 2`` it
#: amplifies the top modes and the V-cycle is no longer positive definite. The Galerkin levels get there: on the
#: shared 128² drape ``omega lambda_max`` reached 2.78 / 2.65 on levels 1 / 2 of the smoothed hierarchy (CG broke
#: down after 0-10 iterations, and adaptive stepping halved 18 steps in the first second), 2.1-2.2 on the plain
#: one's, and 2.7 on levels 3-5 of the smoothed 256² hanging cloth (which converges all the same). The bound
#: 1.75 leaves the fixed 0.7 wherever ``lambda_max <= 2.5`` (the hanging cloths' levels 1-2 measured 2.2-2.5)
#: with a margin for the estimate's error. The finest level keeps ``omega`` (0.7 times a ``lambda_max`` of 1.98
#: on every cloth measured, drape and hanging: a sum of spring Laplacians over their diagonal stays within 2).
#: Why not from the start: estimated at every setup it costs 1.0 / 3.9 / 21.7 ms a setup at 64² / 128² / 256²
#: (8-12 % of a step), and where nothing breaks the damped levels took more iterations (the 256² hanging cloth,
#: one step a frame: 13.4 against 12.3 a frame); runs that never break down keep their numbers.
SMOOTHER_RHO = 1.75
#: Lanczos steps of each coarse level's estimate per setup (see :data:`SMOOTHER_RHO`); from a fixed start every
#: time, so that a setup's damping depends on its matrices only. (Power iterations were 13-16 % low after 8;
#: continued from the last setup's vector, 3 a setup, they missed a mode that a landing made dominant: 2.18
#: for 3.14 on the 32² drape.)
SMOOTHER_LANCZOS_STEPS = 10


def ritz_max(alpha: np.ndarray, beta: np.ndarray, steps: int) -> float:
    """The largest eigenvalue of the Lanczos tridiagonal matrix of ``steps`` steps (nan for none)."""
    if steps <= 0:
        return float("nan")
    if steps == 1:
        return float(alpha[0])
    from scipy.linalg import eigh_tridiagonal

    ev = eigh_tridiagonal(alpha[:steps], beta[:steps - 1], eigvals_only=True, select="i",
                          select_range=(steps - 1, steps - 1))
    return float(ev[0])


def smoother_damping(omega: float, lam: float, bound: float) -> float:
    """The damping of a level whose estimated ``lambda_max(D^-1 A)`` is ``lam`` (:data:`SMOOTHER_RHO`), the
    estimate taken at most ``bound``, and ``bound`` where it is not a positive number. ``bound``: the level's
    most blocks in a block row, which ``lambda_max(D^-1 A)`` of a positive definite matrix cannot exceed
    (``A <= k D`` for ``k`` blocks a row, by Cauchy-Schwarz); the float32 levels of a 512² cloth gave Ritz
    values beyond it (their diagonal blocks rounded to nearly singular), which would stop their smoothing."""
    lam = min(lam, bound) if np.isfinite(lam) and lam > 0.0 else bound
    return min(omega, SMOOTHER_RHO / lam)


#: From this many fine vertices on, the compiled V-cycle keeps its matrices in float32, the fine spring blocks'
#: six-number copy included (vectors, sums, the Galerkin products, the coarse Cholesky and CG itself, with its
#: own float64 copy of the fine matrix, stay float64; the solve's stopping rule and tolerance are CG's, so the
#: accuracy of dv is unchanged). Where the hierarchy no longer fits the cache the passes are limited by memory
#: traffic and half the bytes pay: on the shared hanging scene (2 shared cores, 32 MiB L3) a CG iteration
#: took 7.5-7.8 instead of 8.8-9.0 ms at 192² and 13.6-13.9 instead of 16.0-16.6 ms at 256² (one thread;
#: 9.8 instead of 10.1-11.3 on two), the same iterations; at 128² (everything in cache) the same time
#: within the noise. ``None`` turns it off.
#:
#: The plain multigrid only: the smoothed one (``multigrid_smoothed``) keeps float64. Its prolongation's 3x3
#: blocks mix the directions, and its float32 levels lose the modes only the mass holds (a flat sheet's
#: out-of-plane motion, 1e-5 of the in-plane stiffness at 256²): on the shared drape at 256² its V-cycle turned
#: indefinite, 88 of 557 solves broke down in the first 0.25 s (a free-falling sheet from its fifth step; 0 of
#: 170 in float64, 83 s against 27), and on the hanging scene at 256² float64 was faster as well (130-134
#: against 143-148 ms a frame, one step a frame on two threads, 12.6 against 13.0 CG iterations).
FLOAT32_MIN_VERTICES: int | None = 32768


#: From this many fine vertices CG's dot products are summed over THREAD_CHUNKS fixed chunks, whatever the
#: thread count (the partial sums on threads when the finest level's passes are, then added in order), so
#: that they can run on threads and still give the same numbers at every thread count; smaller cloths keep
#: one plain serial sum (the numbers they always had). At 256² on two threads the serial sums were about a
#: tenth of a CG iteration.
CHUNKED_SUMS_MIN_VERTICES = 16384


def thread_chunks(n: int, uI: np.ndarray, uJ: np.ndarray, chunks: int = THREAD_CHUNKS) -> tuple:
    """Chunks of a level for the threaded symmetric product (:func:`implicit_cloth.kernels.pcg._psymmv`).

    The vertices are cut into ``chunks`` equal ranges; chunk c owns the rows of its range: the stored upper
    blocks ``(uI[k], uJ[k])`` (sorted by row) whose row is in it, a contiguous range of ``k``, and, on their
    column side, the blocks of earlier rows whose column is in it. Returns ``(vertex bounds, block bounds,
    offsets of the incoming lists, the incoming blocks ascending)``.
    """
    vb = np.linspace(0, n, chunks + 1).round().astype(np.int64)
    kb = np.searchsorted(uI, vb).astype(np.int64)
    oi = np.searchsorted(vb, uI, side="right") - 1
    oj = np.searchsorted(vb, uJ, side="right") - 1
    cross = np.flatnonzero(oj != oi)                  # ascending
    owner = oj[cross]
    order = np.argsort(owner, kind="stable")
    ip = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=chunks))]).astype(np.int64)
    return vb, kb, ip, cross[order].astype(np.int32)


def galerkin_chunks(d_ptr: np.ndarray, d_dst: np.ndarray, u_ptr: np.ndarray, u_dst: np.ndarray, cuI: np.ndarray,
                    n_coarse: int, chunks: int = THREAD_CHUNKS) -> tuple:
    """The entries of a level's Galerkin lists (:func:`_galerkin_entries`) cut by the coarse row of the block each
    adds to, for :func:`implicit_cloth.kernels.pcg.pgalerkin` and
    :func:`implicit_cloth.kernels.smoothed.pgalerkin_blocks`: ``chunks`` ranges of coarse rows holding about as
    many entries each. ``cuI``: the coarse level's upper blocks' rows. Returns ``(d_src, d_ord, d_cb, u_src,
    u_ord, u_cb)``: each entry's source block, the entries chunk by chunk (ascending within one: the serial
    order of every coarse block's sum) and the chunks' bounds in that list."""
    def rows(dst: np.ndarray, diag_mode: int) -> np.ndarray:
        """The coarse row of each entry's block: ``t`` itself for a diagonal block, else upper block ``t``'s."""
        t = dst.astype(np.int64) >> 2
        on_diag = (dst & 3) == diag_mode
        return np.where(on_diag, t, cuI[np.where(on_diag, 0, t)])

    rd, ru = rows(d_dst, 3), rows(u_dst, 2)
    cum = np.cumsum(np.bincount(rd, minlength=n_coarse) + np.bincount(ru, minlength=n_coarse))
    rb = np.searchsorted(cum, np.linspace(0, cum[-1] if len(cum) else 0, chunks + 1)[1:-1], side="left")
    out: list = []
    for ptr, r in ((d_ptr, rd), (u_ptr, ru)):
        src = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr)).astype(np.int32)
        ch = np.searchsorted(rb, r, side="right")
        order = np.argsort(ch, kind="stable").astype(np.int32)
        cb = np.concatenate([[0], np.cumsum(np.bincount(ch, minlength=chunks))]).astype(np.int64)
        out += [src, order, cb]
    return tuple(out)


def galerkin_sequence(d_ptr: np.ndarray, d_lists: tuple, u_ptr: np.ndarray, u_lists: tuple, cuI: np.ndarray,
                      n_coarse: int, chunks: int = THREAD_CHUNKS) -> tuple:
    """A level's Galerkin entry lists in :func:`galerkin_chunks`' order, for the chunked Galerkin kernels
    (:func:`implicit_cloth.kernels.pcg.pgalerkin`, :func:`implicit_cloth.kernels.smoothed.pgalerkin_blocks`),
    which then read each chunk's entries sequentially: ``d_lists`` / ``u_lists`` the per-entry arrays of the
    diagonal and upper lists, destinations first (the plain product: destinations and weights; the smoothed:
    destinations and the two prolongation entries). Returns ``(d_src, *d_lists, d_cb, u_src, *u_lists, u_cb)``
    permuted: each list's source blocks and arrays chunk by chunk (integer arrays as int32), and the chunks'
    bounds."""
    dsrc, dord, dcb, usrc, uord, ucb = galerkin_chunks(d_ptr, d_lists[0], u_ptr, u_lists[0], cuI, n_coarse, chunks)
    out: list = []
    for src, order, cb, lists in ((dsrc, dord, dcb, d_lists), (usrc, uord, ucb, u_lists)):
        out.append(np.ascontiguousarray(src[order], dtype=np.int32))
        out += [np.ascontiguousarray(a[order], dtype=np.int32 if a.dtype.kind in "iu" else a.dtype) for a in lists]
        out.append(cb)
    return tuple(out)


class PackedHierarchy(NamedTuple):
    """The packed hierarchy the compiled V-cycle reads (:func:`implicit_cloth.kernels.pcg.vcycle`), in its
    argument order: every level's diagonal and upper blocks, the filter at the constrained vertices, the
    inverted diagonal blocks, the transfers and the coarsest solve."""

    dg: np.ndarray        #: (sum n_l, 3, 3) diagonal blocks of every level (float32 from FLOAT32_MIN_VERTICES)
    uI: np.ndarray        #: row vertex of every stored upper block (i < j), all levels
    uJ: np.ndarray        #: its column vertex
    uv: np.ndarray        #: (sum u_l, 3, 3) the upper blocks
    u6: np.ndarray        #: the fine upper blocks' six distinct numbers (used while all are symmetric; float32
                          #: with the float32 V-cycle)
    use6: bool            #: whether u6 is used
    voff: np.ndarray      #: level l's vertices are voff[l]:voff[l+1]
    uoff: np.ndarray      #: level l's upper blocks are uoff[l]:uoff[l+1]
    clist: np.ndarray     #: constrained fine vertices (fixed, then partial)
    Sc: np.ndarray        #: their 3x3 filters
    ws: np.ndarray        #: work array for the filtered vertices
    dinv: np.ndarray      #: inverted diagonal blocks (the smoother), all levels
    pptr: np.ndarray      #: prolongations P, CSR, concatenated (pointers, indices, values, offsets, nnz offsets)
    pidx: np.ndarray
    pval: np.ndarray
    poff: np.ndarray
    pnnz: np.ndarray
    tptr: np.ndarray      #: restrictions P^T, CSR, concatenated
    tidx: np.ndarray
    tval: np.ndarray
    toff: np.ndarray
    C: np.ndarray         #: the coarsest solve: its upper Cholesky factor, or its dense inverse
    upper: bool           #: True: C is the factor
    omegas: np.ndarray    #: per level: the smoother's damping (Multigrid.level_omega)
    lpar: np.ndarray | None   #: per level: whether its passes run on threads (see :func:`thread_chunks`); None: none
    lpv: np.ndarray       #: per level: THREAD_CHUNKS + 1 vertex bounds, then as many block-row bounds
    lpb: np.ndarray       #: per level: THREAD_CHUNKS + 1 offsets into pbb
    pbb: np.ndarray       #: each chunk's incoming column blocks (local to the level), ascending


class _FusedHierarchy:
    """The hierarchy packed into flat arrays for the compiled kernels (:mod:`implicit_cloth.kernels.pcg`), and
    their drivers.

    Every level's matrix is symmetric, so the kernels store only its
    diagonal blocks and its upper blocks (``i < j``; the lower block
    ``(j, i)`` is the transpose), packed level after level, and multiply
    with one pass over each stored block that serves both ``(i, j)`` and
    ``(j, i)`` (:func:`implicit_cloth.kernels.pcg._symmv`): half the matrix data read per pass
    and a flat loop, 2-5x faster than a CSR or block-row product on the test
    machine. The coarse levels' block values are refreshed by the same
    Galerkin maps as the numpy path and then packed; the fine level's are
    gathered from the assembled blocks at setup (one pass over half of them),
    for CG's products and for the V-cycle (a float32 copy for the latter from
    :data:`FLOAT32_MIN_VERTICES` on, when set). The filter is applied on the
    fly on the finest level, and the first Galerkin product is corrected by the
    few fine blocks that touch a constrained vertex, filtered as they are read
    (:func:`implicit_cloth.kernels.pcg.galerkin_filter`): no per-filter set-up.
    """

    def __init__(self, mg: Multigrid, prolongations: list) -> None:
        from ..kernels import pcg as _fused  # noqa: F401  (imports numba now; the kernels compile, or load from cache, on first use)

        self.mg = mg
        systems = mg._systems()
        fine = mg.fine
        self.voff = np.cumsum([0] + [sm.n for sm in systems]).astype(np.int64)
        f = self.precond_dtype = (np.float32 if FLOAT32_MIN_VERTICES is not None and not mg.smoothed
                                  and fine.n >= FLOAT32_MIN_VERTICES else np.float64)
        self._uidx = [np.flatnonzero(sm.block_rows < sm.block_cols) for sm in systems]
        nup = [len(u) for u in self._uidx]
        self.uoff = np.cumsum([0] + nup).astype(np.int64)
        self.uI = np.concatenate([sm.block_rows[u] for sm, u in zip(systems, self._uidx)]).astype(np.int32)
        self.uJ = np.concatenate([sm.block_cols[u] for sm, u in zip(systems, self._uidx)]).astype(np.int32)
        self.dg = np.zeros((int(self.voff[-1]), 3, 3), dtype=f)
        self.uv = np.zeros((int(self.uoff[-1]), 3, 3), dtype=f)
        n0, u0 = fine.n, nup[0]
        if f == np.float64:                      # CG and the V-cycle share the fine level's arrays
            self.adg, self.auv = self.dg[:n0], self.uv[:u0]
        else:
            self.adg, self.auv = np.zeros((n0, 3, 3)), np.zeros((u0, 3, 3))
        self.auI, self.auJ = self.uI[:u0], self.uJ[:u0]
        #: the fine upper blocks' six distinct numbers, used while every one of them is exactly symmetric
        self.au6 = np.zeros((u0, 6))
        #: the V-cycle's copy of them: ``au6`` itself in float64, a float32 copy with the float32 V-cycle
        self.vu6 = self.au6 if f == np.float64 else np.zeros((u0, 6), dtype=f)
        self.use6 = False
        Ps = [sp.csr_array(P) for P in prolongations]
        self.pptr, self.pidx, self.pval, self.poff = _concat_csr(Ps)
        self.pnnz = np.cumsum([0] + [P.nnz for P in Ps]).astype(np.int64)
        # P^T as CSR: restriction as a gather (same entry ranges as P)
        self.tptr, self.tidx, self.tval, self.toff = _concat_csr([sp.csr_array(P.T) for P in Ps])
        self._gal = [_galerkin_entries(systems[l], systems[l + 1], self._uidx[l], self._uidx[l + 1], P,
                                       entries=mg.smoothed)
                     for l, P in enumerate(prolongations)]
        if mg.smoothed:    # block transfers, refreshed every setup (9 numbers an entry; P^T's are transposes)
            self.pval = np.zeros(9 * int(self.pnnz[-1]))
            self.tval = np.zeros(9 * int(self.pnnz[-1]))
            #: P^T's entries as positions in P's, all levels
            self._tperm = np.concatenate([s_.tperm + self.pnnz[l] for l, s_ in enumerate(mg.sprol)]
                                         ) if mg.sprol else np.zeros(0, dtype=np.int64)
            self._empty_c = np.zeros(0, dtype=np.int64)
            #: each level's rows cut into THREAD_CHUNKS for the smoothing kernel
            self._rows = [np.linspace(0, sm.n, THREAD_CHUNKS + 1).round().astype(np.int64) for sm in systems[:-1]]
            self._empty_S = np.zeros((0, 3, 3))
        self.dinv = np.zeros((int(self.voff[-1]), 3, 3), dtype=f)
        self.wb = np.zeros(3 * int(self.voff[-1]))
        self.wx = np.zeros(3 * int(self.voff[-1]))
        self.wr = np.zeros(3 * int(self.voff[-1]))
        #: the K-cycle's scratch for :meth:`apply` (:func:`implicit_cloth.kernels.pcg.kcycle`), made on first use
        self._kscratch: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._chunks(systems)
        self.filt: Filter | None = None
        self.version = -1

    def __setstate__(self, state: dict) -> None:
        """Unpickled: the fine level's arrays shared by CG and the V-cycle are views again (pickling copies
        them apart, and the V-cycle would keep the fine values of the moment it was pickled)."""
        self.__dict__.update(state)
        n0, u0 = len(self.adg), len(self.auv)          # (the copies: their lengths are right)
        if self.precond_dtype == np.float64:
            self.adg, self.auv = self.dg[:n0], self.uv[:u0]
            self.vu6 = self.au6
        self.auI, self.auJ = self.uI[:u0], self.uJ[:u0]

    def _chunks(self, systems: list[SystemMatrix]) -> None:
        """Every level's chunks for the threaded passes: those of at least backend.THREAD_MIN_VERTICES vertices (which
        run on threads is decided per solve, :meth:`_threaded_levels`)."""
        K = THREAD_CHUNKS + 1
        L1 = len(systems)
        self._level_n = np.array([sm.n for sm in systems])
        self.lpar = np.zeros(L1, dtype=np.uint8)
        self.lpv = np.zeros(2 * L1 * K, dtype=np.int64)
        self.lpb = np.zeros(L1 * K, dtype=np.int64)
        lists, base = [], 0
        for l, sm in enumerate(systems):
            if sm.n < _backend.THREAD_MIN_VERTICES:
                continue
            u0, u1 = self.uoff[l], self.uoff[l + 1]
            vb, kb, ip, ib = thread_chunks(sm.n, self.uI[u0:u1], self.uJ[u0:u1])
            self.lpar[l] = 1
            self.lpv[2 * l * K:(2 * l + 1) * K] = vb
            self.lpv[(2 * l + 1) * K:(2 * l + 2) * K] = kb
            self.lpb[l * K:(l + 1) * K] = ip + base
            lists.append(ib)
            base += len(ib)
        self.pbb = np.concatenate(lists) if lists else np.zeros(0, dtype=np.int32)
        # the fixed chunks CG's dot products are summed over (empty: one serial sum; CHUNKED_SUMS_MIN_VERTICES)
        n0 = systems[0].n
        self.sum_chunks = (np.linspace(0, 3 * n0, THREAD_CHUNKS + 1).round().astype(np.int64)
                           if n0 >= CHUNKED_SUMS_MIN_VERTICES else np.zeros(0, dtype=np.int64))

    def _threaded_levels(self) -> np.ndarray:
        """``lpar`` for this process's threading layer: the chunked levels of at least :func:`thread_min_vertices`."""
        return (self.lpar & (self._level_n >= thread_min_vertices())).astype(np.uint8)

    def _filter_arrays(self, filt: Filter) -> None:
        self.clist = np.concatenate([filt.fixed, filt.partial]).astype(np.int64)
        self.Sc = np.ascontiguousarray(
            np.concatenate([np.zeros((len(filt.fixed), 3, 3)), filt.partial_S]).reshape(-1, 3, 3))
        self.ws = np.zeros(3 * len(self.clist))

    def setup(self, filt: Filter) -> np.ndarray:
        """Pack the levels' current values; returns the coarsest matrix (dense) to factorise."""
        mg, fine = self.mg, self.mg.fine
        L = len(mg.levels)
        self.filt = filt
        self._filter_arrays(filt)
        from ..kernels import pcg as _fused
        if mg.smoothed:
            from ..kernels import smoothed as _smoothed

        flat = fine.blocks.reshape(-1)
        par = mg.backend.threaded(fine.n)               # the copies on threads: the same numbers
        if mg.smoothed and not par:
            set_numba_threads()     # the smoothed set-up's kernels are parallel regions at every thread count
        gather = _fused.pgather_blocks if par else _fused.gather_blocks
        gather(flat, fine.diag_index, self.adg.reshape(-1))
        gather(flat, self._uidx[0], self.auv.reshape(-1))
        self.use6 = bool((_fused.pgather_sym6 if par else _fused.gather_sym6)(flat, self._uidx[0], self.au6))
        if self.precond_dtype != np.float64:     # the V-cycle's float32 copy
            self.dg[:fine.n] = self.adg
            if self.use6:                        # its fine products read the six numbers, not uv's level 0
                self.vu6[:] = self.au6
            else:
                self.uv[:len(self.auv)] = self.auv
        self.version = fine.version
        c, Sc = self.clist, self.Sc
        n0 = fine.n
        self._fine_inverses()
        if L == 0:
            mg._A = [_csr_from_blocks(fine, _filtered_blocks(fine, fine.blocks, filt))]
            return mg._A[-1].toarray()
        for l in range(1, L + 1):
            v0, v1, v2 = self.voff[l - 1], self.voff[l], self.voff[l + 1]
            u0, u1, u2 = self.uoff[l - 1], self.uoff[l], self.uoff[l + 1]
            src_d, src_u = (self.adg, self.auv) if l == 1 else (self.dg[v0:v1], self.uv[u0:u1])
            gal = self._gal[l - 1]
            if l == 1 and len(c):     # the constrained vertices' filters, and the fine blocks touching them
                cpos = np.full(n0, -1, dtype=np.int64)
                cpos[c] = np.arange(len(c))
                td = np.flatnonzero(cpos >= 0)
                tu = np.flatnonzero((cpos[self.auI] >= 0) | (cpos[self.auJ] >= 0))
            if mg.smoothed:           # the level's block prolongation from its current (filtered) matrix
                spl = mg.sprol[l - 1]
                pb = self.pval[9 * self.pnnz[l - 1]:9 * self.pnnz[l]]
                filt_c = cpos if (l == 1 and len(c)) else self._empty_c
                sargs = (src_d.reshape(-1), src_u.reshape(-1), self.dinv[v0:v1].reshape(-1), spl.ptr, spl.p0,
                         spl.target, spl.t_ptr, spl.t_code, spl.t_w, self.uI[u0:u1], self.uJ[u0:u1], filt_c,
                         Sc if len(filt_c) else self._empty_S, mg.p_omega, pb)
                # the chunked kernels at every thread count: the serial kernels' numbers (tested), and compiled as
                # numba parallel regions they are faster even on one thread (at 128² the smoothing 5.6x, the
                # product 2.2x)
                _smoothed.psmooth_prolongation(*sargs, self._rows[l - 1])
                spl.weigh_constrained(pb.reshape(-1, 3, 3), filt, mg.masses)
                gargs: tuple[Any, ...] = (src_d.reshape(-1), src_u.reshape(-1), self.dg[v1:v2].reshape(-1),
                                          self.uv[u1:u2].reshape(-1)) + self._gal_chunks(l - 1) + (pb,)
                _smoothed.pgalerkin_blocks(*gargs)
                if l == 1 and len(c):     # the correction of the blocks touching a constrained vertex
                    _smoothed.pgalerkin_blocks_filter(*(gargs + (cpos, Sc, self.auI, self.auJ, td, tu)))
            else:
                args = (src_d.reshape(-1), src_u.reshape(-1), self.dg[v1:v2].reshape(-1),
                        self.uv[u1:u2].reshape(-1), gal[0], gal[1], gal[2], gal[3], gal[4], gal[5])
                if mg.backend.threaded(v1 - v0):     # on threads (one: slower than serial)
                    _fused.pgalerkin(*(args[:4] + self._gal_chunks(l - 1)))
                else:
                    _fused.galerkin(*args)
                if l == 1 and len(c):     # the product of the filtered fine matrix S A S + (I - S)
                    _fused.galerkin_filter(*args, cpos, Sc, self.auI, self.auJ, td, tu)
            if l < L:
                _fused.inv3(self.dg[v1:v2].reshape(-1), self.dinv[v1:v2].reshape(-1))
            if l < L and mg.damped:      # the level's smoother damping (SMOOTHER_RHO)
                alpha, beta = np.zeros(SMOOTHER_LANCZOS_STEPS), np.zeros(SMOOTHER_LANCZOS_STEPS)
                steps = _fused.smoother_lanczos(l, self.dg, self.uI, self.uJ, self.uv, self.voff, self.uoff,
                                                self.dinv, mg._probe(l), alpha, beta)
                mg._set_damping(l, ritz_max(alpha, beta, steps))
        if mg.smoothed:               # the restrictions: P^T's blocks are P's transposed, in P^T's CSR order
            _smoothed.ptranspose_blocks(self.pval, self._tperm, self.tval)
        mg._A = [None] * (L + 1)
        return self.coarse_dense()

    def refresh_diagonal(self) -> None:
        """The fine level's diagonal blocks and their smoother inverses from the fine system's current values
        (its off-diagonal blocks and the filter unchanged since :meth:`setup`); the coarse levels kept."""
        fine = self.mg.fine
        from ..kernels import pcg as _fused
        _fused.gather_blocks(fine.blocks.reshape(-1), fine.diag_index, self.adg.reshape(-1))
        if self.precond_dtype != np.float64:     # the V-cycle's float32 copy
            self.dg[:fine.n] = self.adg
        self.version = fine.version
        self._fine_inverses()

    def _fine_inverses(self) -> None:
        """The fine level's smoother blocks from its packed diagonal: the inverses of ``D``, and of
        ``S D S + (I - S)`` at the constrained vertices."""
        from ..kernels import pcg as _fused
        c, Sc = self.clist, self.Sc
        _fused.inv3(self.adg.reshape(-1), self.dinv[:self.mg.fine.n].reshape(-1))
        if len(c):
            self.dinv[c] = inv3(Sc @ self.adg[c] @ Sc + (np.eye(3) - Sc))

    def _gal_chunks(self, l: int) -> tuple:
        """Level ``l``'s Galerkin entries in the chunks' order for threads (:func:`galerkin_sequence`), made on
        first use."""
        cache = self.__dict__.setdefault("_gal_chunk_cache", {})
        if l not in cache:
            gal = self._gal[l]
            cuI = self.uI[self.uoff[l + 1]:self.uoff[l + 2]]
            n_coarse = self.mg.levels[l].system.n
            if self.mg.smoothed:     # destinations and the two prolongation entries
                cache[l] = galerkin_sequence(gal[0], (gal[1], gal[3], gal[4]), gal[5], (gal[6], gal[8], gal[9]), cuI,
                                             n_coarse)
            else:                    # destinations and weights
                cache[l] = galerkin_sequence(gal[0], (gal[1], gal[2]), gal[3], (gal[4], gal[5]), cuI, n_coarse)
        return cache[l]

    def coarse_dense(self) -> np.ndarray:
        """The coarsest level's matrix as a dense array, from its packed blocks."""
        L = len(self.mg.levels)
        v0, v1, u0, u1 = self.voff[L], self.voff[L + 1], self.uoff[L], self.uoff[L + 1]
        m = int(v1 - v0)
        C = np.zeros((m, 3, m, 3))
        i = np.arange(m)
        C[i, :, i, :] = self.dg[v0:v1]
        I, J, U = self.uI[u0:u1], self.uJ[u0:u1], self.uv[u0:u1]
        C[I, :, J, :] = U
        C[J, :, I, :] = U.transpose(0, 2, 1)
        return C.reshape(3 * m, 3 * m).astype(float)

    def _coarse(self):
        """The coarsest level's solve for the kernels: (upper Cholesky factor, True) or (dense inverse, False)."""
        ch = self.mg._chol
        if isinstance(ch, tuple) and len(ch) == 2 and isinstance(ch[1], (bool, np.bool_)):
            c, lower = ch
            return (np.ascontiguousarray(c.T) if lower else c), True
        m = 3 * int(self.voff[-1] - self.voff[-2])
        return np.ascontiguousarray(self.mg.coarse_solve(np.eye(m))), False

    def _hier(self) -> PackedHierarchy:
        C, upper = self._coarse()
        lpar = self._threaded_levels() if threads() > 1 else None
        if lpar is not None and lpar.any():
            set_numba_threads()
        else:        # no level on threads: None, so that the kernels compile their serial passes only (kernels.pcg._on)
            lpar = None
        return PackedHierarchy(self.dg, self.uI, self.uJ, self.uv, self.vu6, self.use6, self.voff, self.uoff,
                               self.clist, self.Sc, self.ws, self.dinv, self.pptr, self.pidx, self.pval, self.poff,
                               self.pnnz, self.tptr, self.tidx, self.tval, self.toff, C, upper, self.mg.level_omega,
                               lpar, self.lpv, self.lpb, self.pbb)

    def apply(self, r: np.ndarray) -> np.ndarray:
        from ..kernels import pcg as _fused

        r = np.ascontiguousarray(r, dtype=float)
        out = np.empty_like(r)
        if self.mg.cycle == "K":
            if self._kscratch is None:           # the K-steps' kept iterates and coefficients, made once
                L = len(self.voff)
                self._kscratch = (np.zeros_like(self.wb), np.zeros_like(self.wb), np.zeros(L, dtype=np.int64),
                                  np.zeros(2 * L))
            kc, kv, kstage, kcoef = self._kscratch
            _fused.kcycle(r, out, *self._hier(), self.wb, self.wx, self.wr, kc, kv, kstage, kcoef, K_THRESHOLD)
        else:
            _fused.vcycle(r, out, *self._hier(), self.wb, self.wx, self.wr)
        return out

    def pcg(self, A, b, z, filt, tol=1e-3, max_iterations=1000, guess=None, mass=None, rule="estimate",
            min_delay=4, delay_fraction=0.25):
        from ..kernels import pcg as _fused

        fine = self.mg.fine
        if A is not fine and A is not fine._csr:        # (fine.csr would copy the blocks in: not read here)
            raise BackendMismatch("fused_pcg: A is not the fine system's own matrix (the compiled CG multiplies "
                                  "by the blocks packed at setup)")
        if fine.version != self.version:
            raise BackendMismatch("fused_pcg: the system was assembled again after the preconditioner's setup "
                                  "(call setup after assembly)")
        if filt is not self.filt:
            raise BackendMismatch("fused_pcg: the filter is not the one of the last setup (call setup with it)")
        f = lambda a: np.ascontiguousarray(a, dtype=float).reshape(-1)  # noqa: E731
        h = self._hier()
        dv, it, res, conv, err = _fused.pcg(
            self.adg, self.auI, self.auJ, self.auv, self.au6, self.use6, h.dg, h.uI, h.uJ, h.uv, h.u6, h.voff, h.uoff,
            h.clist, h.Sc, h.dinv, h.pptr, h.pidx, h.pval, h.poff, h.pnnz, h.tptr, h.tidx, h.tval, h.toff,
            h.C, h.upper, h.omegas, h.lpar, h.lpv, h.lpb, h.pbb,
            f(b), f(z), f(guess) if guess is not None else np.zeros(0), guess is not None,
            f(mass) if mass is not None else np.zeros(0), mass is not None, float(tol), int(max_iterations),
            rule == "bound", int(min_delay), float(delay_fraction), self.sum_chunks,
            K_THRESHOLD if self.mg.cycle == "K" else None)     # None: the K-cycle is not compiled
        return dv, SolveResult(int(it), float(res), bool(conv), float(err))


def for_model(model, accelerator: str | None = None, smoothed: bool = False) -> Multigrid:
    """The multigrid preconditioner suited to a model: geometric for grids, smoothed aggregation for meshes;
    with ``smoothed`` its prolongations are smoothed every step (``"multigrid_smoothed"``)."""
    geo = model.geometry
    name = "multigrid_smoothed" if smoothed else "multigrid"
    if geo.grid_shape is not None:
        return Multigrid(model.system, grid_prolongations(*geo.grid_shape), name=name,
                         accelerator=accelerator, smoothed=smoothed, masses=model.masses)
    edges = geo.springs.get("structural")
    if edges is None or not len(edges):
        f = model.faces
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return Multigrid(model.system, aggregation_prolongations(model.n, edges), name=name,
                     accelerator=accelerator, smoothed=smoothed, masses=model.masses)
