"""Classical fourth-order Runge-Kutta on the first-order system ``(x, v)' = (v, a(x, v, t))``.

Four force evaluations per step. Exact for free fall (``x = x0 + g t^2 / 2``).
"""

from __future__ import annotations

from ..constraints import Constraints
from ..model import State
from .base import Integrator, StepInfo


class RK4(Integrator):
    name = "rk4"
    aliases: tuple[str, ...] = ("runge_kutta", "runge_kutta_4", "rk")

    def step(self, state: State, h: float, constraints: Constraints | None = None) -> tuple[State, StepInfo]:
        info = StepInfo()
        x, v, t = state.x, state.v, state.t
        a1 = self._accel(x, v, t, info)
        v2 = v + (0.5 * h) * a1
        a2 = self._accel(x + (0.5 * h) * v, v2, t + 0.5 * h, info)
        v3 = v + (0.5 * h) * a2
        a3 = self._accel(x + (0.5 * h) * v2, v3, t + 0.5 * h, info)
        v4 = v + h * a3
        a4 = self._accel(x + h * v3, v4, t + h, info)
        x1 = x + (h / 6.0) * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v1 = v + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        return self._finish(x1, v1, t + h), info
