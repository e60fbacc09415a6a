"""export: USD, PC2 + rest OBJ, glTF/GLB morph-target animation, OBJ/PLY per frame; each read back and compared
with the trajectory at every frame (float32 files: to 1e-6 m), obstacles placed by the collision code's motion."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.cli import main
from implicit_cloth.files import write_run

trimesh = pytest.importorskip("trimesh")

F32 = 2e-6          # m: float32 rounding of coordinates of order 1 m

#: z-up (simulation) to y-up, written out independently of the package's constant
YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _run(tmp_path, scene, name="run"):
    sim = ic.Simulator(scene)
    traj = sim.run()
    out = tmp_path / name
    out.mkdir()
    write_run(out, traj, sim.scene.data)
    return out


@pytest.fixture(scope="module")
def moving_run(tmp_path_factory):
    """A 6 x 6 hanging cloth pushed by a keyframed, turning box, 0.12 s at 100 Hz (13 frames)."""
    scene = {
        "simulation": {"integrator": "backward_euler", "dt": 0.01, "duration": 0.12, "frame_rate": 100},
        "cloth": {"size": [1.0, 1.0], "resolution": [6, 6], "mass": 0.1, "center": [0.0, 0.0, 1.0],
                  "plane": "xz", "pins": ["top_left", "top_right"],
                  "springs": {"structural": {"stiffness": 500.0, "damping": 0.1},
                              "shear": {"stiffness": 50.0, "damping": 0.05}}},
        "effects": {"gravity": [0.0, 0.0, -9.81]},
        "obstacles": [{"shape": "box", "size": [0.2, 0.2, 0.2], "keyframes": [
            {"time": 0.0, "center": [0.0, -0.4, 0.9]},
            {"time": 0.12, "center": [0.0, 0.1, 0.9], "rotation": [0.0, 0.0, 1.0]}]},
            {"shape": "plane", "point": [0.0, 0.0, 0.0]}],
    }
    return _run(tmp_path_factory.mktemp("export"), scene)


def _traj(run_dir):
    with np.load(run_dir / "trajectory.npz") as z:
        return z["positions"], z["times"], z["faces"]


def _box_pose(run_dir, t):
    """The collision code's pose of the run's first obstacle (built from the stored scene as the Collider does)."""
    from implicit_cloth.collision.shapes import build

    spec = json.loads((run_dir / "report.json").read_text())["scene"]["obstacles"][0]
    _, motion = build(spec)
    return motion.pose(t)


# --------------------------------------------------------------------------- USD
def test_usd_points_normals_and_obstacle_transforms_at_every_frame(moving_run, tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    pos, times, faces = _traj(moving_run)
    assert main(["export", str(moving_run), "--format", "usd", "--out", str(tmp_path)]) == 0
    stage = Usd.Stage.Open(str(tmp_path / "animation.usd"))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 100.0 and stage.GetFramesPerSecond() == 100.0
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == pytest.approx(12.0)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth/piece_0"))
    assert mesh and not stage.GetPrimAtPath("/World/cloth/piece_1")
    src = np.array(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("sourceVertexIndex").Get())
    np.testing.assert_array_equal(src, np.arange(36))                         # one piece: the run's numbering
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), faces)
    samples = mesh.GetPointsAttr().GetTimeSamples()
    np.testing.assert_allclose(samples, times * 100.0, atol=1e-9)
    for k, code in enumerate(samples):
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(code)), pos[k], atol=F32)
        n = np.array(mesh.GetNormalsAttr().Get(code))
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # a grid cloth's normals: (unit) across the sheet, orthogonal to its edges
    e = pos[0][1] - pos[0][0]
    assert np.abs(np.array(mesh.GetNormalsAttr().Get(0.0)) @ (e / np.linalg.norm(e))).max() < 1e-5
    box = stage.GetPrimAtPath("/World/obstacles/obstacle_0_box")
    xf = UsdGeom.Xformable(box)
    local = np.array(UsdGeom.Mesh(box).GetPointsAttr().Get())
    np.testing.assert_allclose(np.abs(local), 0.1, atol=1e-7)                # the box's corners, local frame
    for t in times:
        m = np.array(xf.ComputeLocalToWorldTransform(float(t * 100.0)))
        world = local @ m[:3, :3] + m[3, :3]                                  # USD: row vectors
        c, R = _box_pose(moving_run, t)
        np.testing.assert_allclose(world, local @ R.T + c, atol=1e-6)
    assert stage.GetPrimAtPath("/World/obstacles/obstacle_1_plane")


# --------------------------------------------------------------------------- PC2
def _obj_vertices(path):
    v = [line.split()[1:4] for line in Path(path).read_text().splitlines() if line.startswith("v ")]
    return np.array(v, float)


def test_pc2_and_rest_obj_read_back_at_every_frame(moving_run, tmp_path):
    pos, times, faces = _traj(moving_run)
    assert main(["export", str(moving_run), "--format", "pc2", "--out", str(tmp_path)]) == 0
    data = (tmp_path / "animation.pc2").read_bytes()
    magic, version, n, start, rate, samples = struct.unpack("<12siiffi", data[:32])
    assert (magic, version, n, samples) == (b"POINTCACHE2\0", 1, 36, len(pos))
    assert (start, rate) == (0.0, pytest.approx(1.0))
    pts = np.frombuffer(data[32:], "<f4").reshape(samples, n, 3)
    np.testing.assert_allclose(pts, pos @ YUP.T, atol=F32)                   # y-up, every frame
    np.testing.assert_allclose(_obj_vertices(tmp_path / "rest.obj"), pos[0] @ YUP.T, atol=1e-8)
    from implicit_cloth.export.meshes import read_pc2

    back, _, _ = read_pc2(tmp_path / "animation.pc2")
    np.testing.assert_allclose(back, pos, atol=F32)


@pytest.fixture(scope="module")
def uneven_run(tmp_path_factory):
    """The hanging example's time line (dt 0.01 s, 30 frames a second: frames kept on the nearest step, 0, 0.03,
    0.07, 0.1, ... s) on a small cloth, 0.5 s (16 frames)."""
    scene = ic.load_scene(Path(__file__).parents[1] / "examples" / "hanging.toml").data
    scene["simulation"]["duration"] = 0.5
    scene["cloth"]["resolution"] = [6, 6]
    return _run(tmp_path_factory.mktemp("export_uneven"), scene)


def _pc2_times(path, fps):
    """Each sample's time as a reader honouring the header plays it: (start + k rate) / fps."""
    from implicit_cloth.export.meshes import read_pc2

    pts, start, rate = read_pc2(path)
    return (start + rate * np.arange(len(pts))) / fps, pts


