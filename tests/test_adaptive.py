"""Adaptive time stepping (implicit_cloth.adaptive): the failure criteria, halving and growing back on the
nominal grid, the report, and the stability finding it cures.

Stability benchmark finding (benchmarks/stability.py): backward Euler and BDF2 with one linearisation per step
are not unconditionally stable on a stiff flat-start cloth at large steps (diverged at dt = 1/15 s for
k >= 1e5 N/m). The same case with adaptive stepping (the default for the implicit methods) stays bounded.
"""

import math

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.adaptive import StepController
from implicit_cloth.integrators import StepInfo
from implicit_cloth.model import State


def _flat(k, integrator="backward_euler", dt=1 / 15, adaptive=None):
    """The stability benchmark's scene: 12x12, 1 m, 0.1 kg, flat (xy), top corners pinned, light damping."""
    sim = {"integrator": integrator, "dt": dt, "duration": 0.5}
    if adaptive is not None:
        sim["adaptive"] = adaptive
    return {"simulation": sim,
            "cloth": {"size": [1.0, 1.0], "resolution": [12, 12], "mass": 0.1, "plane": "xy",
                      "pins": ["top_left", "top_right"],
                      "springs": {"structural": {"stiffness": k, "damping": 0.01},
                                  "shear": {"stiffness": k, "damping": 0.01},
                                  "bend": {"stiffness": k / 100, "damping": 1e-4}}},
            "effects": {"gravity": [0.0, 0.0, -9.81]}}


def _perturbed(scene):
    sim = ic.Simulator(scene)
    sim.velocities = 1e-3 * np.random.default_rng(0).standard_normal((sim.model.n, 3))
    return sim


def _growth(traj):
    """Largest E_total(t) - E_total(0) over the kept frames, in units of the run's energy scale."""
    f = traj.report["frames"]
    return (max(f["total"]) - f["total"][0]) / traj.report["divergence_bound"]["energy_scale"]


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2"])
@pytest.mark.parametrize("k", [1e5, 1e6])
def test_adaptive_stepping_cures_the_flat_start_instability(integrator, k):
    """Fixed steps: the energy grows beyond the benchmark's bound E_scale (or the run diverges). Adaptive (the
    default): finite, energy never above its start by more than 0.1 E_scale, frames on the nominal grid, and
    the report counts the redone steps (with Newton iterations first, then halved)."""
    fixed = _perturbed(_flat(k, integrator, adaptive={"enabled": False}))
    try:
        growth_fixed = _growth(fixed.run(frame_rate=240))
    except ic.DivergenceError:
        growth_fixed = math.inf
    assert growth_fixed > 1.0

    sim = _perturbed(_flat(k, integrator))
    traj = sim.run(frame_rate=240)
    rep = traj.report
    assert rep["status"] == "ok" and np.all(np.isfinite(traj.positions))
    assert _growth(traj) < 0.1
    ad = rep["adaptive"]
    assert ad["newton_retries"] + ad["retries"] > 0 and ad["forced"] == 0
    assert ad["failures"]["nonfinite"] + ad["failures"]["energy"] + ad["failures"]["strain"] > 0
    assert np.allclose(traj.times, np.arange(len(traj)) / 15, rtol=0, atol=1e-12)
    assert min(rep["frames"]["min_step"]) == ad["min_step"]


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2"])
def test_without_newton_redos_the_step_is_halved(integrator):
    """The same case with the nonlinear redo switched off (``newton_iterations = 1``): halving alone cures it,
    the steps split and grow back."""
    sim = _perturbed(_flat(1e5, integrator, adaptive={"newton_iterations": 1}))
    traj = sim.run(frame_rate=240)
    rep = traj.report
    assert rep["status"] == "ok" and _growth(traj) < 0.1
    ad = rep["adaptive"]
    assert ad["retries"] > 0 and ad["newton_retries"] == 0 and ad["forced"] == 0
    assert ad["min_step"] < 1 / 15 and ad["min_step"] >= (1 / 15) / 2 ** ad["max_halvings"]
    assert ad["substeps"] > rep["steps"]                       # some steps were split ...
    assert ad["substeps"] < rep["steps"] * 2 ** ad["max_halvings"]   # ... and the step grew back
    assert np.allclose(traj.times, np.arange(len(traj)) / 15, rtol=0, atol=1e-12)
    assert min(rep["frames"]["min_step"]) == ad["min_step"]


