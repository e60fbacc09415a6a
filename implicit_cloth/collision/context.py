"""What every collision stage reads: the obstacles and the cloth's topology (:class:`Context`), and the records
of what a step did (:class:`CollisionInfo`).

The stages are plain functions over one :class:`Context` (contact detection in
:mod:`~implicit_cloth.collision.contacts`, Coulomb friction in
:mod:`~implicit_cloth.collision.friction`, the geometric response in
:mod:`~implicit_cloth.collision.fallback` with its feature and mesh tests), so
that each can be read, tested and timed on its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..rowwise import all1, max1, min1
from .shapes import MeshShape, Plane, RigidMotion, Shape, build, local_aabb


@dataclass
class Obstacle:
    """One rigid obstacle: its shape (local frame), its motion and its friction coefficient."""

    shape: Shape
    motion: RigidMotion
    friction: float
    spec: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> "Obstacle":
        """From a validated ``[[obstacles]]`` table."""
        shape, motion = build(spec)
        return cls(shape, motion, float(spec["friction"]), spec)

    def describe(self) -> str:
        """The table's main keys, for messages: ``{shape = 'sphere', center = [0, 0, 1], radius = 0.3}``."""
        spec = self.spec
        keys = [k for k in ("shape", "center", "point", "radius", "size", "height", "path") if k in spec]
        return "{" + ", ".join(f"{k} = {spec[k]!r}" for k in keys) + "}"


def cloth_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


#: ``collision.newton_iterations`` of a settings table that reaches the collider without the key (built by hand:
#: one linearisation); a validated scene always has it, by default 2 (``implicit_cloth.scene.COLLISION_DEFAULTS``).
COLLISION_NEWTON = 1
#: ``collision.friction_speed`` when a scene does not give it, m/s: friction smoothed below this sliding speed
#: (0 would select Coulomb's sticking and sliding states, decided once a solve and lagged a step where they
#: switch: at large steps those lags held a hanging cloth to a sphere driven through it, and the springs at
#: its pins stretched with it: 22.6 times their length on a 32² cloth at 5 m/s and dt 1/30, 2.0 at dt 1/120
#: and 1/480; see docs/scene.md).
FRICTION_SPEED = 1e-4
#: ``collision.friction_newton`` when a scene does not give it and its friction is smoothed: the smoothed
#: friction solved within each step by up to this many Newton iterations.
FRICTION_NEWTON = 6


def friction_speed(settings: dict[str, Any]) -> float:
    """The scene's smoothed-friction sliding speed, m/s (0: Coulomb's states); :data:`FRICTION_SPEED` if not given."""
    return float(settings.get("friction_speed", FRICTION_SPEED))


def friction_newton(settings: dict[str, Any]) -> int:
    """The Newton iterations its smoothed friction is solved with in a step (0: linearised once, with the state
    rules); :data:`FRICTION_NEWTON` if not given and the friction is smoothed, 0 with Coulomb's states."""
    return int(settings.get("friction_newton", FRICTION_NEWTON if friction_speed(settings) > 0 else 0))