def test_pc2_header_reproduces_the_frame_times_of_steps_not_dividing_the_frames(uneven_run, tmp_path):
    """The samples play at the kept frames' times (to half a step, where the run kept them) and the last one at
    the run's end: the header's rate is one frame at the run's 30 frames a second, not the first gap's 0.9."""
    from implicit_cloth.results import read_run

    pos, times, _ = _traj(uneven_run)
    assert np.diff(times).min() < np.diff(times).max() - 0.005          # the kept frames are unevenly spaced
    run = read_run(uneven_run)
    assert run.fps == 30.0
    assert main(["export", str(uneven_run), "--format", "pc2", "--out", str(tmp_path)]) == 0
    t, pts = _pc2_times(tmp_path / "animation.pc2", run.fps)
    assert struct.unpack("<ff", (tmp_path / "animation.pc2").read_bytes()[20:28]) == (0.0, 1.0)
    assert len(t) == len(times) == 16
    np.testing.assert_allclose(t, times, atol=0.005 + 1e-9)              # half a step
    np.testing.assert_allclose(t[-1], 0.5, rtol=1e-6)                    # 0.5 s plays in 0.5 s
    np.testing.assert_allclose(pts, pos, atol=F32)
    # every third frame: start 3, rate 3 frames
    assert main(["export", str(uneven_run), "--format", "pc2", "--out", str(tmp_path / "thirds"),
                 "--frames", "3", "6", "9", "12", "15"]) == 0
    t, _ = _pc2_times(tmp_path / "thirds" / "animation.pc2", run.fps)
    np.testing.assert_allclose(t, times[3::3], atol=0.005 + 1e-9)
    np.testing.assert_allclose(t, [0.1, 0.2, 0.3, 0.4, 0.5], rtol=1e-6)


def test_pc2_refuses_unevenly_chosen_frames(uneven_run, tmp_path, capsys):
    assert main(["export", str(uneven_run), "--format", "pc2", "--out", str(tmp_path), "--frames", "0", "1", "5"]) == 2
    err = capsys.readouterr().err
    assert "--frames: a PC2 point cache holds evenly spaced samples" in err and "[0, 1, 5]" in err
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- glTF
def _glb(path):
    data = Path(path).read_bytes()
    magic, version, total = struct.unpack("<4sII", data[:12])
    assert (magic, version, total) == (b"glTF", 2, len(data))
    jlen, jtype = struct.unpack("<I4s", data[12:20])
    assert jtype == b"JSON"
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack("<I4s", data[20 + jlen:28 + jlen])
    assert btype == b"BIN\0"
    return doc, data[28 + jlen:28 + jlen + blen]


