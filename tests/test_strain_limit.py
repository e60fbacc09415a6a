"""Provot strain limiting (implicit_cloth.strain_limit): one pass against the closed form, a hanging chain's
limited equilibrium against the closed form, pinned vertices never moved, velocities consistent, validation."""

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.model import State

G = 9.81


def _chain_scene(rows, k, tau, mass=0.2, iterations=200, kd=0.5, drag=0.5, dt=0.01):
    """Two hanging columns of `rows` vertices joined by horizontal springs (a 2 x rows grid, plane xz),
    structural springs only, top corners pinned."""
    return {"simulation": {"integrator": "backward_euler", "dt": dt,
                           "strain_limit": {"max_strain": tau, "iterations": iterations}},
            "solver": {"tolerance": 1e-8},
            "cloth": {"size": [0.2, 1.0], "resolution": [2, rows], "mass": mass, "plane": "xz",
                      "pins": ["top_left", "top_right"],
                      "springs": {"structural": {"stiffness": k, "damping": kd}}},
            "effects": {"gravity": [0.0, 0.0, -G], "drag": drag}}


def test_one_pass_matches_the_closed_form():
    """2 x 2 grid, top pinned: pull the bottom vertices down so the vertical springs are 50 % over their rest
    length. One pass moves each bottom vertex (weight 1; the pinned end has weight 0) back along its spring
    to exactly (1 + tau) L0, leaves the pinned ones where they were and adds (dx / h) to the velocities."""
    tau, h = 0.1, 0.01
    sim = ic.Simulator(_chain_scene(2, 100.0, tau))
    lim = sim.strain_limiter
    x = sim.positions.copy()
    pinned = sim.model.pinned
    bottom = np.setdiff1d(np.arange(4), pinned)
    L0 = 1.0
    x[bottom, 2] -= 0.5 * L0                                    # vertical springs at 1.5 L0
    x[bottom, 0] += [0.01, 0.02]                                # and slanted, so the direction matters
    v = np.ones_like(x)
    state = State(x.copy(), v.copy(), 0.0)
    passes = lim.apply(state, h)
    top = {b: pinned[np.argmin(np.abs(x[pinned, 0] - (x[b, 0] - [0.01, 0.02][k])))]
           for k, b in enumerate(bottom)}
    for b, p in top.items():
        d = x[b] - x[p]
        expect = x[p] + (1 + tau) * L0 * d / np.linalg.norm(d)   # closed form: along the spring from the pin
        assert np.allclose(state.x[b], expect, rtol=0, atol=1e-12)
        assert np.allclose(state.v[b], v[b] + (expect - x[b]) / h, rtol=0, atol=1e-9)
    assert np.array_equal(state.x[pinned], x[pinned]) and np.array_equal(state.v[pinned], v[pinned])
    assert passes >= 1
    assert lim.stats["springs_limited"] == 2 and lim.stats["steps_limited"] == 1
    assert lim.stats["max_strain_after"] == pytest.approx(tau, abs=1e-9)


def test_one_pass_lengthens_a_compressed_spring_to_the_bound():
    """The bound is two-sided for the in-plane springs (``max_compression``, default ``max_strain``): vertical
    springs pushed to 0.5 L0 come back, in one pass, to exactly (1 - c) L0 along the spring from the pin, the
    velocities get (dx / h), the pins stay."""
    c, h = 0.1, 0.01
    sim = ic.Simulator(_chain_scene(2, 100.0, 0.1))
    lim = sim.strain_limiter
    assert lim.max_compression == c
    x = sim.positions.copy()
    pinned = sim.model.pinned
    bottom = np.setdiff1d(np.arange(4), pinned)
    L0 = 1.0
    x[bottom, 2] += 0.5 * L0                                    # vertical springs at 0.5 L0
    x[bottom, 0] += [0.01, 0.02]                                # and slanted
    v = np.zeros_like(x)
    state = State(x.copy(), v.copy(), 0.0)
    assert lim.apply(state, h) >= 1
    for k, b in enumerate(bottom):
        p = pinned[np.argmin(np.abs(x[pinned, 0] - (x[b, 0] - [0.01, 0.02][k])))]
        d = x[b] - x[p]
        expect = x[p] + (1 - c) * L0 * d / np.linalg.norm(d)
        assert np.allclose(state.x[b], expect, rtol=0, atol=1e-12)
        assert np.allclose(state.v[b], (expect - x[b]) / h, rtol=0, atol=1e-9)
    assert np.array_equal(state.x[pinned], x[pinned])


