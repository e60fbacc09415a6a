"""The examples do what their comments say: each one runs briefly (a few frames; the contact-heavy crumple and
two_sheets a few steps), and the claims their comments make are checked where a short run can check them.

Each check quotes the claim it checks, so that a comment changed without its check fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.errors import DivergenceError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DOCS = EXAMPLES.parent / "docs"
SCENES = sorted(p.stem for p in EXAMPLES.glob("*.toml") if p.stem != "sweep")


def _comments(name: str) -> str:
    """The example's comments, joined into one line of text."""
    lines = (EXAMPLES / f"{name}.toml").read_text().splitlines()
    return " ".join(" ".join(line.split("#", 1)[1].split()) for line in lines if "#" in line)


def _claim(name: str, text: str) -> None:
    assert " ".join(text.split()) in _comments(name), f"examples/{name}.toml no longer says: {text}"


def _scene(name: str, **simulation) -> dict:
    data = ic.load_scene(EXAMPLES / f"{name}.toml").data
    data["simulation"].update(simulation)
    return data


def test_every_example_is_checked_here():
    assert set(SCENES) == {"cloth_on_cone", "crumple", "drape_sphere", "five_sheets", "flag", "hanging",
                           "keyframed_sphere", "membrane_drape", "moving_sphere", "stiff_large_step", "towel_fold",
                           "towel_lift",
                           "two_sheets", "wind"}


@pytest.mark.parametrize("name", [*SCENES, "sweep"])
def test_references_point_at_sections_that_exist(name):
    """``see docs/NAME.md, Section`` names a heading of that file; no comment sends the reader to a README
    section (the scene reference is docs/scene.md)."""
    text = _comments(name)
    assert not re.search(r"README[,']", text), text
    for doc, section in re.findall(r"see (docs/[\w/]+\.md), ([A-Z][\w ]+?)\)", text):
        headings = [line.lstrip("#").strip() for line in (DOCS.parent / doc).read_text().splitlines()
                    if line.startswith("#") and not line.startswith("##  ") and " = " not in line]
        assert section in headings, (doc, section)


@pytest.mark.parametrize("name", SCENES)
def test_every_example_runs_a_few_frames(name):
    data = _scene(name)
    dt = data["simulation"]["dt"]
    slow = name in ("crumple", "two_sheets", "five_sheets", "towel_fold")     # self-collision: a few steps only
    sim = ic.Simulator(data)
    traj = sim.run(duration=(3 if slow else 10) * dt)
    assert traj.report["status"] in ("ok", "warning")
    assert np.all(np.isfinite(traj.positions))


def test_vertex_counts_and_piece_ranges():
    for name in ("crumple", "drape_sphere", "hanging"):
        _claim(name, "1024 vertices")
        assert ic.Simulator(_scene(name)).model.n == 1024
    _claim("two_sheets", "piece 0: vertices 0 .. 575")
    _claim("two_sheets", "piece 1: vertices 576 .. 975")
    sizes = [c["resolution"][0] * c["resolution"][1] for c in _scene("two_sheets")["cloth"]]
    assert sizes == [576, 400]


def test_starting_heights():
    d = _scene("drape_sphere")
    _claim("drape_sphere", "5 cm above the sphere's top")
    assert d["cloth"]["center"][2] - (d["obstacles"][0]["center"][2] + d["obstacles"][0]["radius"]) == \
        pytest.approx(0.05)
    d = _scene("cloth_on_cone")
    _claim("cloth_on_cone", "5 cm above the tip")
    cone = d["obstacles"][0]
    tip = np.array(cone["center"]) + cone["height"] * np.array(cone.get("axis", [0.0, 0.0, 1.0]))
    assert d["cloth"]["center"][2] - tip[2] == pytest.approx(0.05)
    d = _scene("crumple")
    _claim("crumple", "its lower edge 12 cm above the floor")
    assert d["cloth"]["plane"] == "xz" and d["cloth"]["center"][2] - d["cloth"]["size"][1] / 2 == pytest.approx(0.12)
    d = _scene("two_sheets")
    _claim("two_sheets", "10 cm above the sphere's top")
    _claim("two_sheets", "4 cm above piece 0")
    top = d["obstacles"][0].get("center", [0.0, 0.0, 0.0])[2] + d["obstacles"][0]["radius"]
    assert d["cloth"][0]["center"][2] - top == pytest.approx(0.10)
    assert d["cloth"][1]["center"][2] - d["cloth"][0]["center"][2] == pytest.approx(0.04)


