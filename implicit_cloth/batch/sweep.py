"""Sweep files: a base scene, fixed overrides and the keys to vary, expanded into validated cases.

See :mod:`implicit_cloth.batch` for the file format. A bad key or value is a
:class:`~implicit_cloth.errors.SceneError` naming its place in the sweep file, re-worded
from the scene error's fields (path, message, value).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from ..config.validate import check_keys, fail, fmt
from ..errors import SceneError
from ..scene import Scene, load_scene, tomllib

#: Most cases a sweep may expand to.
MAX_CASES = 1_000_000
_SEGMENT = re.compile(r"^([^\[\]]+)((?:\[\d+\])*)$")


@dataclass
class Case:
    """One case of a sweep.

    Attributes
    ----------
    case_id : str
        Stable id: the first 12 hex digits of the SHA-256 of the case's
        normalised scene as canonical JSON.
    params : dict
        The swept keys' values for this case (dotted path -> value as given;
        a key an explicit case leaves out shows the base scene's value).
    raw : dict
        The case's scene as given (base scene with the overrides applied).
    base_dir : str or None
        Directory that relative paths in the scene are resolved against.
    """

    case_id: str
    params: dict[str, Any]
    raw: dict[str, Any]
    base_dir: str | None


@dataclass
class Sweep:
    """A parsed and validated sweep: the swept keys (summary columns) and the cases in order."""

    path: str
    base: str
    keys: list[str]
    cases: list[Case] = field(default_factory=list)


def _segments(path: str) -> list[str | int]:
    """``"obstacles[0].radius"`` -> ``["obstacles", 0, "radius"]``; ValueError if malformed."""
    out: list[str | int] = []
    for part in path.split("."):
        m = _SEGMENT.match(part)
        if not m:
            raise ValueError(part)
        out.append(m.group(1))
        out.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return out


def _set_path(raw: dict[str, Any], path: str, value: Any) -> None:
    """Set ``raw[a][b]...[z] = value`` for the dotted ``path``, creating missing tables."""
    segs = _segments(path)
    node: Any = raw
    for k, seg in enumerate(segs[:-1]):
        nxt = segs[k + 1]
        if isinstance(seg, int):
            if not isinstance(node, list) or seg >= len(node):
                raise KeyError(seg)
            node = node[seg]
            continue
        if not isinstance(node, dict):
            raise KeyError(seg)
        if seg not in node:
            if isinstance(nxt, int):
                raise KeyError(seg)
            node[seg] = {}
        node = node[seg]
    last = segs[-1]
    if isinstance(last, int):
        if not isinstance(node, list) or last >= len(node):
            raise KeyError(last)
    elif not isinstance(node, dict):
        raise KeyError(last)
    node[last] = copy.deepcopy(value)


def get_path(data: Any, path: str, default: Any = None) -> Any:
    """The value at dotted ``path`` in nested dicts/lists, or ``default``."""
    try:
        node = data
        for seg in _segments(path):
            node = node[seg]
        return node
    except (KeyError, IndexError, TypeError, ValueError):
        return default


def case_id(scene: Scene) -> str:
    """Stable id of a case: SHA-256 (12 hex digits) of its normalised scene as canonical JSON."""
    text = json.dumps(scene.data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]


def _key_only(where: str) -> str:
    """``sweep.k[2]`` -> ``sweep.k``: for an error about the key itself, not one of its values."""
    return re.sub(r"\[\d+\]$", "", where)


def _where_error(where: str, key: str, exc: SceneError) -> SceneError:
    """Re-word a scene error raised by overriding ``key`` so that it names its place in the sweep file.

    Read from the error's fields (``path``, ``message``, ``value``), never from its text.
    """
    if exc.message.startswith("unknown key") and (key == exc.path or key.startswith(exc.path + ".")):
        named = "" if exc.path == key else f" {exc.path!r}"
        return SceneError(_key_only(where), "unknown key" + named + exc.message[len("unknown key"):])
    if exc.path == key or exc.path.startswith((key + "[", key + ".")):
        return SceneError(where + exc.path[len(key):], exc.message, exc.value)
    return SceneError(where, f"makes the scene invalid ({exc})")


def _apply(base_raw: Mapping[str, Any], overrides: Mapping[str, Any], base_dir: Path | None,
           where: Callable[[str], str], label: str | None = None) -> Scene:
    """The base scene with ``overrides`` (dotted key -> value) applied and validated.

    An error about one of the overridden keys is reported at ``where(key)``;
    any other (values fine alone, not together) at ``label``.
    """
    raw = copy.deepcopy(dict(base_raw))
    for key, value in overrides.items():
        try:
            _set_path(raw, key, value)
        except (KeyError, ValueError):
            raise SceneError(f"{_key_only(where(key))}: not a path into the scene (it goes through a value that is "
                             f"not a table, or a list index out of range), got {fmt(key)}") from None
    try:
        return Scene(raw, base_dir=base_dir)
    except SceneError as exc:
        for key in overrides:          # name the override the error is about, if it is one
            if (exc.path == key or exc.path.startswith((key + "[", key + "."))
                    or (key.startswith(exc.path + ".") and exc.message.startswith("unknown key"))):
                raise _where_error(where(key), key, exc) from None
        if label is None:
            label = where(next(iter(overrides))) if overrides else "base"
        raise SceneError(f"{label}: makes the scene invalid ({exc})") from None


def load_sweep(path: str | os.PathLike[str]) -> Sweep:
    """Read and validate a sweep file; expand it into its cases.

    Raises
    ------
    SceneError
        With a one-line message naming the sweep file's key and the bad value,
        e.g. ``sweep.simulation.dt[2]: must be a finite number > 0, got -1``,
        ``sweep.simulation.dtt: unknown key (did you mean 'dt'?)``,
        ``sweep.simulation.dt: must be a non-empty list of values, got []``,
        ``base: scene file not found, got 'nope.toml'``.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise SceneError(f"{p}: cannot read sweep file ({exc.strerror or exc})") from None
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SceneError(f"{p}: not a valid TOML file ({exc})") from None
    return sweep_from_dict(data, base_dir=p.parent, path=str(p))


