"""Collisions of the cloth with rigid obstacles: continuous detection, impulses, contact constraints.

Imported only by a scene with ``[[obstacles]]``. One step (Bridson, Fedkiw &
Anderson 2002, adapted to rigid obstacles):

1. Before the implicit solve (:meth:`Collider.constrain`): vertices resting on an
   obstacle are constrained through the Baraff-Witkin filter, ``S_i = I - n n^T``
   with a prescribed normal velocity equal to the obstacle's, tangential motion
   free. A contact is released when the constraint's impulse in the previous solve
   pulled the vertex towards the obstacle.
2. After the integrator proposes ``(x1, v1)`` (:meth:`Collider.respond`), with the
   start ``x0`` collision-free, per obstacle in its local frame (the cloth's start
   and end positions moved into the obstacle's frame at ``t0`` and ``t1``, i.e.
   linear relative motion; a keyframe inside the step is approximated by the
   chord from the pose at ``t0`` to the pose at ``t1``, see
   :class:`~implicit_cloth.collision.shapes.RigidMotion`):

   a. friction of the constrained contacts from the normal impulse of the solve;
   b. vertex sweeps: a vertex whose path comes within ``thickness / 2`` of the
      surface is stopped where it first comes within ``thickness``
      (:func:`~implicit_cloth.collision.shapes.Shape.sweep`), gets an inelastic
      impulse with friction there, and moves on with its new velocity for the rest
      of the step;
   c. proximity: a vertex ending within ``thickness`` of the surface is moved out
      along the normal to ``thickness``; an approaching normal velocity is removed;
   d. sharp features: obstacle corners and tips against cloth triangles, obstacle
      edges against cloth edges, by the exact coplanarity time of impact
      (:mod:`~implicit_cloth.collision.ccd`); a crossing stops the primitive's
      vertices approaching from the time of impact on, along the normal turned to
      the side the cloth came from, and a feature nearer than ``thickness`` pushes
      the primitive out (after a crossing, along that normal);
   e. edges: no point of a cloth edge nearer than ``thickness / 2`` (the smallest
      signed distance along it, by golden-section search on the convex shape).

   Mesh obstacles (no signed distance) replace b, c and e by the exact tests of
   cloth vertices against the faces that python-fcl's broad phase
   (:mod:`~implicit_cloth.collision.broadphase`) proposes, and use every mesh
   vertex and edge as a sharp feature in d (edge pairs also keep ``thickness / 2``).

   Rounds repeat until one finds nothing to correct, at most
   ``collision.max_iterations``. Vertices still in violation then are frozen to the
   obstacle (moved rigidly with it from their collision-free start, with its
   velocity): the fail-safe of Bridson et al.'s rigid impact zones, reported.

Pinned vertices are never moved (their inverse mass is 0 in every correction).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..constraints import Constraints
from ..integrators.base import StepInfo
from . import broadphase, ccd, contacts
from .features import FeatureStages, edge_minimum
from .mesh import MeshStages
from .response import PROXIMITY_SLACK, SETTLE_FRACTION, impulse
from .shapes import MeshShape, Plane, RigidMotion, Shape, build, local_aabb

#: A vertex path that comes within this fraction of the thickness counts as an impact.
IMPACT_FRACTION = 0.5
#: Passes of the fail-safe (each freezes the offenders and their neighbours).
FAILSAFE_PASSES = 4
#: A held contact stays held while its vertex is within this multiple of the thickness of the obstacle.
CONTACT_BAND = 1.25
#: A contact whose impulse pulls its vertex towards the obstacle by more than this change of velocity (m/s)
#: is released within the step (and the step solved again); lighter pulls are released from the next step on.
PULL_SPEED = 0.01
#: New contacts violated by at most this fraction of the thickness do not call for another solve: they are
#: held from the next step on, and the geometric response keeps them out in this one.
RESOLVE_FRACTION = 0.1



@dataclass
class Obstacle:
    """One rigid obstacle: its shape (local frame), its motion and its friction coefficient."""

    shape: Shape
    motion: RigidMotion
    friction: float
    spec: dict[str, Any] = field(default_factory=dict)


@dataclass
class CollisionInfo:
    """What the collision stage did in one step.

    Attributes
    ----------
    candidates : int
        Vertex paths and feature pairs tested exactly (after the bounding-box filter).
    contacts : int
        Vertices corrected (impulse or push) plus feature pairs responded to.
    resting : int
        Vertices constrained in the solve of this step.
    toi : float
        Earliest time of impact as a fraction of the step (nan if none).
    rounds : int
        Response rounds taken.
    failsafe : int
        Vertices frozen to an obstacle by the fail-safe.
    max_penetration : float
        Largest depth of a cloth vertex inside an obstacle after the response, m.
    t_collision : float
        Wall time of the collision stage (without the solves), s.
    solves : int
        Linear solves of the step (implicit methods: one, plus one per round that found new contacts).
    fallback : int
        Corrections the geometric response made after the solves (implicit methods): what the
        constrained solves left.
    work : float
        Work the obstacles did on the cloth in the step, J, computed from what they did: each contact's
        impulse times the obstacle's velocity at the contact point (normal impulse of the solve, friction
        force over the step, the fallback response's velocity changes), like the pins' work. Zero for
        obstacles that do not move. The energy balance of every step counts it as external work; the
        energy the contact treatment itself creates or removes is not in it.
    """

    candidates: int = 0
    contacts: int = 0
    resting: int = 0
    toi: float = float("nan")
    rounds: int = 0
    failsafe: int = 0
    max_penetration: float = 0.0
    t_collision: float = 0.0
    work: float = 0.0
    solves: int = 0
    fallback: int = 0

    def absorb(self, other: "CollisionInfo", accepted: bool = True) -> None:
        """Add a later substep's figures (adaptive stepping): counts summed, extremes kept, time summed.

        A discarded substep (``accepted=False``) adds only its time: its contacts were undone.
        """
        self.t_collision += other.t_collision
        if not accepted:
            return
        self.candidates += other.candidates
        self.contacts += other.contacts
        self.resting = max(self.resting, other.resting)
        if other.toi == other.toi and not self.toi <= other.toi:   # nan-aware minimum
            self.toi = other.toi
        self.rounds = max(self.rounds, other.rounds)
        self.failsafe += other.failsafe
        self.max_penetration = max(self.max_penetration, other.max_penetration)
        self.work += other.work
        self.solves += other.solves
        self.fallback += other.fallback


def _describe(spec: dict[str, Any]) -> str:
    keys = [k for k in ("shape", "center", "point", "radius", "size", "height", "path") if k in spec]
    return "{" + ", ".join(f"{k} = {spec[k]!r}" for k in keys) + "}"


def cloth_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


class Collider(FeatureStages, MeshStages):
    """Collision stage for one model and the validated ``obstacles`` and ``collision`` tables.

    Parameters
    ----------
    obstacles : list of dict
        Validated ``[[obstacles]]`` tables.
    settings : dict
        Validated ``[collision]`` table (``thickness`` m, ``restitution``, ``max_iterations``).
    model : Model
        The cloth (masses, faces, pins).
    """

    def __init__(self, obstacles: list[dict[str, Any]], settings: dict[str, Any], model: Any) -> None:
        self.model = model
        self.thickness = float(settings["thickness"])
        self.restitution = float(settings["restitution"])
        self.max_rounds = int(settings["max_iterations"])
        self.obstacles = []
        for spec in obstacles:
            shape, motion = build(spec)
            self.obstacles.append(Obstacle(shape, motion, float(spec["friction"]), spec))
        self._mu = np.array([ob.friction for ob in self.obstacles])
        self.faces = np.asarray(model.faces, dtype=np.int64)
        self.edges = cloth_edges(self.faces)
        self.inv_mass = model.inv_masses.copy()
        self.inv_mass[model.pinned] = 0.0
        self.free = self.inv_mass > 0
        self._n = model.n
        self._check_start(model.rest_positions, 0.0)
        #: (state, contacts held at its end) of the last steps: a step from that state starts with them
        self._carry: list[tuple[Any, contacts.Planes]] = []
        #: the last attempt at a step: (state, h, its contacts, its end velocities), for a nonlinear redo
        self._attempt: tuple[Any, float, contacts.Planes, np.ndarray] | None = None

    def _check_start(self, x: np.ndarray, t: float) -> None:
        """A :class:`SceneError` naming the obstacle if cloth vertices start inside it, deeper than the thickness."""
        from ..errors import SceneError

        for k, ob in enumerate(self.obstacles):
            depth = self.depths(k, x, t)
            bad = (depth > self.thickness) & self.free    # pins are the user's: never moved, never checked
            if np.any(bad):
                raise SceneError(
                    f"obstacles[{k}]: {int(bad.sum())} cloth vertices start inside it (the deepest "
                    f"{1e3 * float(depth.max()):.3g} mm, more than the thickness {self.thickness:g} m; the first is "
                    f"vertex {int(np.flatnonzero(bad)[0])}): move the obstacle or the cloth apart, got "
                    f"{_describe(ob.spec)}")

    def depths(self, k: int, x: np.ndarray, t: float) -> np.ndarray:
        """Depth (m, > 0 inside, 0 outside) of world points ``x`` inside obstacle ``k`` at time ``t``.

        Primitive shapes: minus the signed distance. Meshes: for a closed (watertight) mesh, the distance to
        the nearest face of the points whose winding number says they are inside; an open mesh has no inside
        (0 everywhere).
        """
        ob = self.obstacles[k]
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

    # ------------------------------------------------------------------ implicit step with contacts
    def step(self, integrator: Any, state: Any, h: float, pins: Constraints,
             limiter: Any = None, newton: int | None = None) -> tuple[Any, Any]:
        """One implicit step of ``h`` from the collision-free ``state`` with contacts as constraints of the solve.

        Solve, detect, constrain, solve again: the step is solved with the contacts carried from the
        previous step (:meth:`_carried`); contact detection on the proposed step (:func:`contacts.detect`)
        adds every vertex that would come nearer than the thickness to an obstacle, and Coulomb friction
        decides which contacts stick and which slide (:meth:`_friction`); while either changes, the step is
        solved again from the same state (warm-started), at most ``collision.max_iterations`` solves,
        each with ``newton`` Newton iterations (None: the solver's setting). A vertex that reached an
        obstacle in the step leaves it with the obstacle's normal velocity less ``restitution`` times its
        approach speed. ``limiter`` (strain limiting) then runs with the contact planes held, and the
        geometric response (:meth:`respond`, without friction) corrects what the solves left, counted as
        fallback corrections.

        Returns the new state and the step's :class:`~implicit_cloth.integrators.StepInfo`, whose
        ``collision`` is this stage's :class:`CollisionInfo`.
        """
        t_start = time.perf_counter()
        t1 = state.t + h
        active, carried = self._carried(state, h)
        total = StepInfo()
        info = CollisionInfo()
        guess = start = None
        last = self._attempt
        if newton is not None and newton > 1 and last is not None and last[0] is state and last[1] == h:
            # redone nonlinearly: from where the last attempt at this step ended, with its contacts
            active = contacts.merge(active, last[2])
            start = last[3]
        t_solve = 0.0
        cons = pins
        new = state
        self._switched = np.zeros(self._n, dtype=bool)
        self._released = np.zeros(self._n, dtype=bool)
        for rnd in range(self.max_rounds):
            cons = self._constraints(pins, active, state.t, h)
            ts = time.perf_counter()
            new, si = integrator.step(state, h, cons, guess, newton, start)
            t_solve += time.perf_counter() - ts
            start = None
            total.absorb(si)
            info.rounds = rnd + 1
            if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
                break
            changed = False
            if len(active):   # friction changes of contacts new in this step are solved again, the others wait
                switched = self._friction(active, cons, si.constraint_impulse, new.v, h)
                changed = bool(np.any(switched & ~np.isin(active.idx, carried)))
                # a contact pulling its vertex hard towards the obstacle is released now, lighter pulls next step
                pull = (active.force * h < -PULL_SPEED * self.model.masses[active.idx]) & \
                    ~self._released[active.idx]
                if np.any(pull):
                    self._released[active.idx[pull]] = True
                    active = active.take(~pull)
                    changed = True
            found = contacts.detect(self._frame(state, new), self.obstacles)
            if len(found):
                info.contacts += int(np.count_nonzero(~np.isin(found.idx, active.idx)))
                active = contacts.merge(active, found)
                changed |= float(found.viol.max()) > RESOLVE_FRACTION * self.thickness
            if not changed:
                break      # small new violations are held from the next step on; the response keeps them out now
            guess = new.v - state.v
        self._attempt = (state, h, active.take(slice(None)), new.v.copy())
        info.resting = len(active)
        info.solves = total.solves
        work = 0.0
        if cons.n_contacts and si.constraint_impulse is not None:
            # the obstacles' work: impulses of the contacts (normal, and tangential while sticking) and the
            # kinetic friction force over the step, times the obstacle's velocity at the contact
            J = si.constraint_impulse[cons.contact]
            work += float(np.einsum("ij,ij->", J + h * cons.friction, cons.velocity))
        if len(active) and np.all(np.isfinite(new.v)):
            self._stop_reversed(active, cons, new)
            work += self._impacts(active, cons, carried, state, new)
        if limiter is not None and np.all(np.isfinite(new.x)):
            limiter.apply(new, h, planes=(cons.contact, cons.normal, cons.offset) if cons.n_contacts else None)
        if np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v)):
            v_before = new.v.copy()
            fallback = self.respond(state, new, h, friction=False)
            work += self._impulse_work(v_before, new)
            info.fallback = fallback.contacts
            info.failsafe = fallback.failsafe
            info.max_penetration = fallback.max_penetration
            info.candidates = fallback.candidates
            info.toi = fallback.toi
        info.work = work
        self._carry = self._carry[-7:] + [(new, active.take(active.force >= 0.0))]
        info.t_collision = time.perf_counter() - t_start - t_solve
        total.collision = info
        return new, total

    def _frame(self, before: Any, after: Any) -> contacts.Frame:
        return contacts.Frame(before.x, after.x, before.t, after.t, self.thickness, self.edges, self.faces, self.free)

    def _carried(self, state: Any, h: float) -> tuple[contacts.Planes, np.ndarray]:
        """The contacts the step starts with: those held at the end of the step that produced ``state``.

        Their planes are taken anew at ``state`` (the contact tests at ``state`` with a reach of
        ``CONTACT_BAND`` thicknesses: vertex contacts on the tangent plane of the inflated surface at the
        nearest point, feature contacts as found again); a vertex that moved farther away, or whose contact
        pulled it in the last solve, is free. They keep their normal force and friction state. With no
        carried contacts (the first step, or after the state was assigned), the vertices within the band,
        sticking where there is friction, as new contacts. Returns the contacts and the vertices carried.
        """
        prev = next((p for s, p in reversed(self._carry) if s is state), None)
        still = contacts.Frame(state.x, state.x, state.t, state.t + h, self.thickness, self.edges, self.faces,
                               self.free, reach=(CONTACT_BAND - 1.0) * self.thickness)
        near = contacts.detect(still, self.obstacles)
        near.impact[:] = 0.0
        near.stick &= self._mu[near.ob] > 0
        if prev is None:
            return near, np.zeros(0, dtype=np.int64)
        out = near.take(np.isin(near.idx, prev.idx))
        contacts.inherit(prev, out)
        return out, out.idx.copy()

    def _constraints(self, pins: Constraints, active: contacts.Planes, t0: float, h: float) -> Constraints:
        """World planes at ``t0 + h``, obstacle velocities and friction of the active contacts.

        A sliding contact's kinetic friction force is ``-mu N s``, ``N`` its normal force in the last solve
        that held it and ``s`` its sliding direction relative to the obstacle.
        """
        if not len(active):
            return pins
        t1 = t0 + h
        k = len(active)
        n = np.empty((k, 3))
        offset = np.empty(k)
        u = np.empty((k, 3))
        for j, ob in enumerate(self.obstacles):
            sel = active.ob == j
            if not np.any(sel):
                continue
            c1, R1 = ob.motion.pose(t1)
            n[sel] = active.n[sel] @ R1.T
            offset[sel] = active.off[sel] + n[sel] @ c1
            # the contact point's mean velocity over the step (its chord: a keyframe inside the step included)
            u[sel] = (ob.motion.to_world(active.point[sel], t1) - ob.motion.to_world(active.point[sel], t0)) / h
        stick = active.stick & (self._mu[active.ob] > 0)
        fr = np.where(stick[:, None], 0.0,
                      -(self._mu[active.ob] * np.maximum(active.force, 0.0))[:, None] * active.slip)
        return pins.with_contacts(active.idx, n, offset, u, stick, fr)

    def _friction(self, active: contacts.Planes, cons: Constraints, J: np.ndarray | None, v: np.ndarray,
                  h: float) -> np.ndarray:
        """Update the contacts' normal forces and Coulomb states from a solve (in place); the contacts that changed.

        A sticking contact whose tangential impulse exceeds ``mu`` times its normal impulse slides (in the
        direction the impulse held it back from); a sliding one whose tangential velocity relative to the
        obstacle the friction reversed sticks. A sliding contact's direction follows its velocity. Within one
        step a contact changes its state at most once (``self._switched``), so that the solves of a step
        cannot cycle.
        """
        if J is None:
            return np.zeros(len(active), dtype=bool)
        n = cons.normal
        Jc = J[active.idx]
        jn = np.einsum("ij,ij->i", Jc, n)
        active.force = jn / h
        mu = self._mu[active.ob]
        jt = Jc - jn[:, None] * n
        jt_norm = np.sqrt(np.einsum("ij,ij->i", jt, jt))
        rel = v[active.idx] - cons.velocity
        vt = rel - np.einsum("ij,ij->i", rel, n)[:, None] * n
        vt_norm = np.sqrt(np.einsum("ij,ij->i", vt, vt))
        stick = active.stick & (mu > 0)
        free = ~self._switched[active.idx]
        to_slip = stick & free & (jt_norm > mu * np.maximum(jn, 0.0) * (1.0 + 1e-9) + 1e-15)
        sliding = ~stick & (mu > 0)
        to_stick = sliding & free & (np.einsum("ij,ij->i", vt, active.slip) <= 0.0)
        switched = to_slip | to_stick
        self._switched[active.idx[switched]] = True
        keep = sliding & ~to_stick & (vt_norm > 0)
        active.slip[to_slip] = -jt[to_slip] / jt_norm[to_slip, None]
        active.slip[keep] = vt[keep] / vt_norm[keep, None]
        active.slip[to_stick] = 0.0
        active.stick = (stick & ~to_slip) | to_stick
        return switched

    def _stop_reversed(self, active: contacts.Planes, cons: Constraints, after: Any) -> None:
        """Sliding contacts that the last solve's friction turned back stick: their tangential velocity becomes
        the obstacle's (a velocity change that only takes energy away; they stick from the next step on)."""
        if not cons.n_contacts:
            return
        pos = np.full(self._n, -1, dtype=np.int64)
        pos[cons.contact] = np.arange(cons.n_contacts)
        r = pos[active.idx]
        was_sliding = (r >= 0) & ~cons.stick[np.maximum(r, 0)]
        now = was_sliding & active.stick
        if not np.any(now):
            return
        k = r[now]
        i = cons.contact[k]
        n, u = cons.normal[k], cons.velocity[k]
        rel = after.v[i] - u
        rel_t = rel - np.einsum("ij,ij->i", rel, n)[:, None] * n
        after.v[i] -= rel_t

    def _impacts(self, active: contacts.Planes, cons: Constraints, carried: np.ndarray, before: Any,
                 after: Any) -> float:
        """Held contacts still approaching the obstacle at the end of the step take its normal velocity; those new
        in this step that were approaching at its start leave with it less ``restitution`` times their approach
        speed (velocities only: the positions stay on the planes). An inelastic contact: it only takes energy.

        Returns the work of these velocity changes against the obstacles' motion, J.
        """
        i, n, u = cons.contact, cons.normal, cons.velocity
        un = np.einsum("ij,ij->i", u, n)
        target = un.copy()
        if self.restitution > 0:
            w = np.einsum("ij,ij->i", before.v[i] - u, n)
            bounce = ~np.isin(i, carried) & (w < 0)
            target[bounce] -= self.restitution * w[bounce]
            rows = np.flatnonzero(np.isin(active.idx, i[bounce]))
            active.force[rows] = -1.0          # bouncing off: not carried
        vn = np.einsum("ij,ij->i", after.v[i], n)
        change = np.maximum(target - vn, 0.0)
        if not np.any(change):
            return 0.0
        dv = change[:, None] * n
        after.v[i] += dv
        return float(np.einsum("i,ij,ij->", self.model.masses[i], dv, u))

    def _impulse_work(self, v_before: np.ndarray, after: Any) -> float:
        """Work of the fallback response's velocity changes against the obstacles' motion, J.

        Each changed vertex is charged to the obstacle nearest to it.
        """
        if not any(ob.motion.moving for ob in self.obstacles):
            return 0.0
        moved = np.flatnonzero(np.any(after.v != v_before, axis=1))
        if not len(moved):
            return 0.0
        x = after.x[moved]
        owner = self._nearest_obstacle(x, after.t)
        u = np.zeros((len(moved), 3))
        for k, ob in enumerate(self.obstacles):
            sel = owner == k
            u[sel] = ob.motion.point_velocity(x[sel], after.t)
        dv = after.v[moved] - v_before[moved]
        return float(np.einsum("i,ij,ij->", self.model.masses[moved], dv, u))

    def _nearest_obstacle(self, x: np.ndarray, t: float) -> np.ndarray:
        """Index of the obstacle nearest to each world point at ``t`` (meshes: by their nearest sampled vertex)."""
        best = np.full(len(x), np.inf)
        owner = np.zeros(len(x), dtype=np.int64)
        for k, ob in enumerate(self.obstacles):
            p = ob.motion.to_local(x, t)
            if isinstance(ob.shape, MeshShape):
                V = ob.shape.vertices[::max(1, len(ob.shape.vertices) // 256)]
                d = np.min(np.linalg.norm(p[:, None, :] - V[None], axis=2), axis=1)
            else:
                d = ob.shape.distance(p)
            owner = np.where(d < best, k, owner)
            best = np.minimum(best, d)
        return owner

    # ------------------------------------------------------------------ after the step
    def respond(self, before: Any, after: Any, h: float, friction: bool = True) -> CollisionInfo:
        """Correct the proposed state ``after`` in place so that no cloth vertex, edge or triangle enters an obstacle.

        The geometric response (module docstring, step 2): the whole collision stage of an explicit
        step, and the fallback after the solves of an implicit one (there with ``friction=False``: the
        solve has applied it).

        Parameters
        ----------
        before : State
            The collision-free state at the start of the step.
        after : State
            The proposed state at ``before.t + h`` (its arrays are modified).
        h : float
            Step, s.
        """
        t_start = time.perf_counter()
        info = CollisionInfo()
        x0, x, v = before.x, after.x, after.v
        t0, t1 = before.t, after.t
        self._held: list[tuple[np.ndarray, ...]] = []
        self._current = 0
        self._friction_on = friction
        toi = np.inf
        for rnd in range(self.max_rounds):
            busy = False
            for k, ob in enumerate(self.obstacles):
                self._current = k
                b, s_min, cand, cont = self._round(ob, x0, x, v, t0, t1, h, info)
                busy |= b
                toi = min(toi, s_min)
                if rnd == 0:
                    info.candidates += cand
                info.contacts += cont
            info.rounds = rnd + 1
            if not busy:
                break
        else:
            info.failsafe = self._failsafe(x0, x, v, t0, t1, h)
        info.toi = float(toi) if np.isfinite(toi) else float("nan")
        info.max_penetration = self._penetration(x, t1)
        info.t_collision = time.perf_counter() - t_start
        return info

    def _friction_of(self, ob: Obstacle) -> float:
        return ob.friction if getattr(self, "_friction_on", True) else 0.0

    # ------------------------------------------------------------------ one round against one obstacle
    def _near(self, ob: Obstacle, p0: np.ndarray, p1: np.ndarray, margin: float) -> np.ndarray:
        """Bool mask of swept boxes (rows of p0 -> p1, or (K, m, 3) primitives) near the shape's local box."""
        if isinstance(ob.shape, Plane):
            lo = np.minimum(p0, p1)[..., 2]
            return lo.min(axis=-1) <= margin if lo.ndim > 1 else lo <= margin
        a, b = local_aabb(ob.shape)
        lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
        if lo.ndim == 3:
            lo, hi = lo.min(axis=1), hi.max(axis=1)
        return np.all((lo <= b + margin) & (hi >= a - margin), axis=1)

    def _round(self, ob: Obstacle, x0, x, v, t0, t1, h, info: CollisionInfo):
        if isinstance(ob.shape, MeshShape):
            return self._mesh_round(ob, x0, x, v, t0, t1, h)
        th = self.thickness
        mo, shape = ob.motion, ob.shape
        busy, contacts, cand = False, 0, 0
        s_min = np.inf
        p0 = mo.to_local(x0, t0)
        p1 = mo.to_local(x, t1)
        near = self._near(ob, p0, p1, th) & self.free
        vid = np.flatnonzero(near)
        cand += len(vid)
        # (b) vertex sweeps
        if len(vid):
            deep = shape.sweep(p0[vid], p1[vid], IMPACT_FRACTION * th)
            hit = vid[np.isfinite(deep)]
            if len(hit):
                s = shape.sweep(p0[hit], p1[hit], th)
                s = np.where(np.isfinite(s), s, deep[np.isfinite(deep)])
                s_min = min(s_min, float(s.min()))
                q = p0[hit] + s[:, None] * (p1[hit] - p0[hit])
                _, n_loc, _ = shape.closest(q)
                tc = t0 + s * h
                xc, n_w, u = self._world_at(mo, q, n_loc, tc)
                new, _ = impulse(v[hit], u, n_w, self._friction_of(ob), self.restitution)
                v[hit] = new
                x[hit] = xc + ((1.0 - s) * h)[:, None] * new
                busy, contacts = True, contacts + len(hit)
        # (c) proximity at the end of the step
        if len(vid):
            p1v = mo.to_local(x[vid], t1)
            phi, n_loc, _ = shape.closest(p1v)
            close = phi < th * (1.0 - PROXIMITY_SLACK)   # a vertex held on its plane is not moved
            if np.any(close):
                i = vid[close]
                push = th - phi[close]
                p1v = p1v[close] + push[:, None] * n_loc[close]
                c1, R1 = mo.pose(t1)
                x[i] = p1v @ R1.T + c1
                n_w = n_loc[close] @ R1.T
                u = mo.point_velocity(x[i], t1)
                new, _ = impulse(v[i], u, n_w, self._friction_of(ob), self.restitution)
                x[i] += h * (new - v[i]) - h * np.einsum("ij,ij->i", new - v[i], n_w)[:, None] * n_w
                v[i] = new
                contacts += len(i)
                busy |= bool(np.any(push > SETTLE_FRACTION * th))
        # (d) sharp features
        if len(shape.feature_points) or len(shape.feature_edges):
            b, c, k = self._features(ob, x0, x, v, t0, t1, h)
            busy |= b
            cand += c
            contacts += k
        # (e) edges: no point of a cloth edge nearer than the thickness (convex shapes)
        if not isinstance(shape, Plane):
            b, c, k = self._edge_proximity(ob, x0, x, v, t0, t1, h)
            busy |= b
            cand += c
            contacts += k
        return busy, s_min, cand, contacts

    @staticmethod
    def _world_at(mo: RigidMotion, q: np.ndarray, n_loc: np.ndarray, tc: np.ndarray):
        """World points, normals and obstacle velocities (K, 3) of local points and normals at per-point times ``tc``.

        ``x = c(tc) + R(tc) q``, ``n = R(tc) n_loc``, ``u = dc/dt + omega x (x - c)``: one pose per contact
        time, vectorised (:meth:`RigidMotion.pose` and :meth:`RigidMotion.point_velocity` take arrays of times).
        """
        c, R = mo.pose(tc)
        xc = np.einsum("kij,kj->ki", R, q) + c
        n_w = np.einsum("kij,kj->ki", R, n_loc)
        return xc, n_w, mo.point_velocity(xc, tc)

    def _record(self, idx: np.ndarray, n: np.ndarray, un: np.ndarray) -> None:
        """Remember vertices held by an edge or corner contact in this step (constrained in the next solve)."""
        self._held.append((idx, n, un, np.full(len(idx), self._current)))

    def _stop_approach(self, idx: np.ndarray, w: np.ndarray, n: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
        """Remove each primitive vertex's velocity towards the obstacle along ``n`` (relative to ``u``), in place.

        Per vertex rather than an impulse at the contact point shared by weights: that
        lever throws an already resting vertex off the surface when its neighbours are
        still falling. Where several primitives ask, the largest change is kept.
        """
        vn = np.einsum("kmj,kj->km", v[idx] - u[:, None, :], n)
        touch = (w > 1e-3) & (self.inv_mass[idx] > 0)
        k_, m_ = np.nonzero(touch)
        self._record(idx[k_, m_], n[k_], np.einsum("ij,ij->i", u[k_], n[k_]))
        app = (vn < 0) & touch
        if not np.any(app):
            return
        k_, m_ = np.nonzero(app)
        dv = -vn[k_, m_, None] * n[k_]
        mag = np.einsum("ij,ij->i", dv, dv)
        order = np.argsort(mag)
        best = np.zeros((self._n, 3))
        best[idx[k_, m_][order]] = dv[order]
        v += best

    # ------------------------------------------------------------------ fail-safe and bookkeeping
    def _violations(self, x0, x, t0, t1) -> np.ndarray:
        """Vertices whose path still crosses an obstacle's surface deeper than the impact fraction."""
        bad = np.zeros(self._n, dtype=bool)
        th = self.thickness
        for ob in self.obstacles:
            p0, p1 = ob.motion.to_local(x0, t0), ob.motion.to_local(x, t1)
            if isinstance(ob.shape, MeshShape):   # vertex paths still crossing a face
                vn = np.flatnonzero(self._near(ob, p0, p1, th) & self.free)
                cand = broadphase.candidates(ob.shape.bvh, p0, p1, vn, self.edges[:0], self.faces[:0], th)
                if broadphase.VERTEX_PATH in cand:
                    vi, fi = cand[broadphase.VERTEX_PATH]
                    F = ob.shape.faces[fi]
                    A, B, C = (ob.shape.vertices[F[:, j]] for j in range(3))
                    s, _ = ccd.point_triangle_toi(p0[vi], p1[vi], A, A, B, B, C, C, 0.0)
                    bad[vi[np.isfinite(s)]] = True
                continue
            vid = np.flatnonzero(self._near(ob, p0, p1, th) & self.free)
            if len(vid):
                s = ob.shape.sweep(p0[vid], p1[vid], IMPACT_FRACTION * th)
                bad[vid[np.isfinite(s) & (ob.shape.distance(p1[vid]) < (1 - SETTLE_FRACTION) * th)]] = True
                bad[vid[np.isfinite(s) & (ob.shape.distance(p0[vid]) >= IMPACT_FRACTION * th)]] = True
            if not isinstance(ob.shape, Plane):
                q = p1[self.edges]
                near = np.flatnonzero(self._near(ob, q, q, th))
                if len(near):
                    _, phi = edge_minimum(ob.shape, q[near, 0], q[near, 1])
                    bad[self.edges[near[phi < -SETTLE_FRACTION * th]].ravel()] = True
        return bad

    def _failsafe(self, x0, x, v, t0, t1, h) -> int:
        """Freeze vertices still in violation to the nearest obstacle: carried rigidly from their start.

        Repeated (each time with the one-ring of the offenders) while a violation remains, at most
        :data:`FAILSAFE_PASSES` times; returns the number of frozen vertices.
        """
        frozen = np.zeros(self._n, dtype=bool)
        for _ in range(FAILSAFE_PASSES):
            bad = self._violations(x0, x, t0, t1) & ~frozen
            if not bad.any():
                break
            frozen |= self._freeze(bad, x0, x, v, t0, t1)
        return int(frozen.sum())

    def _freeze(self, bad, x0, x, v, t0, t1) -> np.ndarray:
        # with their one-ring: a frozen vertex next to a moving one can still cut a feature
        ring = np.zeros(self._n, dtype=bool)
        e = self.edges
        ring[e[bad[e[:, 0]], 1]] = True
        ring[e[bad[e[:, 1]], 0]] = True
        bad |= ring
        bad &= self.free
        idx = np.flatnonzero(bad)
        if not len(idx):
            return bad
        owner = self._nearest_obstacle(x0[idx], t0)
        for k, ob in enumerate(self.obstacles):
            sel = idx[owner == k]
            if len(sel):
                x[sel] = ob.motion.to_world(ob.motion.to_local(x0[sel], t0), t1)
                v[sel] = ob.motion.point_velocity(x[sel], t1)
        return bad

    def _penetration(self, x: np.ndarray, t1: float) -> float:
        """The largest depth of a cloth vertex inside a primitive obstacle at ``t1``, m."""
        depth = 0.0
        for ob in self.obstacles:
            if isinstance(ob.shape, MeshShape):
                continue
            p = ob.motion.to_local(x, t1)
            vid = np.flatnonzero(self._near(ob, p, p, 0.0))
            if len(vid):
                depth = max(depth, float(np.max(-ob.shape.distance(p[vid]), initial=0.0)))
        return depth
