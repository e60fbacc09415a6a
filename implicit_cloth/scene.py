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
import os
import re
from pathlib import Path
from typing import Any, Mapping

from .config.registry import EFFECTS, INTEGRATORS, OBSTACLE_SHAPES, PRECONDITIONERS
from .config.validate import boolean, check_keys, choice, fail, integer, is_list, number, vector
from .errors import SceneError
from .materials import MATERIALS
from .obstacles import validate_obstacles

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib  # type: ignore[no-redef]

SPRING_KINDS: tuple[str, ...] = ("structural", "shear", "bend")
CORNERS: tuple[str, ...] = ("top_left", "top_right", "bottom_left", "bottom_right")
PLANES: tuple[str, ...] = ("xy", "xz", "yz")

DEFAULTS: dict[str, dict[str, Any]] = {
    "simulation": {"integrator": "backward_euler", "dt": 0.01, "duration": 1.0, "frame_rate": 30.0},
    "solver": {"tolerance": 1e-3, "max_iterations": 1000, "preconditioner": "auto", "newton_iterations": 1,
               "cycle": "V"},
}

TOP_KEYS = ("simulation", "solver", "cloth", "effects", "obstacles", "collision")
SIM_KEYS = ("integrator", "dt", "duration", "frame_rate", "divergence_factor", "adaptive", "strain_limit")
ADAPTIVE_KEYS = ("enabled", "max_halvings", "grow_after", "max_strain", "max_energy_growth", "retry_unconverged",
                 "newton_iterations")
#: [simulation.adaptive] defaults; ``enabled`` defaults to whether the integrator is implicit.
ADAPTIVE_DEFAULTS: dict[str, Any] = {"max_halvings": 5, "grow_after": 4, "max_strain": 1.0,
                                     "max_energy_growth": 0.01, "retry_unconverged": True, "newton_iterations": 8}
STRAIN_LIMIT_KEYS = ("max_strain", "iterations", "tethers", "max_compression")
#: Most halvings of the step (dt / 2^30 is below a nanosecond for dt = 1 s).
MAX_HALVINGS = 30
SOLVER_KEYS = ("tolerance", "contact_tolerance", "max_iterations", "preconditioner", "newton_iterations", "cycle")
#: ``solver.cycle``: the multigrid's V-cycle, or Notay's K-cycle (flexible CG on every coarse level; see
#: :func:`implicit_cloth.kernels.pcg.kcycle`)
CYCLES = ("V", "K")
#: Most Newton iterations per step.
MAX_NEWTON_ITERATIONS = 100
CLOTH_KEYS = (
    "size", "resolution", "center", "plane", "mesh", "scale", "translation",
    "mass", "density", "pins", "material", "springs", "velocity", "membrane", "bending",
)
#: ``[cloth.membrane]``'s conditions (:mod:`implicit_cloth.effects.membrane`, BW98's stretch and shear)
MEMBRANE_CONDITIONS: tuple[str, ...] = ("stretch_u", "stretch_v", "shear")
#: the spring kinds the membrane replaces
MEMBRANE_REPLACES: tuple[str, ...] = ("structural", "shear")
#: ``[cloth.bending]``'s keys and models: the bend springs (today's), or the hinges' dihedral angles
#: (:mod:`implicit_cloth.effects.dihedral`)
BENDING_KEYS: tuple[str, ...] = ("model", "stiffness", "damping", "rest_angle")
BENDING_MODELS: tuple[str, ...] = ("springs", "dihedral")
#: the dihedral bending's rest angles: the rest mesh's, or 0 (flat)
REST_ANGLES: tuple[str, ...] = ("mesh", "flat")
COLLISION_KEYS = ("method", "thickness", "restitution", "max_iterations", "newton_iterations", "friction_speed",
                  "friction_newton", "friction_pause", "self_collision", "self_friction")
#: ``collision.method``: contacts as constraints found in rounds of solves ("rounds"), or as a barrier energy in
#: the step's one Newton solve of its incremental potential ("barrier", :mod:`implicit_cloth.contact`)
COLLISION_METHODS = ("rounds", "barrier")
#: Coulomb coefficient between layers of cloth when ``self_collision`` is on and ``self_friction`` is not given.
SELF_FRICTION = 0.3
COLLISION_DEFAULTS: dict[str, Any] = {"thickness": 0.005, "restitution": 0.0, "max_iterations": 8,
                                      "newton_iterations": 2}

