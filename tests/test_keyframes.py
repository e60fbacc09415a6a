"""Keyframed obstacle motion: the pose and its velocity, scene keys, and cloth against a keyframed obstacle."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_collision import TOL, _mesh_file, _passes_around, cloth_scene, depths

import implicit_cloth as ic
from implicit_cloth.collision.shapes import KeyframedMotion, Motion

R0 = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()      # the shape's own orientation
KEYS = dict(times=[0.1, 0.4, 0.5, 1.0],
            centers=[[0.0, 0.0, 0.0], [0.3, -0.1, 0.2], [0.3, -0.1, 0.2], [-0.2, 0.4, 0.0]],
            rotvecs=[[0.0, 0.0, 0.0], [0.0, 0.0, 1.2], [0.4, 0.0, 1.2], [-0.5, 1.0, 0.3]])


# --------------------------------------------------------------------------- the motion itself
def test_keyframed_pose_passes_through_the_keys_and_rests_outside_them():
    mo = KeyframedMotion(**KEYS, rotation=R0)
    for t, c, r in zip(KEYS["times"], KEYS["centers"], KEYS["rotvecs"]):
        ck, Rk = mo.pose(t)
        np.testing.assert_allclose(ck, c, atol=1e-15)
        np.testing.assert_allclose(Rk, Rotation.from_rotvec(r).as_matrix() @ R0, atol=1e-14)
    for t, k in ((0.0, 0), (-1.0, 0), (1.0, -1), (7.0, -1)):
        c, R = mo.pose(t)
        np.testing.assert_allclose(c, KEYS["centers"][k], atol=1e-15)
        np.testing.assert_allclose(R, Rotation.from_rotvec(KEYS["rotvecs"][k]).as_matrix() @ R0, atol=1e-14)
        v, w = mo.twist(t)
        assert not np.any(v) and not np.any(w)
    # translation piecewise linear: halfway between two keys, the midpoint of their centres
    np.testing.assert_allclose(mo.pose(0.25)[0], [0.15, -0.05, 0.1], atol=1e-15)
    # vectorised over times: row k is the pose at times[k]
    ts = np.array([0.05, 0.2, 0.45, 0.7, 1.3])
    c, R = mo.pose(ts)
    for k, t in enumerate(ts):
        ck, Rk = mo.pose(t)
        np.testing.assert_allclose(c[k], ck, atol=1e-15)
        np.testing.assert_allclose(R[k], Rk, atol=1e-15)


@pytest.mark.parametrize("kind", ["keyframed", "constant"])
def test_point_velocity_is_the_derivative_of_the_pose(kind):
    """``point_velocity(x(t), t)`` against the central difference of ``x(t) = c(t) + R(t) p`` for fixed local p."""
    if kind == "keyframed":
        mo = KeyframedMotion(**KEYS, rotation=R0)
        ts = np.array([0.15, 0.3, 0.45, 0.62, 0.9])           # inside segments, away from the keys
    else:
        mo = Motion(np.array([0.1, 0.2, 0.3]), R0, np.array([1.0, -2.0, 0.5]), np.array([0.5, 2.0, -1.0]))
        ts = np.array([0.0, 0.15, 0.3, 0.9])
    p = np.random.default_rng(0).uniform(-0.5, 0.5, (len(ts), 3))
    e = 1e-6
    fd = (mo.to_world(p, ts + e) - mo.to_world(p, ts - e)) / (2 * e)
    u = mo.point_velocity(mo.to_world(p, ts), ts)
    assert np.abs(u).max() > 0.5                              # the check is not vacuous
    np.testing.assert_allclose(u, fd, atol=1e-7)
    # the same per instant (scalar times) as vectorised over times
    for k, t in enumerate(ts):
        np.testing.assert_allclose(mo.point_velocity(mo.to_world(p[k:k + 1], t), t)[0], u[k], atol=1e-14)


def test_two_keys_give_the_constant_twist_pose():
    v, w, c0 = np.array([0.4, -1.0, 0.2]), np.array([0.0, 1.5, 2.0]), np.array([0.1, 0.2, -0.3])
    T = 1.0                                                   # |w| T = 2.5 rad < pi: slerp turns the same way
    const = Motion(c0, R0, v, w)
    keyed = KeyframedMotion([0.0, T], [c0, c0 + v * T], [[0.0, 0.0, 0.0], w * T], rotation=R0)
    ts = np.linspace(0.0, T, 11)[:-1]
    for a, b in zip(const.pose(ts), keyed.pose(ts)):
        np.testing.assert_allclose(a, b, atol=1e-14)
    for a, b in zip(const.twist(ts), keyed.twist(ts)):
        np.testing.assert_allclose(a, b, atol=1e-14)


# --------------------------------------------------------------------------- scene keys
def test_keyframe_keys_are_normalised():
    sc = ic.Scene.from_dict(cloth_scene({"shape": "sphere", "radius": 0.1, "keyframes": [
        {"time": 0, "center": [0, -0.3, 0]}, {"time": 0.5, "center": [0, 0.2, 0], "rotation": [0, 0, 1]}]}))
    ob = sc.data["obstacles"][0]
    assert ob["keyframes"] == [{"time": 0.0, "center": [0.0, -0.3, 0.0], "rotation": [0.0, 0.0, 0.0]},
                               {"time": 0.5, "center": [0.0, 0.2, 0.0], "rotation": [0.0, 0.0, 1.0]}]
    assert ob["center"] == [0.0, -0.3, 0.0]                  # where it rests before its first key
    plane = ic.Scene.from_dict(cloth_scene({"shape": "plane", "keyframes": [
        {"time": 0.1, "center": [0, 0, -1]}, {"time": 0.2, "center": [0, 0, 0]}]}))
    assert plane.data["obstacles"][0]["point"] == [0.0, 0.0, -1.0]


K2 = [{"time": 0.0, "center": [0, 0, 0]}, {"time": 0.5, "center": [0, 1, 0]}]


@pytest.mark.parametrize("extra, message", [
    ({"keyframes": [{"time": 0.5, "center": [0, 0, 0]}, {"time": 0.2, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[1].time: must be greater than the previous key's time 0.5, got 0.2"),
    ({"keyframes": [{"time": 0.5, "center": [0, 0, 0]}, {"time": 0.5, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[1].time: must be greater than the previous key's time 0.5, got 0.5"),
    ({"keyframes": [{"time": 0.0, "center": [0, 0, 0]}]},
     "obstacles[0].keyframes: must be a list of at least 2 keys ({time = s, center = [x, y, z]}), got [{"),
    ({"keyframes": [{"time": 0.0, "center": [0, 0, 0]}, {"center": [0, 1, 0]}]},
     "obstacles[0].keyframes[1].time: missing (each key needs its time in s)"),
    ({"keyframes": [{"time": 0.0}, {"time": 1.0, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[0].center: missing"),
    ({"keyframes": K2, "velocity": [0, 5, 0]},
     "obstacles[0].velocity: cannot be combined with keyframes (the keys give the obstacle's position and motion), "
     "got [0, 5, 0]"),
    ({"keyframes": K2, "angular_velocity": [0, 0, 1]}, "obstacles[0].angular_velocity: cannot be combined with"),
    ({"keyframes": K2, "center": [0, 0, 0]}, "obstacles[0].center: cannot be combined with keyframes"),
    ({"keyframes": [{"time": -0.1, "center": [0, 0, 0]}, {"time": 1.0, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[0].time: must be a finite number >= 0, got -0.1"),
    ({"keyframes": [{"time": 0.0, "center": [0, 0]}, {"time": 1.0, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[0].center: must be a list of 3 numbers, got [0, 0]"),
    ({"keyframes": [{"time": 0.0, "center": [0, 0, 0], "rotaton": [0, 0, 1]}, {"time": 1.0, "center": [0, 1, 0]}]},
     "obstacles[0].keyframes[0].rotaton: unknown key (did you mean 'rotation'?)"),
    ({"keyframes": [{"time": 0.0, "center": [0, 0, 0]}, 3]}, "obstacles[0].keyframes[1]: must be a table, got 3"),
    ({"keyframe": K2}, "obstacles[0].keyframe: unknown key (did you mean 'keyframes'?)"),
])
def test_bad_keyframes_give_one_line_errors(extra, message):
    with pytest.raises(ic.SceneError) as err:
        ic.Scene.from_dict({"cloth": {"mass": 0.1}, "obstacles": [{"shape": "sphere", "radius": 0.1, **extra}]})
    assert message in str(err.value) and "\n" not in str(err.value)


# --------------------------------------------------------------------------- cloth against keyframed obstacles
CASES = {
    # a sphere at 5 m/s through a hanging cloth (vertex sweeps, proximity, edges)
    "sphere": (dict(shape="sphere", radius=0.12), np.array([0.0, -0.3, 0.0]), np.array([0.0, 5.0, 0.0]),
               np.zeros(3), dict(center=(0, 0, 0), plane="xz", pins=["top_left", "top_right"]), 0.1),
    # a bar spinning at 6 rad/s while drifting, under a falling cloth (sharp features, rotation)
    "spinning_box": (dict(shape="box", size=[0.5, 0.08, 0.08], rotation=[0.0, 0.0, 0.3]),
                     np.array([0.0, 0.0, -0.05]), np.array([0.1, 0.0, 0.05]), np.array([0.0, 0.0, 6.0]),
                     dict(center=(0, 0, 0.05), friction=0.3), 0.3),
    # a mesh sphere at 5 m/s, turning (mesh vertex-face, corner and edge tests)
    "mesh": (dict(shape="mesh"), np.array([0.0, -0.3, 0.0]), np.array([0.0, 5.0, 0.0]), np.array([0.0, 0.0, 3.0]),
             dict(center=(0, 0, 0), plane="xz", pins=["top_left", "top_right"]), 0.1),
}


@pytest.mark.parametrize("case", list(CASES))
def test_two_keys_reproduce_the_velocity_form(case, tmp_path):
    """Keys at t = 0 and t = T on the constant-twist path give the same cloth trajectory, to round-off."""
    ob, c0, v, w, cloth, duration = CASES[case]
    place = "center"
    if case == "mesh":
        ob = {**ob, "path": _mesh_file(tmp_path, trimesh.creation.icosphere(subdivisions=1, radius=0.12))}
        place = "translation"
    T = 0.4                                                   # the last key after the end of the run
    const = cloth_scene({**ob, place: list(c0), "velocity": list(v), "angular_velocity": list(w)},
                        dt=1 / 30, duration=duration, res=10, size=0.6, **cloth)
    keyed = cloth_scene({**ob, "keyframes": [{"time": 0.0, "center": list(c0)},
                                             {"time": T, "center": list(c0 + v * T), "rotation": list(w * T)}]},
                        dt=1 / 30, duration=duration, res=10, size=0.6, **cloth)
    # the scene's own sensitivity to round-off: the velocity form with its centre moved by 1e-15 m (contacts
    # and the solver's stopping rule amplify a last-bit change to ~1e-8 m over a few steps in the box case)
    nudged = cloth_scene({**ob, place: list(c0 + 1e-15), "velocity": list(v), "angular_velocity": list(w)},
                         dt=1 / 30, duration=duration, res=10, size=0.6, **cloth)
    a, b, c = (ic.Simulator(s, adaptive={"enabled": False}).run() for s in (const, keyed, nudged))
    assert a.report["collision"]["contacts"] > 0
    assert np.abs(a.positions[-1] - a.positions[0]).max() > 0.05        # the cloth did move
    roundoff = np.abs(c.positions - a.positions).max()
    # floor: in the box case a contact decided at a borderline (a vertex at exactly the thickness) moves the
    # cloth by 2.3e-8 m whichever way the last bit falls (the nudge reproduces it on the numpy solver path, not
    # on the numba one); a wrong reading of the keys would move it by millimetres
    assert np.abs(b.positions - a.positions).max() <= max(10 * roundoff, 1e-6)


@pytest.mark.parametrize("dt", [1 / 60, 1 / 30], ids=["dt60", "dt30"])
def test_keyframed_sphere_through_a_hanging_cloth_stops_and_comes_back(dt):
    """Out at 5 m/s through the cloth, a stop, back at 5 m/s; keys inside steps (their chords are taken).

    Every step is a frame: no vertex and no point sampled along an edge is ever inside the sphere.
    """
    R = 0.12
    keys = [{"time": 0.0, "center": [0.0, -0.3, 0.0]}, {"time": 0.105, "center": [0.0, 0.225, 0.0]},
            {"time": 0.205, "center": [0.0, 0.225, 0.0]}, {"time": 0.31, "center": [0.0, -0.3, 0.0]}]
    sc = cloth_scene({"shape": "sphere", "radius": R, "keyframes": keys}, dt=dt, duration=0.4, res=12, size=0.6,
                     center=(0, 0, 0), plane="xz", pins=["top_left", "top_right"])
    sim = ic.Simulator(sc, adaptive={"enabled": False})
    traj = sim.run(frame_rate=1 / dt)
    v_depth, e_depth = depths(sim, traj)
    assert v_depth <= TOL and e_depth <= TOL
    assert traj.report["status"] == "ok" and traj.report["collision"]["contacts"] > 0
    centers = np.array([sim.collider.obstacles[0].motion.pose(t)[0] for t in traj.times])
    assert centers[:, 1].max() > 0.2 and centers[-1, 1] == -0.3  # out, and back where it started
    # between frames: a vertex passing the sphere's centre (in the sphere's frame, the chord of each step) goes round it
    assert _passes_around(traj.positions - centers[:, None, :], R)
    # pushed, not crossed: the cloth's middle stays ahead of the sphere's centre in every frame and is carried
    # past where it hung by more than the radius
    mid = np.argmin(np.linalg.norm(sim.model.rest_positions, axis=1))
    assert np.all(traj.positions[1:, mid, 1] > centers[1:, 1])
    assert traj.positions[:, mid, 1].max() > R


def test_readme_keyframes_block_and_example_load_and_run(tmp_path):
    """The scene reference's keyframes block and examples/keyframed_sphere.toml are valid scenes that step."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    block = next(b for b in re.findall(r"```toml\n(.*?)```", (root / "docs" / "scene.md").read_text(), re.S)
                 if "keyframes" in b)
    path = tmp_path / "k.toml"
    path.write_text('[cloth]\nmass = 0.1\nresolution = [6, 6]\ncenter = [0.0, 0.0, 1.0]\nplane = "xz"\n'
                    '[effects]\ngravity = [0.0, 0.0, -9.81]\n' + block)
    for scene in (ic.load_scene(path), ic.load_scene(root / "examples" / "keyframed_sphere.toml")):
        keys = scene.data["obstacles"][0]["keyframes"]
        assert len(keys) == 4 and keys[-1]["center"] == keys[0]["center"]
        sim = ic.Simulator(scene.replace(cloth={"resolution": [6, 6]}))
        sim.step(2)
        c, _ = sim.collider.obstacles[0].motion.pose(sim.time)
        assert c[1] > keys[0]["center"][1]                    # on its way out