def _accessor(doc, blob, k):
    acc = doc["accessors"][k]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = {5126: "<f4", 5125: "<u4"}[acc["componentType"]]
    a = np.frombuffer(blob, dtype, count=acc["count"] * width, offset=view["byteOffset"])
    return a.reshape(acc["count"], width) if width > 1 else a


def _check_gltf(doc, blob, pos, times, faces, run_dir):
    mesh = doc["meshes"][0]
    prim = mesh["primitives"][0]
    base = _accessor(doc, blob, prim["attributes"]["POSITION"])
    np.testing.assert_array_equal(_accessor(doc, blob, prim["indices"]).reshape(-1, 3), faces)
    assert mesh["extras"]["sourceVertexIndex"] == list(range(36))
    anim = doc["animations"][0]
    weights = next(c for c in anim["channels"] if c["target"]["path"] == "weights")
    sampler = anim["samplers"][weights["sampler"]]
    t = _accessor(doc, blob, sampler["input"])
    w = _accessor(doc, blob, sampler["output"]).reshape(len(t), -1)
    np.testing.assert_allclose(t, times - times[0], atol=1e-6)
    for k in range(len(pos)):       # the shape at frame k's time: base + weights . targets, back to z-up
        shape = base + sum(w[k, j] * _accessor(doc, blob, tg["POSITION"]) for j, tg in enumerate(prim["targets"]))
        np.testing.assert_allclose(shape @ YUP, pos[k], atol=F32)
    node = next(n for n in doc["nodes"] if n["name"] == "obstacle_0_box")
    ch = {c["target"]["path"]: anim["samplers"][c["sampler"]] for c in anim["channels"]
          if doc["nodes"][c["target"]["node"]] is node}
    from scipy.spatial.transform import Rotation

    tr, rot = _accessor(doc, blob, ch["translation"]["output"]), _accessor(doc, blob, ch["rotation"]["output"])
    for k, tk in enumerate(times):
        c, R = _box_pose(run_dir, tk)
        np.testing.assert_allclose(tr[k] @ YUP, c, atol=1e-6)
        np.testing.assert_allclose(YUP.T @ Rotation.from_quat(rot[k]).as_matrix(), R, atol=1e-6)


def test_glb_morph_target_animation_reproduces_every_frame(moving_run, tmp_path):
    pos, times, faces = _traj(moving_run)
    assert main(["export", str(moving_run), "--format", "glb", "--out", str(tmp_path)]) == 0
    doc, blob = _glb(tmp_path / "animation.glb")
    assert doc["asset"]["version"] == "2.0"
    _check_gltf(doc, blob, pos, times, faces, moving_run)
    scene = trimesh.load(tmp_path / "animation.glb")                        # another reader opens it too
    assert "cloth_piece_0" in scene.geometry


def test_gltf_text_with_its_buffer(moving_run, tmp_path):
    pos, times, faces = _traj(moving_run)
    assert main(["export", str(moving_run), "--format", "gltf", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "animation.gltf").read_text())
    assert doc["buffers"][0]["uri"] == "animation.bin"
    _check_gltf(doc, (tmp_path / "animation.bin").read_bytes(), pos, times, faces, moving_run)


# --------------------------------------------------------------------------- per-frame meshes
def test_obj_per_frame_has_normals_and_uvs_and_ply_has_normals(moving_run, tmp_path):
    pos, _, faces = _traj(moving_run)
    assert main(["export", str(moving_run), "--format", "obj", "--frames", "0", "-1", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "frame_0012.obj").read_text()
    lines = text.splitlines()
    assert sum(ln.startswith("vt ") for ln in lines) == 36 and sum(ln.startswith("vn ") for ln in lines) == 36
    assert "f 1/1/1 2/2/2 8/8/8" in lines
    np.testing.assert_allclose(_obj_vertices(tmp_path / "frame_0012.obj"), pos[-1] @ YUP.T, atol=1e-8)
    assert main(["export", str(moving_run), "--format", "ply", "--frames", "3", "--out", str(tmp_path)]) == 0
    m = trimesh.load(tmp_path / "frame_0003.ply", process=False)
    np.testing.assert_allclose(m.vertices, pos[3], atol=1e-6)                 # PLY keeps z-up
    assert b"property float nx" in (tmp_path / "frame_0003.ply").read_bytes()[:1000]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_export_errors_are_one_line(moving_run, tmp_path, capsys):
    assert main(["export", str(moving_run), "--format", "stl"]) == 2
    assert "--format: must be one of usd, pc2, glb, gltf, obj, ply, got 'stl'" in capsys.readouterr().err
    assert main(["export", str(moving_run), "--frames", "13"]) == 2
    assert "--frames[0]: frame index out of range (the run has 13 frames" in capsys.readouterr().err
    assert main(["export", str(moving_run), "--format", "glb", "--frames", "3", "1"]) == 2
    assert "--frames: an animation needs its frames in increasing order" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "nothing")]) == 2
    assert "RUN_DIR: no trajectory.npz" in capsys.readouterr().err


