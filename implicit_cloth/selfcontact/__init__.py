"""Self-collision: the cloth against itself (within a piece, between pieces, between a mesh's components).

Imported only by a scene with ``[collision] self_collision = true``. After the step's solve and the obstacle
stage have proposed ``(x1, v1)`` from the collision-free start ``x0``, the step's motion is taken as linear,
``x(s) = x0 + s h vbar`` with the average velocity ``vbar = (x1 - x0) / h``, and corrected after Bridson, Fedkiw
& Anderson 2002 (§6-7):

1. **Candidates** (:mod:`~implicit_cloth.selfcontact.broadphase`): vertex-triangle and edge-edge pairs whose
   boxes over the step come within the thickness; pairs sharing a vertex are never pairs.
2. **Proximity** at the start: a pair nearer than ``thickness`` whose ``vbar`` approaches gets an inelastic
   impulse along the pair's normal that stops the approach (no more: pushing a resting pair apart would lift
   it against gravity with energy from nowhere), and Coulomb friction (``self_friction``) on the pair's
   tangential relative velocity, never reversing it.
3. **Impacts** (:mod:`~implicit_cloth.selfcontact.response`): the exact time of impact of every candidate
   (:func:`implicit_cloth.collision.ccd.point_triangle_toi` and ``edge_edge_toi``, the coplanarity cubic);
   each impact gets the same kind of impulse at the normal of its time of impact, which may part the pair by
   up to ``IMPACT_SEPARATION`` thicknesses at the end of the step, no faster than it came. Impulses of pairs that
   share a vertex are averaged (Jacobi), and the rounds repeat (``collision.max_iterations``).
4. **Rigid impact zones**, the fail-safe: vertices of impacts still left are gathered into zones (with the
   zones they touch) and each zone moves rigidly over the step with its own linear and angular momentum
   (Bridson et al. §7.4; Provot 1997), which cannot cross itself; zones that still hit merge, until no
   impact is left. The zones used are reported.

5. **Solved again** (implicit methods, :meth:`SelfCollider.step`): a correction made after a large step alone
   leaves the springs around the corrected vertex stretched by its neighbours' uncorrected motion (energy
   from nowhere), so the vertices moved are prescribed their corrected motion and the step is solved again
   (with the obstacles); what that solve proposes is corrected again (1-4), at most ``MAX_RESOLVES`` times.

Every impulse is equal and opposite between the pair's two primitives (weighted by the barycentric
coefficients and inverse masses) and never raises the pair's relative normal speed, so it conserves
momentum and takes kinetic energy away; a rigid zone's motion is the projection of its velocities onto
rigid motions, which only removes kinetic energy. The end velocity ``v1`` gets the same treatment with its
own relative velocities: only its approach is removed. Pinned vertices are not moved (infinite mass); a vertex that an
obstacle holds (within ``CONTACT_BAND`` thicknesses of a primitive obstacle at the end of the step) is not
moved into it: that part of its impulse is the obstacle's reaction, so a layer landing on cloth that lies on
the floor is stopped through it, and an impact zone with such a vertex moves with the vertices held. Only
static obstacles hold vertices so (a moving one's reaction would do work). Moving pins do: a pinned vertex
takes no impulse, its pin takes the reaction, so a pinned edge carried into the cloth pushes it; that work
(each pair's momentum to its free vertices times its pinned part's velocity, and an impact zone's momentum
from its pins times theirs) is booked in the step's energy balance with the pins' own (:attr:`SelfInfo.work`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..errors import SceneError
from . import broadphase
from .response import Pairs, Response, cloth_edges, pair_distances

#: Most solves again per step with the corrected vertices prescribed (each pass's corrected vertices join them).
MAX_RESOLVES = 2
#: A vertex within this many thicknesses of an obstacle at the end of the step is held by it (not moved here).
CONTACT_BAND = 1.5


@dataclass
class SelfInfo:
    """What self-collision did in one step.

    Attributes
    ----------
    candidates : int
        Vertex-triangle and edge-edge pairs from the broad phase.
    proximities : int
        Pairs nearer than the thickness at the start that got an impulse.
    impacts : int
        Impacts responded to with impulses (summed over the rounds).
    rounds : int
        Impulse rounds taken.
    zone_vertices : int
        Vertices moved rigidly in impact zones (the fail-safe).
    zones : int
        Impact zones at the end.
    unresolved : int
        Impacts left when the fail-safe gave up (its iteration cap): 0 unless reported.
    resolved : int
        Vertices prescribed their corrected motion in the step's second solve (implicit methods), 0 if none.
    t_broad, t_self : float
        Wall time of the broad phase and of the whole stage, s.
    """

    candidates: int = 0
    proximities: int = 0
    impacts: int = 0
    rounds: int = 0
    zone_vertices: int = 0
    zones: int = 0
    unresolved: int = 0
    resolved: int = 0
    t_broad: float = 0.0
    t_self: float = 0.0
    #: the pins' work on the cloth through the impulses and impact zones, J (a moving pinned vertex pushing
    #: the cloth through self-contact: the step's energy balance books it with the pins' own)
    work: float = 0.0

    def _combine(self, other: "SelfInfo", add: tuple[str, ...] = (), most: tuple[str, ...] = (),
                 last: tuple[str, ...] = ()) -> None:
        """Fields ``add`` summed with ``other``'s, ``most`` the larger of the two, ``last`` taken from ``other``."""
        for k in add:
            setattr(self, k, getattr(self, k) + getattr(other, k))
        for k in most:
            setattr(self, k, max(getattr(self, k), getattr(other, k)))
        for k in last:
            setattr(self, k, getattr(other, k))

    def merge(self, second: "SelfInfo", resolved: int) -> None:
        """The figures of the second pass of the same step (after the solve again with ``resolved`` vertices
        prescribed): impulses summed, the impact zones and what is unresolved the second pass's."""
        self._combine(second, add=("t_self", "t_broad", "proximities", "impacts", "work"),
                      most=("candidates", "rounds"), last=("zone_vertices", "zones", "unresolved"))
        self.resolved = resolved

    def absorb(self, other: "SelfInfo", accepted: bool = True) -> None:
        """Add a later substep's figures (counts summed, time summed; a discarded one adds only its time)."""
        self._combine(other, add=("t_self", "t_broad"))
        if accepted:
            self._combine(other, add=("candidates", "proximities", "impacts", "zone_vertices", "zones", "unresolved",
                                      "resolved", "work"), most=("rounds",))


