"""Broad phase of the cloth against itself: which vertex-triangle and edge-edge pairs may meet within a step.

Every primitive's box over the step (the box of its corners at the start and at the end, linear motion in
between) is inflated by the reach asked for; two boxes that overlap make a candidate pair. The search is a
k-d tree over the boxes' centres (scipy's ``cKDTree.sparse_distance_matrix`` in the max-norm, all pairs in C):
two boxes overlap only if their centres are within the sum of their half-extents along every axis, so the
tree's radius is the sum of the two largest half-extents and an exact box test keeps the overlapping pairs.
A few primitives much larger than the rest (a fast vertex, a stretched triangle) would make that radius and
the tree's output large for every pair: boxes beyond ``LARGE`` times the median half-extent are tested
against all boxes of the other kind directly (vectorised), the rest through the tree.

Pairs of primitives that share a vertex (a vertex and a triangle it is a corner of, two edges with a common
end) are never candidates. ``benchmarks/self_collision.py`` measured this against ipctk's LBVH, hash grid and
sweep and prune (whose candidates come back as a Python list of objects) and python-fcl's managers.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Boxes with a half-extent beyond this multiple of the median are searched directly, not through the tree.
LARGE = 4.0


def boxes(x0: np.ndarray, x1: np.ndarray, prims: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (K, 3) of the boxes of primitives ``prims`` (K, m) over the step, inflated by
    ``reach`` (m)."""
    p0, p1 = x0[prims], x1[prims]
    lo = np.minimum(p0.min(axis=1), p1.min(axis=1)) - reach
    hi = np.maximum(p0.max(axis=1), p1.max(axis=1)) + reach
    return lo, hi


def _overlap(alo, ahi, blo, bhi, i, j) -> np.ndarray:
    return np.all((alo[i] <= bhi[j]) & (blo[j] <= ahi[i]), axis=1)


def overlapping(alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
                same: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` of overlapping boxes ``a_i``, ``b_j`` (with ``same``: one set, ``i < j``)."""
    ca, cb = 0.5 * (alo + ahi), 0.5 * (blo + bhi)
    ha, hb = (0.5 * (ahi - alo)).max(axis=1), (0.5 * (bhi - blo)).max(axis=1)
    if not len(ha) or not len(hb):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    big_a = ha > LARGE * max(float(np.median(ha)), 1e-300)
    big_b = hb > LARGE * max(float(np.median(hb)), 1e-300) if not same else big_a
    ia, ib = np.flatnonzero(~big_a), np.flatnonzero(~big_b)
    pairs_i, pairs_j = [], []
    if len(ia) and len(ib):
        r = float(ha[ia].max() + hb[ib].max())
        ta = cKDTree(ca[ia])
        tb = ta if same else cKDTree(cb[ib])
        m = ta.sparse_distance_matrix(tb, r, p=np.inf, output_type="ndarray")
        i, j = ia[m["i"]], ib[m["j"]]
        if same:
            keep = i < j
            i, j = i[keep], j[keep]
        pairs_i.append(i)
        pairs_j.append(j)
    # large boxes against every box of the other kind (and, for one set, against the small ones and each other)
    for big, other, flip in ((np.flatnonzero(big_a), np.arange(len(hb)), False),
                             (np.flatnonzero(big_b) if not same else np.zeros(0, np.int64), ia, True)):
        if not len(big) or not len(other):
            continue
        gi = np.repeat(big, len(other))
        gj = np.tile(other, len(big))
        if flip:
            gi, gj = gj, gi
        if same:
            keep = (gi != gj) & (~big_a[gj] | (gi < gj))
            gi, gj = np.minimum(gi[keep], gj[keep]), np.maximum(gi[keep], gj[keep])
        pairs_i.append(gi)
        pairs_j.append(gj)
    i = np.concatenate(pairs_i) if pairs_i else np.zeros(0, dtype=np.int64)
    j = np.concatenate(pairs_j) if pairs_j else np.zeros(0, dtype=np.int64)
    keep = _overlap(alo, ahi, blo, bhi, i, j)
    return i[keep], j[keep]


def vertex_face_pairs(x0: np.ndarray, x1: np.ndarray, faces: np.ndarray, reach: float,
                      verts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (vertex, face) pairs: a vertex's path within ``reach`` of a face's box, the face not its own."""
    vid = np.arange(len(x0)) if verts is None else verts
    vlo, vhi = boxes(x0, x1, vid[:, None], reach)
    flo, fhi = boxes(x0, x1, faces, 0.0)
    i, j = overlapping(vlo, vhi, flo, fhi)
    v = vid[i]
    keep = np.all(faces[j] != v[:, None], axis=1)
    return v[keep], j[keep]


def edge_edge_pairs(x0: np.ndarray, x1: np.ndarray, edges: np.ndarray, reach: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Candidate edge pairs ``(a, b)``, ``a < b``, whose boxes come within ``reach``, sharing no vertex."""
    lo, hi = boxes(x0, x1, edges, 0.5 * reach)
    a, b = overlapping(lo, hi, lo, hi, same=True)
    ea, eb = edges[a], edges[b]
    keep = (ea[:, 0] != eb[:, 0]) & (ea[:, 0] != eb[:, 1]) & (ea[:, 1] != eb[:, 0]) & (ea[:, 1] != eb[:, 1])
    return a[keep], b[keep]
