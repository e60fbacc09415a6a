"""How the implicit step's cost grows with resolution, at a known accuracy.

Scene: the "hanging stiff cloth" (1 m x 1 m, 0.1 kg, flat at rest, top corners
pinned, gravity; structural and shear k, bend k/100; backward Euler, dt = 1/60 s)
at k = 1e4 N/m and the softer k = 1e3 N/m.

For every size and preconditioner the cloth is first run ``--warmup`` steps
(multigrid, tolerance 1e-8, the same state for every preconditioner), then
``--steps`` steps are timed one by one (medians reported). Per step: ms split
into assembly / preconditioner setup / solve / collision / rest, CG iterations,
and the ratio of the step to one SpMV of the same matrix (scipy's CSR product).
That ratio is taken in thread CPU time, with the SpMV timed right after every
step (interleaved, so both see the same machine state: on this shared machine
memory-bound timings drift by 2-3x within minutes): eight products, of which
the first four, slowed by a cache the step has just filled with other data,
are dropped, so the reference is a warm SpMV (the conservative choice: 1.5-2x
faster than the first products after a step at 128²). The ms columns are wall
time.
On the first timed step (the same state for every preconditioner) and,
up to ``--direct-max``, on more of them, the system is also solved directly
(SuperLU on the free coordinates) and the **true relative error of dv** is
measured. The growth exponent of ms/step against vertex count is fitted by
least squares. Finally the default settings' trajectory over the window is
compared with a run at tolerance 1e-8 (largest vertex deviation relative to the
cloth's largest displacement), from the flat rest state (whose buckling
amplifies any difference) and from the state a tight run reaches after
``--trajectory-settle`` seconds.

Usage::

    python benchmarks/scaling.py                         # 32..256, both k, both preconditioners
    python benchmarks/scaling.py --sizes 32 64 --out /tmp/res
    python benchmarks/scaling.py --quick                 # CI smoke test (seconds)
    python benchmarks/scaling.py --accelerators numba numpy   # compiled path against the numpy reference

Writes ``OUT/scaling.json``, ``OUT/scaling.md`` and ``OUT/scaling.png``. Never asserts a time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla
from _common import ROOT, default_out, hanging_stiff, ic, machine, series, spmv_seconds, write_outputs

from implicit_cloth.backend import resolve as resolve_accelerator
from implicit_cloth.backend import set_default_accelerator

H = 1 / 60
#: ``--adaptive``: keep the default step control (a step redone with Newton iterations or halved when it
#: breaks the energy balance or the strain bound); off by default here, so that a step is one solve
ADAPTIVE = False


#: the timed series: a preconditioner, or a multigrid with ``+K`` for its K-cycle (``solver.cycle = "K"``)
SERIES = ["multigrid", "multigrid_smoothed", "block_jacobi", "multigrid+K", "multigrid_smoothed+K"]


def stiff(n: int, k: float, preconditioner: str = "multigrid", tolerance: float | None = None) -> dict:
    """The hanging stiff cloth with this benchmark's step control (fixed steps unless ``--adaptive``);
    ``preconditioner`` one of :data:`SERIES` (``name+K``: that multigrid with the K-cycle)."""
    name, cycle = series(preconditioner)
    d = hanging_stiff(n, k, name, tolerance)
    d["solver"]["cycle"] = cycle
    if not ADAPTIVE:
        d["simulation"]["adaptive"] = {"enabled": False}
    return d


def _direct_dv(sim: ic.Simulator) -> np.ndarray:
    """The exact dv of the coming backward-Euler step (pins prescribed), by a sparse direct solve."""
    m = sim.model
    x, v = sim.positions, sim.velocities
    A, f0, kv = m.linearize(x, v, sim.time, H * H, H, w=v)
    b = (H * (f0 + H * kv)).ravel()
    z = np.zeros_like(v)
    z[m.pinned] = m.pin_velocity - v[m.pinned]
    z = z.ravel()
    free = np.repeat(m.free, 3)
    dv = z.copy()
    dv[free] = spla.spsolve(A[free][:, free].tocsc(), (b - A @ z)[free], permc_spec="COLAMD")
    return dv


def time_steps(n: int, k: float, preconditioner: str, state: ic.simulator.State, steps: int,
               error_samples: int, ref0: np.ndarray, accelerator: str | None = None) -> dict:
    """Time ``steps`` steps from ``state``; true error on the first step (against ``ref0``) and
    ``error_samples - 1`` more evenly spread ones (direct solves of their own). ``accelerator``:
    the multigrid's implementation (numba or numpy; ``None``: the default)."""
    set_default_accelerator(accelerator)
    try:
        sim = ic.Simulator(stiff(n, k, preconditioner), dt=H)
    finally:
        set_default_accelerator(None)
    acc = getattr(sim.integrator.precond, "accelerator", "numpy")
    sim.positions, sim.velocities = state.x, state.v
    sim.state.t = state.t
    extra = np.linspace(0, steps - 1, error_samples).round().astype(int)[1:] if error_samples > 1 else []
    sample_at = set(int(s) for s in extra if s > 0)
    rows, errors = [], []
    A = sim.model.system.csr
    xr = np.random.default_rng(0).standard_normal(A.shape[0])
    spmv_cpu = []
    for s in range(steps):
        ref = ref0 if s == 0 else (_direct_dv(sim) if s in sample_at else None)
        v0 = sim.velocities.copy()
        c0 = time.thread_time()
        t0 = time.perf_counter()
        sim.step(1)
        wall = time.perf_counter() - t0
        cpu = time.thread_time() - c0
        for r in range(8):            # the SpMV reference, interleaved with the steps (same machine state);
            c1 = time.thread_time()   # the first products after a step run on a cold cache and are kept out
            A @ xr
            if r >= 4:
                spmv_cpu.append(time.thread_time() - c1)
        st = sim.last_step
        col = float(getattr(st, "t_collision", 0.0) or 0.0)   # 0 until the engine has a collision stage
        rows.append((wall, st.t_assembly, st.t_setup, st.t_solve, st.iterations, st.converged, col, cpu))
        if ref is not None:
            dv = (sim.velocities - v0).ravel()
            errors.append(float(np.linalg.norm(dv - ref) / np.linalg.norm(ref)))
    spmv = statistics.median(spmv_cpu)
    med = lambda i: statistics.median(r[i] for r in rows)  # noqa: E731
    ms = 1e3 * med(0)
    return {
        "resolution": n, "vertices": sim.model.n, "k": k, "preconditioner": preconditioner, "accelerator": acc,
        "tolerance": sim.integrator.tolerance,
        "ms_step": ms, "ms_assembly": 1e3 * med(1), "ms_setup": 1e3 * med(2), "ms_solve": 1e3 * med(3),
        "ms_collision": 1e3 * med(6),   # StepInfo.t_collision when the engine reports it; no obstacles here
        "ms_rest": 1e3 * statistics.median(r[0] - r[1] - r[2] - r[3] - r[6] for r in rows),
        "iterations_median": med(4), "iterations_max": max(r[4] for r in rows),
        "unconverged_steps": sum(not r[5] for r in rows),
        "ms_step_cpu": 1e3 * med(7), "ms_spmv": 1e3 * spmv, "ms_spmv_wall": 1e3 * spmv_seconds(A),
        "step_in_spmvs": med(7) / spmv,
        "true_error_max": max(errors) if errors else None,
        "true_error_median": statistics.median(errors) if errors else None,
        "error_samples": len(errors),
    }


