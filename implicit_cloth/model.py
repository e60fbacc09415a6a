"""Model (fixed per cloth) and State (per step).

A :class:`Model` holds what does not change during a run: topology, rest
lengths, masses, lumped areas, pins and the declared effects. A
:class:`State` holds positions ``x`` (m), velocities ``v`` (m/s) and time ``t``
(s). Integrators map ``(model, state, dt)`` to a new state.

Pins: vertex ``p`` follows ``x_p(t) = a_p + w_p t`` exactly, with prescribed
velocity ``w_p`` (m/s) and anchor ``a_p`` (set from the initial positions, and
again whenever the user assigns positions). A keyframed pin group follows its
keys (:mod:`implicit_cloth.pin_paths`), each step prescribing the velocity that
ends it on its path (:meth:`Model.pin_velocity_at`); a pin with a ``stiffness``
is a soft pin, a zero-length spring to its path
(:mod:`implicit_cloth.effects.pin_springs`), not a constraint.
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
from .scene import cloth_pieces, dihedral_bending, piece_path


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
        Prescribed velocity of each pinned vertex, m/s (0 on keyframed ones: their step's velocity is
        :meth:`pin_velocity_at`).
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
        pieces = cloth_pieces(scene.data)
        where = [piece_path(scene.data, k) for k in range(len(pieces))]
        geos = [_piece_geometry(c, w) for c, w in zip(pieces, where)]
        geo = _cloth.combine(geos)
        self.geometry = geo
        sizes = [g.n_vertices for g in geos]
        start = np.cumsum([0] + sizes)
        #: each piece's vertex range ``(start, stop)`` in the cloth's numbering, in the scene's order
        self.pieces: list[tuple[int, int]] = [(int(a), int(b)) for a, b in zip(start[:-1], start[1:])]
        face_start = np.cumsum([0] + [len(g.faces) for g in geos])
        #: each piece's face range ``(start, stop)``
        self.piece_faces: list[tuple[int, int]] = [(int(a), int(b)) for a, b in zip(face_start[:-1], face_start[1:])]
        self.n = geo.n_vertices
        self.faces = geo.faces
        self.rest_positions = geo.positions.copy()
        self.areas = _cloth.lumped_areas(geo.positions, geo.faces)
        self.masses = np.concatenate([_piece_masses(c, w, g, self.areas[a:b])
                                      for c, w, g, (a, b) in zip(pieces, where, geos, self.pieces)])
        #: initial velocity of every vertex (each piece's ``velocity``), (N, 3) m/s
        self.initial_velocity = np.concatenate([np.broadcast_to(np.asarray(c["velocity"], dtype=float), (n, 3))
                                                for c, n in zip(pieces, sizes)])
        self.total_mass = float(self.masses.sum())
        self._init_pins([(c["pins"], g, int(o)) for c, g, o in zip(pieces, geos, start)])
        springs = pieces[0]["springs"] if len(pieces) == 1 else _spring_constants(pieces, geos)
        self.effects: list[Effect] = build_effects(self, scene.data["effects"], springs)
        membranes = [(k, c) for k, c in enumerate(pieces) if "membrane" in c]
        if membranes:   # after the others: a scene without [cloth.membrane] sums its forces as before
            from .effects.membrane import build as build_membrane

            self.effects.append(build_membrane(self, [self._membrane_piece(k, c, where[k], geos[k])
                                                      for k, c in membranes]))
        bent = [k for k, c in enumerate(pieces) if dihedral_bending(c)]
        if bent:        # likewise: a scene without [cloth.bending] model = "dihedral" is unchanged
            from .effects.dihedral import build as build_dihedral

            self.effects.append(build_dihedral(self, [self._bending_piece(k, pieces[k]) for k in bent]))
        if self.soft_pins:   # likewise: pins with a stiffness are zero-length springs to their paths
            from .effects.pin_springs import build as build_pin_springs

            self.effects.append(build_pin_springs(self, self.soft_pins))
        self.effect_names: list[str] = scene.effects
        #: the elastic effect made of springs (strain measures, strain limiting), None without springs
        self.springs: SpringSet | None = next((cast(SpringSet, e) for e in self.effects if e.name == "springs"),
                                              None)
        self._system: SystemMatrix | None = None
        self.inv_masses = 1.0 / self.masses
        self.free = np.ones(self.n, dtype=bool)
        self.free[self.pinned] = False

    def _membrane_piece(self, k: int, c: dict[str, Any], where: str, geo: _cloth.ClothGeometry):
        """Piece ``k``'s triangles of positive rest area (indices into :attr:`faces`), their rest ``(u, v)`` (T_k,
        3, 2) m and its ``[cloth.membrane]`` table: a grid's u along its width (the plane's first axis), v along
        its height; a mesh's from its texture coordinates (:func:`~implicit_cloth.effects.membrane.
        metric_rest_coordinates`: its rest shape laid flat, u along the texture's u)."""
        from .effects.membrane import metric_rest_coordinates

        a, b = self.piece_faces[k]
        fs = self.faces[a:b]
        keep = ~_cloth.degenerate_faces(self.rest_positions, fs)
        rest = self.rest_positions[fs[keep]]
        if c["kind"] == "grid":
            axes = {"xy": [0, 1], "xz": [0, 2], "yz": [1, 2]}[c["plane"]]
            uv = rest[:, :, axes]
        else:
            tex = _cloth.mesh_uv(c["mesh"], geo.faces, f"{where}.membrane")[keep]
            uv = metric_rest_coordinates(self.rest_positions, fs[keep], tex)
        return np.arange(a, b)[keep], uv, c["membrane"]

    def _bending_piece(self, k: int, c: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:
        """Piece ``k``'s triangles of positive rest area (rows of :attr:`faces`, whose shared edges are the
        hinges) and its ``[cloth.bending]`` table."""
        a, b = self.piece_faces[k]
        fs = self.faces[a:b]
        return fs[~_cloth.degenerate_faces(self.rest_positions, fs)], c["bending"]

    # ------------------------------------------------------------------ pins
    def _init_pins(self, pieces: list[tuple[list[dict[str, Any]], Any, int]]) -> None:
        """Pins of every piece: ``(pin groups, the piece's geometry, its first vertex)``, indices per piece.

        Exact pins (no ``stiffness``) constrain their vertices (:attr:`pinned`); soft ones (``stiffness``) are
        zero-length springs to their paths, a force (:mod:`implicit_cloth.effects.pin_springs`), kept in
        :attr:`soft_pins` until the effects are built."""
        idx: list[int] = []
        vel: list[list[float]] = []
        motion: list[Any] = []
        seen: dict[int, str] = {}
        keyed: dict[int, list[int]] = {}          # keyframed group (its number) -> its rows in idx
        keys_of: dict[int, Any] = {}
        #: soft pin groups: (vertices, velocity, keyframes or None, stiffness, damping)
        self.soft_pins: list[tuple[list[int], list[float], Any, float, float]] = []
        n_group = 0
        for groups, geo, offset in pieces:
            for g in groups:
                n_group += 1
                verts: list[int] = []
                for m, v in enumerate(g["vertices"]):
                    where = g["paths"][m]
                    p = geo.corner(v, where) if isinstance(v, str) else int(v)
                    if p >= geo.n_vertices:
                        what = "cloth" if len(pieces) == 1 else "piece"
                        raise SceneError(where, f"vertex index out of range (the {what} has {geo.n_vertices} "
                                                f"vertices)", v)
                    verts.append(p + offset)
                if "stiffness" in g:
                    self.soft_pins.append((verts, list(g["velocity"]), g.get("keyframes"), float(g["stiffness"]),
                                           float(g.get("damping", 0.0))))
                    continue
                how = (list(g["velocity"]), g.get("keyframes"))
                for m, p in enumerate(verts):
                    where = g["paths"][m]
                    if p in seen:
                        if how != motion[idx.index(p)]:
                            what = "motions" if any(h[1] is not None for h in (how, motion[idx.index(p)])) \
                                else "velocities"
                            raise SceneError(f"{where}: vertex {p - offset} is pinned twice with different "
                                             f"{what}, got {fmt(g['vertices'][m])}")
                        continue
                    seen[p] = where
                    if how[1] is not None:
                        keyed.setdefault(n_group, []).append(len(idx))
                        keys_of[n_group] = how[1]
                    idx.append(p)
                    vel.append(list(g["velocity"]) if how[1] is None else [0.0, 0.0, 0.0])
                    motion.append(how)
        self.pinned = np.asarray(idx, dtype=np.int64)
        self.pin_velocity = np.asarray(vel, dtype=float).reshape(-1, 3)
        self.pin_anchor = self.rest_positions[self.pinned].copy()   # position at t = 0
        #: the keyframed pins' paths (:class:`~implicit_cloth.pin_paths.PinPaths`), None without keyframed pins
        #: (constant-velocity pins then follow ``pin_anchor + pin_velocity t`` exactly as before)
        self.pin_paths: Any = None
        if keyed:
            from .pin_paths import PinPaths

            self.pin_paths = PinPaths(self.pin_anchor, [(np.asarray(r), v, None) for r, v in
                                                        self._constant_rows(keyed)]
                                      + [(np.asarray(r), None, keys_of[k]) for k, r in keyed.items()])

    def _constant_rows(self, keyed: dict[int, list[int]]) -> list[tuple[list[int], np.ndarray]]:
        """The rows of :attr:`pinned` outside the keyframed groups, one group per row (their constant velocity)."""
        inkey = {r for rows in keyed.values() for r in rows}
        return [([r], self.pin_velocity[r]) for r in range(len(self.pinned)) if r not in inkey]

    @property
    def pins_keyframed(self) -> bool:
        """Whether some exact pins follow keyframes (their step velocities then change from step to step)."""
        return self.pin_paths is not None

    def set_pin_anchors(self, x: np.ndarray, t: float) -> None:
        """Make pins pass through ``x[pinned]`` at time ``t`` (used when positions are assigned)."""
        if self.pin_paths is not None:
            self.pin_paths.reanchor(x[self.pinned], t)
            self.pin_anchor = self.pin_paths.anchors.copy()
        else:
            self.pin_anchor = x[self.pinned] - self.pin_velocity * t
        for e in self.effects if hasattr(self, "effects") else []:
            if hasattr(e, "reanchor"):
                e.reanchor(x, t)

    def pin_positions(self, t: float) -> np.ndarray:
        """Prescribed positions of the pinned vertices at time t, (P, 3) m."""
        if self.pin_paths is not None:
            return self.pin_paths.targets(t)
        return self.pin_anchor + self.pin_velocity * t

    def pin_rates(self, t: float) -> np.ndarray:
        """Velocities of the pinned vertices' paths at time t (a keyframed one's: of the segment starting at t),
        (P, 3) m/s."""
        if self.pin_paths is not None:
            return self.pin_paths.rates(t)
        return self.pin_velocity

    def pin_velocity_at(self, x: np.ndarray, t: float, h: float) -> np.ndarray:
        """The pinned vertices' velocity over the step ``[t, t + h]`` from positions ``x`` (N, 3): ``(target(t + h)
        - x_p) / h``, so that they end the step on their paths (m/s, (P, 3)). Without keyframed pins
        :attr:`pin_velocity` itself."""
        if self.pin_paths is None:
            return self.pin_velocity
        return (self.pin_paths.targets(t + h) - x[self.pinned]) / h

    def pin_speed(self) -> float:
        """The largest speed of a pinned vertex's path, m/s (0 without pins)."""
        if self.pin_paths is not None:
            return self.pin_paths.max_speed()
        return float(np.linalg.norm(self.pin_velocity, axis=1).max()) if len(self.pinned) else 0.0

    def apply_pins(self, x: np.ndarray, v: np.ndarray, t: float) -> None:
        """Set pinned vertices to their prescribed position and velocity at time t (in place)."""
        if len(self.pinned):
            x[self.pinned] = self.pin_positions(t)
            v[self.pinned] = self.pin_rates(t)

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

    def force_rate(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray | None:
        """``dF/dt`` at a fixed state (N, 3), N/s, of the forces that change with time (soft pins' moving targets:
        an effect with ``rate(x, v, t, out)``), for the implicit step's linearisation in time; None when none
        does (every other scene's step unchanged)."""
        timed = [e for e in self.effects if hasattr(e, "rate")]
        if not timed:
            return None
        out = np.zeros_like(x)
        for e in timed:
            cast(Any, e).rate(x, v, t, out)
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
        return {e.name: e.energy(x) for e in self.effects if e.conservative}

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
                  w: np.ndarray | None = None, lazy: bool = False):
        """Assemble ``A = M - c_v dF/dv - c_x dF/dx``, the force ``F(x, v)`` and ``(dF/dx) w``.

        Returns
        -------
        A : scipy.sparse.csr_array, (3N, 3N)
            The same object every call (values refilled); with ``lazy`` the system matrix itself, finalized
            without its CSR copy until a product or a read of its ``csr`` needs it
            (:meth:`~implicit_cloth.assembly.SystemMatrix.finalize_lazy`).
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
        return (sysm.finalize_lazy() if lazy else sysm.finalize()), f, kw


# ---------------------------------------------------------------------- pieces
def _piece_geometry(c: dict[str, Any], where: str) -> _cloth.ClothGeometry:
    """One piece's geometry (grid or mesh file); its errors name the piece (``cloth[1].mesh: ...``)."""
    kinds = tuple(c["springs"])
    try:
        if c["kind"] == "grid":
            geo = _cloth.grid(c["size"], c["resolution"], c["center"], c["plane"], kinds)
        else:
            geo = _cloth.from_mesh(c["mesh"], c["scale"], c["translation"], kinds)
    except SceneError as exc:
        msg = str(exc)
        if where != "cloth" and msg.startswith("cloth."):
            raise SceneError(where + msg[len("cloth"):]) from None
        raise
    if not np.isfinite(geo.positions).all():   # a mesh's coordinates are checked by from_mesh
        raise SceneError(f"{where}.center: vertex positions are not finite (center + size / 2 overflows), "
                         f"got {c.get('center')}")
    return geo


def _piece_masses(c: dict[str, Any], where: str, geo: _cloth.ClothGeometry, areas: np.ndarray) -> np.ndarray:
    """Lumped vertex masses of one piece, kg: a grid's spread evenly, a mesh's by lumped area."""
    n = geo.n_vertices
    total_area = float(areas.sum())
    if c["kind"] == "grid":
        total_mass = c["mass"] if "mass" in c else c["density"] * total_area
        masses = np.full(n, total_mass / n)
    else:
        if np.any(areas <= 0):   # from_mesh's checks catch this first; kept as a safeguard
            bad = np.flatnonzero(areas <= 0)
            raise SceneError(
                f"{where}.mesh: vertex {bad[0]} has no area (it is in no triangle of positive area), so it "
                f"would have no mass ({len(bad)} such vertices: {', '.join(map(str, bad[:5]))}"
                f"{', ...' if len(bad) > 5 else ''}), got {c['mesh']!r}")
        masses = (c["mass"] * areas / total_area) if "mass" in c else c["density"] * areas
    _check_masses(c, where, masses, areas)
    return masses


def _check_masses(c: dict[str, Any], where: str, masses: np.ndarray, areas: np.ndarray) -> None:
    """Every vertex mass must be a positive finite number with a finite inverse (no underflow or overflow)."""
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        ok = np.isfinite(masses) & (masses > 0) & np.isfinite(1.0 / masses)
    if not ok.all():
        n = len(masses)
        v = int(np.flatnonzero(~ok)[0])
        key = "mass" if "mass" in c else "density"
        if key == "mass":
            how = f"total {c['mass']:g} kg over {n} vertices"
        elif c["kind"] == "grid":
            how = f"{c['density']:g} kg/m^2 x area {float(areas.sum()):.3g} m^2 over {n} vertices"
        else:
            how = f"{c['density']:g} kg/m^2 x its area {areas[v]:.3g} m^2"
        raise SceneError(f"{where}.{key}: vertex {v} would get a mass of {masses[v]:.3g} kg ({how}), "
                         f"which is not a positive number with a finite inverse, got {c[key]}")


def _spring_constants(pieces: list[dict[str, Any]], geos: list[_cloth.ClothGeometry]) -> dict[str, dict[str, Any]]:
    """Per-spring stiffness and damping of several pieces, in :func:`cloth.combine`'s order of each kind."""
    out: dict[str, dict[str, Any]] = {}
    for kind in ("structural", "shear", "bend"):
        have = [(c["springs"][kind], len(g.springs[kind])) for c, g in zip(pieces, geos) if kind in c["springs"]]
        if have:
            out[kind] = {key: np.concatenate([np.full(n, p[key]) for p, n in have]) for key in ("stiffness", "damping")}
    return out