@dataclass
class Context:
    """The obstacles, the collision settings and the cloth's topology and masses.

    Attributes
    ----------
    obstacles : list of Obstacle
    thickness : float
        m: the cloth is kept this far from every surface.
    restitution : float
        Fraction of an approaching normal speed an impact returns.
    max_rounds : int
        Most rounds of solves (implicit) or of the geometric response (``collision.max_iterations``).
    faces, edges : int arrays
        The cloth's triangles (T, 3) and unique edges (E, 2).
    masses : (N,) array
        Vertex masses, kg.
    inv_mass : (N,) array
        Inverse masses, 0 for pinned vertices (no correction moves them).
    friction : bool
        Whether the geometric response applies friction (off when it follows an implicit solve, which has).
    newton : int
        Newton iterations of an implicit step with contacts, its contact rounds' linear solve included
        (``collision.newton_iterations``; 1: Baraff & Witkin's single linearisation).
    """

    obstacles: list[Obstacle]
    thickness: float
    restitution: float
    max_rounds: int
    faces: np.ndarray
    edges: np.ndarray
    masses: np.ndarray
    inv_mass: np.ndarray
    friction: bool = True
    newton: int = 1
    #: smoothed friction's sliding speed, m/s (0: Coulomb friction with sticking and sliding states)
    smooth: float = 0.0
    #: the most Newton iterations of a contact step's solves when smoothed friction is solved to convergence
    #: (``collision.friction_newton``; 0: linearised once, with its state rules)
    friction_newton: int = 0
    #: steps the friction's Newton iterations are skipped after two steps in a row that missed the law
    #: (``collision.friction_pause``; 0: never)
    friction_pause: int = 0

    @classmethod
    def build(cls, obstacles: list[dict[str, Any]], settings: dict[str, Any], model: Any) -> "Context":
        inv_mass = model.inv_masses.copy()
        inv_mass[model.pinned] = 0.0
        faces = np.asarray(model.faces, dtype=np.int64)
        return cls([Obstacle.from_spec(s) for s in obstacles], float(settings["thickness"]),
                   float(settings["restitution"]), int(settings["max_iterations"]), faces, cloth_edges(faces),
                   np.asarray(model.masses, dtype=float), inv_mass,
                   newton=int(settings.get("newton_iterations", COLLISION_NEWTON)),
                   smooth=friction_speed(settings), friction_newton=friction_newton(settings),
                   friction_pause=int(settings.get("friction_pause", 0)))

    @property
    def n(self) -> int:
        return len(self.masses)

    @property
    def free(self) -> np.ndarray:
        """(N,) bool: the vertices a collision may move (not pinned)."""
        return self.inv_mass > 0

    @property
    def mu(self) -> np.ndarray:
        """Friction coefficient of each obstacle."""
        return np.array([ob.friction for ob in self.obstacles])

    def friction_of(self, ob: Obstacle) -> float:
        """The obstacle's coefficient where the geometric response applies friction, else 0."""
        return ob.friction if self.friction else 0.0

    def nearest_obstacle(self, x: np.ndarray, t: float) -> np.ndarray:
        """Index of the obstacle nearest to each world point at ``t`` (meshes: by their nearest sampled vertex)."""
        best = np.full(len(x), np.inf)
        owner = np.zeros(len(x), dtype=np.int64)
        for k, ob in enumerate(self.obstacles):
            p = ob.motion.to_local(x, t)
            if isinstance(ob.shape, MeshShape):
                V = ob.shape.vertices[::max(1, len(ob.shape.vertices) // 256)]
                d = np.min(np.linalg.norm(p[:, None, :] - V[None], axis=2), axis=1)
            else:
                d = ob.shape.distance(p)
            owner = np.where(d < best, k, owner)
            best = np.minimum(best, d)
        return owner


def near(shape: Shape, p0: np.ndarray, p1: np.ndarray, margin: float) -> np.ndarray:
    """Bool mask of swept boxes (rows of p0 -> p1, or (K, m, 3) primitives) near the shape's local box."""
    lo, hi = _corners(p0)
    if p1 is not p0:                                  # a step, not a still state
        lo1, hi1 = _corners(p1)
        lo, hi = np.minimum(lo, lo1), np.maximum(hi, hi1)
    if isinstance(shape, Plane):
        return lo[:, 2] <= margin
    a, b = local_aabb(shape)
    return all1((lo <= b + margin) & (hi >= a - margin))


def _corners(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (K, 3) of points (K, 3) or of primitives (K, m, 3)."""
    return (min1(p), max1(p)) if p.ndim == 3 else (p, p)


def world_at(mo: RigidMotion, q: np.ndarray, n_loc: np.ndarray, tc: np.ndarray):
    """World points, normals and obstacle velocities (K, 3) of local points and normals at per-point times ``tc``.

    ``x = c(tc) + R(tc) q``, ``n = R(tc) n_loc``, ``u = dc/dt + omega x (x - c)``: one pose per contact
    time, vectorised (:meth:`RigidMotion.pose` and :meth:`RigidMotion.point_velocity` take arrays of times).
    """
    c, R = mo.pose(tc)
    xc = np.einsum("kij,kj->ki", R, q) + c
    n_w = np.einsum("kij,kj->ki", R, n_loc)
    return xc, n_w, mo.point_velocity(xc, tc)


@dataclass
class CollisionInfo:
    """What the collision stage did in one step.

    Attributes
    ----------
    candidates : int
        Vertex paths and feature pairs tested exactly (after the bounding-box filter).
    contacts : int
        Implicit methods: contacts new in the step (found by detection after a solve). Explicit ones:
        vertices corrected (impulse or push) plus feature pairs responded to.
    resting : int
        Vertices held by a contact in the last solve of the step.
    toi : float
        Earliest time of impact the geometric response found, as a fraction of the step (nan if none).
    rounds : int
        Rounds taken (solves of an implicit step; response rounds of an explicit one).
    failsafe : int
        Vertices frozen to an obstacle by the fail-safe.
    max_penetration : float
        Largest depth of a cloth vertex inside an obstacle after the response, m.
    t_collision : float
        Wall time of the collision stage (without the solves), s.
    solves : int
        Linear solves of the step (implicit methods: one per round, Newton iterations included).
    fallback : int
        Corrections the geometric response made after the solves (implicit methods): what the
        constrained solves left.
    work : float
        Work the obstacles did on the cloth in the step, J, computed from what they did: each contact's
        impulse times the obstacle's velocity at the contact point (the solve's constraint impulse, the
        kinetic friction force over the step, the velocity changes after it), like the pins' work. Zero for
        obstacles that do not move. The energy balance of every step counts it as external work; the
        energy the contact treatment itself creates or removes is not in it.
    """

    candidates: int = 0
    contacts: int = 0
    resting: int = 0
    toi: float = float("nan")
    rounds: int = 0
    failsafe: int = 0
    max_penetration: float = 0.0
    t_collision: float = 0.0
    work: float = 0.0
    solves: int = 0
    fallback: int = 0

    def absorb(self, other: "CollisionInfo", accepted: bool = True) -> None:
        """Add a later substep's figures (adaptive stepping): counts summed, extremes kept, time summed.

        A discarded substep (``accepted=False``) adds only its time: its contacts were undone.
        """
        self.t_collision += other.t_collision
        if not accepted:
            return
        self.candidates += other.candidates
        self.contacts += other.contacts
        self.resting = max(self.resting, other.resting)
        if other.toi == other.toi and not self.toi <= other.toi:   # nan-aware minimum
            self.toi = other.toi
        self.rounds = max(self.rounds, other.rounds)
        self.failsafe += other.failsafe
        self.max_penetration = max(self.max_penetration, other.max_penetration)
        self.work += other.work
        self.solves += other.solves
        self.fallback += other.fallback