def _planar(s):
    return np.concatenate([np.arange(s.kinds[q].start, s.kinds[q].stop) for q in ("structural", "shear")])


def test_the_compression_bound_is_for_in_plane_springs_only():
    """Structural and shear springs get (1 - c) L0; bend springs, which shorten whenever the cloth folds, no
    lower bound; ``max_compression = 1`` is no bound at all."""
    table = {"max_strain": 0.2}
    for mc, expect in ((None, 0.2), (0.05, 0.05), (1.0, 1.0)):
        sim = ic.Simulator({"simulation": {"strain_limit": table if mc is None else {**table, "max_compression": mc}},
                            "cloth": {"resolution": [6, 6], "mass": 0.1, "material": "cotton"}})
        lim, s = sim.strain_limiter, sim.model.springs
        assert len(lim.i) == len(s.i) and lim.max_compression == expect
        planar = np.zeros(len(s.i), dtype=bool)
        planar[_planar(s)] = True
        assert np.allclose(lim.lower[planar], (1 - expect) * s.L0[planar], rtol=0, atol=1e-15)
        assert np.all(lim.lower[~planar] == 0.0) and (~planar).sum() > 0


def test_a_jammed_cloth_is_not_crushed_to_meet_the_stretch_bound():
    """A moving obstacle has pushed the middle of a 16² cloth 0.6 m out from its two pins and holds it there
    (contact planes): no state meets every bound. One-sided passes (Provot's; ``max_compression = 1``) then
    shorten the stretched springs by crushing in-plane springs around them (measured: to -71 %), spring energy
    the model counts; with the two-sided bound the in-plane springs stay near theirs (-17 %) and the passes
    leave less than a third of the spring energy (72 J against 265 J, from 852 J)."""
    out = {}
    for mc in (1.0, 0.1):
        sim = ic.Simulator({"simulation": {"strain_limit": {"max_strain": 0.1, "iterations": 300,
                                                            "max_compression": mc}},
                            "cloth": {"size": [1.0, 1.0], "resolution": [16, 16], "mass": 0.1, "plane": "xz",
                                      "pins": ["top_left", "top_right"], "material": "cotton"}})
        x = sim.positions.copy()
        r = np.linalg.norm(x[:, [0, 2]], axis=1)
        held = np.flatnonzero(r < 0.2)
        x[:, 1] += 0.6 * np.exp(-(r / 0.25) ** 2)
        normals = np.tile([0.0, 1.0, 0.0], (len(held), 1))
        state = State(x.copy(), np.zeros_like(x), 0.0)
        s = sim.model.springs
        sim.strain_limiter.apply(state, 1 / 30, planes=(held, normals, x[held, 1].copy()))
        ext = s.lengths(state.x) - s.L0
        out[mc] = (float(s.strain(state.x)[_planar(s)].min()), 0.5 * float(np.dot(s.k, ext * ext)))
        assert np.all(state.x[held, 1] >= x[held, 1] - 1e-12)         # the planes held
    assert out[1.0][0] < -0.5 and out[0.1][0] > -0.25
    assert out[0.1][1] < out[1.0][1] / 3


