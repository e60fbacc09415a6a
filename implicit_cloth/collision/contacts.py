"""Contact planes: what the collision stage asks of the implicit solve.

A contact holds one cloth vertex on one side of a plane fixed in an obstacle's
local frame, ``n . p >= off`` (``p`` the vertex in that frame, ``n`` the outward
unit normal). The solve treats an active contact as the equality ``n . p = off``
at the end of the step (a Baraff-Witkin filter direction with a prescribed normal
velocity, :class:`~implicit_cloth.constraints.Constraints`); a contact whose
normal impulse pulls the vertex towards the obstacle is released.

Detection (:func:`detect`) looks at a proposed step ``x0 -> x1`` and returns, for
every vertex that comes nearer than the thickness to an obstacle, the plane that
would keep it out, with its violation ``off - n . p1`` (m):

* **vertex** contacts (primitive shapes): the vertex's path first comes within
  the thickness ``th`` of the surface at ``q`` (closed-form or conservative sweep,
  :meth:`~implicit_cloth.collision.shapes.Shape.sweep`); the plane is the tangent
  plane of the inflated surface there, ``n(q) . p >= n(q) . c(q) + th`` (``c`` the
  nearest surface point). On a convex surface, sliding along that plane moves
  the vertex away from the surface, never into it.
* **mesh** contacts: the exact vertex-face time of impact against the faces
  the broad phase (:mod:`~implicit_cloth.collision.broadphase`) proposes (the face's normal turned to the side the
  vertex came from), or the nearest face point within ``th`` of the end position.
* **feature** contacts: an obstacle corner against a cloth triangle, an obstacle
  edge against a cloth edge (exact coplanarity time of impact, or proximity), and
  the nearest point of a cloth edge to a smooth convex shape. The primitive's point
  ``P = sum_j w_j p_j`` must end ``th`` off the feature along ``n``; its vertices get
  planes above their proposed end heights by shares of the shortfall, the smallest
  correction that lifts ``P`` there (:func:`_lift`).

One plane per vertex: where several apply, the most violated one.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ..rowwise import max1, min1
from . import broadphase, ccd
from .context import near
from .features import EDGE_FRACTION, edge_minimum
from .shapes import MeshShape

#: Kinds of contact plane.
VERTEX, FEATURE = 0, 1
#: A plane violated by less than this fraction of the thickness is not a new contact.
DETECT_FRACTION = 0.02
#: Barycentric weights below this do not hold a primitive's vertex.
MIN_WEIGHT = 1e-3
#: Rounding allowance (m) of the edge test's bound from an exact signed distance (:func:`_edge_interiors`).
LIPSCHITZ_SLACK = 1e-9


@dataclass
class Planes:
    """Contact planes, one row per (vertex, obstacle) contact (module docstring).

    Attributes
    ----------
    idx : (K,) int array
        Cloth vertex.
    ob : (K,) int array
        Obstacle index.
    n : (K, 3) array
        Outward unit normal, obstacle's local frame.
    off : (K,) array
        Plane offset, m: the contact asks ``n . p >= off``.
    point : (K, 3) array
        Contact point on the obstacle, local frame (where its velocity is taken).
    kind : (K,) int array
        :data:`VERTEX` or :data:`FEATURE`.
    force : (K,) array
        Normal force of the last solve that held it, N (0 for a new contact).
    viol : (K,) array
        Violation ``off - n . p1`` of the proposed end position when detected, m.
    stick : (K,) bool array
        Friction state: sticking (held tangentially) or sliding.
    slip : (K, 3) array
        World direction of a sliding contact's motion relative to the obstacle (0 while sticking).
    speed : (K,) array
        Smoothed friction (``collision.friction_speed``): a sliding contact's speed relative to the obstacle
        where its friction is linearised, m/s (0 while sticking, and with Coulomb's states).
    """

    idx: np.ndarray
    ob: np.ndarray
    n: np.ndarray
    off: np.ndarray
    point: np.ndarray
    kind: np.ndarray
    force: np.ndarray
    viol: np.ndarray
    stick: np.ndarray
    slip: np.ndarray
    speed: np.ndarray

    @classmethod
    def empty(cls) -> "Planes":
        z = np.zeros(0)
        i = np.zeros(0, dtype=np.int64)
        return cls(i, i.copy(), np.zeros((0, 3)), z, np.zeros((0, 3)), i.copy(), z.copy(), z.copy(),
                   np.zeros(0, dtype=bool), np.zeros((0, 3)), z.copy())

    def __len__(self) -> int:
        return len(self.idx)

    def take(self, sel: Any) -> "Planes":
        return Planes(*(getattr(self, f.name)[sel] for f in fields(self)))

    @classmethod
    def cat(cls, parts: list["Planes"]) -> "Planes":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    def best_per_vertex(self) -> "Planes":
        """The most violated plane of each vertex."""
        if len(self) <= 1:
            return self
        order = np.lexsort((-self.viol, self.idx))
        first = np.ones(len(order), dtype=bool)
        first[1:] = self.idx[order][1:] != self.idx[order][:-1]
        return self.take(order[first])


def make(idx, ob: int, n, off, point, kind: int, viol) -> Planes:
    """New contacts (no normal force yet, sticking) of obstacle ``ob``."""
    k = len(idx)
    return Planes(np.asarray(idx, dtype=np.int64), np.full(k, ob, dtype=np.int64), np.asarray(n, dtype=float),
                  np.asarray(off, dtype=float), np.asarray(point, dtype=float), np.full(k, kind, dtype=np.int64),
                  np.zeros(k), np.asarray(viol, dtype=float), np.ones(k, dtype=bool), np.zeros((k, 3)), np.zeros(k))


def merge(active: Planes, found: Planes) -> Planes:
    """``active`` with ``found``'s planes added; a vertex in both takes the found plane (it is violated),
    keeping its normal force and friction state."""
    if not len(found):
        return active
    keep = ~np.isin(active.idx, found.idx)
    f = found
    if len(active):
        f = found.take(slice(None))
        inherit(active, f)
    return Planes.cat([active.take(keep), f])


def inherit(old: Planes, new: Planes) -> None:
    """Give ``new``'s contacts the normal force and friction state ``old`` has for the same vertices (in place)."""
    if not len(old) or not len(new):
        return
    n = int(max(old.idx.max(), new.idx.max())) + 1
    row = np.full(n, -1, dtype=np.int64)
    row[old.idx] = np.arange(len(old))
    r = row[new.idx]
    had = r >= 0
    new.force[had] = old.force[r[had]]
    new.stick[had] = old.stick[r[had]]
    new.slip[had] = old.slip[r[had]]
    new.speed[had] = old.speed[r[had]]


# --------------------------------------------------------------------------- detection
@dataclass
class Frame:
    """A proposed step and the cloth's topology: what detection looks at."""

    x0: np.ndarray
    x1: np.ndarray
    t0: float
    t1: float
    thickness: float
    edges: np.ndarray
    faces: np.ndarray
    free: np.ndarray        # (N,) bool: not pinned
    #: contacts are looked for within ``thickness + reach`` (planes stay at the thickness): > 0 finds the
    #: contacts a state rests on, with a still frame (x1 = x0)
    reach: float = 0.0


def detect(frame: Frame, obstacles: list, tol: float | None = None) -> Planes:
    """Contact planes violated by the proposed step by more than ``tol`` (default: a fiftieth of the thickness,
    less ``frame.reach``), the most violated one per vertex."""
    th = frame.thickness
    tol = DETECT_FRACTION * th - frame.reach if tol is None else tol
    parts = []
    for k, ob in enumerate(obstacles):
        mo, shape = ob.motion, ob.shape
        p0 = mo.to_local(frame.x0, frame.t0)
        p1 = mo.to_local(frame.x1, frame.t1)
        if isinstance(shape, MeshShape):
            parts += _mesh(frame, k, shape, p0, p1)
        else:
            parts.append(_vertices(frame, k, shape, p0, p1))
            if len(shape.feature_points):
                parts.append(_corners(frame, k, shape, shape.feature_points, p0, p1))
            if len(shape.feature_edges):
                parts.append(_edge_pairs(frame, k, shape, shape.feature_edges, p0, p1))
            if not shape.flat:
                parts.append(_edge_interiors(frame, k, shape, p1))
    found = Planes.cat(parts)
    return found.take(found.viol > tol).best_per_vertex()


def _vertices(frame: Frame, k: int, shape, p0, p1) -> Planes:
    th = frame.thickness
    r = th + frame.reach
    vid = np.flatnonzero(near(shape, p0, p1, r) & frame.free)
    if not len(vid):
        return Planes.empty()
    s = shape.sweep(p0[vid], p1[vid], r)
    hit = np.isfinite(s)
    vid, s = vid[hit], s[hit]
    if not len(vid):
        return Planes.empty()
    q = p0[vid] + s[:, None] * (p1[vid] - p0[vid])
    _, n, c = shape.closest(q)
    off = np.einsum("ij,ij->i", n, c) + th
    viol = off - np.einsum("ij,ij->i", n, p1[vid])
    return make(vid, k, n, off, c, VERTEX, viol)


def _lift(frame: Frame, k: int, prims: np.ndarray, w: np.ndarray, n: np.ndarray, target: np.ndarray,
          point: np.ndarray, p1: np.ndarray) -> Planes:
    """Per-vertex planes that bring primitive points ``P = sum_j w_j p1_j`` up to ``n . P = target`` (features).

    The point's shortfall ``D`` is shared as the smallest correction that makes it up (as a point correction
    is shared among a triangle's or an edge's vertices): vertex ``j`` is asked to end ``w_j D / sum_k w_k^2``
    above its proposed height (pinned vertices take no share), so a vertex far from the point moves little.
    A point within ``reach`` above the target (a resting contact) gets planes at the vertices' heights.
    """
    P1 = p1[prims]                                            # (K, m, 3)
    hj = np.einsum("kmj,kj->km", P1, n)                       # vertex heights along n
    hp = np.einsum("km,km->k", w, hj)                         # the point's height
    short = target - hp                                       # > 0: the point is too low
    share = np.where((w > MIN_WEIGHT) & frame.free[prims], w, 0.0)
    w2 = np.einsum("km,km->k", share, share)
    ok = (short > -frame.reach) & (w2 > 0)
    if not np.any(ok):
        return Planes.empty()
    lift = np.maximum(short, 0.0) / np.where(w2 > 0, w2, 1.0)
    k_, m_ = np.nonzero((share > 0) & ok[:, None])
    rise = share[k_, m_] * lift[k_]
    off = hj[k_, m_] + rise
    return make(prims[k_, m_], k, n[k_], off, point[k_], FEATURE, np.minimum(short[k_], rise))


def _pairs_near(frame: Frame, shape, prims: np.ndarray, feats_lo: np.ndarray, feats_hi: np.ndarray, p0, p1):
    """Candidate (primitive, feature) index pairs whose swept boxes, inflated by the thickness, overlap."""
    r = frame.thickness + frame.reach
    q0, q1 = p0[prims], p1[prims]
    nr = np.flatnonzero(near(shape, q0, q1, r))
    if not len(nr):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo = np.minimum(min1(q0[nr]), min1(q1[nr])) - r
    hi = np.maximum(max1(q0[nr]), max1(q1[nr])) + r
    m = np.all((lo[None] <= feats_hi[:, None]) & (hi[None] >= feats_lo[:, None]), axis=2)   # (F, K)
    fi, kj = np.nonzero(m)
    return nr[kj], fi


def _corners(frame: Frame, k: int, shape, feats: np.ndarray, p0, p1, pairs=None) -> Planes:
    """Obstacle corners and tips (local points ``feats``) against cloth triangles (candidate ``pairs`` if given)."""
    th = frame.thickness
    T = frame.faces
    pr, fi = _pairs_near(frame, shape, T, feats, feats, p0, p1) if pairs is None else pairs
    if not len(pr):
        return Planes.empty()
    A0, A1 = p0[T[pr]], p1[T[pr]]
    f = feats[fi]
    s, side = ccd.point_triangle_toi(f, f, A0[:, 0], A1[:, 0], A0[:, 1], A1[:, 1], A0[:, 2], A1[:, 2], 0.1 * th)
    crossed = np.isfinite(s) & (side != 0)
    # the triangle at its end position (proximity) or at the time of impact (a crossing)
    sh = np.where(crossed, s, 1.0)[:, None, None]
    As = A0 + sh * (A1 - A0)
    qc, w = ccd.point_triangle_closest(f, As[:, 0], As[:, 1], As[:, 2])
    nt = np.cross(As[:, 1] - As[:, 0], As[:, 2] - As[:, 0])
    nn = np.sqrt(np.einsum("ij,ij->i", nt, nt))
    gap = qc - f
    dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    n = np.zeros_like(gap)
    cr = crossed & (nn > 1e-14)
    n[cr] = -side[cr, None] * nt[cr] / nn[cr, None]            # towards the side the cloth came from
    plain = ~cr & (dist > 1e-12) & (dist < th + frame.reach)
    n[plain] = gap[plain] / dist[plain, None]
    act = cr | plain
    if isinstance(shape, MeshShape) and np.any(act):     # a mesh vertex holds the cloth only within its cone
        act[act] = shape.vertex_cone(fi[act], n[act])
    if not np.any(act):
        return Planes.empty()
    a = np.flatnonzero(act)
    if np.any(cr):   # a crossing's weights: where the corner went through
        _, w[cr] = ccd.point_triangle_closest(f[cr], As[cr, 0], As[cr, 1], As[cr, 2])
    target = np.einsum("ij,ij->i", n[a], f[a]) + th
    return _lift(frame, k, T[pr[a]], w[a], n[a], target, f[a], p1)


def _edge_pairs(frame: Frame, k: int, shape, feats: np.ndarray, p0, p1, pairs=None,
                target_fraction: float = 1.0) -> Planes:
    """Obstacle edges (local segments ``feats`` (F, 2, 3)) against cloth edges (candidate ``pairs`` if given).

    Cloth edges are kept ``target_fraction`` of the thickness from the obstacle's edges.
    """
    th = frame.thickness
    E = frame.edges
    pr, fi = _pairs_near(frame, shape, E, feats.min(axis=1), feats.max(axis=1), p0, p1) if pairs is None else pairs
    if not len(pr):
        return Planes.empty()
    A0, A1 = p0[E[pr]], p1[E[pr]]
    e0, e1 = feats[fi, 0], feats[fi, 1]
    s, side = ccd.edge_edge_toi(A0[:, 0], A1[:, 0], A0[:, 1], A1[:, 1], e0, e0, e1, e1, 0.1 * th)
    crossed = np.isfinite(s) & (side != 0)
    sh = np.where(crossed, s, 1.0)[:, None, None]
    As = A0 + sh * (A1 - A0)
    a, b = ccd.segment_closest(As[:, 0], As[:, 1], e0, e1)
    pc = As[:, 0] + a[:, None] * (As[:, 1] - As[:, 0])
    qc = e0 + b[:, None] * (e1 - e0)
    gap = pc - qc
    dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    nx = np.cross(As[:, 1] - As[:, 0], e1 - e0)
    nn = np.sqrt(np.einsum("ij,ij->i", nx, nx))
    n = np.zeros_like(gap)
    cr = crossed & (nn > 1e-14)
    n[cr] = -side[cr, None] * nx[cr] / nn[cr, None]
    target_th = target_fraction * th
    interior = (a > 1e-6) & (a < 1 - 1e-6)
    plain = ~cr & (dist > 1e-12) & (dist < target_th + frame.reach) & interior
    n[plain] = gap[plain] / dist[plain, None]
    act = cr | plain
    if isinstance(shape, MeshShape) and np.any(act):     # a mesh edge holds the cloth only within its cone
        act[act] = shape.edge_cone(fi[act], n[act], qc[act])
    if not np.any(act):
        return Planes.empty()
    i = np.flatnonzero(act)
    w = np.column_stack([1.0 - a[i], a[i]])
    target = np.einsum("ij,ij->i", n[i], qc[i]) + target_th
    return _lift(frame, k, E[pr[i]], w, n[i], target, qc[i], p1)


def _edge_interiors(frame: Frame, k: int, shape, p1) -> Planes:
    """Cloth edges whose nearest point to a convex shape is nearer than ``EDGE_FRACTION`` of the thickness."""
    th = frame.thickness
    E = frame.edges
    q = p1[E]
    target_th = EDGE_FRACTION * th
    if shape.exact_distance:
        # an edge's points are within half its length of an end, so its least signed distance is at least its
        # nearer end's less that: the edges that cannot come within the thickness are skipped (cheaper than
        # their bounding boxes, and fewer; the same planes, as edge_minimum goes edge by edge)
        phi_v = shape.distance(p1)
        d = q[:, 1] - q[:, 0]
        lower = np.minimum(phi_v[E[:, 0]], phi_v[E[:, 1]]) - 0.5 * np.sqrt(np.einsum("ij,ij->i", d, d))
        nr = np.flatnonzero(lower < th + frame.reach + LIPSCHITZ_SLACK)
    else:
        nr = np.flatnonzero(near(shape, q, q, th + frame.reach))
    if not len(nr):
        return Planes.empty()
    a, phi = edge_minimum(shape, q[nr, 0], q[nr, 1])
    act = (phi < target_th + frame.reach) & (a > 1e-6) & (a < 1 - 1e-6)
    if not np.any(act):
        return Planes.empty()
    i = np.flatnonzero(act)
    pm = q[nr[i], 0] + a[i, None] * (q[nr[i], 1] - q[nr[i], 0])
    _, n, c = shape.closest(pm)
    target = np.einsum("ij,ij->i", n, c) + target_th
    w = np.column_stack([1.0 - a[i], a[i]])
    return _lift(frame, k, E[nr[i]], w, n, target, c, p1)


def _mesh(frame: Frame, k: int, shape, p0, p1) -> list[Planes]:
    """Contact planes against a mesh obstacle: vertex-face (time of impact and proximity), corners, edges."""
    r = frame.thickness + frame.reach
    E, T = frame.edges, frame.faces
    vn = np.flatnonzero(near(shape, p0, p1, r) & frame.free)
    en = np.flatnonzero(near(shape, p0[E], p1[E], r))
    tn = np.flatnonzero(near(shape, p0[T], p1[T], r))
    cand = broadphase.candidates(shape.index, p0, p1, vn, E[en], T[tn], r)
    out = []
    pv = [cand[key] for key in (broadphase.VERTEX_PATH,) if key in cand]
    if pv:
        pairs = np.column_stack(broadphase.unique_pairs(np.concatenate([a for a, _ in pv]),
                                                   np.concatenate([b for _, b in pv])))
        out.append(_mesh_vertex_face(frame, k, shape, pairs[:, 0], pairs[:, 1], p0, p1))
    if broadphase.EDGE_QUAD in cand:
        ei, fi = cand[broadphase.EDGE_QUAD]
        pairs = np.column_stack(broadphase.unique_pairs(np.repeat(en[ei], 3), shape.face_edges[fi].ravel()))
        out.append(_edge_pairs(frame, k, shape, shape.feature_edges, p0, p1, pairs=(pairs[:, 0], pairs[:, 1]),
                               target_fraction=EDGE_FRACTION))
    if broadphase.TRIANGLE in cand:
        ti, fi = cand[broadphase.TRIANGLE]
        pairs = np.column_stack(broadphase.unique_pairs(np.repeat(tn[ti], 3), shape.faces[fi].ravel()))
        out.append(_corners(frame, k, shape, shape.vertices, p0, p1, pairs=(pairs[:, 0], pairs[:, 1])))
    return out


def _mesh_vertex_face(frame: Frame, k: int, shape, vi, fi, p0, p1) -> Planes:
    """Cloth vertices ``vi`` against mesh faces ``fi``: the earliest crossing, else the nearest face within th."""
    th = frame.thickness
    F, V = shape.faces[fi], shape.vertices
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    P0, P1 = p0[vi], p1[vi]
    s, side = ccd.point_triangle_toi(P0, P1, A, A, B, B, C, C, 0.1 * th)
    hit = np.isfinite(s) & (side != 0)
    parts = []
    if np.any(hit):
        j = np.flatnonzero(hit)
        j = j[np.argsort(s[j], kind="stable")]
        _, first = np.unique(vi[j], return_index=True)
        j = j[first]                                              # the earliest face per vertex
        n = side[j, None] * shape.face_normals[fi[j]]
        Ps = P0[j] + s[j, None] * (P1[j] - P0[j])
        off = np.einsum("ij,ij->i", n, A[j]) + th
        viol = off - np.einsum("ij,ij->i", n, P1[j])
        parts.append(make(vi[j], k, n, off, Ps, VERTEX, viol))
    q, _ = ccd.point_triangle_closest(P1, A, B, C)
    gap = P1 - q
    dist = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    j = np.flatnonzero((dist < th + frame.reach) & (dist > 1e-12) & ~hit)
    if len(j):
        n = gap[j] / dist[j, None]
        off = np.einsum("ij,ij->i", n, q[j]) + th
        parts.append(make(vi[j], k, n, off, q[j], VERTEX, th - dist[j]))
    return Planes.cat(parts)
