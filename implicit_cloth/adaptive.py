"""Adaptive time stepping after Baraff & Witkin 1998 §5: redo a failed step better, then grow back.

A nominal step of ``dt`` (``simulation.dt``) is taken as substeps of
``h = dt / 2^L``, ``L`` the current level (0 .. ``max_halvings``). A substep
*fails* when

* its state is not finite (NaN or inf);
* the linear solver did not converge (implicit methods; ``retry_unconverged``);
* it leaves a spring stretched beyond ``max_strain`` (relative stretch
  ``(l - L0) / L0``) that it stretched further (a spring already beyond the
  bound and relaxing does not fail the step); with a membrane, likewise a
  triangle whose largest principal strain is beyond it;
* it breaks the energy balance (:mod:`implicit_cloth.diagnostics`): it raises
  the total energy (kinetic + gravity + springs) by more than the work of the
  moving pins, the wind and the obstacles over it plus
  ``max_energy_growth x E_step``, the energy the step itself moves about::

      E(t + h) - E(t) - h (P(t) + P(t + h)) / 2 - W_obstacles > max_energy_growth * E_step

  Gravity and springs are conservative and damping, drag, friction, contact and
  backward Euler only dissipate, so a gain is numerical: a linearised step
  overshooting (springs turning far within one step, at an impact for instance).

A failed substep is discarded. An implicit method's energy or strain failure
is first redone at the same step with Newton iterations (up to
``newton_iterations``, see :meth:`ImplicitIntegrator._newton
<implicit_cloth.integrators.base.ImplicitIntegrator._newton>`): the nonlinear
solve of the same backward-Euler step, which lowers the incremental potential
at every iteration. What still fails is redone from the same state at the next
level (half the step, one linearisation again). After ``grow_after`` accepted
substeps in a row the step doubles, never beyond ``dt`` and only where the
doubled step ends on its own grid, so a nominal step always ends at ``t + dt``
and kept frames stay on the nominal grid. A substep that still fails at the
smallest step ``dt / 2^max_halvings`` is accepted if its state is finite
(counted as *forced*, with the first time and the largest amount per
criterion: the run's report turns them into warnings); the criteria it failed
are then suspended (checked but not retried) until a substep passes them
again. A non-finite state at the smallest step is returned as is: the
simulator reports the divergence.

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

#: A substep function: ``substep(state, h, newton) -> (state, info)`` (``newton``: Newton iterations asked for,
#: None for the method's default).
Substep = Callable[[State, float, Any], tuple[State, StepInfo]]

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
    newton_retries : int
        Substeps redone at the same step with Newton iterations.
    forced_events : dict
        Per criterion of the forced substeps: ``{"count", "first_time" (s), "worst"}``, the worst amount
        being the energy gained beyond the balance (J) or the largest strain.
    """

    substeps: int = 0
    retries: int = 0
    forced: int = 0
    failures: dict[str, int] = field(default_factory=lambda: {c: 0 for c in CRITERIA})
    min_step: float = math.inf
    newton_retries: int = 0
    forced_events: dict[str, dict[str, float]] = field(default_factory=dict)

    def copy(self) -> "AdaptiveStats":
        return AdaptiveStats(self.substeps, self.retries, self.forced, dict(self.failures), self.min_step,
                             self.newton_retries, {k: dict(v) for k, v in self.forced_events.items()})

    def force(self, criterion: str, t: float, amount: float) -> None:
        ev = self.forced_events.setdefault(criterion, {"count": 0, "first_time": t, "worst": amount})
        ev["count"] += 1
        ev["worst"] = max(ev["worst"], amount)


