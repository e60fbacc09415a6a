"""Contact at large steps: energy, strain and where the cloth ends, computed here from the states.

Every row runs one scene with :class:`implicit_cloth.Simulator` and judges it
with this script's own code, not the run's report: at every kept frame (60 Hz)
the total energy ``E = kinetic + gravity + sum_s k_s (l_s - L0_s)^2 / 2`` is
computed from the state's positions and velocities, with the rest lengths
``L0`` taken from frame 0 and the spring pairs and constants from the model.

Static rows (the drape table): a 1 m x 1 m cloth of 0.1 kg, springs
k = 1000 / 333.3 / 10 N/m (structural / shear / bend), damping 0.01 N*s/m (or
a material preset, with its own springs and density), gravity, no drag, is
dropped from 0.2 m above an obstacle's top (friction 0.3, thickness 5 mm) and
simulated for 3 s at dt = 1/60 or 1/30 s: a sphere (r = 0.3 m), a 0.4 m box
face up, edge up and corner up, a cone's tip (r = 0.25, h = 0.4 m), a
horizontal capsule (r = 0.15, length 0.6 m), a vertical cloth landing
edge-first on the floor plane, and the same sphere and box as triangle meshes
(an icosphere of 1280 faces, a 12-triangle box). Per row:

* ``rise``: the largest ``E(t) - E(0)`` over the run, as a percentage of
  ``m g (1 m)`` (goal: at most 2 %);
* ``max strain``: the largest ``(l - L0) / L0`` of any spring at a frame;
* ``end``: ``resting on it`` (at the end some vertex within 2 thicknesses of the
  obstacle, the cloth's centroid less than 0.6 m below its top, and an rms vertex
  speed below 1 cm/s), ``still moving`` (on it, but faster), ``slid off`` (not on
  it: fallen past it); ``at rest from``: the time of the last kept frame with an
  rms speed of 1 cm/s or more (resting rows). A row still moving is run again at
  finer steps (``--finer``, dt / 4 by default): if such a run is at rest, the
  large step kept the cloth moving; if even the finest still moves, the motion is
  the scene's (a skirt swinging with this scene's light damping, which a smaller
  step damps less, not more);
* ``goal``: the static rows' goal, judged per row by :func:`goal`: no energy
  rise beyond 2 %, the cloth on the obstacle, and at rest at the end, or, where
  it still moves, what lies on the obstacle at rest (rms below 1 cm/s: no creep)
  while the finest finer run moves on too (the rest asked for is not the scene's
  at that time: an integrator can only meet it there by damping what it should
  keep, see ``benchmarks/studies/rest_reference.py``);
* ``substeps/frame`` (adaptive stepping: accepted substeps per kept frame) and
  ``ms/frame`` (wall time; the machine is shared, so read it as a ratio).

Moving rows: a sphere (r = 0.15 m) at 2, 5, 10 or 20 m/s through the middle of
a cloth hanging from its two top corners, 1 s at dt = 1/30 s; goal: no spring
beyond 2.5 times its rest length (strain 1.5). The energy there is not bounded
by the start (the sphere does work), so only the strain is judged. Each row runs
without strain limiting and with it (``[simulation.strain_limit]``,
``max_strain = 0.1``, ``iterations = 1000``; ``--moving-limits``): friction 0.3
holds the cloth to the sphere's front, pressed on by its own tension, and the
springs at the two pinned corners take the pull (Provot 1995's super-elastic
corners), more at every finer grid since each spring is shorter; a limited cloth
cannot stretch, so it slides off.

Usage::

    python benchmarks/contact_energy.py                 # the full table (about an hour on 2 cores)
    python benchmarks/contact_energy.py --quick         # CI smoke: a few small rows
    python benchmarks/contact_energy.py --shapes sphere box_face --sizes 32 --dts 30
    python benchmarks/contact_energy.py --workers 2     # rows in parallel processes

Writes ``OUT/contact_energy.{json,md,png}`` (``--out``, default
out/bench/contact_energy). Never asserts: the goals are read off the table.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import default_out, friction_text, friction_used, ic, machine, run_all, save_png, write_outputs

G = 9.81
MASS = 0.1
THICKNESS = 0.005
DROP = 0.2
SPRINGS = {"structural": 1000.0, "shear": 333.3, "bend": 10.0}
DAMPING = 0.01
FRICTION = 0.3
#: Goal of the static rows: the largest energy rise, as a fraction of m g (1 m).
RISE_GOAL = 0.02
#: Goal of the moving rows: no spring beyond this many times its rest length.
STRETCH_GOAL = 2.5
REST_SPEED = 0.01           # m/s: "at rest" when the rms vertex speed at the end is below this
ON_DISTANCE = 2 * THICKNESS  # "on it": some vertex this near the obstacle at the end, and ...
ON_DROP = 0.6               # ... the cloth's centroid less than this far below the obstacle's top, m

BOX = 0.4
_CORNER_ROT = list(np.array([1.0, -1.0, 0.0]) / math.sqrt(2.0) * math.acos(1.0 / math.sqrt(3.0)))
#: shape name -> (obstacle table without friction, height of its top above z = 0, m)
SHAPES: dict[str, tuple[dict, float]] = {
    "sphere": ({"shape": "sphere", "radius": 0.3}, 0.3),
    "box_face": ({"shape": "box", "size": [BOX] * 3}, BOX / 2),
    "box_edge": ({"shape": "box", "size": [BOX] * 3, "rotation": [math.pi / 4, 0.0, 0.0]}, BOX / 2 * math.sqrt(2)),
    "box_corner": ({"shape": "box", "size": [BOX] * 3, "rotation": _CORNER_ROT}, BOX / 2 * math.sqrt(3)),
    "cone": ({"shape": "cone", "radius": 0.25, "height": 0.4}, 0.4),
    "capsule": ({"shape": "capsule", "radius": 0.15, "height": 0.6, "axis": [1.0, 0.0, 0.0]}, 0.15),
    "plane": ({"shape": "plane"}, 0.0),
    "mesh_icosphere": ({"shape": "mesh", "path": "icosphere.obj"}, 0.3),
    "mesh_box": ({"shape": "mesh", "path": "box.obj"}, BOX / 2),
}
MATERIAL_SHAPES = ("sphere", "box_edge")
SPEEDS = (2.0, 5.0, 10.0, 20.0)
#: Moving rows: without strain limiting (0) and with ``max_strain`` 0.1, at most LIMIT_PASSES passes a step.
MOVING_LIMITS = (0.0, 0.1)
LIMIT_PASSES = 1000


def mesh_files(folder: Path) -> Path:
    """Write the mesh obstacles (trimesh's icosphere r = 0.3 m, a 0.4 m box) into ``folder``."""
    import trimesh

    trimesh.creation.icosphere(subdivisions=3, radius=0.3).export(folder / "icosphere.obj")
    trimesh.creation.box(extents=[BOX] * 3).export(folder / "box.obj")
    return folder


def static_scene(shape: str, n: int, dt: float, duration: float, material: str | None = None) -> dict:
    ob, top = SHAPES[shape]
    ob = {**ob, "friction": FRICTION}
    if shape == "plane":   # a vertical cloth whose lower edge starts DROP above the floor
        cloth = {"size": [1.0, 1.0], "resolution": [n, n], "center": [0.0, 0.0, 0.5 + DROP], "plane": "xz"}
    else:
        cloth = {"size": [1.0, 1.0], "resolution": [n, n], "center": [0.0, 0.0, top + DROP], "plane": "xy"}
    if material is None:
        cloth["mass"] = MASS
        cloth["springs"] = {k: {"stiffness": s, "damping": DAMPING} for k, s in SPRINGS.items()}
    else:
        cloth["material"] = material
    return {"simulation": {"integrator": "backward_euler", "dt": dt, "duration": duration, "frame_rate": 60},
            "cloth": cloth, "effects": {"gravity": [0.0, 0.0, -G]}, "obstacles": [ob],
            "collision": {"thickness": THICKNESS}}


def moving_scene(speed: float, n: int, dt: float, duration: float, limit: float = 0.0) -> dict:
    ob = {"shape": "sphere", "radius": 0.15, "center": [0.0, -0.4, 1.0], "velocity": [0.0, speed, 0.0],
          "friction": FRICTION}
    cloth = {"size": [1.0, 1.0], "resolution": [n, n], "center": [0.0, 0.0, 1.0], "plane": "xz", "mass": MASS,
             "pins": ["top_left", "top_right"],
             "springs": {k: {"stiffness": s, "damping": DAMPING} for k, s in SPRINGS.items()}}
    sim = {"integrator": "backward_euler", "dt": dt, "duration": duration, "frame_rate": 60}
    if limit > 0:
        sim["strain_limit"] = {"max_strain": limit, "iterations": LIMIT_PASSES}
    return {"simulation": sim, "cloth": cloth, "effects": {"gravity": [0.0, 0.0, -G]}, "obstacles": [ob],
            "collision": {"thickness": THICKNESS}}


class Judge:
    """Energy and strain of states, from the model's spring pairs and constants and frame 0's lengths."""

    def __init__(self, sim: ic.Simulator) -> None:
        s = sim.model.springs
        self.i, self.j, self.k = s.i.copy(), s.j.copy(), s.k.copy()
        self.m = sim.model.masses.copy()
        self.L0 = self.lengths(sim.positions)

    def lengths(self, x: np.ndarray) -> np.ndarray:
        d = x[self.j] - x[self.i]
        return np.sqrt(np.einsum("ij,ij->i", d, d))

    def __call__(self, x: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """Total energy (J) and the largest strain."""
        ext = self.lengths(x) - self.L0
        e = 0.5 * float(np.dot(self.m, np.einsum("ij,ij->i", v, v))) + G * float(np.dot(self.m, x[:, 2])) \
            + 0.5 * float(np.dot(self.k, ext * ext))
        return e, float(np.max(ext / np.where(self.L0 > 0, self.L0, 1.0)))


def obstacle_distance(sim: ic.Simulator, x: np.ndarray, t: float) -> np.ndarray:
    """Each vertex's distance to the obstacle's surface, m (this script's own geometry, not the library's)."""
    ob = sim.scene.data["obstacles"][0]
    shape = ob["shape"]
    if shape == "sphere":
        c = np.asarray(ob["center"]) + t * np.asarray(ob["velocity"])
        d = np.linalg.norm(x - c, axis=1) - ob["radius"]
    elif shape == "plane":
        d = (x - np.asarray(ob["point"])) @ np.asarray(ob["normal"])
    else:   # boxes, cone, capsule, meshes: distance to a dense surface sample (trimesh)
        d = _sample_distance(sim, x)
    return d


def _sample_distance(sim: ic.Simulator, x: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    from implicit_cloth.render import obstacle_triangles

    ob = sim.scene.data["obstacles"][0]
    tris = obstacle_triangles(ob, sim.time, (x.mean(axis=0), 2.0))
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    rng = np.random.default_rng(0)
    u = rng.random((len(tris), 64, 2))
    flip = u.sum(axis=2) > 1
    u[flip] = 1 - u[flip]
    pts = a[:, None] + u[..., :1] * (b - a)[:, None] + u[..., 1:] * (c - a)[:, None]
    d, _ = cKDTree(np.concatenate([pts.reshape(-1, 3), tris.reshape(-1, 3)])).query(x)
    return d


def rms_speed(v: np.ndarray) -> float:
    """Root-mean-square vertex speed, m/s."""
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", v, v))))


def run_row(spec: dict) -> dict:
    """Simulate one row's scene, judging every kept frame (60 Hz) from its state."""
    folder = Path(spec.get("mesh_dir") or ".")
    sim = ic.Simulator(ic.Scene.from_dict(spec["scene"], base_dir=folder))
    judge = Judge(sim)
    e0, _ = judge(sim.positions, sim.velocities)
    seen = {"rise": -math.inf, "strain": 0.0, "frames": 0, "moving_at": 0.0}

    def on_frame(state) -> None:
        e, s = judge(state.x, state.v)
        seen["rise"], seen["strain"] = max(seen["rise"], e - e0), max(seen["strain"], s)
        seen["frames"] += 1
        if rms_speed(state.v) >= REST_SPEED:
            seen["moving_at"] = float(state.t)      # the last kept frame faster than REST_SPEED (rms)

    t0 = time.perf_counter()
    try:
        report = sim.run(on_frame=on_frame).report
    except ic.DivergenceError as exc:
        report = exc.trajectory.report if exc.trajectory is not None else {"status": "diverged"}
    wall = time.perf_counter() - t0
    done = max(seen["frames"] - 1, 1)
    ad = report.get("adaptive") or {}
    x, v = sim.positions, sim.velocities
    speed = np.linalg.norm(v, axis=1)
    vmax, vrms = float(speed.max()), float(np.sqrt(np.mean(speed**2)))
    mass = float(sim.model.total_mass)
    row = {k: spec[k] for k in ("group", "shape", "n", "dt", "material", "speed")}
    row["limit"] = spec.get("limit", 0.0)
    row.update({"rise_J": seen["rise"], "rise_frac": seen["rise"] / (mass * G * 1.0), "mass": mass,
                "max_strain": seen["strain"], "substeps_per_frame": ad.get("substeps", done) / done,
                "ms_per_frame": 1e3 * wall / done, "vmax_end": vmax, "vrms_end": vrms, "frames": done,
                "report_status": report.get("status"), "report_reason": report.get("reason", "")})
    if spec["group"] != "moving":
        dist = obstacle_distance(sim, x, sim.time) if report.get("status") != "diverged" else np.full(len(x), np.inf)
        gap = float(np.min(dist))
        # what lies on the obstacle (its creep, a contact's failing) apart from what hangs free (a skirt's swing)
        row["on_vrms_end"] = rms_speed(v[dist < ON_DISTANCE]) if np.any(dist < ON_DISTANCE) else None
        top = SHAPES[spec["shape"]][1]
        on = gap < ON_DISTANCE and float(x[:, 2].mean()) > top - ON_DROP
        row["end_gap"], row["end_centroid_z"] = gap, float(x[:, 2].mean())
        row["end"] = "slid off" if not on else "resting on it" if vrms < REST_SPEED else "still moving"
        row["rest_from"] = seen["moving_at"] if vrms < REST_SPEED else None    # s: at rest from this frame on
        if row["end"] == "still moving" and spec.get("finer"):
            row["finer_runs"] = [finer(spec, k, folder) for k in spec["finer"]]
    else:
        row["end"] = "-"
        row["max_stretch"] = 1.0 + seen["strain"]
    return row


def finer(spec: dict, k: int, folder: Path) -> dict:
    """A row still moving at the end, run again at ``dt / k``: is its motion the scene's (the finer step moves
    too) or the large step's (the finer step is at rest)? Less numerical damping at a smaller step can only
    leave more of a physical motion, so a finer run at rest says the large step kept the cloth moving."""
    scene = {**spec["scene"], "simulation": {**spec["scene"]["simulation"], "dt": spec["dt"] / k}}
    sim = ic.Simulator(ic.Scene.from_dict(scene, base_dir=folder))
    seen = {"moving_at": 0.0}

    def on_frame(state) -> None:
        if rms_speed(state.v) >= REST_SPEED:
            seen["moving_at"] = float(state.t)

    sim.run(on_frame=on_frame)
    vrms = rms_speed(sim.velocities)
    return {"factor": int(k), "dt": spec["dt"] / k, "vrms_end": vrms,
            "rest_from": seen["moving_at"] if vrms < REST_SPEED else None}


def finer_runs(row: dict) -> list[dict]:
    """A row's finer runs, finest last (rows of earlier versions of this script kept one, as ``finer_*`` keys)."""
    if "finer_runs" in row:
        return sorted(row["finer_runs"], key=lambda f: -f["dt"])
    if row.get("finer_dt"):
        return [{"factor": round(row["dt"] / row["finer_dt"]), "dt": row["finer_dt"],
                 "vrms_end": row["finer_vrms_end"], "rest_from": row.get("finer_rest_from")}]
    return []


def goal(row: dict) -> tuple[bool, str]:
    """Whether a static (or material) row meets the table's goal, and why (see the module's ``goal``)."""
    if row["rise_frac"] > RISE_GOAL:
        return False, f"energy rise {100 * row['rise_frac']:.2f} %"
    if row["end"] == "slid off":
        return False, "slid off"
    if row["end"] == "resting on it":
        return True, "at rest"
    on = row.get("on_vrms_end")
    if on is None or on >= REST_SPEED:
        return False, "creeps on the obstacle" if on is not None else "moving, nothing on the obstacle"
    runs = finer_runs(row)
    if not runs:
        return False, "still moving (no finer run)"
    rested = [f for f in runs if f["rest_from"] is not None]
    if runs[-1]["rest_from"] is not None:
        return False, f"the large step keeps it moving (at rest at dt 1/{round(1 / runs[-1]['dt'])})"
    return True, ("moving as the scene does: " + ", ".join(
        f"{100 * f['vrms_end']:.2f} cm/s at dt 1/{round(1 / f['dt'])}" for f in runs)
        + ("" if not rested else " (at rest at an intermediate step)"))


def friction_settings(args: argparse.Namespace) -> dict:
    """The ``[collision]`` friction keys of ``--friction-speed`` and ``--friction-newton`` (those given; empty: the
    library's default friction, smoothed and solved within the step)."""
    out = {}
    if args.friction_speed is not None:
        out["friction_speed"] = args.friction_speed
    if args.friction_newton is not None:
        out["friction_newton"] = args.friction_newton
    if getattr(args, "friction_pause", 0):
        out["friction_pause"] = args.friction_pause
    return out


def specs(args: argparse.Namespace, mesh_dir: Path) -> list[dict]:
    base = {"mesh_dir": str(mesh_dir), "material": None, "speed": None, "finer": [k for k in args.finer if k > 1]}
    out = _specs(args, base)
    for spec in out:
        spec["scene"]["collision"].update(friction_settings(args))
    if args.contact_tolerance:
        for spec in out:
            spec["scene"].setdefault("solver", {})["contact_tolerance"] = args.contact_tolerance
    if args.method != "rounds":
        for spec in out:
            spec["scene"]["collision"]["method"] = args.method
    return out


def _specs(args: argparse.Namespace, base: dict) -> list[dict]:
    out = []
    for shape in args.shapes:
        for n in args.sizes:
            for fps in args.dts:
                out.append({**base, "group": "static", "shape": shape, "n": n, "dt": 1.0 / fps,
                            "scene": static_scene(shape, n, 1.0 / fps, args.duration)})
    for mat in args.materials:
        for shape in MATERIAL_SHAPES:
            out.append({**base, "group": "material", "shape": shape, "n": args.material_size, "dt": 1.0 / 60,
                        "material": mat, "scene": static_scene(shape, args.material_size, 1.0 / 60, args.duration,
                                                               mat)})
    for limit in args.moving_limits:
        for speed in args.speeds:
            for n in args.moving_sizes:
                out.append({**base, "group": "moving", "shape": "sphere", "n": n, "dt": 1.0 / 30, "speed": speed,
                            "limit": limit, "scene": moving_scene(speed, n, 1.0 / 30, args.moving_duration, limit)})
    return out


def markdown(res: dict) -> str:
    lines = [f"Contact at large steps, judged from the states by `benchmarks/contact_energy.py` "
             f"({'quick' if res['quick'] else 'full'} run, {res['wall_s']:.0f} s). Cloth 1 m x 1 m; static rows "
             f"{MASS} kg, k = 1000 / 333 / 10 N/m (or the material preset), dropped {DROP} m, friction {FRICTION}, "
             f"thickness {THICKNESS * 1e3:g} mm, {res['duration']:g} s. rise: largest E(t) - E(0) over m g (1 m) "
             f"(goal <= {100 * RISE_GOAL:g} %).", ""]
    lines[0] += friction_text(res)
    if res.get("method", "rounds") != "rounds":
        lines[0] += f" Contact by `collision.method = \"{res['method']}\"`."
    if res.get("contact_tolerance"):
        lines[0] += f" Solves of steps with contacts at `solver.contact_tolerance = {res['contact_tolerance']:g}`."
    lines += ["| group | shape | grid | dt | material | rise | max strain | end | at rest from | on it at the end | "
              "substeps/frame | ms/frame | report | goal |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    still = []
    for r in res["rows"]:
        if r["group"] == "moving":
            continue
        ok = "" if r["rise_frac"] <= RISE_GOAL else " **x**"
        lines.append(f"| {r['group']} | {r['shape']} | {r['n']}² | 1/{round(1 / r['dt'])} | {r['material'] or '-'} | "
                     f"{100 * r['rise_frac']:.2f} %{ok} | {r['max_strain']:.3f} | {r['end']} | "
                     f"{'-' if r.get('rest_from') is None else format(r['rest_from'], '.2f') + ' s'} | "
                     f"{'-' if r.get('on_vrms_end') is None else format(1e3 * r['on_vrms_end'], '.2f') + ' mm/s'} | "
                     f"{r['substeps_per_frame']:.2f} | {r['ms_per_frame']:.0f} | {r['report_status']} | "
                     f"{_goal_cell(r)} |")
        if finer_runs(r):
            still.append(f"{r['group']} {r['shape']} {r['n']}² at dt 1/{round(1 / r['dt'])}"
                         + (f" ({r['material']})" if r["material"] else "")
                         + f": {100 * r['vrms_end']:.2f} cm/s rms at the end; " + ", ".join(
                             f"at dt 1/{round(1 / f['dt'])} "
                             + (f"at rest from {f['rest_from']:.2f} s" if f["rest_from"] is not None else
                                f"{100 * f['vrms_end']:.2f} cm/s") for f in finer_runs(r))
                         + f" ({_finer_verdict(r)})")
    if still:
        lines += ["", "Rows still moving, run again at finer steps (`--finer`): " + "; ".join(still) + "."]
    mov = [r for r in res["rows"] if r["group"] == "moving"]
    if mov:
        lines += ["", f"Moving sphere (r = 0.15 m) through a cloth hanging from two corners, dt 1/30 s, "
                      f"{res['moving_duration']:g} s; goal: no spring beyond {STRETCH_GOAL}x its rest length.", "",
                  "| strain limit | speed | grid | max stretch | substeps/frame | ms/frame | report |",
                  "|---|---|---|---|---|---|---|"]
        for r in mov:
            ok = "" if r["max_stretch"] <= STRETCH_GOAL else " **x**"
            lim = f"{r.get('limit', 0.0):g}" if r.get("limit") else "none"
            lines.append(f"| {lim} | {r['speed']:g} m/s | {r['n']}² | {r['max_stretch']:.2f}x{ok} | "
                         f"{r['substeps_per_frame']:.2f} | {r['ms_per_frame']:.0f} | {r['report_status']} |")
    st = [r for r in res["rows"] if r["group"] != "moving"]
    if st:
        worst = max(st, key=lambda r: r["rise_frac"])
        dt60 = [r["substeps_per_frame"] for r in st if abs(r["dt"] - 1 / 60) < 1e-12 and r["group"] == "static"]
        met = [goal(r) for r in st]
        lines += ["", f"Worst static rise: {100 * worst['rise_frac']:.2f} % ({worst['shape']}, {worst['n']}², "
                      f"dt 1/{round(1 / worst['dt'])}). Rows at or below the goal: "
                      f"{sum(r['rise_frac'] <= RISE_GOAL for r in st)} of {len(st)}.",
                  f"Static and material rows meeting the goal: {sum(m for m, _ in met)} of {len(st)} "
                  f"({sum(why == 'at rest' for _, why in met)} at rest at the end, "
                  f"{sum(m and why != 'at rest' for m, why in met)} still moving as their finer runs do, what "
                  f"lies on the obstacle at rest)."]
        if dt60:
            lines.append(f"Mean substeps per frame over the static rows at dt 1/60: {np.mean(dt60):.2f}.")
    return "\n".join(lines) + "\n"


def _finer_verdict(row: dict) -> str:
    met, why = goal(row)
    return "the scene's own motion" if met else why


def _goal_cell(row: dict) -> str:
    met, why = goal(row)
    if not met:
        return f"**missed**: {why}"
    return "met" if why == "at rest" else "met (the scene moves)"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    st = [r for r in res["rows"] if r["group"] != "moving"]
    labels = sorted({(r["shape"] if r["group"] == "static" else f"{r['shape']}\n{r['material']}") for r in st},
                    key=lambda s: list(SHAPES).index(s.split("\n")[0]) * 10 + len(s))
    pos = {s: k for k, s in enumerate(labels)}
    sizes = sorted({r["n"] for r in st})
    for r in st:
        lab = r["shape"] if r["group"] == "static" else f"{r['shape']}\n{r['material']}"
        x = pos[lab] + 0.12 * (sizes.index(r["n"]) - (len(sizes) - 1) / 2)
        marker = "o" if abs(r["dt"] - 1 / 60) < 1e-12 else "s"
        color = plt.cm.viridis(sizes.index(r["n"]) / max(len(sizes) - 1, 1))
        a.scatter(x, 100 * max(r["rise_frac"], 1e-4), marker=marker, color=color, edgecolor="k", linewidth=0.4)
    a.axhline(100 * RISE_GOAL, color="tab:red", linestyle="--", label=f"goal {100 * RISE_GOAL:g} % of m g (1 m)")
    a.set_yscale("log")
    a.set_xticks(range(len(labels)), labels, rotation=45, ha="right", fontsize=8)
    a.set_ylabel("largest energy rise, % of m g (1 m)")
    for n in sizes:
        a.scatter([], [], color=plt.cm.viridis(sizes.index(n) / max(len(sizes) - 1, 1)), label=f"{n}²")
    a.scatter([], [], marker="o", color="w", edgecolor="k", label="dt 1/60")
    a.scatter([], [], marker="s", color="w", edgecolor="k", label="dt 1/30")
    a.legend(fontsize=7, ncol=2)
    a.set_title("static drapes (rises below 0.01 % drawn at 0.01 %)")
    mov = [r for r in res["rows"] if r["group"] == "moving"]
    for (lim, n) in sorted({(r.get("limit") or 0.0, r["n"]) for r in mov}):
        rr = sorted((r for r in mov if r["n"] == n and (r.get("limit") or 0.0) == lim), key=lambda r: r["speed"])
        b.plot([r["speed"] for r in rr], [r["max_stretch"] for r in rr], "o-" if not lim else "s--",
               label=f"{n}²" + (f", limit {lim:g}" if lim else ""))
    b.axhline(STRETCH_GOAL, color="tab:red", linestyle="--", label=f"goal {STRETCH_GOAL}x")
    b.set_xlabel("sphere speed, m/s")
    b.set_ylabel("largest spring stretch l / L0")
    b.set_yscale("log")
    b.set_title("sphere through a hanging cloth, dt 1/30")
    if mov:
        b.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


def merge(paths: list[Path], out: Path) -> int:
    """Combine partial runs (say, one size per run, as the machine allows) into one result, rows in table order; a
    row in several parts is taken from the last."""
    import json

    parts = [json.loads(Path(p).read_text()) for p in paths]
    order = {"static": 0, "material": 1, "moving": 2}
    latest = {}                 # a row run again in a later part replaces the earlier one
    for part in parts:
        for r in part["rows"]:
            latest[(r["group"], r["shape"], r["n"], r["dt"], r["material"], r["speed"], r.get("limit") or 0.0)] = r
    rows = sorted(latest.values(),
                  key=lambda r: (order[r["group"]], r["material"] or "", list(SHAPES).index(r["shape"]),
                                 r.get("limit") or 0.0, r["speed"] or 0.0, r["n"], -r["dt"]))
    res = {**parts[0], "rows": rows, "wall_s": sum(p["wall_s"] for p in parts),
           "quick": any(p["quick"] for p in parts), "merged_from": [str(p) for p in paths]}
    out.mkdir(parents=True, exist_ok=True)
    write_outputs(out, "contact_energy", res, markdown(res))
    plot(res, out / "contact_energy.png")
    print(markdown(res))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CI smoke: a few small, short rows")
    p.add_argument("--shapes", nargs="*", default=list(SHAPES), choices=list(SHAPES),
                   help="static shapes (none: no static rows)")
    p.add_argument("--sizes", nargs="+", type=int, default=[32, 64, 96])
    p.add_argument("--dts", nargs="+", type=float, default=[60, 30], help="1/dt values, Hz")
    p.add_argument("--materials", nargs="*", default=list(ic.MATERIALS))
    p.add_argument("--material-size", type=int, default=64)
    p.add_argument("--speeds", nargs="*", type=float, default=list(SPEEDS))
    p.add_argument("--moving-sizes", nargs="+", type=int, default=[32, 64, 96])
    p.add_argument("--duration", type=float, default=3.0, help="static rows, s")
    p.add_argument("--moving-duration", type=float, default=1.0, help="moving rows, s")
    p.add_argument("--moving-limits", nargs="*", type=float, default=list(MOVING_LIMITS),
                   help="moving rows: strain limits to run (0: none)")
    p.add_argument("--finer", type=int, nargs="*", default=[4], metavar="K",
                   help="static rows still moving at the end are run again at dt / K for each K (none, or 0: not)")
    p.add_argument("--friction-speed", type=float, default=None, metavar="EPS",
                   help="collision.friction_speed of every row, m/s (smoothed friction; 0: Coulomb's states; "
                        "default: the library's)")
    p.add_argument("--friction-newton", type=int, default=None, metavar="K",
                   help="collision.friction_newton of every row (with --friction-speed: the smoothed friction "
                        "solved within the step by up to K Newton iterations; 0: linearised once)")
    p.add_argument("--friction-pause", type=int, default=0, metavar="P",
                   help="collision.friction_pause of every row (steps without the friction's Newton iterations "
                        "after two steps in a row that missed the law; 0: the default, never)")
    p.add_argument("--contact-tolerance", type=float, default=0.0, metavar="TOL",
                   help="solver.contact_tolerance of every row (0: the default, solver.tolerance)")
    p.add_argument("--method", choices=ic.scene.COLLISION_METHODS, default="rounds",
                   help="collision.method of every row (default: the library's, rounds)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(default_out('contact_energy')), help="output folder (default out/bench/contact_energy; --out benchmarks/results replaces the committed result)")
    p.add_argument("--merge", nargs="+", type=Path, metavar="JSON",
                   help="run nothing: combine the rows of earlier (partial) runs' contact_energy.json into one table")
    args = p.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)
    if args.quick:
        args.shapes, args.sizes, args.dts = ["sphere", "box_face", "mesh_box"], [12], [30]
        args.materials, args.speeds, args.moving_sizes = [], [10.0], [12]
        args.duration, args.moving_duration = 1.0, 0.3
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rows = run_all(run_row, specs(args, mesh_files(Path(tmp))), args.workers, "contact")
    res = {"benchmark": "contact_energy", "quick": args.quick, "machine": machine(), "duration": args.duration,
           "moving_duration": args.moving_duration, **dict(zip(("friction_speed", "friction_newton"),
                                                               friction_used(args.friction_speed, args.friction_newton),
                                                               strict=True)),
           "friction_pause": args.friction_pause, "contact_tolerance": args.contact_tolerance, "method": args.method,
           "wall_s": time.perf_counter() - t0, "rows": rows,
           "goals": {"rise_frac": RISE_GOAL, "stretch": STRETCH_GOAL}}
    args.out.mkdir(parents=True, exist_ok=True)
    write_outputs(args.out, "contact_energy", res, markdown(res))
    plot(res, args.out / "contact_energy.png")
    print(markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
