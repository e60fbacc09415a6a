"""Does the CG stopping rule deliver the accuracy it is asked for? True error of dv against a direct solve.

For each scene the simulation runs at its own settings (default tolerance 1e-3)
and, every ``--every`` steps after ``--skip``, the linear system the step solves
(matrix, right-hand side, prescribed ``z``, Baraff-Witkin filter with any
contact constraints, the preconditioner as set up for that step) is captured.
On each captured system the filtered PCG is re-run (same iteration as
:func:`implicit_cloth.solvers.pcg.filtered_pcg`) to a tight error, recording per
iteration the quantities a stopping rule sees (``alpha_j delta_j``,
``|p_j|^2 / p_j^T A p_j``, ``|dv_k|``, the mass bound) and the **true relative
error** ``|dv_k - dv*| / |dv*|`` against a sparse direct solve of the constrained
system. Since the iterates do not depend on the tolerance, every rule and every
tolerance is then evaluated on the same record:

* ``old``: the error estimate of the iterate ``d = max(4, k/4)`` iterations back
  (the rule before this benchmark was written);
* ``new``: :func:`implicit_cloth.solvers.pcg.current_error_estimate`, the error
  of the current iterate (the library's rule);
* ``ideal``: the first iteration whose true error is at most the tolerance.

Per scene and tolerance it reports the distribution of true error / tolerance
(median, 90th percentile, max) and of the iterations. As a check of the
emulation, the library's own ``filtered_pcg`` is also run on every captured
system at the simulation's tolerance and its iteration count compared.

Scenes: the "hanging stiff cloth" (``benchmarks/_common.hanging_stiff``) at
k = 1e4 and 1e3 N/m, and ``examples/drape_sphere.toml`` (a cloth landing on and
resting on a sphere: contact constraints in the filter).

The sampled states come from the simulation itself, so they depend (slightly)
on the rule the library had when the records were taken; ``--save-records``
keeps the records and ``--from-records`` re-evaluates the rules on them (without
the library check), which is how a candidate rule is compared on the same
systems. ~25 min for the default sizes on the 2-core test machine.

Usage::

    python benchmarks/studies/stopping_rule.py                      # 32, 64, 128; both k; the drape
    python benchmarks/studies/stopping_rule.py --quick              # seconds
    python benchmarks/studies/stopping_rule.py --save-records /tmp/rec.pkl
    python benchmarks/studies/stopping_rule.py --from-records /tmp/rec.pkl

Writes ``OUT/stopping_rule.json``, ``OUT/stopping_rule.md`` and ``OUT/stopping_rule.png`` (the
distribution of true error / tol per rule and tolerance; ``OUT/stopping_rule_from_records.*`` with
``--from-records``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import ROOT, default_out, hanging_stiff, ic, machine, progress, save_png, write_outputs

from implicit_cloth.integrators import base
from implicit_cloth.solvers import pcg as pcg_mod

TOLS = (1e-2, 1e-3, 1e-4)
RECORDS: list | None = None


def direct_solve(A, b, z, filt) -> np.ndarray:
    """Exact constrained solution: ``dv = (I-S) z + y`` with ``S A S y = S (b - A (I-S) z)``, ``y = S y``."""
    n3 = len(b)
    S3 = filt.matrices()
    S = _block_diag(S3)
    zc = z - S @ z
    K = (S @ A @ S + (sp.identity(n3) - S)).tocsc()
    y = spla.spsolve(K, S @ (b - A @ zc), permc_spec="COLAMD")
    return zc + S @ y


def _block_diag(S3: np.ndarray) -> sp.csr_array:
    n = len(S3)
    rows = np.repeat(np.arange(3 * n).reshape(n, 3), 3, axis=1).ravel()
    cols = np.tile(np.arange(3 * n).reshape(n, 3), (1, 3)).ravel()
    return sp.csr_array((S3.reshape(-1), (rows, cols)), shape=(3 * n, 3 * n))


def record(A, b, z, filt, precond, mass, ref, max_iterations=400, stop_error=1e-7) -> dict:
    """Re-run filtered PCG (the numpy reference iteration) recording what a stopping rule sees, and the truth."""
    zc = z - filt.apply(z.copy())
    dv = zc.copy()
    r = filt.apply(b - A @ dv)
    s = filt.apply(precond.apply(r))
    p = s.copy()
    delta = float(r @ s)
    delta0 = delta
    nref = np.linalg.norm(ref)
    ad, pw, dd, err, mb, exact = [], [], [], [], [], []
    for _ in range(max_iterations):
        q = filt.apply(A @ p)
        pq = float(p @ q)
        alpha = delta / pq
        dv += alpha * p
        r -= alpha * q
        ad.append(alpha * delta)
        pw.append(float(p @ p) / pq)
        dd.append(float(dv @ dv))
        err.append(float(np.linalg.norm(dv - ref)) / nref)
        mb.append(np.sqrt(float(r @ (r / mass)) / max(float(dv @ (mass * dv)), 1e-300)))
        s = filt.apply(precond.apply(r))
        delta_new = float(r @ s)
        exact.append(delta_new <= 1e-30 * delta0)
        if err[-1] < stop_error or exact[-1]:
            break
        p *= delta_new / delta
        p += s
        delta = delta_new
    return {k: np.array(v) for k, v in dict(ad=ad, pw=pw, dd=dd, err=err, mb=mb, exact=exact).items()}


def old_estimate(ad, pw, dd, it, min_delay=4, delay_fraction=0.25):
    """The rule before: estimated error of the iterate d back (None while it < d)."""
    d = max(min_delay, int(delay_fraction * it))
    if it < d:
        return None
    eA = np.cumsum(ad[it - d:it][::-1])[::-1]
    e2 = float(pw[it - d:it] @ (eA + np.append(eA[1:], 0.0)))
    return np.sqrt(e2 / max(dd[it - 1], 1e-300))


def stop_iteration(rec: dict, tol: float, rule: str, use_mass: bool = True) -> int:
    """Iteration (1-based count) at which ``rule`` stops; len(record) if it never does within the record."""
    ad, pw, dd, mb, exact = rec["ad"], rec["pw"], rec["dd"], rec["mb"], rec["exact"]
    K = len(ad)
    for it in range(1, K + 1):
        if rule == "ideal":
            if rec["err"][it - 1] <= tol:
                return it
            continue
        if exact[it - 1]:
            return it
        if use_mass and mb[it - 1] <= tol:
            return it
        d = max(4, int(0.25 * it))                      # filtered_pcg's default window
        if rule == "old":
            e = old_estimate(ad, pw, dd, it)
        elif it >= d:
            e = pcg_mod.current_error_estimate(ad, pw, it, dd[it - 1], d)
        else:
            e = None
        if e is not None and e <= tol:
            return it
    return K


class Capture:
    """Wraps ``filtered_pcg`` as the integrators call it, keeping the systems of the steps asked for."""

    def __init__(self) -> None:
        self.want = False
        self.systems: list = []
        self._orig = base.filtered_pcg

    def __enter__(self):
        def grab(A, b, z, filt, precond, tol=1e-3, max_iterations=1000, **kw):
            out = self._orig(A, b, z, filt, precond, tol, max_iterations, **kw)
            if self.want:
                f2 = pcg_mod.Filter(filt.n, filt.fixed.copy(), filt.partial.copy(), filt.partial_S.copy())
                # A is the model's SystemMatrix (finalized lazily): its CSR
                csr = sp.csr_array(getattr(A, "csr", A), copy=True)
                sysm = (csr, b.copy(), z.copy(), f2, precond, kw.get("mass"), tol, out[1])
                self.systems.append(sysm)
                self.want = False
            return out

        base.filtered_pcg = grab
        return self

    def __exit__(self, *exc):
        base.filtered_pcg = self._orig


def run_scene(name: str, scene, dt: float, skip: int, every: int, samples: int) -> list[dict]:
    sim = ic.Simulator(scene, dt=dt)
    rows = []
    with Capture() as cap:
        sim.step(skip)
        for _ in progress(range(samples), desc=name):
            sim.step(every - 1)
            cap.want = True
            sim.step(1)
            A, b, z, filt, precond, mass, tol, res = cap.systems.pop()
            ref = direct_solve(A, b, z, filt)
            rec = record(A, b, z, filt, precond, mass, ref)
            # the library's own solver on the same system (a copy: the numpy loop, with the preconditioner's
            # V-cycle), to check the emulation of its rule
            _, lib = pcg_mod.filtered_pcg(A, b, z, filt, precond, tol, 20000, mass=mass,
                                          rule=precond.stopping_rule, compiled=False)
            row = evaluate(rec)
            row.update({"t": float(sim.time), "sim_tol": tol, "library_iterations": lib.iterations,
                        "emulated": stop_iteration(rec, tol, "new"), "contacts": int(len(filt.partial))})
            rows.append(row)
            if RECORDS is not None:
                RECORDS.append((name, rec))
    return rows


def evaluate(rec: dict) -> dict:
    """Stop iteration and true error at the stop, for every rule and tolerance, on one record."""
    row = {"record_length": len(rec["ad"])}
    for t in TOLS:
        for rule in ("old", "new", "ideal"):
            it = stop_iteration(rec, t, rule)
            row[f"{rule}@{t:g}"] = {"it": it, "err": float(rec["err"][it - 1])}
    return row


def summarise(rows: list[dict]) -> dict:
    out = {}
    for t in TOLS:
        for rule in ("old", "new", "ideal"):
            e = np.array([r[f"{rule}@{t:g}"]["err"] for r in rows]) / t
            its = np.array([r[f"{rule}@{t:g}"]["it"] for r in rows])
            out[f"{rule}@{t:g}"] = {"err_over_tol_median": float(np.median(e)),
                                    "err_over_tol_p90": float(np.quantile(e, 0.9)),
                                    "err_over_tol_max": float(e.max()), "above_tol": int((e > 1).sum()),
                                    "above_1.5tol": int((e > 1.5).sum()),
                                    "it_median": float(np.median(its)), "it_max": int(its.max())}
    checked = [r for r in rows if "library_iterations" in r]
    out["emulation_checked"] = len(checked)
    out["emulation_mismatch"] = int(sum(r["library_iterations"] != r["emulated"] for r in checked))
    out["samples"] = len(rows)
    return out


def pooled(res: dict) -> dict:
    """All scenes together: the distribution of true error / tol at the stop, iterations relative to ``ideal``."""
    rows = [r for rs in res["rows"].values() for r in rs]
    out = summarise(rows)
    for t in TOLS:
        ideal = sum(r[f"ideal@{t:g}"]["it"] for r in rows)
        for rule in ("old", "new", "ideal"):
            out[f"{rule}@{t:g}"]["iterations_over_ideal"] = sum(r[f"{rule}@{t:g}"]["it"] for r in rows) / ideal
    return out


def markdown(res: dict) -> str:
    pool = res["pooled"]
    head = ["All scenes pooled (" + str(pool["samples"]) + " systems): true error / tol at the stop, and the total "
            "iterations relative to stopping at the first iterate within tol.", "",
            "| tol | rule | median | p90 | max | > tol | > 1.5 tol | iterations / ideal |", "|---|---|---|---|---|---|---|---|"]
    for t in TOLS:
        for rule in ("old", "new", "ideal"):
            v = pool[f"{rule}@{t:g}"]
            head.append(f"| {t:g} | {rule} | {v['err_over_tol_median']:.2f} | {v['err_over_tol_p90']:.2f} | "
                        f"{v['err_over_tol_max']:.2f} | {v['above_tol']} | {v['above_1.5tol']} | "
                        f"{v['iterations_over_ideal']:.3f} |")
    if "from_records" in res:
        head += ["", "Re-evaluated on saved records (`--from-records`): the states were simulated with the rule the "
                 "library had when they were recorded; no library check."]
    lines = head + ["", "True relative error of dv (against a direct solve) over tolerance, and CG iterations, per stopping rule.",
             f"Each scene: {res['samples']} systems, every {res['every']} steps after step {res['skip']} (the drape: "
             "after step 80 at dt = 0.01 s, resting on the sphere). "
             "`old`: estimate of the iterate d back; `new`: estimate of the current iterate; `ideal`: first "
             "iteration with true error <= tol.", "",
             "| scene | tol | rule | err/tol median | p90 | max | > tol | iterations median | max |",
             "|---|---|---|---|---|---|---|---|---|"]
    for sc, s in res["scenes"].items():
        for t in TOLS:
            for rule in ("old", "new", "ideal"):
                v = s[f"{rule}@{t:g}"]
                lines.append(f"| {sc} | {t:g} | {rule} | {v['err_over_tol_median']:.2f} | {v['err_over_tol_p90']:.2f} "
                             f"| {v['err_over_tol_max']:.2f} | {v['above_tol']}/{s['samples']} | {v['it_median']:g} "
                             f"| {v['it_max']} |")
    lines.append("")
    lines.append("Library `filtered_pcg` stopping at another iteration than the emulated `new` rule (at the "
                 "simulation's tolerance): " + ", ".join(f"{k} {v['emulation_mismatch']} of {v['emulation_checked']}"
                                                        for k, v in res["scenes"].items()))
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    """Per tolerance: the distribution (empirical CDF over all systems) of true error / tol at the stop, per rule."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for rs in res["rows"].values() for r in rs]
    fig, axes = plt.subplots(1, len(TOLS), figsize=(4.2 * len(TOLS), 3.6), sharey=True)
    for ax, t in zip(axes, TOLS):
        for rule, col in (("old", "tab:red"), ("new", "tab:blue"), ("ideal", "0.5")):
            e = np.sort([r[f"{rule}@{t:g}"]["err"] / t for r in rows])
            its = sum(r[f"{rule}@{t:g}"]["it"] for r in rows) / sum(r[f"ideal@{t:g}"]["it"] for r in rows)
            ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", color=col,
                    label=f"{rule} ({its:.2f}x ideal iterations)")
        ax.axvline(1.0, color="k", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_xlim(5e-3, 3)
        ax.set_title(f"tol = {t:g}")
        ax.set_xlabel("true error of dv / tol at the stop")
        ax.legend(fontsize=7, loc="upper left")
    axes[0].set_ylabel(f"fraction of the {len(rows)} systems")
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e3])
    p.add_argument("--skip", type=int, default=10, help="steps before the first sample")
    p.add_argument("--every", type=int, default=4, help="steps between samples")
    p.add_argument("--samples", type=int, default=20, help="systems per scene")
    p.add_argument("--no-drape", action="store_true", help="skip the drape-on-sphere scene")
    p.add_argument("--quick", action="store_true", help="tiny run (CI smoke)")
    p.add_argument("--save-records", type=Path, default=None, help="also save the raw records (npz) here")
    p.add_argument("--from-records", type=Path, default=None,
                   help="re-evaluate the rules on records saved by --save-records instead of simulating")
    p.add_argument("--out", type=Path, default=Path(default_out('stopping_rule')), help="output folder (default out/bench/stopping_rule)")
    a = p.parse_args(argv)
    global RECORDS
    if a.save_records is not None:
        RECORDS = []
    if a.quick:
        a.sizes, a.samples, a.skip, a.every = [12], 3, 2, 2
    res = {"benchmark": "stopping_rule", "quick": a.quick, "machine": machine(), "skip": a.skip, "every": a.every,
           "samples": a.samples, "scenes": {}, "rows": {}}
    if a.from_records is not None:
        import pickle

        for name, rec in pickle.loads(a.from_records.read_bytes()):
            res["rows"].setdefault(name, []).append(evaluate(rec))
        for name, rows in res["rows"].items():
            res["scenes"][name] = summarise(rows)
        res["from_records"] = str(a.from_records)
        res["pooled"] = pooled(res)
        write_outputs(a.out, "stopping_rule_from_records", res, markdown(res))
        plot(res, a.out / "stopping_rule_from_records.png")
        print(markdown(res))
        return 0
    scenes = [(f"hanging k={k:g} {n}²", hanging_stiff(n, k), 1 / 60) for k in a.stiffness for n in a.sizes]
    if not a.no_drape:
        drape = ic.load_scene(ROOT / "examples" / "drape_sphere.toml")
        if a.quick:
            drape = drape.replace(cloth={"resolution": [12, 12]})
        scenes.append(("drape on sphere 32²" if not a.quick else "drape on sphere", drape, 0.01))
    for name, scene, dt in scenes:
        skip = a.skip if "drape" not in name else max(a.skip, 0 if a.quick else 80)
        rows = run_scene(name, scene, dt, skip, a.every, a.samples)
        res["rows"][name] = rows
        res["scenes"][name] = summarise(rows)
        print(name, {k: (round(v["err_over_tol_median"], 2), round(v["err_over_tol_max"], 2), v["it_median"])
                     for k, v in res["scenes"][name].items() if isinstance(v, dict)}, flush=True)
    res["pooled"] = pooled(res)
    if a.save_records is not None:
        import pickle

        a.save_records.parent.mkdir(parents=True, exist_ok=True)
        a.save_records.write_bytes(pickle.dumps(RECORDS))
    write_outputs(a.out, "stopping_rule", res, markdown(res))
    plot(res, a.out / "stopping_rule.png")
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
