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

from .errors import DivergenceError, MeshWarning, SceneError, SolverWarning
from .materials import MATERIALS, Material
from .scene import INTEGRATORS, Scene, load_scene
from .simulator import Simulator, Trajectory

__version__ = "0.1.0"

__all__ = [
    "INTEGRATORS",
    "MATERIALS",
    "DivergenceError",
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
