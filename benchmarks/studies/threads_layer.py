"""Two threads against one under each of numba's threading layers: short parallel regions and whole steps.

The compiled solver's parallel regions are short (one level's pass of a V-cycle: 0.05-1.3 ms at 256²; a CG
iteration opens about twenty). Whether a second thread helps depends on how soon it joins a region, which the
threading layer decides: numba takes TBB's when ``libtbb`` is installed (Blender's Debian package installs it),
else GNU OpenMP's, else its own work queue; ``implicit_cloth.kernels.layer`` now asks for OpenMP's first, its
threads sleeping between regions (``OMP_WAIT_POLICY=PASSIVE``) rather than spinning first (libgomp's default,
here ``omp-spin``: ``GOMP_SPINCOUNT=300000``).

For each variant (its own processes: numba picks the layer once per process, at the first parallel region),
alternating variants and thread counts within each repetition, this measures

* a compute-bound region (20 fused multiply-adds an element, no memory traffic to speak of) of three lengths,
  on one and on two threads: what the layer's start-up and hand-out of the work cost;
* the shared hanging scene (``vs_blender.py``'s, one linearised step a frame, the default solver) at each
  size, ms a step on one and on two threads, and whether both give the same positions to the last bit;
* with ``--busy`` (default on), the same steps while another process keeps one core busy (a Python loop):
  what a second thread costs when the machine has no second core free.

Usage::

    python benchmarks/studies/threads_layer.py                      # 64², 128², 256², 3 repetitions (~15 min)
    python benchmarks/studies/threads_layer.py --quick              # CI smoke: 32², one repetition, no busy core

Writes ``OUT/threads_layer.{json,md}`` (``OUT`` = ``out/bench/threads_layer``, or ``--out``). Never asserts.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]   # benchmarks/: _common and vs_blender
#: variant -> (numba layer, extra environment)
VARIANTS = {"omp": ("omp", {}), "omp-spin": ("omp", {"GOMP_SPINCOUNT": "300000"}), "tbb": ("tbb", {}),
            "workqueue": ("workqueue", {})}
LAYERS = tuple(VARIANTS)
REGION_SIZES = (20_000, 200_000, 2_000_000)


def _regions() -> list[dict]:
    """The compute-bound region's ms on one and two threads, for each length (in this process's layer)."""
    import numba
    import numpy as np
    from numba import njit, prange

    @njit(parallel=True, fastmath={"contract"})
    def region(a, b, c, s):
        for i in prange(len(a)):
            t = b[i]
            for _ in range(20):
                t = t * s + c[i]
            a[i] = t

    rows = []
    for n in REGION_SIZES:
        a, b, c = np.zeros(n), np.ones(n), np.ones(n)
        ms = {}
        for th in (1, 2, 1, 2):
            numba.set_num_threads(th)
            region(a, b, c, 0.5)
            reps = max(20, 4_000_000 // n)
            t0 = time.perf_counter()
            for _ in range(reps):
                region(a, b, c, 0.5)
            ms.setdefault(th, []).append(1e3 * (time.perf_counter() - t0) / reps)
        rows.append({"elements": n, "ms_1": min(ms[1]), "ms_2": min(ms[2])})
    return rows


def _step(n: int, threads: int, steps: int) -> dict:
    """ms a step of the hanging peer scene at n² on ``threads`` threads (in this process's layer)."""
    sys.path.insert(0, str(HERE))
    import vs_blender

    import implicit_cloth as ic
    from implicit_cloth import backend
    from implicit_cloth.kernels import layer

    backend.set_threads(threads)
    sim = ic.Simulator(ic.Scene.from_dict(vs_blender.scene("hanging", n, fixed=True)))
    sim.step(2)                                           # set-up and kernels loaded from numba's cache
    t0 = time.perf_counter()
    sim.step(steps)
    ms = 1e3 * (time.perf_counter() - t0) / steps
    return {"ms_step": ms, "layer": layer.current(), "iterations": sim.last_step.iterations,
            "digest": hashlib.sha256(sim.positions.tobytes()).hexdigest()[:16]}


def _worker(args: list[str]) -> None:
    kind = args[0]
    out = _regions() if kind == "regions" else _step(int(args[1]), int(args[2]), int(args[3]))
    from implicit_cloth.kernels import layer

    print("RESULT " + json.dumps({"result": out, "layer": layer.current()}))


def _run(variant: str, args: list[str], busy: bool = False) -> dict | None:
    layer, extra = VARIANTS[variant]
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("NUMBA_THREADING_LAYER") and k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.update(NUMBA_THREADING_LAYER=layer, **extra)
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        if hog is not None:
            time.sleep(0.5)
        proc = subprocess.run([sys.executable, __file__, "--worker", *args], env=env, capture_output=True,
                              text=True)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            res = json.loads(line[7:])
            # None: the run opened no parallel region (one thread compiles none), so no layer was chosen
            if res["layer"] in (layer, None):
                return res
            print(f"threads_layer: {variant} {' '.join(args)}: ran on {res['layer']}, not {layer}", file=sys.stderr)
            return None
    # the layer does not load here, or the worker failed: say which, so that a missing row has a reason
    last = (proc.stderr.strip().splitlines() or [""])[-1]
    print(f"threads_layer: {variant} {' '.join(args)}: no result (exit {proc.returncode}) {last}", file=sys.stderr)
    return None


def _measure(layers: list[str], sizes: list[int], repeats: int, quick: bool, busy: bool) -> tuple[dict, dict]:
    """Every (variant, size, threads, busy core) run, alternating within each repetition; the regions' runs."""
    regions: dict = {lay: [] for lay in layers}
    steps: dict = {}
    for rep in range(repeats):
        for lay in layers:
            if not quick:
                res = _run(lay, ["regions"])
                if res:
                    regions[lay].append(res["result"])
            for n in sizes:
                for hog in ((False, True) if busy else (False,)):
                    for th in (1, 2):
                        k = 2 if quick else max(5, 40 * 64 * 64 // (n * n))
                        res = _run(lay, ["step", str(n), str(th), str(k)], busy=hog)
                        if res:
                            steps.setdefault((lay, n, th, hog), []).append(res["result"])
                            print(f"[{rep + 1}/{repeats}] {lay} {n}² {th} thread(s){', a core busy' if hog else ''}: "
                                  f"{res['result']['ms_step']:.1f} ms a step", file=sys.stderr)
    return regions, steps


def _summarise(layers: list[str], sizes: list[int], regions: dict, steps: dict) -> tuple[list, list]:
    """Medians: the steps' rows (speed-up, same numbers; free and busy other core) and the regions' rows."""
    rows = []
    for hog in (False, True):
        for lay in layers:
            for n in sizes:
                one, two = steps.get((lay, n, 1, hog), []), steps.get((lay, n, 2, hog), [])
                if not one or not two:
                    continue
                m1 = statistics.median(r["ms_step"] for r in one)
                m2 = statistics.median(r["ms_step"] for r in two)
                same = len({r["digest"] for r in one + two}) == 1
                rows.append({"layer": lay, "n": n, "busy_core": hog, "ms_1": m1, "ms_2": m2, "speedup": m1 / m2,
                             "same_numbers": same, "iterations": one[0]["iterations"], "runs": len(one)})
    region_rows = []
    for lay in layers:
        for k, n in enumerate(REGION_SIZES):
            got = [r[k] for r in regions[lay]]
            if got:
                m1 = statistics.median(g["ms_1"] for g in got)
                m2 = statistics.median(g["ms_2"] for g in got)
                region_rows.append({"layer": lay, "elements": n, "ms_1": m1, "ms_2": m2, "speedup": m1 / m2})
    return rows, region_rows


def _markdown(result: dict) -> str:
    rows, region_rows = result["rows"], result["regions"]
    md = [f"Two threads against one under each numba threading layer (median of {result['repeats']}; machine: "
          f"{result['machine']['cpus']} cpus). The shared hanging scene, one step a frame, the default solver; "
          "`omp`: OpenMP's threads sleeping between regions (the library's setting), `omp-spin`: spinning first "
          "(libgomp's default). \"a core busy\": another process keeps one core busy meanwhile.", "",
          "| layer | grid | other core | 1 thread (ms/step) | 2 threads (ms/step) | speed-up | same numbers | "
          "CG its (last step) |", "|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['layer']} | {r['n']}² | {'busy' if r['busy_core'] else 'free'} | {r['ms_1']:.1f} | {r['ms_2']:.1f} | "
           f"**{r['speedup']:.2f}** | {'yes' if r['same_numbers'] else 'NO'} | {r['iterations']} |" for r in rows]
    if region_rows:
        md += ["", "A compute-bound parallel region (20 multiply-adds an element):", "",
               "| layer | elements | 1 thread (ms) | 2 threads (ms) | speed-up |", "|---|---|---|---|---|"]
        md += [f"| {r['layer']} | {r['elements']} | {r['ms_1']:.3f} | {r['ms_2']:.3f} | **{r['speedup']:.2f}** |"
               for r in region_rows]
    return "\n".join(md) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    p.add_argument("--layers", nargs="+", default=list(LAYERS), choices=LAYERS)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="CI smoke: 32², one repetition, no busy core")
    p.add_argument("--no-busy", action="store_true", help="leave out the runs with a core kept busy")
    p.add_argument("--out", type=Path, default=Path("out") / "bench" / "threads_layer", help="output folder (default out/bench/threads_layer)")
    p.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        _worker(a.worker)
        return 0
    sys.path.insert(0, str(HERE))
    from _common import machine, write_outputs

    sizes, repeats = ([32], 1) if a.quick else (a.sizes, a.repeats)
    probe = ["step", "8", "1", "1"] if a.quick else ["regions"]
    layers = [lay for lay in a.layers if _run(lay, probe) is not None]     # those that load here
    regions, steps = _measure(layers, sizes, repeats, a.quick, busy=not (a.quick or a.no_busy))
    rows, region_rows = _summarise(layers, sizes, regions, steps)
    result = {"benchmark": "threads_layer", "quick": a.quick, "machine": machine(), "repeats": repeats,
              "rows": rows, "regions": region_rows}
    md = _markdown(result)
    write_outputs(a.out, "threads_layer", result, md)
    print(md, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
