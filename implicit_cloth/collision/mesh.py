"""The geometric response's stage for mesh obstacles (functions over a collision context).

A mesh has no signed distance: the broad phase (:mod:`~implicit_cloth.collision.broadphase`)
(:mod:`~implicit_cloth.collision.broadphase`) proposes candidate pairs, and the
exact tests are cloth vertices against faces plus every mesh vertex and edge as
a sharp feature (:func:`~implicit_cloth.collision.features.feature_pairs`).
"""

from __future__ import annotations

import numpy as np

from . import broadphase, ccd
from .context import Context, Obstacle, near, world_at
from .features import feature_pairs
from .response import PROXIMITY_SLACK, SETTLE_FRACTION, impulse
from .shapes import MeshShape


def mesh_round(ctx: Context, ob: Obstacle, x0, x, v, t0, t1, h):
    """One round against a mesh obstacle: box broad phase, then the exact tests (vertex-face, edge-edge,
    corner-triangle)."""
    th = ctx.thickness
    mo, shape = ob.motion, ob.shape
    assert isinstance(shape, MeshShape)
    q0 = mo.to_local(x0, t0)
    q1 = mo.to_local(x, t1)
    E, T = ctx.edges, ctx.faces
    vn = np.flatnonzero(near(ob.shape, q0, q1, th) & ctx.free)
    en = np.flatnonzero(near(ob.shape, q0[E], q1[E], th))
    tn = np.flatnonzero(near(ob.shape, q0[T], q1[T], th))
    cand = broadphase.candidates(shape.index, q0, q1, vn, E[en], T[tn], th)
    busy, contacts, ncand, s_min = False, 0, 0, np.inf
    pv = [cand[k] for k in (broadphase.VERTEX_PATH,) if k in cand]
    if pv:
        pairs = np.column_stack(broadphase.unique_pairs(np.concatenate([a for a, _ in pv]),
                                                   np.concatenate([b for _, b in pv])))
        ncand += len(pairs)
        b, k, sm = mesh_vertex_face(ctx, ob, pairs[:, 0], pairs[:, 1], q0, x, v, t0, t1, h)
        busy |= b
        contacts += k
        s_min = min(s_min, sm)
    if broadphase.EDGE_QUAD in cand:
        ei, fi = cand[broadphase.EDGE_QUAD]
        pairs = np.column_stack(broadphase.unique_pairs(np.repeat(en[ei], 3), shape.face_edges[fi].ravel()))
        ncand += len(pairs)
        q1 = mo.to_local(x, t1)
        b, k = feature_pairs(ctx, ob, "ee", E, q0[E], q1[E], pairs[:, 0], pairs[:, 1], shape.feature_edges,
                                   x0, x, v, t0, t1, h, ee_proximity=True)
        busy |= b
        contacts += k
    if broadphase.TRIANGLE in cand:
        ti, fi = cand[broadphase.TRIANGLE]
        pairs = np.column_stack(broadphase.unique_pairs(np.repeat(tn[ti], 3), shape.faces[fi].ravel()))
        ncand += len(pairs)
        q1 = mo.to_local(x, t1)
        b, k = feature_pairs(ctx, ob, "vf", T, q0[T], q1[T], pairs[:, 0], pairs[:, 1], shape.vertices,
                                   x0, x, v, t0, t1, h)
        busy |= b
        contacts += k
    return busy, s_min, ncand, contacts

def mesh_vertex_face(ctx: Context, ob: Obstacle, vi, fi, q0, x, v, t0, t1, h) -> tuple[bool, int, float]:
    """Cloth vertices ``vi`` against mesh faces ``fi``: crossings stopped at the time of impact, then proximity.

    A crossing (the exact point-triangle time of impact) puts the vertex ``thickness``
    off the face on the side it came from and applies the impulse with friction
    there; it moves on with its new velocity. A vertex ending nearer than
    ``thickness`` to a face is pushed away along the gap (two-sided).
    """
    th = ctx.thickness
    mo, shape = ob.motion, ob.shape
    assert isinstance(shape, MeshShape)
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
        xc, n_w, u = world_at(mo, pc, d, tc)
        new, _ = impulse(v[i], u, n_w, ctx.friction_of(ob), ctx.restitution)
        v[i] = new
        x[i] = xc + ((1.0 - s[k]) * h)[:, None] * new
        busy, contacts, s_min = True, len(i), float(s[k].min())
    # proximity at the end of the step, nearest face per vertex
    P1 = mo.to_local(x[vi], t1)
    q, _ = ccd.point_triangle_closest(P1, A, B, C)
    gap = P1 - q
    dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    k = np.flatnonzero((dist < th * (1.0 - PROXIMITY_SLACK)) & (dist > 1e-12))
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
        new, _ = impulse(v[i], u, n_w, ctx.friction_of(ob), ctx.restitution)
        x[i] += h * (new - v[i]) - h * np.einsum("ij,ij->i", new - v[i], n_w)[:, None] * n_w
        v[i] = new
        contacts += len(i)
        busy |= bool(np.any(push > SETTLE_FRACTION * th))
    return busy, contacts, s_min
