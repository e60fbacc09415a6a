"""Compiled (numba) proximity of a cloth to itself, for the barrier method's safe-move bound
(:class:`implicit_cloth.contact.cloth.ClothBarrier`).

:func:`clearance`: each vertex's least distance to the primitives not adjacent to it (OGC's per-vertex bound,
Chen et al. 2025; what the IPC Toolkit's ``compute_per_vertex_safe_distances`` gives, at a third of its time
on the 64² crumple), over every point-triangle pair (a vertex and a triangle not incident to it) and every
edge-edge pair (two edges sharing no vertex) nearer than a radius, from a uniform grid of cells. Exact
distances: Ericson's closest points (Real-Time Collision Detection, 5.1.5 and 5.1.9), robust for parallel and
collinear edges (the toolkit 1.6 measures nearly collinear edges by their lines' distance, 0).

Serial. Compiled with ``cache=True``. Importing this module imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@njit(cache=True)
def point_triangle_distance2(p, a, b, c):
    """The squared distance from point ``p`` to the triangle ``abc`` (3-vectors)."""
    abx, aby, abz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    acx, acy, acz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    apx, apy, apz = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    d1 = _dot(abx, aby, abz, apx, apy, apz)
    d2 = _dot(acx, acy, acz, apx, apy, apz)
    if d1 <= 0.0 and d2 <= 0.0:
        return _dot(apx, apy, apz, apx, apy, apz)
    bpx, bpy, bpz = p[0] - b[0], p[1] - b[1], p[2] - b[2]
    d3 = _dot(abx, aby, abz, bpx, bpy, bpz)
    d4 = _dot(acx, acy, acz, bpx, bpy, bpz)
    if d3 >= 0.0 and d4 <= d3:
        return _dot(bpx, bpy, bpz, bpx, bpy, bpz)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        qx, qy, qz = apx - v * abx, apy - v * aby, apz - v * abz
        return _dot(qx, qy, qz, qx, qy, qz)
    cpx, cpy, cpz = p[0] - c[0], p[1] - c[1], p[2] - c[2]
    d5 = _dot(abx, aby, abz, cpx, cpy, cpz)
    d6 = _dot(acx, acy, acz, cpx, cpy, cpz)
    if d6 >= 0.0 and d5 <= d6:
        return _dot(cpx, cpy, cpz, cpx, cpy, cpz)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        qx, qy, qz = apx - w * acx, apy - w * acy, apz - w * acz
        return _dot(qx, qy, qz, qx, qy, qz)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        bcx, bcy, bcz = c[0] - b[0], c[1] - b[1], c[2] - b[2]
        qx, qy, qz = bpx - w * bcx, bpy - w * bcy, bpz - w * bcz
        return _dot(qx, qy, qz, qx, qy, qz)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    qx = apx - v * abx - w * acx
    qy = apy - v * aby - w * acy
    qz = apz - v * abz - w * acz
    return _dot(qx, qy, qz, qx, qy, qz)


@njit(cache=True)
def segment_distance2(p1, q1, p2, q2):
    """The squared distance between the segments ``p1 q1`` and ``p2 q2`` (3-vectors); parallel and degenerate
    segments included."""
    eps = 1e-300
    d1x, d1y, d1z = q1[0] - p1[0], q1[1] - p1[1], q1[2] - p1[2]
    d2x, d2y, d2z = q2[0] - p2[0], q2[1] - p2[1], q2[2] - p2[2]
    rx, ry, rz = p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2]
    a = _dot(d1x, d1y, d1z, d1x, d1y, d1z)
    e = _dot(d2x, d2y, d2z, d2x, d2y, d2z)
    f = _dot(d2x, d2y, d2z, rx, ry, rz)
    if a <= eps and e <= eps:
        return _dot(rx, ry, rz, rx, ry, rz)
    if a <= eps:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = _dot(d1x, d1y, d1z, rx, ry, rz)
        if e <= eps:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = _dot(d1x, d1y, d1z, d2x, d2y, d2z)
            denom = a * e - b * b
            if denom > 1e-14 * a * e:
                s = min(max((b * f - c * e) / denom, 0.0), 1.0)
            else:                       # parallel: any s; Ericson takes 0
                s = 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    dx = rx + s * d1x - t * d2x
    dy = ry + s * d1y - t * d2y
    dz = rz + s * d1z - t * d2z
    return _dot(dx, dy, dz, dx, dy, dz)


@njit(cache=True, inline="always")
def _cell(v, lo, h, dim):
    """The grid's cell along one axis that holds ``v`` (clamped to the grid)."""
    return min(max(int((v - lo) / h), 0), dim - 1)


