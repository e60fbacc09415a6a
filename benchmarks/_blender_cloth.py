"""Blender 3.4's cloth on the benchmark scenes of ``vs_blender.py``; run inside Blender, prints one RESULT line.

    blender -b --factory-startup -noaudio --python benchmarks/_blender_cloth.py -- --scene hanging --n 64
    blender -b --factory-startup -noaudio --python benchmarks/_blender_cloth.py -- --scene crumple --n 32 \\
        --quality 2 --save /tmp/crumple_32.npy

The scenes, in SI units (the same as ``vs_blender.scene``), a 1 m x 1 m cloth of n x n vertices (vertex
``j n + i``: column i along the first axis, row j along the second, as implicit_cloth's grid), dt = 1/60 s:

* "hanging" / "drape": in the xy plane, 0.1 kg, springs k = 1000 (structural) / 333.3 (shear) / 10 (bend) N/m,
  damping 0.01 N*s/m, 2 s (120 frames). "hanging": the two corners of the y = +0.5 row pinned, at z = 0.
  "drape": no pins, at z = 0.5 over a sphere r = 0.3 at the origin (a UV sphere of 64 x 32).
* "crumple" (``self_collision.crumple``): cotton (0.15 kg; k = 5000 / 500 / 20 N/m, damping 1.0 / 0.5 N*s/m
  structural / shear) in the xz plane, centre 0.62 m up, dropped onto the floor z = 0 (a 3 m grid of 5 cm
  cells: one large quad lets a sheet sink) and a rod of radius 3 cm along y at x = 0.1 m, 4 cm up (a cylinder
  of 64 sides, 2 m long), self-collision on, 1.5 s (90 frames).

Contact distance: ours keeps ``thickness`` = 5 mm; Blender's obstacle contact is at the cloth's
``distance_min`` plus the obstacle's ``thickness_outer``, each set to the thickness (10 mm in all, the drape's
mapping since the peer scene), and its self-contact at twice ``self_distance_min``, set to half the thickness
(5 mm between layers). Friction: Blender's obstacle friction is the collision object's ``cloth_friction``
times 0.01 and its self-friction ``self_friction`` times 0.01 (``collision.c``), so mu = 0.3 is 30; the
cloth's own collision ``friction`` has no effect in 3.4 (a 16² drape ends bit-identical with 0 and 80, and
changes with the sphere's ``cloth_friction``).

Blender's units (checked against the 3.4 source, ``cloth_calc_force``): gravity is scaled by 0.001, a
spring's k is its stiffness over the average structural spring length, damping and air drag are not
mass-scaled, and its time unit is a frame times ``time_scale``. With ``T_u = sqrt(0.001)`` s the internal
units are SI: ``time_scale = (1/60) / T_u``, 60 fps, ``quality`` = steps per frame (default ``(1/60) / dt``),
vertex mass ``M / n^2``, tension = compression = ``k_s L / 1000``, shear ``k_sh L / 1000``, spring damping
``kd / (1000 T_u)`` (``L = 1 / (n - 1)``). Free fall checks it: z(1/6 s) = 0.3501 m, the implicit-Euler value
at dt = 1/60 s.

Bending model (``--bending``, default angular): with ``LINEAR`` Blender's structural springs take no
compression (``SIM_mass_spring_force_spring_linear`` acts in compression only when the
``RESIST_SPRING_COMPRESS`` flag is set, which no Python property sets, and never for shear springs), and its
bending springs act in compression only (Choi-Ko); bending ``20 L k_b / 1000``. With ``ANGULAR`` a structural
spring in compression is a linear spring of ``compression_stiffness`` (the Choi-Ko curve lies below it), set
equal to the tension, and bending is a dihedral-angle spring on each edge whose moment is
``bending_stiffness * 0.1 * L * L / 2`` per radian (internal units) where ours' bend springs (every other
vertex, linear in length) give a moment ``k_b L^2 theta^3 / 8`` at a hinge angle theta: no linear mapping
exists, so the two moments are matched at theta = 0.5 rad, ``bending_stiffness = 0.0025 k_b 0.5^2``. Bending
damping is 0 in both models (ours' 0.1 N*s/m on cotton's bend springs has no counterpart).

Blender's solver is one thread, its CG capped at 100 iterations and a 1e-2 residual. Timed: the
``frame_set`` calls of frames 2 to the last (cloth modifier and depsgraph); start-up, frame 1 and the reading
of positions not. ``--save PATH.npy`` writes every frame's positions (frames x n^2 x 3, float32; frame 1, the
start, first) for ``vs_blender.py``'s judge.
"""