def test_membrane_drape_takes_the_denim_membrane():
    _claim("membrane_drape", "576 vertices")
    _claim("membrane_drape", "5 cm above the sphere's top")
    _claim("membrane_drape", "6330 N/m warp and weft, 122.5 N/m shear")
    _claim("membrane_drape", "the areal density 0.4 kg/m^2")
    d = _scene("membrane_drape")
    c = d["cloth"]
    assert c["resolution"][0] * c["resolution"][1] == 576 and list(c["springs"]) == ["bend"]
    assert c["center"][2] - (d["obstacles"][0]["center"][2] + d["obstacles"][0]["radius"]) == pytest.approx(0.05)
    m = c["membrane"]
    assert round(m["stretch_u"]["stiffness"]) == round(m["stretch_v"]["stiffness"]) == 6330
    assert round(m["shear"]["stiffness"], 1) == 122.5 and c["density"] == 0.4
    assert [e.name for e in ic.Simulator(d).model.effects] == ["gravity", "drag", "springs", "membrane"]


def test_hanging_starts_flat_falls_and_hangs_from_its_pins():
    _claim("hanging", "it starts flat (horizontal), falls, swings down under gravity and back up, and is still "
                      "swinging at the end of the 2 s")
    _claim("hanging", "(t = 0, 1/30, ..., 2.0)")
    sim = ic.Simulator(_scene("hanging"))
    traj = sim.run()
    x = traj.positions
    assert len(traj) == 61 and traj.times[0] == 0.0 and traj.times[-1] == pytest.approx(2.0)
    assert np.ptp(x[0, :, 2]) == 0.0                                   # flat, horizontal
    pins = sim.model.pinned
    assert len(pins) == 2 and np.all(x[0, pins, 1] == x[0, :, 1].max())   # two corners of the +y edge ...
    np.testing.assert_allclose(x[:, pins], np.broadcast_to(x[0, pins], x[:, pins].shape))   # ... held in place
    depth = np.ptp(x[:, :, 2], axis=1)                                   # vertical extent at each frame
    down = int(np.argmax(depth > 0.95))
    assert down > 0 and traj.times[down] < 1.0                          # hangs straight down within 1 s ...
    assert depth[down:].min() < 0.6                                     # ... swings back up ...
    speed = np.linalg.norm(x[-1] - x[-2], axis=1).max() * 30            # m/s between the last two frames
    assert speed > 0.3                                                  # ... and still swings at 2 s


def test_stiff_large_step_claims_in_the_first_second():
    _claim("stiff_large_step", "the explicit integrators blow up within a few steps")
    _claim("stiff_large_step", "--integrator symplectic_euler -> diverges within a few steps: exit code 3")
    for integ in ("symplectic_euler", "forward_euler"):
        with pytest.raises(DivergenceError) as err:
            ic.Simulator(_scene("stiff_large_step", integrator=integ)).run()
        assert err.value.trajectory.times[-1] <= 5 * 0.04, integ
    _claim("stiff_large_step", "With fixed steps (simulation.adaptive.enabled = false) the largest strain reaches "
                               "about 2 (200 %) in the first swing at this step, against 0.008 with --dt 0.01")
    fixed = {"adaptive": {"enabled": False}}
    strain = {}
    for dt in (0.04, 0.01):
        data = _scene("stiff_large_step", dt=dt, duration=1.0)
        data["simulation"].update(fixed)
        strain[dt] = max(ic.Simulator(data).run().report["frames"]["max_strain"])
    assert 1.4 < strain[0.04] < 2.6 and 0.006 < strain[0.01] < 0.010, strain


