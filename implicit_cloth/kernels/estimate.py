"""The CG error estimate of the stopping rule, written once: plain Python that numba compiles as it is.

:func:`implicit_cloth.solvers.pcg.current_error_estimate` calls :func:`error_estimate` directly (the
numpy path); :mod:`implicit_cloth.kernels.pcg` compiles the very same function for the compiled PCG, so
the two paths cannot drift apart. It uses only scalar arithmetic, loops and ``np.sqrt``. Importing this
module does not import numba.
"""

from __future__ import annotations

import numpy as np

#: Factor on the extrapolated error of the current iterate, from measurements (see
#: :func:`implicit_cloth.solvers.pcg.filtered_pcg`, Notes, and ``benchmarks/studies/stopping_rule.py``).
ESTIMATE_SAFETY = 2.0


def error_estimate(ad, pw, it, dd, d):
    """Estimated relative Euclidean error ``|dv_k - dv*| / |dv_k|`` of the current CG iterate (k = ``it``).

    ``ad``: ``alpha_j delta_j`` of iterations j = 0 .. it-1 (the decrease of the squared A-norm error in
    iteration j); ``pw``: ``|p_j|^2 / (p_j^T A p_j)``; ``dd``: ``|dv_k|^2``; ``d >= 2``: the window (the
    rate also from its last ``d // 2``). When the window shows no convergence (rate ``q >= 1``) the
    conservative delayed estimate, the error of the iterate ``d`` iterations back.
    """
    k = it
    h = max(1, d // 2)
    # delayed estimate (Strakos & Tichy): |e_{k-d}|^2 - |e_k|^2 with |e_j|_A^2 ~ sum_{i=j}^{k-1} ad_i
    e2 = 0.0
    ea_next = 0.0
    for j in range(k - 1, k - d - 1, -1):
        ea = ea_next + ad[j]
        e2 += pw[j] * (ea + ea_next)
        ea_next = ea
    # convergence rate per iteration: the slower of the whole window's and its last h iterations'
    q = max((ad[k - 1] / ad[k - d]) ** (1.0 / (d - 1)), (ad[k - 1] / ad[k - 1 - h]) ** (1.0 / h))
    if not q < 1.0:
        return np.sqrt(e2 / max(dd, 1e-300))
    recent = 0.0
    pmax = 0.0
    for j in range(k - h, k):
        recent += ad[j]
        pmax = max(pmax, pw[j])
    qh = q ** h
    tail = recent * qh / (1.0 - qh)                     # |e_k|_A^2 = sum_{j>=k} ad_j, geometric
    e2_now = pmax * tail * (1.0 + q) / (1.0 - q)          # |e_k|^2 = sum_{j>=k} pw_j (|e_j|_A^2 + |e_j+1|_A^2)
    return ESTIMATE_SAFETY * np.sqrt(e2_now / max(dd, 1e-300))
