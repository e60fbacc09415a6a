"""implicit_cloth against Blender 3.4's cloth, side by side in one run: ms per 1/60 s frame and the ratio per size.

The scene (SI units; the shared peer scene): a 1 m x 1 m cloth of n x n vertices, 0.1 kg, springs
k = 1000 (structural) / 333.3 (shear) / 10 (bend) N/m, damping 0.01 N*s/m, no air drag, gravity, dt = 1/60 s,
2 s simulated (120 frames). "hanging": the two top corners pinned. "drape": dropped from z = 0.5 m onto a
sphere r = 0.3 m (friction 0.3, contact distance 0.01 m in all). Blender's cloth is set up from the same SI
scene by ``_blender_cloth.py`` (run inside Blender; its docstring gives the unit mapping); its solver is
one thread with CG capped at 100 iterations and a 1e-2 residual (its error is not bounded). Ours: backward
Euler with the default solver (multigrid PCG, tolerance 1e-3 on the error of dv) and the default step control
(adaptive: a step that breaks the energy balance or the strain bound is redone), or ``--fixed`` (one
linearised step per frame, like Blender). Both run in their own processes, alternating (ours, Blender, ours,
...), ``--pairs`` pairs per size and scene; the medians are compared. Timed: the frames after the first
(start-up, the first frame and, for ours, the first load of the compiled kernels, are not). Each run also
reports the lowest point, the rms speed of the last frame (m/s; "at rest" below 0.01) and, for ours, the CG
iterations and solves per frame.

Usage::

    python benchmarks/vs_blender.py                                   # hanging 32..256, drape 32..128
    python benchmarks/vs_blender.py --scenes drape --sizes 32 64 --pairs 1
    python benchmarks/vs_blender.py --fixed --threads 2
    python benchmarks/vs_blender.py --scenes hanging --fixed --preconditioner multigrid_smoothed
    python benchmarks/vs_blender.py --quick                           # both scenes at 8², one pair

Needs Blender (``apt-get install blender python3-numpy``: Debian's 3.4 and the numpy its Python uses);
without it the script says so on stderr and exits 1, except with ``--quick``, which then runs our side alone
(the Blender columns "-"). Writes ``OUT/NAME.{json,md}`` (``--name``, default vs_blender; ``--out``, default
out/bench/vs_blender). Never asserts a time.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
FPS = 60
SIZES = {"hanging": [32, 64, 128, 256], "drape": [32, 64, 128]}
QUICK_SIZE = 8   # --quick: both scenes at 8², one pair


def scene(kind: str, n: int, fixed: bool = False, friction_speed: float | None = None,
          friction_pause: int = 0) -> dict:
    """The benchmark scene as an implicit_cloth scene table (see the module docstring)."""
    springs = {"structural": {"stiffness": 1000.0, "damping": 0.01},
               "shear": {"stiffness": 1000.0 / 3.0, "damping": 0.01},
               "bend": {"stiffness": 10.0, "damping": 0.0}}
    d: dict = {"simulation": {"integrator": "backward_euler", "dt": 1 / FPS, "duration": 2.0, "frame_rate": FPS},
               "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xy",
                         "center": [0.0, 0.0, 0.0 if kind == "hanging" else 0.5],
                         "pins": ["top_left", "top_right"] if kind == "hanging" else [], "springs": springs},
               "effects": {"gravity": [0.0, 0.0, -9.81]}}
    if kind == "drape":
        d["obstacles"] = [{"shape": "sphere", "radius": 0.3, "center": [0.0, 0.0, 0.0], "friction": 0.3}]
        d["collision"] = {"thickness": 0.005}
        if friction_speed is not None:
            d["collision"]["friction_speed"] = friction_speed
        if friction_pause:
            d["collision"]["friction_pause"] = friction_pause
    if fixed:
        d["simulation"]["adaptive"] = {"enabled": False}
    return d


def run_ours(kind: str, n: int, fixed: bool, tolerance: float | None, threads: int | None,
             friction_speed: float | None = None, friction_pause: int = 0, preconditioner: str | None = None) -> dict:
    """One run of ours in this process (the worker): the RESULT record."""
    import numpy as np

    sys.path.insert(0, str(HERE.parent))
    import implicit_cloth as ic
    from implicit_cloth import backend

    if threads is not None:
        backend.set_threads(threads)
    solver = {k: v for k, v in (("tolerance", tolerance), ("preconditioner", preconditioner)) if v} or None
    sim = ic.Simulator(ic.Scene.from_dict(scene(kind, n, fixed, friction_speed, friction_pause)),
                       solver=solver)
    frames = 120
    sim.step(1)                                   # the first frame: kernels loaded from numba's cache
    its = solves = all_its = all_solves = 0

    def book() -> None:
        nonlocal its, solves, all_its, all_solves
        li = sim.last_step
        its += li.iterations
        solves += li.solves
        all_its += li.attempted_iterations                         # discarded attempts included
        all_solves += li.attempted_solves

    t0 = time.perf_counter()
    for _ in range(frames - 2):
        sim.step(1)
        book()
    wall = time.perf_counter() - t0
    x_before = sim.positions.copy()
    t0 = time.perf_counter()
    sim.step(1)
    wall += time.perf_counter() - t0
    book()
    x = sim.positions
    timed = frames - 1
    return {"peer": f"implicit_cloth-{ic.__version__}", "scene": kind, "n": n, "frames": timed,
            "fixed_steps": fixed, "friction_speed": friction_speed,
            "friction_pause": friction_pause, "tolerance": sim.integrator.tolerance, "threads": backend.threads(),
            "accelerator": getattr(sim.integrator.precond, "accelerator", "numpy"),
            "preconditioner": sim.integrator.precond.name,
            "wall_s": wall, "ms_per_frame": 1e3 * wall / timed, "iterations_per_frame": its / timed,
            "solves_per_frame": solves / timed, "attempted_iterations_per_frame": all_its / timed,
            "attempted_solves_per_frame": all_solves / timed, "zmin": float(x[:, 2].min()),
            "rms_speed": float(np.sqrt(np.mean(np.sum((x - x_before) ** 2, axis=1))) * FPS),
            "finite": bool(np.isfinite(x).all())}


def _result(proc: subprocess.CompletedProcess) -> dict:
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError(f"no RESULT line (exit {proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


def ours(kind: str, n: int, a: argparse.Namespace) -> dict:
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
    return _result(subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout))


def blender(exe: str, kind: str, n: int, a: argparse.Namespace) -> dict:
    cmd = [exe, "-b", "--factory-startup", "-noaudio", "--python", str(HERE / "_blender_cloth.py"), "--",
           "--scene", kind, "--n", str(n)]
    return _result(subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout))


def _friction_text(res: dict) -> str:
    """The drape's friction in the header (none without drape rows)."""
    if "drape" not in {r["scene"] for r in res["rows"]}:
        return ""
    from _common import friction_text

    return friction_text(res, "Ours with ")


