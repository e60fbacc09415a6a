"""Broad phase of the cloth against itself: which vertex-triangle and edge-edge pairs may meet within a step.

Every primitive's box over the step (the box of its corners at the start and at the end, linear motion in
between) is inflated by the reach asked for; two boxes that overlap make a candidate pair. The search is a
k-d tree over the boxes' centres (scipy's ``cKDTree.sparse_distance_matrix`` in the max-norm, all pairs in C):
two boxes overlap only if their centres are within the sum of their half-extents along every axis, so the
tree's radius is the sum of the two largest half-extents and an exact box test keeps the overlapping pairs.
A few primitives much larger than the rest (a fast vertex, a stretched triangle) would make that radius and
the tree's output large for every pair, so boxes are searched in size classes (powers of two of the median
half-extent), each class pair with the radius of its own two classes, as the obstacles' broad phase does. (An
earlier version tested the boxes beyond four medians against every box directly: quadratic in an impact step
with thousands of fast vertices, twice the time of the classes' search at 128².)

Pairs of primitives that share a vertex (a vertex and a triangle it is a corner of, two edges with a common
end) are never candidates. ``benchmarks/self_collision.py`` measured this against ipctk's LBVH, hash grid and
sweep and prune (whose candidates come back as a Python list of objects) and python-fcl's managers.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..rowwise import max1, min1


def boxes(x0: np.ndarray, x1: np.ndarray, prims: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (K, 3) of the boxes of primitives ``prims`` (K, m) over the step, inflated by
    ``reach`` (m)."""
    p0, p1 = x0[prims], x1[prims]
    lo = np.minimum(min1(p0), min1(p1)) - reach
    hi = np.maximum(max1(p0), max1(p1)) + reach
    return lo, hi


def _classes(h: np.ndarray, med: float) -> np.ndarray:
    """Size class of each box: 0 up to the median half-extent, k up to ``2^k`` medians."""
    with np.errstate(divide="ignore"):
        c = np.ceil(np.log2(np.maximum(h, 1e-300) / med))
    return np.clip(c, 0, None).astype(np.int64)


