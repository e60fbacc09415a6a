"""Cost of one backward-Euler step against resolution, split into assembly / solver setup / solve / rest.

Scene: the hanging cloth of ``examples/hanging.toml`` (or ``--scene``) at the
resolutions given, ``dt = 1/60`` s. For each resolution the first ``--warmup``
steps are run untimed, then ``--steps`` steps are timed one by one; the
figures are medians over those steps. The same run times one sparse mat-vec
with the step's own matrix (median of 50), so the step can be read as a number
of SpMVs, a ratio that does not depend on how busy the machine is.

Usage::

    python benchmarks/step_cost.py                      # 32, 64, 128
    python benchmarks/step_cost.py --sizes 32 64 128 256 --out benchmarks/results
    python benchmarks/step_cost.py --quick              # CI smoke: tiny and fast

Writes ``OUT/step_cost.json`` (raw figures, machine, versions) and
``OUT/step_cost.md`` (the table). Never asserts a time.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from _common import ROOT, default_out, ic, machine, spmv_seconds, write_outputs


def measure(scene: ic.Scene, n: int, dt: float, warmup: int, steps: int) -> dict:
    scene = scene.replace(cloth={"resolution": [n, n]}, simulation={"dt": dt, "integrator": "backward_euler"})
    sim = ic.Simulator(scene)
    sim.step(warmup)
    rows = []
    for _ in range(steps):
        t0 = time.perf_counter()
        sim.step(1)
        wall = time.perf_counter() - t0
        s = sim.last_step
        rows.append((wall, s.t_assembly, s.t_setup, s.t_solve, s.iterations, s.residual, s.converged))
    spmv = spmv_seconds(sim.model.system.csr)
    med = lambda k: statistics.median(r[k] for r in rows)  # noqa: E731
    step_ms = 1e3 * med(0)
    return {
        "resolution": n,
        "vertices": sim.model.n,
        "preconditioner": sim.integrator.precond.name,          # the one that ran ("auto" picks per size)
        "springs": int(len(sim.model.springs.i)),
        "matrix_nnz": int(sim.model.system.csr.nnz),
        "ms_step": step_ms,
        "ms_assembly": 1e3 * med(1),
        "ms_setup": 1e3 * med(2),
        "ms_solve": 1e3 * med(3),
        "ms_rest": step_ms - 1e3 * (med(1) + med(2) + med(3)),
        "iterations_median": med(4),
        "iterations_max": max(r[4] for r in rows),
        "residual_max": max(r[5] for r in rows),
        "unconverged_steps": sum(not r[6] for r in rows),
        "ms_spmv": 1e3 * spmv,
        "step_in_spmvs": step_ms / (1e3 * spmv),
        "max_strain": float(sim.model.springs.strain(sim.positions)[sim.model.springs.kinds["structural"]].max()),
    }


def markdown(res: dict) -> str:
    lines = [
        f"Backward Euler, dt = {res['dt']:.6g} s, scene `{res['scene']}`, steps {res['warmup']}-"
        f"{res['warmup'] + res['steps']} (median), preconditioner {res['preconditioner']}"
        + (f" (ran: {', '.join(sorted({r['preconditioner'] for r in res['rows'] if 'preconditioner' in r}))})"
           if any("preconditioner" in r for r in res["rows"]) else "") + ", "
        f"{res['machine']['cpus']} cores, BLAS threads 1.",
        "",
        "| grid | vertices | ms/step | assembly | precond setup | solve | rest | CG its (median/max) "
        "| max residual | SpMV ms | step / SpMV |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        lines.append(
            f"| {r['resolution']}² | {r['vertices']} | {r['ms_step']:.1f} | {r['ms_assembly']:.1f} | "
            f"{r['ms_setup']:.1f} | {r['ms_solve']:.1f} | {r['ms_rest']:.1f} | "
            f"{r['iterations_median']:.0f}/{r['iterations_max']} | {r['residual_max']:.2g} | "
            f"{r['ms_spmv']:.3f} | {r['step_in_spmvs']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(ROOT / "examples" / "hanging.toml"))
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--dt", type=float, default=1 / 60)
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--preconditioner", choices=["auto", "multigrid", "multigrid_smoothed", "block_jacobi"],
                   default=None,
                   help="override the scene's solver.preconditioner")
    p.add_argument("--out", default=default_out('step_cost'), help="output folder (default out/bench/step_cost; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="tiny sizes and few steps (CI smoke test)")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.warmup, a.steps = [8, 16], 2, 3
    scene = ic.load_scene(a.scene)
    if a.preconditioner:
        scene = scene.replace(solver={"preconditioner": a.preconditioner})
    rows = []
    for n in a.sizes:
        r = measure(scene, n, a.dt, a.warmup, a.steps)
        rows.append(r)
        print(f"{n:4d}²: {r['ms_step']:8.1f} ms/step  (assembly {r['ms_assembly']:.1f}, setup {r['ms_setup']:.1f}, "
              f"solve {r['ms_solve']:.1f}, rest {r['ms_rest']:.1f})  CG {r['iterations_median']:.0f} its  "
              f"= {r['step_in_spmvs']:.0f} SpMVs", flush=True)
    res = {
        "benchmark": "step_cost",
        "scene": Path(a.scene).name,
        "dt": a.dt,
        "preconditioner": scene.data["solver"]["preconditioner"],
        "warmup": a.warmup,
        "steps": a.steps,
        "quick": a.quick,
        "machine": machine(),
        "rows": rows,
    }
    md = markdown(res)
    write_outputs(Path(a.out), "step_cost", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
