"""Fixed-pattern assembly against an independent COO build; filtered PCG against a direct constrained solve."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import implicit_cloth as ic
from implicit_cloth.assembly import SystemMatrix
from implicit_cloth.solvers import BlockJacobi, Filter, filtered_pcg


def _scene(res=(5, 4), pins=("top_left", "top_right")):
    return {
        "cloth": {"size": [1.0, 0.8], "resolution": list(res), "mass": 0.2, "plane": "xz", "pins": list(pins),
                  "springs": {"structural": {"stiffness": 800.0, "damping": 0.3},
                              "shear": {"stiffness": 90.0, "damping": 0.1},
                              "bend": {"stiffness": 4.0, "damping": 0.02}}},
        "effects": {"gravity": [0, 0, -9.81], "drag": 0.7},
    }


def _stretched_state(sim, rng):
    x = sim.positions * 1.15 + 0.01 * rng.standard_normal(sim.positions.shape)
    v = rng.standard_normal(x.shape)
    return x, v


def _dense_pair_blocks(n, i, j, C):
    """Dense (3n, 3n) matrix with +C_s on blocks (i,i), (j,j) and -C_s on (i,j), (j,i), summed by scipy COO."""
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
        for a in range(3):
            for b in range(3):
                rows.append(3 * p + a)
                cols.append(3 * q + b)
                vals.append(sign * C[:, a, b])
    return sp.coo_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(3 * n, 3 * n)).toarray()


def test_assembled_matrix_equals_independent_coo_build():
    rng = np.random.default_rng(0)
    sim = ic.Simulator(_scene())
    m, s = sim.model, sim.model.springs
    x, v = _stretched_state(sim, rng)
    cx, cv = 1e-4, 1e-2
    A, f, kw = m.linearize(x, v, 0.0, cx, cv, w=v)
    K, D = s.jacobian(x)
    ref = _dense_pair_blocks(m.n, s.i, s.j, cx * K + cv * D)
    ref += np.diag(np.repeat(m.masses + cv * 0.7 * m.areas, 3))      # mass and drag (c = 0.7)
    assert np.allclose(A.toarray(), ref, rtol=1e-12, atol=1e-14)
    assert np.allclose(A.toarray(), A.toarray().T)
    dFdx = -_dense_pair_blocks(m.n, s.i, s.j, K)
    assert np.allclose(kw.ravel(), dFdx @ v.ravel())


def test_pattern_is_built_once_and_refilled():
    sim = ic.Simulator(_scene())
    A1, _, _ = sim.model.linearize(sim.positions, sim.velocities, 0.0, 1e-4, 1e-2)
    ptr, idx = A1.indptr.copy(), A1.indices.copy()
    A2, _, _ = sim.model.linearize(sim.positions * 1.1, sim.velocities, 0.0, 1e-4, 1e-2)
    assert A2 is A1 and np.array_equal(A2.indptr, ptr) and np.array_equal(A2.indices, idx)


def test_system_matrix_block_csr_layout():
    rng = np.random.default_rng(1)
    pairs = np.array([[0, 3], [1, 2], [3, 0], [2, 4], [4, 4]])
    sm = SystemMatrix(5, pairs)
    sm.blocks[:] = rng.standard_normal(sm.blocks.shape)
    dense = np.zeros((15, 15))
    for b, (i, j) in enumerate(zip(sm.block_rows, sm.block_cols)):
        dense[3 * i:3 * i + 3, 3 * j:3 * j + 3] = sm.blocks[b]
    assert np.array_equal(sm.finalize().toarray(), dense)
    assert sm.n_blocks == 5 + 2 * 3   # diagonal + (0,3),(3,0),(1,2),(2,1),(2,4),(4,2)
    with pytest.raises(ValueError):
        sm.block_index(np.array([0]), np.array([1]))


def _constrained_direct(A, b, z, S):
    """Reference: dv = z_c + S y with S A S y = S (b - A z_c), solved densely on the free subspace."""
    Sd = sp.block_diag(list(S)).toarray()
    zc = z - Sd @ z
    # basis of range(S)
    w, V = np.linalg.eigh(Sd)
    B = V[:, w > 0.5]
    y = np.linalg.solve(B.T @ A @ B, B.T @ (b - A @ zc))
    return zc + B @ y


def test_filtered_pcg_matches_direct_constrained_solve():
    rng = np.random.default_rng(2)
    sim = ic.Simulator(_scene())
    m = sim.model
    x, v = _stretched_state(sim, rng)
    A, f, kv = m.linearize(x, v, 0.0, (1 / 30) ** 2, 1 / 30, w=v)
    A = A.copy()
    b = rng.standard_normal(3 * m.n)
    z = rng.standard_normal(3 * m.n)
    # pins fixed in 3 directions, one vertex constrained along a normal, one in two directions
    nrm = rng.standard_normal(3)
    nrm /= np.linalg.norm(nrm)
    e1, e2 = np.eye(3)[0], np.eye(3)[2]
    partial = np.array([5, 7])
    partial_S = np.stack([np.eye(3) - np.outer(nrm, nrm), np.eye(3) - np.outer(e1, e1) - np.outer(e2, e2)])
    filt = Filter(m.n, m.pinned, partial, partial_S)
    pc = BlockJacobi(m.n)
    pc.setup(m.system, filt)
    dv, res = filtered_pcg(A, b, z, filt, pc, tol=1e-12, max_iterations=2000)
    ref = _constrained_direct(A.toarray(), b, z, filt.matrices())
    assert res.converged
    assert np.allclose(dv, ref, rtol=1e-8, atol=1e-10)
    # constrained components are exactly the prescribed ones
    d3, z3 = dv.reshape(-1, 3), z.reshape(-1, 3)
    assert np.array_equal(d3[m.pinned], z3[m.pinned])
    assert d3[5] @ nrm == pytest.approx(z3[5] @ nrm, abs=1e-14)
    assert d3[7][[0, 2]] == pytest.approx(z3[7][[0, 2]], abs=1e-14)
    # warm start reaches the same answer
    dv2, res2 = filtered_pcg(A, b, z, filt, pc, tol=1e-12, max_iterations=2000, guess=ref + 0.01)
    assert np.allclose(dv2, ref, rtol=1e-8, atol=1e-10)


def test_pcg_reports_non_convergence():
    rng = np.random.default_rng(3)
    sim = ic.Simulator(_scene(res=(8, 8)))
    m = sim.model
    A, _, _ = m.linearize(sim.positions, sim.velocities, 0.0, 0.1, 0.1)
    filt = Filter(m.n, m.pinned)
    pc = BlockJacobi(m.n)
    pc.setup(m.system, filt)
    b = rng.standard_normal(3 * m.n)
    _, res = filtered_pcg(A, b, np.zeros_like(b), filt, pc, tol=1e-10, max_iterations=3)
    assert not res.converged and res.iterations == 3 and res.residual > 1e-10


def test_backward_euler_step_solves_its_linear_system():
    """One BE step's dv satisfies BW98 eq. 16 (checked with a direct sparse solve on the free vertices)."""
    rng = np.random.default_rng(4)
    h = 1 / 60
    sim = ic.Simulator(_scene(), integrator="backward_euler", dt=h, solver={"tolerance": 1e-12})
    m = sim.model
    x, v = _stretched_state(sim, rng)
    m.apply_pins(x, v, 0.0)
    sim.positions, sim.velocities = x, v
    x0, v0 = sim.positions.copy(), sim.velocities.copy()
    A, f0, kv = m.linearize(x0, v0, 0.0, h * h, h, w=v0)
    A = A.copy()
    b = (h * (f0 + h * kv)).ravel()
    free = np.repeat(m.free, 3)
    dv_ref = np.zeros_like(b)
    dv_ref[free] = spla.spsolve(A[free][:, free].tocsc(), b[free])
    sim.step(1)
    dv = (sim.velocities - v0).ravel()
    assert np.allclose(dv, dv_ref, rtol=1e-8, atol=1e-12)
    assert np.allclose(sim.positions, x0 + h * sim.velocities)
