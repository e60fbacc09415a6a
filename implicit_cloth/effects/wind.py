"""Wind: the velocity field of the air, m/s.

The wind has no force of its own: air drag (:mod:`implicit_cloth.effects.drag`)
acts on the cloth's velocity *relative* to the wind.
"""

from __future__ import annotations

import numpy as np


class ConstantWind:
    """A uniform, steady wind velocity ``w`` (m/s)."""

    name = "wind"

    def __init__(self, velocity) -> None:
        self.w = np.asarray(velocity, dtype=float)

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        """Air velocity at the points ``x`` (N, 3) and time ``t``, m/s (broadcastable to x)."""
        return self.w
