"""Self-collision response: proximity and impact impulses between cloth primitives, rigid impact zones.

A pair is four vertices ``idx`` and coefficients ``c`` such that the pair's relative velocity is
``sum_k c_k v[idx_k]`` (first primitive minus second): a vertex-triangle pair ``[p, a, b, c]`` with
``c = [1, -w_a, -w_b, -w_c]`` (``w`` the barycentric weights of the closest point), an edge-edge pair
``[p, q, u, w]`` with ``c = [1 - s, s, -(1 - t), -t]`` (``s``, ``t`` the closest points' parameters). The
normal ``n`` points from the second primitive to the first, so ``n . v_rel > 0`` separates.

An impulse changing the relative normal velocity by ``dn >= 0`` is ``j = dn / sum_k c_k^2 / m_k`` along ``n``;
vertex ``k`` changes its velocity by ``c_k j n / m_k`` (Bridson, Fedkiw & Anderson 2002, §7.1, with masses).
Friction removes up to ``mu dn`` of the tangential relative velocity, never more than there is (§7.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..collision.ccd import edge_edge_toi, point_triangle_closest, point_triangle_toi, segment_closest
from ..collision.context import cloth_edges
from . import broadphase

__all__ = ["Pairs", "Response", "cloth_edges", "pair_distances"]

#: Impacts separate to at most this fraction of the thickness by the end of the step (at no more than the
#: speed they approached with).
IMPACT_SEPARATION = 0.1
#: A root of the coplanarity cubic is an impact when the primitives are within this fraction of the thickness
#: then (at the root a crossing point is in the plane only to rounding, so the tolerance must not be 0).
IMPACT_TOLERANCE = 1e-3
#: Pairs whose distances and times of impact are computed at once: the tests hold tens of arrays of this
#: length (the 128² crumple's impact step has tens of millions of candidates; all at once they took the
#: machine's 24 GB).
IMPACT_CHUNK = 1 << 18
#: Most passes of the impact-zone fail-safe (zones merge every pass; Bridson et al. prove it ends).
MAX_ZONE_PASSES = 50
#: A vertex whose corrected end position left its box of the broad phase by more than this fraction of the
#: thickness has the candidates found again.
REBUILD_FRACTION = 0.5
#: When more than this fraction of the vertices drifted so, the candidates are searched again whole, not
#: around them.
AROUND_FRACTION = 0.25


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _unit(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.sqrt(_dot(a, a))
    return a / np.where(n > 0, n, 1.0)[:, None], n


@dataclass
class Pairs:
    """Candidate pairs of one step: ``idx`` (K, 4) vertex indices, ``vf`` (K,) True for vertex-triangle pairs."""

    idx: np.ndarray
    vf: np.ndarray
    x1: np.ndarray          # the broad phase's end positions, to tell when to search again
    d0: np.ndarray          # the pairs' distances at the start of the step, m
    shift: np.ndarray       # the translation (3,) taken from every end in the search (:meth:`find`), m

    @property
    def count(self) -> int:
        return len(self.idx)

    @classmethod
    def find(cls, x0: np.ndarray, x1: np.ndarray, faces: np.ndarray, edges: np.ndarray, reach: float,
             inv: np.ndarray, shift: np.ndarray | None = None) -> "Pairs":
        """Vertex-triangle and edge-edge candidates of the motion ``x0 -> x1`` within ``reach``; pairs with no
        movable vertex are left out.

        The search sees the ends translated by ``shift`` (default: the median displacement). That changes no
        distance at any time of the step: under the straight-line motion every vertex is translated by
        ``s * shift`` at time ``s``, all of them alike. But a cloth falling or swept as a whole no longer
        sweeps its boxes over its own neighbours: a 128² sheet falling 1.3 cm a step in its own plane (the
        crumple) had each vertex's box over the next 2-3 rows of triangles. Each pair is then tested alone
        with the motion of its first vertex taken out (:func:`_together`), before its distance is computed.
        """
        if shift is None:
            shift = np.median(x1 - x0, axis=0) if len(x0) else np.zeros(3)
        y1 = x1 - shift
        found = (broadphase.vertex_face_pairs(x0, y1, faces, reach), broadphase.edge_edge_pairs(x0, y1, edges, reach))
        idx, vf, d0 = _movable_pairs(x0, x1, faces, edges, inv, reach, *found)
        return cls(idx, vf, x1.copy(), d0, np.array(shift, dtype=float))

    def refresh(self, x0: np.ndarray, x1: np.ndarray, far: np.ndarray, faces: np.ndarray, edges: np.ndarray,
                reach: float, inv: np.ndarray) -> tuple["Pairs", np.ndarray]:
        """The candidates after the vertices ``far`` (boolean) moved their ends to ``x1``: the pairs among the
        other vertices are kept, those with a vertex in ``far`` searched again. Returns the new candidates (the
        kept ones first) and the indices of the kept ones among these.

        The result is the candidate set :meth:`find` gives for the motion from ``x0`` to the ends the search
        last saw (``x1`` for the vertices ``far``, the earlier ends for the others) with the same ``shift``, so
        the rule that searches again once a vertex drifts from where the search saw it covers every pair as
        before.
        """
        ref = self.x1.copy()
        ref[far] = x1[far]
        kept = np.flatnonzero(~np.any(far[self.idx], axis=1))
        around = broadphase.pairs_around(x0, ref - self.shift, faces, edges, reach, far)
        idx, vf, d0 = _movable_pairs(x0, ref, faces, edges, inv, reach, *around)
        new = Pairs(np.concatenate([self.idx[kept], idx]), np.concatenate([self.vf[kept], vf]), ref,
                    np.concatenate([self.d0[kept], d0]), self.shift)
        return new, kept


def _movable_pairs(x0: np.ndarray, x1: np.ndarray, faces: np.ndarray, edges: np.ndarray, inv: np.ndarray,
                   reach: float, vf_pairs: tuple[np.ndarray, np.ndarray], ee_pairs: tuple[np.ndarray, np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The broad phase's (vertex, face) and (edge, edge) pairs as ``idx``, ``vf`` (:class:`Pairs`) and their
    distances at ``x0``, leaving out the pairs with no movable vertex and those :func:`_together` rules out."""
    (v, f), (a, b) = vf_pairs, ee_pairs
    idx = np.concatenate([np.column_stack([v, faces[f]]), np.column_stack([edges[a], edges[b]])]).reshape(-1, 4)
    vf = np.concatenate([np.ones(len(v), dtype=bool), np.zeros(len(a), dtype=bool)])
    keep = np.any(inv[idx] > 0, axis=1)
    for p in _pieces(len(idx)):
        keep[p] &= _together(x0, x1, idx[p], vf[p], reach)
    idx, vf = idx[keep], vf[keep]
    d0 = np.empty(len(idx))
    for p in _pieces(len(idx)):
        d0[p] = closest(x0, idx[p], vf[p])[2]
    return idx, vf, d0


