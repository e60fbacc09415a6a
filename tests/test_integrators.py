"""All six integrators against closed forms: free fall, an undamped linear oscillator, moving pins.

The references are derived here from each scheme's textbook recurrence applied to a scalar ODE
(``x'' = g`` or ``x'' = -w^2 x``), not from the library's output.
"""

import numpy as np
import pytest

import implicit_cloth as ic

G = np.array([0.0, 0.0, -9.81])
TIGHT = {"tolerance": 1e-12, "max_iterations": 200}


# --------------------------------------------------------------------------- (a) free fall
def _free_fall_offset(name, n):
    """(x_n - x_0 - v_0 t_n) / (g h^2) for x'' = g: a pure number, the same for every h and v_0."""
    if name == "forward_euler":
        return n * (n - 1) / 2
    if name in ("symplectic_euler", "backward_euler"):
        return n * (n + 1) / 2
    if name in ("verlet", "rk4"):
        return n * n / 2
    if name == "bdf2":
        # x_{n+1} = 4/3 x_n - 1/3 x_{n-1} + 2/3 h v_{n+1}, v_{n+1} = 4/3 v_n - 1/3 v_{n-1} + 2/3 h g,
        # x_1 = g h^2, v_1 = g h (backward-Euler start). The velocity recurrence has roots 1 and 1/3 and the
        # particular solution v_n = g h n, which already meets v_0 = 0, v_1 = g h: v_n = g h n. Then
        # x_n / (g h^2) = n^2/2 + C + D 3^-n with x_0 = 0, x_1 = 1: D = -3/4, C = 3/4.
        return n * n / 2 + 0.75 * (1.0 - 3.0 ** (-n))
    raise AssertionError(name)


def _bdf2_recurrence(n):
    """The BDF2 free-fall recurrence run directly (unit g and h, from rest), to check the closed form."""
    x, v = [0.0, 1.0], [0.0, 1.0]
    for _ in range(n - 1):
        v.append(4 / 3 * v[-1] - 1 / 3 * v[-2] + 2 / 3)
        x.append(4 / 3 * x[-1] - 1 / 3 * x[-2] + 2 / 3 * v[-1])
    return np.array(x), np.array(v)


def test_bdf2_free_fall_closed_form_solves_its_recurrence():
    x, v = _bdf2_recurrence(40)
    n = np.arange(41)
    assert np.allclose(x, [_free_fall_offset("bdf2", k) for k in n], rtol=1e-13)
    assert np.allclose(v, n, rtol=1e-13)


def _free_fall_scene():
    # no springs table: the cloth has faces (masses) but no spring force; no pins
    return {"cloth": {"size": [0.5, 0.4], "resolution": [3, 3], "mass": 0.09, "plane": "xy",
                      "center": [0.1, -0.2, 2.0], "velocity": [0.3, -0.2, 1.0]},
            "effects": {"gravity": G.tolist()}}


@pytest.mark.parametrize("name", ic.INTEGRATORS)
def test_free_fall_equals_discrete_solution(name):
    h, n = 0.01, 60
    sim = ic.Simulator(_free_fall_scene(), integrator=name, dt=h, solver=TIGHT)
    assert sim.model.springs is None and len(sim.model.pinned) == 0
    x0, v0 = sim.positions.copy(), sim.velocities.copy()
    for k in range(1, n + 1):
        sim.step(1)
        t = k * h
        ref_x = x0 + v0 * t + G * h * h * _free_fall_offset(name, k)
        assert np.allclose(sim.positions, ref_x, rtol=0, atol=1e-12), (name, k)
        assert np.allclose(sim.velocities, v0 + G * t, rtol=0, atol=1e-12), (name, k)
    assert sim.time == pytest.approx(n * h, rel=1e-14)
    # the schemes really differ: the exact parabola is met only by verlet and rk4
    exact = x0 + v0 * n * h + 0.5 * G * (n * h) ** 2
    assert np.allclose(sim.positions, exact, atol=1e-12) == (name in ("verlet", "rk4"))


def test_bdf2_restarts_with_a_backward_euler_step_after_assignment():
    """Documented: the first BDF2 step after the state is assigned is a backward-Euler step."""
    h = 0.01
    sim = ic.Simulator(_free_fall_scene(), integrator="bdf2", dt=h, solver=TIGHT)
    sim.step(20)
    x, v = sim.positions.copy(), sim.velocities.copy()
    ahead = ic.Simulator(_free_fall_scene(), integrator="bdf2", dt=h, solver=TIGHT)
    ahead.step(21)                                   # continues the BDF2 recurrence
    sim.positions = x                                # same values: only the history is dropped
    sim.step(1)
    assert np.allclose(sim.velocities, v + G * h, rtol=0, atol=1e-12)
    assert np.allclose(sim.positions, x + h * (v + G * h), rtol=0, atol=1e-12)
    # the uninterrupted run took a genuine BDF2 step instead, g h^2 (21 + c_20 - c_21) ~ g h^2 / 2 lower
    diff = (sim.positions - ahead.positions)[:, 2]
    expected = G[2] * h * h * (21 * 22 / 2 - _free_fall_offset("bdf2", 21) - 20 * 21 / 2
                               + _free_fall_offset("bdf2", 20))
    assert np.allclose(diff, expected, rtol=1e-9) and abs(expected) > 1e-5


