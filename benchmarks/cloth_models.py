"""Cloth models side by side: springs against BW98's triangle membrane with dihedral bending, one material (denim).

Both models are the denim preset: the springs (the default model) take its spring constants (structural 2e4,
shear 2e3, bend 200 N/m per spring), the triangles take its measured membrane (6330 N/m warp and weft, 122.5
N/m shear) and bending modulus (1.687e-5 N m; KES-FB data, see docs/scene.md, Materials), both its density 0.4
kg/m^2 and its damping. Three scenes, each at ``--size`` with backward Euler and the library's defaults:

* hanging: ``examples/hanging.toml`` (1 m, falling from flat from its two top corners, dt 0.01 s);
* drape: ``examples/drape_sphere.toml`` (1 m dropped on a sphere of radius 0.3 m, dt 0.01 s, contact rounds);
* crumple: the crumple of ``self_collision.py`` (1 m dropped edge-first onto a floor and a rod, self-collision
  on, dt 1/60 s), with contact as energy in the Newton solve (``method = "barrier"``) for both models: the
  contact rounds on the triangles take ten substeps a step (a 16² crumple: 625 substeps for 60 steps, 78
  solves a step, where the barrier takes 64 and 3.9).

Columns: ms per step (wall, the machine is shared: read the ratio of the two models), adaptive stepping's
accepted substeps per step, CG iterations per step (summed over a step's solves) and linear solves per step, the largest strain the run's report gives (its
frames' ``max_strain``: the structural springs' ``(l - L0) / L0`` for springs, the triangles' largest principal
strain for the membrane, so a sheared membrane counts its bias stretch and the springs do not), the largest
principal strain of the grid's triangles measured the same way for both models (``Membrane.principal_strains``
on every kept frame), and the report's status. The contact scenes add the judges of the other benchmarks:
the drape the least distance of a vertex to the sphere over the kept frames (``contact_energy.
obstacle_distance``; negative: inside), the crumple the most crossings in a kept frame
(``self_collision.count_crossings``) and the least gaps to the floor and the rod (``contact_methods.
crumple_gaps``).

Then the resolution dependence: the hanging cloth at ``--sag-sizes`` (32², 64², 128²) for both models, the
drop of its lowest point below the pins at each kept time up to ``--sag-duration`` (the table: at 1 s and at
the end). Springs of a fixed ``k`` bend a finer grid less (a bend spring's resistance goes with its length),
and their damping per spring damps a finer grid more; the membrane's stiffness and the bending modulus are the
sheet's, so the triangles' drop converges as the grid refines.

Usage::

    python benchmarks/cloth_models.py                 # 32² scenes and the 32²-128² sag (long: an hour on 2 cores)
    python benchmarks/cloth_models.py --scenes hanging drape --no-sag
    python benchmarks/cloth_models.py --quick         # CI smoke: 8² scenes, 0.1-0.4 s; sag at 6², 8², 10², 0.2 s
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
from _common import ROOT, default_out, ic, machine, write_outputs
from contact_energy import obstacle_distance
from contact_methods import crumple_gaps
from self_collision import count_crossings, crumple, edge_list

from implicit_cloth.effects.membrane import Membrane, metric_rest_coordinates

MODELS = ("springs", "triangles")
SCENES = ("hanging", "drape", "crumple")
#: how each scene's row is labelled in the tables
LABEL = {"springs": "springs (structural, shear, bend)", "triangles": "triangles + dihedral"}


def with_model(scene: dict, model: str) -> dict:
    """``scene`` with its cloth made of denim as ``model``: the preset's springs, or its membrane and bending."""
    scene = copy.deepcopy(scene)
    c = scene["cloth"]
    for key in ("springs", "mass", "density", "membrane", "bending"):
        c.pop(key, None)
    c["material"] = "denim"
    if model == "triangles":
        c["membrane"] = {}
        c["bending"] = {"model": "dihedral"}
    return scene


