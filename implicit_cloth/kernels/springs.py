"""Compiled (numba) spring assembly: :meth:`Springs.linearize` in one pass over the springs.

The optional accelerator of :mod:`implicit_cloth.effects.springs` (numpy stays
the reference and the fallback; :func:`implicit_cloth.backend.resolve`
chooses at bind time). Same equations and the same arithmetic as the numpy
path, fused per spring ``s = (i, j)`` (notation of Baraff & Witkin 1998, §4):

* frame: ``d = x_j - x_i``, ``l = |d|``, ``u = d / l`` (``u = 0`` when
  ``l <= tiny``, the zero-length guard);
* clamped transverse coefficient ``a = max(1 - L0 / l, 0)`` (``a = 0`` for a
  zero-length spring of positive rest length, 1 for ``L0 = 0``);
* force on i ``f_s = k (d - L0 u) + kd ((v_j - v_i) . u) u`` (N), added to
  ``f_i`` and subtracted from ``f_j``;
* ``(dF/dx) w``: ``k a (w_j - w_i) + k (1 - a) (u . (w_j - w_i)) u`` added to
  ``kw_i``, subtracted from ``kw_j``;
* system block ``C = alpha I + beta u u^T`` with ``alpha = c_x k a`` and
  ``beta = c_x k (1 - a) + c_v kd``, added to blocks (i, i), (j, j) and
  subtracted from (i, j), (j, i) through block indices precomputed at bind time.
  ``C`` is written exactly symmetric (``C_ab = beta u_a u_b`` computed once for
  ``a <= b``); numpy's ``(beta u_a) u_b`` and ``(beta u_b) u_a`` may differ in the
  last bit, which is the only difference besides the order of the sums (the
  springs are visited sorted by vertex, for cache locality).

On threads (:func:`springs_linearize_chunks`, from the multigrid's threaded size up) each chunk of vertices
owns its rows and visits the springs that touch it in the serial order: the same numbers to the last bit
(a plain scatter on two threads would race on shared vertices). Compiled with ``cache=True``: the
compilation is paid once per installation. Importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import layer  # noqa: F401  (the threading layer chosen before any region runs: the springs' force is one at every size)


@njit(cache=True, inline="always")
def spring_vector(x, i, j):
    """``(d0, d1, d2, l)``: the spring vector ``d = x_j - x_i`` and its length ``|d|``."""
    d0 = x[j, 0] - x[i, 0]
    d1 = x[j, 1] - x[i, 1]
    d2 = x[j, 2] - x[i, 2]
    return d0, d1, d2, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True, inline="always")
def _add_sym(B, b, sign, c00, c01, c02, c11, c12, c22):
    """``B[9 b : 9 b + 9] += sign * C`` for the symmetric 3x3 ``C`` given by its upper triangle."""
    p = 9 * b
    B[p] += sign * c00
    B[p + 1] += sign * c01
    B[p + 2] += sign * c02
    B[p + 3] += sign * c01
    B[p + 4] += sign * c11
    B[p + 5] += sign * c12
    B[p + 6] += sign * c02
    B[p + 7] += sign * c12
    B[p + 8] += sign * c22


@njit(cache=True, inline="always")
def _spring_terms(x, v, w, with_w, damped, i, j, ks, kds, L, tiny, c_x, c_v):
    """One spring's numbers: its force on ``i`` ``(f0, f1, f2)``, ``(dF/dx) w`` on ``i`` ``(q0, q1, q2)`` (0 without
    ``with_w``) and the upper triangle of its system block ``C`` ``(c00, c01, c02, c11, c12, c22)``."""
    d0, d1, d2, l = spring_vector(x, i, j)
    if l > tiny:
        inv = 1.0 / l
        a = 1.0 - L * inv
    else:
        inv = 0.0
        a = 0.0 if L > 0.0 else 1.0
    if a < 0.0:
        a = 0.0
    u0 = d0 * inv
    u1 = d1 * inv
    u2 = d2 * inv
    # force on i: k (d - L0 u) + kd ((v_j - v_i) . u) u
    f0 = ks * (d0 - L * u0)
    f1 = ks * (d1 - L * u1)
    f2 = ks * (d2 - L * u2)
    if damped:
        g = kds * ((v[j, 0] - v[i, 0]) * u0 + (v[j, 1] - v[i, 1]) * u1 + (v[j, 2] - v[i, 2]) * u2)
        f0 += g * u0
        f1 += g * u1
        f2 += g * u2
    # (dF/dx) w
    q0 = 0.0
    q1 = 0.0
    q2 = 0.0
    if with_w:
        w0 = w[j, 0] - w[i, 0]
        w1 = w[j, 1] - w[i, 1]
        w2 = w[j, 2] - w[i, 2]
        ka = ks * a
        kb = ks * (1.0 - a) * (u0 * w0 + u1 * w1 + u2 * w2)
        q0 = ka * w0 + kb * u0
        q1 = ka * w1 + kb * u1
        q2 = ka * w2 + kb * u2
    # C = alpha I + beta u u^T (exactly symmetric)
    alpha = c_x * ks * a
    beta = c_x * ks * (1.0 - a) + c_v * kds
    b0 = beta * u0
    b1 = beta * u1
    return (f0, f1, f2, q0, q1, q2,
            b0 * u0 + alpha, b0 * u1, b0 * u2, b1 * u1 + alpha, b1 * u2, beta * u2 * u2 + alpha)


@njit(cache=True, inline="always")
def _add_end(B, f, kw, with_w, r, sign, diag, off, t):
    """Spring terms ``t`` (:func:`_spring_terms`) at its end ``r``: ``sign`` (+1 at i, -1 at j) times the force
    and ``(dF/dx) w`` into ``f[r]``, ``kw[r]``, ``C`` into the diagonal block ``diag``, ``-C`` into the block
    ``off`` of row ``r`` (the other end's column)."""
    f0, f1, f2, q0, q1, q2, c00, c01, c02, c11, c12, c22 = t
    if sign > 0.0:
        f[r, 0] += f0
        f[r, 1] += f1
        f[r, 2] += f2
        if with_w:
            kw[r, 0] += q0
            kw[r, 1] += q1
            kw[r, 2] += q2
    else:
        f[r, 0] -= f0
        f[r, 1] -= f1
        f[r, 2] -= f2
        if with_w:
            kw[r, 0] -= q0
            kw[r, 1] -= q1
            kw[r, 2] -= q2
    _add_sym(B, diag, 1.0, c00, c01, c02, c11, c12, c22)
    _add_sym(B, off, -1.0, c00, c01, c02, c11, c12, c22)


@njit(cache=True)
def springs_linearize(x, v, w, with_w, damped, si, sj, k, kd, L0, tiny, c_x, c_v, bidx, blocks, kw, f):
    """One pass over the springs: force into ``f``, ``(dF/dx) w`` into ``kw``, blocks into ``blocks``.

    Parameters
    ----------
    x, v, w : (N, 3) float arrays
        Positions (m), velocities (m/s), the vector multiplied by ``dF/dx``.
    with_w : bool
        Whether to compute ``kw`` (``w`` and ``kw`` are ignored otherwise).
    damped : bool
        Whether any spring has damping (the numpy path skips the term then).
    si, sj : (S,) int arrays
        The spring's vertices.
    k, kd, L0 : (S,) float arrays
        Stiffness N/m, damping N*s/m, rest length m.
    tiny : float
        Length below which a spring has no direction, m.
    c_x, c_v : float
        Coefficients of ``dF/dx`` (s^2) and ``dF/dv`` (s) in the system.
    bidx : (S, 4) int array
        Block positions of (i, i), (j, j), (i, j), (j, i) in ``blocks``.
    blocks : (n_blocks, 3, 3) float array
        System blocks, accumulated into.
    kw, f : (N, 3) float arrays
        Accumulated into.
    """
    # (Written out rather than through :func:`_spring_terms` and :func:`_add_end`, whose shared form gives the
    # same numbers but measured 4-25 % slower here on one thread, 2026-12-06; the threaded pass uses them.)
    B = blocks.reshape(-1)
    for s in range(si.shape[0]):
        i = si[s]
        j = sj[s]
        d0, d1, d2, l = spring_vector(x, i, j)
        ks = k[s]
        L = L0[s]
        if l > tiny:
            inv = 1.0 / l
            a = 1.0 - L * inv
        else:
            inv = 0.0
            a = 0.0 if L > 0.0 else 1.0
        if a < 0.0:
            a = 0.0
        u0 = d0 * inv
        u1 = d1 * inv
        u2 = d2 * inv
        # force on i: k (d - L0 u) + kd ((v_j - v_i) . u) u
        f0 = ks * (d0 - L * u0)
        f1 = ks * (d1 - L * u1)
        f2 = ks * (d2 - L * u2)
        if damped:
            g = kd[s] * ((v[j, 0] - v[i, 0]) * u0 + (v[j, 1] - v[i, 1]) * u1 + (v[j, 2] - v[i, 2]) * u2)
            f0 += g * u0
            f1 += g * u1
            f2 += g * u2
        f[i, 0] += f0
        f[i, 1] += f1
        f[i, 2] += f2
        f[j, 0] -= f0
        f[j, 1] -= f1
        f[j, 2] -= f2
        # (dF/dx) w
        if with_w:
            w0 = w[j, 0] - w[i, 0]
            w1 = w[j, 1] - w[i, 1]
            w2 = w[j, 2] - w[i, 2]
            ka = ks * a
            kb = ks * (1.0 - a) * (u0 * w0 + u1 * w1 + u2 * w2)
            q0 = ka * w0 + kb * u0
            q1 = ka * w1 + kb * u1
            q2 = ka * w2 + kb * u2
            kw[i, 0] += q0
            kw[i, 1] += q1
            kw[i, 2] += q2
            kw[j, 0] -= q0
            kw[j, 1] -= q1
            kw[j, 2] -= q2
        # C = alpha I + beta u u^T (exactly symmetric): + on (i, i), (j, j); - on (i, j), (j, i)
        alpha = c_x * ks * a
        beta = c_x * ks * (1.0 - a) + c_v * kd[s]
        b0 = beta * u0
        b1 = beta * u1
        c00 = b0 * u0 + alpha
        c01 = b0 * u1
        c02 = b0 * u2
        c11 = b1 * u1 + alpha
        c12 = b1 * u2
        c22 = beta * u2 * u2 + alpha
        _add_sym(B, bidx[s, 0], 1.0, c00, c01, c02, c11, c12, c22)
        _add_sym(B, bidx[s, 1], 1.0, c00, c01, c02, c11, c12, c22)
        _add_sym(B, bidx[s, 2], -1.0, c00, c01, c02, c11, c12, c22)
        _add_sym(B, bidx[s, 3], -1.0, c00, c01, c02, c11, c12, c22)


@njit(cache=True, parallel=True)
def springs_linearize_chunks(x, v, w, with_w, damped, si, sj, k, kd, L0, tiny, c_x, c_v, bidx, vlo, cptr, clist,
                             blocks, kw, f):
    """:func:`springs_linearize` on threads, with its numbers to the last bit.

    Chunk ``c`` owns the vertices ``vlo[c] <= r < vlo[c + 1]``: their rows of ``f``, ``kw`` and of the blocks
    (the diagonal block and the blocks ``(r, other end)``). It visits the springs with an end it owns
    (``clist[cptr[c]:cptr[c + 1]]``, ascending) and adds each spring's terms at those ends only, so every
    number is written by one chunk and receives its springs' terms in the serial pass's order (a spring
    joining two chunks is computed by both). No chunk writes where another does: no race, and the same sums
    whatever the number of threads or chunks.
    """
    B = blocks.reshape(-1)
    for c in prange(len(cptr) - 1):
        lo = vlo[c]
        hi = vlo[c + 1]
        for p in range(cptr[c], cptr[c + 1]):
            s = clist[p]
            i = si[s]
            j = sj[s]
            t = _spring_terms(x, v, w, with_w, damped, i, j, k[s], kd[s], L0[s], tiny, c_x, c_v)
            if lo <= i < hi:
                _add_end(B, f, kw, with_w, i, 1.0, bidx[s, 0], bidx[s, 2], t)
            if lo <= j < hi:
                _add_end(B, f, kw, with_w, j, -1.0, bidx[s, 1], bidx[s, 3], t)


def chunk_springs(n: int, si: np.ndarray, sj: np.ndarray, chunks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chunks of :func:`springs_linearize_chunks`: ``chunks`` equal vertex ranges (bounds ``vlo``) and each
    one's springs with an end in it, ascending (``cptr``, ``clist``)."""
    vlo = np.linspace(0, n, chunks + 1).round().astype(np.int64)
    ci = np.searchsorted(vlo, si, side="right") - 1
    cj = np.searchsorted(vlo, sj, side="right") - 1
    s = np.arange(len(si), dtype=np.int64)
    owner = np.concatenate([ci, cj[cj != ci]])
    order = np.concatenate([s, s[cj != ci]])
    o = np.lexsort((order, owner))
    cptr = np.zeros(chunks + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=chunks), out=cptr[1:])
    return vlo, cptr, np.ascontiguousarray(order[o])


@njit(cache=True)
def spring_lengths(x, si, sj, out):
    """``out[s] = |x[sj[s]] - x[si[s]]|``, m (the numpy path's ``Springs.lengths``, one pass)."""
    for s in range(len(si)):
        out[s] = spring_vector(x, si[s], sj[s])[3]


@njit(cache=True)
def spring_dissipation(x, v, si, sj, kd, tiny):
    """Rayleigh's ``sum_s kd ((v_j - v_i) . u)^2 / 2`` at the geometry ``x``, W (the numpy path's
    ``Springs.dissipation``, one pass; ``u = 0`` where ``l <= tiny``)."""
    total = 0.0
    for s in range(len(si)):
        if kd[s] == 0.0:
            continue
        i = si[s]
        j = sj[s]
        d0 = x[j, 0] - x[i, 0]
        d1 = x[j, 1] - x[i, 1]
        d2 = x[j, 2] - x[i, 2]
        l = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if l <= tiny:
            continue
        w = ((v[j, 0] - v[i, 0]) * d0 + (v[j, 1] - v[i, 1]) * d1 + (v[j, 2] - v[i, 2]) * d2) / l
        total += kd[s] * w * w
    return 0.5 * total


@njit(cache=True, inline="always")
def _dot3(a0, a1, a2, b0, b1, b2):
    """``a . b`` summed as numpy's ``einsum("ij,ij->i")`` sums three products here, ``(a0 b0 + a2 b2) + a1 b1``
    (checked bit for bit against it in the tests), so that :func:`spring_forces` gives numpy's numbers."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@njit(cache=True, inline="always")
def _spring_force(x, v, si, sj, k, kd, L0, tiny, damped, s, F):
    """``F[s]``: spring ``s``'s force on its first vertex, with numpy's arithmetic (:func:`spring_forces`)."""
    i = si[s]
    j = sj[s]
    d0 = x[j, 0] - x[i, 0]
    d1 = x[j, 1] - x[i, 1]
    d2 = x[j, 2] - x[i, 2]
    l = math.sqrt(_dot3(d0, d1, d2, d0, d1, d2))
    inv = 1.0 / l if l > tiny else 0.0
    u0 = d0 * inv
    u1 = d1 * inv
    u2 = d2 * inv
    ks = k[s]
    L = L0[s]
    f0 = ks * (d0 - L * u0)
    f1 = ks * (d1 - L * u1)
    f2 = ks * (d2 - L * u2)
    if damped:
        g = kd[s] * _dot3(v[j, 0] - v[i, 0], v[j, 1] - v[i, 1], v[j, 2] - v[i, 2], u0, u1, u2)
        f0 += g * u0
        f1 += g * u1
        f2 += g * u2
    F[s, 0] = f0
    F[s, 1] = f1
    F[s, 2] = f2


@njit(cache=True, inline="always")
def _incidence_row(r, bptr, bcol, bval, F, out):
    """``out[r] += (B F)[r]``, summed in the row's stored order as scipy's product sums."""
    y0 = 0.0
    y1 = 0.0
    y2 = 0.0
    for p in range(bptr[r], bptr[r + 1]):
        c = bcol[p]
        a = bval[p]
        y0 += a * F[c, 0]
        y1 += a * F[c, 1]
        y2 += a * F[c, 2]
    out[r, 0] += y0
    out[r, 1] += y1
    out[r, 2] += y2


@njit(cache=True)
def spring_forces(x, v, si, sj, k, kd, L0, tiny, damped, bptr, bcol, bval, F, out):
    """``out += B F``: the springs' forces on the vertices, with numpy's arithmetic to the last bit.

    :meth:`Springs.force <implicit_cloth.effects.springs.Springs.force>` on the numpy path, one pass: the force
    of each spring on its first vertex (``F``, (S, 3), written; the springs in their own order, ``si``,
    ``sj``, ``k``, ``kd``, ``L0``) as ``_frame`` and ``_forces_from_frame`` compute it (no contraction into
    fused multiply-adds: separately rounded products and sums, the dot products in einsum's order
    (:func:`_dot3`)), then the incidence matrix ``B`` (CSR ``bptr``, ``bcol``, ``bval``: +1 at the first
    vertex, -1 at the second) times ``F`` row by row in its stored order, as scipy's product sums, added to
    ``out``.
    """
    for s in range(si.shape[0]):
        _spring_force(x, v, si, sj, k, kd, L0, tiny, damped, s, F)
    for r in range(bptr.shape[0] - 1):
        _incidence_row(r, bptr, bcol, bval, F, out)


@njit(cache=True, parallel=True)
def pspring_forces(x, v, si, sj, k, kd, L0, tiny, damped, bptr, bcol, bval, F, out):
    """:func:`spring_forces` on threads: each spring's force, then each vertex's row, written by one thread
    each (the same numbers). The library runs it at every size (on one thread below the threaded size: numba's
    parallel lowering vectorises the loop over the springs, three times faster than :func:`spring_forces`),
    which stays the serial reference."""
    for s in prange(si.shape[0]):
        _spring_force(x, v, si, sj, k, kd, L0, tiny, damped, s, F)
    for r in prange(bptr.shape[0] - 1):
        _incidence_row(r, bptr, bcol, bval, F, out)
