"""Cost of the collision stage per step against the rest of the step, on the drape-on-sphere scene.

Scene: ``examples/drape_sphere.toml`` (or ``--scene``) at the resolutions given,
with its ``dt``. For each resolution the first ``--warmup`` steps are run untimed
(the cloth lands and wraps the sphere), then ``--steps`` steps are timed one by
one; the figures are medians over those steps: the whole step, its collision
stage (detection, response, contact bookkeeping) and the rest (assembly,
preconditioner, solve, ...), with the collision stage's share, the candidate
and contact counts and the resting contacts constrained in the solve.

Usage::

    python benchmarks/collision.py                      # 32, 64, 128
    python benchmarks/collision.py --sizes 32 64 --out benchmarks/results
    python benchmarks/collision.py --quick              # CI smoke: tiny and fast

Writes ``OUT/collision.json`` and ``OUT/collision.md``. Never asserts a time.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from _common import ROOT, default_out, ic, machine, write_outputs


def measure(scene: ic.Scene, n: int, warmup: int, steps: int) -> dict:
    scene = scene.replace(cloth={"resolution": [n, n]})
    sim = ic.Simulator(scene)
    sim.step(warmup)
    rows = []
    for _ in range(steps):
        t0 = time.perf_counter()
        sim.step(1)
        wall = time.perf_counter() - t0
        c = sim.last_step.collision
        rows.append((wall, c.t_collision, c.candidates, c.contacts, c.resting, c.rounds, c.failsafe,
                     c.max_penetration))
    med = lambda k: statistics.median(r[k] for r in rows)  # noqa: E731
    step_ms, col_ms = 1e3 * med(0), 1e3 * med(1)
    return {
        "resolution": n,
        "vertices": sim.model.n,
        "ms_step": step_ms,
        "ms_collision": col_ms,
        "ms_rest": step_ms - col_ms,
        "collision_share": col_ms / step_ms,
        "candidates_median": med(2),
        "contacts_median": med(3),
        "resting_median": med(4),
        "rounds_max": max(r[5] for r in rows),
        "failsafe_vertices": sum(r[6] for r in rows),
        "max_penetration": max(r[7] for r in rows),
    }


def markdown(res: dict) -> str:
    lines = [
        f"Drape on a sphere (`{res['scene']}`), dt = {res['dt']:.6g} s, steps {res['warmup']}-"
        f"{res['warmup'] + res['steps']} (median; the cloth rests on the sphere), {res['machine']['cpus']} cores.",
        "",
        "| grid | vertices | ms/step | collision ms | rest ms | collision share | candidates | contacts "
        "| resting (constrained) | rounds (max) | fail-safe vertices | max penetration m |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        lines.append(
            f"| {r['resolution']}² | {r['vertices']} | {r['ms_step']:.1f} | {r['ms_collision']:.1f} | "
            f"{r['ms_rest']:.1f} | {100 * r['collision_share']:.0f} % | {r['candidates_median']:.0f} | "
            f"{r['contacts_median']:.0f} | {r['resting_median']:.0f} | {r['rounds_max']} | "
            f"{r['failsafe_vertices']} | {r['max_penetration']:.2g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(ROOT / "examples" / "drape_sphere.toml"))
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--warmup", type=int, default=60, help="untimed steps first (the cloth lands)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--out", default=default_out('collision'), help="output folder (default out/bench/collision; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="tiny sizes and few steps (CI smoke test)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.warmup, a.steps = [8, 12], 10, 3
    scene = ic.load_scene(a.scene)
    rows = []
    for n in a.sizes:
        r = measure(scene, n, a.warmup, a.steps)
        rows.append(r)
        print(f"{n:4d}²: {r['ms_step']:8.1f} ms/step, collision {r['ms_collision']:.1f} ms "
              f"({100 * r['collision_share']:.0f} %), rest {r['ms_rest']:.1f} ms, "
              f"{r['candidates_median']:.0f} candidates, {r['contacts_median']:.0f} contacts, "
              f"{r['resting_median']:.0f} resting", flush=True)
    res = {
        "benchmark": "collision",
        "scene": Path(a.scene).name,
        "dt": scene.data["simulation"]["dt"],
        "warmup": a.warmup,
        "steps": a.steps,
        "quick": a.quick,
        "machine": machine(),
        "rows": rows,
    }
    md = markdown(res)
    write_outputs(Path(a.out), "collision", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
