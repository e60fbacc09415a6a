"""BW98's triangle membrane (:mod:`implicit_cloth.effects.membrane`): its derivatives by Taylor remainders
(``check_force``), constant-strain patches against their closed forms, a hanging strip at rest against a
uniaxial bar's, the two back-ends against each other, the scene's ``[cloth.membrane]`` and whole runs.

Convention checked here: energy per rest area ``k_u C_u^2 / 2 + k_v C_v^2 / 2 + k_s C_s^2 / 2`` with
``C_u = |w_u| - 1``, ``C_v = |w_v| - 1``, ``C_s = w_u . w_v`` (k in N/m).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from test_forces import _hessian, check_force

import implicit_cloth as ic
from implicit_cloth import cloth
from implicit_cloth.assembly import SystemMatrix
from implicit_cloth.effects.membrane import Membrane, metric_rest_coordinates
from implicit_cloth.errors import SceneError

K = (800.0, 500.0, 90.0)
KD = (0.3, 0.2, 0.1)


def _sheet(size=(1.0, 0.8), res=(5, 4)):
    """A flat grid in the xy plane and its triangles' rest (u, v) = (x, y)."""
    geo = cloth.grid(size, res, plane="xy", kinds=())
    return geo, geo.positions[geo.faces][:, :, :2]


def _membrane(k=K, kd=KD, exact=False, size=(1.0, 0.8), res=(5, 4)):
    geo, uv = _sheet(size, res)
    return Membrane(geo.n_vertices, geo.faces, uv, k, kd, exact=exact), geo


