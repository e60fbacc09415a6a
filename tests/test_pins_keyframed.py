"""Keyframed pins (``cloth.pins[k].keyframes``) and soft pins (``cloth.pins[k].stiffness``).

The references are computed here from the keyframes and closed forms, independently of
:mod:`implicit_cloth.pin_paths`.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_forces import check_force

import implicit_cloth as ic
from implicit_cloth.errors import SceneError
from implicit_cloth.solvers import numba_available, set_default_accelerator

G = [0.0, 0.0, -9.81]
KEYS = [{"time": 0.0},
        {"time": 0.3, "translation": [0.2, 0.1, 0.3], "rotation": [0.0, 0.0, 0.6]},
        {"time": 0.6, "translation": [0.3, 0.0, 0.35], "rotation": [0.0, 0.0, 1.2]}]


def _scene(pins, n=6, dt=0.01, duration=0.8, springs=None):
    return {
        "simulation": {"integrator": "backward_euler", "dt": dt, "duration": duration, "frame_rate": 30},
        "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "center": [0.0, 0.0, 1.0],
                  "plane": "xz", "pins": pins,
                  "springs": springs or {"structural": {"stiffness": 500.0, "damping": 0.1},
                                         "shear": {"stiffness": 50.0, "damping": 0.05},
                                         "bend": {"stiffness": 5.0, "damping": 0.01}}},
        "effects": {"gravity": G},
    }


def _reference(keys, x0, t):
    """``c + R(t) (x0 - c) + T(t)``: translation and rotation vector linear between keys, held after the last."""
    c = x0.mean(axis=0)
    times = [k["time"] for k in keys]
    T = [np.array(k.get("translation", [0.0, 0.0, 0.0])) for k in keys]
    r = [np.array(k.get("rotation", [0.0, 0.0, 0.0])) for k in keys]
    if times[0] > 0:
        times, T, r = [0.0] + times, [np.zeros(3)] + T, [np.zeros(3)] + r
    if t >= times[-1]:
        Tt, rt = T[-1], r[-1]
    else:
        k = max(i for i in range(len(times)) if times[i] <= t)
        a = (t - times[k]) / (times[k + 1] - times[k])
        Tt, rt = (1 - a) * T[k] + a * T[k + 1], (1 - a) * r[k] + a * r[k + 1]
    return c + (x0 - c) @ Rotation.from_rotvec(rt).as_matrix().T + Tt


@pytest.mark.parametrize("keys", [KEYS, [{"time": 0.2, "translation": [0.0, 0.1, 0.2],
                                          "rotation": [0.3, -0.2, 0.5]},
                                         {"time": 0.5, "translation": [0.1, 0.0, 0.1], "rotation": [-0.4, 0.6, 0.1]}]],
                         ids=["about z", "about turning axes, first key later"])
def test_keyframed_pins_are_on_their_paths_at_every_step_end(keys):
    sim = ic.Simulator(_scene([{"vertices": ["top_left", "top_right", 3], "keyframes": keys}]))
    p = sim.model.pinned
    x0 = sim.positions[p].copy()
    for _ in range(80):           # past the last key: the last pose held
        sim.step(1)
        assert np.abs(sim.positions[p] - _reference(keys, x0, sim.time)).max() < 1e-12
    free = np.setdiff1d(np.arange(sim.model.n), p)
    assert np.all(np.isfinite(sim.positions[free]))


@pytest.mark.parametrize("name", ["bdf2", "symplectic_euler", "verlet", "rk4"])
def test_keyframed_pins_are_on_their_paths_with_every_integrator(name):
    sim = ic.Simulator(_scene([{"vertices": ["top_left", "top_right"], "keyframes": KEYS}], n=4), integrator=name,
                       dt=0.002)
    p = sim.model.pinned
    x0 = sim.positions[p].copy()
    for _ in range(60):
        sim.step(1)
        assert np.abs(sim.positions[p] - _reference(KEYS, x0, sim.time)).max() < 1e-12
    assert np.all(np.isfinite(sim.positions))


def test_constant_and_fixed_pins_beside_keyframed_ones_are_as_before():
    """Fixed and constant-velocity pins follow ``a + w t`` exactly beside a keyframed group."""
    w = [0.2, 0.0, 0.1]
    sim = ic.Simulator(_scene(["bottom_left", {"vertices": ["bottom_right"], "velocity": w},
                               {"vertices": ["top_left", "top_right"], "keyframes": KEYS}]))
    x0 = sim.positions.copy()
    sim.step(40)
    assert np.array_equal(sim.positions[0], x0[0])
    assert np.allclose(sim.positions[5], x0[5] + np.array(w) * sim.time, rtol=0, atol=1e-13)


def test_a_keyframed_pin_that_does_not_move_is_a_fixed_pin_bit_for_bit():
    ref = ic.Simulator(_scene(["top_left", "top_right"]))
    key = ic.Simulator(_scene([{"vertices": ["top_left", "top_right"], "keyframes": [{"time": 0.0}]}]))
    assert key.model.pins_keyframed and not ref.model.pins_keyframed
    ref.step(20)
    key.step(20)
    assert np.array_equal(ref.positions, key.positions)


def test_keyframed_towel_lift_keeps_the_energy_balance():
    """A towel corner lifted and carried: the pins' work booked per step, the run's status ok."""
    keys = [{"time": 0.0}, {"time": 0.4, "translation": [0.0, 0.0, 0.4]},
            {"time": 0.8, "translation": [0.5, 0.2, 0.4], "rotation": [0.0, 0.0, 0.8]}]
    sc = _scene([{"vertices": ["top_left"], "keyframes": keys}], n=8, duration=1.0)
    sc["cloth"]["center"] = [0.0, 0.0, 0.0]
    sc["cloth"]["plane"] = "xy"
    sc["cloth"]["pins"].append({"vertices": ["bottom_right"], "stiffness": 20.0, "damping": 0.05})
    tr = ic.Simulator(sc).run()
    assert tr.report["status"] == "ok", tr.report["reason"]
    assert tr.report["frames"]["pin_work"][-1] > 0.05       # lifting it took work, booked


def test_keyframed_run_with_adaptive_stepping_keeps_the_balance():
    sc = _scene([{"vertices": ["top_left", "top_right"], "keyframes": KEYS}], duration=0.8)
    sc["simulation"]["adaptive"] = {"enabled": True}
    tr = ic.Simulator(sc).run()
    assert tr.report["status"] == "ok", tr.report["reason"]


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_keyframed_and_soft_pins_agree_on_both_back_ends():
    sc = _scene([{"vertices": ["top_left"], "keyframes": KEYS},
                 {"vertices": ["top_right"], "stiffness": 30.0, "damping": 0.1, "velocity": [0.1, 0.0, 0.0]}])
    xs = {}
    try:
        for path in ("numpy", "numba"):
            set_default_accelerator(path)
            sim = ic.Simulator(sc, solver={"tolerance": 1e-10})
            sim.step(20)
            xs[path] = sim.positions.copy()
    finally:
        set_default_accelerator(None)
    disp = np.abs(xs["numpy"] - ic.Simulator(sc).positions).max()
    assert disp > 1e-2
    assert np.abs(xs["numba"] - xs["numpy"]).max() <= 1e-7 * disp


# --------------------------------------------------------------------------- soft pins
def _block(K, c=0.0, velocity=None, keyframes=None):
    """A 2 x 2 cloth with all four vertices on soft pins of one motion: it moves rigidly."""
    pin: dict = {"vertices": [0, 1, 2, 3], "stiffness": K}
    if c:
        pin["damping"] = c
    if velocity is not None:
        pin["velocity"] = velocity
    if keyframes is not None:
        pin["keyframes"] = keyframes
    sc = _scene([pin], n=2, springs={"structural": {"stiffness": 500.0, "damping": 0.1}})
    sc["cloth"]["size"] = [0.1, 0.1]
    sc["cloth"]["mass"] = 0.4
    return sc


def test_soft_pins_sag_by_their_closed_form():
    """At rest each vertex hangs ``m g / K`` below its pin (springs unstretched: the block moves rigidly)."""
    K = 40.0
    sim = ic.Simulator(_block(K, c=1.0))
    x0 = sim.positions.copy()
    tr = sim.run(3.0)
    assert tr.report["status"] == "ok", tr.report["reason"]
    assert np.abs(sim.positions - (x0 + 0.1 * np.array(G) / K)).max() < 1e-9


@pytest.mark.parametrize("how", ["velocity", "keyframes"])
def test_a_soft_pin_trails_a_moving_target_by_its_closed_form(how):
    """Target at constant velocity ``w``: at steady state each vertex is ``m g / K`` below it and not behind (the
    step linearises the force in time: the spring pulls towards the target at the step's end; the damping is
    relative to the target's velocity, 0 at steady state)."""
    K, w = 40.0, np.array([0.3, 0.0, 0.1])
    if how == "velocity":
        sc = _block(K, c=2.0, velocity=w.tolist())
    else:
        sc = _block(K, c=2.0, keyframes=[{"time": 0.0}, {"time": 10.0, "translation": (10.0 * w).tolist()}])
    sim = ic.Simulator(sc)
    x0 = sim.positions.copy()
    tr = sim.run(3.0)
    assert tr.report["status"] == "ok", tr.report["reason"]
    pred = x0 + w * sim.time + 0.1 * np.array(G) / K
    assert np.abs(sim.positions - pred).max() < 1e-9


def test_soft_pin_force_has_consistent_derivatives():
    rng = np.random.default_rng(5)
    sc = _scene([{"vertices": ["top_left", 3], "stiffness": 30.0, "damping": 0.4, "keyframes": KEYS},
                 {"vertices": ["top_right", 3], "stiffness": 12.0, "velocity": [0.1, 0.2, 0.0]}])
    model = ic.Simulator(sc).model
    f = next(e for e in model.effects if e.name == "pin_springs")
    x = model.rest_positions + 0.05 * rng.standard_normal((model.n, 3))
    v = rng.standard_normal((model.n, 3))
    o = check_force(f, model.n, x, v, 0.37, rng)
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    assert "dissipation" in o and o["dissipation"][-1] == pytest.approx(2.0, abs=0.05), o
    # quadratic: with the Hessian blocks the remainder is round-off
    for e in (1e-3, 1e-4):
        d = rng.standard_normal(x.shape)
        g = np.zeros_like(x)
        f.gradient(x, 0.37, g)
        rem = f.energy(x + e * d) - f.energy(x) - e * np.vdot(g, d) - 0.5 * e * e * np.vdot(
            np.bincount(f.idx, weights=f.k, minlength=model.n)[:, None] * d, d)
        assert abs(rem) < 1e-12
    # the moving targets' power is F . p'
    F = np.zeros_like(x)
    f.force(x, v, 0.37, F)
    eps = 1e-6
    rate = (f.paths.targets(0.37 + eps) - f.paths.targets(0.37 - eps)) / (2 * eps)
    Frows = -f.k[:, None] * (x[f.idx] - f.paths.targets(0.37)) - f.c[:, None] * (v[f.idx] - f.paths.rates(0.37))
    assert f.power(x, v, 0.37) == pytest.approx(float(np.sum(Frows * rate)), rel=1e-6)


def test_soft_pins_leave_their_vertices_free():
    sim = ic.Simulator(_scene(["top_left", {"vertices": ["top_right"], "stiffness": 10.0}]))
    assert len(sim.model.pinned) == 1
    assert "pin_springs" in [e.name for e in sim.model.effects]


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize("pin, match", [
    ({"vertices": [0], "keyframes": KEYS, "velocity": [1.0, 0.0, 0.0]}, r"cloth.pins\[0\].velocity: cannot be"),
    ({"vertices": [0], "keyframes": [{"time": 0.0}, {"time": 0.0}]},
     r"cloth.pins\[0\].keyframes\[1\].time: keyframe times must be strictly increasing.*got 0"),
    ({"vertices": [0], "keyframes": [{"time": 0.5}, {"time": 0.2}]},
     r"keyframes\[1\].time: .*strictly increasing.*got 0.2"),
    ({"vertices": [0], "keyframes": [{"time": -1.0}]}, r"keyframes\[0\].time: .*got -1"),
    ({"vertices": [0], "keyframes": [{"time": 0.0, "translation": [1.0, 2.0]}]},
     r"keyframes\[0\].translation: must be a list of 3 numbers, got \[1.0, 2.0\]"),
    ({"vertices": [0], "keyframes": [{"time": 0.0, "rotation": [1.0]}]}, r"keyframes\[0\].rotation: must be"),
    ({"vertices": [0], "keyframes": [{"time": 0.0, "spin": 1.0}]}, r"keyframes\[0\].spin: unknown key"),
    ({"vertices": [0], "keyframes": [{"translation": [0.0, 0.0, 0.0]}]}, r"keyframes\[0\].time: missing"),
    ({"vertices": [0], "keyframes": []}, r"cloth.pins\[0\].keyframes: must be a non-empty list"),
    ({"vertices": [0], "keyframe": []}, r"cloth.pins\[0\].keyframe: unknown key"),
    ({"vertices": [0], "stiffness": 0.0}, r"cloth.pins\[0\].stiffness: .*got 0"),
    ({"vertices": [0], "stiffness": -3.0}, r"cloth.pins\[0\].stiffness: .*got -3"),
    ({"vertices": [0], "damping": 1.0}, r"cloth.pins\[0\].damping: needs stiffness.*got 1"),
    ({"vertices": [0], "stiffness": 1.0, "damping": -1.0}, r"cloth.pins\[0\].damping: .*got -1"),
])
def test_pin_table_errors_name_key_and_value(pin, match):
    with pytest.raises(SceneError, match=match):
        ic.Simulator(_scene([pin]))


def test_a_vertex_pinned_with_two_motions_is_an_error():
    with pytest.raises(SceneError, match="pinned twice with different motions"):
        ic.Simulator(_scene([{"vertices": [0], "keyframes": KEYS}, {"vertices": [0], "velocity": [1.0, 0, 0]}]))


def test_keyframed_and_soft_pins_survive_the_scene_round_trip():
    from implicit_cloth.scene import Scene, source_of

    sc = _scene([0, {"vertices": [1, "top_left"], "keyframes": KEYS},
                 {"vertices": [2], "stiffness": 3.0, "damping": 0.1, "velocity": [0.0, 1.0, 0.0]}])
    s = Scene.from_dict(copy.deepcopy(sc))
    assert Scene.from_dict(source_of(s.data)).data == s.data


def test_assigned_positions_move_keyframed_and_soft_pins_paths_with_them():
    sim = ic.Simulator(_scene([{"vertices": ["top_left", "top_right"], "keyframes": KEYS},
                               {"vertices": [0], "stiffness": 5.0, "keyframes": KEYS}]))
    p = sim.model.pinned
    x0 = sim.positions[p].copy()
    sim.step(10)
    d = np.array([0.1, -0.2, 0.05])
    sim.positions = sim.positions + d
    f = next(e for e in sim.model.effects if e.name == "pin_springs")
    assert np.allclose(f.paths.targets(sim.time), sim.positions[[0]], rtol=0, atol=1e-14)
    for _ in range(30):
        sim.step(1)
        assert np.abs(sim.positions[p] - _reference(KEYS, x0 + d, sim.time)).max() < 1e-12


def test_soft_pins_lifting_a_cloth_book_their_work_in_the_frames():
    """The frames' total energy grows by the pins' work less what damping and backward Euler take: the soft
    pins' springs are stored energy at each frame's time and their moving targets' work is pin work."""
    keys = [{"time": 0.0}, {"time": 0.6, "translation": [0.1, 0.0, 0.3]}]
    sc = _scene([{"vertices": ["top_left", "top_right"], "stiffness": 200.0, "damping": 0.2, "keyframes": keys}],
                duration=1.0)
    tr = ic.Simulator(sc).run()
    assert tr.report["status"] == "ok", tr.report["reason"]
    fr = tr.report["frames"]
    work = fr["pin_work"][-1]
    grow = fr["total"][-1] - fr["total"][0]
    assert work > 0.1 * 9.81 * 0.3 * 0.5                  # at least half the lift's gravity energy
    assert -0.2 * work < grow - work <= 1e-3 * work       # nothing created; a little dissipated


def test_keyframed_and_soft_pins_lift_a_towel_off_a_sphere():
    """With an obstacle (contact rounds) and adaptive stepping: a corner on a keyframed pin and one on a soft pin
    of the same keys lift the towel off a sphere and carry it; the balance holds and the pins' work is booked."""
    keys = [{"time": 0.0}, {"time": 0.5, "translation": [0.0, 0.0, 0.4]},
            {"time": 1.0, "translation": [0.4, 0.0, 0.4], "rotation": [0.0, 0.0, 0.5]}]
    sc = _scene([{"vertices": ["top_left"], "keyframes": keys},
                 {"vertices": ["top_right"], "stiffness": 50.0, "damping": 0.1, "keyframes": keys}], n=8, duration=1.0)
    sc["cloth"]["plane"] = "xy"
    sc["cloth"]["center"] = [0.0, 0.0, 0.31]
    sc["obstacles"] = [{"shape": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.3}]
    sc["simulation"]["adaptive"] = {"enabled": True}
    sim = ic.Simulator(sc)
    x0 = sim.positions[sim.model.pinned].copy()
    tr = sim.run()
    assert tr.report["status"] == "ok", tr.report["reason"]
    assert np.abs(sim.positions[sim.model.pinned] - _reference(keys, x0, sim.time)).max() < 1e-12
    assert tr.report["frames"]["pin_work"][-1] > 0.1 * 9.81 * 0.2        # lifted by ~0.4 m, half of it at least
