"""Largest stable time step of each integrator against spring stiffness, next to the explicit bound 2/w_max.

Scene: a 12 x 12 cloth, 1 m x 1 m, 0.1 kg, flat at rest in the xy plane, top
corners pinned, gravity (-z); structural and shear springs of stiffness k, bend
springs of k/100, light damping kd = 0.01 N*s/m (structural, shear) and
1e-4 N*s/m (bend), i.e. the spring damping matrix is (0.01 / k) times the
stiffness matrix at rest. k runs over a log ladder, 1e2 .. 1e6 N/m by default.
Every run starts from the flat rest pose with a small seeded velocity
perturbation (each component of each free vertex ~ N(0, (1e-3 m/s)^2), seed
``--seed``) so that every mode, the stiffest one included, is excited; the cloth
then falls and swings under gravity.

Theoretical bound. K = -dF/dx at the rest pose (the solver's Jacobian, which is
exact at rest since no spring is compressed), pinned vertices removed, lumped
diagonal M. ``w_max^2`` is the largest eigenvalue of ``K phi = lambda M phi``,
computed with ARPACK (``scipy.sparse.linalg.eigsh``, which="LA", tol=0) on
``M^-1/2 K M^-1/2``. For an undamped linear system symplectic Euler and velocity
Verlet are stable iff ``dt < 2 / w_max``; RK4's stability interval on the
imaginary axis is ``2 sqrt(2) / w_max``; forward Euler is unstable on every
undamped mode and, with the damping ratio ``zeta`` of the stiffest mode
(``zeta = gamma / (2 w_max)``, ``gamma = phi^T C phi`` with C = -dF/dv and phi the
M-normalised top mode), needs ``dt < 2 zeta / w_max`` (= kd / k here, for every
elastic mode). Light damping also lowers symplectic Euler's bound to
``(sqrt(1 + zeta^2) - zeta) 2 / w_max`` (reported as "2/w damped").

Stability criterion (what "stable at dt" means). A run of ``--duration`` T
(0.5 s; longer if needed to take ``--min-steps`` 20 steps) from the perturbed
rest pose, with energies checked at kept frames every 1/240 s (every step when
dt > 1/240 s), is *stable* iff

* every state is finite, and
* at every kept frame ``E_total(t) - E_total(0) <= E_bound`` (total = kinetic +
  spring + gravity energy), where ``E_bound`` is the energy scale ``E_scale`` of
  :mod:`implicit_cloth.diagnostics` for a run of exactly T from the same
  initial state (about m g L: 2.6 J at T = 0.5 s), the same for every dt of a
  given k.

The physical motion only loses energy (spring damping, no moving pins), so any
growth is numerical. Explicit runs are made with ``divergence_factor = 1`` so
that they stop as soon as the bound is crossed; past their bound they grow
geometrically, so the threshold depends only weakly on the bound. Measured once
(seed 0, 12² cloth, bisection to 0.1 %): with a bound of 1000 E_scale instead
of E_scale the thresholds move up by 0.07-0.9 % for symplectic Euler and by
1-10 % for RK4 (largest at low k), whose amplification grows only linearly in
dt past 2 sqrt(2) / w (symplectic Euler's as the square root). Implicit runs are made with the library's default
``divergence_factor = 1000`` (whole run seen; the JSON keeps that verdict too as
``library_check_ok``) and then judged against ``E_bound``: their failure mode
here is not exponential growth but a transient energy spike in the first steps
(one linearised Newton step per time step from the flat pose overshoots), so
for them the verdict does depend on the bound; the third Markdown table shows
the size of the spike at the cap. Implicit runs use the default solver settings
(multigrid PCG, tolerance 1e-3); steps where PCG hit its iteration limit are
counted and reported, they do not make a run unstable.

Forward Euler is a special case: near its bound growth is slow (its rate is
``(dt w^2 - 2 zeta w) / 2`` per second on the top mode), so its "largest stable
dt" is a finite-time figure that depends on T and on the size of the
perturbation; read it as an order of magnitude.

Search. The step is capped at ``--cap`` (1/15 s: methods stable there are
reported "stable at the cap") and floored at ``--floor`` (1e-5 s: methods
unstable there are reported "< floor", to keep the run time bounded). From a
first guess (the theoretical bound of the method, else the cap) the step is
doubled or halved until a stable/unstable pair brackets the threshold, which is
then bisected in log(dt) until ``hi / lo <= 1 + --rtol`` (1 %). Stability is
assumed monotone in dt (stable below the threshold, unstable above); the
largest step found stable is reported with the smallest found unstable. Every
trial (dt, verdict, reason, steps, wall time) is kept in the JSON.

Cost. At the largest stable step the wall time of ``--time-steps`` steps is
measured ``--repeats`` times (median), and reported as ms/step and as wall
seconds per simulated second (ms/step / dt): what simulating 1 s costs at the
method's largest stable step on this machine. Never asserted.

Usage::

    python benchmarks/stability.py                          # k = 1e2 .. 1e6, ~2.5 min
    python benchmarks/stability.py --ks 1e3 1e4 --out /tmp/res
    python benchmarks/stability.py --quick                  # CI smoke test (< 1 min)
    implicit-cloth bench stability --quick --out /tmp/res

Writes ``OUT/stability.json`` (raw figures, every trial, machine, versions,
seed), ``OUT/stability.md`` (the tables) and ``OUT/stability.png`` (log-log
plot of the largest stable dt against k with the 2/w_max line).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from _common import FIXED_STEPS, STYLE, default_out, hanging_stiff, ic, machine, progress, save_png, write_outputs

from implicit_cloth import diagnostics

EXPLICIT = ("forward_euler", "symplectic_euler", "verlet", "rk4")
FRAME_RATE = 240.0
NOISE = 1e-3           # m/s, standard deviation of the initial velocity perturbation
KD = 0.01              # N*s/m, structural and shear damping (bend: KD / 100)


# --------------------------------------------------------------------------- scene
def scene(n: int, k: float) -> dict:
    """The benchmark cloth at stiffness ``k`` (see the module docstring)."""
    s = hanging_stiff(n, k)
    s["cloth"]["springs"] = {"structural": {"stiffness": k, "damping": KD},
                             "shear": {"stiffness": k, "damping": KD},
                             "bend": {"stiffness": k / 100, "damping": KD / 100}}
    return s


# --------------------------------------------------------------------------- eigenvalues
def free_matrices(model, x: np.ndarray | None = None) -> tuple[sp.csr_array, sp.csr_array, np.ndarray]:
    """``K = -dF/dx``, ``C = -dF/dv`` (the solver's Jacobians) on the free coordinates, and their masses.

    Assembled with :meth:`Model.linearize` (``A = M - c_v dF/dv - c_x dF/dx``) with
    ``(c_x, c_v) = (1, 0)`` and ``(0, 1)``, minus the lumped mass diagonal; pinned
    vertices' rows and columns are removed. ``x`` defaults to the rest pose.
    Returns ``K``, ``C`` (3F x 3F) and the (3F,) masses of the free coordinates.
    """
    x = model.rest_positions if x is None else np.asarray(x, dtype=float)
    v = np.zeros_like(x)
    m3 = np.repeat(model.masses, 3)
    free = np.repeat(model.free, 3)
    M = sp.diags_array(m3, format="csr")
    out = []
    for c_x, c_v in ((1.0, 0.0), (0.0, 1.0)):
        A, _, _ = model.linearize(x, v, 0.0, c_x, c_v)
        out.append((A - M).tocsr()[free][:, free])
    return out[0], out[1], m3[free]


def top_mode(model, x: np.ndarray | None = None, seed: int = 0) -> dict:
    """The stiffest mode of ``K phi = w^2 M phi`` (free coordinates, lumped M).

    Returns ``omega_max`` (rad/s), ``lambda_max`` (= omega_max^2, 1/s^2), the modal
    damping rate ``gamma = phi^T C phi`` (1/s, phi M-normalised), ``zeta`` =
    gamma / (2 omega_max), and the explicit bounds (s): ``bound_2_over_w`` = 2 /
    w_max (symplectic Euler, Verlet), ``bound_rk4`` = 2 sqrt(2) / w_max,
    ``bound_se_damped`` = (sqrt(1 + zeta^2) - zeta) 2 / w_max and
    ``bound_fe_damped`` = 2 zeta / w_max.
    """
    K, C, m = free_matrices(model, x)
    d = sp.diags_array(1.0 / np.sqrt(m), format="csr")
    S = (d @ K @ d).tocsr()
    v0 = np.random.default_rng(seed).standard_normal(S.shape[0])   # not a symmetric start: it could miss the top mode
    lam, phi = spla.eigsh(S, k=1, which="LA", tol=0, v0=v0)
    lam_max = float(lam[0])
    w = math.sqrt(lam_max)
    p = phi[:, 0]
    gamma = float(p @ ((d @ C @ d) @ p) / (p @ p))
    zeta = gamma / (2 * w)
    return {"lambda_max": lam_max, "omega_max": w, "gamma": gamma, "zeta": zeta,
            "bound_2_over_w": 2 / w, "bound_rk4": 2 * math.sqrt(2) / w,
            "bound_se_damped": (math.sqrt(1 + zeta * zeta) - zeta) * 2 / w,
            "bound_fe_damped": 2 * zeta / w}


def omega_max(model, x: np.ndarray | None = None) -> float:
    """Largest angular frequency of the free, undamped linearised cloth at ``x`` (rest pose by default), rad/s."""
    return top_mode(model, x)["omega_max"]


# --------------------------------------------------------------------------- one trial
def perturbed(sim: ic.Simulator, seed: int) -> None:
    v = np.random.default_rng(seed).normal(0.0, NOISE, (sim.model.n, 3))
    sim.velocities = v


def trial(base: dict, integrator: str, dt: float, duration: float, min_steps: int, seed: int) -> dict:
    """One run at ``dt``; its verdict under the stability criterion (module docstring)."""
    # explicit runs stop as soon as the energy grew by their own energy scale (they blow up geometrically, and
    # stopping early saves time); implicit runs use the library's default bound so that the whole run is seen
    # and its verdict under the library's own divergence check is known too
    factor = 1.0 if integrator in EXPLICIT else diagnostics.DEFAULT_DIVERGENCE_FACTOR
    sim = ic.Simulator(base, integrator=integrator, dt=dt, divergence_factor=factor, adaptive=FIXED_STEPS)
    perturbed(sim, seed)
    # the bound: the energy scale of a run of exactly `duration` from this state (the same for every dt)
    bound = diagnostics.energy_scale(sim.model, sim.positions, sim.velocities, duration)
    T = max(duration, min_steps * dt)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)   # counted below from the report
        try:
            traj = sim.run(duration=T, frame_rate=FRAME_RATE)
            rep, stable, reason = traj.report, True, ""
        except ic.DivergenceError as exc:
            rep, stable, reason = exc.trajectory.report, False, exc.reason
    wall = time.perf_counter() - t0
    fr = rep["frames"]
    e = np.asarray(fr["total"])
    growth = float(np.max(e - e[0])) if len(e) else 0.0
    library_ok = stable if factor == diagnostics.DEFAULT_DIVERGENCE_FACTOR else None
    if stable and growth > bound:   # the run's own bound was larger (factor 1000, or T > duration)
        i = int(np.argmax(e - e[0]))
        stable = False
        reason = (f"energy grew by {growth:.3g} J at t={fr['time'][i]:.6g} s, beyond the bound {bound:.3g} J "
                  f"(energy scale of a {duration:g} s run)")
    return {"dt": dt, "stable": stable, "reason": reason, "library_check_ok": library_ok,
            "divergence_factor": factor, "steps": rep["steps"],
            "steps_planned": max(1, int(round(T / dt))), "wall_s": wall, "bound_J": bound,
            "max_growth_J": growth, "max_growth_over_bound": growth / bound,
            "max_strain": float(np.max(fr["max_strain"])) if fr["max_strain"] else 0.0,
            "unconverged_steps": (rep["solver"] or {}).get("unconverged_steps", 0)}


def search(test, guess: float, floor: float, cap: float, rtol: float) -> dict:
    """Bracket and bisect (in log dt) the largest stable step in ``[floor, cap]`` (module docstring)."""
    trials: list[dict] = []

    def ok(dt: float) -> bool:
        r = test(dt)
        trials.append(r)
        return r["stable"]

    g = min(max(guess, floor), cap)
    lo = hi = None
    if ok(g):
        lo = g
        while hi is None:
            if lo >= cap:
                return {"status": "at_cap", "dt_max": cap, "dt_unstable": None, "trials": trials}
            t = min(2 * lo, cap)
            if ok(t):
                lo = t
            else:
                hi = t
    else:
        hi = g
        while lo is None:
            if hi <= floor:
                return {"status": "below_floor", "dt_max": None, "dt_unstable": floor, "trials": trials}
            t = max(hi / 2, floor)
            if ok(t):
                lo = t
            else:
                hi = t
    while hi / lo > 1 + rtol:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return {"status": "bracketed", "dt_max": lo, "dt_unstable": hi, "trials": trials}


def step_cost(base: dict, integrator: str, dt: float, steps: int, repeats: int, seed: int) -> float | None:
    """Median wall time of one step at ``dt`` over ``repeats`` runs of ``steps`` steps, s (None if it diverged)."""
    sim = ic.Simulator(base, integrator=integrator, dt=dt, adaptive=FIXED_STEPS)
    perturbed(sim, seed)
    times = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)
        try:
            sim.step(1)   # first-step work (Verlet's first force, BDF2's start) not timed
            for _ in range(repeats):
                t0 = time.perf_counter()
                sim.step(steps)
                times.append((time.perf_counter() - t0) / steps)
        except ic.DivergenceError:
            return None
    return statistics.median(times)


def guess_for(integrator: str, mode: dict, cap: float) -> float:
    return {"forward_euler": mode["bound_fe_damped"], "symplectic_euler": mode["bound_2_over_w"],
            "verlet": mode["bound_2_over_w"], "rk4": mode["bound_rk4"]}.get(integrator, cap)


# --------------------------------------------------------------------------- output
def _cell(r: dict, w_bound: float) -> str:
    if r["status"] == "at_cap":
        return f"≥ {r['dt_max']:.3g} (cap)"
    if r["status"] == "below_floor":
        return f"< {r['dt_unstable']:.3g} (floor)"
    return f"{r['dt_max']:.3g} ({r['dt_max'] / w_bound:.3g})"


def markdown(res: dict) -> str:
    s = res["settings"]
    ints = res["integrators"]
    out = [f"Largest stable dt (s) of each integrator; in parentheses dt_max / (2/ω_max). "
           f"{s['resolution']}² cloth, 1 m, 0.1 kg, flat, top corners pinned, gravity; structural = shear = k, "
           f"bend = k/100; kd = {KD:g} N·s/m (bend {KD / 100:g}). Stable: {s['duration']:g} s "
           f"(≥ {s['min_steps']} steps) from rest + N(0, ({NOISE:g} m/s)²) velocities (seed {res['seed']}), "
           f"finite, and E_total(t) − E_total(0) ≤ E_bound (energy scale of a {s['duration']:g} s run, "
           f"{res['rows'][0]['results'][ints[0]]['trials'][0]['bound_J']:.2g} J) at every frame "
           f"(1/{FRAME_RATE:g} s). Bisection to hi/lo ≤ {1 + s['rtol']:g}; cap {s['cap']:.3g} s, "
           f"floor {s['floor']:.3g} s.", "",
           "| k (N/m) | ω_max (rad/s) | 2/ω_max (s) | 2/ω damped (s) | ζ_top | " + " | ".join(ints) + " |",
           "|---" * (5 + len(ints)) + "|"]
    for row in res["rows"]:
        m = row["mode"]
        cells = [_cell(row["results"][i], m["bound_2_over_w"]) for i in ints]
        out.append(f"| {row['k']:.0e} | {m['omega_max']:.4g} | {m['bound_2_over_w']:.3e} | "
                   f"{m['bound_se_damped']:.3e} | {m['zeta']:.2g} | " + " | ".join(cells) + " |")
    out += ["", f"Cost at the largest stable dt: wall seconds per simulated second (median of {s['repeats']} x "
            f"{s['time_steps']} steps; in parentheses ms/step). {res['machine']['cpus']} cores, one BLAS thread, "
            f"shared machine.", "",
            "| k (N/m) | " + " | ".join(ints) + " |", "|---" * (1 + len(ints)) + "|"]
    for row in res["rows"]:
        cells = []
        for i in ints:
            r = row["results"][i]
            if r.get("s_per_step") is None:
                cells.append("-")
            else:
                cells.append(f"{r['s_per_step'] / r['dt_max']:.3g} ({1e3 * r['s_per_step']:.2g})")
        out.append(f"| {row['k']:.0e} | " + " | ".join(cells) + " |")
    imp = [i for i in ints if i not in EXPLICIT]
    if imp:
        out += ["", f"Implicit methods at the cap dt = {s['cap']:.3g} s (first trial): largest energy growth over "
                f"E_bound, largest structural strain, and the verdict of the library's own divergence check "
                f"(factor 1000).", "",
                "| k (N/m) | " + " | ".join(f"{i}: growth/E_bound, max strain, library check" for i in imp) + " |",
                "|---" * (1 + len(imp)) + "|"]
        for row in res["rows"]:
            cells = []
            for i in imp:
                t0 = next((t for t in row["results"][i]["trials"] if t["dt"] == s["cap"]), None)
                if t0 is None:
                    cells.append("-")
                elif t0["library_check_ok"] is False:   # stopped at the step that crossed 1000 E_scale
                    cells.append(f"> 1000 E_scale at step {t0['steps']}: diverged")
                else:
                    cells.append(f"{t0['max_growth_over_bound']:.3g}, {t0['max_strain']:.3g}, ok")
            out.append(f"| {row['k']:.0e} | " + " | ".join(cells) + " |")
    unconv = [(row["k"], i, t["dt"], t["unconverged_steps"]) for row in res["rows"] for i in ints
              for t in row["results"][i]["trials"] if t["unconverged_steps"]]
    out += ["", "Theory: symplectic Euler and Verlet need dt < 2/ω_max undamped, (√(1+ζ²) − ζ)·2/ω_max "
            "with the top mode's damping ratio ζ; RK4 2√2/ω_max; forward Euler 2ζ/ω_max = kd/k here "
            "(unstable on every undamped mode). Implicit methods are linearised once per step: A-stable for a "
            "linear system, not for this nonlinear one. Explicit thresholds are finite-time figures: with an energy "
            "bound of 1000 E_scale they rose by < 1 % (symplectic Euler) and 1-10 % (RK4) in a one-off check."]
    if unconv:
        out.append(f"PCG hit its iteration limit in {sum(u[3] for u in unconv)} steps over {len(unconv)} trial runs "
                   "(listed in the JSON).")
    out.append("")
    return "\n".join(out)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = np.array([r["k"] for r in res["rows"]])
    fig, ax = plt.subplots(figsize=(10, 5.5))
    w = np.array([r["mode"]["omega_max"] for r in res["rows"]])
    ax.loglog(ks, 2 / w, "k-", lw=1.5, label="2/ω_max (symplectic Euler, Verlet)")
    ax.loglog(ks, 2 * np.sqrt(2) / w, "k:", lw=1.2, label="2√2/ω_max (RK4)")
    ax.loglog(ks, [r["mode"]["bound_fe_damped"] for r in res["rows"]], color="0.5", ls="-.", lw=1,
              label="2ζ/ω_max (forward Euler, damped)")
    s = res["settings"]
    ax.axhline(s["cap"], color="0.6", ls="--", lw=1)
    ax.axhline(s["floor"], color="0.6", ls="--", lw=1)
    ax.text(ks[0], s["cap"] * 1.08, "cap", fontsize=8, color="0.4")
    ax.text(ks[0], s["floor"] * 1.08, "floor", fontsize=8, color="0.4")
    n = len(res["integrators"])
    for j, name in enumerate(res["integrators"]):
        mk, col = STYLE.get(name, ("o", None))
        off = 1 + 0.04 * (j - (n - 1) / 2)   # small horizontal offset so coincident points stay visible
        xs = ks * off
        ys = np.array([{"bracketed": r["dt_max"], "at_cap": s["cap"], "below_floor": s["floor"]}[r["status"]]
                       for r in (row["results"][name] for row in res["rows"])], dtype=float)
        censored = np.array([row["results"][name]["status"] != "bracketed" for row in res["rows"]])
        ax.loglog(xs[~censored], ys[~censored], color=col, ls="-", lw=1.2, label=name, marker=mk, ms=6)
        if censored.any():
            ax.loglog(xs, ys, color=col, ls=":", lw=0.8)
            ax.loglog(xs[censored], ys[censored], marker=mk, color=col, ls="none", ms=9, mfc="none")
    ax.plot([], [], "o", color="0.3", mfc="none", ms=9, label="hollow: stable at the cap / unstable at the floor")
    ax.set_xlabel("spring stiffness k (N/m)")
    ax.set_ylabel("largest stable time step dt_max (s)")
    ax.set_title(f"Stability limit vs stiffness ({s['resolution']}² cloth, {s['duration']:g} s runs)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ks", type=float, nargs="+", default=[1e2, 1e3, 1e4, 1e5, 1e6], help="spring stiffnesses, N/m")
    p.add_argument("--integrators", nargs="+", default=list(ic.INTEGRATORS), choices=list(ic.INTEGRATORS))
    p.add_argument("--resolution", type=int, default=12, help="grid vertices per side")
    p.add_argument("--duration", type=float, default=0.5, help="simulated time of each trial, s")
    p.add_argument("--min-steps", type=int, default=20, help="each trial runs at least this many steps")
    p.add_argument("--cap", type=float, default=1 / 15, help="largest dt tried, s")
    p.add_argument("--floor", type=float, default=1e-5, help="smallest dt tried, s")
    p.add_argument("--rtol", type=float, default=0.01, help="bisection stops when hi/lo <= 1 + rtol")
    p.add_argument("--time-steps", type=int, default=100, help="steps per timing repeat at dt_max")
    p.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial velocity perturbation")
    p.add_argument("--out", default=default_out('stability'), help="output folder (default out/bench/stability; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="8² cloth, two k, short runs, coarse bisection (CI smoke)")
    a = p.parse_args(argv)
    if a.quick:
        a.ks, a.resolution, a.duration, a.min_steps = [1e2, 1e4], 8, 0.1, 10
        a.floor, a.rtol, a.time_steps, a.repeats = 1e-4, 0.1, 10, 3
    wall0 = time.perf_counter()
    rows = []
    bar = progress(total=len(a.ks) * len(a.integrators), desc="stability")
    for k in a.ks:
        base = scene(a.resolution, k)
        mode = top_mode(ic.Simulator(base, integrator="backward_euler").model, seed=a.seed)
        row = {"k": k, "mode": mode, "results": {}}
        print(f"k={k:8.0e} N/m  w_max={mode['omega_max']:.5g} rad/s  2/w_max={mode['bound_2_over_w']:.4e} s  "
              f"zeta_top={mode['zeta']:.3g}", flush=True)
        for name in a.integrators:
            bar.set_postfix_str(f"k={k:.0e} {name}")
            test = lambda dt, name=name, base=base: trial(base, name, dt, a.duration, a.min_steps, a.seed)  # noqa: E731
            r = search(test, guess_for(name, mode, a.cap), a.floor, a.cap, a.rtol)
            r["s_per_step"] = None
            if r["dt_max"] is not None:
                steps = max(5, min(a.time_steps, int(round(a.duration / r["dt_max"]))))
                r["s_per_step"] = step_cost(base, name, r["dt_max"], steps, a.repeats, a.seed)
                r["timing_steps"] = steps
            r["ratio_to_2_over_w"] = r["dt_max"] / mode["bound_2_over_w"] if r["dt_max"] else None
            r["trial_wall_s"] = sum(t["wall_s"] for t in r["trials"])
            row["results"][name] = r
            bar.update(1)
            print(f"    {name:17s} {_cell(r, mode['bound_2_over_w']):>24s}  [{len(r['trials'])} trials, "
                  f"{r['trial_wall_s']:.1f} s]", flush=True)
        rows.append(row)
    bar.close()
    res = {"benchmark": "stability", "quick": a.quick, "seed": a.seed, "machine": machine(),
           "integrators": a.integrators, "ks": a.ks,
           "settings": {"resolution": a.resolution, "size_m": 1.0, "mass_kg": 0.1, "damping_kd": KD,
                        "duration": a.duration, "min_steps": a.min_steps, "frame_rate": FRAME_RATE,
                        "divergence_factor": 1.0, "noise_m_per_s": NOISE, "cap": a.cap, "floor": a.floor,
                        "rtol": a.rtol, "time_steps": a.time_steps, "repeats": a.repeats},
           "criterion": ("stable iff Simulator.run(duration=max(T, min_steps*dt), frame_rate=240) keeps every "
                         "state finite and E_total(t) - E_total(0) <= E_bound at every kept frame, E_bound = "
                         "diagnostics.energy_scale of a run of T from the same initial state (trial bound_J); "
                         "explicit runs use divergence_factor=1 (stop early), implicit runs 1000"),
           "rows": rows}
    res["wall_time_s"] = time.perf_counter() - wall0
    md = markdown(res)
    out = Path(a.out)
    write_outputs(out, "stability", res, md)
    plot(res, out / "stability.png")
    print(md)
    print(f"wall time {res['wall_time_s']:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