def _base_scene(data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None) -> tuple[Path, Scene]:
    """The sweep's ``base`` key: the path of the base scene file and the scene, validated."""
    if "base" not in data:
        raise SceneError("base: missing (a sweep file names its base scene: base = \"scene.toml\")")
    base = data["base"]
    if not isinstance(base, str) or not base:
        raise fail("base", "must be the path of a scene file", base)
    base_path = Path(base)
    if not base_path.is_absolute() and base_dir is not None:
        base_path = Path(base_dir) / base_path
    if not base_path.is_file():
        raise fail("base", f"scene file not found ({base_path})", base)
    try:
        base_scene = load_scene(base_path)
    except SceneError as exc:
        raise fail("base", f"the base scene is invalid ({exc})", base) from None
    return base_path, base_scene


def _explicit_cases(value: Any) -> list[dict[str, Any]]:
    """The ``[[cases]]`` array, each table flattened to dotted keys."""
    if not isinstance(value, list) or not all(isinstance(c, Mapping) for c in value):
        raise fail("cases", "must be a list of tables ([[cases]] with dotted keys)", value)
    return [_flat(f"cases[{n}]", c) for n, c in enumerate(value)]


def sweep_from_dict(data: Mapping[str, Any], base_dir: str | os.PathLike[str] | None = None,
                    path: str = "<dict>") -> Sweep:
    """Validate a sweep given as a dict with the keys of the sweep file (see :func:`load_sweep`)."""
    check_keys("", data, ("base", "set", "sweep", "cases"))
    base_path, base_scene = _base_scene(data, base_dir)
    base_raw = base_scene.source
    scene_dir = base_scene.base_dir

    fixed = _flat("set", data.get("set", {}))
    if fixed:
        base_scene = _apply(base_raw, fixed, scene_dir, lambda k: f"set.{k}")
        base_raw = base_scene.source

    sweep = _flat("sweep", data.get("sweep", {}))
    explicit = _explicit_cases(data.get("cases", []))
    if not sweep and not explicit:
        raise SceneError("sweep: missing (a sweep file needs a [sweep] table of keys and value lists, "
                         "or [[cases]])")

    keys = list(sweep)
    for key, values in sweep.items():
        if not isinstance(values, list) or not values:
            raise fail(f"sweep.{key}", "must be a non-empty list of values", values)
        for i, v in enumerate(values):            # each value alone: the clearest message
            _apply(base_raw, {key: v}, scene_dir, lambda k, i=i: f"sweep.{k}[{i}]")  # type: ignore[misc]
    for n, c in enumerate(explicit):
        if not c:
            raise fail(f"cases[{n}]", "must set at least one key", dict(c))
        keys += [k for k in c if k not in keys]

    n_product = math.prod(len(v) for v in sweep.values()) if sweep else 0
    if n_product + len(explicit) > MAX_CASES:
        raise fail("sweep", f"expands to {n_product + len(explicit)} cases, more than the limit of "
                    f"{MAX_CASES}", {k: len(v) for k, v in sweep.items()})

    result = Sweep(path=str(path), base=str(base_path), keys=keys)
    seen: dict[str, str] = {}

    def add(params: dict[str, Any], label: str, where: Callable[[str], str]) -> None:
        scene = _apply(base_raw, params, scene_dir, where, label)
        cid = case_id(scene)
        if cid in seen:
            raise SceneError(f"{label}: the same scene as {seen[cid]} (equal after normalisation), "
                             f"got {fmt(params)}")
        seen[cid] = label
        full = {k: params[k] if k in params else get_path(scene.data, k) for k in keys}
        result.cases.append(Case(cid, full, scene.source, str(scene_dir) if scene_dir is not None else None))

    if sweep:
        for combo in itertools.product(*sweep.values()):
            params = dict(zip(sweep, combo))
            label = "sweep (case " + ", ".join(f"{k} = {fmt(v)}" for k, v in params.items()) + ")"
            add(params, label, lambda k: f"sweep.{k}")
    for n, c in enumerate(explicit):
        add(dict(c), f"cases[{n}]", lambda k, n=n: f"cases[{n}].{k}")  # type: ignore[misc]
    return result


def _flat(path: str, table: Any) -> dict[str, Any]:
    """A table of dotted keys, with nested tables flattened into dotted keys.

    TOML reads an unquoted ``simulation.dt = [...]`` (or a ``[sweep.simulation]``
    table) as nested tables; both mean the same as the quoted ``"simulation.dt"``.
    """
    if not isinstance(table, Mapping):
        raise fail(path, "must be a table of dotted scene keys", table)
    out: dict[str, Any] = {}

    def walk(prefix: str, node: Mapping[str, Any]) -> None:
        for key, value in node.items():
            full = f"{prefix}.{key}" if prefix else str(key)
            try:
                _segments(full)
            except ValueError:
                raise fail(f"{path}.{full}", "not a dotted scene key (e.g. simulation.dt, obstacles[0].radius)",
                            full) from None
            if isinstance(value, Mapping) and value:
                walk(full, value)
            elif full in out:
                raise fail(f"{path}.{full}", "given twice (quoted and as a table)", value)
            else:
                out[full] = value

    walk("", table)
    return out
