"""Compiled (numba) kernels of the multigrid-preconditioned filtered PCG: the optional accelerator.

Same algorithm, same arithmetic order up to floating-point reassociation, as
the numpy reference path (:func:`implicit_cloth.solvers.pcg.filtered_pcg` with
:class:`implicit_cloth.solvers.multigrid.Multigrid`), fused so that one CG
iteration makes about four passes over the matrix data (the product ``A p``,
the V-cycle's pre- and post-smoothing residuals on every level) and no Python
call per vector operation:

* matrices are kept as 3x3 block rows (``bptr``, ``bcol``, ``vals`` of shape
  (n_blocks, 3, 3)): 80 bytes a block against 108 for scalar CSR;
* the Baraff-Witkin filter is applied on the fly: block ``(i, j)`` of the
  filtered matrix is ``S_i A_ij S_j + delta_ij (I - S_i)``, with ``cidx[i]``
  the index of vertex i's filter in ``Sc`` (-1 for a free vertex), so the
  unfiltered fine blocks are never copied;
* each level's residual and its damped block-Jacobi post-smoothing are one
  pass over the block rows each; restriction and prolongation are gathers
  through the node-level ``P^T`` and ``P`` (CSR, acting on 3-vectors);
* the coarsest level is solved with the upper Cholesky factor ``U``
  (``A_c = U^T U``), or a dense inverse when no factor is available;
* CG's vector updates, dot products and the error estimate of the stopping
  rule are fused loops.

Floating-point contraction (fused multiply-add) is allowed (``fastmath={"contract"}``:
no reassociation, NaN and infinity kept): the V-cycle got 12-18 % faster at 128².

Every function is compiled with ``cache=True`` (the compiled code is stored
next to this file in ``__pycache__``), so the compilation (25-50 s on the
2-core test machine) is paid once per installation, not per run.
Single-threaded: a multi-threaded variant (``prange``, two threads) was
measured 1.3-14x *slower* per step on the shared 2-core machine and dropped.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
def _row(bptr, bcol, vals, cidx, Sc, filtered, x, i):
    """Block row ``i`` of ``A x`` (of ``S A S x + (I - S) x`` with ``filtered``), as three numbers."""
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    for k in range(bptr[i], bptr[i + 1]):
        j = bcol[k]
        x0 = x[3 * j]
        x1 = x[3 * j + 1]
        x2 = x[3 * j + 2]
        if filtered and cidx[j] >= 0:
            x0, x1, x2 = _filt3(Sc, cidx[j], x0, x1, x2)
        v = vals[k]
        a0 += v[0, 0] * x0 + v[0, 1] * x1 + v[0, 2] * x2
        a1 += v[1, 0] * x0 + v[1, 1] * x1 + v[1, 2] * x2
        a2 += v[2, 0] * x0 + v[2, 1] * x1 + v[2, 2] * x2
    if filtered and cidx[i] >= 0:
        c = cidx[i]
        xi0, xi1, xi2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]
        a0, a1, a2 = _filt3(Sc, c, a0, a1, a2)
        s0, s1, s2 = _filt3(Sc, c, xi0, xi1, xi2)
        a0 += xi0 - s0
        a1 += xi1 - s1
        a2 += xi2 - s2
    return a0, a1, a2


@njit(cache=True, fastmath={"contract"})
def _matvec(bptr, bcol, vals, cidx, Sc, filtered, x, y):
    """``y = A x``; with ``filtered``: ``y = S A S x + (I - S) x`` (the filtered matrix of the module docstring)."""
    for i in range(len(bptr) - 1):
        a0, a1, a2 = _row(bptr, bcol, vals, cidx, Sc, filtered, x, i)
        y[3 * i] = a0
        y[3 * i + 1] = a1
        y[3 * i + 2] = a2


@njit(cache=True, fastmath={"contract"})
def _presmooth(dinv, omega, b, x):
    """Pre-smoothing from zero: ``x = omega D^-1 b``."""
    n = len(dinv)
    for i in range(n):
        d = dinv[i]
        b0, b1, b2 = b[3 * i], b[3 * i + 1], b[3 * i + 2]
        x[3 * i] = omega * (d[0, 0] * b0 + d[0, 1] * b1 + d[0, 2] * b2)
        x[3 * i + 1] = omega * (d[1, 0] * b0 + d[1, 1] * b1 + d[1, 2] * b2)
        x[3 * i + 2] = omega * (d[2, 0] * b0 + d[2, 1] * b1 + d[2, 2] * b2)


@njit(cache=True, fastmath={"contract"})
def _residual(bptr, bcol, vals, cidx, Sc, filtered, b, x, r):
    """``r = b - A x`` (``A`` filtered as in :func:`_matvec` when ``filtered``)."""
    for i in range(len(bptr) - 1):
        a0, a1, a2 = _row(bptr, bcol, vals, cidx, Sc, filtered, x, i)
        r[3 * i] = b[3 * i] - a0
        r[3 * i + 1] = b[3 * i + 1] - a1
        r[3 * i + 2] = b[3 * i + 2] - a2


@njit(cache=True, fastmath={"contract"})
def _transfer(ptr, idx, val, x, y, add):
    """``y (+)= M x`` for a node-level CSR ``M`` (``P`` to prolong, ``P^T`` to restrict) acting on 3-vectors."""
    n = len(ptr) - 1
    for i in range(n):
        y0 = 0.0
        y1 = 0.0
        y2 = 0.0
        for m in range(ptr[i], ptr[i + 1]):
            J = idx[m]
            w = val[m]
            y0 += w * x[3 * J]
            y1 += w * x[3 * J + 1]
            y2 += w * x[3 * J + 2]
        if add:
            y[3 * i] += y0
            y[3 * i + 1] += y1
            y[3 * i + 2] += y2
        else:
            y[3 * i] = y0
            y[3 * i + 1] = y1
            y[3 * i + 2] = y2


@njit(cache=True, fastmath={"contract"})
def _postsmooth(bptr, bcol, vals, cidx, Sc, filtered, dinv, omega, b, x, y):
    """Post-smoothing: ``y = x + omega D^-1 (b - A x)`` (``y`` may alias ``b``, not ``x``)."""
    for i in range(len(bptr) - 1):
        a0, a1, a2 = _row(bptr, bcol, vals, cidx, Sc, filtered, x, i)
        xi0, xi1, xi2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]
        r0 = b[3 * i] - a0
        r1 = b[3 * i + 1] - a1
        r2 = b[3 * i + 2] - a2
        d = dinv[i]
        y[3 * i] = xi0 + omega * (d[0, 0] * r0 + d[0, 1] * r1 + d[0, 2] * r2)
        y[3 * i + 1] = xi1 + omega * (d[1, 0] * r0 + d[1, 1] * r1 + d[1, 2] * r2)
        y[3 * i + 2] = xi2 + omega * (d[2, 0] * r0 + d[2, 1] * r1 + d[2, 2] * r2)


@njit(cache=True, fastmath={"contract"})
def _dot2(p, q):
    """``(p.q, p.p)``."""
    pq = 0.0
    pp = 0.0
    for k in range(len(p)):
        pq += p[k] * q[k]
        pp += p[k] * p[k]
    return pq, pp


@njit(cache=True, fastmath={"contract"})
def _dot(a, b):
    s = 0.0
    for k in range(len(a)):
        s += a[k] * b[k]
    return s


@njit(cache=True, fastmath={"contract"})
def _cg_update(dv, r, p, q, alpha, mass, use_mass):
    """``dv += alpha p``, ``r -= alpha q``; returns ``(dv.dv, r.M^-1 r, dv.M dv)`` (the last two with ``use_mass``)."""
    dd = 0.0
    rmr = 0.0
    dmd = 0.0
    for k in range(len(dv)):
        d = dv[k] + alpha * p[k]
        rk = r[k] - alpha * q[k]
        dv[k] = d
        r[k] = rk
        dd += d * d
        if use_mass:
            rmr += rk * rk / mass[k]
            dmd += d * d * mass[k]
    return dd, rmr, dmd


@njit(cache=True, fastmath={"contract"})
def _p_update(p, s, beta):
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
def _level(l, bptr0, bcol0, vals0, lbptr, lbcol, lvals, rowoff, blkoff, voff):
    """Block rows of level l: the fine arrays for l = 0, views into the packed coarse ones otherwise."""
    if l == 0:
        return bptr0, bcol0, vals0
    n = voff[l + 1] - voff[l]
    return (lbptr[rowoff[l]:rowoff[l] + n + 1], lbcol[blkoff[l]:blkoff[l + 1]], lvals[blkoff[l]:blkoff[l + 1]])


@njit(cache=True, fastmath={"contract"})
def vcycle(b, out, bptr0, bcol0, vals0, cidx, Sc,
           lbptr, lbcol, lvals, rowoff, blkoff, dinv, voff, pptr, pidx, pval, poff, pnnz,
           tptr, tidx, tval, toff, C, upper, omega, wb, wx, wr):
    """One V-cycle of the filtered hierarchy: ``out = M^-1 b`` (``b`` the fine residual).

    Level l (0 finest, L = len(voff) - 2 coarsest) has ``n_l = voff[l+1] - voff[l]``
    vertices; its vectors live at ``3 voff[l]`` in the work arrays ``wb`` (right-hand
    sides), ``wx`` (iterates) and ``wr`` (residuals, then smoothed iterates). Coarse
    level l >= 1 has block rows ``lbptr[rowoff[l]:rowoff[l] + n_l + 1]`` (local),
    blocks ``blkoff[l]:blkoff[l+1]`` of ``lbcol``/``lvals``. The prolongation
    l -> l+1 has rows ``pptr[poff[l]:poff[l] + n_l + 1]`` (local), entries
    ``pnnz[l]:pnnz[l+1]`` of ``pidx``/``pval``; its transpose likewise in ``t*``
    (rows ``toff[l]:toff[l] + n_{l+1} + 1``, the same entry range).
    ``dinv[voff[l]:voff[l+1]]`` are level l's inverted (filtered) diagonal blocks.
    """
    L = len(voff) - 2
    if L == 0:                                         # a single level: solved directly
        _coarse_solve(C, upper, b, out)
        return
    for l in range(L):
        n = voff[l + 1] - voff[l]
        nc = voff[l + 2] - voff[l + 1]
        bp, bc, bv = _level(l, bptr0, bcol0, vals0, lbptr, lbcol, lvals, rowoff, blkoff, voff)
        bl = b if l == 0 else wb[3 * voff[l]:3 * voff[l + 1]]
        x = wx[3 * voff[l]:3 * voff[l + 1]]
        r = wr[3 * voff[l]:3 * voff[l + 1]]
        d = dinv[voff[l]:voff[l + 1]]
        tp = tptr[toff[l]:toff[l] + nc + 1]
        ti = tidx[pnnz[l]:pnnz[l + 1]]
        tv = tval[pnnz[l]:pnnz[l + 1]]
        _presmooth(d, omega, bl, x)
        _residual(bp, bc, bv, cidx, Sc, l == 0, bl, x, r)
        _transfer(tp, ti, tv, r, wb[3 * voff[l + 1]:3 * voff[l + 2]], False)
    _coarse_solve(C, upper, wb[3 * voff[L]:3 * voff[L + 1]], wx[3 * voff[L]:3 * voff[L + 1]])
    for l in range(L - 1, -1, -1):
        n = voff[l + 1] - voff[l]
        bp, bc, bv = _level(l, bptr0, bcol0, vals0, lbptr, lbcol, lvals, rowoff, blkoff, voff)
        bl = b if l == 0 else wb[3 * voff[l]:3 * voff[l + 1]]
        x = wx[3 * voff[l]:3 * voff[l + 1]]
        y = out if l == 0 else wr[3 * voff[l]:3 * voff[l + 1]]
        xc = wx[3 * voff[L]:3 * voff[L + 1]] if l + 1 == L else wr[3 * voff[l + 1]:3 * voff[l + 2]]
        d = dinv[voff[l]:voff[l + 1]]
        pp = pptr[poff[l]:poff[l] + n + 1]
        pi = pidx[pnnz[l]:pnnz[l + 1]]
        pv = pval[pnnz[l]:pnnz[l + 1]]
        _transfer(pp, pi, pv, xc, x, True)
        _postsmooth(bp, bc, bv, cidx, Sc, l == 0, d, omega, bl, x, y)


@njit(cache=True, fastmath={"contract"})
def pcg(bptr0, bcol0, vals0, avals, cidx, Sc, clist,
        lbptr, lbcol, lvals, rowoff, blkoff, dinv, voff, pptr, pidx, pval, poff, pnnz,
        tptr, tidx, tval, toff, C, upper, omega,
        b, z, guess, use_guess, mass, use_mass, tol, max_iterations, bound_only, min_delay, delay_fraction):
    """The filtered PCG of :func:`implicit_cloth.solvers.pcg.filtered_pcg` with the V-cycle preconditioner.

    ``avals`` are the fine matrix's blocks (float64) used by CG; ``vals0`` its V-cycle copy.

    Returns ``(dv, iterations, residual, converged, error)``.
    """
    N = len(b)
    Ntot = 3 * voff[len(voff) - 1]
    wb = np.zeros(Ntot)
    wx = np.zeros(Ntot)
    wr = np.zeros(Ntot)
    dv = np.zeros(N)
    for c in range(len(clist)):                        # dv = (I - S) z
        i = clist[c]
        z0, z1, z2 = z[3 * i], z[3 * i + 1], z[3 * i + 2]
        s0, s1, s2 = _filt3(Sc, c, z0, z1, z2)
        dv[3 * i], dv[3 * i + 1], dv[3 * i + 2] = z0 - s0, z1 - s1, z2 - s2
    r = np.empty(N)
    _residual(bptr0, bcol0, avals, cidx, Sc, False, b, dv, r)
    filter_vec(clist, Sc, r)
    norm0 = np.sqrt(_dot(r, r))
    if use_guess:
        g = guess.copy()
        filter_vec(clist, Sc, g)
        dv += g
        _residual(bptr0, bcol0, avals, cidx, Sc, False, b, dv, r)
        filter_vec(clist, Sc, r)
    if norm0 == 0.0:
        return dv, 0, 0.0, True, 0.0
    s = np.empty(N)
    vcycle(r, s, bptr0, bcol0, vals0, cidx, Sc, lbptr, lbcol, lvals, rowoff, blkoff, dinv, voff,
           pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omega, wb, wx, wr)
    filter_vec(clist, Sc, s)
    p = s.copy()
    q = np.empty(N)
    delta = _dot(r, s)
    delta0 = delta
    ad = np.zeros(max_iterations)
    pw = np.zeros(max_iterations)
    converged = delta <= 0.0
    error = 0.0 if converged else np.inf
    it = 0
    while not converged and it < max_iterations:
        # p is filtered, so S A S p + (I - S) p = S A p: the filtered product
        _matvec(bptr0, bcol0, avals, cidx, Sc, True, p, q)
        pq, pp = _dot2(p, q)
        if pq <= 0.0:
            break
        alpha = delta / pq
        dd, rmr, dmd = _cg_update(dv, r, p, q, alpha, mass, use_mass)
        ad[it] = alpha * delta
        pw[it] = pp / pq
        it += 1
        vcycle(r, s, bptr0, bcol0, vals0, cidx, Sc, lbptr, lbcol, lvals, rowoff, blkoff, dinv, voff,
               pptr, pidx, pval, poff, pnnz, tptr, tidx, tval, toff, C, upper, omega, wb, wx, wr)
        filter_vec(clist, Sc, s)
        delta_new = _dot(r, s)
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
            beta = delta_new / delta
            _p_update(p, s, beta)
        delta = delta_new
    _residual(bptr0, bcol0, avals, cidx, Sc, False, b, dv, q)
    filter_vec(clist, Sc, q)
    res = np.sqrt(_dot(q, q)) / norm0
    return dv, it, res, converged, error


@njit(cache=True)
def error_estimate(ad, pw, it, dd, d):
    """:func:`implicit_cloth.solvers.pcg.current_error_estimate`, compiled: the same loops in the same order."""
    k = it
    h = max(1, d // 2)
    e2 = 0.0
    ea_next = 0.0
    for j in range(k - 1, k - d - 1, -1):
        ea = ea_next + ad[j]
        e2 += pw[j] * (ea + ea_next)
        ea_next = ea
    q = max((ad[k - 1] / ad[k - d]) ** (1.0 / (d - 1)), (ad[k - 1] / ad[k - 1 - h]) ** (1.0 / h))
    if not q < 1.0:
        return np.sqrt(e2 / max(dd, 1e-300))
    recent = 0.0
    pmax = 0.0
    for j in range(k - h, k):
        recent += ad[j]
        pmax = max(pmax, pw[j])
    qh = q ** h
    tail = recent * qh / (1.0 - qh)
    e2_now = pmax * tail * (1.0 + q) / (1.0 - q)
    return 2.0 * np.sqrt(e2_now / max(dd, 1e-300))             # pcg.ESTIMATE_SAFETY (a test checks they agree)