def _random_state(geo, rng, scale=0.1):
    x = geo.positions + scale * rng.standard_normal(geo.positions.shape)
    return x, rng.standard_normal(x.shape)


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("kd", [KD, (0.0, 0.0, 0.0)], ids=["damped", "undamped"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_derivatives_by_their_orders(seed, kd):
    """Energy against gradient (order 2), the exact Hessian (order 3) and the damping's dissipation against its
    force (order 2; quadratic, so its Hessian leaves round-off) at random deformed states: compressed, sheared
    and stretched triangles at once."""
    rng = np.random.default_rng(seed)
    m, geo = _membrane(kd=kd, exact=True)
    x, v = _random_state(geo, rng)
    C = m.strains(x)
    assert (C[:, :2] < 0).any() and (C[:, :2] > 0).any() and (np.abs(C[:, 2]) > 0.01).any()
    o = check_force(m, geo.n_vertices, x, v, 0.0, rng)
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    assert o["hessian"][-1] == pytest.approx(3.0, abs=0.1), o
    assert ("dissipation" in o) == any(kd)
    if any(kd):
        assert o["dissipation"][-1] == pytest.approx(2.0, abs=0.05), o
        assert "dissipation_hessian" not in o       # the damping's dv blocks are exact


def test_system_hessian_is_exact_in_pure_tension_without_shear():
    """The clamped / Gauss-Newton blocks the step uses equal the exact Hessian where every thread is stretched
    and no triangle sheared (a rotated, stretched sheet): order 3 there."""
    rng = np.random.default_rng(5)
    m, geo = _membrane()
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    x = (geo.positions * [1.15, 1.08, 1.0]) @ q.T + [0.1, 0.2, 0.3]
    C = m.strains(x)
    assert np.all(C[:, :2] > 0.05) and np.abs(C[:, 2]).max() < 1e-12
    v = rng.standard_normal(x.shape)
    o = check_force(m, geo.n_vertices, x, v, 0.0, rng)
    assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), o
    assert o["hessian"][-1] == pytest.approx(3.0, abs=0.1), o
    exact = Membrane(m.n, m.faces, _sheet()[1], K, KD, exact=True)
    H = _hessian(m, m.n, x, v, 0.0, 1.0, 0.0)
    assert np.allclose(H, _hessian(exact, m.n, x, v, 0.0, 1.0, 0.0), rtol=1e-12, atol=1e-9 * np.abs(H).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_system_hessian_is_positive_semidefinite_and_differs_only_by_the_dropped_terms(seed):
    """At random states (compressed and sheared) the exact Hessian is indefinite, the system's is not; their
    difference is the dropped terms: ``k (a_exact - a) (I - n n^T)`` of compressed threads and the shear's
    ``k_s C_s (b_i c_j + c_i b_j) I``, written again here."""
    rng = np.random.default_rng(seed)
    m, geo = _membrane()
    exact = Membrane(m.n, m.faces, _sheet()[1], K, KD, exact=True)
    x, v = _random_state(geo, rng)
    H = _hessian(m, m.n, x, v, 0.0, 1.0, 0.0)
    He = _hessian(exact, m.n, x, v, 0.0, 1.0, 0.0)
    top = np.abs(H).max()
    assert np.linalg.eigvalsh(H).min() > -1e-10 * top
    assert np.linalg.eigvalsh(He).min() < -1e-3 * top
    # the dropped terms
    D = np.zeros((m.n, 3, m.n, 3))
    wu, wv = m.deformation(x)
    for t, f in enumerate(m.faces):
        for w, coef, kk in ((wu, m.b[t], K[0]), (wv, m.c[t], K[1])):
            lw = np.linalg.norm(w[t])
            if lw < 1.0:      # compressed: the exact transverse term (1 - 1/|w|) (I - n n^T) was clamped to 0
                n = w[t] / lw
                P = kk * (1.0 - 1.0 / lw) * (np.eye(3) - np.outer(n, n))
                D[f[:, None], :, f[None, :], :] += m.area[t] * np.einsum("i,j,ab->ijab", coef, coef, P)
        cs = float(wu[t] @ wv[t])
        bc = np.outer(m.b[t], m.c[t])
        D[f[:, None], :, f[None, :], :] += (m.area[t] * K[2] * cs * np.einsum("ij,ab->ijab", bc + bc.T,
                                                                                  np.eye(3)))
    assert np.allclose(He - H, D.reshape(3 * m.n, 3 * m.n), rtol=0, atol=1e-11 * top)


def test_linearize_gives_the_force_and_the_product_with_its_blocks():
    """``linearize``'s force is ``force``'s, its ``(dF/dx) w`` is minus the stiffness blocks times w, and its
    ``c_v`` part is the damping's ``d2D/dv2``."""
    rng = np.random.default_rng(7)
    m, geo = _membrane()
    x, v = _random_state(geo, rng)
    w = rng.standard_normal(x.shape)
    S = SystemMatrix(m.n, m.pairs(), "numpy")
    m.bind(S)
    S.reset_diagonal(np.zeros(m.n))
    f, kw = np.zeros_like(x), np.zeros_like(x)
    m.linearize(x, v, 0.0, 0.25, 0.5, w, S, kw, f)
    F = np.zeros_like(x)
    m.force(x, v, 0.0, F)
    assert np.allclose(f, F, rtol=1e-13, atol=1e-12)
    K0 = _hessian(m, m.n, x, v, 0.0, 1.0, 0.0)
    assert np.allclose(kw.ravel(), -K0 @ w.ravel(), rtol=1e-12, atol=1e-10)
    Dv = _hessian(m, m.n, x, v, 0.0, 0.0, 1.0)
    assert np.allclose(S.finalize().toarray(), 0.25 * K0 + 0.5 * Dv, rtol=1e-12, atol=1e-10)


def test_pairs_are_every_triangle_edge_and_rest_is_force_free():
    m, geo = _membrane()
    e = {tuple(sorted(p)) for f in geo.faces for p in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    assert {tuple(p) for p in m.pairs()} == e
    f = np.zeros_like(geo.positions)
    m.force(geo.positions, np.zeros_like(geo.positions), 0.0, f)
    assert np.abs(f).max() < 1e-12 and m.energy(geo.positions) < 1e-25


# --------------------------------------------------------------------------- constant strain
def _interior(res):
    nx, ny = res
    idx = np.arange(nx * ny).reshape(ny, nx)
    return idx[1:-1, 1:-1].ravel(), idx


@pytest.mark.parametrize("plane_rotation", [False, True])
def test_uniaxial_stretch_patch(plane_rotation):
    """``x = (1 + e) u, y = v``: energy ``A k_u e^2 / 2``, no force on interior vertices, the pulled edge's
    force the tension ``k_u e`` times its length; also with the sheet rotated in space."""
    size, res, e = (1.0, 0.8), (6, 5), 0.07
    m, geo = _membrane(size=size, res=res)
    x = geo.positions * [1.0 + e, 1.0, 1.0]
    if plane_rotation:
        q, _ = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))
        x = x @ q.T
    A = size[0] * size[1]
    assert m.energy(x) == pytest.approx(A * K[0] * e * e / 2, rel=1e-12)
    f = np.zeros_like(x)
    m.force(x, np.zeros_like(x), 0.0, f)
    inner, idx = _interior(res)
    scale = K[0] * e * size[1]
    assert np.abs(f[inner]).max() < 1e-12 * scale
    right = f[idx[:, -1]].sum(axis=0)
    if plane_rotation:
        right = right @ q                       # back in the sheet's frame
    assert right == pytest.approx([-K[0] * e * size[1], 0.0, 0.0], abs=1e-12 * scale)


def test_pure_shear_patch():
    """Threads kept at length, the angle between them changed: ``x = u + sin(t) v, y = cos(t) v``, so
    ``w_u = (1, 0)``, ``w_v = (sin t, cos t)``: energy exactly ``A k_s sin(t)^2 / 2``, interior forces zero."""
    size, res, th = (1.0, 0.8), (6, 5), 0.2
    m, geo = _membrane(size=size, res=res)
    u, v = geo.positions[:, 0], geo.positions[:, 1]
    x = np.stack([u + math.sin(th) * v, math.cos(th) * v, np.zeros_like(u)], axis=1)
    C = m.strains(x)
    assert np.abs(C[:, :2]).max() < 1e-14 and np.allclose(C[:, 2], math.sin(th), rtol=1e-14)
    A = size[0] * size[1]
    assert m.energy(x) == pytest.approx(A * K[2] * math.sin(th) ** 2 / 2, rel=1e-12)
    f = np.zeros_like(x)
    m.force(x, np.zeros_like(x), 0.0, f)
    inner, _ = _interior(res)
    assert np.abs(f[inner]).max() < 1e-12 * K[2]


def test_simple_shear_patch():
    """``x = u + g v, y = v``: ``C_s = g`` and the v threads lengthen to ``sqrt(1 + g^2)``, so the energy is
    ``A (k_s g^2 + k_v (sqrt(1 + g^2) - 1)^2) / 2``; interior forces zero."""
    size, res, g = (1.0, 0.8), (6, 5), 0.15
    m, geo = _membrane(size=size, res=res)
    x = geo.positions.copy()
    x[:, 0] += g * geo.positions[:, 1]
    A = size[0] * size[1]
    assert m.energy(x) == pytest.approx(A * (K[2] * g * g + K[1] * (math.sqrt(1 + g * g) - 1) ** 2) / 2, rel=1e-12)
    f = np.zeros_like(x)
    m.force(x, np.zeros_like(x), 0.0, f)
    inner, _ = _interior(res)
    assert np.abs(f[inner]).max() < 1e-12 * K[2]


def test_damping_of_a_uniform_stretch_rate():
    """``x = u, v_x = r u``: the u threads lengthen at ``r`` (1/s), so the dissipation is ``A kd_u r^2 / 2``."""
    size, res, r = (1.0, 0.8), (6, 5), 0.3
    m, geo = _membrane(size=size, res=res)
    vel = np.zeros_like(geo.positions)
    vel[:, 0] = r * geo.positions[:, 0]
    assert m.dissipation(geo.positions, vel, 0.0) == pytest.approx(size[0] * size[1] * KD[0] * r * r / 2,
                                                                    rel=1e-12)


def test_metric_rest_coordinates_of_a_mesh():
    """A curved, irregular mesh with texture coordinates of another scale and a rotation: its rest state has
    no strain, and u follows the texture's u."""
    rng = np.random.default_rng(2)
    geo, uv = _sheet((1.0, 1.0), (6, 6))
    p = geo.positions + 0.03 * rng.standard_normal(geo.positions.shape) * [1, 1, 0]
    rest = np.stack([p[:, 0], p[:, 1], 0.3 * p[:, 0] ** 2], axis=1)           # a bent sheet
    ang = 0.4
    rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    tex = 5.0 * p[:, :2] @ rot.T
    ruv = metric_rest_coordinates(rest, geo.faces, tex[geo.faces])
    m = Membrane(geo.n_vertices, geo.faces, ruv, K, KD)
    C = m.strains(rest)
    assert np.abs(C).max() < 1e-12
    wu, _ = m.deformation(rest)
    # the rest shape's dx/du points along the texture's u direction mapped on the surface
    du = np.array([math.cos(ang), -math.sin(ang)])            # the direction in p's plane where tex's u grows
    assert np.all(np.abs(wu[:, :2] @ du) / np.linalg.norm(wu[:, :2], axis=1) > 0.9)


# --------------------------------------------------------------------------- back-ends
@pytest.mark.parametrize("exact", [False, True])
def test_numpy_and_numba_agree(exact):
    pytest.importorskip("numba")
    rng = np.random.default_rng(11)
    geo, uv = _sheet((1.0, 0.8), (7, 6))
    x, v = _random_state(geo, rng)
    w = rng.standard_normal(x.shape)
    out = {}
    for acc in ("numpy", "numba"):
        m = Membrane(geo.n_vertices, geo.faces, uv, K, KD, exact=exact)
        S = SystemMatrix(m.n, m.pairs(), acc)
        m.bind(S)
        assert m.accelerator == acc
        S.reset_diagonal(np.ones(m.n))
        f, kw, F, g = (np.zeros_like(x) for _ in range(4))
        m.linearize(x, v, 0.0, 0.01, 0.1, w, S, kw, f)
        m.force(x, v, 0.0, F)
        m.gradient(x, 0.0, g)
        out[acc] = (S.finalize().toarray(), f, kw, F, g)
    for a, b in zip(out["numpy"], out["numba"]):
        assert np.allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(a).max())


