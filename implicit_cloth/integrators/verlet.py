"""Velocity Verlet, with velocity-dependent forces evaluated at the half-step velocity.

::

    v_half = v0 + (h/2) a0
    x1     = x0 + h v_half
    a1     = a(x1, v_half)            (damping and drag see the half-step velocity)
    v1     = v_half + (h/2) a1

``a1`` is reused as the next step's ``a0``, so a step costs one force
evaluation (the first step evaluates ``a(x0, v0)``). Exact for constant
acceleration (free fall: ``x = x0 + g t^2 / 2``).
"""

from __future__ import annotations

import numpy as np

from ..constraints import Constraints
from ..model import State
from .base import Integrator, StepInfo


class Verlet(Integrator):
    name = "verlet"
    aliases: tuple[str, ...] = ("velocity_verlet", "stormer_verlet", "leapfrog")

    def __init__(self, model, solver=None) -> None:
        super().__init__(model, solver)
        self._cache: tuple[State, np.ndarray] | None = None

    def reset(self) -> None:
        self._cache = None

    def step(self, state: State, h: float, constraints: Constraints | None = None) -> tuple[State, StepInfo]:
        info = StepInfo()
        if self._cache is not None and self._cache[0] is state:
            a0 = self._cache[1]
        else:
            a0 = self._accel(state.x, state.v, state.t, info)
        v_half = state.v + (0.5 * h) * a0
        x1 = state.x + h * v_half
        self.model.apply_pins(x1, v_half, state.t + h)
        a1 = self._accel(x1, v_half, state.t + h, info)
        new = self._finish(x1, v_half + (0.5 * h) * a1, state.t + h)
        self._cache = (new, a1)
        return new, info
