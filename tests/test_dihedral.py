"""Dihedral bending (:mod:`implicit_cloth.effects.dihedral`): its derivatives by Taylor remainders
(``check_force``), the energy constant on cylinders, a cantilever strip against the beam formula at three
resolutions (and the bend springs on the same strip), the two back-ends against each other, the scene's
``[cloth.bending]`` and whole runs.

Convention checked here: ``U = sum_e B w_e (theta_e - theta_0e)^2 / 2`` with ``w_e = |e_0|^2 / A_e`` (rest edge
length squared over the rest area of the hinge's two triangles), ``B`` the bending modulus in N m.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from test_forces import _hessian, check_force
from test_membrane import _hanging as _membrane_hanging

import implicit_cloth as ic
from implicit_cloth import cloth
from implicit_cloth.assembly import SystemMatrix
from implicit_cloth.effects.dihedral import Dihedral, hinges
from implicit_cloth.effects.membrane import Membrane
from implicit_cloth.effects.springs import Springs
from implicit_cloth.errors import SceneError


def _sheet(size=(1.0, 0.8), res=(5, 4)):
    return cloth.grid(size, res, plane="xy", kinds=())


def _dihedral(k=2.0, kd=0.3, size=(1.0, 0.8), res=(5, 4), rest=None):
    geo = _sheet(size, res)
    return Dihedral(geo.n_vertices, hinges(geo.faces), geo.positions if rest is None else rest, k, kd), geo


def _bent(geo, rng, scale=0.1):
    x = geo.positions + scale * rng.standard_normal(geo.positions.shape)
    return x, rng.standard_normal(x.shape)


# --------------------------------------------------------------------------- hinges
def test_hinges_of_a_grid():
    """Every interior edge once, its two wings on either side; the pairs are the six of each hinge, the wings'
    pair not a triangle edge."""
    geo = _sheet(res=(4, 3))
    h = hinges(geo.faces)
    nx, ny = 4, 3
    # interior edges: vertical (nx - 2) (ny - 1), horizontal (nx - 1) (ny - 2), one diagonal per cell
    assert len(h) == (nx - 2) * (ny - 1) + (nx - 1) * (ny - 2) + (nx - 1) * (ny - 1)
    edges = {tuple(sorted(e)) for f in geo.faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    for a, b, c, d in h:
        assert tuple(sorted((a, b))) in edges and c != d
        assert tuple(sorted((a, c))) in edges and tuple(sorted((b, d))) in edges
        assert tuple(sorted((c, d))) not in edges
    m = Dihedral(geo.n_vertices, h, geo.positions, 1.0, 0.0)
    p = {tuple(q) for q in m.pairs()}
    assert all(tuple(sorted((c, d))) in p for _, _, c, d in h)
    assert len(p) == len(np.unique(np.sort(np.concatenate([h[:, [i, j]] for i in range(4) for j in range(i + 1, 4)]),
                                           axis=1), axis=0))
    assert np.abs(m.angles(geo.positions)).max() == 0.0 and m.energy(geo.positions) == 0.0


def test_signed_angle_by_atan2_up_to_pi():
    """One hinge folded by phi (its wing rotated about the edge): theta = -phi for phi in (-pi, pi), with the
    sign of the side it folds to, also beyond pi / 2 (where acos of the normals' product loses accuracy)."""
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0.3, 1, 0], [0.6, -1, 0]])
    h = np.array([[0, 1, 2, 3]])
    m = Dihedral(4, h, x, 1.0, 0.0)
    for phi in (-3.0, -1.7, -0.2, 1e-7, 0.5, 2.0, 3.1):
        y = x.copy()
        y[2] = [0.3, np.cos(phi), np.sin(phi)]
        assert m.angles(y)[0] == pytest.approx(-phi, rel=1e-12)
        assert m.energy(y) == pytest.approx(0.5 * 1.0 * (1.0 / 1.0) * phi ** 2, rel=1e-12)   # w = 1^2 / (1/2 + 1/2)


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("kd", [0.3, 0.0], ids=["damped", "undamped"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_and_damping_by_their_orders(seed, kd):
    """Energy against gradient (order 2) and the damping's dissipation against its force (order 2; quadratic in
    v, so its Hessian blocks leave round-off) at random bent states (hinges up to ~2 rad)."""
    rng = np.random.default_rng(seed)
    m, geo = _dihedral(kd=kd)
    x, v = _bent(geo, rng)
    assert np.abs(m.angles(x)).max() > 1.0
    o = check_force(m, geo.n_vertices, x, v, 0.0, rng)
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    assert ("dissipation" in o) == bool(kd)
    if kd:
        assert o["dissipation"][-1] == pytest.approx(2.0, abs=0.05), o
        assert "dissipation_hessian" not in o


@pytest.mark.parametrize("seed", [0, 1])
def test_gauss_newton_hessian_is_exact_at_the_rest_angle(seed):
    """Where every hinge is at its rest angle (a rigid motion of the rest shape, flat or curved) the dropped term
    ``B w (theta - theta_0) d2theta/dx2`` vanishes: the Hessian's remainder is third order."""
    rng = np.random.default_rng(seed)
    geo = _sheet()
    rest = geo.positions.copy()
    rest[:, 2] = 0.2 * np.sin(2.0 * rest[:, 0]) + 0.1 * rest[:, 1] ** 2     # a curved rest shape
    m = Dihedral(geo.n_vertices, hinges(geo.faces), rest, 2.0, 0.3)
    assert np.abs(m.theta0).max() > 0.05
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    x = rest @ q.T + [0.1, -0.2, 0.3]
    v = rng.standard_normal(x.shape)
    assert np.abs(m.angles(x) - m.theta0).max() < 1e-12
    o = check_force(m, geo.n_vertices, x, v, 0.0, rng)
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    assert o["hessian"][-1] == pytest.approx(3.0, abs=0.1), o


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hessian_is_positive_semidefinite_and_differs_by_the_dropped_term(seed):
    """Away from the rest angle the system's blocks stay PSD, the exact Hessian (finite differences of the exact
    gradient) is indefinite, and their difference is the dropped ``sum_e B w_e (theta - theta_0)
    d2theta_e/dx2`` (each hinge's second derivatives of theta by central differences of its gradient)."""
    rng = np.random.default_rng(seed)
    m, geo = _dihedral(kd=0.0)
    x, v = _bent(geo, rng)
    n = geo.n_vertices
    H = _hessian(m, n, x, v, 0.0, 1.0, 0.0)
    top = np.abs(H).max()
    assert np.linalg.eigvalsh(H).min() > -1e-10 * top

    def grad(y):
        g = np.zeros_like(y)
        m.gradient(y, 0.0, g)
        return g.ravel()

    def dtheta(y, e):      # d theta_e / dx of hinge e alone
        one = Dihedral(n, m.hinges[e:e + 1], geo.positions, 1.0, 0.0)
        one.weight[:] = 1.0
        g = np.zeros_like(y)
        one.gradient(y, 0.0, g)
        return g.ravel() / (one.angles(y)[0] - one.theta0[0])

    eps = 1e-6
    He = np.zeros((3 * n, 3 * n))
    D = np.zeros((3 * n, 3 * n))
    d = wrap_angles = m.angles(x) - m.theta0
    for j in range(3 * n):
        dx = np.zeros(3 * n)
        dx[j] = eps
        He[:, j] = (grad(x + dx.reshape(-1, 3)) - grad(x - dx.reshape(-1, 3))) / (2 * eps)
    He = 0.5 * (He + He.T)
    assert np.linalg.eigvalsh(He).min() < -1e-3 * top
    for e in range(len(m.hinges)):
        col = np.zeros((3 * n, 3 * n))
        for j in np.ravel(3 * m.hinges[e][:, None] + np.arange(3)):
            dx = np.zeros(3 * n)
            dx[j] = eps
            col[:, j] = (dtheta(x + dx.reshape(-1, 3), e) - dtheta(x - dx.reshape(-1, 3), e)) / (2 * eps)
        D += m.k[e] * m.weight[e] * wrap_angles[e] * col
    assert np.abs(d).max() < np.pi
    assert np.allclose(He - H, 0.5 * (D + D.T), rtol=0, atol=1e-6 * top)


def test_linearize_gives_the_force_and_the_product_with_its_blocks():
    rng = np.random.default_rng(7)
    m, geo = _dihedral()
    x, v = _bent(geo, rng)
    w = rng.standard_normal(x.shape)
    S = SystemMatrix(m.n, m.pairs(), "numpy")
    m.bind(S)
    S.reset_diagonal(np.zeros(m.n))
    f, kw, F = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
    m.linearize(x, v, 0.0, 0.01, 0.1, w, S, kw, f)
    m.force(x, v, 0.0, F)
    assert np.allclose(f, F, rtol=1e-13, atol=1e-15)
    K = _hessian(m, m.n, x, v, 0.0, 1.0, 0.0)
    Dv = _hessian(m, m.n, x, v, 0.0, 0.0, 1.0)
    assert np.allclose(kw.ravel(), -K @ w.ravel(), rtol=1e-12, atol=1e-12 * np.abs(kw).max())
    assert np.allclose(S.finalize().toarray(), 0.01 * K + 0.1 * Dv, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------- the constant
def _cylinder(p, axis, R):
    """Positions ``p`` (in the z = 0 plane) bent isometrically onto a cylinder of radius R, curving along
    ``axis`` (a unit vector in the plane)."""
    axis = np.asarray(axis, dtype=float)
    perp = np.array([-axis[1], axis[0], 0.0])
    s, t = p @ axis, p @ perp
    return np.outer(R * np.sin(s / R), axis) + np.outer(t, perp) + np.outer(R * (1 - np.cos(s / R)), [0, 0, 1.0])


@pytest.mark.parametrize("along", [0, 1])
def test_a_grid_bent_into_a_cylinder_stores_b_over_2r2_per_area(along):
    """A grid sheet bent onto a cylinder of radius R along either axis, at two resolutions: the energy is the
    plate's ``B / (2 R^2)`` per unit area over the cells whose edges along the axis are hinges (every cell but
    one row or column of them), to round-off: the edges along the axis bend by ``h / R`` exactly, with
    ``w = h^2 / h^2``, and nothing else bends. Over the whole sheet it tends to ``B / (2 R^2) L^2`` as
    ``1 - 1 / (n - 1)``."""
    B, R, L = 0.37, 0.5, 0.4
    for n in (9, 33):
        geo = cloth.grid((L, L), (n, n), plane="xy", kinds=())
        m = Dihedral(geo.n_vertices, hinges(geo.faces), geo.positions, B, 0.0)
        x = _cylinder(geo.positions, np.eye(3)[along], R)
        h = L / (n - 1)
        assert m.energy(x) == pytest.approx(B / (2 * R ** 2) * (n - 2) * (n - 1) * h * h, rel=1e-12)
        assert m.energy(x) / (B / (2 * R ** 2) * L * L) == pytest.approx(1 - 1 / (n - 1), rel=1e-12)


def _equilateral(n, h):
    """A mesh of equilateral triangles (side h), n x n vertices, in the z = 0 plane."""
    pts = [[(i + 0.5 * (j % 2)) * h, j * h * np.sqrt(3) / 2, 0.0] for j in range(n) for i in range(n)]
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            faces += [[a, b, c], [b, d, c]] if j % 2 == 0 else [[a, d, c], [a, b, d]]
    return np.array(pts), np.array(faces)


@pytest.mark.parametrize("angle", [0.0, 0.3, np.pi / 2])
def test_an_equilateral_mesh_bent_into_a_cylinder_converges_to_b_over_2r2(angle):
    """The same constant on a mesh of equilateral triangles, for three directions of the cylinder's axis: the
    energy over the hinges' dual area (``A_e / 3`` each) tends to ``B / (2 R^2)`` (within 2 % at 12 x 12
    vertices, 0.5 % at 48 x 48: the sheet's border)."""
    B, R = 0.37, 0.5
    errs = []
    for n in (12, 48):
        p, f = _equilateral(n, 0.4 / n)
        m = Dihedral(len(p), hinges(f), p, B, 0.0)
        x = _cylinder(p, [np.cos(angle), np.sin(angle), 0.0], R)
        errs.append(abs(m.energy(x) / (B / (2 * R ** 2) * m.area.sum() / 3) - 1))
    assert errs[0] < 0.035 and errs[1] < 0.01 and errs[1] < errs[0] / 2, errs


# --------------------------------------------------------------------------- the cantilever
L_FREE, WIDTH, RHO, G, B_STRIP = 0.2, 0.02, 0.2, 9.81, 0.1
#: the membrane's in-plane stiffness, N/m
K_PLANE = 1e4


def _strip(n):
    """A strip one cell wide in the xy plane: columns 0 and 1 pinned (the clamp), ``n`` free columns after
    them, spacing ``h = L / (n + 1/2)`` so that the free length from the root hinge's dual edge (half a cell
    before column 1... see :func:`_cantilever`) to the tip is L."""
    h = L_FREE / (n + 0.5)
    geo = cloth.grid(((n + 1) * h, WIDTH), (n + 2, 2), center=((n + 1) * h / 2, 0.0, 0.0), plane="xy",
                     kinds=("structural", "shear", "bend"))
    return geo, h


def _reduction(n, pinned, tie):
    """``R`` (3N, Q): positions ``x = x_rest + R q`` with the pinned vertices fixed, the free ones' x and y free,
    and one z for each pair in ``tie`` (its first vertex free), one for each other free vertex."""
    free = np.ones(n, bool)
    free[pinned] = False
    cols = [[3 * i + c] for i in np.flatnonzero(free) for c in (0, 1)]
    tied = set()
    for i, j in (tie if tie is not None else []):
        if free[i]:
            cols.append([3 * i + 2, 3 * j + 2])
            tied |= {int(i), int(j)}
    cols += [[3 * i + 2] for i in np.flatnonzero(free) if int(i) not in tied]
    R = np.zeros((3 * n, len(cols)))
    for q, rows in enumerate(cols):
        R[rows, q] = 1.0
    return R


def _static(geo, forces, pinned, g, tie=None, tol=1e-8, start=None):
    """The strip's equilibrium under gravity (lumped masses: a third of each triangle, the tip half a column's)
    by Levenberg-Marquardt-damped Newton on the total energy with the forces' own blocks (dense). The unknowns:
    the free vertices' x and y, and their z, except that the vertex pairs in ``tie`` share one z (kept level
    across: the beam's straight cross-sections)."""
    n = geo.n_vertices
    mass = RHO * cloth.lumped_areas(geo.positions, geo.faces)
    pairs = np.concatenate([f.pairs() for f in forces])
    S = SystemMatrix(n, pairs, "numpy")
    for f in forces:
        f.bind(S)
    R = _reduction(n, pinned, tie)
    grav = np.outer(mass, [0.0, 0.0, -g])

    def energy(y):
        return sum(f.energy(y) for f in forces) - float(np.sum(grav * y))

    def grad(y):
        out = -grav.copy()
        for f in forces:
            f.gradient(y, 0.0, out)
        return R.T @ out.ravel()

    x = geo.positions.copy() if start is None else start.copy()
    mu = 1e-6
    e0 = energy(x)
    for _ in range(2000):
        S.reset_diagonal(np.zeros(n))
        for f in forces:
            f.linearize(x, np.zeros_like(x), 0.0, 1.0, 0.0, None, S, None, np.zeros_like(x))
        Hm = R.T @ S.finalize().toarray() @ R
        gr = grad(x)
        if np.abs(gr).max() < tol * mass.sum() * g:
            break
        scale = np.abs(np.diag(Hm)).max()
        while mu < 1e3:
            step = np.linalg.solve(Hm + mu * scale * np.eye(len(gr)), -gr)
            y = x + (R @ step).reshape(-1, 3)
            e1 = energy(y)
            if e1 <= e0 or np.abs(grad(y)).max() < 0.5 * np.abs(gr).max():
                x, e0 = y, e1
                mu = max(mu / 3, 1e-14)
                break
            mu *= 10
        else:       # no step lowers the energy: round-off; the gradient must be small
            break
    assert np.abs(grad(x)).max() < 10 * tol * mass.sum() * g, np.abs(grad(x)).max() / (mass.sum() * g)
    return x


def _cantilever(n, bending, straight=True):
    """Tip deflection of the strip with ``n`` free columns, with the given bending (``"dihedral"``: modulus
    ``B_STRIP``; or a bend-spring constant in N/m), a stiff membrane in-plane (k = 1e4 N/m: its stretch under
    this load is ~1e-7), and the beam's figure for its lumped loads.

    The beam: the root hinge (column 1, between the clamp's column 0 and the first free column) bends over its
    dual length, half a cell each side, so the beam is clamped half a cell before column 1 and the free length
    to the tip is ``(n + 1/2) h = L``. Its loads are the free vertices' lumped masses (the tip's half), the
    continuum's ``w = RHO g W`` per length to O(h^2)."""
    geo, h = _strip(n)
    pinned = np.array([0, 1, n + 2, n + 3])
    uv = geo.positions[geo.faces][:, :, :2]
    forces: list = [Membrane(geo.n_vertices, geo.faces, uv, (K_PLANE,) * 3, (0.0, 0.0, 0.0), exact=True)]
    if bending == "dihedral":
        forces.append(Dihedral(geo.n_vertices, hinges(geo.faces), geo.positions, B_STRIP, 0.0))
    else:
        p = geo.springs["bend"]
        L0 = np.linalg.norm(geo.positions[p[:, 1]] - geo.positions[p[:, 0]], axis=1)
        forces.append(Springs(geo.n_vertices, p, np.full(len(p), float(bending)), np.zeros(len(p)), L0,
                              {"bend": slice(0, len(p))}))
    tie = np.stack([np.arange(n + 2), np.arange(n + 2) + n + 2], 1) if straight else None
    start = None
    if bending != "dihedral":     # flat, bend springs have no stiffness across: start from a bent strip
        start = geo.positions.copy()
        start[:, 2] = -beam_deflection() * (start[:, 0] / start[:, 0].max()) ** 2
    x = _static(geo, forces, pinned, G, tie, 1e-8 if bending == "dihedral" else 1e-6, start)
    return -x[[n + 1, 2 * n + 3], 2].mean()


def beam_deflection():
    """``delta = w L^4 / (8 B W)``: the small-deflection cantilever under its weight ``w = RHO g W`` per length."""
    return RHO * G * WIDTH * L_FREE ** 4 / (8 * B_STRIP * WIDTH)


def test_cantilever_tip_deflection_matches_the_beam_at_three_resolutions():
    """A strip 0.2 m long and 0.02 m wide (one cell across), clamped at one end (two columns of vertices
    pinned), at rest under gravity (static equilibrium of the same forces: dihedral bending ``B = 0.1 N m``, a
    stiff membrane in-plane, k = 1e4 N/m), each column's two vertices at one height (the beam's straight
    cross-sections, see the next test for why): the tip deflection against ``w L^4 / (8 B W)`` = 3.924 mm (1.96 %
    of L: small deflection) at 8, 16 and 32 free columns. Measured: 3.8957, 3.9158, 3.9221 mm (-0.72 %,
    -0.21 %, -0.05 %): second-order convergence to the beam (the midpoint rule of the hinges' curvatures and the
    lumped loads, O(h^2); what is left at 32, ~0.05 %, the geometric nonlinearity at this deflection).
    Tolerances 1.5 %, 0.5 %, 0.2 % (about twice the measured errors); a constant off by a factor, a root or the
    loads half a cell off (O(h): 1/n = 12 %, 6 %, 3 %) fail them."""
    ref = beam_deflection()
    assert ref / L_FREE == pytest.approx(0.0196, abs=1e-4)
    got = {n: _cantilever(n, "dihedral") for n in (8, 16, 32)}
    err = {n: got[n] / ref - 1 for n in got}
    assert abs(err[8]) < 0.015 and abs(err[16]) < 0.005 and abs(err[32]) < 0.002, (got, err)
    assert abs(err[32]) < abs(err[16]) < abs(err[8])


def test_free_cantilever_strip_one_cell_wide_twists_on_the_grid():
    """The same strip with its cross-sections free: on the grids' triangulation (every cell cut by the same
    diagonal) the hinge energy couples bending with twist, so a strip free to twist is softer, and by how much
    depends on the cells' aspect W / h. A hinge across the strip has its two wings on different rows, so its
    angle measures ``h z_xx + W z_xy``, not ``z_xx``; the diagonals' hinges measure the twist alone; a square grid's
    energy per area tends to ``B/2 [(z_xx + z_xy)^2 + (z_yy + z_xy)^2 + 4 z_xy^2]``, whose minimum over a free
    twist is 4/5 of the cylinder's. Measured on this strip (W = 0.02 m, one cell across): 1.130, 1.469, 1.782
    times the beam's deflection at 8, 16, 32 columns (W / h = 0.85, 1.65, 3.25). This is the model's limit on
    such strips (a property of the triangulation, not of the constant); asserted here so that a change shows."""
    ref = beam_deflection()
    got = [_cantilever(n, "dihedral", straight=False) / ref for n in (8, 16, 32)]
    assert got == pytest.approx([1.130, 1.469, 1.782], abs=0.005), got


def test_bend_springs_are_not_resolution_independent_on_the_same_strip():
    """The same strip (cross-sections straight) with bend springs (every other vertex along it, k = 1e6 N/m)
    instead of the dihedral bending: a flat bend spring has no bending stiffness to first order (its length
    changes by ``-h theta^2 / 4``: its energy is quartic in the angle), so the strip sags until that stiffness
    holds its weight, and how far depends on the resolution at one constant. Measured: 23.5, 38.6 and 45.1 times
    the beam's 3.9 mm (0.092, 0.151, 0.177 m, nearly hanging) at 8, 16, 32 columns: a factor 1.9 from the
    coarsest to the finest, against the dihedral bending's 0.993, 0.998, 1.000."""
    ref = beam_deflection()
    got = [_cantilever(n, 1e6) / ref for n in (8, 16, 32)]
    assert got == pytest.approx([23.46, 38.60, 45.15], rel=0.01), got
    assert got[2] / got[0] > 1.8


# --------------------------------------------------------------------------- back-ends
def test_numpy_and_numba_agree():
    """Energy, force, gradient, ``(dF/dx) w`` and the assembled blocks: the same to round-off (1e-12 relative)."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(11)
    geo = _sheet((1.0, 0.8), (7, 6))
    x, v = _bent(geo, rng)
    w = rng.standard_normal(x.shape)
    out = {}
    for acc in ("numpy", "numba"):
        m = Dihedral(geo.n_vertices, hinges(geo.faces), geo.positions, 2.0, 0.3)
        S = SystemMatrix(m.n, m.pairs(), acc)
        m.bind(S)
        assert m.accelerator == acc
        S.reset_diagonal(np.ones(m.n))
        f, kw, F, g = (np.zeros_like(x) for _ in range(4))
        m.linearize(x, v, 0.0, 0.01, 0.1, w, S, kw, f)
        m.force(x, v, 0.0, F)
        m.gradient(x, 0.0, g)
        out[acc] = (S.finalize().toarray(), f, kw, F, g, np.array([m.energy(x), m.dissipation(x, v, 0.0)]))
    for a, b in zip(out["numpy"], out["numba"]):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(a).max())


# --------------------------------------------------------------------------- scenes
BENDING = {"model": "dihedral", "stiffness": 1e-3, "damping": 1e-5}


def _hanging(bending=None, **cloth_keys):
    """The membrane tests' hanging cloth, with ``[cloth.bending]`` = ``bending`` when given."""
    if bending is not None:
        cloth_keys["bending"] = bending
    return _membrane_hanging(**cloth_keys)


def test_a_scene_without_the_bending_table_is_unchanged():
    """No ``[cloth.bending]`` (or ``model = "springs"``): no bending key in the normalised scene (or only the
    model), the same effects and springs as before, bit for bit the same run."""
    s = ic.Scene(_hanging())
    assert "bending" not in s.data["cloth"] and "bending" not in s.effects
    model = ic.Simulator(_hanging()).model
    assert [e.name for e in model.effects] == ["gravity", "springs"]
    assert list(model.springs.kinds) == ["structural", "shear", "bend"]
    springs = ic.Scene(_hanging({"model": "springs"}))
    assert springs.data["cloth"]["bending"] == {"model": "springs"} and springs.effects == s.effects
    runs = []
    for sc in (_hanging(), _hanging({"model": "springs"})):
        sc["simulation"]["duration"] = 0.1
        runs.append(ic.Simulator(sc).run().positions)
    assert np.array_equal(runs[0], runs[1])


def test_dihedral_replaces_the_bend_springs():
    scene = _hanging(BENDING)
    del scene["cloth"]["springs"]["bend"]
    s = ic.Scene(scene)
    assert list(s.data["cloth"]["springs"]) == ["structural", "shear"]
    assert s.effects == ["gravity", "structural", "shear", "bending"]
    assert s.data["cloth"]["bending"] == {"model": "dihedral", "stiffness": 1e-3, "damping": 1e-5,
                                          "rest_angle": "mesh"}
    model = ic.Simulator(scene).model
    assert [e.name for e in model.effects] == ["gravity", "springs", "bending"]
    assert list(model.springs.kinds) == ["structural", "shear"]
    b = model.effects[-1]
    assert len(b.hinges) == 8 * 9 * 2 + 9 * 9 and np.all(b.k == 1e-3) and np.all(b.kd == 1e-5)
    e = b.pairs()
    assert model.system.has_blocks(e[:, 0], e[:, 1]).all()      # the wings' pairs are on the pattern


def test_hanging_cloth_with_dihedral_bending_runs_ok():
    scene = _hanging(BENDING)
    del scene["cloth"]["springs"]["bend"]
    traj = ic.Simulator(scene).run()
    assert traj.report["status"] == "ok", traj.report.get("health")
    x = traj.positions[-1]
    assert np.all(np.isfinite(x)) and x[:, 2].min() < 0.5


def test_drape_on_a_sphere_with_dihedral_bending():
    """The drape example at 16² with the dihedral bending instead of the bend springs: status ok, on the sphere,
    not through it."""
    data = ic.load_scene("examples/drape_sphere.toml").source
    c = data["cloth"]
    c["resolution"] = [16, 16]
    c["springs"] = {k: v for k, v in c["springs"].items() if k != "bend"}
    c["bending"] = {"model": "dihedral", "stiffness": 1e-4, "damping": 1e-6}
    data["simulation"]["duration"] = 0.8
    traj = ic.Simulator(data).run()
    r = traj.report
    assert r["status"] == "ok", r.get("health")
    assert r["collision"]["contacts"] > 0
    assert np.linalg.norm(traj.positions, axis=2).min() > 0.3 + 0.5 * data["collision"]["thickness"]
    assert traj.positions[-1][:, 2].max() > 0.25


def test_a_material_supplies_the_bending_modulus():
    """Denim's KES-FB2 bending rigidity (0.172 gf cm^2/cm, Hindawi J. Textiles 2016, 4614168, Table 5, fabric A)
    as N m; a preset without a measurement, or none, is an error naming the key."""
    scene = _hanging({"model": "dihedral"}, material="denim")
    del scene["cloth"]["springs"]
    data = ic.Scene(scene).data["cloth"]
    assert data["bending"]["stiffness"] == pytest.approx(0.172 * 9.80665e-5) == ic.MATERIALS["denim"].bending
    assert data["bending"]["damping"] == 0.0 and "bend" not in data["springs"]
    assert ic.Scene(copy.deepcopy(ic.Scene(scene).data)).data == ic.Scene(scene).data     # a report loads back
    scene["cloth"]["material"] = "cotton"
    with pytest.raises(SceneError, match=r"cloth\.bending\.stiffness: missing \(material 'cotton' has no measured"):
        ic.Scene(scene)
    del scene["cloth"]["material"]
    with pytest.raises(SceneError, match=r"cloth\.bending\.stiffness: missing \(the sheet's bending modulus"):
        ic.Scene(scene)


@pytest.mark.parametrize("table, message", [
    ({"model": "hinges"}, "cloth.bending.model: must be one of"),
    ({"model": "dihedral", "stiffness": 0.0}, "cloth.bending.stiffness: must be a finite number > 0, got 0"),
    ({"model": "dihedral", "stiffness": 1.0, "damping": -1.0}, "cloth.bending.damping: must be a finite number >= 0,"
                                                               " got -1"),
    ({"model": "dihedral", "stiffness": 1.0, "rest_angle": "bent"}, "cloth.bending.rest_angle: must be one of"),
    ({"model": "dihedral", "stifness": 1.0}, "cloth.bending.stifness: unknown key (did you mean 'stiffness'?)"),
    ({"model": "springs", "stiffness": 1.0}, "cloth.bending.stiffness: not used with cloth.bending.model = "
                                             "'springs'"),
    ("stiff", "cloth.bending: must be a table, got 'stiff'"),
])
def test_bending_table_errors_name_the_key_and_value(table, message):
    scene = _hanging(table)
    del scene["cloth"]["springs"]["bend"]
    with pytest.raises(SceneError) as e:
        ic.Scene(scene)
    assert message in str(e.value)


def test_bend_springs_given_with_dihedral_are_an_error():
    with pytest.raises(SceneError, match=r"cloth\.springs\.bend: not used with cloth\.bending\.model = 'dihedral'"):
        ic.Scene(_hanging(BENDING))


def test_pieces_and_meshes_each_with_their_own_bending(tmp_path):
    """Several pieces: a grid with the dihedral bending, one with bend springs, a mesh (OBJ) with the dihedral
    bending and its rest angles from the rest mesh (a bent sheet: at rest, no force)."""
    a = _hanging(BENDING)["cloth"]
    del a["springs"]["bend"]
    b = _hanging()["cloth"]
    b["center"] = [0.0, 0.0, 0.5]
    geo = cloth.grid((1.0, 1.0), (5, 5), plane="xy", kinds=())
    p = geo.positions.copy()
    p[:, 2] = 0.2 * p[:, 0] ** 2 + 0.1
    (tmp_path / "bent.obj").write_text("\n".join([f"v {q[0]} {q[1]} {q[2]}" for q in p]
                                                 + [f"f {f[0] + 1} {f[1] + 1} {f[2] + 1}" for f in geo.faces]) + "\n")
    c = {"mesh": str(tmp_path / "bent.obj"), "mass": 0.05,
         "springs": {"structural": {"stiffness": 1000.0}},
         "bending": {"model": "dihedral", "stiffness": 2e-3}}
    model = ic.Simulator({"cloth": [a, b, c], "effects": {"gravity": [0.0, 0.0, -9.81]}}).model
    assert [e.name for e in model.effects] == ["gravity", "springs", "bending"]
    bend = model.effects[-1]
    n1 = 8 * 9 * 2 + 81
    n3 = 3 * 4 * 2 + 16
    assert len(bend.hinges) == n1 + n3
    assert np.all(bend.hinges[:n1] < 100) and np.all(bend.hinges[n1:] >= 200)
    assert np.all(bend.k[:n1] == 1e-3) and np.all(bend.k[n1:] == 2e-3) and np.all(bend.kd[n1:] == 0.0)
    assert np.abs(bend.theta0[n1:]).max() > 0.01
    f = np.zeros((model.n, 3))
    bend.force(model.rest_positions, np.zeros((model.n, 3)), 0.0, f)
    assert np.abs(f).max() < 1e-12
    assert set(model.springs.kinds) == {"structural", "shear", "bend"}
    # rest_angle = "flat": the bent mesh is pushed flat
    c["bending"]["rest_angle"] = "flat"
    m = ic.Simulator({"cloth": c}).model
    flat = m.effects[-1]
    assert np.all(flat.theta0 == 0.0) and flat.energy(m.rest_positions) > 0
