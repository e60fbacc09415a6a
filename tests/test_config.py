"""config/: the input checks, InputError's fields, and the registries that validation reads."""

from __future__ import annotations

import pickle

import pytest

import implicit_cloth as ic
from implicit_cloth.batch import sweep_from_dict
from implicit_cloth.config import EFFECTS, INTEGRATORS, OBSTACLE_SHAPES, PRECONDITIONERS, Registry
from implicit_cloth.config.validate import check_keys, number, vector
from implicit_cloth.errors import NO_VALUE, InputError, SceneError

CLOTH = {"resolution": [3, 3], "mass": 0.1}


def test_input_error_keeps_its_parts_and_reads_as_before():
    e = SceneError("cloth.mass", "must be a finite number > 0", -1)
    assert str(e) == "cloth.mass: must be a finite number > 0, got -1"
    assert (e.path, e.message, e.value) == ("cloth.mass", "must be a finite number > 0", -1)
    assert isinstance(e, InputError) and isinstance(e, ValueError)
    legacy = SceneError("cloth.mesh: file not found, got 'x.obj'")       # one string: path split off
    assert (legacy.path, legacy.value) == ("cloth.mesh", NO_VALUE) and str(legacy).endswith("'x.obj'")
    back = pickle.loads(pickle.dumps(e))                                # batch workers send errors back
    assert type(back) is SceneError and (back.path, back.value) == ("cloth.mass", -1) and str(back) == str(e)


def test_checks_name_the_key_and_the_value():
    with pytest.raises(SceneError, match=r"^a\.b\[1\]: must be a finite number, got nan$"):
        vector("a.b", [0.0, float("nan"), 1.0], 3)
    with pytest.raises(SceneError, match=r"^t\.dtt: unknown key \(did you mean 'dt'\?\)$"):
        check_keys("t", {"dtt": 1}, ("dt", "duration"))
    with pytest.raises(SceneError, match=r"^x: must be a finite number > 0 and <= 1, got True$"):
        number("x", True, lo=0.0, lo_open=True, hi=1.0)


def test_validation_reads_the_registries_each_component_fills():
    assert INTEGRATORS.names() == ic.INTEGRATORS
    assert INTEGRATORS.where(implicit=True) == ("backward_euler", "bdf2")
    assert PRECONDITIONERS.names() == ("auto", "multigrid", "block_jacobi", "multigrid_smoothed")
    assert PRECONDITIONERS.where(default=True) == ("auto",)
    assert OBSTACLE_SHAPES.names() == ("sphere", "box", "cone", "capsule", "plane", "mesh")
    assert EFFECTS.names() == ("gravity", "drag", "aerodynamics", "wind")
    with pytest.raises(SceneError, match=r"^simulation\.integrator: must be one of forward_euler, .*bdf2 "
                                         r"\(did you mean 'bdf2'\?\), got 'bfd2'$"):
        ic.Scene.from_dict({"cloth": CLOTH, "simulation": {"integrator": "bfd2"}})


def test_a_new_obstacle_shape_is_one_registration():
    """Registering a shape (keys + check) is all validation needs: the scene accepts it and checks its keys."""
    def disc(path, d, base_dir):
        return {"radius": number(f"{path}.radius", d.get("radius", 1.0), lo=0.0, lo_open=True)}

    OBSTACLE_SHAPES.register("disc", keys=("radius",), check=disc, place="center")
    try:
        _check_disc()
    finally:
        OBSTACLE_SHAPES.unregister("disc")
    assert "disc" not in OBSTACLE_SHAPES


def _check_disc():
    s = ic.Scene.from_dict({"cloth": CLOTH, "obstacles": [{"shape": "disc", "radius": 0.5}]})
    assert s.data["obstacles"][0]["shape"] == "disc" and s.data["obstacles"][0]["radius"] == 0.5
    with pytest.raises(SceneError, match=r"^obstacles\[0\]\.radius: must be a finite number > 0, got -1$"):
        ic.Scene.from_dict({"cloth": CLOTH, "obstacles": [{"shape": "disc", "radius": -1}]})
    with pytest.raises(SceneError, match=r"^obstacles\[0\]\.size: unknown key"):
        ic.Scene.from_dict({"cloth": CLOTH, "obstacles": [{"shape": "disc", "size": [1, 1, 1]}]})


def test_registry_refuses_keys_it_does_not_take_and_loads_its_providers_once():
    r = Registry("thing", providers=("implicit_cloth.effects",))
    with pytest.raises(ValueError, match=r"thing\.a: required or defaulted keys must be among its keys"):
        r.register("a", keys=("x",), required=("y",))
    r.register("a", keys=("x",))
    assert r.names() == ("a",) and "a" in r and r.choice("p", "a") == "a"


def test_a_sweep_error_is_reworded_from_the_fields(tmp_path):
    (tmp_path / "base.toml").write_text("[cloth]\nresolution = [3, 3]\nmass = 0.1\n")
    with pytest.raises(SceneError, match=r"^sweep\.simulation\.dt\[1\]: must be a finite number > 0, got -1$"):
        sweep_from_dict({"base": "base.toml", "sweep": {"simulation.dt": [0.01, -1]}}, base_dir=tmp_path)
    with pytest.raises(SceneError, match=r"^sweep\.simulation\.dtt: unknown key \(did you mean 'dt'\?\)$"):
        sweep_from_dict({"base": "base.toml", "sweep": {"simulation.dtt": [0.01]}}, base_dir=tmp_path)