# --------------------------------------------------------------------------- (b) linear oscillator
# A 3x2 grid with only bend springs has exactly two springs, 0-2 and 3-5 (along the bottom and top rows).
# Pinning every vertex but 2 leaves vertex 2 on one spring along x: displaced along x it stays on the axis and
# feels f = -k (x - x_rest), exactly linear (l > 0 throughout), so x'' = -w^2 x with w^2 = k / m.
K_OSC, MASS, WIDTH = 100.0, 0.6, 20.0
M_VERTEX = MASS / 6                           # the grid spreads the total mass equally over its 6 vertices
OMEGA = np.sqrt(K_OSC / M_VERTEX)             # 31.6 rad/s


def _oscillator(name, h, amplitude=0.01, damping=0.0):
    scene = {"cloth": {"size": [WIDTH, 1.0], "resolution": [3, 2], "mass": MASS, "plane": "xy",
                       "pins": [0, 1, 3, 4, 5],
                       "springs": {"bend": {"stiffness": K_OSC, "damping": damping}}}}
    sim = ic.Simulator(scene, integrator=name, dt=h, solver={"tolerance": 1e-10})
    s = sim.model.springs
    assert sorted(map(tuple, s.pairs().tolist())) == [(0, 2), (3, 5)]
    assert np.allclose(sim.model.masses, M_VERTEX)
    x = sim.positions.copy()
    rest = x[2].copy()
    x[2, 0] += amplitude
    sim.positions = x
    return sim, rest


def _run_oscillator(sim, rest, n):
    """Scaled phase-space trajectory z_k = (w (x_k - x_rest), v_k) of the free vertex, k = 0..n."""
    z = np.zeros((n + 1, 2))
    off_axis = 0.0
    for k in range(n + 1):
        if k:
            sim.step(1)
        p, v = sim.positions[2], sim.velocities[2]
        z[k] = OMEGA * (p[0] - rest[0]), v[0]
        off_axis = max(off_axis, abs(p[1] - rest[1]), abs(p[2] - rest[2]), abs(v[1]), abs(v[2]))
    assert off_axis == 0.0
    return z


def _one_step_matrix(name, h, w=OMEGA, gamma=0.0):
    """The scheme's map (x, v) -> (x, v) on x'' = -w^2 x - gamma x', from its textbook definition."""
    w2 = w * w
    if name == "forward_euler":
        return np.array([[1.0, h], [-w2 * h, 1.0 - gamma * h]])
    if name == "symplectic_euler":                      # v1 = v0 + h a(x0, v0); x1 = x0 + h v1
        kick = np.array([[1.0, 0.0], [-w2 * h, 1.0 - gamma * h]])
        drift = np.array([[1.0, h], [0.0, 1.0]])
        return drift @ kick
    if name == "verlet" and gamma == 0.0:               # kick h/2, drift h, kick h/2 (damped: see _reference)
        kick = np.array([[1.0, 0.0], [-w2 * h / 2, 1.0]])
        drift = np.array([[1.0, h], [0.0, 1.0]])
        return kick @ drift @ kick
    if name == "rk4":
        L = h * np.array([[0.0, 1.0], [-w2, -gamma]])
        return np.eye(2) + L + L @ L / 2 + L @ L @ L / 6 + L @ L @ L @ L / 24
    if name == "backward_euler":                        # x1 = x0 + h v1; v1 = v0 + h (-w^2 x1 - gamma v1)
        return np.linalg.inv(np.array([[1.0, -h], [w2 * h, 1.0 + gamma * h]]))
    raise AssertionError(name)