#: Largest grid (nx * ny vertices, 4096 x 4096): beyond it the arrays alone need tens of GB.
MAX_VERTICES = 4096 * 4096
#: Most steps a run may take (round(duration / dt)).
MAX_STEPS = 10**9
#: Most frames a run may keep (duration x min(frame_rate, 1 / dt) + 1).
MAX_FRAMES = 10**7
#: Largest solver.max_iterations (the solver keeps two arrays of this length per solve).
MAX_SOLVER_ITERATIONS = 10**6


# --------------------------------------------------------------------------- sections
def _simulation(d: Mapping[str, Any]) -> dict[str, Any]:
    check_keys("simulation", d, SIM_KEYS)
    out = dict(DEFAULTS["simulation"])
    if "integrator" in d:
        out["integrator"] = INTEGRATORS.choice("simulation.integrator", d["integrator"])
    if "dt" in d:
        out["dt"] = number("simulation.dt", d["dt"], lo=0.0, lo_open=True)
    if "duration" in d:
        out["duration"] = number("simulation.duration", d["duration"], lo=0.0, lo_open=True)
    if "frame_rate" in d:
        out["frame_rate"] = number("simulation.frame_rate", d["frame_rate"], lo=0.0, lo_open=True)
    if "divergence_factor" in d:
        out["divergence_factor"] = number("simulation.divergence_factor", d["divergence_factor"], lo=1.0)
    check_run_length(out)
    out["adaptive"] = _adaptive(d.get("adaptive", {}), out["integrator"])
    if "strain_limit" in d:
        out["strain_limit"] = _strain_limit(d["strain_limit"])
    return out


def _adaptive(d: Any, integrator: str) -> dict[str, Any]:
    """``[simulation.adaptive]``: adaptive time stepping (see :mod:`implicit_cloth.adaptive`)."""
    path = "simulation.adaptive"
    check_keys(path, d, ADAPTIVE_KEYS)
    out: dict[str, Any] = {"enabled": integrator in INTEGRATORS.where(implicit=True), **ADAPTIVE_DEFAULTS}
    if "enabled" in d:
        out["enabled"] = boolean(f"{path}.enabled", d["enabled"])
    if "max_halvings" in d:
        out["max_halvings"] = integer(f"{path}.max_halvings", d["max_halvings"], lo=0, hi=MAX_HALVINGS)
    if "grow_after" in d:
        out["grow_after"] = integer(f"{path}.grow_after", d["grow_after"], lo=1, hi=10**6)
    if "max_strain" in d:
        out["max_strain"] = number(f"{path}.max_strain", d["max_strain"], lo=0.0, lo_open=True)
    if "max_energy_growth" in d:
        out["max_energy_growth"] = number(f"{path}.max_energy_growth", d["max_energy_growth"], lo=0.0)
    if "retry_unconverged" in d:
        out["retry_unconverged"] = boolean(f"{path}.retry_unconverged", d["retry_unconverged"])
    if "newton_iterations" in d:
        out["newton_iterations"] = integer(f"{path}.newton_iterations", d["newton_iterations"], lo=1,
                                           hi=MAX_NEWTON_ITERATIONS)
    return out


def _strain_limit(d: Any) -> dict[str, Any]:
    """``[simulation.strain_limit]``: Provot strain limiting (see :mod:`implicit_cloth.strain_limit`)."""
    path = "simulation.strain_limit"
    check_keys(path, d, STRAIN_LIMIT_KEYS)
    iterations = integer(f"{path}.iterations", d.get("iterations", 10), lo=1, hi=10_000)
    if "max_strain" not in d:
        raise SceneError(f"{path}.max_strain: missing (the largest relative stretch (l - L0) / L0 to allow, "
                         f"e.g. 0.1)")
    max_strain = number(f"{path}.max_strain", d["max_strain"], lo=0.0, lo_open=True)
    return {"max_strain": max_strain,
            "iterations": iterations, "tethers": boolean(f"{path}.tethers", d.get("tethers", True)),
            "max_compression": number(f"{path}.max_compression", d.get("max_compression", min(max_strain, 1.0)),
                                      lo=0.0, hi=1.0)}


def check_run_length(sim: Mapping[str, Any]) -> None:
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
        raise fail(f"simulation.{key}", f"the run would take {steps:.3g} steps (duration / dt = "
                    f"{duration:g} s / {dt:g} s), more than the limit of {MAX_STEPS:.0e}", sim[key])
    frames = duration * min(rate, 1.0 / dt)
    if not frames <= MAX_FRAMES:
        raise fail("simulation.frame_rate", f"the run would keep {frames:.3g} frames (duration x "
                    f"min(frame_rate, 1 / dt)), more than the limit of {MAX_FRAMES:.0e}", rate)