def test_no_failure_means_the_same_trajectory():
    """When no step fails, adaptive stepping changes nothing: bitwise the same frames (BDF2 keeps its
    two-step history too), one substep per step, no retries."""
    scene = _flat(1e3, "bdf2", dt=0.01)
    a = ic.Simulator(scene).run(duration=0.2, frame_rate=100)
    scene["simulation"]["adaptive"] = {"enabled": False}
    b = ic.Simulator(scene).run(duration=0.2, frame_rate=100)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.times, b.times)
    ad = a.report["adaptive"]
    assert ad["retries"] == 0 and ad["substeps"] == a.report["steps"] == 20 and ad["min_step"] == 0.01
    assert b.report["adaptive"] is None


def test_explicit_baselines_are_not_adaptive_by_default():
    for name in ("forward_euler", "symplectic_euler", "verlet", "rk4"):
        sim = ic.Simulator(_flat(1e3, name, dt=1e-3))
        assert sim.adaptive is None
    for name in ("backward_euler", "bdf2"):
        assert ic.Simulator(_flat(1e3, name)).adaptive is not None


def test_explicit_method_with_adaptive_enabled_survives_its_unstable_step():
    """Symplectic Euler at dt = 4 ms, 6.7x its stability bound 2 / w_max = 0.60 ms (w_max^2 the largest
    eigenvalue of M^-1/2 K M^-1/2 at rest, free vertices, computed once with scipy.linalg.eigvalsh), diverges
    with fixed steps; with adaptive stepping enabled explicitly it halves to 0.5 ms or below (under the bound;
    0.25 ms where a step's energy error exceeds the per-step balance), keeps retrying whenever it grows back,
    and finishes bounded."""
    scene = _flat(1e3, "symplectic_euler", dt=4e-3)
    with pytest.raises(ic.DivergenceError):
        _perturbed(scene).run(duration=0.2, frame_rate=250)
    scene["simulation"]["adaptive"] = {"enabled": True, "max_halvings": 4}
    traj = _perturbed(scene).run(duration=0.2, frame_rate=250)
    assert traj.report["status"] == "ok" and traj.report["adaptive"]["retries"] > 0
    assert traj.report["adaptive"]["min_step"] in (4e-3 / 8, 4e-3 / 16)
    assert _growth(traj) < 0.1


def test_unconverged_solves_are_retried_then_forced():
    """A 3-iteration cap cannot be met at any step: each step is retried down to the smallest step, accepted
    there (forced) and the solver criterion is then suspended until a solve converges; all counted."""
    scene = _flat(1e4, dt=1 / 30, adaptive={"max_halvings": 2})
    sim = ic.Simulator(scene, solver={"tolerance": 1e-10, "max_iterations": 3})
    with pytest.warns(ic.SolverWarning):
        traj = sim.run(duration=4 / 30, frame_rate=30)
    ad = traj.report["adaptive"]
    assert ad["failures"]["solver"] >= 3 and ad["retries"] >= 2 and ad["forced"] >= 1
    assert ad["min_step"] == pytest.approx((1 / 30) / 4)
    assert "solver" in sim.adaptive.suspended
    sim.velocities = sim.velocities          # assigning the state forgets the suspension
    assert not sim.adaptive.suspended


# --------------------------------------------------------------------------- the controller alone
class _Fake:
    """A substep that fails (NaN) whenever h exceeds a limit, else leaves x unchanged and advances t."""

    def __init__(self, limit):
        self.limit, self.calls = limit, []

    def __call__(self, state, h, *args, **kwargs):
        self.calls.append(h)
        x = state.x.copy() * (np.nan if h > self.limit * (1 + 1e-12) else 1.0)
        return State(x, state.v.copy(), state.t + h), StepInfo(iterations=1)


