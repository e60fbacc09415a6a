"""Integrator interface and the pieces shared by the implicit methods."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..model import Model, State
from ..solvers import Filter, filtered_pcg, make_preconditioner


@dataclass
class StepInfo:
    """What one step did: solver figures (implicit methods) and where its time went (s)."""

    iterations: int = 0
    residual: float = 0.0
    converged: bool = True
    t_assembly: float = 0.0
    t_setup: float = 0.0
    t_solve: float = 0.0
    #: collision figures of the step (a CollisionInfo), when the scene has obstacles
    collision: Any = None


class Integrator:
    """Maps ``(state, h)`` to the state one step of ``h`` seconds later.

    Subclasses implement :meth:`step`. Every method uses the same force code
    (:meth:`~implicit_cloth.model.Model.forces` / ``linearize``) and honours pins
    exactly: pinned vertices end each step at ``a_p + w_p t`` with velocity ``w_p``.
    """

    name = ""
    implicit = False

    def __init__(self, model: Model, solver: dict[str, Any] | None = None) -> None:
        self.model = model

    def reset(self) -> None:
        """Forget any history (called when the state is assigned or dt changes)."""

    def step(self, state: State, h: float) -> tuple[State, StepInfo]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _accel(self, x: np.ndarray, v: np.ndarray, t: float, info: StepInfo) -> np.ndarray:
        t0 = time.perf_counter()
        a = self.model.accelerations(x, v, t)
        info.t_assembly += time.perf_counter() - t0
        return a

    def _finish(self, x: np.ndarray, v: np.ndarray, t: float) -> State:
        self.model.apply_pins(x, v, t)
        return State(x, v, t)


class ImplicitIntegrator(Integrator):
    """Shared machinery of the implicit methods: assembly, filter, preconditioner, filtered PCG."""

    implicit = True

    def __init__(self, model: Model, solver: dict[str, Any] | None = None) -> None:
        super().__init__(model, solver)
        opts = {"tolerance": 1e-3, "max_iterations": 1000, "preconditioner": "multigrid"}
        opts.update(solver or {})
        self.tolerance = float(opts["tolerance"])
        self.max_iterations = int(opts["max_iterations"])
        self.precond = make_preconditioner(opts["preconditioner"], model)
        self.filter = Filter(model.n, model.pinned)
        self._mass3 = np.repeat(model.masses, 3)
        #: prescribed velocity changes (N, 3) of constrained non-pinned vertices (set by the collider)
        self.extra_dv: np.ndarray | None = None
        #: ``A dv - b`` (N, 3), N*s, of the last solve when the filter had partial constraints:
        #: the impulse the constraints applied (only their constrained components are non-zero)
        self.constraint_impulse: np.ndarray | None = None

    def _pin_dv(self, v: np.ndarray) -> np.ndarray:
        """Prescribed velocity changes z: pinned vertices reach their pin velocity (plus ``extra_dv``)."""
        z = np.zeros_like(v) if self.extra_dv is None else self.extra_dv.copy()
        if len(self.model.pinned):
            z[self.model.pinned] = self.model.pin_velocity - v[self.model.pinned]
        return z

    def _linearize(self, x, v, t, c_x, c_v, w, info: StepInfo):
        t0 = time.perf_counter()
        out = self.model.linearize(x, v, t, c_x, c_v, w)
        info.t_assembly += time.perf_counter() - t0
        return out

    def _solve(self, A, b: np.ndarray, z: np.ndarray, info: StepInfo) -> np.ndarray:
        """Solve ``A dv = b`` with pins prescribing ``dv = z`` through the filter."""
        t0 = time.perf_counter()
        self.precond.setup(self.model.system, self.filter)
        t1 = time.perf_counter()
        dv, res = filtered_pcg(A, b.reshape(-1), z.reshape(-1), self.filter, self.precond,
                               self.tolerance, self.max_iterations, mass=self._mass3,
                               rule=self.precond.stopping_rule)
        info.t_setup += t1 - t0
        info.t_solve += time.perf_counter() - t1
        info.iterations, info.residual, info.converged = res.iterations, res.residual, res.converged
        if len(self.filter.partial):
            self.constraint_impulse = (A @ dv - b.reshape(-1)).reshape(-1, 3)
        else:
            self.constraint_impulse = None
        return dv.reshape(-1, 3)
