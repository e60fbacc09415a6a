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
* Stopping rule: the estimated relative Euclidean error of the current ``dv``
  (see :func:`filtered_pcg`), so that ``tolerance`` means an accuracy of the
  answer, not of the residual. The reported residual is the plain 2-norm
  relative residual ``|S (b - A dv)| / |S (b - A z)|``.

The solver knows nothing about cloth: it takes a matrix (anything with ``@``),
a preconditioner with ``apply(r)`` and a :class:`Filter`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels import estimate
from .blocks import block_diagonal_operator, inv3

#: Factor on the extrapolated error of the current iterate (defined with the estimate itself, in
#: :mod:`implicit_cloth.kernels.estimate`).
ESTIMATE_SAFETY = estimate.ESTIMATE_SAFETY


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
    error : float
        The relative error of ``dv`` the stopping rule saw last (estimate or bound).
    """

    iterations: int
    residual: float
    converged: bool
    error: float = 0.0


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
    #: CG with block Jacobi stagnates for long stretches: stop on the guaranteed bound
    stopping_rule = "bound"

    def __init__(self, n: int) -> None:
        self.n = n
        self._P = block_diagonal_operator(n)

    def setup(self, system, filt: Filter) -> None:
        """Invert the filtered diagonal blocks of the assembled ``system`` (a SystemMatrix)."""
        B = system.diagonal_blocks()
        if not filt.trivial:
            S = filt.matrices()
            B = S @ B @ S + (np.eye(3)[None] - S)
        self._P.data[:] = inv3(B).reshape(-1)

    def apply(self, r: np.ndarray) -> np.ndarray:
        return self._P @ r


def filtered_pcg(A, b: np.ndarray, z: np.ndarray, filt: Filter, precond, tol: float = 1e-3,
                 max_iterations: int = 1000, guess: np.ndarray | None = None, mass: np.ndarray | None = None,
                 rule: str = "estimate", min_delay: int = 4,
                 delay_fraction: float = 0.25, compiled: bool | None = None) -> tuple[np.ndarray, SolveResult]:
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
        Relative error tolerance: iterate until the estimated ``|dv - dv*| / |dv|``
        (Euclidean norm, ``dv*`` the exact solution) is at most ``tol``.
    max_iterations : int
        Iteration cap; reaching it is reported as ``converged=False``.
    guess : (3N,) array, optional
        Initial guess of the free part (warm start); its constrained part is ignored.
    mass : (3N,) array, optional
        Lumped masses per coordinate, for the guaranteed bound (needs ``A >= M``).
    compiled : bool, optional
        Run the whole iteration compiled (``precond.fused_pcg``, the numba back-end, which takes
        only the system the preconditioner was set up on, else a ``BackendMismatch``) or the numpy
        loop with ``precond.apply`` (``False``: e.g. to solve another matrix with a compiled
        V-cycle). Default: the preconditioner's back-end decides (``precond.compiled``).
    rule : {"estimate", "bound"}
        ``"estimate"``: stop when the error estimate (or the bound) is below
        ``tol``; ``"bound"``: only when the guaranteed bound is (for weak
        preconditioners whose CG stagnates, which fools any estimate).
    min_delay, delay_fraction : int, float
        The error estimate at iteration k uses the last ``d = max(min_delay,
        delay_fraction * k)`` iterations (see below); ``min_delay >= 2``.

    Returns
    -------
    dv : (3N,) array
    result : SolveResult

    Notes
    -----
    Stopping rule. CG's error is estimated from quantities it already has
    (Hestenes & Stiefel 1952; Strakos & Tichy 2005), and the rule stops when the
    estimated error of the *current* iterate is at most ``tol``. With
    ``ad_j = alpha_j delta_j`` (``delta_j = r_j^T P^-1 r_j``) the decrease of the
    squared A-norm error in iteration j, ``|e_j|_A^2 = sum_{i>=j} ad_i``, and
    ``pw_j = |p_j|^2 / (p_j^T A p_j)``, the Euclidean error obeys
    ``|e_j|^2 - |e_{j+1}|^2 = pw_j (|e_j|_A^2 + |e_{j+1}|_A^2)``. The sums over
    iterations not yet made are extrapolated from the last ``d`` iterations
    (:func:`current_error_estimate`): a convergence rate ``q`` per iteration is
    read from the window (``ad_{k-1} / ad_{k-d}`` over ``d - 1`` iterations or
    ``ad_{k-1} / ad_{k-1-h}`` over its last ``h = d // 2``, whichever is slower);
    the A-norm tail is then ``T = |e_k|_A^2 = (sum of the last h ad) q^h / (1 - q^h)``
    and ``|e_k|^2 = T max(pw over the last h) (1 + q) / (1 - q)``, both exact for
    a steady rate and steady ``pw``. Real CG is not steady (its rate slows as the
    error concentrates in soft modes, ``pw`` grows with it), and the pure
    extrapolation under-reads: on the hanging stiff cloths (k = 1e3, 1e4 N/m;
    32²-128²) and the drape on a sphere of ``benchmarks/studies/stopping_rule.py``, over
    the iterates within 2 % of the solution, by more than 1.5x on 1 % of them and
    by 2.3x at worst (3x on the 24² test systems, early in a solve). So the
    estimate is multiplied by ``ESTIMATE_SAFETY = 2``, the smallest of 1.5, 1.75
    and 2 that kept every measured stop (156 systems, tolerances 1e-2, 1e-3 and
    1e-4: 468 stops) at or below ``tol`` (1.5 and 1.75 let 4 and 1 of them exceed
    it, by up to 1.5x and 1.06x). Measured there, true error / tol at the stop: median 0.34-0.40,
    max 0.69-0.97, at 1.11-1.19x the iterations of an oracle stopping at the
    first iterate within ``tol``; the previous rule (the estimated error of the
    iterate ``d`` back): median 0.04-0.24, 1.30-1.33x. When the window shows no
    convergence (``q >= 1``: a plateau, or a slowdown in its last half) the
    extrapolation is not trusted and the rule falls back to that delayed
    estimate, which can still under-read during a long stagnation of a weak
    preconditioner at a loose tolerance: block Jacobi plateaus for 50-200
    iterations at 5-9 % error on a stiff cloth, so it uses ``rule="bound"``.
    A residual tolerance is not an accuracy: the true error of Delta v was
    10-60x the relative residual on stiff cloths.

    Guaranteed bound. When ``A >= M`` (true here: every effect adds a positive
    semi-definite ``-c_v dF/dv - c_x dF/dx``, compressed springs' transverse
    terms being clamped), ``|e|_M <= |S r|_{M^-1}``, so
    ``|S r|_{M^-1} / |dv|_M <= tol`` guarantees a relative error below ``tol``
    in the mass-weighted norm (the Euclidean one for equal masses). It is
    pessimistic when the residual is made of stiff modes (by 10-1000x after
    multigrid), tight when it is made of soft ones (after block Jacobi).
    """
    if min_delay < 2:
        raise ValueError(f"min_delay: must be an integer >= 2, got {min_delay!r}")
    if compiled is None:
        compiled = bool(getattr(precond, "compiled", False))
    if compiled:                                     # the same iteration compiled (the numba back-end)
        return precond.fused_pcg(A, b, z, filt, tol=tol, max_iterations=max_iterations, guess=guess, mass=mass,
                                 rule=rule, min_delay=min_delay, delay_fraction=delay_fraction)
    zc = z - filt.apply(z.copy())                    # (I - S) z: the constrained part
    dv = zc.copy()
    r = filt.apply(b - A @ dv)
    norm0 = float(np.linalg.norm(r))
    if guess is not None:
        dv += filt.apply(guess.copy())
        r = filt.apply(b - A @ dv)
    if norm0 == 0.0:
        return dv, SolveResult(0, 0.0, True)
    s = filt.apply(precond.apply(r))
    flexible = bool(getattr(precond, "flexible", False))
    p = s.copy()
    delta = float(r @ s)
    delta0 = delta
    ad = np.zeros(max_iterations)                     # alpha_j delta_j
    pw = np.zeros(max_iterations)                     # |p_j|^2 / p_j^T A p_j
    inv_mass = None if mass is None else 1.0 / mass
    converged = delta <= 0.0 and not np.any(r)       # an exact guess; else delta <= 0 is a breakdown
    error = 0.0 if converged else np.inf
    it = 0
    while not converged and delta > 0.0 and it < max_iterations:
        q = filt.apply(A @ p)
        pq = float(p @ q)
        if pq <= 0.0:  # breakdown: A not SPD on the free subspace
            break
        alpha = delta / pq
        dv += alpha * p
        r -= alpha * q
        ad[it] = alpha * delta
        pw[it] = float(p @ p) / pq
        it += 1
        s = filt.apply(precond.apply(r))
        delta_new = float(r @ s)
        if delta_new < -1e-30 * delta0:               # breakdown: the preconditioner is not positive definite
            break
        if delta_new <= 1e-30 * delta0:
            converged, error = True, 0.0              # exact to round-off
        else:
            if inv_mass is not None:
                error = np.sqrt(float(r @ (inv_mass * r)) / max(float(dv @ (mass * dv)), 1e-300))
                converged = error <= tol
            d = max(min_delay, int(delay_fraction * it))
            if not converged and rule == "estimate" and it >= d:
                error = current_error_estimate(ad, pw, it, float(dv @ dv), d)
                converged = error <= tol
        if not converged:
            # a preconditioner that varies with its argument (the K-cycle): Polak-Ribiere's beta, with
            # r_new - r = -alpha q equal to -s_new . q / p . q (Fletcher-Reeves' for a fixed one)
            p *= -float(s @ q) / pq if flexible else delta_new / delta
            p += s
        delta = delta_new
    res = float(np.linalg.norm(filt.apply(b - A @ dv))) / norm0
    return dv, SolveResult(it, res, converged, float(error))



def current_error_estimate(ad: np.ndarray, pw: np.ndarray, it: int, dd: float, d: int) -> float:
    """Estimated relative Euclidean error ``|dv_k - dv*| / |dv_k|`` of the current CG iterate (k = ``it``).

    Parameters
    ----------
    ad : (>= it,) array
        ``alpha_j delta_j`` of iterations j = 0 .. it-1: the decrease of the squared
        A-norm error in iteration j (``delta_j = r_j^T P^-1 r_j``).
    pw : (>= it,) array
        ``|p_j|^2 / (p_j^T A p_j)`` of the same iterations.
    it : int
        Iterations done, ``it >= d``.
    dd : float
        ``|dv_k|^2``.
    d : int
        Window, ``d >= 2``: the last ``d`` iterations are used (the rate also from the last ``d // 2``).

    Returns
    -------
    float
        The estimate (see Notes of :func:`filtered_pcg`); when the window shows no
        convergence (rate ``q >= 1``, stagnation) the conservative delayed estimate,
        the error of the iterate ``d`` iterations back.
    """
    return float(estimate.error_estimate(ad, pw, it, dd, d))
