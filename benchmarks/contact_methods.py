"""Contact methods side by side: the crumple with the contact rounds and with the barrier in one Newton solve.

The crumple of ``self_collision.py`` (a 1 m cotton sheet dropped edge-first onto a floor and a low rod, thickness
5 mm, self-collision on, backward Euler at dt 1/60 with adaptive stepping) is run with ``[collision] method =
"rounds"`` and ``"barrier"`` at each size in the same process, one after the other, beside the same cloth
hanging free (two corners pinned, no contact) for the cost ratio. Each run is judged from its kept frames by
this script: crossings (edges through triangles sharing no vertex, ``self_collision.count_crossings``), the
least gap to the floor and to the rod (their distances written here), and the run's own energy health.

Columns: ms per 1/60 s frame, substeps per frame, linear solves per substep (Newton corrections and contact
rounds; the discarded attempts' included), the ratio to the hanging cloth's ms per frame, crossings (the most at
any kept frame), floor and rod gaps (mm; the cloth keeps half the thickness, 2.5 mm, with the barrier and the
whole thickness with the rounds), and the status.

Usage::

    python benchmarks/contact_methods.py                     # 32², 1.5 s (minutes on 2 cores)
    python benchmarks/contact_methods.py --sizes 32 64 --duration 1.5
    python benchmarks/contact_methods.py --quick             # CI smoke: 8², 0.2 s
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
from _common import default_out, ic, machine, write_outputs
from self_collision import count_crossings, crumple, edge_list

METHODS = ("rounds", "barrier")


def hanging(n: int, duration: float) -> dict:
    """The crumple's cloth hanging free: the same sheet and step, its two top corners pinned, no contact."""
    scene = crumple(n, 1 / 60, duration)
    del scene["obstacles"], scene["collision"]
    scene["cloth"]["pins"] = ["top_left", "top_right"]
    return scene


def crumple_gaps(X: np.ndarray) -> tuple[float, float]:
    """The least gap over the frames ``X`` (F, N, 3) to the crumple's floor (z = 0) and to its rod (a capsule of
    radius 3 cm along y through x = 0.1 m, z = 0.04 m), mm (negative: inside)."""
    return (1e3 * float(X[..., 2].min()),
            1e3 * float((np.hypot(X[..., 0] - 0.1, X[..., 2] - 0.04) - 0.03).min()))


def run(scene: dict, frames: int) -> tuple[object, object, float]:
    sim = ic.Simulator(scene)
    t0 = time.perf_counter()
    traj = sim.run()
    return sim, traj, (time.perf_counter() - t0) * 1e3 / frames


def row(n: int, method: str, duration: float, free_ms: float) -> dict:
    scene = copy.deepcopy(crumple(n, 1 / 60, duration))
    scene["collision"]["method"] = method
    frames = int(round(duration * 60))
    sim, traj, ms = run(scene, frames)
    rep = traj.report
    X = traj.positions
    faces = traj.faces
    edges = edge_list(faces)
    crossings = max(count_crossings(x, faces, edges) for x in X)
    floor_gap, rod_gap = crumple_gaps(X)
    substeps = rep["adaptive"]["substeps"] if rep.get("adaptive") else rep["steps"]
    return {
        "resolution": n, "method": method, "ms_frame": ms, "ratio_to_hanging": ms / free_ms,
        "substeps_per_frame": substeps / frames,
        "solves_per_substep": rep["solver"].get("mean_attempted_solves"),
        "crossings": int(crossings),
        "floor_gap_mm": floor_gap, "rod_gap_mm": rod_gap,
        "status": rep["status"], "health": [h["message"] for h in rep["health"]],
    }


def markdown(res: dict) -> str:
    lines = ["# Contact methods: the crumple, contact rounds against the barrier in one Newton solve", "",
             f"cotton sheet, dt 1/60 s (adaptive), {res['duration']:g} s simulated, thickness 5 mm, self-collision "
             "on; the same cloth hanging free at the same size in the same run for the ratio. The machine is "
             "shared (2 cores): read ratios.", "",
             "| size | method | ms/frame | × hanging | substeps/frame | solves/substep | crossings | floor gap mm | "
             "rod gap mm | status |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        sps = "-" if r["solves_per_substep"] is None else f"{r['solves_per_substep']:.1f}"
        lines.append(f"| {r['resolution']}² | {r['method']} | {r['ms_frame']:.0f} | {r['ratio_to_hanging']:.1f} | "
                     f"{r['substeps_per_frame']:.2f} | {sps} | {r['crossings']} | {r['floor_gap_mm']:.2f} | "
                     f"{r['rod_gap_mm']:.2f} | {r['status']} |")
    lines += ["", "Hanging free, ms per frame: " + ", ".join(f"{n}²: {ms:.1f}" for n, ms in res["hanging"].items())]
    for r in res["rows"]:
        for h in r["health"]:
            lines.append(f"- {r['resolution']}² {r['method']}: {h}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI smoke: 8², 0.2 s")
    ap.add_argument("--sizes", type=int, nargs="+", default=[32])
    ap.add_argument("--duration", type=float, default=1.5)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--out", type=Path, default=Path(default_out("contact_methods")),
                    help="output folder (default out/bench/contact_methods; --out benchmarks/results replaces the "
                         "committed result)")
    args = ap.parse_args(argv)
    sizes, duration = ([8], 0.2) if args.quick else (args.sizes, args.duration)
    rows, free = [], {}
    for m in args.methods:        # warm-up: the kernels each path uses compiled (or loaded) before any timing
        row(6, m, 2 / 60, 1.0)
    for n in sizes:
        run(hanging(n, 2 / 60), 2)
        _, _, free[n] = run(hanging(n, duration), int(round(duration * 60)))
        for m in args.methods:
            rows.append(row(n, m, duration, free[n]))
            print(f"{n}² {m}: {rows[-1]['ms_frame']:.0f} ms/frame, {rows[-1]['crossings']} crossings", flush=True)
    res = {"benchmark": "contact_methods", "machine": machine(), "quick": args.quick, "duration": duration, "hanging": free, "rows": rows}
    write_outputs(args.out, "contact_methods", res, markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
