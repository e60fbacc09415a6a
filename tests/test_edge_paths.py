"""The path check of a cloth edge against a convex obstacle (:func:`implicit_cloth.contact.obstacles.edge_prefix`):
against an independent dense sampling of the true moving edge, numpy against the compiled capsule, and an edge
sliding over a rod at a nanometre keeps its whole move."""

import numpy as np
import pytest

import implicit_cloth.contact.obstacles as O
from implicit_cloth.collision.shapes import Capsule, Sphere


def _sampled_low(shape, a0, a1, d0, d1, s_max, n=200):
    """The least distance of the true moving edge (its ends on straight paths) over [0, s_max], sampled."""
    sig = np.linspace(0.0, 1.0, n)[:, None, None] * s_max
    t = np.linspace(0.0, 1.0, n)[None, :, None]
    p = (1 - t) * (a0 + sig * d0) + t * (a1 + sig * d1)
    return shape.distance(p.reshape(-1, 3)).min()


@pytest.mark.parametrize("shape", [Capsule(0.02, 0.6), Sphere(0.1)])
def test_an_edge_s_allowed_prefix_keeps_its_gap_and_is_not_far_short(shape):
    rng = np.random.default_rng(4)
    k = 60
    a0 = rng.normal(size=(k, 3)) * 0.05 + [0.06, 0, 0]
    a0[:, 0] = np.abs(a0[:, 0]) + (0.1 if shape.name == "sphere" else 0.025)
    a1 = a0 + rng.normal(size=(k, 3)) * 0.02
    d0 = rng.normal(size=(k, 3)) * 0.04
    d1 = d0 + rng.normal(size=(k, 3)) * 0.01
    g0 = shape.segment_minimum(a0, a1)[1]
    keep = g0 > 1e-3
    a0, a1, d0, d1, g0 = a0[keep], a1[keep], d0[keep], d1[keep], g0[keep]
    target = 0.1 * g0
    s = O.edge_prefix(shape, a0, a1, d0, d1, target)
    assert np.all((s >= 0) & (s <= 1))
    assert np.any(s < 1) and np.any(s == 1)
    for i in range(len(s)):
        low = _sampled_low(shape, a0[i], a1[i], d0[i], d1[i], s[i])
        assert low >= target[i] - 1e-12, i                      # never past the target
        if s[i] < 1:                                             # and cut near where the bound crosses it
            more = _sampled_low(shape, a0[i], a1[i], d0[i], d1[i], min(1.0, s[i] * 1.5 + 0.05))
            assert more < target[i] + np.linalg.norm(d0[i] - d1[i]) + 1e-3, i


def test_numpy_and_compiled_capsule_agree(monkeypatch):
    rng = np.random.default_rng(5)
    shape = Capsule(0.02, 0.6)
    k = 200
    a0 = rng.normal(size=(k, 3)) * 0.03
    a0[:, 0] = np.abs(a0[:, 0]) + 0.025
    a1 = a0 + rng.normal(size=(k, 3)) * 0.015
    d0 = rng.normal(size=(k, 3)) * 0.03
    d1 = d0 + rng.normal(size=(k, 3)) * 0.005
    g0 = shape.segment_minimum(a0, a1)[1]
    target = 0.1 * np.maximum(g0, 1e-6)
    compiled = O.edge_prefix(shape, a0, a1, d0, d1, target)
    monkeypatch.setattr(O, "COMPILED_PATHS", False)
    reference = O.edge_prefix(shape, a0, a1, d0, d1, target)
    np.testing.assert_allclose(compiled, reference, rtol=0, atol=1e-9)


def test_an_edge_sliding_over_a_rod_at_a_nanometre_keeps_its_whole_move():
    shape = Capsule(0.02, 0.6)
    gap = 1e-9
    a0 = np.array([[0.02 + gap, -0.01, 0.0]])
    a1 = np.array([[0.02 + gap, 0.01, 0.0]])
    along = np.array([[0.0, 0.0, 0.03]])              # 3 cm along the rod's axis
    assert O.edge_prefix(shape, a0, a1, along, along, np.array([0.1 * gap]))[0] == 1.0
    into = np.array([[-0.01, 0.0, 0.0]])               # 1 cm into it: cut at about 0.9 nm
    s = O.edge_prefix(shape, a0, a1, into, into, np.array([0.1 * gap]))[0]
    assert 0.0 < s * 0.01 <= 0.9 * gap * (1 + 1e-6)
    assert s * 0.01 > 0.8 * gap