def warm_state(n: int, k: float, warmup: int) -> ic.simulator.State:
    sim = ic.Simulator(stiff(n, k, "multigrid", 1e-8), dt=H)
    sim.step(warmup)
    return sim.state.copy()


def trajectory_error(n: int, k: float, steps: int, perturbation: float = 1e-9, settle: float = 0.0) -> dict:
    """Default settings against tolerance 1e-8 over ``steps`` steps, from rest or from a settled state.

    With ``settle > 0`` every run starts from the state a tolerance-1e-8 run reaches after ``settle`` seconds
    (the cloth hanging, swinging, its buckles formed) instead of from the flat rest state, whose symmetric
    buckling amplifies any difference about 1e7 times.
    Control: the same tight run started from positions perturbed by ``perturbation`` m
    (random, seeded). If that drifts as far as the default run, the deviation is the
    scene's sensitivity (a flat cloth buckling as it falls), not solver error.
    """
    start = None
    if settle > 0:
        pre = ic.Simulator(stiff(n, k, "multigrid", 1e-8), dt=H)
        pre.step(int(round(settle / H)))
        start = (pre.positions.copy(), pre.velocities.copy())
    runs = {}
    for name, tol, eps in (("default", None, 0.0), ("tight", 1e-8, 0.0), ("perturbed", 1e-8, perturbation)):
        sim = ic.Simulator(stiff(n, k, "multigrid", tol), dt=H)
        x0 = sim.positions if start is None else start[0]
        sim.positions = x0 + eps * np.random.default_rng(1).standard_normal(x0.shape)
        if start is not None:
            sim.velocities = start[1]
        try:
            runs[name] = sim.run(duration=steps * H, frame_rate=60).positions
        except ic.DivergenceError as exc:
            # one linearisation a step (no step control here) can blow up on the flat start's buckling: the
            # run's own energy check stops it; recorded, not a crash of the whole benchmark
            return {"resolution": n, "k": k, "steps": steps, "settle_s": settle, "diverged": f"{name}: {exc}",
                    "max_displacement_m": float("nan"), "max_deviation_m": float("nan"), "relative": float("inf"),
                    "perturbation_m": perturbation, "perturbed_relative": float("nan")}
    disp = float(np.linalg.norm(runs["tight"] - runs["tight"][0], axis=2).max())
    dev = float(np.linalg.norm(runs["default"] - runs["tight"], axis=2).max())
    ctrl = float(np.linalg.norm(runs["perturbed"] - runs["tight"], axis=2).max())
    return {"resolution": n, "k": k, "steps": steps, "settle_s": settle, "max_displacement_m": disp,
            "max_deviation_m": dev, "relative": dev / disp if disp > 0 else 0.0, "perturbation_m": perturbation,
            "perturbed_relative": ctrl / disp if disp > 0 else 0.0}


