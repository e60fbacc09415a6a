"""The headline: what one implicit step costs against resolution, and what one simulated second costs per integrator.

Part 1, cost per step against resolution. Backward Euler (dt = 1/60 s, the
default solver: multigrid PCG, tolerance 1e-3) on the "hanging stiff cloth"
(:func:`_common.hanging_stiff`: 1 m x 1 m, 0.1 kg, flat at rest, top corners
pinned, gravity; structural and shear k = ``--k`` = 1e4 N/m, bend k/100) at
``--sizes`` 16² ... 256². ``--warmup`` steps, then a window of ``--steps``
steps run ``--repeats`` times from the same warm state (:func:`step_costs`);
per step: the cost, its split into assembly (forces, Jacobians, matrix),
preconditioner setup, PCG solve, collision (``t_collision`` of the run
report's ``timing`` when the engine reports one; 0 until collisions exist) and
the rest; CG iterations (mean / max). The growth exponent of ms/step
against the vertex count is a least-squares fit on log-log.
:mod:`scaling` measures the same at 32²-256² with the true error of dv and
the solver-choice table (issue 4); this part adds 16² and the collision column.

Part 2, run time per simulated second at each method's own largest stable
step. The scene of :mod:`stability` (the hanging stiff cloth with kd = 0.01
N*s/m, bend 1e-4, 12², started from rest plus seeded N(0, (1e-3 m/s)^2)
velocities) at every k of the stability run (1e2 ... 1e6 N/m). The largest
stable dt of each integrator is read from the stability benchmark's result
(``--stability``, default ``benchmarks/results/stability.json``: run
``implicit-cloth bench stability`` first); when that file does not exist (and
in ``--quick`` mode) it is searched here with the same functions
(:func:`stability.search`, :func:`stability.trial`: 0.5 s runs, at least 20
steps, finite and energy growth below the run's energy scale; bisection to
``--rtol``, cap 1/15 s, floor 1e-5 s) at ``--resolution`` and ``--ks``. At that dt:

* when one simulated second takes at most ``--full-max-steps`` (2000) steps, the
  time of a whole 1 s run (``Simulator.run``, median of ``--repeats``) is
  measured ("run");
* otherwise the median cost of a step (``--repeats`` x up to 100 steps, after
  one untimed step) times the number of steps in 1 s ("extrapolated"): explicit
  steps cost the same throughout a run.

Clock. Every time is measured both as the CPU time of this process
(``time.process_time``) and as wall time; ``--clock`` (``cpu``, the default)
picks the one the tables, plot and headline use, and both are in the JSON. The
engine steps on one thread (BLAS pinned to one), so on an idle machine they
agree; on the shared machine of these results (five jobs on two cores;
``nice`` made no visible difference) wall times were inflated 5-20 times and
varied from repeat to repeat. The engine's own split
of a step (assembly / setup / solve / collision, :class:`StepInfo`) is in wall
time; it is shown as shares of the step's wall time, which a uniform slowdown
leaves unchanged.

The headline ratio at each k is (the cheapest explicit method's time per
simulated second) / (the cheapest implicit method's): > 1 means implicit wins
by that factor, < 1 that the "many small explicit steps" view (Macklin et al.
2019, "Small steps in physics simulation") wins. Stability is not accuracy:
the accuracy-cost benchmark (:mod:`accuracy_cost`) compares the methods at equal
error, where small explicit steps can win even when they lose here.

Usage::

    python benchmarks/headline.py                  # ~15 min on 2 shared cores (256²: ~20 steps)
    python benchmarks/headline.py --sizes 16 32 --ks 1e3 1e5 --out /tmp/res
    python benchmarks/headline.py --stability '' --resolution 32 --ks 1e2 1e3 1e4 --sizes 16 --name headline_32
    python benchmarks/headline.py --quick          # CI smoke test (< 1 min)
    implicit-cloth bench headline --quick --out /tmp/res

Writes ``OUT/headline.json`` (raw figures, every stability trial, machine,
versions, seed), ``OUT/headline.md`` (both tables and the headline sentence)
and ``OUT/headline.png`` (ms/step against vertices with its split; seconds per
simulated second against k per integrator). Never asserts a time.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import stability
from _common import FIXED_STEPS, ROOT, default_out, hanging_stiff, ic, machine, progress, save_png, write_outputs

EXPLICIT = stability.EXPLICIT
H = 1 / 60
CLOCK = {"name": "cpu"}   # the cost measure: "cpu" (process CPU time) or "wall"; set by --clock


def _timed(fn) -> tuple[float, float]:
    """(CPU, wall) seconds of ``fn()``."""
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.process_time() - c0, time.perf_counter() - t0


# --------------------------------------------------------------------------- part 1
def step_costs(n: int, k: float, warmup: int, steps: int, repeats: int = 3) -> dict:
    """Cost of one backward-Euler step (dt = 1/60 s, default solver) of the hanging stiff cloth at n², ms.

    After ``warmup`` steps, a window of ``steps`` steps is run ``repeats`` times from
    the same warm state (one ``Simulator.run`` each: the BLAS thread limit is
    entered once per window, not once per step, whose cost on a loaded machine
    dwarfed a small step's); per-step figures are the window's totals / steps,
    medians over the repeats. The split comes from the run report's ``timing``
    (``t_assembly``, ``t_setup``, ``t_solve`` and ``t_collision`` if the engine
    reports it), in wall time; "rest" is the step's wall time minus those.
    """
    sim = ic.Simulator(hanging_stiff(n, k), dt=H)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)
        sim.step(warmup)
        x0, v0, t0 = sim.positions.copy(), sim.velocities.copy(), sim.time
        rows = []
        for _ in range(repeats):
            sim.positions, sim.velocities = x0, v0
            sim.state.t = t0
            box: dict = {}
            cpu, wall = _timed(lambda box=box, sim=sim: box.setdefault("traj", sim.run(
                duration=steps * H, frame_rate=1 / (steps * H))))
            rep = box["traj"].report
            tm = rep["timing"]
            rows.append({"cpu": cpu / steps, "wall": wall / steps, "assembly": tm["t_assembly"] / steps,
                         "setup": tm["t_setup"] / steps, "solve": tm["t_solve"] / steps,
                         "collision": float(tm.get("t_collision", 0.0)) / steps,
                         "its_mean": rep["solver"]["mean_iterations"], "its_max": rep["solver"]["max_iterations"],
                         "unconverged": rep["solver"]["unconverged_steps"],
                         "collision_reported": "t_collision" in tm})
    med = lambda key: statistics.median(r[key] for r in rows)  # noqa: E731
    out = {"resolution": n, "vertices": sim.model.n, "k": k, "steps_timed": steps, "warmup": warmup,
           "repeats": repeats, "ms_step_cpu": 1e3 * med("cpu"), "ms_step_wall": 1e3 * wall}
    for part in ("assembly", "setup", "solve", "collision"):   # each a median over the repeats
        out[f"ms_{part}"] = 1e3 * med(part)
        out[f"share_{part}"] = statistics.median(r[part] / r["wall"] for r in rows)
    rest = [r["wall"] - r["assembly"] - r["setup"] - r["solve"] - r["collision"] for r in rows]
    out["ms_rest"] = 1e3 * statistics.median(rest)
    out["share_rest"] = statistics.median(x / r["wall"] for x, r in zip(rest, rows))
    out.update({"iterations_mean": med("its_mean"), "iterations_max": max(r["its_max"] for r in rows),
                "unconverged_steps": max(r["unconverged"] for r in rows),
                "collision_reported": any(r["collision_reported"] for r in rows)})
    out["ms_step"] = out["ms_step_cpu"] if CLOCK["name"] == "cpu" else out["ms_step_wall"]
    return out


def fit_exponent(rows: list[dict]) -> float | None:
    """Least-squares slope of log(ms/step) against log(vertices)."""
    if len(rows) < 2:
        return None
    N = np.array([r["vertices"] for r in rows], dtype=float)
    return float(np.polyfit(np.log(N), np.log([r["ms_step"] for r in rows]), 1)[0])


# --------------------------------------------------------------------------- part 2
def one_second(base: dict, integrator: str, dt: float, repeats: int, seed: int, full_max_steps: int) -> dict:
    """Wall time to simulate 1 s at ``dt`` from the perturbed rest pose (module docstring), s."""
    n_steps = int(round(1.0 / dt))
    full = n_steps <= full_max_steps
    steps = n_steps if full else min(100, n_steps)
    cpus, walls, status = [], [], "ok"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)
        for _ in range(repeats):
            sim = ic.Simulator(base, integrator=integrator, dt=dt, adaptive=FIXED_STEPS)
            stability.perturbed(sim, seed)
            try:
                if full:
                    c, w = _timed(lambda sim=sim: sim.run(duration=1.0, frame_rate=30))
                else:
                    sim.step(1)   # first-step work (Verlet's first force, BDF2's start) not timed
                    c, w = _timed(lambda sim=sim: sim.step(steps))
            except ic.DivergenceError:
                status = "diverged"
                break
            cpus.append(c * n_steps / steps)
            walls.append(w * n_steps / steps)
    out = {"method": "run" if full else "extrapolated", "steps": n_steps, "steps_timed": steps, "status": status,
           "repeats": len(walls), "cpu_s": statistics.median(cpus) if cpus else None,
           "wall_s": statistics.median(walls) if walls else None}
    out["cost_s"] = (out["cpu_s"] if CLOCK["name"] == "cpu" else out["wall_s"]) if status == "ok" else None
    return out


def headline_ratio(row: dict) -> dict:
    """Cheapest explicit and implicit cost (s) per simulated second at one k, and their ratio."""
    def best(family: bool) -> tuple[str | None, float | None]:
        c = [(r["one_second"]["cost_s"], name) for name, r in row["results"].items()
             if (name in EXPLICIT) == family and r.get("one_second") and r["one_second"]["cost_s"] is not None]
        return (min(c)[1], min(c)[0]) if c else (None, None)
    ne, we = best(True)
    ni, wi = best(False)
    return {"explicit": ne, "explicit_cost_s": we, "implicit": ni, "implicit_cost_s": wi,
            "implicit_wins_by": (we / wi) if (we and wi) else None}


def load_stability(path: Path) -> dict | None:
    """The stability benchmark's JSON (its largest stable steps), or None if ``path`` does not exist."""
    import json

    if not path.is_file():
        return None
    res = json.loads(path.read_text())
    if res.get("benchmark") != "stability":
        raise SystemExit(f"headline: --stability: not a stability benchmark result, got {str(path)!r}")
    return res


# --------------------------------------------------------------------------- output
def markdown(res: dict) -> str:
    s = res["settings"]
    clk = "CPU" if s["clock"] == "cpu" else "wall"
    out = ["## Cost of one backward-Euler step against resolution", "",
           f"Hanging stiff cloth (1 m, 0.1 kg, flat at rest, top corners pinned), k = {s['k']:g} N/m, dt = 1/60 s, "
           f"default solver (multigrid, tolerance 1e-3); steps {s['warmup']}-{s['warmup'] + s['steps']} timed as one "
           f"window, {s['repeats']} times from the same state, medians. ms/step in CPU time of the process and in wall time ({res['machine']['cpus']} cores shared "
           "with other jobs, one BLAS thread); the split is the engine's own (wall-time) split, as shares of the "
           "step's wall time. Collision: "
           + ("from StepInfo.t_collision." if any(r["collision_reported"] for r in res["scaling"])
              else "0, the engine has no collision stage yet."), "",
           "| grid | vertices | ms/step (CPU) | ms/step (wall) | assembly | precond setup | solve | collision | rest "
           "| CG its (mean/max) |", "|---|---|---|---|---|---|---|---|---|---|"]
    pc = lambda x: f"{100 * x:.0f} %"  # noqa: E731
    for r in res["scaling"]:
        out.append(f"| {r['resolution']}² | {r['vertices']} | {r['ms_step_cpu']:.1f} | {r['ms_step_wall']:.1f} | "
                   f"{pc(r['share_assembly'])} | {pc(r['share_setup'])} | {pc(r['share_solve'])} | "
                   f"{pc(r['share_collision'])} | {pc(r['share_rest'])} | "
                   f"{r['iterations_mean']:.0f}/{r['iterations_max']} |")
    if res["exponent"] is not None:
        out += ["", f"{clk} ms/step grows as N^{res['exponent']:.2f} (least squares over these sizes)."]
    ints = res["integrators"]
    clk = "CPU" if s["clock"] == "cpu" else "wall"
    out += ["", f"## {clk.capitalize() if clk == 'wall' else clk} time to simulate 1 s at each method's largest stable step", "",
            f"Stability scene at {s['resolution']}² (hanging stiff cloth, kd = {stability.KD:g} N·s/m, from rest "
            f"+ N(0, ({stability.NOISE:g} m/s)²) velocities, seed {res['seed']}); largest stable dt from the stability "
            f"benchmark's search (0.5 s runs, energy bound; source: {s['stability_source']}). Cell: {clk} seconds per simulated second (median of "
            f"{s['repeats']}), and dt_max in ms; *: extrapolated from the median step cost (more than "
            f"{s['full_max_steps']} steps per second); -: unstable at the floor.", "",
            "| k (N/m) | " + " | ".join(ints) + " | cheapest explicit / cheapest implicit |",
            "|---" * (2 + len(ints)) + "|"]
    for row in res["rows"]:
        cells = []
        for name in ints:
            r = row["results"][name]
            o = r.get("one_second")
            if r["dt_max"] is None or not o or o["cost_s"] is None:
                cells.append("-")
                continue
            cap = "≥" if r["status"] == "at_cap" else ""
            star = "*" if o["method"] == "extrapolated" else ""
            cells.append(f"{o['cost_s']:.3g}{star} ({cap}{1e3 * r['dt_max']:.3g})")
        h = row["headline"]
        ratio = (f"{h['implicit_wins_by']:.3g} ({h['explicit']} / {h['implicit']})"
                 if h["implicit_wins_by"] is not None else "-")
        out.append(f"| {row['k']:.0e} | " + " | ".join(cells) + f" | {ratio} |")
    out += ["", res["headline"], ""]
    return "\n".join(out)


def headline_sentence(rows: list[dict], resolution: int) -> str:
    rs = [r for r in rows if r["headline"]["implicit_wins_by"] is not None]
    if not rs:
        return "No stiffness had both an explicit and an implicit stable step."
    parts = []
    for r in rs:
        h = r["headline"]
        x = h["implicit_wins_by"]
        parts.append(f"k = {r['k']:.0e} N/m: " + (f"implicit wins by {x:.3g}x" if x >= 1 else
                                                    f"explicit wins by {1 / x:.3g}x")
                     + f" ({h['implicit']} {h['implicit_cost_s']:.3g} s vs {h['explicit']} "
                       f"{h['explicit_cost_s']:.3g} s per simulated second)")
    return f"Headline ({resolution}² cloth, each method at its largest stable step): " + "; ".join(parts) + "."


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5.2))
    rows = res["scaling"]
    N = [r["vertices"] for r in rows]
    clk = "CPU" if res["settings"]["clock"] == "cpu" else "wall"
    a1.loglog(N, [r["ms_step"] for r in rows], "o-", label=f"whole step ({clk})", ms=5)
    if clk == "CPU":
        a1.loglog(N, [r["ms_step_wall"] for r in rows], "o:", color="0.5", lw=1, ms=3, label="whole step (wall)")
    for key, ls, lab in (("share_solve", "s--", "PCG solve"), ("share_assembly", "^--", "assembly"),
                         ("share_setup", "v--", "precond setup"), ("share_rest", "d:", "rest"),
                         ("share_collision", "x:", "collision")):
        if key == "share_collision" and not any(r[key] > 0 for r in rows):
            continue
        a1.loglog(N, [max(r[key] * r["ms_step"], 1e-3) for r in rows], ls, label=lab, ms=5)
    for r in rows:
        a1.annotate(f"{r['resolution']}²", (r["vertices"], r["ms_step"]), textcoords="offset points",
                    xytext=(-10, 6), fontsize=7)
    exp = res["exponent"]
    a1.set_xlabel("vertices N")
    a1.set_ylabel("ms per backward-Euler step (median; parts: wall-time share x step)")
    a1.set_title(f"Implicit step cost, k = {res['settings']['k']:g} N/m, dt = 1/60 s"
                 + (f" (N^{exp:.2f})" if exp is not None else ""))
    a1.grid(True, which="both", alpha=0.3)
    a1.legend(fontsize=8)
    ks = np.array([r["k"] for r in res["rows"]])
    for name in res["integrators"]:
        mk, col = stability.STYLE.get(name, ("o", None))
        ys = np.array([(r["results"][name].get("one_second") or {}).get("cost_s") or np.nan for r in res["rows"]],
                      dtype=float)
        a2.loglog(ks, ys, marker=mk, color=col, ls="-" if name not in EXPLICIT else "--", label=name)
    a2.axhline(1.0, color="0.5", ls=":", lw=1)
    a2.text(ks[0], 1.08, "real time", fontsize=7, color="0.4")
    a2.set_xlabel("spring stiffness k (N/m)")
    a2.set_ylabel(f"{res['settings']['clock'].upper() if res['settings']['clock'] == 'cpu' else 'wall'} "
                  "seconds per simulated second")
    a2.set_title(f"1 s of the hanging cloth at each method's largest stable dt ({res['settings']['resolution']}²)")
    a2.grid(True, which="both", alpha=0.3)
    a2.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64, 128, 256], help="part 1 grid sizes")
    p.add_argument("--k", type=float, default=1e4, help="part 1 spring stiffness, N/m")
    p.add_argument("--warmup", type=int, default=5, help="part 1 untimed steps")
    p.add_argument("--steps", type=int, default=5, help="part 1 steps per timed window (repeated --repeats times)")
    p.add_argument("--stability", default=str(ROOT / "benchmarks" / "results" / "stability.json"),
                   help="part 2: take the largest stable steps from this stability.json (resolution and k too); "
                        "searched here (--resolution, --ks) if the file does not exist, with --quick, or if ''")
    p.add_argument("--ks", type=float, nargs="+", default=[1e2, 1e3, 1e4, 1e5, 1e6], help="part 2 stiffnesses, N/m")
    p.add_argument("--integrators", nargs="+", default=list(ic.INTEGRATORS), choices=list(ic.INTEGRATORS))
    p.add_argument("--resolution", type=int, default=12, help="part 2 grid vertices per side")
    p.add_argument("--rtol", type=float, default=0.05, help="part 2 bisection stops when hi/lo <= 1 + rtol")
    p.add_argument("--cap", type=float, default=1 / 15, help="part 2 largest dt tried, s")
    p.add_argument("--floor", type=float, default=1e-5, help="part 2 smallest dt tried, s")
    p.add_argument("--duration", type=float, default=0.5, help="part 2 stability trial length, s")
    p.add_argument("--full-max-steps", type=int, default=2000, help="part 2: time whole 1 s runs up to this many steps")
    p.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial velocity perturbation")
    p.add_argument("--clock", choices=["cpu", "wall"], default="cpu",
                   help="cost measure: process CPU time (default) or wall time")
    p.add_argument("--out", default=default_out('headline'), help="output folder (default out/bench/headline; --out benchmarks/results replaces the committed result)")
    p.add_argument("--name", default="headline", help="output file stem (OUT/NAME.json, .md, .png)")
    p.add_argument("--quick", action="store_true", help="8² and 12², two k at 6² searched here, coarse (CI smoke)")
    a = p.parse_args(argv)
    if a.quick:
        a.warmup, a.steps = 2, 3
        a.sizes = [8, 12]
        a.ks, a.resolution, a.rtol, a.duration, a.floor, a.repeats = [1e2, 1e4], 6, 0.5, 0.1, 1e-4, 1
        a.full_max_steps = 200
    CLOCK["name"] = a.clock
    wall0 = time.perf_counter()
    scaling = []
    for n in progress(a.sizes, desc="headline: ms/step"):
        r = step_costs(n, a.k, a.warmup, a.steps, a.repeats)
        scaling.append(r)
        print(f"{n:4d}²  {r['ms_step_cpu']:9.1f} ms/step CPU, {r['ms_step_wall']:9.1f} wall (assembly {r['ms_assembly']:.1f}, setup {r['ms_setup']:.1f}, "
              f"solve {r['ms_solve']:.1f}, collision {r['ms_collision']:.1f}, rest {r['ms_rest']:.1f})  "
              f"its {r['iterations_mean']:.0f}", flush=True)
    searched = load_stability(Path(a.stability)) if (a.stability and not a.quick) else None
    if searched is not None:
        a.resolution, a.ks = searched["settings"]["resolution"], [r["k"] for r in searched["rows"]]
        print(f"largest stable steps from {a.stability} ({a.resolution}², k = {a.ks})", flush=True)
    rows = []
    bar = progress(total=len(a.ks) * len(a.integrators), desc="headline: 1 s per integrator")
    for j, k in enumerate(a.ks):
        base = stability.scene(a.resolution, k)
        if searched is not None:
            row = {"k": k, "mode": searched["rows"][j]["mode"], "results": {}, "source": str(a.stability)}
        else:
            mode = stability.top_mode(ic.Simulator(base, integrator="backward_euler").model, seed=a.seed)
            row = {"k": k, "mode": mode, "results": {}, "source": "searched here"}
        for name in a.integrators:
            if searched is not None:
                got = searched["rows"][j]["results"].get(name)
                if got is None:
                    raise SystemExit(f"headline: {a.stability} has no result for {name} at k = {k:g}")
                r = {key: got[key] for key in ("status", "dt_max", "dt_unstable")}
            else:
                test = lambda dt, name=name, base=base: stability.trial(base, name, dt, a.duration, 20, a.seed)  # noqa: E731
                r = stability.search(test, stability.guess_for(name, row["mode"], a.cap), a.floor, a.cap, a.rtol)
            if r["dt_max"] is not None:
                r["one_second"] = one_second(base, name, r["dt_max"], a.repeats, a.seed, a.full_max_steps)
            row["results"][name] = r
            bar.update(1)
            o = r.get("one_second")
            print(f"k={k:8.0e} {name:17s} dt_max {r['dt_max'] if r['dt_max'] else float('nan'):.3e} s ({r['status']})"
                  + (f"  {o['cost_s']:.3g} s per simulated s ({o['method']}; wall {o['wall_s']:.3g} s)"
                     if o and o["cost_s"] else ""),
                  flush=True)
        row["headline"] = headline_ratio(row)
        rows.append(row)
    bar.close()
    res = {"benchmark": "headline", "quick": a.quick, "seed": a.seed, "machine": machine(),
           "integrators": a.integrators, "ks": a.ks, "sizes": a.sizes,
           "settings": {"k": a.k, "dt": H, "warmup": a.warmup, "steps": a.steps, "resolution": a.resolution,
                        "stability_source": rows[0]["source"] if rows else None,
                        "rtol": a.rtol, "cap": a.cap, "floor": a.floor, "duration": a.duration,
                        "full_max_steps": a.full_max_steps, "repeats": a.repeats, "clock": a.clock},
           "scaling": scaling, "exponent": fit_exponent(scaling), "rows": rows}
    res["headline"] = headline_sentence(rows, a.resolution)
    res["wall_time_s"] = time.perf_counter() - wall0
    md = markdown(res)
    out = Path(a.out)
    write_outputs(out, a.name, res, md)
    plot(res, out / f"{a.name}.png")
    print(md)
    print(f"wall time {res['wall_time_s']:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
