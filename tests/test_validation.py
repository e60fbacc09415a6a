"""Bad input and faults: scene values and mesh files are refused (SceneError naming the key and the value) or
warned about (MeshWarning), never an unrelated exception; failed writes leave previous results intact.

Complements test_scene.py / test_cloth.py / test_cli.py (which cover the basic messages) with the rules added
for the issue "Bad input, faults and hard numerics": huge and non-standard numbers, run-length limits, NumPy
inputs, derived masses and positions, every kind of broken mesh file, and fault injection on output writes.
"""

from __future__ import annotations

import copy
import datetime
import errno
import json
import os
import warnings

import numpy as np
import pytest
import trimesh

import implicit_cloth as ic
from implicit_cloth import cli, cloth
from implicit_cloth import files as icio

INF, NAN = float("inf"), float("nan")


@pytest.fixture
def scene():
    return {
        "simulation": {"integrator": "backward_euler", "dt": 0.01, "duration": 0.5, "frame_rate": 30},
        "cloth": {
            "size": [1.0, 1.0], "resolution": [4, 4], "mass": 0.1, "center": [0.0, 0.0, 1.0],
            "plane": "xz", "pins": ["top_left", "top_right"],
            "springs": {"structural": {"stiffness": 500.0, "damping": 0.1},
                        "shear": {"stiffness": 50.0, "damping": 0.05},
                        "bend": {"stiffness": 5.0, "damping": 0.01}},
        },
        "effects": {"gravity": [0.0, 0.0, -9.81], "drag": 0.1},
    }


def _with(scene, path, value):
    d = copy.deepcopy(scene)
    keys = path.split(".")
    t = d
    for k in keys[:-1]:
        t = t.setdefault(k, {})
    t[keys[-1]] = value
    return d