class StepController:
    """Halve-and-grow step control wrapped around a substep function (module docstring).

    Parameters
    ----------
    model : Model
    settings : dict
        The normalised ``simulation.adaptive`` table: ``max_halvings``,
        ``grow_after``, ``max_strain``, ``max_energy_growth``,
        ``retry_unconverged``, ``newton_iterations``.
    implicit : bool
        Whether the substeps are an implicit method's (they can then be redone with Newton iterations).
    """

    def __init__(self, model: Model, settings: dict[str, Any], implicit: bool = True) -> None:
        self.model = model
        self.max_halvings = int(settings["max_halvings"])
        self.grow_after = int(settings["grow_after"])
        self.max_strain = float(settings["max_strain"])
        self.max_energy_growth = float(settings["max_energy_growth"])
        self.retry_unconverged = bool(settings["retry_unconverged"])
        self.newton_iterations = int(settings.get("newton_iterations", 8)) if implicit else 0
        self.level = 0
        self._streak = 0
        self.suspended: set[str] = set()
        self.stats = AdaptiveStats()
        #: smallest accepted step since the caller last reset it to inf, s (per-frame reports)
        self.window_min_step = math.inf
        self.measures = diagnostics.StepMeasures(model)
        #: the criteria the last Newton retry was made for
        self.retry_for: frozenset[str] = frozenset()

    def check(self, old: State, new: State, info: StepInfo, h: float) -> dict[str, float]:
        """The criteria a substep from ``old`` to ``new`` of ``h`` seconds fails, each with its amount.

        The amount is the energy gained beyond the balance (J, ``"energy"``), the largest strain
        (``"strain"``), the solve's residual (``"solver"``) or inf (``"nonfinite"``).
        """
        if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
            return {"nonfinite": math.inf}
        failed: dict[str, float] = {}
        if self.retry_unconverged and not info.converged:
            failed["solver"] = info.residual
        eps0 = self.measures.strains(old)
        eps1 = self.measures.strains(new)
        if eps1 is not None:
            over = (eps1 > self.max_strain) & (eps1 > eps0)
            if np.any(over):
                failed["strain"] = float(eps1[over].max())
        gain = self._energy_gain(old, new, h, info.external_work, info.contact_stored)
        if gain is not None:
            failed["energy"] = gain
        return failed

    def _energy_gain(self, old: State, new: State, h: float, work: float, stored: float = 0.0) -> float | None:
        """The energy the substep gained beyond its external work ``work`` and the pins', J, when that is more
        than the balance allows (``max_energy_growth`` of the energy it moves about, the contact potential's
        ``stored`` energy included) or not a number; None otherwise."""
        gain, e_step = self.measures.balance(old, new, h, work, stored)
        return None if gain <= self.max_energy_growth * e_step else gain

    def passes(self, old: State, new: State, h: float, work: float = 0.0) -> bool:
        """Whether the substep ``old -> new`` meets the energy criterion as :meth:`check` judges it (``work``: its
        external work beside the pins' and the wind's, J): a Newton retry made for it alone whose iterate passes
        is done (more iterations would not change the verdict). A retry for the strain converges (stopping
        there tore coincident vertices' springs past the report's bound)."""
        return self._energy_gain(old, new, h, work) is None

    def _verdict(self, failed: dict[str, float], newton: int | None) -> tuple[set[str], bool, bool]:
        """The criteria of ``failed`` that count (not suspended), whether the step is redone with Newton
        iterations, and whether it is redone at all (Newton, or a smaller step)."""
        active = set(failed) - self.suspended     # (what advance unsuspends first is not in failed)
        nonlinear = newton is None and self.newton_iterations > 1 and bool(active & {"energy", "strain"})
        return active, nonlinear, bool(active) and (nonlinear or self.level < self.max_halvings)

    def redone(self, old: State, new: State, info: StepInfo, h: float, newton: int | None) -> bool:
        """Whether :meth:`advance` will discard the substep ``old -> new`` (of ``h``, with ``newton``) and
        redo it, judged as it will judge it (without booking anything). A later stage that only corrects the
        proposal, at a cost, can be skipped for a proposal that will be discarded whatever it does: the
        step is redone anyway, and a step that cannot be redone any more is never skipped."""
        return self._verdict(self.check(old, new, info, h), newton)[2]

    # ------------------------------------------------------------------ stepping
    def advance(self, state: State, dt: float, substep: Substep) -> tuple[State, StepInfo]:
        """Advance ``state`` by one nominal step ``dt`` in substeps taken by ``substep(state, h, newton)``.

        Returns the state at ``state.t + dt`` (exactly that time) and the
        substeps' combined figures: iterations summed, residual the largest,
        converged only if every accepted substep's solve was, timings summed
        over every attempt (discarded ones included), the discarded attempts'
        solves and iterations in ``discarded_solves`` and
        ``discarded_iterations``. A non-finite state at the
        smallest step is returned as it came (the caller reports it).
        """
        units = 1 << self.max_halvings                # the nominal step in units of the smallest step
        done = 0
        total = StepInfo()
        t_end = state.t + dt
        newton = None
        while done < units:
            if self.level > 0 and self._streak >= self.grow_after:
                bigger = 1 << (self.max_halvings - self.level + 1)
                if done % bigger == 0 and units - done >= bigger:
                    self.level -= 1
                    self._streak = 0
            size = 1 << (self.max_halvings - self.level)
            h = dt if self.level == 0 else dt / (1 << self.level)
            new, info = substep(state, h, newton)
            total.t_assembly += info.t_assembly
            total.t_setup += info.t_setup
            total.t_solve += info.t_solve
            failed = self.check(state, new, info, h)
            for c in failed:
                self.stats.failures[c] += 1
            if "nonfinite" not in failed:                  # a criterion passed: retry on it again
                self.suspended -= set(CRITERIA) - set(failed)
            active, nonlinear, retry = self._verdict(failed, newton)
            if retry or "nonfinite" in active:             # discarded: not booked with the accepted below
                total.discarded_solves += info.solves
                total.discarded_iterations += info.iterations
            if info.collision is not None:   # collision figures: of accepted substeps; time of every attempt
                if total.collision is None:
                    total.collision = type(info.collision)()
                total.collision.absorb(info.collision, accepted=not retry)
            if active:
                if nonlinear:                              # the same step, solved nonlinearly
                    self.stats.newton_retries += 1
                    newton = self.newton_iterations
                    self.retry_for = frozenset(active)
                    continue
                if self.level < self.max_halvings:
                    self.stats.retries += 1
                    self.level += 1
                    self._streak = 0
                    newton = None
                    continue
                if "nonfinite" in active:
                    return new, total
                self.stats.forced += 1
                for c in active:
                    self.stats.force(c, new.t, failed[c])
                self.suspended |= active
            state = new
            newton = None
            done += size
            self._streak += 1
            self.stats.substeps += 1
            self.stats.min_step = min(self.stats.min_step, h)
            self.window_min_step = min(self.window_min_step, h)
            total.iterations += info.iterations
            total.residual = max(total.residual, info.residual)
            total.converged = total.converged and info.converged
            total.solves += info.solves
            total.newton_iterations = max(total.newton_iterations, info.newton_iterations)
            total.self_work += info.self_work
        state.t = t_end          # sums of dt / 2^L may round differently (in place: BDF2 keys its history on it)
        return state, total

    def reset(self) -> None:
        """After the state is assigned: forget the cached measures and the suspended criteria.

        The level (current step) and the counters stay.
        """
        self.measures.forget()
        self.suspended.clear()