def base_scene(name: str, n: int, duration: float) -> dict:
    """The scene ``name`` at ``n``² for ``duration`` s (before :func:`with_model`)."""
    if name == "crumple":
        scene = crumple(n, 1 / 60, duration)
        scene["collision"]["method"] = "barrier"
        return scene
    example = {"hanging": "hanging.toml", "drape": "drape_sphere.toml"}[name]
    scene = copy.deepcopy(ic.load_scene(ROOT / "examples" / example).source)
    scene["cloth"]["resolution"] = [n, n]
    scene["simulation"]["duration"] = duration
    return scene


def strain_gauge(model) -> Membrane:
    """The grid's triangles as a :class:`Membrane`, for their principal strains (any model): rest shapes from
    the rest positions (the principal strain does not depend on which way u points)."""
    rest, faces = model.rest_positions, np.asarray(model.faces)
    uv = metric_rest_coordinates(rest, faces, rest[faces][:, :, :2])
    return Membrane(model.n, faces, uv, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))


def lowest_drop(sim: ic.Simulator, X: np.ndarray) -> np.ndarray:
    """The lowest vertex's depth below the pins, m, per frame of ``X`` (F, N, 3)."""
    pins = sim.model.pinned
    return X[:, pins, 2].mean(axis=1) - X[..., 2].min(axis=1)


def run_row(name: str, model: str, n: int, duration: float) -> dict:
    scene = with_model(base_scene(name, n, duration), model)
    sim = ic.Simulator(scene)
    t0 = time.perf_counter()
    try:
        traj = sim.run()
    except ic.DivergenceError as exc:
        traj = exc.trajectory
    wall = time.perf_counter() - t0
    rep = traj.report
    X = traj.positions
    steps = max(rep["steps"], 1)
    gauge = strain_gauge(sim.model)
    row = {"scene": name, "model": model, "n": n, "duration": duration, "vertices": sim.model.n,
           "effects": rep["effects"], "ms_step": 1e3 * wall / steps,
           "cg_per_step": rep["solver"]["mean_iterations"], "solves_per_step": rep["solver"]["mean_solves"],
           "substeps_per_step": rep["adaptive"]["substeps_per_step"] if rep.get("adaptive") else 1.0,
           "report_max_strain": float(max(rep["frames"]["max_strain"])),
           "principal_strain": float(max(gauge.principal_strains(x).max() for x in X)),
           "status": rep["status"], "health": [h["message"] for h in rep["health"]],
           "times": [float(t) for t in traj.times]}
    if name == "hanging":
        row["drop"] = [float(d) for d in lowest_drop(sim, X)]
    if name == "drape":
        row["sphere_gap_mm"] = 1e3 * float(min(obstacle_distance(sim, x, t).min() for x, t in zip(X, traj.times)))
    if name == "crumple":
        edges = edge_list(traj.faces)
        row["crossings"] = int(max(count_crossings(x, traj.faces, edges) for x in X))
        row["floor_gap_mm"], row["rod_gap_mm"] = crumple_gaps(X)
    return row


def _at(row: dict, t: float) -> float:
    """The row's drop at the kept frame nearest ``t``."""
    times = np.asarray(row["times"])
    return row["drop"][int(np.argmin(np.abs(times - t)))]


