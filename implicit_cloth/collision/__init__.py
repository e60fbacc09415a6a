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
   linear relative motion):

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
from scipy.spatial.transform import Rotation

from . import broadphase, ccd
from .response import impulse, spread
from .shapes import MeshShape, Motion, Plane, Shape, build, local_aabb

#: A vertex path that comes within this fraction of the thickness counts as an impact.
IMPACT_FRACTION = 0.5
#: Corrections below this fraction of the thickness do not call for another round.
SETTLE_FRACTION = 0.02
#: Golden-section steps for the nearest point of an edge (0.618^30 ~ 5e-7 of the edge).
GOLDEN_STEPS = 30
#: Points along cloth edges are kept this fraction of the thickness from a surface.
EDGE_FRACTION = 0.5
#: Bisection steps in time for where an edge first entered a shape.
ENTRY_BISECTIONS = 8
#: Passes of the fail-safe (each freezes the offenders and their neighbours).
FAILSAFE_PASSES = 4
#: A vertex within this multiple of the thickness after the response is in resting contact.
CONTACT_BAND = 1.05


@dataclass
class Obstacle:
    """One rigid obstacle: its shape (local frame), its motion and its friction coefficient."""

    shape: Shape
    motion: Motion
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
    """

    candidates: int = 0
    contacts: int = 0
    resting: int = 0
    toi: float = float("nan")
    rounds: int = 0
    failsafe: int = 0
    max_penetration: float = 0.0
    t_collision: float = 0.0


def edge_minimum(shape: Shape, a0: np.ndarray, a1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter ``a`` (K,) and value (K,) m of the smallest signed distance along segments a0 -> a1.

    The signed distance of a convex shape is convex, so along a segment it has one
    minimum, found by golden-section search (:data:`GOLDEN_STEPS` steps).
    """
    d = a1 - a0
    lo, hi = np.zeros(len(a0)), np.ones(len(a0))
    g = 0.5 * (np.sqrt(5.0) - 1.0)
    m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1 = shape.distance(a0 + m1[:, None] * d)
    f2 = shape.distance(a0 + m2[:, None] * d)
    for _ in range(GOLDEN_STEPS):
        left = f1 < f2                       # the minimum lies in [lo, m2], else in [m1, hi]
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
        n1 = np.where(left, hi - g * (hi - lo), m2)
        n2 = np.where(left, m1, lo + g * (hi - lo))
        fn = shape.distance(a0 + np.where(left, n1, n2)[:, None] * d)
        f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
        m1, m2 = n1, n2
    a = 0.5 * (lo + hi)
    ends = np.column_stack([shape.distance(a0), shape.distance(a1), shape.distance(a0 + a[:, None] * d)])
    best = np.argmin(ends, axis=1)
    a = np.choose(best, [np.zeros(len(a0)), np.ones(len(a0)), a])
    return a, ends[np.arange(len(a0)), best]


