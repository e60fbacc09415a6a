"""Configuration: the shared input checks and the registries of named components.

:mod:`.validate` holds the checks (``number``, ``vector``, ``choice``, ``check_keys``...)
that scenes, sweeps and the command line share; :mod:`.registry` holds the
registries that integrators, preconditioners, obstacle shapes and effects
register into, and that validation reads. Both sit at the bottom of the import
graph: they import nothing of the package but :mod:`implicit_cloth.errors`.
"""

from __future__ import annotations

from . import registry, validate
from .registry import EFFECTS, INTEGRATORS, OBSTACLE_SHAPES, PRECONDITIONERS, Entry, Registry

__all__ = ["EFFECTS", "INTEGRATORS", "OBSTACLE_SHAPES", "PRECONDITIONERS", "Entry", "Registry", "registry",
           "validate"]
