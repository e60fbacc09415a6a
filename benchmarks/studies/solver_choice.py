"""Which V-cycle: iterations and true error of dv per lever, on systems taken from real steps, free and in contact.

Systems: the linear system (matrix, right-hand side, prescribed dv, Baraff-Witkin filter) of a step taken from
a run of the engine with its default settings:

* ``stiff``: the hanging stiff cloth of ``scaling.py`` (k = 1e4 N/m), the first solve of step ``--stiff-step``;
* ``hanging`` and ``drape``: the peer scene of ``vs_blender.py`` (k = 1e3 N/m) hanging from two corners, and
  dropped on the sphere, the last solve of step ``--peer-step`` (2 s: the drape at rest on the sphere, with
  its resting contacts: sliding ``S = I - n n^T`` or sticking ``S = 0``); ``drape`` is also solved with its
  contact constraints removed (the same matrix, free), which separates what the constraints cost from what
  the draped state costs.

Levers (a numpy V-cycle written here, the same hierarchy as ``implicit_cloth.solvers.multigrid``:
bilinear prolongations, Galerkin coarse matrices of the filtered fine matrix ``S A S + (I - S)``, dense
Cholesky at the coarsest level), each the preconditioner of the library's filtered PCG
(``filtered_pcg(compiled=False)``, tolerance ``--tolerance``, its stopping rule unchanged):
``jacobi`` (the library's: one damped block-Jacobi sweep, omega 0.7, before and after), ``jacobi2`` (two
sweeps), ``W`` (a W-cycle), ``chebyshev2`` / ``chebyshev3`` (a Chebyshev polynomial of ``D^-1 A`` of degree
2 / 3 on ``[lmax / 30, lmax]``, ``lmax`` 1.1 times a 15-step power estimate per level), ``filtered_P``
(coarse spaces in the free directions: prolongation ``S P``, coarse matrices ``P^T S A S P``), ``weighed_P``
(the constrained directions of the prolongation's rows weighed by ``sqrt(m)``: ``(S + sqrt(m) (I - S)) P``, as
the library's smoothed multigrid does since 2026-12-07, here on the plain bilinear hierarchy and at every
constrained vertex, pins too, where the library weighs the partially constrained ones only), ``sa_rigid``
(not this hierarchy: pyamg's smoothed aggregation with the six rigid motions at the step's positions as the
near-null space, interpolation that follows the cloth's shape; its setup is rebuilt per system). The true
error is against a sparse direct solve of the filtered system. Cost: fine-level matrix passes per CG
iteration (CG's product plus the V-cycle's, its coarse levels counted at their share of the fine level's
blocks), the figure that decides time once the iterations are known (this script's numpy times are not a
measure of anything).

The library's own preconditioners, compiled (``lib_multigrid``: the plain multigrid, which ``jacobi`` writes
again in numpy; ``lib_smoothed``: the smoothed multigrid; ``lib_smoothed_K``: the same with the K-cycle,
``solver.cycle = "K"``; ``lib_smoothed_identity``: the smoothed multigrid with its contacts' constrained
directions weighed in the coarse levels by the filtered matrix's identity, as before 2026-12-07, instead of
by the vertices' masses), solve the same systems where they were captured, on
the model's live system matrix, as the integrator runs them: set-up and solve timed together (best of 3,
``--threads`` threads), with their iterations and true error; for them the table gives ms instead of passes.

Usage::

    python benchmarks/studies/solver_choice.py --sizes 32 64            # ~10 min on 2 shared cores
    python benchmarks/studies/solver_choice.py --sizes 32 64 128 256 --systems stiff
    python benchmarks/studies/solver_choice.py --sizes 128 256 --levers jacobi lib_multigrid lib_smoothed

Writes ``OUT/solver_choice.{json,md}``. Never asserts.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # benchmarks/: _common and the benchmarks studied

from _common import default_out, hanging_stiff, ic, machine, series, write_outputs
from vs_blender import scene as peer_scene

from implicit_cloth.solvers.blocks import inv3
from implicit_cloth.solvers.multigrid import grid_prolongations
from implicit_cloth.solvers.pcg import Filter, filtered_pcg

#: the library's own preconditioners, compiled (numba), timed on the live system of the captured solve
LIBRARY = {"lib_multigrid": "multigrid", "lib_smoothed": "multigrid_smoothed", "lib_smoothed_K": "multigrid_smoothed+K",
           "lib_smoothed_identity": "multigrid_smoothed"}
#: the library's smoothed multigrid as it was before 2026-12-07: the contacts' constrained directions weighed by
#: the filtered matrix's identity in its coarse levels, not by the vertices' masses (Multigrid.masses None;
#: SmoothedProlongation.weigh_constrained)
UNWEIGHED = {"lib_smoothed_identity"}

LEVERS = {
    "jacobi": {}, "jacobi2": {"nu": 2}, "W": {"cycle": "W"},
    "chebyshev2": {"smoother": "chebyshev", "degree": 2}, "chebyshev3": {"smoother": "chebyshev", "degree": 3},
    "filtered_P": {"filtered_p": True}, "weighed_P": {"weighed_p": True},
    "sa_rigid": {},
}


def library_solves(model, A, b: np.ndarray, z: np.ndarray, filters: dict, tol: float, library: list[str],
                    repeats: int = 3) -> dict:
    """The library's own compiled preconditioners (:data:`LIBRARY`) on the live system ``A`` (the model's
    :class:`SystemMatrix`, as assembled for the captured solve) under each filter of ``filters``: set-up and
    solve timed together as the integrator runs them (best of ``repeats``), its iterations and answer."""
    from implicit_cloth.solvers import make_preconditioner

    mass = np.repeat(model.masses, 3)
    out = {}
    for name in library:
        pname, cycle = series(LIBRARY[name])
        pc = make_preconditioner(pname, model, "numba")
        pc.cycle = cycle
        if name in UNWEIGHED:
            pc.masses = None
        for key, filt in filters.items():
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                pc.setup(model.system, filt)
                dv, res = filtered_pcg(A, b, z, filt, pc, tol, 2000, mass=mass, rule=pc.stopping_rule)
                if not res.converged and res.iterations < 2000 and pc.protect():   # as the integrator does
                    dv, res = filtered_pcg(A, b, z, filt, pc, tol, 2000, mass=mass, rule=pc.stopping_rule)
                best = min(best, time.perf_counter() - t0)
            out[(name, key)] = {"dv": dv.copy(), "iterations": res.iterations, "converged": res.converged,
                                "ms": 1e3 * best, "levels": pc.n_levels}
    return out


def capture(kind: str, n: int, step: int, fixed: bool = False, library: list[str] = (),
            tol: float = 1e-3) -> dict:
    """The linear system of step ``step`` of a default run (first solve for ``stiff``, last for the others;
    ``fixed``: one step a frame, no adaptive stepping), with the model's springs and the step's start positions;
    with ``library``, the library's own preconditioners' solves of it (:func:`library_solves`; the drape's also
    with its contact constraints removed)."""
    d = hanging_stiff(n, 1e4) if kind == "stiff" else peer_scene(kind, n, fixed=fixed)
    sim = ic.Simulator(ic.Scene.from_dict(d))
    integ = sim.integrator
    rec: list[dict] = []
    orig = integ._solve

    def spy(A, b, z, filt, info, guess=None, tolerance=None, **kw):
        # A is the model's SystemMatrix (finalized lazily): its CSR
        r = {"A": sp.csr_array(getattr(A, "csr", A), copy=True), "b": b.reshape(-1).copy(),
             "z": z.reshape(-1).copy(), "filt": Filter(filt.n, filt.fixed.copy(), filt.partial.copy(),
                                                        filt.partial_S.copy())}
        if library and (kind != "stiff" or not rec):     # stiff: its first solve only
            filters = {"": filt}
            if kind == "drape":
                filters["free"] = Filter(filt.n, np.zeros(0, dtype=np.int64))
            r["library"] = library_solves(sim.model, A, b.reshape(-1), z.reshape(-1), filters, tol, list(library))
        rec.append(r)
        return orig(A, b, z, filt, info, guess, tolerance, **kw)

    sim.step(step - 1)
    x = sim.state.x.copy()
    integ._solve = spy
    sim.step(1)
    r = rec[0] if kind == "stiff" else rec[-1]
    r.update(masses=sim.model.masses.copy(), grid=sim.model.geometry.grid_shape, kind=kind, n=n, step=step,
             solves_in_step=len(rec), x=x, springs=sim.model.springs, h=sim.dt)
    return r


def _bdiag(B: np.ndarray) -> sp.csr_array:
    n = len(B)
    return sp.csr_array(sp.bsr_matrix((B, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr())


def _diag_blocks(A) -> np.ndarray:
    A = sp.csr_array(A)
    n = A.shape[0] // 3
    i = np.arange(n) * 3
    return np.stack([np.stack([A[i + a, i + b] for b in range(3)], -1) for a in range(3)], -2)


def power_bound(A, D, iterations: int) -> float:
    """1.1 times a power-iteration estimate of the largest eigenvalue of ``D A`` (from a fixed random start)."""
    v = np.random.default_rng(0).standard_normal(A.shape[0])
    lam = 1.0
    for _ in range(iterations):
        v = D @ (A @ v)
        lam = float(np.linalg.norm(v))
        v /= lam
    return 1.1 * lam


def chebyshev(A, D, b: np.ndarray, x: np.ndarray | None, lmax: float, degree: int) -> np.ndarray:
    """``degree`` steps of the Chebyshev iteration for ``A x = b`` preconditioned by ``D``, on the interval
    ``[lmax / 30, lmax]``, from ``x`` (``None``: zero, whose first product is skipped)."""
    lmin = lmax / 30.0
    th, de = (lmax + lmin) / 2, (lmax - lmin) / 2
    sig = th / de
    rho = 1 / sig
    d = (D @ (b if x is None else b - A @ x)) / th
    x = np.zeros_like(b) if x is None else x
    for k in range(degree):
        x = x + d
        if k == degree - 1:
            break
        rho_new = 1 / (2 * sig - rho)
        d = rho_new * rho * d + 2 * rho_new / de * (D @ (b - A @ x))
        rho = rho_new
    return x


class VCycle:
    """The numpy V-cycle with the levers of the module docstring."""

    def __init__(self, A, filt: Filter, Ps: list, nu: int = 1, cycle: str = "V", smoother: str = "jacobi",
                 degree: int = 2, omega: float = 0.7, filtered_p: bool = False, weighed_p: bool = False,
                 masses: np.ndarray | None = None) -> None:
        S = _bdiag(filt.matrices())
        I3 = sp.identity(A.shape[0], format="csr")
        self.A = [sp.csr_array(S @ A @ S + (I3 - S))]
        self.P: list = []
        for l, P in enumerate(Ps):
            P3 = sp.csr_array(sp.kron(P, sp.identity(3), format="csr"))
            if l == 0 and weighed_p and masses is not None:    # the library's smoothed multigrid's weights
                Q = np.eye(3) - filt.matrices()
                P3 = sp.csr_array(_bdiag(filt.matrices() + np.sqrt(masses)[:, None, None] * Q) @ P3)
                C = P3.T @ self.A[-1] @ P3
            elif l == 0 and filtered_p:
                P3 = sp.csr_array(S @ P3)
                C = P3.T @ (S @ A @ S) @ P3
                d = np.abs(C.diagonal())        # directions no coarse function reaches: identity
                C = C + sp.diags(np.where(d < 1e-14 * max(d.max(), 1e-300), 1.0, 0.0))
            else:
                C = P3.T @ self.A[-1] @ P3
            self.P.append(P3)
            self.A.append(sp.csr_array(C))
        self.D = [_bdiag(inv3(_diag_blocks(Al))) for Al in self.A[:-1]]
        self.chol = sla.cho_factor(self.A[-1].toarray())
        self.nu, self.cycle, self.smoother, self.degree, self.omega = nu, cycle, smoother, degree, omega
        self.lmax = []
        if smoother == "chebyshev":
            self.lmax = [power_bound(Al, D, 15) for Al, D in zip(self.A[:-1], self.D)]

    def _smooth(self, l: int, b: np.ndarray, x: np.ndarray) -> np.ndarray:
        A, D = self.A[l], self.D[l]
        if self.smoother == "jacobi":
            for _ in range(self.nu):
                x = x + self.omega * (D @ (b - A @ x))
            return x
        return chebyshev(A, D, b, x, self.lmax[l], self.degree)

    def _vcycle(self, l: int, b: np.ndarray) -> np.ndarray:
        if l == len(self.A) - 1:
            return sla.cho_solve(self.chol, b)
        x = self._smooth(l, b, np.zeros_like(b))
        for _ in range(2 if self.cycle == "W" and l < len(self.A) - 2 else 1):
            x = x + self.P[l] @ self._vcycle(l + 1, self.P[l].T @ (b - self.A[l] @ x))
        return self._smooth(l, b, x)

    def apply(self, r: np.ndarray) -> np.ndarray:
        return self._vcycle(0, r)

    def passes(self) -> float:
        """Fine-level matrix passes per CG iteration (CG's product + the V-cycle's, coarse levels by share)."""
        per = 2 * self.nu if self.smoother == "jacobi" else 2 * self.degree   # pre + post, residuals included
        share = [Al.nnz / self.A[0].nnz for Al in self.A[:-1]]
        visits = [(2 ** l if self.cycle == "W" else 1) for l in range(len(share))]
        return 1.0 + per * sum(s * v for s, v in zip(share, visits))


def rigid_modes(x: np.ndarray) -> np.ndarray:
    """The six rigid motions of the cloth at positions ``x`` (N, 3), columns of a (3N, 6) array."""
    c = x - x.mean(axis=0)
    B = np.zeros((3 * len(x), 6))
    for a in range(3):
        B[a::3, a] = 1.0
    B[1::3, 3], B[2::3, 3] = -c[:, 2], c[:, 1]     # rotations e_k x c
    B[0::3, 4], B[2::3, 4] = c[:, 2], -c[:, 0]
    B[0::3, 5], B[1::3, 5] = -c[:, 1], c[:, 0]
    return B


class SmoothedAggregation:
    """pyamg's smoothed aggregation of ``S A S + (I - S)`` (3x3 blocks) with the rigid motions at the step's
    positions as near-null space, its default V-cycle (symmetric block Gauss-Seidel) as the preconditioner.
    Rebuilt from scratch for every system: its setup (``setup_s``) is a full pyamg setup in Python."""

    def __init__(self, A, filt: Filter, x: np.ndarray) -> None:
        import pyamg

        S = _bdiag(filt.matrices())
        K = sp.bsr_matrix(S @ A @ S + (sp.identity(A.shape[0], format="csr") - S), blocksize=(3, 3))
        t0 = time.perf_counter()
        self.ml = pyamg.smoothed_aggregation_solver(K, B=rigid_modes(x), max_coarse=100)
        self.setup_s = time.perf_counter() - t0
        self.M = self.ml.aspreconditioner(cycle="V")

    def apply(self, r: np.ndarray) -> np.ndarray:
        return np.asarray(self.M @ r)

    def passes(self) -> float:
        """CG's product + per level a symmetric Gauss-Seidel sweep (2 passes) before and after and a residual."""
        nnz = [lv.A.nnz for lv in self.ml.levels[:-1]]
        return 1.0 + 5.0 * sum(n / nnz[0] for n in nnz)