def test_free_spring_ends_move_by_inverse_mass_and_keep_momentum():
    """No pins: pull one vertex of a 2 x 2 cloth 1 m out (its two springs over-stretched, sharing a vertex).
    The limit holds after the passes and the velocity corrections carry no momentum (equal and opposite
    mass-weighted moves per spring)."""
    sim = ic.Simulator({"simulation": {"strain_limit": {"max_strain": 0.2}},
                        "cloth": {"size": [1.0, 1.0], "resolution": [2, 2], "mass": 0.4, "plane": "xy",
                                  "springs": {"structural": {"stiffness": 10.0}}}})
    lim = sim.strain_limiter
    x = sim.positions.copy()
    x[1] += [1.0, 0.0, 0.0]          # spring 0-1 (bottom edge) at 2 L0; the two vertical springs slant
    state = State(x.copy(), np.zeros_like(x), 0.0)
    lim.apply(state, 0.1)
    s = sim.model.springs
    assert np.all(s.strain(state.x) <= 0.2 + 1e-9)
    p = sim.model.masses @ state.v
    assert np.allclose(p, 0.0, atol=1e-12)


@pytest.mark.parametrize("tau", [0.02, 0.1])
def test_hanging_chain_held_at_the_limit_matches_the_closed_form(tau):
    """Each column of the 2 x 6 grid is a chain whose spring with r vertices below it would stretch to
    r m g / (k L0) >= 0.2 > tau at equilibrium. Strain-limited, every vertical spring is held at tau: the
    columns hang straight down from the pins with vertex r (from the top) at z_pin - r (1 + tau) L0 (closed
    form). Pinned vertices never move (exactly); the report shows the limiting."""
    rows, mass, k = 6, 0.2, 4.0
    m, L0 = mass / (2 * rows), 1.0 / (rows - 1)
    assert m * G / (k * L0) > 0.2 >= 2 * tau
    sim = ic.Simulator(_chain_scene(rows, k, tau, mass, iterations=1000, dt=0.05))
    pinned = sim.model.pinned
    pinned_x = sim.positions[pinned].copy()
    traj = sim.run(duration=1.0, frame_rate=2)
    assert np.array_equal(sim.positions[pinned], pinned_x)
    assert traj.report["frames"]["kinetic"][-1] < 1e-12
    x0, x = sim.model.rest_positions, sim.positions
    depth = np.rint((x0[:, 2].max() - x0[:, 2]) / L0)                    # rows below the top
    expect = x0.copy()
    expect[:, 2] = x0[:, 2].max() - depth * (1 + tau) * L0
    assert np.allclose(x, expect, rtol=0, atol=1e-6)
    rep = traj.report["strain_limit"]
    assert rep["max_strain"] == tau and rep["springs_limited"] > 0 and rep["steps_limited"] > 0
    assert 0 < rep["max_iterations"] <= 1000 and rep["max_strain_after"] <= tau + 2e-7


def _dragged(tethers: bool, n: int = 24, iterations: int = 200):
    """A n² cloth pinned at its top corners (plane xz), every other vertex moved 1 m along y, as a fast
    obstacle drags it; the limiter (max_strain 0.1) given ``iterations`` passes."""
    sim = ic.Simulator({"simulation": {"strain_limit": {"max_strain": 0.1, "iterations": iterations,
                                                        "tethers": tethers}},
                        "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xz",
                                  "pins": ["top_left", "top_right"],
                                  "springs": {"structural": {"stiffness": 1e3}, "shear": {"stiffness": 300.0},
                                              "bend": {"stiffness": 10.0}}}})
    x = sim.positions.copy()
    free = np.setdiff1d(np.arange(len(x)), sim.model.pinned)
    x[free, 1] += 1.0
    state = State(x, np.zeros_like(x), 0.0)
    passes = sim.strain_limiter.apply(state, 0.01)
    return sim, state, passes