def _refused(d, expect):
    with pytest.raises(ic.SceneError) as exc:
        ic.Simulator(d)
    msg = str(exc.value)
    assert expect in msg, msg
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- scene values
BAD_VALUES = [
    # numbers: huge ints, strings, tables, lists, booleans, None, dates, non-finite
    ("simulation.dt", 10**400, "simulation.dt: must be a finite number > 0, got 1000000000"),
    ("simulation.dt", "0.01", "simulation.dt: must be a finite number > 0, got '0.01'"),
    ("simulation.dt", 10**5000, "simulation.dt: must be a finite number > 0, got an integer of about 5000 digits"),
    ("simulation.dt", -INF, "simulation.dt: must be a finite number > 0, got -inf"),
    ("simulation.duration", [1.0], "simulation.duration: must be a finite number > 0, got [1.0]"),
    ("simulation.frame_rate", {"value": 30}, "simulation.frame_rate: must be a finite number > 0, got {'value': 30}"),
    ("simulation.frame_rate", None, "simulation.frame_rate: must be a finite number > 0, got None"),
    ("simulation.divergence_factor", 0.5, "simulation.divergence_factor: must be a finite number >= 1, got 0.5"),
    ("simulation.divergence_factor", NAN, "simulation.divergence_factor: must be a finite number >= 1, got nan"),
    ("simulation.integrator", 4, "simulation.integrator: must be one of forward_euler"),
    ("simulation", "fast", "simulation: must be a table, got 'fast'"),
    # run length: a step or frame count that cannot be counted or stored
    ("simulation.dt", 1e-12, "simulation.dt: the run would take 5e+11 steps (duration / dt = 0.5 s / 1e-12 s), "
                             "more than the limit of 1e+09, got 1e-12"),
    ("simulation.dt", 5e-324, "simulation.dt: the run would take inf steps"),
    ("simulation.duration", 1e300, "simulation.duration: the run would take 1e+302 steps"),
    ("solver.tolerance", 0, "solver.tolerance: must be a finite number > 0 and <= 1, got 0"),
    ("solver.tolerance", "1e-3", "solver.tolerance: must be a finite number > 0 and <= 1, got '1e-3'"),
    ("solver.contact_tolerance", 0.0, "solver.contact_tolerance: must be a finite number > 0 and <= 1, got 0.0"),
    ("solver.contact_tolerance", 3, "solver.contact_tolerance: must be a finite number > 0 and <= 1, got 3"),
    ("solver.max_iterations", 0, "solver.max_iterations: must be an integer >= 1 and <= 1000000, got 0"),
    ("solver.max_iterations", 2.5, "solver.max_iterations: must be an integer >= 1 and <= 1000000, got 2.5"),
    ("solver.max_iterations", True, "solver.max_iterations: must be an integer >= 1 and <= 1000000, got True"),
    ("solver.max_iterations", 10**30, "solver.max_iterations: must be an integer >= 1 and <= 1000000, got 1000"),
    ("solver.preconditioner", "jacobi", "solver.preconditioner: must be one of auto, multigrid, block_jacobi"),
    ("solver", [1], "solver: must be a table, got [1]"),
    ("cloth.resolution", [10**6, 10**6], "cloth.resolution: must give at most 16777216 vertices (4096 x 4096), "
                                         "nx * ny = 1000000000000, got [1000000, 1000000]"),
    ("cloth.resolution", [10**20, 2], "cloth.resolution: must give at most 16777216 vertices"),
    ("cloth.resolution", [4.0, 4], "cloth.resolution[0]: must be an integer >= 2, got 4.0"),
    ("cloth.resolution", [4, True], "cloth.resolution[1]: must be an integer >= 2, got True"),
    ("cloth.resolution", 4, "cloth.resolution: must be a list of 2 integers >= 2, got 4"),
    ("cloth.resolution", [4, 4, 4], "cloth.resolution: must be a list of 2 integers >= 2, got [4, 4, 4]"),
    ("cloth.size", [1.0, INF], "cloth.size[1]: must be a finite number > 0, got inf"),
    ("cloth.size", [0.0, 1.0], "cloth.size[0]: must be a finite number > 0, got 0.0"),
    ("cloth.size", "1x1", "cloth.size: must be a list of 2 numbers, got '1x1'"),
    ("cloth.center", [0, 0, None], "cloth.center[2]: must be a finite number, got None"),
    ("cloth.center", [0, 0], "cloth.center: must be a list of 3 numbers, got [0, 0]"),
    ("cloth.velocity", "fast", "cloth.velocity: must be a list of 3 numbers, got 'fast'"),
    ("cloth.velocity", [0, NAN, 0], "cloth.velocity[1]: must be a finite number, got nan"),
    ("cloth.mass", -INF, "cloth.mass: must be a finite number > 0, got -inf"),
    ("cloth.mass", True, "cloth.mass: must be a finite number > 0, got True"),
    ("cloth.mass", datetime.date(2020, 1, 1), "cloth.mass: must be a finite number > 0, got datetime.date(2020, 1, 1)"),
    ("cloth.density", 0.2, "cloth.density: give either cloth.mass or cloth.density, not both"),
    ("cloth.material", "wool", "cloth.material: must be one of cotton, silk, denim, leather, rubber, got 'wool'"),
    ("cloth.plane", ["xz"], "cloth.plane: must be one of xy, xz, yz, got ['xz']"),
    ("cloth.scale", 2.0, "cloth.scale: only used with cloth.mesh"),
    ("cloth.springs", [1], "cloth.springs: must be a table, got [1]"),
    ("cloth.springs.bend", 5.0, "cloth.springs.bend: must be a table, got 5.0"),
    ("cloth.springs.bend.damping", "0.1", "cloth.springs.bend.damping: must be a finite number >= 0, got '0.1'"),
    ("cloth.springs.bend.stiffness", INF, "cloth.springs.bend.stiffness: must be a finite number >= 0, got inf"),
    ("cloth.springs.bend.stifness", 1.0, "cloth.springs.bend.stifness: unknown key (did you mean 'stiffness'?)"),
    ("cloth.pins", [-1], "cloth.pins[0]: must be an integer >= 0, got -1"),
    ("cloth.pins", [1.5], "cloth.pins[0]: must be an integer >= 0, got 1.5"),
    ("cloth.pins", [True], "cloth.pins[0]: must be an integer >= 0, got True"),
    ("cloth.pins", "top_left", "cloth.pins: must be a list of vertex indices, corner names or tables, got 'top_left'"),
    ("cloth.pins", [{"velocity": [0, 0, 1]}], "cloth.pins[0].vertices: missing"),
    ("cloth.pins", [{"vertices": []}], "cloth.pins[0].vertices: must be a non-empty list"),
    ("cloth.pins", [{"vertices": [0], "velocity": [0, 0]}], "cloth.pins[0].velocity: must be a list of 3 numbers"),
    ("cloth.pins", [{"vertices": [0], "speed": 1}], "cloth.pins[0].speed: unknown key"),
    ("cloth.pins", [0, {"vertices": [0], "velocity": [0, 0, 1]}],
     "cloth.pins[1].vertices[0]: vertex 0 is pinned twice with different velocities"),
    ("cloth.pins", [10**30], "cloth.pins[0]: vertex index out of range (the cloth has 16 vertices)"),
    ("cloth.pins", [10**5000], "cloth.pins[0]: vertex index out of range (the cloth has 16 vertices), got an integer"),
    ("effects.drag", -0.1, "effects.drag: must be a finite number >= 0, got -0.1"),
    ("effects.drag", [0.1], "effects.drag: must be a finite number >= 0, got [0.1]"),
    ("effects.gravity", [0, 0, "-9.81"], "effects.gravity[2]: must be a finite number, got '-9.81'"),
    ("effects.gravity", {"z": -9.81}, "effects.gravity: must be a list of 3 numbers, got {'z': -9.81}"),
    ("effects.gravity", np.zeros((1, 3)), "effects.gravity: must be a list of 3 numbers, got array([[0., 0., 0.]])"),
    ("effects.wind", {"speed": 3}, "effects.wind.speed: unknown key (allowed: velocity)"),
    ("effects.wind", [0, 1, 0], "effects.wind: must be a table, got [0, 1, 0]"),
    ("effects.wind", {"velocity": [0, INF, 0]}, "effects.wind.velocity[1]: must be a finite number, got inf"),
    ("effects", 9.81, "effects: must be a table, got 9.81"),
]