def direct(A, b: np.ndarray, z: np.ndarray, filt: Filter) -> np.ndarray:
    """The exact filtered solution: ``(I - S) dv = (I - S) z``, ``S (A dv - b) = 0``."""
    S = _bdiag(filt.matrices())
    zc = z - filt.apply(z.copy())
    K = sp.csc_matrix(S @ A @ S + (sp.identity(A.shape[0]) - S))
    return zc + S @ spla.spsolve(K, S @ (b - A @ zc))


def solve_all(sysd: dict, levers: list[str], tol: float, label: str, key: str = "") -> list[dict]:
    A, b, z, filt = sysd["A"], sysd["b"], sysd["z"], sysd["filt"]
    Ps = grid_prolongations(*sysd["grid"])
    ref = direct(A, b, z, filt)
    rows = []
    for name in levers:
        if name in LIBRARY:
            lib = sysd["library"][(name, key)]
            row = {"system": label, "n": sysd["n"], "lever": name, "iterations": lib["iterations"],
                   "true_error": float(np.linalg.norm(lib["dv"] - ref) / np.linalg.norm(ref)),
                   "converged": lib["converged"], "ms": lib["ms"], "levels": lib["levels"],
                   "constrained": int(len(filt.fixed) + len(filt.partial))}
            rows.append(row)
            print(f"{label:16s} {sysd['n']:4d}² {name:11s} its {row['iterations']:4d}  true err "
                  f"{row['true_error']:.1e}  {row['ms']:.2f} ms (compiled: set-up and solve)", flush=True)
            continue
        t0 = time.perf_counter()
        try:
            pc = (SmoothedAggregation(A, filt, sysd["x"]) if name == "sa_rigid"
                  else VCycle(A, filt, Ps, masses=sysd["masses"], **LEVERS[name]))
            dv, res = filtered_pcg(A, b, z, filt, pc, tol, 2000, mass=np.repeat(sysd["masses"], 3), compiled=False)
        except (ValueError, np.linalg.LinAlgError, sla.LinAlgError) as e:   # a row, not a crash (NaN in a V-cycle)
            print(f"{label:16s} {sysd['n']:4d}² {name:11s} failed: {type(e).__name__}: {e}", flush=True)
            rows.append({"system": label, "n": sysd["n"], "lever": name, "iterations": None, "true_error": None,
                         "converged": False, "failed": f"{type(e).__name__}: {e}", "passes": None,
                         "constrained": int(len(filt.fixed) + len(filt.partial)), "numpy_s": time.perf_counter() - t0})
            continue
        row = {"system": label, "n": sysd["n"], "lever": name, "iterations": res.iterations,
               "true_error": float(np.linalg.norm(dv - ref) / np.linalg.norm(ref)), "converged": res.converged,
               "passes_per_iteration": pc.passes(), "constrained": int(len(filt.fixed) + len(filt.partial)),
               "numpy_s": time.perf_counter() - t0, "setup_s": getattr(pc, "setup_s", None)}
        row["passes"] = row["passes_per_iteration"] * row["iterations"]
        rows.append(row)
        print(f"{label:16s} {sysd['n']:4d}² {name:11s} its {res.iterations:4d}  true err {row['true_error']:.1e}  "
              f"{row['passes_per_iteration']:.2f} passes/it = {row['passes']:.0f}  (constrained {row['constrained']})",
              flush=True)
    return rows


