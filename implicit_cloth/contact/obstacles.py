"""Cloth against rigid obstacles as terms of the step's incremental potential (``collision.method = "barrier"``).

Detection gives a value, :class:`Contacts` (the vertices near an obstacle at the step's start, with their
normals and normal forces, for the lagged friction); the step's forces are built from it
(:meth:`ObstacleContact.terms`) and minimised with the springs, gravity and drag in one Newton solve
(:meth:`ImplicitIntegrator.minimize <implicit_cloth.integrators.base.ImplicitIntegrator.minimize>`).

* :class:`ObstacleBarrier` (conservative): ``U = sum_v kappa_v b(phi(x_v) - xi)`` over the free vertices and
  obstacles, ``phi`` the obstacle's exact signed distance at the step's end, ``xi`` the offset (half the
  thickness) and ``b`` IPC's barrier active within ``dhat`` (the other half): a vertex rests between half the
  thickness and the thickness from the surface and never nearer. ``kappa_v = m_v / dt^2`` (so that the
  barrier's stiffness is the vertex's inertia at the scene's step). Its Hessian is ``kappa b'' n n^T`` per
  vertex plus the curvature term ``kappa b' grad^2 phi`` (negative semidefinite outside a convex shape; kept
  where the shape gives ``grad^2 phi``, scaled so that the block stays positive definite: projected Newton), a
  diagonal block: the system's fixed pattern holds it.
* :meth:`ObstacleBarrier.fractions`: each vertex's move in a Newton iteration is truncated where its path
  would close more than :data:`SAFE` of its gap, or of the barrier's reach for a vertex farther (checked along
  the path: the shape's exact minimum on the segment, then conservative advancement on the 1-Lipschitz
  ``phi``), so no iterate crosses or tunnels through
  an obstacle, however thin (the per-vertex displacement bound of Offset Geometric Contact, Chen et al. 2025,
  made exact along the path for primitives).
* :class:`ObstacleFriction` (dissipative): IPC's lagged smoothed friction, ``D = sum mu lambda f0(|v_t|)``
  with the normal force ``lambda`` and the tangent plane of the step's start, ``f0`` C1 with
  ``f0' = f1(s) = 2 s / eps - s^2 / eps^2`` below the sliding speed ``eps``: Coulomb's law above it. ``v_t`` is
  the cloth's velocity relative to the obstacle's surface (the obstacle's velocity at the contact, lagged).
* Moving and keyframed obstacles: the potential is against each obstacle's pose at the step's end ``t + h``
  (:meth:`ObstacleBarrier.at`), every iterate's path checked against that pose. The first iterate starts the
  vertices (and, for obstacles whose edges are felt, the edges) that the obstacle's motion over the step could
  reach, held at their predicted positions, carried rigidly with it from their step-start positions
  (:meth:`ObstacleBarrier.start`): their gap at the end pose is the one they had at the step's start. So every
  step ends outside every obstacle, and an obstacle never passes through the cloth within a step, however fast.
  The energy balance books the barrier's stored energy (each end at its own pose) and the obstacle's work on
  the cloth, the end-of-step contact and friction forces times its displacement over the step
  (:meth:`ObstacleBarrier.step_work`, :meth:`ObstacleFriction.step_work`).

* Mesh obstacles: ``phi`` is the unsigned distance to the mesh's surface (:class:`MeshField`; two-sided like
  the rounds method's meshes, the cloth stays on the side it is on), exact near it, a lower bound elsewhere
  that the path check's conservative advancement may use; a free vertex that starts inside a closed mesh is
  an error.

Limits: the cloth's vertices and edges against primitives, its vertices only against a mesh (a box corner, or
a mesh's edge or corner, can poke through a cloth triangle's interior or between two vertices); a vertex
carried by a moving obstacle into another obstacle is not resolved (that step's energy is infinite, which the
line search refuses).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ..collision.context import Obstacle, cloth_edges
from ..collision.shapes import MeshShape, Shape
from ..errors import SceneError
from ..forces import ConservativeTerm, DissipativeTerm
from . import barrier

#: A line search moves a vertex at most this fraction of its gap to an obstacle.
SAFE = 0.9
#: No path of a step's first iterate comes nearer an obstacle than this fraction of the barrier's reach
#: (:func:`_path_floor`).
GAP_FLOOR = 1e-6
#: The barrier's stiffness per vertex, in units of its mass over the scene's ``dt^2``.
BARRIER_STIFFNESS = 1.0
#: A vertex that a Newton direction would take into an obstacle is constrained to arrive at this fraction of the
#: barrier's reach from the offset (or half its gap, if it is nearer), where the barrier holds it
#: (:meth:`ObstacleBarrier.normal_targets`).
ARRIVAL = 0.5
#: The most of a vertex's inertia (``m / dt^2``) the barrier's curvature term may take from its Hessian block.
CURVATURE_SHARE = 0.5
#: Conservative-advancement iterations of the path check (:meth:`ObstacleBarrier.fractions`; stopping short is
#: safe: the point reached is never too near).
ADVANCE_ITERATIONS = 20
#: The same for a mesh (:class:`MeshField`), whose distance costs more: its first is OGC's bound (0.9 of the gap).
MESH_ADVANCE_ITERATIONS = 4
#: The finer splits of the step the carry's swept test (:meth:`ObstacleBarrier.start`) tries, one after the other,
#: on the vertices it flags (a vertex in contact with a turning sphere is flagged by the coarse chord's dip).
SWEPT_REFINE = (8, 64)
#: A round shape's edges are felt where a straight edge between two vertices at the offset dips more than this
#: share of the offset toward it (:func:`needs_edges`).
EDGE_DIP = 1.0
#: Passes of the edges' check over the cut moves (:meth:`ObstacleBarrier.fractions`) before the move is scaled.
EDGE_PASSES = 3
#: Point-triangle pairs a mesh's distance query evaluates all at once before it searches the triangles' boxes.
BRUTE_PAIRS = 50_000
#: The friction's sliding speed when the scene gives none, m/s.
FRICTION_SPEED = 1e-3


@dataclass(frozen=True)
class Contacts:
    """The step's obstacle contacts at its start: vertex, obstacle, outward normal (K, 3), normal force
    ``lambda`` (K,) N, friction coefficient (K,) and the obstacle's velocity at the contact over the step
    (K, 3) m/s (None: still)."""

    vertex: np.ndarray
    obstacle: np.ndarray
    normal: np.ndarray
    force: np.ndarray
    mu: np.ndarray
    velocity: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.vertex)


def _add_diagonal_blocks(system: Any, idx: np.ndarray, blocks: np.ndarray) -> None:
    if len(idx):
        np.add.at(system.blocks, system.diag_index[idx], blocks)


class _Stencil(NamedTuple):
    """Contact primitives of one kind near one obstacle: their cloth vertices ``idx`` (K, m), the weights
    ``w`` (K, m) of the closest point ``p = sum_c w_c x_idx_c``, the outward normal there (K, 3), the gap
    ``g = phi(p) - xi`` (K,), the barrier's stiffness (K,) and the obstacle."""

    idx: np.ndarray
    w: np.ndarray
    n: np.ndarray
    g: np.ndarray
    kappa: np.ndarray
    #: the obstacle's index
    obstacle: int = 0
    #: the signed distance's Hessian (K, 3, 3, world axes) at a vertex stencil, when asked for and given
    hess: np.ndarray | None = None


