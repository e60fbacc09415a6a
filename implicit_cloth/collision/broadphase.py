"""Broad phase against mesh obstacles: which cloth primitives may touch which obstacle triangles.

Axis-aligned boxes, searched with scipy's k-d trees: every obstacle triangle's box (local frame, built once per
mesh: :class:`TriangleIndex`) against each cloth primitive's box over the step, grown by the proximity radius
``r``; the pairs whose boxes overlap are the candidates for the exact tests in numpy
(:mod:`implicit_cloth.collision.ccd`). A primitive's box holds everything the exact tests look for:

* vertex: its path ``x0 -> x1`` and the ball of radius ``r`` around ``x1``;
* edge: its swept quad ``(a0, b0, b1, a1)`` and its end segment widened by ``r``;
* triangle: its end position, shifted by up to ``r`` along its normal to either side.

Boxes of very different sizes are searched in size classes (powers of two of their largest half-extent), each
class pair with one ``cKDTree.sparse_distance_matrix`` in the maximum norm, so a few fast-moving primitives do not
widen the search of all the others. (python-fcl did this search before, on one BVH of the swept cloth's
triangles rebuilt for every query: 70 % of a step of a 32² cloth on a 1280-face icosphere.)
"""

from __future__ import annotations

import numpy as np

from ..rowwise import max1, min1

#: Candidate kinds (the keys of :func:`candidates`' result).
VERTEX_PATH, EDGE_QUAD, TRIANGLE = 0, 2, 3


def _classes(half: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Indices grouped by size class (power of two of ``half``), with each group's largest ``half``."""
    k = np.floor(np.log2(np.maximum(half, 1e-12))).astype(np.int64)
    order = np.argsort(k, kind="stable")
    ks, starts = np.unique(k[order], return_index=True)
    groups = np.split(order, starts[1:])
    return [(g, float(half[g].max())) for g in groups]


class TriangleIndex:
    """Boxes of a fixed triangle set (an obstacle mesh in its local frame), searchable by box overlap."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        tri = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)]
        self.lo, self.hi = tri.min(axis=1), tri.max(axis=1)
        centre, half = (self.lo + self.hi) / 2, (self.hi - self.lo) / 2
        self.groups = [(ids, bound, cKDTree(centre[ids])) for ids, bound in _classes(half.max(axis=1))]

    def overlaps(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(box, triangle)`` index pairs of the boxes ``lo``, ``hi`` (K, 3) that overlap a triangle's box."""
        from scipy.spatial import cKDTree

        if not len(lo):
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        bi, ti = [], []
        for ids, bound in _classes(half.max(axis=1)):
            tree = cKDTree(centre[ids])
            for tids, tbound, ttree in self.groups:
                pairs = tree.sparse_distance_matrix(ttree, bound + tbound, p=np.inf, output_type="ndarray")
                if len(pairs):
                    bi.append(ids[pairs["i"]])
                    ti.append(tids[pairs["j"]])
        if not bi:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        b, t = np.concatenate(bi), np.concatenate(ti)
        keep = np.all((lo[b] <= self.hi[t]) & (self.lo[t] <= hi[b]), axis=1)
        return b[keep], t[keep]


def unique_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct pairs ``(a[k], b[k])`` of non-negative integers, sorted (one 1-D sort of packed keys)."""
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    if not len(a):
        return a, b
    m = int(b.max()) + 1
    key = np.unique(a * m + b)
    return key // m, key % m


def candidates(index: TriangleIndex, p0: np.ndarray, p1: np.ndarray, verts: np.ndarray, edges: np.ndarray,
               tris: np.ndarray, r: float) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Candidate pairs (cloth primitive index, obstacle triangle index) of each kind.

    Parameters
    ----------
    index : TriangleIndex
        The obstacle's triangles, local frame.
    p0, p1 : (N, 3) arrays
        Cloth positions at the start and end of the step, obstacle's local frame, m.
    verts, edges, tris : int arrays
        The cloth's vertices (K,), edges (E, 2) and triangles (T, 3) to include.
    r : float
        Proximity radius, m.

    Returns
    -------
    dict
        ``{VERTEX_PATH: (vertex ids, triangles), EDGE_QUAD: (rows of edges, triangles),
        TRIANGLE: (rows of tris, triangles)}``, kinds without candidates left out.
    """
    groups = {VERTEX_PATH: (verts, lambda: np.stack([p0[verts], p1[verts]], axis=1)),    # both ends
              EDGE_QUAD: (edges, lambda: np.concatenate([p0[edges], p1[edges]], axis=1)),   # ends at both
              TRIANGLE: (tris, lambda: p1[tris])}                                         # corners at the end
    out = {}
    for kind, (prims, points) in groups.items():
        if not len(prims):
            continue
        q = points()                                       # (K, m, 3): each primitive's points over the step
        i, t = index.overlaps(min1(q) - r, max1(q) + r)
        if len(i):
            out[kind] = (verts[i] if kind == VERTEX_PATH else i, t)
    return out