def markdown(res: dict) -> str:
    out = [f"Iterations / true error of dv / fine-level matrix passes of the whole solve, tolerance {res['tolerance']:g}; "
           f"the library's own preconditioners (`lib_*`: compiled, "
           f"{res.get('threads', 1)} thread(s)) give their set-up and solve's ms (best of 3) instead of passes.",
           ""]
    for label in dict.fromkeys(r["system"] for r in res["rows"]):
        rows = [r for r in res["rows"] if r["system"] == label]
        sizes = sorted({r["n"] for r in rows})
        out += [f"**{label}**", "", "| lever | " + " | ".join(f"{n}²" for n in sizes) + " |",
                "|---|" + "---|" * len(sizes)]
        for lever in dict.fromkeys(r["lever"] for r in rows):
            cells = []
            for n in sizes:
                r = next((r for r in rows if r["n"] == n and r["lever"] == lever), None)
                cells.append("-" if r is None else "failed" if r.get("failed") else
                             f"{r['iterations']} / {r['true_error']:.1e} / **{r['ms']:.1f} ms**" if "ms" in r else
                             f"{r['iterations']} / {r['true_error']:.1e} / {r['passes']:.0f}")
            out.append(f"| {lever} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    p.add_argument("--systems", nargs="+", default=["stiff", "hanging", "drape"], choices=["stiff", "hanging", "drape"])
    p.add_argument("--levers", nargs="+", default=list(LEVERS) + list(LIBRARY), choices=list(LEVERS) + list(LIBRARY))
    p.add_argument("--threads", type=int, default=1, help="threads of the library's compiled solves (lib_*)")
    p.add_argument("--tolerance", type=float, default=1e-3)
    p.add_argument("--stiff-step", type=int, default=21)
    p.add_argument("--peer-step", type=int, default=120)
    p.add_argument("--out", default=default_out('solver_choice'), help="output folder (default out/bench/solver_choice)")
    a = p.parse_args(argv)
    library = [x for x in a.levers if x in LIBRARY]
    if library:
        from implicit_cloth import backend

        backend.set_threads(a.threads)
    rows = []
    for kind in a.systems:
        for n in a.sizes:
            sysd = capture(kind, n, a.stiff_step if kind == "stiff" else a.peer_step, library=library,
                           tol=a.tolerance)
            label = {"stiff": "stiff hanging (k = 1e4)", "hanging": "hanging (k = 1e3)", "drape": "drape, at rest"}[kind]
            rows += solve_all(sysd, a.levers, a.tolerance, label)
            if kind == "drape":
                free = dict(sysd, filt=Filter(sysd["filt"].n, np.zeros(0, dtype=np.int64)))
                rows += solve_all(free, ["jacobi"] + library, a.tolerance, "drape, constraints removed", key="free")
    res = {"benchmark": "solver_choice", "sizes": a.sizes, "tolerance": a.tolerance, "rows": rows,
           "machine": machine(), "threads": a.threads}
    md = markdown(res)
    write_outputs(Path(a.out), "solver_choice", res, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
