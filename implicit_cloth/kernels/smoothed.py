"""Compiled (numba) kernels of the smoothed-prolongation hierarchy (``solver.preconditioner =
"multigrid_smoothed"``, :mod:`implicit_cloth.solvers.multigrid`): the per-step prolongation blocks and the
Galerkin product with them.

A level's prolongation keeps the node pattern of its geometric ``P0`` (bilinear on grids) but each entry is a
3x3 block, refreshed every step from the level's current matrix ``A`` (the filtered one on the finest level):

    P~[f, c] = P0[f, c] I - w D_f^-1 sum_j A[f, j] P0[j, c]       (only on P0's pattern)
    P[f, c]  = F_f P~[f, c],   F_f = s_f (sum_c P~[f, c])^-1,   s_f = sum_c P0[f, c]

(one damped-Jacobi smoothing of ``P0``, as smoothed aggregation does, restricted to ``P0``'s pattern so that
the coarse matrices keep their pattern; ``F_f`` restores each fine vertex's block row sum, so a translation is
still interpolated exactly). The blocks mix the three components, which the scalar ``P0 kron I3`` cannot: on a
curved or wrinkled cloth the stiff (stretching) directions turn from vertex to vertex, and the coarse space
follows them.

Block arrays are flat, 9 numbers a block, row-major, as in :mod:`.pcg`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .pcg import filter_delta, filtered_block, gal_add


@njit(cache=True, fastmath={"contract"}, inline="always")
def _add_term(sd, su, code, w, Sc, cpos, f, uI, uJ, tmp, B, acc):
    """``acc += w A[f, j]`` for a smoothing term: ``code = 3 k + kind`` with kind 0 the diagonal block ``k``,
    1 the upper block ``k`` as stored, 2 the upper block ``k`` transposed (``j < f``). A block no filter
    touches is added from where it is stored; one where ``cpos`` marks a constrained vertex is filtered first
    (``S_f A S_j + (I - S_f)`` on the diagonal; ``tmp``, ``B``: scratch)."""
    k = code // 3
    kind = code - 3 * k
    j = f if kind == 0 else (uJ[k] if kind == 1 else uI[k])
    if len(cpos) == 0 or (cpos[f] < 0 and cpos[j] < 0):
        if kind == 0:
            for m in range(9):
                acc[m] += w * sd[9 * k + m]
        elif kind == 1:
            for m in range(9):
                acc[m] += w * su[9 * k + m]
        else:
            for a in range(3):
                for b in range(3):
                    acc[3 * a + b] += w * su[9 * k + 3 * b + a]
        return
    if kind == 0:
        for m in range(9):
            tmp[m] = sd[9 * k + m]
    elif kind == 1:
        for m in range(9):
            tmp[m] = su[9 * k + m]
    else:
        for a in range(3):
            for b in range(3):
                tmp[3 * a + b] = su[9 * k + 3 * b + a]
    filtered_block(tmp, 0, Sc, cpos[f], cpos[j], kind == 0, B)
    for m in range(9):
        acc[m] += w * B[m]


@njit(cache=True, fastmath={"contract"})
def smooth_prolongation(sd, su, dinv, ptr, p0, target, t_ptr, t_code, t_w, uI, uJ, cpos, Sc, omega, out):
    """The blocks ``P[f, c]`` of the module docstring, for every entry of ``P0`` (CSR ``ptr``, values ``p0``;
    its entry ``e``'s terms ``t_ptr[e]:t_ptr[e+1]``: block codes ``t_code`` (see :func:`_add_term`) with
    weights ``t_w = P0[j, c]``), from the level's diagonal (``sd``) and upper (``su``) blocks and its inverted
    (filtered) diagonal blocks ``dinv``; ``cpos``/``Sc``: the finest level's filter (empty elsewhere).
    Writes ``out`` (9 numbers an entry). A row whose block sum is singular keeps ``P0`` (times I)."""
    _smooth_rows(0, len(ptr) - 1, sd, su, dinv, ptr, p0, target, t_ptr, t_code, t_w, uI, uJ, cpos, Sc, omega, out)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def psmooth_prolongation(sd, su, dinv, ptr, p0, target, t_ptr, t_code, t_w, uI, uJ, cpos, Sc, omega, out, rb):
    """:func:`smooth_prolongation` on threads, the rows cut at ``rb`` (each row is computed alone: the same
    numbers)."""
    for k in prange(len(rb) - 1):
        _smooth_rows(rb[k], rb[k + 1], sd, su, dinv, ptr, p0, target, t_ptr, t_code, t_w, uI, uJ, cpos, Sc,
                     omega, out)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _smooth_rows(f0, f1, sd, su, dinv, ptr, p0, target, t_ptr, t_code, t_w, uI, uJ, cpos, Sc, omega, out):  # noqa: C901
    """Rows ``f0:f1`` of :func:`smooth_prolongation`."""
    B = np.empty(9)
    acc = np.empty(9)
    tmp = np.empty(9)
    rs = np.empty(9)
    F = np.empty(9)
    for f in range(f0, f1):
        for m in range(9):
            rs[m] = 0.0
        for e in range(ptr[f], ptr[f + 1]):
            for m in range(9):
                acc[m] = 0.0
            for t in range(t_ptr[e], t_ptr[e + 1]):
                _add_term(sd, su, t_code[t], t_w[t], Sc, cpos, f, uI, uJ, tmp, B, acc)
            o = 9 * e
            for a in range(3):
                for b in range(3):
                    s = 0.0
                    for q in range(3):
                        s += dinv[9 * f + 3 * a + q] * acc[3 * q + b]
                    v = (p0[e] if a == b else 0.0) - omega * s
                    out[o + 3 * a + b] = v
                    rs[3 * a + b] += v
        # F = target_f * rs^-1 (adjugate), applied from the left to the row's blocks
        a0, a1, a2, a3, a4, a5, a6, a7, a8 = rs[0], rs[1], rs[2], rs[3], rs[4], rs[5], rs[6], rs[7], rs[8]
        c00 = a4 * a8 - a5 * a7
        c10 = a5 * a6 - a3 * a8
        c20 = a3 * a7 - a4 * a6
        det = a0 * c00 + a1 * c10 + a2 * c20
        if not np.isfinite(det) or abs(det) <= 1e-12 * max(abs(a0), abs(a4), abs(a8)) ** 3:
            for e in range(ptr[f], ptr[f + 1]):
                for a in range(3):
                    for b in range(3):
                        out[9 * e + 3 * a + b] = p0[e] if a == b else 0.0
            continue
        s = target[f] / det
        F[0], F[1], F[2] = c00 * s, (a2 * a7 - a1 * a8) * s, (a1 * a5 - a2 * a4) * s
        F[3], F[4], F[5] = c10 * s, (a0 * a8 - a2 * a6) * s, (a2 * a3 - a0 * a5) * s
        F[6], F[7], F[8] = c20 * s, (a1 * a6 - a0 * a7) * s, (a0 * a4 - a1 * a3) * s
        for e in range(ptr[f], ptr[f + 1]):
            o = 9 * e
            for m in range(9):
                B[m] = out[o + m]
            for a in range(3):
                for b in range(3):
                    out[o + 3 * a + b] = F[3 * a] * B[b] + F[3 * a + 1] * B[3 + b] + F[3 * a + 2] * B[6 + b]


@njit(cache=True, fastmath={"contract"}, inline="always")
def _pt_b(pb, q, B, o, Y):
    """``Y = P^T B`` for the flat block ``P = pb[q:q + 9]`` and ``B = B[o:o + 9]``."""
    for a in range(3):
        for b in range(3):
            Y[3 * a + b] = pb[q + a] * B[o + b] + pb[q + 3 + a] * B[o + 3 + b] + pb[q + 6 + a] * B[o + 6 + b]


@njit(cache=True, fastmath={"contract"}, inline="always")
def _y_p(Y, pb, r, C):
    """``C = Y P`` for the flat block ``P = pb[r:r + 9]``."""
    for a in range(3):
        for b in range(3):
            C[3 * a + b] = Y[3 * a] * pb[r + b] + Y[3 * a + 1] * pb[r + 3 + b] + Y[3 * a + 2] * pb[r + 6 + b]


@njit(cache=True, fastmath={"contract"})
def galerkin_blocks(sd, su, od, ou, d_ptr, d_dst, d_pa, d_pb, u_ptr, u_dst, u_pa, u_pb, pb):
    """Galerkin product ``P^T A P`` for a block prolongation ``pb`` (9 numbers an entry of ``P0``'s pattern):
    the entry lists of :func:`implicit_cloth.kernels.pcg.galerkin` with, instead of the weight
    ``P0[i, I] P0[j, J]``, the two prolongation entries ``pa``, ``pb`` whose blocks give ``P[i, I]^T B P[j, J]``."""
    od[:] = 0.0
    ou[:] = 0.0
    Y = np.empty(9)
    C = np.empty(9)
    _galerkin_list(sd, od, ou, d_ptr, d_dst, d_pa, d_pb, pb, Y, C)
    _galerkin_list(su, od, ou, u_ptr, u_dst, u_pa, u_pb, pb, Y, C)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def pgalerkin_blocks(sd, su, od, ou, d_src, d_dst, d_pa, d_pb, d_cb, u_src, u_dst, u_pa, u_pb, u_cb, pb):
    """:func:`galerkin_blocks` on threads. Chunk ``k`` owns a range of the coarse rows and adds, to the blocks of
    its rows, their entries in the order the serial kernel adds them: the entry lists come in that order
    (:func:`implicit_cloth.solvers.multigrid.galerkin_sequence`: chunk by chunk, ascending within one, the
    diagonal list's before the upper list's; ``*_src``: each entry's source block; chunk ``k`` is
    ``*_cb[k]:*_cb[k + 1]``), so every coarse block is the same sum, in the same order, as serially, whatever the
    thread count, and each chunk reads its entries sequentially (read through an order array instead, the
    128² level took 1.4 times as long)."""
    od[:] = 0.0
    ou[:] = 0.0
    for k in prange(len(d_cb) - 1):
        Y = np.empty(9)
        C = np.empty(9)
        _galerkin_chunk(sd, od, ou, d_src, d_dst, d_pa, d_pb, d_cb[k], d_cb[k + 1], pb, Y, C)
        _galerkin_chunk(su, od, ou, u_src, u_dst, u_pa, u_pb, u_cb[k], u_cb[k + 1], pb, Y, C)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def pgalerkin_blocks_filter(sd, su, od, ou, d_src, d_dst, d_pa, d_pb, d_cb, u_src, u_dst, u_pa, u_pb, u_cb, pb,
                            cpos, Sc, fuI, fuJ, td, tu):
    """:func:`galerkin_blocks_filter` on threads, chunked as :func:`pgalerkin_blocks`: each chunk adds
    ``filtered - unfiltered`` of the source blocks touching a constrained vertex (``td``: diagonal blocks,
    ``tu``: upper blocks, ascending) through those of its entries, in the serial kernel's order (the same
    numbers). A chunk's entries come by source block (ascending), so each touching block's entries in the chunk
    are one run, found by bisection: the chunk reads those entries only, not all of its own."""
    for k in prange(len(d_cb) - 1):
        B = np.empty(9)
        Y = np.empty(9)
        C = np.empty(9)
        _filter_runs(sd, od, ou, d_src, d_dst, d_pa, d_pb, d_cb[k], d_cb[k + 1], pb, cpos, Sc, fuI, fuJ, td,
                     True, B, Y, C)
        _filter_runs(su, od, ou, u_src, u_dst, u_pa, u_pb, u_cb[k], u_cb[k + 1], pb, cpos, Sc, fuI, fuJ, tu,
                     False, B, Y, C)


@njit(cache=True, inline="always")
def _first_at_least(a, lo, hi, v):
    """The first position in ``a[lo:hi]`` (ascending) whose value is at least ``v`` (``hi`` if none)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, fastmath={"contract"}, inline="always")
