"""The compiled per-vertex clearance of the self-contact bound (:mod:`implicit_cloth.kernels.proximity`) against
independent references: every pair measured by brute force with the numpy closest-point routines of
:mod:`implicit_cloth.collision.ccd`, and the IPC Toolkit's per-vertex safe distances."""

import numpy as np
import pytest

pytest.importorskip("numba")
from implicit_cloth.collision.ccd import point_triangle_closest, segment_closest
from implicit_cloth.kernels.proximity import clearance


def _sheet(n, rng, fold=True):
    u, v = np.meshgrid(np.linspace(0, 0.3, n), np.linspace(0, 0.3, n), indexing="ij")
    x = np.stack([u.ravel(), v.ravel(), 0.02 * np.sin(20 * u.ravel()) * np.cos(15 * v.ravel())], axis=1)
    x += 1e-3 * rng.standard_normal(x.shape)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + n, a + 1], [a + 1, a + n, a + n + 1]]
    faces = np.array(faces, dtype=np.int64)
    if fold:         # a second layer a few millimetres over the first
        x = np.vstack([x, x + [0.004, 0.007, 0.006]])
        faces = np.vstack([faces, faces + n * n])
    return x, faces


def _edges(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def _brute(x, faces, edges, radius):
    out = np.full(len(x), radius)
    for p in range(len(x)):
        keep = np.all(faces != p, axis=1)
        f = faces[keep]
        q, _ = point_triangle_closest(np.repeat(x[p:p + 1], len(f), 0), x[f[:, 0]], x[f[:, 1]], x[f[:, 2]])
        d = np.linalg.norm(q - x[p], axis=1)
        near = d < radius
        for col in (np.full(len(f), p), f[:, 0], f[:, 1], f[:, 2]):
            np.minimum.at(out, col[near], d[near])
    for a, b in edges:
        keep = np.all((edges != a) & (edges != b), axis=1)
        e = edges[keep]
        s, t = segment_closest(np.repeat(x[a:a + 1], len(e), 0), np.repeat(x[b:b + 1], len(e), 0), x[e[:, 0]],
                               x[e[:, 1]])
        p = x[a] + s[:, None] * (x[b] - x[a])
        q = x[e[:, 0]] + t[:, None] * (x[e[:, 1]] - x[e[:, 0]])
        d = np.linalg.norm(p - q, axis=1)
        near = d < radius
        for col in (np.full(len(e), a), np.full(len(e), b), e[:, 0], e[:, 1]):
            np.minimum.at(out, col[near], d[near])
    return out


def _clearance(x, faces, edges, radius, cell):
    lo = x.min(axis=0) - 1e-9
    dims = np.maximum(np.ceil((x.max(axis=0) - lo) / cell).astype(np.int64), 1)
    out = np.empty(len(x))
    clearance(np.ascontiguousarray(x), faces, edges, radius, lo, cell, dims, out)
    return out


@pytest.mark.parametrize("radius, cell", [(0.01, 0.02), (0.03, 0.03), (0.05, 0.2)])
def test_clearance_is_every_pair_s_least_distance(radius, cell):
    """Each vertex's clearance equals the brute force's least distance over all its non-adjacent pairs (capped at
    the radius), at any cell size: the grid misses no pair and adds none."""
    x, faces = _sheet(9, np.random.default_rng(1))
    edges = _edges(faces)
    got = _clearance(x, faces, edges, radius, cell)
    want = _brute(x, faces, edges, radius)
    assert np.all(got <= radius)
    assert np.any(got < radius)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_clearance_agrees_with_the_ipc_toolkit():
    """The toolkit's per-vertex safe distances (from its own broad phase), on a folded sheet with no collinear
    edges, are the same figures."""
    ipctk = pytest.importorskip("ipctk")
    x, faces = _sheet(16, np.random.default_rng(2))
    edges = np.asarray(ipctk.edges(faces), dtype=np.int64)
    radius = 0.02
    got = _clearance(x, faces, edges, radius, radius)
    mesh = ipctk.CollisionMesh(np.asfortranarray(x), edges, faces)
    cand = ipctk.Candidates()
    cand.build(mesh, np.asfortranarray(x), radius)
    want = np.asarray(cand.compute_per_vertex_safe_distances(mesh, np.asfortranarray(x), radius, 0.0)).ravel()
    np.testing.assert_allclose(got, np.minimum(want, radius), rtol=0, atol=1e-12)


def test_clearance_of_collinear_edges_is_their_distance():
    """Two collinear edges 5 cm apart along a line are 5 cm apart (the toolkit 1.6 gives their lines' distance,
    0); parallel edges side by side are their offset apart."""
    x = np.array([[0, 0, 0], [0.1, 0, 0], [0.15, 0, 0], [0.25, 0, 0],       # collinear, 5 cm gap
                  [0, 0.01, 0], [0.1, 0.01, 0.0]], dtype=float)            # parallel to the first, 1 cm off
    edges = np.array([[0, 1], [2, 3], [4, 5]], dtype=np.int64)
    faces = np.zeros((0, 3), dtype=np.int64)
    got = _clearance(x, faces, edges, 0.2, 0.05)
    np.testing.assert_allclose(got[[2, 3]], [0.05, 0.05], atol=1e-15)
    np.testing.assert_allclose(got[[0, 1, 4, 5]], 0.01, atol=1e-15)