def _solver(d: Mapping[str, Any]) -> dict[str, Any]:
    check_keys("solver", d, SOLVER_KEYS)
    out = dict(DEFAULTS["solver"])
    if "tolerance" in d:
        out["tolerance"] = number("solver.tolerance", d["tolerance"], lo=0.0, lo_open=True, hi=1.0)
    if "contact_tolerance" in d:
        out["contact_tolerance"] = number("solver.contact_tolerance", d["contact_tolerance"], lo=0.0, lo_open=True,
                                          hi=1.0)
    if "max_iterations" in d:
        out["max_iterations"] = integer("solver.max_iterations", d["max_iterations"], lo=1,
                                         hi=MAX_SOLVER_ITERATIONS)
    if "preconditioner" in d:
        out["preconditioner"] = choice("solver.preconditioner", d["preconditioner"], PRECONDITIONERS.names())
    if "newton_iterations" in d:
        out["newton_iterations"] = integer("solver.newton_iterations", d["newton_iterations"], lo=1,
                                           hi=MAX_NEWTON_ITERATIONS)
    if "cycle" in d:
        out["cycle"] = choice("solver.cycle", d["cycle"], CYCLES)
        if out["cycle"] != "V" and out["preconditioner"] == "block_jacobi":
            raise fail("solver.cycle", "is a multigrid's cycle; solver.preconditioner = \"block_jacobi\" has none",
                       d["cycle"])
    return out


def _pins(value: Any, n_vertices: int | None = None, where: str = "cloth") -> list[dict[str, Any]]:
    if not is_list(value):
        raise fail(f"{where}.pins", "must be a list of vertex indices, corner names or tables", value)
    groups: list[dict[str, Any]] = []
    loose: list[int | str] = []
    loose_paths: list[str] = []

    def vertex(path: str, v: Any) -> int | str:
        if isinstance(v, str):
            return choice(path, v, CORNERS)
        return integer(path, v, lo=0)

    for k, item in enumerate(value):
        path = f"{where}.pins[{k}]"
        if isinstance(item, Mapping):
            check_keys(path, item, PIN_KEYS)
            if "vertices" not in item:
                raise SceneError(f"{path}.vertices: missing (a pin table needs its vertices)")
            verts = item["vertices"]
            if not is_list(verts) or not len(verts):
                raise fail(f"{path}.vertices", "must be a non-empty list of vertex indices or corner names", verts)
            if "keyframes" in item and "velocity" in item:
                raise fail(f"{path}.velocity", "cannot be given with keyframes (the keyframes give the pins' "
                                               "motion)", item["velocity"])
            paths = [f"{path}.vertices[{m}]" for m in range(len(verts))]
            group: dict[str, Any] = {
                "vertices": [vertex(p, v) for p, v in zip(paths, verts)],
                "velocity": vector(f"{path}.velocity", item.get("velocity", [0.0, 0.0, 0.0]), 3),
                "paths": paths,
            }
            if "keyframes" in item:
                group["keyframes"] = _pin_keyframes(f"{path}.keyframes", item["keyframes"])
            if "stiffness" in item:
                group["stiffness"] = number(f"{path}.stiffness", item["stiffness"], lo=0.0, lo_open=True)
            if "damping" in item:
                if "stiffness" not in item:
                    raise fail(f"{path}.damping", "needs stiffness (only a soft pin, one with a stiffness, has "
                                                  "a damping)", item["damping"])
                group["damping"] = number(f"{path}.damping", item["damping"], lo=0.0)
            groups.append(group)
        else:
            loose.append(vertex(path, item))
            loose_paths.append(path)
    if loose:
        groups.insert(0, {"vertices": loose, "velocity": [0.0, 0.0, 0.0], "paths": loose_paths})
    if n_vertices is not None:
        _pins_in_range(groups, n_vertices, "cloth" if where == "cloth" else "piece")
    return groups


#: the keys of a pin table (``cloth.pins[k]``)
PIN_KEYS = ("vertices", "velocity", "keyframes", "stiffness", "damping")