def test_tethers_bring_a_dragged_cloth_back_within_the_limit():
    """Passes of local corrections carry the pins' pull one spring per pass: 200 of them leave a 24² cloth
    dragged 1 m from its two pins far beyond the bound (measured: strain 2.4, the excess piled in the springs at
    the pins). With the tethers (the default) the same 200 passes end near it (0.18: what is left is the slow
    tail of local corrections, 0.108 after 1000 passes)."""
    sim, state, _ = _dragged(tethers=False)
    assert sim.model.springs.strain(state.x).max() > 1.0
    sim, state, passes = _dragged(tethers=True)
    assert sim.strain_limiter.n_tethers == sim.model.n - 2
    assert sim.model.springs.strain(state.x).max() <= 0.2


def test_tethers_never_forbid_a_state_the_springs_allow():
    """Each tether's length is (1 + max_strain) times a path of rest lengths from the vertex to its pin: at
    least the straight rest distance (so the rest state, and any state the springs' bounds allow, is inside
    every tether) and, on the grid's structural and shear springs, at most 8.3 % longer than it."""
    sim, _, _ = _dragged(tethers=True, n=12)
    lim = sim.strain_limiter
    i, j, limit = (a[:lim.n_tethers] for a in lim._all[:3])
    x0 = sim.model.rest_positions
    straight = np.linalg.norm(x0[i] - x0[j], axis=1)
    path = limit / 1.1
    assert np.all(np.isin(j, sim.model.pinned))
    assert np.all(path >= straight * (1 - 1e-12))
    assert np.all(path <= straight * 1.083 + 1e-12)
    # each vertex is tied to its nearer pin
    other = np.where(j == sim.model.pinned[0], sim.model.pinned[1], sim.model.pinned[0])
    assert np.all(straight <= np.linalg.norm(x0[i] - x0[other], axis=1) * 1.083)


def test_colour_classes_are_disjoint_and_cover_every_spring():
    from implicit_cloth.strain_limit import _colour_classes

    sim = ic.Simulator({"cloth": {"resolution": [20, 20], "mass": 0.1, "material": "cotton"}})
    s = sim.model.springs
    classes = _colour_classes(s.i, s.j, sim.model.n)
    allc = np.concatenate(classes)
    assert np.array_equal(np.sort(allc), np.arange(len(s.i)))
    for c in classes:
        ends = np.concatenate([s.i[c], s.j[c]])
        assert len(np.unique(ends)) == len(ends)
    # a grid vertex has at most 12 springs (4 structural, 4 shear, 4 bend); greedy rounds give more classes
    # than that minimum (measured 41 here, 46 at 128 x 128), but a few tens, not thousands
    assert 12 <= len(classes) < 60


def test_without_the_table_nothing_is_limited_or_imported():
    sim = ic.Simulator({"cloth": {"resolution": [3, 3], "mass": 0.1, "springs": {"structural": {"stiffness": 1.0}}}})
    assert sim.strain_limiter is None
    assert sim.run(duration=0.02).report["strain_limit"] is None


@pytest.mark.parametrize("table,expect", [
    ({}, "simulation.strain_limit.max_strain: missing"),
    ({"max_strain": 0}, "simulation.strain_limit.max_strain: must be a finite number > 0, got 0"),
    ({"max_strain": 0.1, "iterations": 0}, "simulation.strain_limit.iterations: must be an integer >= 1"),
    ({"max_strain": 0.1, "iteration": 3}, "simulation.strain_limit.iteration: unknown key (did you mean"),
    (0.1, "simulation.strain_limit: must be a table, got 0.1"),
    ({"max_strain": 0.1, "tethers": 1}, "simulation.strain_limit.tethers: must be true or false, got 1"),
    ({"max_strain": 0.1, "max_compression": 1.5},
     "simulation.strain_limit.max_compression: must be a finite number >= 0 and <= 1, got 1.5"),
])
def test_strain_limit_keys_are_validated(table, expect):
    with pytest.raises(ic.SceneError) as exc:
        ic.Scene.from_dict({"simulation": {"strain_limit": table}, "cloth": {"mass": 1.0}})
    assert str(exc.value).startswith(expect), str(exc.value)


