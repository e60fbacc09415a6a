"""Is a drape still moving at 3 s because of the step, or because the scene moves? A converged reference.

The contact table (``benchmarks/contact_energy.py``) asks every static row to be
at rest after 3 s. Backward Euler damps what it steps over, more at larger
steps, so a large step can bring to rest a cloth whose exact motion goes on (a
skirt hanging off an obstacle swings like a pendulum; the scene has no air
drag and its spring damping does not damp a rigid swing), and it can also keep
a cloth creeping that the exact motion brings to rest (contacts sticking and
slipping by turns at a large step). Which one a row is cannot be read off the
large-step run: this script runs the same scene

* with backward Euler at the row's step and at ``dt / K`` for each ``--factors``
  K (adaptive stepping as in the table), and
* with symplectic Euler, an explicit method without numerical damping, at a
  fixed step well inside its stability limit (``--explicit``; by default
  ``EXPLICIT_STEP_32 * 32 / n``: the limit of the springs' fastest mode scales
  with the spacing), the collision stage being the explicit methods' own
  (impulses), not the implicit contact solve's: an independent reference, on
  grids up to ``--explicit-max-n`` (32: a 64² cloth's 60 000 explicit steps
  took more than 70 min of CPU for 3 s),

and records the rms vertex speed at every kept frame (60 Hz), and at the end
the rms speed of what lies on the obstacle (vertices within 2 thicknesses,
the contact table's measure) and the largest energy rise over ``m g (1 m)``
(as in the table: computed here from the states). As the step shrinks the
backward-Euler runs approach the explicit one; the row's motion at 3 s is the
scene's if the reference moves, the large step's if it is at rest.

Usage::

    python benchmarks/studies/rest_reference.py --workers 2            # the README's three rows (about 7 min on 2 cores)
    python benchmarks/studies/rest_reference.py --rows capsule:32:60    # one row: SHAPE:N:1/DT
    python benchmarks/studies/rest_reference.py --quick                 # CI smoke

Writes ``OUT/rest_reference.{json,md,png}`` (``--out``, default out/bench/rest_reference). Never asserts.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, friction_text, friction_used, ic, machine, run_all, save_png, write_outputs
from contact_energy import (
    ON_DISTANCE,
    REST_SPEED,
    SHAPES,
    G,
    Judge,
    friction_settings,
    mesh_files,
    obstacle_distance,
    rms_speed,
    static_scene,
)

#: Symplectic Euler's step for a 32² cloth of the table's scene, s (stable: its fastest spring mode's
#: limit is about 2e-4 s there); finer grids scale it by 32 / n.
EXPLICIT_STEP_32 = 1e-4
#: The rows run by default: the skirts and the cone that the contact table's runs leave moving at 3 s.
ROWS = ("capsule:32:60", "capsule:64:60", "cone:64:30")
FACTORS = (4, 16)


def parse_row(text: str) -> tuple[str, int, float]:
    """``SHAPE:N:HZ`` -> (shape, n, dt)."""
    try:
        shape, n, hz = text.split(":")
        if shape not in SHAPES:
            raise ValueError(f"unknown shape {shape!r} (one of {', '.join(SHAPES)})")
        return shape, int(n), 1.0 / float(hz)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is not SHAPE:N:1/DT ({exc})") from None


def row_text(text: str) -> str:
    """``--rows``' type: the text, once :func:`parse_row` has read it."""
    parse_row(text)
    return text


def run(spec: dict) -> dict:
    """One run of a row's scene with the given integrator and step: rms speed at every kept frame."""
    folder = Path(spec["mesh_dir"])
    scene = static_scene(spec["shape"], spec["n"], spec["dt"], spec["duration"])
    scene["simulation"]["integrator"] = spec["integrator"]
    scene["collision"].update(spec["collision"])
    sim = ic.Simulator(ic.Scene.from_dict(scene, base_dir=folder))
    judge = Judge(sim)
    e0, _ = judge(sim.positions, sim.velocities)
    seen: dict = {"t": [], "vrms": [], "rise": 0.0}

    def on_frame(state) -> None:
        e, _ = judge(state.x, state.v)
        seen["rise"] = max(seen["rise"], e - e0)
        seen["t"].append(float(state.t))
        seen["vrms"].append(rms_speed(state.v))

    t0 = time.process_time()
    report = sim.run(on_frame=on_frame).report
    cpu = time.process_time() - t0
    x, v = sim.positions, sim.velocities
    on = obstacle_distance(sim, x, sim.time) < ON_DISTANCE
    frames = max(len(seen["t"]) - 1, 1)
    ad = report.get("adaptive") or {}
    return {**{k: spec[k] for k in ("row", "shape", "n", "dt", "integrator", "factor")},
            "t": seen["t"], "vrms": seen["vrms"], "vrms_end": rms_speed(v),
            "on_vrms_end": rms_speed(v[on]) if np.any(on) else None,
            "rise_frac": seen["rise"] / (float(sim.model.total_mass) * G),
            "substeps_per_frame": ad.get("substeps", frames) / frames, "cpu_s": cpu,
            "status": report.get("status")}


def specs(args: argparse.Namespace, mesh_dir: Path) -> list[dict]:
    collision = friction_settings(args)
    out = []
    for text in args.rows:
        shape, n, dt = parse_row(text)
        base = {"row": text, "shape": shape, "n": n, "duration": args.duration, "mesh_dir": str(mesh_dir),
                "collision": collision}
        for k in (1, *args.factors):
            out.append({**base, "dt": dt / k, "integrator": "backward_euler", "factor": k})
        if args.explicit >= 0 and n <= args.explicit_max_n:
            h = args.explicit or EXPLICIT_STEP_32 * 32 / n
            out.append({**base, "dt": h, "integrator": "symplectic_euler", "factor": None})
    return out


