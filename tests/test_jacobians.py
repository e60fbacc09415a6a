"""Spring and assembled Jacobians against central finite differences of the force code.

References are computed here, independently of the Jacobian code: central
differences of ``Springs.spring_forces`` / ``Model.forces``, and the closed-form
error order of a central difference (O(h^2) for the derivative estimate).
"""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import implicit_cloth as ic
from implicit_cloth.effects.springs import Springs

KINDS = ("structural", "shear", "bend")


def _scene(res=(4, 4), damping=True, drag=None, wind=None, k=(800.0, 90.0, 4.0)):
    kd = (0.3, 0.1, 0.02) if damping else (0.0, 0.0, 0.0)
    scene = {
        "cloth": {"size": [1.0, 0.8], "resolution": list(res), "mass": 0.2, "plane": "xz",
                  "pins": ["top_left", "top_right"],
                  "springs": {kind: {"stiffness": k[m], "damping": kd[m]} for m, kind in enumerate(KINDS)}},
        "effects": {"gravity": [0.0, 0.0, -9.81]},
    }
    if drag is not None:
        scene["effects"]["drag"] = drag
    if wind is not None:
        scene["effects"]["wind"] = {"velocity": list(wind)}
    return scene


def _mixed_state(sim, rng, scale=1.0, noise=0.08):
    """Positions with a mix of stretched and compressed springs (noise ~ a quarter of the spacing)."""
    x0 = sim.model.rest_positions
    return scale * x0 + noise * rng.standard_normal(x0.shape)


def _stretched_state(sim, rng):
    """Every spring stretched (so the compression clamp is inactive): uniform 25 % stretch plus small noise."""
    s = sim.model.springs
    x = _mixed_state(sim, rng, scale=1.25, noise=0.01)
    assert np.all(s.lengths(x) > s.L0 * 1.05), "test setup: some spring is not stretched"
    return x


def _fd_spring_jacobians(s, x, v, h):
    """Central differences of the per-spring force f_i(x, v): returns (dF/dx_j, dF/dx_i, dF/dv_j) per spring."""
    S = len(s.i)
    Kj, Ki, Dj = np.zeros((S, 3, 3)), np.zeros((S, 3, 3)), np.zeros((S, 3, 3))
    for p in range(x.shape[0]):
        on_j, on_i = s.j == p, s.i == p
        for a in range(3):
            xp, xm = x.copy(), x.copy()
            xp[p, a] += h
            xm[p, a] -= h
            col = (s.spring_forces(xp, v) - s.spring_forces(xm, v)) / (2 * h)
            Kj[on_j, :, a] = col[on_j]
            Ki[on_i, :, a] = col[on_i]
            vp, vm = v.copy(), v.copy()
            vp[p, a] += h
            vm[p, a] -= h
            colv = (s.spring_forces(x, vp) - s.spring_forces(x, vm)) / (2 * h)
            Dj[on_j, :, a] = colv[on_j]
    return Kj, Ki, Dj


def _fd_dense(fun, y, h):
    """Dense central-difference Jacobian of fun: (N, 3) -> (N, 3), as a (3N, 3N) matrix."""
    n3 = y.size
    J = np.zeros((n3, n3))
    for c in range(n3):
        yp, ym = y.copy().reshape(-1), y.copy().reshape(-1)
        yp[c] += h
        ym[c] -= h
        J[:, c] = (fun(yp.reshape(y.shape)) - fun(ym.reshape(y.shape))).reshape(-1) / (2 * h)
    return J


def _dense_from_blocks(n, i, j, K):
    """dF/dx (3N, 3N) from per-spring blocks K = df_i/dx_j (df_i/dx_i = -K, force on j is -f_i)."""
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, j, 1), (j, i, 1), (i, i, -1), (j, j, -1)):
        for a in range(3):
            for b in range(3):
                rows.append(3 * p + a)
                cols.append(3 * q + b)
                vals.append(sign * K[:, a, b])
    return sp.coo_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(3 * n, 3 * n)).toarray()


