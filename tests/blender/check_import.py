"""Run inside Blender (headless): import a run's USD, glTF/GLB and OBJ + PC2 exports and compare vertex positions.

    blender -b --factory-startup --python-exit-code 1 -P tests/blender/check_import.py -- EXPORT_DIR EXPECTED.npz OUT.json

``EXPECTED.npz`` holds ``positions`` (F, N, 3, simulation z-up metres), ``codes`` (F,) the frames' time codes and
``check`` the frame indices to compare, ``fps`` the frame rate and optionally ``obstacle`` (F, V, 3) the first
obstacle's world vertices at each frame (its bounding-box centre is compared). For every format the world-space vertex positions of the evaluated mesh at
each checked frame are compared with the trajectory (Blender is z-up and metric like the simulation); the largest
deviation per format, in metres, is written to ``OUT.json``.
"""

import json
import sys

import bpy
import numpy as np

if not hasattr(np, "bool"):   # Debian's Blender 3.4 glTF add-on uses np.bool, gone from the system's numpy
    np.bool = bool

args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]   # blender -P, or python with bpy
export_dir, expected_path, out_path = args
expected = np.load(expected_path)
positions, codes, check = expected["positions"], expected["codes"], expected["check"]
result = {"blender": bpy.app.version_string}


def clear():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def world_vertices(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    mesh = ev.to_mesh()
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    m = np.array(ev.matrix_world)
    co = co.reshape(-1, 3)
    return co @ m[:3, :3].T + m[:3, 3]


def cloth_object(prefix):
    found = [o for o in bpy.data.objects if o.type == "MESH" and o.name.startswith(prefix)]
    if not found:
        raise RuntimeError(f"no mesh named {prefix}* among {[o.name for o in bpy.data.objects]}")
    return found[0]


def compare(name, obj, frame_of, obstacle=None):
    """Largest deviation of ``obj``'s evaluated world vertices from the run's at the checked frames (and of the
    obstacle object's bounding-box centre from the obstacle's exported vertices' centre)."""
    worst, worst_ob = 0.0, 0.0
    for f in check:
        bpy.context.scene.frame_set(int(round(frame_of(f))))
        got = world_vertices(obj)
        if got.shape != positions[f].shape:
            raise RuntimeError(f"{name}: {got.shape[0]} vertices, the run has {positions[f].shape[0]}")
        worst = max(worst, float(np.abs(got - positions[f]).max()))
        if obstacle is not None and "obstacle" in expected:
            ob = world_vertices(obstacle)
            want = expected["obstacle"][f]
            worst_ob = max(worst_ob, float(np.abs((ob.min(0) + ob.max(0)) / 2 - (want.min(0) + want.max(0)) / 2).max()))
    result[name] = {"max_error_m": worst, "frames": [int(f) for f in check], "vertices": int(positions.shape[1])}
    if obstacle is not None:
        result[name]["obstacle_max_error_m"] = worst_ob


def obstacle_object():
    found = [o for o in bpy.data.objects if o.type == "MESH" and o.name.startswith("obstacle_0")]
    return found[0] if found else None


def attempt(name, fn):
    try:
        fn()
    except Exception as exc:  # report every format, even after one fails
        result[name] = {"error": f"{type(exc).__name__}: {exc}"}


def usd():
    clear()
    if not bpy.app.build_options.usd:
        raise RuntimeError(f"this Blender ({bpy.app.version_string}) was built without USD support")
    bpy.ops.wm.usd_import(filepath=f"{export_dir}/animation.usd")
    compare("usd", cloth_object("piece_0"), lambda f: codes[f], obstacle_object())


def glb():
    clear()
    bpy.context.scene.render.fps = int(round(float(expected["fps"])))
    bpy.context.scene.render.fps_base = 1.0
    bpy.ops.import_scene.gltf(filepath=f"{export_dir}/animation.glb")
    compare("glb", cloth_object("cloth_piece_0"), lambda f: codes[f] - codes[0], obstacle_object())


def pc2():
    clear()
    bpy.context.scene.render.fps = int(round(float(expected["fps"])))   # frame k of the scene: time k / fps
    bpy.context.scene.render.fps_base = 1.0
    bpy.ops.wm.obj_import(filepath=f"{export_dir}/rest.obj")
    obj = [o for o in bpy.data.objects if o.type == "MESH"][0]
    mod = obj.modifiers.new("cache", "MESH_CACHE")
    mod.cache_format = "PC2"
    mod.filepath = f"{export_dir}/animation.pc2"
    compare("pc2", obj, lambda f: codes[f])


attempt("usd", usd)
attempt("glb", glb)
attempt("pc2", pc2)
with open(out_path, "w") as fh:
    json.dump(result, fh, indent=2)
print(json.dumps(result))
