"""Model (fixed per cloth) and State (per step).

A :class:`Model` holds what does not change during a run: topology, rest
lengths, masses, lumped areas, pins and the declared effects. A
:class:`State` holds positions ``x`` (m), velocities ``v`` (m/s) and time ``t``
(s). Integrators map ``(model, state, dt)`` to a new state.

Pins: vertex ``p`` follows ``x_p(t) = a_p + w_p t`` exactly, with prescribed
velocity ``w_p`` (m/s) and anchor ``a_p`` (set from the initial positions, and
again whenever the user assigns positions).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from . import cloth as _cloth
from .assembly import SystemMatrix
from .backend import Backend, get_backend
from .config.validate import fmt
from .effects import Effect, SpringSet, build_effects
from .errors import SceneError


@dataclass
class State:
    """Positions ``x`` (N, 3) m, velocities ``v`` (N, 3) m/s and time ``t`` s."""

    x: np.ndarray
    v: np.ndarray
    t: float = 0.0

    def copy(self) -> "State":
        return State(self.x.copy(), self.v.copy(), float(self.t))


class Model:
    """The fixed part of a simulation, built from a validated :class:`~implicit_cloth.scene.Scene`.

    Attributes
    ----------
    n : int
        Number of vertices.
    masses : (N,) array
        Lumped vertex masses, kg.
    areas : (N,) array
        Lumped vertex areas (a third of each adjacent triangle), m^2.
    faces : (T, 3) int array
    pinned : (P,) int array
        Indices of pinned vertices.
    pin_velocity : (P, 3) array
        Prescribed velocity of each pinned vertex, m/s.
    effects : list
        The declared effects only (see :mod:`implicit_cloth.effects`).
    effect_names : list of str
        Names of the active effects, as listed in the run report.
    """

    def __init__(self, scene: Any) -> None:
        self.scene = scene
        #: the numerical back-end (numpy or numba), resolved once here: the system matrix, the springs bound
        #: to it and the preconditioner dispatch through it
        self.backend: Backend = get_backend()
        c = scene.data["cloth"]
        kinds = tuple(c["springs"])
        if c["kind"] == "grid":
            geo = _cloth.grid(c["size"], c["resolution"], c["center"], c["plane"], kinds)
        else:
            geo = _cloth.from_mesh(c["mesh"], c["scale"], c["translation"], kinds)
        self.geometry = geo
        if not np.isfinite(geo.positions).all():   # a mesh's coordinates are checked by from_mesh
            raise SceneError(f"cloth.center: vertex positions are not finite (center + size / 2 overflows), "
                             f"got {c.get('center')}")
        self.n = geo.n_vertices
        self.faces = geo.faces
        self.rest_positions = geo.positions.copy()
        self.areas = _cloth.lumped_areas(geo.positions, geo.faces)
        total_area = float(self.areas.sum())
        if c["kind"] == "grid":
            total_mass = c["mass"] if "mass" in c else c["density"] * total_area
            self.masses = np.full(self.n, total_mass / self.n)
        else:
            if np.any(self.areas <= 0):   # from_mesh's checks catch this first; kept as a safeguard
                bad = np.flatnonzero(self.areas <= 0)
                raise SceneError(
                    f"cloth.mesh: vertex {bad[0]} has no area (it is in no triangle of positive area), so it "
                    f"would have no mass ({len(bad)} such vertices: {', '.join(map(str, bad[:5]))}"
                    f"{', ...' if len(bad) > 5 else ''}), got {c['mesh']!r}")
            self.masses = (c["mass"] * self.areas / total_area) if "mass" in c else c["density"] * self.areas
        self._check_masses(c)
        self.total_mass = float(self.masses.sum())
        self._init_pins(c["pins"])
        self.effects: list[Effect] = build_effects(self, scene.data["effects"], c["springs"])
        self.effect_names: list[str] = scene.effects
        #: the elastic effect made of springs (strain measures, strain limiting), None without springs
        self.springs: SpringSet | None = next((cast(SpringSet, e) for e in self.effects if e.elastic), None)
        self._system: SystemMatrix | None = None
        self.inv_masses = 1.0 / self.masses
        self.free = np.ones(self.n, dtype=bool)
        self.free[self.pinned] = False

    def _check_masses(self, c: dict[str, Any]) -> None:
        """Every vertex mass must be a positive finite number with a finite inverse (no underflow or overflow)."""
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            ok = np.isfinite(self.masses) & (self.masses > 0) & np.isfinite(1.0 / self.masses)
        if not ok.all():
            v = int(np.flatnonzero(~ok)[0])
            key = "mass" if "mass" in c else "density"
            if key == "mass":
                how = f"total {c['mass']:g} kg over {self.n} vertices"
            elif c["kind"] == "grid":
                how = f"{c['density']:g} kg/m^2 x area {float(self.areas.sum()):.3g} m^2 over {self.n} vertices"
            else:
                how = f"{c['density']:g} kg/m^2 x its area {self.areas[v]:.3g} m^2"
            raise SceneError(f"cloth.{key}: vertex {v} would get a mass of {self.masses[v]:.3g} kg ({how}), "
                             f"which is not a positive number with a finite inverse, got {c[key]}")

    # ------------------------------------------------------------------ pins
    def _init_pins(self, groups: list[dict[str, Any]]) -> None:
        idx: list[int] = []
        vel: list[list[float]] = []
        seen: dict[int, str] = {}
        for g in groups:
            for m, v in enumerate(g["vertices"]):
                where = g["paths"][m]
                p = self.geometry.corner(v, where) if isinstance(v, str) else int(v)
                if p >= self.n:
                    raise SceneError(where, f"vertex index out of range (the cloth has {self.n} vertices)", v)
                if p in seen:
                    if g["velocity"] != vel[idx.index(p)]:
                        raise SceneError(f"{where}: vertex {p} is pinned twice with different velocities, got {fmt(v)}")
                    continue
                seen[p] = where
                idx.append(p)
                vel.append(list(g["velocity"]))
        self.pinned = np.asarray(idx, dtype=np.int64)
        self.pin_velocity = np.asarray(vel, dtype=float).reshape(-1, 3)
        self.pin_anchor = self.rest_positions[self.pinned].copy()   # position at t = 0

    def set_pin_anchors(self, x: np.ndarray, t: float) -> None:
        """Make pins pass through ``x[pinned]`` at time ``t`` (used when positions are assigned)."""
        self.pin_anchor = x[self.pinned] - self.pin_velocity * t

    def pin_positions(self, t: float) -> np.ndarray:
        """Prescribed positions of the pinned vertices at time t, (P, 3) m."""
        return self.pin_anchor + self.pin_velocity * t

    def apply_pins(self, x: np.ndarray, v: np.ndarray, t: float) -> None:
        """Set pinned vertices to their prescribed position and velocity at time t (in place)."""
        if len(self.pinned):
            x[self.pinned] = self.pin_positions(t)
            v[self.pinned] = self.pin_velocity

    # ------------------------------------------------------------------ forces
    def forces(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray | None = None) -> np.ndarray:
        """Total force of all active effects on every vertex, (N, 3) N."""
        if out is None:
            out = np.zeros_like(x)
        else:
            out.fill(0.0)
        for e in self.effects:
            e.force(x, v, t, out)
        return out

    def accelerations(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """``a = M^-1 F`` with pinned vertices' accelerations set to 0, (N, 3) m/s^2."""
        a = self.forces(x, v, t)
        a *= self.inv_masses[:, None]
        if len(self.pinned):
            a[self.pinned] = 0.0
        return a

    def potential_energy(self, x: np.ndarray) -> dict[str, float]:
        """Potential energy of each conservative effect, J."""
        return {e.name: e.potential(x) for e in self.effects if e.conservative}

    def kinetic_energy(self, v: np.ndarray) -> float:
        """``sum_i m_i |v_i|^2 / 2``, J."""
        return 0.5 * float(np.dot(self.masses, np.einsum("ij,ij->i", v, v)))

    # ------------------------------------------------------------------ implicit system
    @property
    def system(self) -> SystemMatrix:
        """The fixed-pattern system matrix, built (once) on first use by an implicit integrator."""
        if self._system is None:
            blocks = [e.pairs() for e in self.effects]
            pairs = np.concatenate(blocks) if blocks else np.zeros((0, 2), dtype=np.int64)
            self._system = SystemMatrix(self.n, pairs, self.backend)
            for e in self.effects:
                e.bind(self._system)
        return self._system

    def linearize(self, x: np.ndarray, v: np.ndarray, t: float, c_x: float, c_v: float,
                  w: np.ndarray | None = None):
        """Assemble ``A = M - c_v dF/dv - c_x dF/dx``, the force ``F(x, v)`` and ``(dF/dx) w``.

        Returns
        -------
        A : scipy.sparse.csr_array, (3N, 3N)
            The same object every call (values refilled).
        f : (N, 3) array
            Total force, N.
        kw : (N, 3) array or None
            ``(dF/dx) w`` if ``w`` is given.
        """
        sysm = self.system
        sysm.reset_diagonal(self.masses)
        kw = np.zeros_like(x) if w is not None else None
        f = np.zeros_like(x)
        for e in self.effects:
            e.linearize(x, v, t, c_x, c_v, w, sysm, kw, f)
        return sysm.finalize(), f, kw