# --------------------------------------------------------------------------- scenes
MEMBRANE = {"stretch_u": {"stiffness": 100.0, "damping": 0.5}, "stretch_v": {"stiffness": 100.0, "damping": 0.5},
            "shear": {"stiffness": 20.0, "damping": 0.1}}


@pytest.mark.parametrize("along", ["v", "u"])
def test_hanging_strip_at_rest_is_a_uniaxial_bar(along):
    """A strip pinned along its top edge, hanging under gravity, run to rest by backward Euler: each band of
    triangles carries the weight below it, tension ``k W e``, so the strip lengthens by ``M g L / (2 k W)`` (the
    continuous bar's, exact for equal vertex masses) and its top band is strained by ``M g (1 - 1/n) / (k W)``.
    Once with the strip along the grid's height (v), once along its width (u), gravity along the strip. One
    cell wide: a grid's vertices have equal masses, and the two of a row then also take equal shares of the
    band's tension (a wider strip's edge vertices take half an interior one's share for the same mass, and the
    strip is no longer uniaxial)."""
    L, W, M = 1.0, 0.2, 0.1
    k = {"v": 100.0, "u": 150.0}[along]
    mem = copy.deepcopy(MEMBRANE)
    mem[f"stretch_{along}"]["stiffness"] = k
    if along == "v":
        size, res, gravity = [W, L], [2, 11], [0.0, 0.0, -9.81]
        n = res[1]
        pins = [(res[1] - 1) * res[0] + i for i in range(res[0])]           # the top row
    else:
        size, res, gravity = [L, W], [11, 2], [-9.81, 0.0, 0.0]
        n = res[0]
        pins = [j * res[0] + res[0] - 1 for j in range(res[1])]             # the +x column
    scene = {"cloth": {"size": size, "resolution": res, "mass": M, "plane": "xz", "pins": pins, "membrane": mem},
             "effects": {"gravity": gravity}, "simulation": {"dt": 0.02, "duration": 4.0, "frame_rate": 5}}
    sim = ic.Simulator(scene)
    assert [e.name for e in sim.model.effects] == ["gravity", "membrane"]
    traj = sim.run()
    assert traj.report["status"] == "ok"
    x = traj.positions[-1]
    assert np.abs(sim.state.v).max() < 1e-6
    axis = 2 if along == "v" else 0
    span = np.ptp(x[:, axis])
    ext = M * 9.81 * L / (2 * k * W)
    assert span - L == pytest.approx(ext, rel=1e-4), (span - L, ext)
    # the top band's strain: tension k W e = the weight below it
    h = L / (n - 1)
    if along == "v":
        top = x[pins[0], 2] - x[pins[0] - res[0], 2]
    else:
        top = x[pins[0], 0] - x[pins[0] - 1, 0]
    e_top = top / h - 1.0
    assert k * W * e_top == pytest.approx(M * 9.81 * (1 - 1 / n), rel=1e-4)
    # no lateral strain or shear (the membrane has no Poisson coupling)
    C = sim.model.effects[-1].strains(x)
    other = 0 if along == "v" else 1
    assert np.abs(C[:, other]).max() < 1e-8 and np.abs(C[:, 2]).max() < 1e-8


