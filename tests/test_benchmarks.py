"""Benchmarks' quick (CI smoke) mode writes well-formed outputs. Numbers are not asserted."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "benchmarks" / "studies"


def _results_state() -> dict:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in (ROOT / "benchmarks" / "results").iterdir()}


def test_bench_help_lists_every_benchmark_with_a_line_each(capsys):
    """``bench --help`` names each benchmark with the first line of its docstring; the studies (a record of a
    lever measured) and helpers are not listed."""
    from implicit_cloth.cli import bench_names, main

    names = bench_names()
    assert {"accuracy_cost", "stability", "damping", "scaling", "contact_energy", "self_collision",
            "vs_blender"} <= set(names)
    assert not {"_common", "_blender_cloth", "stopping_rule", "mg_levers", "digests"} & set(names)
    assert all(len(line) > 20 and "\n" not in line for line in names.values())
    assert main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    for name, line in names.items():
        assert f"  {name} " in out and line[:40] in out
    assert "(also: bench contact)" in out


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(__import__("implicit_cloth.cli").cli.bench_names()))
def test_every_listed_benchmark_runs_quick(name, tmp_path):
    """Every name ``bench --help`` lists runs with ``--quick`` (a small case end to end, seconds), prints its
    table and writes it, without ``--out``, to ``out/bench/NAME/`` under the working directory, leaving the
    committed results as they were."""
    before = _results_state()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-m", "implicit_cloth.cli", "bench", name, "--quick"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    out = tmp_path / "out" / "bench" / name
    res = json.loads((out / f"{name}.json").read_text())
    assert res["benchmark"] == name and res["quick"] is True
    md = (out / f"{name}.md").read_text()
    assert "|---" in md and "\n| " in proc.stdout
    assert _results_state() == before


def test_step_cost_quick(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "step_cost.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    res = json.loads((tmp_path / "step_cost.json").read_text())
    assert res["benchmark"] == "step_cost" and res["quick"] is True
    assert [r["resolution"] for r in res["rows"]] == [8, 16]
    for r in res["rows"]:
        assert r["ms_step"] > 0 and r["iterations_median"] >= 1 and r["step_in_spmvs"] > 0
    md = (tmp_path / "step_cost.md").read_text()
    assert md.count("\n| 8² |") + md.count("\n| 16² |") == 2


def test_scaling_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "scaling", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "scaling.json").read_text())
    assert res["benchmark"] == "scaling" and res["quick"] is True
    assert {r["preconditioner"] for r in res["rows"]} == {"multigrid", "block_jacobi"}
    for r in res["rows"]:
        assert r["ms_step"] > 0 and r["step_in_spmvs"] > 0
        assert r["true_error_max"] is not None and 0 <= r["true_error_max"] < 1
    assert set(res["exponents"]) == {"multigrid@10000", "multigrid@1000", "block_jacobi@10000", "block_jacobi@1000"}
    assert (tmp_path / "scaling.md").read_text().count("### k =") == 4
    png = (tmp_path / "scaling.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_bench_unknown_name_exits_2(capsys):
    from implicit_cloth.cli import main

    assert main(["bench", "nonsense"]) == 2
    assert "unknown benchmark 'nonsense'" in capsys.readouterr().err


def test_self_collision_quick_via_cli(tmp_path):
    from implicit_cloth.cli import main

    assert main(["bench", "self_collision", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "self_collision.json").read_text())
    assert res["benchmark"] == "self_collision" and res["quick"] is True
    assert [r["resolution"] for r in res["rows"]] == [10, 14]
    for r in res["rows"]:
        assert r["ms_step"] > 0 and r["max_crossings"] == 0 and r["unresolved_steps"] == 0
        assert r["ms_self"] <= r["ms_step"]
    assert "| 14² |" in (tmp_path / "self_collision.md").read_text()


def test_cloth_models_quick_via_cli(tmp_path):
    """``bench cloth_models --quick``: both models on the three scenes (the springs without a membrane, the
    triangles with the membrane and the dihedral bending and no spring), each run ok, the crumple's judges (no
    crossing) and the drape's (outside the sphere) filled in, and the sag table at three sizes per model."""
    from implicit_cloth.cli import main

    assert main(["bench", "cloth_models", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "cloth_models.json").read_text())
    assert res["benchmark"] == "cloth_models" and res["quick"] is True
    assert [(r["scene"], r["model"]) for r in res["rows"]] == [
        (s, m) for s in ("hanging", "drape", "crumple") for m in ("springs", "triangles")]
    for r in res["rows"]:
        assert r["ms_step"] > 0 and r["cg_per_step"] >= 1 and r["status"] == "ok", r
        assert 0 <= r["principal_strain"] < 0.5 and r["report_max_strain"] >= 0
        if r["model"] == "triangles":
            assert {"membrane", "bending"} <= set(r["effects"]) and not {"structural", "bend"} & set(r["effects"])
        else:
            assert {"structural", "shear", "bend"} <= set(r["effects"]) and "membrane" not in r["effects"]
        if r["scene"] == "crumple":      # landed: on the floor, kept the thickness (5 mm) off it by the rounds
            assert r["crossings"] == 0 and r["floor_gap_mm"] > 2.49 and r["rod_gap_mm"] > 2.49
        if r["scene"] == "drape":        # on the sphere
            assert 4.0 < r["sphere_gap_mm"] < 6.0
    assert sorted((r["n"], r["model"]) for r in res["sag"]) == [
        (n, m) for n in (6, 8, 10) for m in ("springs", "triangles")]
    assert all(len(r["drop"]) == len(r["times"]) and r["drop"][-1] > 0 for r in res["sag"])
    md = (tmp_path / "cloth_models.md").read_text()
    assert "| crumple (0.4 s) | 8² | triangles + dihedral |" in md and "## The hanging cloth's sag" in md


