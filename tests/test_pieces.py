"""Several cloths in one scene (``[[cloth]]``): one system of pieces, each with its own shape, material and pins.

Checks: each piece validated and named in errors (``cloth[1].resolution``); vertices in the scene's order and faces
offset; per-piece masses, springs, velocities and pins (corner names per piece); a single ``[[cloth]]`` piece runs
bit for bit like ``[cloth]``; two pieces that never touch move as each does alone (to the solver's tolerance); the
report lists the pieces' vertex ranges; export writes one mesh per piece, in the scene's order.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.cli import main
from implicit_cloth.files import write_run


def _piece(n, center, **kw):
    return {"size": [0.5, 0.5], "resolution": [n, n], "plane": "xy", "center": center, **kw}


def two_pieces() -> dict:
    return {"simulation": {"dt": 0.01, "duration": 0.1, "frame_rate": 100},
            "solver": {"tolerance": 1e-8},
            "cloth": [_piece(6, [0.0, 0.0, 1.0], material="cotton", pins=["top_left", "top_right"]),
                      _piece(5, [2.0, 0.0, 1.0], material="silk", mass=0.02, velocity=[0.0, 0.0, 0.5],
                             pins=[{"vertices": ["bottom_left", 1], "velocity": [0.1, 0.0, 0.0]}])],
            "effects": {"gravity": [0.0, 0.0, -9.81]}}


def test_pieces_are_numbered_in_order_with_their_own_masses_springs_and_pins():
    sim = ic.Simulator(two_pieces())
    m = sim.model
    assert m.pieces == [(0, 36), (36, 61)] and m.n == 61
    assert m.faces.min() == 0 and m.faces[: 50].max() < 36 and m.faces[50:].min() == 36
    assert m.piece_faces == [(0, 50), (50, 82)]
    assert np.allclose(m.masses[36:], 0.02 / 25)
    assert np.allclose(m.masses[:36], ic.MATERIALS["cotton"].density * 0.25 / 36)
    # piece 1's pins: its corner and its vertex 1, offset by piece 0's 36 vertices; with piece 1's velocity
    assert sorted(m.pinned.tolist()) == [30, 35, 36, 37]
    assert np.allclose(m.pin_velocity[np.isin(m.pinned, [36, 37])], [0.1, 0.0, 0.0])
    assert np.allclose(sim.velocities[38:], [0.0, 0.0, 0.5]) and np.allclose(sim.velocities[:30], 0.0)
    s = m.springs
    in1 = s.i >= 36
    assert np.all((s.j >= 36) == in1)                      # no spring joins two pieces
    k_str = s.k[s.kinds["structural"]]
    assert set(np.unique(k_str[~in1[s.kinds["structural"]]])) == {ic.MATERIALS["cotton"].structural.stiffness}
    assert set(np.unique(k_str[in1[s.kinds["structural"]]])) == {ic.MATERIALS["silk"].structural.stiffness}


@pytest.mark.parametrize("key, value, message", [
    ("resolution", [1, 4], r"cloth\[1\]\.resolution\[0\]: must be an integer >= 2, got 1"),
    ("pins", [99], r"cloth\[1\]\.pins\[0\]: vertex index out of range \(the piece has 25 vertices\), got 99"),
    ("pins", ["top_middle"], r"cloth\[1\]\.pins\[0\]: must be one of"),
    ("material", "tweed", r"cloth\[1\]\.material: must be one of"),
    ("mesh", "missing.obj", r"cloth\[1\]\.(size|mesh)"),
    ("colour", 1, r"cloth\[1\]\.colour: unknown key"),
])
def test_errors_name_the_piece(key, value, message):
    d = two_pieces()
    d["cloth"][1][key] = value
    with pytest.raises(ic.SceneError, match=message):
        ic.Simulator(d)


def test_a_missing_mesh_piece_is_named(tmp_path):
    d = two_pieces()
    d["cloth"][1] = {"mesh": str(tmp_path / "missing.obj"), "mass": 0.1}
    with pytest.raises(ic.SceneError, match=r"^cloth\[1\]\.mesh: file not found"):
        ic.Simulator(d)
    d["cloth"] = []
    with pytest.raises(ic.SceneError, match=r"^cloth: must be a table or a non-empty array"):
        ic.Simulator(d)


def test_one_piece_as_an_array_runs_bit_for_bit_like_a_table():
    d = two_pieces()
    one = dict(d, cloth=d["cloth"][0])
    arr = dict(d, cloth=[d["cloth"][0]])
    a, b = ic.Simulator(one).run(), ic.Simulator(arr).run()
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.faces, b.faces)
    assert "pieces" not in a.report and b.report["pieces"] == [{"vertices": [0, 36], "faces": [0, 50]}]


def test_pieces_apart_move_as_each_alone():
    d = two_pieces()
    both = ic.Simulator(d).run()
    for k, (a, b) in enumerate([(0, 36), (36, 61)]):
        alone = ic.Simulator(dict(d, cloth=[d["cloth"][k]])).run()
        assert np.allclose(both.positions[:, a:b], alone.positions, atol=1e-6)
    assert both.report["status"] == "ok"
    assert both.report["pieces"] == [{"vertices": [0, 36], "faces": [0, 50]}, {"vertices": [36, 61], "faces": [50, 82]}]


def test_the_normalised_scene_loads_back_as_it_ran():
    s = ic.Scene.from_dict(two_pieces())
    again = ic.Scene(copy.deepcopy(s.data))
    assert again.data == s.data
    assert again.data["cloth"][1]["pins"][0]["paths"][0] == "cloth[1].pins[0].vertices[0]"


def test_export_writes_one_mesh_per_piece_in_order(tmp_path):
    sim = ic.Simulator(two_pieces())
    traj = sim.run()
    run = tmp_path / "run"
    run.mkdir()
    write_run(run, traj, sim.scene.data)
    assert json.loads((run / "report.json").read_text())["pieces"][1]["vertices"] == [36, 61]
    assert main(["export", str(run), "--format", "gltf", "--out", str(tmp_path / "gl")]) == 0
    doc = json.loads((tmp_path / "gl" / "animation.gltf").read_text())
    names = [m["name"] for m in doc["meshes"]]
    assert names[:2] == ["cloth_piece_0", "cloth_piece_1"]
    # piece 1 is the smaller one: in the scene's order, not largest first
    assert doc["meshes"][1]["extras"]["sourceVertexIndex"][0] == 36
    from implicit_cloth.results import read_run

    r = read_run(run)
    assert [len(p) for p in r.pieces()] == [36, 25]
    assert r.uvs().shape == (61, 2) and np.allclose(r.rest_positions(), sim.model.rest_positions)