def _hanging(membrane=None, **cloth):
    c = {"size": [1.0, 1.0], "resolution": [10, 10], "mass": 0.1, "plane": "xy", "center": [0.0, 0.0, 1.0],
         "pins": ["top_left", "top_right"],
         "springs": {"structural": {"stiffness": 2000.0, "damping": 0.1}, "shear": {"stiffness": 200.0,
                                                                                   "damping": 0.05},
                     "bend": {"stiffness": 5.0, "damping": 0.01}}}
    c.update(cloth)
    if membrane is not None:
        c["membrane"] = membrane
    return {"cloth": c, "effects": {"gravity": [0.0, 0.0, -9.81]}, "simulation": {"duration": 0.5}}


def test_a_scene_without_the_membrane_is_unchanged():
    """No ``[cloth.membrane]``: no membrane key in the normalised scene, the same effects and springs (every
    kind, in the same order) as before it existed, and the report's effects list."""
    s = ic.Scene(_hanging())
    assert "membrane" not in s.data["cloth"] and "membrane" not in s.effects
    model = ic.Simulator(_hanging()).model
    assert [e.name for e in model.effects] == ["gravity", "springs"]
    assert list(model.springs.kinds) == ["structural", "shear", "bend"]
    geo = cloth.grid((1.0, 1.0), (10, 10), (0.0, 0.0, 1.0), "xy")
    pairs = np.concatenate([geo.springs[k] for k in ("structural", "shear", "bend")])
    assert np.array_equal(np.stack([model.springs.i, model.springs.j], 1), pairs)


