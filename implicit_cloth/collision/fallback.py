"""The geometric response: corrections of a proposed step's positions and velocities so that nothing enters an
obstacle (Bridson, Fedkiw & Anderson 2002, adapted to rigid obstacles).

The whole collision stage of an explicit step, and the fallback after an implicit step's constrained solves
(there without friction: the solve applied it; what it still corrects is counted). With the step's start
``x0`` collision-free, per obstacle in its local frame (the cloth's start and end positions moved into the
obstacle's frame at ``t0`` and ``t1``: linear relative motion; a keyframe inside the step is approximated by
the chord from the pose at ``t0`` to the pose at ``t1``, see
:class:`~implicit_cloth.collision.shapes.RigidMotion`):

a. vertex sweeps (:func:`_vertex_sweeps`): a vertex whose path comes within ``thickness / 2`` of the surface
   is stopped where it first comes within ``thickness``
   (:meth:`~implicit_cloth.collision.shapes.Shape.sweep`), gets an inelastic impulse with friction there,
   and moves on with its new velocity for the rest of the step;
b. proximity (:func:`_proximity`): a vertex ending within ``thickness`` of the surface is moved out along the
   normal to ``thickness``; an approaching normal velocity is removed;
c. sharp features (:func:`~implicit_cloth.collision.features.features`): obstacle corners and tips against
   cloth triangles, obstacle edges against cloth edges, by the exact coplanarity time of impact;
d. edges (:func:`~implicit_cloth.collision.features.edge_proximity`): no point of a cloth edge nearer than
   ``thickness / 2`` to a curved convex shape.

Mesh obstacles (no signed distance) replace a, b and d by the exact tests of cloth vertices against the
faces the broad phase (:mod:`~implicit_cloth.collision.broadphase`) proposes
(:func:`~implicit_cloth.collision.mesh.mesh_round`).

Rounds repeat until one finds nothing to correct, at most ``collision.max_iterations``. Vertices still in
violation then are frozen to the obstacle (moved rigidly with it from their collision-free start, with its
velocity; :func:`failsafe`): the fail-safe of Bridson et al.'s rigid impact zones, reported. Pinned
vertices are never moved (their inverse mass is 0 in every correction).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from . import broadphase, ccd
from .context import CollisionInfo, Context, Obstacle, near, world_at
from .features import edge_minimum, edge_proximity, features
from .mesh import mesh_round
from .response import PROXIMITY_SLACK, SETTLE_FRACTION, impulse
from .shapes import MeshShape, Plane

#: A vertex path that comes within this fraction of the thickness counts as an impact.
IMPACT_FRACTION = 0.5
#: Passes of the fail-safe (each freezes the offenders and their neighbours).
FAILSAFE_PASSES = 4


def respond(ctx: Context, before: Any, after: Any, h: float) -> CollisionInfo:
    """Correct the proposed state ``after`` in place so that no cloth vertex, edge or triangle enters an obstacle.

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
    toi = np.inf
    for rnd in range(ctx.max_rounds):
        busy = False
        for ob in ctx.obstacles:
            if isinstance(ob.shape, MeshShape):
                b, s_min, cand, cont = mesh_round(ctx, ob, x0, x, v, t0, t1, h)
            else:
                b, s_min, cand, cont = _round(ctx, ob, x0, x, v, t0, t1, h)
            busy |= b
            toi = min(toi, s_min)
            if rnd == 0:
                info.candidates += cand
            info.contacts += cont
        info.rounds = rnd + 1
        if not busy:
            break
    else:
        info.failsafe = failsafe(ctx, x0, x, v, t0, t1)
    info.toi = float(toi) if np.isfinite(toi) else float("nan")
    info.max_penetration = penetration(ctx, x, t1)
    info.t_collision = time.perf_counter() - t_start
    return info


