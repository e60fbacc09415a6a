"""The K-cycle (``solver.cycle = "K"``, Notay & Vassilevski 2008): its solves against a direct solve with the
constraints exact, the compiled path against the numpy reference, one and two threads, the iterations it saves
on a deep hierarchy, and the scene key."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
from test_solvers import ACCELERATORS, H, _scene, _system

import implicit_cloth as ic
from implicit_cloth import SceneError, cloth
from implicit_cloth.solvers import Filter, filtered_pcg, make_preconditioner, numba_available

# An opt-in cycle whose compiled kernels take three minutes to compile from a cold cache on this 2-core machine
# (18 s warm): slow, so the README's quick test command stays within its time; CI runs it.
pytestmark = pytest.mark.slow


def _contact_filter(m):
    """Pins, vertices sliding along a tilted normal (S = I - n n^T) and sticking ones (S = 0)."""
    nrm = np.array([0.3, -0.2, 0.93])
    nrm /= np.linalg.norm(nrm)
    slide = np.arange(m.n // 4, m.n // 4 + 40)
    stick = np.arange(m.n // 2, m.n // 2 + 15)
    PS = np.concatenate([np.broadcast_to(np.eye(3) - np.outer(nrm, nrm), (len(slide), 3, 3)),
                         np.zeros((len(stick), 3, 3))])
    return Filter(m.n, m.pinned, np.concatenate([slide, stick]), PS)


def _mesh_file(tmp_path):
    """An irregular 40 x 40 triangle mesh (deep enough an aggregation hierarchy for K-steps)."""
    g = cloth.grid((1.0, 1.0), (40, 40), plane="xy")
    rng = np.random.default_rng(5)
    pos = g.positions + 0.2 / 39 * rng.uniform(-1, 1, g.positions.shape) * [1, 1, 0]
    path = tmp_path / "cloth.obj"
    trimesh.Trimesh(pos, g.faces, process=False).export(path)
    return str(path)


def _reference(A, b, z, filt):
    """The filtered system ``S A S y = S (b - A zc)``, ``dv = zc + S y``, solved directly; and ``zc``."""
    S = filt.matrices()
    zc = z - np.einsum("nij,nj->ni", S, z.reshape(-1, 3)).ravel()
    Sm = sp.block_diag(list(S), format="csr")
    K = (Sm @ A @ Sm + sp.identity(A.shape[0]) - Sm).tocsc()
    return zc + Sm @ spla.spsolve(K, Sm @ (b - A @ zc)), zc, S


def _k(name, m, accelerator):
    mg = make_preconditioner(name, m, accelerator)
    mg.cycle = "K"
    assert mg.flexible
    return mg


@pytest.mark.parametrize("name", ["multigrid", "multigrid_smoothed"])
@pytest.mark.parametrize("kind", ["grid", "mesh"])
@pytest.mark.parametrize("accelerator", ACCELERATORS)
@pytest.mark.parametrize("tol", [1e-2, 1e-4])
def test_kcycle_matches_direct_solve_within_tolerance(tmp_path, name, kind, accelerator, tol):
    sim = ic.Simulator(_scene(res=(40, 37), mesh=_mesh_file(tmp_path) if kind == "mesh" else None), dt=H)
    m, A, b = _system(sim, steps=12)
    filt = _contact_filter(m)
    z = np.random.default_rng(3).standard_normal(b.shape) * 0.01
    mg = _k(name, m, accelerator)
    assert mg.n_levels >= 3                       # K-steps on at least one coarse level
    mg.setup(None, filt)
    dv, res = filtered_pcg(m.system.csr, b, z, filt, mg, tol=tol, max_iterations=2000,
                           mass=np.repeat(m.masses, 3))
    ref, zc, S = _reference(A, b, z, filt)
    assert res.converged
    assert np.linalg.norm(dv - ref) / np.linalg.norm(ref) <= tol
    # the constrained components exact
    assert np.allclose(dv - np.einsum("nij,nj->ni", S, dv.reshape(-1, 3)).ravel(), zc, rtol=0, atol=1e-15)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
@pytest.mark.parametrize("name", ["multigrid", "multigrid_smoothed"])
def test_kcycle_numba_path_is_the_numpy_iteration(name):
    sim = ic.Simulator(_scene(res=(40, 37)), dt=H)
    m, A, b = _system(sim, steps=10)
    filt = _contact_filter(m)
    out = {}
    for acc in ("numpy", "numba"):
        mg = _k(name, m, acc)
        mg.setup(None, filt)
        r = filt.apply(np.random.default_rng(2).standard_normal(b.shape))
        out[acc] = (mg.apply(r), *filtered_pcg(m.system.csr, b, np.zeros_like(b), filt, mg, tol=1e-6,
                                               mass=np.repeat(m.masses, 3)))
    (v0, dv0, r0), (v1, dv1, r1) = out["numpy"], out["numba"]
    assert np.allclose(v1, v0, rtol=1e-9, atol=1e-10 * np.abs(v0).max())
    assert abs(r1.iterations - r0.iterations) <= 1 and r1.converged and r0.converged
    assert np.linalg.norm(dv1 - dv0) <= 2e-6 * np.linalg.norm(dv0)
    # the K-cycle is not the V-cycle: it varies with its argument (two applications do not add up)
    mg = _k(name, m, "numba")
    mg.setup(None, filt)
    r1 = filt.apply(np.random.default_rng(2).standard_normal(b.shape))
    r2 = filt.apply(np.random.default_rng(5).standard_normal(b.shape))
    assert not np.allclose(mg.apply(r1 + r2), mg.apply(r1) + mg.apply(r2), rtol=1e-6, atol=0)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
@pytest.mark.parametrize("name", ["multigrid_smoothed", "multigrid float32"])
def test_kcycle_one_and_two_threads_give_the_same_numbers(monkeypatch, name):
    """Every level threaded: the K-cycle's steps (serial sums on the coarse levels) give the same numbers to the
    last bit on one and two threads, within the tolerance of a direct solve (also with the plain multigrid's
    float32 V-cycle of large cloths), and whole steps agree."""
    from implicit_cloth import backend
    from implicit_cloth.solvers import multigrid

    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES", 0)
    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES_OTHER_LAYERS", 0)
    monkeypatch.setattr(multigrid, "FLOAT32_MIN_VERTICES", 0 if name.endswith("float32") else None)
    sim = ic.Simulator(_scene(res=(30, 27)), dt=H)
    m, A, b = _system(sim, steps=4)
    filt = _contact_filter(m)
    z = np.random.default_rng(4).standard_normal(b.shape) * 0.01
    out = {}
    try:
        for th in (1, 2):
            backend.set_threads(th)
            mg = _k(name.split()[0], m, "numba")
            mg.setup(None, filt)
            assert mg.engine.lpar.all() and (mg.engine.vu6.dtype == np.float32) == name.endswith("float32")
            dv, res = filtered_pcg(m.system.csr, b, z, filt, mg, tol=1e-4, mass=np.repeat(m.masses, 3))
            out[th] = (dv, res.iterations)
        assert np.array_equal(out[1][0], out[2][0]) and out[1][1] == out[2][1]
        ref, _, _ = _reference(A, b, z, filt)
        assert np.linalg.norm(out[1][0] - ref) / np.linalg.norm(ref) <= 1e-4
        steps = {}
        for th in (1, 2):
            backend.set_threads(th)
            d = _scene(res=(30, 27))
            d["solver"] = {"cycle": "K"}
            s = ic.Simulator(d, dt=H)
            s.step(3)
            steps[th] = s.positions.copy()
        assert np.array_equal(steps[1], steps[2])
    finally:
        backend.set_threads(None)


@pytest.mark.parametrize("accelerator", ACCELERATORS)
def test_kcycle_saves_iterations_on_a_deep_hierarchy(accelerator):
    """The stiff cloth buckling at 64² (6 levels): the V-cycle's iterations grow with the levels' recursion, the
    K-cycle's coarse corrections hold them (the stiff benchmark at 256²-512²: 12-13 against 28-31)."""
    sim = ic.Simulator(_scene(res=(64, 64)), dt=H)
    m, A, b = _system(sim, steps=25)
    filt = Filter(m.n, m.pinned)
    its = {}
    for cycle in ("V", "K"):
        mg = make_preconditioner("multigrid", m, accelerator)
        mg.cycle = cycle
        mg.setup(None, filt)
        _, res = filtered_pcg(m.system.csr, b, np.zeros_like(b), filt, mg, tol=1e-3, mass=np.repeat(m.masses, 3))
        assert res.converged
        its[cycle] = res.iterations
    assert its["K"] <= 0.75 * its["V"], its


