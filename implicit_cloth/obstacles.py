"""The ``[[obstacles]]`` table: every rigid obstacle shape registers its keys and its check here.

A shape is one :data:`~implicit_cloth.config.registry.OBSTACLE_SHAPES` entry: the
keys it takes besides the common ones (:data:`COMMON_KEYS`), the key that places
it (a keyframe's ``center`` stands for it) and a function that checks its own keys
and returns them normalised. :func:`validate_obstacles` checks the whole array;
the collision code (:func:`implicit_cloth.collision.shapes.build`) builds the shapes
from the normalised tables, and :mod:`implicit_cloth.render` draws them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping

from .config.registry import OBSTACLE_SHAPES
from .config.validate import check_keys, direction, fail, is_list, number, vector
from .errors import SceneError
from .geometry import load_obstacle_mesh

__all__ = ["COMMON_KEYS", "KEYFRAME_KEYS", "validate_keyframes", "validate_obstacles"]

#: Keys every obstacle takes, whatever its shape.
COMMON_KEYS: tuple[str, ...] = ("shape", "velocity", "angular_velocity", "keyframes", "friction")
#: Keys of one obstacle keyframe.
KEYFRAME_KEYS: tuple[str, ...] = ("time", "center", "rotation")
ZERO = [0.0, 0.0, 0.0]

Check = Callable[[str, Mapping[str, Any], "Path | None"], dict[str, Any]]


def _lengths(path: str, d: Mapping[str, Any], shape: str, keys: tuple[str, ...]) -> dict[str, Any]:
    out = {}
    for key in keys:
        if key not in d:
            raise SceneError(f"{path}.{key}", f"missing (a {shape} needs its {key} in m)")
        out[key] = number(f"{path}.{key}", d[key], lo=0.0, lo_open=True)
    return out


def _sphere(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    return {**_lengths(path, d, "sphere", ("radius",)), "center": vector(f"{path}.center", d.get("center", ZERO), 3)}


def _box(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    if "size" not in d:
        raise SceneError(f"{path}.size", "missing (a box needs its full extents [x, y, z] in m)")
    return {"size": vector(f"{path}.size", d["size"], 3, positive=True),
            "rotation": vector(f"{path}.rotation", d.get("rotation", ZERO), 3),
            "center": vector(f"{path}.center", d.get("center", ZERO), 3)}


def _round(shape: str) -> Check:
    """A cone or a capsule: radius, height, center and axis."""
    def check(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
        return {**_lengths(path, d, shape, ("radius", "height")),
                "center": vector(f"{path}.center", d.get("center", ZERO), 3),
                "axis": direction(f"{path}.axis", d.get("axis", [0.0, 0.0, 1.0]))}
    return check


def _plane(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    return {"point": vector(f"{path}.point", d.get("point", ZERO), 3),
            "normal": direction(f"{path}.normal", d.get("normal", [0.0, 0.0, 1.0]))}


def _mesh(path: str, d: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    """A mesh obstacle's file (read with trimesh, so that a bad file is refused here), scale, translation, rotation."""
    if "path" not in d:
        raise SceneError(f"{path}.path", "missing (a mesh obstacle needs the path of a mesh file)")
    f = d["path"]
    if not isinstance(f, str) or not f:
        raise fail(f"{path}.path", "must be a path to a mesh file", f)
    p = Path(f)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    if not p.is_file():
        raise fail(f"{path}.path", "file not found", f)
    load_obstacle_mesh(str(p), f"{path}.path", f)
    return {
        "path": str(p),
        "scale": number(f"{path}.scale", d.get("scale", 1.0), lo=0.0, lo_open=True),
        "translation": vector(f"{path}.translation", d.get("translation", ZERO), 3),
        "rotation": vector(f"{path}.rotation", d.get("rotation", ZERO), 3),
    }


