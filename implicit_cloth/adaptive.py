"""Adaptive time stepping after Baraff & Witkin 1998 §5: redo a failed step with half the step, then grow back.

A nominal step of ``dt`` (``simulation.dt``) is taken as substeps of
``h = dt / 2^L``, ``L`` the current level (0 .. ``max_halvings``). A substep
*fails* when

* its state is not finite (NaN or inf);
* the linear solver did not converge (implicit methods; ``retry_unconverged``);
* it leaves a spring stretched beyond ``max_strain`` (relative stretch
  ``(l - L0) / L0``) that it stretched further (a spring already beyond the
  bound and relaxing does not fail the step);
* it raises the total energy (kinetic + gravity + springs) by more than
  ``max_energy_growth x E_scale`` beyond the work the moving pins and the wind
  did over it and the energy the collision response added (``W_c``, the work
  of moving obstacles less contact dissipation)::

      E(t + h) - E(t) - h (P(t) + P(t + h)) / 2 - W_c > max_energy_growth * E_scale

  with ``P`` the power of the pins (:func:`~implicit_cloth.diagnostics.pin_power`)
  plus that of the wind on the drag (``sum_i c A_i w . v_i``) and ``E_scale``
  the run's energy scale (:func:`~implicit_cloth.diagnostics.energy_scale`).
  Gravity and springs are conservative and damping, drag and backward Euler
  only dissipate, so a gain is numerical: a linearised step overshooting.

A failed substep is discarded and redone from the same state at the next
level (half the step). After ``grow_after`` accepted substeps in a row the
step doubles, never beyond ``dt`` and only where the doubled step ends on its
own grid, so a nominal step always ends at ``t + dt`` and kept frames stay on
the nominal grid. A substep that still fails at the smallest step
``dt / 2^max_halvings`` is accepted if its state is finite (counted as
*forced*); the criteria it failed are then suspended (checked but not
retried) until a substep passes them again, since a stretch or an energy gain
the smallest step cannot avoid is physical (a pin dragging the cloth). A
non-finite state at the smallest step is returned as is: the simulator
reports the divergence.

The criteria cost two energy and strain evaluations per substep (one when the
previous substep's end is reused), no force evaluation unless pins move or
wind blows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from . import diagnostics
from .integrators import StepInfo
from .model import Model, State

#: the failure criteria, in the order they are checked
CRITERIA: tuple[str, ...] = ("nonfinite", "solver", "strain", "energy")


@dataclass
class AdaptiveStats:
    """Counters of a controller since it was made or :meth:`Simulator.run` last started.

    Attributes
    ----------
    substeps : int
        Accepted substeps.
    retries : int
        Substeps discarded and redone with half the step.
    forced : int
        Substeps accepted at the smallest step although they failed a criterion.
    failures : dict
        Failed substeps per criterion (a substep can fail several).
    min_step : float
        Smallest step of an accepted substep, s (inf before the first).
    """

    substeps: int = 0
    retries: int = 0
    forced: int = 0
    failures: dict[str, int] = field(default_factory=lambda: {c: 0 for c in CRITERIA})
    min_step: float = math.inf

    def copy(self) -> "AdaptiveStats":
        return AdaptiveStats(self.substeps, self.retries, self.forced, dict(self.failures), self.min_step)


class StepController:
    """Halve-and-grow step control wrapped around a substep function (module docstring).

    Parameters
    ----------
    model : Model
    settings : dict
        The normalised ``simulation.adaptive`` table: ``max_halvings``,
        ``grow_after``, ``max_strain``, ``max_energy_growth``,
        ``retry_unconverged``.
    energy_scale : float
        ``E_scale`` of the energy criterion, J (the simulator sets the run's).
    """

    def __init__(self, model: Model, settings: dict[str, Any], energy_scale: float) -> None:
        self.model = model
        self.max_halvings = int(settings["max_halvings"])
        self.grow_after = int(settings["grow_after"])
        self.max_strain = float(settings["max_strain"])
        self.max_energy_growth = float(settings["max_energy_growth"])
        self.retry_unconverged = bool(settings["retry_unconverged"])
        self.energy_scale = float(energy_scale)
        self.level = 0
        self._streak = 0
        self.suspended: set[str] = set()
        self.stats = AdaptiveStats()
        #: smallest accepted step since the caller last reset it to inf, s (per-frame reports)
        self.window_min_step = math.inf
        self._cache: tuple[State, float, np.ndarray | None, float] | None = None
        self._wind = next((e for e in model.effects if e.name == "drag" and e.wind is not None), None)
        self._pins_move = bool(len(model.pinned)) and bool(np.any(model.pin_velocity))

    # ------------------------------------------------------------------ measures of a state
    def _power(self, s: State) -> float:
        """Power of the pins and of the wind on the cloth, W."""
        p = diagnostics.pin_power(self.model, s.x, s.v, s.t) if self._pins_move else 0.0
        if self._wind is not None:
            w = np.broadcast_to(self._wind.wind.velocity(s.x, s.t), s.v.shape)
            p += float(np.einsum("i,ij,ij->", self._wind._cA[:, 0], w, s.v))
        return p

    def _measures(self, s: State) -> tuple[float, np.ndarray | None, float]:
        """Total energy (J), spring strains and external power (W) of a state (cached for the last one)."""
        if self._cache is not None and self._cache[0] is s:
            return self._cache[1:]
        m = self.model
        energy = m.kinetic_energy(s.v) + sum(e.potential(s.x) for e in m.effects if e.name == "gravity")
        strain = None
        sp = m.springs
        if sp is not None and len(sp.i):      # spring energy and strains from one evaluation of the lengths
            ext = sp.lengths(s.x) - sp.L0
            energy += 0.5 * float(np.dot(sp.k, ext * ext))
            strain = np.divide(ext, sp.L0, out=np.zeros_like(ext), where=sp.L0 > 0)
        out = (energy, strain, self._power(s))
        self._cache = (s, *out)
        return out

    def check(self, old: State, new: State, info: StepInfo, h: float) -> set[str]:
        """The criteria a substep from ``old`` to ``new`` of ``h`` seconds fails (module docstring)."""
        if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
            return {"nonfinite"}
        failed = set()
        if self.retry_unconverged and not info.converged:
            failed.add("solver")
        e0, eps0, p0 = self._measures(old)
        e1, eps1, p1 = self._measures(new)
        if eps1 is not None and np.any((eps1 > self.max_strain) & (eps1 > eps0)):
            failed.add("strain")
        external = 0.5 * h * (p0 + p1) + (info.collision.work if info.collision is not None else 0.0)
        if e1 - e0 - external > self.max_energy_growth * self.energy_scale:
            failed.add("energy")
        return failed

    # ------------------------------------------------------------------ stepping
    def advance(self, state: State, dt: float,
                substep: Callable[[State, float], tuple[State, StepInfo]]) -> tuple[State, StepInfo]:
        """Advance ``state`` by one nominal step ``dt`` in substeps taken by ``substep(state, h)``.

        Returns the state at ``state.t + dt`` (exactly that time) and the
        substeps' combined figures: iterations summed, residual the largest,
        converged only if every accepted substep's solve was, timings summed
        over every attempt (discarded ones included). A non-finite state at the
        smallest step is returned as it came (the caller reports it).
        """
        units = 1 << self.max_halvings                # the nominal step in units of the smallest step
        done = 0
        total = StepInfo()
        t_end = state.t + dt
        while done < units:
            if self.level > 0 and self._streak >= self.grow_after:
                bigger = 1 << (self.max_halvings - self.level + 1)
                if done % bigger == 0 and units - done >= bigger:
                    self.level -= 1
                    self._streak = 0
            size = 1 << (self.max_halvings - self.level)
            h = dt if self.level == 0 else dt / (1 << self.level)
            new, info = substep(state, h)
            total.t_assembly += info.t_assembly
            total.t_setup += info.t_setup
            total.t_solve += info.t_solve
            failed = self.check(state, new, info, h)
            for c in failed:
                self.stats.failures[c] += 1
            if "nonfinite" not in failed:                  # a criterion passed: retry on it again
                self.suspended -= set(CRITERIA) - failed
            active = failed - self.suspended
            retry = bool(active) and self.level < self.max_halvings
            if info.collision is not None:   # collision figures: of accepted substeps; time of every attempt
                if total.collision is None:
                    total.collision = type(info.collision)()
                total.collision.absorb(info.collision, accepted=not retry)
            if active:
                if self.level < self.max_halvings:
                    self.stats.retries += 1
                    self.level += 1
                    self._streak = 0
                    continue
                if "nonfinite" in active:
                    return new, total
                self.stats.forced += 1
                self.suspended |= active
            state = new
            done += size
            self._streak += 1
            self.stats.substeps += 1
            self.stats.min_step = min(self.stats.min_step, h)
            self.window_min_step = min(self.window_min_step, h)
            total.iterations += info.iterations
            total.residual = max(total.residual, info.residual)
            total.converged = total.converged and info.converged
        state.t = t_end          # sums of dt / 2^L may round differently (in place: BDF2 keys its history on it)
        return state, total

    def reset(self) -> None:
        """After the state is assigned: forget the cached measures and the suspended criteria.

        The level (current step) and the counters stay.
        """
        self._cache = None
        self.suspended.clear()