def markdown(res: dict) -> str:
    lines = ["# Cloth models: springs against triangles + dihedral bending, denim", "",
             "Both models are the denim preset (springs: its spring constants; triangles: its measured membrane and "
             "bending modulus). Backward Euler with the library's defaults; the machine is shared (2 cores): read "
             "the ratio of the two models' ms, not the ms.", ""]
    if res["rows"]:
        lines += ["| scene | size | model | ms/step | substeps/step | CG it/step | solves/step | strain (report) "
                  "| principal strain | contact | status |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in res["rows"]:
            contact = "-"
            if r["scene"] == "drape":
                contact = f"sphere gap {r['sphere_gap_mm']:.2f} mm"
            elif r["scene"] == "crumple":
                contact = (f"{r['crossings']} crossings, floor gap {r['floor_gap_mm']:.2f} mm, rod gap "
                           f"{r['rod_gap_mm']:.2f} mm")
            lines.append(f"| {r['scene']} ({r['duration']:g} s) | {r['n']}² | {LABEL[r['model']]} | "
                         f"{r['ms_step']:.1f} | {r['substeps_per_step']:.2f} | {r['cg_per_step']:.1f} | "
                         f"{r['solves_per_step']:.2f} | "
                         f"{r['report_max_strain']:.3f} | {r['principal_strain']:.3f} | {contact} | {r['status']} |")
        lines += ["", "Strain (report): the run's frames' `max_strain` (springs: the structural springs'; triangles: "
                  "the largest principal strain). Principal strain: the grid triangles' largest principal strain, "
                  "measured the same way for both models. Gaps: least over the kept frames (the drape's contact rounds "
                  "keep the thickness, 5 mm; the crumple's barrier at least half of it, 2.5 mm)."]
        for r in res["rows"]:
            for h in r["health"]:
                lines.append(f"- {r['scene']} {r['n']}² {r['model']}: {h}")
    if res["sag"]:
        sizes = sorted({r["n"] for r in res["sag"]})
        t_end = res["sag_duration"]
        marks = sorted({min(1.0, t_end), t_end})
        lines += ["", f"## The hanging cloth's sag against resolution ({t_end:g} s)", "",
                  "Drop of the lowest point below the pins, mm, at the kept frame nearest each time; spread: (largest "
                  "- smallest) / smallest over the sizes.", "",
                  "| model | time | " + " | ".join(f"{n}²" for n in sizes) + " | spread |",
                  "|---|---|" + "---|" * len(sizes) + "---|"]
        for model in MODELS:
            rows = {r["n"]: r for r in res["sag"] if r["model"] == model}
            if not rows:
                continue
            for t in marks:
                d = [1e3 * _at(rows[n], t) for n in sizes if n in rows]
                spread = (max(d) - min(d)) / min(d) if min(d) > 0 else float("nan")
                lines.append(f"| {LABEL[model]} | {t:g} s | " + " | ".join(f"{v:.1f}" for v in d)
                             + f" | {100 * spread:.1f} % |")
        for r in res["sag"]:
            if r["status"] != "ok":
                lines.append(f"- sag {r['n']}² {r['model']}: {r['status']}: " + "; ".join(r["health"]))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI smoke: 8² scenes, 0.1-0.4 s (the drape and the crumple reach their obstacles); sag at 6², 8², 10², 0.2 s")
    ap.add_argument("--size", type=int, default=32, help="the scenes' resolution (default 32)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--duration", type=float, nargs=3, default=[1.0, 1.5, 1.5], metavar=("HANGING", "DRAPE", "CRUMPLE"),
                    help="simulated seconds of each scene (default 1.0 1.5 1.5)")
    ap.add_argument("--sag-sizes", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--sag-duration", type=float, default=2.0)
    ap.add_argument("--no-sag", action="store_true", help="leave out the resolution table")
    ap.add_argument("--out", type=Path, default=Path(default_out("cloth_models")),
                    help="output folder (default out/bench/cloth_models; --out benchmarks/results replaces the "
                         "committed result)")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.duration, args.sag_sizes, args.sag_duration = 8, [0.1, 0.25, 0.4], [6, 8, 10], 0.2
    durations = dict(zip(SCENES, args.duration))
    for model in args.models:     # warm-up: the kernels each path uses compiled (or loaded) before any timing
        run_row("hanging", model, 6, 0.02)
        if "crumple" in args.scenes:
            run_row("crumple", model, 6, 2 / 60)
    rows, sag = [], []
    for name in args.scenes:
        for model in args.models:
            rows.append(run_row(name, model, args.size, durations[name]))
            r = rows[-1]
            print(f"{name} {args.size}² {model}: {r['ms_step']:.1f} ms/step, {r['cg_per_step']:.1f} CG/step, "
                  f"strain {r['report_max_strain']:.3f}, {r['status']}", flush=True)
    if not args.no_sag:
        for n in args.sag_sizes:
            for model in args.models:
                sag.append(run_row("hanging", model, n, args.sag_duration))
                print(f"sag {n}² {model}: drop {1e3 * sag[-1]['drop'][-1]:.1f} mm at {args.sag_duration:g} s",
                      flush=True)
    res = {"benchmark": "cloth_models", "machine": machine(), "quick": args.quick, "size": args.size,
           "durations": durations, "sag_duration": args.sag_duration, "rows": rows, "sag": sag}
    write_outputs(args.out, "cloth_models", res, markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