def _controller(**kw):
    sim = ic.Simulator(_flat(1e3))
    settings = {**sim.scene.data["simulation"]["adaptive"], **kw}
    return sim, StepController(sim.model, settings)


def test_controller_halves_then_grows_back_on_the_grid():
    sim, c = _controller(max_halvings=3, grow_after=2)
    dt = 0.08
    fake = _Fake(limit=dt / 4)
    state = sim.state
    new, info = c.advance(state, dt, fake)
    # dt fails, dt/2 fails, dt/4 succeeds 2x -> would double to dt/2 at the half-way point (on its grid) and
    # fail again, then dt/4 twice more
    assert fake.calls == pytest.approx([dt, dt / 2, dt / 4, dt / 4, dt / 2, dt / 4, dt / 4])
    assert new.t == state.t + dt and info.iterations == 4
    assert c.stats.retries == 3 and c.stats.substeps == 4 and c.stats.min_step == dt / 4
    assert c.stats.failures["nonfinite"] == 3 and c.stats.forced == 0
    # the limit lifted: the step grows back (never beyond dt) within the next nominal steps
    fake.limit = dt
    for _ in range(3):
        new, _ = c.advance(new, dt, fake)
    assert max(fake.calls) == dt and fake.calls[-1] == dt and c.level == 0


def test_controller_returns_a_non_finite_state_at_the_smallest_step():
    sim, c = _controller(max_halvings=2)
    fake = _Fake(limit=0.0)
    new, _ = c.advance(sim.state, 0.04, fake)
    assert not np.all(np.isfinite(new.x)) and fake.calls == pytest.approx([0.04, 0.02, 0.01])


def test_nonfinite_at_smallest_step_is_a_divergence_error():
    """Through the simulator: a step that is non-finite even at dt / 2^max_halvings raises DivergenceError and
    keeps the last finite state."""
    sim = ic.Simulator(_flat(1e3, dt=0.01, adaptive={"max_halvings": 1}))
    x0 = sim.positions.copy()
    sim.integrator.step = _Fake(limit=0.0)
    with pytest.raises(ic.DivergenceError):
        sim.step(1)
    assert np.array_equal(sim.positions, x0) and sim.time == 0.0


@pytest.mark.parametrize("key,value,expect", [
    ("enabled", "yes", "simulation.adaptive.enabled: must be true or false, got 'yes'"),
    ("max_halvings", -1, "simulation.adaptive.max_halvings: must be an integer >= 0 and <= 30, got -1"),
    ("max_halvings", 31, "simulation.adaptive.max_halvings: must be an integer >= 0 and <= 30, got 31"),
    ("grow_after", 0, "simulation.adaptive.grow_after: must be an integer >= 1 and <= 1000000, got 0"),
    ("max_strain", 0.0, "simulation.adaptive.max_strain: must be a finite number > 0, got 0.0"),
    ("max_energy_growth", float("nan"), "simulation.adaptive.max_energy_growth: must be a finite number >= 0, got nan"),
    ("retry_unconverged", 1, "simulation.adaptive.retry_unconverged: must be true or false, got 1"),
    ("newton_iterations", 0, "simulation.adaptive.newton_iterations: must be an integer >= 1 and <= 100, got 0"),
    ("max_halving", 3, "simulation.adaptive.max_halving: unknown key (did you mean 'max_halvings'?)"),
])
def test_adaptive_keys_are_validated(key, value, expect):
    scene = _flat(1e3)
    scene["simulation"]["adaptive"] = {key: value}
    with pytest.raises(ic.SceneError) as exc:
        ic.Simulator(scene)
    assert str(exc.value) == expect


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2"])
def test_a_newton_redo_continues_from_the_linearisation_it_redoes(monkeypatch, integrator):
    """A step that fails the energy balance after its single linearisation is redone with Newton iterations,
    whose first solve is that same linearisation: the redo continues from its end velocities instead of
    solving it again. The same trajectory bit for bit, one solve less per redo."""
    runs = {}
    for mode in ("continue", "solve again"):
        if mode == "solve again":
            def again(self, state, h, pins, newton):
                return self.integrator.step(state, h, pins, newton=newton, done=self._retry_done(state, h, newton))

            monkeypatch.setattr(ic.Simulator, "_implicit_step", again)
        traj = _perturbed(_flat(1e5, integrator)).run(frame_rate=240)
        runs[mode] = (traj.positions, traj.report)
    (xa, a), (xb, b) = runs["continue"], runs["solve again"]
    assert np.array_equal(xa, xb)
    retries = a["adaptive"]["newton_retries"]
    assert retries == b["adaptive"]["newton_retries"] > 0
    steps = a["steps"]
    assert a["solver"]["mean_solves"] * steps == b["solver"]["mean_solves"] * steps - retries
    assert a["solver"]["mean_iterations"] < b["solver"]["mean_iterations"]
    assert a["solver"]["max_newton_iterations"] == b["solver"]["max_newton_iterations"]