class SelfCollider:
    """Self-collision stage of one model with the validated ``[collision]`` table.

    Parameters
    ----------
    model : Model
        The cloth (faces, masses, pins).
    settings : dict
        ``thickness`` (m, the cloth-cloth separation), ``self_friction`` (Coulomb coefficient between
        layers) and ``max_iterations`` (impulse rounds).

    Raises
    ------
    SceneError
        Naming ``collision.thickness`` when pairs of the cloth that share no vertex start nearer than the
        thickness (layers that would repel each other from the first step).
    """

    def __init__(self, model: Any, settings: dict[str, Any]) -> None:
        self.model = model
        self.thickness = float(settings["thickness"])
        self.friction = float(settings["self_friction"])
        self.rounds = int(settings["max_iterations"])
        self.faces = np.asarray(model.faces, dtype=np.int64)
        self.edges = cloth_edges(self.faces)
        self.masses = np.asarray(model.masses, dtype=float)
        inv = 1.0 / self.masses
        inv[model.pinned] = 0.0
        self.inv_mass = inv
        #: run totals of the accepted steps (:class:`SelfTotals`)
        self.totals = SelfTotals()
        self.response = Response(self.faces, self.edges, self.masses, self.thickness, self.friction, self.rounds)
        self.last_pairs: Pairs | None = None
        #: the pins' work through self-contact in the last step corrected (:attr:`SelfInfo.work`), J
        self.last_work = 0.0
        self._check_start(model.rest_positions)

    def _check_start(self, x: np.ndarray) -> None:
        th = self.thickness
        vf = broadphase.vertex_face_pairs(x, x, self.faces, th)
        ee = broadphase.edge_edge_pairs(x, x, self.edges, th)
        d_vf, d_ee = pair_distances(x, self.faces, self.edges, vf, ee)
        n_vf, n_ee = int(np.sum(d_vf < th)), int(np.sum(d_ee < th))
        if n_vf or n_ee:
            nearest = float(min(d_vf.min(initial=np.inf), d_ee.min(initial=np.inf)))
            raise SceneError(
                f"collision.thickness: {n_vf} vertex-triangle and {n_ee} edge-edge pairs of the cloth that share no "
                f"vertex start nearer than the thickness (the nearest {1e3 * nearest:.3g} mm apart), so those layers "
                f"would repel each other from the first step: use a thickness below {nearest:.3g} m (or a finer "
                f"cloth) or start the layers further apart, got {th:g}")

    def held(self, collider: Any, x: np.ndarray, t: float) -> np.ndarray | None:
        """Outward normals (N, 3) of the obstacles holding vertices at the end of the step (0 elsewhere): vertices
        within ``CONTACT_BAND`` thicknesses of a static primitive obstacle's surface; None without obstacles. (Mesh
        obstacles, which have no closest-point query, hold none here.)"""
        if collider is None:
            return None
        wall = np.zeros_like(x)
        band = CONTACT_BAND * max(self.thickness, collider.thickness)
        for ob in collider.obstacles:
            closest = getattr(ob.shape, "closest", None)
            if closest is None or not hasattr(ob.shape, "distance") or ob.motion.moving:
                continue    # a moving obstacle's reaction would do work: its vertices are free here
            p = ob.motion.to_local(x, t)
            near = np.flatnonzero(ob.shape.distance(p) < band)
            if len(near):
                _, n_loc, _ = closest(p[near])
                wall[near] = n_loc @ ob.motion.pose(t)[1].T
        return wall

    def respond(self, before: Any, after: Any, h: float, collider: Any = None,
                pairs: Pairs | None = None) -> SelfInfo:
        """Correct the proposed state ``after`` in place so that the cloth does not pass through itself.

        ``before`` is the collision-free state at the start of the step, ``collider`` the obstacle stage
        (or None): the vertices it holds are not moved. ``pairs``: candidates of an earlier pass of this step,
        used again while no vertex's end is farther than ``REBUILD_FRACTION`` thicknesses from where they
        were searched (:class:`~implicit_cloth.selfcontact.response.Response`). The candidates the pass ended
        with are kept in ``last_pairs``.
        """
        t0 = time.perf_counter()
        inv = self.inv_mass
        wall = self.held(collider, after.x, after.t)
        info = SelfInfo()
        x0, x1 = before.x, after.x
        tb = time.perf_counter()
        if pairs is None:
            pairs = Pairs.find(x0, x1, self.faces, self.edges, self.thickness, inv)
        info.t_broad = time.perf_counter() - tb
        info.candidates = pairs.count
        if pairs.count:
            pairs = self.response.run(x0, after, h, inv, pairs, info, wall)
        self.last_pairs = pairs
        info.t_self = time.perf_counter() - t0
        return info

    # ------------------------------------------------------------------ in the step, and the run's totals
    def step(self, before: Any, after: Any, h: float, collider: Any = None,
             resolve: Callable[[np.ndarray, np.ndarray], Any] | None = None) -> Any:
        """:meth:`respond` within a run; returns the step's end state. The attempt is booked, and counted once a
        later step starts from it.

        ``resolve(idx, vel)``: the step solved again with vertices ``idx`` prescribed to end it with velocity
        ``vel`` (their corrected motion); when given, the vertices moved by :meth:`respond` are so prescribed and
        what that solve proposes is corrected again (:meth:`respond`), up to ``MAX_RESOLVES`` times while a
        pass moves vertices not yet prescribed (they join the prescribed ones); the last pass's state is the
        end state. The second solve lets
        the corrected vertices' neighbours follow them within the step: corrections made after a large step
        alone leave the springs around them stretched (the step's energy would rise).
        """
        self.totals.accept(before)
        if not (np.all(np.isfinite(after.x)) and np.all(np.isfinite(after.v))):
            return after
        proposed = after.x.copy()
        info = self.respond(before, after, h, collider)
        fixed = np.zeros(len(proposed), dtype=bool)
        for _ in range(MAX_RESOLVES if resolve is not None else 0):
            moved = np.any(after.x != proposed, axis=1)
            if not np.any(moved):
                break
            fixed |= moved
            idx = np.flatnonzero(fixed)
            assert resolve is not None
            again = resolve(idx, (after.x[idx] - before.x[idx]) / h)
            if not (np.all(np.isfinite(again.x)) and np.all(np.isfinite(again.v))):
                break
            proposed = again.x.copy()
            info.merge(self.respond(before, again, h, collider, self.last_pairs), resolved=len(idx))
            after = again
        self.totals.attempt(after, info)
        self.last_work = info.work
        return after

    def report(self, state: Any, health: Any) -> dict[str, Any]:
        """The report's ``self_collision`` section (the run's accepted steps), unresolved impacts into ``health``."""
        tot = self.totals
        tot.accept(state)
        if tot.unresolved_steps:
            health.add("self_collision", tot.first_unresolved, tot.worst_unresolved, tot.unresolved_steps)
        a, n = tot.sum, max(tot.steps, 1)
        return {
            "thickness": self.thickness, "friction": self.friction,
            "steps": tot.steps, "candidates": a.candidates, "mean_candidates": a.candidates / n,
            "proximities": a.proximities, "impacts": a.impacts, "mean_impacts": a.impacts / n,
            "max_rounds": a.rounds, "resolve_steps": tot.resolve_steps, "resolved_vertices": a.resolved,
            "zone_steps": tot.zone_steps, "zone_vertices": a.zone_vertices,
            "max_zone_vertices": tot.max_zone_vertices, "unresolved_steps": tot.unresolved_steps,
            "time": a.t_self, "broad_phase_time": a.t_broad, "mean_time_per_step": a.t_self / n,
        }