def _id(value):
    try:
        return repr(value)[:30]
    except ValueError:   # an int beyond Python's str conversion limit
        return "huge int"


@pytest.mark.parametrize("path,value,expect", BAD_VALUES, ids=[f"{p}={_id(v)}" for p, v, _ in BAD_VALUES])
def test_bad_value_is_a_scene_error_naming_key_and_value(scene, path, value, expect):
    msg = _refused(_with(scene, path, value), expect)
    assert len(msg) < 400   # a huge value is shortened


@pytest.mark.parametrize("edit,expect", [
    (lambda d: d.pop("cloth"), "cloth: missing (a scene needs a [cloth] table)"),
    (lambda d: d["cloth"].pop("mass"), "cloth.mass: missing (give cloth.mass in kg"),
    (lambda d: d["cloth"]["springs"]["shear"].pop("stiffness"), "cloth.springs.shear.stiffness: missing"),
    (lambda d: d["effects"].update(wind={"velocity": [1, 0, 0]}, drag=0.1) or d["effects"].pop("drag"),
     "effects.drag: missing"),
    (lambda d: d["effects"].update(wind={}), "effects.wind.velocity: missing"),
    (lambda d: d.update(extra=1), "extra: unknown key"),
])
def test_missing_required_keys(scene, edit, expect):
    d = copy.deepcopy(scene)
    edit(d)
    _refused(d, expect)


@pytest.mark.parametrize("data", [None, 5, [], "scene.toml", (("cloth", {}),)])
def test_scene_that_is_not_a_table(data):
    with pytest.raises(ic.SceneError, match=r"^scene: must be a table, got "):
        ic.Scene.from_dict(data)


def test_frame_count_limit(scene):
    d = _with(scene, "simulation.dt", 1e-8)
    d["simulation"]["frame_rate"] = 1e9
    _refused(d, "simulation.frame_rate: the run would keep 5e+07 frames (duration x min(frame_rate, 1 / dt)), "
                "more than the limit of 1e+07, got 1000000000.0")
    d["simulation"]["frame_rate"] = 30   # the same dt and duration keep 16 frames: fine
    ic.Scene.from_dict(d)


