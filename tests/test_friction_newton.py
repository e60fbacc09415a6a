"""Smoothed friction solved to convergence within the step (``collision.friction_newton``): the friction
law's closed form on a floor, step by step (a scalar root found in this file by bisection, not the engine's
Newton), drapes at rest, the key's validation, and the energy judged from the states as in
test_contact_energy. (The tilted-plane closed forms and the drops on four shapes run with it in
test_smoothed_friction.)"""

from __future__ import annotations

import numpy as np
import pytest
from test_collision import TH, cloth_scene
from test_contact_energy import assert_resting_on_the_sphere, drop_scene, judged_run

import implicit_cloth as ic

EPS = 1e-4          # m/s
NEWTON = {"friction_speed": EPS, "friction_newton": 6}


def huber_step(v0: float, u: float, h: float, a_fric: float, a_push: float = 0.0) -> float:
    """Backward Euler's end speed of one step of a body on a floor moving at ``u``, under smoothed Coulomb
    friction of bound ``a_fric`` (mu g) and a push ``a_push``: the root of
    ``(v1 - v0) / h = a_push + a_fric (u - v1) / max(|u - v1|, EPS)`` (monotone in v1: bisection)."""
    def r(v1: float) -> float:
        w = u - v1
        return (v1 - v0) / h - a_push - a_fric * w / max(abs(w), EPS)
    lo, hi = min(v0, u) - 10.0, max(v0, u) + 10.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if r(mid) > 0:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def test_a_cloth_dragged_by_a_floor_follows_the_friction_law_through_the_step_it_catches_up():
    """A floor set moving at 1 m/s under a resting cloth (mu = 0.3, dt 1/60): the cloth gains mu g h a step
    until, in one step, it catches up with the floor and sticks (the viscous branch then holds it within eps of
    the floor's speed). Every step's speed is the friction law's backward-Euler root, the catching step
    included: the friction is solved within the step, not decided by a state from the step before."""
    mu, h, g, t0, U = 0.3, 1 / 60, 9.81, 0.2, 1.0
    floor = {"shape": "plane", "normal": [0, 0, 1],
             "keyframes": [{"time": 0.0, "center": [0.0, 0.0, 0.0]}, {"time": t0, "center": [0.0, 0.0, 0.0]},
                           {"time": t0 + 1.0, "center": [U, 0.0, 0.0]}]}
    sc = cloth_scene(floor, dt=h, duration=t0 + 0.6, res=8, size=0.3, center=(0, 0, TH), friction=mu,
                     collision=dict(NEWTON))
    sc["effects"].pop("drag")
    sim = ic.Simulator(sc, adaptive={"enabled": False})
    sim.step(round(t0 / h))
    assert np.abs(sim.velocities).max() < 1e-9
    v = 0.0
    caught = None
    for k in range(30):
        sim.step(1)
        v = huber_step(v, U, h, mu * g)
        vx = sim.velocities[:, 0]
        assert vx == pytest.approx(np.full_like(vx, v), abs=2e-5, rel=1e-6), k
        if caught is None and U - v < EPS:
            caught = k
    assert caught is not None and 15 < caught < 25          # mu g h = 4.9 cm/s a step: about 20 steps
    assert np.allclose(sim.positions[:, 2], TH, atol=1e-9)


def test_a_drape_with_friction_solved_in_the_step_comes_to_rest_on_the_sphere():
    """32² on the sphere at dt 1/30 for 3 s (the contact benchmark's row): on top, no energy rise, at rest."""
    scene = drop_scene("sphere", n=32, dt=1 / 30, duration=3.0)
    scene["collision"].update(NEWTON)
    assert_resting_on_the_sphere(*judged_run(scene))


@pytest.mark.parametrize("value, message", [
    (-1, "collision.friction_newton: must be an integer"),
    (2.5, "collision.friction_newton: must be an integer"),
])
def test_friction_newton_key_errors_name_the_key(value, message):
    d = {"cloth": {"mass": 0.1}, "obstacles": [{"shape": "sphere", "radius": 1}],
         "collision": {"friction_speed": EPS, "friction_newton": value}}
    with pytest.raises(ic.SceneError) as err:
        ic.Scene.from_dict(d)
    assert message in str(err.value)