def thread_speedup(n: int, k: float, state: ic.simulator.State, steps: int, counts: list[int],
                   preconditioner: str = "multigrid") -> dict:
    """Each step from the same state once per thread count, alternating (same machine state): ms/step
    medians, the speed-up of the last count over the first, and whether every count gave the same state."""
    from implicit_cloth import backend

    sim = ic.Simulator(stiff(n, k, preconditioner), dt=H)
    sim.positions, sim.velocities = state.x, state.v
    sim.state.t = state.t
    times: dict[int, list[float]] = {c: [] for c in counts}
    same = True
    try:
        for _ in range(steps):
            start = sim.state.copy()
            ends = []
            for c in counts:
                backend.set_threads(c)
                sim.state = start.copy()
                sim._reset_history()
                t0 = time.perf_counter()
                sim.step(1)
                times[c].append(time.perf_counter() - t0)
                ends.append(sim.state.copy())
            same &= all(np.array_equal(e.x, ends[0].x) and np.array_equal(e.v, ends[0].v) for e in ends)
    finally:
        backend.set_threads(None)
    med = {c: 1e3 * statistics.median(t) for c, t in times.items()}
    return {"resolution": n, "vertices": sim.model.n, "k": k, "ms_step": {str(c): med[c] for c in counts},
            "speedup": med[counts[0]] / med[counts[-1]], "identical": bool(same), "steps": steps}


