"""Symplectic (semi-implicit) Euler: velocity first, then position.

``v1 = v0 + h a(x0, v0)``, ``x1 = x0 + h v1``. Free fall from rest:
``x_n = x_0 + g h^2 n (n + 1) / 2``. For an undamped oscillator of angular
frequency w it is bounded for ``h < 2 / w`` and unstable above.
"""

from __future__ import annotations

from ..constraints import Constraints
from ..model import State
from .base import Integrator, StepInfo


class SymplecticEuler(Integrator):
    name = "symplectic_euler"
    aliases: tuple[str, ...] = ("semi_implicit_euler", "semi_explicit_euler", "euler_cromer", "symplectic")

    def step(self, state: State, h: float, constraints: Constraints | None = None) -> tuple[State, StepInfo]:
        info = StepInfo()
        v1 = state.v + h * self._accel(state.x, state.v, state.t, info)
        return self._finish(state.x + h * v1, v1, state.t + h), info
