"""implicit_cloth: mass-spring cloth with Baraff-Witkin implicit integration.

Public API::

    import implicit_cloth as ic
    scene = ic.load_scene("scene.toml")            # or ic.Scene.from_dict(d)
    sim = ic.Simulator(scene, integrator="backward_euler", dt=0.01)
    sim.step(n=1); sim.positions; sim.velocities; sim.time
    traj = sim.run(duration=2.0)                   # ic.Trajectory
    traj.save("out/trajectory.npz")
    ic.INTEGRATORS                                 # the six integrator names

All quantities are SI: metres, seconds, kilograms, newtons.
"""

#: The package version (the one place it is written; pyproject.toml reads it from here).
__version__ = "0.1.0"

from .errors import DivergenceError, InputError, MeshWarning, SceneError, SolverWarning
from .integrators import INTEGRATORS
from .materials import MATERIALS, Material
from .scene import Scene, load_scene
from .simulator import Simulator, Trajectory

__all__ = [
    "INTEGRATORS",
    "MATERIALS",
    "DivergenceError",
    "InputError",
    "Material",
    "MeshWarning",
    "Scene",
    "SceneError",
    "Simulator",
    "SolverWarning",
    "Trajectory",
    "load_scene",
    "__version__",
]