def _pin_keyframes(path: str, value: Any) -> list[dict[str, Any]]:
    """A pin group's ``keyframes``: a non-empty list of ``{time, translation, rotation}`` (s >= 0, strictly
    increasing; m, the group's displacement from its place at t = 0; rad, a rotation vector about the group's
    centre at t = 0), translation and rotation 0 when left out."""
    if not is_list(value) or not len(value):
        raise fail(path, "must be a non-empty list of tables {time, translation, rotation}", value)
    out: list[dict[str, Any]] = []
    for k, key in enumerate(value):
        p = f"{path}[{k}]"
        check_keys(p, key, ("time", "translation", "rotation"))
        if "time" not in key:
            raise SceneError(f"{p}.time: missing (each keyframe needs its time, s)")
        t = number(f"{p}.time", key["time"], lo=0.0)
        if out and t <= out[-1]["time"]:
            raise fail(f"{p}.time", f"keyframe times must be strictly increasing (the previous is "
                                    f"{out[-1]['time']:g} s)", key["time"])
        out.append({"time": t,
                    "translation": vector(f"{p}.translation", key.get("translation", [0.0, 0.0, 0.0]), 3),
                    "rotation": vector(f"{p}.rotation", key.get("rotation", [0.0, 0.0, 0.0]), 3)})
    return out


def _grid_vertices(cloth: Mapping[str, Any]) -> int | None:
    """A grid cloth's vertex count; None for a mesh, whose count is known once its file is read (Model checks)."""
    if cloth["kind"] != "grid":
        return None
    return int(cloth["resolution"][0] * cloth["resolution"][1])


def _pins_in_range(groups: list[dict[str, Any]], n: int, what: str = "cloth") -> None:
    for g in groups:
        for path, v in zip(g["paths"], g["vertices"]):
            if isinstance(v, int) and v >= n:
                raise fail(path, f"vertex index out of range (the {what} has {n} vertices)", v)


def _springs(d: Any, material: str | None, where: str = "cloth") -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    if material is not None:
        for kind, p in MATERIALS[material].springs().items():
            out[kind] = {"stiffness": p.stiffness, "damping": p.damping}
    if d is None:
        return out
    check_keys(f"{where}.springs", d, SPRING_KINDS)
    for kind, spec in d.items():
        path = f"{where}.springs.{kind}"
        check_keys(path, spec, ("stiffness", "damping"))
        base = out.get(kind, {})
        given = {key: number(f"{path}.{key}", spec[key], lo=0.0) for key in ("stiffness", "damping") if key in spec}
        if "stiffness" not in given and "stiffness" not in base:
            raise SceneError(f"{path}.stiffness: missing (no material preset supplies it)")
        out[kind] = {
            "stiffness": given["stiffness"] if "stiffness" in given else base["stiffness"],
            "damping": given.get("damping", base.get("damping", 0.0)),
        }
    return out


def _membrane(d: Any, material: str | None, where: str = "cloth") -> dict[str, dict[str, float]]:
    """``[cloth.membrane]``: each condition's stiffness (N/m, > 0) and damping (N*s/m, >= 0), from the table or
    the material's measured values (:attr:`Material.membrane <implicit_cloth.materials.Material.membrane>`)."""
    path = f"{where}.membrane"
    check_keys(path, d, MEMBRANE_CONDITIONS)
    preset = MATERIALS[material].membrane if material is not None else None
    out: dict[str, dict[str, float]] = {}
    for cond in MEMBRANE_CONDITIONS:
        p = f"{path}.{cond}"
        spec = d.get(cond, {})
        check_keys(p, spec, ("stiffness", "damping"))
        base = preset.conditions()[cond] if preset is not None else None
        k = _stiffness(p, spec, None if base is None else base.stiffness, material, "membrane values",
                       "in-plane stiffness in N/m")
        kd = number(f"{p}.damping", spec["damping"], lo=0.0) if "damping" in spec else (
            base.damping if base is not None else 0.0)
        out[cond] = {"stiffness": k, "damping": kd}
    return out


def _stiffness(path: str, spec: Mapping[str, Any], measured: float | None, material: str | None, lacks: str,
               need: str) -> float:
    """``path.stiffness`` (> 0) from the table, else the material's ``measured`` value; missing both, an error
    saying what the material ``lacks`` or that no preset was named, and what to give (``need``)."""
    if "stiffness" in spec:
        return number(f"{path}.stiffness", spec["stiffness"], lo=0.0, lo_open=True)
    if measured is not None:
        return measured
    if material is not None:
        raise SceneError(f"{path}.stiffness: missing (material {material!r} has no measured {lacks}; give the "
                         f"sheet's {need})")
    raise SceneError(f"{path}.stiffness: missing (the sheet's {need}; no material preset supplies it)")


