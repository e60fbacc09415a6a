"""Scene description: loading, validation and defaults.

A scene is a nested mapping (from a TOML file or a dict) with the tables
``simulation``, ``solver``, ``cloth`` (with ``cloth.springs``) and ``effects``.
Validation checks every key and reports the dotted path of a bad key together
with the bad value, e.g. ``cloth.springs.shear.stiffness: must be a finite
number >= 0, got -5``; an unknown key is an error with a "did you mean"
suggestion. The validated scene is stored in a normalised form with every
default filled in (see :attr:`Scene.data`).

Numbers may be Python or NumPy scalars (``bool`` is never a number) and lists
may be lists, tuples or 1-D NumPy arrays; the normalised scene holds plain
floats, ints and lists. Besides each key's own range, a few limits keep a
valid scene runnable: at most :data:`MAX_VERTICES` grid vertices,
:data:`MAX_STEPS` steps per run, :data:`MAX_FRAMES` kept frames and
:data:`MAX_SOLVER_ITERATIONS` CG iterations per step.
"""

from __future__ import annotations

import copy
import difflib
import math
import numbers
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from .errors import SceneError
from .materials import MATERIALS

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib  # type: ignore[no-redef]

#: Names of the integrators, in the order used by reports and benchmarks.
INTEGRATORS: tuple[str, ...] = (
    "forward_euler",
    "symplectic_euler",
    "verlet",
    "rk4",
    "backward_euler",
    "bdf2",
)

#: The implicit integrators: adaptive stepping is on by default for these, off for the explicit baselines.
IMPLICIT_INTEGRATORS: tuple[str, ...] = ("backward_euler", "bdf2")

SPRING_KINDS: tuple[str, ...] = ("structural", "shear", "bend")
CORNERS: tuple[str, ...] = ("top_left", "top_right", "bottom_left", "bottom_right")
PLANES: tuple[str, ...] = ("xy", "xz", "yz")
PRECONDITIONERS: tuple[str, ...] = ("multigrid", "block_jacobi")

DEFAULTS: dict[str, dict[str, Any]] = {
    "simulation": {"integrator": "backward_euler", "dt": 0.01, "duration": 1.0, "frame_rate": 30.0},
    "solver": {"tolerance": 1e-3, "max_iterations": 1000, "preconditioner": "multigrid"},
}

_TOP_KEYS = ("simulation", "solver", "cloth", "effects", "obstacles", "collision")
_SIM_KEYS = ("integrator", "dt", "duration", "frame_rate", "divergence_factor", "adaptive", "strain_limit")
_ADAPTIVE_KEYS = ("enabled", "max_halvings", "grow_after", "max_strain", "max_energy_growth", "retry_unconverged")
#: [simulation.adaptive] defaults; ``enabled`` defaults to whether the integrator is implicit.
ADAPTIVE_DEFAULTS: dict[str, Any] = {"max_halvings": 5, "grow_after": 4, "max_strain": 1.0,
                                     "max_energy_growth": 0.1, "retry_unconverged": True}
_STRAIN_LIMIT_KEYS = ("max_strain", "iterations")
#: Most halvings of the step (dt / 2^30 is below a nanosecond for dt = 1 s).
MAX_HALVINGS = 30
_SOLVER_KEYS = ("tolerance", "max_iterations", "preconditioner")
_CLOTH_KEYS = (
    "size", "resolution", "center", "plane", "mesh", "scale", "translation",
    "mass", "density", "pins", "material", "springs", "velocity",
)
_EFFECT_KEYS = ("gravity", "drag", "wind")
#: Obstacle shapes and the keys each takes besides the common ones (velocity, angular_velocity, friction).
OBSTACLE_SHAPES: dict[str, tuple[str, ...]] = {
    "sphere": ("radius", "center"),
    "box": ("size", "center", "rotation"),
    "cone": ("radius", "height", "center", "axis"),
    "capsule": ("radius", "height", "center", "axis"),
    "plane": ("point", "normal"),
    "mesh": ("path", "scale", "translation", "rotation"),
}
_OBSTACLE_COMMON = ("shape", "velocity", "angular_velocity", "keyframes", "friction")
#: Keys of one obstacle keyframe.
_KEYFRAME_KEYS = ("time", "center", "rotation")
#: The key that places each shape (a keyframe's ``center`` stands for it).
_OBSTACLE_PLACE = {"plane": "point", "mesh": "translation"}
_COLLISION_KEYS = ("thickness", "restitution", "max_iterations")
COLLISION_DEFAULTS: dict[str, Any] = {"thickness": 0.005, "restitution": 0.0, "max_iterations": 8}