def _round(ctx: Context, ob: Obstacle, x0, x, v, t0, t1, h) -> tuple[bool, float, int, int]:
    """One round against a primitive obstacle: ``(busy, earliest time of impact, candidates, contacts)``."""
    th = ctx.thickness
    mo, shape = ob.motion, ob.shape
    p0 = mo.to_local(x0, t0)
    p1 = mo.to_local(x, t1)
    vid = np.flatnonzero(near(shape, p0, p1, th) & ctx.free)
    busy, s_min, contacts = False, np.inf, 0
    if len(vid):
        busy, s_min, contacts = _vertex_sweeps(ctx, ob, vid, p0, p1, x, v, t0, h)
        b, k = _proximity(ctx, ob, vid, x, v, t1, h)
        busy |= b
        contacts += k
    cand = len(vid)
    stages = []
    if len(shape.feature_points) or len(shape.feature_edges):
        stages.append(features)
    if not shape.flat:
        stages.append(edge_proximity)
    for stage in stages:
        b, c, k = stage(ctx, ob, x0, x, v, t0, t1, h)
        busy |= b
        cand += c
        contacts += k
    return busy, s_min, cand, contacts


def _vertex_sweeps(ctx: Context, ob: Obstacle, vid, p0, p1, x, v, t0, h) -> tuple[bool, float, int]:
    """Stage a: vertices whose path comes within ``IMPACT_FRACTION * thickness`` are stopped at ``thickness``."""
    th = ctx.thickness
    shape, mo = ob.shape, ob.motion
    deep = shape.sweep(p0[vid], p1[vid], IMPACT_FRACTION * th)
    hit = vid[np.isfinite(deep)]
    if not len(hit):
        return False, np.inf, 0
    s = shape.sweep(p0[hit], p1[hit], th)
    s = np.where(np.isfinite(s), s, deep[np.isfinite(deep)])
    q = p0[hit] + s[:, None] * (p1[hit] - p0[hit])
    _, n_loc, _ = shape.closest(q)
    xc, n_w, u = world_at(mo, q, n_loc, t0 + s * h)
    new, _ = impulse(v[hit], u, n_w, ctx.friction_of(ob), ctx.restitution)
    v[hit] = new
    x[hit] = xc + ((1.0 - s) * h)[:, None] * new
    return True, float(s.min()), len(hit)


def _proximity(ctx: Context, ob: Obstacle, vid, x, v, t1, h) -> tuple[bool, int]:
    """Stage b: vertices ending nearer than the thickness are moved out to it; approaching velocity removed."""
    th = ctx.thickness
    shape, mo = ob.shape, ob.motion
    p1v = mo.to_local(x[vid], t1)
    phi, n_loc, _ = shape.closest(p1v)
    close = phi < th * (1.0 - PROXIMITY_SLACK)   # a vertex held on its plane is not moved
    if not np.any(close):
        return False, 0
    i = vid[close]
    push = th - phi[close]
    c1, R1 = mo.pose(t1)
    x[i] = (p1v[close] + push[:, None] * n_loc[close]) @ R1.T + c1
    n_w = n_loc[close] @ R1.T
    u = mo.point_velocity(x[i], t1)
    new, _ = impulse(v[i], u, n_w, ctx.friction_of(ob), ctx.restitution)
    x[i] += h * (new - v[i]) - h * np.einsum("ij,ij->i", new - v[i], n_w)[:, None] * n_w
    v[i] = new
    return bool(np.any(push > SETTLE_FRACTION * th)), len(i)


