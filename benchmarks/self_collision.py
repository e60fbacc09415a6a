"""Self-collision: the crumple scene at 32², 64², 128², where the step's time goes, and whether it crossed.

The scene (the self-collision issue's): a 1 m x 1 m cotton sheet hanging in the xz plane (centre 0.62 m up) is
dropped edge-first onto the floor and a low rod (a capsule of radius 3 cm along y at x = 0.1 m, 4 cm up),
backward Euler at dt = 1/60 s with adaptive stepping, thickness 5 mm, friction 0.3 against the obstacles and
between layers, simulated for ``--duration`` s (it folds and piles onto itself from about 1 s on). Per size:

* ms per step split into the solve (assembly, preconditioner set-up, PCG), the obstacle collision stage and
  self-collision (the run report's timings; the machine is shared, so read them as shares of the step);
* candidates, proximity impulses and impacts per step, steps solved again with the corrected vertices
  prescribed (and those vertices per step), steps that used impact zones and their vertices, the impacts left
  unresolved (must be 0);
* crossings: edges through triangles (sharing no vertex) at every kept frame, judged by ipctk's
  ``has_intersections`` (an independent implementation) and counted by this script's own segment-triangle test
  (must be 0);
* the energy balance: the run's status and health.

The exponent of self-collision's cost in the number of vertices is fitted over the sizes (goal: <= 1.2), and
its share of the step at 64² is reported (goal: <= 50 %). ``--broad-phase`` also times the broad phases on a
piled frame: this package's (k-d tree over swept boxes by size class) against ipctk's LBVH, hash grid and sweep
and prune (their candidates come back as a list of Python objects, converted here to index arrays).

Usage::

    python benchmarks/self_collision.py                  # 32², 64², 128² (long: tens of minutes on 2 cores)
    python benchmarks/self_collision.py --quick          # CI smoke: 10² and 14², 0.3 s
    python benchmarks/self_collision.py --sizes 32 64 --duration 2.0 --broad-phase
    python benchmarks/self_collision.py --sizes 32 --save out/     # out/crumple_32 for implicit-cloth render
    python benchmarks/self_collision.py --sizes 128 --duration 1.5 --out part128/    # one size per run, then
    python benchmarks/self_collision.py --merge benchmarks/results/self_collision.json part128/self_collision.json
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from _common import default_out, ic, machine, write_outputs
from scipy.spatial import cKDTree

G = 9.81
TH = 0.005


def crumple(n: int, dt: float, duration: float, self_collision: bool = True) -> dict:
    return {"simulation": {"dt": dt, "duration": duration, "frame_rate": 30},
            "cloth": {"size": [1.0, 1.0], "resolution": [n, n], "plane": "xz", "center": [0.0, 0.0, 0.62],
                      "material": "cotton"},
            "effects": {"gravity": [0.0, 0.0, -G]},
            "obstacles": [{"shape": "plane", "friction": 0.3},
                          {"shape": "capsule", "radius": 0.03, "height": 2.0, "axis": [0.0, 1.0, 0.0],
                           "center": [0.1, 0.0, 0.04], "friction": 0.3}],
            "collision": {"thickness": TH, "self_collision": self_collision}}


def edge_list(faces: np.ndarray) -> np.ndarray:
    return np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)


def _near_pairs(x: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (edge, triangle) pair that can cross: the edge's midpoint within its half-length plus the
    triangle's radius (its farthest vertex from its centroid) of the triangle's centroid. The k-d trees are
    queried by groups (the longest 5 % of edges and the largest 5 % of triangles apart), each with its own
    largest radius, so that a few stretched elements do not widen the search for all (on a piled 128² frame
    a single radius made several times more candidates)."""
    a, b, c = (x[faces[:, k]] for k in range(3))
    cen = (a + b + c) / 3
    rad = np.max([np.linalg.norm(q - cen, axis=1) for q in (a, b, c)], axis=0)
    mid = (x[edges[:, 0]] + x[edges[:, 1]]) / 2
    half = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1) / 2
    eg = [g for g in np.split(np.argsort(half), [int(0.95 * len(half))]) if len(g)]
    tg = [g for g in np.split(np.argsort(rad), [int(0.95 * len(rad))]) if len(g)]
    ii, jj = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    trees = [cKDTree(cen[g]) for g in tg]
    for ge in eg:
        te = cKDTree(mid[ge])
        for gt, tt in zip(tg, trees):
            m = te.sparse_distance_matrix(tt, half[ge].max() + rad[gt].max(), output_type="ndarray")
            i, j = ge[m["i"]], gt[m["j"]]
            keep = m["v"] <= half[i] + rad[j]
            ii.append(i[keep])
            jj.append(j[keep])
    return np.concatenate(ii), np.concatenate(jj)


