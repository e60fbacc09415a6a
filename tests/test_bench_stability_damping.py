"""The stability and damping benchmarks: the eigenvalue bound against brute force, the search, and the quick modes.

Numbers of the benchmarks themselves are not asserted, only that the outputs exist and are well formed.
"""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import implicit_cloth as ic

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "benchmarks") not in sys.path:
    sys.path.insert(0, str(ROOT / "benchmarks"))

import damping  # noqa: E402
import stability  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _model(n, k):
    return ic.Simulator(stability.scene(n, k), integrator="symplectic_euler", dt=1e-4).model


def _dense_minus_dfdx(model, x):
    """-dF/dx, dense, by a plain loop over the springs' exact 3x3 blocks (no system-matrix assembly)."""
    s = model.springs
    Kb, _ = s.jacobian(x, exact=True)       # df_i/dx_j of each spring
    K = np.zeros((3 * model.n, 3 * model.n))
    for b, i, j in zip(Kb, s.i, s.j):
        I, J = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
        K[I, I] += b
        K[J, J] += b
        K[I, J] -= b
        K[J, I] -= b
    return K


def _free(model, A):
    f = np.repeat(model.free, 3)
    return A[np.ix_(f, f)]


@pytest.mark.parametrize("k", [1e2, 1e4, 1e6])
@pytest.mark.parametrize("stretch", [1.0, 1.05])
def test_eigenvalue_bound_matches_dense_generalized_problem(k, stretch):
    """w_max^2 from eigsh on M^-1/2 K M^-1/2 equals the largest eigenvalue of the dense K phi = lambda M phi."""
    model = _model(5, k)
    x = model.rest_positions * stretch   # 1.05: every spring stretched (the clamped and exact Jacobians agree)
    K = _free(model, _dense_minus_dfdx(model, x))
    M = np.diag(_free(model, np.diag(np.repeat(model.masses, 3))))
    lam_dense = scipy.linalg.eigh(K, np.diag(M), eigvals_only=True)[-1]
    mode = stability.top_mode(model, x)
    assert mode["lambda_max"] == pytest.approx(lam_dense, rel=1e-8)
    assert stability.omega_max(model, x) == pytest.approx(math.sqrt(lam_dense), rel=1e-8)
    assert mode["bound_2_over_w"] == pytest.approx(2 / math.sqrt(lam_dense), rel=1e-8)


def test_stiffness_is_the_true_derivative_at_rest():
    """The assembled K is -dF/dx of the force code (central differences), at the rest pose of a 5x5 cloth."""
    model = _model(5, 1e3)
    x0 = model.rest_positions.copy()
    v = np.zeros_like(x0)
    K, C, m = stability.free_matrices(model, x0)
    free = np.flatnonzero(np.repeat(model.free, 3))
    eps = 1e-7
    J = np.zeros((len(free), len(free)))
    for c, q in enumerate(free):
        xp, xm = x0.copy().ravel(), x0.copy().ravel()
        xp[q] += eps
        xm[q] -= eps
        fp = model.forces(xp.reshape(-1, 3), v, 0.0).ravel()[free]
        fm = model.forces(xm.reshape(-1, 3), v, 0.0).ravel()[free]
        J[:, c] = -(fp - fm) / (2 * eps)
    assert np.allclose(K.toarray(), J, rtol=1e-6, atol=1e-6 * np.abs(J).max())
    assert np.array_equal(m, np.repeat(model.masses, 3)[free])
    # the damping matrix of this scene is (kd / k) K at rest: every mode has the same 2 zeta / w = kd / k
    assert np.allclose(C.toarray(), (stability.KD / 1e3) * K.toarray(), atol=1e-12)


def test_search_brackets_a_known_threshold():
    def fake(threshold):
        return lambda dt: {"dt": dt, "stable": dt <= threshold}

    r = stability.search(fake(0.0123), guess=0.05, floor=1e-5, cap=1 / 15, rtol=0.01)
    assert r["status"] == "bracketed"
    assert r["dt_max"] <= 0.0123 < r["dt_unstable"] <= r["dt_max"] * 1.01
    r = stability.search(fake(1.0), guess=1e-3, floor=1e-5, cap=1 / 15, rtol=0.01)
    assert r["status"] == "at_cap" and r["dt_max"] == 1 / 15
    r = stability.search(fake(1e-6), guess=1e-3, floor=1e-5, cap=1 / 15, rtol=0.01)
    assert r["status"] == "below_floor" and r["dt_max"] is None and r["dt_unstable"] == 1e-5