# --------------------------------------------------------------------------- Blender (skipped without it)
def _blender() -> list[str] | None:
    """The command that runs the check script: ``blender -b ... -P``, or a Python with the ``bpy`` module
    named by IMPLICIT_CLOTH_BPY_PYTHON."""
    py = os.environ.get("IMPLICIT_CLOTH_BPY_PYTHON")
    if py:
        return [py]
    exe = shutil.which("blender")
    return [exe, "-b", "--factory-startup", "--python-exit-code", "1", "-P"] if exe else None


@pytest.mark.slow
def test_blender_imports_the_exports_headless(moving_run, tmp_path):
    cmd = _blender()
    if cmd is None:
        pytest.skip("Blender is not installed (apt-get install blender) and IMPLICIT_CLOTH_BPY_PYTHON is unset")
    from implicit_cloth.results import read_run

    for fmt in ("usd", "glb", "pc2"):
        assert main(["export", str(moving_run), "--format", fmt, "--out", str(tmp_path)]) == 0
    run = read_run(moving_run)
    box = run.obstacles()[0]
    np.savez(tmp_path / "expected.npz", positions=run.positions, codes=run.time_codes(),
             check=np.array([0, 4, 7, 12]), fps=run.fps, obstacle=np.array([box.world(t) for t in run.times]))
    script = Path(__file__).parent / "blender" / "check_import.py"
    sep = ["--"] if "-P" in cmd else []
    proc = subprocess.run([*cmd, str(script), *sep, str(tmp_path), str(tmp_path / "expected.npz"),
                           str(tmp_path / "blender.json")], capture_output=True, text=True, timeout=300)
    assert (tmp_path / "blender.json").is_file(), proc.stdout[-2000:] + proc.stderr[-2000:]
    result = json.loads((tmp_path / "blender.json").read_text())
    print(json.dumps(result))
    for fmt in ("glb", "pc2", "usd"):
        r = result[fmt]
        if fmt == "usd" and "built without USD" in r.get("error", ""):
            continue                              # Debian's Blender 3.4 has no USD importer
        assert "error" not in r, r
        assert r["max_error_m"] < 1e-5, r
        assert r.get("obstacle_max_error_m", 0.0) < 1e-5, r
    if "error" in result["usd"]:
        pytest.skip(f"USD not checked in Blender: {result['usd']['error']}")


@pytest.mark.slow
def test_blender_plays_the_pc2_of_uneven_steps_at_the_frame_times(uneven_run, tmp_path):
    """In Blender's Mesh Cache modifier, the scene at the run's frame rate shows frame f of the hanging example's
    time line at the scene frame of its time (``round(times[f] * fps)``)."""
    cmd = _blender()
    if cmd is None:
        pytest.skip("Blender is not installed (apt-get install blender) and IMPLICIT_CLOTH_BPY_PYTHON is unset")
    from implicit_cloth.results import read_run

    for fmt in ("usd", "glb", "pc2"):       # the check script imports all three; only PC2 is checked here
        assert main(["export", str(uneven_run), "--format", fmt, "--out", str(tmp_path)]) == 0
    run = read_run(uneven_run)
    np.savez(tmp_path / "expected.npz", positions=run.positions, codes=run.time_codes(),
             check=np.array([1, 2, 7, 15]), fps=run.fps)
    script = Path(__file__).parent / "blender" / "check_import.py"
    sep = ["--"] if "-P" in cmd else []
    proc = subprocess.run([*cmd, str(script), *sep, str(tmp_path), str(tmp_path / "expected.npz"),
                           str(tmp_path / "blender.json")], capture_output=True, text=True, timeout=300)
    assert (tmp_path / "blender.json").is_file(), proc.stdout[-2000:] + proc.stderr[-2000:]
    r = json.loads((tmp_path / "blender.json").read_text())["pc2"]
    assert "error" not in r, r
    assert r["max_error_m"] < 1e-5, r

