"""Force effects. Each lives in its own module, imported only when a scene declares it.

Every effect offers the same small interface (after Bullet's deformable force
terms), so integrators and the assembly know nothing about what the force is:

``force(x, v, t, out)``
    Add the force, N, on every vertex to ``out`` (N, 3).
``potential(x)``
    Potential energy, J (0 for dissipative effects).
``pairs()``
    (P, 2) vertex pairs whose 3x3 Jacobian blocks couple (for the sparsity pattern).
``bind(system)``
    Precompute index maps into a :class:`~implicit_cloth.assembly.SystemMatrix`.
``linearize(x, v, t, c_x, c_v, w, system, kw, f)``
    Add ``-(c_v dF/dv + c_x dF/dx)`` to ``system.blocks``, ``(dF/dx) w`` to ``kw``
    and the force to ``f`` (so that an implicit step evaluates each effect once).
"""

from __future__ import annotations

import importlib
from typing import Any, Protocol

import numpy as np

from ..config.registry import EFFECTS

# The [effects] table, in evaluation order. Each entry's module checks its own value (``validate(path,
# value)``) and is imported only when a scene declares it; ``requires`` names the entry it acts through
# and why (wind has no force of its own: drag acts relative to it).
EFFECTS.register("gravity", module="implicit_cloth.effects.gravity")
EFFECTS.register("drag", module="implicit_cloth.effects.drag")
EFFECTS.register("wind", module="implicit_cloth.effects.wind", requires=(
    "drag", "wind acts through air drag; set effects.drag, the drag coefficient in N*s/m^3, for effects.wind "
            "to have an effect"))

#: effect name -> (module, builder function); modules are imported on demand only.
_REGISTRY: dict[str, tuple[str, str]] = {
    "gravity": ("implicit_cloth.effects.gravity", "build"),
    "drag": ("implicit_cloth.effects.drag", "build"),
    "springs": ("implicit_cloth.effects.springs", "build"),
}


class Effect(Protocol):
    name: str

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None: ...

    def potential(self, x: np.ndarray) -> float: ...

    def pairs(self) -> np.ndarray: ...

    def bind(self, system: Any) -> None: ...

    def linearize(self, x: np.ndarray, v: np.ndarray, t: float, c_x: float, c_v: float,
                  w: np.ndarray | None, system: Any, kw: np.ndarray | None, f: np.ndarray) -> None: ...


def build_effects(model: Any, effects: dict[str, Any], springs: dict[str, Any]) -> list[Effect]:
    """Instantiate only the declared effects (importing only their modules)."""
    out: list[Effect] = []
    if "gravity" in effects:
        out.append(_load("gravity")(model, effects["gravity"]))
    if "drag" in effects:
        out.append(_load("drag")(model, effects["drag"], effects.get("wind")))
    if springs:
        out.append(_load("springs")(model, springs))
    return out


def _load(name: str):
    module, fn = _REGISTRY[name]
    return getattr(importlib.import_module(module), fn)
