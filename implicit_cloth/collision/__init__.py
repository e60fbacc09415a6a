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

from . import broadphase, ccd
from .features import FeatureStages, edge_minimum
from .mesh import MeshStages
from .response import SETTLE_FRACTION, impulse
from .shapes import MeshShape, Plane, RigidMotion, Shape, build, local_aabb

#: A vertex path that comes within this fraction of the thickness counts as an impact.
IMPACT_FRACTION = 0.5
#: Passes of the fail-safe (each freezes the offenders and their neighbours).
FAILSAFE_PASSES = 4
#: A vertex within this multiple of the thickness after the response is in resting contact.
CONTACT_BAND = 1.05


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
        Wall time of the collision stage, s.
    work : float
        Energy the obstacles gave the cloth in the step, J: the work of the resting-contact constraints in the
        solve (:meth:`Collider.constraint_work`) plus the energy change of the response (kinetic + gravity +
        springs after it minus before it), i.e. the work of moving obstacles less what inelastic contact and
        friction dissipated. The divergence check and adaptive stepping count it like the pins' work.
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
        self.faces = np.asarray(model.faces, dtype=np.int64)
        self.edges = cloth_edges(self.faces)
        self.inv_mass = model.inv_masses.copy()
        self.inv_mass[model.pinned] = 0.0
        self.free = self.inv_mass > 0
        n = model.n
        # resting contacts for the next solve: vertex, world normal, obstacle normal velocity, friction
        self.contact_idx = np.zeros(0, dtype=np.int64)
        self.contact_n = np.zeros((0, 3))
        self.contact_un = np.zeros(0)
        self.contact_obstacle = np.zeros(0, dtype=np.int64)
        self._constrained = np.zeros(0, dtype=np.int64)
        self._n = n

    def reset(self) -> None:
        """Forget the resting contacts (called when the state is assigned)."""
        self.contact_idx = np.zeros(0, dtype=np.int64)
        self.contact_n = np.zeros((0, 3))
        self.contact_un = np.zeros(0)
        self.contact_obstacle = np.zeros(0, dtype=np.int64)
        self._constrained = np.zeros(0, dtype=np.int64)

    def constraint_work(self, integrator: Any, v0: np.ndarray, v1: np.ndarray) -> float:
        """Work of the resting-contact constraints over the last solve, J: ``sum_i J_i . (v0_i + v1_i) / 2``.

        ``J`` is the impulse the constraints applied (``integrator.constraint_impulse``, N*s) on the vertices
        this collider constrained (pinned vertices' impulses are the pins' work, counted apart); ``v0``, ``v1``
        the velocities before and after the solve, m/s. Non-zero when the obstacle moves (it prescribes the
        normal velocity) or the contact holds the cloth against its weight while it slides.
        """
        J = getattr(integrator, "constraint_impulse", None)
        idx = self._constrained
        if J is None or not len(idx):
            return 0.0
        return float(np.einsum("ij,ij->", J[idx], 0.5 * (v0[idx] + v1[idx])))

    # ------------------------------------------------------------------ before the solve
    def constrain(self, integrator: Any, state: Any) -> int:
        """Put the resting contacts into an implicit integrator's filter (no-op for explicit ones).

        Returns the number of constrained vertices.
        """
        if not getattr(integrator, "implicit", False):
            return 0
        from ..solvers import Filter

        keep = np.ones(len(self.contact_idx), dtype=bool)
        J = getattr(integrator, "constraint_impulse", None)
        if J is not None and len(self._constrained) and len(self.contact_idx):
            # released: the constraint pulled the vertex towards the obstacle in the last solve
            pulled = np.zeros(self._n, dtype=bool)
            jn = np.einsum("ij,ij->i", J[self._constrained], self._last_n)
            pulled[self._constrained[jn < 0]] = True
            keep &= ~pulled[self.contact_idx]
        idx, nrm, un = self.contact_idx[keep], self.contact_n[keep], self.contact_un[keep]
        self._constrained, self._last_n = idx, nrm
        if not len(idx):
            integrator.filter = Filter(self._n, self.model.pinned)
            integrator.extra_dv = None
            return 0
        S = np.eye(3)[None] - nrm[:, :, None] * nrm[:, None, :]
        integrator.filter = Filter(self._n, self.model.pinned, idx, S)
        z = np.zeros((self._n, 3))
        vn = np.einsum("ij,ij->i", state.v[idx], nrm)
        z[idx] = (un - vn)[:, None] * nrm
        integrator.extra_dv = z
        return len(idx)

    # ------------------------------------------------------------------ after the step
    def respond(self, before: Any, after: Any, h: float, integrator: Any = None) -> CollisionInfo:
        """Correct the proposed state ``after`` in place so that no cloth vertex, edge or triangle enters an obstacle.

        Parameters
        ----------
        before : State
            The collision-free state at the start of the step.
        after : State
            The integrator's proposed state at ``before.t + h`` (its arrays are modified).
        h : float
            Step, s.
        integrator : Integrator, optional
            Supplies the contact constraints' impulses of the last solve (for friction).
        """
        t_start = time.perf_counter()
        info = CollisionInfo(resting=len(self._constrained))
        x0, x, v = before.x, after.x, after.v
        t0, t1 = before.t, after.t
        self._held: list[tuple[np.ndarray, ...]] = []
        self._current = 0
        self._resting_friction(x, v, h, t1, integrator)
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
        info.max_penetration = self._update_contacts(x, v, t1, h)
        info.t_collision = time.perf_counter() - t_start
        return info

    def _resting_friction(self, x, v, h, t1, integrator) -> None:
        """Coulomb friction of the constrained contacts, bounded by the normal impulse of the solve."""
        idx = self._constrained
        J = getattr(integrator, "constraint_impulse", None)
        if not len(idx) or J is None:
            return
        n = self._last_n
        dvn = np.einsum("ij,ij->i", J[idx], n) * self.inv_mass[idx]
        mu = np.empty(len(idx))
        u = np.empty((len(idx), 3))
        for k, ob in enumerate(self.obstacles):
            sel = self.contact_obstacle_of(idx) == k
            mu[sel] = ob.friction
            u[sel] = ob.motion.point_velocity(x[idx[sel]], t1)
        new, _ = impulse(v[idx], u, n, mu, 0.0, dvn)
        x[idx] += h * (new - v[idx])
        v[idx] = new

    def contact_obstacle_of(self, idx: np.ndarray) -> np.ndarray:
        lookup = np.full(self._n, -1, dtype=np.int64)
        lookup[self.contact_idx] = self.contact_obstacle
        return lookup[idx]

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
                new, _ = impulse(v[hit], u, n_w, ob.friction, self.restitution)
                v[hit] = new
                x[hit] = xc + ((1.0 - s) * h)[:, None] * new
                busy, contacts = True, contacts + len(hit)
        # (c) proximity at the end of the step
        if len(vid):
            p1v = mo.to_local(x[vid], t1)
            phi, n_loc, _ = shape.closest(p1v)
            close = phi < th
            if np.any(close):
                i = vid[close]
                push = th - phi[close]
                p1v = p1v[close] + push[:, None] * n_loc[close]
                c1, R1 = mo.pose(t1)
                x[i] = p1v @ R1.T + c1
                n_w = n_loc[close] @ R1.T
                u = mo.point_velocity(x[i], t1)
                new, _ = impulse(v[i], u, n_w, ob.friction, self.restitution)
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
        best = np.full(len(idx), np.inf)
        owner = np.zeros(len(idx), dtype=np.int64)
        for k, ob in enumerate(self.obstacles):
            if isinstance(ob.shape, MeshShape):   # no signed distance: the nearest vertex of the mesh
                p = ob.motion.to_local(x0[idx], t0)
                d = np.min(np.linalg.norm(p[:, None, :] - ob.shape.vertices[None, ::max(1, len(ob.shape.vertices)
                                                                                       // 256)], axis=2), axis=1)
            else:
                d = ob.shape.distance(ob.motion.to_local(x0[idx], t0))
            owner = np.where(d < best, k, owner)
            best = np.minimum(best, d)
        for k, ob in enumerate(self.obstacles):
            sel = idx[owner == k]
            if len(sel):
                x[sel] = ob.motion.to_world(ob.motion.to_local(x0[sel], t0), t1)
                v[sel] = ob.motion.point_velocity(x[sel], t1)
        return bad

    def _update_contacts(self, x, v, t1, h) -> float:
        """Record resting contacts for the next solve; return the largest penetration depth, m."""
        th = self.thickness
        idx_l, n_l, un_l, ob_l = [], [], [], []
        depth = 0.0
        taken = np.zeros(self._n, dtype=bool)
        for k, ob in enumerate(self.obstacles):
            if isinstance(ob.shape, MeshShape):   # its contacts are recorded by the response (self._held)
                continue
            p = ob.motion.to_local(x, t1)
            vid = np.flatnonzero(self._near(ob, p, p, CONTACT_BAND * th))
            if not len(vid):
                continue
            phi, n_loc, _ = ob.shape.closest(p[vid])
            depth = max(depth, float(np.max(-phi, initial=0.0)))
            c = (phi <= CONTACT_BAND * th) & self.free[vid] & ~taken[vid]
            i = vid[c]
            if not len(i):
                continue
            _, R = ob.motion.pose(t1)
            n_w = n_loc[c] @ R.T
            u = ob.motion.point_velocity(x[i], t1)
            un = np.einsum("ij,ij->i", u, n_w)
            # not separating: leaving at less than SETTLE_FRACTION of the thickness per step
            approach = np.einsum("ij,ij->i", v[i], n_w) - un <= SETTLE_FRACTION * th / h
            i, n_w, un = i[approach], n_w[approach], un[approach]
            taken[i] = True
            idx_l.append(i)
            n_l.append(n_w)
            un_l.append(un)
            ob_l.append(np.full(len(i), k))
        if self._held:   # vertices held by edges and corners: the last request per vertex
            hi, hn, hu, hk = (np.concatenate(a) for a in zip(*self._held))
            last = np.zeros(self._n, dtype=np.int64) - 1
            last[hi] = np.arange(len(hi))
            j = last[(last >= 0) & ~taken]
            if len(j):
                rel = np.einsum("ij,ij->i", v[hi[j]], hn[j]) - hu[j] <= SETTLE_FRACTION * th / h
                j = j[rel]
                idx_l.append(hi[j])
                n_l.append(hn[j])
                un_l.append(hu[j])
                ob_l.append(hk[j])
        if idx_l:
            self.contact_idx = np.concatenate(idx_l)
            self.contact_n = np.concatenate(n_l)
            self.contact_un = np.concatenate(un_l)
            self.contact_obstacle = np.concatenate(ob_l)
        else:
            self.contact_idx = np.zeros(0, dtype=np.int64)
            self.contact_n = np.zeros((0, 3))
            self.contact_un = np.zeros(0)
            self.contact_obstacle = np.zeros(0, dtype=np.int64)
        return depth