def _together(x0: np.ndarray, x1: np.ndarray, idx: np.ndarray, vf: np.ndarray, reach: float) -> np.ndarray:
    """Whether each pair's two boxes over the step overlap, inflated as in the broad phase (a vertex's by
    ``reach``, a triangle's by 0, each edge's by half of it), with the mean displacement of the pair's four
    vertices taken from their ends (the same whichever primitive comes first): a translation of one pair's
    motion (as :meth:`Pairs.find`'s of all) keeps its distances at every time, so a pair ruled out so
    cannot come within ``reach`` in the step. It rules out the neighbours that a fold moving as one sweeps
    over, which the search's one translation for the whole cloth cannot."""
    A, B = x0[idx], x1[idx]
    B -= 0.25 * ((B[:, 0] - A[:, 0]) + (B[:, 1] - A[:, 1]) + (B[:, 2] - A[:, 2]) + (B[:, 3] - A[:, 3]))[:, None, :]
    return _boxes_meet(A, B, vf, reach)


def _boxes_meet(A: np.ndarray, B: np.ndarray, vf: np.ndarray, reach: float) -> np.ndarray:
    """Whether each pair's two primitives' boxes over the step (corners ``A -> B``, (K, 4, 3)) overlap, a
    vertex's inflated by ``reach``, a triangle's by 0, each edge's by half of it (column by column: no masks,
    no reductions over a short axis)."""
    out = np.empty(len(A), dtype=bool)
    for kind, cut, r1, r2 in ((vf, 1, reach, 0.0), (~vf, 2, 0.5 * reach, 0.5 * reach)):
        a, b = A[kind], B[kind]
        one = [Y[:, k] for Y in (a, b) for k in range(cut)]
        two = [Y[:, k] for Y in (a, b) for k in range(cut, 4)]
        lo1, hi1 = np.minimum.reduce(one) - r1, np.maximum.reduce(one) + r1
        lo2, hi2 = np.minimum.reduce(two) - r2, np.maximum.reduce(two) + r2
        out[kind] = np.all((lo1 <= hi2) & (lo2 <= hi1), axis=1)
    return out


