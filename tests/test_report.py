"""The typed run report: it reads every report the simulator makes, key for key, and refuses a drifted one."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import implicit_cloth as ic
from implicit_cloth.files import load_run, write_run
from implicit_cloth.report import SCHEMA_VERSION, ReportError, RunReport

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(scene, duration=0.05, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return ic.Simulator(scene, **kw).run(duration=duration)
        except ic.DivergenceError as err:
            return err.trajectory


SMALL = {"cloth": {"resolution": [6, 6], "mass": 0.1, "pins": ["top_left", {"vertices": [5], "velocity": [0, 0, 0.1]}],
                   "springs": {"structural": {"stiffness": 500.0}}},
         "effects": {"gravity": [0, 0, -9.81], "drag": 0.1, "wind": {"velocity": [0, 1, 0]}}}


@pytest.mark.parametrize("case", [
    "examples/hanging.toml", "examples/drape_sphere.toml", "examples/keyframed_sphere.toml",
    "strain_limit", "explicit", "diverged"])
def test_every_kind_of_report_reads_back_key_for_key_with_nothing_unknown(case):
    if case == "strain_limit":
        traj = _run({**SMALL, "simulation": {"strain_limit": {"max_strain": 0.05}}})
    elif case == "explicit":
        traj = _run(SMALL, integrator="verlet", dt=1e-3)
    elif case == "diverged":
        traj = _run(EXAMPLES / "stiff_large_step.toml", duration=0.2, integrator="symplectic_euler")
        assert traj.report["status"] == "diverged"
    else:
        traj = _run(EXAMPLES.parent / case, duration=0.05)
    report = RunReport.from_dict(traj.report)
    assert report.to_dict() == traj.report
    assert report.extra == {}                      # the schema knows every key the simulator writes
    for section in ("solver", "adaptive", "strain_limit", "collision"):
        sub = getattr(report, section)
        assert (sub is None) == (traj.report.get(section) is None)
        if sub is not None:
            assert sub.extra == {} and sub.to_dict() == traj.report[section]


def test_a_missing_key_is_an_error_naming_it_and_unknown_keys_are_kept():
    d = _run(SMALL).report
    broken = json.loads(json.dumps(d))
    del broken["solver"]["tolerance"]
    with pytest.raises(ReportError, match=r"^report\.solver\.tolerance: missing$"):
        RunReport.from_dict(broken)
    with pytest.raises(ReportError, match=r"^report\.frames: must be a table, got 3$"):
        RunReport.from_dict({**d, "frames": 3})
    extended = {**d, "warnings": ["w"], "status": "warning", "case_id": "abc"}
    r = RunReport.from_dict(extended)
    assert r.warnings == ["w"] and r.status == "warning"
    assert r.extra == {"case_id": "abc"} and r.to_dict() == extended


def test_written_run_loads_back_and_its_scene_reproduces_the_run_bit_for_bit(tmp_path):
    scene = ic.load_scene(EXAMPLES / "keyframed_sphere.toml").replace(cloth={"resolution": [8, 8]})
    traj = _run(scene, duration=0.1)
    write_run(tmp_path, traj, scene.data)
    run = load_run(tmp_path)
    assert run.report.schema_version == SCHEMA_VERSION
    assert np.array_equal(run.positions, traj.positions) and np.array_equal(run.times, traj.times)
    again = ic.Scene.from_dict(run.report.scene)   # the normalised scene, as JSON wrote it
    assert again.data == scene.data
    rerun = _run(again, duration=0.1)
    assert rerun.positions.tobytes() == traj.positions.tobytes()


def test_pins_of_a_normalised_scene_come_back_where_they_were_given():
    s = ic.Scene.from_dict(SMALL)
    back = ic.Scene.from_dict(json.loads(json.dumps(s.data)))
    assert back.source["cloth"]["pins"] == ["top_left", {"vertices": [5], "velocity": [0.0, 0.0, 0.1]}]
    assert back.data == s.data
    with pytest.raises(ic.SceneError, match=r"^cloth\.kind: must be grid or mesh .*, got 'disc'$"):
        ic.Scene.from_dict({**s.data, "cloth": {**s.data["cloth"], "kind": "disc"}})