import argparse
import json
import math
import sys
import time

import bpy
import numpy as np

G = 9.81
FPS = 60
T_U = math.sqrt(0.001)
THICKNESS = 0.005           # ours' collision.thickness in the drape and the crumple
BEND_THETA = 0.5            # ANGULAR bending: the hinge angle (rad) where its moment matches ours' bend springs'

# per scene: mass (kg), (k, kd) of structural / shear / bend springs, plane, centre, duration (s)
PEER = {"mass": 0.1, "structural": (1000.0, 0.01), "shear": (1000.0 / 3.0, 0.01), "bend": (10.0, 0.0)}
COTTON = {"mass": 0.15, "structural": (5.0e3, 1.0), "shear": (5.0e2, 0.5), "bend": (2.0e1, 0.1)}
SCENES = {
    "hanging": {**PEER, "plane": "xy", "center": (0.0, 0.0, 0.0), "duration": 2.0},
    "drape": {**PEER, "plane": "xy", "center": (0.0, 0.0, 0.5), "duration": 2.0},
    "crumple": {**COTTON, "plane": "xz", "center": (0.0, 0.0, 0.62), "duration": 1.5},
}
SPHERE_R = 0.3
ROD_R, ROD_X, ROD_Z, ROD_LEN = 0.03, 0.1, 0.04, 2.0
FRICTION = 0.3

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
ap = argparse.ArgumentParser()
ap.add_argument("--scene", default="hanging", choices=sorted(SCENES))
ap.add_argument("--n", type=int, default=32)
ap.add_argument("--dt", type=float, default=1 / 60)
ap.add_argument("--quality", type=int, default=None, help="Blender's steps per frame (default (1/60) / dt)")
ap.add_argument("--collision-quality", type=int, default=None, help="Blender's collision_quality (default its own)")
ap.add_argument("--duration", type=float, default=None, help="s (default: the scene's)")
ap.add_argument("--bending", default="angular", choices=["angular", "linear"])
ap.add_argument("--save", default=None, help="write every frame's positions to this .npy")
a = ap.parse_args(argv)
sp = SCENES[a.scene]
n = a.n
quality = a.quality or max(1, int(round((1.0 / FPS) / a.dt)))
frames = int(round((a.duration or sp["duration"]) * FPS))

bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.fps, sc.render.fps_base = FPS, 1.0
sc.frame_start, sc.frame_end = 1, frames + 1
sc.use_gravity = True
sc.gravity = (0.0, 0.0, -G)

# implicit_cloth's grid: vertex j * n + i, u = column i along the plane's first axis, v = row j along its second
ii, jj = np.meshgrid(np.arange(n), np.arange(n))
ax = {"xy": (0, 1), "xz": (0, 2)}[sp["plane"]]
P = np.zeros((n * n, 3))
P[:, ax[0]] = ii.ravel() / (n - 1) - 0.5
P[:, ax[1]] = jj.ravel() / (n - 1) - 0.5
P += np.asarray(sp["center"])
quads = [(j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i) for j in range(n - 1) for i in range(n - 1)]
me = bpy.data.meshes.new("cloth")
me.from_pydata(P.tolist(), [], quads)
me.update()
ob = bpy.data.objects.new("cloth", me)
sc.collection.objects.link(ob)
if a.scene == "hanging":
    vg = ob.vertex_groups.new(name="pin")
    vg.add([(n - 1) * n, n * n - 1], 1.0, "REPLACE")