def _bending(d: Any, material: str | None, where: str = "cloth") -> dict[str, Any]:
    """``[cloth.bending]``: ``model = "springs"`` (the bend springs, ``[cloth.springs.bend]``) or ``"dihedral"``
    with the bending modulus ``stiffness`` (N m, > 0; or the material's measured one,
    :attr:`Material.bending <implicit_cloth.materials.Material.bending>`), ``damping`` (N m s, >= 0, default 0)
    and ``rest_angle`` ("mesh": the rest mesh's, the default; "flat")."""
    path = f"{where}.bending"
    check_keys(path, d, BENDING_KEYS)
    model = choice(f"{path}.model", d["model"], BENDING_MODELS) if "model" in d else "springs"
    if model == "springs":
        for key in ("stiffness", "damping", "rest_angle"):
            if key in d:
                raise SceneError(f"{path}.{key}: not used with {path}.model = 'springs' (the bend springs take "
                                 f"theirs from {where}.springs.bend, in N/m and N*s/m), got {d[key]!r}")
        return {"model": "springs"}
    preset = MATERIALS[material].bending if material is not None else None
    k = _stiffness(path, d, preset, material, "bending modulus", "bending modulus in N m")
    kd = number(f"{path}.damping", d["damping"], lo=0.0) if "damping" in d else 0.0
    rest = choice(f"{path}.rest_angle", d["rest_angle"], REST_ANGLES) if "rest_angle" in d else "mesh"
    return {"model": "dihedral", "stiffness": k, "damping": kd, "rest_angle": rest}


def dihedral_bending(c: Mapping[str, Any]) -> bool:
    """Whether a normalised cloth piece bends by its hinges' dihedral angles (``[cloth.bending] model =
    "dihedral"``) instead of bend springs."""
    return c.get("bending", {}).get("model") == "dihedral"


def _cloth_mesh(d: Mapping[str, Any], base_dir: Path | None, where: str = "cloth") -> dict[str, Any]:
    """A mesh cloth's shape keys: the file, scale and translation."""
    for key in ("size", "resolution", "plane", "center"):
        if key in d:
            raise SceneError(f"{where}.{key}: not used with cloth.mesh (a mesh cloth takes scale and translation)")
    mesh = d["mesh"]
    if not isinstance(mesh, str) or not mesh:
        raise fail(f"{where}.mesh", "must be a path to a mesh file", mesh)
    path = Path(mesh)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return {"kind": "mesh", "mesh": str(path),
            "scale": number(f"{where}.scale", d.get("scale", 1.0), lo=0.0, lo_open=True),
            "translation": vector(f"{where}.translation", d.get("translation", [0.0, 0.0, 0.0]), 3)}


def _cloth_grid(d: Mapping[str, Any], where: str = "cloth") -> dict[str, Any]:
    """A grid cloth's shape keys: size, resolution, center and plane."""
    for key in ("scale", "translation"):
        if key in d:
            raise SceneError(f"{where}.{key}: only used with cloth.mesh (a grid cloth takes size and center)")
    out: dict[str, Any] = {"kind": "grid"}
    out["size"] = vector(f"{where}.size", d.get("size", [1.0, 1.0]), 2, positive=True)
    res = d.get("resolution", [32, 32])
    if not is_list(res) or len(res) != 2:
        raise fail(f"{where}.resolution", "must be a list of 2 integers >= 2", res)
    out["resolution"] = [integer(f"{where}.resolution[{k}]", r, lo=2) for k, r in enumerate(res)]
    if out["resolution"][0] * out["resolution"][1] > MAX_VERTICES:
        raise fail(f"{where}.resolution", f"must give at most {MAX_VERTICES} vertices (4096 x 4096), "
                   f"nx * ny = {out['resolution'][0] * out['resolution'][1]}", res)
    out["center"] = vector(f"{where}.center", d.get("center", [0.0, 0.0, 0.0]), 3)
    out["plane"] = choice(f"{where}.plane", d.get("plane", "xz"), PLANES)
    return out