# --------------------------------------------------------------------------- (a) per spring
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_per_spring_exact_jacobian_matches_central_differences(seed):
    """K = df_i/dx_j and -K = df_i/dx_i (exact=True) and D = df_i/dv_j, on stretched AND compressed springs."""
    rng = np.random.default_rng(seed)
    sim = ic.Simulator(_scene())
    s = sim.model.springs
    x = _mixed_state(sim, rng)
    strain = s.strain(x)
    for kind, sl in s.kinds.items():   # every kind has both stretched and compressed springs in this state
        assert np.any(strain[sl] > 0.02) and np.any(strain[sl] < -0.02), kind
    # damping's x-derivative is documented as dropped: use a rigid translation velocity so it vanishes
    v_rigid = np.tile(rng.standard_normal(3), (sim.model.n, 1))
    Kj, Ki, _ = _fd_spring_jacobians(s, x, v_rigid, h=1e-6)
    v = rng.standard_normal(x.shape)
    _, _, Dj = _fd_spring_jacobians(s, x, v, h=1e-3)   # the force is linear in v: any step is exact
    K, D = s.jacobian(x, exact=True)
    scale = s.k.max()
    # FD error: truncation ~ k (h/l)^2 ~ 1e-8 relative, round-off ~ eps |f| / h ~ 1e-9 relative
    assert np.abs(K - Kj).max() <= 1e-6 * scale
    assert np.abs(-K - Ki).max() <= 1e-6 * scale
    assert np.abs(D - Dj).max() <= 1e-9 * s.kd.max()
    # and the per-kind stiffness is the scene's one (the blocks' u-direction eigenvalue is k)
    d = x[s.j] - x[s.i]
    u = d / np.linalg.norm(d, axis=1)[:, None]
    assert np.allclose(np.einsum("sa,sab,sb->s", u, K, u), s.k, rtol=1e-12)
    assert np.allclose(s.k[s.kinds["structural"]], 800.0) and np.allclose(s.k[s.kinds["bend"]], 4.0)


def test_per_spring_random_springs_both_signs_of_strain():
    """A random spring set (not a grid): exact K against FD; the clamped K equals it exactly where l >= L0."""
    rng = np.random.default_rng(7)
    n, S = 12, 40
    pairs = np.array([rng.choice(n, 2, replace=False) for _ in range(S)])
    x = rng.uniform(-1, 1, (n, 3))
    l = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1)
    L0 = l * rng.uniform(0.5, 1.5, S)     # about half compressed, half stretched
    k = rng.uniform(10.0, 1000.0, S)
    kd = rng.uniform(0.0, 2.0, S)
    s = Springs(n, pairs, k, kd, L0, {"structural": slice(0, S)})
    v0 = np.zeros_like(x)
    Kj, Ki, _ = _fd_spring_jacobians(s, x, v0, h=1e-6)
    Kex, _ = s.jacobian(x, exact=True)
    Kcl, _ = s.jacobian(x, exact=False)
    assert np.abs(Kex - Kj).max() <= 1e-6 * k.max()
    assert np.abs(-Kex - Ki).max() <= 1e-6 * k.max()
    stretched = l >= L0
    assert 10 < stretched.sum() < S - 10
    assert np.array_equal(Kcl[stretched], Kex[stretched])
    # compressed: the transverse term is dropped, leaving k u u^T (PSD), and the exact one has a negative eigenvalue
    u = (x[pairs[:, 1]] - x[pairs[:, 0]]) / l[:, None]
    uu = np.einsum("sa,sb->sab", u, u)
    assert np.allclose(Kcl[~stretched], k[~stretched, None, None] * uu[~stretched], rtol=1e-12, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(Kex[~stretched]).min(axis=1) < 0)
    assert np.all(np.linalg.eigvalsh(Kcl).min(axis=1) > -1e-9 * k.max())


@settings(max_examples=60, deadline=None, derandomize=True)
@given(d=st.tuples(*[st.floats(-2.0, 2.0) for _ in range(3)]).filter(lambda t: np.linalg.norm(t) > 1e-2),
       ratio=st.floats(0.2, 5.0), k=st.floats(1.0, 1e5))
def test_single_spring_jacobian_property(d, ratio, k):
    """One spring in any direction, length 0.01..3.5 m, L0 = ratio * l (compressed to 5x stretched):
    the exact K matches FD, and the force is k (l - L0) along u."""
    x = np.array([[0.3, -0.1, 0.2], [0.3, -0.1, 0.2]]) + np.array([[0, 0, 0], d])
    l = np.linalg.norm(d)
    s = Springs(2, np.array([[0, 1]]), np.array([k]), np.array([0.0]), np.array([ratio * l]),
                {"structural": slice(0, 1)})
    v = np.zeros_like(x)
    f = s.spring_forces(x, v)[0]
    assert np.allclose(f, k * (l - ratio * l) * np.asarray(d) / l, rtol=1e-12, atol=1e-12 * k * l)
    hh = 1e-6 * l
    Kj, Ki, _ = _fd_spring_jacobians(s, x, v, h=hh)
    K, _ = s.jacobian(x, exact=True)
    scale = k * max(1.0, ratio)            # |K| <= k max(1, L0 / l)
    assert np.abs(K[0] - Kj[0]).max() <= 1e-6 * scale
    assert np.abs(K[0] + Ki[0]).max() <= 1e-6 * scale