@pytest.mark.slow
def test_stiff_large_step_claims_over_the_whole_run():
    """The whole 3 s, adaptive (the default) and with fixed steps (about 10 s on numba's path, 45 on numpy's)."""
    fixed = {"adaptive": {"enabled": False}}
    _claim("stiff_large_step", "redoes almost every step at the same size with Newton iterations (report.json: "
                               "adaptive.newton_retries, about 70 of the 75 steps), halves none "
                               "(adaptive.retries = 0) and keeps the strain to about 0.002")
    _claim("stiff_large_step", "the strain decays to about 0.001 or less as it settles")
    traj = ic.Simulator(_scene("stiff_large_step")).run()
    r = traj.report
    assert r["status"] == "ok"
    assert r["adaptive"]["retries"] == 0 and 60 <= r["adaptive"]["newton_retries"] <= 75, r["adaptive"]
    ms = r["frames"]["max_strain"]
    assert 0.001 < max(ms) < 0.004 and ms[-1] < 0.0012, (max(ms), ms[-1])
    data = _scene("stiff_large_step")
    data["simulation"].update(fixed)
    ms = ic.Simulator(data).run().report["frames"]["max_strain"]
    assert ms[-1] < 0.0015, ms[-1]


def test_wind_material_and_direction():
    _claim("wind", "A cotton cloth")
    _claim("wind", "preset springs and areal density 0.15 kg/m^2")
    from implicit_cloth.materials import MATERIALS

    assert _scene("wind")["cloth"]["material"] == "cotton" and MATERIALS["cotton"].density == 0.15
    _claim("wind", "(blows along +y)")
    traj = ic.Simulator(_scene("wind")).run(duration=0.3)
    assert traj.positions[-1, :, 1].mean() - traj.positions[0, :, 1].mean() > 0.02


def test_flag_flaps_from_its_pole():
    _claim("flag", "A 0.9 m x 0.6 m denim flag on a vertical pole, flapping in a 6 m/s breeze")
    _claim("flag", "600 vertices")
    _claim("flag", "6330 N/m warp and weft, 122.5 N/m shear, bending modulus 1.687e-5 N m")
    _claim("flag", "the left column of the grid (vertex 30 k, k = 0 .. 19), fixed to the pole")
    d = _scene("flag")
    c = d["cloth"]
    assert c["resolution"][0] * c["resolution"][1] == 600 and c["size"] == [0.9, 0.6] and c["density"] == 0.4
    assert c["membrane"]["stretch_u"]["stiffness"] == pytest.approx(6330, abs=0.5)
    assert c["bending"]["model"] == "dihedral" and c["bending"]["stiffness"] == pytest.approx(1.687e-5, rel=1e-3)
    assert np.linalg.norm(d["effects"]["wind"]["velocity"]) == pytest.approx(6.2, abs=0.05)
    sim = ic.Simulator(d)
    assert [e.name for e in sim.model.effects] == ["gravity", "aerodynamics", "membrane", "bending"]
    pole = np.flatnonzero(np.isclose(sim.model.rest_positions[:, 0], 0.0))
    assert np.array_equal(np.sort(sim.model.pinned), pole) and np.array_equal(pole, 30 * np.arange(20))
    _claim("flag", "flapping")
    traj = sim.run(duration=2.0)
    assert traj.report["status"] == "ok"
    free = np.isclose(sim.model.rest_positions[:, 0], 0.9)
    y = traj.positions[traj.times >= 1.0][:, free, 1].mean(axis=1)   # the free edge, across the wind
    assert np.ptp(y) > 0.1, y          # it swings by more than 10 cm in the second second, not streaming still


