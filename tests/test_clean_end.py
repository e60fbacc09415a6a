"""Runs that end cleanly: Ctrl-C gives exit 130 and "interrupted" on both back-ends, the two outputs are one pair
(a kill between the renames is detected, killed writers' temporaries are removed), out of memory is one line."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.cli import main
from implicit_cloth.errors import InputError
from implicit_cloth.files import _sha256, check_pair, remove_stale, write_run

SCENE = """
[simulation]
integrator = "backward_euler"
dt = 0.01
duration = {duration}
frame_rate = 10

[cloth]
size = [1.0, 1.0]
resolution = [{n}, {n}]
center = [0.0, 0.0, 1.0]
plane = "xz"
mass = 0.1
pins = ["top_left", "top_right"]

[cloth.springs.structural]
stiffness = 2000.0
damping = 0.5
[cloth.springs.shear]
stiffness = 200.0
damping = 0.1

[effects]
gravity = [0.0, 0.0, -9.81]
"""

CLI = [sys.executable, "-m", "implicit_cloth"]


def _env(accelerator):
    env = dict(os.environ)
    if accelerator == "numpy":
        env["IMPLICIT_CLOTH_ACCELERATOR"] = "numpy"
    else:
        env.pop("IMPLICIT_CLOTH_ACCELERATOR", None)
    return env


# --------------------------------------------------------------------------- Ctrl-C
@pytest.mark.slow
@pytest.mark.parametrize("accelerator", ["numba", "numpy"])
def test_sigint_exits_130_with_one_line_on_both_backends(tmp_path, accelerator):
    """SIGINT at several moments (setting up, compiling, stepping): always 130 and
    "interrupted", never a traceback (the numba path used to end in SystemError 7 times in 10)."""
    if accelerator == "numba":
        pytest.importorskip("numba")
    scene = tmp_path / "long.toml"
    scene.write_text(SCENE.format(n=40, duration=600.0))
    out = tmp_path / "out"
    for delay in (3.0, 4.5, 6.0, 8.0):        # after the imports (see the README: Ctrl-C while importing)
        p = subprocess.Popen([*CLI, "run", str(scene), "--out", str(out)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=_env(accelerator),
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        time.sleep(delay)
        assert p.poll() is None, p.communicate()
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
        assert p.returncode == 130, (delay, err[-1500:])
        assert err.strip().splitlines()[-1] == "implicit-cloth: interrupted", (delay, err[-1500:])
        assert "Traceback" not in err
        assert not (out / "trajectory.npz").exists() and not list(out.glob(".*"))


_STEP_CHILD = """
import json, sys, traceback
import implicit_cloth as ic
sim = ic.Simulator(ic.load_scene(sys.argv[1]))
sim.step(1)                                        # compiled (or loaded from the cache) before the first SIGINT
while True:
    print("ready", flush=True)
    try:
        sim.step(100000)
        print(json.dumps({"traceback": "finished", "steps": 0.0}), flush=True)
    except BaseException:
        print(json.dumps({"traceback": traceback.format_exc(), "steps": sim.time / sim.dt}), flush=True)
"""


@pytest.mark.parametrize("accelerator", ["numba", "numpy"])
def test_sigint_in_api_step_is_keyboard_interrupt_on_both_backends(accelerator):
    """``sim.step(100000)`` interrupted 20 times at random moments (a SIGINT 0-0.3 s into the call): each time a
    KeyboardInterrupt, never ``SystemError: CPUDispatcher(...) returned a result with an exception set`` (the
    numba path gave it 12 times in 20 while ``step`` let Python's handler raise inside compiled calls), and the
    state that of a whole step."""
    if accelerator == "numba":
        pytest.importorskip("numba")
    root = Path(ic.__file__).resolve().parents[1]
    env = {**_env(accelerator), "PYTHONPATH": str(root)}
    env["IMPLICIT_CLOTH_ACCELERATOR"] = accelerator
    p = subprocess.Popen([sys.executable, "-c", _STEP_CHILD, str(root / "examples" / "hanging.toml")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    rng = np.random.default_rng()
    try:
        for k in range(20):
            line = p.stdout.readline()
            assert line.strip() == "ready", (line, p.poll() is not None and p.stderr.read()[-2000:])
            delay = float(rng.uniform(0.0, 0.3))
            time.sleep(delay)
            os.kill(p.pid, signal.SIGINT)
            got = json.loads(p.stdout.readline())
            tb = got["traceback"]
            assert tb.strip().splitlines()[-1] == "KeyboardInterrupt", (k, delay, tb[-2000:])
            assert "SystemError" not in tb, (k, delay, tb[-2000:])
            assert got["steps"] == pytest.approx(round(got["steps"]), abs=1e-6), (k, delay, got["steps"])
    finally:
        p.kill()
        p.communicate()


def test_deferred_interrupt_raises_between_steps(hanging_scene):
    """In process: a SIGINT during a step is raised as KeyboardInterrupt at the next step's start."""
    hanging_scene["simulation"]["duration"] = 1.0
    sim = ic.Simulator(hanging_scene)
    calls = {"n": 0}
    real = sim._advance

    def advance():
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGINT)      # arrives inside the step; the step still completes
        return real()
    sim._advance = advance
    with pytest.raises(KeyboardInterrupt):
        sim.run()
    assert calls["n"] == 3 and sim.state.t == pytest.approx(0.03)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler       # handler restored


