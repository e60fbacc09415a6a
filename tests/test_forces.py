"""The Force interface (:mod:`implicit_cloth.forces`): every force's energy, gradient, dissipation, force and
Hessian blocks against finite differences of each other, with the error order.

The references are Taylor remainders computed here from the interface's own values:

* ``|U(x + e d) - U(x) - e dU/dx . d|`` is O(e^2) when the gradient is U's (halving e divides it by 4) and
  ``|U(x + e d) - U(x) - e g . d - e^2 d.H d / 2|`` is O(e^3) when the Hessian blocks are too (ratio 8);
* ``D(v + e d) - D(v) - e dD/dv . d`` likewise in the velocities, with ``dD/dv = -F - dU/dx`` read off the
  force (so the force is checked to be ``-dU/dx - dD/dv``);
* a wrong derivative leaves an O(e) remainder, ratio 2: the checks can fail.

``check_force`` is written for any force term, so each new one (contact, friction) is one more case.
"""

from __future__ import annotations

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth import forces
from implicit_cloth.assembly import SystemMatrix

EPS = 1e-3 * 0.5 ** np.arange(6)


def _scene(drag=None, wind=None, damping=True):
    kd = (0.3, 0.1, 0.02) if damping else (0.0, 0.0, 0.0)
    scene = {
        "cloth": {"size": [1.0, 0.8], "resolution": [5, 4], "mass": 0.2, "plane": "xz",
                  "pins": ["top_left"],
                  "springs": {kind: {"stiffness": k, "damping": d}
                              for kind, k, d in zip(("structural", "shear", "bend"), (800.0, 90.0, 4.0), kd)}},
        "effects": {"gravity": [0.0, -1.0, -9.81]},
    }
    if drag is not None:
        scene["effects"]["drag"] = drag
    if wind is not None:
        scene["effects"]["wind"] = {"velocity": list(wind)}
    return scene


def _hessian(force, n: int, x, v, t, c_x: float, c_v: float) -> np.ndarray:
    """The dense ``c_x d2U/dx2 + c_v d2D/dv2`` the force assembles on its own pattern (``-(c_v dF/dv + c_x
    dF/dx)``, :meth:`Force.linearize`)."""
    sysm = SystemMatrix(n, force.pairs(), "numpy")
    force.bind(sysm)
    sysm.reset_diagonal(np.zeros(n))
    force.linearize(x, v, t, c_x, c_v, None, sysm, None, np.zeros_like(x))
    return sysm.finalize().toarray()


def _orders(r: np.ndarray) -> np.ndarray:
    return np.log2(r[:-1] / r[1:])