def test_moving_and_keyframed_spheres():
    d = _scene("moving_sphere")
    s = d["obstacles"][0]
    _claim("moving_sphere", "the sphere moves 5 cm a step")
    assert s["velocity"][1] * d["simulation"]["dt"] == pytest.approx(0.05)
    _claim("moving_sphere", "the sphere ends 0.4 m past the cloth's plane")
    assert s["center"][1] + s["velocity"][1] * d["simulation"]["duration"] - d["cloth"]["center"][1] == \
        pytest.approx(0.4)
    _claim("moving_sphere", "starts 40 cm in front of the cloth")
    assert d["cloth"]["center"][1] - s["center"][1] == pytest.approx(0.4)
    k = _scene("keyframed_sphere")["obstacles"][0]["keyframes"]
    _claim("keyframed_sphere", "out through a hanging cloth at 5 m/s, a pause turning 1.5 rad about the vertical, "
                               "then back at 5 m/s")
    speed = [np.linalg.norm(np.subtract(b["center"], a["center"])) / (b["time"] - a["time"]) for a, b in zip(k, k[1:])]
    assert speed == pytest.approx([5.0, 0.0, 5.0])
    turn = [np.array(f.get("rotation", [0.0, 0.0, 0.0])) for f in k]
    assert np.linalg.norm(turn[2] - turn[1]) == pytest.approx(1.5) and turn[2][:2].tolist() == [0.0, 0.0]
    assert np.array_equal(turn[3], turn[2]) and not turn[0].any() and not turn[1].any()


def test_sweep_cases_and_the_explicit_one_diverging():
    from implicit_cloth.batch.sweep import load_sweep

    _claim("sweep", "3 time steps x 3 integrators x 3 stiffnesses = 27 cases, each on a 16 x 16 cloth for 1 s")
    sweep = load_sweep(EXAMPLES / "sweep.toml")
    assert len(sweep.cases) == 27
    assert {tuple(c.raw["cloth"]["resolution"]) for c in sweep.cases} == {(16, 16)}
    assert {c.raw["simulation"]["duration"] for c in sweep.cases} == {1.0}
    _claim("sweep", "the explicit one diverges here")
    mildest = [c for c in sweep.cases if c.params["simulation.integrator"] == "symplectic_euler"
               and c.params["simulation.dt"] == 0.005 and c.params["cloth.springs.structural.stiffness"] == 1e3]
    with pytest.raises(DivergenceError):
        ic.Simulator(mildest[0].raw).run()


@pytest.mark.slow
def test_five_sheets_keep_their_order_never_cross_and_rest_apart():
    """The first second (the sheets land and drape; the whole 2 s takes minutes): no edge through a triangle at
    any kept frame (the segment-triangle judge of test_self_collision), each sheet above the one below it over
    the sphere's top at the end (its height interpolated on the lower sheet's vertices), and every pair of
    non-adjacent primitives at least half the thickness apart."""
    from scipy.interpolate import LinearNDInterpolator
    from test_self_collision import crossings

    pytest.importorskip("ipctk")
    for k in range(5):
        _claim("five_sheets", f"piece {k}: vertices {k * 1024} .. {k * 1024 + 1023}")
    _claim("five_sheets", "The layers keep their order")
    d = _scene("five_sheets")
    assert d["collision"]["method"] == "barrier" and [c["center"][2] for c in d["cloth"]] == \
        pytest.approx([0.40, 0.42, 0.44, 0.46, 0.48])
    sim = ic.Simulator(d)
    traj = sim.run(duration=1.0)
    assert traj.report["status"] == "ok", traj.report["reason"]
    faces = traj.faces
    assert max(crossings(x, faces) for x in traj.positions) == 0
    x = traj.positions[-1]
    for k in range(4):
        low, up = x[k * 1024:(k + 1) * 1024], x[(k + 1) * 1024:(k + 2) * 1024]
        z_low = LinearNDInterpolator(low[:, :2], low[:, 2])
        top = up[np.hypot(up[:, 0], up[:, 1]) < 0.1]
        assert len(top) > 10 and np.all(top[:, 2] > z_low(top[:, :2]))
    th = d["collision"]["thickness"]
    assert sim.cloth_contact.term(x).distance(x) >= th / 2