# --------------------------------------------------------------------------- (b) assembled
@pytest.mark.parametrize("damping", [False, True])
def test_assembled_dFdx_matches_central_differences(damping):
    """dF/dx from Model.linearize(c_x=-1, c_v=0) minus the mass part equals FD of Model.forces (stretched state)."""
    rng = np.random.default_rng(10)
    sim = ic.Simulator(_scene(damping=damping, drag=0.7, wind=[1.0, 0.5, 0.0]))
    m = sim.model
    x = _stretched_state(sim, rng)
    # with damping the dropped x-derivative of the damping force vanishes only at zero relative velocity
    v = np.tile([0.3, -0.2, 0.1], (m.n, 1)) if damping else rng.standard_normal(x.shape)
    A, f, _ = m.linearize(x, v, 0.0, c_x=-1.0, c_v=0.0)
    dFdx = A.toarray() - np.diag(np.repeat(m.masses, 3))
    ref = _fd_dense(lambda y: m.forces(y, v, 0.0), x, h=1e-6)
    scale = np.abs(ref).max()
    assert np.abs(dFdx - ref).max() <= 1e-6 * scale
    assert np.allclose(f, m.forces(x, v, 0.0), rtol=0, atol=1e-12 * np.abs(f).max())
    assert np.allclose(dFdx, dFdx.T, atol=1e-12 * scale)


def test_assembled_dFdv_matches_central_differences_with_drag():
    """dF/dv from Model.linearize(c_x=0, c_v=-1) minus the mass part equals FD of the force in v (springs + drag)."""
    rng = np.random.default_rng(11)
    c = 0.7
    sim = ic.Simulator(_scene(drag=c, wind=[1.0, 0.5, 0.0]))
    m = sim.model
    x = _mixed_state(sim, rng)
    v = rng.standard_normal(x.shape)
    A, _, _ = m.linearize(x, v, 0.0, c_x=0.0, c_v=-1.0)
    dFdv = A.toarray() - np.diag(np.repeat(m.masses, 3))
    ref = _fd_dense(lambda y: m.forces(x, y, 0.0), v, h=1e-4)
    assert np.abs(dFdv - ref).max() <= 1e-9 * np.abs(ref).max()
    # the drag part alone: -c A_i on the diagonal (lumped areas computed here from the triangles)
    tri = m.rest_positions[m.faces]      # lumped areas are fixed from the rest shape
    ta = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    areas = np.bincount(m.faces.ravel(), np.repeat(ta / 3, 3), minlength=m.n)
    assert areas.sum() == pytest.approx(1.0 * 0.8, rel=1e-12)
    no_springs = _scene(drag=c, wind=[1.0, 0.5, 0.0])
    del no_springs["cloth"]["springs"]
    m2 = ic.Simulator(no_springs).model
    A2, _, _ = m2.linearize(x, v, 0.0, c_x=0.0, c_v=-1.0)
    assert np.allclose(A2.toarray() - np.diag(np.repeat(m2.masses, 3)), np.diag(np.repeat(-c * areas, 3)),
                       rtol=1e-12, atol=0)


# --------------------------------------------------------------------------- (c) error order
def _central_errors(fun, J, y, dy, hs):
    """|(fun(y + h dy) - fun(y - h dy)) / 2h - J dy| for each h."""
    exact = (J @ dy.reshape(-1)).reshape(y.shape)
    return np.array([np.abs((fun(y + h * dy) - fun(y - h * dy)) / (2 * h) - exact).max() for h in hs])