def _filter_runs(src, od, ou, esrc, dst, pa, pbi, lo, hi, pb, cpos, Sc, fuI, fuJ, touch, diag, B, Y, C):
    """The entries ``lo:hi`` of one list of :func:`pgalerkin_blocks_filter` whose source block is one of
    ``touch`` (the blocks touching a constrained vertex: ``diag``, the list of diagonal blocks, vertex ``s``;
    else upper block ``s``, vertices ``fuI[s]``, ``fuJ[s]``): ``B`` its ``filtered - unfiltered``, ``Y`` formed
    again where ``pa`` changes within the block's run."""
    q0 = lo
    for t in range(len(touch)):
        s = touch[t]
        q0 = _first_at_least(esrc, q0, hi, s)
        if q0 >= hi:
            break
        if esrc[q0] != s:
            continue
        ci = cpos[s] if diag else cpos[fuI[s]]
        cj = cpos[s] if diag else cpos[fuJ[s]]
        filter_delta(src, s, Sc, ci, cj, diag, B)
        last_a = -1
        q = q0
        while q < hi and esrc[q] == s:
            if pa[q] != last_a:
                last_a = pa[q]
                _pt_b(pb, 9 * last_a, B, 0, Y)
            _y_p(Y, pb, 9 * pbi[q], C)
            gal_add(C, dst[q], 1.0, od, ou)
            q += 1
        q0 = q


