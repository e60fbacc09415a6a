import numpy as np

import implicit_cloth as ic


def test_hanging_cloth_runs_and_reports(hanging_scene):
    traj = ic.Simulator(hanging_scene, integrator="backward_euler", dt=0.01).run(duration=0.1)
    assert traj.report["status"] == "ok"
    assert traj.positions.shape == (len(traj.times), 16, 3)
    assert np.all(np.isfinite(traj.positions))
    assert traj.report["effects"] == ["gravity", "structural", "shear", "bend"]