def test_friction_newton_needs_a_friction_speed():
    d = {"cloth": {"mass": 0.1}, "obstacles": [{"shape": "sphere", "radius": 1}],
         "collision": {"friction_newton": 6, "friction_speed": 0}}
    with pytest.raises(ic.SceneError, match="collision.friction_newton: 6 .* collision.friction_speed is 0"):
        ic.Scene.from_dict(d)
    d["collision"] = {"friction_newton": 6}          # the default sliding speed is smoothed friction's
    ic.Scene.from_dict(d)


def test_the_default_friction_is_smoothed_and_solved_within_the_step():
    """A scene that says nothing of friction's model runs as ``friction_speed = 1e-4`` with ``friction_newton
    = 6`` (bit for bit); its normalised table does not name them (scenes of before are unchanged), and giving
    ``friction_speed = 0`` (Coulomb's states) or ``friction_newton = 0`` (the smoothed friction linearised once,
    with its state rules) changes the trajectory."""
    from implicit_cloth.collision.context import FRICTION_NEWTON, FRICTION_SPEED

    assert (FRICTION_SPEED, FRICTION_NEWTON) == (1e-4, 6)
    base = drop_scene("sphere", n=10, duration=0.4)
    assert "friction_speed" not in ic.Scene.from_dict(base).data["collision"]
    runs = {}
    for name, extra in {"default": {}, "given": {"friction_speed": 1e-4, "friction_newton": 6},
                        "coulomb": {"friction_speed": 0}, "linearised": {"friction_newton": 0}}.items():
        sc = drop_scene("sphere", n=10, duration=0.4)
        sc["collision"].update(extra)
        sim = ic.Simulator(sc)
        sim.run()
        runs[name] = sim.positions
    assert np.array_equal(runs["default"], runs["given"])
    assert not np.array_equal(runs["default"], runs["coulomb"])
    assert not np.array_equal(runs["default"], runs["linearised"])


def test_on_the_cone_tip_the_friction_solve_keeps_large_steps_and_rests():
    """32² dropped point-first on the cone at dt 1/30 for 3 s (the contact benchmark's row): while the cloth
    folds over the tip the Newton iterations may not meet the friction law (the springs' projected Newton
    stalls there); keeping such an iterate made this drape thrash at 10 substeps a step with the fallback
    pushing vertices out every step. Those steps are their first solve's instead: no energy rise, at most 1.2
    substeps a step, at rest at the end (rms below 2 mm/s) and on the cone."""
    scene = drop_scene("cone", n=32, dt=1 / 30, duration=3.0)
    scene["collision"].update(NEWTON)
    sim, traj, e0, frames = judged_run(scene)
    assert max(e for _, e, _ in frames) - e0 <= 0.0
    speed = np.linalg.norm(sim.velocities, axis=1)
    assert np.sqrt(np.mean(speed**2)) < 2e-3
    assert traj.report["adaptive"]["substeps_per_step"] <= 1.2
    assert sim.positions[:, 2].max() == pytest.approx(0.4 + TH, abs=5e-3)
    assert traj.report["status"] == "ok", traj.report["reason"]