def test_the_membrane_replaces_structural_and_shear_springs():
    scene = _hanging(MEMBRANE)
    del scene["cloth"]["springs"]["structural"], scene["cloth"]["springs"]["shear"]
    s = ic.Scene(scene)
    assert list(s.data["cloth"]["springs"]) == ["bend"] and s.effects == ["gravity", "bend", "membrane"]
    model = ic.Simulator(scene).model
    assert [e.name for e in model.effects] == ["gravity", "springs", "membrane"]
    assert list(model.springs.kinds) == ["bend"]
    mem = model.effects[-1]
    assert len(mem.faces) == 2 * 9 * 9 and np.allclose(mem.k, [100.0, 100.0, 20.0])
    assert np.allclose(mem.area.sum(), 1.0)
    # every triangle edge is on the system's pattern
    e = mem.pairs()
    assert model.system.has_blocks(e[:, 0], e[:, 1]).all()


def test_hanging_cloth_with_the_membrane_runs_ok():
    scene = _hanging(MEMBRANE)
    for kind in ("structural", "shear"):
        del scene["cloth"]["springs"][kind]
    sim = ic.Simulator(scene)
    traj = sim.run()
    assert traj.report["status"] == "ok"
    x = traj.positions[-1]
    assert np.all(np.isfinite(x)) and x[:, 2].min() < 0.5           # it fell and hangs
    assert traj.report["frames"]["springs"][-1] > 0                  # the stored energy counts the membrane's


def test_a_material_supplies_the_membrane():
    """``membrane = {}`` with a preset that has measured values (denim) takes them; a preset without them, or
    no preset, is an error naming the key."""
    scene = _hanging({}, material="denim")
    del scene["cloth"]["springs"]
    data = ic.Scene(scene).data["cloth"]
    mem = ic.MATERIALS["denim"].membrane
    assert data["membrane"]["stretch_u"] == {"stiffness": mem.stretch_u.stiffness, "damping": 2.0}
    assert data["membrane"]["shear"]["stiffness"] == pytest.approx(122.49, abs=0.01)
    assert mem.stretch_u.stiffness == pytest.approx(0.712 * 490.3325 / 0.05515)
    assert list(data["springs"]) == ["bend"]
    scene["cloth"]["membrane"] = {"shear": {"stiffness": 50.0}}
    assert ic.Scene(scene).data["cloth"]["membrane"]["shear"] == {"stiffness": 50.0, "damping": 1.0}
    scene["cloth"]["material"] = "cotton"
    with pytest.raises(SceneError, match=r"cloth\.membrane\.stretch_u\.stiffness: missing \(material 'cotton'"):
        ic.Scene(scene)
    del scene["cloth"]["material"]
    scene["cloth"]["mass"] = 0.1
    with pytest.raises(SceneError, match=r"cloth\.membrane\.stretch_u\.stiffness: missing"):
        ic.Scene(scene)


@pytest.mark.parametrize("change, message", [
    (lambda m: m.update(strech_u={}), "cloth.membrane.strech_u: unknown key (did you mean 'stretch_u'?)"),
    (lambda m: m["shear"].update(stiffnes=1.0), "cloth.membrane.shear.stiffnes: unknown key"),
    (lambda m: m["shear"].update(stiffness=0.0), "cloth.membrane.shear.stiffness: must be a finite number > 0, "
                                                 "got 0"),
    (lambda m: m["stretch_v"].update(stiffness=float("inf")), "cloth.membrane.stretch_v.stiffness: must be a "
                                                              "finite number > 0, got inf"),
    (lambda m: m["stretch_u"].update(damping=-1.0), "cloth.membrane.stretch_u.damping: must be a finite number "
                                                    ">= 0, got -1"),
    (lambda m: m.update(shear="stiff"), "cloth.membrane.shear: must be a table, got 'stiff'"),
])
def test_membrane_table_errors_name_the_key_and_value(change, message):
    mem = copy.deepcopy(MEMBRANE)
    change(mem)
    scene = _hanging(mem)
    for kind in ("structural", "shear"):
        del scene["cloth"]["springs"][kind]
    with pytest.raises(SceneError) as e:
        ic.Scene(scene)
    assert message in str(e.value)