def test_damping_helpers():
    t = np.linspace(0, 3, 181)
    y = 0.4 * np.exp(-0.1 * t) * np.sin(4.0 * t)
    ex = damping.extremes(t, y)
    assert len(ex) == 4
    assert damping.swing_omega(ex) == pytest.approx(4.0, rel=2e-3)
    (ta, aa), (tb, ab) = ex[0], ex[-1]
    assert math.log(aa / ab) / (tb - ta) == pytest.approx(0.1, rel=1e-2)
    # exact backward Euler on a linear oscillator: energy x 1/(1 + w^2 h^2) per step; BDF2 far less dissipative
    assert damping.theory_rate("backward_euler", 4.0, 0.01) == pytest.approx(math.log(1.0016) / 0.01)
    assert 0 < damping.theory_rate("bdf2", 4.0, 0.01) < 1e-2 * damping.theory_rate("backward_euler", 4.0, 0.01)
    assert damping._dt_label(1 / 60) == "1/60" and damping._dt_label(2.5e-4) == "0.00025"


def _md_table_rows(md):
    return [line for line in md.splitlines() if line.startswith("|") and line.endswith("|")]


def test_stability_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "stability", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "stability.json").read_text())
    assert res["benchmark"] == "stability" and res["quick"] is True and res["seed"] == 0
    assert {"platform", "python", "cpus", "versions"} <= set(res["machine"])
    assert set(res["integrators"]) == set(ic.INTEGRATORS)
    assert [r["k"] for r in res["rows"]] == res["ks"] and len(res["rows"]) >= 2
    rtol = res["settings"]["rtol"]
    for row in res["rows"]:
        assert row["mode"]["omega_max"] > 0 and row["mode"]["bound_2_over_w"] > 0
        for name in ic.INTEGRATORS:
            r = row["results"][name]
            assert r["status"] in ("bracketed", "at_cap", "below_floor") and r["trials"]
            if r["status"] == "bracketed":
                assert r["dt_max"] < r["dt_unstable"] <= r["dt_max"] * (1 + rtol) * (1 + 1e-12)
            for t in r["trials"]:
                assert isinstance(t["stable"], bool) and t["dt"] > 0
    md = (tmp_path / "stability.md").read_text()
    rows = _md_table_rows(md)
    assert any(line.startswith("| k (N/m) | ω_max") for line in rows)
    assert sum(line.startswith("| 1e+02 |") for line in rows) >= 2   # both tables have a row per k
    png = (tmp_path / "stability.png").read_bytes()
    assert png[:8] == PNG_MAGIC and len(png) > 5000


def test_damping_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "damping", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "damping.json").read_text())
    assert res["benchmark"] == "damping" and res["quick"] is True and "seed" in res
    assert {"platform", "python", "cpus", "versions"} <= set(res["machine"])
    assert set(res["reference"]) == {"off", "on"}
    for ref in res["reference"].values():
        assert ref["status"] == "ok" and 0 < ref["energy_remaining"] <= 1.01 and ref["rate_error"] >= 0
    expected = {(i, d) for i in ic.INTEGRATORS for d in ("off", "on")}
    assert {(r["integrator"], r["damping"]) for r in res["runs"]} == expected
    for r in res["runs"]:
        assert r["status"] in ("ok", "diverged")
        if r["status"] == "ok":
            assert len(r["curve_t"]) == len(r["curve_E"]) >= 2 and "numerical_rate" in r
    md = (tmp_path / "damping.md").read_text()
    assert "### Physical damping off" in md and "### Physical damping on" in md
    rows = _md_table_rows(md)
    assert sum(line.startswith("| backward_euler |") for line in rows) == 4
    png = (tmp_path / "damping.png").read_bytes()
    assert png[:8] == PNG_MAGIC and len(png) > 5000