@pytest.mark.parametrize("edit,expect", [
    # a total mass that underflows per vertex, or a density x area that overflows
    (lambda d: d["cloth"].update(mass=5e-324), "cloth.mass: vertex 0 would get a mass of 0 kg (total 4.94066e-324 kg "
                                               "over 16 vertices), which is not a positive number with a finite "
                                               "inverse, got 5e-324"),
    (lambda d: (d["cloth"].pop("mass"), d["cloth"].update(density=1e300, size=[1e10, 1e10])),
     "cloth.density: vertex 0 would get a mass of inf kg"),
    # positions that overflow
    (lambda d: d["cloth"].update(center=[1.5e308, 0.0, 0.0], size=[1e308, 1.0]),
     "cloth.center: vertex positions are not finite (center + size / 2 overflows), got [1.5e+308, 0.0, 0.0]"),
])
def test_derived_masses_and_positions_are_checked(scene, edit, expect):
    d = copy.deepcopy(scene)
    edit(d)
    _refused(d, expect)


def test_numpy_numbers_and_arrays_are_accepted(scene):
    """NumPy scalars and 1-D arrays validate like Python numbers and lists; the normalised scene holds plain types."""
    d = copy.deepcopy(scene)
    d["simulation"].update(dt=np.float32(0.01), frame_rate=np.int64(30))
    d["cloth"].update(resolution=np.array([4, 4]), size=(1.0, 1.0), center=np.array([0.0, 0.0, 1.0]),
                      mass=np.float64(0.1), pins=np.array([0, 3]))
    d["solver"] = {"max_iterations": np.int32(500)}
    d["effects"]["gravity"] = np.array([0.0, 0.0, -9.81])
    s = ic.Scene.from_dict(d)
    plain = ic.Scene.from_dict(_with(_with(scene, "cloth.pins", [0, 3]), "solver.max_iterations", 500)).data
    assert s.data["cloth"]["resolution"] == [4, 4] and type(s.data["cloth"]["resolution"][0]) is int
    assert s.data["simulation"]["dt"] == pytest.approx(0.01) and type(s.data["simulation"]["dt"]) is float
    assert s.data["effects"] == plain["effects"] and s.data["solver"] == plain["solver"]
    json.dumps(s.data)   # report.json needs plain types
    sim = ic.Simulator(d)
    assert sim.model.pinned.tolist() == [0, 3]
    # numpy booleans are not numbers either
    _refused(_with(scene, "cloth.mass", np.bool_(True)), "cloth.mass: must be a finite number > 0, got")


def test_overrides_are_validated_like_the_file(scene):
    s = ic.Scene.from_dict(scene)
    with pytest.raises(ic.SceneError, match=r"^simulation: overrides must be a table .*, got 5$"):
        s.replace(simulation=5)
    with pytest.raises(ic.SceneError, match=r"^simulation\.frame_rate: must be a finite number > 0, got '30'$"):
        ic.Simulator(scene, frame_rate="30")
    with pytest.raises(ic.SceneError, match=r"^simulation\.dt: the run would take"):
        ic.Simulator(scene, dt=1e-300)
    with pytest.raises(ic.SceneError, match=r"^simulation\.speed: unknown key"):
        ic.Simulator(scene, speed=2.0)
    assert s.data["simulation"]["dt"] == 0.01   # the original scene is untouched