def _preconditioner_text(res: dict) -> str:
    """The preconditioner asked for and, where the runs say it, the one that ran (``auto`` picks per size)."""
    ran = sorted({o.get("preconditioner") for r in res["rows"] for o in r.get("ours_runs", [])} - {None})
    asked = res.get("preconditioner") or "the default (auto)"
    return asked + (f", ran: {', '.join(ran)}" if ran and ran != [asked] else "")


def markdown(res: dict) -> str:
    mode = "fixed steps (one per frame)" if res["fixed"] else "default step control (adaptive)"
    out = [f"ms per 1/60 s frame, median of {res['pairs']} alternating pairs; ours: tolerance "
           f"{res['tolerance'] or 1e-3:g}, {mode}, {res['threads'] or 1} solver thread(s), preconditioner "
           f"{_preconditioner_text(res)}; "
           + ("Blender not installed: our side only." if res["blender_version"] == "not installed" else
              f"Blender {res['blender_version']}, one thread, CG capped at 100 iterations / 1e-2 residual.")
           + _friction_text(res), "",
           "| scene | grid | ours (ms/frame) | Blender (ms/frame) | ratio ours / Blender | ours: CG its / frame | "
           "ours: solves / frame | ours: rms speed at the end (m/s) | Blender: rms speed (m/s) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        # the counts of every attempt (adaptive stepping's discarded ones included) where they differ
        its, solves = f"{r['ours_iterations']:.1f}", f"{r['ours_solves']:.2f}"
        if r["ours_attempted_solves"] > r["ours_solves"]:
            its += f" ({r['ours_attempted_iterations']:.1f} all)"
            solves += f" ({r['ours_attempted_solves']:.2f} all)"
        if r["blender_ms"] is None:                 # Blender not installed (--quick): our side only
            theirs = "- | - "
            speed = "-"
        else:
            theirs = f"{r['blender_ms']:.1f} | **{r['ratio']:.2f}** "
            speed = f"{r['blender_rms_speed']:.3f}"
        out.append(f"| {r['scene']} | {r['n']}² | {r['ours_ms']:.1f} | {theirs}| {its} | {solves} | "
                   f"{r['ours_rms_speed']:.3f} | {speed} |")
    out += ["", "ours: the accepted substeps' CG iterations and solves; in brackets those of every attempt, the "
            "steps adaptive stepping discarded and redid included (what the frames cost)."]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["hanging", "drape"], choices=["hanging", "drape"])
    p.add_argument("--sizes", type=int, nargs="+", default=None, help="default: hanging 32-256, drape 32-128")
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--fixed", action="store_true", help="ours with one linearised step per frame (no adaptive)")
    p.add_argument("--tolerance", type=float, default=None, help="ours: solver tolerance (default 1e-3)")
    p.add_argument("--threads", type=int, default=None, help="ours: solver threads (default: the library's)")
    p.add_argument("--timeout", type=float, default=3600.0, help="s per run")
    p.add_argument("--friction-speed", type=float, default=None, metavar="EPS",
                   help="ours, drape: collision.friction_speed, m/s (0: Coulomb's states; default: the library's)")
    p.add_argument("--friction-pause", type=int, default=0, metavar="P",
                   help="ours, drape: collision.friction_pause, steps (0: the default, none)")
    p.add_argument("--preconditioner", default=None, choices=["multigrid", "multigrid_smoothed"],
                   help="ours: solver.preconditioner (default: the library's, auto)")
    p.add_argument("--out", default=str(Path("out") / "bench" / "vs_blender"), help="output folder (default out/bench/vs_blender; --out benchmarks/results replaces the committed result)")
    p.add_argument("--name", default="vs_blender", help="output file stem (default vs_blender)")
    p.add_argument("--quick", action="store_true",
                   help=f"both scenes at {QUICK_SIZE}², one pair (without Blender: our side alone)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        print("RESULT " + json.dumps(run_ours(a.scenes[0], a.sizes[0], a.fixed, a.tolerance, a.threads,
                                              a.friction_speed, a.friction_pause, a.preconditioner)))
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
    for kind in a.scenes:
        for n in (a.sizes or SIZES[kind]):
            o, b = [], []
            for _ in range(a.pairs):
                o.append(ours(kind, n, a))
                if exe is not None:
                    b.append(blender(exe, kind, n, a))
                print(f"{kind} {n}²: ours {o[-1]['ms_per_frame']:.1f} ms/frame ({o[-1]['iterations_per_frame']:.1f} "
                      f"its)" + (f", Blender {b[-1]['ms_per_frame']:.1f}" if b else ""), flush=True)
            if b:
                version = b[-1]["peer"]
            row = {"scene": kind, "n": n, "ours_ms": med(o, "ms_per_frame"), "blender_ms": med(b, "ms_per_frame"),
                   "ours_iterations": med(o, "iterations_per_frame"), "ours_solves": med(o, "solves_per_frame"),
                   "ours_attempted_iterations": med(o, "attempted_iterations_per_frame"),
                   "ours_attempted_solves": med(o, "attempted_solves_per_frame"),
                   "ours_rms_speed": med(o, "rms_speed"), "blender_rms_speed": med(b, "rms_speed"),
                   "ours_runs": o, "blender_runs": b}
            row["ratio"] = row["ours_ms"] / row["blender_ms"] if b else None
            rows.append(row)
            if b:
                print(f"{kind} {n}²: ours {row['ours_ms']:.1f} ms/frame, Blender {row['blender_ms']:.1f} ms/frame, "
                      f"ratio {row['ratio']:.2f}", flush=True)
    res = {"benchmark": "vs_blender", "quick": a.quick, "pairs": a.pairs, "fixed": a.fixed, "tolerance": a.tolerance,
           "threads": a.threads, "preconditioner": a.preconditioner, "blender_version": version, "rows": rows}
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