def test_central_difference_error_order_is_two():
    """Halving h divides the central-difference error by 4 (O(h^2)) when the Jacobian is right.

    The error of the derivative estimate is h^2 F'''[dy,dy,dy]/6 + O(h^4), so successive ratios approach
    2^2 = 4 (equivalently the undivided residual F(y+h dy) - F(y-h dy) - 2h J dy is O(h^3), ratio 8).
    A wrong Jacobian leaves an O(1) error whose ratio approaches 1: the check can fail.
    """
    rng = np.random.default_rng(12)
    sim = ic.Simulator(_scene(damping=False))
    m = sim.model
    v = np.zeros((m.n, 3))
    fun = lambda y: m.forces(y, v, 0.0)   # noqa: E731

    # stretched state: the assembled (clamped) Jacobian is exact there
    x = _stretched_state(sim, rng)
    A, _, _ = m.linearize(x, v, 0.0, c_x=-1.0, c_v=0.0)
    J = A.toarray() - np.diag(np.repeat(m.masses, 3))
    dy = rng.standard_normal(x.shape)
    dy /= np.abs(dy).max()
    hs = 2e-2 * 0.5 ** np.arange(7)          # from 6 % of the 0.27 m spacing down to 0.1 %
    err = _central_errors(fun, J, x, dy, hs)
    ratios = err[:-1] / err[1:]
    assert np.all(err > 1e-9 * np.abs(J).max()), "errors must stay far above round-off for the ratio to mean much"
    assert np.all(np.abs(ratios[2:] - 4.0) < 0.01), ratios   # observed 3.9987 ... 3.99998
    order = np.log2(ratios[-1])
    assert order == pytest.approx(2.0, abs=0.02)
    residual = err * 2 * hs                   # undivided residual: third order
    assert residual[-2] / residual[-1] == pytest.approx(8.0, rel=1e-3)

    # compressed state: the exact per-spring Jacobian gives order 2 as well ...
    s = m.springs
    xc = _mixed_state(sim, rng, scale=0.85, noise=0.03)
    assert np.any(s.lengths(xc) < s.L0)
    Kex, _ = s.jacobian(xc, exact=True)
    Jex = _dense_from_blocks(m.n, s.i, s.j, Kex)
    err_ex = _central_errors(fun, Jex, xc, dy, hs)
    assert np.all(np.abs(err_ex[:-1] / err_ex[1:] - 4.0)[2:] < 0.01)
    # ... while the clamped one (a deliberate approximation there) does not converge: ratio -> 1
    Ac, _, _ = m.linearize(xc, v, 0.0, c_x=-1.0, c_v=0.0)
    Jcl = Ac.toarray() - np.diag(np.repeat(m.masses, 3))
    err_cl = _central_errors(fun, Jcl, xc, dy, hs)
    assert abs(err_cl[-2] / err_cl[-1] - 1.0) < 0.01


# --------------------------------------------------------------------------- (d) SPD
@pytest.mark.parametrize("seed", [0, 1])
def test_clamped_system_is_spd_where_exact_one_is_indefinite(seed):
    """Crumpled, compressed cloth with stiff springs at dt = 1/30 (backward Euler's c_x = h^2, c_v = h)."""
    rng = np.random.default_rng(20 + seed)
    sim = ic.Simulator(_scene(res=(6, 6), k=(2e4, 2e3, 2e2)))
    m, s = sim.model, sim.model.springs
    x = _mixed_state(sim, rng, scale=0.6, noise=0.05)    # spacing is 0.2 x 0.16 m: crumpled and compressed
    assert np.mean(s.lengths(x) < s.L0) > 0.5
    v = rng.standard_normal(x.shape)
    h = 1 / 30
    A, _, _ = m.linearize(x, v, 0.0, c_x=h * h, c_v=h)
    A = A.toarray()
    assert np.allclose(A, A.T, rtol=0, atol=1e-12 * np.abs(A).max())
    assert np.linalg.eigvalsh(A).min() > 0
    Kex, D = s.jacobian(x, exact=True)
    M = np.diag(np.repeat(m.masses, 3))
    A_exact = M - h * _dense_from_blocks(m.n, s.i, s.j, D) - h * h * _dense_from_blocks(m.n, s.i, s.j, Kex)
    assert np.linalg.eigvalsh(A_exact).min() < 0
    # the clamped system is SPD for any step: -dF/dx is positive semidefinite
    A0, _, _ = m.linearize(x, v, 0.0, c_x=-1.0, c_v=0.0)
    negK = -(A0.toarray() - M)
    assert np.linalg.eigvalsh(negK).min() > -1e-9 * np.abs(negK).max()