OBSTACLE_SHAPES.register("sphere", keys=("radius", "center"), required=("radius",), check=_sphere, place="center")
OBSTACLE_SHAPES.register("box", keys=("size", "center", "rotation"), required=("size",), check=_box, place="center")
OBSTACLE_SHAPES.register("cone", keys=("radius", "height", "center", "axis"), required=("radius", "height"),
                         check=_round("cone"), place="center")
OBSTACLE_SHAPES.register("capsule", keys=("radius", "height", "center", "axis"), required=("radius", "height"),
                         check=_round("capsule"), place="center")
OBSTACLE_SHAPES.register("plane", keys=("point", "normal"), check=_plane, place="point")
OBSTACLE_SHAPES.register("mesh", keys=("path", "scale", "translation", "rotation"), required=("path",),
                         check=_mesh, place="translation")


def validate_keyframes(path: str, value: Any) -> list[dict[str, Any]]:
    """An obstacle's ``keyframes``: at least two tables ``{time, center, rotation}``, times strictly increasing.

    ``time`` in s (>= 0), ``center`` in m, ``rotation`` a rotation vector in rad (default [0, 0, 0]) on top of
    the shape's own orientation.
    """
    if not is_list(value) or len(value) < 2:
        raise fail(path, "must be a list of at least 2 keys ({time = s, center = [x, y, z]})", value)
    keys: list[dict[str, Any]] = []
    for k, key in enumerate(value):
        kp = f"{path}[{k}]"
        check_keys(kp, key, KEYFRAME_KEYS)
        for name, what in (("time", "its time in s"), ("center", "its center [x, y, z] in m")):
            if name not in key:
                raise SceneError(f"{kp}.{name}", f"missing (each key needs {what})")
        t = number(f"{kp}.time", key["time"], lo=0.0)
        if keys and not t > keys[-1]["time"]:
            raise fail(f"{kp}.time", f"must be greater than the previous key's time {keys[-1]['time']:g}",
                       key["time"])
        keys.append({"time": t, "center": vector(f"{kp}.center", key["center"], 3),
                     "rotation": vector(f"{kp}.rotation", key.get("rotation", ZERO), 3)})
    return keys


def validate_obstacle(path: str, d: Any, base_dir: Path | None = None) -> dict[str, Any]:
    """One ``[[obstacles]]`` table, normalised: its shape's keys, then the motion (or keyframes) and friction."""
    shapes = OBSTACLE_SHAPES.names()
    if not isinstance(d, Mapping):
        raise fail(path, "must be a table", d)
    if "shape" not in d:
        raise SceneError(f"{path}.shape", f"missing (one of {', '.join(shapes)})")
    shape = OBSTACLE_SHAPES.choice(f"{path}.shape", d["shape"])
    entry = OBSTACLE_SHAPES[shape]
    check_keys(path, d, COMMON_KEYS + entry.keys)
    o: dict[str, Any] = {"shape": shape, **entry.meta["check"](path, d, base_dir)}
    if "keyframes" in d:
        place = entry.meta["place"]
        for key in ("velocity", "angular_velocity", place):
            if key in d:
                raise fail(f"{path}.{key}", "cannot be combined with keyframes (the keys give the "
                           "obstacle's position and motion)", d[key])
        o["keyframes"] = validate_keyframes(f"{path}.keyframes", d["keyframes"])
        o[place] = list(o["keyframes"][0]["center"])
    o["velocity"] = vector(f"{path}.velocity", d.get("velocity", ZERO), 3)
    o["angular_velocity"] = vector(f"{path}.angular_velocity", d.get("angular_velocity", ZERO), 3)
    o["friction"] = number(f"{path}.friction", d.get("friction", 0.0), lo=0.0)
    return o


def validate_obstacles(value: Any, base_dir: Path | None = None) -> list[dict[str, Any]]:
    """The ``[[obstacles]]`` array: one normalised table per rigid obstacle."""
    if not is_list(value):
        raise fail("obstacles", "must be an array of tables ([[obstacles]])", value)
    return [validate_obstacle(f"obstacles[{k}]", d, base_dir) for k, d in enumerate(value)]