# --------------------------------------------------------------------------- fail-safe and measures
def violations(ctx: Context, x0, x, t0, t1) -> np.ndarray:
    """Vertices whose path still crosses an obstacle's surface deeper than the impact fraction, (N,) bool."""
    bad = np.zeros(ctx.n, dtype=bool)
    th = ctx.thickness
    for ob in ctx.obstacles:
        p0, p1 = ob.motion.to_local(x0, t0), ob.motion.to_local(x, t1)
        vid = np.flatnonzero(near(ob.shape, p0, p1, th) & ctx.free)
        if isinstance(ob.shape, MeshShape):   # vertex paths still crossing a face
            cand = broadphase.candidates(ob.shape.index, p0, p1, vid, ctx.edges[:0], ctx.faces[:0], th)
            if broadphase.VERTEX_PATH in cand:
                vi, fi = cand[broadphase.VERTEX_PATH]
                F = ob.shape.faces[fi]
                A, B, C = (ob.shape.vertices[F[:, j]] for j in range(3))
                s, _ = ccd.point_triangle_toi(p0[vi], p1[vi], A, A, B, B, C, C, 0.0)
                bad[vi[np.isfinite(s)]] = True
            continue
        if len(vid):
            s = ob.shape.sweep(p0[vid], p1[vid], IMPACT_FRACTION * th)
            bad[vid[np.isfinite(s) & (ob.shape.distance(p1[vid]) < (1 - SETTLE_FRACTION) * th)]] = True
            bad[vid[np.isfinite(s) & (ob.shape.distance(p0[vid]) >= IMPACT_FRACTION * th)]] = True
        if not isinstance(ob.shape, Plane):
            q = p1[ctx.edges]
            nr = np.flatnonzero(near(ob.shape, q, q, th))
            if len(nr):
                _, phi = edge_minimum(ob.shape, q[nr, 0], q[nr, 1])
                bad[ctx.edges[nr[phi < -SETTLE_FRACTION * th]].ravel()] = True
    return bad


def failsafe(ctx: Context, x0, x, v, t0, t1) -> int:
    """Freeze vertices still in violation to the nearest obstacle: carried rigidly from their start.

    Repeated (each time with the one-ring of the offenders) while a violation remains, at most
    :data:`FAILSAFE_PASSES` times; returns the number of frozen vertices.
    """
    frozen = np.zeros(ctx.n, dtype=bool)
    for _ in range(FAILSAFE_PASSES):
        bad = violations(ctx, x0, x, t0, t1) & ~frozen
        if not bad.any():
            break
        frozen |= _freeze(ctx, bad, x0, x, v, t0, t1)
    return int(frozen.sum())


def _freeze(ctx: Context, bad, x0, x, v, t0, t1) -> np.ndarray:
    # with their one-ring: a frozen vertex next to a moving one can still cut a feature
    ring = np.zeros(ctx.n, dtype=bool)
    e = ctx.edges
    ring[e[bad[e[:, 0]], 1]] = True
    ring[e[bad[e[:, 1]], 0]] = True
    bad |= ring
    bad &= ctx.free
    idx = np.flatnonzero(bad)
    if not len(idx):
        return bad
    owner = ctx.nearest_obstacle(x0[idx], t0)
    for k, ob in enumerate(ctx.obstacles):
        sel = idx[owner == k]
        if len(sel):
            x[sel] = ob.motion.to_world(ob.motion.to_local(x0[sel], t0), t1)
            v[sel] = ob.motion.point_velocity(x[sel], t1)
    return bad


def penetration(ctx: Context, x: np.ndarray, t1: float) -> float:
    """The largest depth of a cloth vertex inside a primitive obstacle at ``t1``, m."""
    depth = 0.0
    for ob in ctx.obstacles:
        if isinstance(ob.shape, MeshShape):
            continue
        p = ob.motion.to_local(x, t1)
        vid = np.flatnonzero(near(ob.shape, p, p, 0.0))
        if len(vid):
            depth = max(depth, float(np.max(-ob.shape.distance(p[vid]), initial=0.0)))
    return depth


def impulse_work(ctx: Context, v_before: np.ndarray, after: Any) -> float:
    """Work of velocity changes of the response against the obstacles' motion, J (each changed vertex is
    charged to the obstacle nearest to it)."""
    if not any(ob.motion.moving for ob in ctx.obstacles):
        return 0.0
    moved = np.flatnonzero(np.any(after.v != v_before, axis=1))
    if not len(moved):
        return 0.0
    x = after.x[moved]
    owner = ctx.nearest_obstacle(x, after.t)
    u = np.zeros((len(moved), 3))
    for k, ob in enumerate(ctx.obstacles):
        sel = owner == k
        u[sel] = ob.motion.point_velocity(x[sel], after.t)
    dv = after.v[moved] - v_before[moved]
    return float(np.einsum("i,ij,ij->", ctx.masses[moved], dv, u))
