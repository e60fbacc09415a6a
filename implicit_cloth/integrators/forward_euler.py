"""Forward (explicit) Euler: ``x1 = x0 + h v0``, ``v1 = v0 + h a(x0, v0)``.

Free fall from rest: ``x_n = x_0 + g h^2 n (n - 1) / 2``. For an undamped
oscillator the amplitude grows by ``sqrt(1 + w^2 h^2)`` per step (always unstable).
"""

from __future__ import annotations

from ..constraints import Constraints
from ..model import State
from .base import Integrator, StepInfo


class ForwardEuler(Integrator):
    name = "forward_euler"
    aliases: tuple[str, ...] = ("explicit_euler", "euler_explicit", "euler", "explicit", "forward")

    def step(self, state: State, h: float, constraints: Constraints | None = None) -> tuple[State, StepInfo]:
        info = StepInfo()
        a = self._accel(state.x, state.v, state.t, info)
        return self._finish(state.x + h * state.v, state.v + h * a, state.t + h), info