L = 1.0 / (n - 1)
(ks, ds), (ksh, dsh), (kb, _) = sp["structural"], sp["shear"], sp["bend"]
cm = ob.modifiers.new("Cloth", "CLOTH")
cs = cm.settings
cs.quality = quality
cs.time_scale = (1.0 / FPS) / T_U
cs.mass = sp["mass"] / (n * n)
cs.air_damping = 0.0
cs.bending_model = a.bending.upper()
cs.tension_stiffness = cs.compression_stiffness = ks * L / 1000.0
cs.shear_stiffness = ksh * L / 1000.0
if a.bending == "linear":
    cs.bending_stiffness = 20.0 * L * kb / 1000.0
else:
    cs.bending_stiffness = 0.0025 * kb * BEND_THETA ** 2
cs.tension_damping = cs.compression_damping = ds / (1000.0 * T_U)
cs.shear_damping = dsh / (1000.0 * T_U)
cs.bending_damping = 0.0
cs.effector_weights.gravity = 1.0
if a.scene == "hanging":
    cs.vertex_group_mass = "pin"
    cs.pin_stiffness = 1.0
cc = cm.collision_settings
cc.use_collision = a.scene != "hanging"
cc.use_self_collision = a.scene == "crumple"
if a.collision_quality:
    cc.collision_quality = a.collision_quality
cc.distance_min = THICKNESS
if a.scene == "crumple":
    cc.self_distance_min = THICKNESS / 2
    cc.self_friction = 100.0 * FRICTION
cm.point_cache.frame_start, cm.point_cache.frame_end = 1, frames + 1


def collider(obj: "bpy.types.Object") -> None:
    obj.modifiers.new("Collision", "COLLISION")
    obj.collision.thickness_outer = THICKNESS
    obj.collision.cloth_friction = 100.0 * FRICTION


if a.scene == "drape":
    bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32, radius=SPHERE_R, location=(0.0, 0.0, 0.0))
    collider(bpy.context.active_object)
elif a.scene == "crumple":
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=60, y_subdivisions=60, size=3.0, location=(0.0, 0.0, 0.0))
    collider(bpy.context.active_object)
    bpy.ops.mesh.primitive_cylinder_add(vertices=64, radius=ROD_R, depth=ROD_LEN, location=(ROD_X, 0.0, ROD_Z),
                                        rotation=(math.pi / 2, 0.0, 0.0))
    collider(bpy.context.active_object)
buf = np.empty(3 * n * n, dtype=np.float32)


def positions() -> np.ndarray:
    """The cloth's vertices after the modifier (the object sits at the origin, unrotated: local = world)."""
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    ev.data.vertices.foreach_get("co", buf)
    return buf.reshape(-1, 3).copy()


sc.frame_set(1)
X = [positions()]
wall = 0.0
for f in range(2, frames + 2):
    t0 = time.perf_counter()
    sc.frame_set(f)
    wall += time.perf_counter() - t0
    X.append(positions())
x, x_before = X[-1].astype(np.float64), X[-2].astype(np.float64)
speed = float(np.sqrt(np.mean(np.sum((x - x_before) ** 2, axis=1))) * FPS)
if a.save:
    np.save(a.save, np.stack(X))
print("RESULT " + json.dumps({
    "peer": "blender-" + bpy.app.version_string, "scene": a.scene, "n": n, "dt": 1 / (FPS * quality),
    "frames": frames, "substeps_per_frame": quality, "quality": quality,
    "collision_quality": cc.collision_quality, "bending_model": cs.bending_model, "wall_s": wall,
    "ms_per_frame": 1e3 * wall / frames, "zmin": float(x[:, 2].min()), "rms_speed": speed,
    "finite": bool(np.isfinite(x).all()), "positions": a.save}))
