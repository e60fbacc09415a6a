"""The compiled (numba) assembly against the numpy reference path and against finite differences.

The numpy path (``Springs.linearize`` with a sparse scatter product,
``SystemMatrix.finalize`` with ``np.take``) is the reference; the numba path
must give the same blocks, CSR values, force and ``(dF/dx) w`` up to the
round-off of a different summation order, on a grid and on an irregular mesh
cloth, with compressed, stretched and zero-length springs, damping on and off.
"""

import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

import implicit_cloth as ic
from implicit_cloth import cloth
from implicit_cloth.assembly import SystemMatrix
from implicit_cloth.effects.springs import Springs
from implicit_cloth.solvers import numba_available, set_default_accelerator

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba not installed")
PATHS = ("numpy", "numba")
KINDS = ("structural", "shear", "bend")


@pytest.fixture(autouse=True)
def _reset_accelerator():
    yield
    set_default_accelerator(None)


def _springs(damping: bool) -> dict:
    k, kd = (800.0, 90.0, 4.0), (0.3, 0.1, 0.02)
    return {kind: {"stiffness": k[m], "damping": kd[m] if damping else 0.0} for m, kind in enumerate(KINDS)}


def _grid_scene(damping: bool) -> dict:
    return {"cloth": {"size": [1.0, 0.8], "resolution": [7, 6], "mass": 0.2, "plane": "xz",
                      "pins": ["top_left", "top_right"], "springs": _springs(damping)},
            "effects": {"gravity": [0.0, 0.0, -9.81], "drag": 0.4}}


def _mesh_scene(tmp_path, damping: bool) -> dict:
    """An irregular mesh cloth: a perturbed grid whose vertices are shuffled (no grid order left)."""
    g = cloth.grid((1.0, 1.0), (6, 5), plane="xy")
    rng = np.random.default_rng(3)
    perm = rng.permutation(g.n_vertices)
    inv = np.argsort(perm)
    pos = g.positions[perm] + 0.02 * rng.standard_normal(g.positions.shape) * [1, 1, 0]
    path = tmp_path / "shuffled.obj"
    trimesh.Trimesh(pos, inv[g.faces], process=False).export(path)
    return {"cloth": {"mesh": str(path), "mass": 0.3, "pins": [0, 5], "springs": _springs(damping)},
            "effects": {"gravity": [0.0, 0.0, -9.81]}}


def _states(model, rng):
    """Mixed (compressed and stretched), all stretched, and one with coincident vertices (zero-length springs)."""
    x0 = model.rest_positions
    mixed = 0.9 * x0 + 0.05 * rng.standard_normal(x0.shape)
    stretched = 1.2 * x0 + 0.005 * rng.standard_normal(x0.shape)
    coincident = mixed.copy()
    s = model.springs
    coincident[s.j[0]] = coincident[s.i[0]]                  # a zero-length spring of positive rest length
    coincident[s.j[-1]] = coincident[s.i[-1]] + [1e-13, 0, 0]   # below the 1e-9 x mean rest length guard
    return {"mixed": mixed, "stretched": stretched, "coincident": coincident}


def _assemble(scene: dict, path: str, rng_seed: int = 0):
    set_default_accelerator(path)
    sim = ic.Simulator(scene)
    m = sim.model
    assert m.system.accelerator == path and m.springs.accelerator == path
    rng = np.random.default_rng(rng_seed)
    out = {}
    v = rng.standard_normal((m.n, 3))
    w = rng.standard_normal((m.n, 3))
    for name, x in _states(m, rng).items():
        with np.errstate(all="raise"):
            A, f, kw = m.linearize(x, v, 0.0, 1.3e-3, 3.7e-2, w=w)
        out[name] = (m.system.blocks.copy(), A.data.copy(), f.copy(), kw.copy())
    return m, out


def _close(a, b, what):
    scale = np.abs(a).max()
    assert np.all(np.isfinite(b)), what
    assert np.abs(a - b).max() <= 1e-13 * scale, f"{what}: {np.abs(a - b).max() / scale:.2e}"