#: Largest grid (nx * ny vertices, 4096 x 4096): beyond it the arrays alone need tens of GB.
MAX_VERTICES = 4096 * 4096
#: Most steps a run may take (round(duration / dt)).
MAX_STEPS = 10**9
#: Most frames a run may keep (duration x min(frame_rate, 1 / dt) + 1).
MAX_FRAMES = 10**7
#: Largest solver.max_iterations (the solver keeps two arrays of this length per solve).
MAX_SOLVER_ITERATIONS = 10**6


# --------------------------------------------------------------------------- checks
def _fmt(value: Any) -> str:
    """The value as it was given (repr, so that '1.0' and 1.0 differ), shortened to one readable line."""
    try:
        text = " ".join(repr(value).split())
    except ValueError:   # an int beyond Python's str conversion limit (4300 digits)
        return f"an integer of about {int(value).bit_length() * 0.30103:.0f} digits"
    return text if len(text) <= 80 else text[:60] + " ... " + text[-15:]


def _is_number(value: Any) -> bool:
    """A real number (Python or NumPy scalar), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _is_list(value: Any) -> bool:
    """A list, a tuple or a 1-D NumPy array."""
    return isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim == 1)


def _fail(path: str, what: str, value: Any) -> SceneError:
    return SceneError(f"{path}: {what}, got {_fmt(value)}")


def _check_keys(path: str, table: Any, allowed: Iterable[str]) -> Mapping[str, Any]:
    if not isinstance(table, Mapping):
        raise _fail(path or "scene", "must be a table", table)
    allowed = tuple(allowed)
    for key in table:
        if key not in allowed:
            where = f"{path}.{key}" if path else str(key)
            near = difflib.get_close_matches(str(key), allowed, n=1, cutoff=0.6)
            hint = f" (did you mean '{near[0]}'?)" if near else f" (allowed: {', '.join(allowed)})"
            raise SceneError(f"{where}: unknown key{hint}")
    return table


def _number(path: str, value: Any, *, lo: float | None = None, lo_open: bool = False,
            hi: float | None = None) -> float:
    ok = _is_number(value)
    if ok:
        try:
            x = float(value)
        except (OverflowError, ValueError):   # an int beyond the float range
            x = math.inf
        ok = math.isfinite(x)
    if ok and lo is not None:
        ok = x > lo if lo_open else x >= lo
    if ok and hi is not None:
        ok = x <= hi
    if not ok:
        rng = ""
        if lo is not None:
            rng += f" {'>' if lo_open else '>='} {lo:g}"
        if hi is not None:
            rng += f"{' and' if lo is not None else ''} <= {hi:g}"
        raise _fail(path, f"must be a finite number{rng}", value)
    return x


def _integer(path: str, value: Any, *, lo: int, hi: int | None = None) -> int:
    ok = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
    ok = ok and int(value) >= lo and (hi is None or int(value) <= hi)
    if not ok:
        raise _fail(path, f"must be an integer >= {lo}" + (f" and <= {hi}" if hi is not None else ""), value)
    return int(value)


def _vector(path: str, value: Any, n: int, *, positive: bool = False) -> list[float]:
    if not _is_list(value) or len(value) != n:
        raise _fail(path, f"must be a list of {n} numbers", value)
    return [_number(f"{path}[{k}]", x, lo=0.0 if positive else None, lo_open=positive)
            for k, x in enumerate(value)]


def _boolean(path: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise _fail(path, "must be true or false", value)
    return bool(value)


def _choice(path: str, value: Any, choices: Iterable[str]) -> str:
    choices = tuple(choices)
    if not isinstance(value, str) or value not in choices:
        near = difflib.get_close_matches(str(value), choices, n=1, cutoff=0.6) if isinstance(value, str) else []
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise _fail(path, f"must be one of {', '.join(choices)}{hint}", value)
    return value


# --------------------------------------------------------------------------- sections
def _simulation(d: Mapping[str, Any]) -> dict[str, Any]:
    _check_keys("simulation", d, _SIM_KEYS)
    out = dict(DEFAULTS["simulation"])
    if "integrator" in d:
        out["integrator"] = _choice("simulation.integrator", d["integrator"], INTEGRATORS)
    if "dt" in d:
        out["dt"] = _number("simulation.dt", d["dt"], lo=0.0, lo_open=True)
    if "duration" in d:
        out["duration"] = _number("simulation.duration", d["duration"], lo=0.0, lo_open=True)
    if "frame_rate" in d:
        out["frame_rate"] = _number("simulation.frame_rate", d["frame_rate"], lo=0.0, lo_open=True)
    if "divergence_factor" in d:
        out["divergence_factor"] = _number("simulation.divergence_factor", d["divergence_factor"], lo=1.0)
    _run_length(out)
    out["adaptive"] = _adaptive(d.get("adaptive", {}), out["integrator"])
    if "strain_limit" in d:
        out["strain_limit"] = _strain_limit(d["strain_limit"])
    return out


def _adaptive(d: Any, integrator: str) -> dict[str, Any]:
    """``[simulation.adaptive]``: adaptive time stepping (see :mod:`implicit_cloth.adaptive`)."""
    path = "simulation.adaptive"
    _check_keys(path, d, _ADAPTIVE_KEYS)
    out: dict[str, Any] = {"enabled": integrator in IMPLICIT_INTEGRATORS, **ADAPTIVE_DEFAULTS}
    if "enabled" in d:
        out["enabled"] = _boolean(f"{path}.enabled", d["enabled"])
    if "max_halvings" in d:
        out["max_halvings"] = _integer(f"{path}.max_halvings", d["max_halvings"], lo=0, hi=MAX_HALVINGS)
    if "grow_after" in d:
        out["grow_after"] = _integer(f"{path}.grow_after", d["grow_after"], lo=1, hi=10**6)
    if "max_strain" in d:
        out["max_strain"] = _number(f"{path}.max_strain", d["max_strain"], lo=0.0, lo_open=True)
    if "max_energy_growth" in d:
        out["max_energy_growth"] = _number(f"{path}.max_energy_growth", d["max_energy_growth"], lo=0.0)
    if "retry_unconverged" in d:
        out["retry_unconverged"] = _boolean(f"{path}.retry_unconverged", d["retry_unconverged"])
    return out


def _strain_limit(d: Any) -> dict[str, Any]:
    """``[simulation.strain_limit]``: Provot strain limiting (see :mod:`implicit_cloth.strain_limit`)."""
    path = "simulation.strain_limit"
    _check_keys(path, d, _STRAIN_LIMIT_KEYS)
    iterations = _integer(f"{path}.iterations", d.get("iterations", 10), lo=1, hi=10_000)
    if "max_strain" not in d:
        raise SceneError(f"{path}.max_strain: missing (the largest relative stretch (l - L0) / L0 to allow, "
                         f"e.g. 0.1)")
    return {"max_strain": _number(f"{path}.max_strain", d["max_strain"], lo=0.0, lo_open=True),
            "iterations": iterations}


def _run_length(sim: Mapping[str, Any]) -> None:
    """Refuse a run whose step or frame count is beyond what can be counted or stored.

    A step count beyond the limit names whichever of dt and duration is further
    from its default in the direction that makes the run long; a frame count
    beyond it names frame_rate.
    """
    dt, duration, rate = sim["dt"], sim["duration"], sim["frame_rate"]
    base = DEFAULTS["simulation"]
    steps = duration / dt                                   # may be inf (5e-324 s steps)
    if not steps <= MAX_STEPS:
        key = "duration" if duration / base["duration"] >= base["dt"] / dt else "dt"
        raise _fail(f"simulation.{key}", f"the run would take {steps:.3g} steps (duration / dt = "
                    f"{duration:g} s / {dt:g} s), more than the limit of {MAX_STEPS:.0e}", sim[key])
    frames = duration * min(rate, 1.0 / dt)
    if not frames <= MAX_FRAMES:
        raise _fail("simulation.frame_rate", f"the run would keep {frames:.3g} frames (duration x "
                    f"min(frame_rate, 1 / dt)), more than the limit of {MAX_FRAMES:.0e}", rate)


def _solver(d: Mapping[str, Any]) -> dict[str, Any]:
    _check_keys("solver", d, _SOLVER_KEYS)
    out = dict(DEFAULTS["solver"])
    if "tolerance" in d:
        out["tolerance"] = _number("solver.tolerance", d["tolerance"], lo=0.0, lo_open=True, hi=1.0)
    if "max_iterations" in d:
        out["max_iterations"] = _integer("solver.max_iterations", d["max_iterations"], lo=1,
                                         hi=MAX_SOLVER_ITERATIONS)
    if "preconditioner" in d:
        out["preconditioner"] = _choice("solver.preconditioner", d["preconditioner"], PRECONDITIONERS)
    return out


def _pins(value: Any, n_vertices: int | None = None) -> list[dict[str, Any]]:
    if not _is_list(value):
        raise _fail("cloth.pins", "must be a list of vertex indices, corner names or tables", value)
    groups: list[dict[str, Any]] = []
    loose: list[int | str] = []
    loose_paths: list[str] = []

    def vertex(path: str, v: Any) -> int | str:
        if isinstance(v, str):
            return _choice(path, v, CORNERS)
        return _integer(path, v, lo=0)

    for k, item in enumerate(value):
        path = f"cloth.pins[{k}]"
        if isinstance(item, Mapping):
            _check_keys(path, item, ("vertices", "velocity"))
            if "vertices" not in item:
                raise SceneError(f"{path}.vertices: missing (a pin table needs its vertices)")
            verts = item["vertices"]
            if not _is_list(verts) or not len(verts):
                raise _fail(f"{path}.vertices", "must be a non-empty list of vertex indices or corner names", verts)
            paths = [f"{path}.vertices[{m}]" for m in range(len(verts))]
            groups.append({
                "vertices": [vertex(p, v) for p, v in zip(paths, verts)],
                "velocity": _vector(f"{path}.velocity", item.get("velocity", [0.0, 0.0, 0.0]), 3),
                "paths": paths,
            })
        else:
            loose.append(vertex(path, item))
            loose_paths.append(path)
    if loose:
        groups.insert(0, {"vertices": loose, "velocity": [0.0, 0.0, 0.0], "paths": loose_paths})
    if n_vertices is not None:
        _pins_in_range(groups, n_vertices)
    return groups


def _grid_vertices(cloth: Mapping[str, Any]) -> int | None:
    """A grid cloth's vertex count; None for a mesh, whose count is known once its file is read (Model checks)."""
    if cloth["kind"] != "grid":
        return None
    return int(cloth["resolution"][0] * cloth["resolution"][1])


