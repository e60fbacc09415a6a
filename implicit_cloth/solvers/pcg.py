"""Modified (filtered) preconditioned conjugate gradient, Baraff & Witkin 1998 §5.3.

Solves ``A dv = b`` for symmetric positive definite ``A`` subject to per-vertex
constraints on ``dv``: vertex i's velocity change is prescribed (``z_i``) in the
directions its filter ``S_i`` removes, and free in the others.

* ``S_i = I`` for a free vertex, ``I - n n^T`` for one constrained direction
  ``n``, ``I - n n^T - m m^T`` for two, ``0`` for a pinned vertex.
* The solution satisfies ``(I - S) dv = (I - S) z`` exactly and
  ``S (A dv - b) = 0`` (the filtered residual vanishes), which is the
  constrained system ``S A S y = S (b - A z)``, ``dv = z + S y`` of Ascher &
  Boxerman (2003): the iterate starts at ``z`` (plus a filtered guess), and the
  residual and every search direction are filtered.
* Stopping rule: ``r^T P^-1 r <= tol^2 r0^T P^-1 r0`` with ``r0 = S (b - A z)``,
  the residual at a zero free part; i.e. a relative residual in the norm of the
  preconditioner. The reported residual is the plain 2-norm relative residual
  ``|S (b - A dv)| / |S (b - A z)|``.

The solver knows nothing about cloth: it takes a matrix (anything with ``@``),
a preconditioner with ``apply(r)`` and a :class:`Filter`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass
class SolveResult:
    """Outcome of one linear solve.

    Attributes
    ----------
    iterations : int
        CG iterations taken.
    residual : float
        Final relative residual ``|S (b - A dv)|_2 / |S (b - A z)|_2`` (0 when the
        right-hand side vanishes).
    converged : bool
        Whether the stopping rule was met within ``max_iterations``.
    """

    iterations: int
    residual: float
    converged: bool


class Filter:
    """Baraff-Witkin constraint filter ``S``, applied per vertex in place.

    Parameters
    ----------
    n : int
        Number of vertices.
    fixed : (P,) int array
        Vertices constrained in all three directions (``S_i = 0``).
    partial : (Q,) int array, optional
        Vertices constrained in one or two directions.
    partial_S : (Q, 3, 3) array, optional
        Their filters, e.g. ``I - n n^T``.
    """

    def __init__(self, n: int, fixed: np.ndarray, partial: np.ndarray | None = None,
                 partial_S: np.ndarray | None = None) -> None:
        self.n = n
        self.fixed = np.asarray(fixed, dtype=np.int64)
        self.partial = np.zeros(0, dtype=np.int64) if partial is None else np.asarray(partial, dtype=np.int64)
        self.partial_S = np.zeros((0, 3, 3)) if partial_S is None else np.asarray(partial_S, dtype=float)

    @property
    def trivial(self) -> bool:
        return len(self.fixed) == 0 and len(self.partial) == 0

    def apply(self, vec: np.ndarray) -> np.ndarray:
        """Filter a flat (3N,) or (N, 3) vector in place and return it."""
        v3 = vec.reshape(-1, 3)
        if len(self.fixed):
            v3[self.fixed] = 0.0
        if len(self.partial):
            v3[self.partial] = np.einsum("nij,nj->ni", self.partial_S, v3[self.partial])
        return vec

    def matrices(self) -> np.ndarray:
        """The per-vertex 3x3 filters, (N, 3, 3)."""
        S = np.broadcast_to(np.eye(3), (self.n, 3, 3)).copy()
        S[self.fixed] = 0.0
        if len(self.partial):
            S[self.partial] = self.partial_S
        return S


class BlockJacobi:
    """3x3 block-Jacobi preconditioner of the filtered system.

    Inverts ``S_i A_ii S_i + (I - S_i)`` per vertex, which is SPD whenever
    ``A_ii`` is, and keeps constrained components untouched. Applied as one
    sparse mat-vec with a block-diagonal matrix whose pattern is built once.
    """

    name = "block_jacobi"

    def __init__(self, n: int) -> None:
        self.n = n
        cols = (3 * np.repeat(np.arange(n), 9) + np.tile(np.arange(3), 3 * n))
        self._P = sp.csr_array((np.zeros(9 * n), cols, np.arange(0, 9 * n + 1, 3)), shape=(3 * n, 3 * n))

    def setup(self, diag_blocks: np.ndarray, filt: Filter) -> None:
        B = diag_blocks
        if not filt.trivial:
            S = filt.matrices()
            B = S @ B @ S + (np.eye(3)[None] - S)
        self._P.data[:] = np.linalg.inv(B).reshape(-1)

    def apply(self, r: np.ndarray) -> np.ndarray:
        return self._P @ r


def filtered_pcg(A, b: np.ndarray, z: np.ndarray, filt: Filter, precond, tol: float = 1e-3,
                 max_iterations: int = 1000, guess: np.ndarray | None = None) -> tuple[np.ndarray, SolveResult]:
    """Solve ``A dv = b`` with the constraints ``(I - S) dv = (I - S) z`` (BW98 §5.3).

    Parameters
    ----------
    A : sparse matrix or LinearOperator, (3N, 3N)
        Symmetric positive definite system matrix.
    b : (3N,) array
        Right-hand side.
    z : (3N,) array
        Prescribed velocity changes; only its constrained components matter.
    filt : Filter
        The constraint filter S.
    precond : object with ``apply(r) -> (3N,) array``
        Preconditioner (already set up for ``A`` and ``filt``).
    tol : float
        Relative residual tolerance (preconditioned norm, see module docstring).
    max_iterations : int
        Iteration cap; reaching it is reported as ``converged=False``.
    guess : (3N,) array, optional
        Initial guess of the free part (warm start); its constrained part is ignored.

    Returns
    -------
    dv : (3N,) array
    result : SolveResult
    """
    zc = z - filt.apply(z.copy())                    # (I - S) z: the constrained part
    dv = zc.copy()
    r0 = filt.apply(b - A @ dv)
    if guess is not None:
        dv += filt.apply(guess.copy())
        r = filt.apply(b - A @ dv)
    else:
        r = r0.copy()
    s = precond.apply(r0)
    delta0 = float(r0 @ filt.apply(s))
    norm0 = float(np.linalg.norm(r0))
    if norm0 == 0.0 or delta0 <= 0.0:
        return dv, SolveResult(0, 0.0, True)
    c = filt.apply(precond.apply(r))
    delta = float(r @ c)
    target = tol * tol * delta0
    it = 0
    while delta > target and it < max_iterations:
        q = filt.apply(A @ c)
        cq = float(c @ q)
        if cq <= 0.0:  # breakdown: A not SPD on the free subspace
            break
        alpha = delta / cq
        dv += alpha * c
        r -= alpha * q
        s = filt.apply(precond.apply(r))
        delta_old, delta = delta, float(r @ s)
        c *= delta / delta_old
        c += s
        it += 1
    res = float(np.linalg.norm(filt.apply(b - A @ dv))) / norm0
    return dv, SolveResult(it, res, delta <= target)
