"""IPC's clamped logarithmic barrier (Li et al. 2020, eq. 6) and its derivatives, vectorised.

``b(d) = -(d - dhat)^2 ln(d / dhat)`` for ``0 < d < dhat``, 0 for ``d >= dhat`` and ``+inf`` for ``d <= 0``:
C2 at ``dhat``, ``b' < 0`` (it repels) and ``b'' > 0`` on ``(0, dhat)``, so its Hessian along the contact
normal is positive and the energy grows without bound as a gap closes.
"""

from __future__ import annotations

import numpy as np


def _reach(d: np.ndarray, dhat: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d`` as floats, where ``0 < d < dhat`` (``dhat`` a scalar or one per ``d``), and ``d``, ``dhat`` there."""
    d = np.asarray(d, dtype=float)
    dhat = np.broadcast_to(np.asarray(dhat, dtype=float), d.shape)
    on = (d > 0) & (d < dhat)
    return on, d[on], dhat[on]


def value(d: np.ndarray, dhat: float | np.ndarray) -> np.ndarray:
    """``b(d)`` (m^2; the caller scales it by a stiffness), ``inf`` where ``d <= 0``."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on, dd, dhat = _reach(d, dhat)
    out[on] = -(dd - dhat) ** 2 * np.log(dd / dhat)
    out[d <= 0] = np.inf
    return out


def first(d: np.ndarray, dhat: float | np.ndarray) -> np.ndarray:
    """``b'(d)`` (m), <= 0; 0 at and beyond ``dhat`` (where ``d <= 0``: ``-inf``)."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on, dd, dhat = _reach(d, dhat)
    out[on] = -2.0 * (dd - dhat) * np.log(dd / dhat) - (dd - dhat) ** 2 / dd
    out[d <= 0] = -np.inf
    return out


def second(d: np.ndarray, dhat: float | np.ndarray) -> np.ndarray:
    """``b''(d)`` (dimensionless), > 0 on ``(0, dhat)``, 0 beyond."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on, dd, dhat = _reach(d, dhat)
    out[on] = -2.0 * np.log(dd / dhat) - 4.0 * (dd - dhat) / dd + (dd - dhat) ** 2 / dd ** 2
    out[d <= 0] = np.inf
    return out


def equilibrium(a: np.ndarray, g_free: np.ndarray, kappa: np.ndarray, dhat: float,
                iterations: int = 60) -> np.ndarray:
    """Where a gap held by a spring toward ``g_free`` rests against the barrier: the root on ``(0, dhat)`` of
    ``a (g - g_free) + kappa b'(g)`` (``a`` N/m, ``kappa`` N/m^2; increasing in ``g``), by bisection on a log
    scale; ``dhat`` where the spring does not reach the barrier (``g_free >= dhat``)."""
    a, g_free, kappa = (np.broadcast_to(np.asarray(q, dtype=float), np.shape(g_free)) for q in (a, g_free, kappa))
    lo = np.full(np.shape(g_free), np.log(1e-12 * dhat))
    hi = np.full(np.shape(g_free), np.log(dhat))
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        g = np.exp(mid)
        above = a * (g - g_free) + kappa * first(g, dhat) > 0
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    out = np.exp(0.5 * (lo + hi))
    return np.where(g_free >= dhat, dhat, out)