def _asked_and_missed(pause: int | None) -> list[list[tuple[bool, bool]]]:
    """Per collider step with contacts of a 24² drape folding over the sphere (dt 1/60, 1 s), per round:
    whether the friction's Newton iterations were asked for, and whether they missed the law."""
    from implicit_cloth.collision import collider as col
    from implicit_cloth.integrators import base

    scene = drop_scene("sphere", n=24, dt=1 / 60, duration=1.0)
    if pause is not None:
        scene["collision"]["friction_pause"] = pause
    sim = ic.Simulator(ic.Scene.from_dict(scene))
    steps: list[list[tuple[bool, bool]]] = []
    real_step = base.ImplicitIntegrator.step
    real_rounds = col.Collider._solve_rounds

    def rounds(self, *args, **kw):
        steps.append([])
        return real_rounds(self, *args, **kw)

    def step(self, state, h, constraints=None, guess=None, newton=None, start=None, **kw):
        new, info = real_step(self, state, h, constraints, guess, newton, start, **kw)
        if start is None and constraints is not None and constraints.n_contacts:
            asked = newton is not None and newton > 1
            steps[-1].append((asked, asked and info.friction_converged is False))
        return new, info

    mp = pytest.MonkeyPatch()
    mp.setattr(col.Collider, "_solve_rounds", rounds)
    mp.setattr(base.ImplicitIntegrator, "step", step)
    try:
        sim.step(60)
    finally:
        mp.undo()
    return [s for s in steps if s]


def test_friction_pause_skips_the_newton_iterations_after_two_missed_steps_in_a_row():
    """``collision.friction_pause = P``: while a drape folds, the friction's Newton iterations miss the law in
    runs of steps; after two steps in a row whose iterations missed it, the next P steps go to the state rules
    at once (one linear solve a round, no iterations), the step after tries them again, and a single miss
    pauses nothing. Without the key every contact step asks for them."""
    pause = 3
    steps = _asked_and_missed(pause)
    pauses = singles = 0
    prev_missed = False                                       # the last step that asked
    k = 0
    while k < len(steps):
        asked = any(a for a, _ in steps[k])
        missed = any(m for _, m in steps[k])
        assert asked, k                                       # no pause running here: every step asks
        if missed and prev_missed:
            pauses += 1
            after = steps[k + 1:k + 1 + pause]
            assert all(not a for s in after for a, _ in s), k
            k += 1 + pause
        else:
            singles += missed and not prev_missed
            k += 1
        prev_missed = missed
    assert pauses >= 2 and singles >= 1                       # the fold makes runs of misses
    default = _asked_and_missed(None)
    assert all(s[0][0] for s in default)
    assert sum(any(m for _, m in s) for s in default) > pauses


@pytest.mark.parametrize("collision, message", [
    ({"friction_pause": -1}, "collision.friction_pause: must be an integer"),
    ({"friction_pause": 1.5}, "collision.friction_pause: must be an integer"),
    ({"friction_pause": 3, "friction_speed": 0}, "collision.friction_pause: 3 steps .* nothing to pause"),
    ({"friction_pause": 3, "friction_newton": 0}, "collision.friction_pause: 3 steps .* nothing to pause"),
])
def test_friction_pause_key_errors_name_the_key(collision, message):
    d = {"cloth": {"mass": 0.1}, "obstacles": [{"shape": "sphere", "radius": 1}], "collision": collision}
    with pytest.raises(ic.SceneError, match=message):
        ic.Scene.from_dict(d)


def test_the_friction_continuation_is_the_least_of_the_steps_model_with_the_friction_law():
    """The friction's Newton iterations keep the springs at the step's linearisation: their result must be the
    minimiser of ``dv^T A0 dv / 2 - b0^T dv + h sum mu N f(|v_t|)`` (Huber's ``f``) over the velocities the
    constraints allow. Checked on continuations of a 16² drape landing on a sphere against scipy's L-BFGS on
    that function, with the constrained components exactly the first solve's and the function lowered."""
    from implicit_cloth.integrators import base

    sc = cloth_scene({"shape": "sphere", "radius": 0.2, "center": [0.0, 0.0, -0.2]}, dt=1 / 60, duration=1.0,
                     res=16, center=(0, 0, 0.05), friction=0.3, collision=dict(NEWTON))
    sim = ic.Simulator(sc, adaptive={"enabled": False})
    seen: list[tuple] = []
    real = base.ImplicitIntegrator._friction_newton

    def spy(self, state, h, c, scheme, filt, dv, iterations, info):
        sysm = self.model.system
        A = sysm.csr.copy()                                   # A0 + h D of the first solve's linearisation
        held = self._held_damping
        S = filt.matrices()
        out = real(self, state, h, c, scheme, filt, dv, iterations, info)
        if out is not None and len(seen) < 3 and c.n_contacts >= 8:
            seen.append((state, scheme, c, A, held, S, dv.copy(), out[0]))
        return out

    mp = pytest.MonkeyPatch()
    mp.setattr(base.ImplicitIntegrator, "_friction_newton", spy)
    try:
        while len(seen) < 3 and sim.time < 1.0:
            sim.step(1)
    finally:
        mp.undo()
    assert len(seen) == 3
    for state, scheme, c, A, held, S, dv_first, dv in seen:
        _check_least(sim.model.masses, state, scheme, c, A, held, S, dv_first, dv)