@njit(cache=True, fastmath={"contract"}, inline="always")
def _galerkin_chunk(src, od, ou, esrc, dst, pa, pbi, lo, hi, pb, Y, C):
    """The entries ``lo:hi`` of one list of :func:`pgalerkin_blocks`; ``Y`` formed again where the source
    block or ``pa`` changes, as :func:`_galerkin_list` does (the same products)."""
    last_s = -1
    last_a = -1
    for q in range(lo, hi):
        s = esrc[q]
        if s != last_s or pa[q] != last_a:
            last_s = s
            last_a = pa[q]
            _pt_b(pb, 9 * last_a, src, 9 * s, Y)
        _y_p(Y, pb, 9 * pbi[q], C)
        gal_add(C, dst[q], 1.0, od, ou)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _galerkin_list(src, od, ou, ptr, dst, pa, pbi, pb, Y, C):
    """One entry list of :func:`galerkin_blocks`: source block ``s`` is ``src[9 s:9 s + 9]``, its entries
    ``ptr[s]:ptr[s+1]``. They come in runs of the same ``pa`` (the pairs are listed ``a``-major), so
    ``Y = P[i, I]^T B`` is formed once a run and each entry costs one 3x3 product ``Y P[j, J]``, added with the
    modes of the scalar product (:func:`~.pcg.gal_add`, weight 1)."""
    for s in range(len(ptr) - 1):
        o = 9 * s
        last = -1
        for e in range(ptr[s], ptr[s + 1]):
            if pa[e] != last:
                last = pa[e]
                _pt_b(pb, 9 * last, src, o, Y)
            _y_p(Y, pb, 9 * pbi[e], C)
            gal_add(C, dst[e], 1.0, od, ou)