@pytest.mark.parametrize("damping", [True, False])
@pytest.mark.parametrize("kind", ["grid", "mesh"])
def test_numba_assembly_equals_numpy_path(tmp_path, kind, damping):
    scene = _grid_scene(damping) if kind == "grid" else _mesh_scene(tmp_path, damping)
    m0, ref = _assemble(scene, "numpy")
    m1, got = _assemble(scene, "numba")
    s = m1.springs
    assert s._damped is damping
    assert len(m0.system.csr.data) == len(m1.system.csr.data)
    for state in ref:
        for what, a, b in zip(("blocks", "csr", "f", "kw"), ref[state], got[state]):
            _close(a, b, f"{kind} {state} {what}")
    # the states did exercise both signs of strain and the zero-length guard
    x = _states(m1, np.random.default_rng(0))
    strain = s.lengths(x["mixed"]) / s.L0 - 1
    assert strain.min() < -0.05 and strain.max() > 0.05
    assert s.lengths(x["coincident"]).min() < s._tiny
    for state in x.values():                    # compiled lengths (adaptive checks, energies) = numpy's
        assert m0.springs.accelerator == "numpy"
        np.testing.assert_allclose(s.lengths(state), m0.springs.lengths(state), rtol=1e-14, atol=1e-300)


@pytest.mark.parametrize("L0", [0.0, 0.3])
def test_numba_springs_with_zero_rest_length_and_coincident_vertices(L0):
    """Springs bound to a bare SystemMatrix: L0 = 0 springs (Jacobian k I at zero length) and L0 > 0 ones (none)."""
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    k, kd = np.array([250.0, 40.0, 7.0, 90.0]), np.array([1.5, 0.0, 0.2, 0.4])
    x = np.zeros((4, 3))
    x[3] = [0.5, 0.1, 0.0]          # springs 0-1 and 1-2 have zero length, 2-3 and 3-0 not
    rng = np.random.default_rng(5)
    v, w = rng.standard_normal((2, 4, 3))
    res = {}
    for path in PATHS:
        sm = SystemMatrix(4, pairs, accelerator=path)
        s = Springs(4, pairs, k, kd, np.full(4, L0), {"structural": slice(0, 4)})
        s.bind(sm)
        assert s.accelerator == path
        sm.reset_diagonal(np.full(4, 0.1))
        f, kw = np.zeros((4, 3)), np.zeros((4, 3))
        with np.errstate(all="raise"):
            s.linearize(x, v, 0.0, 0.01, 0.1, w, sm, kw, f)
        res[path] = (sm.blocks.copy(), sm.finalize().toarray(), f, kw)
    for what, a, b in zip(("blocks", "A", "f", "kw"), res["numpy"], res["numba"]):
        _close(a, b, what)
    blocks = res["numba"][0]
    off01 = blocks[SystemMatrix(4, pairs).block_index(np.array([0]), np.array([1]))[0]]
    # the zero-length spring 0-1: -(c_x k I) if L0 = 0 (damping has no direction), else nothing
    assert np.allclose(off01, -0.01 * 250.0 * np.eye(3) if L0 == 0.0 else np.zeros((3, 3)), rtol=0, atol=1e-15)


