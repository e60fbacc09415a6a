"""Numerical damping of each integrator against the physical damping: energy and amplitude decay of a swinging cloth.

Scene: a 12 x 12 cloth, 1 m x 1 m, 0.1 kg, hanging vertically (xz plane) with
its whole top edge pinned, gravity (-z); structural and shear springs of
k = 1e3 N/m, bend 10 N/m. It starts at its static equilibrium (found by
relaxing the cloth with large backward-Euler steps until it is at rest) with
the velocity of a rigid rotation about the pinned edge, ``v_y = W0 (z_top - z)``,
``W0 = --omega0`` = 1.5 rad/s (bottom edge at 1.5 m/s, a swing of about 25
degrees), and swings freely for ``--duration`` T = 3 s (almost two periods).

Two settings of the physical damping:

* ``off``: no spring damping, no air drag. The exact motion conserves energy;
  every loss is numerical.
* ``on``: spring damping kd = 0.1 N*s/m (structural, shear), 0.01 (bend) and
  air drag 0.01 N*s/m^3 (``effects.drag``), which is what damps the swing
  itself.

What is measured. The swing energy ``E_s(t) = E_total(t) - E_eq`` (kinetic +
spring + gravity energy, minus that of the equilibrium, so ``E_s(0)`` is the
kick's kinetic energy and ``E_s -> 0`` at rest), read at kept frames (60 Hz,
or every step for dt > 1/60 s). Per run:

* ``energy_remaining`` = E_s(T) / E_s(0);
* the mean energy decay rate ``lambda = -ln(E_s(T) / E_s(0)) / T`` (1/s);
* the **numerical** decay rate ``lambda - lambda_ref``, where the reference is
  RK4 at ``--ref-dt`` (1e-4 s, a ninth of its stability limit; its own error is
  estimated from a second RK4 run at 2 x ref-dt as |difference| / 15, RK4 being
  4th order) and ``lambda_ref`` is the physical decay (0 with damping off);
* the swing amplitude: the y displacement of the bottom edge (mean over its
  vertices) at its successive extremes (parabolic interpolation between
  frames); ``amplitude_ratio`` = last extreme / first extreme and the amplitude
  decay rate ln(first / last) / (t_last - t_first) (1/s; half the energy rate
  for a linear damped oscillator).

Every integrator runs at every step of the ``--dts`` ladder (2.5e-4 .. 1/15 s),
except that the implicit methods skip steps below ``--implicit-min-dt`` (1e-3
s: thousands of linear solves, and their numerical damping there is read off
the trend). Explicit methods above their stability limit (about 6e-4 s here)
diverge and are reported as such; a run that gains energy shows a negative
numerical decay rate. For comparison the plot shows the decay rate of a
linear oscillator at the swing's frequency ``w_s`` (measured from the
reference) under exact backward Euler, ``ln(1 + w_s^2 dt^2) / dt``, and exact
BDF2; the cloth's swing is not a single linear mode and the engine linearises
once per step, so these are guides, not predictions (at a ten times smaller
kick, ``--omega0 0.15``, the measured backward-Euler rate at 1/60 s matched
the guide to 1 % and BDF2's fell 25-fold: at 1.5 rad/s much of the implicit
methods' dissipation comes from linearising the swing's large rotations once
per step). The decay rate's
dependence on dt is fitted as ``lambda_num ~ dt^p`` (least squares on log-log,
over the stable runs whose numerical rate exceeds 10 x the reference's error).

Usage::

    python benchmarks/damping.py                           # ~1.5 min
    python benchmarks/damping.py --dts 1e-3 1/60 --out /tmp/res
    python benchmarks/damping.py --quick                   # CI smoke test (< 1 min)
    implicit-cloth bench damping --quick --out /tmp/res

Writes ``OUT/damping.json`` (every run's figures and energy curve, machine,
versions; no random input, ``seed`` is null), ``OUT/damping.md`` (the tables)
and ``OUT/damping.png`` (energy vs time, numerical decay rate vs dt). Wall
times in the JSON are single runs, for information only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np
from _common import FIXED_STEPS, STYLE, default_out, ic, machine, progress, save_png, write_outputs

from implicit_cloth import diagnostics

EXPLICIT = ("forward_euler", "symplectic_euler", "verlet", "rk4")
FRAME_RATE = 60.0
K = 1e3
SETTINGS = {"off": {"kd": 0.0, "drag": 0.0}, "on": {"kd": 0.1, "drag": 0.01}}


def scene(n: int, damping: str) -> dict:
    """The swinging cloth with physical damping ``"off"`` or ``"on"`` (module docstring)."""
    d = SETTINGS[damping]
    effects: dict = {"gravity": [0.0, 0.0, -9.81]}
    if d["drag"]:
        effects["drag"] = d["drag"]
    return {"cloth": {"size": [1.0, 1.0], "resolution": [n, n], "mass": 0.1, "plane": "xz",
                      "pins": list(range((n - 1) * n, n * n)),   # the whole top row
                      "springs": {"structural": {"stiffness": K, "damping": d["kd"]},
                                  "shear": {"stiffness": K, "damping": d["kd"]},
                                  "bend": {"stiffness": K / 100, "damping": d["kd"] / 10}}},
            "effects": effects}


def equilibrium(n: int) -> tuple[np.ndarray, float, float]:
    """Static equilibrium by large backward-Euler steps: positions, E_eq (J) and the largest free force left (N)."""
    sim = ic.Simulator(scene(n, "off"), integrator="backward_euler", dt=0.1, solver={"tolerance": 1e-10})
    for _ in range(40):
        sim.step(10)
        if np.abs(sim.velocities).max() < 1e-12:
            break
    x = sim.positions.copy()
    m = sim.model
    f = m.forces(x, np.zeros_like(x), 0.0)
    f[m.pinned] = 0.0
    return x, diagnostics.measure(m, x, np.zeros_like(x))["total"], float(np.abs(f).max())


def kick(x: np.ndarray, omega0: float) -> np.ndarray:
    v = np.zeros_like(x)
    v[:, 1] = omega0 * (x[:, 2].max() - x[:, 2])
    return v


def extremes(t: np.ndarray, y: np.ndarray) -> list[tuple[float, float]]:
    """Local extremes of |y| as (time, |y|), refined by a parabola through the three frames around each."""
    out = []
    a = np.abs(y)
    for i in range(1, len(y) - 1):
        if a[i] >= a[i - 1] and a[i] > a[i + 1] and np.sign(y[i - 1]) == np.sign(y[i]) == np.sign(y[i + 1]):
            # parabola through (t[i-1], y[i-1]), (t[i], y[i]), (t[i+1], y[i+1])
            c = np.polyfit(t[i - 1:i + 2] - t[i], y[i - 1:i + 2], 2)
            if c[0] != 0:
                tv = -c[1] / (2 * c[0])
                if abs(tv) <= max(t[i + 1] - t[i], t[i] - t[i - 1]):
                    out.append((float(t[i] + tv), float(abs(np.polyval(c, tv)))))
                    continue
            out.append((float(t[i]), float(a[i])))
    return out


def run_one(n: int, damping: str, integrator: str, dt: float, x0: np.ndarray, v0: np.ndarray, e_eq: float,
            duration: float) -> dict:
    sim = ic.Simulator(scene(n, damping), integrator=integrator, dt=dt, adaptive=FIXED_STEPS)
    sim.positions = x0
    sim.velocities = v0
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ic.SolverWarning)
        try:
            traj = sim.run(duration=duration, frame_rate=FRAME_RATE)
            status, reason = "ok", ""
        except ic.DivergenceError as exc:
            traj, status, reason = exc.trajectory, "diverged", exc.reason
    wall = time.perf_counter() - t0
    rep = traj.report
    r = {"integrator": integrator, "dt": dt, "damping": damping, "status": status, "reason": reason,
         "steps": rep["steps"], "wall_s": wall,
         "unconverged_steps": (rep["solver"] or {}).get("unconverged_steps", 0)}
    if status != "ok":
        return r
    t = np.asarray(traj.times) - traj.times[0]
    es = np.asarray(rep["frames"]["total"]) - e_eq
    T = float(t[-1])
    frac = es / es[0]
    r.update({"T": T, "E_s0": float(es[0]), "energy_remaining": float(frac[-1]),
              "energy_rate": float(-math.log(frac[-1]) / T) if frac[-1] > 0 else None,
              "max_strain": float(np.max(rep["frames"]["max_strain"]))})
    yb = traj.positions[:, :n, 1].mean(axis=1)   # bottom row: vertices 0 .. n-1
    ex = extremes(t, yb)
    r["extremes"] = ex
    if len(ex) >= 2:
        (ta, aa), (tb, ab) = ex[0], ex[-1]
        r["amplitude_ratio"] = ab / aa
        r["amplitude_rate"] = math.log(aa / ab) / (tb - ta)
    else:
        r["amplitude_ratio"] = r["amplitude_rate"] = None
    # the energy curve, thinned to <= 30 points per second, for the JSON and the plot
    stride = max(1, int(round(len(t) / (30 * T)))) if T > 0 else 1
    r["curve_t"] = t[::stride].tolist() + ([float(t[-1])] if (len(t) - 1) % stride else [])
    r["curve_E"] = frac[::stride].tolist() + ([float(frac[-1])] if (len(t) - 1) % stride else [])
    return r


def swing_omega(ex: list[tuple[float, float]]) -> float | None:
    """Angular frequency from successive extremes (half a period apart), rad/s."""
    if len(ex) < 2:
        return None
    half = np.diff([e[0] for e in ex]).mean()
    return float(math.pi / half)


def theory_rate(integrator: str, w: float, h: float) -> float:
    """Energy decay rate (1/s) of the exact method on the linear oscillator x'' = -w^2 x."""
    z = 1j * w * h
    if integrator == "backward_euler":
        return math.log(1 + (w * h) ** 2) / h
    if integrator == "bdf2":   # (3/2 - z) r^2 - 2 r + 1/2 = 0, principal root
        roots = np.roots([1.5 - z, -2.0, 0.5])
        r = roots[np.argmin(np.abs(roots - np.exp(z)))]
        return -2 * math.log(abs(r)) / h
    raise ValueError(integrator)


def fit_power(rows: list[dict], floor: float) -> float | None:
    pts = [(r["dt"], r["numerical_rate"]) for r in rows
           if r["status"] == "ok" and r.get("numerical_rate") is not None and r["numerical_rate"] > floor]
    if len(pts) < 2:
        return None
    h, lam = np.array(pts).T
    return float(np.polyfit(np.log(h), np.log(lam), 1)[0])


# --------------------------------------------------------------------------- output
def _dt_label(dt: float) -> str:
    """``0.001``, ``0.00025`` for round decimals, ``1/60`` for reciprocals of integers."""
    if abs(dt * 1e6 - round(dt * 1e6)) < 1e-6 * dt * 1e6:
        return f"{dt:g}"
    inv = 1 / dt
    if abs(inv - round(inv)) < 1e-9 * inv:
        return f"1/{round(inv)}"
    return f"{dt:.3g}"


def _pct(x: float | None) -> str:
    return f"{100 * x:.1f} %" if x is not None else "n/a"


def markdown(res: dict) -> str:
    dts, ints = res["dts"], res["integrators"]
    ws = res["omega_swing"]
    freq = f" Swing frequency ω_s = {ws:.3f} rad/s (period {2 * math.pi / ws:.3f} s)." if ws else ""
    out = [f"Swinging cloth ({res['settings']['resolution']}², 1 m, 0.1 kg, top edge pinned, k = {K:g} N/m), "
           f"kicked at {res['settings']['omega0']:g} rad/s about the top edge from equilibrium, "
           f"{res['settings']['duration']:g} s. E_s = E_total − E_eq (swing energy). Reference: RK4 at "
           f"dt = {res['settings']['ref_dt']:g} s." + freq, ""]
    for d in ("off", "on"):
        ref = res["reference"][d]
        head = "| integrator | " + " | ".join(f"dt = {_dt_label(h)}" for h in dts)
        out += [f"### Physical damping {d} ({'kd = 0.1 N·s/m, drag 0.01 N·s/m³' if d == 'on' else 'none'}): "
                f"reference E_s(T)/E_s(0) = {100 * ref['energy_remaining']:.2f} %, physical decay rate "
                f"λ_ref = {ref['energy_rate']:.4f} 1/s (± {ref['rate_error']:.1e}), amplitude last/first "
                f"{_pct(ref.get('amplitude_ratio'))}", "",
                "Energy remaining E_s(T)/E_s(0) in %, and in parentheses the swing amplitude's last/first extreme "
                "in % (div: diverged; -: not run).", "",
                head + " |", "|---" * (1 + len(dts)) + "|"]
        by = {(r["integrator"], r["dt"]): r for r in res["runs"] if r["damping"] == d}
        for i in ints:
            cells = []
            for h in dts:
                r = by.get((i, h))
                if r is None:
                    cells.append("-")
                elif r["status"] != "ok":
                    cells.append("div")
                else:
                    amp = f" ({100 * r['amplitude_ratio']:.1f})" if r.get("amplitude_ratio") is not None else ""
                    cells.append(f"{100 * r['energy_remaining']:.2f}{amp}")
            out.append(f"| {i} | " + " | ".join(cells) + " |")
        out += ["", "Numerical energy decay rate λ − λ_ref (1/s; negative: energy gained), and the fitted "
                "exponent p of λ_num ∝ dt^p.", "", head + " | p |", "|---" * (2 + len(dts)) + "|"]
        for i in ints:
            cells = []
            for h in dts:
                r = by.get((i, h))
                if r is None:
                    cells.append("-")
                elif r["status"] != "ok" or r.get("numerical_rate") is None:
                    cells.append("div" if r["status"] != "ok" else "n/a")
                else:
                    cells.append(f"{r['numerical_rate']:.3g}")
            p = res["exponents"].get(f"{i}@{d}")
            out.append(f"| {i} | " + " | ".join(cells) + f" | {p:.2f} |" if p is not None else
                       f"| {i} | " + " | ".join(cells) + " | - |")
        out.append("")
    if ws:
        out.append("Linear-oscillator guide at ω_s (exact methods, energy decay rate, 1/s): " + "; ".join(
            f"dt = {_dt_label(h)}: BE {theory_rate('backward_euler', ws, h):.3g}, BDF2 {theory_rate('bdf2', ws, h):.2g}"
            for h in dts if h >= 1e-3) + ".")
        out.append("")
    return "\n".join(out)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5.2))
    # left: energy curves, damping on; the reference, each implicit method at 1/60 s (or the nearest ladder
    # step) and 1/15 s, each explicit method at its largest stable ladder step
    ref = res["reference"]["on"]
    a1.plot(ref["curve_t"], ref["curve_E"], "k-", lw=2.5, alpha=0.6,
            label=f"reference rk4 dt={res['settings']['ref_dt']:g} s")
    runs = [r for r in res["runs"] if r["damping"] == "on" and r["status"] == "ok"]
    for name in res["integrators"]:
        mine = sorted((r for r in runs if r["integrator"] == name), key=lambda r: r["dt"])
        if not mine:
            continue
        mk, col = STYLE.get(name, ("o", None))
        if name in EXPLICIT:
            pick = [mine[-1]]
        else:
            pick = [min(mine, key=lambda r: abs(math.log(r["dt"] * 60)))]
            if mine[-1] is not pick[0]:
                pick.append(mine[-1])
        for r, ls in zip(pick, ("-", "--")):
            a1.plot(r["curve_t"], r["curve_E"], ls=ls, color=col, lw=1.3, label=f"{name} dt={_dt_label(r['dt'])} s")
    a1.set_xlabel("time t (s)")
    a1.set_ylabel("swing energy E_s(t) / E_s(0) (1)")
    a1.set_title("Energy decay, physical damping on")
    a1.grid(True, alpha=0.3)
    a1.legend(fontsize=7)
    # right: numerical decay rate vs dt
    err = max(res["reference"][d]["rate_error"] for d in ("off", "on"))
    floor = 10 * err if err > 0 else 1e-12
    for name in res["integrators"]:
        mk, col = STYLE.get(name, ("o", None))
        for d, ls in (("off", "-"), ("on", "--")):
            rs = sorted((r for r in res["runs"] if r["integrator"] == name and r["damping"] == d
                         and r["status"] == "ok" and r.get("numerical_rate") is not None), key=lambda r: r["dt"])
            if not rs:
                continue
            h = np.array([r["dt"] for r in rs])
            lam = np.array([r["numerical_rate"] for r in rs])
            shown = np.maximum(np.abs(lam), floor)
            a2.loglog(h, shown, ls=ls, color=col, lw=1.2, marker=mk, ms=5,
                      markevery=list(np.flatnonzero(lam > 0)), label=f"{name}, damping {d}")
            neg = lam <= 0
            if neg.any():
                a2.loglog(h[neg], shown[neg], ls="none", marker=mk, color=col, ms=7, mfc="none")
    ws = res["omega_swing"]
    if ws:
        hh = np.geomspace(min(res["dts"]), max(res["dts"]), 100)
        a2.loglog(hh, [theory_rate("backward_euler", ws, h) for h in hh], "k:", lw=1,
                  label=f"linear BE at ω_s = {ws:.2f} rad/s")
        tb = np.array([theory_rate("bdf2", ws, h) for h in hh])
        a2.loglog(hh[tb > floor], tb[tb > floor], "k-.", lw=1, label="linear BDF2 at ω_s")
    a2.axhline(floor, color="0.6", ls="--", lw=0.8)
    a2.text(min(res["dts"]), floor * 1.15, "10 x reference error (values below are noise)", fontsize=7, color="0.4")
    a2.set_xlabel("time step dt (s)")
    a2.set_ylabel("numerical energy decay rate λ − λ_ref (1/s)")
    a2.set_title("Numerical damping vs dt (hollow: |negative|, energy gained)")
    a2.grid(True, which="both", alpha=0.3)
    a2.legend(fontsize=6.5, ncol=2, loc="upper left")
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


# --------------------------------------------------------------------------- main
def _dt(s: str) -> float:
    return float(Fraction(s)) if "/" in s else float(s)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dts", type=_dt, nargs="+",
                   default=[2.5e-4, 5e-4, 1e-3, 2e-3, 1 / 240, 1 / 120, 1 / 60, 1 / 30, 1 / 15],
                   help="time steps, s (fractions like 1/60 accepted)")
    p.add_argument("--integrators", nargs="+", default=list(ic.INTEGRATORS), choices=list(ic.INTEGRATORS))
    p.add_argument("--resolution", type=int, default=12)
    p.add_argument("--duration", type=float, default=3.0, help="simulated time of each run, s")
    p.add_argument("--omega0", type=float, default=1.5, help="initial rotation rate about the top edge, rad/s")
    p.add_argument("--ref-dt", type=_dt, default=1e-4, help="time step of the RK4 reference, s")
    p.add_argument("--implicit-min-dt", type=_dt, default=1e-3, help="implicit methods skip smaller steps")
    p.add_argument("--out", default=default_out('damping'), help="output folder (default out/bench/damping; --out benchmarks/results replaces the committed result)")
    p.add_argument("--quick", action="store_true", help="6² cloth, 0.8 s, three steps (CI smoke)")
    a = p.parse_args(argv)
    if a.quick:
        a.resolution, a.duration, a.dts, a.ref_dt = 6, 0.8, [5e-4, 1 / 60, 1 / 15], 2.5e-4
    a.dts = sorted(set(a.dts))
    wall0 = time.perf_counter()
    n = a.resolution
    x0, e_eq, residual = equilibrium(n)
    v0 = kick(x0, a.omega0)
    print(f"equilibrium: E_eq = {e_eq:.6g} J, largest free force {residual:.2e} N", flush=True)
    jobs = [(d, i, h) for d in ("off", "on") for i in a.integrators for h in a.dts
            if not (i not in EXPLICIT and h < a.implicit_min_dt)]
    bar = progress(total=4 + len(jobs), desc="damping")
    reference = {}
    for d in ("off", "on"):
        bar.set_postfix_str(f"reference, damping {d}")
        ref = run_one(n, d, "rk4", a.ref_dt, x0, v0, e_eq, a.duration)
        bar.update(1)
        chk = run_one(n, d, "rk4", 2 * a.ref_dt, x0, v0, e_eq, a.duration)
        bar.update(1)
        if ref["status"] != "ok" or chk["status"] != "ok":
            raise SystemExit(f"damping: the RK4 reference diverged at dt = {a.ref_dt:g} s; use a smaller --ref-dt")
        ref["rate_error"] = abs(ref["energy_rate"] - chk["energy_rate"]) / 15
        ref["check_dt"], ref["check_energy_rate"] = chk["dt"], chk["energy_rate"]
        reference[d] = ref
        print(f"reference (rk4 dt={a.ref_dt:g} s), damping {d}: E_s(T)/E_s(0) = {ref['energy_remaining']:.5f}, "
              f"rate {ref['energy_rate']:.5f} 1/s (+- {ref['rate_error']:.1e}), amplitude ratio "
              f"{ref['amplitude_ratio']}", flush=True)
    omega_s = swing_omega(reference["off"]["extremes"])
    runs = []
    for d, i, h in jobs:
        bar.set_postfix_str(f"{d} {i} dt={_dt_label(h)}")
        r = run_one(n, d, i, h, x0, v0, e_eq, a.duration)
        if r["status"] == "ok" and r["energy_rate"] is not None:
            r["numerical_rate"] = r["energy_rate"] - reference[d]["energy_rate"]
        runs.append(r)
        bar.update(1)
        if r["status"] == "ok":
            print(f"damping {d:3s} {i:17s} dt={_dt_label(h):>7s}: E_s(T)/E_s(0) = {r['energy_remaining']:.4f}, "
                  f"numerical rate {r.get('numerical_rate', float('nan')):+.4g} 1/s  [{r['wall_s']:.1f} s]", flush=True)
        else:
            print(f"damping {d:3s} {i:17s} dt={_dt_label(h):>7s}: diverged  [{r['wall_s']:.1f} s]", flush=True)
    bar.close()
    floor = 10 * max(reference[d]["rate_error"] for d in ("off", "on"))
    exponents = {}
    for i in a.integrators:
        for d in ("off", "on"):
            e = fit_power([r for r in runs if r["integrator"] == i and r["damping"] == d], floor)
            if e is not None:
                exponents[f"{i}@{d}"] = e
    res = {"benchmark": "damping", "quick": a.quick, "seed": None, "machine": machine(),
           "integrators": a.integrators, "dts": a.dts,
           "settings": {"resolution": n, "size_m": 1.0, "mass_kg": 0.1, "k": K, "duration": a.duration,
                        "omega0": a.omega0, "ref_dt": a.ref_dt, "implicit_min_dt": a.implicit_min_dt,
                        "frame_rate": FRAME_RATE, "physical_damping": SETTINGS},
           "measured": ("E_s(t) = E_total(t) - E_eq at kept frames; energy_remaining = E_s(T)/E_s(0); "
                        "energy_rate = -ln(energy_remaining)/T; numerical_rate = energy_rate - reference "
                        "energy_rate (RK4 at ref_dt, same damping); amplitude_ratio = last/first extreme of "
                        "the bottom edge's mean y displacement"),
           "equilibrium": {"E_eq": e_eq, "largest_free_force_N": residual},
           "omega_swing": omega_s, "reference": reference, "runs": runs, "exponents": exponents}
    res["wall_time_s"] = time.perf_counter() - wall0
    md = markdown(res)
    out = Path(a.out)
    write_outputs(out, "damping", res, md)
    plot(res, out / "damping.png")
    print(md)
    print(f"wall time {res['wall_time_s']:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
