"""implicit_cloth against Blender 3.4's cloth, side by side: ms per 1/60 s frame, the ratio, and one judge of both.

One run times both programs per size and judges the quality of both from their positions with one script.

The scenes (SI units), dt = 1/60 s:

* "hanging" and "drape" (the shared peer scene): a 1 m x 1 m cloth of n x n vertices, 0.1 kg, springs
  k = 1000 (structural) / 333.3 (shear) / 10 (bend) N/m, damping 0.01 N*s/m, no air drag, gravity, 2 s
  simulated (120 frames). "hanging": the two top corners pinned. "drape": dropped from z = 0.5 m onto a
  sphere r = 0.3 m (friction 0.3, thickness 5 mm).
* "crumple" (``self_collision.crumple``, the same scene table): a 1 m cotton sheet (0.15 kg, k = 5000 / 500 /
  20 N/m) hanging in the xz plane 0.62 m up, dropped edge-first onto the floor and a rod (radius 3 cm along y
  at x = 0.1 m, 4 cm up), friction 0.3 with the obstacles and between layers, thickness 5 mm, self-collision
  on, 1.5 s (90 frames). ``--method rounds|barrier`` chooses ours' ``[collision] method`` (default the
  scene's: rounds).

Blender's cloth is set up from the same SI scenes by ``_blender_cloth.py`` (run inside Blender; its docstring
gives the unit mapping, the contact distances and the friction: Blender's obstacle friction is the collision
object's ``cloth_friction`` times 0.01, so 30 for mu = 0.3, its self-friction likewise); its solver is one
thread with CG capped at 100 iterations and a 1e-2 residual (its error is not bounded). Blender's bending
model is ANGULAR (``--blender-bending``): with LINEAR its structural springs take no compression
(``SIM_mass_spring_force_spring_linear`` skips a compressed spring unless a flag no Python property sets is
on): at the end of the 32² drape (2 s) 24.1 % of its structural springs are more than 20 % compressed (the
shortest at 0.38 of its length), none with ANGULAR (compression stiffness = tension stiffness; 0.7 % at the
worst frame) and none of ours (``benchmarks/studies/blender_compression.py``); on the crumple LINEAR
leaves 50.8 % (32²) / 35.0 % (64²) compressed, ANGULAR 0.1 % / 0.0 %. ANGULAR bending is a
dihedral-angle spring, ours are linear springs over two edges: the two are matched at a 0.5 rad hinge.

Ours: backward Euler with the default solver (multigrid PCG, tolerance 1e-3 on the error of dv) and the
default step control (adaptive: a step that breaks the energy balance or the strain bound is redone), or
``--fixed`` (one linearised step per frame, like Blender). Both run in their own processes, alternating
(ours, Blender at each ``--blender-quality``, ours, ...), ``--pairs`` pairs per size and scene; the medians
are compared. Timed: the frames after the first (start-up, the first frame and, for ours, the first load of
the compiled kernels, are not; nor is the copying of positions). Blender's quality sweep
(``--blender-quality 1 2 4 ...``) is over its ``quality``, the steps per frame (``collision_quality``, the
collision passes per step, stays at its default 2 unless ``--blender-collision-quality`` is given; Blender
3.4 has no separate self-collision quality).

The judge (``judge``, the same code for both programs): every run writes every frame's positions, and from
them: self-crossings (``self_collision.count_crossings``: edges through triangles sharing no vertex, at every
``--judge-every``-th frame and the last), the most at any judged frame and at the end; penetration, the
deepest point inside an obstacle's surface (the sphere; the floor and the rod), m, at any frame and at the
end (n/a for the hanging cloth); the rms speed of the last frame (m/s; "at rest" below 0.01). Per size the
table compares ours with Blender's cheapest quality (ms per frame) with no penetration, no point deeper than
``PENETRATION_TOL`` = 1 mm at any frame (if every quality run penetrates: the least penetrating, marked), and
gives both programs' crossings; a second table lists every run's quality. Ours also reports its CG iterations
and solves per frame.

Usage::

    python benchmarks/vs_blender.py                                   # hanging 32..256, drape and crumple 32..128
    python benchmarks/vs_blender.py --scenes crumple --blender-quality 1 2 4 8 --threads 2
    python benchmarks/vs_blender.py --scenes crumple --method barrier --sizes 32 64 --pairs 1
    python benchmarks/vs_blender.py --scenes drape --sizes 32 64 --pairs 1
    python benchmarks/vs_blender.py --fixed --threads 2
    python benchmarks/vs_blender.py --scenes hanging --fixed --preconditioner multigrid_smoothed
    python benchmarks/vs_blender.py --quick                           # every scene at 8², one pair
    python benchmarks/vs_blender.py --scenes crumple --sizes 128 --pairs 1 --name part128   # one size a run, then
    python benchmarks/vs_blender.py --merge out/bench/vs_blender/vs_blender.json out/bench/vs_blender/part128.json

Needs Blender (``apt-get install blender python3-numpy``: Debian's 3.4 and the numpy its Python uses; it is
run with the system's Python first on PATH); without it the script says so on stderr and exits 1, except
with ``--quick``, which then runs our side alone (the Blender columns "-"). Writes ``OUT/NAME.{json,md}``
(``--name``, default vs_blender; ``--out``, default out/bench/vs_blender). Never asserts a time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FPS = 60
SIZES = {"hanging": [32, 64, 128, 256], "drape": [32, 64, 128], "crumple": [32, 64, 128]}
DURATION = {"hanging": 2.0, "drape": 2.0, "crumple": 1.5}      # s simulated (the crumple's as self_collision.py's)
QUICK_SIZE = 8   # --quick: every scene at 8², one pair
PENETRATION_TOL = 1e-3    # m: a run "has no penetration" when no frame has a point deeper inside an obstacle
SPHERE_R = 0.3
ROD_R, ROD_CENTER, ROD_HALF = 0.03, (0.1, 0.0, 0.04), 1.0    # the crumple's rod: a capsule along y


def scene(kind: str, n: int, fixed: bool = False, friction_speed: float | None = None,
          friction_pause: int = 0, method: str | None = None, duration: float | None = None) -> dict:
    """The benchmark scene as an implicit_cloth scene table (see the module docstring)."""
    dur = duration or DURATION[kind]
    if kind == "crumple":
        from self_collision import crumple

        d = crumple(n, 1 / FPS, dur)
    else:
        springs = {"structural": {"stiffness": 1000.0, "damping": 0.01},
                   "shear": {"stiffness": 1000.0 / 3.0, "damping": 0.01},
                   "bend": {"stiffness": 10.0, "damping": 0.0}}
        d = {"simulation": {"integrator": "backward_euler", "dt": 1 / FPS, "duration": dur, "frame_rate": FPS},
             "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xy",
                       "center": [0.0, 0.0, 0.0 if kind == "hanging" else 0.5],
                       "pins": ["top_left", "top_right"] if kind == "hanging" else [], "springs": springs},
             "effects": {"gravity": [0.0, 0.0, -9.81]}}
    if kind == "drape":
        d["obstacles"] = [{"shape": "sphere", "radius": SPHERE_R, "center": [0.0, 0.0, 0.0], "friction": 0.3}]
        d["collision"] = {"thickness": 0.005}
    if kind != "hanging":
        if friction_speed is not None:
            d["collision"]["friction_speed"] = friction_speed
        if friction_pause:
            d["collision"]["friction_pause"] = friction_pause
        if method:
            d["collision"]["method"] = method
    if fixed:
        d["simulation"]["adaptive"] = {"enabled": False}
    return d


def grid_faces(n: int) -> np.ndarray:
    """The n x n grid's triangles, vertex ``j n + i`` (implicit_cloth's grid; Blender's mesh is built in this
    order from quads ``(a, b, d, c)`` with this diagonal)."""
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int64)


def penetration(kind: str, x: np.ndarray) -> float | None:
    """The deepest point of positions ``x`` inside an obstacle's surface (the sphere; the floor and the rod), m;
    0 if none is inside, None for a scene without obstacles."""
    if kind == "hanging":
        return None
    if kind == "drape":
        depth = SPHERE_R - np.linalg.norm(x, axis=1)
    else:
        c = np.asarray(ROD_CENTER)
        r = x - c
        r[:, 1] -= np.clip(r[:, 1], -ROD_HALF, ROD_HALF)           # from the rod's segment along y
        depth = np.maximum(-x[:, 2], ROD_R - np.linalg.norm(r, axis=1))
    return max(0.0, float(depth.max()))


def judge(kind: str, X: np.ndarray, every: int = 1) -> dict:
    """One judge for both programs, from a run's frames ``X`` (frames x n^2 x 3, the start first): self-crossings
    (``self_collision.count_crossings``: edges through triangles sharing no vertex), the most at any judged frame
    (every ``every``-th and the last) and at the end; the deepest penetration of an obstacle at any frame and at
    the end (m; None without obstacles); the rms speed of the last frame (m/s)."""
    from self_collision import count_crossings, edge_list

    X = np.asarray(X, dtype=np.float64)
    n = int(round(np.sqrt(X.shape[1])))
    faces = grid_faces(n)
    edges = edge_list(faces)
    judged = sorted(set(range(0, len(X), max(1, every))) | {len(X) - 1})
    crossings = {k: count_crossings(X[k], faces, edges) for k in judged}
    pen = [penetration(kind, x) for x in X]
    return {"crossings_max": max(crossings.values()), "crossings_end": crossings[len(X) - 1],
            "penetration_max": None if pen[0] is None else max(p for p in pen if p is not None),
            "penetration_end": pen[-1],
            "rms_speed_end": float(np.sqrt(np.mean(np.sum((X[-1] - X[-2]) ** 2, axis=1))) * FPS),
            "frames_judged": len(judged), "finite": bool(np.isfinite(X).all())}


def run_ours(kind: str, n: int, fixed: bool, tolerance: float | None, threads: int | None,
             friction_speed: float | None = None, friction_pause: int = 0, preconditioner: str | None = None,
             method: str | None = None, duration: float | None = None, save: str | None = None) -> dict:
    """One run of ours in this process (the worker): the RESULT record; ``save``: every frame's positions to
    that .npy (float32, the start first), for the judge."""
    sys.path.insert(0, str(HERE.parent))
    import implicit_cloth as ic
    from implicit_cloth import backend

    if threads is not None:
        backend.set_threads(threads)
    solver = {k: v for k, v in (("tolerance", tolerance), ("preconditioner", preconditioner)) if v} or None
    sim = ic.Simulator(ic.Scene.from_dict(scene(kind, n, fixed, friction_speed, friction_pause, method, duration)),
                       solver=solver)
    frames = int(round((duration or DURATION[kind]) * FPS))
    X = [sim.positions.astype(np.float32)]
    sim.step(1)                                   # the first frame: kernels loaded from numba's cache
    X.append(sim.positions.astype(np.float32))
    its = solves = all_its = all_solves = 0
    wall = 0.0
    for _ in range(frames - 1):
        t0 = time.perf_counter()
        sim.step(1)
        wall += time.perf_counter() - t0
        li = sim.last_step
        its += li.iterations
        solves += li.solves
        all_its += li.attempted_iterations                         # discarded attempts included
        all_solves += li.attempted_solves
        X.append(sim.positions.astype(np.float32))
    x, x_before = sim.positions, X[-2].astype(np.float64)
    if save:
        np.save(save, np.stack(X))
    timed = frames - 1
    coll = sim.scene.data.get("collision", {})
    return {"peer": f"implicit_cloth-{ic.__version__}", "scene": kind, "n": n, "frames": timed,
            "fixed_steps": fixed, "friction_speed": friction_speed,
            "friction_pause": friction_pause, "method": coll.get("method", "rounds") if coll else None,
            "tolerance": sim.integrator.tolerance, "threads": backend.threads(),
            "accelerator": getattr(sim.integrator.precond, "accelerator", "numpy"),
            "preconditioner": sim.integrator.precond.name,
            "wall_s": wall, "ms_per_frame": 1e3 * wall / timed, "iterations_per_frame": its / timed,
            "solves_per_frame": solves / timed, "attempted_iterations_per_frame": all_its / timed,
            "attempted_solves_per_frame": all_solves / timed, "zmin": float(x[:, 2].min()),
            "rms_speed": float(np.sqrt(np.mean(np.sum((x - x_before) ** 2, axis=1))) * FPS),
            "finite": bool(np.isfinite(x).all()), "positions": save}


def _result(proc: subprocess.CompletedProcess) -> dict:
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError(f"no RESULT line (exit {proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


def ours(kind: str, n: int, a: argparse.Namespace, save: str | None = None) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--scenes", kind, "--sizes", str(n)]
    if a.fixed:
        cmd.append("--fixed")
    if a.tolerance:
        cmd += ["--tolerance", str(a.tolerance)]
    if a.threads:
        cmd += ["--threads", str(a.threads)]
    if a.friction_speed is not None:
        cmd += ["--friction-speed", str(a.friction_speed)]
    if a.friction_pause:
        cmd += ["--friction-pause", str(a.friction_pause)]
    if a.preconditioner:
        cmd += ["--preconditioner", a.preconditioner]
    if a.method:
        cmd += ["--method", a.method]
    if a.duration:
        cmd += ["--duration", str(a.duration)]
    if save:
        cmd += ["--save", save]
    return _result(subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout))


def blender(exe: str, kind: str, n: int, a: argparse.Namespace, quality: int | None = None,
            save: str | None = None) -> dict:
    cmd = [exe, "-b", "--factory-startup", "-noaudio", "--python", str(HERE / "_blender_cloth.py"), "--",
           "--scene", kind, "--n", str(n), "--bending", a.blender_bending]
    if quality:
        cmd += ["--quality", str(quality)]
    if a.blender_collision_quality:
        cmd += ["--collision-quality", str(a.blender_collision_quality)]
    if a.duration:
        cmd += ["--duration", str(a.duration)]
    if save:
        cmd += ["--save", save]
    # Debian's Blender takes the Python its interpreter finds first on PATH: under pyenv or a venv, that one's
    # library without the system's numpy; run it with its own directory and the system's
    env = dict(os.environ, PATH=os.pathsep.join(dict.fromkeys([str(Path(exe).parent), "/usr/bin", "/bin"])))
    env.pop("PYTHONHOME", None)
    env.pop("PYTHONPATH", None)
    return _result(subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout, env=env))


def _judged(run: dict, kind: str, every: int) -> dict:
    """The run's record with the judge's verdict on its saved positions (the file removed after)."""
    path = Path(run["positions"])
    run.update(judge(kind, np.load(path), every))
    path.unlink()
    return run


def _friction_text(res: dict) -> str:
    """The drape's / crumple's friction in the header (none with the hanging cloth alone)."""
    if not {"drape", "crumple"} & {r["scene"] for r in res["rows"]}:
        return ""
    from _common import friction_text

    return friction_text(res, "Ours with ")


def _preconditioner_text(res: dict) -> str:
    """The preconditioner asked for and, where the runs say it, the one that ran (``auto`` picks per size)."""
    ran = sorted({o.get("preconditioner") for r in res["rows"] for o in r.get("ours_runs", [])} - {None})
    asked = res.get("preconditioner") or "the default (auto)"
    return asked + (f", ran: {', '.join(ran)}" if ran and ran != [asked] else "")


def _mm(v: float | None) -> str:
    return "n/a" if v is None else f"{1e3 * v:.1f}"


def _quality_cells(q: dict) -> str:
    """crossings (most, end) | penetration mm (most, end) | rms speed at the end."""
    return (f"{q['crossings_max']} ({q['crossings_end']}) | {_mm(q['penetration_max'])} "
            f"({_mm(q['penetration_end'])}) | {q['rms_speed_end']:.3f}")


def markdown(res: dict) -> str:
    mode = "fixed steps (one per frame)" if res["fixed"] else "default step control (adaptive)"
    tol = res.get("penetration_tolerance", PENETRATION_TOL)
    out = [f"ms per 1/60 s frame, median of {res['pairs']} alternating pairs; ours: tolerance "
           f"{res['tolerance'] or 1e-3:g}, {mode}, {res['threads'] or 1} solver thread(s), preconditioner "
           f"{_preconditioner_text(res)}, contact method {res.get('method') or 'the default (rounds)'}; "
           + ("Blender not installed: our side only." if res["blender_version"] == "not installed" else
              f"Blender {res['blender_version']}, one thread, CG capped at 100 iterations / 1e-2 residual, "
              f"bending model {res.get('blender_bending', 'linear').upper()}, quality (steps per frame) "
              f"{', '.join(str(q) for q in res.get('blender_quality', [1]))}, collision_quality "
              f"{res.get('blender_collision_quality') or 'its default (2)'}.")
           + _friction_text(res), "",
           f"Blender's reference per size: its cheapest quality (ms per frame) with no penetration (no point "
           f"deeper than {1e3 * tol:g} mm in an obstacle at any frame; the hanging cloth has none: the cheapest).",
           "",
           "| scene | grid | ours (ms/frame) | Blender (ms/frame) | ratio ours / Blender | Blender quality | "
           "Blender: crossings | ours: crossings | ours: CG its / frame | ours: solves / frame |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        # the counts of every attempt (adaptive stepping's discarded ones included) where they differ
        its, solves = f"{r['ours_iterations']:.1f}", f"{r['ours_solves']:.2f}"
        if r["ours_attempted_solves"] > r["ours_solves"]:
            its += f" ({r['ours_attempted_iterations']:.1f} all)"
            solves += f" ({r['ours_attempted_solves']:.2f} all)"
        if r["blender_ms"] is None:                 # Blender not installed (--quick): our side only
            theirs = "- | - | - | - "
        else:
            ref = r["blender"][str(r["blender_reference"])]
            q = f"{r['blender_reference']}" + ("" if r["blender_clean"] else " (all penetrate: the best)")
            theirs = f"{r['blender_ms']:.1f} | **{r['ratio']:.2f}** | {q} | {ref['crossings_max']} "
        out.append(f"| {r['scene']} | {r['n']}² | {r['ours_ms']:.1f} | {theirs}| {r['ours_crossings_max']} | "
                   f"{its} | {solves} |")
    out += ["", "ours: the accepted substeps' CG iterations and solves; in brackets those of every attempt, the "
            "steps adaptive stepping discarded and redid included (what the frames cost).", "",
            "Quality, judged by one script from both programs' positions at every frame (the worst over the pairs; "
            "rms speed: the median): crossings, edges through triangles sharing no vertex "
            "(`self_collision.count_crossings`), the most at any judged frame (at the end); penetration, the "
            "deepest point inside an obstacle's surface (sphere; floor and rod), mm, at any frame (at the end).", "",
            "| scene | grid | program | ms/frame | ratio ours / this | crossings | penetration (mm) | "
            "rms speed at the end (m/s) |", "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        out.append(f"| {r['scene']} | {r['n']}² | ours | {r['ours_ms']:.1f} | - | {_quality_cells(r['ours_quality'])} |")
        for q, b in r["blender"].items():
            out.append(f"| {r['scene']} | {r['n']}² | Blender, quality {q} | {b['ms']:.1f} | "
                       f"{r['ours_ms'] / b['ms']:.2f} | {_quality_cells(b)} |")
    return "\n".join(out) + "\n"


def _worst(runs: list[dict]) -> dict:
    """The judge's verdict over a program's pairs: the most crossings and the deepest penetration, the median
    rms speed."""
    def most(k: str) -> float | None:
        v = [r[k] for r in runs if r[k] is not None]
        return max(v) if v else None
    return {"crossings_max": most("crossings_max"), "crossings_end": most("crossings_end"),
            "penetration_max": most("penetration_max"), "penetration_end": most("penetration_end"),
            "rms_speed_end": statistics.median(r["rms_speed_end"] for r in runs)}


def merge(paths: list[Path], out: Path, name: str) -> int:
    """Combine the rows of earlier runs (one scene or size per run, as a shared machine allows) into one result:
    rows by scene and size (one given twice: the later file's), the settings of the first file. The runs must
    share the settings the header states."""
    from _common import write_outputs

    parts = [json.loads(Path(p).read_text()) for p in paths]
    for key in ("fixed", "tolerance", "threads", "method", "duration", "blender_bending", "blender_collision_quality",
                "friction_speed", "friction_pause"):
        if len({json.dumps(part.get(key)) for part in parts}) > 1:
            raise SystemExit(f"--merge: the runs differ in {key}: {[part.get(key) for part in parts]}")
    order = {k: i for i, k in enumerate(SIZES)}
    rows = sorted({(r["scene"], r["n"]): r for part in parts for r in part["rows"]}.values(),
                  key=lambda r: (order.get(r["scene"], 99), r["n"]))
    qs = sorted({q for part in parts for q in part.get("blender_quality", [1])})
    res = {**parts[0], "rows": rows, "blender_quality": qs, "pairs": min(part["pairs"] for part in parts),
           "merged_from": [str(p) for p in paths]}
    md = markdown(res)
    write_outputs(out, name, res, md)
    print(md)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["hanging", "drape", "crumple"], choices=list(SIZES))
    p.add_argument("--sizes", type=int, nargs="+", default=None,
                   help="default: hanging 32-256, drape and crumple 32-128")
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--duration", type=float, default=None,
                   help="s simulated (default: hanging and drape 2, crumple 1.5)")
    p.add_argument("--fixed", action="store_true", help="ours with one linearised step per frame (no adaptive)")
    p.add_argument("--tolerance", type=float, default=None, help="ours: solver tolerance (default 1e-3)")
    p.add_argument("--threads", type=int, default=None, help="ours: solver threads (default: the library's)")
    p.add_argument("--method", default=None, choices=["rounds", "barrier"],
                   help="ours, drape and crumple: collision.method (default: the scene's, rounds)")
    p.add_argument("--timeout", type=float, default=3600.0, help="s per run")
    p.add_argument("--friction-speed", type=float, default=None, metavar="EPS",
                   help="ours, drape and crumple: collision.friction_speed, m/s (0: Coulomb's states; default: "
                        "the library's)")
    p.add_argument("--friction-pause", type=int, default=0, metavar="P",
                   help="ours, drape and crumple: collision.friction_pause, steps (0: the default, none)")
    p.add_argument("--preconditioner", default=None, choices=["multigrid", "multigrid_smoothed"],
                   help="ours: solver.preconditioner (default: the library's, auto)")
    p.add_argument("--blender-quality", type=int, nargs="+", default=[1], metavar="Q",
                   help="Blender's quality (steps per frame) to run, each (default 1: one step per frame, as ours' "
                        "dt); per size the table compares ours with the cheapest that does not penetrate")
    p.add_argument("--blender-collision-quality", type=int, default=None, metavar="C",
                   help="Blender's collision_quality (collision passes per step; default its own, 2)")
    p.add_argument("--blender-bending", default="angular", choices=["angular", "linear"],
                   help="Blender's bending model (default angular: LINEAR's structural springs take no "
                        "compression; see the docstring)")
    p.add_argument("--judge-every", type=int, default=1, metavar="K",
                   help="count crossings at every K-th frame and the last (default 1: every frame)")
    p.add_argument("--out", default=str(Path("out") / "bench" / "vs_blender"), help="output folder (default out/bench/vs_blender; --out benchmarks/results replaces the committed result)")
    p.add_argument("--name", default="vs_blender", help="output file stem (default vs_blender)")
    p.add_argument("--quick", action="store_true",
                   help=f"every scene at {QUICK_SIZE}², one pair (without Blender: our side alone)")
    p.add_argument("--merge", nargs="+", type=Path, metavar="JSON",
                   help="run nothing: combine the rows of earlier runs' JSON files into one table (OUT/NAME)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--save", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.merge:
        return merge(a.merge, Path(a.out), a.name)
    if a.worker:
        print("RESULT " + json.dumps(run_ours(a.scenes[0], a.sizes[0], a.fixed, a.tolerance, a.threads,
                                              a.friction_speed, a.friction_pause, a.preconditioner, a.method,
                                              a.duration, a.save)))
        return 0
    if a.quick:
        a.sizes, a.pairs = a.sizes or [QUICK_SIZE], 1
    exe = shutil.which("blender")
    if exe is None:
        if not a.quick:
            print("vs_blender: error: Blender is not installed (no 'blender' on PATH; apt-get install blender "
                  "python3-numpy); --quick runs our side alone", file=sys.stderr)
            return 1
        print("vs_blender: Blender is not installed: our side only (apt-get install blender python3-numpy)",
              flush=True)
    rows, version = [], "not installed" if exe is None else "?"
    med = lambda rs, k: statistics.median(r[k] for r in rs) if rs else None  # noqa: E731
    tmp = Path(tempfile.mkdtemp(prefix="vs_blender_"))
    try:
        for kind in a.scenes:
            for n in (a.sizes or SIZES[kind]):
                o: list[dict] = []
                b: dict[int, list[dict]] = {q: [] for q in a.blender_quality}
                for k in range(a.pairs):
                    o.append(_judged(ours(kind, n, a, str(tmp / f"ours_{kind}_{n}_{k}.npy")), kind, a.judge_every))
                    line = (f"{kind} {n}²: ours {o[-1]['ms_per_frame']:.1f} ms/frame "
                            f"({o[-1]['iterations_per_frame']:.1f} its, {o[-1]['crossings_max']} crossings, "
                            f"penetration {_mm(o[-1]['penetration_max'])} mm)")
                    if exe is not None:
                        for q in a.blender_quality:
                            b[q].append(_judged(blender(exe, kind, n, a, q, str(tmp / f"blender_{kind}_{n}_{q}_{k}.npy")),
                                                kind, a.judge_every))
                            line += (f"; Blender q{q} {b[q][-1]['ms_per_frame']:.1f} ({b[q][-1]['crossings_max']} "
                                     f"crossings, penetration {_mm(b[q][-1]['penetration_max'])} mm)")
                    print(line, flush=True)
                row = {"scene": kind, "n": n, "ours_ms": med(o, "ms_per_frame"),
                       "ours_iterations": med(o, "iterations_per_frame"), "ours_solves": med(o, "solves_per_frame"),
                       "ours_attempted_iterations": med(o, "attempted_iterations_per_frame"),
                       "ours_attempted_solves": med(o, "attempted_solves_per_frame"),
                       "ours_rms_speed": med(o, "rms_speed"), "ours_quality": _worst(o),
                       "ours_runs": o, "blender_runs": [r for q in b for r in b[q]], "blender": {},
                       "blender_ms": None, "blender_rms_speed": None, "ratio": None, "blender_reference": None,
                       "blender_clean": None}
                row["ours_crossings_max"] = row["ours_quality"]["crossings_max"]
                if exe is not None:
                    version = b[a.blender_quality[0]][-1]["peer"]
                    for q in a.blender_quality:
                        row["blender"][str(q)] = {"quality": q, "ms": med(b[q], "ms_per_frame"), **_worst(b[q])}
                    qs = list(row["blender"].values())
                    clean = [v for v in qs if (v["penetration_max"] or 0.0) <= PENETRATION_TOL]
                    # the cheapest clean setting; if every one penetrates, the least penetrating
                    ref = min(clean, key=lambda v: v["ms"]) if clean else min(qs, key=lambda v: v["penetration_max"])
                    row.update(blender_reference=ref["quality"], blender_clean=bool(clean), blender_ms=ref["ms"],
                               blender_rms_speed=ref["rms_speed_end"], ratio=row["ours_ms"] / ref["ms"])
                    print(f"{kind} {n}²: ours {row['ours_ms']:.1f} ms/frame, Blender (quality {ref['quality']}"
                          f"{'' if clean else ', penetrating'}) {row['blender_ms']:.1f} ms/frame, "
                          f"ratio {row['ratio']:.2f}", flush=True)
                rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res = {"benchmark": "vs_blender", "quick": a.quick, "pairs": a.pairs, "fixed": a.fixed, "tolerance": a.tolerance,
           "threads": a.threads, "preconditioner": a.preconditioner, "method": a.method, "duration": a.duration,
           "blender_version": version, "blender_quality": a.blender_quality,
           "blender_collision_quality": a.blender_collision_quality, "blender_bending": a.blender_bending,
           "penetration_tolerance": PENETRATION_TOL, "judge_every": a.judge_every, "rows": rows}
    from _common import friction_used, machine, write_outputs

    res["friction_speed"], res["friction_newton"] = friction_used(a.friction_speed, None)
    res["friction_pause"] = a.friction_pause

    res["machine"] = machine()
    md = markdown(res)
    write_outputs(Path(a.out), a.name, res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