def test_scene_key_selects_the_kcycle_and_the_report_names_it():
    d = _scene(res=(12, 12))
    d["solver"] = {"cycle": "K"}
    sim = ic.Simulator(d, dt=H)
    assert sim.integrator.precond.cycle == "K"
    r = sim.run(duration=0.1)
    assert r.report["solver"]["cycle"] == "K" and np.isfinite(r.positions).all()
    base = ic.Simulator(_scene(res=(12, 12)), dt=H).run(duration=0.1)
    assert base.report["solver"]["cycle"] == "V"
    disp = np.linalg.norm(base.positions[-1] - base.positions[0], axis=1).max()
    assert np.linalg.norm(r.positions[-1] - base.positions[-1], axis=1).max() <= 0.01 * disp
    for bad, match in (({"cycle": "W"}, r"solver\.cycle.*W"),
                       ({"cycle": "K", "preconditioner": "block_jacobi"}, r"solver\.cycle.*block_jacobi")):
        d["solver"] = bad
        with pytest.raises(SceneError, match=match):
            ic.Simulator(d, dt=H)


def test_cli_names_the_kcycle(tmp_path, capsys):
    from implicit_cloth.cli import main

    scene = tmp_path / "k.toml"
    scene.write_text('[simulation]\ndt = 0.02\nduration = 0.06\n[solver]\ncycle = "K"\n[cloth]\n'
                     'resolution = [12, 12]\nmass = 0.1\npins = ["top_left", "top_right"]\n'
                     '[effects]\ngravity = [0.0, 0.0, -9.81]\n')
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 0
    assert "PCG (" in (out := capsys.readouterr().out) and ", K-cycle)" in out