def _check_least(masses, state, scheme, c, A, held, S, dv_first, dv) -> None:
    """``dv`` against scipy's minimiser of the step's function (constraints from the first solve)."""
    import scipy.sparse as sp
    from scipy.optimize import minimize

    n = len(state.v)
    blocks = np.zeros((n, 3, 3))
    blocks[held[0]] = held[1]
    A0 = (A - sp.block_diag(list(blocks), format="csr")).tocsr()   # the first solve's friction damping out
    b0 = scheme.b.reshape(-1)
    cv = scheme.c_v
    z = dv_first - np.einsum("nij,nj->ni", S, dv_first)   # the constrained components
    SS = sp.block_diag(list(S), format="csr")

    def phi(y):
        d = z.reshape(-1) + SS @ y
        v = state.v + d.reshape(-1, 3)
        f = np.zeros((n, 3))
        f[c.contact] = c.friction_force(v)
        grad = A0 @ d - b0 - cv * f.reshape(-1)
        return 0.5 * d @ (A0 @ d) - b0 @ d + cv * c.friction_potential(v), SS @ grad

    best = minimize(phi, (SS @ dv_first.reshape(-1)), jac=True, method="L-BFGS-B",
                    options={"gtol": 1e-13, "ftol": 1e-16, "maxiter": 20000, "maxcor": 20})
    star = z + (SS @ best.x).reshape(-1, 3)
    m = masses[:, None]
    err = np.sqrt(np.sum(m * (dv - star) ** 2) / np.sum(m * (star - dv_first) ** 2))
    assert err < 0.05, err          # of what the iterations moved the first solve (measured 0.4-1.3 %)
    assert np.allclose(dv - np.einsum("nij,nj->ni", S, dv), z, atol=1e-12)   # constraints exact
    assert phi(SS @ dv.reshape(-1))[0] <= phi(SS @ dv_first.reshape(-1))[0]


@pytest.mark.parametrize("paused", [False, True])
def test_a_new_contacts_friction_is_solved_in_the_step_that_finds_it(paused):
    """A flat cloth sliding at 1 m/s lands on a floor: the landing step finds the contacts after its first
    solve, and their friction (no normal force before: none in that solve) is solved in the same round at the
    normal force of the round's first solve, not in a third round. The cloth's speed after the step is the
    inelastic impact's Coulomb closed form, ``vx0 - mu (vz1 - vz0 + g h)`` with ``vz1 = (TH - z0) / h`` (the
    contact's end on its plane, which the solve's normal impulse brings), the rounds two. In a step whose
    friction iterations are paused (``friction_pause``) the bounds are not set in the step: the new contacts
    are solved again with their friction in a third round (their friction linearised once), not left without."""
    from implicit_cloth.collision import collider as col

    mu, h, g, vx0, vz0, z0 = 0.3, 1 / 60, 9.81, 1.0, -0.6, TH + 0.004
    floor = {"shape": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]}
    sc = cloth_scene(floor, dt=h, duration=0.1, res=8, size=0.3, center=(0, 0, z0), friction=mu,
                     collision=dict(NEWTON))
    sc["effects"].pop("drag")
    if paused:
        sc["collision"]["friction_pause"] = 3
    sim = ic.Simulator(sc, adaptive={"enabled": False})
    sim.state.v[:] = (vx0, 0.0, vz0)
    if paused:
        sim.collider._friction_pause = 1                 # as after two steps in a row that missed the law
    rounds: list[int] = []
    real = col.Collider._solve_rounds

    def spy(self, *a, **k):
        out = real(self, *a, **k)
        rounds.append(out[2].rounds)
        return out

    mp = pytest.MonkeyPatch()
    mp.setattr(col.Collider, "_solve_rounds", spy)
    try:
        sim.step(1)
    finally:
        mp.undo()
    assert rounds == [3 if paused else 2]
    vz1 = (TH - z0) / h
    assert np.allclose(sim.positions[:, 2], TH, atol=1e-12)
    assert np.allclose(sim.velocities[:, 2], 0.0, atol=1e-12)     # the contacts then leave inelastically
    assert sim.velocities[:, 0] == pytest.approx(np.full(sim.model.n, vx0 - mu * (vz1 - vz0 + g * h)), rel=1e-6)