def big_run(n: int, k: float, steps: int, warmup: int, memory_gb: float, preconditioner: str = "multigrid") -> dict:
    """One size in a process of its own (``--big-worker``): ms/step (median), iterations, peak memory. The
    process may use at most ``memory_gb`` of address space (the machine is shared): beyond that it fails with
    a MemoryError, reported in the row (``error``) instead of a time."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--big-worker", str(n), "--ks", str(k),
           "--steps", str(steps), "--warmup", str(warmup), "--big-memory-gb", str(memory_gb),
           "--big-preconditioner", preconditioner] + \
        (["--adaptive"] if ADAPTIVE else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
    return {"resolution": n, "vertices": n * n, "k": k, "error": tail, "memory_limit_gb": memory_gb}


def big_worker(n: int, k: float, steps: int, warmup: int, memory_gb: float, preconditioner: str = "multigrid") -> dict:
    import resource

    limit = int(memory_gb * 2**30)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    t0 = time.perf_counter()
    sim = ic.Simulator(stiff(n, k, preconditioner), dt=H)
    setup = time.perf_counter() - t0
    sim.step(warmup)
    rows = []
    for _ in range(steps):
        c0 = time.perf_counter()
        sim.step(1)
        st = sim.last_step
        rows.append((time.perf_counter() - c0, st.iterations, st.t_assembly, st.t_setup, st.t_solve))
    med = lambda i: statistics.median(r[i] for r in rows)  # noqa: E731
    return {"resolution": n, "vertices": sim.model.n, "k": k, "steps": steps, "warmup": warmup,
            "ms_step": 1e3 * med(0), "iterations_median": med(1), "ms_assembly": 1e3 * med(2),
            "ms_setup": 1e3 * med(3), "ms_solve": 1e3 * med(4), "setup_s": setup,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "levels": sim.integrator.precond.n_levels, "preconditioner": preconditioner}


def fit_exponent(rows: list[dict]) -> float | None:
    if len(rows) < 2:
        return None
    N = np.array([r["vertices"] for r in rows], dtype=float)
    t = np.array([r["ms_step"] for r in rows])
    return float(np.polyfit(np.log(N), np.log(t), 1)[0])


def _series(res: dict) -> list[tuple[str, str, str]]:
    """(preconditioner, accelerator, exponent key) of every timed series; block Jacobi is numpy only.

    The first accelerator's multigrid series keeps the plain key ``multigrid``; others get ``multigrid/ACC``.
    """
    out = []
    for pc in res["preconditioners"]:
        accs = res.get("accelerators", ["numpy"]) if pc.startswith("multigrid") else ["numpy"]
        for m, acc in enumerate(accs):
            out.append((pc, acc, pc if m == 0 else f"{pc}/{acc}"))
    return out


def _extra_tables(res: dict) -> list[str]:
    """The large cloths' and the threads' tables."""
    out: list[str] = []
    if res.get("big"):
        warm = next((b["warmup"] for b in res["big"] if "warmup" in b), None)
        out += [f"### Large cloths (one process each: ms/step, peak resident memory; "
                f"{res.get('big_preconditioner', 'multigrid')}"
                + (f"; timed after {warm} warm-up steps" if warm is not None else "") + ")", "",
                "| grid | vertices | levels | ms/step | assembly | setup | solve | CG its (median) | set-up (s) | "
                "peak memory (MB) |", "|---|---|---|---|---|---|---|---|---|---|"]
        for b in res["big"]:
            if "error" in b:
                out.append(f"| {b['resolution']}² | {b['vertices']} | - | not run: {b['error']} (address space "
                           f"limited to {b['memory_limit_gb']:g} GB) | | | | | | |")
                continue
            out.append(f"| {b['resolution']}² | {b['vertices']} | {b['levels']} | {b['ms_step']:.0f} | "
                       f"{b['ms_assembly']:.0f} | {b['ms_setup']:.0f} | {b['ms_solve']:.0f} | "
                       f"{b['iterations_median']:.0f} | {b['setup_s']:.1f} | {b['peak_rss_mb']:.0f} |")
        out.append("")
    if res.get("threads"):
        counts = list(res["threads"][0]["ms_step"])
        out += [f"### Solver threads (each step from the same state once per count, alternating; "
                f"{res.get('big_preconditioner', 'multigrid')})", "",
                "| grid | " + " | ".join(f"ms/step, {c} thread(s)" for c in counts) + " | speed-up | same numbers |",
                "|---|" + "---|" * (len(counts) + 2)]
        for t in res["threads"]:
            out.append(f"| {t['resolution']}² | " + " | ".join(f"{t['ms_step'][c]:.0f}" for c in counts)
                       + f" | {t['speedup']:.2f}x | {'yes' if t['identical'] else 'no'} |")
        out.append("")
    return out


def markdown(res: dict) -> str:
    steps = "adaptive step control" if res.get("adaptive") else "fixed steps (one solve each)"
    out = [f"Hanging stiff cloth, backward Euler dt = 1/60 s, {steps}; steps {res['warmup']}-{res['warmup'] + res['steps']} "
           f"timed (median); {res['machine']['cpus']} cores, one BLAS thread. Default solver settings: "
           f"preconditioner {res['default_solver']['preconditioner']}, tolerance "
           f"{res['default_solver']['tolerance']:g}; multigrid implementation(s): "
           f"{', '.join(res.get('accelerators', ['numpy']))} (numba: compiled kernels, one thread).", ""]
    for k in res["ks"]:
        for pc, acc, key in _series(res):
            rows = [r for r in res["rows"] if r["k"] == k and r["preconditioner"] == pc and r["accelerator"] == acc]
            if not rows:
                continue
            exp = res["exponents"].get(f"{key}@{k:g}")
            out += [f"### k = {k:g} N/m, {pc} ({acc})" + (f" (ms/step ~ N^{exp:.2f})" if exp is not None else ""), "",
                    "| grid | vertices | ms/step | assembly | setup | solve | collision | rest | CG its (med/max) "
                    "| true error of dv (max) | step / SpMV (CPU time) |",
                    "|---|---|---|---|---|---|---|---|---|---|---|"]
            for r in rows:
                err = f"{r['true_error_max']:.1e}" if r["true_error_max"] is not None else "-"
                out.append(f"| {r['resolution']}² | {r['vertices']} | {r['ms_step']:.1f} | {r['ms_assembly']:.1f} | "
                           f"{r['ms_setup']:.1f} | {r['ms_solve']:.1f} | {r['ms_collision']:.1f} | "
                           f"{r['ms_rest']:.1f} | {r['iterations_median']:.0f}/{r['iterations_max']} | {err} | "
                           f"{r['step_in_spmvs']:.0f} |")
            out.append("")
    accs = res.get("accelerators", [])
    if "numba" in accs and "numpy" in accs:
        out += ["### Compiled (numba) against reference (numpy) multigrid path, same run", "",
                "| k | grid | ms/step numpy | ms/step numba | step speed-up | CG its numpy / numba |",
                "|---|---|---|---|---|---|"]
        for k in res["ks"]:
            for n in res["sizes"]:
                pair = {r["accelerator"]: r for r in res["rows"]
                        if r["k"] == k and r["resolution"] == n and r["preconditioner"] == "multigrid"}
                if len(pair) == 2:
                    a, b = pair["numpy"], pair["numba"]
                    out.append(f"| {k:g} | {n}² | {a['ms_step']:.1f} | {b['ms_step']:.1f} | "
                               f"{a['ms_step'] / b['ms_step']:.2f}x | {a['iterations_median']:.0f} / "
                               f"{b['iterations_median']:.0f} |")
        out.append("")
    out += _extra_tables(res)
    if res["trajectory"]:
        out += ["### Default settings against tolerance 1e-8 (trajectory)", "",
                "Control: the tolerance-1e-8 run started 1e-9 m away (random); when it drifts as far, "
                "the deviation is the scene's sensitivity, not the solver's error.", "",
                "| grid | k | start | steps | largest displacement (m) | largest deviation (m) | relative | "
                "control: 1e-9 m start perturbation, relative |", "|---|---|---|---|---|---|---|---|"]
        for t in res["trajectory"]:
            start = f"after {t['settle_s']:g} s" if t.get("settle_s") else "flat, at rest"
            if t.get("diverged"):
                out.append(f"| {t['resolution']}² | {t['k']:g} | {start} | {t['steps']} | diverged: "
                           f"{t['diverged']} | | | |")
                continue
            out.append(f"| {t['resolution']}² | {t['k']:g} | {start} | {t['steps']} | "
                       f"{t['max_displacement_m']:.4f} | "
                       f"{t['max_deviation_m']:.2e} | {t['relative']:.2e} | {t['perturbed_relative']:.2e} |")
        out.append("")
    return "\n".join(out)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for k in res["ks"]:
        for (pc, acc, key), style in zip(_series(res), ("o-", "s--", "^-.", "v:")):
            rows = [r for r in res["rows"] if r["k"] == k and r["preconditioner"] == pc and r["accelerator"] == acc]
            if not rows:
                continue
            exp = res["exponents"].get(f"{key}@{k:g}")
            N = [r["vertices"] for r in rows]
            ax.loglog(N, [r["ms_step"] for r in rows], style,
                      label=f"{pc} ({acc}), k={k:g} N/m" + (f" (N^{exp:.2f})" if exp is not None else ""))
    big = [b for b in res.get("big") or [] if "error" not in b]
    if big:
        bpc = res.get("big_preconditioner", "multigrid")
        color = f"C{[pc for pc, _, _ in _series(res)].index(bpc)}" if bpc in res["preconditioners"] else "C0"
        top = max(b["resolution"] for b in big)
        exp = res["exponents"].get(f"{bpc}@{res['ks'][0]:g}, to {top}²")
        ax.loglog([b["vertices"] for b in big], [b["ms_step"] for b in big], "o", mfc="none", color=color,
                  label=f"{bpc}, k={res['ks'][0]:g} N/m, own process ({big[0].get('warmup', 3)} warm-up steps)"
                        + (f" (N^{exp:.2f} to {top}²)" if exp is not None else ""))
    if res.get("blender"):
        bl = res["blender"]
        ax.loglog([b["vertices"] for b in bl], [b["ms_frame"] for b in bl], "kx-",
                  label="Blender 3.4 (vs_blender.py hanging, k=1e3, ms/frame)")
        ax.loglog([b["vertices"] for b in bl], [b["ours_ms_frame"] for b in bl], "k+--",
                  label="ours on the same scene (vs_blender.py)")
    pc0, acc0, _ = _series(res)[0]
    rows = [r for r in res["rows"] if r["k"] == res["ks"][0] and r["preconditioner"] == pc0
            and r["accelerator"] == acc0]
    ax.loglog([r["vertices"] for r in rows], [r["ms_spmv"] for r in rows], "k:", label="one SpMV (floor)")
    ax.set_xlabel("vertices N")
    ax.set_ylabel("ms per backward-Euler step (median)")
    ax.set_title("Implicit step cost vs resolution (hanging stiff cloth, dt = 1/60 s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    from implicit_cloth.files import atomic_write

    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=120))
    plt.close(fig)


def _extras(a, rows: list[dict], accelerators: list[str], exponents: dict) -> tuple:
    """The large sizes (own processes), the thread comparison and Blender's points (when asked for)."""
    big = []
    for n in a.big_sizes:
        warm = a.warmup if a.big_warmup is None else a.big_warmup
        b = big_run(n, a.ks[0], a.big_steps, warm, a.big_memory_gb, a.big_preconditioner)
        big.append(b)
        if "error" in b:
            print(f"k={a.ks[0]:g} {n}² (own process): failed within {a.big_memory_gb:g} GB: {b['error']}", flush=True)
            continue
        print(f"k={a.ks[0]:g} {n}² (own process): {b['ms_step']:.0f} ms/step, its {b['iterations_median']:.0f}, "
              f"peak {b['peak_rss_mb']:.0f} MB", flush=True)
    done = [b for b in big if "error" not in b]
    if done:
        pts = [(r["vertices"], r["ms_step"]) for r in rows if r["k"] == a.ks[0]
               and r["preconditioner"] == a.big_preconditioner
               and r["accelerator"] == accelerators[0]] + [(b["vertices"], b["ms_step"]) for b in done]
        N, t = np.array(pts, dtype=float).T
        top = max(b["resolution"] for b in done)
        exponents[f"{a.big_preconditioner}@{a.ks[0]:g}, to {top}²"] = float(np.polyfit(np.log(N), np.log(t), 1)[0])
    threads = []
    if len(a.threads) > 1:
        for n in a.thread_sizes:
            th = thread_speedup(n, a.ks[0], warm_state(n, a.ks[0], a.warmup), a.thread_steps, a.threads,
                                a.big_preconditioner)
            threads.append(th)
            print(f"k={a.ks[0]:g} {n}² threads {a.threads}: {th['ms_step']} ms/step, speed-up {th['speedup']:.2f}x, "
                  f"identical {th['identical']}", flush=True)
    return big, threads, blender_points(a.blender)