def test_springs_replaced_by_the_membrane_are_an_error_when_given():
    with pytest.raises(SceneError, match=r"cloth\.springs\.structural: not used with cloth\.membrane"):
        ic.Scene(_hanging(MEMBRANE))


def test_pieces_each_with_their_own_membrane():
    a = _hanging(MEMBRANE)["cloth"]
    del a["springs"]
    b = copy.deepcopy(a)
    b["center"] = [0.0, 0.0, 0.5]
    b["membrane"] = {c: {"stiffness": 2 * MEMBRANE[c]["stiffness"]} for c in MEMBRANE}
    c = _hanging()["cloth"]
    c["center"] = [0.0, 0.0, 0.2]
    model = ic.Simulator({"cloth": [a, b, c], "effects": {"gravity": [0.0, 0.0, -9.81]}}).model
    names = [e.name for e in model.effects]
    assert names == ["gravity", "springs", "membrane"]
    mem = model.effects[-1]
    assert len(mem.faces) == 2 * 162
    assert np.all(mem.faces[:162] < 100) and np.all((mem.faces[162:] >= 100) & (mem.faces[162:] < 200))
    assert np.allclose(mem.k[:162], [100.0, 100.0, 20.0]) and np.allclose(mem.k[162:], [200.0, 200.0, 40.0])
    assert np.all(mem.kd[162:] == 0.0)
    assert np.all(model.springs.i >= 200)           # only the third piece has springs


def _obj(path, uv=True):
    geo, tex = _sheet((1.0, 1.0), (4, 4))
    lines = [f"v {p[0]} {p[1]} {p[2] + 1.0}" for p in geo.positions]
    if uv:
        lines += [f"vt {p[0] * 2 + 1} {p[1] * 2 + 1}" for p in geo.positions]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in geo.faces]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in geo.faces]
    path.write_text("\n".join(lines) + "\n")
    return geo


def test_a_mesh_takes_its_rest_uv_from_its_texture_coordinates(tmp_path):
    geo = _obj(tmp_path / "sheet.obj")
    scene = {"cloth": {"mesh": str(tmp_path / "sheet.obj"), "mass": 0.1, "membrane": MEMBRANE},
             "effects": {"gravity": [0.0, 0.0, -9.81]}}
    model = ic.Simulator(scene).model
    mem = model.effects[-1]
    assert mem.name == "membrane"
    assert np.abs(mem.strains(model.rest_positions)).max() < 1e-12
    # the same membrane as the grid's with (u, v) = (x, y)
    _, uv = _sheet((1.0, 1.0), (4, 4))
    ref = Membrane(geo.n_vertices, geo.faces, uv, [100.0, 100.0, 20.0], [0.5, 0.5, 0.1])
    x = model.rest_positions + 0.05 * np.random.default_rng(0).standard_normal(model.rest_positions.shape)
    assert mem.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)


def test_a_mesh_without_texture_coordinates_is_an_error_naming_the_file(tmp_path):
    _obj(tmp_path / "plain.obj", uv=False)
    scene = {"cloth": {"mesh": str(tmp_path / "plain.obj"), "mass": 0.1, "membrane": MEMBRANE}}
    with pytest.raises(SceneError) as e:
        ic.Simulator(scene)
    assert "cloth.membrane: the mesh file has no texture coordinates" in str(e.value)
    assert "plain.obj" in str(e.value)
    del scene["cloth"]["membrane"]
    ic.Simulator(scene)                      # without the membrane it needs none


def test_drape_on_a_sphere_with_the_membrane_keeps_the_contact_goals():
    """The drape example at 16² with the membrane instead of the structural and shear springs (rounds of
    contact constraints): no vertex inside the sphere, the report's status ok (its energy balance)."""
    data = ic.load_scene("examples/drape_sphere.toml").source
    c = data["cloth"]
    c["resolution"] = [16, 16]
    c["springs"] = {"bend": c["springs"]["bend"]}
    c["membrane"] = {"stretch_u": {"stiffness": 2000.0, "damping": 0.5},
                     "stretch_v": {"stiffness": 2000.0, "damping": 0.5}, "shear": {"stiffness": 200.0, "damping": 0.1}}
    data["simulation"]["duration"] = 0.8
    sim = ic.Simulator(data)
    traj = sim.run()
    r = traj.report
    assert r["status"] == "ok", r.get("health")
    assert r["collision"]["contacts"] > 0
    th = data["collision"]["thickness"]
    d = np.linalg.norm(traj.positions, axis=2).min()
    assert d > 0.3 + 0.5 * th, d
    assert traj.positions[-1][:, 2].max() > 0.25                 # on the sphere, not through it


