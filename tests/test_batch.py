"""Batch sweeps: validation, resumability, kill safety, local vs Dask cluster determinism."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from implicit_cloth import SceneError
from implicit_cloth.batch import HEALTH_COLUMNS, MARKER, finished_row, load_sweep, run_sweep, summary_columns
from implicit_cloth.cli import main

ROOT = Path(__file__).resolve().parents[1]

BASE = """\
[simulation]
integrator = "backward_euler"
dt = 0.01
duration = {duration}
frame_rate = 50

[cloth]
size = [1.0, 1.0]
resolution = [{n}, {n}]
center = [0.0, 0.0, 1.0]
plane = "xz"
mass = 0.1
pins = ["top_left", "top_right"]

[cloth.springs.structural]
stiffness = 500.0
damping = 0.1

[cloth.springs.shear]
stiffness = 50.0

[effects]
gravity = [0.0, 0.0, -9.81]
"""

EIGHT = """\
base = "base.toml"
[sweep]
"simulation.dt" = [0.01, 0.02]
"simulation.integrator" = ["backward_euler", "bdf2"]
"cloth.springs.structural.stiffness" = [300.0, 600.0]
"""


def make(tmp_path: Path, sweep: str, n: int = 5, duration: float = 0.1) -> Path:
    (tmp_path / "base.toml").write_text(BASE.format(n=n, duration=duration))
    p = tmp_path / "sweep.toml"
    p.write_text(sweep)
    return p


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="") as f:
        r = csv.DictReader(f)
        return list(r.fieldnames or []), list(r)


def check_all_loadable(out: Path) -> None:
    """Every case file in ``out`` loads, and no temporary file is left."""
    for case_dir in (p for p in out.iterdir() if p.is_dir() and p.name != "compare"):
        names = {p.name for p in case_dir.iterdir()}
        assert not [n for n in names if n.startswith(".")], (case_dir, names)
        if "report.json" in names:
            json.loads((case_dir / "report.json").read_text())
        if "trajectory.npz" in names:
            with np.load(case_dir / "trajectory.npz") as z:
                assert np.all(np.isfinite(z["positions"]))
        if MARKER in names:
            json.loads((case_dir / MARKER).read_text())


# --------------------------------------------------------------------------- sweep files
def test_product_and_explicit_cases_with_stable_ids(tmp_path):
    p = make(tmp_path, EIGHT + '[[cases]]\n"simulation.dt" = 0.005\n"simulation.integrator" = "verlet"\n')
    sweep = load_sweep(p)
    assert sweep.keys == ["simulation.dt", "simulation.integrator", "cloth.springs.structural.stiffness"]
    assert len(sweep.cases) == 9
    assert sweep.cases[0].params == {"simulation.dt": 0.01, "simulation.integrator": "backward_euler",
                                     "cloth.springs.structural.stiffness": 300.0}
    # the explicit case leaves the stiffness out: its column shows the base scene's value
    assert sweep.cases[8].params["cloth.springs.structural.stiffness"] == 500.0
    assert len({c.case_id for c in sweep.cases}) == 9
    assert [c.case_id for c in load_sweep(p).cases] == [c.case_id for c in sweep.cases]   # stable
    # the id is of the normalised scene: 600 written as 6e2 or 600 is the same case
    p2 = make(tmp_path, EIGHT.replace("600.0", "6e2"))
    assert [c.case_id for c in load_sweep(p2).cases] == [c.case_id for c in sweep.cases[:8]]
    # ... and it changes with the base scene
    (tmp_path / "base.toml").write_text(BASE.format(n=6, duration=0.1))
    assert not {c.case_id for c in load_sweep(p).cases} & {c.case_id for c in sweep.cases}


def test_unquoted_dotted_keys_mean_the_same(tmp_path):
    quoted = load_sweep(make(tmp_path, EIGHT))
    bare = load_sweep(make(tmp_path, 'base = "base.toml"\n[sweep]\nsimulation.dt = [0.01, 0.02]\n'
                                     'simulation.integrator = ["backward_euler", "bdf2"]\n'
                                     '[sweep.cloth.springs.structural]\nstiffness = [300.0, 600.0]\n'))
    assert bare.keys == quoted.keys
    assert [c.case_id for c in bare.cases] == [c.case_id for c in quoted.cases]
    with pytest.raises(SceneError, match=r"^sweep.simulation.dt: given twice"):
        load_sweep(make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01]\n'
                                  'simulation.dt = [0.02]\n'))


@pytest.mark.parametrize("text, message", [
    ('base = "base.toml"\n[sweep]\n"simulation.dtt" = [0.01]\n',
     "sweep.simulation.dtt: unknown key (did you mean 'dt'?)"),
    ('base = "base.toml"\n[sweep]\n"simulaton.dt" = [0.01]\n',
     "sweep.simulaton.dt: unknown key 'simulaton' (did you mean 'simulation'?)"),
    ('base = "base.toml"\n[sweep]\n"simulation.dt" = []\n',
     "sweep.simulation.dt: must be a non-empty list of values, got []"),
    ('base = "base.toml"\n[sweep]\n"simulation.dt" = 0.01\n',
     "sweep.simulation.dt: must be a non-empty list of values, got 0.01"),
    ('base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01, -1.0]\n',
     "sweep.simulation.dt[1]: must be a finite number > 0, got -1.0"),
    ('base = "base.toml"\n[sweep]\n"cloth.size" = [[1.0, 0.0]]\n',
     "sweep.cloth.size[0][1]: must be a finite number > 0, got 0.0"),
    ('base = "base.toml"\n[sweep]\n"simulation.integrator" = ["bdf3"]\n',
     "sweep.simulation.integrator[0]: must be one of"),
    ('base = "nope.toml"\n[sweep]\n"simulation.dt" = [0.01]\n',
     "base: scene file not found"),
    ('base = 3\n[sweep]\n"simulation.dt" = [0.01]\n', "base: must be the path of a scene file, got 3"),
    ('[sweep]\n"simulation.dt" = [0.01]\n', "base: missing"),
    ('base = "base.toml"\n[swep]\n"simulation.dt" = [0.01]\n', "swep: unknown key (did you mean 'sweep'?)"),
    ('base = "base.toml"\n', "sweep: missing"),
    ('base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01, 0.010]\n', "the same scene as"),
    ('base = "base.toml"\n[sweep]\n"cloth.springs.structural.stiffness.x" = [1.0]\n',
     "sweep.cloth.springs.structural.stiffness.x: not a path into the scene"),
    ('base = "base.toml"\n[[cases]]\n"simulation.dt" = "fast"\n',
     "cases[0].simulation.dt: must be a finite number > 0, got 'fast'"),
    ('base = "base.toml"\n[set]\n"cloth.mass" = -1\n[sweep]\n"simulation.dt" = [0.01]\n',
     "set.cloth.mass: must be a finite number > 0, got -1"),
])
def test_bad_sweep_files_give_one_line_errors(tmp_path, capsys, text, message):
    p = make(tmp_path, text)
    with pytest.raises(SceneError) as err:
        load_sweep(p)
    assert message in str(err.value)
    assert main(["batch", str(p), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("implicit-cloth: error: ") and message in lines[0]
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_invalid_base_scene_is_named(tmp_path):
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01]\n')
    (tmp_path / "base.toml").write_text("[cloth]\nmass = -1\n")
    with pytest.raises(SceneError, match=r"^base: the base scene is invalid \(cloth.mass: must be"):
        load_sweep(p)


# --------------------------------------------------------------------------- running
def test_diverged_and_failed_cases_are_recorded_and_the_sweep_goes_on(tmp_path):
    # symplectic Euler at dt = 0.02 with k = 5e4 N/m on 0.1 kg / 25 vertices is far beyond 2/omega;
    # a total mass of 1e-320 kg passes scene validation but not the model (each of 25 vertices would get
    # 4e-322 kg, whose inverse overflows): that case raises
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.integrator" = ["backward_euler", '
                       '"symplectic_euler"]\n"simulation.dt" = [0.02]\n'
                       '"cloth.springs.structural.stiffness" = [5e4]\n'
                       '[[cases]]\n"cloth.mass" = 1e-320\n')
    sweep = load_sweep(p)
    out = tmp_path / "out"
    res = run_sweep(sweep, out, workers=1)
    assert res.counts == {"ok": 1, "warning": 0, "diverged": 1, "failed": 1, "pending": 0}
    ok, div, failed = (res.rows[c.case_id] for c in sweep.cases)
    assert ok["status"] == "ok" and ok["reason"] == ""
    assert div["status"] == "diverged" and ("energy grew" in div["reason"] or "non-finite" in div["reason"])
    assert failed["status"] == "failed"
    assert failed["reason"].startswith("SceneError: cloth.mass: vertex 0 would get a mass")
    # the diverged case keeps its partial trajectory and its report
    d = out / sweep.cases[1].case_id
    report = json.loads((d / "report.json").read_text())
    assert report["status"] == "diverged" and report["scene"]["simulation"]["integrator"] == "symplectic_euler"
    with np.load(d / "trajectory.npz") as z:
        assert 1 <= len(z["times"]) < 6 and np.all(np.isfinite(z["positions"]))
    assert not (out / sweep.cases[2].case_id / "trajectory.npz").exists()
    cols, rows = read_csv(out / "summary.csv")
    assert [r["status"] for r in rows] == ["ok", "diverged", "failed"]
    assert rows[1]["energy_drift"] != "" and rows[2]["energy_drift"] == ""
    assert rows[0]["max_penetration"] == "0.0"          # no obstacles
    check_all_loadable(out)
    # a second run skips all three; --retry-failed runs only the failed one again
    again = run_sweep(sweep, out, workers=1)
    assert again.skipped == 3 and again.counts == res.counts
    before = (out / sweep.cases[0].case_id / MARKER).stat().st_mtime_ns
    retried = run_sweep(sweep, out, workers=1, retry_failed=True)
    assert retried.skipped == 2 and retried.counts["failed"] == 1
    assert (out / sweep.cases[0].case_id / MARKER).stat().st_mtime_ns == before


def test_summary_columns_and_values(tmp_path, capsys):
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.integrator" = ["backward_euler", "verlet"]\n'
                       '"simulation.dt" = [0.001]\n')
    sweep = load_sweep(p)
    out = tmp_path / "out"
    run_sweep(sweep, out, workers=1, progress=True)
    bar = capsys.readouterr().err.split("\r")[-1]          # the progress bar's last state
    assert "2/2" in bar and "ok=2, warning=0, diverged=0, failed=0" in bar
    cols, rows = read_csv(out / "summary.csv")
    assert cols == ["case_id", "simulation.integrator", "simulation.dt", "status", "reason", "wall_s",
                    "steps", "energy_drift", "energy_drift_rel", "max_strain", "mean_iterations",
                    "max_iterations", "unconverged_steps", "max_penetration", "health"]
    assert cols == summary_columns(sweep) and tuple(cols[-len(HEALTH_COLUMNS):]) == HEALTH_COLUMNS
    js = json.loads((out / "summary.json").read_text())
    assert js["counts"] == {"ok": 2, "warning": 0, "diverged": 0, "failed": 0, "pending": 0}
    for row, case in zip(js["cases"], sweep.cases):
        report = json.loads((out / case.case_id / "report.json").read_text())
        fr = report["frames"]
        assert row["steps"] == report["steps"] == 100
        assert row["energy_drift"] == pytest.approx(fr["total"][-1] - fr["total"][0] - fr["pin_work"][-1])
        assert row["energy_drift_rel"] == pytest.approx(
            row["energy_drift"] / report["divergence_bound"]["energy_scale"])
        assert row["max_strain"] == max(fr["max_strain"])
    assert js["cases"][0]["mean_iterations"] == json.loads(
        (out / sweep.cases[0].case_id / "report.json").read_text())["solver"]["mean_iterations"]
    assert rows[1]["mean_iterations"] == "" and rows[1]["simulation.integrator"] == "verlet"


def test_marker_is_trusted_only_with_matching_files(tmp_path):
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01, 0.02]\n')
    sweep = load_sweep(p)
    out = tmp_path / "out"
    run_sweep(sweep, out, workers=1)
    a, b = sweep.cases
    assert finished_row(out, a) is not None
    # a report replaced by another (as if the marker were stale) or a truncated trajectory: not finished
    (out / a.case_id / "report.json").write_text("{}")
    npz = out / b.case_id / "trajectory.npz"
    npz.write_bytes(npz.read_bytes()[:100])
    assert finished_row(out, a) is None and finished_row(out, b) is None
    res = run_sweep(sweep, out, workers=1)
    assert res.skipped == 0 and res.counts["ok"] == 2
    check_all_loadable(out)


def test_salvage_keeps_a_finished_case_and_removes_temporaries(tmp_path):
    """What the pool does with in-flight cases after their workers are gone (interrupted or killed)."""
    from implicit_cloth.batch import run_case, salvage, store_result

    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01, 0.02]\n')
    done_case, cut_case = load_sweep(p).cases
    out = tmp_path / "out"
    store_result(out, done_case, run_case(done_case))       # written completely, result never delivered
    (out / done_case.case_id / ".trajectory.npz.x1.new").write_bytes(b"partial")
    (out / cut_case.case_id).mkdir()                          # killed while writing
    (out / cut_case.case_id / ".report.json.x2.tmp").write_text("{")
    recorded: list[dict] = []
    assert salvage([done_case, cut_case], out, recorded.append) == [done_case]
    assert [r["case_id"] for r in recorded] == [done_case.case_id] and recorded[0]["status"] == "ok"
    assert sorted(p.name for p in (out / done_case.case_id).iterdir()) == [MARKER, "report.json", "trajectory.npz"]
    assert list((out / cut_case.case_id).iterdir()) == []


def _count_markers(out: Path) -> int:
    return sum(1 for _ in out.glob(f"*/{MARKER}")) if out.is_dir() else 0


def _batch_process(sweep: Path, out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "implicit_cloth", "batch", str(sweep), "--out", str(out),
                             "--workers", "2", "--no-progress"], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_markers(proc: subprocess.Popen, out: Path, at_least: int, timeout: float = 120.0) -> int:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        n = _count_markers(out)
        if n >= at_least or proc.poll() is not None:
            return n
        time.sleep(0.02)
    raise AssertionError("the batch made no progress")


def _children(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of the direct children of ``pid`` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                out.append((int(d.name), (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()))
        except (OSError, ValueError, IndexError):
            continue
    return out


# 8 cases of about 0.5-0.8 s of CPU each (10 x 10 cloth, 200-300 steps): long enough to be killed part way
SLOW_EIGHT = """\
base = "base.toml"
[sweep]
"simulation.dt" = [0.002, 0.003]
"cloth.springs.structural.stiffness" = [300.0, 400.0, 500.0, 600.0]
"""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses process groups and /proc")
def test_interrupted_sweep_resumes_to_completion(tmp_path):
    """Ctrl-C, then SIGKILL of the whole run, then a run whose worker is killed: it completes the sweep."""
    p = make(tmp_path, SLOW_EIGHT, n=10, duration=0.6)
    sweep = load_sweep(p)
    out = tmp_path / "out"
    total = 8

    # 1. Ctrl-C (SIGINT to the process group, as a terminal sends it): exit 130, finished cases kept
    proc = _batch_process(p, out)
    _wait_markers(proc, out, 1)
    assert proc.poll() is None, "the sweep ended too soon"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err, err
    check_all_loadable(out)                        # the workers' unfinished files were removed
    done = _count_markers(out)
    _, rows = read_csv(out / "summary.csv")
    assert 1 <= done < total and len(rows) == total
    assert sum(r["status"] == "ok" for r in rows) == done
    assert sum(r["status"] == "pending" for r in rows) == total - done

    # 2. SIGKILL of the whole run (parent and workers) part way
    proc = _batch_process(p, out)
    _wait_markers(proc, out, done + 1)
    assert proc.poll() is None, "the sweep ended too soon"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    kept = {d.name: (d / MARKER).stat().st_mtime_ns for d in out.iterdir() if (d / MARKER).exists()}
    assert done < len(kept) < total                # (temporary files may remain: hidden, removed next run)

    # 3. the same command again, and one of its workers killed: the pool restarts and the sweep completes
    proc = _batch_process(p, out)
    _wait_markers(proc, out, len(kept) + 1)
    workers = [pid for pid, cmd in _children(proc.pid) if "spawn_main" in cmd]
    assert workers and proc.poll() is None and _count_markers(out) < total, "the sweep ended too soon"
    os.kill(workers[0], signal.SIGKILL)
    stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "worker process died" in err
    assert f"8: 8 ok, 0 warning, 0 diverged, 0 failed, 0 pending ({len(kept)} already finished" in stdout
    # nothing finished was lost or redone; every case exactly once; every file loads; no temporary file left
    assert {name: (out / name / MARKER).stat().st_mtime_ns for name in kept} == kept
    _, rows = read_csv(out / "summary.csv")
    assert [r["case_id"] for r in rows] == [c.case_id for c in sweep.cases]
    assert all(r["status"] == "ok" for r in rows)
    check_all_loadable(out)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
def test_worker_deaths_beyond_the_limit_stop_cleanly(tmp_path):
    """With max_restarts=0 a killed worker stops the run: nothing false recorded, the rest pending, resumable."""
    import threading

    p = make(tmp_path, SLOW_EIGHT, n=10, duration=0.6)
    sweep = load_sweep(p)
    out = tmp_path / "out"
    before = {pid for pid, _ in _children(os.getpid())}
    result: dict[str, object] = {}
    thread = threading.Thread(target=lambda: result.update(r=run_sweep(sweep, out, workers=2, max_restarts=0)))
    thread.start()
    t0 = time.monotonic()
    while _count_markers(out) < 1 and thread.is_alive() and time.monotonic() - t0 < 120:
        time.sleep(0.02)
    workers = [pid for pid, cmd in _children(os.getpid()) if "spawn_main" in cmd and pid not in before]
    assert workers and thread.is_alive(), "the sweep ended too soon"
    os.kill(workers[0], signal.SIGKILL)
    thread.join(timeout=120)
    res = result["r"]
    assert res.counts["pending"] > 0 and res.counts["ok"] + res.counts["pending"] == 8
    assert res.counts["failed"] == res.counts["diverged"] == 0            # nothing false recorded
    assert any("stopping with" in n for n in res.notes)
    _, rows = read_csv(out / "summary.csv")
    assert sum(r["status"] == "pending" for r in rows) == res.counts["pending"]
    check_all_loadable(out)
    again = run_sweep(sweep, out, workers=2)
    assert again.skipped == res.counts["ok"] and again.counts["ok"] == 8
    check_all_loadable(out)


@pytest.mark.slow
def test_local_and_dask_cluster_give_identical_results(tmp_path):
    distributed = pytest.importorskip("distributed")
    p = make(tmp_path, EIGHT)
    sweep = load_sweep(p)
    local = run_sweep(sweep, tmp_path / "local", workers=2)
    with distributed.LocalCluster(processes=True, n_workers=2, threads_per_worker=1, dashboard_address=None,
                                  silence_logs=40) as cluster:
        # through the command line, as a user would: batch connects its own client to the scheduler
        assert main(["batch", str(p), "--out", str(tmp_path / "cluster"), "--scheduler",
                     cluster.scheduler_address, "--no-progress"]) == 0
        # and again: every case is found finished, nothing is sent
        with distributed.Client(cluster) as client:
            again = run_sweep(sweep, tmp_path / "cluster", client=client)
    assert again.skipped == 8
    remote = again
    assert local.counts == remote.counts == {"ok": 8, "warning": 0, "diverged": 0, "failed": 0, "pending": 0}
    for case in sweep.cases:
        a, b = dict(local.rows[case.case_id]), dict(remote.rows[case.case_id])
        a.pop("wall_s"), b.pop("wall_s")
        assert a == b
        with np.load(tmp_path / "local" / case.case_id / "trajectory.npz") as za, \
                np.load(tmp_path / "cluster" / case.case_id / "trajectory.npz") as zb:
            assert np.array_equal(za["positions"], zb["positions"])   # bit for bit
    ja = json.loads((tmp_path / "local" / "summary.json").read_text())
    jb = json.loads((tmp_path / "cluster" / "summary.json").read_text())
    for ra, rb in zip(ja["cases"], jb["cases"]):
        ra.pop("wall_s"), rb.pop("wall_s")
    assert ja["cases"] == jb["cases"]
    check_all_loadable(tmp_path / "cluster")


def test_unreachable_scheduler_is_a_one_line_error(tmp_path, capsys):
    pytest.importorskip("distributed")
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01]\n')
    assert main(["batch", str(p), "--out", str(tmp_path / "o"), "--scheduler", "nonsense://x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("implicit-cloth: error: --scheduler: cannot connect")
    assert err[0].endswith("got 'nonsense://x'")
    _, rows = read_csv(tmp_path / "o" / "summary.csv")
    assert [r["status"] for r in rows] == ["pending"]


def test_cli_batch_output_and_locked_directory(tmp_path, capsys):
    p = make(tmp_path, 'base = "base.toml"\n[sweep]\n"simulation.dt" = [0.01, 0.02]\n')
    out = tmp_path / "out"
    assert main(["batch", str(p), "--out", str(out), "--workers", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "2: 2 ok, 0 warning, 0 diverged, 0 failed, 0 pending (0 already finished" in text
    assert main(["batch", str(p), "--out", str(out), "--workers", "0"]) == 2
    assert "--workers: must be an integer >= 1, got 0" in capsys.readouterr().err
    import fcntl

    with open(out / ".batch.lock", "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        assert main(["batch", str(p), "--out", str(out), "--no-progress"]) == 2
    assert "another batch run is using this output directory" in capsys.readouterr().err


def test_worker_set_up_pins_every_blas_to_one_thread():
    """NumPy's and SciPy's own OpenBLAS both (SciPy's is loaded late, by scipy.linalg)."""
    code = ("from implicit_cloth.batch.runner import worker_init; worker_init(); "
            "import implicit_cloth as ic; from threadpoolctl import threadpool_info; "
            "ic.Simulator({'cloth': {'resolution': [4, 4], 'mass': 0.1, 'springs': {'structural': "
            "{'stiffness': 10.0}}}}, duration=0.02).run(); "
            "print(sorted((i['filepath'].rsplit('/', 1)[-1], i['num_threads']) for i in threadpool_info() "
            "if i['user_api'] == 'blas'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT))).stdout
    libs = eval(out)
    assert libs and all(n == 1 for _, n in libs), libs
