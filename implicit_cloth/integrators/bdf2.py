"""Second-order backward differentiation (BDF2), linearised once per step (Choi & Ko 2002).

::

    x_{n+1} = 4/3 x_n - 1/3 x_{n-1} + 2/3 h v_{n+1}
    v_{n+1} = 4/3 v_n - 1/3 v_{n-1} + 2/3 h a(x_{n+1}, v_{n+1})

Linearising ``F`` about ``(x_n, v_n)`` with ``dv = v_{n+1} - v_n`` gives::

    (M - 2/3 h dF/dv - 4/9 h^2 dF/dx) dv = M (v_n - v_{n-1}) / 3 + 2/3 h (F0 + (dF/dx) w)
    w = (x_n - x_{n-1}) / 3 + 2/3 h v_n

The same Jacobians and the same filtered PCG as backward Euler. The first step
(and the first after the state is assigned or the step size changes) is a
backward-Euler step.
"""

from __future__ import annotations


from ..model import State
from .backward_euler import BackwardEuler
from .base import StepInfo


class BDF2(BackwardEuler):
    name = "bdf2"

    def __init__(self, model, solver=None) -> None:
        super().__init__(model, solver)
        self._prev: tuple[State, State, float] | None = None   # (state n-1, state n, h)

    def reset(self) -> None:
        self._prev = None

    def step(self, state: State, h: float) -> tuple[State, StepInfo]:
        hist = self._prev
        if hist is None or hist[1] is not state or hist[2] != h:
            new, info = super().step(state, h)
        else:
            info = StepInfo()
            old = hist[0]
            x, v, t = state.x, state.v, state.t
            dx_hist = (x - old.x) / 3.0
            w = dx_hist + (2.0 / 3.0) * h * v
            A, f0, kw = self._linearize(x, v, t, (4.0 / 9.0) * h * h, (2.0 / 3.0) * h, w, info)
            b = self.model.masses[:, None] * ((v - old.v) / 3.0) + (2.0 / 3.0) * h * (f0 + kw)
            dv = self._solve(A, b, self._pin_dv(v), info)
            v1 = v + dv
            new = self._finish(x + dx_hist + (2.0 / 3.0) * h * v1, v1, t + h)
        self._prev = (state, new, h)
        return new, info