@pytest.mark.parametrize("path", PATHS)
def test_assembled_jacobians_match_central_differences_on_each_path(path):
    """dF/dx and dF/dv from linearize (minus the mass) equal central differences of Model.forces (numpy code)."""
    set_default_accelerator(path)
    sim = ic.Simulator(_grid_scene(True))
    m = sim.model
    assert m.springs.accelerator == path
    rng = np.random.default_rng(11)
    x = 1.15 * m.rest_positions + 0.01 * rng.standard_normal((m.n, 3))
    v = rng.standard_normal((m.n, 3))
    M = np.diag(np.repeat(m.masses, 3))
    A, f, _ = m.linearize(x, v, 0.0, c_x=-1.0, c_v=0.0)
    assert np.allclose(f, m.forces(x, v, 0.0), rtol=0, atol=1e-12 * np.abs(f).max())
    dFdx = A.toarray() - M
    h = 1e-6
    fd = np.zeros_like(dFdx)
    for q in range(3 * m.n):
        e = np.zeros(3 * m.n)
        e[q] = h
        e = e.reshape(-1, 3)
        fd[:, q] = ((m.forces(x + e, 0 * v, 0.0) - m.forces(x - e, 0 * v, 0.0)) / (2 * h)).ravel()
    assert np.abs(dFdx - fd).max() <= 1e-6 * np.abs(fd).max()
    A, _, _ = m.linearize(x, v, 0.0, c_x=0.0, c_v=-1.0)
    dFdv = A.toarray() - M
    for q in range(3 * m.n):
        e = np.zeros(3 * m.n)
        e[q] = h
        e = e.reshape(-1, 3)
        fd[:, q] = ((m.forces(x, v + e, 0.0) - m.forces(x, v - e, 0.0)) / (2 * h)).ravel()
    assert np.abs(dFdv - fd).max() <= 1e-6 * np.abs(fd).max()


def _reset_then_finalize(sm, vals, d):
    """``reset_diagonal(d)`` over the blocks ``vals`` (checked: zeros but ``d_i I`` on the diagonal), then
    ``finalize`` of the blocks ``vals``; returns the matrix."""
    sm.blocks[:] = vals
    sm.reset_diagonal(d)
    expect = np.zeros_like(vals)
    expect[sm.diag_index] = d[:, None, None] * np.eye(3)
    assert np.array_equal(sm.blocks, expect)
    sm.blocks[:] = vals
    return sm.finalize()


def _dense(sm, vals):
    """The dense matrix of the blocks ``vals`` on ``sm``'s pattern."""
    n = 3 * (len(sm.bptr) - 1)
    dense = np.zeros((n, n))
    for b, (i, j) in enumerate(zip(sm.block_rows, sm.block_cols)):
        dense[3 * i:3 * i + 3, 3 * j:3 * j + 3] = vals[b]
    return dense


def test_finalize_reset_and_add_diagonal_agree_on_both_paths():
    rng = np.random.default_rng(2)
    pairs = np.array([[0, 3], [1, 2], [3, 0], [2, 4], [4, 4], [1, 4]])
    sms = {p: SystemMatrix(5, pairs, accelerator=p) for p in PATHS}
    vals = rng.standard_normal(sms["numpy"].blocks.shape)
    d = rng.uniform(1, 2, 5)
    out = {}
    for p, sm in sms.items():
        csr, v0 = sm.csr, sm.version
        A = _reset_then_finalize(sm, vals, d)
        assert A is csr and sm.version == v0 + 1
        out[p] = A.toarray()
    sm = sms["numba"]
    dense = _dense(sm, vals)
    assert np.array_equal(out["numba"], dense) and np.array_equal(out["numpy"], dense)
    for p, sm in sms.items():
        sm.blocks[:] = vals
        sm.add_diagonal(d)
        expect = vals.copy()
        expect[sm.diag_index] += d[:, None, None] * np.eye(3)
        assert np.array_equal(sm.blocks, expect), p
    with pytest.raises(ValueError, match="expected 5 diagonal values"):
        sm.reset_diagonal(np.ones(4))
    with pytest.raises(ValueError, match="expected 5 diagonal values"):
        sm.add_diagonal(np.ones(6))


