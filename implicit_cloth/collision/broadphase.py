"""Broad phase against mesh obstacles with python-fcl: which cloth primitives may touch which obstacle triangles.

python-fcl 0.7 cannot sweep a deforming mesh (its continuous collision segfaults,
misses or only moves a whole mesh rigidly, and a BVHModel cannot be refit from
Python), so fcl does only the geometric search: the cloth's swept primitives
near the obstacle, in the obstacle's local frame, become one "soup" BVHModel,
collided with the obstacle's BVH (built once) in a single ``fcl.collide``; the
contacts' triangle indices are the candidate pairs for the exact tests in numpy
(:mod:`implicit_cloth.collision.ccd`). The soup holds, per cloth primitive:

* vertex path ``x0 -> x1``: the degenerate triangle ``(x0, x1, x1)``, and an
  octahedron of circumradius ``sqrt(3) r`` around ``x1`` (it contains the ball of
  radius ``r``, so a surface within ``r`` of the end position is found);
* edge ``(a, b)``: its swept quad ``(a0, b0, b1), (a0, b1, a1)``, and its end
  segment widened by ``r`` across it in two directions (an obstacle edge within
  about ``r`` of it cuts one of them);
* triangle: its end position ``(a1, b1, c1)`` (an obstacle corner that crossed it
  in the step is on its far side then, so the obstacle's surface cuts it), and
  the same shifted by ``r`` along its normal to either side (a corner within ``r``).
"""

from __future__ import annotations

import numpy as np

#: Soup primitive kinds.
VERTEX_PATH, VERTEX_BALL, EDGE_QUAD, TRIANGLE = 0, 1, 2, 3

_OCTA_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
_OCTA_FACES = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def bvh(vertices: np.ndarray, faces: np.ndarray):
    """An fcl collision object of a triangle mesh (identity transform)."""
    import fcl

    m = fcl.BVHModel()
    m.beginModel(len(vertices), len(faces))
    m.addSubModel(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(faces, dtype=np.int64))
    m.endModel()
    return fcl.CollisionObject(m, fcl.Transform())


def _across(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (K, 3) perpendicular to each row of ``d`` and to each other."""
    d = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    pick = np.where(np.abs(d[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(d, pick)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-300)[:, None]
    return e1, np.cross(d, e1)


def candidates(obstacle, p0: np.ndarray, p1: np.ndarray, verts: np.ndarray, edges: np.ndarray,
               tris: np.ndarray, r: float) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Candidate pairs (cloth primitive index, obstacle triangle index) of each kind.

    Parameters
    ----------
    obstacle : fcl.CollisionObject
        The obstacle's BVH, local frame.
    p0, p1 : (N, 3) arrays
        Cloth positions at the start and end of the step, obstacle's local frame, m.
    verts, edges, tris : int arrays
        The cloth's vertices (K,), edges (E, 2) and triangles (T, 3) to include.
    r : float
        Proximity radius of the vertex balls, m.
    """
    import fcl

    pts, tri, kind, owner = [], [], [], []
    n = 0

    def add(points, faces, k, ids, per):
        nonlocal n
        pts.append(points)
        tri.append(faces + n)
        kind.append(np.full(len(faces), k))
        owner.append(np.repeat(ids, per))
        n += len(points)

    if len(verts):
        m = len(verts)
        a, b = p0[verts], p1[verts]
        add(np.concatenate([a, b]), np.column_stack([np.arange(m), m + np.arange(m), m + np.arange(m)]),
            VERTEX_PATH, verts, 1)
        ball = (b[:, None, :] + np.sqrt(3.0) * r * _OCTA_DIRS[None]).reshape(-1, 3)
        add(ball, (_OCTA_FACES[None] + 6 * np.arange(m)[:, None, None]).reshape(-1, 3), VERTEX_BALL, verts, 8)
    if len(edges):
        m = len(edges)
        quad = np.stack([p0[edges[:, 0]], p0[edges[:, 1]], p1[edges[:, 1]], p1[edges[:, 0]]], axis=1).reshape(-1, 3)
        base = 4 * np.arange(m)[:, None]
        faces = np.stack([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
        add(quad, faces, EDGE_QUAD, np.arange(m), 2)
        # the end segment widened by r across it in two directions: obstacle edges within about r of it
        a, b = p1[edges[:, 0]], p1[edges[:, 1]]
        e1, e2 = _across(b - a)
        for e in (e1, e2):
            wide = np.stack([a - r * e, b - r * e, b + r * e, a + r * e], axis=1).reshape(-1, 3)
            add(wide, faces, EDGE_QUAD, np.arange(m), 2)
    if len(tris):
        m = len(tris)
        t1 = p1[tris]
        tf = 3 * np.arange(m)[:, None] + [0, 1, 2]
        add(t1.reshape(-1, 3), tf, TRIANGLE, np.arange(m), 1)
        # and shifted by r to either side: an obstacle corner within r of the triangle cuts one of them
        nrm = np.cross(t1[:, 1] - t1[:, 0], t1[:, 2] - t1[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-300)[:, None]
        for sgn in (1.0, -1.0):
            add((t1 + sgn * r * nrm[:, None, :]).reshape(-1, 3), tf, TRIANGLE, np.arange(m), 1)
    if not n:
        return {}
    soup = bvh(np.concatenate(pts), np.concatenate(tri))
    req = fcl.CollisionRequest(num_max_contacts=10**7, enable_contact=False)
    res = fcl.CollisionResult()
    fcl.collide(soup, obstacle, req, res)
    if not res.contacts:
        return {}
    b1 = np.fromiter((c.b1 for c in res.contacts), dtype=np.int64, count=len(res.contacts))
    b2 = np.fromiter((c.b2 for c in res.contacts), dtype=np.int64, count=len(res.contacts))
    kinds, owners = np.concatenate(kind), np.concatenate(owner)
    out = {}
    for k in (VERTEX_PATH, VERTEX_BALL, EDGE_QUAD, TRIANGLE):
        sel = kinds[b1] == k
        if np.any(sel):
            pairs = np.unique(np.column_stack([owners[b1[sel]], b2[sel]]), axis=0)
            out[k] = (pairs[:, 0], pairs[:, 1])
    return out
