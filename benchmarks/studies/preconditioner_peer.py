"""Ours on the shared peer scenes (``vs_blender.py``'s hanging and drape) with two preconditioners, one after
the other: ms per 1/60 s frame (process CPU time, 119 frames after the first), CG iterations and solves a frame,
the rms speed at the end. No Blender needed; for the ratio against Blender run ``vs_blender.py``.

Usage::

    python benchmarks/studies/preconditioner_peer.py --sizes 32 64 128 --out DIR    # writes DIR/preconditioner_peer.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, ic, machine
from vs_blender import scene

PRECONDITIONERS = ("multigrid", "multigrid_smoothed")


def run(kind: str, n: int, fixed: bool, pc: str) -> dict:
    d = scene(kind, n, fixed, 0.0)
    d.setdefault("solver", {})["preconditioner"] = pc
    sim = ic.Simulator(ic.Scene.from_dict(d))
    sim.step(1)                                   # the first frame: kernels loaded from numba's cache
    its = solves = 0
    t0 = time.process_time()
    for _ in range(119):
        sim.step(1)
        its += sim.last_step.iterations
        solves += sim.last_step.solves
    cpu = time.process_time() - t0
    v = sim.velocities
    return {"scene": kind, "n": n, "fixed_steps": fixed, "preconditioner": pc, "ms_per_frame": 1e3 * cpu / 119,
            "iterations_per_frame": its / 119, "solves_per_frame": solves / 119,
            "rms_speed": float(np.sqrt(np.mean(np.sum(v ** 2, axis=1))))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--out", default=default_out('preconditioner_peer'), help="output folder (default out/bench/preconditioner_peer)")
    a = p.parse_args(argv)
    rows = []
    for kind, fixed in (("hanging", True), ("hanging", False), ("drape", False)):
        for n in a.sizes:
            for pc in PRECONDITIONERS:
                r = run(kind, n, fixed, pc)
                rows.append(r)
                print(f"{kind:8s} {n:4d}² {'fixed' if fixed else 'adaptive':8s} {pc:19s} {r['ms_per_frame']:8.1f} ms "
                      f"its {r['iterations_per_frame']:6.1f} solves {r['solves_per_frame']:.2f} "
                      f"rms {r['rms_speed']:.4f} m/s", flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "preconditioner_peer.json").write_text(json.dumps({"rows": rows, "machine": machine()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