@njit(cache=True)
def _cells(a, b, lo, h, dim):
    """The grid's cells (first, last) along one axis that the interval ``[a, b]`` meets."""
    return _cell(a, lo, h, dim), _cell(b, lo, h, dim)


@njit(cache=True)
def clearance(x, faces, edges, radius, lo, h, dims, out):
    """Each vertex's least distance (N,) to the primitives of the cloth not adjacent to it, capped at ``radius``,
    into ``out``: over every point-triangle pair (a vertex and a triangle not incident to it) and edge-edge pair
    (two edges sharing no vertex) nearer than ``radius`` at ``x`` (N, 3), each pair's distance taken by all of its
    four vertices. The grid: origin ``lo``, cell size ``h``, ``dims`` cells (vertices and edges' boxes binned; each
    triangle's and edge's box, grown by the radius, searched)."""
    for i in range(out.shape[0]):
        out[i] = radius
    _point_triangle_pass(x, faces, radius, lo, h, dims, out)
    _edge_edge_pass(x, edges, radius, lo, h, dims, out)


@njit(cache=True)
def _point_triangle_pass(x, faces, radius, lo, h, dims, out):
    """:func:`clearance`'s point-triangle pairs: the vertices binned, each triangle's grown box searched."""
    r2 = radius * radius
    start, order = _bin_boxes(np.hstack((x, x)), lo, h, dims)          # a vertex: a box of no extent
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        bx0 = min(x[a, 0], x[b, 0], x[c, 0]) - radius
        bx1 = max(x[a, 0], x[b, 0], x[c, 0]) + radius
        by0 = min(x[a, 1], x[b, 1], x[c, 1]) - radius
        by1 = max(x[a, 1], x[b, 1], x[c, 1]) + radius
        bz0 = min(x[a, 2], x[b, 2], x[c, 2]) - radius
        bz1 = max(x[a, 2], x[b, 2], x[c, 2]) + radius
        x0, x1 = _cells(bx0, bx1, lo[0], h, dims[0])
        y0, y1 = _cells(by0, by1, lo[1], h, dims[1])
        z0, z1 = _cells(bz0, bz1, lo[2], h, dims[2])
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                for iz in range(z0, z1 + 1):
                    cc = (ix * dims[1] + iy) * dims[2] + iz
                    for k in range(start[cc], start[cc + 1]):
                        p = order[k]
                        if p == a or p == b or p == c:
                            continue
                        px, py, pz = x[p, 0], x[p, 1], x[p, 2]
                        if px < bx0 or px > bx1 or py < by0 or py > by1 or pz < bz0 or pz > bz1:
                            continue
                        d2 = point_triangle_distance2(x[p], x[a], x[b], x[c])
                        if d2 < r2:
                            d = math.sqrt(d2)
                            out[p] = min(out[p], d)
                            out[a] = min(out[a], d)
                            out[b] = min(out[b], d)
                            out[c] = min(out[c], d)


