"""Compiled (numba) kernels of the multigrid-preconditioned filtered PCG: the default back-end's.

Same algorithm, same arithmetic order up to floating-point reassociation, as
the numpy reference path (:func:`implicit_cloth.solvers.pcg.filtered_pcg` with
:class:`implicit_cloth.solvers.multigrid.Multigrid`), fused so that one CG
iteration makes about four passes over the matrix data (the product ``A p``,
the V-cycle's pre- and post-smoothing residuals on every level) and no Python
call per vector operation:

* every level's matrix is symmetric and is stored as its diagonal blocks
  and its upper blocks only (``i < j``, with their vertex pair; the block
  ``(j, i)`` is the transpose): one flat pass over the stored blocks gives
  both of their products (:func:`_symmv`). Against block rows holding every
  block this reads half the data and drops the inner loop's variable trip
  count: the product got 2-5x faster at 64²-256², the V-cycle 2-3x;
* the Baraff-Witkin filter is applied on the fly on the finest level
  (:func:`_fsymmv`: ``S A S x + (I - S) x`` by filtering ``x`` at the
  constrained vertices, multiplying, and filtering the result there), so the
  unfiltered fine blocks are never copied per filter;
* each level's residual and its damped block-Jacobi post-smoothing are one
  product pass and one vector pass each; restriction and prolongation are
  gathers through the node-level ``P^T`` and ``P`` (CSR, acting on 3-vectors);
* the coarsest level is solved with the upper Cholesky factor ``U``
  (``A_c = U^T U``), or a dense inverse when no factor is available;
* CG's vector updates, dot products and the error estimate of the stopping
  rule are fused loops;
* ``solver.cycle = "K"``: the K-cycle (:func:`kcycle`) instead of the V-cycle, the same
  passes on every level but each coarse correction one or two flexible-CG iterations on
  the next level, and CG then flexible (:func:`pcg`'s ``kthreshold``).

Floating-point contraction (fused multiply-add) is allowed (``fastmath={"contract"}``:
no reassociation, NaN and infinity kept): the V-cycle got 12-18 % faster at 128².

Every function is compiled with ``cache=True`` (the compiled code is stored
next to this file in ``__pycache__``), so the compilation is paid once per installation, not per run, and only
for the passes a run uses: on one thread (:func:`_on`: the threads' flags ``lpar`` None) no ``parallel=True``
kernel, with the V-cycle (``kthreshold`` None) no K-cycle. The hanging example's solver compiled in about 20 s
of CPU on the 2-core test machine that way, against about 40 s with the threaded passes and the K-cycle.
Threads (:func:`implicit_cloth.backend.threads`, one by default): the passes of levels of at least
``backend.thread_min_vertices()`` vertices run on numba threads (``prange``) over a fixed number of
chunks, each writing only its own rows (:func:`_psymmv`: a stored block between two chunks is read by
both, each taking its side), so the numbers are the same, to the last bit, for every thread count and
as serially. CG's dot products are one serial sum on small cloths; from
``multigrid.CHUNKED_SUMS_MIN_VERTICES`` fine vertices they are summed over fixed chunks at every thread
count (:func:`_sums`), the partial sums on threads, so they too give the same numbers whatever the
thread count. The parallel regions run on numba's threading layer as :mod:`.layer` chooses it.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import estimate, layer  # noqa: F401  (layer: the threading layer, chosen before any region runs)


@njit(cache=True, inline="always")
def _filt3(Sc, c, x0, x1, x2):
    s = Sc[c]
    return (s[0, 0] * x0 + s[0, 1] * x1 + s[0, 2] * x2,
            s[1, 0] * x0 + s[1, 1] * x1 + s[1, 2] * x2,
            s[2, 0] * x0 + s[2, 1] * x1 + s[2, 2] * x2)


@njit(cache=True, fastmath={"contract"})
def filter_vec(cidx_list, Sc, x):
    """``x <- S x`` for the constrained vertices ``cidx_list`` (their filters ``Sc`` in the same order)."""
    for c in range(len(cidx_list)):
        i = cidx_list[c]
        y0, y1, y2 = _filt3(Sc, c, x[3 * i], x[3 * i + 1], x[3 * i + 2])
        x[3 * i], x[3 * i + 1], x[3 * i + 2] = y0, y1, y2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _diag_rows(dg, x, y, lo, hi):
    """``y[i] = D_i x_i`` for the vertices ``lo:hi``."""
    for i in range(lo, hi):
        d = dg[i]
        x0 = x[3 * i]
        x1 = x[3 * i + 1]
        x2 = x[3 * i + 2]
        y[3 * i] = d[0, 0] * x0 + d[0, 1] * x1 + d[0, 2] * x2
        y[3 * i + 1] = d[1, 0] * x0 + d[1, 1] * x1 + d[1, 2] * x2
        y[3 * i + 2] = d[2, 0] * x0 + d[2, 1] * x1 + d[2, 2] * x2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _diag_product(dg, x, y):
    """``y = D x`` for the diagonal blocks ``dg`` (n, 3, 3): the start of every symmetric product."""
    _diag_rows(dg, x, y, 0, len(dg))


@njit(cache=True, fastmath={"contract"}, inline="always")
def _block_row_side(s, i, j, x, y):
    """``y_i += B x_j`` for the stored block ``B = s`` (3, 3) at ``(i, j)``."""
    xj0 = x[3 * j]
    xj1 = x[3 * j + 1]
    xj2 = x[3 * j + 2]
    y[3 * i] += s[0, 0] * xj0 + s[0, 1] * xj1 + s[0, 2] * xj2
    y[3 * i + 1] += s[1, 0] * xj0 + s[1, 1] * xj1 + s[1, 2] * xj2
    y[3 * i + 2] += s[2, 0] * xj0 + s[2, 1] * xj1 + s[2, 2] * xj2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _block_col_side(s, i, j, x, y):
    """``y_j += B^T x_i`` for the stored block ``B = s`` (3, 3) at ``(i, j)``."""
    xi0 = x[3 * i]
    xi1 = x[3 * i + 1]
    xi2 = x[3 * i + 2]
    y[3 * j] += s[0, 0] * xi0 + s[1, 0] * xi1 + s[2, 0] * xi2
    y[3 * j + 1] += s[0, 1] * xi0 + s[1, 1] * xi1 + s[2, 1] * xi2
    y[3 * j + 2] += s[0, 2] * xi0 + s[1, 2] * xi1 + s[2, 2] * xi2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _block6_both(s, i, j, x, y, row, col):
    b00, b01, b02, b11, b12, b22 = s[0], s[1], s[2], s[3], s[4], s[5]
    if row:
        xj0 = x[3 * j]
        xj1 = x[3 * j + 1]
        xj2 = x[3 * j + 2]
        y[3 * i] += b00 * xj0 + b01 * xj1 + b02 * xj2
        y[3 * i + 1] += b01 * xj0 + b11 * xj1 + b12 * xj2
        y[3 * i + 2] += b02 * xj0 + b12 * xj1 + b22 * xj2
    if col:
        xi0 = x[3 * i]
        xi1 = x[3 * i + 1]
        xi2 = x[3 * i + 2]
        y[3 * j] += b00 * xi0 + b01 * xi1 + b02 * xi2
        y[3 * j + 1] += b01 * xi0 + b11 * xi1 + b12 * xi2
        y[3 * j + 2] += b02 * xi0 + b12 * xi1 + b22 * xi2


@njit(cache=True, fastmath={"contract"})
def _symmv(dg, uI, uJ, uv, x, y):
    """``y = A x`` for a symmetric block matrix stored as its diagonal blocks ``dg`` (n, 3, 3) and its upper
    blocks ``uv[k] = A[uI[k], uJ[k]]`` (``uI[k] < uJ[k]``; ``A[uJ[k], uI[k]] = uv[k]^T``): each stored
    off-diagonal block serves both of its products, so one pass reads half the matrix."""
    _diag_product(dg, x, y)
    for k in range(len(uI)):
        _block_row_side(uv[k], uI[k], uJ[k], x, y)
        _block_col_side(uv[k], uI[k], uJ[k], x, y)


@njit(cache=True, fastmath={"contract"})
def _symmv6(dg, uI, uJ, u6, x, y):
    """:func:`_symmv` for upper blocks that are themselves symmetric, stored as their six distinct numbers
    ``(B00, B01, B02, B11, B12, B22)``: a third less data again (spring blocks ``alpha I + beta u u^T``)."""
    _diag_product(dg, x, y)
    for k in range(len(uI)):
        _block6_both(u6[k], uI[k], uJ[k], x, y, True, True)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _psymmv(dg, uI, uJ, uv, u6, use6, vb, kb, ip, ib, x, y):
    """:func:`_symmv` (:func:`_symmv6` with ``use6``) on threads, with the same result to the last bit.

    The vertices are cut into chunks ``vb[c]:vb[c+1]`` and chunk c writes only its own rows of ``y``: its
    diagonal blocks; the stored blocks ``(j, i)`` of earlier rows whose column is its own, the listed
    ``ib[ip[c]:ip[c+1]]`` (ascending), on their column side; then its own rows' blocks ``kb[c]:kb[c+1]``
    (the blocks are sorted by row), on both sides when the column is its own too. Every ``y_i`` thus
    receives the same terms in the same order as in the serial pass, whatever the number of threads.
    """
    for c in prange(len(vb) - 1):
        v0 = vb[c]
        v1 = vb[c + 1]
        # each chunk works on views whose loops start at 0: with ranges starting at a chunk's bound LLVM could
        # not prove the indices non-negative and kept numba's wraparound test on every access (the chunked
        # product was 30 % slower a thread than the serial one; with the views the same speed)
        _diag_product(dg[v0:v1], x[3 * v0:3 * v1], y[3 * v0:3 * v1])
        inc = ib[ip[c]:ip[c + 1]]
        for m in range(len(inc)):
            k = inc[m]
            if use6:
                _block6_both(u6[k], uI[k], uJ[k], x, y, False, True)
            else:
                _block_col_side(uv[k], uI[k], uJ[k], x, y)
        ci = uI[kb[c]:kb[c + 1]]
        cj = uJ[kb[c]:kb[c + 1]]
        if use6:
            c6 = u6[kb[c]:kb[c + 1]]
            for k in range(len(ci)):
                i = ci[k]
                j = cj[k]
                if j < v1:
                    _block6_both(c6[k], i, j, x, y, True, True)
                else:
                    _block6_both(c6[k], i, j, x, y, True, False)
        else:
            cv = uv[kb[c]:kb[c + 1]]
            for k in range(len(ci)):
                i = ci[k]
                j = cj[k]
                _block_row_side(cv[k], i, j, x, y)
                if j < v1:
                    _block_col_side(cv[k], i, j, x, y)


@njit(cache=True, fastmath={"contract"})
def _msymmv(dg, uI, uJ, uv, u6, use6, part, x, y):
    """``y = A x`` serially, or on threads when ``part`` (a level's chunks, :func:`_psymmv`) is given:
    ``part = (vb, kb, ip, ib)``, empty ``vb`` for the serial pass. Both give the same numbers. ``part`` None: the
    serial pass, decided when compiling (:func:`_on`: the threaded pass is then not compiled)."""
    if part is None:
        if use6:
            _symmv6(dg, uI, uJ, u6, x, y)
        else:
            _symmv(dg, uI, uJ, uv, x, y)
        return
    vb, kb, ip, ib = part
    if len(vb) == 0:
        if use6:
            _symmv6(dg, uI, uJ, u6, x, y)
        else:
            _symmv(dg, uI, uJ, uv, x, y)
    else:
        _psymmv(dg, uI, uJ, uv, u6, use6, vb, kb, ip, ib, x, y)


@njit(cache=True)
def gather_sym6(src, idx, out6):
    """``out6[k]`` = the six distinct numbers of block ``src[idx[k]]`` (flat, 9 a block); returns whether
    every gathered block is exactly symmetric (only then may :func:`_symmv6` stand in for :func:`_symmv`)."""
    return _sym6_range(src, idx, out6, 0, len(idx))


@njit(cache=True, parallel=True)
def pgather_sym6(src, idx, out6):
    """:func:`gather_sym6` on threads (a copy and a test: the same result)."""
    n = len(idx)
    chunks = 8
    sym = np.ones(chunks, dtype=np.bool_)
    for c in prange(chunks):
        sym[c] = _sym6_range(src, idx, out6, n * c // chunks, n * (c + 1) // chunks)
    return np.all(sym)


@njit(cache=True, inline="always")
def _sym6_range(src, idx, out6, k0, k1):
    """Blocks ``k0:k1`` of :func:`gather_sym6`; whether they are all exactly symmetric."""
    sym = True
    for k in range(k0, k1):
        s = 9 * idx[k]
        out6[k, 0] = src[s]
        out6[k, 1] = src[s + 1]
        out6[k, 2] = src[s + 2]
        out6[k, 3] = src[s + 4]
        out6[k, 4] = src[s + 5]
        out6[k, 5] = src[s + 8]
        if src[s + 1] != src[s + 3] or src[s + 2] != src[s + 6] or src[s + 5] != src[s + 7]:
            sym = False
    return sym


@njit(cache=True, fastmath={"contract"})
def _fsymmv(dg, uI, uJ, uv, u6, use6, clist, Sc, ws, x, y, part):
    """``y = (S A S + I - S) x``, the filtered matrix (``x`` is filtered in place for the product and
    restored; ``ws`` holds ``3 len(clist)`` numbers of scratch); with ``use6`` the upper blocks are read
    from their symmetric six-number copy ``u6`` (:func:`_symmv6`); ``part``: see :func:`_msymmv`."""
    nc = len(clist)
    for c in range(nc):
        i = clist[c]
        x0, x1, x2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]
        ws[3 * c], ws[3 * c + 1], ws[3 * c + 2] = x0, x1, x2
        x[3 * i], x[3 * i + 1], x[3 * i + 2] = _filt3(Sc, c, x0, x1, x2)
    _msymmv(dg, uI, uJ, uv, u6, use6, part, x, y)
    for c in range(nc):
        i = clist[c]
        x0, x1, x2 = ws[3 * c], ws[3 * c + 1], ws[3 * c + 2]
        s0, s1, s2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]          # S x
        x[3 * i], x[3 * i + 1], x[3 * i + 2] = x0, x1, x2
        a0, a1, a2 = _filt3(Sc, c, y[3 * i], y[3 * i + 1], y[3 * i + 2])
        y[3 * i] = a0 + x0 - s0
        y[3 * i + 1] = a1 + x1 - s1
        y[3 * i + 2] = a2 + x2 - s2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _presmooth_row(dinv, omega, b, x, i):
    d = dinv[i]
    b0, b1, b2 = b[3 * i], b[3 * i + 1], b[3 * i + 2]
    x[3 * i] = omega * (d[0, 0] * b0 + d[0, 1] * b1 + d[0, 2] * b2)
    x[3 * i + 1] = omega * (d[1, 0] * b0 + d[1, 1] * b1 + d[1, 2] * b2)
    x[3 * i + 2] = omega * (d[2, 0] * b0 + d[2, 1] * b1 + d[2, 2] * b2)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _ppresmooth(dinv, omega, b, x):
    for i in prange(len(dinv)):
        _presmooth_row(dinv, omega, b, x, i)


@njit(cache=True, fastmath={"contract"})
def _presmooth(dinv, omega, b, x, par):
    """Pre-smoothing from zero: ``x = omega D^-1 b`` (on threads with ``par``: the same numbers)."""
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _ppresmooth(dinv, omega, b, x)
    else:
        for i in range(len(dinv)):
            _presmooth_row(dinv, omega, b, x, i)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _psub(b, y):
    for k in prange(len(y)):
        y[k] = b[k] - y[k]


@njit(cache=True, fastmath={"contract"})
def _sub(b, y, par=False):
    """``y <- b - y``."""
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _psub(b, y)
    else:
        for k in range(len(y)):
            y[k] = b[k] - y[k]


@njit(cache=True, fastmath={"contract"}, inline="always")
def _store3(y, i, y0, y1, y2, add):
    """``y[3 i : 3 i + 3] (+)= (y0, y1, y2)``: the end of a transfer row."""
    if add:
        y[3 * i] += y0
        y[3 * i + 1] += y1
        y[3 * i + 2] += y2
    else:
        y[3 * i] = y0
        y[3 * i + 1] = y1
        y[3 * i + 2] = y2


@njit(cache=True, fastmath={"contract"}, inline="always")
def _transfer_row(ptr, idx, val, x, y, add, i):
    y0 = 0.0
    y1 = 0.0
    y2 = 0.0
    for m in range(ptr[i], ptr[i + 1]):
        J = idx[m]
        w = val[m]
        y0 += w * x[3 * J]
        y1 += w * x[3 * J + 1]
        y2 += w * x[3 * J + 2]
    _store3(y, i, y0, y1, y2, add)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _btransfer_row(ptr, idx, val, x, y, add, i):
    """:func:`_transfer_row` for a block-valued ``M`` (9 numbers an entry: the smoothed prolongation)."""
    y0 = 0.0
    y1 = 0.0
    y2 = 0.0
    for m in range(ptr[i], ptr[i + 1]):
        J = idx[m]
        o = 9 * m
        x0, x1, x2 = x[3 * J], x[3 * J + 1], x[3 * J + 2]
        y0 += val[o] * x0 + val[o + 1] * x1 + val[o + 2] * x2
        y1 += val[o + 3] * x0 + val[o + 4] * x1 + val[o + 5] * x2
        y2 += val[o + 6] * x0 + val[o + 7] * x1 + val[o + 8] * x2
    _store3(y, i, y0, y1, y2, add)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _ptransfer(ptr, idx, val, x, y, add):
    if len(val) == 9 * len(idx):
        for i in prange(len(ptr) - 1):
            _btransfer_row(ptr, idx, val, x, y, add, i)
    else:
        for i in prange(len(ptr) - 1):
            _transfer_row(ptr, idx, val, x, y, add, i)


@njit(cache=True, fastmath={"contract"})
def _transfer(ptr, idx, val, x, y, add, par):
    """``y (+)= M x`` for a node-level CSR ``M`` (``P`` to prolong, ``P^T`` to restrict) acting on 3-vectors
    (rows on threads with ``par``: the same numbers); ``val`` holds a scalar an entry, or a 3x3 block an entry
    (9 numbers: the smoothed prolongation, recognised by its length)."""
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _ptransfer(ptr, idx, val, x, y, add)
    elif len(val) == 9 * len(idx) and len(idx):
        for i in range(len(ptr) - 1):
            _btransfer_row(ptr, idx, val, x, y, add, i)
    else:
        for i in range(len(ptr) - 1):
            _transfer_row(ptr, idx, val, x, y, add, i)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _smooth_row(dinv, omega, b, x, y, i):
    d = dinv[i]
    r0 = b[3 * i] - y[3 * i]
    r1 = b[3 * i + 1] - y[3 * i + 1]
    r2 = b[3 * i + 2] - y[3 * i + 2]
    y[3 * i] = x[3 * i] + omega * (d[0, 0] * r0 + d[0, 1] * r1 + d[0, 2] * r2)
    y[3 * i + 1] = x[3 * i + 1] + omega * (d[1, 0] * r0 + d[1, 1] * r1 + d[1, 2] * r2)
    y[3 * i + 2] = x[3 * i + 2] + omega * (d[2, 0] * r0 + d[2, 1] * r1 + d[2, 2] * r2)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _psmooth(dinv, omega, b, x, y):
    for i in prange(len(dinv)):
        _smooth_row(dinv, omega, b, x, y, i)


@njit(cache=True, fastmath={"contract"})
def _smooth(dinv, omega, b, x, y, par):
    """Post-smoothing update from ``y = A x``: ``y <- x + omega D^-1 (b - y)`` (in place in ``y``; on threads
    with ``par``: the same numbers)."""
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _psmooth(dinv, omega, b, x, y)
    else:
        for i in range(len(dinv)):
            _smooth_row(dinv, omega, b, x, y, i)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _sums_range(a, b, c, d, alpha, mass, mode, lo, hi):
    """Chunk ``lo:hi`` of the CG sums (views from 0: no wraparound test). ``mode`` 0: ``(a.b, 0, 0)``;
    1: ``(a.b, a.a, 0)``; 2: the update ``a += alpha c``, ``b -= alpha d`` (``dv``, ``r``, ``p``, ``q``), then
    ``(a.a, b.M^-1 b, a.M a)`` (the last two with ``mass`` non-empty)."""
    x = a[lo:hi]
    y = b[lo:hi]
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    if mode == 0:
        for k in range(len(x)):
            s0 += x[k] * y[k]
    elif mode == 1:
        for k in range(len(x)):
            s0 += x[k] * y[k]
            s1 += x[k] * x[k]
    else:
        pc = c[lo:hi]
        qd = d[lo:hi]
        weighted = len(mass) > 0
        m = mass[lo:hi] if weighted else mass
        for k in range(len(x)):
            u = x[k] + alpha * pc[k]
            w = y[k] - alpha * qd[k]
            x[k] = u
            y[k] = w
            s0 += u * u
            if weighted:
                s1 += w * w / m[k]
                s2 += u * u * m[k]
    return s0, s1, s2


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _psums(a, b, c, d, alpha, mass, mode, cb, out):
    for ch in prange(len(cb) - 1):
        out[ch, 0], out[ch, 1], out[ch, 2] = _sums_range(a, b, c, d, alpha, mass, mode, cb[ch], cb[ch + 1])


@njit(cache=True, fastmath={"contract"})
def _sums(a, b, c, d, alpha, mass, mode, cb, par, out):
    """:func:`_sums_range` over the whole vectors: one serial sum with no chunks ``cb``, else over the fixed
    chunks ``cb`` (on threads with ``par``; partial sums in ``out``), the partials then added in chunk order:
    the same numbers at every thread count."""
    if len(cb) == 0:
        return _sums_range(a, b, c, d, alpha, mass, mode, 0, len(a))
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _psums(a, b, c, d, alpha, mass, mode, cb, out)
    else:
        for ch in range(len(cb) - 1):
            out[ch, 0], out[ch, 1], out[ch, 2] = _sums_range(a, b, c, d, alpha, mass, mode, cb[ch], cb[ch + 1])
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for ch in range(len(cb) - 1):
        s0 += out[ch, 0]
        s1 += out[ch, 1]
        s2 += out[ch, 2]
    return s0, s1, s2


@njit(cache=True, fastmath={"contract"})
def _dot(a, b, cb, par, out):
    """``a.b`` (:func:`_sums`)."""
    return _sums(a, b, a, a, 0.0, a[:0], 0, cb, par, out)[0]


@njit(cache=True, fastmath={"contract"})
def _dot2(p, q, cb, par, out):
    """``(p.q, p.p)`` (:func:`_sums`)."""
    s0, s1, _ = _sums(p, q, p, p, 0.0, p[:0], 1, cb, par, out)
    return s0, s1


@njit(cache=True, fastmath={"contract"})
def _cg_update(dv, r, p, q, alpha, mass, use_mass, cb, par, out):
    """``dv += alpha p``, ``r -= alpha q``; returns ``(dv.dv, r.M^-1 r, dv.M dv)`` (the last two with ``use_mass``;
    :func:`_sums`)."""
    return _sums(dv, r, p, q, alpha, mass if use_mass else mass[:0], 2, cb, par, out)


@njit(cache=True, fastmath={"contract"}, parallel=True)
def _pp_update(p, s, beta):
    for k in prange(len(p)):
        p[k] = beta * p[k] + s[k]


@njit(cache=True, fastmath={"contract"})
def _p_update(p, s, beta, par):
    if par is not None and par:   # None: serial, the threaded pass not compiled (:func:`_on`)
        _pp_update(p, s, beta)
    else:
        for k in range(len(p)):
            p[k] = beta * p[k] + s[k]


@njit(cache=True, fastmath={"contract"})
def _coarse_solve(C, upper, b, x):
    """``x = A_c^-1 b``: with ``upper``, ``C = U`` (``A_c = U^T U``, upper triangle read only); else ``C = A_c^-1``."""
    m = len(b)
    if upper:
        for i in range(m):                 # U^T y = b
            s = b[i]
            for k in range(i):
                s -= C[k, i] * x[k]
            x[i] = s / C[i, i]
        for i in range(m - 1, -1, -1):     # U x = y
            s = x[i]
            for k in range(i + 1, m):
                s -= C[i, k] * x[k]
            x[i] = s / C[i, i]
    else:
        for i in range(m):
            s = 0.0
            for k in range(m):
                s += C[i, k] * b[k]
            x[i] = s


@njit(cache=True, fastmath={"contract"})
def _lev(l, dg, uI, uJ, uv, voff, uoff):
    """Level l's diagonal and upper blocks: views into the packed arrays."""
    return (dg[voff[l]:voff[l + 1]], uI[uoff[l]:uoff[l + 1]], uJ[uoff[l]:uoff[l + 1]], uv[uoff[l]:uoff[l + 1]])


@njit(cache=True)
def _on(lpar, l):
    """Whether level l's passes run on threads (``lpar[l]``). ``lpar`` None (no level on threads, as with one
    thread): None, a type rather than a value, so that the passes given it (``par is not None and par``,
    :func:`_msymmv`'s ``part is None``) compile their serial loop only: numba prunes a branch on an argument's
    ``is None`` when it compiles, and a run on one thread compiles none of the ``parallel=True`` kernels
    (about as long to compile as the rest of the solver)."""
    if lpar is None:
        return None
    return bool(lpar[l])


@njit(cache=True, fastmath={"contract"})
def _part(l, lpar, lpv, lpb, pbb):
    """Level l's chunks for :func:`_msymmv` (empty bounds: the serial pass): vertex bounds, block-row bounds,
    offsets of the chunks' incoming column blocks and their list (:func:`_psymmv`); None with ``lpar`` None
    (:func:`_on`)."""
    if lpar is None:
        return None
    K = len(lpv) // (2 * len(lpar))
    o = 2 * l * K
    if lpar[l]:
        return lpv[o:o + K], lpv[o + K:o + 2 * K], lpb[l * K:(l + 1) * K], pbb
    return lpv[0:0], lpv[0:0], lpb[0:0], pbb


@njit(cache=True, fastmath={"contract"})
def _apply_level(l, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, x, y, lpar, lpv, lpb, pbb):
    """``y = A_l x`` (the filtered matrix on the finest level, whose upper blocks may come from ``u6``),
    on threads when ``lpar[l]``."""
    d, i, j, u = _lev(l, dg, uI, uJ, uv, voff, uoff)
    part = _part(l, lpar, lpv, lpb, pbb)
    if l == 0:
        _fsymmv(d, i, j, u, u6, use6, clist, Sc, ws, x, y, part)
    else:
        _msymmv(d, i, j, u, u6, False, part, x, y)


@njit(cache=True, fastmath={"contract"}, inline="always")
def _level_down(l, b, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pnnz, tptr, tidx, tval, toff,
                omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk):
    """Level l's cycle before its coarse correction (:func:`vcycle`): pre-smooth from zero, the residual,
    restricted into level l + 1's right-hand side."""
    nc = voff[l + 2] - voff[l + 1]
    bl = b if l == 0 else wb[3 * voff[l]:3 * voff[l + 1]]
    x = wx[3 * voff[l]:3 * voff[l + 1]]
    r = wr[3 * voff[l]:3 * voff[l + 1]]
    d = dinv[voff[l]:voff[l + 1]]
    tp = tptr[toff[l]:toff[l] + nc + 1]
    ti = tidx[pnnz[l]:pnnz[l + 1]]
    tv = tval[9 * pnnz[l]:9 * pnnz[l + 1]] if blk else tval[pnnz[l]:pnnz[l + 1]]
    par = _on(lpar, l)
    _presmooth(d, omegas[l], bl, x, par)
    _apply_level(l, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, x, r, lpar, lpv, lpb, pbb)
    _sub(bl, r, par)
    _transfer(tp, ti, tv, r, wb[3 * voff[l + 1]:3 * voff[l + 2]], False, _on(lpar, l + 1))


@njit(cache=True, fastmath={"contract"}, inline="always")
def _level_up(l, b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pptr, pidx, pval, poff, pnnz,
              omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk):
    """Level l's cycle after its coarse correction (:func:`vcycle`; the correction in level l + 1's ``wr``, the
    coarsest's in its ``wx``): prolongated and added, then post-smoothed into ``wr`` (the finest level into
    ``out``)."""
    L = len(voff) - 2
    n = voff[l + 1] - voff[l]
    bl = b if l == 0 else wb[3 * voff[l]:3 * voff[l + 1]]
    x = wx[3 * voff[l]:3 * voff[l + 1]]
    y = out if l == 0 else wr[3 * voff[l]:3 * voff[l + 1]]
    xc = wx[3 * voff[L]:3 * voff[L + 1]] if l + 1 == L else wr[3 * voff[l + 1]:3 * voff[l + 2]]
    d = dinv[voff[l]:voff[l + 1]]
    pp = pptr[poff[l]:poff[l] + n + 1]
    pi = pidx[pnnz[l]:pnnz[l + 1]]
    pv = pval[9 * pnnz[l]:9 * pnnz[l + 1]] if blk else pval[pnnz[l]:pnnz[l + 1]]
    par = _on(lpar, l)
    _transfer(pp, pi, pv, xc, x, True, par)
    _apply_level(l, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, x, y, lpar, lpv, lpb, pbb)
    _smooth(d, omegas[l], bl, x, y, par)


@njit(cache=True, fastmath={"contract"})
def vcycle(b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
           pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
           wb, wx, wr):
    """One V-cycle of the filtered hierarchy: ``out = M^-1 b`` (``b`` the fine residual).

    Level l (0 finest, L = len(voff) - 2 coarsest) has ``n_l = voff[l+1] - voff[l]``
    vertices, diagonal blocks ``dg[voff[l]:voff[l+1]]`` and upper blocks
    ``uv[uoff[l]:uoff[l+1]]`` at local block indices ``uI``, ``uJ`` (see :func:`_symmv`);
    the finest level's are unfiltered, the filter being applied on the fly
    (:func:`_fsymmv`), and with ``use6`` read from their six-number copy ``u6``. Its vectors live at
    ``3 voff[l]`` in the work arrays ``wb``
    (right-hand sides), ``wx`` (iterates) and ``wr`` (products, residuals, then smoothed
    iterates). The prolongation l -> l+1 has rows ``pptr[poff[l]:poff[l] + n_l + 1]``
    (local), entries ``pnnz[l]:pnnz[l+1]`` of ``pidx``/``pval``; its transpose likewise in
    ``t*`` (rows ``toff[l]:toff[l] + n_{l+1} + 1``, the same entry range). With 9 values an entry in
    ``pval``/``tval`` the transfers are 3x3 blocks (the smoothed prolongation; entry e at ``9 e``).
    ``dinv[voff[l]:voff[l+1]]`` are level l's inverted (filtered) diagonal blocks, ``omegas[l]`` its
    smoother's damping (one damped block-Jacobi sweep before and one after the coarse correction).

    Threads: level l's passes run on threads when ``lpar[l]`` (its products chunked as in
    :func:`_psymmv`: ``lpv``/``lpb`` hold K chunk bounds and block-list offsets per level, the lists in
    ``pbb``; its vector passes split by rows); the numbers are the same as serially.
    """
    L = len(voff) - 2
    if L == 0:                                         # a single level: solved directly
        _coarse_solve(C, upper, b, out)
        return
    blk = len(pval) == 9 * len(pidx)                   # block transfers (the smoothed prolongation)
    for l in range(L):
        _level_down(l, b, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pnnz, tptr, tidx, tval, toff,
                    omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk)
    _coarse_solve(C, upper, wb[3 * voff[L]:3 * voff[L + 1]], wx[3 * voff[L]:3 * voff[L + 1]])
    for l in range(L - 1, -1, -1):
        _level_up(l, b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pptr, pidx, pval, poff,
                  pnnz, omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk)


@njit(cache=True, fastmath={"contract"})
def _vdot(x, y):
    """``x . y``, one serial sum (:func:`_sums_range`; the K-cycle's coarse levels: the same numbers at every
    thread count)."""
    return _sums_range(x, y, x, x, 0.0, x[:0], 0, 0, len(x))[0]


@njit(cache=True, fastmath={"contract"})
def kcycle(b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
           pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
           wb, wx, wr, kc, kv, kstage, kcoef, threshold):
    """One K-cycle (Notay & Vassilevski 2008; Notay's AGMG): :func:`vcycle`'s smoothing and transfers, but the
    coarse correction of every level l whose next level is not the coarsest is one or two iterations of
    flexible CG on level ``l + 1``'s matrix from zero, preconditioned by level ``l + 1``'s own cycle (the same,
    recursively); the second iteration is skipped when the first leaves ``|r1| <= threshold |r|``. Not a
    fixed linear operator: the outer CG must be flexible (:func:`pcg` with ``kthreshold >= 0``).

    Written as a loop over an explicit descent (each level's cycle may run twice per coarse correction of the
    level above): ``kstage[m]`` is the K-step of level m's progress (0: its first cycle, 1: its second), its
    first cycle's result kept in ``kc`` and that times level m's matrix in ``kv`` (both laid out as ``wb``),
    ``kcoef[2 m], kcoef[2 m + 1]`` the first iteration's ``c1 . A c1`` and ``c1 . r``. A level's right-hand side
    (``wb``) is the K-step's residual: the second cycle's is ``r1 = r - (c1 . r / c1 . A c1) A c1``. A level's
    cycle leaves its result in ``wr`` (the finest in ``out``), where the K-step combines its two.
    """
    L = len(voff) - 2
    if L <= 1:                                     # no level whose coarse correction takes a K-step
        vcycle(b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
               pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
               wb, wx, wr)
        return
    blk = len(pval) == 9 * len(pidx)
    l = 0
    down = True
    while True:
        if down:                                   # level l's cycle: pre-smooth, residual, restrict
            _level_down(l, b, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pnnz, tptr, tidx, tval,
                        toff, omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk)
            if l + 1 == L:
                _coarse_solve(C, upper, wb[3 * voff[L]:3 * voff[L + 1]], wx[3 * voff[L]:3 * voff[L + 1]])
                down = False
            else:
                l += 1
                kstage[l] = 0
            continue
        # level l's cycle, after its coarse correction: prolongate it, post-smooth
        _level_up(l, b, out, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv, pptr, pidx, pval, poff,
                  pnnz, omegas, lpar, lpv, lpb, pbb, wb, wx, wr, blk)
        if l == 0:
            return
        # level m = l's cycle done, its result c in wr: the K-step of level m goes on
        m = l
        l = m - 1                                  # unless the second cycle is run: back to the level above
        lo, hi = 3 * voff[m], 3 * voff[m + 1]
        c = wr[lo:hi]
        rm = wb[lo:hi]
        c1 = kc[lo:hi]
        v1 = kv[lo:hi]
        if kstage[m] == 0:
            for k in range(hi - lo):
                c1[k] = c[k]
            _apply_level(m, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, c1, v1, lpar, lpv, lpb, pbb)
            rho1 = _vdot(c1, v1)
            if not rho1 > 0.0:                     # no descent: the cycle's result as it is
                continue
            a1 = _vdot(c1, rm)
            g1 = a1 / rho1
            rr = _vdot(rm, rm)
            r1 = 0.0
            for k in range(hi - lo):               # the residual after the first iteration, in place
                rm[k] -= g1 * v1[k]
                r1 += rm[k] * rm[k]
            if r1 <= threshold * threshold * rr:
                for k in range(hi - lo):
                    c[k] = g1 * c1[k]
                continue
            kcoef[2 * m] = rho1
            kcoef[2 * m + 1] = a1
            kstage[m] = 1
            l = m                                  # level m's cycle again, on r1
            down = True
        else:
            rho1 = kcoef[2 * m]
            a1 = kcoef[2 * m + 1]
            v2 = wx[lo:hi]                         # (level m's iterate: free once its cycle is done)
            _apply_level(m, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, c, v2, lpar, lpv, lpb, pbb)
            gm = _vdot(c, v1)
            beta = _vdot(c, v2) - gm * gm / rho1
            a2 = _vdot(c, rm)
            kstage[m] = 0
            if beta > 0.0:
                f1 = a1 / rho1 - gm * a2 / (rho1 * beta)
                f2 = a2 / beta
                for k in range(hi - lo):
                    c[k] = f1 * c1[k] + f2 * c[k]
            else:                                  # the second direction adds nothing: the first iteration's
                for k in range(hi - lo):
                    c[k] = (a1 / rho1) * c1[k]


@njit(cache=True)
def _flexible(kthreshold):
    """Whether :func:`pcg`'s CG is flexible: a K-cycle threshold (``>= 0``) given."""
    if kthreshold is None:
        return False
    return kthreshold >= 0.0


@njit(cache=True, fastmath={"contract"})
def _precondition(r, s, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
                  pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
                  wb, wx, wr, kc, kv, kstage, kcoef, kthreshold):
    """``s = B r``: the V-cycle, or the K-cycle when ``kthreshold >= 0``. ``kthreshold`` None: the V-cycle, decided
    when compiling (numba prunes the branch on an argument's ``is None``), so a V-cycle run never compiles the
    K-cycle."""
    if kthreshold is None:
        vcycle(r, s, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
               pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
               wb, wx, wr)
    elif kthreshold >= 0.0:
        kcycle(r, s, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
               pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
               wb, wx, wr, kc, kv, kstage, kcoef, kthreshold)
    else:
        vcycle(r, s, dg, uI, uJ, uv, u6, use6, voff, uoff, clist, Sc, ws, dinv,
               pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
               wb, wx, wr)


@njit(cache=True, fastmath={"contract"})
def smoother_lanczos(l, dg, uI, uJ, uv, voff, uoff, dinv, q, alpha, beta):
    """Lanczos on ``D^-1 A`` of the (unfiltered, coarse) level ``l`` in the ``D`` inner product, from ``q``
    (overwritten), ``len(alpha)`` steps at most: the tridiagonal matrix's diagonal in ``alpha`` and its
    off-diagonal in ``beta`` (``len(alpha) - 1`` long); returns the steps taken (fewer when an invariant subspace
    ends it). Its largest eigenvalue estimates ``lambda_max(D^-1 A)`` from below. ``D``: the level's diagonal
    blocks, ``dinv`` their inverses (all levels' packed arrays)."""
    d, i, j, u = _lev(l, dg, uI, uJ, uv, voff, uoff)
    dl = dinv[voff[l]:voff[l + 1]]
    n = len(d)
    m = 3 * n
    qp = np.zeros(m)
    aq = np.empty(m)
    w = np.empty(m)
    nq = np.sqrt(_dnorm2(d, q))
    if not nq > 0.0:
        return 0
    for k in range(m):
        q[k] /= nq
    b = 0.0
    steps = len(alpha)
    for s in range(steps):
        _symmv(d, i, j, u, q, aq)
        a = 0.0
        for k in range(m):
            a += q[k] * aq[k]
        alpha[s] = a
        if s == steps - 1:
            return steps
        for v in range(n):
            a0, a1, a2 = aq[3 * v], aq[3 * v + 1], aq[3 * v + 2]
            for c in range(3):
                k = 3 * v + c
                w[k] = dl[v, c, 0] * a0 + dl[v, c, 1] * a1 + dl[v, c, 2] * a2 - a * q[k] - b * qp[k]
        b = np.sqrt(_dnorm2(d, w))
        if not b > 0.0:
            return s + 1
        beta[s] = b
        for k in range(m):
            qp[k] = q[k]
            q[k] = w[k] / b
    return steps


@njit(cache=True, fastmath={"contract"}, inline="always")
def _dnorm2(d, x):
    """``x^T D x`` for the block diagonal ``D`` (blocks ``d``)."""
    s = 0.0
    for v in range(len(d)):
        x0, x1, x2 = x[3 * v], x[3 * v + 1], x[3 * v + 2]
        for c in range(3):
            s += x[3 * v + c] * (d[v, c, 0] * x0 + d[v, c, 1] * x1 + d[v, c, 2] * x2)
    return s


@njit(cache=True, fastmath={"contract"})
def pcg(adg, auI, auJ, auv, au6, use6, dg, uI, uJ, uv, vu6, voff, uoff, clist, Sc, dinv,
        pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
        b, z, guess, use_guess, mass, use_mass, tol, max_iterations, bound_only, min_delay, delay_fraction,
        sum_chunks, kthreshold=None):
    """The filtered PCG of :func:`implicit_cloth.solvers.pcg.filtered_pcg` with the V-cycle preconditioner.

    ``adg``, ``auI``, ``auJ``, ``auv``: the fine matrix (unfiltered, float64, symmetric storage of
    :func:`_symmv`) that CG multiplies by (its upper blocks from ``au6`` with ``use6``); the V-cycle's packed
    hierarchy (:func:`vcycle`) may hold its own (float32) copy of it as level 0, its six-number upper blocks
    then ``vu6`` (else ``vu6`` is ``au6``). ``lpar``, ...: the threads' chunks (:func:`vcycle`); CG's
    products and its updates without a sum run on threads when the finest level's do, its dot products as
    ``sum_chunks`` says, so the iterates are the same whatever the number of threads.

    ``sum_chunks``: fixed bounds of the chunks CG's dot products are summed over (each chunk's partial sum,
    on threads when the finest level's passes are, then the partials in order: the same numbers at every
    thread count); empty for one plain serial sum.

    ``kthreshold``: None (compiles the V-cycle only) or below 0 the V-cycle (:func:`vcycle`); else the K-cycle
    (:func:`kcycle`, that threshold), and
    CG flexible: ``beta = -s_new . A p / p . A p`` (Polak-Ribiere's, equal to Fletcher-Reeves' with a fixed
    preconditioner, since ``r_new - r = -alpha A p``), ``p`` then A-orthogonal to the last direction only.

    Returns ``(dv, iterations, residual, converged, error)``.
    """
    N = len(b)
    Ntot = 3 * voff[len(voff) - 1]
    wb = np.zeros(Ntot)
    wx = np.zeros(Ntot)
    wr = np.zeros(Ntot)
    ws = np.zeros(3 * len(clist))
    dv = np.zeros(N)
    for c in range(len(clist)):                        # dv = (I - S) z
        i = clist[c]
        z0, z1, z2 = z[3 * i], z[3 * i + 1], z[3 * i + 2]
        s0, s1, s2 = _filt3(Sc, c, z0, z1, z2)
        dv[3 * i], dv[3 * i + 1], dv[3 * i + 2] = z0 - s0, z1 - s1, z2 - s2
    r = np.empty(N)
    part = _part(0, lpar, lpv, lpb, pbb)
    par = _on(lpar, 0)
    _msymmv(adg, auI, auJ, auv, au6, False, part, dv, r)
    _sub(b, r, par)
    filter_vec(clist, Sc, r)
    cb = sum_chunks
    sums = np.zeros((max(len(cb) - 1, 0), 3))
    norm0 = np.sqrt(_dot(r, r, cb, par, sums))
    if use_guess:
        g = guess.copy()
        filter_vec(clist, Sc, g)
        dv += g
        _msymmv(adg, auI, auJ, auv, au6, False, part, dv, r)
        _sub(b, r, par)
        filter_vec(clist, Sc, r)
    if norm0 == 0.0:
        return dv, 0, 0.0, True, 0.0
    s = np.empty(N)
    flexible = _flexible(kthreshold)
    kc = np.zeros(Ntot if flexible else 0)
    kv = np.zeros(Ntot if flexible else 0)
    kstage = np.zeros(len(voff), dtype=np.int64)
    kcoef = np.zeros(2 * len(voff))
    _precondition(r, s, dg, uI, uJ, uv, vu6, use6, voff, uoff, clist, Sc, ws, dinv,
                  pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
                  wb, wx, wr, kc, kv, kstage, kcoef, kthreshold)
    filter_vec(clist, Sc, s)
    p = s.copy()
    q = np.empty(N)
    delta = _dot(r, s, cb, par, sums)
    delta0 = delta
    ad = np.zeros(max_iterations)
    pw = np.zeros(max_iterations)
    converged = delta <= 0.0 and not np.any(r != 0.0)    # an exact guess; else delta <= 0 is a breakdown
    error = 0.0 if converged else np.inf
    it = 0
    while not converged and delta > 0.0 and it < max_iterations:
        # p is filtered, so S A S p + (I - S) p = S A p: the filtered product
        _fsymmv(adg, auI, auJ, auv, au6, use6, clist, Sc, ws, p, q, part)
        pq, pp = _dot2(p, q, cb, par, sums)
        if pq <= 0.0:
            break
        alpha = delta / pq
        dd, rmr, dmd = _cg_update(dv, r, p, q, alpha, mass, use_mass, cb, par, sums)
        ad[it] = alpha * delta
        pw[it] = pp / pq
        it += 1
        _precondition(r, s, dg, uI, uJ, uv, vu6, use6, voff, uoff, clist, Sc, ws, dinv,
                      pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omegas, lpar, lpv, lpb, pbb,
                      wb, wx, wr, kc, kv, kstage, kcoef, kthreshold)
        filter_vec(clist, Sc, s)
        delta_new = _dot(r, s, cb, par, sums)
        if delta_new < -1e-30 * delta0:     # breakdown: the preconditioner is not positive definite
            break
        if delta_new <= 1e-30 * delta0:
            converged = True
            error = 0.0
        else:
            if use_mass:
                error = np.sqrt(rmr / max(dmd, 1e-300))
                converged = error <= tol
            d = max(min_delay, int(delay_fraction * it))
            if not converged and not bound_only and it >= d:
                error = error_estimate(ad, pw, it, dd, d)
                converged = error <= tol
        if not converged:
            beta = -_dot(s, q, cb, par, sums) / pq if flexible else delta_new / delta
            _p_update(p, s, beta, par)
        delta = delta_new
    _msymmv(adg, auI, auJ, auv, au6, False, part, dv, q)
    _sub(b, q, par)
    filter_vec(clist, Sc, q)
    res = np.sqrt(_dot(q, q, cb, par, sums)) / norm0
    return dv, it, res, converged, error


@njit(cache=True, fastmath={"contract"}, inline="always")
def filtered_block(src, o, Sc, ci, cj, diag, out):
    """``out = S_i B S_j`` (plus ``I - S_i`` when ``diag``) for the flat block ``B = src[o:o + 9]``; ``ci``,
    ``cj``: the positions of its row and column vertex in the filters ``Sc`` (-1: a free vertex, ``S = I``)."""
    for k in range(9):
        out[k] = src[o + k]
    if ci >= 0:                                      # rows: S_i B
        s = Sc[ci]
        for b in range(3):
            t0, t1, t2 = out[b], out[3 + b], out[6 + b]
            for a in range(3):
                out[3 * a + b] = s[a, 0] * t0 + s[a, 1] * t1 + s[a, 2] * t2
    if cj >= 0:                                      # columns: (S_i B) S_j
        s = Sc[cj]
        for a in range(3):
            t0, t1, t2 = out[3 * a], out[3 * a + 1], out[3 * a + 2]
            for b in range(3):
                out[3 * a + b] = t0 * s[0, b] + t1 * s[1, b] + t2 * s[2, b]
    if diag and ci >= 0:                             # + (I - S_i): the constrained directions' identity
        s = Sc[ci]
        for a in range(3):
            for b in range(3):
                out[3 * a + b] += (1.0 if a == b else 0.0) - s[a, b]


@njit(cache=True, fastmath={"contract"})
def galerkin(sd, su, od, ou, d_ptr, d_dst, d_w, u_ptr, u_dst, u_w):
    """Galerkin product ``P^T A P`` of a symmetric block matrix in the storage of :func:`_symmv`,
    for a prolongation ``P kron I3``, written into the coarse level's diagonal (``od``) and upper (``ou``) blocks.

    All block arrays are flat (9 numbers a block, row-major). ``sd``, ``su``: the fine level's diagonal and
    upper blocks. Fine block ``s`` adds ``w = P[i, I] P[j, J]`` times itself to one coarse block per entry
    ``e`` in ``ptr[s]:ptr[s+1]`` (one entry per pair of prolongation entries), the coarse block and the way
    packed in ``dst[e] = 4 t + mode``:

    * diagonal fine blocks (``d_*``), mode 0: ``ou[t] += w B``; mode 3: ``od[t] += w B``;
    * upper fine blocks ``B`` (fine blocks ``(i, j)`` and ``(j, i) = B^T``; ``u_*``), mode 0:
      ``ou[t] += w B`` (``I < J``); 1: ``ou[t] += w B^T`` (``I > J``: the stored coarse block is ``(J, I)``);
      2: ``od[t] += w (B + B^T)`` (``I = J``).
    """
    od[:] = 0.0
    ou[:] = 0.0
    for s in range(len(d_ptr) - 1):
        o = 9 * s
        for e in range(d_ptr[s], d_ptr[s + 1]):
            t = 9 * (d_dst[e] >> 2)
            w = d_w[e]
            if d_dst[e] & 3 == 3:
                for k in range(9):
                    od[t + k] += w * sd[o + k]
            else:
                for k in range(9):
                    ou[t + k] += w * sd[o + k]
    for s in range(len(u_ptr) - 1):
        o = 9 * s
        for e in range(u_ptr[s], u_ptr[s + 1]):
            t = 9 * (u_dst[e] >> 2)
            w = u_w[e]
            m = u_dst[e] & 3
            if m == 0:
                for k in range(9):
                    ou[t + k] += w * su[o + k]
            elif m == 1:
                for a in range(3):
                    for b in range(3):
                        ou[t + 3 * a + b] += w * su[o + 3 * b + a]
            else:
                for a in range(3):
                    for b in range(3):
                        od[t + 3 * a + b] += w * (su[o + 3 * a + b] + su[o + 3 * b + a])


@njit(cache=True, fastmath={"contract"}, parallel=True)
def pgalerkin(sd, su, od, ou, d_src, d_dst, d_w, d_cb, u_src, u_dst, u_w, u_cb):
    """:func:`galerkin` on threads. Chunk ``k`` owns a range of the coarse rows and adds, to the blocks of its
    rows, their entries in the order the serial kernel adds them: the entry lists come in that order
    (:func:`implicit_cloth.solvers.multigrid.galerkin_sequence`: chunk by chunk, ascending within one, the
    diagonal list's before the upper list's; ``*_src``: each entry's source block; chunk ``k`` is
    ``*_cb[k]:*_cb[k + 1]``): every coarse block is the same sum, in the same order, as serially, whatever the
    thread count."""
    od[:] = 0.0
    ou[:] = 0.0
    for k in prange(len(d_cb) - 1):
        for q in range(d_cb[k], d_cb[k + 1]):
            gal_add(sd[9 * d_src[q]:9 * d_src[q] + 9], d_dst[q], d_w[q], od, ou)
        for q in range(u_cb[k], u_cb[k + 1]):
            gal_add(su[9 * u_src[q]:9 * u_src[q] + 9], u_dst[q], u_w[q], od, ou)


@njit(cache=True, fastmath={"contract"}, inline="always")
def gal_add(B, dst, w, od, ou):
    """One Galerkin entry of :func:`galerkin`: the flat block ``B`` times ``w`` into the coarse block and way
    packed in ``dst = 4 t + mode``."""
    t = 9 * (dst >> 2)
    m = dst & 3
    if m == 3:
        for k in range(9):
            od[t + k] += w * B[k]
    elif m == 0:
        for k in range(9):
            ou[t + k] += w * B[k]
    elif m == 1:
        for a in range(3):
            for b in range(3):
                ou[t + 3 * a + b] += w * B[3 * b + a]
    else:
        for a in range(3):
            for b in range(3):
                od[t + 3 * a + b] += w * (B[3 * a + b] + B[3 * b + a])


@njit(cache=True, fastmath={"contract"}, inline="always")
def filter_delta(src, s, Sc, ci, cj, diag, out):
    """``out = filtered - unfiltered`` of the flat block ``s`` of ``src`` (:func:`filtered_block`): what a block
    touching a constrained vertex adds to the Galerkin product of the unfiltered matrix."""
    filtered_block(src, 9 * s, Sc, ci, cj, diag, out)
    for k in range(9):
        out[k] -= src[9 * s + k]


@njit(cache=True, fastmath={"contract"})
def galerkin_filter(sd, su, od, ou, d_ptr, d_dst, d_w, u_ptr, u_dst, u_w, cpos, Sc, fuI, fuJ, td, tu):
    """After :func:`galerkin` of the unfiltered fine matrix: the correction that makes it the product of the
    Baraff-Witkin filtered matrix ``S A S + (I - S)``, from the few fine blocks touching a constrained vertex
    (diagonal blocks ``td``, upper blocks ``tu``; ``cpos[i]``: vertex i's position in the filters ``Sc``, -1
    free; ``fuI``, ``fuJ``: the upper blocks' vertices). Each such block adds ``filtered - unfiltered``
    through its own Galerkin entries: no per-filter set-up, no copy of the fine matrix."""
    B = np.empty(9)
    for q in range(len(td)):
        s = td[q]
        filter_delta(sd, s, Sc, cpos[s], cpos[s], True, B)
        for e in range(d_ptr[s], d_ptr[s + 1]):
            gal_add(B, d_dst[e], d_w[e], od, ou)
    for q in range(len(tu)):
        s = tu[q]
        filter_delta(su, s, Sc, cpos[fuI[s]], cpos[fuJ[s]], False, B)
        for e in range(u_ptr[s], u_ptr[s + 1]):
            gal_add(B, u_dst[e], u_w[e], od, ou)


#: :func:`implicit_cloth.solvers.pcg.current_error_estimate`, compiled: the one definition in :mod:`.estimate`
error_estimate = njit(cache=True)(estimate.error_estimate)


@njit(cache=True)
def gather_blocks(src, idx, out):
    """``out[k] = src[idx[k]]`` for flat arrays of 3x3 blocks (9 numbers each)."""
    for k in range(len(idx)):
        s = 9 * idx[k]
        t = 9 * k
        for m in range(9):
            out[t + m] = src[s + m]


@njit(cache=True, parallel=True)
def pgather_blocks(src, idx, out):
    """:func:`gather_blocks` on threads (a copy: the same numbers)."""
    for k in prange(len(idx)):
        s = 9 * idx[k]
        t = 9 * k
        for m in range(9):
            out[t + m] = src[s + m]


@njit(cache=True, error_model="numpy")
def inv3(B, out):
    """Inverses of flat 3x3 blocks by the adjugate, as :func:`implicit_cloth.solvers.blocks.inv3` (a singular
    block gives inf/nan, which the solve then reports, rather than an exception)."""
    for k in range(len(B) // 9):
        o = 9 * k
        a, b, c = B[o], B[o + 1], B[o + 2]
        d, e, f = B[o + 3], B[o + 4], B[o + 5]
        g, h, i = B[o + 6], B[o + 7], B[o + 8]
        c00 = e * i - f * h
        c10 = f * g - d * i
        c20 = d * h - e * g
        det = a * c00 + b * c10 + c * c20
        out[o] = c00 / det
        out[o + 1] = (c * h - b * i) / det
        out[o + 2] = (b * f - c * e) / det
        out[o + 3] = c10 / det
        out[o + 4] = (a * i - c * g) / det
        out[o + 5] = (c * d - a * f) / det
        out[o + 6] = c20 / det
        out[o + 7] = (b * g - a * h) / det
        out[o + 8] = (a * e - b * d) / det
