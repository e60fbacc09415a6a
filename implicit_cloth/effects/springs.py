"""Hookean springs with damping along the spring (structural, shear and bend kinds).

Notation (Baraff & Witkin 1998, §4 and §5.1): spring s joins vertices i and j,
``d = x_j - x_i``, ``l = |d|``, ``u = d / l``, rest length ``L0``, spring
constant ``k`` (N/m), damping ``kd`` (N*s/m).

Force on i (the force on j is its negative)::

    f_i = k (l - L0) u + kd ((v_j - v_i) . u) u

A :class:`~implicit_cloth.forces.Force` with both parts: the elastic energy
``U = sum_s k (l - L0)^2 / 2`` and Rayleigh's dissipation ``D = sum_s kd ((v_j - v_i) . u)^2 / 2``.

Jacobian blocks (``df_i/dx_j = K``, ``df_i/dx_i = -K``, likewise for v)::

    K = k [u u^T + c (I - u u^T)],   c = 1 - L0/l       (exact)
    D = kd u u^T

Choices that keep the implicit system symmetric positive definite:

* The transverse term ``c (I - u u^T)`` is kept for stretched springs and
  clamped at ``c >= 0`` for compressed ones (for ``l < L0`` it is negative and
  makes ``-dF/dx`` indefinite, the buckling instability of BW98 §5.1 / Choi &
  Ko 2002). Use ``exact=True`` in :meth:`Springs.jacobian` for the unclamped
  derivative.
* The derivative of the damping force with respect to x is dropped (BW98 §4.5:
  it is not symmetric and small).
* Zero-length springs (coincident vertices, ``l < 1e-9 * mean rest length``)
  have no direction: ``u = 0``, so their force is ``k d`` (exact when
  ``L0 = 0``) and their Jacobian is ``k I`` if ``L0 = 0`` and 0 otherwise. No
  division by zero, no NaN.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from ..assembly import accumulate_product
from ..backend import Backend, get_backend


class Springs:
    """All springs of the declared kinds, evaluated as one vectorised set.

    Parameters
    ----------
    n : int
        Number of vertices.
    pairs : (S, 2) int array
        Vertex indices (i, j) of each spring.
    stiffness, damping, rest_length : (S,) arrays
        k in N/m, kd in N*s/m, L0 in m.
    kinds : dict of str -> slice
        Which rows belong to which kind (for per-kind reports).
    """

    name = "springs"
    conservative = True
    elastic = True

    def __init__(self, n: int, pairs: np.ndarray, stiffness: np.ndarray, damping: np.ndarray,
                 rest_length: np.ndarray, kinds: dict[str, slice]) -> None:
        self.n = int(n)
        self.i = np.ascontiguousarray(pairs[:, 0], dtype=np.int64)
        self.j = np.ascontiguousarray(pairs[:, 1], dtype=np.int64)
        self.k = np.asarray(stiffness, dtype=float)
        self.kd = np.asarray(damping, dtype=float)
        self.L0 = np.asarray(rest_length, dtype=float)
        self.kinds = dict(kinds)
        #: whether the springs damp (a dissipation potential beside the elastic energy)
        self.dissipative = bool(np.any(self.kd))
        s = len(self.i)
        positive = self.L0[self.L0 > 0]
        self._tiny = 1e-9 * (positive.mean() if positive.size else 1.0)
        # incidence: F = B @ f_s puts +f_s on i and -f_s on j
        rows = np.concatenate([self.i, self.j])
        cols = np.concatenate([np.arange(s), np.arange(s)])
        vals = np.concatenate([np.ones(s), -np.ones(s)])
        self._B = sp.csr_array((vals, (rows, cols)), shape=(self.n, s))
        self._G: sp.csr_array | None = None
        #: the back-end: numpy until :meth:`bind`, then the system matrix's (one matrix, one path)
        self.backend: Backend = get_backend("numpy")

    # ------------------------------------------------------------------ geometry
    def _frame(self, x: np.ndarray):
        d = x[self.j] - x[self.i]
        l = np.sqrt(np.einsum("ij,ij->i", d, d))
        ok = l > self._tiny
        inv = np.divide(1.0, l, out=np.zeros_like(l), where=ok)
        u = d * inv[:, None]
        return d, l, u, ok, inv

    @property
    def accelerator(self) -> str:
        """The back-end's name: "numba" (one compiled pass over the springs) or "numpy" (reference)."""
        return self.backend.name

    def lengths(self, x: np.ndarray) -> np.ndarray:
        """Current length of each spring, m (compiled on the numba path: the adaptive step's strain and
        energy checks measure every state)."""
        return self.backend.spring_lengths(x, self.i, self.j)

    def strain(self, x: np.ndarray) -> np.ndarray:
        """Engineering strain ``(l - L0) / L0`` of each spring (0 where ``L0 = 0``)."""
        l = self.lengths(x)
        return np.divide(l - self.L0, self.L0, out=np.zeros_like(l), where=self.L0 > 0)

    # ------------------------------------------------------------------ effect API
    def spring_forces(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Force of each spring on its first vertex i, (S, 3) N."""
        d, l, u, ok, inv = self._frame(x)
        return self._forces_from_frame(d, u, v)

    def _forces_from_frame(self, d: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        # k (l - L0) u, written k (d - L0 u) so that it stays k d when u = 0
        f = self.k[:, None] * (d - self.L0[:, None] * u)
        if np.any(self.kd):
            dv = v[self.j] - v[self.i]
            f += (self.kd * np.einsum("ij,ij->i", dv, u))[:, None] * u
        return f

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        if self.backend.compiled and out.dtype == np.float64 and out.flags.c_contiguous:
            # one compiled pass with numpy's arithmetic: the same numbers (the line searches and energy checks
            # evaluate forces many times a step). Always the kernel compiled as a parallel region, on one thread
            # below the threaded size: numba's parallel lowering vectorises its loop over the springs (square
            # roots and divisions four at a time), which the serial kernel's does not: 0.19 -> 0.06 / 0.76 ->
            # 0.25 / 3.2 -> 1.0 ms at 32² / 64² / 128² on one thread, the same numbers
            from ..backend import one_numba_thread
            from ..kernels.springs import pspring_forces

            c = np.ascontiguousarray
            B = self._B
            args = (c(x, dtype=float), c(v, dtype=float), *self._plain, float(self._tiny), self._damped,
                    B.indptr, B.indices, B.data, self._F, out)
            if self.backend.threaded(self.n):
                pspring_forces(*args)
            else:
                with one_numba_thread():
                    pspring_forces(*args)
            return
        out += self._B @ self.spring_forces(x, v)

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0   # internal: its work is the change of its potential

    def energy(self, x: np.ndarray) -> float:
        """Elastic energy ``sum_s k (l - L0)^2 / 2``, J."""
        return 0.5 * float(np.dot(self.k, (self.lengths(x) - self.L0) ** 2))

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        """Add ``dU/dx``, the negative of the elastic force (the force at rest velocities), N."""
        f = np.zeros_like(out)
        self.force(x, np.zeros_like(x), t, f)
        out -= f

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """Rayleigh's ``sum_s kd ((v_j - v_i) . u)^2 / 2`` at the geometry ``x``, W (its ``-dD/dv`` is the
        damping force)."""
        if not self.dissipative:
            return 0.0
        if self.backend.compiled:   # one compiled pass (every point of a step's line search evaluates it)
            from ..kernels.springs import spring_dissipation

            c = np.ascontiguousarray
            i, j, _, kd, _ = self._plain
            return float(spring_dissipation(c(x, dtype=float), c(v, dtype=float), i, j, kd, float(self._tiny)))
        d, l, u, ok, inv = self._frame(x)
        s = np.einsum("ij,ij->i", v[self.j] - v[self.i], u)
        return 0.5 * float(np.dot(self.kd, s * s))

    def pairs(self) -> np.ndarray:
        return np.stack([self.i, self.j], axis=1)

    def bind(self, system: Any) -> None:
        """Precompute the index maps into ``system`` and choose the implementation (numba or numpy).

        The springs follow the system's back-end (``system.backend``, the model's), so that one
        matrix is assembled by one path: numba runs one compiled pass over the springs
        (:mod:`implicit_cloth.kernels.springs`), numpy is the reference.
        """
        self.backend = system.backend
        if self.backend.compiled:
            from ..kernels import springs as _kernels  # noqa: F401  (imports numba; compiles or loads from cache on first use)

            # springs visited in (i, j) order: each vertex's blocks are written while they are in cache
            # (about 2x faster at 256^2 than the kinds' order; only the order of the sums changes)
            o = np.lexsort((self.j, self.i))
            c = np.ascontiguousarray
            i, j = c(self.i[o]), c(self.j[o])
            self._sorted = (i, j, c(self.k[o], dtype=float), c(self.kd[o], dtype=float), c(self.L0[o], dtype=float))
            self._bidx = c(np.stack([system.block_index(i, i), system.block_index(j, j),
                                     system.block_index(i, j), system.block_index(j, i)], axis=1), dtype=np.int64)
            self._damped = bool(np.any(self.kd))
            #: the threaded pass's chunks (:meth:`_threaded_chunks`), made on its first use
            self._chunks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
            #: the springs in their own order for the compiled force pass (:meth:`force`), and its scratch
            self._plain = (c(self.i), c(self.j), c(self.k, dtype=float), c(self.kd, dtype=float),
                           c(self.L0, dtype=float))
            self._F = np.empty((len(self.i), 3))
            self._G = None
        else:
            self._G = system.pair_scatter(self.pairs())
            self._X = np.empty((len(self.i), 3, 3))   # per-spring blocks, reused every step

    def _transverse(self, ok: np.ndarray, inv: np.ndarray, exact: bool = False) -> np.ndarray:
        """``a`` of ``K = k [a I + (1 - a) u u^T]``: ``1 - L0/l``, clamped at 0 unless ``exact``."""
        a = np.where(ok, 1.0 - self.L0 * inv, np.where(self.L0 > 0, 0.0, 1.0))
        if not exact:
            np.maximum(a, 0.0, out=a)
        return a

    def _threaded_chunks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The chunks of the threaded pass (:func:`implicit_cloth.kernels.springs.springs_linearize_chunks`)
        when the back-end runs this cloth's passes on threads (:meth:`Backend.threaded
        <implicit_cloth.backend.Backend.threaded>`); else None (the serial pass: the same numbers)."""
        if not self.backend.threaded(self.n):
            return None
        if self._chunks is None:
            from ..backend import THREAD_CHUNKS
            from ..kernels.springs import chunk_springs

            self._chunks = chunk_springs(self.n, self._sorted[0], self._sorted[1], THREAD_CHUNKS)
        return self._chunks

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        """Add ``-(c_v dF/dv + c_x dF/dx)`` to the system blocks, ``(dF/dx) w`` to ``kw`` and F to ``f``.

        Per spring the block is ``C = c_x K + c_v D = alpha I + beta u u^T`` with
        ``alpha = c_x k a`` and ``beta = c_x k (1 - a) + c_v kd``; it enters the
        (i,i) and (j,j) blocks with + and the (i,j), (j,i) blocks with - (one
        sparse product giving contiguous (n_blocks, 9) values, added in one pass).
        On the numba path all of it is one compiled pass over the springs
        (:func:`implicit_cloth.kernels.springs.springs_linearize`), on threads where the solver's passes are
        (the same numbers).
        """
        if self.backend.compiled:
            from ..kernels.springs import springs_linearize

            with_w = kw is not None and w is not None
            c = np.ascontiguousarray   # the kernel is compiled for C-contiguous float64 arrays (no copy if so)
            x, v = c(x, dtype=float), c(v, dtype=float)
            w = c(w, dtype=float) if with_w else x
            args = (x, v, w, with_w, self._damped, *self._sorted, float(self._tiny), float(c_x), float(c_v),
                    self._bidx)
            chunks = self._threaded_chunks()
            if chunks is None:
                springs_linearize(*args, system.blocks, kw if with_w else f, f)
            else:
                from ..kernels.springs import springs_linearize_chunks

                springs_linearize_chunks(*args, *chunks, system.blocks, kw if with_w else f, f)
            return
        d, l, u, ok, inv = self._frame(x)
        a = self._transverse(ok, inv)
        fs = self._forces_from_frame(d, u, v)       # the force, from the same frame
        alpha = c_x * self.k * a
        beta = c_x * self.k * (1.0 - a) + c_v * self.kd
        X = self._X
        np.multiply((beta[:, None] * u)[:, :, None], u[:, None, :], out=X)
        X[:, 0, 0] += alpha
        X[:, 1, 1] += alpha
        X[:, 2, 2] += alpha
        accumulate_product(self._G, X.reshape(-1, 9), system.blocks.reshape(-1, 9))
        if kw is not None and w is not None:
            dw = w[self.j] - w[self.i]
            kdw = (self.k * a)[:, None] * dw + (self.k * (1.0 - a) * np.einsum("ij,ij->i", u, dw))[:, None] * u
            kw += self._B @ kdw
        f += self._B @ fs

    def jacobian(self, x: np.ndarray, exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Per-spring blocks ``K = df_i/dx_j`` and ``D = df_i/dv_j``, each (S, 3, 3).

        With ``exact=False`` (what the solver uses) the transverse term of
        compressed springs is clamped; ``exact=True`` gives the true derivative.
        """
        d, l, u, ok, inv = self._frame(x)
        a = self._transverse(ok, inv, exact)
        uu = u[:, :, None] * u[:, None, :]
        eye = np.eye(3)[None]
        K = self.k[:, None, None] * (a[:, None, None] * eye + (1.0 - a)[:, None, None] * uu)
        D = self.kd[:, None, None] * uu
        return K, D


def build(model: Any, params: dict[str, dict[str, float]]) -> Springs:
    """Springs of the declared kinds with rest lengths taken from the initial positions."""
    pairs, k, kd = [], [], []
    kinds: dict[str, slice] = {}
    start = 0
    for kind in ("structural", "shear", "bend"):
        if kind not in params:
            continue
        p = model.geometry.springs.get(kind, np.zeros((0, 2), dtype=np.int64))
        pairs.append(p)
        # one constant per kind, or one per spring (several pieces of different materials)
        k.append(np.broadcast_to(np.asarray(params[kind]["stiffness"], dtype=float), (len(p),)))
        kd.append(np.broadcast_to(np.asarray(params[kind]["damping"], dtype=float), (len(p),)))
        kinds[kind] = slice(start, start + len(p))
        start += len(p)
    allp = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
    x0 = model.rest_positions
    L0 = np.linalg.norm(x0[allp[:, 1]] - x0[allp[:, 0]], axis=1)
    return Springs(model.n, allp, np.concatenate(k), np.concatenate(kd), L0, kinds)
