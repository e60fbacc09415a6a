"""The geometric response's stages for sharp features and cloth edges (functions over a collision context).

* Obstacle corners and tips against cloth triangles, obstacle edges against
  cloth edges: exact coplanarity time of impact (:mod:`~implicit_cloth.collision.ccd`),
  then per-vertex stopping from the time of impact and proximity pushes.
* Cloth edges against convex shapes: the smallest signed distance along each
  edge (:func:`edge_minimum`), kept at :data:`EDGE_FRACTION` of the thickness.
"""

from __future__ import annotations

import numpy as np

from ..rowwise import max1, min1
from . import ccd
from .context import Context, Obstacle, near
from .response import SETTLE_FRACTION, spread
from .shapes import Shape

#: Points along cloth edges are kept this fraction of the thickness from a surface.
EDGE_FRACTION = 0.5
#: Bisection steps in time for where an edge first entered a shape.
ENTRY_BISECTIONS = 8


def edge_minimum(shape: Shape, a0: np.ndarray, a1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter ``a`` (K,) and value (K,) m of the smallest signed distance along segments a0 -> a1
    (:meth:`Shape.segment_minimum <implicit_cloth.collision.shapes.Shape.segment_minimum>`)."""
    return shape.segment_minimum(a0, a1)



def stop_approach(ctx: Context, idx: np.ndarray, w: np.ndarray, n: np.ndarray, u: np.ndarray,
                  v: np.ndarray) -> None:
    """Remove each primitive vertex's velocity towards the obstacle along ``n`` (relative to ``u``), in place.

    Per vertex rather than an impulse at the contact point shared by weights: that
    lever throws an already resting vertex off the surface when its neighbours are
    still falling. Where several primitives ask, the largest change is kept.
    """
    vn = np.einsum("kmj,kj->km", v[idx] - u[:, None, :], n)
    app = (vn < 0) & (w > 1e-3) & (ctx.inv_mass[idx] > 0)
    if not np.any(app):
        return
    k_, m_ = np.nonzero(app)
    dv = -vn[k_, m_, None] * n[k_]
    mag = np.einsum("ij,ij->i", dv, dv)
    order = np.argsort(mag)
    best = np.zeros((ctx.n, 3))
    best[idx[k_, m_][order]] = dv[order]
    v += best


def edge_proximity(ctx: Context, ob: Obstacle, x0, x, v, t0, t1, h) -> tuple[bool, int, int]:
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
    th = ctx.thickness
    mo, shape = ob.motion, ob.shape
    if shape.flat:
        return False, 0, 0
    _, R1 = mo.pose(t1)
    p = mo.to_local(x, t1)
    q = p[ctx.edges]
    nr = np.flatnonzero(near(ob.shape, q, q, th))
    if not len(nr):
        return False, 0, 0
    a0, a1 = q[nr, 0], q[nr, 1]
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
        return False, len(nr), 0
    deep = np.flatnonzero(act & (phi < -th))
    if len(deep):
        e = ctx.edges[nr[deep]]
        s0 = mo.to_local(x0, t0)[e]
        lo, hi = np.zeros(len(deep)), np.ones(len(deep))
        for _ in range(ENTRY_BISECTIONS):
            mid = 0.5 * (lo + hi)
            qm = s0 + mid[:, None, None] * (q[nr[deep]] - s0)
            _, fm = edge_minimum(shape, qm[:, 0], qm[:, 1])
            inside = fm < target
            hi = np.where(inside, mid, hi)
            lo = np.where(inside, lo, mid)
        qe = s0 + hi[:, None, None] * (q[nr[deep]] - s0)
        ae, _ = edge_minimum(shape, qe[:, 0], qe[:, 1])
        _, ne, ce = shape.closest(qe[:, 0] + ae[:, None] * (qe[:, 1] - qe[:, 0]))
        a[deep] = ae
        n_loc[deep] = ne
        pe = a0[deep] + ae[:, None] * d[deep]
        phi[deep] = np.einsum("ij,ij->i", pe - ce, ne)     # height above the entry's tangent plane
    idx = ctx.edges[nr[act]]
    w = np.column_stack([1.0 - a[act], a[act]])
    deficit = np.maximum(target - phi[act], 0.0)
    n_w = n_loc[act] @ R1.T
    change, _ = spread(ctx.n, idx, w, ctx.inv_mass, deficit[:, None] * n_w)
    x += change
    stop_approach(ctx, idx, w, n_w, mo.point_velocity(np.einsum("km,kmj->kj", w, x[idx]), t1), v)
    return bool(np.any(deficit > SETTLE_FRACTION * th)), len(nr), int(act.sum())

def features(ctx: Context, ob: Obstacle, x0, x, v, t0, t1, h):
    """Obstacle corners vs cloth triangles and obstacle edges vs cloth edges (step d)."""
    th = ctx.thickness
    mo, shape = ob.motion, ob.shape
    busy, cand, contacts = False, 0, 0
    fp, fe = shape.feature_points, shape.feature_edges
    for kind in ("vf", "ee"):
        prims = ctx.faces if kind == "vf" else ctx.edges
        feats = fp if kind == "vf" else fe
        if not len(feats):
            continue
        q0 = mo.to_local(x0, t0)[prims]            # (K, m, 3)
        q1 = mo.to_local(x, t1)[prims]
        nr = np.flatnonzero(near(ob.shape, q0, q1, th))
        if not len(nr):
            continue
        lo = np.minimum(min1(q0[nr]), min1(q1[nr])) - th
        hi = np.maximum(max1(q0[nr]), max1(q1[nr])) + th
        if kind == "vf":
            flo = fhi = feats                      # (F, 3)
        else:
            flo, fhi = feats.min(axis=1), feats.max(axis=1)
        m = np.all((lo[None] <= fhi[:, None]) & (hi[None] >= flo[:, None]), axis=2)   # (F, K)
        fi, kj = np.nonzero(m)
        if not len(fi):
            continue
        pr = nr[kj]
        cand += len(pr)
        b, k = feature_pairs(ctx, ob, kind, prims, q0, q1, pr, fi, feats, x0, x, v, t0, t1, h)
        busy |= b
        contacts += k
    return busy, cand, contacts

def feature_pairs(ctx: Context, ob: Obstacle, kind: str, prims: np.ndarray, q0: np.ndarray, q1: np.ndarray,
                   pr: np.ndarray, fi: np.ndarray, feats: np.ndarray, x0, x, v, t0, t1, h,
                   ee_proximity: bool = False) -> tuple[bool, int]:
    """Exact tests and response for candidate pairs: obstacle point ``feats[fi]`` vs cloth triangle
    ``prims[pr]`` (kind "vf") or obstacle edge ``feats[fi]`` vs cloth edge ``prims[pr]`` (kind "ee").

    ``q0``, ``q1`` are the primitives' corners (K, m, 3) at the start and end, local frame.
    """
    th = ctx.thickness
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
            dv *= (ctx.inv_mass[vid] > 0)[:, None]
            best = np.zeros((ctx.n, 3))
            when = np.zeros(ctx.n)
            # one change per vertex: the largest requested (they share a direction locally),
            # applied from the time of impact: x = x(s) + (1 - s) h v'
            mag = np.sqrt(np.einsum("ij,ij->i", dv, dv))
            order = np.argsort(mag)
            best[vid[order]] = dv[order]
            when[vid[order]] = s[hi_[k_]][order]
            x += (h * (1.0 - when))[:, None] * best
            v += best
            busy = True
            contacts += int(np.any(app, axis=1).sum())
    if kind == "ee":
        if ee_proximity:   # meshes: no signed distance, so edges keep EDGE_FRACTION of the thickness here
            b, k = edge_edge_proximity(ctx, ob, prims, pr, feats[fi, 0], feats[fi, 1], hit, side, x, v, t1)
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
    change, _ = spread(ctx.n, idx, wa, ctx.inv_mass, (deficit[:, None] * d) @ R1.T)
    x += change
    # velocity: the triangle's vertices stop approaching the feature
    stop_approach(ctx, idx, wa, d @ R1.T, mo.point_velocity(f[act] @ R1.T + c1, t1), v)
    contacts += int(act.sum())
    busy |= bool(np.any(deficit > SETTLE_FRACTION * th))
    return busy, contacts

def edge_edge_proximity(ctx: Context, ob: Obstacle, prims, pr, e0, e1, hit, side, x, v, t1) -> tuple[bool, int]:
    """Cloth edges ``prims[pr]`` nearer than ``EDGE_FRACTION * thickness`` to obstacle edges ``e0 e1`` are pushed away.

    Along the gap between the closest points; after a crossing in this step, along
    ``(cloth edge) x (obstacle edge)`` turned to the side the cloth edge came from.
    """
    th = ctx.thickness
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
    change, _ = spread(ctx.n, idx, w, ctx.inv_mass, (deficit[:, None] * d) @ R1.T)
    x += change
    g = (e0 + b[:, None] * (e1 - e0))[act] @ R1.T + c1
    stop_approach(ctx, idx, w, d @ R1.T, mo.point_velocity(g, t1), v)
    return bool(np.any(deficit > SETTLE_FRACTION * th)), int(act.sum())