def test_cli_rejects_an_override_beyond_the_run_length_limit(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('[cloth]\nresolution = [3, 3]\nmass = 0.1\n')
    assert cli.main(["run", str(path), "--out", str(tmp_path / "o"), "--duration", "1e300", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("implicit-cloth: error: simulation.duration: the run would take") and err.count("\n") == 1


# --------------------------------------------------------------------------- mesh files
SQUARE = cloth.grid((1.0, 1.0), (4, 4), plane="xy")   # 16 vertices, 18 triangles


def _mesh_scene(path, **cloth_keys):
    return {"cloth": {"mesh": str(path), "mass": 0.5, "pins": [0],
                      "springs": {"structural": {"stiffness": 100.0, "damping": 0.1}, "bend": {"stiffness": 1.0}},
                      **cloth_keys},
            "effects": {"gravity": [0.0, 0.0, -9.81]},
            "simulation": {"dt": 0.01, "duration": 0.05}}


def _obj(tmp_path, verts, faces, name="m.obj"):
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(verts, dtype=float).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _ply(tmp_path, verts, faces, name="m.ply"):
    head = ["ply", "format ascii 1.0", f"element vertex {len(verts)}", "property double x", "property double y",
            "property double z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    body = [" ".join(map(repr, v)) for v in np.asarray(verts, dtype=float).tolist()]
    body += ["3 " + " ".join(map(str, f)) for f in np.asarray(faces).tolist()]
    path = tmp_path / name
    path.write_text("\n".join(head + body) + "\n")
    return path


def _mesh_warnings(path, **cloth_keys):
    """Build and run a mesh cloth; return the MeshWarning messages and the simulator."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim = ic.Simulator(_mesh_scene(path, **cloth_keys))
        traj = sim.run()
    assert traj.report["status"] == "ok" and np.all(np.isfinite(traj.positions))
    return [str(w.message) for w in caught if issubclass(w.category, ic.MeshWarning)], sim


@pytest.mark.parametrize("name,content,expect", [
    ("empty.obj", b"", "cloth.mesh: file is empty, got "),
    ("notes.txt", b"v 0 0 0\n", "cloth.mesh: unsupported mesh format '.txt' (supported: .obj, .ply, .stl, .off, "
                                ".glb, .gltf), got "),
    ("points.xyz", b"0 0 0\n1 0 0\n", "cloth.mesh: unsupported mesh format '.xyz'"),
    ("mesh", b"v 0 0 0\n", "cloth.mesh: no file extension to tell the mesh format (supported: .obj"),
    ("garbage.ply", b"hello\n", "cloth.mesh: cannot read mesh file "),
    ("garbage.off", b"hello\n", "as OFF (ValueError: "),
    ("garbage.glb", b"\x00\x01garbage", "as GLB (ValueError: "),
    ("garbage.obj", b"hello world\n", "cloth.mesh: mesh has no triangles, got "),
    ("lines.obj", b"v 0 0 0\nv 1 0 0\nl 1 2\n", "cloth.mesh: mesh has no triangles, got "),
    ("oob.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n",
     "cloth.mesh: face 1 = [0, 1, 8] refers to vertex 8, which is not in the file (it has 3 vertices, 0 to 2)"),
    ("bad_v.obj", b"v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "cloth.mesh: line 1: a vertex needs three numbers x y z"),
    ("bad_f.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "cloth.mesh: line 4: face corner 'x' is not a vertex"),
    ("zero.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "cloth.mesh: line 4: vertex index 0 (OBJ counts from 1)"),
    ("oob.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "cloth.mesh: cannot read mesh file "),
    ("nan.obj", b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
     "cloth.mesh: vertex 0 has a non-finite coordinate [nan, 0.0, 0.0] (1 such vertices), got "),
])
def test_bad_mesh_file_is_a_scene_error(tmp_path, name, content, expect):
    path = tmp_path / name
    path.write_bytes(content)
    msg = _refused(_mesh_scene(path), expect)
    assert str(path) in msg


def test_face_index_out_of_range_is_a_scene_error(tmp_path):
    """PLY keeps out-of-range indices (trimesh does not check them): they used to raise IndexError in Model."""
    verts = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    path = _ply(tmp_path, verts, [[0, 1, 2], [0, 1, 7]])
    _refused(_mesh_scene(path), "cloth.mesh: face 1 = [0, 1, 7] refers to vertex 7, which is not in the file "
                                "(it has 3 vertices, 0 to 2), got ")
    path = _ply(tmp_path, verts, [[0, 1, 2], [0, 1, -2]], "neg.ply")
    _refused(_mesh_scene(path), "cloth.mesh: face 1 = [0, 1, -2] refers to vertex -2, which is not in the file")


def test_missing_directory_and_unreadable_mesh(tmp_path, monkeypatch):
    _refused(_mesh_scene(tmp_path / "nope.obj"), "cloth.mesh: file not found, got ")
    folder = tmp_path / "folder.obj"
    folder.mkdir()
    _refused(_mesh_scene(folder), "cloth.mesh: not a file (a directory?), got ")
    path = _obj(tmp_path, SQUARE.positions, SQUARE.faces)

    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(cloth, "open", denied, raising=False)   # portable stand-in for chmod 000 (we may be root)
    _refused(_mesh_scene(path), "cloth.mesh: cannot read mesh file (Permission denied), got ")


def test_upper_case_extension_and_scale_overflow(tmp_path):
    path = _obj(tmp_path, SQUARE.positions, SQUARE.faces, "SQUARE.OBJ")
    assert ic.Simulator(_mesh_scene(path)).model.n == 16
    _refused(_mesh_scene(path, scale=1e308, translation=[1.7e308, 0.0, 0.0]),
             "cloth.scale: scaled and translated mesh coordinates are not finite (largest file coordinate 0.5), "
             "got 1e+308")


def test_zero_area_triangles_warn_and_simulate(tmp_path):
    """Two zero-area triangles whose vertices also belong to good triangles: a MeshWarning and a normal run."""
    faces = np.concatenate([SQUARE.faces, [[0, 1, 2], [5, 5, 6]]])   # collinear bottom row; a repeated vertex
    msgs, sim = _mesh_warnings(_obj(tmp_path, SQUARE.positions, faces))
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith("cloth.mesh: 2 zero-area triangles (faces 18, 19; first = [0, 1, 2]); they add no "
                              "mass and no bend springs (file ")
    clean = ic.Simulator(_mesh_scene(_obj(tmp_path, SQUARE.positions, SQUARE.faces, "clean.obj")))
    np.testing.assert_allclose(sim.model.masses, clean.model.masses, rtol=1e-12)
    pairs = sim.model.springs.pairs()
    assert np.all(pairs[:, 0] != pairs[:, 1])        # no spring joins a vertex to itself
    assert len(pairs) == len(clean.model.springs.pairs()) + 1   # [0, 1, 2] adds the structural edge 0-2 only


@pytest.mark.parametrize("extra_faces,extra_verts,expect", [
    # vertex 16 on the edge 0-1: its only triangle has zero area
    ([[0, 16, 1]], [[-0.25, -0.5, 0.0]], "cloth.mesh: vertex 16 is only in zero-area triangles (faces 18), so it "
                                         "would have no mass; fix or remove those triangles (1 such vertices: 16)"),
    ([[16, 16, 3]], [[2.0, 2.0, 0.0]], "cloth.mesh: vertex 16 is only in zero-area triangles (faces 18)"),
    # vertices 16, 17 in no face (a PLY keeps them; trimesh drops them from an OBJ)
    ([], [[2.0, 2.0, 0.0], [3.0, 2.0, 0.0]], "cloth.mesh: vertex 16 is in no triangle (unreferenced), so it would "
                                             "have no mass; remove it from the file (2 such vertices: 16, 17)"),
])
def test_vertex_without_area_names_vertex_and_reason(tmp_path, extra_faces, extra_verts, expect):
    verts = np.concatenate([SQUARE.positions, extra_verts])
    faces = np.concatenate([SQUARE.faces, np.asarray(extra_faces, dtype=int).reshape(-1, 3)])
    _refused(_mesh_scene(_ply(tmp_path, verts, faces)), expect)


def test_every_triangle_zero_area(tmp_path):
    path = _obj(tmp_path, [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], [[0, 1, 2], [1, 2, 3]])
    _refused(_mesh_scene(path), "cloth.mesh: every triangle has zero area (2 triangles), so the cloth would have "
                                "no mass, got ")


def test_duplicate_vertices_warn_and_simulate(tmp_path):
    """Two squares side by side, each with its own copy of the shared seam: warned, simulated unjoined."""
    right = SQUARE.positions + [1.0, 0.0, 0.0]
    verts = np.concatenate([SQUARE.positions, right])
    faces = np.concatenate([SQUARE.faces, SQUARE.faces + 16])
    msgs, sim = _mesh_warnings(_obj(tmp_path, verts, faces))
    assert msgs == [f"cloth.mesh: 4 duplicate vertices (vertex 16 has the coordinates of vertex 3); vertices are "
                    f"not merged, so the cloth is not joined there (file '{tmp_path / 'm.obj'}')"]
    assert sim.model.n == 32


def test_stl_triangle_soup_warns_about_duplicates(tmp_path):
    path = tmp_path / "square.stl"
    trimesh.Trimesh(SQUARE.positions, SQUARE.faces, process=False).export(path)
    msgs, _ = _mesh_warnings(path)
    assert len(msgs) == 1 and msgs[0].startswith("cloth.mesh: 38 duplicate vertices")


def test_non_manifold_edge_warns_and_gets_no_bend_spring(tmp_path):
    """A fin: a third triangle on the edge 5-10 of the square (which two good triangles already share)."""
    verts = np.concatenate([SQUARE.positions, [[0.0, 0.0, 0.5]]])
    faces = np.concatenate([SQUARE.faces, [[5, 10, 16]]])
    msgs, sim = _mesh_warnings(_obj(tmp_path, verts, faces))
    assert len(msgs) == 1 and msgs[0].startswith("cloth.mesh: 1 non-manifold edges (edge 5-10 is in 3 triangles); "
                                                 "they get no bend spring (file ")
    bend = cloth.mesh_springs(faces)["bend"].tolist()
    clean_bend = cloth.mesh_springs(SQUARE.faces)["bend"].tolist()
    assert len(bend) == len(clean_bend) - 1          # the bend spring across 5-10 is gone


def test_cli_prints_mesh_warnings_as_one_line_each(tmp_path, capsys):
    faces = np.concatenate([SQUARE.faces, [[0, 1, 2]]])
    _obj(tmp_path, SQUARE.positions, faces, "flag.obj")
    (tmp_path / "s.toml").write_text('[simulation]\nduration = 0.02\n[cloth]\nmesh = "flag.obj"\nmass = 0.2\n'
                                     '[cloth.springs.structural]\nstiffness = 100.0\n')
    code = cli.main(["run", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--no-progress"])
    assert code == 0
    err = capsys.readouterr().err
    assert err == (f"implicit-cloth: warning: cloth.mesh: 1 zero-area triangles (faces 18; first = [0, 1, 2]); "
                   f"they add no mass and no bend springs (file '{tmp_path / 'flag.obj'}')\n")


def test_cli_bad_mesh_exits_2_with_one_line(tmp_path, capsys):
    (tmp_path / "flag.obj").write_bytes(b"")
    (tmp_path / "s.toml").write_text('[cloth]\nmesh = "flag.obj"\nmass = 0.2\n')
    assert cli.main(["run", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("implicit-cloth: error: cloth.mesh: file is empty, got ") and err.count("\n") == 1


# --------------------------------------------------------------------------- fault injection on writes
ENOSPC = OSError(errno.ENOSPC, "No space left on device")


def _savez_fills_the_disk(file, *args, **kwargs):
    file.write(b"PK\x03\x04 half a zip")   # some bytes reach the temporary file, then the disk is full
    raise OSError(errno.ENOSPC, "No space left on device")


class _FullDisk:
    """A file object that accepts ``budget`` bytes and then fails with ENOSPC (half of a write goes through)."""

    def __init__(self, f, budget):
        self._f, self._budget = f, budget

    def write(self, data):
        if len(data) > self._budget:
            self._f.write(bytes(data)[:self._budget])
            self._budget = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self._budget -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


def _disk_full_on_open_number(monkeypatch, k, budget=10):
    """From the k-th file opened for writing by implicit_cloth.files (1-based), the disk is full."""
    real = os.fdopen
    count = {"n": 0}

    def fdopen(fd, *args, **kwargs):
        f = real(fd, *args, **kwargs)
        count["n"] += 1
        return _FullDisk(f, budget) if count["n"] >= k else f

    monkeypatch.setattr(icio.os, "fdopen", fdopen)


def _small_run():
    return ic.Simulator({"cloth": {"resolution": [3, 3], "mass": 0.1, "pins": [6],
                                   "springs": {"structural": {"stiffness": 50.0}}},
                         "effects": {"gravity": [0, 0, -9.81]}}, duration=0.05).run()


def test_failed_trajectory_save_keeps_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "trajectory.npz"
    first = _small_run()
    first.save(path)
    before = path.read_bytes()
    second = ic.Simulator({"cloth": {"resolution": [4, 4], "mass": 0.1}}, duration=0.02).run()
    monkeypatch.setattr(np, "savez_compressed", _savez_fills_the_disk)
    with pytest.raises(OSError, match="No space left on device"):
        second.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["trajectory.npz"]
    np.testing.assert_array_equal(ic.Trajectory.load(path).positions, first.positions)
    # the same through a file that fails half-way through a write
    _disk_full_on_open_number(monkeypatch, 1, budget=100)
    with pytest.raises(OSError, match="No space left on device"):
        second.save(path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["trajectory.npz"]


def test_failed_json_write_keeps_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "report.json"
    icio.save_json(path, {"status": "ok", "frames": list(range(100))})
    before = path.read_bytes()
    _disk_full_on_open_number(monkeypatch, 1, budget=50)
    with pytest.raises(OSError, match="No space left on device"):
        icio.save_json(path, {"status": "diverged", "frames": list(range(1000))})
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["report.json"]


SCENE_TOML = """\
[simulation]
duration = 0.05
[cloth]
resolution = [4, 4]
mass = 0.1
pins = ["top_left"]
[cloth.springs.structural]
stiffness = 100.0
[effects]
gravity = [0.0, 0.0, -9.81]
"""


@pytest.mark.parametrize("fault", ["savez_compressed", "trajectory_half_written", "report_half_written",
                                   "interrupted"])
def test_cli_second_run_failing_to_write_keeps_the_first_results(tmp_path, monkeypatch, capsys, fault):
    """Run twice into the same --out; the second run's writing fails. Exit 1 (130 for Ctrl-C), the first run's
    trajectory.npz and report.json untouched and loadable, no temporary file left."""
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE_TOML)
    out = tmp_path / "out"
    args = ["run", str(scene), "--out", str(out), "--no-progress"]
    assert cli.main(args) == 0
    npz, js = (out / "trajectory.npz").read_bytes(), (out / "report.json").read_bytes()
    capsys.readouterr()

    if fault == "savez_compressed":
        monkeypatch.setattr(np, "savez_compressed", _savez_fills_the_disk)
    elif fault == "interrupted":
        def interrupted(*args, **kwargs):
            raise KeyboardInterrupt
        monkeypatch.setattr(np, "savez_compressed", interrupted)
    else:   # the disk fills up half-way through the trajectory (1st file written) or the report (2nd)
        k = 1 if fault == "trajectory_half_written" else 2
        real = cli.write_run

        def write_outputs(*a, **kw):
            _disk_full_on_open_number(monkeypatch, k, budget=200)
            return real(*a, **kw)

        monkeypatch.setattr(cli, "write_run", write_outputs)
    code = cli.main(args + ["--duration", "0.1"])
    monkeypatch.undo()

    err = capsys.readouterr().err
    if fault == "interrupted":
        assert code == 130 and err == "implicit-cloth: interrupted\n"
    else:
        assert code == 1
        assert err == f"implicit-cloth: error: cannot write results to '{out}' (No space left on device)\n"
    assert sorted(os.listdir(out)) == ["report.json", "trajectory.npz"]    # no temporary file behind
    assert (out / "trajectory.npz").read_bytes() == npz and (out / "report.json").read_bytes() == js
    report = json.loads(js)
    assert report["steps"] == 5
    assert len(ic.Trajectory.load(out / "trajectory.npz")) == len(report["frames"]["time"])


def test_cli_first_run_failing_to_write_leaves_nothing(tmp_path, monkeypatch, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE_TOML)
    out = tmp_path / "out"
    monkeypatch.setattr(np, "savez_compressed", _savez_fills_the_disk)
    assert cli.main(["run", str(scene), "--out", str(out), "--no-progress"]) == 1
    assert os.listdir(out) == []
