"""Compiled (numba) aerodynamics: :class:`implicit_cloth.effects.aerodynamics.Aerodynamics`'s force and its
``-c_v dF/dv`` blocks in one pass over the triangles.

The same equations as the numpy reference (see :mod:`implicit_cloth.effects.aerodynamics`), per triangle in
order; only the order of the sums differs from numpy's (tested equal to round-off). Serial. Compiled with
``cache=True``. Importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def aerodynamics_pass(x, v, wind, faces, c_d, c_l, tiny, with_blocks, exact, c_v, bidx, blocks, f):
    """The force into ``f`` and (``with_blocks``) ``-c_v dF_i/dv_j`` into ``blocks`` (triangle ``t``'s corner
    pair ``(i, j)`` at ``bidx[t, 3 i + j]``): the exact block with ``exact``, else its normal-normal part.

    Parameters
    ----------
    x, v : (N, 3) float arrays
        Positions (m) and velocities (m/s).
    wind : (3,) float array
        The uniform air velocity, m/s.
    faces : (T, 3) int array
    c_d, c_l : float
        ``rho C_d / 2`` and ``rho C_l / 2``, kg/m^3.
    """
    B = blocks.reshape(-1)
    n = np.empty(3)
    u = np.empty(3)
    uh = np.empty(3)
    K = np.empty((3, 3))
    third = 1.0 / 3.0
    for t in range(faces.shape[0]):
        p0 = faces[t, 0]
        p1 = faces[t, 1]
        p2 = faces[t, 2]
        e1x = x[p1, 0] - x[p0, 0]
        e1y = x[p1, 1] - x[p0, 1]
        e1z = x[p1, 2] - x[p0, 2]
        e2x = x[p2, 0] - x[p0, 0]
        e2y = x[p2, 1] - x[p0, 1]
        e2z = x[p2, 2] - x[p0, 2]
        n[0] = e1y * e2z - e1z * e2y
        n[1] = e1z * e2x - e1x * e2z
        n[2] = e1x * e2y - e1y * e2x
        L = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        iL = 1.0 / L if L > tiny else 0.0
        for d in range(3):
            n[d] *= iL
            u[d] = (v[p0, d] + v[p1, d] + v[p2, d]) * third - wind[d]
        s = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
        if not s > tiny:
            continue
        A = 0.5 * L
        a = u[0] * n[0] + u[1] * n[1] + u[2] * n[2]
        inv = 1.0 / s
        for d in range(3):
            uh[d] = u[d] * inv
        c = c_d + c_l
        for d in range(3):
            fd = -A * a * (c * s * n[d] - c_l * a * uh[d]) * third
            f[p0, d] += fd
            f[p1, d] += fd
            f[p2, d] += fd
        if not with_blocks:
            continue
        if exact:
            for i in range(3):
                for j in range(3):
                    P = (1.0 if i == j else 0.0) - uh[i] * uh[j]
                    J = (c * (a * n[i] * uh[j] + s * n[i] * n[j])
                         - c_l * (a * a * inv * P + 2.0 * a * uh[i] * n[j]))
                    K[i, j] = c_v / 9.0 * A * J
        else:
            q = 1.0 - a * a * inv * inv
            k = c_v / 9.0 * A * (c_d * (s + a * a * inv) + c_l * s * q * q)
            for i in range(3):
                for j in range(3):
                    K[i, j] = k * n[i] * n[j]
        for m in range(9):
            b = 9 * bidx[t, m]
            for i in range(3):
                for j in range(3):
                    B[b + 3 * i + j] += K[i, j]
