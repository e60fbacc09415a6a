"""Where the shared drape's frames go, phase by phase: the fall, the landing, the cloth at rest.

The shared drape of ``benchmarks/vs_blender.py`` (1 m, 0.1 kg, k = 1000 / 333 / 10 N/m, dropped from 0.5 m onto
a sphere r = 0.3 m with friction 0.3, thickness 5 mm, dt 1/60 s, the default step control), timed frame by frame
in one process after its first frame. Each frame is read from the simulator's own figures
(``Simulator.last_step``: solves, CG iterations, the set-up's and the solves' time; its ``collision``: the
collider's rounds, the contacts held) and split into three phases by what the cloth does:

* **fall**: the frames before the first contact;
* **landing**: from the first contact until the cloth is at rest;
* **rest**: from the first frame after which the cloth's rms speed stays below ``--rest-speed`` (m/s).

Per phase: ms a frame (mean), its split into the multigrid's set-up, the PCG solves and the rest (assembly,
contact detection, the collider, the step control), the linear solves, the collider's rounds and the CG
iterations a frame. A contact step solves its rounds (solve, detect, release the contacts that pull, again),
then the friction's Newton corrections and the balance-driven refinement (``collision.newton_iterations``):
``solves - rounds`` counts those last two. Solves and iterations include the attempts the step control discarded
(what the frames cost). Never asserts a time.

Usage::

    python benchmarks/studies/drape_phases.py --sizes 32 64 128 --threads 2
    python benchmarks/studies/drape_phases.py --quick --out OUT          # CI smoke: tiny and fast

Writes ``OUT/drape_phases.json`` (per-frame figures, phases, machine) and ``OUT/drape_phases.md`` (the table);
``--quick`` writes ``drape_phases_quick.*``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, ic, machine, write_outputs
from vs_blender import FPS, scene

PHASES = ("fall", "landing", "rest")
#: per-frame figures kept (``frames`` rows of the result)
FIELDS = ("ms", "setup_ms", "solve_ms", "solves", "rounds", "iterations", "resting", "rms_speed")


def run(n: int, frames: int, threads: int | None) -> dict:
    """The drape at ``n``² for ``frames`` frames: per-frame figures (the first frame untimed)."""
    from implicit_cloth import backend

    if threads is not None:
        backend.set_threads(threads)
    sim = ic.Simulator(ic.Scene.from_dict(scene("drape", n)))
    sim.step(1)
    rows = []
    for _ in range(frames - 1):
        t0 = time.perf_counter()
        sim.step(1)
        wall = time.perf_counter() - t0
        s = sim.last_step
        col = s.collision
        v = sim.velocities
        rows.append({"ms": 1e3 * wall, "setup_ms": 1e3 * s.t_setup, "solve_ms": 1e3 * s.t_solve,
                     "solves": s.solves + s.discarded_solves, "rounds": col.rounds if col is not None else 0,
                     "iterations": s.iterations + s.discarded_iterations,
                     "resting": col.resting if col is not None else 0,
                     "rms_speed": float(np.sqrt(np.mean(np.einsum("ij,ij->i", v, v))))})
    return {"n": n, "vertices": sim.model.n, "preconditioner": sim.integrator.precond.name,
            "threads": backend.threads(), "frames": rows}


def phases(rows: list[dict], rest_speed: float) -> dict[str, tuple[int, int]]:
    """Frame ranges ``[start, stop)`` of the three phases (empty ranges where a phase did not happen)."""
    n = len(rows)
    touch = next((i for i, r in enumerate(rows) if r["resting"] > 0), n)
    moving = [i for i, r in enumerate(rows) if r["rms_speed"] >= rest_speed]
    rest = max(touch, moving[-1] + 1 if moving else 0)
    return {"fall": (0, touch), "landing": (touch, rest), "rest": (rest, n)}


def summary(rows: list[dict], span: tuple[int, int]) -> dict:
    """Means a frame over ``rows[span[0]:span[1]]``."""
    sel = rows[span[0]:span[1]]
    if not sel:
        return {"frames": 0}
    mean = {k: float(np.mean([r[k] for r in sel])) for k in FIELDS}
    mean["other_ms"] = mean["ms"] - mean["setup_ms"] - mean["solve_ms"]
    mean["frames"] = len(sel)
    mean["first"] = span[0] + 2                    # the frame number (the untimed first frame is 1)
    mean["ms_share"] = float(sum(r["ms"] for r in sel) / max(sum(r["ms"] for r in rows), 1e-300))
    return mean


def markdown(res: dict) -> str:
    lines = [f"The shared drape (`benchmarks/vs_blender.py`'s scene), {res['frames']} frames of 1/{FPS} s, the "
             f"default step control, {res['threads']} solver thread(s); frames 2-{res['frames']} timed one by one in "
             f"one process; at rest: rms speed below {res['rest_speed']:g} m/s from then on. A frame's solves "
             "beyond its rounds are the friction's Newton corrections and the balance-driven refinement.",
             "",
             "| grid | phase | frames | share of the time | ms a frame | set-up | solves | other | linear solves | "
             "rounds | CG its | its a solve |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        for ph in PHASES:
            s = r["phases"][ph]
            if not s["frames"]:
                lines.append(f"| {r['n']}² | {ph} | 0 | | | | | | | | | |")
                continue
            lines.append(
                f"| {r['n']}² | {ph} (from {s['first']}) | {s['frames']} | {100 * s['ms_share']:.0f} % | "
                f"{s['ms']:.1f} | {s['setup_ms']:.1f} | {s['solve_ms']:.1f} | {s['other_ms']:.1f} | "
                f"{s['solves']:.2f} | {s['rounds']:.2f} | {s['iterations']:.1f} | "
                f"{s['iterations'] / max(s['solves'], 1e-300):.1f} |")
        lines.append(f"| {r['n']}² | whole run | {len(r['frames'])} | 100 % | {r['ms_frame']:.1f} | | | | | | | |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--frames", type=int, default=120, help="frames of 1/60 s (default 120: 2 s, as vs_blender)")
    p.add_argument("--threads", type=int, default=None, help="solver threads (default: the library's)")
    p.add_argument("--rest-speed", type=float, default=0.01, help="rms speed (m/s) below which the cloth is at rest")
    p.add_argument("--out", default=default_out('drape_phases'), help="output folder (default out/bench/drape_phases)")
    p.add_argument("--quick", action="store_true", help="a 16² drape for 40 frames (CI smoke test)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.frames = [16], 40
    if a.frames < 2:
        p.error(f"--frames: at least 2 (the first is not timed), got {a.frames}")
    rows = []
    for n in a.sizes:
        r = run(n, a.frames, a.threads)
        r["phases"] = {ph: summary(r["frames"], span) for ph, span in phases(r["frames"], a.rest_speed).items()}
        r["ms_frame"] = float(np.mean([f["ms"] for f in r["frames"]]))
        rows.append(r)
        print(f"{n:4d}²: {r['ms_frame']:.1f} ms a frame; " + "; ".join(
            f"{ph} {s['frames']} frames {s.get('ms', 0.0):.1f} ms" for ph, s in r["phases"].items()), flush=True)
    res = {"benchmark": "drape_phases", "quick": a.quick, "frames": a.frames, "rest_speed": a.rest_speed,
           "threads": rows[0]["threads"] if rows else a.threads, "machine": machine(), "rows": rows}
    md = markdown(res)
    write_outputs(Path(a.out), "drape_phases_quick" if a.quick else "drape_phases", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
