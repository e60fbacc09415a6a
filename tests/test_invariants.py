"""Physical invariants of every integrator on the same force code.

Momentum. With no external force (no gravity, no drag, no pins) every force is a spring force, equal and
opposite on its two vertices (damping too: it acts along the spring), so ``sum_i F_i = 0`` and the total linear
momentum ``p = sum_i m_i v_i`` is conserved, and the centre of mass moves in a straight line at ``p / M``.

* Explicit methods only add ``h sum_i F_i`` (or a weighted sum of such stage sums for RK4) to ``p``: conserved
  to round-off (measured 2e-16 to 7e-15 of the momentum scale ``sum_i m_i |v_i|``; checked at 1e-12).
* Implicit methods solve ``A dv = b`` with ``A = M - c_v dF/dv - c_x dF/dx``. Each spring's Jacobian blocks sum to
  zero over the spring's two vertices (translation is in the null space of ``dF/dx`` and ``dF/dv``), so the
  block column sums of ``A`` are those of ``M``; and ``sum_i b_i = 0`` (internal forces only). Hence the momentum
  change of a step is ``sum_i m_i dv_i = -sum_i r_i`` with ``r = b - A dv`` the linear solver's residual: zero
  for an exact solve and of the order of the solver tolerance times ``|M dv|`` per step otherwise. With
  ``solver.tolerance = 1e-8`` the drift over 60 steps is checked at 1e-6 of the momentum scale (measured 3e-10
  with block Jacobi; multigrid solves a grid this small exactly on its coarsest level, so it conserves ``p`` to
  round-off). At the default tolerance 1e-3 the drift with block Jacobi is ~1e-4: it is the solver's, not the
  force code's, which the last momentum test checks.

Energy. With damping on and nothing doing work on the cloth (no pins, or static ones; gravity is conservative
and counted in the total), the total energy of backward Euler (springs + damping + drag + its own numerical
dissipation) must not increase from one frame to the next (every step kept), up to round-off: 1e-12 of the
run's energy scale (measured: every step lost at least 1e-6 of it).
"""

import numpy as np
import pytest

import implicit_cloth as ic

EXPLICIT = ("forward_euler", "symplectic_euler", "verlet", "rk4")
IMPLICIT = ("backward_euler", "bdf2")


def _free_scene(res=(6, 5), kd=0.5):
    """No gravity, no drag, no pins; damped springs of all three kinds."""
    return {"cloth": {"size": [1.0, 0.8], "resolution": list(res), "mass": 0.5, "plane": "xy",
                      "springs": {"structural": {"stiffness": 200.0, "damping": kd},
                                  "shear": {"stiffness": 40.0, "damping": kd},
                                  "bend": {"stiffness": 2.0, "damping": kd}}}}


def _perturbed(sim, seed):
    """A shape off rest (random displacements of ~25 % of the spacing) and random velocities with a drift."""
    rng = np.random.default_rng(seed)
    x = sim.positions
    sim.positions = x + 0.05 * rng.standard_normal(x.shape)
    sim.velocities = rng.standard_normal(x.shape) + [0.3, -0.2, 0.5]
    return sim


def _momentum_drift(sim, n_steps):
    """Largest |p(t) - p(0)| and centre-of-mass deviation from the straight line, relative to their scales."""
    m = sim.model.masses
    total = m.sum()
    p0 = m @ sim.velocities
    scale = m @ np.linalg.norm(sim.velocities, axis=1)      # sum_i m_i |v_i|
    c0, t0 = m @ sim.positions / total, sim.time
    drift_p = drift_c = 0.0
    for _ in range(n_steps):
        sim.step()
        drift_p = max(drift_p, np.linalg.norm(m @ sim.velocities - p0) / scale)
        t = sim.time - t0
        c = m @ sim.positions / total
        drift_c = max(drift_c, np.linalg.norm(c - c0 - p0 / total * t) / (scale / total * t))
    assert np.all(np.isfinite(sim.positions))
    return drift_p, drift_c


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("integrator", EXPLICIT)
def test_explicit_methods_conserve_momentum_to_round_off(integrator, seed):
    sim = _perturbed(ic.Simulator(_free_scene(), integrator=integrator, dt=2e-3), seed)
    assert sim.model.effect_names == ["structural", "shear", "bend"]
    drift_p, drift_c = _momentum_drift(sim, 100)
    assert drift_p < 1e-12 and drift_c < 1e-12, (drift_p, drift_c)


@pytest.mark.parametrize("preconditioner", ["block_jacobi", "multigrid"])
@pytest.mark.parametrize("integrator", IMPLICIT)
def test_implicit_methods_conserve_momentum_to_solver_tolerance(integrator, preconditioner):
    sim = ic.Simulator(_free_scene(), integrator=integrator, dt=1 / 30,
                       solver={"tolerance": 1e-8, "preconditioner": preconditioner})
    drift_p, drift_c = _momentum_drift(_perturbed(sim, 0), 60)
    assert drift_p < 1e-6 and drift_c < 1e-6, (drift_p, drift_c)


def test_implicit_momentum_drift_is_the_solvers():
    """Block Jacobi at tolerance 1e-3 drifts visibly more than at 1e-8: the drift comes from the linear solve."""
    drift = {}
    for tol in (1e-3, 1e-8):
        sim = ic.Simulator(_free_scene(), integrator="backward_euler", dt=1 / 30,
                           solver={"tolerance": tol, "preconditioner": "block_jacobi"})
        drift[tol] = _momentum_drift(_perturbed(sim, 0), 30)[0]
    assert drift[1e-3] > 1e3 * drift[1e-8], drift


def _hanging(res=(8, 6)):
    d = _free_scene(res)
    d["cloth"].update(plane="xz", center=[0.0, 0.0, 1.0], pins=["top_left", "top_right"])
    d["effects"] = {"gravity": [0.0, 0.0, -9.81], "drag": 0.3}
    return d


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dt", [1 / 100, 1 / 30])
@pytest.mark.parametrize("case,preconditioner", [("free", "multigrid"), ("free", "block_jacobi"),
                                                 ("hanging", "multigrid"), ("hanging", "block_jacobi")])
def test_backward_euler_energy_never_increases(case, preconditioner, dt, seed):
    scene = _free_scene((8, 6)) if case == "free" else _hanging()
    sim = ic.Simulator(scene, integrator="backward_euler", dt=dt,
                       solver={"tolerance": 1e-8, "preconditioner": preconditioner})
    traj = _perturbed(sim, seed).run(duration=0.5, frame_rate=1 / dt)
    rep = traj.report
    assert rep["status"] == "ok" and rep["solver"]["unconverged_steps"] == 0
    assert len(traj) == round(0.5 / dt) + 1            # every step is a frame
    total = np.asarray(rep["frames"]["total"])
    assert np.all(np.asarray(rep["frames"]["pin_work"]) == 0.0)
    increase = np.diff(total)
    assert increase.max() <= 1e-12 * rep["divergence_bound"]["energy_scale"], (increase.max(), int(increase.argmax()))
    assert total[-1] < 0.5 * total[0] if case == "free" else total[-1] < total[0]
