"""What accuracy costs: position error and energy drift against run time, for every integrator, step and tolerance.

Scenes (both ``--resolution`` n = 12: a 12 x 12 cloth, 1 m x 1 m, 0.1 kg, in
the vertical xz plane; structural and shear springs k = 1e3 N/m, bend k/100,
spring damping kd = 0.01 N*s/m (bend kd/100); gravity -z). Both start at the
static equilibrium of the cloth hanging from its two top corners (found by
backward-Euler relaxation at tolerance 1e-10 until every velocity is below
1e-10 m/s; the largest free force left is reported):

* ``hanging``: at t = 0 the top-right pin is released; the cloth swings about
  the top-left corner (a swing of 90 degrees, from 45 degrees right of the
  pin to about 45 degrees left of it in 1 s), folding as it goes;
* ``wind``: both pins kept, air drag 0.2 N*s/m^3 and a wind of 5 m/s along +y
  switched on at t = 0 (a load of about 1 N/m^2 against gravity's 1 N/m^2); the
  cloth is blown out and swings towards its new equilibrium.

Each is simulated for ``--duration`` T = 1 s and compared at the frames
``t = 0, 1/15, ..., T`` (15 Hz: every step of the ladder divides 1/15 s, so every
run is compared at exactly the same times).

Ladder. Time steps ``dt = (1/15 s) / 2^j``, j = 0, 1, ..., down to the first one
below 0.9 x 2/omega_max (omega_max: the largest angular frequency of the
linearised cloth at the start, :func:`stability.top_mode`), so that the smallest
step is stable for symplectic Euler and Verlet, plus ``--explicit-extra`` (1)
further halvings for the explicit methods only (so that each stable explicit
method has at least two points). The implicit methods (backward Euler, BDF2)
run every step >= ``--implicit-min-dt`` (1/480 s; below it their cost per
simulated second only grows) at every solver tolerance of ``--tolerances``
(1e-1 ... 1e-6: the relative error of each step's dv the PCG stops at, see
docs/scene.md, "Filtered PCG"), default multigrid preconditioner, max_iterations 1000.
Explicit methods run every step of the ladder; above their stability limit they
diverge, and a diverged run is recorded as such (status, reason, step reached)
with no error figure. A run that finishes inside the library's divergence
bound (1000 E_scale) but whose total energy leaves the reference's by more than
its energy scale E_scale (:func:`implicit_cloth.diagnostics.energy_scale`, about
1.5-3 J here) is recorded as ``unstable`` (in a few steps forward Euler can
grow by hundreds of joules without reaching 1000 E_scale): its figures stay in
the JSON, but it is left out of the Pareto front and the cheapest-run table.

Reference. RK4 at ``dt_ref`` = smallest ladder step / ``--ref-factor`` (8), about
1/9 of its own stability limit. Its convergence is shown by a second RK4 run at
2 dt_ref: their difference (RMS and max, over frames and vertices, relative to
the cloth size) is reported, and (RK4 being 4th order) the reference's own
error is about that difference / 15. Every error is reported next to this
difference; the smallest measured error should be far above it (the Markdown
states the ratio).

Measured per run (frames at 15 Hz, including t = 0):

* ``rms_error``: sqrt(mean over frames and vertices of |x - x_ref|^2) / L, L =
  1 m the cloth's size (its width);
* ``max_error``: max over frames and vertices of |x - x_ref| / L;
* ``energy_drift``: max over frames of |E(t) - E_ref(t)| / (m g L), E = kinetic +
  spring + gravity energy (J), m g L = 0.98 J the swing's energy scale; and
  ``energy_drift_final`` = (E(T) - E_ref(T)) / (m g L), signed (negative:
  numerical dissipation);
* the cost of the run, ``cost_s``: by default (``--clock cpu``) the CPU time of
  this process (``time.process_time``) spent in ``Simulator.run``, median of
  ``--repeats`` (3) runs; ``--clock wall`` uses the wall time instead. Both are
  kept (``cpu_s``, ``wall_s``, with min and max). The engine steps on one
  thread (BLAS pinned to one), so on an idle machine the two agree; on the
  shared machine these results come from (five jobs on two cores; ``nice``
  made no visible difference) wall times were inflated 5-20 times and varied
  from repeat to repeat, CPU times much less. The simulator's
  construction (including the multigrid hierarchy) is not timed. Diverged runs
  are timed once (to the divergence).

Pareto front: the runs (all integrators of a scene) that no other run beats on
both cost and RMS error (a run must improve on every cheaper run's error by
more than 1 %, so that tolerances giving the same error do not crowd it). For each accuracy level of ``--levels`` (RMS
error <= level) the cheapest run, and the cheapest of the other family
(explicit vs implicit) for comparison.

Usage::

    python benchmarks/accuracy_cost.py                     # the full run, ~15 min on 2 shared cores
    python benchmarks/accuracy_cost.py --scenes hanging --tolerances 1e-2 1e-4 --out /tmp/res
    python benchmarks/accuracy_cost.py --k 1e4 --scenes hanging --tolerances 1e-1 1e-3 --name accuracy_cost_k1e4
    python benchmarks/accuracy_cost.py --quick             # CI smoke test (< 1 min)
    python benchmarks/accuracy_cost.py --render results/accuracy_cost.json --out /tmp/res   # tables and plot only
    implicit-cloth bench accuracy_cost --quick --out /tmp/res

Writes ``OUT/accuracy_cost.json`` (every run's figures, the reference check,
machine, versions; no random input, so ``seed`` is null),
``OUT/accuracy_cost.md`` (tables, Pareto fronts, cheapest method per accuracy
level) and ``OUT/accuracy_cost.png`` (log-log RMS error against cost per
integrator, one panel per scene, Pareto front marked). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np
import stability
from _common import FIXED_STEPS, default_out, ic, machine, progress, save_png, write_outputs

from implicit_cloth import diagnostics

EXPLICIT = ("forward_euler", "symplectic_euler", "verlet", "rk4")
IMPLICIT = ("backward_euler", "bdf2")
SCENES = ("hanging", "wind")
K = 1e3                 # N/m, structural and shear stiffness (bend K / 100); --k sets it for a run
KD = 0.01               # N*s/m, structural and shear damping (bend KD / 100)
SIZE = 1.0              # m, cloth width and height (the L of the relative errors)
MASS = 0.1              # kg
G = 9.81                # m/s^2
DRAG = 0.2              # N*s/m^3, wind scene
WIND = 5.0              # m/s, wind scene, along +y
FRAME_RATE = 15.0       # Hz, comparison frames; the top of the dt ladder is 1 / FRAME_RATE
CLOCK = {"name": "cpu"}   # what ``cost_s`` is: "cpu" (process CPU time) or "wall"; set by --clock
TOLERANCES = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
LEVELS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4)


# --------------------------------------------------------------------------- scenes
def scene(n: int, name: str, k: float | None = None) -> dict:
    """The benchmark cloth: ``"equilibrium"`` (both top corners pinned, gravity), ``"hanging"`` or ``"wind"``.

    ``k`` (N/m, structural and shear; bend k/100) defaults to the module's ``K``.
    """
    k = K if k is None else k
    if name not in ("equilibrium",) + SCENES:
        raise ValueError(f"scene: must be one of equilibrium, {', '.join(SCENES)}, got {name!r}")
    effects: dict = {"gravity": [0.0, 0.0, -G]}
    if name == "wind":
        effects["drag"] = DRAG
        effects["wind"] = {"velocity": [0.0, WIND, 0.0]}
    return {"cloth": {"size": [SIZE, SIZE], "resolution": [n, n], "mass": MASS, "plane": "xz",
                      "pins": ["top_left"] if name == "hanging" else ["top_left", "top_right"],
                      "springs": {"structural": {"stiffness": k, "damping": KD},
                                  "shear": {"stiffness": k, "damping": KD},
                                  "bend": {"stiffness": k / 100, "damping": KD / 100}}},
            "effects": effects}


def equilibrium(n: int) -> tuple[np.ndarray, float]:
    """Static equilibrium hanging from both top corners: positions (n*n, 3) m and the largest free force left (N)."""
    sim = ic.Simulator(scene(n, "equilibrium"), integrator="backward_euler", dt=0.02,
                       solver={"tolerance": 1e-10})
    for _ in range(200):
        sim.step(10)
        if np.abs(sim.velocities).max() < 1e-10:
            break
    x = sim.positions.copy()
    m = sim.model
    f = m.forces(x, np.zeros_like(x), 0.0)
    f[m.pinned] = 0.0
    return x, float(np.abs(f).max())


def ladder(dt_stable: float, explicit_extra: int, top: float = 1 / FRAME_RATE) -> list[float]:
    """``top / 2^j`` for j = 0 .. J + explicit_extra, J the first j with top / 2^j <= 0.9 dt_stable (ascending)."""
    j = 0
    while top / 2 ** j > 0.9 * dt_stable:
        j += 1
    return [top / 2 ** i for i in range(j + explicit_extra, -1, -1)]


# --------------------------------------------------------------------------- runs
def simulate(n: int, name: str, integrator: str, dt: float, x0: np.ndarray, duration: float,
             tolerance: float | None = None, repeats: int = 1) -> dict:
    """Run one scene from ``x0`` (at rest) for ``duration`` s; frames at 15 Hz, timed ``repeats`` times.

    Returns the status (``"ok"`` or ``"diverged"`` with its reason), the frames'
    times, positions (F, N, 3) and total energies (only when ok), the solver's
    figures (implicit methods) and the median, min and max CPU and wall times (s).
    """
    solver = {"tolerance": tolerance} if tolerance is not None else None
    walls: list[float] = []
    cpus: list[float] = []
    out: dict = {}
    for rep in range(max(1, repeats)):
        sim = ic.Simulator(scene(n, name), integrator=integrator, dt=dt, solver=solver, adaptive=FIXED_STEPS)
        sim.positions = x0
        sim.velocities = np.zeros_like(x0)
        e_scale = diagnostics.energy_scale(sim.model, sim.positions, sim.velocities, duration)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ic.SolverWarning)   # counted from the report
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                traj = sim.run(duration=duration, frame_rate=FRAME_RATE)
                status, reason = "ok", ""
            except ic.DivergenceError as exc:
                traj, status, reason = exc.trajectory, "diverged", exc.reason
            cpus.append(time.process_time() - c0)
            walls.append(time.perf_counter() - t0)
        if rep == 0:
            rep0 = traj.report
            out = {"status": status, "reason": reason, "steps": rep0["steps"],
                   "steps_planned": max(1, int(round(duration / dt))), "solver": rep0["solver"],
                   "energy_scale_J": e_scale}
            if status == "ok":
                out["times"] = np.asarray(traj.times)
                out["positions"] = np.asarray(traj.positions)
                out["energy"] = np.asarray(rep0["frames"]["total"])
            else:
                break   # a diverged run is timed once, to its divergence
    out["wall_s"] = statistics.median(walls)
    out["wall_min_s"], out["wall_max_s"] = min(walls), max(walls)
    out["cpu_s"] = statistics.median(cpus)
    out["cpu_min_s"], out["cpu_max_s"] = min(cpus), max(cpus)
    out["cost_s"] = out["cpu_s"] if CLOCK["name"] == "cpu" else out["wall_s"]
    out["repeats"] = len(walls)
    return out


def position_errors(x: np.ndarray, x_ref: np.ndarray, size: float = SIZE) -> tuple[float, float]:
    """RMS and max of ``|x - x_ref|`` over frames and vertices, divided by ``size`` (arrays (F, N, 3))."""
    d = np.linalg.norm(np.asarray(x) - np.asarray(x_ref), axis=-1)
    return float(np.sqrt(np.mean(d * d)) / size), float(d.max() / size)


def reference(n: int, name: str, x0: np.ndarray, duration: float, dt_ref: float) -> dict:
    """RK4 at ``dt_ref`` and at ``2 dt_ref``; the difference of the two shows the reference has converged.

    Returns the reference run (times, positions, energy, wall_s) with
    ``check_rms`` / ``check_max`` (the RMS / max position difference of the two
    runs relative to the cloth size) and ``check_energy`` (max |dE| / (m g L)).
    Raises ``RuntimeError`` if either run diverges.
    """
    ref = simulate(n, name, "rk4", dt_ref, x0, duration)
    chk = simulate(n, name, "rk4", 2 * dt_ref, x0, duration)
    for r, h in ((ref, dt_ref), (chk, 2 * dt_ref)):
        if r["status"] != "ok":
            raise RuntimeError(f"accuracy_cost: the RK4 reference diverged at dt = {h:g} s ({r['reason']}); "
                               "raise --ref-factor")
    if not np.allclose(ref["times"], chk["times"], rtol=0, atol=1e-9):
        raise RuntimeError("accuracy_cost: reference frames at different times")
    ref["check_rms"], ref["check_max"] = position_errors(chk["positions"], ref["positions"])
    ref["check_energy"] = float(np.abs(chk["energy"] - ref["energy"]).max() / (MASS * G * SIZE))
    ref["dt"] = dt_ref
    return ref


def compare(run: dict, ref: dict) -> dict:
    """Error figures of an ok run against the reference (module docstring), added to a copy of ``run``."""
    r = {k: v for k, v in run.items() if k not in ("times", "positions", "energy")}
    if run["status"] != "ok":
        return r
    if not np.allclose(run["times"], ref["times"], rtol=0, atol=1e-9):
        raise RuntimeError("accuracy_cost: run and reference frames at different times")
    r["rms_error"], r["max_error"] = position_errors(run["positions"], ref["positions"])
    de = (run["energy"] - ref["energy"]) / (MASS * G * SIZE)
    r["energy_drift"] = float(np.abs(de).max())
    r["energy_drift_final"] = float(de[-1])
    off = r["energy_drift"] * MASS * G * SIZE
    if off > run["energy_scale_J"]:   # finished within the library's bound (1000 E_scale), but unstable
        i = int(np.argmax(np.abs(de)))
        r["status"] = "unstable"
        r["reason"] = (f"energy off the reference by {off:.3g} J at t={run['times'][i]:.4g} s, more than the run's "
                       f"energy scale {run['energy_scale_J']:.3g} J")
    return r


# --------------------------------------------------------------------------- analysis
def pareto(runs: list[dict], margin: float = 0.01) -> list[dict]:
    """The Pareto front of the ok runs in (``cost_s``, ``rms_error``), by increasing cost.

    A run is on the front if every cheaper run has a larger RMS error; to keep
    runs that differ only in the solver tolerance (same error to a few digits)
    from crowding it, a run must improve on the best cheaper error by more than
    ``margin`` (1 %) to count.
    """
    ok = sorted((r for r in runs if r["status"] == "ok"), key=lambda r: (r["cost_s"], r["rms_error"]))
    front, best = [], math.inf
    for r in ok:
        if r["rms_error"] < (1 - margin) * best:
            front.append(r)
            best = r["rms_error"]
    return front


def cheapest(runs: list[dict], level: float, family: tuple[str, ...] | None = None) -> dict | None:
    """The ok run of least ``cost_s`` with ``rms_error <= level`` (among ``family`` if given), or None."""
    ok = [r for r in runs if r["status"] == "ok" and r["rms_error"] <= level
          and (family is None or r["integrator"] in family)]
    return min(ok, key=lambda r: r["cost_s"]) if ok else None


# --------------------------------------------------------------------------- output
def _dt_label(dt: float) -> str:
    inv = 1 / dt
    return f"1/{round(inv)}" if abs(inv - round(inv)) < 1e-6 * inv else f"{dt:.3g}"


def _run_label(r: dict) -> str:
    tol = f", tol {r['tolerance']:g}" if r.get("tolerance") is not None else ""
    return f"{r['integrator']} dt={_dt_label(r['dt'])}{tol}"


def _cell(r: dict | None) -> str:
    if r is None:
        return "-"
    if r["status"] == "unstable":
        return f"unstable (ΔE {r['energy_drift'] * MASS * G * SIZE / r['energy_scale_J']:.2g} E_scale)"
    if r["status"] != "ok":
        return f"div (step {r['steps']}/{r['steps_planned']})"
    return f"{r['rms_error']:.2e} / {r['max_error']:.2e} / {r['energy_drift']:.1e}, {r['cost_s']:.3g} s"


def markdown(res: dict) -> str:
    s = res["settings"]
    out = [f"{s['resolution']}² cloth, 1 m x 1 m, 0.1 kg, vertical, k = {s['k']:g} N/m (bend {s['k'] / 100:g}), "
           f"kd = {KD:g} N·s/m; from the equilibrium hanging by both top corners; {s['duration']:g} s simulated, "
           f"compared at 15 Hz frames. Cell: RMS / max vertex position error relative to the cloth size (1 m) / "
           f"max |E − E_ref| over m g L ({MASS * G * SIZE:.3g} J), and the cost of the run: its "
           f"{'CPU' if s['clock'] == 'cpu' else 'wall'} time, s (median of {s['repeats']}; "
           f"{res['machine']['cpus']} cores shared with other jobs, one BLAS thread; wall times in the JSON). "
           f"div: diverged (step reached / planned), no error figure; unstable: finished, but its energy left the "
           f"reference's by more than the run's energy scale E_scale (ratio given); -: not run.", ""]
    for name in res["scenes"]:
        sc = res["results"][name]
        ref = sc["reference"]
        runs = sc["runs"]
        oks = [r for r in runs if r["status"] == "ok"]
        smallest = min((r["rms_error"] for r in oks), default=float("nan"))
        out += [f"## Scene `{name}`", "",
                f"ω_max = {sc['mode']['omega_max']:.4g} rad/s at the start (2/ω_max = "
                f"{sc['mode']['bound_2_over_w']:.3e} s). Reference: RK4 at dt_ref = {ref['dt']:.3e} s "
                f"({ref['wall_s']:.1f} s of wall time). Convergence: RK4 at 2 dt_ref differs from it by "
                f"{ref['check_rms']:.1e} RMS / {ref['check_max']:.1e} max (relative to the size) and "
                f"{ref['check_energy']:.1e} m g L in energy, so the reference's own error is about "
                f"{ref['check_rms'] / 15:.0e} RMS (4th order: difference / 15). The smallest error measured below "
                f"is {smallest:.1e} RMS, {smallest / ref['check_rms']:.2g} x the difference.", "",
                "### Explicit methods", "",
                "| dt (s) | " + " | ".join(res["explicit"]) + " |", "|---" * (1 + len(res["explicit"])) + "|"]
        by = {(r["integrator"], r["dt"], r.get("tolerance")): r for r in runs}
        for h in sc["dts"]:
            out.append(f"| {_dt_label(h)} | " + " | ".join(_cell(by.get((i, h, None))) for i in res["explicit"]) + " |")
        for i in res["implicit"]:
            out += ["", f"### {i} (columns: solver tolerance)", "",
                    "| dt (s) | " + " | ".join(f"{t:g}" for t in res["tolerances"]) + " |",
                    "|---" * (1 + len(res["tolerances"])) + "|"]
            for h in sc["dts"]:
                if h < s["implicit_min_dt"] * (1 - 1e-9):
                    continue
                out.append(f"| {_dt_label(h)} | " + " | ".join(_cell(by.get((i, h, t))) for t in res["tolerances"])
                           + " |")
        out += ["", "### Pareto front (no other run is both cheaper and more accurate)", "",
                "| run | cost (s) | RMS error | max error | energy drift | mean CG its |", "|---|---|---|---|---|---|"]
        for r in sc["pareto"]:
            its = f"{r['solver']['mean_iterations']:.1f}" if r.get("solver") else "-"
            out.append(f"| {_run_label(r)} | {r['cost_s']:.3g} | {r['rms_error']:.2e} | {r['max_error']:.2e} | "
                       f"{r['energy_drift']:.1e} | {its} |")
        out += ["", "### Cheapest run for each accuracy level (RMS error ≤ level)", "",
                "| level | cheapest run | cost (s) | RMS error | cheapest explicit | cost (s) | cheapest implicit | "
                "cost (s) | implicit / explicit cost |", "|---|---|---|---|---|---|---|---|---|"]
        for row in sc["cheapest"]:
            b, e, i = row["best"], row["explicit"], row["implicit"]
            cells = [f"{row['level']:g}"]
            cells += [_run_label(b), f"{b['cost_s']:.3g}", f"{b['rms_error']:.1e}"] if b else ["none", "-", "-"]
            for r in (e, i):
                cells += [_run_label(r), f"{r['cost_s']:.3g}"] if r else ["none", "-"]
            cells.append(f"{i['cost_s'] / e['cost_s']:.2g}" if (e and i) else "-")
            out.append("| " + " | ".join(cells) + " |")
        div = [r for r in runs if r["status"] == "diverged"]
        uns = [r for r in runs if r["status"] == "unstable"]
        out += ["", f"Diverged runs: {len(div)} of {len(runs)}; unstable: {len(uns)}"
                + (f" ({', '.join(_run_label(r) for r in uns)})" if uns else "") + ".", ""]
    return "\n".join(out)


STYLE = stability.STYLE


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = res["scenes"]
    fig, axes = plt.subplots(1, len(names), figsize=(7.5 * len(names), 6), squeeze=False)
    for ax, name in zip(axes[0], names):
        sc = res["results"][name]
        runs = sc["runs"]
        ok = [r for r in runs if r["status"] == "ok"]
        top = max((r["rms_error"] for r in ok), default=1.0) * 3
        for integ in res["explicit"] + res["implicit"]:
            mk, col = STYLE.get(integ, ("o", None))
            mine = [r for r in ok if r["integrator"] == integ]
            if integ in EXPLICIT:
                mine.sort(key=lambda r: r["dt"])
                ax.loglog([r["cost_s"] for r in mine], [r["rms_error"] for r in mine], marker=mk, color=col,
                          ls="-", lw=1, ms=6, label=integ)
            else:   # one line per tolerance across dt; lighter for looser tolerances
                for j, tol in enumerate(res["tolerances"]):
                    pts = sorted((r for r in mine if r["tolerance"] == tol), key=lambda r: r["dt"])
                    if pts:
                        ax.loglog([r["cost_s"] for r in pts], [r["rms_error"] for r in pts], marker=mk, color=col,
                                  ls="-", lw=0.6, ms=4 + 0.6 * j, alpha=0.35 + 0.1 * j,
                                  label=f"{integ} (tol {res['tolerances'][0]:g} … {res['tolerances'][-1]:g}, "
                                        "darker = tighter)" if j == len(res["tolerances"]) - 1 else None)
            div = [r for r in runs if r["integrator"] == integ and r["status"] != "ok"]
            if div:
                ax.loglog([r["cost_s"] for r in div], [top] * len(div), ls="none", marker="x", color=col, ms=7)
        front = sc["pareto"]
        ax.loglog([r["cost_s"] for r in front], [r["rms_error"] for r in front], drawstyle="steps-post", color="k",
                  lw=1.5, label="Pareto front")
        ax.loglog([r["cost_s"] for r in front], [r["rms_error"] for r in front], ls="none", marker="o", ms=12,
                  mfc="none", mec="k")
        ax.axhline(sc["reference"]["check_rms"], color="0.5", ls=":", lw=1)
        ax.text(ax.get_xlim()[0], sc["reference"]["check_rms"] * 1.2, " reference vs 2 dt_ref", fontsize=7,
                color="0.4")
        ax.axhline(top, color="0.7", ls="--", lw=0.8)
        ax.text(ax.get_xlim()[0], top * 1.1, " x: diverged (no error; at its cost to divergence)", fontsize=7, color="0.4")
        ax.set_xlabel(f"{'CPU' if res['settings']['clock'] == 'cpu' else 'wall'} time of the run "
                      f"(s, median of {res['settings']['repeats']})")
        ax.set_ylabel("RMS vertex position error / cloth size (1)")
        ax.set_title(f"{name}: {res['settings']['resolution']}² cloth, {res['settings']['duration']:g} s simulated")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="center left")
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


def analyse(runs: list[dict], levels: list[float]) -> tuple[list[dict], list[dict]]:
    """The Pareto front and, for each level (decreasing), the cheapest run overall / explicit / implicit."""
    cheap = [{"level": lv, "best": cheapest(runs, lv), "explicit": cheapest(runs, lv, EXPLICIT),
              "implicit": cheapest(runs, lv, IMPLICIT)} for lv in sorted(levels, reverse=True)]
    return pareto(runs), cheap


def render(path: Path, out: Path, name: str = "accuracy_cost") -> int:
    """Re-derive fronts and cheapest runs of a saved result (the runs themselves unchanged) and write the outputs."""
    import json

    res = json.loads(Path(path).read_text())
    if res.get("benchmark") != "accuracy_cost":
        raise SystemExit(f"accuracy_cost: --render: not an accuracy_cost result, got {str(path)!r}")
    for sc in res["results"].values():
        sc["pareto"], sc["cheapest"] = analyse(sc["runs"], res["settings"]["levels"])
    md = markdown(res)
    write_outputs(out, name, res, md)
    plot(res, out / f"{name}.png")
    print(md)
    return 0


# --------------------------------------------------------------------------- main
def _dt(s: str) -> float:
    return float(Fraction(s)) if "/" in s else float(s)


def main(argv: list[str] | None = None) -> int:
    global K
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--integrators", nargs="+", default=list(ic.INTEGRATORS), choices=list(ic.INTEGRATORS))
    p.add_argument("--resolution", type=int, default=12, help="grid vertices per side")
    p.add_argument("--duration", type=_dt, default=1.0, help="simulated time, s (a multiple of 1/15)")
    p.add_argument("--tolerances", type=float, nargs="+", default=list(TOLERANCES),
                   help="solver tolerances of the implicit methods")
    p.add_argument("--explicit-extra", type=int, default=1, help="halvings below the stable explicit step")
    p.add_argument("--implicit-min-dt", type=_dt, default=1 / 480, help="implicit methods skip smaller steps, s")
    p.add_argument("--ref-factor", type=int, default=8, help="dt_ref = smallest ladder step / this")
    p.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    p.add_argument("--clock", choices=["cpu", "wall"], default="cpu",
                   help="cost measure: process CPU time (default) or wall time")
    p.add_argument("--levels", type=float, nargs="+", default=list(LEVELS), help="RMS error levels")
    p.add_argument("--out", default=default_out('accuracy_cost'), help="output folder (default out/bench/accuracy_cost; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="6² cloth, 0.2 s, two tolerances, one repeat (CI smoke)")
    p.add_argument("--k", type=float, default=K, help="structural and shear spring stiffness, N/m (bend k/100)")
    p.add_argument("--name", default="accuracy_cost", help="output file stem (OUT/NAME.json, .md, .png)")
    p.add_argument("--render", metavar="JSON",
                   help="do not simulate: re-derive the Pareto fronts and cheapest runs of an accuracy_cost.json "
                        "and write the MD and PNG (and the JSON) to --out")
    a = p.parse_args(argv)
    if a.render:
        return render(Path(a.render), Path(a.out), a.name)
    if a.quick:
        a.resolution, a.duration, a.tolerances, a.repeats = 6, 0.2, [1e-1, 1e-3], 1
        a.implicit_min_dt, a.ref_factor, a.explicit_extra = 1 / 240, 4, 0
    CLOCK["name"] = a.clock
    K = a.k   # every scene of this run (module default otherwise)
    steps_15 = a.duration * FRAME_RATE
    if abs(steps_15 - round(steps_15)) > 1e-9 or steps_15 < 1:
        raise SystemExit(f"accuracy_cost: --duration must be a positive multiple of 1/15 s, got {a.duration:g}")
    wall0 = time.perf_counter()
    n = a.resolution
    x0, residual = equilibrium(n)
    print(f"equilibrium ({n}²): largest free force {residual:.2e} N", flush=True)
    explicit = [i for i in a.integrators if i in EXPLICIT]
    implicit = [i for i in a.integrators if i in IMPLICIT]
    results = {}
    dts: list[float] = []
    for name in a.scenes:
        probe = ic.Simulator(scene(n, name), integrator="backward_euler", dt=0.01)
        probe.positions = x0
        mode = stability.top_mode(probe.model, x0)
        dts = ladder(mode["bound_2_over_w"], a.explicit_extra)
        dt_ref = dts[0] / a.ref_factor
        print(f"{name}: w_max = {mode['omega_max']:.5g} rad/s, 2/w_max = {mode['bound_2_over_w']:.4e} s; ladder "
              f"{', '.join(_dt_label(h) for h in dts)}; reference RK4 at {dt_ref:.3e} s", flush=True)
        ref = reference(n, name, x0, a.duration, dt_ref)
        print(f"  reference vs 2 dt_ref: RMS {ref['check_rms']:.2e}, max {ref['check_max']:.2e}, energy "
              f"{ref['check_energy']:.2e} m g L  [{ref['wall_s']:.1f} s]", flush=True)
        for i in a.integrators:   # untimed warm-up: lazy imports and first-call costs stay out of the timings
            simulate(n, name, i, dts[-1], x0, 1 / FRAME_RATE)
        jobs = [(i, h, None) for i in explicit for h in dts]
        jobs += [(i, h, t) for i in implicit for h in dts if h >= a.implicit_min_dt * (1 - 1e-9)
                 for t in a.tolerances]
        runs = []
        for i, h, t in progress(jobs, desc=f"accuracy_cost {name}"):
            run = simulate(n, name, i, h, x0, a.duration, tolerance=t, repeats=a.repeats)
            r = compare(run, ref)
            r.update({"integrator": i, "dt": h, "tolerance": t})
            runs.append(r)
            tag = f"{i:17s} dt={_dt_label(h):>7s}" + (f" tol={t:g}" if t is not None else "")
            if r["status"] == "ok":
                print(f"  {tag:40s} rms {r['rms_error']:.2e} max {r['max_error']:.2e} dE {r['energy_drift']:.1e}  "
                      f"[{r['cost_s']:.3g} s]", flush=True)
            else:
                print(f"  {tag:40s} diverged at step {r['steps']}/{r['steps_planned']}  [{r['cost_s']:.3g} s]",
                      flush=True)
        front, cheap = analyse(runs, a.levels)
        ref_out = {k: v for k, v in ref.items() if k not in ("times", "positions", "energy")}
        ref_out["energy_J"] = ref["energy"].tolist()
        ref_out["times"] = ref["times"].tolist()
        results[name] = {"mode": mode, "dts": dts, "reference": ref_out, "runs": runs,
                         "pareto": front, "cheapest": cheap}
    res = {"benchmark": "accuracy_cost", "quick": a.quick, "seed": None, "machine": machine(),
           "scenes": a.scenes, "explicit": explicit, "implicit": implicit, "tolerances": a.tolerances,
           "dts": dts,
           "settings": {"resolution": n, "size_m": SIZE, "mass_kg": MASS, "k": K, "kd": KD, "drag": DRAG,
                        "wind_m_per_s": WIND, "duration": a.duration, "frame_rate": FRAME_RATE,
                        "explicit_extra": a.explicit_extra, "implicit_min_dt": a.implicit_min_dt,
                        "ref_factor": a.ref_factor, "repeats": a.repeats, "levels": a.levels, "clock": a.clock,
                        "equilibrium_residual_N": residual},
           "measured": ("rms_error = sqrt(mean_{frames, vertices} |x - x_ref|^2) / L; max_error = max |x - x_ref| / L; "
                        "energy_drift = max_frames |E - E_ref| / (m g L); energy_drift_final signed at T; cost_s = "
                        "median over repeats of the CPU (--clock cpu) or wall time of Simulator.run; frames at 15 Hz incl. t = 0; x_ref: RK4 at dt_ref"),
           "results": results}
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