def _pieces(k: int) -> list[slice]:
    """``range(k)`` in slices of at most IMPACT_CHUNK pairs: each pair's distance or time of impact depends on
    that pair alone, so computing them piece by piece gives the same numbers with a bounded working set."""
    return [slice(a, min(a + IMPACT_CHUNK, k)) for a in range(0, k, IMPACT_CHUNK)]


def closest(x: np.ndarray, idx: np.ndarray, vf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (K, 4), unit normals (K, 3) and distances (K,) of the pairs' closest points at ``x``."""
    k = len(idx)
    c = np.zeros((k, 4))
    diff = np.zeros((k, 3))
    plane = np.zeros((k, 3))
    P = x[idx]
    t = np.flatnonzero(vf)
    if len(t):
        p, a, b, cc = P[t, 0], P[t, 1], P[t, 2], P[t, 3]
        q, w = point_triangle_closest(p, a, b, cc)
        c[t, 0] = 1.0
        c[t, 1:] = -w
        diff[t] = p - q
        nt = np.cross(b - a, cc - a)
        plane[t] = nt * np.where(_dot(nt, p - a) < 0, -1.0, 1.0)[:, None]
    e = np.flatnonzero(~vf)
    if len(e):
        p, q, u, w = P[e, 0], P[e, 1], P[e, 2], P[e, 3]
        s, r = segment_closest(p, q, u, w)
        c[e] = np.column_stack([1.0 - s, s, -(1.0 - r), -r])
        diff[e] = (p + s[:, None] * (q - p)) - (u + r[:, None] * (w - u))
        ne = np.cross(q - p, w - u)
        plane[e] = ne * np.where(_dot(ne, diff[e]) < 0, -1.0, 1.0)[:, None]
    n, d = _unit(diff)
    tiny = d <= 1e-12
    if np.any(tiny):                                    # touching: the plane's normal, on the pair's side
        n[tiny] = _unit(plane[tiny])[0]
    return c, n, d


def pair_distances(x: np.ndarray, faces: np.ndarray, edges: np.ndarray, vf_pairs, ee_pairs
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Distances of vertex-triangle pairs ``(v, f)`` and edge-edge pairs ``(a, b)`` at ``x``, m."""
    v, f = vf_pairs
    a, b = ee_pairs
    idx = np.concatenate([np.column_stack([v, faces[f]]), np.column_stack([edges[a], edges[b]])]).reshape(-1, 4)
    vf = np.arange(len(idx)) < len(v)
    _, _, d = closest(x, idx, vf)
    return d[vf], d[~vf]


def impacts(x0: np.ndarray, x1: np.ndarray, idx: np.ndarray, vf: np.ndarray, tol: float,
            d0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Time of impact (fraction of the step, inf if none) and unit normal (first minus second primitive) of each
    pair under the linear motion ``x0 -> x1``: the coplanarity cubic's earliest root at which the primitives
    are within ``tol`` (m) of each other (:mod:`implicit_cloth.collision.ccd`).

    ``d0``: the pairs' distances at ``x0``; a pair farther apart than the largest displacement of a vertex of its
    first primitive relative to one of its second cannot meet in the step and is not tested (the closest points
    are convex combinations of the vertices, so the distance changes by no more than that; layers falling
    together move little relative to each other however fast they fall).
    """
    k = len(idx)
    if k <= IMPACT_CHUNK:
        return _impacts(x0, x1, idx, vf, tol, d0)
    s, n = np.full(k, np.inf), np.zeros((k, 3))
    for p in _pieces(k):
        s[p], n[p] = _impacts(x0, x1, idx[p], vf[p], tol, None if d0 is None else d0[p])
    return s, n


def _impacts(x0: np.ndarray, x1: np.ndarray, idx: np.ndarray, vf: np.ndarray, tol: float,
             d0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`impacts` of one piece of the pairs."""
    k = len(idx)
    s = np.full(k, np.inf)
    n = np.zeros((k, 3))
    if not k:
        return s, n
    A, B = x0[idx], x1[idx]
    if d0 is not None:
        D = B - A
        # vertex pairs (first, second): (0, 1), (0, 2), (0, 3) of a vertex-triangle pair, the last four of an edge pair
        links = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3))
        rel = np.stack([_dot(D[:, i] - D[:, j], D[:, i] - D[:, j]) for i, j in links], axis=1)
        most = np.sqrt(np.where(vf, rel[:, :3].max(axis=1), rel[:, 1:].max(axis=1)))
        cand = np.flatnonzero(d0 <= most + tol)
    else:
        cand = np.arange(k)
    # the two primitives' boxes over the step must overlap (first: vertex or edge, second: triangle or edge)
    near = np.zeros(k, dtype=bool)
    near[cand[_boxes_meet(A[cand], B[cand], vf[cand], 0.0)]] = True
    # each kind's time of impact, and its normal then: the triangle's (corners 1, 2, 3) for a vertex-triangle
    # pair, minus the two edges' cross product for an edge-edge pair; ``side`` orients it (first minus second)
    kinds: tuple[tuple[np.ndarray, Callable[..., Any], tuple[int, int, int, int], float], ...] = (
        (vf, point_triangle_toi, (2, 1, 3, 1), 1.0), (~vf, edge_edge_toi, (1, 0, 3, 2), -1.0))
    for kind, toi, (i0, i1, j0, j1), sign in kinds:
        sel = np.flatnonzero(near & kind)
        if not len(sel):
            continue
        st, side = toi(*(Y[sel, m] for m in range(4) for Y in (A, B)), tol)
        s[sel] = st
        hit = np.isfinite(st)
        h_ = sel[hit]
        X = A[h_] + st[hit, None, None] * (B[h_] - A[h_])
        n[h_] = sign * _unit(np.cross(X[:, i0] - X[:, i1], X[:, j0] - X[:, j1]))[0] * side[hit, None]
    # a pair that starts coplanar (side 0) takes the normal of its closest points at the start
    flat = np.isfinite(s) & (np.einsum("ij,ij->i", n, n) < 0.5)
    if np.any(flat):
        n[flat] = closest(x0, idx[flat], vf[flat])[1]
    return s, n


def impulses(v: np.ndarray, idx: np.ndarray, c: np.ndarray, n: np.ndarray, dn: np.ndarray, inv: np.ndarray,
             mu: float, wall: np.ndarray | None = None, work: list[float] | None = None) -> np.ndarray:
    """Velocity changes (N, 3) of the impulses that raise each pair's relative normal velocity by ``dn >= 0``,
    with friction ``mu``, averaged over the pairs acting on each vertex (Jacobi).

    ``wall`` (N, 3): the outward normal of the obstacle holding each vertex (0 where none): the part of a
    vertex's change into that obstacle is taken by the obstacle (removed), so a layer landing on cloth that
    lies on the floor is stopped by the floor through it. The pair's other vertices keep their share only, so
    the pair's approach slows less but never reverses: still only energy taken.

    ``work`` (a list, appended to): the work of the pins through these impulses, J. A pinned vertex (``inv``
    0) does not move: its pin takes the pair's reaction and, moving, does work on the cloth. Each pair with
    pinned vertices gives its free vertices the momentum ``c_k j n`` (shared as their changes are, over the
    pairs acting on them); the pins' work is that momentum times the pinned part's velocity at the pair
    (``v`` of its pinned vertices, weighted by ``|c_k|``). In that part's frame the impulse only takes energy
    away, so the free vertices gain at most that. Vertices an obstacle holds (``wall``) are left out of it (the
    obstacle takes part of their change): the work is not over-counted.
    """
    out = np.zeros_like(v)
    act = dn > 0
    if not np.any(act):
        return out
    idx, c, n, dn = idx[act], c[act], n[act], dn[act]
    w = inv[idx]                                        # (K, 4)
    m_inv = np.einsum("ik,ik->i", c * c, w)
    ok = m_inv > 0
    idx, c, n, dn, w, m_inv = idx[ok], c[ok], n[ok], dn[ok], w[ok], m_inv[ok]
    rel = np.einsum("ik,ikj->ij", c, v[idx])
    vt = rel - _dot(rel, n)[:, None] * n
    t_dir, vt_norm = _unit(vt)
    dt = np.minimum(mu * dn, vt_norm)                  # Coulomb: at most mu times the normal change, never reversing
    J = ((dn / m_inv)[:, None] * n - (dt / m_inv)[:, None] * t_dir)
    dv = (c * w)[:, :, None] * J[:, None, :]            # (K, 4, 3)
    flat = idx.ravel()
    for j in range(3):
        out[:, j] = np.bincount(flat, weights=dv[:, :, j].ravel(), minlength=len(v))
    count = np.bincount(flat[(c * w).ravel() != 0], minlength=len(v))
    out /= np.maximum(count, 1)[:, None]
    if work is not None:
        work.append(_pins_work(v, idx, c, w, J, count, wall))
    if wall is not None:
        into = np.minimum(_dot(out, wall), 0.0)
        out -= into[:, None] * wall
    return out


def _pins_work(v: np.ndarray, idx: np.ndarray, c: np.ndarray, w: np.ndarray, J: np.ndarray, count: np.ndarray,
               wall: np.ndarray | None) -> float:
    """The pins' work through the impulses ``J`` (K, 3) of pairs ``idx``, ``c`` (inverse masses ``w``) of
    :func:`impulses`: each pair's momentum to its free vertices times its pinned part's velocity, J."""
    pinned = (w == 0) & (c != 0)
    rows = np.flatnonzero(pinned.any(axis=1))
    if not len(rows):
        return 0.0
    weight = np.where(pinned[rows], np.abs(c[rows]), 0.0)
    u = np.einsum("rk,rkj->rj", weight, v[idx[rows]]) / weight.sum(axis=1)[:, None]
    free = (w[rows] > 0) & (c[rows] != 0)
    if wall is not None:
        free &= ~np.any(wall[idx[rows]] != 0, axis=2)
    share = np.where(free, c[rows] / np.maximum(count[idx[rows]], 1), 0.0).sum(axis=1)
    return float(np.einsum("r,rj,rj->", share, J[rows], u))


class Response:
    """The proximity, impact and impact-zone passes of one step (module docstring)."""

    def __init__(self, faces: np.ndarray, edges: np.ndarray, masses: np.ndarray, thickness: float,
                 friction: float, rounds: int) -> None:
        self.faces, self.edges, self.masses = faces, edges, masses
        self.th, self.mu, self.rounds = thickness, friction, rounds
        self.wall: np.ndarray | None = None
        self.tol = IMPACT_TOLERANCE * thickness
        #: the pins' work on the cloth through this pass's impulses and impact zones, J (appended to)
        self.work: list[float] = []

    def run(self, x0: np.ndarray, after: Any, h: float, inv: np.ndarray, pairs: Pairs, info: Any,
            wall: np.ndarray | None = None) -> Pairs:
        """Correct ``after`` (x, v) in place; ``inv`` the inverse masses (0: not moved), ``wall`` the normals of
        the obstacles holding vertices (:func:`impulses`; held vertices anchor impact zones). Returns the
        candidates as last searched."""
        self.wall = wall
        self.work = []
        th, mu = self.th, self.mu
        vb = (after.x - x0) / h
        vb0 = vb.copy()
        v1 = after.v
        # proximity at the start: stop the approach of pairs nearer than the thickness
        near = pairs.d0 < th
        if np.any(near):
            c, n, d = closest(x0, pairs.idx[near], pairs.vf[near])
            idx, cn, nn = pairs.idx[near], c, n
            vn = _dot(np.einsum("ik,ikj->ij", cn, vb[idx]), nn)
            dn = np.maximum(-vn, 0.0)       # inelastic: pushing the pair apart would lift it from nowhere
            info.proximities += int(np.count_nonzero(dn > 0))
            self._apply(vb, v1, idx, cn, nn, dn, inv, mu)
        # impacts: each round tests again only the pairs with a vertex the last round moved
        toi = _Impacts(self)
        hit = np.zeros(pairs.count, dtype=bool)
        for _ in range(self.rounds):
            x1 = x0 + h * vb
            pairs, s, n = toi.update(pairs, x0, x1, inv)
            hit = np.isfinite(s)
            info.rounds += 1
            if not np.any(hit):
                break
            info.impacts += int(hit.sum())
            idx, vf, s_, n_ = pairs.idx[hit], pairs.vf[hit], s[hit], n[hit]
            Xs = x0[idx] + s_[:, None, None] * (x1[idx] - x0[idx])
            c, _, _ = closest(Xs.reshape(-1, 3), np.arange(4 * len(idx)).reshape(-1, 4), vf)
            vn = _dot(np.einsum("ik,ikj->ij", c, vb[idx]), n_)
            sep = IMPACT_SEPARATION * th / np.maximum((1.0 - s_) * h, 1e-12)
            dn = np.where(vn < 0, np.minimum(-vn, sep) - vn, 0.0)
            before = vb.copy()
            self._apply(vb, v1, idx, c, n_, dn, inv, mu)
            toi.moved(np.any(vb != before, axis=1))
        else:
            x1 = x0 + h * vb
            pairs, s, _ = toi.update(pairs, x0, x1, inv)
            hit = np.isfinite(s)
        if np.any(hit):
            self._zones(x0, vb, v1, h, inv, pairs, hit, info, toi)
        moved = np.any(vb != vb0, axis=1)
        after.x[moved] = x0[moved] + h * vb[moved]
        info.work += float(sum(self.work))
        return toi.pairs if toi.pairs is not None else pairs

    def _apply(self, vb, v1, idx, c, n, dn, inv, mu) -> None:
        """The impulses on the average velocity, and on the end velocity only what removes its approach (the
        pins' work booked from these: the end velocities carry the kinetic energy the step ends with)."""
        vb += impulses(vb, idx, c, n, dn, inv, mu, self.wall)
        vn1 = _dot(np.einsum("ik,ikj->ij", c, v1[idx]), n)
        dn1 = np.minimum(np.maximum(-vn1, 0.0), dn)
        v1 += impulses(v1, idx, c, n, dn1, inv, mu, self.wall, self.work)

    def _fresh(self, pairs: Pairs, x0: np.ndarray, x1: np.ndarray, inv: np.ndarray
               ) -> tuple[Pairs, np.ndarray | None]:
        """The candidates again around the vertices whose end moved away from where the broad phase saw it (all
        of them when many did), and the indices of the pairs kept (None: all new, or no change)."""
        far = np.abs(x1 - pairs.x1).max(axis=1) > REBUILD_FRACTION * self.th
        count = int(np.count_nonzero(far))
        if not count:
            return pairs, None
        if count > AROUND_FRACTION * len(x0):
            return Pairs.find(x0, x1, self.faces, self.edges, self.th, inv), None
        return pairs.refresh(x0, x1, far, self.faces, self.edges, self.th, inv)

    # ------------------------------------------------------------------ rigid impact zones
    def _zones(self, x0, vb, v1, h, inv, pairs: Pairs, hit, info, toi: "_Impacts") -> None:
        n = len(x0)
        label = np.full(n, -1, dtype=np.int64)
        for _ in range(MAX_ZONE_PASSES):
            ids = pairs.idx[hit]
            involved = np.zeros(n, dtype=bool)
            involved[ids.ravel()] = True
            involved |= label >= 0
            rows = [ids[:, :3].ravel()]
            cols = [ids[:, 1:].ravel()]
            zv = np.flatnonzero(label >= 0)           # keep old zones joined: each member to its zone's first
            if len(zv):
                first = np.full(label.max() + 1, -1)
                first[label[zv][::-1]] = zv[::-1]
                rows.append(zv)
                cols.append(first[label[zv]])
            r, cc = np.concatenate(rows), np.concatenate(cols)
            graph = coo_matrix((np.ones(len(r)), (r, cc)), shape=(n, n))
            _, comp = connected_components(graph, directed=False)
            members = np.flatnonzero(involved)
            _, label_m = np.unique(comp[members], return_inverse=True)
            label[:] = -1
            label[members] = label_m
            before = vb.copy()
            rigid = self._rigid(x0, vb, v1, h, inv, label)
            toi.moved(np.any(vb != before, axis=1))
            x1 = x0 + h * vb
            pairs, s, _ = toi.update(pairs, x0, x1, inv)
            hit = np.isfinite(s)
            found = np.flatnonzero(hit)                 # (the few hits, not all the candidates)
            hit[found[_within(label, rigid, pairs.idx[found])]] = False
            if not np.any(hit):
                break
        info.unresolved = int(hit.sum())
        info.zones = int(label.max() + 1)
        info.zone_vertices = int(np.count_nonzero(label >= 0))

    def _rigid(self, x0, vb, v1, h, inv, label) -> np.ndarray:
        """Each zone's vertices move rigidly (their own linear and angular momentum). A zone with a pinned vertex
        translates with the pins' mean motion; one with a vertex held by an obstacle translates with its mean
        motion, or stays where it started if that goes into an obstacle holding one of its vertices. Returns
        which zones moved rigidly over the step (all but those whose pins move apart)."""
        zv = np.flatnonzero(label >= 0)
        z = label[zv]
        nz = int(z.max()) + 1
        m = self.masses[zv]
        pinned = inv[zv] == 0
        held = np.any(self.wall[zv] != 0, axis=1) if self.wall is not None else np.zeros(len(zv), dtype=bool)
        n_pin = np.bincount(z[pinned], minlength=nz)
        n_held = np.bincount(z[held], minlength=nz)
        mean_b = np.zeros((nz, 3))
        for arr in (vb, v1):
            # pinned: the pins' mean velocity; held: the zone's mean velocity (momentum kept), or rest
            w = np.where(n_pin[z] > 0, pinned.astype(float), m)
            mean = _sums(z, nz, w[:, None] * arr[zv]) / np.maximum(np.bincount(z, weights=w, minlength=nz),
                                                                    1e-300)[:, None]
            if arr is vb:
                mean_b = mean
            if self.wall is not None and np.any(held):
                into = np.zeros(nz, dtype=bool)
                np.logical_or.at(into, z[held], _dot(mean[z[held]], self.wall[zv[held]]) < 0)
                mean[into & (n_pin == 0)] = 0.0
            sel = ~pinned & ((n_pin[z] > 0) | (n_held[z] > 0))
            if arr is v1:                  # the pins' work: the momentum they give the zone times their velocity
                by_pins = sel & (n_pin[z] > 0)
                if np.any(by_pins):
                    k = zv[by_pins]
                    dp = m[by_pins, None] * (mean[z[by_pins]] - arr[k])
                    self.work.append(float(np.einsum("ij,ij->", dp, mean[z[by_pins]])))
            arr[zv[sel]] = mean[z[sel]]
        # a zone's pins moving apart (not with one velocity) do not move it rigidly
        spread = np.zeros(nz)
        if np.any(pinned):
            np.maximum.at(spread, z[pinned], np.abs(vb[zv[pinned]] - mean_b[z[pinned]]).max(axis=1))
        rigid = spread == 0
        free = (n_pin[z] == 0) & (n_held[z] == 0)
        if not np.any(free):
            return rigid
        zv, m = zv[free], m[free]
        _, z = np.unique(z[free], return_inverse=True)
        nz = int(z.max()) + 1
        x1 = x0[zv] + h * rigid_velocities(x0[zv], vb[zv], m, z, nz, h)
        vb[zv] = (x1 - x0[zv]) / h
        v1[zv] = rigid_velocities(x1, v1[zv], m, z, nz, None)
        return rigid


def _within(label: np.ndarray, rigid: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Pairs whose four vertices are in one zone that moved rigidly: they keep their distances over the step
    (its end is a rigid motion of a start without crossings), so a time of impact found for them is not an
    impact: the straight-line motion's coplanarity cubic of a rigidly moving pair keeps its sign (it scales
    by a positive determinant), and such a hit is a pair already coplanar and within the tolerance at the
    start (layers lying flat on each other), which no zone motion could clear (Bridson et al. 2002, §7.4)."""
    z = label[idx]
    same = np.all(z == z[:, :1], axis=1) & (z[:, 0] >= 0)
    out = np.zeros(len(idx), dtype=bool)
    out[same] = rigid[z[same, 0]]
    return out


class _Impacts:
    """The times of impact of one step's candidates, kept between the rounds: after a round only the pairs with a
    vertex it moved are tested again (a pair's time of impact depends on its four vertices' motion only), all of
    them when the candidates were searched again."""

    def __init__(self, response: Response) -> None:
        self.r = response
        self.pairs: Pairs | None = None
        self.s: np.ndarray = np.zeros(0)
        self.n: np.ndarray = np.zeros((0, 3))
        self.changed: np.ndarray | None = None

    def moved(self, changed: np.ndarray) -> None:
        self.changed = changed if self.changed is None else (self.changed | changed)

    def update(self, pairs: Pairs, x0: np.ndarray, x1: np.ndarray, inv: np.ndarray
               ) -> tuple[Pairs, np.ndarray, np.ndarray]:
        fresh, kept = self.r._fresh(pairs, x0, x1, inv)
        if self.changed is None or (fresh is not self.pairs and kept is None):
            self.s, self.n = impacts(x0, x1, fresh.idx, fresh.vf, self.r.tol, fresh.d0)
        else:
            test = np.any(self.changed[fresh.idx], axis=1)
            if fresh is not self.pairs:         # kept pairs first, their times as they were; the new ones tested
                assert kept is not None
                s, n = np.full(fresh.count, np.inf), np.zeros((fresh.count, 3))
                s[:len(kept)], n[:len(kept)] = self.s[kept], self.n[kept]
                self.s, self.n = s, n
                test[len(kept):] = True
            sel = np.flatnonzero(test)
            if len(sel):
                self.s[sel], self.n[sel] = impacts(x0, x1, fresh.idx[sel], fresh.vf[sel], self.r.tol, fresh.d0[sel])
        self.pairs, self.changed = fresh, None
        return fresh, self.s, self.n


def _sums(z: np.ndarray, nz: int, w: np.ndarray) -> np.ndarray:
    return np.stack([np.bincount(z, weights=w[:, j], minlength=nz) for j in range(w.shape[1])], 1)


def rigid_velocities(x: np.ndarray, v: np.ndarray, m: np.ndarray, z: np.ndarray, nz: int,
                     h: float | None) -> np.ndarray:
    """The rigid motion of each zone ``z`` with the zone's linear and angular momentum.

    With ``h`` None: the rigid velocity field ``v_c + omega x (x - x_c)`` (the mass-weighted projection of
    ``v`` onto rigid motions, which only removes kinetic energy). With ``h``: the average velocity over ``h``
    of the exact rigid motion, ``(x_c + h v_c + R(h omega) (x - x_c) - x) / h`` (Bridson et al. §7.4).
    """
    M = np.bincount(z, weights=m, minlength=nz)
    xc = _sums(z, nz, m[:, None] * x) / M[:, None]
    vc = _sums(z, nz, m[:, None] * v) / M[:, None]
    r = x - xc[z]
    L = _sums(z, nz, m[:, None] * np.cross(r, v - vc[z]))
    rr = _dot(r, r)
    Iv = (m * rr)[:, None, None] * np.eye(3)[None] - m[:, None, None] * r[:, :, None] * r[:, None, :]
    inertia = _sums(z, nz, Iv.reshape(-1, 9)).reshape(nz, 3, 3)
    scale = np.trace(inertia, axis1=1, axis2=2)
    inertia += (1e-12 * scale + 1e-300)[:, None, None] * np.eye(3)[None]   # a zone on a line turns about it freely
    omega = np.linalg.solve(inertia, L[:, :, None])[:, :, 0]
    if h is None:
        return vc[z] + np.cross(omega[z], r)
    theta = np.sqrt(_dot(omega, omega)) * h
    axis = omega / np.where(theta > 0, theta / h, 1.0)[:, None]
    k = axis[z]
    ct, st = np.cos(theta)[z][:, None], np.sin(theta)[z][:, None]
    rot = r * ct + np.cross(k, r) * st + k * (_dot(k, r)[:, None]) * (1.0 - ct)   # Rodrigues
    return (xc[z] + h * vc[z] + rot - x) / h
