"""Blender 3.4's cloth on the benchmark scene of ``vs_blender.py``; run inside Blender, prints one RESULT line.

    blender -b --factory-startup -noaudio --python benchmarks/_blender_cloth.py -- --scene hanging --n 64

The scene, in SI units (the same as ``vs_blender.scene``): a 1 m x 1 m cloth of n x n vertices in the xy
plane, 0.1 kg, springs k = 1000 (structural) / 333.3 (shear) / 10 (bend) N/m, damping 0.01 N*s/m, no air
drag, gravity -9.81 m/s^2 along z, dt = 1/60 s, 2 s (120 frames). "hanging": the two corners of the
y = +0.5 row pinned, at z = 0. "drape": no pins, at z = 0.5 over a sphere r = 0.3 at the origin, contact
distance 0.01 m in all (5 mm on each side).

Blender's units (checked against the 3.4 source, ``cloth_calc_force``): gravity is scaled by 0.001, a
spring's k is its stiffness over the average spring length, damping and air drag are not mass-scaled, and
its time unit is a frame times ``time_scale``. With ``T_u = sqrt(0.001)`` s the internal units are SI:
``time_scale = (1/60) / T_u``, 60 fps, ``quality = (1/60) / dt`` substeps, vertex mass ``0.1 / n^2``,
tension = compression = ``1000 L / 1000``, shear ``333.3 L / 1000``, bending (LINEAR) ``20 L 10 / 1000``,
spring damping ``0.01 / (1000 T_u)`` (``L = 1 / (n - 1)``). Free fall checks it: z(1/6 s) = 0.3501 m, the
implicit-Euler value at dt = 1/60 s. Blender's solver is one thread, its CG capped at 100 iterations and a
1e-2 residual. Timed: the 120 ``frame_set`` calls (cloth modifier and depsgraph); start-up and frame 1 not.
"""

import argparse
import json
import math
import sys
import time

import bpy
import numpy as np

G = 9.81
MASS = 0.1
K_STRUCT, K_SHEAR, K_BEND = 1000.0, 1000.0 / 3.0, 10.0
DAMPING = 0.01
SPHERE_R = 0.3
DRAPE_Z = 0.5
MARGIN = 0.01
FPS = 60
T_U = math.sqrt(0.001)

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
ap = argparse.ArgumentParser()
ap.add_argument("--scene", default="hanging", choices=["hanging", "drape"])
ap.add_argument("--n", type=int, default=32)
ap.add_argument("--dt", type=float, default=1 / 60)
ap.add_argument("--duration", type=float, default=2.0)
a = ap.parse_args(argv)
n = a.n
quality = max(1, int(round((1.0 / FPS) / a.dt)))
frames = int(round(a.duration * FPS))

bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.fps, sc.render.fps_base = FPS, 1.0
sc.frame_start, sc.frame_end = 1, frames + 1
sc.use_gravity = True
sc.gravity = (0.0, 0.0, -G)

xs = np.linspace(-0.5, 0.5, n)
X, Y = np.meshgrid(xs, xs)          # vertex i * n + j: row i along +y, column j along +x
z0 = DRAPE_Z if a.scene == "drape" else 0.0
P = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z0)], axis=1)
quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]
me = bpy.data.meshes.new("cloth")
me.from_pydata(P.tolist(), [], quads)
me.update()
ob = bpy.data.objects.new("cloth", me)
sc.collection.objects.link(ob)
if a.scene == "hanging":
    vg = ob.vertex_groups.new(name="pin")
    vg.add([(n - 1) * n, n * n - 1], 1.0, "REPLACE")

L = 1.0 / (n - 1)
cm = ob.modifiers.new("Cloth", "CLOTH")
cs = cm.settings
cs.quality = quality
cs.time_scale = (1.0 / FPS) / T_U
cs.mass = MASS / (n * n)
cs.air_damping = 0.0
cs.bending_model = "LINEAR"
cs.tension_stiffness = cs.compression_stiffness = K_STRUCT * L / 1000.0
cs.shear_stiffness = K_SHEAR * L / 1000.0
cs.bending_stiffness = 20.0 * L * K_BEND / 1000.0
cs.tension_damping = cs.compression_damping = DAMPING / (1000.0 * T_U)
cs.shear_damping = DAMPING / (1000.0 * T_U)
cs.bending_damping = 0.0
cs.effector_weights.gravity = 1.0
if a.scene == "hanging":
    cs.vertex_group_mass = "pin"
    cs.pin_stiffness = 1.0
cc = cm.collision_settings
cc.use_self_collision = False
cc.use_collision = a.scene == "drape"
cm.point_cache.frame_start, cm.point_cache.frame_end = 1, frames + 1
if a.scene == "drape":
    bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32, radius=SPHERE_R, location=(0.0, 0.0, 0.0))
    sph = bpy.context.active_object
    sph.modifiers.new("Collision", "COLLISION")
    sph.collision.thickness_outer = MARGIN / 2
    cc.distance_min = MARGIN / 2


def positions():
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    return np.array([ev.matrix_world @ v.co for v in ev.data.vertices], dtype=np.float64)


sc.frame_set(1)
t0 = time.perf_counter()
for f in range(2, frames + 1):
    sc.frame_set(f)
wall = time.perf_counter() - t0
x_before = positions()                      # not timed: the last frame's speed, for "at rest"
t0 = time.perf_counter()
sc.frame_set(frames + 1)
wall += time.perf_counter() - t0
x = positions()
speed = float(np.sqrt(np.mean(np.sum((x - x_before) ** 2, axis=1))) * FPS)
print("RESULT " + json.dumps({
    "peer": "blender-" + bpy.app.version_string, "scene": a.scene, "n": n, "dt": a.dt, "frames": frames,
    "substeps_per_frame": quality, "wall_s": wall, "ms_per_frame": 1e3 * wall / frames,
    "zmin": float(x[:, 2].min()), "rms_speed": speed, "finite": bool(np.isfinite(x).all())}))