def _pins_in_range(groups: list[dict[str, Any]], n: int) -> None:
    for g in groups:
        for path, v in zip(g["paths"], g["vertices"]):
            if isinstance(v, int) and v >= n:
                raise SceneError(f"{path}: vertex index out of range (the cloth has {n} vertices), "
                                 f"got {_fmt(v)}")


def _springs(d: Any, material: str | None) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    if material is not None:
        for kind, p in MATERIALS[material].springs().items():
            out[kind] = {"stiffness": p.stiffness, "damping": p.damping}
    if d is None:
        return out
    _check_keys("cloth.springs", d, SPRING_KINDS)
    for kind, spec in d.items():
        path = f"cloth.springs.{kind}"
        _check_keys(path, spec, ("stiffness", "damping"))
        base = out.get(kind, {})
        given = {key: _number(f"{path}.{key}", spec[key], lo=0.0) for key in ("stiffness", "damping") if key in spec}
        if "stiffness" not in given and "stiffness" not in base:
            raise SceneError(f"{path}.stiffness: missing (no material preset supplies it)")
        out[kind] = {
            "stiffness": given.get("stiffness", base.get("stiffness")),
            "damping": given.get("damping", base.get("damping", 0.0)),
        }
    return out


def _cloth(d: Any, base_dir: Path | None) -> dict[str, Any]:
    _check_keys("cloth", d, _CLOTH_KEYS)
    out: dict[str, Any] = {}
    if "mesh" in d:
        for key in ("size", "resolution", "plane", "center"):
            if key in d:
                raise SceneError(f"cloth.{key}: not used with cloth.mesh (a mesh cloth takes scale and translation)")
        mesh = d["mesh"]
        if not isinstance(mesh, str) or not mesh:
            raise _fail("cloth.mesh", "must be a path to a mesh file", mesh)
        path = Path(mesh)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        out["kind"] = "mesh"
        out["mesh"] = str(path)
        out["scale"] = _number("cloth.scale", d.get("scale", 1.0), lo=0.0, lo_open=True)
        out["translation"] = _vector("cloth.translation", d.get("translation", [0.0, 0.0, 0.0]), 3)
    else:
        for key in ("scale", "translation"):
            if key in d:
                raise SceneError(f"cloth.{key}: only used with cloth.mesh (a grid cloth takes size and center)")
        out["kind"] = "grid"
        out["size"] = _vector("cloth.size", d.get("size", [1.0, 1.0]), 2, positive=True)
        res = d.get("resolution", [32, 32])
        if not _is_list(res) or len(res) != 2:
            raise _fail("cloth.resolution", "must be a list of 2 integers >= 2", res)
        out["resolution"] = [_integer(f"cloth.resolution[{k}]", r, lo=2) for k, r in enumerate(res)]
        if out["resolution"][0] * out["resolution"][1] > MAX_VERTICES:
            raise _fail("cloth.resolution", f"must give at most {MAX_VERTICES} vertices (4096 x 4096), "
                        f"nx * ny = {out['resolution'][0] * out['resolution'][1]}", res)
        out["center"] = _vector("cloth.center", d.get("center", [0.0, 0.0, 0.0]), 3)
        out["plane"] = _choice("cloth.plane", d.get("plane", "xz"), PLANES)

    material = None
    if "material" in d:
        material = _choice("cloth.material", d["material"], MATERIALS.keys())
    out["material"] = material
    if "mass" in d and "density" in d:
        raise SceneError("cloth.density: give either cloth.mass or cloth.density, not both")
    if "mass" in d:
        out["mass"] = _number("cloth.mass", d["mass"], lo=0.0, lo_open=True)
    elif "density" in d:
        out["density"] = _number("cloth.density", d["density"], lo=0.0, lo_open=True)
    elif material is not None:
        out["density"] = MATERIALS[material].density
    else:
        raise SceneError("cloth.mass: missing (give cloth.mass in kg, cloth.density in kg/m^2, or a material)")
    out["velocity"] = _vector("cloth.velocity", d.get("velocity", [0.0, 0.0, 0.0]), 3)
    out["pins"] = _pins(d.get("pins", []), _grid_vertices(out))
    if "springs" in d and d["springs"] is None:
        raise _fail("cloth.springs", "must be a table", None)
    out["springs"] = _springs(d.get("springs"), material)
    return out