def _label(r: dict) -> str:
    if r["integrator"] == "symplectic_euler":
        return f"symplectic Euler, dt {r['dt']:.2g} s"
    return f"backward Euler, dt 1/{1 / r['dt']:.0f}"


def verdict(rows: list[dict]) -> str:
    """What a row's motion at the end is, from its runs."""
    large = next(r for r in rows if r["factor"] == 1)
    ref = next((r for r in rows if r["integrator"] == "symplectic_euler"), None)
    if ref is None:
        ref = min(rows, key=lambda r: r["dt"])
    moving, ref_moving = large["vrms_end"] >= REST_SPEED, ref["vrms_end"] >= REST_SPEED
    if ref_moving and not moving:
        return "the scene moves on; the large step's damping brings it to rest"
    if ref_moving:
        return "the scene moves on (the large step moves less)" if large["vrms_end"] <= ref["vrms_end"] \
            else "moving, faster than the reference"
    return "the large step keeps it moving; the reference rests" if moving else "at rest, as the reference"


def markdown(res: dict) -> str:
    lines = [f"Rows of the contact table run at finer steps and with an explicit reference, by "
             f"`benchmarks/studies/rest_reference.py` ({'quick' if res['quick'] else 'full'} run, {res['wall_s']:.0f} s; "
             f"{res['duration']:g} s of the contact table's static scene"
             + ")." + friction_text(res) + " rms: the rms vertex speed; on it: that of the vertices within 2 thicknesses of the obstacle;"
             " rise: largest E(t) - E(0) over m g (1 m), from the states.", "",
             "| row | run | rms at 1 s | rms at 2 s | rms at the end | on it at the end | rise | substeps/frame "
             "| CPU s | report |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["runs"]:
        t = np.asarray(r["t"])

        def at(s: float, r: dict = r, t: np.ndarray = t) -> str:
            return f"{100 * r['vrms'][int(np.argmin(abs(t - s)))]:.1f} cm/s" if len(t) else "-"

        on = "-" if r["on_vrms_end"] is None else f"{1e3 * r['on_vrms_end']:.2f} mm/s"
        lines.append(f"| {r['row']} | {_label(r)} | {at(1.0)} | {at(2.0)} | {100 * r['vrms_end']:.2f} cm/s | {on} | "
                     f"{100 * r['rise_frac']:.2f} % | {r['substeps_per_frame']:.2f} | {r['cpu_s']:.0f} | "
                     f"{r['status']} |")
    lines += ["", "At the end (at rest: rms below 1 cm/s):", ""]
    for row in dict.fromkeys(r["row"] for r in res["runs"]):
        lines.append(f"* {row}: {verdict([r for r in res['runs'] if r['row'] == row])}.")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["row"] for r in res["runs"]))
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        for r in (r for r in res["runs"] if r["row"] == name):
            ax.semilogy(r["t"], np.maximum(r["vrms"], 1e-5), label=_label(r),
                        lw=1.6 if r["factor"] == 1 else 1.0, ls="--" if r["factor"] is None else "-")
        ax.axhline(REST_SPEED, color="k", lw=0.6, ls=":")
        ax.set_title(name.replace(":", " ", 1).replace(":", "², 1/"), fontsize=9)
        ax.set_xlabel("t, s")
        ax.set_ylabel("rms vertex speed, m/s")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CI smoke: one small, short row")
    p.add_argument("--rows", nargs="+", type=row_text, default=list(ROWS), metavar="SHAPE:N:HZ")
    p.add_argument("--factors", nargs="*", type=int, default=list(FACTORS),
                   help="backward Euler also at dt / K for each K")
    p.add_argument("--explicit", type=float, default=0.0, metavar="DT",
                   help="symplectic Euler's step, s (0: EXPLICIT_STEP_32 * 32 / n; negative: no explicit run)")
    p.add_argument("--explicit-max-n", type=int, default=32, metavar="N",
                   help="the explicit reference only on grids up to N x N")
    p.add_argument("--duration", type=float, default=3.0)
    p.add_argument("--friction-speed", type=float, default=None, metavar="EPS",
                   help="collision.friction_speed, m/s (0: Coulomb's states; default: the library's)")
    p.add_argument("--friction-newton", type=int, default=None, metavar="K")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(default_out('rest_reference')), help="output folder (default out/bench/rest_reference)")
    args = p.parse_args(argv)
    if args.quick:
        args.rows, args.factors, args.duration, args.explicit = ["capsule:8:30"], [2], 0.3, 4e-4
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        todo = sorted(specs(args, mesh_files(Path(tmp))), key=lambda s: s["n"] ** 3 / s["dt"], reverse=True)
        runs = run_all(run, todo, args.workers, "reference")
    order = {row: i for i, row in enumerate(args.rows)}
    runs.sort(key=lambda r: (order[r["row"]], r["integrator"] != "backward_euler", r["factor"] or 0))
    res = {"benchmark": "rest_reference", "quick": args.quick, "machine": machine(), "duration": args.duration,
           **dict(zip(("friction_speed", "friction_newton"),
                      friction_used(args.friction_speed, args.friction_newton), strict=True)),
           "wall_s": time.perf_counter() - t0, "runs": runs}
    args.out.mkdir(parents=True, exist_ok=True)
    write_outputs(args.out, "rest_reference", res, markdown(res))
    plot(res, args.out / "rest_reference.png")
    print(markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
