"""Per-triangle drag and lift (:mod:`implicit_cloth.effects.aerodynamics`): the force and its exact ``dF/dv``
against finite differences with the error order, the closed forms of a flat triangle, wind against motion, the
step's projected blocks, the two back-ends against each other, the wind's power, the scene's
``[effects.aerodynamics]`` and its errors, and that a scene without it is unchanged.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from test_forces import _hessian

import implicit_cloth as ic
from implicit_cloth import cloth
from implicit_cloth.assembly import SystemMatrix
from implicit_cloth.effects.aerodynamics import Aerodynamics
from implicit_cloth.effects.wind import ConstantWind
from implicit_cloth.errors import SceneError

RHO, CD, CL = 1.2, 1.1, 0.6
EPS = 1e-3 * 0.5 ** np.arange(6)


def _sheet(res=(5, 4)):
    return cloth.grid((1.0, 0.8), res, plane="xy", kinds=())


def _aero(geo, wind=None, exact=False, drag=CD, lift=CL):
    field = None if wind is None else ConstantWind(wind)
    return Aerodynamics(geo.n_vertices, geo.faces, drag, lift, RHO, field, exact=exact)


def _force(f, x, v, t=0.0):
    out = np.zeros_like(x)
    f.force(x, v, t, out)
    return out


def _state(geo, rng, scale=0.1):
    return geo.positions + scale * rng.standard_normal(geo.positions.shape), rng.standard_normal(
        geo.positions.shape)


def _orders(r):
    return np.log2(r[:-1] / r[1:])


# --------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("wind", [None, (2.0, -1.0, 0.5)], ids=["still", "wind"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_velocity_jacobian_by_its_order(seed, wind):
    """``F(v + e d) - F(v)`` against ``e dF/dv d`` with the exact blocks: the remainder is O(e^2) (order 2);
    without the Jacobian it is O(e) (order 1), so the check can fail."""
    rng = np.random.default_rng(seed)
    geo = _sheet()
    f = _aero(geo, wind, exact=True)
    x, v = _state(geo, rng)
    d = rng.standard_normal(v.shape)
    H = _hessian(f, geo.n_vertices, x, v, 0.0, 0.0, 1.0)     # -(dF/dv)
    F0 = _force(f, x, v)
    r1 = np.array([np.linalg.norm(_force(f, x, v + e * d) - F0) for e in EPS])
    r2 = np.array([np.linalg.norm(_force(f, x, v + e * d) - F0 + e * (H @ d.reshape(-1)).reshape(-1, 3))
                   for e in EPS])
    assert _orders(r1)[-1] == pytest.approx(1.0, abs=0.05)
    assert _orders(r2)[-1] == pytest.approx(2.0, abs=0.05), _orders(r2)
    assert not np.allclose(H, H.T)          # the exact Jacobian is not symmetric


def test_the_force_is_neither_conservative_nor_dissipative_by_a_potential():
    rng = np.random.default_rng(3)
    geo = _sheet()
    f = _aero(geo, (1.0, 2.0, 0.0))
    x, v = _state(geo, rng)
    g = np.zeros_like(x)
    f.gradient(x, 0.0, g)
    assert not np.any(g) and f.energy(x) == 0.0 and f.dissipation(x, v, 0.0) == 0.0
    assert not f.conservative and not f.dissipative and not f.elastic
    assert not np.any(_hessian(f, geo.n_vertices, x, v, 0.0, 1.0, 0.0))     # dF/dx is not assembled


@pytest.mark.parametrize("seed", [0, 1])
def test_step_blocks_are_the_normal_part_symmetric_and_positive(seed):
    """The blocks the step uses: ``-(n^T J n) n n^T / 9`` per corner pair, symmetric and positive
    semidefinite, equal to the exact one along the normal (``n^T B n``) of each triangle."""
    rng = np.random.default_rng(seed)
    geo = _sheet()
    x, v = _state(geo, rng)
    f, ex = _aero(geo, (0.5, 0.0, 1.0)), _aero(geo, (0.5, 0.0, 1.0), exact=True)
    H = _hessian(f, geo.n_vertices, x, v, 0.0, 0.0, 1.0)
    assert np.allclose(H, H.T, atol=1e-14)
    assert np.linalg.eigvalsh(H).min() > -1e-12 * np.abs(H).max()
    Bp, Be = f.blocks(x, v, 0.0, 1.0), ex.blocks(x, v, 0.0, 1.0)
    A, n, u, s, a = f._frame(x, v, 0.0)
    assert np.allclose(np.einsum("ti,tij,tj->t", n, Bp, n), np.einsum("ti,tij,tj->t", n, Be, n), rtol=1e-12)


# --------------------------------------------------------------------------- closed forms
def _triangle(theta=0.0):
    """One right triangle in the xy plane (area 0.02 m^2, normal +z) and a unit velocity at ``theta`` from its
    normal, in the xz plane."""
    x = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.2, 0.0]])
    u = np.array([math.sin(theta), 0.0, math.cos(theta)])
    return x, np.array([[0, 1, 2]]), u, 0.02


@pytest.mark.parametrize("speed", [0.5, 3.0])
def test_face_on_drag_is_half_rho_cd_area_speed_squared_without_lift(speed):
    x, faces, u, A = _triangle()
    f = Aerodynamics(3, faces, CD, CL, RHO)
    F = _force(f, x, np.tile(speed * u, (3, 1)))
    assert np.allclose(F, F[0])                               # a third at each corner
    assert np.allclose(F.sum(axis=0), [0.0, 0.0, -0.5 * RHO * CD * A * speed ** 2], rtol=1e-14, atol=1e-15)


def test_at_45_degrees_drag_and_lift_have_their_closed_forms():
    """``u`` at 45 degrees from ``n``: drag ``c_d A s^2 cos 45`` against the normal, lift ``c_l A s^2 cos 45
    sin 45 = rho C_l A s^2 / 4`` across ``u``, towards ``-(n - (n . u^) u^)``."""
    s = 2.0
    x, faces, u, A = _triangle(math.pi / 4)
    drag = _force(Aerodynamics(3, faces, CD, 0.0, RHO), x, np.tile(s * u, (3, 1))).sum(axis=0)
    lift = _force(Aerodynamics(3, faces, 0.0, CL, RHO), x, np.tile(s * u, (3, 1))).sum(axis=0)
    n = np.array([0.0, 0.0, 1.0])
    assert np.allclose(drag, -0.5 * RHO * CD * A * s * s * math.cos(math.pi / 4) * n, rtol=1e-14)
    assert lift @ u == pytest.approx(0.0, abs=1e-15)
    assert np.linalg.norm(lift) == pytest.approx(RHO * CL * A * s * s / 4, rel=1e-14)
    across = n - (n @ u) * u
    assert np.allclose(lift / np.linalg.norm(lift), -across / np.linalg.norm(across), rtol=1e-14)
    both = _force(Aerodynamics(3, faces, CD, CL, RHO), x, np.tile(s * u, (3, 1))).sum(axis=0)
    assert np.allclose(both, drag + lift, rtol=1e-14)


def test_edge_on_and_either_orientation():
    x, faces, _, _ = _triangle()
    f = Aerodynamics(3, faces, CD, CL, RHO)
    assert not np.any(_force(f, x, np.tile([3.0, 1.0, 0.0], (3, 1))))           # in the plane: nothing
    v = np.tile([0.3, -0.2, 1.5], (3, 1))
    flipped = Aerodynamics(3, faces[:, ::-1], CD, CL, RHO)                       # normal -z
    assert np.allclose(_force(f, x, v), _force(flipped, x, v), rtol=1e-14)


def test_a_still_triangle_in_wind_is_one_moving_against_it_in_still_air():
    rng = np.random.default_rng(7)
    geo = _sheet()
    x, _ = _state(geo, rng)
    wind = np.array([1.5, -0.5, 2.5])
    still = _force(_aero(geo, wind), x, np.zeros_like(x))
    moving = _force(_aero(geo), x, np.tile(-wind, (geo.n_vertices, 1)))
    assert np.allclose(still, moving, rtol=1e-14, atol=1e-15) and np.abs(still).max() > 0.01


# --------------------------------------------------------------------------- power
def test_power_is_the_winds_and_bounds_the_work_on_the_cloth():
    """``F . v = sum_t F_t . w + sum_t F_t . u_t`` with the second term (the drag relative to the air) <= 0 and
    the lift's share 0: the cloth gains at most the wind's power :meth:`power`; 0 in still air."""
    rng = np.random.default_rng(5)
    geo = _sheet()
    x, v = _state(geo, rng)
    wind = np.array([0.0, 4.0, 1.0])
    f = _aero(geo, wind)
    F = _force(f, x, v)
    p = f.power(x, v, 0.0)
    assert p == pytest.approx(float(f.triangle_forces(x, v, 0.0).sum(axis=0) @ wind), rel=1e-13)
    assert float(np.sum(F * v)) <= p
    lift_only = _aero(geo, wind, drag=0.0)
    assert float(np.sum(_force(lift_only, x, v) * v)) == pytest.approx(lift_only.power(x, v, 0.0), rel=1e-10)
    assert _aero(geo).power(x, v, 0.0) == 0.0


# --------------------------------------------------------------------------- back-ends
@pytest.mark.parametrize("exact", [False, True])
def test_numpy_and_numba_agree(exact):
    pytest.importorskip("numba")
    rng = np.random.default_rng(11)
    geo = _sheet((7, 6))
    x, v = _state(geo, rng)
    out = {}
    for acc in ("numpy", "numba"):
        f = _aero(geo, (1.0, -2.0, 0.5), exact=exact)
        S = SystemMatrix(f.n, f.pairs(), acc)
        f.bind(S)
        assert f.accelerator == acc
        S.reset_diagonal(np.ones(f.n))
        lin, F = np.zeros_like(x), np.zeros_like(x)
        f.linearize(x, v, 0.0, 0.01, 0.1, None, S, None, lin)
        f.force(x, v, 0.0, F)
        out[acc] = (S.finalize().toarray(), lin, F)
    for a, b in zip(out["numpy"], out["numba"]):
        assert np.allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(a).max())


# --------------------------------------------------------------------------- scenes
def _flag(aero=None, wind=(4.0, 0.0, 0.0), **effects):
    scene = {"cloth": {"size": [0.6, 0.4], "resolution": [7, 5], "mass": 0.05, "plane": "xz",
                       "pins": ["top_left", "bottom_left"],
                       "springs": {"structural": {"stiffness": 300.0, "damping": 0.05},
                                   "shear": {"stiffness": 30.0, "damping": 0.01},
                                   "bend": {"stiffness": 0.5, "damping": 0.001}}},
             "effects": {"gravity": [0.0, 0.0, -9.81], **effects},
             "simulation": {"dt": 0.01, "duration": 0.2}}
    if aero is not None:
        scene["effects"]["aerodynamics"] = aero
    if wind is not None:
        scene["effects"]["wind"] = {"velocity": list(wind)}
    return scene


def test_the_scene_key_builds_the_force_with_its_wind_and_defaults():
    s = ic.Scene(_flag({"drag": 1.0}))
    assert s.data["effects"]["aerodynamics"] == {"drag": 1.0, "lift": 0.0, "air_density": 1.2}
    assert s.effects == ["gravity", "aerodynamics", "wind", "structural", "shear", "bend"]
    model = ic.Simulator(_flag({"drag": 1.0, "lift": 0.3, "air_density": 1.0})).model
    aero = next(e for e in model.effects if e.name == "aerodynamics")
    assert aero.c_d == 0.5 and aero.c_l == pytest.approx(0.15) and np.array_equal(aero.wind.w, [4.0, 0.0, 0.0])
    assert len(aero.faces) == len(model.faces)
    assert model.system.has_blocks(*aero.pairs().T).all()


def test_a_flag_in_wind_runs_ok_and_is_blown_downwind():
    """A wind at an angle to the sheet (edge-on, a flat sheet feels nothing) pushes it along its normal."""
    traj = ic.Simulator(_flag({"drag": 1.0, "lift": 0.3}, wind=(4.0, 2.0, 0.0))).run()
    assert traj.report["status"] == "ok", traj.report["health"]
    x = traj.positions
    assert x[-1, :, 1].mean() - x[0, :, 1].mean() > 0.005


def test_a_scene_without_the_key_does_not_import_or_build_it():
    """No ``[effects.aerodynamics]``: not in the normalised scene, not built, its modules never imported (a run
    of the wind example's effects, drag with its wind), the effects as before."""
    scene = _flag(None, drag=0.3)
    s = ic.Scene(scene)
    assert "aerodynamics" not in s.data["effects"] and s.effects == ["gravity", "drag", "wind", "structural",
                                                                      "shear", "bend"]
    assert [e.name for e in ic.Simulator(scene).model.effects] == ["gravity", "drag", "springs"]
    code = ("import json, sys, implicit_cloth as ic\n"
            f"ic.Simulator(json.loads({json.dumps(json.dumps(scene))})).run(duration=0.03)\n"
            "print(json.dumps(sorted(m for m in sys.modules if 'aerodynamics' in m)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


@pytest.mark.parametrize("value,message", [
    ({"drag": -1.0}, "effects.aerodynamics.drag: must be a finite number >= 0, got -1"),
    ({"drag": 1.0, "lift": float("nan")}, "effects.aerodynamics.lift: must be a finite number >= 0, got nan"),
    ({"drag": 1.0, "air_density": 0}, "effects.aerodynamics.air_density: must be a finite number > 0, got 0"),
    ({"drag": "high"}, "effects.aerodynamics.drag: must be a finite number >= 0, got 'high'"),
    ({"drag": 1.0, "lfit": 0.2}, "effects.aerodynamics.lfit: unknown key (did you mean 'lift'?)"),
    ({"air_density": 1.2}, "effects.aerodynamics.drag: missing"),
    (1.0, "effects.aerodynamics: must be a table, got 1.0"),
])
def test_errors_name_the_key_and_value(value, message):
    with pytest.raises(SceneError) as e:
        ic.Scene(_flag(value))
    assert message in str(e.value)


def test_wind_needs_drag_or_aerodynamics():
    with pytest.raises(SceneError, match=r"effects\.drag: missing \(wind acts through air drag; .*"
                                         r"effects\.aerodynamics"):
        ic.Scene(_flag(None))
    ic.Scene(_flag({"lift": 0.5}))      # the aerodynamics alone will do


def test_with_the_barrier_contact_it_enters_the_steps_potential_lagged():
    """``collision.method = "barrier"`` minimises the step's potential, which the aerodynamics (no potential)
    enters as its work lagged at each iterate: a cloth falling through air, in a wind, onto a sphere stays
    outside it, the run ok, its Newton iterations taken (with the force left out of the potential the line
    search refused the first direction of every step: no iteration) and the air slows its fall against the same
    fall without it."""
    def scene(aero):
        s = {"simulation": {"integrator": "backward_euler", "dt": 1 / 60, "duration": 0.5, "frame_rate": 30},
             "cloth": {"size": [0.6, 0.6], "resolution": [8, 8], "mass": 0.05, "center": [0.0, 0.0, 0.3],
                       "plane": "xy",
                       "springs": {"structural": {"stiffness": 500.0, "damping": 0.05},
                                   "shear": {"stiffness": 50.0, "damping": 0.01},
                                   "bend": {"stiffness": 1.0, "damping": 0.001}}},
             "effects": {"gravity": [0.0, 0.0, -9.81]},
             "obstacles": [{"shape": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.2, "friction": 0.3}],
             "collision": {"method": "barrier", "thickness": 0.01}}
        if aero:
            s["effects"].update(aerodynamics={"drag": 1.2, "lift": 0.3}, wind={"velocity": [6.0, 0.0, 3.0]})
        return s
    air, vacuum = (ic.Simulator(scene(a)).run(duration=d) for a, d in ((True, 0.5), (False, 0.1)))
    assert air.report["status"] == "ok", air.report["health"]
    assert np.linalg.norm(air.positions, axis=2).min() > 0.2
    assert air.report["solver"]["max_newton_iterations"] > 0
    early = ic.Simulator(scene(True)).run(duration=0.1)
    assert early.positions[-1, :, 2].mean() > vacuum.positions[-1, :, 2].mean() + 1e-3
