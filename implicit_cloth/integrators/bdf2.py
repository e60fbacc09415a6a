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

History: a step from state ``s`` uses the state the previous accepted step
started from. Several steps may be tried from the same ``s`` (the collision
stage solves again with more contacts, adaptive stepping retries); the one
whose result the next step starts from is the one that counts.
"""

from __future__ import annotations

from ..model import State
from .backward_euler import BackwardEuler
from .base import Scheme, StepInfo


class BDF2(BackwardEuler):
    name = "bdf2"
    aliases: tuple[str, ...] = ("bdf",)      # not backward Euler's, which it derives from

    def __init__(self, model, solver=None) -> None:
        super().__init__(model, solver)
        self._prev: tuple[State, State, float] | None = None   # (state n-1, state n, h)
        self._tried: list[tuple[State, State, float]] = []      # steps made since: (from, result, h)

    def reset(self) -> None:
        super().reset()
        self._prev = None
        self._tried = []

    def _history(self, state: State) -> tuple[State, State, float] | None:
        """``(state n-1, state, h)`` if ``state`` is the result of a step tried from n-1, else the last history."""
        for t in reversed(self._tried):
            if t[1] is state:
                self._prev = t
                self._tried = []
                break
        return self._prev

    def _scheme(self, state: State, h: float, info: StepInfo) -> Scheme:
        hist = self._history(state)
        if hist is None or hist[1] is not state or hist[2] != h:
            return super()._scheme(state, h, info)
        old = hist[0]
        x, v, t = state.x, state.v, state.t
        dx_hist = (x - old.x) / 3.0
        w = dx_hist + (2.0 / 3.0) * h * v
        A, f0, kw = self._linearize(x, v, t, (4.0 / 9.0) * h * h, (2.0 / 3.0) * h, w, info)
        b = self.model.masses[:, None] * ((v - old.v) / 3.0) + (2.0 / 3.0) * h * (f0 + kw)
        ft = self.model.force_rate(x, v, t)   # forces that change with time at a fixed state (soft pins' targets)
        if ft is not None:
            b += (2.0 / 3.0) * h * h * ft
        return Scheme((4.0 / 9.0) * h * h, (2.0 / 3.0) * h, b, x + dx_hist, (2.0 / 3.0) * h,
                       (4.0 / 3.0) * v - (1.0 / 3.0) * old.v)

    def step(self, state: State, h: float, constraints=None, guess=None, newton=None, start=None, redone=None,
             done=None):
        self._history(state)
        new, info = super().step(state, h, constraints, guess, newton, start, redone, done)
        self._tried = self._tried[-63:] + [(state, new, h)]
        return new, info