class SelfTotals:
    """Run totals of the accepted steps: an attempt (adaptive stepping may redo a step) counts when a later step
    starts from the state it ended in; the others add only their time."""

    def __init__(self) -> None:
        self.reset(None)

    def reset(self, state: Any) -> None:
        self.sum = SelfInfo()
        self.steps = self.zone_steps = self.max_zone_vertices = self.unresolved_steps = self.resolve_steps = 0
        self.first_unresolved = 0.0
        self.worst_unresolved = 0
        self._pending: list[tuple[Any, SelfInfo]] = []

    def attempt(self, end: Any, info: SelfInfo) -> None:
        self._pending.append((end, info))

    def accept(self, state: Any) -> None:
        """``state`` was accepted: the attempt that ended in it counts, the others were discarded."""
        if not any(end is state for end, _ in self._pending):
            return
        for end, info in self._pending:
            ok = end is state
            self.sum.absorb(info, accepted=ok)
            if ok:
                self.steps += 1
                self.zone_steps += int(info.zone_vertices > 0)
                self.resolve_steps += int(info.resolved > 0)
                self.max_zone_vertices = max(self.max_zone_vertices, info.zone_vertices)
                if info.unresolved:
                    if not self.unresolved_steps:
                        self.first_unresolved = float(end.t)
                    self.unresolved_steps += 1
                    self.worst_unresolved = max(self.worst_unresolved, info.unresolved)
        self._pending = []
