import pytest


@pytest.fixture
def hanging_scene():
    return {
        "simulation": {"integrator": "backward_euler", "dt": 0.01, "duration": 0.5, "frame_rate": 30},
        "cloth": {
            "size": [1.0, 1.0], "resolution": [4, 4], "mass": 0.1, "center": [0.0, 0.0, 1.0],
            "plane": "xz", "pins": ["top_left", "top_right"],
            "springs": {
                "structural": {"stiffness": 500.0, "damping": 0.1},
                "shear": {"stiffness": 50.0, "damping": 0.05},
                "bend": {"stiffness": 5.0, "damping": 0.01},
            },
        },
        "effects": {"gravity": [0.0, 0.0, -9.81]},
    }