@njit(cache=True)
def _bin_boxes(box, lo, h, dims):
    """Boxes (K, 6: low corner, high corner) binned into every cell of the grid they meet (a counting sort):
    each cell's entries are ``entries[start[c]:start[c + 1]]``."""
    n = box.shape[0]
    nc = dims[0] * dims[1] * dims[2]
    span = np.empty((n, 6), dtype=np.int64)
    start = np.zeros(nc + 1, dtype=np.int64)
    for i in range(n):
        for k in range(3):
            span[i, k], span[i, 3 + k] = _cells(box[i, k], box[i, 3 + k], lo[k], h, dims[k])
        for ix in range(span[i, 0], span[i, 3] + 1):
            for iy in range(span[i, 1], span[i, 4] + 1):
                for iz in range(span[i, 2], span[i, 5] + 1):
                    start[(ix * dims[1] + iy) * dims[2] + iz + 1] += 1
    for c in range(nc):
        start[c + 1] += start[c]
    fill = start[:nc].copy()
    entries = np.empty(start[nc], dtype=np.int64)
    for i in range(n):
        for ix in range(span[i, 0], span[i, 3] + 1):
            for iy in range(span[i, 1], span[i, 4] + 1):
                for iz in range(span[i, 2], span[i, 5] + 1):
                    c = (ix * dims[1] + iy) * dims[2] + iz
                    entries[fill[c]] = i
                    fill[c] += 1
    return start, entries


@njit(cache=True, inline="always")
def _meets_here(box, i, j, radius, ix, iy, iz, lo, h, dims):
    """Whether box ``j`` meets box ``i`` grown by ``radius`` and the low corner of their overlap lies in the cell
    ``(ix, iy, iz)`` (so that a pair found in several cells is taken in one)."""
    for k in range(3):
        if box[j, k] > box[i, 3 + k] + radius or box[j, 3 + k] < box[i, k] - radius:
            return False
    return (_cell(max(box[j, 0], box[i, 0] - radius), lo[0], h, dims[0]) == ix
            and _cell(max(box[j, 1], box[i, 1] - radius), lo[1], h, dims[1]) == iy
            and _cell(max(box[j, 2], box[i, 2] - radius), lo[2], h, dims[2]) == iz)


@njit(cache=True)
def _edge_edge_pass(x, edges, radius, lo, h, dims, out):
    """:func:`clearance`'s edge-edge pairs: each edge's box binned into every cell it meets, each box grown by the
    radius searched; a pair met in several cells is measured in one, the cell of its boxes' overlap's low
    corner."""
    r2 = radius * radius
    ne = edges.shape[0]
    box = np.empty((ne, 6))
    for i in range(ne):
        for k in range(3):
            box[i, k] = min(x[edges[i, 0], k], x[edges[i, 1], k])
            box[i, 3 + k] = max(x[edges[i, 0], k], x[edges[i, 1], k])
    start, entries = _bin_boxes(box, lo, h, dims)
    for i in range(ne):
        a, b = edges[i, 0], edges[i, 1]
        x0, x1 = _cells(box[i, 0] - radius, box[i, 3] + radius, lo[0], h, dims[0])
        y0, y1 = _cells(box[i, 1] - radius, box[i, 4] + radius, lo[1], h, dims[1])
        z0, z1 = _cells(box[i, 2] - radius, box[i, 5] + radius, lo[2], h, dims[2])
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                for iz in range(z0, z1 + 1):
                    cc = (ix * dims[1] + iy) * dims[2] + iz
                    for k in range(start[cc], start[cc + 1]):
                        j = entries[k]
                        if j <= i:
                            continue
                        c, d = edges[j, 0], edges[j, 1]
                        if c == a or c == b or d == a or d == b:
                            continue
                        if not _meets_here(box, i, j, radius, ix, iy, iz, lo, h, dims):
                            continue
                        d2 = segment_distance2(x[a], x[b], x[c], x[d])
                        if d2 < r2:
                            dd = math.sqrt(d2)
                            out[a] = min(out[a], dd)
                            out[b] = min(out[b], dd)
                            out[c] = min(out[c], dd)
                            out[d] = min(out[d], dd)