def _effects(d: Any) -> dict[str, Any]:
    _check_keys("effects", d, _EFFECT_KEYS)
    out: dict[str, Any] = {}
    if "gravity" in d:
        out["gravity"] = _vector("effects.gravity", d["gravity"], 3)
    if "drag" in d:
        out["drag"] = _number("effects.drag", d["drag"], lo=0.0)
    if "wind" in d:
        w = d["wind"]
        _check_keys("effects.wind", w, ("velocity",))
        if "velocity" not in w:
            raise SceneError("effects.wind.velocity: missing (wind needs a velocity [vx, vy, vz] in m/s)")
        out["wind"] = {"velocity": _vector("effects.wind.velocity", w["velocity"], 3)}
        if "drag" not in out:
            raise SceneError(
                "effects.drag: missing (wind acts through air drag; set effects.drag, the drag coefficient "
                "in N*s/m^3, for effects.wind to have an effect)")
    return out


def _direction(path: str, value: Any) -> list[float]:
    vec = _vector(path, value, 3)
    if not math.hypot(*vec) > 0:
        raise _fail(path, "must be a non-zero direction", value)
    return vec


def _obstacle_mesh(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    """A mesh obstacle's file (read with trimesh), scale, translation and rotation."""
    if "path" not in d:
        raise SceneError(f"{path}.path: missing (a mesh obstacle needs the path of a mesh file)")
    f = d["path"]
    if not isinstance(f, str) or not f:
        raise _fail(f"{path}.path", "must be a path to a mesh file", f)
    p = Path(f)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    if not p.is_file():
        raise _fail(f"{path}.path", "file not found", f)
    load_obstacle_mesh(str(p), f"{path}.path", f)
    return {
        "path": str(p),
        "scale": _number(f"{path}.scale", d.get("scale", 1.0), lo=0.0, lo_open=True),
        "translation": _vector(f"{path}.translation", d.get("translation", [0.0, 0.0, 0.0]), 3),
        "rotation": _vector(f"{path}.rotation", d.get("rotation", [0.0, 0.0, 0.0]), 3),
    }


def load_obstacle_mesh(file: str, key: str = "obstacles.path", given: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of a mesh obstacle's file, read with trimesh (merged vertices).

    Raises
    ------
    SceneError
        Naming ``key``: unreadable file, no triangles, non-finite coordinates.
    """
    import trimesh  # deferred: only mesh obstacles need it

    given = file if given is None else given
    try:
        m = trimesh.load(file, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for bad files
        raise _fail(key, f"cannot read mesh file ({type(exc).__name__}: {' '.join(str(exc).split())})",
                    given) from None
    faces = np.asarray(getattr(m, "faces", np.zeros((0, 3))))
    verts = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), dtype=float)
    if faces.ndim != 2 or len(faces) == 0 or faces.shape[1] != 3:
        raise _fail(key, "mesh has no triangles", given)
    if not np.isfinite(verts).all():
        raise _fail(key, "mesh has non-finite coordinates", given)
    return verts, faces.astype(np.int64)


def _keyframes(path: str, value: Any) -> list[dict[str, Any]]:
    """An obstacle's ``keyframes``: at least two tables ``{time, center, rotation}``, times strictly increasing.

    ``time`` in s (>= 0), ``center`` in m, ``rotation`` a rotation vector in rad (default [0, 0, 0]) on top of
    the shape's own orientation.
    """
    if not _is_list(value) or len(value) < 2:
        raise _fail(path, "must be a list of at least 2 keys ({time = s, center = [x, y, z]})", value)
    keys: list[dict[str, Any]] = []
    for k, key in enumerate(value):
        kp = f"{path}[{k}]"
        _check_keys(kp, key, _KEYFRAME_KEYS)
        for name, what in (("time", "its time in s"), ("center", "its center [x, y, z] in m")):
            if name not in key:
                raise SceneError(f"{kp}.{name}: missing (each key needs {what})")
        t = _number(f"{kp}.time", key["time"], lo=0.0)
        if keys and not t > keys[-1]["time"]:
            raise _fail(f"{kp}.time", f"must be greater than the previous key's time {keys[-1]['time']:g}",
                        key["time"])
        keys.append({"time": t, "center": _vector(f"{kp}.center", key["center"], 3),
                     "rotation": _vector(f"{kp}.rotation", key.get("rotation", [0.0, 0.0, 0.0]), 3)})
    return keys


def _obstacles(value: Any, base_dir: Path | None = None) -> list[dict[str, Any]]:
    """The ``[[obstacles]]`` array: one table per rigid obstacle (see :data:`OBSTACLE_SHAPES`)."""
    if not _is_list(value):
        raise _fail("obstacles", "must be an array of tables ([[obstacles]])", value)
    out = []
    for k, d in enumerate(value):
        path = f"obstacles[{k}]"
        if not isinstance(d, Mapping):
            raise _fail(path, "must be a table", d)
        if "shape" not in d:
            raise SceneError(f"{path}.shape: missing (one of {', '.join(OBSTACLE_SHAPES)})")
        shape = _choice(f"{path}.shape", d["shape"], OBSTACLE_SHAPES)
        _check_keys(path, d, _OBSTACLE_COMMON + OBSTACLE_SHAPES[shape])
        o: dict[str, Any] = {"shape": shape}
        for key in ("radius", "height"):
            if key in OBSTACLE_SHAPES[shape]:
                if key not in d:
                    raise SceneError(f"{path}.{key}: missing (a {shape} needs its {key} in m)")
                o[key] = _number(f"{path}.{key}", d[key], lo=0.0, lo_open=True)
        if shape == "box":
            if "size" not in d:
                raise SceneError(f"{path}.size: missing (a box needs its full extents [x, y, z] in m)")
            o["size"] = _vector(f"{path}.size", d["size"], 3, positive=True)
            o["rotation"] = _vector(f"{path}.rotation", d.get("rotation", [0.0, 0.0, 0.0]), 3)
        if shape == "mesh":
            o.update(_obstacle_mesh(path, d, base_dir))
        elif shape == "plane":
            o["point"] = _vector(f"{path}.point", d.get("point", [0.0, 0.0, 0.0]), 3)
            o["normal"] = _direction(f"{path}.normal", d.get("normal", [0.0, 0.0, 1.0]))
        else:
            o["center"] = _vector(f"{path}.center", d.get("center", [0.0, 0.0, 0.0]), 3)
        if "axis" in OBSTACLE_SHAPES[shape]:
            o["axis"] = _direction(f"{path}.axis", d.get("axis", [0.0, 0.0, 1.0]))
        if "keyframes" in d:
            place = _OBSTACLE_PLACE.get(shape, "center")
            for key in ("velocity", "angular_velocity", place):
                if key in d:
                    raise _fail(f"{path}.{key}", "cannot be combined with keyframes (the keys give the "
                                "obstacle's position and motion)", d[key])
            o["keyframes"] = _keyframes(f"{path}.keyframes", d["keyframes"])
            o[place] = list(o["keyframes"][0]["center"])
        o["velocity"] = _vector(f"{path}.velocity", d.get("velocity", [0.0, 0.0, 0.0]), 3)
        o["angular_velocity"] = _vector(f"{path}.angular_velocity", d.get("angular_velocity", [0.0, 0.0, 0.0]), 3)
        o["friction"] = _number(f"{path}.friction", d.get("friction", 0.0), lo=0.0)
        out.append(o)
    return out


def _collision(d: Any) -> dict[str, Any]:
    _check_keys("collision", d, _COLLISION_KEYS)
    out = dict(COLLISION_DEFAULTS)
    if "thickness" in d:
        out["thickness"] = _number("collision.thickness", d["thickness"], lo=0.0, lo_open=True)
    if "restitution" in d:
        out["restitution"] = _number("collision.restitution", d["restitution"], lo=0.0, hi=1.0)
    if "max_iterations" in d:
        out["max_iterations"] = _integer("collision.max_iterations", d["max_iterations"], lo=1, hi=1000)
    return out


# --------------------------------------------------------------------------- Scene
class Scene:
    """A validated scene.

    Parameters
    ----------
    data : mapping
        The raw scene (as read from TOML).
    base_dir : path, optional
        Directory that relative paths in the scene (mesh files) are resolved against.

    Attributes
    ----------
    data : dict
        The normalised scene: every table present, every default filled in.
    """

    def __init__(self, data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None = None) -> None:
        self.base_dir = Path(base_dir) if base_dir is not None else None
        self.source: dict[str, Any] = copy.deepcopy(dict(data)) if isinstance(data, Mapping) else data
        self.data = self._validate(data)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None = None) -> "Scene":
        """Validate a scene given as a nested dict with the same keys as the TOML file."""
        return cls(data, base_dir=base_dir)

    def _validate(self, data: Any) -> dict[str, Any]:
        _check_keys("", data, _TOP_KEYS)
        if "cloth" not in data:
            raise SceneError("cloth: missing (a scene needs a [cloth] table)")
        out = {
            "simulation": _simulation(data.get("simulation", {})),
            "solver": _solver(data.get("solver", {})),
            "cloth": _cloth(data["cloth"], self.base_dir),
            "effects": _effects(data.get("effects", {})),
            "obstacles": _obstacles(data.get("obstacles", []), self.base_dir),
        }
        if "collision" in data and not out["obstacles"]:
            raise SceneError("collision: given, but the scene has no [[obstacles]] to collide with")
        out["collision"] = _collision(data.get("collision", {})) if out["obstacles"] else None
        return out

    def replace(self, **sections: Mapping[str, Any]) -> "Scene":
        """A new scene with some keys of some tables overridden, e.g. ``replace(simulation={"dt": 0.02})``."""
        raw = copy.deepcopy(self.source)
        for name, updates in sections.items():
            if not isinstance(updates, Mapping):
                raise _fail(name, "overrides must be a table (a dict of keys to replace)", updates)
            table = raw.get(name, {})
            raw[name] = {**(table if isinstance(table, Mapping) else {}), **updates}
        return Scene(raw, base_dir=self.base_dir)

    @property
    def effects(self) -> list[str]:
        """The names of the effects this scene declares, in evaluation order."""
        names = [k for k in ("gravity", "drag", "wind") if k in self.data["effects"]]
        names += [k for k in SPRING_KINDS if k in self.data["cloth"]["springs"]]
        if self.data["obstacles"]:
            names.append("collision")
        return names

    def __repr__(self) -> str:
        c = self.data["cloth"]
        what = f"grid {c['resolution'][0]}x{c['resolution'][1]}" if c["kind"] == "grid" else f"mesh {c['mesh']}"
        return f"Scene({what}, effects={self.effects})"


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Read and validate a TOML scene file.

    Relative paths inside the scene (mesh files) are resolved against the
    scene file's directory.

    Raises
    ------
    SceneError
        If the file cannot be read, is not valid TOML, or fails validation.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise SceneError(f"{p}: cannot read scene file ({exc.strerror or exc})") from None
    if not text.strip():
        raise SceneError(f"{p}: scene file is empty")
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SceneError(f"{p}: not a valid TOML file ({exc})") from None
    return Scene(data, base_dir=p.parent)
