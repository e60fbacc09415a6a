"""The accuracy-cost and headline benchmarks: the reference solution's convergence, the Pareto and cheapest-run
selection, and the quick modes. Numbers of the benchmarks themselves (times) are not asserted."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

import implicit_cloth as ic

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "benchmarks") not in sys.path:
    sys.path.insert(0, str(ROOT / "benchmarks"))

import accuracy_cost  # noqa: E402
import headline  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def tiny_equilibrium():
    x, residual = accuracy_cost.equilibrium(4)
    return x, residual


def test_equilibrium_is_static(tiny_equilibrium):
    x, residual = tiny_equilibrium
    assert residual < 1e-8          # N; the cloth's weight is ~1 N
    sim = ic.Simulator(accuracy_cost.scene(4, "equilibrium"), integrator="rk4", dt=1e-4)
    sim.positions = x
    sim.step(50)                    # an independent integrator does not move it
    assert np.abs(sim.positions - x).max() < 1e-9


def test_reference_converges_at_fourth_order(tiny_equilibrium):
    """The reference check (RK4 at dt_ref against 2 dt_ref) shrinks 16-fold per halving of dt_ref, and is far
    below the error of a run of the benchmark's ladder, so the reference stands in for the exact motion."""
    x0, _ = tiny_equilibrium
    T = 2 / 15
    h = 1 / 7680                    # 2/omega_max of this 4x4 cloth is about 1.8e-3 s
    fine = accuracy_cost.reference(4, "hanging", x0, T, h)
    coarse = accuracy_cost.reference(4, "hanging", x0, T, 2 * h)
    assert fine["check_rms"] > 0 and coarse["check_rms"] > 0
    ratio = coarse["check_rms"] / fine["check_rms"]
    assert 12 < ratio < 20, ratio   # 2^4 = 16 for a 4th-order method in its asymptotic range
    assert 10 < coarse["check_max"] / fine["check_max"] < 22
    run = accuracy_cost.simulate(4, "hanging", "verlet", 1 / 960, x0, T)
    r = accuracy_cost.compare(run, fine)
    assert r["status"] == "ok" and r["rms_error"] > 1e3 * fine["check_rms"]
    assert 0 < r["rms_error"] <= r["max_error"]
    # and a run compared with itself has no error (the error figures measure what they say)
    same = accuracy_cost.compare(dict(fine, energy_scale_J=1.0, status="ok"), fine)
    assert same["rms_error"] == 0 and same["max_error"] == 0 and same["energy_drift"] == 0


def test_position_errors_closed_form():
    x_ref = np.zeros((2, 3, 3))
    x = x_ref.copy()
    x[1, 0] = [3.0, 4.0, 0.0]       # one vertex 5 m off in one of two frames: RMS = sqrt(25 / 6)
    rms, mx = accuracy_cost.position_errors(x, x_ref, size=2.0)
    assert rms == pytest.approx(math.sqrt(25 / 6) / 2) and mx == pytest.approx(2.5)


def test_ladder_reaches_the_explicit_bound():
    dts = accuracy_cost.ladder(6e-4, explicit_extra=1)
    assert dts[-1] == pytest.approx(1 / 15) and dts == sorted(dts)
    assert dts[1] <= 0.9 * 6e-4 < dts[2]                       # first step under the bound, then one more halving
    assert np.allclose(np.array(dts[1:]) / np.array(dts[:-1]), 2.0)
    assert all(abs((1 / 15) / h - round((1 / 15) / h)) < 1e-9 for h in dts)   # every step divides the frame interval


def test_pareto_and_cheapest():
    def run(i, wall, err, status="ok"):
        return {"integrator": i, "cost_s": wall, "rms_error": err, "status": status}

    runs = [run("rk4", 1.0, 1e-6), run("symplectic_euler", 0.2, 1e-3), run("backward_euler", 0.1, 1e-1),
            run("bdf2", 0.3, 2e-3), run("verlet", 0.25, 1e-4), run("forward_euler", 0.01, 0.0, "diverged")]
    front = accuracy_cost.pareto(runs)
    assert [r["integrator"] for r in front] == ["backward_euler", "symplectic_euler", "verlet", "rk4"]
    assert accuracy_cost.cheapest(runs, 1e-2)["integrator"] == "symplectic_euler"
    assert accuracy_cost.cheapest(runs, 1e-2, accuracy_cost.IMPLICIT)["integrator"] == "bdf2"
    assert accuracy_cost.cheapest(runs, 1e-7) is None
    assert accuracy_cost.cheapest(runs, 1.0)["integrator"] == "backward_euler"   # the diverged run never counts


