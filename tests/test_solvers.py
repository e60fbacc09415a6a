"""Every solver path against a direct sparse solve: the tolerance is the true relative error of dv."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh

import implicit_cloth as ic
from implicit_cloth import cloth
from implicit_cloth.backend import BackendMismatch
from implicit_cloth.solvers import Filter, filtered_pcg, make_preconditioner, numba_available
from implicit_cloth.solvers.multigrid import Multigrid, grid_prolongations

#: every multigrid test runs on both paths: numpy (reference, fallback) and the numba accelerator
NUMBA = pytest.param("numba", marks=pytest.mark.skipif(not numba_available(), reason="numba not installed"))
ACCELERATORS = ["numpy", NUMBA]

H = 1 / 60


def _scene(res=(24, 24), k=1e4, mesh=None):
    c = {"mass": 0.1, "pins": [0, 5] if mesh else ["top_left", "top_right"],
         "springs": {"structural": {"stiffness": k, "damping": 0.1},
                     "shear": {"stiffness": k, "damping": 0.1},
                     "bend": {"stiffness": k / 100, "damping": 0.01}}}
    if mesh:
        c["mesh"] = mesh
        del c["springs"]["shear"]
    else:
        c.update(size=[1.0, 1.0], resolution=list(res), plane="xy")
    return {"cloth": c, "effects": {"gravity": [0, 0, -9.81], "drag": 0.1}}


def _mesh_file(tmp_path):
    g = cloth.grid((1.0, 1.0), (20, 20), plane="xy")
    rng = np.random.default_rng(5)
    pos = g.positions + 0.2 / 19 * rng.uniform(-1, 1, g.positions.shape) * [1, 1, 0]   # irregular triangles
    path = tmp_path / "cloth.obj"
    trimesh.Trimesh(pos, g.faces, process=False).export(path)
    return str(path)


def _system(sim, steps=8):
    """A mid-swing system A dv = b with its exact constrained solution (direct solve on free coordinates)."""
    sim.step(steps)
    m = sim.model
    x, v = sim.positions, sim.velocities
    A, f0, kv = m.linearize(x, v, sim.time, H * H, H, w=v)
    A = A.copy()
    b = (H * (f0 + H * kv)).ravel()
    return m, A, b


def _direct(A, b, z, filt):
    """Exact solution with (I-S) dv = (I-S) z, for any filter (fixed vertices, constraints along any
    directions): ``dv = zc + T y`` with ``(T^T A T) y = T^T (b - A zc)``, ``zc = (I - S) z`` and ``T``'s columns
    each vertex's eigenvectors of ``S_i`` with eigenvalue 1 (the filter's range)."""
    S = filt.matrices()
    n = len(S)
    zc = z - np.einsum("nij,nj->ni", S, z.reshape(-1, 3)).ravel()
    w, V = np.linalg.eigh(S)
    keep = (w > 0.5).ravel()
    cols = V.transpose(0, 2, 1).reshape(-1, 3)[keep]                # the kept eigenvectors, one a row
    rows = np.broadcast_to(np.arange(3 * n).reshape(-1, 1, 3), (n, 3, 3)).reshape(-1, 3)[keep]
    T = sp.csr_array((cols.ravel(), (rows.ravel(), np.repeat(np.arange(len(cols)), 3))), shape=(3 * n, len(cols)))
    y = spla.spsolve(sp.csc_matrix(T.T @ A @ T), T.T @ (b - A @ zc))
    return zc + T @ y


def _constraints(m, b, seed):
    """Prescribed changes ``z`` (random) and a filter: the pins plus two vertices constrained along coordinate
    axes (one and two directions); returns ``(z, filt, partial)``."""
    z = np.random.default_rng(seed).standard_normal(b.shape) * 0.01
    partial = np.array([m.n // 2, m.n // 3])
    PS = np.stack([np.diag([1.0, 1.0, 0.0]), np.diag([1.0, 0.0, 0.0])])
    return z, Filter(m.n, m.pinned, partial, PS), partial


def _check_against_direct(m, A, b, z, filt, partial, pc, tol):
    """The filtered PCG with ``pc`` converges within ``tol`` of the direct solve, its constrained components
    exactly the prescribed ones."""
    dv, res = filtered_pcg(A, b, z, filt, pc, tol=tol, max_iterations=5000,
                           mass=np.repeat(m.masses, 3), rule=pc.stopping_rule)
    ref = _direct(A, b, z, filt)
    assert res.converged
    assert np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= tol
    d3, z3 = dv.reshape(-1, 3), z.reshape(-1, 3)
    assert np.array_equal(d3[m.pinned], z3[m.pinned])               # constrained: exact, not approximate
    assert d3[partial[0], 2] == z3[partial[0], 2]
    assert np.array_equal(d3[partial[1], 1:], z3[partial[1], 1:])


@pytest.mark.parametrize("kind", ["grid", "mesh"])
@pytest.mark.parametrize("preconditioner, accelerator",
                         [("multigrid", "numpy"), pytest.param("multigrid", "numba", marks=NUMBA.marks),
                          ("block_jacobi", "numpy")])
@pytest.mark.parametrize("tol", [1e-2, 1e-4])
def test_solver_matches_direct_solve_within_tolerance(tmp_path, kind, preconditioner, accelerator, tol):
    scene = _scene(mesh=_mesh_file(tmp_path) if kind == "mesh" else None)
    sim = ic.Simulator(scene, dt=H, solver={"preconditioner": preconditioner})
    m, A, b = _system(sim)
    z, filt, partial = _constraints(m, b, seed=0)
    pc = make_preconditioner(preconditioner, m, accelerator)
    pc.setup(m.system, filt)
    if accelerator == "numba":   # the system's own matrix, unchanged since setup: the whole PCG runs compiled
        A = m.system.csr
        assert pc.fused_pcg(A, b, z, filt) is not None
        with pytest.raises(BackendMismatch, match="A is not the fine system's own matrix"):
            pc.fused_pcg(A.copy(), b, z, filt)           # never a silent numpy solve
        with pytest.raises(BackendMismatch, match="filter is not the one of the last setup"):
            filtered_pcg(A, b, z, Filter(m.n, m.pinned), pc)
    _check_against_direct(m, A, b, z, filt, partial, pc, tol)


@pytest.mark.parametrize("preconditioner", ["multigrid", "multigrid_smoothed"])
@pytest.mark.parametrize("accelerator", ACCELERATORS)
def test_deep_hierarchy_of_a_larger_grid_matches_direct_solve(preconditioner, accelerator):
    """From COARSEST_FROM vertices the grid is coarsened to a coarsest level of at most COARSEST_VERTICES (one
    level more than before, a small dense factor): still a solve within tolerance of the direct one, the
    constrained components exact; smaller grids keep their coarsest level of up to DIRECT_VERTICES."""
    from implicit_cloth.solvers.multigrid import COARSEST_FROM, COARSEST_VERTICES, DIRECT_VERTICES

    shapes = [P.shape for P in grid_prolongations(33, 32)]
    assert 33 * 32 >= COARSEST_FROM and shapes[-1][1] <= COARSEST_VERTICES < shapes[-2][1]
    small = grid_prolongations(31, 31)
    assert 31 * 31 < COARSEST_FROM and COARSEST_VERTICES < small[-1].shape[1] <= DIRECT_VERTICES
    assert grid_prolongations(10, 10) == []
    sim = ic.Simulator(_scene(res=(33, 32)), dt=H, solver={"preconditioner": preconditioner})
    m, A, b = _system(sim, steps=4)
    z, filt, partial = _constraints(m, b, seed=1)
    pc = make_preconditioner(preconditioner, m, accelerator)
    assert pc.n_levels == len(shapes) + 1
    pc.setup(m.system, filt)
    if accelerator == "numba":
        A = m.system.csr
    _check_against_direct(m, A, b, z, filt, partial, pc, 1e-4)


def test_multigrid_levels_and_galerkin_products():
    sim = ic.Simulator(_scene(res=(33, 20)), dt=H)
    m, A, _ = _system(sim, steps=2)
    mg = make_preconditioner("multigrid", m, "numpy")
    assert isinstance(mg, Multigrid) and mg.n_levels >= 3
    mg.setup(None, Filter(m.n, np.zeros(0, dtype=int)))
    for lvl, (Af, Ac) in zip(mg.levels, zip(mg._A[:-1], mg._A[1:])):
        ref = (lvl.P3.T @ Af @ lvl.P3).toarray()
        assert np.allclose(Ac.toarray(), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    # bilinear prolongation reproduces linear fields exactly
    P = grid_prolongations(33, 20)[0]
    ii, jj = np.meshgrid(np.arange(33), np.arange(20))
    coarse = grid_prolongations(33, 20)[0].T @ np.zeros(33 * 20)
    xc = np.array([i for i in range(0, 33, 2)], dtype=float)
    yc = np.array(list(range(0, 20, 2)) + [19], dtype=float)
    XC, YC = np.meshgrid(xc, yc)
    f = 2.0 * XC.ravel() - 3.0 * YC.ravel() + 1.0
    assert np.allclose(P @ f, 2.0 * ii.ravel() - 3.0 * jj.ravel() + 1.0)
    assert coarse.shape == (len(xc) * len(yc),)


@pytest.mark.parametrize("accelerator", ACCELERATORS)
def test_stale_preconditioner_still_converges(accelerator):
    """A preconditioner set up one step earlier is a worse one (hence the per-step refresh), never a wrong answer:
    on the numpy back-end it still converges; the compiled PCG, which multiplies by the blocks packed at setup,
    refuses it (BackendMismatch) instead of solving another matrix."""
    sim = ic.Simulator(_scene(), dt=H)
    m, A_old, _ = _system(sim, steps=5)
    filt = Filter(m.n, m.pinned)
    stale = make_preconditioner("multigrid", m, accelerator)
    stale.setup(None, filt)                        # from the step-5 matrix
    m, A, b = _system(sim, steps=1)                # the shared pattern now holds the step-6 values
    fresh = make_preconditioner("multigrid", m, accelerator)
    fresh.setup(None, filt)
    assert not np.allclose(A.data, A_old.data)
    ref = _direct(A, b, np.zeros_like(b), filt)
    its = {}
    if accelerator == "numba":                     # the compiled CG takes the system's own matrix only
        with pytest.raises(BackendMismatch, match="assembled again after the preconditioner's setup"):
            filtered_pcg(m.system.csr, b, np.zeros_like(b), filt, stale, tol=1e-4, max_iterations=3000)
        dv, res = filtered_pcg(m.system.csr, b, np.zeros_like(b), filt, fresh, tol=1e-4, max_iterations=3000)
        assert res.converged and np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= 1e-4
        return
    for name, p in (("stale", stale), ("fresh", fresh)):
        dv, res = filtered_pcg(A, b, np.zeros_like(b), filt, p, tol=1e-4, max_iterations=3000)
        assert res.converged, name
        assert np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= 1e-4, name
        its[name] = res.iterations
    assert its["stale"] > its["fresh"]


def test_default_trajectory_within_one_percent_of_tight_run():
    scene = _scene(res=(16, 16))
    tight = ic.Simulator(scene, dt=H, solver={"tolerance": 1e-8}).run(duration=1.0)
    default = ic.Simulator(scene, dt=H).run(duration=1.0)
    assert default.report["solver"]["tolerance"] == ic.Scene.from_dict(scene).data["solver"]["tolerance"]
    displacement = np.linalg.norm(tight.positions - tight.positions[0], axis=2).max()
    deviation = np.linalg.norm(default.positions - tight.positions, axis=2).max()
    assert deviation <= 0.01 * displacement


def test_coarse_cholesky_shifts_only_a_numerically_indefinite_matrix():
    """An SPD coarse matrix is factorised as is; one whose small eigenvalues round-off made negative (a spring
    chain at k h^2 / m = 1e20) gets the smallest tenfold shift that factorises, stays SPD and still solves
    its stiff modes; a non-finite matrix is not factorised (NaN shift) and propagates NaN."""
    import scipy.linalg as sla

    from implicit_cloth.solvers.multigrid import coarse_cholesky

    rng = np.random.default_rng(0)
    n = 30
    Q = rng.standard_normal((n, n))
    spd = Q @ Q.T + n * np.eye(n)
    fac, tau = coarse_cholesky(spd)
    b = rng.standard_normal(n)
    assert tau == 0.0
    assert np.allclose(sla.cho_solve(fac, b), np.linalg.solve(spd, b), rtol=1e-10, atol=0)

    # 1-D chain Laplacian (rigid mode) times 1e20 plus a unit mass: exact eigenvalues >= 1, numerically < 0
    L = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    L[0, 0] = L[-1, -1] = 1.0
    C = 1e20 * L + np.eye(n)
    with pytest.raises(np.linalg.LinAlgError):
        sla.cho_factor(C, check_finite=False)
    fac, tau = coarse_cholesky(C)
    assert 0 < tau < 1e-10 * 2e20                     # a shift of the order of round-off, not of the matrix
    Pinv = sla.cho_solve(fac, np.eye(n))
    assert np.linalg.eigvalsh(0.5 * (Pinv + Pinv.T)).min() > 0        # SPD preconditioner

    bad = spd.copy()
    bad[3, 4] = np.inf
    fac, tau = coarse_cholesky(bad)
    assert np.isnan(tau)
    assert np.all(np.isnan(sla.cho_solve(fac, b) * np.nan))


@pytest.mark.parametrize("k", [1e20, 1e22])
def test_multigrid_preconditioner_stays_spd_at_extreme_stiffness(k):
    """k h^2 / m_i = 1.6e18 .. 1.6e20 on a 4x4 cloth (coarsest level = the whole system): setup no longer raises, the
    shift is reported, and the V-cycle is a symmetric positive definite operator (CG's requirement)."""
    scene = {"cloth": {"resolution": [4, 4], "mass": 0.1, "pins": ["top_left"],   # rotations about the pin:
                       "springs": {"structural": {"stiffness": k}}}}              # zero modes of the stiffness
    sim = ic.Simulator(scene, integrator="backward_euler", dt=0.01)
    integ = sim.integrator
    integ.model.linearize(sim.positions, sim.velocities, 0.0, 1e-4, 1e-2)
    integ.precond.setup(integ.model.system, Filter(sim.model.n, sim.model.pinned))
    assert integ.precond.coarse_shift > 0
    n3 = 3 * sim.model.n
    P = np.column_stack([integ.precond.apply(e) for e in np.eye(n3)])
    free = np.flatnonzero(np.repeat(sim.model.free, 3))
    Pf = P[np.ix_(free, free)]
    assert np.allclose(Pf, Pf.T, rtol=1e-8, atol=1e-12 * np.abs(Pf).max())
    assert np.linalg.eigvalsh(0.5 * (Pf + Pf.T)).min() > 0


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_numba_path_is_the_numpy_iteration():
    """The compiled PCG and V-cycle do the reference's arithmetic: same iterations, same dv to round-off,
    the same coarse matrices; on a tiny cloth (one level, solved directly) too."""
    for res in ((33, 20), (8, 8)):
        sim = ic.Simulator(_scene(res=res), dt=H)
        m, A, b = _system(sim, steps=3)
        z = np.random.default_rng(1).standard_normal(b.shape) * 0.01
        filt = Filter(m.n, m.pinned, np.array([m.n // 2]), np.diag([1.0, 0.0, 1.0])[None])
        out = {}
        for acc in ("numpy", "numba"):
            mg = make_preconditioner("multigrid", m, acc)
            mg.setup(None, filt)
            r = filt.apply(np.random.default_rng(2).standard_normal(b.shape))
            out[acc] = (mg, mg.apply(r), *filtered_pcg(m.system.csr, b, z, filt, mg, tol=1e-6,
                                                        mass=np.repeat(m.masses, 3)))
        (mg0, v0, dv0, r0), (mg1, v1, dv1, r1) = out["numpy"], out["numba"]
        assert mg1.accelerator == "numba" and mg0.accelerator == "numpy"
        assert np.allclose(v1, v0, rtol=1e-10, atol=1e-12 * np.abs(v0).max())
        assert r1.iterations == r0.iterations and r1.converged
        assert np.allclose(dv1, dv0, rtol=1e-9, atol=1e-12 * np.abs(dv0).max())
        fh = mg1.engine                        # the compiled path keeps diagonal + upper blocks, packed
        for li, l0 in enumerate(mg0.levels, start=1):
            ref = l0.system.blocks
            packed = np.concatenate([fh.dg[fh.voff[li]:fh.voff[li + 1]], fh.uv[fh.uoff[li]:fh.uoff[li + 1]]])
            want = np.concatenate([ref[l0.system.diag_index], ref[fh._uidx[li]]])
            assert np.allclose(packed, want, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
            lower = l0.system.block_rows > l0.system.block_cols      # what the packing leaves out: transposes
            up = l0.system.block_index(l0.system.block_cols[lower], l0.system.block_rows[lower])
            assert np.allclose(ref[lower], ref[up].transpose(0, 2, 1), atol=1e-12 * np.abs(ref).max())
    with pytest.raises(ValueError, match="accelerator: unknown accelerator.*'fortran'"):
        make_preconditioner("multigrid", m, "fortran")


def test_accelerator_falls_back_to_numpy_without_numba(monkeypatch):
    from implicit_cloth import backend as accel

    monkeypatch.setattr(accel, "numba_available", lambda: False)
    assert accel.resolve("auto") == "numpy" and accel.resolve("numpy") == "numpy"
    with pytest.raises(ValueError, match="numba is not installed"):
        accel.resolve("numba")
    monkeypatch.setenv("IMPLICIT_CLOTH_ACCELERATOR", "gpu")
    with pytest.raises(ValueError, match="IMPLICIT_CLOTH_ACCELERATOR: unknown accelerator.*'gpu'"):
        accel.resolve()
    monkeypatch.setenv("IMPLICIT_CLOTH_ACCELERATOR", "numpy")
    sim = ic.Simulator(_scene(res=(12, 12)), dt=H)
    assert sim.integrator.precond.accelerator == "numpy"


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_backward_euler_steps_agree_between_paths(monkeypatch):
    """A few whole steps (assembly, refresh, solve) on each path land on the same state."""
    runs = {}
    for acc in ("numpy", "numba"):
        monkeypatch.setenv("IMPLICIT_CLOTH_ACCELERATOR", acc)
        sim = ic.Simulator(_scene(res=(20, 20)), dt=H, solver={"tolerance": 1e-8})
        assert sim.integrator.precond.accelerator == acc
        sim.step(5)
        runs[acc] = (sim.positions.copy(), sim.last_step.iterations)
    (x0, i0), (x1, i1) = runs["numpy"], runs["numba"]
    assert i0 == i1
    assert np.abs(x1 - x0).max() <= 1e-9


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
@pytest.mark.parametrize("tol", [1e-3, 1e-6])
def test_numba_float32_vcycle_matches_direct_solve(monkeypatch, tol):
    """Large cloths run the compiled V-cycle on float32 matrices: still dv within the tolerance, pins exact."""
    from implicit_cloth.solvers import multigrid

    monkeypatch.setattr(multigrid, "FLOAT32_MIN_VERTICES", 0)
    sim = ic.Simulator(_scene(), dt=H)
    m, A, b = _system(sim)
    z = np.random.default_rng(3).standard_normal(b.shape) * 0.01
    filt = Filter(m.n, m.pinned, np.array([m.n // 2]), np.diag([1.0, 1.0, 0.0])[None])
    mg = make_preconditioner("multigrid", m, "numba")
    mg.setup(None, filt)
    assert mg.engine.uv.dtype == np.float32 and mg.engine.auv.dtype == np.float64
    # the fine spring blocks' six-number copy too: CG's in float64, the V-cycle's in float32
    assert mg.engine.use6 and mg.engine.au6.dtype == np.float64 and mg.engine.vu6.dtype == np.float32
    dv, res = filtered_pcg(m.system.csr, b, z, filt, mg, tol=tol, mass=np.repeat(m.masses, 3))
    ref = _direct(A, b, z, filt)
    assert res.converged and np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= tol
    d3, z3 = dv.reshape(-1, 3), z.reshape(-1, 3)
    assert np.array_equal(d3[m.pinned], z3[m.pinned]) and d3[m.n // 2, 2] == z3[m.n // 2, 2]
    # the smoothed multigrid keeps float64 at every size (its float32 levels broke down on a 256² drape)
    sm = make_preconditioner("multigrid_smoothed", m, "numba")
    sm.setup(None, filt)
    assert sm.engine.precond_dtype == np.float64 and sm.engine.uv.dtype == np.float64
    assert sm.engine.vu6.dtype == np.float64


def test_run_report_names_the_accelerator_that_ran():
    from implicit_cloth.solvers import set_default_accelerator

    scene = {"cloth": {"resolution": [6, 6], "mass": 0.1, "pins": ["top_left"],
                       "springs": {"structural": {"stiffness": 100.0}}},
             "simulation": {"dt": 0.01, "duration": 0.03}}
    try:
        for acc in ("numpy",) + (("numba",) if numba_available() else ()):
            set_default_accelerator(acc)
            assert ic.Simulator(scene).run().report["solver"]["accelerator"] == acc
        set_default_accelerator("numpy")
        assert ic.Simulator(scene, solver={"preconditioner": "block_jacobi"}).run().report["solver"][
            "accelerator"] == "numpy"
    finally:
        set_default_accelerator(None)


# --------------------------------------------------------------------------- the stopping rule's error estimate
def _estimators():
    from implicit_cloth.solvers import pcg

    out = [pytest.param(pcg.current_error_estimate, id="numpy")]
    if numba_available():
        from implicit_cloth.kernels import pcg as _fused

        out.append(pytest.param(_fused.error_estimate, id="numba"))
    return out


def _delayed_estimate(ad, pw, it, dd, d):
    """Strakos-Tichy: the error of the iterate d back, |e_{k-d}|^2 ~ sum_j pw_j (|e_j|_A^2 + |e_{j+1}|_A^2)."""
    eA = np.cumsum(ad[it - d:it][::-1])[::-1]
    return np.sqrt(pw[it - d:it] @ (eA + np.append(eA[1:], 0.0)) / dd)


@pytest.mark.parametrize("estimate", _estimators())
def test_error_estimate_extrapolates_steady_convergence_and_falls_back_on_stagnation(estimate):
    """For CG converging at a steady rate (alpha_j delta_j = a q^j, |p_j|^2 / p_j^T A p_j = c) the error of the
    current iterate is |e_k|^2 = sum_{j>=k} c (|e_j|_A^2 + |e_{j+1}|_A^2) = c a q^k (1 + q) / (1 - q)^2: the
    estimate is that times the documented safety factor. When the window shows no convergence (flat or growing
    alpha delta, over the whole window or only its last half) it falls back to the delayed estimate."""
    from implicit_cloth.solvers.pcg import ESTIMATE_SAFETY

    a, c, q, dd = 2.0, 300.0, 0.6, 4.0
    j = np.arange(60)
    pw = np.full(60, c)
    for it, d in ((12, 4), (40, 10), (60, 15)):
        exact = np.sqrt(c * a * q**it * (1 + q) / (1 - q) ** 2 / dd)
        assert estimate(a * q**j, pw, it, dd, d) == pytest.approx(ESTIMATE_SAFETY * exact, rel=1e-10)
    rng = np.random.default_rng(0)
    pw = rng.uniform(100, 600, 60)
    slowdown = np.concatenate([1e-2 * 0.5 ** j[:24], np.full(36, 1e-2 * 0.5**24)])
    for ad in (np.full(60, 1e-3), 1e-3 * 1.05**j, slowdown):
        for it, d in ((30, 7), (29, 7)):
            est = estimate(ad, pw, it, dd, d)
            assert est == pytest.approx(_delayed_estimate(ad, pw, it, dd, d), rel=1e-12)


def test_stopping_rule_is_not_needlessly_conservative():
    """At tol 1e-3 on a stiff 24² cloth the answer is within tol of a direct solve but not far more accurate than
    asked: above tol / 8 (the rule estimating the error of the iterate d steps back returned tol / 25 - tol / 17
    on these systems). The numpy and numba paths stop at the same iteration."""
    sim = ic.Simulator(_scene(), dt=H)
    tol = 1e-3
    for steps in (8, 4, 4):
        m, A, b = _system(sim, steps)
        filt = Filter(m.n, m.pinned)
        z = np.zeros_like(b)
        ref = _direct(A, b, z, filt)
        its = set()
        for acc in ("numpy",) + (("numba",) if numba_available() else ()):
            pc = make_preconditioner("multigrid", m, acc)
            pc.setup(m.system, filt)
            dv, res = filtered_pcg(m.system.csr, b, z, filt, pc, tol=tol, mass=np.repeat(m.masses, 3))
            err = np.linalg.norm(dv - ref) / np.linalg.norm(ref)
            assert res.converged and tol / 8 < err <= tol, (steps, acc, err / tol)
            its.add(res.iterations)
        assert len(its) == 1, its


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_numba_fine_blocks_need_not_be_symmetric_themselves():
    """The compiled path reads spring blocks from their six distinct numbers only while every fine upper block
    is exactly symmetric; a symmetric matrix whose off-diagonal blocks are not (A_ji = A_ij^T != A_ij) falls
    back to all nine and still solves to the tolerance."""
    sim = ic.Simulator(_scene(res=(16, 16)), dt=H)
    m, _, b = _system(sim, steps=3)
    sm = m.system
    mg = make_preconditioner("multigrid", m, "numba")
    filt = Filter(m.n, m.pinned)
    mg.setup(None, filt)
    assert mg.engine.use6                        # springs: alpha I + beta u u^T, exactly symmetric
    i, j = sm.block_rows, sm.block_cols
    up = np.flatnonzero(i < j)[::7]              # skew some blocks, keeping the matrix symmetric
    skew = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]) * 1e-3 * np.abs(sm.blocks).max()
    sm.blocks[up] += skew
    sm.blocks[sm.block_index(j[up], i[up])] += skew.T
    A = sm.finalize()
    assert abs(A - A.T).max() == 0.0
    mg.setup(None, filt)
    assert not mg.engine.use6
    z = np.zeros_like(b)
    dv, res = filtered_pcg(A, b, z, filt, mg, tol=1e-6)
    ref = _direct(A, b, z, filt)
    assert res.converged and np.linalg.norm(dv - ref) <= 1e-6 * np.linalg.norm(ref)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
@pytest.mark.parametrize("vcycle", ["float64", "float32", "chunked sums"])
def test_threads_give_the_same_numbers_and_match_a_direct_solve(monkeypatch, vcycle):
    """The threaded passes (every level threaded here) give the serial numbers to the last bit, for 1 and 2
    threads, with pins and contact-like filters (sliding along a tilted normal, sticking); dv within the
    tolerance of a direct solve, constrained components exact. Whole steps agree as well. Both with the
    float64 V-cycle and with the float32 one of large cloths, and with CG's dot products summed by chunks
    (large cloths: on threads, the same numbers at every thread count)."""
    from implicit_cloth import backend
    from implicit_cloth.solvers import multigrid

    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES", 0)
    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES_OTHER_LAYERS", 0)
    monkeypatch.setattr(multigrid, "FLOAT32_MIN_VERTICES", 0 if vcycle == "float32" else None)
    monkeypatch.setattr(multigrid, "CHUNKED_SUMS_MIN_VERTICES", 0 if vcycle == "chunked sums" else 10**9)
    sim = ic.Simulator(_scene(res=(30, 27)), dt=H)
    m, A, b = _system(sim, steps=4)
    z = np.random.default_rng(4).standard_normal(b.shape) * 0.01
    nrm = np.array([0.3, -0.2, 0.93])
    nrm /= np.linalg.norm(nrm)
    slide = np.arange(100, 160)                                   # sliding: S = I - n n^T
    stick = np.arange(400, 420)                                   # sticking: S = 0
    PS = np.concatenate([np.broadcast_to(np.eye(3) - np.outer(nrm, nrm), (len(slide), 3, 3)),
                         np.zeros((len(stick), 3, 3))])
    filt = Filter(m.n, m.pinned, np.concatenate([slide, stick]), PS)
    out = {}
    try:
        for th in (1, 2, 1):
            backend.set_threads(th)
            mg = make_preconditioner("multigrid", m, "numba")
            mg.setup(None, filt)
            assert mg.engine.lpar.all() and mg.engine.vu6.dtype == np.dtype(vcycle if vcycle != "chunked sums"
                                                                            else "float64")
            assert len(mg.engine.sum_chunks) == (9 if vcycle == "chunked sums" else 0)
            r = filt.apply(np.random.default_rng(2).standard_normal(b.shape))
            v = mg.apply(r)
            dv, res = filtered_pcg(m.system.csr, b, z, filt, mg, tol=1e-4, mass=np.repeat(m.masses, 3))
            out.setdefault(th, []).append((v, dv, res.iterations))
        for (v1, dv1, i1), (v2, dv2, i2) in ((out[1][0], out[2][0]), (out[1][0], out[1][1])):
            assert np.array_equal(v1, v2) and np.array_equal(dv1, dv2) and i1 == i2
        S = filt.matrices()
        zc = z - np.einsum("nij,nj->ni", S, z.reshape(-1, 3)).ravel()
        dv = out[2][0][1]
        assert np.allclose(dv - np.einsum("nij,nj->ni", S, dv.reshape(-1, 3)).ravel(), zc, rtol=0, atol=1e-15)
        # the reference: the filtered system S A S y = S (b - A zc), dv = zc + S y, solved directly
        import scipy.sparse as sp

        Sm = sp.block_diag(list(S), format="csr")
        K = (Sm @ A @ Sm + sp.identity(3 * m.n) - Sm).tocsc()
        ref = zc + Sm @ spla.spsolve(K, Sm @ (b - A @ zc))
        assert np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= 1e-4
        steps = {}
        for th in (1, 2):
            backend.set_threads(th)
            s = ic.Simulator(_scene(res=(30, 27)), dt=H)
            s.step(3)
            steps[th] = s.positions.copy()
        assert np.array_equal(steps[1], steps[2])
    finally:
        backend.set_threads(None)


def test_thread_setting_is_checked(monkeypatch):
    from implicit_cloth import backend

    monkeypatch.setenv("IMPLICIT_CLOTH_THREADS", "2")
    assert backend.threads() == 2
    monkeypatch.setenv("IMPLICIT_CLOTH_THREADS", "two")
    with pytest.raises(ValueError, match="IMPLICIT_CLOTH_THREADS: must be an integer >= 1, got 'two'"):
        backend.threads()
    with pytest.raises(ValueError, match="threads: must be an integer >= 1, got 0"):
        backend.set_threads(0)
    backend.set_threads(1)
    try:
        assert backend.threads() == 1
    finally:
        backend.set_threads(None)


@pytest.mark.parametrize("sign", ["at once", "later"])
def test_an_indefinite_preconditioner_is_a_breakdown_not_a_converged_solve(sign):
    """CG needs a positive definite preconditioner; a negative ``r^T P^-1 r`` is a breakdown. It used to end the
    solve as converged with error 0 (taken for round-off), a wrong answer reported as exact."""
    rng = np.random.default_rng(0)
    n = 12
    B = rng.normal(size=(3 * n, 3 * n))
    A = B @ B.T + 3 * n * np.eye(3 * n)
    b = rng.normal(size=3 * n)
    d = -np.ones(3 * n) if sign == "at once" else np.where(np.arange(3 * n) % 3 == 0, -1.0, 1.0)

    class Bad:
        compiled = False

        def apply(self, r):
            return d * r

    dv, res = filtered_pcg(A, b, np.zeros(3 * n), Filter(n, np.zeros(0, dtype=np.int64)), Bad(), tol=1e-6,
                           max_iterations=200, rule="bound", mass=np.ones(3 * n))
    assert not res.converged
    assert np.linalg.norm(dv - np.linalg.solve(A, b)) > 1e-3 * np.linalg.norm(np.linalg.solve(A, b))


@pytest.mark.parametrize("accelerator", ["numpy", NUMBA])
def test_a_simulator_pickled_mid_run_goes_on_exactly_as_the_original(monkeypatch, accelerator):
    """Pickling a simulator (a checkpoint, a process pool) and going on from the copy gives the same steps bit for
    bit. The compiled hierarchy's CG and V-cycle share the fine level's arrays (views); pickling copies them
    apart, and the copy's V-cycle kept the fine values of the moment it was pickled: a stale, indefinite
    preconditioner (found on a 128² contact run)."""
    import pickle

    monkeypatch.setenv("IMPLICIT_CLOTH_ACCELERATOR", accelerator)
    sim = ic.Simulator(_scene(res=(20, 20)), dt=H)
    sim.step(3)
    copy = pickle.loads(pickle.dumps(sim))
    sim.step(4)
    copy.step(4)
    assert copy.last_step.converged
    assert np.array_equal(copy.positions, sim.positions)
    assert copy.last_step.iterations == sim.last_step.iterations


@pytest.mark.parametrize("preconditioner", ["multigrid", "multigrid_smoothed"])
@pytest.mark.parametrize("accelerator", ACCELERATORS)
@pytest.mark.parametrize("tol", [1e-1, 1e-3])
def test_a_diagonal_refresh_still_solves_within_tolerance(preconditioner, accelerator, tol):
    """``Multigrid.refresh_diagonal`` (the friction's Newton corrections: only contacts' diagonal blocks change
    between solves) re-reads the fine diagonal and its smoother and keeps the coarse levels: an SPD
    preconditioner of the changed matrix, so the solve is within tolerance of the direct one and the
    constrained components exact, with damping blocks from 1e-3 to 1e3 times a vertex's mass added after the
    setup (the numpy back-end sets up again)."""
    sim = ic.Simulator(_scene(), dt=H)
    m, _, b = _system(sim)
    z, filt, partial = _constraints(m, b, seed=2)
    pc = make_preconditioner(preconditioner, m, accelerator)
    pc.setup(m.system, filt)
    rng = np.random.default_rng(3)
    idx = rng.choice(np.setdiff1d(np.arange(m.n), np.concatenate([m.pinned, partial])), 60, replace=False)
    t = rng.standard_normal((60, 3))
    t /= np.linalg.norm(t, axis=1)[:, None]
    scale = m.masses[idx] * 10.0 ** rng.uniform(-3, 3, 60)
    D = scale[:, None, None] * (np.eye(3)[None] - t[:, :, None] * t[:, None, :])   # tangential, PSD
    sysm = m.system
    before = sysm.csr.copy()
    np.add.at(sysm.blocks, sysm.diag_index[idx], D)
    sysm.finalize_lazy()
    pc.refresh_diagonal(sysm, filt)
    A = sysm.csr
    assert abs(A - before).sum() > 0
    _check_against_direct(m, A, b, z, filt, partial, pc, tol)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_threading_layer_prefers_openmp_unless_the_user_chose():
    """The kernels ask numba for GNU OpenMP's layer first (short parallel regions scale under it, not under
    TBB's), its threads sleeping between regions; a layer or wait policy named in the environment is kept;
    the run report says which layer ran (fresh processes: numba chooses the layer once per process)."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np, numba, implicit_cloth as ic\n"
            "from implicit_cloth.kernels import layer, pcg\n"
            "assert layer.current() is None\n"
            "pcg.pgather_blocks(np.zeros(90), np.arange(10), np.zeros(90))\n"
            "sim = ic.Simulator(ic.Scene.from_dict({'cloth': {'resolution': [8, 8], 'mass': 0.1, 'pins': ['top_left']},"
            " 'simulation': {'dt': 0.01}}))\n"
            "rep = sim.run(duration=0.02).report['solver']\n"
            "import os\n"
            "print(numba.config.THREADING_LAYER_PRIORITY, os.environ.get('OMP_WAIT_POLICY'), layer.current(),"
            " rep.get('threading_layer'))\n")
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("NUMBA_THREADING_LAYER") and k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}

    def run(extra):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()[-2:], out.stdout

    (ran, reported), text = run({})
    assert "['omp', 'tbb', 'workqueue'] PASSIVE" in text          # OpenMP's threads sleep between regions
    assert ran == reported and ran in ("omp", "tbb", "workqueue")
    try:
        from numba.np.ufunc import omppool  # noqa: F401
    except ImportError:
        pass
    else:
        assert ran == "omp"
    (ran, reported), text = run({"NUMBA_THREADING_LAYER": "workqueue", "OMP_WAIT_POLICY": "ACTIVE"})
    assert ran == reported == "workqueue" and " ACTIVE " in text      # the user's choices kept