def test_drape_on_a_sphere_with_the_membrane_and_the_barrier():
    """The barrier method with the membrane: every step ends outside half the thickness, the run's own energy
    balance holds (no "energy" event: the report's status), and the energy (kinetic, gravity, membrane and bend
    springs, barrier, computed here) falls overall. Not the springs' stricter "never rises by more than
    round-off" (tests/test_contact_barrier.py): backward Euler on this non-convex potential gains up to 0.13 %
    of the energy in a few steps here (the cloth rises while its compressed membrane and bend springs relax),
    also with the Newton solve converged tightly; it stays within the run's balance."""
    from test_contact_barrier import SPHERE, TH, _barrier_energy, _scene

    d = _scene([dict(SPHERE)], n=10, center=(0.0, 0.0, 0.23))
    d["cloth"]["springs"] = {"bend": d["cloth"]["springs"]["bend"]}
    d["cloth"]["membrane"] = {"stretch_u": {"stiffness": 500.0, "damping": 0.05},
                              "stretch_v": {"stiffness": 500.0, "damping": 0.05},
                              "shear": {"stiffness": 50.0, "damping": 0.01}}
    sim = ic.Simulator(d)
    m = sim.model

    def energy(s):
        return m.kinetic_energy(s.v) + sum(m.potential_energy(s.x).values()) + _barrier_energy(sim, s.x)

    states = [sim.state]
    for _ in range(60):
        sim.step(1)
        states.append(sim.state)
    total = np.array([energy(s) for s in states])
    assert np.diff(total).max() < 2e-3 * total[0], np.diff(total).max()
    assert total[-1] < 0.6 * total[0]
    for s in states:
        assert np.linalg.norm(s.x, axis=1).min() > 0.2 + TH / 2
    assert np.linalg.norm(states[-1].x, axis=1).min() < 0.2 + TH       # it reached the sphere
    assert "energy" not in sim.health.events


@pytest.mark.parametrize("ext, has_uv", [("ply", True), ("glb", True), ("off", False)])
def test_other_mesh_formats_take_their_per_vertex_uvs(tmp_path, ext, has_uv):
    """Formats read by trimesh give per-vertex UVs (``visual.uv``); a format without them (OFF) is the error
    naming the file."""
    trimesh = pytest.importorskip("trimesh")
    geo, _ = _sheet((1.0, 1.0), (4, 4))
    mesh = trimesh.Trimesh(geo.positions + [0.0, 0.0, 1.0], geo.faces, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=geo.positions[:, :2] * 2 + 1))
    path = tmp_path / f"sheet.{ext}"
    mesh.export(path)
    scene = {"cloth": {"mesh": str(path), "mass": 0.1, "membrane": MEMBRANE}}
    if not has_uv:
        with pytest.raises(SceneError, match=r"cloth\.membrane: the mesh file has no texture coordinates.*sheet\.off"):
            ic.Simulator(scene)
        return
    model = ic.Simulator(scene).model
    mem = model.effects[-1]
    assert len(mem.faces) == len(geo.faces) and mem.area.sum() == pytest.approx(1.0)
    assert np.abs(mem.strains(model.rest_positions)).max() < 1e-12


def test_a_run_report_scene_with_the_membrane_loads_back_as_it_ran():
    """A normalised scene (a report's) with ``[cloth.membrane]`` and a material validates back to itself."""
    scene = _hanging({"shear": {"stiffness": 50.0}}, material="denim")
    del scene["cloth"]["springs"]
    data = ic.Scene(scene).data
    assert ic.Scene(copy.deepcopy(data)).data == data


