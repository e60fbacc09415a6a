"""Time integrators, all on the same force model. See :data:`INTEGRATOR_CLASSES`."""

from __future__ import annotations

from typing import Any

from ..config.registry import INTEGRATORS as REGISTRY
from .backward_euler import BackwardEuler
from .base import ImplicitIntegrator, Integrator, StepInfo
from .bdf2 import BDF2
from .forward_euler import ForwardEuler
from .rk4 import RK4
from .symplectic_euler import SymplecticEuler
from .verlet import Verlet

#: integrator name -> class
INTEGRATOR_CLASSES: dict[str, type[Integrator]] = {
    c.name: c for c in (ForwardEuler, SymplecticEuler, Verlet, RK4, BackwardEuler, BDF2)
}
for _cls in INTEGRATOR_CLASSES.values():   # the registry that scene validation reads (names, implicit or not)
    REGISTRY.register(_cls.name, factory=_cls, implicit=_cls.implicit, aliases=_cls.aliases)
#: Names of the integrators, in the order used by reports and benchmarks.
INTEGRATORS: tuple[str, ...] = tuple(INTEGRATOR_CLASSES)


def make_integrator(name: str, model: Any, solver: dict[str, Any] | None = None) -> Integrator:
    """Instantiate an integrator by name."""
    try:
        cls = INTEGRATOR_CLASSES[name]
    except KeyError:
        raise ValueError(f"integrator: must be one of {', '.join(INTEGRATORS)}, got {name!r}") from None
    return cls(model, solver)


__all__ = ["INTEGRATORS", "INTEGRATOR_CLASSES", "Integrator", "ImplicitIntegrator", "StepInfo", "make_integrator"]