# --------------------------------------------------------------------------- (e) product
@pytest.mark.parametrize("stretched", [True, False])
def test_linearize_product_equals_dense_jacobian_times_w(stretched):
    rng = np.random.default_rng(30)
    sim = ic.Simulator(_scene(drag=0.5))
    m = sim.model
    x = _stretched_state(sim, rng) if stretched else _mixed_state(sim, rng, scale=0.8)
    v = rng.standard_normal(x.shape)
    w = rng.standard_normal(x.shape)
    A, _, _ = m.linearize(x, v, 0.0, c_x=-1.0, c_v=0.0)
    dFdx = A.toarray() - np.diag(np.repeat(m.masses, 3))
    _, _, kw = m.linearize(x, v, 0.0, c_x=0.3, c_v=0.1, w=w)
    ref = (dFdx @ w.reshape(-1)).reshape(w.shape)
    assert np.allclose(kw, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    if stretched:   # and the product is the directional derivative of the force (FD, v = 0 so damping drops out)
        v0 = np.zeros_like(x)
        hh = 1e-6
        fd = (m.forces(x + hh * w, v0, 0.0) - m.forces(x - hh * w, v0, 0.0)) / (2 * hh)
        assert np.abs(kw - fd).max() <= 1e-6 * np.abs(fd).max()


# --------------------------------------------------------------------------- (f) coincident vertices
@pytest.mark.parametrize("L0", [0.0, 0.3])
def test_zero_length_springs_are_finite(L0):
    """Coincident endpoints: finite force and Jacobians; L0 = 0 is the linear spring k d with Jacobian k I."""
    k, kd = 250.0, 1.5
    pairs = np.array([[0, 1], [1, 2], [2, 3]])
    s = Springs(4, pairs, np.full(3, k), np.full(3, kd), np.full(3, L0), {"structural": slice(0, 3)})
    rng = np.random.default_rng(40)
    x = np.zeros((4, 3))
    x[3] = [0.5, 0.1, 0.0]          # springs 0-1 and 1-2 have zero length, 2-3 not
    v = rng.standard_normal(x.shape)
    with np.errstate(all="raise"):
        f = s.spring_forces(x, v)
        for exact in (False, True):
            K, D = s.jacobian(x, exact=exact)
            assert np.all(np.isfinite(K)) and np.all(np.isfinite(D))
    assert np.all(np.isfinite(f))
    assert np.array_equal(f[:2], np.zeros((2, 3)))      # no direction: no elastic force, no damping force
    if L0 == 0.0:
        # f_i = k (x_j - x_i) exactly, at any length: Jacobian k I, matching FD through the coincident point
        assert np.allclose(K[:2], k * np.eye(3))
        Kj, Ki, _ = _fd_spring_jacobians(s, x, np.zeros_like(v), h=1e-7)
        assert np.allclose(Kj[:2], k * np.eye(3), rtol=1e-6)
        assert np.allclose(Ki[:2], -k * np.eye(3), rtol=1e-6)
        assert np.allclose(s.spring_forces(x + [[0, 0, 0], [1e-12, 0, 0], [0, 0, 0], [0, 0, 0]], 0 * v)[0],
                           [k * 1e-12, 0, 0], rtol=1e-9)
    else:
        assert np.array_equal(K[:2], np.zeros((2, 3, 3)))   # documented: no Jacobian without a direction


def test_coincident_vertices_through_the_model():
    """All vertices at one point: Model.forces and linearize are finite and A is SPD (it reduces to M + drag)."""
    sim = ic.Simulator(_scene(drag=0.5))
    m = sim.model
    x = np.tile([0.1, 0.2, 0.3], (m.n, 1))
    v = np.random.default_rng(41).standard_normal(x.shape)
    with np.errstate(all="raise"):
        A, f, kw = m.linearize(x, v, 0.0, c_x=(1 / 30) ** 2, c_v=1 / 30, w=v)
    A = A.toarray()
    assert np.all(np.isfinite(A)) and np.all(np.isfinite(f)) and np.all(np.isfinite(kw))
    assert np.linalg.eigvalsh(A).min() > 0
    # nearly coincident (a pair at 1e-12 m, below the documented 1e-9 x mean rest length): still finite
    x2 = sim.positions.copy()
    x2[1] = x2[0] + [1e-12, 0, 0]
    with np.errstate(all="raise"):
        A2, f2, _ = m.linearize(x2, v, 0.0, c_x=(1 / 30) ** 2, c_v=1 / 30)
    assert np.all(np.isfinite(A2.toarray())) and np.all(np.isfinite(f2))