def _reference(name, h, z0, n, gamma=0.0):
    """Reference scaled trajectory: the 2x2 map for one-step methods, the BDF2 recurrence otherwise."""
    S = np.diag([OMEGA, 1.0])
    w2 = OMEGA**2
    y = [np.linalg.solve(S, z0)]
    if name == "bdf2":
        y.append(_one_step_matrix("backward_euler", h, gamma=gamma) @ y[0])   # backward-Euler start
        # x2 = 4/3 x1 - 1/3 x0 + 2/3 h v2;  v2 = 4/3 v1 - 1/3 v0 + 2/3 h (-w^2 x2 - gamma v2)
        lhs = np.array([[1.0, -2 / 3 * h], [2 / 3 * h * w2, 1.0 + 2 / 3 * h * gamma]])
        for _ in range(n - 1):
            y.append(np.linalg.solve(lhs, 4 / 3 * y[-1] - 1 / 3 * y[-2]))
    elif name == "verlet":
        # velocity Verlet as documented: v_half = v0 + h/2 a0; x1 = x0 + h v_half; a1 = a(x1, v_half);
        # v1 = v_half + h/2 a1, and a1 is the next step's a0 (a0 = a(x0, v0) on the first step only), with
        # a(x, v) = -w^2 x - gamma v. Without damping this is kick-drift-kick.
        x0, v0 = y[0]
        a = -w2 * x0 - gamma * v0
        for _ in range(n):
            x0, v0 = y[-1]
            vh = v0 + h / 2 * a
            x1 = x0 + h * vh
            a = -w2 * x1 - gamma * vh
            y.append(np.array([x1, vh + h / 2 * a]))
    else:
        T = _one_step_matrix(name, h, gamma=gamma)
        for _ in range(n):
            y.append(T @ y[-1])
    return np.array(y[: n + 1]) @ S.T


def _norm(z):
    return np.linalg.norm(z, axis=1)


@pytest.mark.parametrize("theta", [0.3, 3.0])
def test_backward_euler_amplitude_factor(theta):
    """Per step, |z| shrinks by exactly 1/sqrt(1 + w^2 h^2), also far beyond the explicit limit (w h = 3)."""
    h = theta / OMEGA
    n = 40 if theta < 1 else 6     # stop while the displacement (>= 1e-5 m) is far above round-off of x ~ 10 m
    sim, rest = _oscillator("backward_euler", h)
    z = _run_oscillator(sim, rest, n)
    assert np.allclose(_norm(z)[1:] / _norm(z)[:-1], 1 / np.sqrt(1 + theta**2), rtol=1e-8, atol=0)
    assert np.allclose(z, _reference("backward_euler", h, z[0], n), rtol=1e-8, atol=1e-9 * _norm(z[:1])[0])


def test_forward_euler_amplitude_factor():
    """Per step, |z| grows by exactly sqrt(1 + w^2 h^2) (unstable at any step)."""
    theta = 0.3
    h = theta / OMEGA
    sim, rest = _oscillator("forward_euler", h)
    z = _run_oscillator(sim, rest, 40)
    assert np.allclose(_norm(z)[1:] / _norm(z)[:-1], np.sqrt(1 + theta**2), rtol=1e-9, atol=0)


def test_rk4_amplitude_factor_and_boundedness():
    """RK4's map is c I + s J (J the scaled rotation generator): |z| shrinks by |R(i w h)| < 1 every step."""
    theta = 0.1
    h = theta / OMEGA
    sim, rest = _oscillator("rk4", h)
    z = _run_oscillator(sim, rest, 2000)
    R = abs(1 + 1j * theta + (1j * theta) ** 2 / 2 + (1j * theta) ** 3 / 6 + (1j * theta) ** 4 / 24)
    assert 1 - 1e-8 < R < 1
    assert np.allclose(_norm(z)[1:] / _norm(z)[:-1], R, rtol=1e-9, atol=0)
    assert _norm(z).max() <= _norm(z[:1])[0] * (1 + 1e-12)
    assert np.allclose(z, _reference("rk4", h, z[0], 2000), rtol=0, atol=1e-7 * _norm(z[:1])[0])


@pytest.mark.parametrize("name,theta", [("symplectic_euler", 1.5), ("symplectic_euler", 0.1), ("verlet", 0.1),
                                        ("verlet", 1.9)])
def test_symplectic_methods_bounded_below_two_over_omega(name, theta):
    """h < 2/w: the map has unit-modulus eigenvalues, so |z_n| stays within cond(V) of |z_0| for ever.

    Over 2000 steps the amplitude neither grows nor decays beyond that eigenvector-condition bound, and the
    trajectory follows the scheme's own map.
    """
    h = theta / OMEGA
    sim, rest = _oscillator(name, h)
    n = 2000
    z = _run_oscillator(sim, rest, n)
    T = np.diag([OMEGA, 1.0]) @ _one_step_matrix(name, h) @ np.diag([1 / OMEGA, 1.0])
    lam, V = np.linalg.eig(T)
    assert np.allclose(np.abs(lam), 1.0, atol=1e-12)
    c = np.linalg.cond(V)
    r = _norm(z) / _norm(z[:1])[0]
    assert r.max() <= c * (1 + 1e-9) and r.min() >= (1 - 1e-9) / c
    assert r.max() > 1 - 1e-3 * theta     # it does oscillate back to its initial amplitude: no dissipation
    assert np.allclose(z, _reference(name, h, z[0], n), rtol=0, atol=1e-6 * _norm(z[:1])[0])