def test_lazy_finalize_copies_the_blocks_when_read_and_a_free_step_skips_it():
    """``finalize_lazy`` bumps the version and defers the CSR copy: the first read of ``csr`` makes it (the
    values of that finalize), on both paths, and so does a product on the numpy path (the compiled one multiplies
    from the blocks, the CSR product's numbers to the last bit); a free cloth's step with the compiled solver
    never reads the CSR (a step's numbers against the eager finalize's were checked bit for bit when it came
    in)."""
    rng = np.random.default_rng(3)
    pairs = np.array([[0, 3], [1, 2], [2, 4], [1, 4]])
    for p in PATHS:
        sm = SystemMatrix(5, pairs, accelerator=p)
        sm.blocks[:] = rng.standard_normal(sm.blocks.shape)
        eager = sm.finalize().toarray()
        sm.blocks *= 2.0
        v0 = sm.version
        assert sm.finalize_lazy() is sm and sm.version == v0 + 1 and not sm._csr_current
        assert np.array_equal(sm._csr.toarray(), eager)                 # not copied yet
        x = rng.standard_normal(15)
        y = sm @ x
        assert np.allclose(y, 2.0 * eager @ x, rtol=1e-14, atol=0)
        assert sm._csr_current == (p == "numpy")        # compiled: multiplied from the blocks, no copy
        assert np.array_equal(sm.csr.toarray(), 2.0 * eager) and sm.shape == (15, 15) and sm._csr_current
        assert np.array_equal(y, sm.csr @ x)              # the CSR product's numbers to the last bit
    if not numba_available():
        return
    scene = {"cloth": {"size": [1.0, 1.0], "resolution": [12, 12], "mass": 0.1, "pins": ["top_left"]},
             "effects": {"gravity": [0.0, 0.0, -9.81]}}
    sim = ic.Simulator(scene, dt=0.01)
    copies = []
    backend = sim.model.system.backend
    orig = backend.blocks_to_csr
    backend.blocks_to_csr = lambda *a: (copies.append(1), orig(*a))[1]
    try:
        sim.step(3)
        assert not copies and not sim.model.system._csr_current
        A = sim.model.system.csr                                           # a read makes the copy
        assert copies == [1] and sim.model.system._csr_current
    finally:
        backend.blocks_to_csr = orig
    # the CSR then holds the last assembly: the blocks' values, as an eager finalize would
    dense = np.zeros(A.shape)
    sm = sim.model.system
    for b, (i, j) in enumerate(zip(sm.block_rows, sm.block_cols)):
        dense[3 * i:3 * i + 3, 3 * j:3 * j + 3] = sm.blocks[b]
    assert np.array_equal(A.toarray(), dense)


def test_numba_assembly_is_symmetric_exactly():
    set_default_accelerator("numba")
    sim = ic.Simulator(_grid_scene(True))
    m = sim.model
    x = 0.9 * m.rest_positions + 0.05 * np.random.default_rng(4).standard_normal((m.n, 3))
    A, _, _ = m.linearize(x, np.zeros_like(x), 0.0, 1e-3, 1e-2)
    A = A.toarray()
    assert np.array_equal(A, A.T)


def test_steps_agree_on_both_paths(hanging_scene):
    """A few backward-Euler steps at a tight tolerance: the same trajectory whichever path assembles and solves."""
    xs = {}
    for p in PATHS:
        set_default_accelerator(p)
        sim = ic.Simulator(hanging_scene, solver={"tolerance": 1e-10})
        sim.step(5)
        xs[p] = sim.positions.copy()
    disp = np.abs(xs["numpy"] - ic.Simulator(hanging_scene).positions).max()
    assert disp > 1e-3
    assert np.abs(xs["numba"] - xs["numpy"]).max() <= 1e-7 * disp


def test_numpy_path_and_core_import_do_not_import_numba(hanging_scene):
    code = ("import json, os, sys, implicit_cloth as ic, implicit_cloth.cli\n"
            "first = 'numba' in sys.modules\n"
            "sim = ic.Simulator(json.loads(sys.argv[1])); sim.step(2)\n"
            "print(first, 'numba' in sys.modules, sim.model.springs.accelerator)\n")
    import json
    import os

    env = dict(os.environ, IMPLICIT_CLOTH_ACCELERATOR="numpy")
    out = subprocess.run([sys.executable, "-c", code, json.dumps(hanging_scene)], capture_output=True, text=True,
                         check=True, env=env).stdout.split()
    assert out == ["False", "False", "numpy"]


