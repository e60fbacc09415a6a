"""IPC's clamped logarithmic barrier (Li et al. 2020, eq. 6) and its derivatives, vectorised.

``b(d) = -(d - dhat)^2 ln(d / dhat)`` for ``0 < d < dhat``, 0 for ``d >= dhat`` and ``+inf`` for ``d <= 0``:
C2 at ``dhat``, ``b' < 0`` (it repels) and ``b'' > 0`` on ``(0, dhat)``, so its Hessian along the contact
normal is positive and the energy grows without bound as a gap closes.
"""

from __future__ import annotations

import numpy as np


def value(d: np.ndarray, dhat: float) -> np.ndarray:
    """``b(d)`` (m^2; the caller scales it by a stiffness), ``inf`` where ``d <= 0``."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on = (d > 0) & (d < dhat)
    dd = d[on]
    out[on] = -(dd - dhat) ** 2 * np.log(dd / dhat)
    out[d <= 0] = np.inf
    return out


def first(d: np.ndarray, dhat: float) -> np.ndarray:
    """``b'(d)`` (m), <= 0; 0 at and beyond ``dhat`` (where ``d <= 0``: ``-inf``)."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on = (d > 0) & (d < dhat)
    dd = d[on]
    out[on] = -2.0 * (dd - dhat) * np.log(dd / dhat) - (dd - dhat) ** 2 / dd
    out[d <= 0] = -np.inf
    return out


def second(d: np.ndarray, dhat: float) -> np.ndarray:
    """``b''(d)`` (dimensionless), > 0 on ``(0, dhat)``, 0 beyond."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    on = (d > 0) & (d < dhat)
    dd = d[on]
    out[on] = -2.0 * np.log(dd / dhat) - 4.0 * (dd - dhat) / dd + (dd - dhat) ** 2 / dd ** 2
    out[d <= 0] = np.inf
    return out
