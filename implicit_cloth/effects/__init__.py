"""Force effects. Each lives in its own module, imported only when a scene declares it.

Every effect is a :class:`~implicit_cloth.forces.Force` (energy, gradient, dissipation, force, power and the
Hessian blocks on the fixed pattern; see :mod:`implicit_cloth.forces`), so integrators, the assembly and the
report know nothing about what the force is.

A new entry of the ``[effects]`` table is one module with ``validate(path, value)``
and ``build(model, value, effects)`` (``effects``: the whole validated table) plus
its registration below; :func:`build_effects` builds the declared ones in
registration order.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from ..config.registry import EFFECTS
from ..forces import Force

# The [effects] table, in evaluation order. Each entry's module checks its own value (``validate(path,
# value)``), builds its force term (``build``, when ``builds``) and is imported only when a scene declares
# it; ``requires`` names the entry it acts through and why, ``requires_any`` the entries any one of which will
# do (wind has no force of its own: drag or the aerodynamics act relative to it, and build it).
EFFECTS.register("gravity", module="implicit_cloth.effects.gravity", builds=True)
EFFECTS.register("drag", module="implicit_cloth.effects.drag", builds=True)
EFFECTS.register("aerodynamics", module="implicit_cloth.effects.aerodynamics", builds=True)
EFFECTS.register("wind", module="implicit_cloth.effects.wind", builds=False, requires=(
    "drag", "wind acts through air drag; set effects.drag, the drag coefficient in N*s/m^3, or "
            "effects.aerodynamics, for effects.wind to have an effect"), requires_any=("drag", "aerodynamics"))
#: the springs come from the [cloth.springs] tables, not [effects]; built after the [effects] entries
SPRINGS_MODULE = "implicit_cloth.effects.springs"


#: an effect is a :class:`~implicit_cloth.forces.Force` (energy, gradient, dissipation, Hessian blocks)
Effect = Force


class SpringSet(Effect, Protocol):
    """An elastic effect made of springs (``elastic``): its pairs ``i``, ``j``, constants ``k`` (N/m), rest
    lengths ``L0`` (m), rows per kind, and its lengths and strains, for the run's strain measures."""

    i: np.ndarray
    j: np.ndarray
    k: np.ndarray
    L0: np.ndarray
    kinds: dict[str, slice]

    def lengths(self, x: np.ndarray) -> np.ndarray: ...

    def strain(self, x: np.ndarray) -> np.ndarray: ...


def build_effects(model: Any, effects: dict[str, Any], springs: dict[str, Any]) -> list[Effect]:
    """Instantiate only the declared effects (importing only their modules), in evaluation order."""
    out: list[Effect] = []
    for name in EFFECTS.names():
        entry = EFFECTS[name]
        if name in effects and entry.meta.get("builds"):
            out.append(entry.load("build")(model, effects[name], effects))
    if springs:
        from .springs import build

        out.append(build(model, springs))
    return out
