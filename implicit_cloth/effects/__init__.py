"""Force effects. Each lives in its own module, imported only when a scene declares it.

Every effect offers the same small interface (after Bullet's deformable force
terms), so integrators and the assembly know nothing about what the force is:

``force(x, v, t, out)``
    Add the force, N, on every vertex to ``out`` (N, 3).
``potential(x)``
    Potential energy, J (0 for dissipative effects); ``conservative`` says which
    effects have one (the run report lists their energies), ``elastic`` which
    of those is energy the cloth stores (>= 0: the springs; gravity's only
    changes).
``power(x, v, t)``
    Power an outside source delivers to the cloth through the effect, W: the
    wind through the drag (0 for the others), for the energy balance of a step.
``pairs()``
    (P, 2) vertex pairs whose 3x3 Jacobian blocks couple (for the sparsity pattern).
``bind(system)``
    Precompute index maps into a :class:`~implicit_cloth.assembly.SystemMatrix`.
``linearize(x, v, t, c_x, c_v, w, system, kw, f)``
    Add ``-(c_v dF/dv + c_x dF/dx)`` to ``system.blocks``, ``(dF/dx) w`` to ``kw``
    and the force to ``f`` (so that an implicit step evaluates each effect once).

A new entry of the ``[effects]`` table is one module with ``validate(path, value)``
and ``build(model, value, effects)`` (``effects``: the whole validated table) plus
its registration below; :func:`build_effects` builds the declared ones in
registration order.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from ..config.registry import EFFECTS

# The [effects] table, in evaluation order. Each entry's module checks its own value (``validate(path,
# value)``), builds its force term (``build``, when ``builds``) and is imported only when a scene declares
# it; ``requires`` names the entry it acts through and why (wind has no force of its own: drag acts
# relative to it, and builds it).
EFFECTS.register("gravity", module="implicit_cloth.effects.gravity", builds=True)
EFFECTS.register("drag", module="implicit_cloth.effects.drag", builds=True)
EFFECTS.register("wind", module="implicit_cloth.effects.wind", builds=False, requires=(
    "drag", "wind acts through air drag; set effects.drag, the drag coefficient in N*s/m^3, for effects.wind "
            "to have an effect"))
#: the springs come from the [cloth.springs] tables, not [effects]; built after the [effects] entries
SPRINGS_MODULE = "implicit_cloth.effects.springs"


class Effect(Protocol):
    name: str
    #: whether :meth:`potential` is an energy the run reports (gravity, springs) or 0 (drag)
    conservative: bool
    #: whether that energy is stored in the cloth (>= 0; the springs), not a field's (gravity)
    elastic: bool

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None: ...

    def potential(self, x: np.ndarray) -> float: ...

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float: ...

    def pairs(self) -> np.ndarray: ...

    def bind(self, system: Any) -> None: ...

    def linearize(self, x: np.ndarray, v: np.ndarray, t: float, c_x: float, c_v: float,
                  w: np.ndarray | None, system: Any, kw: np.ndarray | None, f: np.ndarray) -> None: ...


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