def check_force(force, n: int, x: np.ndarray, v: np.ndarray, t: float, rng,
                d: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Taylor remainders' orders of ``force`` at ``(x, v)`` along ``d`` (random if None); each list's last
    entries should read 2 (gradient against energy, dissipation's gradient against dissipation) or 3 (with the
    Hessian blocks: "hessian", "dissipation_hessian" where the dissipation is not quadratic)."""
    if d is None:
        d = rng.standard_normal(x.shape)
    g = np.zeros_like(x)
    force.gradient(x, t, g)
    F = np.zeros_like(x)
    force.force(x, v, t, F)
    dDdv = -F - g
    out: dict[str, np.ndarray] = {}
    if force.conservative:
        H = _hessian(force, n, x, v, t, 1.0, 0.0)
        u0 = force.energy(x)
        r1 = np.array([abs(force.energy(x + e * d) - u0 - e * np.vdot(g, d)) for e in EPS])
        r2 = np.array([abs(force.energy(x + e * d) - u0 - e * np.vdot(g, d) - 0.5 * e * e * d.reshape(-1)
                           @ H @ d.reshape(-1)) for e in EPS])
        out["energy"], out["hessian"] = _orders(r1), _orders(r2)
    else:
        assert not np.any(g), f"{force.name}: no conservative part, but a gradient"
        assert force.energy(x) == 0.0
    if force.dissipative:
        Hv = _hessian(force, n, x, v, t, 0.0, 1.0)
        d0 = force.dissipation(x, v, t)
        r1 = np.array([abs(force.dissipation(x, v + e * d, t) - d0 - e * np.vdot(dDdv, d)) for e in EPS])
        r2 = np.array([abs(force.dissipation(x, v + e * d, t) - d0 - e * np.vdot(dDdv, d) - 0.5 * e * e
                           * d.reshape(-1) @ Hv @ d.reshape(-1)) for e in EPS])
        out["dissipation"] = _orders(r1)
        # quadratic in v at a fixed geometry (damping, drag): with its Hessian the remainder is round-off;
        # otherwise (smoothed friction) third order
        if not np.all(r2 <= 1e-9 * max(r1[0], 1e-300) + 1e-13):
            out["dissipation_hessian"] = _orders(r2)
    else:
        assert np.allclose(dDdv, 0.0, atol=1e-12 * (1 + np.abs(F).max())), \
            f"{force.name}: no dissipative part, but a velocity-dependent force"
        assert force.dissipation(x, v, t) == 0.0
    return out


def _stretched(model, rng):
    x = 1.2 * model.rest_positions + 0.01 * rng.standard_normal((model.n, 3))
    assert np.all(model.springs.lengths(x) > model.springs.L0), "test set-up: a spring is not stretched"
    return x


@pytest.mark.parametrize("scene", [
    _scene(),
    _scene(drag=0.8, wind=(3.0, -1.0, 0.5)),
    _scene(drag=0.5, damping=False),
], ids=["gravity+damped springs", "drag with wind", "undamped springs, drag"])
def test_every_force_has_consistent_derivatives(scene):
    rng = np.random.default_rng(3)
    model = ic.Simulator(scene).model
    x = _stretched(model, rng)        # the springs' Hessian is exact where they are stretched (clamp inactive)
    v = rng.standard_normal((model.n, 3))
    assert {f.name for f in model.effects} >= {"gravity", "springs"}
    for f in model.effects:
        o = check_force(f, model.n, x, v, 0.3, rng)
        if "energy" in o:
            # gravity is linear (its remainders are round-off): its orders are not checked, its Hessian zero
            if f.name == "gravity":
                assert not np.any(_hessian(f, model.n, x, v, 0.3, 1.0, 0.0))
                continue
            assert o["energy"][-1] == pytest.approx(2.0, abs=0.05), (f.name, o)
            assert o["hessian"][-1] == pytest.approx(3.0, abs=0.1), (f.name, o)
        if "dissipation" in o:
            assert o["dissipation"][-1] == pytest.approx(2.0, abs=0.05), (f.name, o)


def test_a_wrong_gradient_is_caught():
    """The energy check fails (order tending to 1) for a gradient off by a few percent."""
    rng = np.random.default_rng(4)
    model = ic.Simulator(_scene(damping=False)).model
    s = model.springs
    x = _stretched(model, rng)

    class Off:
        name, conservative, dissipative, elastic = "off", True, False, True

        def energy(self, y):
            return s.energy(y)

        def gradient(self, y, t, out):
            s.gradient(y, t, out)
            out *= 1.03

        def force(self, y, v, t, out):
            g = np.zeros_like(y)
            self.gradient(y, t, g)
            out -= g

        def dissipation(self, y, v, t):
            return 0.0

        pairs, bind, linearize = s.pairs, s.bind, s.linearize

    o = check_force(Off(), model.n, x, np.zeros_like(x), 0.0, rng)
    assert o["energy"][-1] < 1.5 and np.all(np.diff(o["energy"]) < 0), o      # tending to 1, not 2


def test_incremental_potential_gradient():
    """``grad Phi = M (v - v_hat) - c_v F``: the line search's potential (:func:`forces.energy` and
    :func:`forces.dissipation` summed over the model's forces, the geometry of the dissipation held at x)
    against the force the step solves for, by the Taylor remainder's order."""
    rng = np.random.default_rng(5)
    model = ic.Simulator(_scene(drag=0.8, wind=(1.0, 0.0, 2.0))).model
    fs = model.effects
    M = model.masses[:, None]
    x_pred = _stretched(model, rng)
    cv = 0.02
    v_hat = rng.standard_normal((model.n, 3))
    v = rng.standard_normal((model.n, 3))
    x_lag = x_pred + cv * v

    def phi(w):
        return (0.5 * float(np.sum(M * (w - v_hat) ** 2)) + forces.energy(fs, x_pred + cv * w)
                + cv * forces.dissipation(fs, x_lag, w, 0.0))

    # the force at (x(v), v) with the dissipation's geometry at x_lag = x(v)
    grad = M * (v - v_hat) - cv * model.forces(x_lag, v, 0.0)
    d = rng.standard_normal(v.shape)
    p0 = phi(v)
    r = np.array([abs(phi(v + e * d) - p0 - e * np.vdot(grad, d)) for e in EPS])
    assert _orders(r)[-1] == pytest.approx(2.0, abs=0.05)
    u, fc = forces.conservative(fs, x_pred, 0.0)
    assert u == pytest.approx(sum(model.potential_energy(x_pred).values()))
    fv = model.forces(x_pred, np.zeros_like(v), 0.0) - np.zeros_like(v)
    drag = next(f for f in fs if f.name == "drag")
    wind_push = np.zeros_like(v)
    drag.force(x_pred, np.zeros_like(v), 0.0, wind_push)      # the wind's push on a cloth at rest
    assert np.allclose(fc, fv - wind_push, rtol=1e-12, atol=1e-12)