def count_crossings(x: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> int:
    """Edges through triangles that share no vertex with them (k-d tree candidates, Moller-Trumbore)."""
    i, j = _near_pairs(x, faces, edges)
    keep = ~(edges[i][:, :, None] == faces[j][:, None, :]).any(axis=(1, 2))
    i, j = i[keep], j[keep]
    p, d = x[edges[i, 0]], x[edges[i, 1]] - x[edges[i, 0]]
    o, e1, e2 = x[faces[j, 0]], x[faces[j, 1]] - x[faces[j, 0]], x[faces[j, 2]] - x[faces[j, 0]]
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-20
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p - o
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return int(np.sum(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)))


def ipc_intersecting(x: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> bool | None:
    try:
        import ipctk
    except ImportError:
        return None
    return bool(ipctk.has_intersections(ipctk.CollisionMesh(x, edges, faces), x))


def run_row(n: int, dt: float, duration: float, save: Path | None = None) -> dict:
    sim = ic.Simulator(crumple(n, dt, duration))
    t0 = time.perf_counter()
    traj = sim.run()
    wall = time.perf_counter() - t0
    if save is not None:      # a run directory as `implicit-cloth run` writes it (for `implicit-cloth render`)
        from implicit_cloth.files import write_run

        (save / f"crumple_{n}").mkdir(parents=True, exist_ok=True)
        write_run(save / f"crumple_{n}", traj, sim.scene.data)
    rep = traj.report
    faces = traj.faces
    edges = edge_list(faces)
    crossings = [count_crossings(x, faces, edges) for x in traj.positions]
    ipc = [ipc_intersecting(x, faces, edges) for x in traj.positions]
    steps = rep["adaptive"]["substeps"] if rep.get("adaptive") else rep["steps"]
    tm = rep["timing"]
    solve = tm["t_assembly"] + tm["t_setup"] + tm["t_solve"]
    sc = rep["self_collision"]
    per = 1e3 / max(steps, 1)
    return {
        "resolution": n, "vertices": sim.model.n, "dt": dt, "duration": duration, "substeps": steps,
        "wall_s": wall, "ms_step": wall * per, "ms_solve": solve * per, "ms_obstacles": tm["t_collision"] * per,
        "ms_self": sc["time"] * per, "ms_self_broad": sc["broad_phase_time"] * per,
        "self_share": sc["time"] / wall if wall > 0 else math.nan,
        "candidates_per_step": sc["candidates"] / max(sc["steps"], 1),
        "proximities_per_step": sc["proximities"] / max(sc["steps"], 1),
        "impacts_per_step": sc["impacts"] / max(sc["steps"], 1),
        "resolve_steps": sc["resolve_steps"], "resolved_vertices_per_step": sc["resolved_vertices"] / max(sc["steps"], 1),
        "zone_steps": sc["zone_steps"], "zone_vertices": sc["zone_vertices"],
        "max_zone_vertices": sc["max_zone_vertices"], "unresolved_steps": sc["unresolved_steps"],
        "max_crossings": max(crossings), "ipctk_intersecting_frames": None if ipc[0] is None else int(sum(ipc)),
        "zmin": float(traj.positions[..., 2].min()), "status": rep["status"],
        "health": [h["message"] for h in rep["health"]],
    }


def broad_phase_rows(n: int, repeats: int = 5) -> list[dict]:
    """Time the broad phases on a piled frame of the crumple (self-collision off, to get there fast)."""
    from implicit_cloth.selfcontact import broadphase

    sim = ic.Simulator(crumple(n, 1 / 60, 1.5, self_collision=False))
    sim.step(75)
    x0 = sim.positions.copy()
    sim.step(1)
    x1 = sim.positions.copy()
    faces = sim.model.faces
    edges = edge_list(faces)

    def timed(f):
        f()
        t = time.perf_counter()
        for _ in range(repeats):
            out = f()
        return 1e3 * (time.perf_counter() - t) / repeats, out

    rows = []

    def ours():
        v, f = broadphase.vertex_face_pairs(x0, x1, faces, TH)
        a, b = broadphase.edge_edge_pairs(x0, x1, edges, TH)
        return len(v), len(a)

    ms, (nvf, nee) = timed(ours)
    rows.append({"method": "numpy/scipy k-d tree (ours)", "ms_build": ms, "ms_to_arrays": 0.0, "vf": nvf, "ee": nee})
    try:
        import ipctk
    except ImportError:
        return rows
    mesh = ipctk.CollisionMesh(x0, edges, faces)
    for name in ("LBVH", "HashGrid", "SweepAndPrune"):
        kind = getattr(ipctk, name)

        def build(kind=kind):
            c = ipctk.Candidates()
            c.build(mesh, x0, x1, TH, kind())
            return c

        ms, c = timed(build)
        t = time.perf_counter()
        vf = np.array([(q.vertex_id, q.face_id) for q in c.fv_candidates]).reshape(-1, 2)
        ee = np.array([(q.edge0_id, q.edge1_id) for q in c.ee_candidates]).reshape(-1, 2)
        conv = 1e3 * (time.perf_counter() - t)
        rows.append({"method": f"ipctk {name}", "ms_build": ms, "ms_to_arrays": conv, "vf": len(vf), "ee": len(ee)})
    return rows


def exponent(rows: list[dict], key: str) -> float | None:
    """Least-squares slope of log(cost per step) against log(vertices)."""
    if len(rows) < 2:
        return None
    n = np.log([r["vertices"] for r in rows])
    t = np.log([max(r[key], 1e-12) for r in rows])
    return float(np.polyfit(n, t, 1)[0])


def markdown(res: dict) -> str:
    lines = ["# Self-collision: the crumple scene", "",
             f"cotton, dt = {res['dt']:.4g} s (adaptive), {res['duration']:g} s simulated, thickness 5 mm; "
             "ms per accepted substep; the machine is shared (2 cores), so read the times as shares.", "",
             "| size | substeps | ms/step | solve | obstacles | self (broad) | self share | candidates | "
             "proximities | impacts | solved again (vertices) | zone steps (vertices) | unresolved | crossings | "
             "ipctk says | status |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        ipc = "n/a" if r["ipctk_intersecting_frames"] is None else \
            ("none" if r["ipctk_intersecting_frames"] == 0 else f"{r['ipctk_intersecting_frames']} frames")
        lines.append(
            f"| {r['resolution']}² | {r['substeps']} | {r['ms_step']:.0f} | {r['ms_solve']:.0f} | "
            f"{r['ms_obstacles']:.0f} | {r['ms_self']:.0f} ({r['ms_self_broad']:.0f}) | {100 * r['self_share']:.0f} % | "
            f"{r['candidates_per_step']:.0f} | {r['proximities_per_step']:.1f} | {r['impacts_per_step']:.2f} | "
            f"{r['resolve_steps']} ({r['resolved_vertices_per_step']:.1f}) | {r['zone_steps']} ({r['max_zone_vertices']}) | {r['unresolved_steps']} | {r['max_crossings']} | {ipc} | "
            f"{r['status']} |")
    ex = res.get("self_exponent")
    lines += ["", f"Self-collision's cost per step ~ N^{ex:.2f} over the sizes (goal <= 1.2)." if ex is not None else ""]
    for r in res["rows"]:
        for h in r["health"]:
            lines.append(f"- {r['resolution']}²: {h}")
    if res.get("broad_phase"):
        lines += ["", f"## Broad phases on a piled {res['broad_phase_size']}² frame (VF and EE candidates)", "",
                  "| method | build ms | to numpy ms | VF | EE |", "|---|---|---|---|---|"]
        for b in res["broad_phase"]:
            lines.append(f"| {b['method']} | {b['ms_build']:.1f} | {b['ms_to_arrays']:.1f} | {b['vf']} | {b['ee']} |")
    return "\n".join(lines) + "\n"


def merge(paths: list[Path], out: Path) -> int:
    """Combine partial runs (one size per run, as a shared machine allows) into one result: rows by size (a size
    given twice: the later file's row), the exponent fitted again over all of them. The runs must share dt and
    duration."""
    import json

    parts = [json.loads(Path(p).read_text()) for p in paths]
    for key in ("dt", "duration", "quick"):
        if len({part[key] for part in parts}) > 1:
            raise SystemExit(f"--merge: the runs differ in {key}: {[part[key] for part in parts]}")
    rows = sorted({r["resolution"]: r for part in parts for r in part["rows"]}.values(), key=lambda r: r["resolution"])
    res = {**parts[0], "rows": rows, "self_exponent": exponent(rows, "ms_self"),
           "merged_from": [str(p) for p in paths]}
    write_outputs(out, "self_collision", res, markdown(res))
    print(markdown(res))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI smoke: 10² and 14², 0.3 s")
    ap.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--dt", type=float, default=1 / 60)
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--broad-phase", action="store_true", help="also time the broad phases (ours, ipctk's)")
    ap.add_argument("--out", type=Path, default=Path(default_out('self_collision')), help="output folder (default out/bench/self_collision; --out benchmarks/results replaces the committed result)")
    ap.add_argument("--save", type=Path, default=None,
                    help="also write each run's trajectory.npz and report.json to SAVE/crumple_N (to render it)")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="JSON",
                    help="run nothing: combine the rows of earlier (partial) runs' self_collision.json into one table")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)
    sizes, duration = ([10, 14], 0.3) if args.quick else (args.sizes, args.duration)
    rows = []
    for n in sizes:
        rows.append(run_row(n, args.dt, duration, args.save))
        r = rows[-1]
        print(f"{n}²: {r['ms_step']:.0f} ms/step, self {100 * r['self_share']:.0f} %, crossings {r['max_crossings']}, "
              f"{r['status']}", flush=True)
    res = {"benchmark": "self_collision", "quick": args.quick, "machine": machine(), "dt": args.dt,
           "duration": duration, "rows": rows, "self_exponent": exponent(rows, "ms_self")}
    if args.broad_phase and not args.quick:
        res["broad_phase_size"] = 64
        res["broad_phase"] = broad_phase_rows(64)
    md = markdown(res)
    write_outputs(args.out, "self_collision", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
