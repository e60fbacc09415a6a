"""Compiled (numba) membrane: :class:`implicit_cloth.effects.membrane.Membrane`'s force, ``(dF/dx) w`` and
Hessian blocks in one pass over the triangles.

The same equations as the numpy reference (see :mod:`implicit_cloth.effects.membrane`: BW98's stretch and
shear conditions, energy per rest area ``k C^2 / 2``, the clamped stretch and Gauss-Newton shear blocks, or
the exact ones), per triangle in order; only the order of the sums differs from numpy's (tested equal to
round-off). Serial: the membrane is assembled on one thread at every size. Compiled with ``cache=True``.
Importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def membrane_pass(x, v, w, with_w, damped, with_blocks, exact, faces, b, c, area, k, kd, tiny, c_x, c_v, bidx,
                  blocks, kw, f):
    """One pass over the triangles: the force into ``f``, ``-(K w)`` into ``kw`` (``with_w``), the blocks
    ``c_x K + c_v D`` into ``blocks`` (``with_blocks``; triangle ``t``'s corner pair ``(i, j)`` at
    ``bidx[t, 3 i + j]``).

    Parameters
    ----------
    x, v, w : (N, 3) float arrays
        Positions (m), velocities (m/s), the vector multiplied by ``dF/dx``.
    damped : bool
        Whether to add the damping force (``v`` unused otherwise).
    exact : bool
        The exact Hessian instead of the clamped stretch / Gauss-Newton shear one.
    faces : (T, 3) int array; b, c : (T, 3) float arrays
        The triangles and the weights of ``w_u = sum b_k x_k``, ``w_v = sum c_k x_k``.
    area : (T,) float array
        Rest areas, m^2.
    k, kd : (T, 3) float arrays
        Stiffness (N/m) and damping (N*s/m) of the conditions u, v, shear.
    """
    B = blocks.reshape(-1)
    wu = np.empty(3)
    wv = np.empty(3)
    nu = np.empty(3)
    nv = np.empty(3)
    g = np.empty((3, 3))
    Qu = np.empty((3, 3))
    Qv = np.empty((3, 3))
    Ku = np.empty((3, 3))
    Kv = np.empty((3, 3))
    bw = np.empty(3)
    cw = np.empty(3)
    for t in range(faces.shape[0]):
        A = area[t]
        for a in range(3):
            su = 0.0
            sv = 0.0
            for m in range(3):
                su += b[t, m] * x[faces[t, m], a]
                sv += c[t, m] * x[faces[t, m], a]
            wu[a] = su
            wv[a] = sv
        lu = math.sqrt(wu[0] * wu[0] + wu[1] * wu[1] + wu[2] * wu[2])
        lv = math.sqrt(wv[0] * wv[0] + wv[1] * wv[1] + wv[2] * wv[2])
        iu = 1.0 / lu if lu > tiny else 0.0
        iv = 1.0 / lv if lv > tiny else 0.0
        for a in range(3):
            nu[a] = wu[a] * iu
            nv[a] = wv[a] * iv
        Cu = lu - 1.0
        Cv = lv - 1.0
        Cs = wu[0] * wv[0] + wu[1] * wv[1] + wu[2] * wv[2]
        for m in range(3):
            for a in range(3):
                g[m, a] = b[t, m] * wv[a] + c[t, m] * wu[a]
        su = k[t, 0] * Cu
        sv = k[t, 1] * Cv
        ss = k[t, 2] * Cs
        if damped:
            ru, rv, rs = _rates(v, faces, t, b, c, nu, nv, g)
            su += kd[t, 0] * ru
            sv += kd[t, 1] * rv
            ss += kd[t, 2] * rs
        for m in range(3):
            p = faces[t, m]
            for a in range(3):
                f[p, a] -= A * (su * b[t, m] * nu[a] + sv * c[t, m] * nv[a] + ss * g[m, a])
        if not (with_blocks or with_w):
            continue
        _stretch_blocks(Ku, Qu, k[t, 0], kd[t, 0], lu, iu, nu, tiny, exact, c_x, c_v)
        _stretch_blocks(Kv, Qv, k[t, 1], kd[t, 1], lv, iv, nv, tiny, exact, c_x, c_v)
        if with_blocks:
            _add_blocks(B, bidx, t, b, c, A, Qu, Qv, g, c_x * k[t, 2] + c_v * kd[t, 2], c_x * k[t, 2] * Cs if exact
                        else 0.0)
        if with_w:
            _add_kw(kw, w, faces, t, b, c, A, Ku, Kv, g, k[t, 2], k[t, 2] * Cs if exact else 0.0, bw, cw)


@njit(cache=True, inline="always")
def _rates(v, faces, t, b, c, nu, nv, g):
    """``(Cdot_u, Cdot_v, Cdot_s)`` of triangle ``t``, 1/s."""
    ru = 0.0
    rv = 0.0
    rs = 0.0
    for m in range(3):
        p = faces[t, m]
        for a in range(3):
            ru += b[t, m] * v[p, a] * nu[a]
            rv += c[t, m] * v[p, a] * nv[a]
            rs += g[m, a] * v[p, a]
    return ru, rv, rs


@njit(cache=True, inline="always")
def _stretch_blocks(K, Q, ks, kds, l, inv, n, tiny, exact, c_x, c_v):
    """One thread's ``K = ks (a I + (1 - a) n n^T)`` (``a = 1 - 1/|w|``, clamped at 0 unless ``exact``) and
    ``Q = c_x K + c_v kds n n^T``."""
    a = 1.0 - inv if l > tiny else 0.0
    if not exact:
        a = max(a, 0.0)
    for i in range(3):
        for j in range(3):
            K[i, j] = ks * ((a if i == j else 0.0) + (1.0 - a) * n[i] * n[j])
            Q[i, j] = c_x * K[i, j] + c_v * kds * n[i] * n[j]


@njit(cache=True, inline="always")
def _add_blocks(B, bidx, t, b, c, A, Qu, Qv, g, gs, ex):
    """Triangle ``t``'s blocks ``A (b_i b_j Qu + c_i c_j Qv + gs g_i g_j^T + ex (b_i c_j + c_i b_j) I)``."""
    for i in range(3):
        for j in range(3):
            bb = b[t, i] * b[t, j]
            cc = c[t, i] * c[t, j]
            q = 9 * bidx[t, 3 * i + j]
            e = ex * (b[t, i] * c[t, j] + c[t, i] * b[t, j])
            for a in range(3):
                for d in range(3):
                    val = bb * Qu[a, d] + cc * Qv[a, d] + gs * g[i, a] * g[j, d]
                    if a == d:
                        val += e
                    B[q + 3 * a + d] += A * val


