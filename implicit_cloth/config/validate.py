"""Checks of input values, each naming the dotted path of the key and the value on failure.

Every check returns the normalised value (a plain float, int, list or str) or
raises :class:`~implicit_cloth.errors.SceneError` (an
:class:`~implicit_cloth.errors.InputError`) reading ``"{path}: {what}, got {value}"``.
Numbers may be Python or NumPy scalars (``bool`` is never a number) and lists may
be lists, tuples or 1-D NumPy arrays. Scenes, sweeps and the command line share
these checks.
"""

from __future__ import annotations

import difflib
import math
import numbers
import re
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..errors import SceneError, show

__all__ = ["boolean", "check_keys", "choice", "direction", "fail", "fmt", "integer", "is_list", "is_number",
           "number", "vector"]

#: The value as it was given, shortened to one line (see :func:`implicit_cloth.errors.show`).
fmt = show


def is_number(value: Any) -> bool:
    """A real number (Python or NumPy scalar), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def is_list(value: Any) -> bool:
    """A list, a tuple or a 1-D NumPy array."""
    return isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim == 1)


def fail(path: str, what: str, value: Any) -> SceneError:
    """The error for ``value`` at ``path`` (to be raised): ``"{path}: {what}, got {value}"``."""
    return SceneError(path, what, value)


def check_keys(path: str, table: Any, allowed: Iterable[str]) -> Mapping[str, Any]:
    """``table`` itself if it is a mapping whose keys are all ``allowed`` (an unknown one gets a "did you mean")."""
    if not isinstance(table, Mapping):
        raise fail(path or "scene", "must be a table", table)
    allowed = tuple(allowed)
    for key in table:
        if key not in allowed:
            where = f"{path}.{key}" if path else str(key)
            near = difflib.get_close_matches(str(key), allowed, n=1, cutoff=0.6)
            hint = f" (did you mean '{near[0]}'?)" if near else f" (allowed: {', '.join(allowed)})"
            raise SceneError(where, f"unknown key{hint}")
    return table


def number(path: str, value: Any, *, lo: float | None = None, lo_open: bool = False,
           hi: float | None = None) -> float:
    """A finite number, optionally ``>= lo`` (``> lo`` with ``lo_open``) and ``<= hi``, as a float."""
    ok = is_number(value)
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
        raise fail(path, f"must be a finite number{rng}", value)
    return x


def integer(path: str, value: Any, *, lo: int, hi: int | None = None) -> int:
    """An integer (not a bool) in ``lo .. hi``."""
    ok = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
    ok = ok and int(value) >= lo and (hi is None or int(value) <= hi)
    if not ok:
        raise fail(path, f"must be an integer >= {lo}" + (f" and <= {hi}" if hi is not None else ""), value)
    return int(value)


def vector(path: str, value: Any, n: int, *, positive: bool = False) -> list[float]:
    """A list of ``n`` finite numbers (each ``> 0`` with ``positive``)."""
    if not is_list(value) or len(value) != n:
        raise fail(path, f"must be a list of {n} numbers", value)
    return [number(f"{path}[{k}]", x, lo=0.0 if positive else None, lo_open=positive)
            for k, x in enumerate(value)]


def direction(path: str, value: Any) -> list[float]:
    """A non-zero 3-vector."""
    vec = vector(path, value, 3)
    if not math.hypot(*vec) > 0:
        raise fail(path, "must be a non-zero direction", value)
    return vec


def boolean(path: str, value: Any) -> bool:
    """``true`` or ``false`` (Python or NumPy bool)."""
    if not isinstance(value, (bool, np.bool_)):
        raise fail(path, "must be true or false", value)
    return bool(value)


def _normal(name: str) -> str:
    """A name spelled as the choices are: lower case, words joined by ``_`` (``Implicit-Euler``: ``implicit_euler``)."""
    return re.sub(r"[\s\-]+", "_", name.strip().lower())


def suggestion(value: str, choices: Sequence[str], aliases: Mapping[str, str] | None = None) -> str | None:
    """The choice a near miss ``value`` most likely means: its spelling normalised (:func:`_normal`), then another
    name of a choice (``aliases``: ``implicit_euler`` -> ``backward_euler``), then the closest spelling; None."""
    norm = _normal(value)
    if norm in choices:
        return norm
    if aliases and norm in aliases:
        return aliases[norm]
    near = difflib.get_close_matches(norm, choices, n=1, cutoff=0.6)
    return near[0] if near else None


def choice(path: str, value: Any, choices: Iterable[str], aliases: Mapping[str, str] | None = None) -> str:
    """One of ``choices`` (a near miss gets a "did you mean": :func:`suggestion`, ``aliases`` mapping other
    names of a choice to it)."""
    choices = tuple(choices)
    if not isinstance(value, str) or value not in choices:
        near = suggestion(value, choices, aliases) if isinstance(value, str) else None
        hint = f" (did you mean '{near}'?)" if near else ""
        raise fail(path, f"must be one of {', '.join(choices)}{hint}", value)
    return value