def test_symplectic_euler_unbounded_above_two_over_omega():
    """h > 2/w: an eigenvalue of modulus rho > 1; |z| grows by rho per step (checked while the spring stays linear)."""
    theta = 2.1
    h = theta / OMEGA
    sim, rest = _oscillator("symplectic_euler", h)
    n = 11                                   # 0.01 m * rho^11 ~ 10 m: still on the same side of the pinned end
    z = _run_oscillator(sim, rest, n)
    tr = 2 - theta**2
    rho = (abs(tr) + np.sqrt(tr * tr - 4)) / 2   # real eigenvalues with product 1
    assert rho > 1.8
    assert _norm(z)[-1] / _norm(z)[0] > 0.1 * rho**n > 1e2
    assert _norm(z)[-1] / _norm(z)[-2] == pytest.approx(rho, rel=1e-4)
    assert np.allclose(z, _reference("symplectic_euler", h, z[0], n), rtol=1e-9)
    # and a run to a fixed horizon blows up into the divergence check
    sim2, _ = _oscillator("symplectic_euler", h)
    with pytest.raises(ic.DivergenceError):
        sim2.run(duration=2000 * h, frame_rate=1 / h)


def test_bdf2_follows_its_recurrence_and_decays():
    theta = 0.5
    h = theta / OMEGA
    sim, rest = _oscillator("bdf2", h)
    z = _run_oscillator(sim, rest, 200)
    assert np.allclose(z, _reference("bdf2", h, z[0], 200), rtol=0, atol=1e-8 * _norm(z[:1])[0])
    assert _norm(z[-5:]).max() < 0.5 * _norm(z[:1])[0]    # dissipative, but less so than backward Euler:
    assert _norm(z)[-1] > _norm(z)[0] * (1 + theta**2) ** (-100)


@pytest.mark.parametrize("name", ic.INTEGRATORS)
def test_damped_oscillator_follows_each_scheme(name):
    """Spring damping kd along the spring: x'' = -w^2 x - gamma x' with gamma = kd / m; every integrator's
    trajectory equals its scheme's recurrence (for the implicit ones this exercises D = kd u u^T in A)."""
    theta, gamma_h = 0.3, 0.1
    h = theta / OMEGA
    kd = gamma_h / h * M_VERTEX
    sim, rest = _oscillator(name, h, damping=kd)
    n = 200
    z = _run_oscillator(sim, rest, n)
    ref = _reference(name, h, z[0], n, gamma=gamma_h / h)
    assert np.allclose(z, ref, rtol=0, atol=1e-8 * _norm(z[:1])[0])
    if name != "forward_euler":
        assert _norm(z)[-1] < 0.01 * _norm(z)[0]      # it decays (e^{-gamma t / 2} = e^{-10} for the exact ODE)


# --------------------------------------------------------------------------- (c) moving pins
@pytest.mark.parametrize("name", ic.INTEGRATORS)
def test_moving_pin_is_honoured_exactly(name, hanging_scene):
    scene = dict(hanging_scene)
    cloth = dict(hanging_scene["cloth"])
    w = np.array([0.4, -0.3, 0.25])
    cloth["pins"] = ["top_right", {"vertices": ["top_left", 1], "velocity": w.tolist()}]
    cloth["springs"] = {"structural": {"stiffness": 50.0, "damping": 0.05},
                        "shear": {"stiffness": 5.0, "damping": 0.01}}
    scene["cloth"] = cloth
    scene["effects"] = {"gravity": G.tolist(), "drag": 0.2}
    h, n = 1e-3, 300
    sim = ic.Simulator(scene, integrator=name, dt=h)
    nx = 4
    moving, fixed = [(nx - 1) * nx, 1], [nx * nx - 1]
    x0 = sim.positions.copy()
    sim.step(n)
    assert sim.time == pytest.approx(n * h, rel=1e-12)
    assert np.allclose(sim.positions[moving], x0[moving] + w * sim.time, rtol=0, atol=1e-13)
    assert np.allclose(sim.positions[moving], x0[moving] + w * n * h, rtol=0, atol=1e-12)
    assert np.array_equal(sim.positions[fixed], x0[fixed])
    assert np.array_equal(sim.velocities[moving], np.tile(w, (2, 1)))
    assert np.array_equal(sim.velocities[fixed], np.zeros((1, 3)))
    # the cloth is dragged along (the pins are not merely reported, they act), and stays finite
    assert np.all(np.isfinite(sim.positions))
    assert sim.positions[5, 0] - x0[5, 0] > 0.01