def overlapping(alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
                same: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` of overlapping boxes ``a_i``, ``b_j`` (with ``same``: one set, ``i < j``).

    Boxes are split into size classes (half-extent up to 1, 2, 4, ... medians) so that each k-d tree search
    uses the radius of its own two classes, not of the largest box.
    """
    empty = np.zeros(0, dtype=np.int64)
    if not len(alo) or not len(blo):
        return empty, empty
    ca, cb = 0.5 * (alo + ahi), 0.5 * (blo + bhi)
    ha, hb = (0.5 * (ahi - alo)).max(axis=1), (0.5 * (bhi - blo)).max(axis=1)
    med = max(float(np.median(np.concatenate([ha, hb]) if not same else ha)), 1e-300)
    ka, kb = _classes(ha, med), (_classes(hb, med) if not same else None)
    kb_ = ka if kb is None else kb
    groups_a = {int(k): np.flatnonzero(ka == k) for k in np.unique(ka)}
    groups_b = groups_a if same else {int(k): np.flatnonzero(kb_ == k) for k in np.unique(kb_)}
    trees_a = {k: cKDTree(ca[g]) for k, g in groups_a.items()}
    trees_b = trees_a if same else {k: cKDTree(cb[g]) for k, g in groups_b.items()}
    out_i, out_j = [], []
    for p, ga in groups_a.items():            # a handful of size classes, not primitives
        for q, gb in groups_b.items():
            if same and q < p:
                continue
            r = float(ha[ga].max() + hb[gb].max())
            if same and p == q:               # each pair once
                m = trees_a[p].query_pairs(r, p=np.inf, output_type="ndarray")
                i, j = ga[m[:, 0]], ga[m[:, 1]]
            else:
                d = trees_a[p].sparse_distance_matrix(trees_b[q], r, p=np.inf, output_type="ndarray")
                i, j = ga[d["i"]], gb[d["j"]]
                if same:                      # one set, two classes: each pair as (min, max)
                    i, j = np.minimum(i, j), np.maximum(i, j)
            out_i.append(i)
            out_j.append(j)
    cols = [tuple(np.ascontiguousarray(c[:, axis]) for c in (alo, ahi, blo, bhi)) for axis in range(3)]
    i = np.concatenate(out_i) if out_i else empty
    j = np.concatenate(out_j) if out_j else empty
    return _keep_overlapping(i, j, cols)


def _keep_overlapping(i: np.ndarray, j: np.ndarray, cols: list[tuple[np.ndarray, ...]]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)`` whose boxes overlap, in their order (axis by axis on the pairs still overlapping;
    ``cols``: per axis, the lower and upper bounds of the a boxes, then of the b boxes)."""
    for al, ah, bl, bh in cols:
        keep = (al[i] <= bh[j]) & (bl[j] <= ah[i])
        i, j = i[keep], j[keep]
    return i, j


def vertex_face_pairs(x0: np.ndarray, x1: np.ndarray, faces: np.ndarray, reach: float,
                      verts: np.ndarray | None = None, face_ids: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (vertex, face) pairs: a vertex's path within ``reach`` of a face's box, the face not its own
    (of the vertices ``verts`` and the faces ``face_ids`` only, when given)."""
    vid = np.arange(len(x0)) if verts is None else verts
    fid = np.arange(len(faces)) if face_ids is None else face_ids
    vlo, vhi = boxes(x0, x1, vid[:, None], reach)
    flo, fhi = boxes(x0, x1, faces[fid], 0.0)
    i, j = overlapping(vlo, vhi, flo, fhi)
    v, f = vid[i], fid[j]
    keep = np.all(faces[f] != v[:, None], axis=1)
    return v[keep], f[keep]


def edge_edge_pairs(x0: np.ndarray, x1: np.ndarray, edges: np.ndarray, reach: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Candidate edge pairs ``(a, b)`` (each once, in either order) whose boxes come within ``reach``, sharing no
    vertex."""
    lo, hi = boxes(x0, x1, edges, 0.5 * reach)
    a, b = overlapping(lo, hi, lo, hi, same=True)
    ea, eb = edges[a], edges[b]
    keep = (ea[:, 0] != eb[:, 0]) & (ea[:, 0] != eb[:, 1]) & (ea[:, 1] != eb[:, 0]) & (ea[:, 1] != eb[:, 1])
    return a[keep], b[keep]


def pairs_around(x0: np.ndarray, x1: np.ndarray, faces: np.ndarray, edges: np.ndarray, reach: float,
                 around: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The candidate pairs of :func:`vertex_face_pairs` and :func:`edge_edge_pairs` that have a vertex in
    ``around`` (boolean, per vertex), each once: the primitives touching those vertices searched against all
    (a search again after a few vertices moved costs in proportion to them, not to the cloth)."""
    verts = np.flatnonzero(around)
    v1, f1 = vertex_face_pairs(x0, x1, faces, reach, verts=verts)
    touched = np.flatnonzero(np.any(around[faces], axis=1))
    v2, f2 = vertex_face_pairs(x0, x1, faces, reach, verts=np.flatnonzero(~around), face_ids=touched)
    sel = np.flatnonzero(np.any(around[edges], axis=1))
    lo, hi = boxes(x0, x1, edges, 0.5 * reach)
    i, j = overlapping(lo[sel], hi[sel], lo, hi)
    a, b = sel[i], j
    mine = np.zeros(len(edges), dtype=bool)
    mine[sel] = True
    once = ~mine[b] | (a < b)                   # a pair of two such edges is found from both: keep one
    a, b = a[once], b[once]
    a, b = np.minimum(a, b), np.maximum(a, b)
    ea, eb = edges[a], edges[b]
    keep = (ea[:, 0] != eb[:, 0]) & (ea[:, 0] != eb[:, 1]) & (ea[:, 1] != eb[:, 0]) & (ea[:, 1] != eb[:, 1])
    return (np.concatenate([v1, v2]), np.concatenate([f1, f2])), (a[keep], b[keep])