def cloth_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


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
    def _world_at(mo: Motion, q: np.ndarray, n_loc: np.ndarray, tc: np.ndarray):
        """World points, normals and obstacle velocities at per-point times ``tc``."""
        if not mo.moving:
            c, R = mo.pose(0.0)
            xc = q @ R.T + c
            return xc, n_loc @ R.T, np.zeros_like(xc)
        xc = np.empty_like(q)
        n_w = np.empty_like(q)
        if np.any(mo.angular_velocity):   # one rotation per contact time
            R = Rotation.from_rotvec(tc[:, None] * mo.angular_velocity).as_matrix() @ mo.rotation
            xc = np.einsum("kij,kj->ki", R, q) + mo.center + tc[:, None] * mo.velocity
            n_w = np.einsum("kij,kj->ki", R, n_loc)
        else:
            _, R = mo.pose(0.0)
            xc = q @ R.T + mo.center + tc[:, None] * mo.velocity
            n_w = n_loc @ R.T
        u = mo.velocity + np.cross(mo.angular_velocity, xc - (mo.center + tc[:, None] * mo.velocity))
        return xc, n_w, u

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

    @staticmethod
    def _inner_point(shape: Shape) -> np.ndarray:
        """A point inside the (convex) shape, local frame: the centre of its bounding box."""
        a, b = local_aabb(shape)
        return 0.5 * (a + b)

    def _edge_proximity(self, ob: Obstacle, x0, x, v, t0, t1, h) -> tuple[bool, int, int]:
        """Keep every point of the cloth's edges out of a convex shape (step e).

        The signed distance of a convex shape is a convex function, so along an edge
        ``x(a) = (1 - a) x_i + a x_j`` its minimum is found by golden-section search.
        An edge whose minimum is below ``EDGE_FRACTION * thickness`` is moved out
        along the normal there, shared between its two vertices by the weights
        ``(1 - a, a)``. An edge that ends deeper than the thickness swept into the
        shape during the step (across a strongly curved part, such as near a cone's
        tip, between two vertices outside): it is moved out across the tangent plane
        where it first entered (found by bisection in time), not towards the nearest
        surface, which may be the far side.
        """
        th = self.thickness
        mo, shape = ob.motion, ob.shape
        _, R1 = mo.pose(t1)
        p = mo.to_local(x, t1)
        q = p[self.edges]
        near = np.flatnonzero(self._near(ob, q, q, th))
        if not len(near):
            return False, 0, 0
        a0, a1 = q[near, 0], q[near, 1]
        d = a1 - a0
        a, phi = edge_minimum(shape, a0, a1)
        phi, n_loc, _ = shape.closest(a0 + a[:, None] * d)
        # kept at EDGE_FRACTION of the thickness (a smooth surface's sag between two vertices
        # at the thickness is left alone)
        target = EDGE_FRACTION * th
        act = phi < target
        # the ends are the vertices, kept out by steps b and c
        act &= (a > 1e-6) & (a < 1 - 1e-6)
        if not np.any(act):
            return False, len(near), 0
        deep = np.flatnonzero(act & (phi < -th))
        if len(deep):
            e = self.edges[near[deep]]
            s0 = mo.to_local(x0, t0)[e]
            lo, hi = np.zeros(len(deep)), np.ones(len(deep))
            for _ in range(ENTRY_BISECTIONS):
                mid = 0.5 * (lo + hi)
                qm = s0 + mid[:, None, None] * (q[near[deep]] - s0)
                _, fm = edge_minimum(shape, qm[:, 0], qm[:, 1])
                inside = fm < target
                hi = np.where(inside, mid, hi)
                lo = np.where(inside, lo, mid)
            qe = s0 + hi[:, None, None] * (q[near[deep]] - s0)
            ae, _ = edge_minimum(shape, qe[:, 0], qe[:, 1])
            _, ne, ce = shape.closest(qe[:, 0] + ae[:, None] * (qe[:, 1] - qe[:, 0]))
            a[deep] = ae
            n_loc[deep] = ne
            pe = a0[deep] + ae[:, None] * d[deep]
            phi[deep] = np.einsum("ij,ij->i", pe - ce, ne)     # height above the entry's tangent plane
        idx = self.edges[near[act]]
        w = np.column_stack([1.0 - a[act], a[act]])
        deficit = np.maximum(target - phi[act], 0.0)
        n_w = n_loc[act] @ R1.T
        change, _ = spread(self._n, idx, w, self.inv_mass, deficit[:, None] * n_w)
        x += change
        self._stop_approach(idx, w, n_w, mo.point_velocity(np.einsum("km,kmj->kj", w, x[idx]), t1), v)
        return bool(np.any(deficit > SETTLE_FRACTION * th)), len(near), int(act.sum())

    def _features(self, ob: Obstacle, x0, x, v, t0, t1, h):
        """Obstacle corners vs cloth triangles and obstacle edges vs cloth edges (step d)."""
        th = self.thickness
        mo, shape = ob.motion, ob.shape
        busy, cand, contacts = False, 0, 0
        fp, fe = shape.feature_points, shape.feature_edges
        for kind in ("vf", "ee"):
            prims = self.faces if kind == "vf" else self.edges
            feats = fp if kind == "vf" else fe
            if not len(feats):
                continue
            q0 = mo.to_local(x0, t0)[prims]            # (K, m, 3)
            q1 = mo.to_local(x, t1)[prims]
            near = np.flatnonzero(self._near(ob, q0, q1, th))
            if not len(near):
                continue
            lo = np.minimum(q0[near], q1[near]).min(axis=1) - th
            hi = np.maximum(q0[near], q1[near]).max(axis=1) + th
            if kind == "vf":
                flo = fhi = feats                      # (F, 3)
            else:
                flo, fhi = feats.min(axis=1), feats.max(axis=1)
            m = np.all((lo[None] <= fhi[:, None]) & (hi[None] >= flo[:, None]), axis=2)   # (F, K)
            fi, kj = np.nonzero(m)
            if not len(fi):
                continue
            pr = near[kj]
            cand += len(pr)
            b, k = self._feature_pairs(ob, kind, prims, q0, q1, pr, fi, feats, x0, x, v, t0, t1, h)
            busy |= b
            contacts += k
        return busy, cand, contacts

    def _feature_pairs(self, ob: Obstacle, kind: str, prims: np.ndarray, q0: np.ndarray, q1: np.ndarray,
                       pr: np.ndarray, fi: np.ndarray, feats: np.ndarray, x0, x, v, t0, t1, h,
                       ee_proximity: bool = False) -> tuple[bool, int]:
        """Exact tests and response for candidate pairs: obstacle point ``feats[fi]`` vs cloth triangle
        ``prims[pr]`` (kind "vf") or obstacle edge ``feats[fi]`` vs cloth edge ``prims[pr]`` (kind "ee").

        ``q0``, ``q1`` are the primitives' corners (K, m, 3) at the start and end, local frame.
        """
        th = self.thickness
        mo = ob.motion
        c1, R1 = mo.pose(t1)
        tol = 0.1 * th
        busy, contacts = False, 0
        A0, A1 = q0[pr], q1[pr]
        if kind == "vf":
            f = feats[fi]
            s, side = ccd.point_triangle_toi(f, f, A0[:, 0], A1[:, 0], A0[:, 1], A1[:, 1],
                                             A0[:, 2], A1[:, 2], tol)
        else:
            e0, e1 = feats[fi, 0], feats[fi, 1]
            s, side = ccd.edge_edge_toi(A0[:, 0], A1[:, 0], A0[:, 1], A1[:, 1], e0, e0, e1, e1, tol)
        hit = np.isfinite(s)
        # (d1) crossings in this step: an inelastic impulse at the time of impact, applied to the
        # primitive's motion over the whole step (x = x0 + h v), along the normal oriented to the
        # side the cloth came from; a later round's proximity test then keeps it at the thickness
        if np.any(hit):
            hi_ = np.flatnonzero(hit)
            sh = s[hi_, None, None]
            As = A0[hi_] + sh * (A1[hi_] - A0[hi_])
            if kind == "vf":
                _, ws = ccd.point_triangle_closest(f[hi_], As[:, 0], As[:, 1], As[:, 2])
                ns = np.cross(As[:, 1] - As[:, 0], As[:, 2] - As[:, 0])
            else:
                a_s, _ = ccd.segment_closest(As[:, 0], As[:, 1], e0[hi_], e1[hi_])
                ws = np.column_stack([1.0 - a_s, a_s])
                ns = np.cross(As[:, 1] - As[:, 0], e1[hi_] - e0[hi_])
            nns = np.sqrt(np.einsum("ij,ij->i", ns, ns))
            ok = (nns > 1e-14) & (side[hi_] != 0)
            dh = -side[hi_, None] * ns / np.where(ok, nns, 1.0)[:, None]
            # from the time of impact, every vertex of the primitive stops approaching along dh
            # (relative to the obstacle, with its mean velocity over the step):
            # the primitive's point then cannot approach either, and no vertex is levered
            # away (an impulse at the point, shared by weights, throws an already stopped
            # vertex off the surface)
            vrel = (A1[hi_] - A0[hi_]) / h                                  # (K, m, 3), local
            vn = np.einsum("kmj,kj->km", vrel, dh)
            app = ok[:, None] & (vn < 0) & (ws > 1e-3)
            if np.any(app):
                k_, m_ = np.nonzero(app)
                vid = prims[pr[hi_[k_]], m_]
                dv = (-vn[k_, m_, None] * dh[k_]) @ R1.T
                dv *= (self.inv_mass[vid] > 0)[:, None]
                best = np.zeros((self._n, 3))
                when = np.zeros(self._n)
                # one change per vertex: the largest requested (they share a direction locally),
                # applied from the time of impact: x = x(s) + (1 - s) h v'
                mag = np.sqrt(np.einsum("ij,ij->i", dv, dv))
                order = np.argsort(mag)
                best[vid[order]] = dv[order]
                when[vid[order]] = s[hi_[k_]][order]
                x += (h * (1.0 - when))[:, None] * best
                v += best
                nw = dh[k_] @ R1.T
                self._record(vid, nw, np.einsum("ij,ij->i", mo.point_velocity(x[vid], t1), nw))
                busy = True
                contacts += int(np.any(app, axis=1).sum())
        if kind == "ee":
            if ee_proximity:   # meshes: no signed distance, so edges keep EDGE_FRACTION of the thickness here
                b, k = self._edge_edge_proximity(ob, prims, pr, feats[fi, 0], feats[fi, 1], hit, side, x, v, t1)
                busy |= b
                contacts += k
            # primitives: without a crossing, edges are kept out by the distance along them (step e)
            return busy, contacts
        # (d2) proximity: a corner nearer than the thickness pushes the triangle away along the gap
        p1 = mo.to_local(x, t1)[prims[pr]]
        qc, w = ccd.point_triangle_closest(f, p1[:, 0], p1[:, 1], p1[:, 2])
        gap = qc - f
        dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
        # after a crossing in this step, along the triangle's normal turned to the side it came from
        # (it may end touching, or still a little across); otherwise along the gap
        nt = np.cross(p1[:, 1] - p1[:, 0], p1[:, 2] - p1[:, 0])
        nn = np.sqrt(np.einsum("ij,ij->i", nt, nt))
        crossed = hit & (side != 0) & (nn > 1e-14)
        dd = np.zeros_like(gap)
        dd[crossed] = -side[crossed, None] * nt[crossed] / nn[crossed, None]
        plain = ~crossed & (dist > 1e-12)
        dd[plain] = gap[plain] / dist[plain, None]
        sep = np.einsum("ij,ij->i", gap, dd)
        act = (crossed | plain) & (sep < th)
        if not np.any(act):
            return busy, contacts
        d = dd[act]
        deficit = th - sep[act]
        idx = prims[pr[act]]
        wa = w[act]
        change, _ = spread(self._n, idx, wa, self.inv_mass, (deficit[:, None] * d) @ R1.T)
        x += change
        # velocity: the triangle's vertices stop approaching the feature
        self._stop_approach(idx, wa, d @ R1.T, mo.point_velocity(f[act] @ R1.T + c1, t1), v)
        contacts += int(act.sum())
        busy |= bool(np.any(deficit > SETTLE_FRACTION * th))
        return busy, contacts

    def _edge_edge_proximity(self, ob: Obstacle, prims, pr, e0, e1, hit, side, x, v, t1) -> tuple[bool, int]:
        """Cloth edges ``prims[pr]`` nearer than ``EDGE_FRACTION * thickness`` to obstacle edges ``e0 e1`` are pushed away.

        Along the gap between the closest points; after a crossing in this step, along
        ``(cloth edge) x (obstacle edge)`` turned to the side the cloth edge came from.
        """
        th = self.thickness
        mo = ob.motion
        c1, R1 = mo.pose(t1)
        target = EDGE_FRACTION * th
        p1 = mo.to_local(x, t1)[prims[pr]]
        a, b = ccd.segment_closest(p1[:, 0], p1[:, 1], e0, e1)
        gap = (p1[:, 0] + a[:, None] * (p1[:, 1] - p1[:, 0])) - (e0 + b[:, None] * (e1 - e0))
        dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
        nx = np.cross(p1[:, 1] - p1[:, 0], e1 - e0)
        nn = np.sqrt(np.einsum("ij,ij->i", nx, nx))
        crossed = hit & (side != 0) & (nn > 1e-14)
        dd = np.zeros_like(gap)
        dd[crossed] = -side[crossed, None] * nx[crossed] / nn[crossed, None]
        plain = ~crossed & (dist > 1e-12)
        dd[plain] = gap[plain] / dist[plain, None]
        sep = np.einsum("ij,ij->i", gap, dd)
        act = (crossed | plain) & (sep < target) & (a > 1e-6) & (a < 1 - 1e-6)
        if not np.any(act):
            return False, 0
        d = dd[act]
        idx = prims[pr[act]]
        w = np.column_stack([1.0 - a[act], a[act]])
        deficit = target - sep[act]
        change, _ = spread(self._n, idx, w, self.inv_mass, (deficit[:, None] * d) @ R1.T)
        x += change
        g = (e0 + b[:, None] * (e1 - e0))[act] @ R1.T + c1
        self._stop_approach(idx, w, d @ R1.T, mo.point_velocity(g, t1), v)
        return bool(np.any(deficit > SETTLE_FRACTION * th)), int(act.sum())

    # ------------------------------------------------------------------ mesh obstacles
    def _mesh_round(self, ob: Obstacle, x0, x, v, t0, t1, h):
        """One round against a mesh obstacle: fcl broad phase, then exact tests (vertex-face, edge-edge, corner-triangle)."""
        th = self.thickness
        mo, shape = ob.motion, ob.shape
        q0 = mo.to_local(x0, t0)
        q1 = mo.to_local(x, t1)
        E, T = self.edges, self.faces
        vn = np.flatnonzero(self._near(ob, q0, q1, th) & self.free)
        en = np.flatnonzero(self._near(ob, q0[E], q1[E], th))
        tn = np.flatnonzero(self._near(ob, q0[T], q1[T], th))
        cand = broadphase.candidates(shape.bvh, q0, q1, vn, E[en], T[tn], th)
        busy, contacts, ncand, s_min = False, 0, 0, np.inf
        pv = [cand[k] for k in (broadphase.VERTEX_PATH, broadphase.VERTEX_BALL) if k in cand]
        if pv:
            pairs = np.unique(np.column_stack([np.concatenate([a for a, _ in pv]),
                                               np.concatenate([b for _, b in pv])]), axis=0)
            ncand += len(pairs)
            b, k, sm = self._mesh_vertex_face(ob, pairs[:, 0], pairs[:, 1], q0, x, v, t0, t1, h)
            busy |= b
            contacts += k
            s_min = min(s_min, sm)
        if broadphase.EDGE_QUAD in cand:
            ei, fi = cand[broadphase.EDGE_QUAD]
            pairs = np.unique(np.column_stack([np.repeat(en[ei], 3), shape.face_edges[fi].ravel()]), axis=0)
            ncand += len(pairs)
            q1 = mo.to_local(x, t1)
            b, k = self._feature_pairs(ob, "ee", E, q0[E], q1[E], pairs[:, 0], pairs[:, 1], shape.feature_edges,
                                       x0, x, v, t0, t1, h, ee_proximity=True)
            busy |= b
            contacts += k
        if broadphase.TRIANGLE in cand:
            ti, fi = cand[broadphase.TRIANGLE]
            pairs = np.unique(np.column_stack([np.repeat(tn[ti], 3), shape.faces[fi].ravel()]), axis=0)
            ncand += len(pairs)
            q1 = mo.to_local(x, t1)
            b, k = self._feature_pairs(ob, "vf", T, q0[T], q1[T], pairs[:, 0], pairs[:, 1], shape.vertices,
                                       x0, x, v, t0, t1, h)
            busy |= b
            contacts += k
        return busy, s_min, ncand, contacts

    def _mesh_vertex_face(self, ob: Obstacle, vi, fi, q0, x, v, t0, t1, h) -> tuple[bool, int, float]:
        """Cloth vertices ``vi`` against mesh faces ``fi``: crossings stopped at the time of impact, then proximity.

        A crossing (the exact point-triangle time of impact) puts the vertex ``thickness``
        off the face on the side it came from and applies the impulse with friction
        there; it moves on with its new velocity. A vertex ending nearer than
        ``thickness`` to a face is pushed away along the gap (two-sided).
        """
        th = self.thickness
        mo, shape = ob.motion, ob.shape
        F, V = shape.faces[fi], shape.vertices
        A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        P0, P1 = q0[vi], mo.to_local(x[vi], t1)
        s, side = ccd.point_triangle_toi(P0, P1, A, A, B, B, C, C, 0.1 * th)
        hit = np.isfinite(s) & (side != 0)
        busy, contacts, s_min = False, 0, np.inf
        if np.any(hit):
            k = np.flatnonzero(hit)
            k = k[np.argsort(s[k], kind="stable")]
            _, first = np.unique(vi[k], return_index=True)
            k = k[first]                                            # the earliest face per vertex
            i = vi[k]
            d = side[k, None] * shape.face_normals[fi[k]]           # from the face towards the vertex
            pc = P0[k] + s[k, None] * (P1[k] - P0[k]) + th * d
            tc = t0 + s[k] * h
            xc, n_w, u = self._world_at(mo, pc, d, tc)
            new, _ = impulse(v[i], u, n_w, ob.friction, self.restitution)
            v[i] = new
            x[i] = xc + ((1.0 - s[k]) * h)[:, None] * new
            busy, contacts, s_min = True, len(i), float(s[k].min())
        # proximity at the end of the step, nearest face per vertex
        P1 = mo.to_local(x[vi], t1)
        q, _ = ccd.point_triangle_closest(P1, A, B, C)
        gap = P1 - q
        dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
        k = np.flatnonzero((dist < th) & (dist > 1e-12))
        if len(k):
            k = k[np.argsort(dist[k], kind="stable")]
            _, first = np.unique(vi[k], return_index=True)
            k = k[first]
            i = vi[k]
            d = gap[k] / dist[k, None]
            push = th - dist[k]
            c1, R1 = mo.pose(t1)
            x[i] = (P1[k] + push[:, None] * d) @ R1.T + c1
            n_w = d @ R1.T
            u = mo.point_velocity(x[i], t1)
            new, _ = impulse(v[i], u, n_w, ob.friction, self.restitution)
            x[i] += h * (new - v[i]) - h * np.einsum("ij,ij->i", new - v[i], n_w)[:, None] * n_w
            v[i] = new
            self._record(i, n_w, np.einsum("ij,ij->i", u, n_w))
            contacts += len(i)
            busy |= bool(np.any(push > SETTLE_FRACTION * th))
        return busy, contacts, s_min

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
