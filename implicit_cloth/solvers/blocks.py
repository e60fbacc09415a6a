"""Small helpers for 3x3 block operators."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def inv3(B: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3x3 matrices (N, 3, 3) by the adjugate (twice as fast as ``np.linalg.inv``)."""
    a, b, c = B[:, 0, 0], B[:, 0, 1], B[:, 0, 2]
    d, e, f = B[:, 1, 0], B[:, 1, 1], B[:, 1, 2]
    g, h, i = B[:, 2, 0], B[:, 2, 1], B[:, 2, 2]
    out = np.empty_like(B)
    out[:, 0, 0] = e * i - f * h
    out[:, 0, 1] = c * h - b * i
    out[:, 0, 2] = b * f - c * e
    out[:, 1, 0] = f * g - d * i
    out[:, 1, 1] = a * i - c * g
    out[:, 1, 2] = c * d - a * f
    out[:, 2, 0] = d * h - e * g
    out[:, 2, 1] = b * g - a * h
    out[:, 2, 2] = a * e - b * d
    det = a * out[:, 0, 0] + b * out[:, 1, 0] + c * out[:, 2, 0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):   # a singular (overflowed) block gives
        out /= det[:, None, None]                                           # inf/nan, which the solve reports
    return out


def block_diagonal_operator(n: int) -> sp.csr_array:
    """A (3n, 3n) CSR matrix with the pattern of n dense 3x3 diagonal blocks (values zero, row-major)."""
    cols = 3 * np.repeat(np.arange(n), 9) + np.tile(np.arange(3), 3 * n)
    return sp.csr_array((np.zeros(9 * n), cols, np.arange(0, 9 * n + 1, 3)), shape=(3 * n, 3 * n))