@njit(cache=True, fastmath={"contract"})
def galerkin_blocks_filter(sd, su, od, ou, d_ptr, d_dst, d_pa, d_pb, u_ptr, u_dst, u_pa, u_pb, pb,
                           cpos, Sc, fuI, fuJ, td, tu):
    """:func:`implicit_cloth.kernels.pcg.galerkin_filter` for a block prolongation: after
    :func:`galerkin_blocks` of the unfiltered fine matrix, add ``filtered - unfiltered`` of the few fine blocks
    touching a constrained vertex through their own entries."""
    B = np.empty(9)
    Y = np.empty(9)
    C = np.empty(9)
    for q in range(len(td)):
        s = td[q]
        filter_delta(sd, s, Sc, cpos[s], cpos[s], True, B)       # one source block, B: its entries d_ptr[s]:d_ptr[s+1]
        _galerkin_list(B, od, ou, d_ptr[s:s + 2], d_dst, d_pa, d_pb, pb, Y, C)
    for q in range(len(tu)):
        s = tu[q]
        filter_delta(su, s, Sc, cpos[fuI[s]], cpos[fuJ[s]], False, B)
        _galerkin_list(B, od, ou, u_ptr[s:s + 2], u_dst, u_pa, u_pb, pb, Y, C)


@njit(cache=True, parallel=True)
def ptranspose_blocks(pval, perm, out):
    """``out[k] = pval[perm[k]]^T`` for flat 3x3 blocks (the restrictions' blocks from the prolongations'), on
    threads (a copy: the same numbers)."""
    n = len(perm)
    chunks = 8
    for c in prange(chunks):
        for k in range(n * c // chunks, n * (c + 1) // chunks):
            s = 9 * perm[k]
            t = 9 * k
            for a in range(3):
                for b in range(3):
                    out[t + 3 * a + b] = pval[s + 3 * b + a]
