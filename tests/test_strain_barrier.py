"""Strain limiting as a barrier in the step's solve (``collision.method = "barrier"`` with
``[simulation.strain_limit]``, :mod:`implicit_cloth.contact.strain`): its derivatives against finite differences
with their order, its line-search bound against sampled paths, and whole runs judged from their states (every
spring's strain at every frame, the energy from the states, the pins)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from test_forces import check_force

import implicit_cloth as ic
from implicit_cloth.contact import strain as strain_mod
from implicit_cloth.errors import SceneError

G = 9.81


def _hanging(n=10, k=5.0, limit=0.1, method="barrier", duration=1.0, dt=1 / 60, **limits):
    """A soft sheet hanging from its two top corners: without a limit its top springs stretch far past 10 %."""
    scene = {"simulation": {"integrator": "backward_euler", "dt": dt, "duration": duration, "frame_rate": 60},
             "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xz",
                       "center": [0.0, 0.0, 1.0], "pins": ["top_left", "top_right"],
                       "springs": {"structural": {"stiffness": k, "damping": 0.01},
                                   "shear": {"stiffness": k / 3, "damping": 0.01},
                                   "bend": {"stiffness": 0.1, "damping": 0.001}}},
             "effects": {"gravity": [0.0, 0.0, -G]}}
    if limit:
        scene["simulation"]["strain_limit"] = {"max_strain": limit, **limits}
    if method == "barrier":
        scene["collision"] = {"method": "barrier"}
    return scene


def _strains(model, x):
    s = model.springs
    return (np.linalg.norm(x[s.j] - x[s.i], axis=1) - s.L0) / s.L0


def _energy(model, x, v):
    """Kinetic + gravity + the springs' elastic energy, from the state alone (the barrier's is >= 0 and left out)."""
    s = model.springs
    m = model.masses
    l = np.linalg.norm(x[s.j] - x[s.i], axis=1)
    return (0.5 * float(np.sum(m * np.sum(v * v, axis=1))) + G * float(np.sum(m * x[:, 2]))
            + 0.5 * float(np.sum(s.k * (l - s.L0) ** 2)))


def _run(scene, monkeypatch=None, accelerator=None):
    if accelerator is not None:
        monkeypatch.setenv("IMPLICIT_CLOTH_ACCELERATOR", accelerator)
    sim = ic.Simulator(scene)
    states = [(sim.state.x.copy(), sim.state.v.copy())]
    for _ in range(round(scene["simulation"]["duration"] * 60)):
        sim.step()
        states.append((sim.state.x.copy(), sim.state.v.copy()))
    return sim, states


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("scale, hessian", [(1.09, True), (0.915, False)], ids=["stretched", "compressed"])
def test_the_strain_barrier_derivatives_with_their_order(scale, hessian):
    """Every limited spring within the barrier's reach (stretched 9 % of a 10 % bound, or the in-plane ones
    compressed 8.5 %): the gradient is the energy's (Taylor remainder O(e^2)) and, stretched, the Hessian
    blocks too (O(e^3); compressed, the transverse part is clamped: projected Newton, not the exact Hessian)."""
    rng = np.random.default_rng(5)
    sim = ic.Simulator(_hanging(n=6))
    stage = sim.strain_contact
    x0 = sim.model.rest_positions
    x = scale * x0 + 1e-5 * rng.standard_normal(x0.shape)
    term = stage.term(x)
    assert term.active(x) > 0.5 * len(stage.i), "test set-up: the springs are not within the barrier's reach"
    o = check_force(term, sim.model.n, x, np.zeros_like(x), 0.0, rng, d=1e-2 * rng.standard_normal(x.shape))
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    if hessian:
        assert o["hessian"][-1] == pytest.approx(3.0, abs=0.1), o
    assert term.energy(x) > 0.0


def test_the_strain_barrier_is_infinite_beyond_its_bound_and_zero_far_from_it():
    sim = ic.Simulator(_hanging(n=6))
    term = sim.strain_contact.term(sim.model.rest_positions)
    x0 = sim.model.rest_positions
    assert term.energy(x0) == 0.0 and term.active(x0) == 0
    assert term.energy(1.05 * x0) == 0.0                   # 5 %: outside the reach (the last quarter of 10 %)
    assert term.energy(1.101 * x0) == np.inf
    assert term.energy(0.899 * x0) == np.inf               # the in-plane springs' compression bound


def test_the_line_search_bound_is_exact_on_sampled_paths():
    """:meth:`StrainBarrier.step_limit`: along ``x + s dx`` for every ``s`` up to the share it returns no spring
    closes more than SAFE of its room to either bound (sampled densely), and at that share one spring has closed
    exactly SAFE of it (the bound is not loose)."""
    rng = np.random.default_rng(7)
    sim = ic.Simulator(_hanging(n=6))
    stage = sim.strain_contact
    x0 = sim.model.rest_positions
    checked = 0
    for _ in range(40):
        x = (1.0 + 0.04 * rng.uniform(-1, 1)) * x0 + 2e-3 * rng.standard_normal(x0.shape)
        term = stage.term(x)
        dx = 0.05 * rng.standard_normal(x.shape)
        a = term.step_limit(x, dx)
        l0 = term.lengths(x)
        room_up, room_down = term.upper - l0, l0 - term.lower
        shortens = stage.reach_down > 0
        worst = 0.0
        for s in np.linspace(0.0, a, 201):
            l = term.lengths(x + s * dx)
            closed = np.maximum((l - l0) / room_up, np.where(shortens, (l0 - l) / room_down, -np.inf))
            worst = max(worst, float(closed.max()))
        assert worst <= strain_mod.SAFE * (1 + 1e-9)
        if a < 1.0:
            checked += 1
            assert worst == pytest.approx(strain_mod.SAFE, rel=1e-6)
    assert checked > 10


# --------------------------------------------------------------------------- whole runs
def test_a_soft_hanging_sheet_never_passes_its_strain_bound_and_gains_no_energy():
    """Every spring's strain at every frame within [-0.1, 0.1] (the projection's bounds), computed here from the
    states; the energy from the states never above its start (the barrier's stored energy is >= 0); the pins
    where they were; the run's report ok. Without the limit the same sheet stretches far past it."""
    free_sim, free = _run(_hanging(limit=0.0, method="rounds"))
    assert max(_strains(free_sim.model, x).max() for x, _ in free) > 0.3      # the limit has work to do
    sim, states = _run(_hanging())
    m = sim.model
    e0 = _energy(m, *states[0])
    for x, v in states:
        s = _strains(m, x)
        assert s.max() <= 0.1 + 1e-9 and s[_planar(m)].min() >= -0.1 - 1e-9
        assert _energy(m, x, v) <= e0 + 1e-9 * abs(e0)
        assert np.array_equal(x[m.pinned], states[0][0][m.pinned])
    assert max(_strains(m, x).max() for x, _ in states) > 0.09            # the bound held it, near the bound
    rep = sim.run(duration=0.2).report
    assert rep["status"] == "ok", rep["health"]
    assert rep["strain_limit"]["max_strain_after"] <= 0.1 + 1e-9
    assert rep["strain_limit"]["steps_limited"] > 0


def _planar(model):
    s = model.springs
    out = np.zeros(len(s.L0), dtype=bool)
    for kind in ("structural", "shear"):
        out[s.kinds[kind]] = True
    return out


def test_numpy_and_numba_agree_with_the_strain_barrier(monkeypatch):
    pytest.importorskip("numba")
    _, a = _run(_hanging(duration=0.5), monkeypatch, "numpy")
    _, b = _run(_hanging(duration=0.5), monkeypatch, "numba")
    assert np.abs(a[-1][0] - b[-1][0]).max() < 1e-6
    assert np.abs(a[-1][1] - b[-1][1]).max() < 1e-4


def test_pins_pulled_apart_beyond_the_bound_are_reported_not_a_failure():
    """Pins moving apart (0.4 m on a 1 m sheet) force the springs between them past any bound: the step admits it
    (the bound is moved out for the springs the pins alone break), the run finishes, and the report says
    ``strain``."""
    scene = _hanging(n=6, k=50.0, duration=0.5)
    scene["cloth"]["pins"] = [{"vertices": ["top_left"], "velocity": [-0.4, 0.0, 0.0]},
                              {"vertices": ["top_right"], "velocity": [0.4, 0.0, 0.0]}]
    sim = ic.Simulator(scene)
    rep = sim.run().report
    assert rep["status"] == "warning"
    assert any(w["criterion"] == "strain" for w in rep["health"])
    assert np.all(np.isfinite(sim.state.x))


# --------------------------------------------------------------------------- input
def test_a_barrier_strain_limit_needs_no_obstacle_but_a_rounds_collision_table_still_does():
    ic.Simulator(_hanging())                                  # [collision] method = "barrier", no obstacles: fine
    scene = _hanging()
    scene["collision"] = {"method": "rounds"}
    with pytest.raises(SceneError, match="no \\[\\[obstacles\\]\\] to collide with"):
        ic.Simulator(scene)
    scene = copy.deepcopy(_hanging())
    del scene["simulation"]["strain_limit"]
    with pytest.raises(SceneError, match="no \\[\\[obstacles\\]\\] to collide with"):
        ic.Simulator(scene)


def test_the_cli_says_what_the_barrier_limit_did(tmp_path, capsys):
    """``implicit-cloth run``: the report's strain_limit says ``method = "barrier"`` and the summary line counts
    springs within the barrier's reach, not over-stretched ones (none is)."""
    import json

    from implicit_cloth.cli import main

    scene = tmp_path / "scene.toml"
    scene.write_text("""
[simulation]
integrator = "backward_euler"
dt = 0.016666666666666666
duration = 0.5
strain_limit = { max_strain = 0.1 }

[cloth]
size = [1.0, 1.0]
resolution = [8, 8]
plane = "xz"
mass = 0.1
pins = ["top_left", "top_right"]
springs = { structural = { stiffness = 5.0 }, shear = { stiffness = 1.7 }, bend = { stiffness = 0.1 } }

[effects]
gravity = [0.0, 0.0, -9.81]

[collision]
method = "barrier"
""")
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    sl = report["strain_limit"]
    assert sl["method"] == "barrier" and sl["steps_limited"] > 0 and sl["max_strain_after"] <= 0.1 + 1e-9
    out = capsys.readouterr().out
    assert "strain limit 0.1 (barrier):" in out and "over-stretched" not in out


def test_a_bound_let_out_comes_back_without_a_jump_in_the_barrier_s_energy():
    """Pins pulled apart let bounds out; the next step's barrier starts at the energy the last step's ended with
    (its bounds drawn back only as far as that holds: no energy appears between steps)."""
    scene = _hanging(n=6, k=50.0, duration=1.0)
    scene["cloth"]["pins"] = [{"vertices": ["top_left"], "velocity": [-0.4, 0.0, 0.0]},
                              {"vertices": ["top_right"], "velocity": [0.4, 0.0, 0.0]}]
    sim = ic.Simulator(scene)
    stage = sim.strain_contact
    let_out = 0
    for _ in range(20):
        sim.step()
        x1 = sim.state.x
        _, u_end, lo_end = stage._ends[-1]
        ended = strain_mod.StrainBarrier(stage, x1, u_end, lo_end)
        let_out += int(np.count_nonzero(u_end > stage.upper))
        nxt = stage.term(x1)
        assert nxt.energy(x1) == pytest.approx(ended.energy(x1), rel=1e-12, abs=1e-15)
    assert let_out > 0
