"""Only the effects a scene declares are imported, assembled and reported."""

import json
import subprocess
import sys

import numpy as np

import implicit_cloth as ic


def _modules_after_run(scene: dict, integrator: str) -> list[str]:
    code = (
        "import json, sys, implicit_cloth as ic\n"
        f"sim = ic.Simulator(json.loads({json.dumps(json.dumps(scene))}), integrator={integrator!r}, dt=0.01)\n"
        "sim.run(duration=0.03)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('implicit_cloth.effects', 'fcl')))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_no_obstacles_no_fcl_and_undeclared_effects_not_imported(hanging_scene):
    mods = _modules_after_run(hanging_scene, "backward_euler")
    assert "fcl" not in mods
    assert "implicit_cloth.effects.drag" not in mods and "implicit_cloth.effects.wind" not in mods
    assert {"implicit_cloth.effects.gravity", "implicit_cloth.effects.springs"} <= set(mods)


def test_scene_without_springs_imports_and_assembles_no_spring_term(hanging_scene):
    scene = dict(hanging_scene)
    scene["cloth"] = {k: v for k, v in hanging_scene["cloth"].items() if k != "springs"}
    mods = _modules_after_run(scene, "backward_euler")
    assert "implicit_cloth.effects.springs" not in mods
    sim = ic.Simulator(scene)
    assert sim.model.springs is None
    A, f, _ = sim.model.linearize(sim.positions, sim.velocities, 0.0, 1e-4, 1e-2)
    # only the diagonal (mass) blocks exist: no spring coupling was assembled
    assert A.nnz == 9 * sim.model.n
    assert np.allclose(A.toarray(), np.diag(np.repeat(sim.model.masses, 3)))


def test_report_effects_equal_declared(hanging_scene):
    scene = dict(hanging_scene)
    scene["effects"] = {"gravity": [0, 0, -9.81], "drag": 0.5, "wind": {"velocity": [2.0, 0.0, 0.0]}}
    scene["cloth"] = dict(hanging_scene["cloth"])
    scene["cloth"]["springs"] = {"structural": {"stiffness": 100.0}, "bend": {"stiffness": 1.0}}
    traj = ic.Simulator(scene).run(duration=0.05)
    assert traj.report["effects"] == ["gravity", "drag", "wind", "structural", "bend"]
    assert set(traj.report["n_springs"]) == {"structural", "bend"}


def test_drag_is_resolution_independent_and_relative_to_wind(hanging_scene):
    """Total drag force = -c * area * (v - w) for a uniform velocity, at any resolution."""
    for res in ([3, 3], [9, 5]):
        scene = {"cloth": {"size": [2.0, 0.5], "resolution": res, "mass": 1.0, "plane": "xy"},
                 "effects": {"drag": 0.3, "wind": {"velocity": [1.0, 2.0, 0.0]}}}
        sim = ic.Simulator(scene)
        v = np.tile([0.5, -1.0, 4.0], (sim.model.n, 1))
        f = sim.model.forces(sim.positions, v, 0.0)
        assert np.allclose(f.sum(axis=0), -0.3 * 1.0 * (np.array([0.5, -1.0, 4.0]) - [1.0, 2.0, 0.0]))