def test_contact_energy_quick_via_cli(tmp_path):
    """``implicit-cloth bench contact --quick``: every row judged from its states (energy rise, strain, end state),
    the goals recorded; the outputs are well formed. Goals are read off the table, not asserted here (the
    contact tests assert them)."""
    from implicit_cloth.cli import main

    assert main(["bench", "contact", "--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "contact_energy.json").read_text())
    assert res["benchmark"] == "contact_energy" and res["quick"] is True
    groups = {r["group"] for r in res["rows"]}
    assert groups == {"static", "moving"}
    for r in res["rows"]:
        assert r["frames"] >= 1 and r["ms_per_frame"] > 0 and r["substeps_per_frame"] >= 1
        assert r["report_status"] in ("ok", "warning")
        if r["group"] == "static":
            assert r["end"] in ("resting on it", "still moving", "slid off")
        else:
            assert r["max_stretch"] >= 1.0
    # a row still moving after its 1 s is run again at a quarter of its step, and the table says what that gave
    still = [r for r in res["rows"] if r["group"] == "static" and r["end"] == "still moving"]
    assert still and all([f["dt"] for f in r["finer_runs"]] == [r["dt"] / 4] and r["finer_runs"][0]["vrms_end"] >= 0
                         for r in still)
    assert all("finer_runs" not in r for r in res["rows"] if r not in still)
    md = (tmp_path / "contact_energy.md").read_text()
    assert "| static | sphere | 12² |" in md and "Moving sphere" in md and "run again at finer steps" in md
    assert "meeting the goal" in md
    # merging parts: a row run again in a later part replaces the earlier one
    again = dict(res, rows=[dict(still[0], ms_per_frame=-1.0)])
    (tmp_path / "again.json").write_text(json.dumps(again))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import contact_energy

    contact_energy.merge([tmp_path / "contact_energy.json", tmp_path / "again.json"], tmp_path / "merged")
    merged = json.loads((tmp_path / "merged" / "contact_energy.json").read_text())
    assert len(merged["rows"]) == len(res["rows"])
    assert sum(r["ms_per_frame"] == -1.0 for r in merged["rows"]) == 1
    png = (tmp_path / "contact_energy.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_rest_reference_quick(tmp_path):
    """``benchmarks/studies/rest_reference.py --quick``: a row of the contact table at its step, at the finer
    steps and with symplectic Euler, each run's speed at every kept frame, and a verdict per row."""
    script = str(STUDIES / "rest_reference.py")
    subprocess.run([sys.executable, script, "--quick", "--out", str(tmp_path)], check=True, capture_output=True)
    res = json.loads((tmp_path / "rest_reference.json").read_text())
    assert res["benchmark"] == "rest_reference" and res["quick"] is True
    runs = res["runs"]
    assert [(r["integrator"], r["factor"]) for r in runs] == [("backward_euler", 1), ("backward_euler", 2),
                                                               ("symplectic_euler", None)]
    assert runs[1]["dt"] == runs[0]["dt"] / 2
    for r in runs:
        assert len(r["t"]) == len(r["vrms"]) >= 10 and r["t"] == sorted(r["t"]) and r["vrms_end"] >= 0
        assert r["vrms"][-1] == r["vrms_end"] and r["status"] in ("ok", "warning")
    md = (tmp_path / "rest_reference.md").read_text()
    assert "| capsule:8:30 | symplectic Euler, dt 0.0004 s |" in md and "* capsule:8:30: " in md
    assert (tmp_path / "rest_reference.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a bad row names the option and the value: argparse's usage error, exit code 2
    bad = subprocess.run([sys.executable, script, "--rows", "torus:8:30", "--out", str(tmp_path)],
                         capture_output=True, text=True)
    assert bad.returncode == 2
    err = bad.stderr
    assert "argument --rows: 'torus:8:30' is not SHAPE:N:1/DT (unknown shape 'torus'" in err


def test_vs_blender_without_blender_and_its_worker_reports(tmp_path):
    """Without Blender on PATH the comparison says so on stderr and exits 1, writing nothing, and ``--quick``
    runs our side alone; the worker that times our side prints one RESULT record (a small cloth, fixed steps)
    with the fields the comparison reads."""
    env = dict(os.environ, PATH=str(Path(sys.executable).parent))       # no blender there
    script = str(ROOT / "benchmarks" / "vs_blender.py")
    proc = subprocess.run([sys.executable, script, "--sizes", "8", "--out", str(tmp_path)], env=env,
                          capture_output=True, text=True)
    assert proc.returncode == 1 and "Blender is not installed" in proc.stderr and "--quick" in proc.stderr
    assert not list(tmp_path.iterdir())
    # --quick without Blender: our side alone, Blender's columns empty
    out = subprocess.run([sys.executable, script, "--quick", "--scenes", "hanging", "--out", str(tmp_path)], env=env,
                         check=True, capture_output=True, text=True).stdout
    assert "Blender is not installed: our side only" in out
    (row,) = json.loads((tmp_path / "vs_blender.json").read_text())["rows"]
    assert row["n"] == 8 and row["ours_ms"] > 0 and row["blender_ms"] is None and row["ratio"] is None
    assert "| hanging | 8² |" in out and "| - | - |" in out
    # --merge combines runs' rows (a scene and size given twice: one row)
    merged = subprocess.run([sys.executable, script, "--merge", str(tmp_path / "vs_blender.json"),
                             str(tmp_path / "vs_blender.json"), "--out", str(tmp_path / "m")],
                            check=True, capture_output=True, text=True).stdout
    assert len(json.loads((tmp_path / "m" / "vs_blender.json").read_text())["rows"]) == 1
    assert "| hanging | 8² |" in merged
    out = subprocess.run([sys.executable, script, "--worker", "--scenes", "drape", "--sizes", "8", "--fixed"],
                         check=True, capture_output=True, text=True).stdout
    res = json.loads(next(line for line in out.splitlines() if line.startswith("RESULT "))[7:])
    assert res["scene"] == "drape" and res["n"] == 8 and res["fixed_steps"] is True and res["finite"]
    assert res["ms_per_frame"] > 0 and res["iterations_per_frame"] > 0 and res["solves_per_frame"] >= 1
    # fixed steps: no attempt discarded, every solve an accepted one
    assert res["attempted_solves_per_frame"] == res["solves_per_frame"]
    assert res["attempted_iterations_per_frame"] == res["iterations_per_frame"]
    assert res["zmin"] > -0.35       # on the sphere (r = 0.3), not through it
    assert res["preconditioner"] == "multigrid"
    out = subprocess.run([sys.executable, script, "--worker", "--scenes", "hanging", "--sizes", "8", "--fixed",
                          "--preconditioner", "multigrid_smoothed"], check=True, capture_output=True, text=True).stdout
    res = json.loads(next(line for line in out.splitlines() if line.startswith("RESULT "))[7:])
    assert res["preconditioner"] == "multigrid_smoothed" and res["finite"] and res["iterations_per_frame"] > 0


def test_contact_energy_goal_per_row():
    """The contact table's goal per static row: a rise, a slide or creep on the obstacle misses it; a row still
    moving meets it only where its finest finer run moves on too (the scene's motion), and rows of the script's
    earlier versions (one finer run as ``finer_*`` keys) are judged the same way."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import contact_energy as ce

    base = {"rise_frac": 0.0, "end": "resting on it", "on_vrms_end": 1e-4, "dt": 1 / 60, "vrms_end": 0.005}
    assert ce.goal(base) == (True, "at rest")
    assert not ce.goal(dict(base, rise_frac=0.03))[0]
    assert ce.goal(dict(base, end="slid off")) == (False, "slid off")
    moving = dict(base, end="still moving", vrms_end=0.015)
    assert ce.goal(moving) == (False, "still moving (no finer run)")
    assert ce.goal(dict(moving, on_vrms_end=0.02))[1] == "creeps on the obstacle"
    swing = [{"factor": 4, "dt": 1 / 240, "vrms_end": 0.04, "rest_from": None},
             {"factor": 16, "dt": 1 / 960, "vrms_end": 0.1, "rest_from": None}]
    met, why = ce.goal(dict(moving, finer_runs=swing))
    assert met and "0.1" not in why and "10.00 cm/s at dt 1/960" in why
    rests = [swing[0], dict(swing[1], vrms_end=0.002, rest_from=2.0)]
    assert ce.goal(dict(moving, finer_runs=rests)) == (False, "the large step keeps it moving (at rest at dt 1/960)")
    # the finest run decides, whatever the order stored
    assert ce.goal(dict(moving, finer_runs=rests[::-1]))[0] is False
    legacy = dict(moving, finer_dt=1 / 240, finer_vrms_end=0.03, finer_rest_from=None)
    assert ce.goal(legacy)[0] and ce.finer_runs(legacy)[0]["factor"] == 4


def test_solver_choice_small_run_writes_rows(tmp_path):
    """The systems are captured from the model's lazily finalized SystemMatrix (its CSR): a 12² run of the
    script's numpy V-cycle and the library's own compiled preconditioners on the same systems (free and in
    contact). The numpy V-cycle (``jacobi``) is the library's plain multigrid written again: the same iterations
    as ``lib_multigrid`` (within one: the compiled products round otherwise)."""
    subprocess.run([sys.executable, str(STUDIES / "solver_choice.py"), "--sizes", "12", "--systems",
                    "hanging", "drape", "--levers", "jacobi", "weighed_P", "lib_multigrid", "lib_smoothed",
                    "lib_smoothed_identity", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True, cwd=STUDIES)
    res = json.loads((tmp_path / "solver_choice.json").read_text())
    rows = [r for r in res["rows"] if r["lever"] == "jacobi"]
    assert len(rows) == 3 and all(r["converged"] and r["true_error"] < 1e-2 for r in rows)
    weighed = [r for r in res["rows"] if r["lever"] == "weighed_P"]
    assert len(weighed) == 2 and all(r["converged"] and r["true_error"] < 1e-2 for r in weighed)
    lib = {(r["system"], r["lever"]): r for r in res["rows"] if r["lever"].startswith("lib_")}
    assert len(lib) == 9 and all(r["converged"] and r["true_error"] < 1e-2 and r["ms"] > 0 for r in lib.values())
    for r in rows:
        assert abs(lib[(r["system"], "lib_multigrid")]["iterations"] - r["iterations"]) <= 1
    assert "drape, constraints removed" in {s for s, _ in lib}


def test_soft_modes_quick(tmp_path):
    subprocess.run([sys.executable, str(STUDIES / "soft_modes.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True, cwd=STUDIES)
    res = json.loads((tmp_path / "soft_modes_quick.json").read_text())
    assert res["benchmark"] == "soft_modes" and res["quick"] is True
    assert {r["system"] for r in res["rows"]} == {"hanging", "drape"}
    for r in res["rows"]:
        assert r["iterations"] >= 1 and r["true_error"] < 1e-2 and r["as_preconditioner_iterations"] >= 1
    assert 0 < res["compressed"]["drape 12"]["all"] < 1
    assert (tmp_path / "soft_modes_quick.md").read_text().count("\n| ") >= 8


def test_rigid_coarse_quick(tmp_path):
    """The rigid-mode aggregation study runs its levers on captured systems; each solves to the tolerance."""
    subprocess.run([sys.executable, str(STUDIES / "rigid_coarse.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True, cwd=STUDIES)
    res = json.loads((tmp_path / "rigid_coarse_quick.json").read_text())
    assert res["benchmark"] == "rigid_coarse" and res["quick"] is True
    assert {r["lever"] for r in res["rows"]} == {"bilinear", "rigid", "rigid + SA below", "SA everywhere"}
    for r in res["rows"]:
        assert r["converged"] and r["iterations"] >= 1 and r["true_error"] < 1e-2 and r["passes"] > 0
    assert (tmp_path / "rigid_coarse_quick.md").read_text().count("\n| ") == 5      # header, four levers


@pytest.mark.slow
def test_threads_layer_quick(tmp_path):
    """The threading-layer study runs each layer that loads here on one and two threads, in its own processes."""
    proc = subprocess.run([sys.executable, str(STUDIES / "threads_layer.py"), "--quick", "--out", str(tmp_path)],
                          check=True, capture_output=True, text=True)
    res = json.loads((tmp_path / "threads_layer.json").read_text())
    assert res["benchmark"] == "threads_layer" and res["quick"] is True
    assert res["rows"] and {r["n"] for r in res["rows"]} == {32}, proc.stderr[-2000:]
    for r in res["rows"]:
        assert r["layer"] in ("tbb", "omp", "omp-spin", "workqueue") and r["ms_1"] > 0 and r["ms_2"] > 0
        assert r["same_numbers"]                     # two threads give one thread's positions to the last bit
    assert (tmp_path / "threads_layer.md").read_text().count("\n| ") == 1 + len(res["rows"])      # header, rows


def test_drape_phases_quick(tmp_path):
    """``benchmarks/studies/drape_phases.py --quick``: the 16² drape's frames split into the fall and the landing, each
    frame's figures the simulator's own (solves at least its collider's rounds, one round a frame in the fall)."""
    subprocess.run([sys.executable, str(STUDIES / "drape_phases.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True, cwd=STUDIES)
    res = json.loads((tmp_path / "drape_phases_quick.json").read_text())
    assert res["benchmark"] == "drape_phases" and res["quick"] is True
    (r,) = res["rows"]
    frames, ph = r["frames"], r["phases"]
    assert len(frames) == 39 and all(f["solves"] >= f["rounds"] >= 1 for f in frames)
    assert ph["fall"]["frames"] > 0 and ph["landing"]["frames"] > 0
    assert sum(p["frames"] for p in ph.values()) == 39
    assert ph["fall"]["rounds"] == 1.0 and ph["landing"]["solves"] > ph["fall"]["solves"]
    assert (tmp_path / "drape_phases_quick.md").read_text().count("\n| 16² |") == 4


def test_stopping_rule_quick(tmp_path):
    """The stopping-rule study captures real steps' systems (the model's SystemMatrix, copied as its CSR) and
    replays CG on them: every scene sampled, each captured system solved, the rules' errors measured."""
    subprocess.run([sys.executable, str(STUDIES / "stopping_rule.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    res = json.loads((tmp_path / "stopping_rule.json").read_text())
    assert res["benchmark"] == "stopping_rule" and res["quick"] is True
    assert len(res["scenes"]) == 3 and res["rows"]
    assert "| drape on sphere |" in (tmp_path / "stopping_rule.md").read_text()


def test_mg_levers_and_preconditioner_peer_run_small(tmp_path):
    """The two studies without a quick mode still run, at a small size: the numpy V-cycle solves a captured
    system to its tolerance; the peer scenes run with both preconditioners."""
    subprocess.run([sys.executable, str(STUDIES / "mg_levers.py"), "--sizes", "16", "--steps", "2", "--variants",
                    "jacobi", "--out", str(tmp_path)], check=True, capture_output=True, text=True)
    (row,) = json.loads((tmp_path / "mg_levers.json").read_text())["rows"]
    assert row["variant"] == "jacobi" and row["converged"] and row["true_error"] < 1e-2
    subprocess.run([sys.executable, str(STUDIES / "preconditioner_peer.py"), "--sizes", "8", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    rows = json.loads((tmp_path / "preconditioner_peer.json").read_text())["rows"]
    assert {(r["scene"], r["fixed_steps"], r["preconditioner"]) for r in rows} == {
        (s, f, pc) for s, f in (("hanging", True), ("hanging", False), ("drape", False))
        for pc in ("multigrid", "multigrid_smoothed")}
    assert all(r["iterations_per_frame"] >= 1 and r["ms_per_frame"] > 0 for r in rows)


def test_vs_blender_crumple_worker_and_its_judge(tmp_path):
    """The crumple's worker (ours, 8², 0.2 s) writes every frame's positions, and the judge that reads both
    programs' positions finds no crossing and no penetration in them; the judge's penetration on points placed
    inside the sphere, the floor and the rod, and its crossing count on a grid folded through itself."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import numpy as np
    from vs_blender import grid_faces, judge, penetration

    save = tmp_path / "x.npy"
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "vs_blender.py"), "--worker", "--scenes",
                          "crumple", "--sizes", "8", "--duration", "0.2", "--save", str(save)],
                         check=True, capture_output=True, text=True).stdout
    res = json.loads(next(line for line in out.splitlines() if line.startswith("RESULT "))[7:])
    assert res["scene"] == "crumple" and res["method"] == "rounds" and res["finite"]
    X = np.load(save)
    assert X.shape == (13, 64, 3)
    q = judge("crumple", X)
    assert q["crossings_max"] == 0 and q["penetration_max"] == 0.0 and q["rms_speed_end"] > 0
    assert penetration("hanging", X[0]) is None
    assert penetration("drape", np.array([[0.0, 0.0, 0.29], [0.0, 0.0, 0.5]])) == pytest.approx(0.01)
    assert penetration("crumple", np.array([[0.3, 0.0, -0.002], [0.1, 0.4, 0.02], [0.1, 1.5, 0.02]])) == \
        pytest.approx(0.01)
    # a 4 x 4 flat grid whose top row is pushed down through the row below: its edges pierce triangles
    x = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0)), -1).reshape(-1, 2)
    x = np.concatenate([x, np.zeros((16, 1))], 1)
    folded = x.copy()
    folded[12:, 1], folded[12:, 2] = 1.5, np.where(np.arange(4) % 2, 1.0, -1.0)
    assert judge("hanging", np.stack([x, x]))["crossings_max"] == 0
    assert len(grid_faces(4)) == 18 and judge("hanging", np.stack([x, folded]))["crossings_end"] > 0