@pytest.mark.parametrize("damping", [True, False])
@pytest.mark.parametrize("kind", ["grid", "mesh"])
def test_numba_spring_force_equals_numpy_path(tmp_path, kind, damping):
    """``Springs.force`` (what the line searches, the energy balance and the explicit methods evaluate) on the
    numba path is one compiled pass with numpy's arithmetic: numpy's force, stretched, compressed and at zero
    length, damped or not, added to what the array held (bit for bit where it was written; asserted to round-off,
    since numpy's einsum may sum three products in another order on another processor). ``Springs.dissipation``
    (every point of a line search) is one compiled pass too: numpy's to round-off."""
    scene = _grid_scene(damping) if kind == "grid" else _mesh_scene(tmp_path, damping)
    models = {}
    for path in PATHS:
        set_default_accelerator(path)
        models[path] = ic.Simulator(scene).model
    s0, s1 = models["numpy"].springs, models["numba"].springs
    assert (s0.accelerator, s1.accelerator) == ("numpy", "numba")
    rng = np.random.default_rng(7)
    v = rng.standard_normal((s1.n, 3))
    start = rng.standard_normal((s1.n, 3))
    for name, x in _states(models["numba"], rng).items():
        ref, got = start.copy(), start.copy()
        with np.errstate(all="raise"):
            s0.force(x, v, 0.0, ref)
            s1.force(x, v, 0.0, got)
        assert np.all(np.isfinite(got)), name
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14 * np.abs(ref).max(), err_msg=f"{kind} {name}")
        assert not np.array_equal(got, start)
        # the damping's dissipation (every point of a line search evaluates it): one compiled pass, numpy's sum
        d0, d1 = s0.dissipation(x, v, 0.0), s1.dissipation(x, v, 0.0)
        assert (d0 > 0.0) == damping and d1 == pytest.approx(d0, rel=1e-12, abs=0.0), (kind, name)


def test_spring_force_kernels_agree_at_every_thread_count():
    """``Springs.force`` runs the springs' force as a compiled parallel region at every size (on one thread below
    the threaded size, numba's parallel lowering being the faster there too): the serial kernel's numbers to the
    last bit, on one thread and on two, and numba's thread count restored after the one-thread block."""
    from numba import get_num_threads, set_num_threads

    from implicit_cloth.backend import one_numba_thread
    from implicit_cloth.kernels.springs import pspring_forces, spring_forces

    set_default_accelerator("numba")
    sim = ic.Simulator(_grid_scene(True))
    sp = sim.model.springs
    rng = np.random.default_rng(11)
    x = sim.positions + 0.01 * rng.standard_normal((sp.n, 3))
    v = rng.standard_normal((sp.n, 3))
    B = sp._B
    outs = []
    original = get_num_threads()
    try:
        for kernel, threads in ((spring_forces, None), (pspring_forces, 1), (pspring_forces, 2)):
            out = np.zeros((sp.n, 3))
            args = (x, v, *sp._plain, float(sp._tiny), sp._damped, B.indptr, B.indices, B.data, sp._F.copy(), out)
            if threads == 1:
                set_num_threads(min(2, original))
                before = get_num_threads()
                with one_numba_thread():
                    assert get_num_threads() == 1
                    kernel(*args)
                assert get_num_threads() == before
            else:
                kernel(*args)
            outs.append(out)
    finally:
        set_num_threads(original)      # the process's count as the test found it
    assert np.any(outs[0] != 0.0)
    assert np.array_equal(outs[0], outs[1]) and np.array_equal(outs[0], outs[2])
    got = np.zeros((sp.n, 3))
    sp.force(x, v, 0.0, got)
    assert np.array_equal(got, outs[0])