# --------------------------------------------------------------------------- the pair
def _pair(tmp_path, hanging_scene, duration):
    hanging_scene["simulation"].update(duration=duration, frame_rate=50)
    sim = ic.Simulator(hanging_scene)
    return sim.run(), sim.scene.data


def test_outputs_name_each_other_and_a_kill_between_renames_is_detected(tmp_path, hanging_scene, capsys):
    out = tmp_path / "run"
    out.mkdir()
    traj, data = _pair(tmp_path, hanging_scene, 0.1)
    write_run(out, traj, data)
    report = json.loads((out / "report.json").read_text())
    assert report["outputs"] == {"trajectory": "trajectory.npz",
                                 "trajectory_sha256": _sha256(out / "trajectory.npz")}
    check_pair(out)
    first = (out / "report.json").read_bytes()
    # a second run into the same directory is killed (SIGKILL) right after renaming its trajectory
    code = textwrap.dedent(f"""
        import os, signal, sys
        import implicit_cloth as ic
        from implicit_cloth import files
        real = os.replace
        def replace(a, b):
            real(a, b)
            if str(b).endswith("trajectory.npz"):
                os.kill(os.getpid(), signal.SIGKILL)
        files.os.replace = replace
        scene = {json.dumps(hanging_scene)!r}
        import json
        d = json.loads(scene)
        d["simulation"]["duration"] = 0.2
        sim = ic.Simulator(d)
        files.write_run(__import__("pathlib").Path({str(out)!r}), sim.run(), sim.scene.data)
    """)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]
    assert (out / "report.json").read_bytes() == first                 # the old report ...
    with np.load(out / "trajectory.npz") as z:
        assert len(z["times"]) == 11                                    # ... beside the new trajectory
    stale = [q for q in out.iterdir() if q.name.startswith(".")]
    assert [q.name.split(".")[1] for q in stale] == ["report"]         # the killed writer's staged report
    with pytest.raises(InputError, match="report.json belongs to another run than trajectory.npz"):
        check_pair(out)
    assert main(["export", str(out), "--format", "obj"]) == 2
    assert "report.json belongs to another run" in capsys.readouterr().err
    write_run(out, traj, data)                                     # the next write: a pair, no leftovers
    check_pair(out)
    assert not [q for q in out.iterdir() if q.name.startswith(".")]


def test_a_failed_write_keeps_the_previous_pair_and_leaves_no_temporary(tmp_path, hanging_scene, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    traj, data = _pair(tmp_path, hanging_scene, 0.1)
    write_run(out, traj, data)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    from implicit_cloth import files

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(files.json, "dumps", full_disk)                # the report fails after the trajectory
    with pytest.raises(OSError):
        write_run(out, traj, data)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_remove_stale_keeps_a_live_writers_files(tmp_path):
    live = tmp_path / f".trajectory.npz.{os.getpid()}.ab12.new"
    dead = tmp_path / ".report.json.999999999.cd34.new"
    legacy = tmp_path / ".trajectory.npz.x1y2z3.new"
    other = tmp_path / ".hidden_user_file"
    for p in (live, dead, legacy, other):
        p.write_text("x")
    assert sorted(p.name for p in remove_stale(tmp_path)) == sorted([dead.name, legacy.name])
    assert live.exists() and other.exists()


# --------------------------------------------------------------------------- out of memory
@pytest.mark.slow
def test_out_of_memory_is_one_line(tmp_path):
    scene = tmp_path / "huge.toml"
    scene.write_text(SCENE.format(n=4096, duration=1.0))
    limit = 3 << 30
    p = subprocess.run([*CLI, "run", str(scene), "--out", str(tmp_path / "out")], capture_output=True, text=True,
                       env=_env("numpy"), timeout=300,
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)))
    assert p.returncode == 1, p.stderr[-2000:]
    assert p.stderr.strip().splitlines() == [
        "implicit-cloth: error: out of memory while running run (a smaller cloth.resolution, fewer kept frames "
        "or a shorter run needs less)"]
    assert not Path(tmp_path / "out" / "trajectory.npz").exists()