def test_the_compiled_passes_give_the_numpy_reference():
    """A 12² cloth crumpled at random (springs up to 3x their rest length) with contact planes held: the
    compiled limiter (numba) and the numpy reference make the same passes and leave the same positions, and
    both end every spring within the limit and every held vertex on its plane."""
    pytest.importorskip("numba")
    from implicit_cloth.backend import get_backend

    sim = ic.Simulator({"simulation": {"strain_limit": {"max_strain": 0.1, "iterations": 2000}},
                        "cloth": {"size": [1.0, 1.0], "resolution": [12, 12], "mass": 0.1, "plane": "xy",
                                  "pins": ["top_left", "top_right"], "material": "cotton"}})
    lim = sim.strain_limiter
    rng = np.random.default_rng(3)
    x = sim.positions + rng.normal(scale=0.05, size=sim.positions.shape)
    x[sim.model.pinned] = sim.positions[sim.model.pinned]
    held = np.setdiff1d(np.arange(0, sim.model.n, 7), sim.model.pinned)
    normals = rng.normal(size=(len(held), 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    offsets = np.einsum("ij,ij->i", normals, x[held])          # held on planes through where they start
    out = {}
    for name in ("numpy", "numba"):
        xx = x.copy()
        passes, first, pushed = get_backend(name).limit_strain(xx, lim.i, lim.j, lim.limit, lim.share_i,
                                                               lim.share_j, lim.classes, lim.tolerance, 2000,
                                                               (held, normals, offsets), lim.lower)
        out[name] = (xx, passes, first, pushed)
    (xa, pa, fa, qa), (xb, pb, fb, qb) = out["numpy"], out["numba"]
    assert fa == fb > 10 and pa == pb > 1
    assert np.allclose(xa, xb, rtol=0, atol=1e-12)
    assert np.allclose(qa, qb, rtol=0, atol=1e-12) and np.all(qb >= 0) and qb.max() > 1e-3   # the planes pushed
    d = xb[lim.j] - xb[lim.i]
    assert np.max(np.linalg.norm(d, axis=1) / lim.L0) <= 1.1 * (1 + 1e-6)
    assert np.min(np.linalg.norm(d, axis=1) / lim.L0 - lim.lower / lim.L0) >= -1.1e-6   # and the lower bounds
    assert np.min(np.einsum("ij,ij->i", normals, xb[held]) - offsets) >= -1e-12


def test_the_planes_pushes_during_limiting_are_measured():
    """The planes the limiter holds belong to obstacles: what a plane pushes its vertex over the passes is the
    obstacle's impulse ``m pushed / h`` along the normal (the collider books its work, impulse times the
    obstacle's velocity, with the solve's contact impulses). 2 x 2 cloth, the bottom vertices 0.5 below the
    limit and held by planes 0.3 above them, short of it: every pass the springs pull them up to the plane and
    0.1 beyond (0.4 in the first), the plane pushes 0.1 back, so after ``passes`` passes each plane has pushed
    0.1 passes (closed form), and the vertices end on their planes."""
    tau, h = 0.1, 0.01
    sim = ic.Simulator(_chain_scene(2, 100.0, tau, iterations=50))
    lim = sim.strain_limiter
    x = sim.positions.copy()
    bottom = np.setdiff1d(np.arange(4), sim.model.pinned)
    x[bottom, 2] -= 0.5                                          # vertical springs at 1.5 L0
    n = np.tile([0.0, 0.0, -1.0], (2, 1))
    offset = -(x[bottom, 2] + 0.3)                               # n . x >= offset  <=>  z <= z_start + 0.3
    state = State(x.copy(), np.zeros_like(x), 0.0)
    passes = lim.apply(state, h, planes=(bottom, n, offset))
    assert passes == 50
    assert np.allclose(lim.pushed, 0.1 * passes, rtol=1e-9)
    assert np.allclose(state.x[bottom, 2], x[bottom, 2] + 0.3, atol=1e-12)
