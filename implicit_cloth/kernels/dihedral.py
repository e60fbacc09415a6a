"""Compiled (numba) dihedral bending: :class:`implicit_cloth.effects.dihedral.Dihedral`'s force, ``(dF/dx) w`` and
Gauss-Newton blocks in one pass over the hinges.

The same equations as the numpy reference (see :mod:`implicit_cloth.effects.dihedral`: ``theta`` by atan2,
energy ``B w (theta - theta_0)^2 / 2``, blocks ``(c_x B + c_v B_d) w g g^T``), per hinge in order; only the
order of the sums differs from numpy's (tested equal to round-off). Serial. Compiled with ``cache=True``.
Importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def dihedral_pass(x, v, w, with_w, damped, with_blocks, hinges, weight, theta0, k, kd, tiny_e, tiny_n, c_x, c_v,
                  bidx, blocks, kw, f):
    """One pass over the hinges: the force into ``f``, ``-(K w)`` into ``kw`` (``with_w``), the blocks
    ``(c_x B + c_v B_d) w g g^T`` into ``blocks`` (``with_blocks``; hinge ``e``'s pair ``(i, j)`` at
    ``bidx[e, 4 i + j]``).

    Parameters
    ----------
    x, v, w : (N, 3) float arrays
        Positions (m), velocities (m/s), the vector multiplied by ``dF/dx``.
    damped : bool
        Whether to add the damping force (``v`` unused otherwise).
    hinges : (H, 4) int array
        ``(x_0, x_1, x_2, x_3)``: the edge and the two wings.
    weight, theta0, k, kd, tiny_e, tiny_n : (H,) float arrays
        ``|e_0|^2 / A_e``, rest angles (rad), ``B`` (N m), ``B_d`` (N m s), and the squared edge length and
        doubled areas below which a hinge is degenerate.
    """
    Bk = blocks.reshape(-1)
    e = np.empty(3)
    a = np.empty(3)
    b = np.empty(3)
    n1 = np.empty(3)
    n2 = np.empty(3)
    g = np.empty((4, 3))
    for h in range(hinges.shape[0]):
        p0 = hinges[h, 0]
        p1 = hinges[h, 1]
        p2 = hinges[h, 2]
        p3 = hinges[h, 3]
        for c in range(3):
            e[c] = x[p1, c] - x[p0, c]
            a[c] = x[p2, c] - x[p0, c]
            b[c] = x[p3, c] - x[p0, c]
        _cross(e, a, n1)
        _cross(b, e, n2)
        ee = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
        q1 = n1[0] * n1[0] + n1[1] * n1[1] + n1[2] * n1[2]
        q2 = n2[0] * n2[0] + n2[1] * n2[1] + n2[2] * n2[2]
        if not (ee > tiny_e[h] and q1 > tiny_n[h] and q2 > tiny_n[h]):
            continue
        le = math.sqrt(ee)
        cx = n1[1] * n2[2] - n1[2] * n2[1]
        cy = n1[2] * n2[0] - n1[0] * n2[2]
        cz = n1[0] * n2[1] - n1[1] * n2[0]
        sin = (cx * e[0] + cy * e[1] + cz * e[2]) / le
        cos = n1[0] * n2[0] + n1[1] * n2[1] + n1[2] * n2[2]
        d = math.atan2(sin, cos) - theta0[h]
        d = math.pi - ((math.pi - d) % (2.0 * math.pi))
        s1 = (a[0] * e[0] + a[1] * e[1] + a[2] * e[2]) / ee
        s2 = (b[0] * e[0] + b[1] * e[1] + b[2] * e[2]) / ee
        for c in range(3):
            g2 = -le / q1 * n1[c]
            g3 = -le / q2 * n2[c]
            g[2, c] = g2
            g[3, c] = g3
            g[0, c] = -(1.0 - s1) * g2 - (1.0 - s2) * g3
            g[1, c] = -s1 * g2 - s2 * g3
        s = k[h] * d
        if damped:
            s += kd[h] * _dot4(g, v, hinges, h)
        _scatter(f, g, hinges, h, -s * weight[h])
        if with_blocks:
            _add_blocks(Bk, bidx, h, g, (c_x * k[h] + c_v * kd[h]) * weight[h])
        if with_w:
            _scatter(kw, g, hinges, h, -k[h] * weight[h] * _dot4(g, w, hinges, h))


@njit(cache=True, inline="always")
def _dot4(g, v, hinges, h):
    """``sum_m g_m . v[hinges[h, m]]``."""
    r = 0.0
    for m in range(4):
        p = hinges[h, m]
        for c in range(3):
            r += g[m, c] * v[p, c]
    return r


@njit(cache=True, inline="always")
def _scatter(out, g, hinges, h, s):
    """``out[hinges[h, m]] += s g_m``."""
    for m in range(4):
        p = hinges[h, m]
        for c in range(3):
            out[p, c] += s * g[m, c]


@njit(cache=True, inline="always")
def _add_blocks(Bk, bidx, h, g, sb):
    """Hinge ``h``'s blocks ``sb g_i g_j^T``."""
    for i in range(4):
        for j in range(4):
            q = 9 * bidx[h, 4 * i + j]
            for r1 in range(3):
                for r2 in range(3):
                    Bk[q + 3 * r1 + r2] += sb * g[i, r1] * g[j, r2]


@njit(cache=True, inline="always")
def _cross(u, v, out):
    out[0] = u[1] * v[2] - u[2] * v[1]
    out[1] = u[2] * v[0] - u[0] * v[2]
    out[2] = u[0] * v[1] - u[1] * v[0]
