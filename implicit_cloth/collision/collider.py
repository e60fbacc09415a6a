"""The collision stage of one cloth: :class:`Collider` (module docstring of :mod:`implicit_cloth.collision`)."""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from ..constraints import Constraints
from ..errors import SceneError
from ..integrators.base import StepInfo
from . import contacts, fallback, friction
from .context import CollisionInfo, Context
from .shapes import MeshShape

#: A held contact stays held while its vertex is within this multiple of the thickness of the obstacle.
CONTACT_BAND = 1.25
#: A contact whose impulse pulls its vertex towards the obstacle by more than this change of velocity (m/s)
#: is released within the step (and the step solved again): a moving obstacle dragging the cloth back. Lighter
#: pulls (where a resting cloth leaves the surface, about its weight) are released from the next step on.
PULL_SPEED = 0.5
#: A contact step whose last linear solve leaves the free vertices out of balance by more than this rms
#: acceleration (m/s², one g) is continued by ``collision.newton_iterations`` - 1 Newton iterations.
BALANCE = 9.81
#: New contacts violated by at most this fraction of the thickness do not call for another solve: they are
#: held from the next step on, and the geometric response keeps them out in this one.
RESOLVE_FRACTION = 0.1


class Collider:
    """Collision stage for one model and the validated ``obstacles`` and ``collision`` tables.

    Parameters
    ----------
    obstacles : list of dict
        Validated ``[[obstacles]]`` tables.
    settings : dict
        Validated ``[collision]`` table (``thickness`` m, ``restitution``, ``max_iterations``).
    model : Model
        The cloth (masses, faces, pins).

    Raises
    ------
    SceneError
        Naming the obstacle, if free cloth vertices start inside it deeper than the thickness.
    """

    def __init__(self, obstacles: list[dict[str, Any]], settings: dict[str, Any], model: Any) -> None:
        self.model = model
        self.ctx = Context.build(obstacles, settings, model)
        self._mu = self.ctx.mu
        self._check_start(model.rest_positions, 0.0)
        #: (state, contacts held at its end) of the last steps: a step from that state starts with them
        self._carry: list[tuple[Any, contacts.Planes]] = []
        #: the last attempt at a step: (state, h, its contacts, its end velocities), for a nonlinear redo
        self._attempt: tuple[Any, float, contacts.Planes, np.ndarray] | None = None
        #: steps still to go without the friction's Newton iterations (``collision.friction_pause``)
        self._friction_pause = 0
        #: whether the last step that tried them missed the law (``collision.friction_pause``)
        self._friction_missed = False

    # the settings, as the report reads them
    @property
    def obstacles(self) -> list[Any]:
        return self.ctx.obstacles

    @property
    def thickness(self) -> float:
        return self.ctx.thickness

    @property
    def edges(self) -> np.ndarray:
        return self.ctx.edges

    def _check_start(self, x: np.ndarray, t: float) -> None:
        """A :class:`SceneError` naming the obstacle if cloth vertices start inside it, deeper than the thickness."""
        th = self.ctx.thickness
        for k, ob in enumerate(self.ctx.obstacles):
            depth = self.depths(k, x, t)
            bad = (depth > th) & self.ctx.free    # pins are the user's: never moved, never checked
            if np.any(bad):
                raise SceneError(
                    f"obstacles[{k}]: {int(bad.sum())} cloth vertices start inside it (the deepest "
                    f"{1e3 * float(depth.max()):.3g} mm, more than the thickness {th:g} m; the first is "
                    f"vertex {int(np.flatnonzero(bad)[0])}): move the obstacle or the cloth apart, got "
                    f"{ob.describe()}")

    def depths(self, k: int, x: np.ndarray, t: float) -> np.ndarray:
        """Depth (m, > 0 inside, 0 outside) of world points ``x`` inside obstacle ``k`` at time ``t``.

        Primitive shapes: minus the signed distance. Meshes: for a closed (watertight) mesh, the distance to
        the nearest face of the points whose winding number says they are inside; an open mesh has no inside
        (0 everywhere).
        """
        ob = self.ctx.obstacles[k]
        p = ob.motion.to_local(x, t)
        if not isinstance(ob.shape, MeshShape):
            return np.maximum(-ob.shape.distance(p), 0.0)
        return ob.shape.depth(p)

    @property
    def held(self) -> np.ndarray:
        """Vertices held by a contact at the end of the last step (carried into the next one), (K,) int."""
        return self._carry[-1][1].idx.copy() if self._carry else np.zeros(0, dtype=np.int64)

    def reset(self) -> None:
        """Forget the contacts carried from step to step (called when the state is assigned)."""
        self._carry = []
        self._attempt = None
        self._friction_pause = 0
        self._friction_missed = False

    # ------------------------------------------------------------------ explicit methods
    def respond(self, before: Any, after: Any, h: float) -> CollisionInfo:
        """The geometric response (:func:`~implicit_cloth.collision.fallback.respond`, with friction) of an
        explicit step, in place; its ``work`` is the velocity changes' against moving obstacles."""
        v_before = after.v.copy()
        info = fallback.respond(self.ctx, before, after, h)
        info.work = fallback.impulse_work(self.ctx, v_before, after)
        return info

    # ------------------------------------------------------------------ implicit step with contacts
    def step(self, integrator: Any, state: Any, h: float, pins: Constraints,
             limiter: Any = None, newton: int | None = None) -> tuple[Any, StepInfo]:
        """One implicit step of ``h`` from the collision-free ``state`` with contacts as constraints of the solve.

        Solve, detect, constrain, solve again: the step is solved with the contacts carried from the
        previous step (:meth:`_carried`); contact detection on the proposed step
        (:func:`~implicit_cloth.collision.contacts.detect`) adds every vertex that would come nearer than the
        thickness to an obstacle, and Coulomb friction (:func:`~implicit_cloth.collision.friction.update`)
        decides which contacts stick and which slide; while new contacts (or the friction of new ones) call
        for it, the step is solved again from the same state (warm-started), at most
        ``collision.max_iterations`` solves, each with ``newton`` Newton iterations (None: the solver's
        setting). Then contacts leave inelastically (:func:`~implicit_cloth.collision.friction.inelastic`),
        ``limiter`` (strain limiting) runs with the contact planes held, and the geometric response (without
        friction) corrects what the solves left, counted as fallback corrections.

        Returns the new state and the step's :class:`~implicit_cloth.integrators.StepInfo`, whose
        ``collision`` is this stage's :class:`~implicit_cloth.collision.context.CollisionInfo`.
        """
        t_start = time.perf_counter()
        active, carried = self._carried(state, h)
        start = None
        last = self._attempt
        if newton is not None and newton > 1 and last is not None and last[0] is state and last[1] == h:
            # redone nonlinearly: from where the last attempt at this step ended, with its contacts
            active = contacts.merge(active, last[2])
            start = last[3]
        new, total, info, cons, active, t_solve = self._solve_rounds(integrator, state, h, pins, active,
                                                                     carried, newton, start)
        self._attempt = (state, h, active.take(slice(None)), new.v.copy())
        info.resting = len(active)
        info.solves = total.solves
        if np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v)):
            info.work = self._finish(state, new, h, cons, active, carried, total.constraint_impulse, limiter, info,
                                     bool(total.friction_converged))
        self._carry = self._carry[-7:] + [(new, active.take(active.force >= 0.0))]
        info.t_collision = time.perf_counter() - t_start - t_solve
        total.collision = info
        return new, total

    def _solve_rounds(self, integrator: Any, state: Any, h: float, pins: Constraints, active: contacts.Planes,
                      carried: np.ndarray, newton: int | None, start: np.ndarray | None):
        """The rounds of :meth:`step`: solve, update friction and releases, detect; again while needed.

        Self-collision's re-solve of a step that adaptive stepping redoes with Newton iterations (``newton`` >
        1, with vertices its corrections prescribe) solves the rounds with one linearisation each and continues
        the last with the ``newton - 1`` Newton iterations once (:meth:`_refine`), instead of iterating to
        convergence in every round: the rounds only find the contacts. On the crumple benchmark's 1.5 s, side
        by side, the 64² sheet took 387 s of CPU instead of 443 (its first second: 140 instead of 178), the
        32² one 72 instead of 82; substeps 495 against 497 (32²: 326 against 290), status ok, no crossing.
        (A plain Newton redo's rounds, without self-collision, still iterate in every round.)
        """
        total = StepInfo()
        info = CollisionInfo()
        guess = None
        t_solve = 0.0
        cons, new = pins, state
        switched = np.zeros(self.ctx.n, dtype=bool)
        released = np.zeros(self.ctx.n, dtype=bool)
        balance: Callable[[], float] | None = None      # the last round's (StepInfo.balance_of)
        extra = len(pins.pinned) > len(self.model.pinned)     # vertices prescribed for this step (self-collision)
        # self-collision's re-solve of a Newton redo: the contact rounds linear, its Newton iterations once, last
        redo_newton = newton - 1 if extra and newton is not None and newton > 1 else None
        round_newton = None if redo_newton is not None else newton
        friction_newton = self.ctx.friction_newton if redo_newton is None else 0   # solves converge friction
        if friction_newton and self._friction_pause > 0:      # missed the law lately: the state rules at once
            self._friction_pause -= 1
            friction_newton = 0
        step_missed: bool | None = None      # whether a round of this step missed the law (None: none tried)
        for rnd in range(self.ctx.max_rounds):
            if extra and len(active):                           # a prescribed vertex is no contact
                active = active.take(~np.isin(active.idx, pins.pinned))
            cons = self._constraints(pins, active, state.t, h)
            ts = time.perf_counter()
            k = max(round_newton or 1, friction_newton) if friction_newton and cons.n_contacts else round_newton
            redone = self._pulls(active, cons, h, released) if friction_newton and cons.n_contacts else None
            new, si = integrator.step(state, h, cons, guess, k, start, redone=redone)
            t_solve += time.perf_counter() - ts
            start = None
            total.absorb(si)
            total.constraint_impulse = si.constraint_impulse
            total.friction_converged = si.friction_converged
            if self.ctx.friction_pause and friction_newton and cons.n_contacts and si.friction_converged is not None:
                missed = si.friction_converged is False
                if missed and self._friction_missed:
                    # the Newton iterations missed the law again: pause them from the next step on (this step's
                    # later rounds still try: skipping those too left a 32² drape at dt 1/30 sliding at mm/s)
                    self._friction_pause = self.ctx.friction_pause
                step_missed = step_missed or missed
            if si.friction_converged and si.pending_bounds:
                # the new contacts' friction was solved in this step at its first solve's normal forces: no
                # second solve for it
                switched[cons.contact[cons.pending > 0.0]] = True
            balance = si.balance_of
            info.rounds = rnd + 1
            if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
                break
            changed = False
            if len(active):
                active, changed = self._after_solve(active, cons, si.constraint_impulse, new.v, h,
                                                    carried if rnd == 0 else active.idx, switched, released,
                                                    rnd == 0, bool(si.friction_converged))
            active, viol = self._detect(state, new, active, info)
            changed |= viol > RESOLVE_FRACTION * self.ctx.thickness
            if not changed:
                break      # small new violations are held from the next step on; the response keeps them out now
            guess = new.v - state.v
        if step_missed is not None:
            self._friction_missed = step_missed
        iterations = redo_newton
        if redo_newton is not None:
            active = active.take(~np.isin(active.idx, pins.pinned))
        elif len(active) and not extra and (newton is None or newton <= 1) and self.ctx.newton > 1 \
                and balance is not None and balance() > BALANCE:
            iterations = self.ctx.newton - 1
        if iterations is not None and np.all(np.isfinite(new.v)):
            new, cons, t = self._refine(integrator, state, h, pins, active, new, total, iterations)
            t_solve += t
            if np.all(np.isfinite(new.x)):   # contacts the refined motion makes: held from the next step on
                active, _ = self._detect(state, new, active, info)
        return new, total, info, cons, active, t_solve

    def _detect(self, state: Any, new: Any, active: contacts.Planes,
                info: CollisionInfo) -> tuple[contacts.Planes, float]:
        """``active`` with the contacts the step ``state -> new`` makes merged in (new ones counted in ``info``),
        and the largest violation among those found (m; 0 if none)."""
        found = contacts.detect(self._frame(state, new), self.ctx.obstacles)
        if not len(found):
            return active, 0.0
        info.contacts += int(np.count_nonzero(~np.isin(found.idx, active.idx)))
        return contacts.merge(active, found), float(found.viol.max())

    def _refine(self, integrator: Any, state: Any, h: float, pins: Constraints, active: contacts.Planes,
                new: Any, total: StepInfo, iterations: int) -> tuple[Any, Constraints, float]:
        """``iterations`` Newton iterations from the rounds' last linear solve, with its contacts: the step's
        ``collision.newton_iterations`` - 1 where that solve left the free vertices out of balance by more than
        :data:`BALANCE`, or a redo's own (self-collision's re-solve of a Newton redo, :meth:`_solve_rounds`).

        A single linearisation leaves the free vertices out of balance by the linearisation error of their
        springs' forces (rms 3-6 times a vertex's weight on a 32² drape at dt 1/30) and puts it into the
        contacts' impulses, which decide sticking and sliding: contacts whose friction should hold slip, and
        a draped cloth creeps instead of coming to rest. The Newton iterations (line search on the incremental
        potential: they cannot raise it) remove it. They hold every contact the rounds found (the small new
        ones included) in the states the rounds left them, and the result updates the contacts' normal
        forces and sliding directions only: whether a contact sticks or slides is decided by the solves
        of the rounds (here the next step's), never by the refinement's impulses, whose Newton solves stop at
        a loose forcing tolerance. (Letting the refinement switch states kept a landed 16² drape at dt 1/60
        sliding at mm/s, stick and slip taking turns from step to step; held, it comes to rest to 1e-15 m/s.)
        The balance-driven refinement is not run in the solves of a step that self-collision's corrections
        prescribe vertices for (those solves follow a first one that had its refinement; a redo's re-solve
        takes the redo's iterations here, as it took them in every round before): the iterations there pull
        against the prescribed
        vertices, whose holding forces are not booked as work, and made energy the balance saw (a towel's
        fold landing, 0.9 mJ in a step forced at the smallest substep).
        Returns the state, its constraints and the solve time.
        """
        cons = self._constraints(pins, active, state.t, h)
        ts = time.perf_counter()
        new, si = integrator.step(state, h, cons, None, iterations, new.v)
        t = time.perf_counter() - ts
        total.absorb(si)
        total.constraint_impulse = si.constraint_impulse
        total.friction_converged = si.friction_converged
        every = np.ones(self.ctx.n, dtype=bool)                   # every state held: forces and directions only
        if len(active) and self.ctx.friction_newton and si.friction_converged:
            friction.newton_update(active, cons, si.constraint_impulse, new.v, h, self._mu[active.ob],
                                   self.ctx.smooth, every)
        elif len(active) and self.ctx.smooth > 0:
            friction.smooth_update(active, cons, si.constraint_impulse, new.v, h, self._mu[active.ob],
                                   self.ctx.smooth, every)
        elif len(active):
            friction.update(active, cons, si.constraint_impulse, new.v, h, self._mu[active.ob], every)
        return new, cons, t

    def _pulls(self, active: contacts.Planes, cons: Constraints, h: float,
               released: np.ndarray) -> Callable[[np.ndarray], bool]:
        """For :meth:`ImplicitIntegrator.step <implicit_cloth.integrators.base.ImplicitIntegrator.step>`'s
        ``redone``: whether a solve's constraint impulse ``J`` (N, 3) over the step ``h`` makes
        :meth:`_after_solve` release a contact of ``active`` and solve the round again (:meth:`_pulling`, on the
        normal force the friction update will give it), so that the integrator skips the friction's Newton
        iterations of a solve the round throws away. ``cons`` are ``active``'s constraints (the same order)."""
        idx, normal = active.idx, cons.normal

        def redone(J: np.ndarray) -> bool:
            return bool(np.any(self._pulling(idx, np.einsum("ij,ij->i", J[idx], normal) / h, h, released)))
        return redone

    def _pulling(self, idx: np.ndarray, force: np.ndarray, h: float, released: np.ndarray) -> np.ndarray:
        """Which contacts at vertices ``idx`` with normal forces ``force`` (N; negative: pulling the vertex towards
        the obstacle) are released within the step: a pull worth more than :data:`PULL_SPEED` of the vertex's
        velocity over ``h``, at a vertex not ``released`` in the step yet."""
        return (force * h < -PULL_SPEED * self.ctx.masses[idx]) & ~released[idx]

    def _after_solve(self, active: contacts.Planes, cons: Constraints, J: np.ndarray | None, v: np.ndarray,
                     h: float, settled: np.ndarray, switched: np.ndarray, released: np.ndarray,
                     first: bool = False, met: bool = False) -> tuple[contacts.Planes, bool]:
        """Friction states and releases from a solve; whether the step must be solved again.

        The friction changes of contacts not in ``settled`` (after the first solve: the contacts the step did
        not carry; after later ones: none) are solved again, and so are, after the ``first`` solve, the carried
        contacts on a moving obstacle that start to slide; the other changes wait for the next step. A contact
        pulling its vertex hard towards the obstacle is released now, lighter pulls next step.

        Why carried slips on moving obstacles: a sticking contact that leaves its friction cone and waits a
        step is held to the obstacle's velocity for that step. Against a static obstacle that only stops the
        vertex a step longer (it takes energy away); against a moving one it gives the vertex the obstacle's
        velocity, whatever the friction: a floor jerked sideways at 1 m/s under a resting cloth dragged it at
        1 m/s in one step instead of ``mu g`` per step. Solving every carried slip again (tried, static
        obstacles too) brought folds sliding down a cone to rest sooner (the 64² cone of
        ``benchmarks/contact_energy.py`` at dt 1/30: from 2.0 s against 3.6; 2.1 s at dt 1/120), but a 32²
        drape on a sphere at dt 1/30 later (1.9 s against 1.5; 1.3 s at dt 1/120) at 1.5 times the cost, and
        a resting 16² drape at dt 1/60 never settled (held vertices taking turns at sliding at 0.5 mm/s). A
        threshold on the excess over the cone (3-10 times the vertex's weight over the step) let the 16²
        drape settle, not the 32² one sooner, and missed the jerked floor (an excess of 6 weights).
        """
        mu = self._mu[active.ob]
        if self.ctx.friction_newton and met:     # friction solved in the step: forces and speeds only
            again = bool(np.any(friction.newton_update(active, cons, J, v, h, mu, self.ctx.smooth, switched)))
        elif self.ctx.smooth > 0:     # smoothed friction: every state change is solved again (friction.smooth_update)
            again = bool(np.any(friction.smooth_update(active, cons, J, v, h, mu, self.ctx.smooth, switched)))
        else:
            changed = friction.update(active, cons, J, v, h, mu, switched)
            redo = ~np.isin(active.idx, settled)
            if first:
                redo |= ~active.stick & np.any(cons.velocity != 0.0, axis=1)
            again = bool(np.any(changed & redo))
        pull = self._pulling(active.idx, active.force, h, released)
        if np.any(pull):
            released[active.idx[pull]] = True
            active = active.take(~pull)
            again = True
        return active, again

    def _finish(self, state: Any, new: Any, h: float, cons: Constraints, active: contacts.Planes,
                carried: np.ndarray, J: np.ndarray | None, limiter: Any, info: CollisionInfo,
                met: bool = False) -> float:
        """After the solves: inelastic contacts, strain limiting, the geometric fallback; the obstacles' work, J.

        The work: the contacts' impulses (normal, and tangential while sticking) and the kinetic friction
        force over the step times the obstacle's velocity at the contact, plus the velocity changes after.
        """
        work = 0.0
        if cons.n_contacts and J is not None:
            fr = cons.friction_force(new.v)
            work += float(np.einsum("ij,ij->", J[cons.contact] + h * fr, cons.velocity))
        # (a friction solved to its law on its convex potential reversed nothing)
        if len(active) and not (self.ctx.friction_newton and met):
            if self.ctx.smooth > 0:
                friction.stop_reversed_smooth(active, cons, new)
            else:
                friction.stop_reversed(active, cons, new)
        if len(active):
            work += friction.inelastic(active, cons, carried, state, new, self.ctx.restitution, self.ctx.masses)
        if limiter is not None:
            limiter.apply(new, h, planes=(cons.contact, cons.normal, cons.offset) if cons.n_contacts else None)
            if cons.n_contacts and len(limiter.pushed):     # the planes' pushes: impulses m dx / h along n
                m = self.ctx.masses[cons.contact]
                work += float(np.sum(m * limiter.pushed / h * np.einsum("ij,ij->i", cons.normal, cons.velocity)))
        v_before = new.v.copy()
        self.ctx.friction = False
        try:
            fb = fallback.respond(self.ctx, state, new, h)
        finally:
            self.ctx.friction = True
        work += fallback.impulse_work(self.ctx, v_before, new)
        info.fallback, info.failsafe, info.max_penetration = fb.contacts, fb.failsafe, fb.max_penetration
        info.candidates, info.toi = fb.candidates, fb.toi
        return work

    def _frame(self, before: Any, after: Any) -> contacts.Frame:
        c = self.ctx
        return contacts.Frame(before.x, after.x, before.t, after.t, c.thickness, c.edges, c.faces, c.free)

    def _carried(self, state: Any, h: float) -> tuple[contacts.Planes, np.ndarray]:
        """The contacts the step starts with: those held at the end of the step that produced ``state``.

        Their planes are taken anew at ``state`` (the contact tests at ``state`` with a reach of
        ``CONTACT_BAND`` thicknesses: vertex contacts on the tangent plane of the inflated surface at the
        nearest point, feature contacts as found again); a vertex that moved farther away, or whose contact
        pulled it in the last solve, is free. They keep their normal force and friction state. With no
        carried contacts (the first step, or after the state was assigned), the vertices within the band,
        sticking where there is friction, as new contacts. Returns the contacts and the vertices carried.
        """
        c = self.ctx
        prev = next((p for s, p in reversed(self._carry) if s is state), None)
        still = contacts.Frame(state.x, state.x, state.t, state.t + h, c.thickness, c.edges, c.faces, c.free,
                               reach=(CONTACT_BAND - 1.0) * c.thickness)
        near = contacts.detect(still, c.obstacles)
        near.stick &= self._mu[near.ob] > 0
        if prev is None:
            return near, np.zeros(0, dtype=np.int64)
        out = near.take(np.isin(near.idx, prev.idx))
        contacts.inherit(prev, out)
        return out, out.idx.copy()

    def _constraints(self, pins: Constraints, active: contacts.Planes, t0: float, h: float) -> Constraints:
        """World planes at ``t0 + h``, obstacle velocities and friction of the active contacts.

        The obstacle's velocity at a contact is its contact point's mean velocity over the step (the chord:
        a keyframe inside the step included).
        """
        if not len(active):
            return pins
        t1 = t0 + h
        k = len(active)
        n = np.empty((k, 3))
        offset = np.empty(k)
        u = np.empty((k, 3))
        for j, ob in enumerate(self.ctx.obstacles):
            sel = active.ob == j
            if not np.any(sel):
                continue
            c1, R1 = ob.motion.pose(t1)
            n[sel] = active.n[sel] @ R1.T
            offset[sel] = active.off[sel] + n[sel] @ c1
            u[sel] = (ob.motion.to_world(active.point[sel], t1) - ob.motion.to_world(active.point[sel], t0)) / h
        if self.ctx.smooth > 0:    # every contact held along its normal only, its friction a force of the solve
            mu = self._mu[active.ob]
            fr, damping = friction.smooth_model(active, mu, n, self.ctx.smooth)
            rub = pending = None
            if self.ctx.friction_newton:
                rub = mu * np.maximum(active.force, 0.0)
                pending = np.where(active.force == 0.0, mu, 0.0)     # new contacts: bound from the first solve
            return pins.with_contacts(active.idx, n, offset, u, friction=fr, damping=damping, rub=rub,
                                      slide_speed=self.ctx.smooth, pending=pending)
        stick, fr = friction.friction_forces(active, self._mu[active.ob])
        return pins.with_contacts(active.idx, n, offset, u, stick, fr)