@njit(cache=True, inline="always")
def _add_kw(kw, w, faces, t, b, c, A, Ku, Kv, g, ks, ex, bw, cw):
    """``kw -= K w`` for triangle ``t``: ``A (b_i Ku (sum b_j w_j) + c_i Kv (sum c_j w_j) + ks g_i (g . w)
    + ex (b_i sum c_j w_j + c_i sum b_j w_j))``; ``bw``, ``cw``: scratch (3,)."""
    bw[:] = 0.0
    cw[:] = 0.0
    gw = 0.0
    for m in range(3):
        p = faces[t, m]
        for a in range(3):
            bw[a] += b[t, m] * w[p, a]
            cw[a] += c[t, m] * w[p, a]
            gw += g[m, a] * w[p, a]
    for i in range(3):
        p = faces[t, i]
        for a in range(3):
            val = (b[t, i] * (Ku[a, 0] * bw[0] + Ku[a, 1] * bw[1] + Ku[a, 2] * bw[2])
                   + c[t, i] * (Kv[a, 0] * cw[0] + Kv[a, 1] * cw[1] + Kv[a, 2] * cw[2])
                   + ks * g[i, a] * gw + ex * (b[t, i] * cw[a] + c[t, i] * bw[a]))
            kw[p, a] -= A * val
