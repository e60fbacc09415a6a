"""Compiled (numba) strain limiting: the passes of :meth:`implicit_cloth.backend.Backend.limit_strain`.

The same Gauss-Seidel-by-colour-classes projection as the numpy reference (module docstring of
:mod:`implicit_cloth.strain_limit`), spring by spring: the springs of one class share no vertex, so
visiting them one after the other gives what the numpy path's one vectorised update per class gives. A
pass marks the springs outside their bounds from the positions at its start, corrects those of each class in
turn (the excess taken from the current positions, corrected only while still outside), then puts every
contact vertex below its plane back on it. Single-threaded; ``cache=True``. Importing this module imports
numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .springs import spring_vector


@njit(cache=True)
def limit_passes(x, si, sj, lower, limit, share_i, share_j, order, over, tolerance, max_passes, ci, cn, co, pushed):
    """Strain-limit ``x`` in place; returns ``(passes, springs outside their bounds before the first pass)``.

    ``lower``, ``limit``: the shortest (0: no bound) and longest length each spring may take; ``order``: the
    springs class after class; ``over``: a bool work array of one entry per spring;
    ``ci``, ``cn``, ``co``: contact vertices, normals and offsets (``n . x >= offset``), empty for none;
    ``pushed`` (one per contact, zeroed by the caller): how far each plane pushed its vertex, summed over passes.
    """
    n_s = len(si)
    first = 0
    passes = 0
    for it in range(max_passes):
        count = 0
        for s in range(n_s):
            l = spring_vector(x, si[s], sj[s])[3]
            o = (l - limit[s] > tolerance * limit[s]) or (lower[s] - l > tolerance * limit[s])
            over[s] = o
            if o:
                count += 1
        if it == 0:
            first = count
        if count == 0:
            break
        passes += 1
        for k in range(len(order)):
            s = order[k]
            if not over[s]:
                continue
            i = si[s]
            j = sj[s]
            d0, d1, d2, l = spring_vector(x, i, j)
            e = l - limit[s]
            if e <= 0.0:
                e = l - lower[s]
                if e >= 0.0:
                    continue
            c = e / max(l, 2.2250738585072014e-308)
            c0 = c * d0
            c1 = c * d1
            c2 = c * d2
            x[i, 0] += share_i[s] * c0
            x[i, 1] += share_i[s] * c1
            x[i, 2] += share_i[s] * c2
            x[j, 0] -= share_j[s] * c0
            x[j, 1] -= share_j[s] * c1
            x[j, 2] -= share_j[s] * c2
        for k in range(len(ci)):
            v = ci[k]
            below = co[k] - (cn[k, 0] * x[v, 0] + cn[k, 1] * x[v, 1] + cn[k, 2] * x[v, 2])
            if below > 0.0:
                x[v, 0] += below * cn[k, 0]
                x[v, 1] += below * cn[k, 1]
                x[v, 2] += below * cn[k, 2]
                pushed[k] += below
    return passes, first


def empty_planes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """No contact planes, typed for :func:`limit_passes`."""
    return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
