"""Scene validation: every bad key is named with its value; defaults are filled in."""

import copy

import pytest

import implicit_cloth as ic


def _with(scene, path, value):
    d = copy.deepcopy(scene)
    keys = path.split(".")
    t = d
    for k in keys[:-1]:
        t = t.setdefault(k, {})
    t[keys[-1]] = value
    return d


@pytest.mark.parametrize("path,value,expect", [
    ("cloth.springs.shear.stiffness", -5, "cloth.springs.shear.stiffness: must be a finite number >= 0, got -5"),
    ("simulation.dt", 0, "simulation.dt: must be a finite number > 0, got 0"),
    ("simulation.dt", float("nan"), "simulation.dt: must be a finite number > 0, got nan"),
    ("cloth.mass", -1.0, "cloth.mass: must be a finite number > 0, got -1.0"),
    ("cloth.resolution", [1, 4], "cloth.resolution[0]: must be an integer >= 2, got 1"),
    ("cloth.size", [1.0], "cloth.size: must be a list of 2 numbers, got [1.0]"),
    ("simulation.integrator", "backward_eular", "did you mean 'backward_euler'"),
    ("cloth.plane", "xx", "cloth.plane: must be one of xy, xz, yz"),
    ("effects.gravity", [0, 0], "effects.gravity: must be a list of 3 numbers"),
    ("cloth.pins", ["top_middle"], "cloth.pins[0]: must be one of top_left"),
    ("solver.tolerance", 2.0, "solver.tolerance: must be a finite number > 0 and <= 1, got 2.0"),
    ("simulation.duration", True, "simulation.duration: must be a finite number > 0, got True"),
])
def test_bad_values_name_key_and_value(hanging_scene, path, value, expect):
    with pytest.raises(ic.SceneError) as exc:
        ic.Scene.from_dict(_with(hanging_scene, path, value))
    assert expect in str(exc.value)


def test_scene_error_is_value_error():
    assert issubclass(ic.SceneError, ValueError)


@pytest.mark.parametrize("path,suggest", [
    ("cloth.stifness", None),
    ("cloth.springs.strctural", "structural"),
    ("effects.gravty", "gravity"),
    ("simulaton", "simulation"),
])
def test_unknown_keys_suggest(hanging_scene, path, suggest):
    with pytest.raises(ic.SceneError) as exc:
        ic.Scene.from_dict(_with(hanging_scene, path, 1.0))
    msg = str(exc.value)
    assert msg.startswith(path + ": unknown key")
    if suggest:
        assert f"did you mean '{suggest}'" in msg


def test_wind_without_drag_names_missing_key(hanging_scene):
    d = _with(hanging_scene, "effects.wind", {"velocity": [1.0, 0.0, 0.0]})
    with pytest.raises(ic.SceneError, match=r"^effects\.drag: missing"):
        ic.Scene.from_dict(d)


def test_pin_out_of_range(hanging_scene):
    d = _with(hanging_scene, "cloth.pins", [0, 99])
    with pytest.raises(ic.SceneError, match=r"cloth\.pins\[1\]: vertex index out of range .*16 vertices.*99"):
        ic.Simulator(d)
    d = _with(hanging_scene, "cloth.pins", [{"vertices": [3, 40], "velocity": [0, 0, 1]}])
    with pytest.raises(ic.SceneError, match=r"cloth\.pins\[0\]\.vertices\[1\]: vertex index out of range"):
        ic.Simulator(d)


def test_defaults_and_material(hanging_scene):
    d = copy.deepcopy(hanging_scene)
    del d["simulation"]
    d["cloth"].pop("springs")
    d["cloth"]["material"] = "denim"
    s = ic.Scene.from_dict(d)
    assert s.data["simulation"] == {"integrator": "backward_euler", "dt": 0.01, "duration": 1.0, "frame_rate": 30.0,
                                    "adaptive": {"enabled": True, "max_halvings": 5, "grow_after": 4,
                                                 "max_strain": 1.0, "max_energy_growth": 0.01,
                                                 "retry_unconverged": True, "newton_iterations": 8}}
    denim = ic.MATERIALS["denim"]
    assert s.data["cloth"]["springs"]["bend"] == {"stiffness": denim.bend.stiffness, "damping": denim.bend.damping}
    # a [cloth.springs] entry overrides the preset, per key
    d["cloth"]["springs"] = {"shear": {"stiffness": 7.0}}
    s = ic.Scene.from_dict(d)
    assert s.data["cloth"]["springs"]["shear"] == {"stiffness": 7.0, "damping": denim.shear.damping}


def test_load_scene_errors(tmp_path):
    with pytest.raises(ic.SceneError, match="cannot read scene file"):
        ic.load_scene(tmp_path / "missing.toml")
    empty = tmp_path / "empty.toml"
    empty.write_text("  \n")
    with pytest.raises(ic.SceneError, match="scene file is empty"):
        ic.load_scene(empty)
    bad = tmp_path / "bad.toml"
    bad.write_text("[cloth\nsize = 1")
    with pytest.raises(ic.SceneError, match="not a valid TOML file"):
        ic.load_scene(bad)


def test_simulator_overrides_are_validated(hanging_scene):
    with pytest.raises(ic.SceneError, match=r"simulation\.dt: must be a finite number > 0, got -0.1"):
        ic.Simulator(hanging_scene, dt=-0.1)
    with pytest.raises(ic.SceneError, match=r"simulation\.integrator"):
        ic.Simulator(hanging_scene, integrator="euler")
    sim = ic.Simulator(hanging_scene, integrator="rk4", dt=0.001, solver={"tolerance": 1e-6})
    assert sim.integrator.name == "rk4" and sim.dt == 0.001