def test_accuracy_cost_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "accuracy_cost", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "accuracy_cost.json").read_text())
    assert res["benchmark"] == "accuracy_cost" and res["quick"] is True and "seed" in res
    assert {"platform", "python", "cpus", "versions"} <= set(res["machine"])
    assert res["scenes"] == ["hanging", "wind"]
    for name in res["scenes"]:
        sc = res["results"][name]
        ref = sc["reference"]
        assert 0 <= ref["check_rms"] <= ref["check_max"] and ref["dt"] < min(sc["dts"])
        runs = sc["runs"]
        assert {r["integrator"] for r in runs} == set(ic.INTEGRATORS)
        assert {r["tolerance"] for r in runs if r["integrator"] in accuracy_cost.IMPLICIT} == set(res["tolerances"])
        for r in runs:
            assert r["status"] in ("ok", "diverged", "unstable") and r["wall_s"] > 0 and r["cpu_s"] > 0
            assert r["cost_s"] == r["cpu_s"]          # the default clock
            if r["status"] == "diverged":
                assert "rms_error" not in r and r["reason"]
            else:
                assert 0 <= r["rms_error"] <= r["max_error"] and r["energy_drift"] >= 0
        assert any(r["status"] == "diverged" for r in runs)       # explicit methods past their bound
        front = sc["pareto"]
        assert front and all(r["status"] == "ok" for r in front)
        assert all(a["cost_s"] <= b["cost_s"] and a["rms_error"] > b["rms_error"] for a, b in zip(front, front[1:]))
        assert [c["level"] for c in sc["cheapest"]] == sorted(res["settings"]["levels"], reverse=True)
    md = (tmp_path / "accuracy_cost.md").read_text()
    assert md.count("## Scene `") == 2 and md.count("### Pareto front") == 2
    assert "| 1/15 |" in md and "div (step" in md
    png = (tmp_path / "accuracy_cost.png").read_bytes()
    assert png[:8] == PNG_MAGIC and len(png) > 5000
    # --render re-derives the same tables from the JSON without simulating
    again = tmp_path / "again"
    assert accuracy_cost.main(["--render", str(tmp_path / "accuracy_cost.json"), "--out", str(again)]) == 0
    assert (again / "accuracy_cost.md").read_text() == md
    assert (again / "accuracy_cost.png").read_bytes()[:8] == PNG_MAGIC


def test_headline_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "headline", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "headline.json").read_text())
    assert res["benchmark"] == "headline" and res["quick"] is True and res["seed"] == 0
    assert [r["resolution"] for r in res["scaling"]] == res["sizes"]
    for r in res["scaling"]:
        assert r["ms_step"] > 0 and r["ms_collision"] >= 0 and r["iterations_max"] >= 1
    assert [r["k"] for r in res["rows"]] == res["ks"]
    for row in res["rows"]:
        assert set(row["results"]) == set(ic.INTEGRATORS)
        for r in row["results"].values():
            assert r["status"] in ("bracketed", "at_cap", "below_floor")
            if r["dt_max"] is not None:
                assert r["one_second"]["method"] in ("run", "extrapolated") and r["one_second"]["steps"] >= 1
        h = row["headline"]
        assert h["implicit"] in ("backward_euler", "bdf2") and h["implicit_wins_by"] > 0
    assert res["headline"].startswith("Headline (")
    md = (tmp_path / "headline.md").read_text()
    assert "| 8² |" in md and "| 12² |" in md and "| 1e+02 |" in md and "| collision |" in md
    png = (tmp_path / "headline.png").read_bytes()
    assert png[:8] == PNG_MAGIC and len(png) > 5000


def test_headline_takes_steps_from_a_stability_result(tmp_path):
    """Part 2 reads dt_max from a stability.json instead of searching (resolution and k too)."""
    fake = {"benchmark": "stability", "settings": {"resolution": 4},
            "rows": [{"k": 100.0, "mode": {"omega_max": 1.0},
                      "results": {i: ({"status": "below_floor", "dt_max": None, "dt_unstable": 1e-5}
                                      if i == "forward_euler" else
                                      {"status": "bracketed", "dt_max": 1 / 240, "dt_unstable": 1 / 230})
                                  for i in ic.INTEGRATORS}}]}
    path = tmp_path / "stability.json"
    path.write_text(json.dumps(fake))
    assert headline.main(["--sizes", "4", "--warmup", "1", "--steps", "2", "--repeats", "1",
                          "--stability", str(path), "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "headline.json").read_text())
    assert res["settings"]["resolution"] == 4 and res["ks"] == [100.0]
    row = res["rows"][0]
    assert row["source"] == str(path) and "one_second" not in row["results"]["forward_euler"]
    for i in ic.INTEGRATORS[1:]:
        o = row["results"][i]["one_second"]
        assert o["method"] == "run" and o["steps"] == 240 and o["status"] == "ok"
