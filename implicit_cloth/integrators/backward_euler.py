"""Backward Euler, linearised once per step (Baraff & Witkin 1998, eqs. 15-17).

::

    (M - h dF/dv - h^2 dF/dx) dv = h (F0 + h (dF/dx) v0)
    v1 = v0 + dv,   x1 = x0 + h v1

with ``F0``, ``dF/dx`` and ``dF/dv`` evaluated at ``(x0, v0)`` and the system
solved by the filtered PCG with pinned vertices' ``dv`` prescribed. Free fall
from rest: ``x_n = x_0 + g h^2 n (n + 1) / 2``. For an undamped linear
oscillator the amplitude shrinks by ``1 / sqrt(1 + w^2 h^2)`` per step.
"""

from __future__ import annotations

from ..model import State
from .base import ImplicitIntegrator, Scheme, StepInfo


class BackwardEuler(ImplicitIntegrator):
    name = "backward_euler"
    aliases: tuple[str, ...] = ("implicit_euler", "euler_implicit", "backward", "implicit", "bdf1", "baraff_witkin")

    def _scheme(self, state: State, h: float, info: StepInfo) -> Scheme:
        x, v, t = state.x, state.v, state.t
        A, f0, kv = self._linearize(x, v, t, h * h, h, v, info)
        ft = self.model.force_rate(x, v, t)   # forces that change with time at a fixed state (soft pins' targets)
        if ft is not None:
            return Scheme(h * h, h, h * (f0 + h * kv + h * ft), x, h, v)
        return Scheme(h * h, h, h * (f0 + h * kv), x, h, v)
