"""Does Blender's cloth resist compression? Its structural springs' strain at the end of a drape, per bending model.

Blender 3.4's ``SIM_mass_spring_force_spring_linear`` gives a structural spring no force in compression unless
the ``RESIST_SPRING_COMPRESS`` flag is set (no Python property sets it) or the bending model is ``ANGULAR``
(then ``compression_stiffness`` acts, linear near the rest length); shear springs take none in either model.
This study runs ``vs_blender.py``'s scenes in Blender (``_blender_cloth.py``) with ``--bending linear`` and
``--bending angular`` (compression stiffness = tension stiffness), and ours beside them, and measures from the
positions the fraction of structural springs (grid edges) more than 20 % compressed (shorter than 0.8 of the
rest length) at the end, the most at any frame, and the shortest spring's length over its rest length.

Usage::

    python benchmarks/studies/blender_compression.py                       # drape 32², 2 s
    python benchmarks/studies/blender_compression.py --scenes drape crumple --sizes 32 64 --duration 1.5
    python benchmarks/studies/blender_compression.py --quick               # drape 8², 0.5 s

Needs Blender (``apt-get install blender python3-numpy``; without it, our side only). Writes
``OUT/blender_compression.{json,md}`` (``--out``, default out/bench/blender_compression). Never asserts.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and vs_blender

from _common import default_out, machine, write_outputs
from vs_blender import DURATION, blender, run_ours

COMPRESSED = 0.8       # a structural spring shorter than this fraction of its rest length is "compressed"


def structural(n: int) -> np.ndarray:
    """The grid's structural springs (vertex ``j n + i``): along rows and along columns."""
    idx = np.arange(n * n).reshape(n, n)
    return np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                           np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1)])


def strain(X: np.ndarray) -> dict:
    """From a run's frames (frames x n^2 x 3): the fraction of structural springs shorter than ``COMPRESSED``
    of their rest length at the end and at the worst frame, and the shortest one's length ratio."""
    n = int(round(np.sqrt(X.shape[1])))
    s = structural(n)
    ratio = np.linalg.norm(X[:, s[:, 1]] - X[:, s[:, 0]], axis=2) * (n - 1)      # length / rest length (1/(n-1))
    frac = (ratio < COMPRESSED).mean(axis=1)
    return {"compressed_end": float(frac[-1]), "compressed_max": float(frac.max()),
            "shortest_end": float(ratio[-1].min()), "stretched_end": float(ratio[-1].max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["drape"], choices=["drape", "crumple", "hanging"])
    ap.add_argument("--sizes", type=int, nargs="+", default=[32])
    ap.add_argument("--duration", type=float, default=None, help="s (default: the scene's, 2 / 1.5)")
    ap.add_argument("--quick", action="store_true", help="drape 8², 0.5 s")
    ap.add_argument("--out", type=Path, default=Path(default_out("blender_compression")))
    a = ap.parse_args(argv)
    if a.quick:
        a.scenes, a.sizes, a.duration = ["drape"], [8], 0.5
    exe = shutil.which("blender")
    if exe is None:
        print("blender_compression: Blender is not installed: our side only", flush=True)
    opts = argparse.Namespace(blender_collision_quality=None, duration=a.duration, timeout=3600.0)
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="blender_compression_"))
    try:
        for kind in a.scenes:
            for n in a.sizes:
                path = tmp / f"ours_{kind}_{n}.npy"
                run_ours(kind, n, False, None, None, duration=a.duration, save=str(path))
                rows.append({"scene": kind, "n": n, "program": "ours", **strain(np.load(path))})
                for bending in (["linear", "angular"] if exe else []):
                    opts.blender_bending = bending
                    path = tmp / f"blender_{kind}_{n}_{bending}.npy"
                    blender(exe, kind, n, opts, None, str(path))
                    rows.append({"scene": kind, "n": n, "program": f"Blender, {bending.upper()}",
                                 **strain(np.load(path))})
                for r in rows[-3:]:
                    print(f"{kind} {n}² {r['program']}: {100 * r['compressed_end']:.1f} % compressed at the end "
                          f"({100 * r['compressed_max']:.1f} % at most), shortest {r['shortest_end']:.2f}", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lines = ["# Blender's structural springs in compression, per bending model", "",
             f"Structural springs (grid edges) shorter than {COMPRESSED:g} of their rest length, from the positions; "
             f"{a.duration or ', '.join(f'{k} {DURATION[k]:g}' for k in a.scenes)} s, dt 1/60 s, Blender's "
             "quality 1; ours with its defaults.", "",
             "| scene | grid | program | compressed > 20 % at the end | most at any frame | shortest / rest at the end | "
             "longest / rest at the end |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['n']}² | {r['program']} | {100 * r['compressed_end']:.1f} % | "
                     f"{100 * r['compressed_max']:.1f} % | {r['shortest_end']:.2f} | {r['stretched_end']:.2f} |")
    md = "\n".join(lines) + "\n"
    write_outputs(a.out, "blender_compression",
                  {"benchmark": "blender_compression", "quick": a.quick, "duration": a.duration, "rows": rows,
                   "machine": machine()}, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