# --------------------------------------------------------------------------- the run's strain measures
def test_principal_strain_is_the_largest_stretch_in_any_direction():
    """``principal_strains`` is the largest singular value of the deformation gradient minus 1 (a uniform
    deformation ``x = A X`` of the flat sheet: ``F = A[:, :2]``), at least the threads' and the edges' strains;
    a stretch along the bias (the diagonal), which the threads see partly as shear, is caught whole."""
    mem, geo = _membrane()
    rng = np.random.default_rng(3)
    X = geo.positions
    for _ in range(5):
        A = np.eye(3) + 0.4 * rng.standard_normal((3, 3))
        x = X @ A.T
        p = mem.principal_strains(x)
        top = np.linalg.svd(A[:, :2], compute_uv=False)[0] - 1.0
        assert np.allclose(p, top, atol=1e-12)
        assert np.all(p >= mem.strains(x)[:, :2].max(axis=1) - 1e-12)
        E = x[geo.faces] - x[np.roll(geo.faces, 1, axis=1)]
        E0 = X[geo.faces] - X[np.roll(geo.faces, 1, axis=1)]
        edge = np.linalg.norm(E, axis=2) / np.linalg.norm(E0, axis=2) - 1.0
        assert np.all(p >= edge.max(axis=1) - 1e-12)
    d = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    x = X @ (np.eye(3) + 0.5 * np.outer(d, d)).T           # 50 % along the bias
    assert np.allclose(mem.principal_strains(x), 0.5)
    assert mem.strains(x)[:, :2].max() < 0.3                 # the threads: sqrt(1.25^2 + 0.25^2) - 1 = 0.275
    assert np.abs(mem.principal_strains(X)).max() < 1e-12


def _torn(adaptive=True):
    """An 8² membrane cloth with dihedral bending (no spring at all), its left edge pinned and its right edge
    carried 2 m away in 0.5 s: torn to three times its width, far beyond any cloth."""
    ids = np.arange(64).reshape(8, 8)
    c = {"size": [1.0, 1.0], "resolution": [8, 8], "mass": 0.1, "plane": "xy", "center": [0.0, 0.0, 1.0],
         "membrane": copy.deepcopy(MEMBRANE), "bending": {"model": "dihedral", "stiffness": 1e-3, "damping": 1e-5},
         "pins": [{"vertices": ids[:, 0].tolist()},
                  {"vertices": ids[:, -1].tolist(),
                   "keyframes": [{"time": 0.0}, {"time": 0.5, "translation": [2.0, 0.0, 0.0]}]}]}
    return {"cloth": c, "effects": {"gravity": [0.0, 0.0, -9.81]},
            "simulation": {"duration": 0.6, "adaptive": {"enabled": adaptive}}}


@pytest.mark.parametrize("adaptive", [True, False], ids=["adaptive", "fixed"])
def test_a_torn_membrane_is_a_strain_warning(adaptive):
    """With the membrane (and no spring) the report's strain is the triangles' largest principal strain: the
    kept frames' ``max_strain`` reaches the tear (~2), and the steps that stretched a triangle beyond the strain
    bound (adaptive's ``max_strain``, 1) make the status a ``strain`` warning, with adaptive stepping (its
    strain criterion, forced at the smallest step) and without (the step check)."""
    sim = ic.Simulator(_torn(adaptive))
    assert sim.model.springs is None
    r = sim.run().report
    assert r["n_springs"] == {} and max(r["frames"]["max_strain"]) > 1.9
    assert r["status"] == "warning", r["health"]
    strain = [h for h in r["health"] if h["criterion"] == "strain"]
    assert strain and strain[0]["worst"] > 1.9 and 0.2 < strain[0]["first_time"] < 0.35
    x = sim.state.x
    assert r["frames"]["max_strain"][-1] == pytest.approx(
        float(next(e for e in sim.model.effects if e.name == "membrane").principal_strains(x).max()), rel=1e-9)


def test_a_membrane_drape_is_ok_with_its_strain_measured():
    """The membrane drape (denim, 16², dihedral bending instead of the bend springs, its first 0.8 s): status
    ok. Its threads barely stretch (denim's 6330 N/m warp and weft), but where it wraps the sphere it shears
    (denim's shear, 122.5 N/m, is 50 times softer): ``C_s`` up to 0.2 stretches the bias by up to 10 %
    (``sqrt(1 + C_s) - 1`` for unit threads), and that is the largest principal strain the report gives, well
    within the bound."""
    data = ic.load_scene("examples/membrane_drape.toml").source
    c = data["cloth"]
    c["resolution"] = [16, 16]
    c["bending"] = {"model": "dihedral"}
    data["simulation"]["duration"] = 0.8
    sim = ic.Simulator(data)
    assert sim.model.springs is None
    traj = sim.run()
    r = traj.report
    assert r["status"] == "ok", r["health"]
    assert r["collision"]["contacts"] > 0
    assert 0.01 < max(r["frames"]["max_strain"]) < 0.15
    mem = next(e for e in sim.model.effects if e.name == "membrane")
    assert max(float(mem.strains(x)[:, :2].max()) for x in traj.positions) < 0.01      # the threads'