def _cloth_mass(d: Mapping[str, Any], material: str | None, where: str = "cloth") -> dict[str, float]:
    """``cloth.mass`` or ``cloth.density`` (or the material's density)."""
    if "mass" in d and "density" in d:
        raise SceneError(f"{where}.density: give either cloth.mass or cloth.density, not both")
    if "mass" in d:
        return {"mass": number(f"{where}.mass", d["mass"], lo=0.0, lo_open=True)}
    if "density" in d:
        return {"density": number(f"{where}.density", d["density"], lo=0.0, lo_open=True)}
    if material is not None:
        return {"density": MATERIALS[material].density}
    raise SceneError(f"{where}.mass: missing (give cloth.mass in kg, cloth.density in kg/m^2, or a material)")


def _cloth(d: Any, base_dir: Path | None, where: str = "cloth") -> dict[str, Any]:
    check_keys(where, d, CLOTH_KEYS)
    out = _cloth_mesh(d, base_dir, where) if "mesh" in d else _cloth_grid(d, where)
    material = None
    if "material" in d:
        material = choice(f"{where}.material", d["material"], MATERIALS.keys())
    out["material"] = material
    out.update(_cloth_mass(d, material, where))
    out["velocity"] = vector(f"{where}.velocity", d.get("velocity", [0.0, 0.0, 0.0]), 3)
    out["pins"] = _pins(d.get("pins", []), _grid_vertices(out), where)
    if "springs" in d and d["springs"] is None:
        raise fail(f"{where}.springs", "must be a table", None)
    out["springs"] = _springs(d.get("springs"), material, where)
    if "membrane" in d:    # in the normalised table only when given: a scene without it is unchanged
        if d["membrane"] is None:
            raise fail(f"{where}.membrane", "must be a table", None)
        out["membrane"] = _membrane(d["membrane"], material, where)
        for kind in MEMBRANE_REPLACES:
            if isinstance(d.get("springs"), Mapping) and kind in d["springs"]:
                raise SceneError(f"{where}.springs.{kind}: not used with {where}.membrane (the membrane replaces "
                                 f"the structural and shear springs; bend springs stay)")
            out["springs"].pop(kind, None)
    if "bending" in d:     # likewise: only when given
        if d["bending"] is None:
            raise fail(f"{where}.bending", "must be a table", None)
        out["bending"] = _bending(d["bending"], material, where)
        if out["bending"]["model"] == "dihedral":
            if isinstance(d.get("springs"), Mapping) and "bend" in d["springs"]:
                raise SceneError(f"{where}.springs.bend: not used with {where}.bending.model = 'dihedral' (the "
                                 f"dihedral bending replaces the bend springs)")
            out["springs"].pop("bend", None)
    return out


def _cloths(d: Any, base_dir: Path | None) -> dict[str, Any] | list[dict[str, Any]]:
    """``[cloth]`` (one table) or ``[[cloth]]`` (several pieces, each checked as ``cloth[k]``)."""
    if not is_list(d):
        return _cloth(d, base_dir)
    if not len(d):
        raise fail("cloth", "must be a table or a non-empty array of tables ([[cloth]])", d)
    pieces = [_cloth(c, base_dir, f"cloth[{k}]") for k, c in enumerate(d)]
    total = sum(r[0] * r[1] for r in (c.get("resolution") for c in pieces) if r is not None)
    if total > MAX_VERTICES:
        raise fail("cloth", f"the pieces' grids must give at most {MAX_VERTICES} vertices in all (4096 x 4096), "
                   f"got {total}", [c.get("resolution") for c in pieces])
    return pieces