def blender_points(path: str | None) -> list[dict]:
    """Blender's and our ms per frame on the shared hanging scene, from a ``vs_blender.py`` result (if any)."""
    if not path or not Path(path).is_file():
        return []
    vb = json.loads(Path(path).read_text())
    return [{"vertices": r["n"] ** 2, "ms_frame": r["blender_ms"], "ours_ms_frame": r["ours_ms"]}
            for r in vb["rows"] if r["scene"] == "hanging"]


def replot(path: Path, out: Path, blender: str | None) -> int:
    """Draw an earlier result's table and plot again, with Blender's points from ``blender`` (nothing is run)."""
    res = json.loads(path.read_text())
    res["blender"] = blender_points(blender)
    md = markdown(res)
    write_outputs(out, path.stem, res, md)
    plot(res, out / f"{path.stem}.png")
    print(md)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--ks", type=float, nargs="+", default=[1e4, 1e3])
    p.add_argument("--preconditioners", nargs="+", default=["multigrid", "block_jacobi"],
                   choices=SERIES, help="name+K: that multigrid with the K-cycle (solver.cycle = \"K\")")
    p.add_argument("--accelerators", nargs="+", default=["auto"], choices=["auto", "numba", "numpy"],
                   help="multigrid implementations to time (auto: numba if installed); the first is the default "
                        "series, e.g. --accelerators numba numpy for the speed-up of the compiled path")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--slow-steps", type=int, default=5,
                   help="timed steps for block_jacobi at sizes >= 128 (hundreds of iterations each)")
    p.add_argument("--slow-max", type=int, default=128,
                   help="largest size timed with block_jacobi (thousands of iterations a step above)")
    p.add_argument("--error-samples", type=int, default=3,
                   help="steps per run whose dv is checked against a direct solve (the first always)")
    p.add_argument("--direct-max", type=int, default=64,
                   help="above this size only the first timed step is checked (direct solves are slow)")
    p.add_argument("--trajectory-sizes", type=int, nargs="*", default=[32, 64, 128])
    p.add_argument("--trajectory-settle", type=float, nargs="*", default=[0.0, 2.0],
                   help="start the trajectory comparison from rest (0) and/or after this many seconds of a "
                        "tight run (the flat start's buckling amplifies any difference ~1e7 times)")
    p.add_argument("--out", default=default_out('scaling'), help="output folder (default out/bench/scaling; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="tiny sizes and few steps (CI smoke test)")
    p.add_argument("--adaptive", action="store_true",
                   help="keep the default adaptive step control (off here: one solve a step)")
    p.add_argument("--threads", type=int, nargs="*", default=[],
                   help="thread counts to compare at --thread-sizes, alternating from the same states (e.g. 1 2)")
    p.add_argument("--thread-sizes", type=int, nargs="*", default=[128, 256])
    p.add_argument("--thread-steps", type=int, default=10)
    p.add_argument("--big-sizes", type=int, nargs="*", default=[],
                   help="sizes run in a process each for ms/step and peak memory (e.g. 512 1024)")
    p.add_argument("--big-steps", type=int, default=3)
    p.add_argument("--big-preconditioner", default="multigrid", choices=[c for c in SERIES if c != "block_jacobi"],
                   help="the preconditioner of the --big-sizes runs, the thread comparison and the exponent fitted "
                        "to the largest size (with the timed sizes' rows of the same preconditioner)")
    p.add_argument("--big-warmup", type=int, default=None,
                   help="warm-up steps of each --big-sizes run (default --warmup: timed over the same window as the "
                        "smaller sizes, past the falling sheet's buckling, whose first steps take 3-4 times the "
                        "iterations)")
    p.add_argument("--big-memory-gb", type=float, default=12.0,
                   help="address-space limit of each --big-sizes process (a shared machine), GB")
    p.add_argument("--blender", default=str(ROOT / "benchmarks" / "results" / "vs_blender_fixed.json"),
                   help="vs_blender.py's JSON, whose hanging rows are drawn in the plot (if the file exists)")
    p.add_argument("--replot", type=Path, metavar="JSON",
                   help="run nothing: draw this earlier result's table and plot again (Blender's points from "
                        "--blender) into --out, under the JSON's name")
    p.add_argument("--big-worker", type=int, default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    global ADAPTIVE
    ADAPTIVE = a.adaptive
    if a.replot:
        return replot(a.replot, Path(a.out), a.blender)
    if a.big_worker is not None:
        print("RESULT " + json.dumps(big_worker(a.big_worker, a.ks[0], a.steps, a.warmup, a.big_memory_gb,
                                                a.big_preconditioner)))
        return 0
    if a.quick:
        a.sizes, a.warmup, a.steps, a.slow_steps, a.error_samples = [8, 16], 2, 3, 3, 1
        a.trajectory_sizes, a.trajectory_settle = [8], [0.0, 0.1]
    default_solver = ic.Scene.from_dict({"cloth": {"mass": 1.0}}).data["solver"]
    accelerators = list(dict.fromkeys(resolve_accelerator(x) for x in a.accelerators))
    rows = []
    for k in a.ks:
        for n in a.sizes:
            state = warm_state(n, k, a.warmup)
            sim = ic.Simulator(stiff(n, k), dt=H)
            sim.positions, sim.velocities = state.x, state.v
            sim.state.t = state.t
            ref0 = _direct_dv(sim)  # the first timed step's exact dv, shared by all preconditioners
            samples = a.error_samples if n <= a.direct_max else 1
            for pc in a.preconditioners:
                if pc == "block_jacobi" and n > a.slow_max:
                    print(f"k={k:g} {n:4d}² {pc:12s} skipped (--slow-max {a.slow_max})", flush=True)
                    continue
                steps = a.slow_steps if (pc == "block_jacobi" and n >= 128) else a.steps
                for acc in (accelerators if pc.startswith("multigrid") else ["numpy"]):
                    r = time_steps(n, k, pc, state, steps, samples, ref0, acc)
                    rows.append(r)
                    err = f"{r['true_error_max']:.1e}" if r["true_error_max"] is not None else "-"
                    print(f"k={k:g} {n:4d}² {pc:12s} {acc:5s} {r['ms_step']:9.1f} ms/step (asm "
                          f"{r['ms_assembly']:.1f}, setup {r['ms_setup']:.1f}, solve {r['ms_solve']:.1f})  its "
                          f"{r['iterations_median']:.0f}  true err {err}  = {r['step_in_spmvs']:.0f} SpMVs", flush=True)
    res = {"preconditioners": a.preconditioners, "accelerators": accelerators}
    exponents = {}
    for k in a.ks:
        for pc, acc, key in _series(res):
            e = fit_exponent([r for r in rows if r["k"] == k and r["preconditioner"] == pc
                              and r["accelerator"] == acc])
            if e is not None:
                exponents[f"{key}@{k:g}"] = e
    traj = []
    for k in a.ks:
        for n in a.trajectory_sizes:
            for settle in a.trajectory_settle:
                t = trajectory_error(n, k, a.warmup + a.steps, settle=settle)
                traj.append(t)
                print(f"trajectory k={k:g} {n}² from t={settle:g} s: " + (
                      f"diverged ({t['diverged']})" if t.get("diverged") else
                      f"deviation {t['relative']:.2e} of the displacement (1e-9 m start perturbation: "
                      f"{t['perturbed_relative']:.2e})"), flush=True)
    big, threads, blender = _extras(a, rows, accelerators, exponents)
    res = {"benchmark": "scaling", "quick": a.quick, "sizes": a.sizes, "ks": a.ks, "adaptive": a.adaptive,
           "preconditioners": a.preconditioners, "accelerators": accelerators, "warmup": a.warmup, "steps": a.steps,
           "slow_steps": a.slow_steps, "default_solver": default_solver, "machine": machine(),
           "rows": rows, "exponents": exponents, "trajectory": traj, "big": big, "threads": threads,
           "big_preconditioner": a.big_preconditioner,
           "blender": blender}
    md = markdown(res)
    out = Path(a.out)
    write_outputs(out, "scaling", res, md)
    plot(res, out / "scaling.png")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
