"""Wind: the velocity field of the air, m/s.

The wind has no force of its own: air drag (:mod:`implicit_cloth.effects.drag`)
acts on the cloth's velocity *relative* to the wind.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..config.validate import check_keys, vector
from ..errors import SceneError


def validate(path: str, value: Any) -> dict[str, Any]:
    """``effects.wind``: a table with the wind's ``velocity`` [vx, vy, vz], m/s."""
    check_keys(path, value, ("velocity",))
    if "velocity" not in value:
        raise SceneError(f"{path}.velocity", "missing (wind needs a velocity [vx, vy, vz] in m/s)")
    return {"velocity": vector(f"{path}.velocity", value["velocity"], 3)}


class ConstantWind:
    """A uniform, steady wind velocity ``w`` (m/s)."""

    name = "wind"

    def __init__(self, velocity) -> None:
        self.w = np.asarray(velocity, dtype=float)

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        """Air velocity at the points ``x`` (N, 3) and time ``t``, m/s (broadcastable to x)."""
        return self.w