def test_redone_tells_in_advance_which_substeps_advance_discards():
    """``StepController.redone`` (self-collision is skipped on a proposal it says will be discarded) judges a
    proposal as ``advance`` then does: true exactly for the substeps redone (the next attempt starts from the
    same state), false for those kept, and false for a failing substep at the smallest step (kept, reported)."""
    sim = _perturbed(_flat(1e6, adaptive={"newton_iterations": 1, "max_halvings": 2}))
    calls = []
    substep = sim._substep

    def recorded(state, h, newton=None):
        new, info = substep(state, h, newton)
        failing = bool(sim.adaptive.check(state, new, info, h))
        calls.append((state, sim.adaptive.redone(state, new, info, h, newton), failing))
        return new, info

    sim._substep = recorded
    rep = sim.run(frame_rate=240).report
    assert rep["adaptive"]["forced"] > 0 and rep["status"] == "warning"
    said = [r for _, r, _ in calls[:-1]]
    done = [calls[i + 1][0] is calls[i][0] for i in range(len(calls) - 1)]
    assert said == done and sum(done) > 3
    assert any(f and not r for _, r, f in calls[:-1])       # failed at the smallest step: kept, not redone


def test_the_report_counts_every_solve_discarded_attempts_included(monkeypatch):
    """``mean_attempted_solves`` / ``mean_attempted_iterations`` count every linear solve the run made (each
    counted here as the integrator makes it), the discarded attempts' too; ``mean_solves`` / ``mean_iterations``
    only the accepted substeps'."""
    from implicit_cloth.integrators.base import ImplicitIntegrator

    made = {"solves": 0, "iterations": 0}
    solve = ImplicitIntegrator._solve

    def counted(self, A, b, z, filt, info, *args, **kw):
        before = info.iterations
        out = solve(self, A, b, z, filt, info, *args, **kw)
        made["solves"] += 1
        made["iterations"] += info.iterations - before
        return out

    monkeypatch.setattr(ImplicitIntegrator, "_solve", counted)
    traj = _perturbed(_flat(1e5)).run(frame_rate=240)
    rep = traj.report
    s, n = rep["solver"], rep["steps"]
    ad = rep["adaptive"]
    assert ad["newton_retries"] + ad["retries"] > 0            # attempts were discarded
    assert round(s["mean_attempted_solves"] * n) == made["solves"]
    assert round(s["mean_attempted_iterations"] * n) == made["iterations"]
    assert s["mean_attempted_solves"] * n >= s["mean_solves"] * n + ad["newton_retries"] + ad["retries"]
    assert s["mean_attempted_iterations"] > s["mean_iterations"]


def test_without_adaptive_stepping_every_solve_is_an_accepted_one():
    sim = _perturbed(_flat(1e3, adaptive={"enabled": False}))
    s = sim.run(frame_rate=240).report["solver"]
    assert s["mean_attempted_solves"] == s["mean_solves"] >= 1
    assert s["mean_attempted_iterations"] == s["mean_iterations"] > 0
