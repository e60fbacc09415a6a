"""Bit-for-bit digests of short runs: every example and the benchmarks' quick scenes, on both back-ends.

A refactoring that must not change a number is checked by taking these digests before
and after it and comparing them: each scene is run (shortened to a few steps where the
full run would be slow) with ``Simulator.run`` and reduced to two SHA-256 digests, one
of the trajectory (positions and times, as raw float64 bytes) and one of the report's
numbers (every entry except wall-clock timings, which differ from run to run).

    python benchmarks/tools/digests.py                          # print a table, both back-ends
    python benchmarks/tools/digests.py --write out/digests.json
    python benchmarks/tools/digests.py --compare out/digests.json   # exit 1 on any difference

Each back-end runs in its own process with ``IMPLICIT_CLOTH_ACCELERATOR`` set (numpy,
numba); a back-end that is not installed is reported as skipped.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
BACKENDS = ("numpy", "numba")
MAX_DURATION = 0.3      # s: examples are cut to at most this much simulated time
# report entries that measure the machine, not the run
TIMING_KEYS = {"wall_time", "timing", "t_assembly", "t_setup", "t_solve", "t_other", "t_collision", "time",
               "mean_time_per_step", "broad_phase_time", "threading_layer"}


def _report_numbers(obj: Any, path: str = "") -> list[str]:
    """Canonical ``path=value`` lines of a report, timings left out (``frames.time`` is kept)."""
    out: list[str] = []
    if isinstance(obj, dict):
        for k in sorted(obj):
            p = f"{path}.{k}" if path else str(k)
            if k in TIMING_KEYS and p != "frames.time":
                continue
            out += _report_numbers(obj[k], p)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out += _report_numbers(v, f"{path}[{i}]")
    elif isinstance(obj, float):
        out.append(f"{path}={obj.hex() if math.isfinite(obj) else repr(obj)}")
    else:
        out.append(f"{path}={obj!r}")
    return out


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def digest_run(sim: Any, duration: float, frame_rate: float | None = None) -> dict[str, Any]:
    """Run ``sim`` for ``duration`` s and digest its trajectory and report (a diverged run is digested too)."""
    import numpy as np

    import implicit_cloth as ic

    try:
        traj = sim.run(duration=duration, frame_rate=frame_rate)
    except ic.DivergenceError as err:
        traj = err.trajectory
    report = traj.report.to_dict() if hasattr(traj.report, "to_dict") else traj.report
    pos = np.ascontiguousarray(traj.positions, dtype=np.float64)
    times = np.ascontiguousarray(traj.times, dtype=np.float64)
    return {
        "frames": int(len(times)),
        "status": report.get("status"),
        "accelerator": (report.get("solver") or {}).get("accelerator"),
        "trajectory": _sha(pos.tobytes() + times.tobytes()),
        "report": _sha("\n".join(_report_numbers(report)).encode()),
    }


def scenes() -> dict[str, Callable[[], dict[str, Any]]]:
    """Name -> a thunk that runs the scene and returns its digests."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))   # the benchmarks import each other by name
    import implicit_cloth as ic

    table: dict[str, Callable[[], dict[str, Any]]] = {}

    def example(path: Path) -> Callable[[], dict[str, Any]]:
        def run() -> dict[str, Any]:
            scene = ic.load_scene(path)
            sim = ic.Simulator(scene)
            return digest_run(sim, min(scene.data["simulation"]["duration"], MAX_DURATION))
        return run

    for path in sorted(EXAMPLES.glob("*.toml")):
        if path.name == "sweep.toml":
            continue
        table[f"example/{path.stem}"] = example(path)
        if path.stem == "stiff_large_step":
            table["example/stiff_large_step+symplectic_euler"] = (
                lambda p=path: digest_run(ic.Simulator(ic.load_scene(p), integrator="symplectic_euler"), 0.2))

    # the sweep's base with its fixed overrides, at the corners of its sweep
    sweep_base = ic.load_scene(EXAMPLES / "hanging.toml").replace(cloth={"resolution": [16, 16]})
    for integrator in ("backward_euler", "bdf2", "symplectic_euler"):
        for dt, k in ((0.005, 1e3), (0.02, 2e4)):
            name = f"sweep/{integrator}/dt={dt:g}/k={k:g}"
            table[name] = (lambda i=integrator, dt=dt, k=k: digest_run(ic.Simulator(
                sweep_base.replace(cloth={"springs": {"structural": {"stiffness": k, "damping": 0.1}}}),
                integrator=i, dt=dt), 0.1))

    table.update(_bench_scenes(ic, drape=ic.load_scene(EXAMPLES / "drape_sphere.toml")))
    return table