def cloth_pieces(data: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The normalised scene's cloth pieces in order: ``[cloth]`` is one piece, ``[[cloth]]`` several."""
    c = data["cloth"]
    return list(c) if isinstance(c, list) else [c]


def piece_path(data: Mapping[str, Any], k: int) -> str:
    """How errors name piece ``k``: ``cloth`` for a single ``[cloth]`` table, ``cloth[k]`` for ``[[cloth]]``."""
    return f"cloth[{k}]" if isinstance(data["cloth"], list) else "cloth"


def _effects(d: Any) -> dict[str, Any]:
    """``[effects]``: each entry checked by the effect registered under its name (:data:`EFFECTS`)."""
    check_keys("effects", d, EFFECTS.names())
    out: dict[str, Any] = {}
    for name in EFFECTS.names():
        if name in d:
            entry = EFFECTS[name]
            out[name] = entry.load("validate")(f"effects.{name}", d[name])
            needs = entry.meta.get("requires")
            if needs and not any(k in out for k in entry.meta.get("requires_any", (needs[0],))):
                raise SceneError(f"effects.{needs[0]}", f"missing ({needs[1]})")
    return out


def _collision(d: Any) -> dict[str, Any]:
    check_keys("collision", d, COLLISION_KEYS)
    out = dict(COLLISION_DEFAULTS)
    if "method" in d:    # in the normalised table only when given, so a scene without it is unchanged
        out["method"] = choice("collision.method", d["method"], COLLISION_METHODS)
    if "thickness" in d:
        out["thickness"] = number("collision.thickness", d["thickness"], lo=0.0, lo_open=True)
    if "restitution" in d:
        out["restitution"] = number("collision.restitution", d["restitution"], lo=0.0, hi=1.0)
    if "max_iterations" in d:
        out["max_iterations"] = integer("collision.max_iterations", d["max_iterations"], lo=1, hi=1000)
    if "newton_iterations" in d:
        out["newton_iterations"] = integer("collision.newton_iterations", d["newton_iterations"], lo=1, hi=100)
    # friction: smoothed and solved within each step unless the scene says otherwise (the defaults are
    # collision.context.FRICTION_SPEED and FRICTION_NEWTON); the keys are in the normalised table only when
    # given, so a scene without them is unchanged. friction_speed = 0: Coulomb's sticking and sliding states.
    if "friction_speed" in d:
        out["friction_speed"] = number("collision.friction_speed", d["friction_speed"], lo=0.0)
    if "friction_newton" in d:
        iters = integer("collision.friction_newton", d["friction_newton"], lo=0, hi=100)
        if iters > 0 and out.get("friction_speed") == 0:
            raise SceneError(f"collision.friction_newton: {iters} Newton iterations of smoothed friction, but "
                             "collision.friction_speed is 0 (Coulomb's sticking and sliding states, which have "
                             "no smoothed friction to solve); give a sliding speed > 0 or leave friction_newton out")
        out["friction_newton"] = iters
    if "friction_pause" in d:   # opt-in speed: in the normalised table only when given
        pause = integer("collision.friction_pause", d["friction_pause"], lo=0, hi=1000)
        if pause > 0 and (out.get("friction_newton") == 0 or out.get("friction_speed") == 0):
            raise SceneError(f"collision.friction_pause: {pause} steps without the friction's Newton iterations, "
                             "but the scene's friction is not solved within the step (friction_newton or "
                             "friction_speed is 0): nothing to pause; leave friction_pause out")
        out["friction_pause"] = pause
    # self-collision's keys appear in the normalised table only when it is on (a scene without it is unchanged)
    if boolean("collision.self_collision", d.get("self_collision", False)):
        out["self_collision"] = True
        out["self_friction"] = number("collision.self_friction", d.get("self_friction", SELF_FRICTION), lo=0.0)
    elif "self_friction" in d:
        raise SceneError("collision.self_friction: given, but collision.self_collision is not true")
    return out


def self_collision(data: Mapping[str, Any]) -> bool:
    """Whether the normalised scene asks for self-collision (``[collision] self_collision = true``)."""
    return bool((data.get("collision") or {}).get("self_collision", False))


def is_normalised(data: Any) -> bool:
    """Whether ``data`` is a normalised scene (:attr:`Scene.data`, e.g. a ``report.json``'s ``"scene"``)."""
    if not isinstance(data, Mapping):
        return False
    c = data.get("cloth")
    first = c[0] if isinstance(c, list) and c else c
    return isinstance(first, Mapping) and "kind" in first


def _pins_source(groups: list[Any]) -> list[Any]:
    """Normalised pin groups back to the ``cloth.pins`` list they came from (their ``paths`` say where)."""
    items: dict[int, Any] = {}
    for g in groups:
        if not isinstance(g, Mapping):
            return groups
        paths = [_PIN_PATH.match(p) for p in g.get("paths", [])]
        if not paths or not all(paths) or len(paths) != len(g.get("vertices", ())):
            return [{k: v for k, v in h.items() if k != "paths"} for h in groups]
        for m, v in zip(paths, g["vertices"]):
            assert m is not None   # checked above
            if m.group(2) is None:       # a loose entry: cloth.pins[k]
                items[int(m.group(1))] = v
            else:                        # a table: cloth.pins[k].vertices[j]
                table = {"vertices": [], "velocity": g["velocity"],
                         **{k: g[k] for k in ("keyframes", "stiffness", "damping") if k in g}}
                if "keyframes" in g:
                    del table["velocity"]
                items.setdefault(int(m.group(1)), table)["vertices"].append(v)
    return [items[k] for k in sorted(items)]


_PIN_PATH = re.compile(r"^cloth(?:\[\d+\])?\.pins\[(\d+)\](\.vertices\[\d+\])?$")


def source_of(data: Mapping[str, Any]) -> dict[str, Any]:
    """A scene as given (a :class:`Scene` source) that normalises back to the normalised scene ``data``.

    What normalisation adds is taken out again: ``cloth.kind``, an empty material, the pins' source
    paths, the table of the collision stage of a scene without obstacles, and an obstacle's place and
    motion when its keyframes give them. Everything else is already valid scene input, so that
    ``Scene(source_of(s.data)).data == s.data`` and the run it describes is the same, bit for bit.
    """
    raw = copy.deepcopy(dict(data))
    cloth = raw.get("cloth")
    for c in cloth if isinstance(cloth, list) else [cloth]:
        if not isinstance(c, dict):
            continue
        kind = c.pop("kind", None)
        if kind not in ("grid", "mesh"):
            raise fail("cloth.kind", "must be grid or mesh (a normalised scene's kind of cloth)", kind)
        if c.get("material", "") is None:
            del c["material"]
        if isinstance(c.get("pins"), list):
            c["pins"] = _pins_source(c["pins"])
    if raw.get("collision", "") is None:
        del raw["collision"]
    for o in raw.get("obstacles") or []:
        if isinstance(o, dict) and "keyframes" in o:
            place = OBSTACLE_SHAPES[o["shape"]].meta["place"] if o.get("shape") in OBSTACLE_SHAPES else "center"
            for key in ("velocity", "angular_velocity", place):
                o.pop(key, None)
    return raw


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
        if is_normalised(data):   # a scene written by a run (report.json["scene"]) loads back as it ran
            data = source_of(data)
        self.source: dict[str, Any] = copy.deepcopy(dict(data)) if isinstance(data, Mapping) else data
        self.data = self._validate(data)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None = None) -> "Scene":
        """Validate a scene given as a nested dict with the same keys as the TOML file."""
        return cls(data, base_dir=base_dir)

    def _validate(self, data: Any) -> dict[str, Any]:
        check_keys("", data, TOP_KEYS)
        if "cloth" not in data:
            raise SceneError("cloth: missing (a scene needs a [cloth] table)")
        out: dict[str, Any] = {
            "simulation": _simulation(data.get("simulation", {})),
            "solver": _solver(data.get("solver", {})),
            "cloth": _cloths(data["cloth"], self.base_dir),
            "effects": _effects(data.get("effects", {})),
            "obstacles": validate_obstacles(data.get("obstacles", []), self.base_dir),
        }
        collision = _collision(data.get("collision", {})) if "collision" in data or out["obstacles"] else None
        limits = collision is not None and collision.get("method") == "barrier" and "strain_limit" in out["simulation"]
        if collision is not None and not out["obstacles"] and not collision.get("self_collision") and not limits:
            raise SceneError("collision: given, but the scene has no [[obstacles]] to collide with (and "
                             "collision.self_collision is not true, nor a barrier method for "
                             "simulation.strain_limit)")
        out["collision"] = collision
        return out

    def replace(self, **sections: Mapping[str, Any]) -> "Scene":
        """A new scene with some keys of some tables overridden, e.g. ``replace(simulation={"dt": 0.02})``."""
        raw = copy.deepcopy(self.source)
        for name, updates in sections.items():
            if not isinstance(updates, Mapping):
                raise fail(name, "overrides must be a table (a dict of keys to replace)", updates)
            table = raw.get(name, {})
            raw[name] = {**(table if isinstance(table, Mapping) else {}), **updates}
        return Scene(raw, base_dir=self.base_dir)

    @property
    def effects(self) -> list[str]:
        """The names of the effects this scene declares, in evaluation order."""
        names = [k for k in EFFECTS.names() if k in self.data["effects"]]
        names += [k for k in SPRING_KINDS if any(k in c["springs"] for c in cloth_pieces(self.data))]
        if any("membrane" in c for c in cloth_pieces(self.data)):
            names.append("membrane")
        if any(dihedral_bending(c) for c in cloth_pieces(self.data)):
            names.append("bending")
        if self.data["obstacles"]:
            names.append("collision")
        if self_collision(self.data):
            names.append("self_collision")
        return names

    def __repr__(self) -> str:
        what = ", ".join(f"grid {c['resolution'][0]}x{c['resolution'][1]}" if c["kind"] == "grid"
                         else f"mesh {c['mesh']}" for c in cloth_pieces(self.data))
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