def test_a_forked_child_simulates_after_a_one_thread_run():
    """A compiled run on one thread may open numba parallel regions (the springs' force runs as one), and GNU
    OpenMP is not fork-safe once it has run regions on several threads: a program that forks workers after a
    one-thread run keeps working, the child's numbers the parent's (the batch runner spawns its workers whatever
    the thread count)."""
    code = (
        "import multiprocessing as mp, numpy as np, implicit_cloth as ic\n"
        "def run(_):\n"
        "    sim = ic.Simulator(SCENE); sim.step(3); return float(np.abs(sim.positions).sum())\n"
        "SCENE = {'simulation': {'dt': 0.01}, 'cloth': {'size': [1.0, 1.0], 'resolution': [12, 12], 'mass': 0.1,\n"
        "         'pins': ['top_left', 'top_right'], 'springs': {'structural': {'stiffness': 1000.0}}},\n"
        "         'effects': {'gravity': [0.0, 0.0, -9.81]}}\n"
        "if __name__ == '__main__':\n"
        "    here = run(0)\n"
        "    with mp.get_context('fork').Pool(1) as pool:\n"
        "        there = pool.map(run, [0])[0]\n"
        "    assert here == there\n"
        "    print('ok')\n")
    env = dict(os.environ, IMPLICIT_CLOTH_ACCELERATOR="numba", IMPLICIT_CLOTH_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0 and out.stdout.split() == ["ok"], out.stderr[-2000:]


def test_block_product_gives_the_csr_products_numbers():
    """After a lazy finalize the compiled path multiplies from the blocks (no CSR copy): on an assembled cloth
    system (13 blocks a row inside) the same numbers as scipy's CSR product, to the last bit."""
    scene = {"cloth": {"size": [1.0, 1.0], "resolution": [20, 17], "mass": 0.1, "pins": ["top_left"]},
             "effects": {"gravity": [0.0, 0.0, -9.81]}}
    sim = ic.Simulator(scene, dt=0.01)
    sim.step(2)
    sm = sim.model.system
    assert sm.accelerator == "numba"
    rng = np.random.default_rng(7)
    for _ in range(3):
        x = rng.standard_normal(3 * sm.n)
        sm.finalize_lazy()
        y = sm @ x
        assert not sm._csr_current
        assert np.array_equal(y, sm.csr @ x)


@pytest.mark.parametrize("kind", ["grid", "mesh"])
@pytest.mark.parametrize("chunks", [1, 3, 8, 40])
def test_threaded_spring_pass_gives_the_serial_pass_numbers_bit_for_bit(tmp_path, kind, chunks):
    """The chunked pass (each chunk owns its vertices' rows and visits the springs touching them in order)
    gives the serial pass's blocks, forces and ``(dF/dx) w`` to the last bit, whatever the chunks: on a grid
    and on a shuffled mesh (chunks' springs far apart), with a spring given twice (two springs on one pair)."""
    from implicit_cloth.kernels.springs import chunk_springs, springs_linearize, springs_linearize_chunks

    scene = _grid_scene(True) if kind == "grid" else _mesh_scene(tmp_path, True)
    set_default_accelerator("numba")
    m = ic.Simulator(scene).model
    s = m.springs
    si, sj, k, kd, L0 = s._sorted
    # a doubled spring: the same pair twice in the sorted order, each with its own constants
    si, sj = np.insert(si, 5, si[5]), np.insert(sj, 5, sj[5])
    k, kd, L0 = np.insert(k, 5, 0.5 * k[5]), np.insert(kd, 5, 2 * kd[5]), np.insert(L0, 5, 0.8 * L0[5])
    bidx = np.insert(s._bidx, 5, s._bidx[5], axis=0)
    rng = np.random.default_rng(11)
    v, w = rng.standard_normal((2, m.n, 3))
    blocks0 = rng.standard_normal(m.system.blocks.shape)       # whatever the other effects put there
    f0, kw0 = rng.standard_normal((2, m.n, 3))
    vlo, cptr, clist = chunk_springs(m.n, si, sj, chunks)
    assert len(vlo) == chunks + 1 and cptr[-1] == len(clist)
    for name, x in _states(m, rng).items():
        for with_w in (True, False):
            out = []
            for chunked in (False, True):
                B, f, kw = blocks0.copy(), f0.copy(), kw0.copy()
                args = (x, v, w, with_w, True, si, sj, k, kd, L0, float(s._tiny), 1.3e-3, 3.7e-2, bidx)
                if chunked:
                    springs_linearize_chunks(*args, vlo, cptr, clist, B, kw, f)
                else:
                    springs_linearize(*args, B, kw, f)
                out.append((B, f, kw))
            for what, a, b in zip(("blocks", "f", "kw"), *out):
                assert np.array_equal(a, b), f"{kind} {name} {what} with_w={with_w}"
            assert not np.array_equal(out[0][0], blocks0)


def test_threaded_spring_pass_runs_from_the_threaded_size(monkeypatch):
    """With two threads and a cloth of the multigrid's threaded size the springs take the chunked pass (its
    chunks made once), with one thread or a smaller cloth the serial one; the blocks the same, and the forces
    of the threaded force pass."""
    from implicit_cloth import backend
    from implicit_cloth.kernels import springs as kernels

    set_default_accelerator("numba")
    m = ic.Simulator(_grid_scene(True)).model
    calls = []
    real = kernels.springs_linearize_chunks
    monkeypatch.setattr(kernels, "springs_linearize_chunks", lambda *a: calls.append(1) or real(*a))
    x = m.rest_positions * 1.1
    v = np.ones_like(x)
    res = []
    for n_threads, tmin in ((1, 0), (2, 10 ** 6), (2, 0), (2, 0)):
        monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES", tmin)
        monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES_OTHER_LAYERS", tmin)
        with backend.using_threads(n_threads):
            m.linearize(x, v, 0.0, 1e-3, 1e-2)
        res.append(m.system.blocks.copy())
    assert len(calls) == 2
    assert m.springs._chunks is not None
    for b in res[1:]:
        assert np.array_equal(b, res[0])
    forces = []                                  # the force pass's threaded twin: the same numbers
    for n_threads in (1, 2):
        with backend.using_threads(n_threads):
            assert m.springs.backend.threaded(m.n) is (n_threads > 1)
            out = np.zeros_like(x)
            m.springs.force(x, v + np.arange(m.n)[:, None], 0.0, out)
        forces.append(out)
    assert np.array_equal(forces[0], forces[1]) and np.any(forces[0])


@pytest.mark.parametrize("n_threads", [1, 2])
def test_threaded_assembly_passes_give_the_serial_numbers(monkeypatch, n_threads):
    """The back-end's threaded twins (reset, CSR copy, block product) run where :meth:`Backend.threaded` says,
    and give the serial passes' numbers to the last bit."""
    from implicit_cloth import backend
    from implicit_cloth.kernels import assembly as kernels

    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES", 0)
    monkeypatch.setattr("implicit_cloth.backend.THREAD_MIN_VERTICES_OTHER_LAYERS", 0)
    rng = np.random.default_rng(4)
    g = cloth.grid((1.0, 1.0), (9, 8), plane="xy", kinds=KINDS)
    pairs = np.concatenate([g.springs[k] for k in KINDS])
    sm = SystemMatrix(g.n_vertices, pairs, accelerator="numba")
    b = sm.backend
    assert not backend.get_backend("numpy").threaded(10 ** 9)
    vals = rng.standard_normal(sm.blocks.shape)
    d = rng.uniform(1, 2, g.n_vertices)
    x = rng.standard_normal(3 * g.n_vertices)
    calls = []
    for name in ("preset_diagonal", "pblocks_to_csr", "pblock_matvec"):
        real = getattr(kernels, name)
        monkeypatch.setattr(kernels, name, lambda *a, _r=real, _n=name: calls.append(_n) or _r(*a))
    with backend.using_threads(n_threads):
        assert b.threaded(g.n_vertices) is (n_threads > 1)
        A = _reset_then_finalize(sm, vals, d)
        y = b.block_matvec(sm.blocks, sm.bptr, sm.block_cols, x)
    assert len(calls) == (3 if n_threads > 1 else 0)
    assert np.array_equal(A.toarray(), _dense(sm, vals))
    assert np.array_equal(y, A @ x)      # scipy's CSR product: the same additions in the same order