def _bench_scenes(ic: Any, drape: Any) -> dict[str, Callable[[], dict[str, Any]]]:
    """The benchmarks' quick scenes, shortened to a few steps each."""
    from benchmarks import accuracy_cost, damping, stability
    from benchmarks._common import hanging_stiff

    table: dict[str, Callable[[], dict[str, Any]]] = {}
    # benchmarks: scaling / step_cost / headline / stopping_rule (hanging stiff cloth, both preconditioners)
    for n in (8, 16):
        for pre in ("multigrid", "block_jacobi"):
            table[f"bench/hanging_stiff/{n}/{pre}"] = (
                lambda n=n, pre=pre: digest_run(ic.Simulator(hanging_stiff(n, preconditioner=pre)), 5 / 60))
    table["bench/hanging_stiff/12/k=1e2/tol=1e-6"] = (
        lambda: digest_run(ic.Simulator(hanging_stiff(12, 1e2, tolerance=1e-6)), 5 / 60))
    # accuracy_cost (hanging, wind) and damping: every integrator at a small step
    for name in accuracy_cost.SCENES:
        for integrator in ic.INTEGRATORS:
            dt = 1 / 240 if integrator in ("backward_euler", "bdf2") else 1 / 960
            table[f"bench/accuracy_cost/{name}/{integrator}"] = (
                lambda name=name, i=integrator, dt=dt: digest_run(ic.Simulator(
                    accuracy_cost.scene(6, name), integrator=i, dt=dt, adaptive={"enabled": False}), 0.05, 60))
    for d in ("off", "on"):
        for integrator in ("backward_euler", "bdf2", "verlet"):
            table[f"bench/damping/{d}/{integrator}"] = (
                lambda d=d, i=integrator: digest_run(ic.Simulator(
                    damping.scene(6, d), integrator=i, dt=1 / 120 if i != "verlet" else 1 / 960), 0.1, 60))
    for k in (1e2, 1e4):
        table[f"bench/stability/8/k={k:g}"] = (lambda k=k: digest_run(ic.Simulator(stability.scene(8, k)), 5 / 60))
    # collision and stopping_rule: the sphere drape at small sizes
    for n in (8, 12):
        table[f"bench/collision/drape_sphere/{n}"] = (
            lambda n=n: digest_run(ic.Simulator(drape.replace(cloth={"resolution": [n, n]})), 0.3))
    return table


def _run_backend(backend: str, only: list[str] | None) -> dict[str, Any]:
    """Digests of every scene in this process (the accelerator is taken from the environment)."""
    warnings.simplefilter("ignore")
    out: dict[str, Any] = {}
    for name, run in scenes().items():
        if only and not any(s in name for s in only):
            continue
        try:
            out[name] = run()
        except Exception as exc:   # a scene that cannot run is a difference too
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
        print(f"  {backend:6s} {name:55s} {out[name].get('trajectory', out[name].get('error'))[:16]}",
              file=sys.stderr, flush=True)
    return out


def collect(backends: list[str], only: list[str] | None = None) -> dict[str, Any]:
    """``{backend: {scene: digests}}``, each back-end in a fresh process."""
    result: dict[str, Any] = {}
    for b in backends:
        if b == "numba" and importlib.util.find_spec("numba") is None:
            result[b] = {"skipped": "numba is not installed"}
            continue
        env = dict(os.environ, IMPLICIT_CLOTH_ACCELERATOR=b, PYTHONHASHSEED="0")
        cmd = [sys.executable, __file__, "--child", b] + (["--only", *only] if only else [])
        p = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, check=True)
        result[b] = json.loads(p.stdout)
    return result


def compare(ref: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Lines naming every scene whose digests differ or that is missing on one side."""
    diffs = []
    for b in sorted(set(ref) | set(new)):
        r, n = ref.get(b, {}), new.get(b, {})
        if "skipped" in r or "skipped" in n:
            diffs.append(f"{b}: skipped ({r.get('skipped') or n.get('skipped')})") if r != n else None
            continue
        for s in sorted(set(r) | set(n)):
            if r.get(s) != n.get(s):
                diffs.append(f"{b} {s}: {r.get(s)} != {n.get(s)}")
    return diffs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS)
    p.add_argument("--only", nargs="+", default=None, help="run only scenes whose name contains one of these")
    p.add_argument("--write", type=Path, default=None, help="write the digests (JSON) here")
    p.add_argument("--compare", type=Path, default=None, help="compare with digests written by --write")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        json.dump(_run_backend(a.child, a.only), sys.stdout, indent=1, sort_keys=True)
        return 0
    res = collect(a.backends, a.only)
    if a.write:
        a.write.parent.mkdir(parents=True, exist_ok=True)
        a.write.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
    n = sum(len(v) for v in res.values() if "skipped" not in v)
    if a.compare:
        ref = json.loads(a.compare.read_text())
        if a.only:
            ref = {b: ({s: d for s, d in v.items() if any(o in s for o in a.only)} if "skipped" not in v else v)
                   for b, v in ref.items() if b in a.backends}
        else:
            ref = {b: v for b, v in ref.items() if b in a.backends}
        diffs = compare(ref, res)
        for line in diffs:
            print("DIFFERS", line)
        print(f"{n} runs on {', '.join(a.backends)}: {'all identical' if not diffs else f'{len(diffs)} differ'}")
        return 1 if diffs else 0
    print(f"{n} runs on {', '.join(a.backends)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