class ObstacleBarrier(ConservativeTerm):
    """The barrier energy of the cloth's free vertices and of its edges against every obstacle (a
    :class:`~implicit_cloth.forces.Force`).

    The gap of an edge is the least ``phi - xi`` along it (the shape's exact segment minimum: a convex
    function of its end points, whose gradient is ``(1 - s) n`` and ``s n`` at the nearest point ``s``), so a
    thin rod between two vertices is felt by the edge across it; edge terms only where the shape needs them
    (:func:`needs_edges`). An edge's Hessian is Gauss-Newton's ``kappa b'' w w^T n n^T``, exact up to the
    negative semidefinite curvature term it drops (a vertex's keeps it: :meth:`_curvature`); its off-diagonal
    block lies on the springs' pattern
    (a mesh edge is a structural spring, a grid's diagonal a shear spring) and is left out where it does not
    (:meth:`SystemMatrix.has_blocks <implicit_cloth.assembly.SystemMatrix.has_blocks>`).
    """

    name = "contact"

    def __init__(self, obstacles: list[Obstacle], free: np.ndarray, kappa: np.ndarray, xi: float,
                 dhat: float, t: float, edges: np.ndarray | None = None, rest: np.ndarray | None = None) -> None:
        self.obstacles = obstacles
        self.free = np.flatnonzero(free)
        self._free_mask = np.asarray(free, dtype=bool)
        self.kappa = kappa[self.free]
        self.xi, self.dhat, self.t = float(xi), float(dhat), float(t)
        #: the step's start time and positions (:meth:`at`); the potential is at ``t``, the step's end
        self.t0 = self.t
        self.x_start: np.ndarray | None = None
        #: which obstacles move (their start differs from their end pose within a step)
        self.moving = [bool(ob.motion.moving) for ob in obstacles]
        e = np.zeros((0, 2), dtype=np.int64) if edges is None else np.asarray(edges, dtype=np.int64)
        rest = np.zeros((len(free), 3)) if rest is None else rest
        e = e[self._free_mask[e[:, 0]] | self._free_mask[e[:, 1]]]          # an edge with a free end
        self.edges = e
        longest = float(np.sqrt(np.max(np.einsum("ij,ij->i", rest[e[:, 1]] - rest[e[:, 0]],
                                                  rest[e[:, 1]] - rest[e[:, 0]]), initial=0.0)))
        #: per obstacle, whether its edges are felt (:func:`needs_edges`)
        self.edged = [needs_edges(ob.shape, longest, self.xi) for ob in obstacles]
        # an edge's share of its ends' stiffness: each vertex has about six edges, each edge two ends
        self.kappa_edge = (kappa[e[:, 0]] + kappa[e[:, 1]]) / 6.0
        #: the safe-move filter's geometry of the last iterate (:meth:`_geometry`)
        self._geo_key: tuple[float, np.ndarray] | None = None
        #: the step's start and the energy stored there (:meth:`step_work`)
        self._start_energy: tuple[np.ndarray, float] | None = None
        self._last_energy: tuple[float, np.ndarray, float] | None = None
        self._geo: list = []

    # ------------------------------------------------------------------ geometry
    def _local(self, ob: Obstacle, x: np.ndarray, t: float | None = None) -> np.ndarray:
        return ob.motion.to_local(x, self.t if t is None else t)

    def _world_normal(self, ob: Obstacle, n: np.ndarray, t: float | None = None) -> np.ndarray:
        return n @ ob.motion.pose(self.t if t is None else t)[1].T

    def _geometry(self, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, tuple | None]]:
        """Per obstacle at its pose at ``t``, what the safe-move filter needs of the iterate ``x`` alone (cached
        for the last ``x``: a Newton iteration filters many moves from one iterate): the free vertices' gaps and
        local positions and, where edges are felt, the edges' local ends, their ends' least gap and half
        length."""
        key = self._geo_key
        if key is not None and key[0] == self.t and np.array_equal(key[1], x):
            return self._geo
        out = []
        e = self.edges
        for ob, edged in zip(self.obstacles, self.edged):
            loc = self._local(ob, x)
            p0 = loc[self.free]
            g0 = ob.shape.closest(p0)[0] - self.xi      # as gaps() has it
            edge_geo = None
            if edged and len(e):
                a0, a1 = loc[e[:, 0]], loc[e[:, 1]]
                ends = np.minimum(ob.shape.distance(a0), ob.shape.distance(a1)) - self.xi
                half = 0.5 * np.sqrt(np.einsum("ij,ij->i", a1 - a0, a1 - a0))
                edge_geo = (a0, a1, ends, half, np.full(len(e), np.nan))
            out.append((g0, p0, edge_geo))
        self._geo_key, self._geo = (self.t, x.copy()), out
        return out

    def at(self, x0: np.ndarray, t0: float, t1: float) -> "ObstacleBarrier":
        """This barrier for the step from ``x0`` at ``t0`` to ``t1``: its potential against the obstacles' poses
        at ``t1`` (:meth:`start` and :meth:`step_work` read the rest)."""
        out = copy.copy(self)
        out.t, out.t0, out.x_start = float(t1), float(t0), np.asarray(x0)
        out._start_energy = None
        out._last_energy = None
        return out

    def stencils(self, x: np.ndarray, reach: float | None = None, t: float | None = None,
                 hessian: bool = False, within: list | None = None) -> list[_Stencil]:
        """The vertex and edge primitives within ``reach`` (default the barrier's) of each obstacle at ``x``,
        the obstacles at their pose at ``t`` (default the potential's, the step's end); ``hessian``: with the
        distance's Hessian at the vertices, where the shape gives it. ``within`` (:meth:`_within`): per obstacle,
        the free vertices and the edges that may be within the barrier's reach; the others are not measured."""
        reach = self.dhat if reach is None else reach
        out = []
        for j, (ob, edged) in enumerate(zip(self.obstacles, self.edged)):
            vsel, esel = (None, None) if within is None else within[j]
            free = self.free if vsel is None else self.free[vsel]
            kappa = self.kappa if vsel is None else self.kappa[vsel]
            loc = self._local(ob, x, t) if within is None else None     # every vertex's, or the rows asked for

            def at(rows: np.ndarray, ob: Obstacle = ob, loc: np.ndarray | None = loc) -> np.ndarray:
                return loc[rows] if loc is not None else self._local(ob, x[rows], t)

            pts = at(free)
            phi, n, c = ob.shape.closest(pts)
            g = phi - self.xi
            near = g < reach
            hess = None
            if hessian and np.any(near):
                H = ob.shape.distance_hessian(pts[near], n[near], c[near])
                if H is not None:
                    R = ob.motion.pose(self.t if t is None else t)[1]
                    hess = np.einsum("ab,kbc,dc->kad", R, H, R)
            out.append(_Stencil(free[near, None], np.ones((int(near.sum()), 1)),
                                self._world_normal(ob, n[near], t), g[near], kappa[near], j, hess))
            if not len(self.edges) or not edged:
                continue
            eidx = np.arange(len(self.edges)) if esel is None else np.flatnonzero(esel)
            if not len(eidx):
                continue
            e = self.edges[eidx]
            a0, a1 = at(e[:, 0]), at(e[:, 1])
            # phi is 1-Lipschitz: an edge is at least (nearer end's phi) - (half its length) away
            ends = np.minimum(ob.shape.distance(a0), ob.shape.distance(a1)) - self.xi
            half = 0.5 * np.sqrt(np.einsum("ij,ij->i", a1 - a0, a1 - a0))
            cand = np.flatnonzero(ends - half < reach)
            if not len(cand):
                continue
            s, _ = ob.shape.segment_minimum(a0[cand], a1[cand])
            p = a0[cand] + s[:, None] * (a1[cand] - a0[cand])
            phi_e, n_e, _ = ob.shape.closest(p)
            g_e = phi_e - self.xi
            # every edge within reach, its nearest point at an end too: leaving those to the vertex term would
            # drop the edge's energy where its nearest point reaches an end, a jump (energy from nowhere)
            inner = g_e < reach
            k = cand[inner]
            out.append(_Stencil(e[k], np.stack([1.0 - s[inner], s[inner]], axis=1),
                                self._world_normal(ob, n_e[inner], t), g_e[inner], self.kappa_edge[eidx[k]], j))
        return out

    def _within(self, x: np.ndarray, t: float) -> list | None:
        """Per obstacle, masks of the free vertices and of the edges that may be within the barrier's reach at
        ``x``, from the last iterate's geometry (:meth:`_geometry`, the same pose): ``phi`` is 1-Lipschitz, so a
        vertex whose gap there less its move since is at least the reach, or an edge whose lower bound there
        (nearer end's gap less half its length) less its faster end's move is, stores no energy. None without
        that geometry (everything is measured)."""
        key = self._geo_key
        if key is None or key[0] != t or key[1].shape != x.shape:
            return None
        d = x - key[1]
        move = np.sqrt(np.einsum("ij,ij->i", d, d))
        out = []
        for g0, _, edge_geo in self._geo:
            vsel = g0 - move[self.free] < self.dhat
            esel = None
            if edge_geo is not None:
                _, _, ends, half, _ = edge_geo
                e = self.edges
                esel = ends - half - np.maximum(move[e[:, 0]], move[e[:, 1]]) < self.dhat
            out.append((vsel, esel))
        return out

    def gaps(self, x: np.ndarray, t: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per obstacle: each free vertex's gap ``phi - xi`` (m) and the outward normal (world axes), the
        obstacles at their pose at ``t`` (default the potential's)."""
        out = []
        for ob in self.obstacles:
            phi, n, _ = ob.shape.closest(self._local(ob, x[self.free], t))
            out.append((phi - self.xi, self._world_normal(ob, n, t)))
        return out

    # ------------------------------------------------------------------ the Force interface
    def energy(self, x: np.ndarray, t: float | None = None) -> float:
        """The stored energy at ``x``, the obstacles at their pose at ``t`` (default the potential's); the last
        answer kept (the balance and its allowance ask for the same iterate)."""
        t = self.t if t is None else t
        last = self._last_energy
        if last is not None and last[0] == t and np.array_equal(last[1], x):
            return last[2]
        e = float(sum(np.dot(st.kappa, barrier.value(st.g, self.dhat))
                      for st in self.stencils(x, t=t, within=self._within(x, t))))
        self._last_energy = (t, x.copy(), e)
        return e

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        for st in self.stencils(x):
            gn = (st.kappa * barrier.first(st.g, self.dhat))[:, None] * st.n
            for c in range(st.idx.shape[1]):
                np.add.at(out, st.idx[:, c], st.w[:, c, None] * gn)

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        for st in self.stencils(x, hessian=True):
            if not len(st.g):
                continue
            k1 = st.kappa * barrier.first(st.g, self.dhat)
            gn = k1[:, None] * st.n
            k2 = st.kappa * barrier.second(st.g, self.dhat)        # d2U/dg2: the Hessian is k2 w w^T n n^T
            nn = st.n[:, :, None] * st.n[:, None, :]
            if st.hess is not None:
                self._curvature(st, k1, c_x, system, kw, w)
            m = st.idx.shape[1]
            for a in range(m):
                np.subtract.at(f, st.idx[:, a], st.w[:, a, None] * gn)
                for b in range(m):
                    H = (c_x * k2 * st.w[:, a] * st.w[:, b])[:, None, None] * nn
                    if a == b:
                        np.add.at(system.blocks, system.diag_index[st.idx[:, a]], H)
                    else:
                        ok = system.has_blocks(st.idx[:, a], st.idx[:, b])
                        if np.any(ok):
                            np.add.at(system.blocks, system.block_index(st.idx[ok, a], st.idx[ok, b]), H[ok])
                    if kw is not None and w is not None:   # (dF/dx) w, accumulated over repeated vertices
                        np.subtract.at(kw, st.idx[:, a], (k2 * st.w[:, a] * st.w[:, b] * np.einsum(
                            "ij,ij->i", st.n, w[st.idx[:, b]]))[:, None] * st.n)

    def _curvature(self, st: _Stencil, k1: np.ndarray, c_x: float, system: Any, kw: np.ndarray | None,
                   w: np.ndarray | None) -> None:
        """The Hessian's curvature term ``kappa b'(g) d2phi/dx2`` at vertex stencils (negative semidefinite
        outside a convex shape: the barrier's force turns with the normal as a vertex slides over a curved
        surface), scaled down where it would take more than :data:`CURVATURE_SHARE` of the vertex's inertia
        ``m / dt^2`` (``kappa`` over :data:`BARRIER_STIFFNESS`), so the system's diagonal block stays positive
        definite. Without it Newton's iterations over a thin rod converge linearly."""
        assert st.hess is not None
        H = k1[:, None, None] * st.hess                              # d2U/dx2's curvature part (<= 0)
        lam = -k1 * np.linalg.eigvalsh(st.hess)[:, -1]              # its largest magnitude
        inertia = st.kappa / BARRIER_STIFFNESS
        scale = np.minimum(1.0, CURVATURE_SHARE * inertia / np.maximum(lam, 1e-300))   # c_x |H| <= share m
        H *= scale[:, None, None]
        i = st.idx[:, 0]
        np.add.at(system.blocks, system.diag_index[i], c_x * H)
        if kw is not None and w is not None:
            np.subtract.at(kw, i, np.einsum("kij,kj->ki", H, w[i]))

    # ------------------------------------------------------------------ safe steps
    def fractions(self, x: np.ndarray, dx: np.ndarray, first: bool = False) -> np.ndarray:
        """Per vertex (N,), the largest ``s <= 1`` such that moving the vertices along ``x + s' dx_v``,
        ``s' <= s``, keeps every primitive's gap above ``(1 - SAFE)`` of what it is at ``x``: for a vertex, a
        continuous check of its path (the shape's exact minimum along the segment, then conservative
        advancement on the 1-Lipschitz ``phi``), so a vertex sliding along a surface is not held back and none
        tunnels through a thin obstacle; for an edge, conservative advancement of its gap (which changes no
        faster than its faster end moves), the cut ends checked again until every edge passes (else the whole
        move is scaled down, a prefix of one that passed). 1 for pinned vertices."""
        s = np.ones(len(x))
        p0w, dw = x[self.free], dx[self.free]
        step = np.sqrt(np.einsum("ij,ij->i", dw, dw))
        geo = self._geometry(x)
        for (g0, p0, _), ob in zip(geo, self.obstacles):
            # phi must stay above this along the path: (1 - SAFE) of the gap, of the barrier's reach for a vertex
            # farther (one arriving from afar reaches the barrier's zone in one move)
            target = self.xi + _path_floor(g0, self.dhat, first)
            # phi is 1-Lipschitz: a path shorter than its start's phi less the target is safe unchecked (and a
            # vertex that does not move crosses nothing); at the step's first iterate a vertex already within the
            # offset of a moving obstacle's end pose is the carry's (start), not cut here
            near = np.flatnonzero((step > 0.0) & (g0 + self.xi - step < target) & ~(first & (g0 <= 0.0)))
            if not len(near):
                continue
            p1 = self._local(ob, p0w[near] + dw[near])
            low = _segment_low(ob.shape, p0[near], p1)
            hit = low < target[near]
            near, p1 = near[hit], p1[hit]
            if len(near):
                adv = _advance(ob.shape, p0[near], p1 - p0[near], target[near], g0[near] + self.xi,
                               MESH_ADVANCE_ITERATIONS if ob.shape.name == "mesh" else ADVANCE_ITERATIONS)
                s[self.free[near]] = np.minimum(s[self.free[near]], adv)
        if not len(self.edges) or not any(self.edged):
            return s
        for _ in range(EDGE_PASSES):
            cut = self._edge_fractions(x, dx * s[:, None], first)
            if cut is None:
                return s
            e, f = cut
            np.minimum.at(s, e[:, 0], s[e[:, 0]] * f)
            np.minimum.at(s, e[:, 1], s[e[:, 1]] * f)
        cut = self._edge_fractions(x, dx * s[:, None], first)
        if cut is not None:                 # scaled down as a whole: a prefix of the move just checked
            s *= float(cut[1].min())
        return s

    def normal_targets(self, x: np.ndarray, move: np.ndarray, idx: np.ndarray, full: np.ndarray,
                       stiffness: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of the vertices ``idx`` (cut moves ``move``, whole moves ``full``, (N, 3)), those whose cut move ends
        within the barrier's reach of an obstacle: the vertices, the obstacle's outward normal ``n`` at that end
        (the nearest obstacle's) and the move along ``n`` that brings each to its arrival gap ``g*`` to first
        order (exact for the plane): ``n . move + (xi + g* - phi(end))``. ``g*`` is where the barrier holds the
        vertex against its pull toward where the whole move would take it (``stiffness`` (N,) N/m, the system's
        along the normal without the barrier: :func:`barrier.equilibrium`), at least twice the path's floor."""
        idx = np.asarray(idx, dtype=np.int64)
        idx = idx[self._free_mask[idx]]
        if not len(idx) or not self.obstacles:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
        end = x[idx] + move[idx]
        best = np.full(len(idx), np.inf)
        nrm = np.zeros((len(idx), 3))
        g0 = np.full(len(idx), np.inf)
        for ob in self.obstacles:
            phi, n, _ = ob.shape.closest(self._local(ob, end))
            nearer = phi < best
            best = np.where(nearer, phi, best)
            nrm[nearer] = self._world_normal(ob, n[nearer])
            g0 = np.where(nearer, ob.shape.distance(self._local(ob, x[idx])) - self.xi, g0)
        near = best - self.xi < self.dhat
        idx, nrm, best, g0 = idx[near], nrm[near], best[near], g0[near]
        g_end = best - self.xi
        g_free = g_end + np.einsum("ij,ij->i", nrm, full[idx] - move[idx])     # the whole move, to first order
        kappa = self.kappa[np.searchsorted(self.free, idx)]
        target = barrier.equilibrium(stiffness[idx], g_free, kappa, self.dhat)
        floor = _path_floor(np.maximum(g0, 0.0), self.dhat)
        target = np.clip(target, 2.0 * floor, np.maximum(g0, 2.0 * floor))
        m = np.einsum("ij,ij->i", nrm, move[idx]) + (target - g_end)
        return idx, nrm, m

    def filter_move(self, x: np.ndarray, dx: np.ndarray, first: bool = False) -> np.ndarray:
        """``dx`` with each vertex's move cut to what its path allows (:meth:`fractions`); ``dx`` itself when
        nothing is cut. ``first``: the step's first iterate (its paths also kept off :data:`GAP_FLOOR`)."""
        s = self.fractions(x, dx, first)
        return dx * s[:, None] if np.any(s < 1.0) else dx

    def _edge_fractions(self, x: np.ndarray, dx: np.ndarray, first: bool = False
                        ) -> tuple[np.ndarray, np.ndarray] | None:
        """The edges whose gap the move ``dx`` would close by more than :data:`SAFE`, and the fraction of the
        move each allows (conservative advancement); None when every edge passes."""
        e = self.edges
        vspeed = np.sqrt(np.einsum("ij,ij->i", dx, dx))
        fastest = float(vspeed.max(initial=0.0))
        bad_e: list[np.ndarray] = []
        bad_f: list[np.ndarray] = []
        for ob, edged, (_, _, edge_geo) in zip(self.obstacles, self.edged, self._geometry(x)):
            if not edged:
                continue
            assert edge_geo is not None
            a0, a1, ends, half, low_all = edge_geo
            # only edges the move could bring near: gap lower bound minus the move below (1 - SAFE) of a gap
            cand = np.flatnonzero(ends - half - fastest < self.dhat)
            speed = np.maximum(vspeed[e[cand, 0]], vspeed[e[cand, 1]])     # each candidate's faster end
            keep = (speed > 0) & (ends[cand] - half[cand] - speed < self.dhat)
            cand, speed = cand[keep], speed[keep]
            if not len(cand):
                continue
            unknown = cand[np.isnan(low_all[cand])]        # each edge's least distance at x, once an iterate
            if len(unknown):
                low_all[unknown] = ob.shape.segment_minimum(a0[unknown], a1[unknown])[1]
            g0 = low_all[cand] - self.xi
            if first:               # an edge already within a moving obstacle's end pose is the carry's (start)
                out = g0 > 0.0
                cand, speed, g0 = cand[out], speed[out], g0[out]
            floor = _path_floor(g0, self.dhat, first)           # as for the vertices (fractions)
            target = self.xi + floor
            lin = g0 - speed > floor                             # 1-Lipschitz: the whole move is safe
            check = np.flatnonzero(~lin)
            if not len(check):
                continue
            k = cand[check]
            d0 = self._local(ob, x[e[k, 0]] + dx[e[k, 0]]) - a0[k]
            d1 = self._local(ob, x[e[k, 1]] + dx[e[k, 1]]) - a1[k]
            f = _edge_advance(ob.shape, a0[k], a1[k], d0, d1, target[check], speed[check],
                              0.01 * (g0[check] + self.xi))
            short = f < 1.0
            if np.any(short):
                bad_e.append(e[k[short]])
                bad_f.append(f[short])
        if not bad_e:
            return None
        return np.concatenate(bad_e), np.concatenate(bad_f)

    # ------------------------------------------------------------------ moving obstacles
    def start(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """The first iterate's move ``dx`` from ``x`` (the scheme's predicted positions, ``dx`` already cut by
        :meth:`filter_move`) with every vertex a moving obstacle could pass through during the step carried
        with it instead: such a vertex starts at its step-start position moved rigidly from the obstacle's
        start pose to its end pose (``T1 T0^-1 x_start``), so its gap to that obstacle at the end pose is the
        gap it had at the step's start, > 0 (the previous step ended outside every obstacle's pose at this
        step's start). ``dx`` itself when nothing is carried.

        A vertex is carried when the least gap of its predicted position held still, along the obstacle's
        motion over ``[t0, t1]``, can be <= 0 (:meth:`_swept`: in the obstacle's frame the held point moves on
        a curve; the shape's exact minimum on its chord between keyframes, less the chord's deviation bound
        second order in the step's turn); for an obstacle whose edges are felt, both ends of an
        edge whose nearer end's bound is within half the edge of the offset (``phi`` is 1-Lipschitz: every
        point of the edge is then cleared), and both ends of any edge the carried start still leaves within
        the offset at the end pose (until none; a carried edge is a rigid copy of a step-start edge, outside).
        The vertices not carried start where the cut move takes them from a predicted position that no pose of
        the obstacle during the step reaches: outside its end pose, and every later iterate stays outside
        (:meth:`fractions`), so the step ends outside. Limit: a vertex carried by one obstacle into another
        (pressed between the two) is left there (the step's energy is then infinite, which the line search
        refuses)."""
        if self.x_start is None or not any(self.moving):
            return dx
        n = len(x)
        y = x + dx
        carried = np.zeros(n, dtype=bool)
        e = self.edges
        for k, ob in enumerate(self.obstacles):
            if not self.moving[k]:
                continue
            low = np.full(n, np.inf)
            low[self.free] = self._swept(ob, x[self.free])
            for pieces in SWEPT_REFINE:     # the bound again on finer pieces where it flags a vertex
                again = self.free[low[self.free] <= self.xi]
                if not len(again):
                    break
                low[again] = self._swept(ob, x[again], pieces)
            take = np.zeros(n, dtype=bool)
            take[self.free] = low[self.free] <= self.xi
            if self.edged[k] and len(e):
                half = 0.5 * np.sqrt(np.einsum("ij,ij->i", x[e[:, 1]] - x[e[:, 0]], x[e[:, 1]] - x[e[:, 0]]))
                near = np.minimum(low[e[:, 0]], low[e[:, 1]]) - half <= self.xi
                take[e[near].ravel()] = True
            take &= self._free_mask & ~carried
            if np.any(take):
                y[take] = self._carry(ob, self.x_start[take])
                carried |= take
            if not (self.edged[k] and len(e)):
                continue
            for _ in range(len(e)):                      # edges the carried start leaves within the offset
                a0, a1 = self._local(ob, y[e[:, 0]]), self._local(ob, y[e[:, 1]])
                _, low_e = ob.shape.segment_minimum(a0, a1)
                grow = np.zeros(n, dtype=bool)
                grow[e[low_e <= self.xi].ravel()] = True
                grow &= self._free_mask & ~carried
                if not np.any(grow):
                    break
                y[grow] = self._carry(ob, self.x_start[grow])
                carried |= grow
        return y - x if np.any(carried) else dx

    def _carry(self, ob: Obstacle, p: np.ndarray) -> np.ndarray:
        """World points at the step's start moved with the obstacle to its end pose: ``T1 T0^-1 p``."""
        return ob.motion.to_world(ob.motion.to_local(p, self.t0), self.t)

    def _swept(self, ob: Obstacle, p: np.ndarray, pieces: int = 1) -> np.ndarray:
        """A lower bound (K,) of ``phi`` at the world points ``p`` held still while the obstacle moves from its
        pose at ``t0`` to ``t1``. Piece by piece between the keyframes inside the step (where the centre moves
        at a constant velocity ``u`` and the frame turns at a constant angular velocity ``omega``): the local
        point ``l(tau) = R^T (p - c)`` has ``|l''| <= |omega|^2 |p - c| + 2 |omega| |u|``, so it differs from its
        chord by at most ``(b - a)^2 / 8`` times that (``|p - c|`` at its larger end: ``p - c`` is linear), and
        ``phi`` is 1-Lipschitz: the chord's exact minimum less that bound is a lower bound along the curve.
        ``pieces``: each piece split into this many (the bound falls as their square)."""
        times = np.asarray(getattr(ob.motion, "times", ()), dtype=float)
        knots = np.concatenate([[self.t0], times[(times > self.t0) & (times < self.t)], [self.t]])
        if pieces > 1:
            knots = np.concatenate([np.linspace(a, b, pieces + 1)[:-1] for a, b in zip(knots[:-1], knots[1:])]
                                   + [knots[-1:]])
        low = np.full(len(p), np.inf)
        for a, b in zip(knots[:-1], knots[1:]):
            qa, qb = ob.motion.to_local(p, a), ob.motion.to_local(p, b)
            chord = _segment_low(ob.shape, qa, qb)
            u, omega = ob.motion.twist(0.5 * (a + b))
            w = float(np.linalg.norm(omega))
            if w > 0.0:
                ca, cb = ob.motion.pose(a)[0], ob.motion.pose(b)[0]
                r = np.maximum(np.linalg.norm(p - ca, axis=1), np.linalg.norm(p - cb, axis=1))
                chord = chord - (b - a) ** 2 / 8.0 * (w * w * r + 2.0 * w * float(np.linalg.norm(u)))
            low = np.minimum(low, chord)
        return low

    def displacement(self, ob: Obstacle, p: np.ndarray) -> np.ndarray:
        """The step's displacement (K, 3) of the obstacle's material points at world ``p`` at its end:
        ``p - T0 T1^-1 p`` (0 for an obstacle that does not move)."""
        return p - ob.motion.to_world(ob.motion.to_local(p, self.t), self.t0)

    def start_energy(self, x0: np.ndarray) -> float:
        """The energy stored at the step's start ``x0`` against the obstacles' poses then, J; once a step (every
        iterate's balance asks)."""
        e0 = self._start_energy
        if e0 is None or e0[0] is not x0:
            e0 = self._start_energy = (x0, self.energy(x0, self.t0))
        return e0[1]

    def step_work(self, x0: np.ndarray, x1: np.ndarray, v1: np.ndarray, h: float) -> float:
        """The energy the step's balance books for the barrier, J: what it gave back,
        ``U(x0; T0) - U(x1; T1)`` (each against the obstacles' pose at its time), plus the work the moving
        obstacles did on the cloth through it: ``U`` is a function of the cloth's position relative to the
        obstacle, so moving the obstacle by ``delta`` at a contact changes it by ``F . delta`` (``F =
        -dU/dx`` the contact force on the cloth), here the end-of-step force times the step's displacement of
        the obstacle's material point at the contact (backward Euler's quadrature)."""
        work = self.start_energy(x0) - self.energy(x1)
        if not any(self.moving):
            return work
        for st in self.stencils(x1):
            if not len(st.g) or not self.moving[st.obstacle]:
                continue
            p = np.einsum("kc,kcj->kj", st.w, x1[st.idx])
            f = -(st.kappa * barrier.first(st.g, self.dhat))[:, None] * st.n      # on the cloth, N
            work += float(np.einsum("ij,ij->", f, self.displacement(self.obstacles[st.obstacle], p)))
        return work

    def active(self, x: np.ndarray) -> int:
        """Vertex and edge primitives within the barrier's reach at ``x``."""
        return int(sum(len(st.g) for st in self.stencils(x)))


def _path_floor(g0: np.ndarray, dhat: float, first: bool = False) -> np.ndarray:
    """The least gap a path from gap ``g0`` may reach in one move: ``1 - SAFE`` of the gap (of the barrier's reach
    for a vertex farther); for the step's ``first`` iterate never under :data:`GAP_FLOOR` of the reach either (nor
    below ``g0`` if it is already nearer). The first iterate is the step's start velocity, cut: a vertex resting
    on an obstacle with a little velocity toward it (a corner of the triangle membrane's crumple pushed into the
    floor by its compressed triangles) lost nine tenths of its gap to it every step, the Newton corrections that
    would lift it scaled to nothing by the rest of the cloth's cuts, until the gap was 0 in floating point and
    the barrier's energy infinite. A floor on every iterate cost the 64² crumple a third more solves (7.3 a
    substep); at 1e-4 on the first iterate the denim crumple of benchmarks/cloth_models.py created energy in a
    step (a vertex held short of the step's minimiser), at 1e-6 and 1e-8 it did not."""
    floor = (1.0 - SAFE) * np.minimum(g0, dhat)
    return np.maximum(floor, np.minimum(g0, GAP_FLOOR * dhat)) if first else floor


def _segment_low(shape: Any, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """The least signed distance along each segment ``p0 -> p1`` (local points): at an end for the plane (its
    distance is linear along a segment), the shape's segment minimum otherwise."""
    if shape.name == "plane":
        return np.minimum(shape.distance(p0), shape.distance(p1))
    return shape.segment_minimum(p0, p1)[1]


def needs_edges(shape: Any, longest: float, xi: float) -> bool:
    """Whether the cloth's edges must be kept off a shape, not only its vertices: a shape with sharp features
    (box, cone), or one so thin that a straight edge between two vertices at the offset could reach it
    (``L^2 / (8 R) >`` :data:`EDGE_DIP` ``xi``, ``L`` the longest edge at rest, ``R`` the shape's radius). Felt
    where a chord dips only half the offset, a sphere of 0.15 m passing through a 32² sheet dragged it along
    (strain 1.5 in 0.47 s): the chords' gaps of a few micrometres cut their vertices' moves to nothing, every
    iteration.
    Edge terms on a large curved shape add nothing the vertices do not keep and, at large steps, cost energy:
    their gaps close to a few hundred nanometres as the cloth slides (the chord is nearer than its ends), and
    backward Euler's end-of-step force on a curved barrier then gains energy (a 32² drape on a 0.3 m sphere
    gained 0.39 J in one step with them, none without)."""
    if shape.name in ("plane", "mesh"):       # a mesh: its vertices only (a limit: see the module notes)
        return False
    radius = getattr(shape, "radius", 0.0) if shape.name in ("sphere", "capsule") else 0.0
    return radius <= 0.0 or longest * longest / (8.0 * radius) > EDGE_DIP * xi


def _edge_advance(shape: Any, a0: np.ndarray, a1: np.ndarray, d0: np.ndarray, d1: np.ndarray, target: np.ndarray,
                  speed: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Per edge, the fraction of its ends' moves ``d0, d1`` (local) that conservative advancement of its gap
    reaches before ``target`` (the gap changes no faster than the faster end moves, ``speed``), within ``tol``."""
    frac = np.zeros(len(a0))
    live = np.arange(len(a0))
    for _ in range(ADVANCE_ITERATIONS):
        _, low = shape.segment_minimum(a0[live] + frac[live, None] * d0[live], a1[live] + frac[live, None] * d1[live])
        gap = low - target[live]
        frac[live] = np.minimum(frac[live] + np.maximum(gap, 0.0) / speed[live], 1.0 + 1e-12)
        live = live[(gap > tol[live]) & (frac[live] <= 1.0)]
        if not len(live):
            break
    return np.clip(frac, 0.0, 1.0)


def _advance(shape: Any, p0: np.ndarray, d: np.ndarray, target: np.ndarray, scale: np.ndarray,
             iterations: int = ADVANCE_ITERATIONS) -> np.ndarray:
    """Conservative advancement along ``p0 + s d`` (s in [0, 1], local points) until the shape's distance is
    within 1 % of ``scale`` above ``target`` (the distance is 1-Lipschitz): the fraction reached, never past
    where it would come below ``target``."""
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    s = np.zeros(len(p0))
    live = np.arange(len(p0))
    tol = 0.01 * scale
    for _ in range(iterations):
        g = shape.distance(p0[live] + s[live, None] * d[live]) - target[live]
        s[live] += np.maximum(g, 0.0) / np.maximum(length[live], 1e-300)
        live = live[(g > tol[live]) & (s[live] < 1.0)]
        if not len(live):
            break
    return np.clip(s, 0.0, 1.0)


class MeshField(Shape):
    """The unsigned distance to a mesh obstacle's surface (local frame), the ``phi`` of a mesh for the barrier
    (two-sided, like the rounds method's meshes: the cloth stays on the side it is on; the unsigned distance is
    1-Lipschitz and reaches 0 on the surface, so a path that keeps it above the offset crosses no triangle).

    Exact (closest point over the triangles whose boxes meet the cube of the nearest mesh vertex's distance, which
    holds the nearest triangle) where the point may be within ``exact_within`` of the surface; elsewhere the larger
    of the lower bounds ``|p - nearest vertex| - longest edge`` (every surface point is within the longest edge
    of a vertex) and the distance to the mesh's bounding box, which is all the path check's conservative
    advancement needs there (a lower bound never lets it overshoot). No segment minimum: :meth:`segment_minimum`
    bounds a segment by its ends less half its length."""

    name = "mesh"
    exact_distance = True

    def __init__(self, mesh: MeshShape, exact_within: float) -> None:
        from scipy.spatial import cKDTree

        self.mesh = mesh
        self.tri = mesh.vertices[mesh.faces]
        self.tree = cKDTree(mesh.vertices)
        ev = mesh.vertices[mesh.edges]
        self.rmax = float(np.sqrt(np.max(np.einsum("ij,ij->i", ev[:, 1] - ev[:, 0], ev[:, 1] - ev[:, 0]))))
        self.exact_within = float(exact_within)
        #: the last query and its answer (the same points are asked again within an iteration)
        self._last: tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance (K,) m (a lower bound beyond ``exact_within``), unit normal from the surface to the point
        (K, 3) and the nearest surface point (K, 3)."""
        from ..collision.ccd import point_triangle_closest

        last = self._last
        if last is not None and last[0].shape == p.shape and np.array_equal(last[0], p):
            return last[1]
        dv, iv = self.tree.query(p)
        q = self.mesh.vertices[iv]
        lo, hi = self.mesh.bounds
        box = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        d = np.maximum(dv - self.rmax, np.sqrt(np.einsum("ij,ij->i", box, box)))
        near = np.flatnonzero(d <= self.exact_within)
        d = np.maximum(d, 0.0)
        if len(near):
            pn, r = p[near], dv[near][:, None] * (1.0 + 1e-9) + 1e-12
            k, f = len(near), len(self.tri)
            if k * f <= BRUTE_PAIRS:              # a small mesh: every triangle (no box search to set up)
                P = np.repeat(pn, f, axis=0)
                qq, _ = point_triangle_closest(P, np.tile(self.tri[:, 0], (k, 1)), np.tile(self.tri[:, 1], (k, 1)),
                                               np.tile(self.tri[:, 2], (k, 1)))
                dd = np.einsum("ij,ij->i", P - qq, P - qq).reshape(k, f)
                j = np.argmin(dd, axis=1)
                d[near] = np.sqrt(dd[np.arange(k), j])
                q[near] = qq.reshape(k, f, 3)[np.arange(k), j]
            else:
                b, t = self.mesh.index.overlaps(pn - r, pn + r)
                qq, _ = point_triangle_closest(pn[b], self.tri[t, 0], self.tri[t, 1], self.tri[t, 2])
                dd = np.sqrt(np.einsum("ij,ij->i", pn[b] - qq, pn[b] - qq))
                order = np.lexsort((dd, b))                              # each point's nearest triangle first
                bs = b[order]
                first = order[np.r_[True, bs[1:] != bs[:-1]]]
                rows = near[b[first]]
                d[rows] = dd[first]
                q[rows] = qq[first]
        diff = p - q
        length = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        n = diff / np.maximum(length, 1e-300)[:, None]
        self._last = (p.copy(), (d, n, q))
        return d, n, q

    def distance(self, p: np.ndarray) -> np.ndarray:
        return self.closest(p)[0]

    def segment_minimum(self, a0: np.ndarray, a1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A lower bound of the distance along each segment (at its midpoint's parameter): the nearer end's less
        half the segment's length."""
        half = 0.5 * np.sqrt(np.einsum("ij,ij->i", a1 - a0, a1 - a0))
        return np.full(len(a0), 0.5), np.minimum(self.distance(a0), self.distance(a1)) - half


class ObstacleFriction(DissipativeTerm):
    """IPC's lagged smoothed friction on the contacts of the step's start (a dissipative
    :class:`~implicit_cloth.forces.Force`): the sliding velocity is the cloth's relative to the obstacle's surface,
    ``v_t = P (v - u)`` with the obstacle's velocity ``u`` at the contact over the step (lagged like the normal:
    :attr:`Contacts.velocity`; 0 for a still obstacle)."""

    name = "friction"

    def __init__(self, contacts: Contacts, eps: float) -> None:
        keep = (contacts.mu > 0) & (contacts.force > 0)
        self.idx = contacts.vertex[keep]
        self.n = contacts.normal[keep]
        self.scale = (contacts.mu * contacts.force)[keep]      # mu lambda, N
        self.eps = float(eps)
        self.u = None if contacts.velocity is None else contacts.velocity[keep]

    def _tangent(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = v[self.idx] if self.u is None else v[self.idx] - self.u
        vt = u - np.einsum("ij,ij->i", u, self.n)[:, None] * self.n
        return vt, np.sqrt(np.einsum("ij,ij->i", vt, vt))

    def step_work(self, x0: np.ndarray, x1: np.ndarray, v1: np.ndarray, h: float) -> float:
        """The moving obstacles' work on the cloth through friction in the step, J: the end-of-step friction force
        times the obstacle's displacement ``h u`` at each contact (the rest of the friction's power, against the
        relative velocity, is dissipated)."""
        if self.u is None or not len(self.idx):
            return 0.0
        vt, s = self._tangent(v1)
        fc = -(self.scale * self._over_s(s))[:, None] * vt                  # each contact's force on the cloth
        return h * float(np.einsum("ij,ij->", fc, self.u))

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        _, s = self._tangent(v)
        e = self.eps
        f0 = np.where(s < e, s * s / e - s ** 3 / (3 * e * e) + e / 3, s)
        return float(np.dot(self.scale, f0))

    def _over_s(self, s: np.ndarray) -> np.ndarray:
        """``f1(s) / s``, finite at 0."""
        e = self.eps
        return np.where(s < e, 2.0 / e - s / (e * e), 1.0 / np.maximum(s, e))

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        vt, s = self._tangent(v)
        np.subtract.at(out, self.idx, (self.scale * self._over_s(s))[:, None] * vt)

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        if not len(self.idx):
            return
        self.force(x, v, t, f)
        vt, s = self._tangent(v)
        e = self.eps
        over = self._over_s(s)
        slope = np.where(s < e, 2.0 / e - 2.0 * s / (e * e), 0.0)            # f1'(s)
        that = vt / np.maximum(s, 1e-300)[:, None]
        P = np.eye(3)[None] - self.n[:, :, None] * self.n[:, None, :]
        tt = that[:, :, None] * that[:, None, :]
        H = self.scale[:, None, None] * (slope[:, None, None] * tt + over[:, None, None] * (P - tt))
        _add_diagonal_blocks(system, self.idx, c_v * H)


class ObstacleContact:
    """The obstacle stage of ``collision.method = "barrier"``: detection (:meth:`detect`, a value) and the
    step's contact forces built from it (:meth:`terms`).

    Raises
    ------
    SceneError
        Naming the obstacle, for free cloth vertices that start inside a closed mesh or within half the
        thickness of an obstacle.
    """

    def __init__(self, obstacles: list[dict[str, Any]], settings: dict[str, Any], model: Any, dt: float) -> None:
        self.obstacles = [Obstacle.from_spec(s) for s in obstacles]
        self.thickness = float(settings["thickness"])
        self.xi = self.dhat = 0.5 * self.thickness
        eps = float(settings.get("friction_speed", FRICTION_SPEED))
        if eps <= 0:
            raise SceneError("collision.friction_speed: the barrier method's friction is smoothed below a sliding "
                             "speed > 0 (Coulomb's sticking and sliding states are the rounds method's), got 0")
        self.eps = eps
        self.free = np.ones(model.n, dtype=bool)
        self.free[model.pinned] = False
        self.kappa = BARRIER_STIFFNESS * model.masses / float(dt) ** 2
        # a mesh's phi for the barrier: its unsigned distance (MeshField), exact within twice the thickness
        fields = [dataclasses.replace(ob, shape=MeshField(ob.shape, 2.0 * self.thickness))
                  if isinstance(ob.shape, MeshShape) else ob for ob in self.obstacles]
        self.barrier = ObstacleBarrier(fields, self.free, self.kappa, self.xi, self.dhat, 0.0,
                                       cloth_edges(np.asarray(model.faces, dtype=np.int64)), model.rest_positions)
        for k, ob in enumerate(self.obstacles):
            if isinstance(ob.shape, MeshShape):
                inside = self.depths(k, model.rest_positions, 0.0)[self.free] > 0
                if np.any(inside):
                    raise SceneError(f"obstacles[{k}]: {int(inside.sum())} free cloth vertices start inside the "
                                     f"closed mesh {ob.describe()}, where the barrier method cannot start: move "
                                     f"the cloth or the obstacle apart")
        start = min((float(g.min()) for g, _ in self.barrier.gaps(model.rest_positions) if len(g)), default=np.inf)
        if start <= 0:
            raise SceneError(f"obstacles: free cloth vertices start within half the thickness "
                             f"({self.xi:g} m) of an obstacle, where the barrier method cannot start (the "
                             f"nearest is {start + self.xi:.3g} m from its surface): move the cloth or the "
                             f"obstacle apart")

    @property
    def edges(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def reset(self) -> None:
        """Nothing is carried from step to step."""

    def detect(self, x: np.ndarray, t: float = 0.0, h: float = 0.0) -> Contacts:
        """The contacts at ``x`` (the step's start, the obstacles at their pose at ``t``): vertices within the
        barrier's reach, their normals and normal forces ``kappa |b'(gap)|``, and the obstacle's velocity at
        each over the step of ``h`` (its displacement there over ``h``; None when no obstacle moves)."""
        vs, obs, ns, lams, mus, us = [], [], [], [], [], []
        bar = self.barrier.at(x, t, t + h)
        for k, (g, n) in enumerate(bar.gaps(x, t)):
            on = g < self.dhat
            idx = bar.free[on]
            vs.append(idx)
            obs.append(np.full(int(on.sum()), k))
            ns.append(n[on])
            lams.append(-bar.kappa[on] * barrier.first(g[on], self.dhat))
            mus.append(np.full(int(on.sum()), self.obstacles[k].friction))
            if bar.moving[k] and h > 0:     # the material point at x at t, over the step: (T1 T0^-1 x - x) / h
                us.append((bar._carry(self.obstacles[k], x[idx]) - x[idx]) / h)
            else:
                us.append(np.zeros((len(idx), 3)))
        moving = any(bar.moving) and h > 0
        return Contacts(np.concatenate(vs), np.concatenate(obs), np.concatenate(ns).reshape(-1, 3),
                        np.concatenate(lams), np.concatenate(mus),
                        np.concatenate(us).reshape(-1, 3) if moving else None)

    def terms(self, contacts: Contacts, x0: np.ndarray | None = None, t: float = 0.0,
              h: float = 0.0) -> list[Any]:
        """The step's contact forces: the barrier against the obstacles' poses at the step's end ``t + h`` (from
        ``x0`` at ``t``: :meth:`ObstacleBarrier.at`), and the friction of ``contacts`` where it has any."""
        bar = self.barrier if x0 is None else self.barrier.at(x0, t, t + h)
        out: list[Any] = [bar]
        if len(contacts) and np.any(contacts.mu > 0):
            out.append(ObstacleFriction(contacts, self.eps))
        return out

    def depths(self, k: int, x: np.ndarray, t: float) -> np.ndarray:
        """Depth (m, > 0 inside) of world points ``x`` inside obstacle ``k``."""
        ob = self.obstacles[k]
        if isinstance(ob.shape, MeshShape):           # inside a closed mesh (winding number), else 0
            return ob.shape.depth(ob.motion.to_local(x, t))
        return np.maximum(-ob.shape.distance(ob.motion.to_local(x, t)), 0.0)