def test_towel_lift_corners_rise_turn_and_hold():
    _claim("towel_lift", "the corners rise 0.2 m in the first second, then the pair turns a quarter turn (90 degrees) "
                         "about the vertical through their midpoint in the next, and holds there")
    _claim("towel_lift", "The third corner hangs on a soft pin (a zero-length spring to where it started)")
    sim = ic.Simulator(_scene("towel_lift"))
    p = sim.model.pinned
    x0 = sim.positions[p].copy()
    mid = x0.mean(axis=0)
    lift = np.array([0.0, 0.0, 0.2])
    turned = mid + lift + (x0 - mid) @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T
    np.testing.assert_allclose(sim.model.pin_positions(1.0), x0 + lift, rtol=0, atol=1e-15)
    np.testing.assert_allclose(sim.model.pin_positions(2.0), turned, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sim.model.pin_positions(2.5), turned, rtol=0, atol=1e-12)
    assert len(p) == 2 and [e.name for e in sim.model.effects][-1] == "pin_springs"


@pytest.mark.slow
def test_towel_fold_folds_in_two_without_crossing():
    """The whole run (about 25 s here): no edge through a triangle at any kept frame (test_self_collision's
    judge), status ok (energy balance and the strain bound on the membrane's triangles), and folded in half at
    the end: the lifted half lies over the other, its edge over the other's edge 2.5 to 5 mm (the barrier's
    half and whole thickness) above the lower layer wherever it lies over it, and the lower half still flat on
    the floor."""
    from scipy.interpolate import LinearNDInterpolator
    from test_self_collision import crossings

    pytest.importorskip("ipctk")
    _claim("towel_fold", "its right edge, held by keyframed pins, lifts, travels over the fold line and comes down "
                         "onto the left edge, so the towel ends folded in half on itself")
    _claim("towel_fold", "the 24 vertices i = 23 of each row j: 24 j + 23")
    d = _scene("towel_fold")
    c = d["cloth"]
    nx, ny = c["resolution"]
    assert (nx, ny) == (24, 24) and c["size"] == [0.5, 0.5] and c["material"] == "denim"
    assert d["collision"]["method"] == "barrier" and d["collision"]["self_collision"]
    sim = ic.Simulator(d)
    assert [e.name for e in sim.model.effects][-2:] == ["membrane", "bending"] and sim.model.springs is None
    edge = np.arange(ny) * nx + nx - 1
    assert np.array_equal(np.sort(sim.model.pinned), edge)
    traj = sim.run()
    r = traj.report
    assert r["status"] == "ok", r["reason"]
    assert max(crossings(x, traj.faces) for x in traj.positions) == 0
    x = traj.positions[-1].reshape(ny, nx, 3)
    lower, upper = x[:, : nx // 2].reshape(-1, 3), x[:, nx // 2:].reshape(-1, 3)
    th = d["collision"]["thickness"]
    # flat, but for the column at the fold, which the crease lifts; in place within 2 cm (the lift drags the towel
    # about 1 cm over the floor, friction 0.3; the layers' friction a few millimetres more)
    flat = x[:, : nx // 2 - 1].reshape(-1, 3)
    assert flat[:, 2].max() < th and lower[:, 0].min() == pytest.approx(-0.25, abs=0.02)
    assert upper[:, 0].max() < 0.0 and upper[:, 0].min() > -0.26                               # over the left half
    np.testing.assert_allclose(x[:, -1, 0], -0.25, atol=1e-9)                                  # the edge over the edge
    z_low = LinearNDInterpolator(lower[:, :2], lower[:, 2])(upper[:, :2])
    over = np.isfinite(z_low)
    assert over.sum() > 0.8 * len(upper)
    gap = upper[over, 2] - z_low[over]
    assert gap.min() > 0.5 * th - 1e-4 and np.median(gap) < 1.5 * th
