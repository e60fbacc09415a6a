"""Registries of the named components a scene can select: integrators, preconditioners, obstacle shapes, effects.

Each component declares itself where it is defined (its name, the scene keys it
takes, their defaults and anything else validation needs), and scene validation
reads the registry instead of keeping its own copy of the names::

    INTEGRATORS.register("bdf2", factory=BDF2, implicit=True)     # in implicit_cloth/integrators
    INTEGRATORS.names()                                           # (..., "bdf2")
    INTEGRATORS.choice("simulation.integrator", "bfd2")           # SceneError: ... (did you mean 'bdf2'?)

A registry knows which modules register into it (``providers``) and imports them
on first use, so asking for the names never depends on what happened to be
imported before; the providers sit above this module and are never imported by it
statically (the import graph stays one-way).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping

from .validate import choice

__all__ = ["EFFECTS", "INTEGRATORS", "OBSTACLE_SHAPES", "PRECONDITIONERS", "Entry", "Registry"]


@dataclass(frozen=True)
class Entry:
    """One registered component.

    Attributes
    ----------
    name : str
        Its name in a scene (``simulation.integrator = "bdf2"``).
    keys : tuple of str
        Scene keys it takes (its table's keys), in documentation order.
    required : tuple of str
        Those of ``keys`` that must be given.
    defaults : mapping
        Values of the optional keys when left out.
    factory : callable or None
        What builds it (a class or function), if the registry's users build through it.
    meta : mapping
        Anything else its users need (``implicit`` for an integrator, ``validate`` for an effect...).
    """

    name: str
    keys: tuple[str, ...] = ()
    required: tuple[str, ...] = ()
    defaults: Mapping[str, Any] = field(default_factory=dict)
    factory: Callable[..., Any] | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)

    def load(self, attr: str) -> Any:
        """``attr`` of the module named by ``meta["module"]``, imported now (components imported only when used)."""
        return getattr(importlib.import_module(self.meta["module"]), attr)


class Registry:
    """Named components of one kind, in registration order."""

    def __init__(self, kind: str, providers: tuple[str, ...] = ()) -> None:
        self.kind = kind
        self.providers = providers
        self._entries: dict[str, Entry] = {}
        self._loaded = False

    def register(self, name: str, *, keys: tuple[str, ...] = (), required: tuple[str, ...] = (),
                 defaults: Mapping[str, Any] | None = None, factory: Callable[..., Any] | None = None,
                 **meta: Any) -> Entry:
        """Add (or, for the same name, replace) a component; returns its entry."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind}: a registered name must be a non-empty string, got {name!r}")
        unknown = [k for k in (*required, *(defaults or {})) if k not in keys]
        if unknown:
            raise ValueError(f"{self.kind}.{name}: required or defaulted keys must be among its keys, got {unknown}")
        entry = Entry(name, tuple(keys), tuple(required), dict(defaults or {}), factory, dict(meta))
        self._entries[name] = entry
        return entry

    def unregister(self, name: str) -> None:
        """Remove a component (a plug-in unloaded, a test's temporary entry)."""
        del self._entries[name]

    def _load(self) -> None:
        if not self._loaded:
            self._loaded = True
            for module in self.providers:
                importlib.import_module(module)

    def names(self) -> tuple[str, ...]:
        """Every registered name, in registration order."""
        self._load()
        return tuple(self._entries)

    def __getitem__(self, name: str) -> Entry:
        self._load()
        return self._entries[name]

    def __contains__(self, name: object) -> bool:
        self._load()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def aliases(self) -> dict[str, str]:
        """Other names of the components (``meta["aliases"]``), each mapped to its registered name: what a
        "did you mean" suggests for them (``implicit_euler`` -> ``backward_euler``)."""
        self._load()
        return {a: n for n, e in self._entries.items() for a in e.meta.get("aliases", ())}

    def choice(self, path: str, value: Any) -> str:
        """``value`` if it is a registered name, else a :class:`~implicit_cloth.errors.SceneError` at ``path``
        (with a "did you mean" for a near miss or another name of a component, :meth:`aliases`)."""
        return choice(path, value, self.names(), self.aliases())

    def where(self, **meta: Any) -> tuple[str, ...]:
        """Names whose ``meta`` has all the given items, e.g. ``INTEGRATORS.where(implicit=True)``."""
        self._load()
        return tuple(n for n, e in self._entries.items() if all(e.meta.get(k) == v for k, v in meta.items()))


#: Time integrators (``simulation.integrator``); ``meta["implicit"]`` says which use the linear solver.
INTEGRATORS = Registry("simulation.integrator", providers=("implicit_cloth.integrators",))
#: Preconditioners of the filtered PCG (``solver.preconditioner``); ``meta["default"]`` marks the default.
PRECONDITIONERS = Registry("solver.preconditioner", providers=("implicit_cloth.solvers",))
#: Rigid obstacle shapes (``[[obstacles]] shape``): their keys, required keys and defaults.
OBSTACLE_SHAPES = Registry("obstacles.shape", providers=("implicit_cloth.obstacles",))
#: Force effects of the ``[effects]`` table, in evaluation order; ``load("validate")`` checks a value.
EFFECTS = Registry("effects", providers=("implicit_cloth.effects",))