def _rounds_of_a_landing(skip: bool) -> tuple[list[tuple[bool, bool]], int]:
    """A 24² drape landing on the sphere (dt 1/60, 0.4 s): per solve of a contact round, whether the integrator
    skipped the friction's iterations (asked for, friction_converged None) and whether the collider then released
    a contact and solved the round again; and the friction continuations made. ``skip`` False: the collider passes
    no ``redone`` (the rounds as before 2026-12-06)."""
    from implicit_cloth.collision import collider as col
    from implicit_cloth.integrators import base

    sim = ic.Simulator(ic.Scene.from_dict(drop_scene("sphere", n=24, dt=1 / 60, duration=0.4)))
    seen: list[tuple[bool, bool]] = []
    corrections = [0]
    real_step, real_after, real_fn = base.ImplicitIntegrator.step, col.Collider._after_solve, \
        base.ImplicitIntegrator._friction_newton

    def step(self, state, h, constraints=None, guess=None, newton=None, start=None, redone=None):
        said: list[bool] = []

        def asked(J):                       # called only where the iterations would follow the first solve
            said.append(redone(J))
            return said[-1]
        new, info = real_step(self, state, h, constraints, guess, newton, start, redone and asked)
        if redone is not None:
            skipped = any(said)
            assert not skipped or (info.friction_converged is None and info.solves == 1)
            seen.append((skipped, False))
        return new, info

    def after(self, active, *args, **kw):
        out = real_after(self, active, *args, **kw)
        if seen:
            seen[-1] = (seen[-1][0], len(out[0]) < len(active) and out[1])
        return out

    def fn(self, *args, **kw):
        out = real_fn(self, *args, **kw)
        corrections[0] += 1
        return out

    mp = pytest.MonkeyPatch()
    mp.setattr(base.ImplicitIntegrator, "step", step)
    mp.setattr(col.Collider, "_after_solve", after)
    mp.setattr(base.ImplicitIntegrator, "_friction_newton", fn)
    if not skip:
        mp.setattr(col.Collider, "_pulls", lambda self, *a: None)
    try:
        traj = sim.run()
    finally:
        mp.undo()
    assert traj.report["status"] == "ok", traj.report["reason"]
    return seen, corrections[0]


def test_a_round_the_collider_redoes_for_a_release_makes_no_friction_iterations():
    """A round whose first solve pulls a contact hard enough to be released (``collider.PULL_SPEED``) is solved
    again whatever its friction does: the integrator skips its friction iterations (``redone``). Every skipped
    solve is followed by a release and another round (the prediction is the collider's own rule), the landing has
    such rounds, and it makes fewer friction continuations than with the iterations run in every round."""
    seen, continuations = _rounds_of_a_landing(skip=True)
    skipped = [released for s, released in seen if s]
    assert len(skipped) >= 3
    assert all(skipped)
    _, before = _rounds_of_a_landing(skip=False)
    assert continuations < before
