"""Command-line interface: outputs, exit codes and error messages."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from implicit_cloth.cli import main

ROOT = Path(__file__).resolve().parents[1]

SMALL = """\
[simulation]
integrator = "backward_euler"
dt = 0.01
duration = 0.1
frame_rate = 50

[cloth]
size = [1.0, 1.0]
resolution = [5, 5]
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


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def run(*args: str) -> int:
    return main(["run", *args, "--no-progress"])


def test_ok_run_writes_trajectory_and_report(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    out = tmp_path / "result"
    assert run(str(scene), "--out", str(out)) == 0

    with np.load(out / "trajectory.npz") as z:
        pos, times, faces = z["positions"], z["times"], z["faces"]
    assert pos.shape == (len(times), 25, 3)
    assert np.all(np.isfinite(pos))
    np.testing.assert_allclose(times, np.arange(6) * 0.02, atol=1e-12)   # 0, 1/50, ..., 0.1
    assert faces.shape == (2 * 4 * 4, 3)

    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "ok"
    assert report["integrator"] == "backward_euler"
    assert report["steps"] == 10
    assert report["scene"]["cloth"]["resolution"] == [5, 5]
    assert report["scene"]["simulation"]["dt"] == 0.01
    assert len(report["frames"]["time"]) == len(times)

    stdout = capsys.readouterr().out
    for word in ("backward_euler", "vertices", "ms/step", "max strain", "unconverged steps", "status       ok",
                 "trajectory.npz", "report.json"):
        assert word in stdout


def test_default_output_directory_is_out_slash_stem(tmp_path, monkeypatch):
    scene = write(tmp_path, SMALL, "tiny_drape.toml")
    monkeypatch.chdir(tmp_path)
    assert run(str(scene)) == 0
    assert (tmp_path / "out" / "tiny_drape" / "trajectory.npz").is_file()
    assert (tmp_path / "out" / "tiny_drape" / "report.json").is_file()


def test_overrides_are_applied_and_recorded(tmp_path):
    scene = write(tmp_path, SMALL)
    out = tmp_path / "o"
    code = run(str(scene), "--out", str(out), "--integrator", "rk4", "--dt", "0.005",
               "--duration", "0.05", "--frame-rate", "100")
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert report["integrator"] == "rk4" and report["solver"] is None
    assert report["dt"] == 0.005 and report["steps"] == 10
    assert report["scene"]["simulation"]["integrator"] == "rk4"
    assert len(report["frames"]["time"]) == 6


@pytest.mark.parametrize("edit, key", [
    (("stiffness = 50.0", "stiffness = -5"), "cloth.springs.shear.stiffness"),
    (("mass = 0.1", "mass = 0.1\nstifness = 3"), "cloth.stifness"),
])
def test_bad_scene_exits_2_with_one_line(tmp_path, capsys, edit, key):
    scene = write(tmp_path, SMALL.replace(*edit))
    out = tmp_path / "o"
    assert run(str(scene), "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"implicit-cloth: error: {key}: ")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_debug_shows_traceback(tmp_path, capsys):
    scene = write(tmp_path, SMALL.replace("stiffness = 50.0", "stiffness = -5"))
    assert run(str(scene), "--out", str(tmp_path / "o"), "--debug") == 2
    err = capsys.readouterr().err
    assert "Traceback" in err
    assert err.rstrip().splitlines()[-1].startswith("implicit-cloth: error: cloth.springs.shear.stiffness")


@pytest.mark.parametrize("text", [None, "", "[cloth\nmass = 1"])
def test_unreadable_scene_exits_2(tmp_path, capsys, text):
    path = tmp_path / "missing.toml" if text is None else write(tmp_path, text)
    assert run(str(path), "--out", str(tmp_path / "o")) == 2
    err = capsys.readouterr().err
    assert err.startswith("implicit-cloth: error: ") and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("args, key", [
    (("--integrator", "nonsense"), "simulation.integrator"),
    (("--dt", "-1"), "simulation.dt"),
    (("--dt", "nan"), "simulation.dt"),
    (("--duration", "0"), "simulation.duration"),
    (("--frame-rate", "inf"), "simulation.frame_rate"),
])
def test_bad_override_exits_2(tmp_path, capsys, args, key):
    scene = write(tmp_path, SMALL)
    assert run(str(scene), "--out", str(tmp_path / "o"), *args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"implicit-cloth: error: {key}: ")
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("given, meant", [
    ("implicit_euler", "backward_euler"), ("Implicit-Euler", "backward_euler"), ("bdf1", "backward_euler"),
    ("explicit_euler", "forward_euler"), ("euler", "forward_euler"), ("semi_implicit_euler", "symplectic_euler"),
    ("velocity_verlet", "verlet"), ("runge_kutta", "rk4"), ("bfd2", "bdf2"), ("Backward_Euler", "backward_euler"),
])
def test_integrator_suggestion_names_the_method_meant(tmp_path, capsys, given, meant):
    """Another name of a method (implicit Euler is backward Euler) or a misspelling suggests that method, not the
    closest spelling (``implicit_euler`` used to suggest ``symplectic_euler``)."""
    assert run(str(write(tmp_path, SMALL)), "--out", str(tmp_path / "o"), "--integrator", given) == 2
    err = capsys.readouterr().err
    assert f"(did you mean '{meant}'?), got '{given}'" in err, err
    assert err.startswith("implicit-cloth: error: simulation.integrator: must be one of ")


def test_integrator_without_a_near_name_gets_no_suggestion(tmp_path, capsys):
    assert run(str(write(tmp_path, SMALL)), "--out", str(tmp_path / "o"), "--integrator", "nonsense") == 2
    assert "did you mean" not in capsys.readouterr().err


def test_help_lists_every_exit_code(capsys):
    """The top-level --help and run's name every exit code the command line returns (the EXIT_ constants)."""
    from implicit_cloth import cli

    codes = {v for k, v in vars(cli).items() if k.startswith("EXIT_")}
    assert codes == {0, 1, 2, 3, 4, 130}
    for argv in (["--help"], ["run", "--help"]):
        assert main(argv) == 0
        text = " ".join(capsys.readouterr().out.split())
        listed = text[text.index("Exit codes:"):]
        named = {int(c) for c in re.findall(r"(?:: |, )(\d+) ", listed)}
        assert named == codes, (argv, listed)


def test_usage_errors_exit_2(tmp_path, capsys):
    assert main([]) == 2
    assert main(["run"]) == 2
    assert main(["run", str(write(tmp_path, SMALL)), "--dt", "abc"]) == 2
    assert main(["--version"]) == 0


def test_out_that_is_a_file_exits_2(tmp_path, capsys):
    scene = write(tmp_path, SMALL)
    blocker = write(tmp_path, "x", "not_a_dir")
    assert run(str(scene), "--out", str(blocker)) == 2
    assert "--out" in capsys.readouterr().err


def test_divergent_run_exits_3_and_writes_partial_results(tmp_path, capsys):
    stiff = (SMALL.replace("stiffness = 500.0", "stiffness = 1e5")
             .replace('integrator = "backward_euler"', 'integrator = "forward_euler"')
             .replace("dt = 0.01", "dt = 0.02").replace("duration = 0.1", "duration = 1.0"))
    scene = write(tmp_path, stiff)
    out = tmp_path / "o"
    assert run(str(scene), "--out", str(out)) == 3

    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "diverged"
    assert report["reason"]
    assert report["steps"] < 50
    with np.load(out / "trajectory.npz") as z:
        pos, times = z["positions"], z["times"]
    assert 1 <= len(times) < 51 and pos.shape[0] == len(times)
    assert np.all(np.isfinite(pos))
    err = capsys.readouterr().err
    assert err.startswith("implicit-cloth: diverged: ") and err.count("\n") == 1


def test_readme_scene_is_valid_and_runs(tmp_path):
    """The annotated scene in docs/scene.md uses every key; it must load and run."""
    text = (ROOT / "docs" / "scene.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert blocks, "docs/scene.md has no toml block"
    scene = write(tmp_path, blocks[0], "readme.toml")
    out = tmp_path / "readme"
    assert run(str(scene), "--out", str(out), "--duration", "0.03", "--frame-rate", "100") == 0
    report = json.loads((out / "report.json").read_text())
    assert report["effects"] == ["gravity", "drag", "wind", "structural", "shear", "bend"]
    assert report["n_pinned"] == 3


def _console_script() -> str | None:
    exe = Path(sys.executable).with_name("implicit-cloth" + (".exe" if os.name == "nt" else ""))
    return str(exe) if exe.is_file() else shutil.which("implicit-cloth")


@pytest.mark.parametrize("how", ["module", "console_script"])
def test_subprocess_run_exits_0(tmp_path, how):
    if how == "module":
        cmd = [sys.executable, "-m", "implicit_cloth"]
    else:
        script = _console_script()
        if script is None:
            pytest.skip("implicit-cloth console script not installed (pip install -e .)")
        cmd = [script]
    scene = write(tmp_path, SMALL)
    out = tmp_path / "sub"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([*cmd, "run", str(scene), "--out", str(out)],
                          capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "status       ok" in proc.stdout
    assert proc.stderr == ""          # stderr is not a terminal: no progress bar
    assert json.loads((out / "report.json").read_text())["status"] == "ok"


def test_outputs_get_a_normal_file_mode(tmp_path):
    import os
    import stat

    from implicit_cloth.files import save_json

    path = save_json(tmp_path / "r.json", {"a": 1})
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask


def test_solver_line_says_newton_corrections_are_solved_looser(tmp_path, capsys):
    """The largest residual comes from Newton corrections solved to NEWTON_FORCING where a step took any: the
    summary says so instead of putting it bare next to the step tolerance."""
    from implicit_cloth.integrators.base import NEWTON_FORCING

    lines = {}
    for newton in (1, 4):
        scene = write(tmp_path, SMALL + f'\n[solver]\nnewton_iterations = {newton}\n', f"n{newton}.toml")
        assert run(str(scene), "--out", str(tmp_path / f"o{newton}"), "--no-progress") == 0
        report = json.loads((tmp_path / f"o{newton}" / "report.json").read_text())
        out = capsys.readouterr().out
        lines[newton] = next(line for line in out.splitlines() if line.startswith("solver "))
        assert (report["solver"]["max_newton_iterations"] > 1) == (newton > 1)
    assert f"Newton corrections included: those are solved to {NEWTON_FORCING:g}" in lines[4]
    assert "Newton" not in lines[1]


def test_threads_option_is_recorded_checked_and_restored(tmp_path, capsys):
    """``--threads N`` runs the compiled solver on N threads for that run (the report says so), is checked
    like every option, and leaves the process's setting as it was."""
    from implicit_cloth import backend

    scene = write(tmp_path, SMALL)
    before = backend.threads()
    assert run(str(scene), "--out", str(tmp_path / "o"), "--threads", "0") == 2
    assert capsys.readouterr().err.splitlines() == ["implicit-cloth: error: --threads: must be an integer >= 1, got 0"]
    assert run(str(scene), "--out", str(tmp_path / "o"), "--threads", "2", "--duration", "0.05") == 0
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    if report["solver"]["accelerator"] == "numba":
        assert report["solver"]["threads"] == 2
    assert backend.threads() == before
