"""The cloth against itself as a term of the step's incremental potential (``collision.method = "barrier"`` with
``self_collision = true``), on the IPC Toolkit (``ipctk``: Li et al. 2020's barrier over point-triangle and
edge-edge distances, and Offset Geometric Contact's per-vertex trust regions, Chen et al. 2025).

* :class:`ClothBarrier` (conservative): IPC's barrier on every pair of non-adjacent primitives (point-triangle,
  edge-edge; within a piece and between pieces) nearer than ``xi + dhat``: infinite at ``xi`` (half the
  thickness), zero beyond (``dhat``, the other half), so layers rest between half the thickness and the
  thickness apart and never nearer. Its stiffness is the mean vertex mass over ``dt^2 dhat^2`` (the toolkit's
  barrier is on squared distances). Its Hessian
  (projected to positive semidefinite pair by pair) couples vertices the springs' pattern does not: its
  diagonal blocks go into the system (the multigrid sees them), the rest into the solve's product
  (:attr:`ClothBarrier.coupling`).
* :meth:`ClothBarrier.filter_move`: each vertex's move cut to the distance it may move on its own without any
  pair coming within ``xi`` (OGC's per-vertex bound, compiled: :mod:`implicit_cloth.kernels.proximity`), so no
  iterate crosses the cloth, without CCD, and a pair in contact does not hold the rest of the cloth back.
  (Tried first and left: ``ipctk.ogc``'s planar divide-and-truncate removed every move, however small, of a
  few hundred vertices of a 32² sheet falling onto a rod; the global CCD step, one pair in contact stopped the
  whole sheet.)
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from ..forces import ConservativeTerm, DissipativeTerm

#: A vertex moves at most this fraction of its safe distance in one Newton iteration: under half (OGC's gamma_p),
#: since a vertex's safe distance is how far it may move with everything else still, and both sides
#: of a pair move (with 0.9 two stacked sheets came 0.3 mm within the offset on one run)
SAFE = 0.45
#: The candidates are gathered this many times the longest move (plus the offset) out, so that the safe
#: distances' cap there lets the fastest vertex move whole (SAFE x INFLATION > 1).
INFLATION = 2.5
#: The proximity grid has cells no smaller than the cloth's extent over this
GRID_CELLS = 64


class ClothBarrier(ConservativeTerm):
    """The cloth's self-contact barrier for one step (a :class:`~implicit_cloth.forces.Force`), its trust
    regions centred at the step's start ``x0``."""

    name = "self_contact"

    def __init__(self, mesh: Any, potential: Any, xi: float, dhat: float, x0: np.ndarray,
                 primitives: "_Primitives") -> None:
        import ipctk

        self._ipc = ipctk
        self.mesh, self.potential = mesh, potential
        self.xi, self.dhat = float(xi), float(dhat)
        #: the off-diagonal part of the last Hessian (c_x scaled), for the solve's product; None if none
        self.coupling: sp.csr_matrix | None = None
        self._key: tuple[int, bytes] | None = None
        self._collisions: Any = None
        #: Newton iterations whose barrier Hessian was not finite and was left out
        self.skipped = 0
        #: the last iterate's safe distances and the radius they were gathered in (:meth:`_safe_distances`)
        self._safe_key: tuple[float, np.ndarray] | None = None
        self._safe = np.zeros(0)
        self._primitives = primitives

    def _collisions_at(self, x: np.ndarray) -> Any:
        """The pairs within reach at ``x`` (cached for the last ``x``)."""
        key = (x.shape[0], x.tobytes())
        if self._key != key:
            c = self._ipc.NormalCollisions()
            if not self._beyond_reach(x):
                c.build(self.mesh, _f(x), self.dhat, self.xi)
            self._collisions, self._key = c, key
        return self._collisions

    def _beyond_reach(self, x: np.ndarray) -> bool:
        """Whether the last safe distances (:meth:`_safe_distances`, at ``x_ref``) prove that no pair of
        non-adjacent primitives is within the barrier's reach ``xi + dhat`` at ``x``: every pair's distance at
        ``x_ref`` is at least the least safe distance plus ``xi``, and a pair's distance changes by at most twice
        the longest move of a vertex beside the cloth's common translation (which moves no pair). The line
        search's points and the iterates of a cloth far from itself skip the toolkit's collision set."""
        key = self._safe_key
        if key is None or key[1].shape != x.shape or not len(x):
            return False
        rel = x - key[1]
        rel -= rel.mean(axis=0)
        reach = float(np.sqrt(np.max(np.einsum("ij,ij->i", rel, rel))))
        return float(self._safe.min()) - 2.0 * reach > self.dhat

    def pairs_within_reach(self, x: np.ndarray) -> int:
        return len(self._collisions_at(x))

    def distance(self, x: np.ndarray) -> float:
        """The least distance between non-adjacent primitives within reach at ``x`` (inf if none), m."""
        c = self._collisions_at(x)
        return float(np.sqrt(c.compute_minimum_distance(self.mesh, _f(x)))) if len(c) else np.inf

    # ------------------------------------------------------------------ the Force interface
    def energy(self, x: np.ndarray) -> float:
        c = self._collisions_at(x)
        return float(self.potential(c, self.mesh, _f(x))) if len(c) else 0.0

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        c = self._collisions_at(x)
        if len(c):
            out += np.asarray(self.potential.gradient(c, self.mesh, _f(x))).reshape(-1, 3)

    def hessian(self, x: np.ndarray) -> sp.csr_matrix:
        """The barrier's Hessian at ``x``, each pair's projected to positive semidefinite, (3N, 3N)."""
        c = self._collisions_at(x)
        n3 = 3 * len(x)
        if not len(c):
            return sp.csr_matrix((n3, n3))
        try:
            H = sp.csr_matrix(self.potential.hessian(c, self.mesh, _f(x), self._ipc.PSDProjectionMethod.CLAMP))
        except RuntimeError:
            H = None
        if H is None or not np.all(np.isfinite(H.data)):
            # a pair's Hessian not finite (nearly parallel edges): this iteration goes without the barrier's
            # curvature (a slower iteration, still a descent direction; its line search keeps the energy)
            self.skipped += 1
            return sp.csr_matrix((n3, n3))
        return H

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        g = np.zeros_like(f)
        self.gradient(x, t, g)
        f -= g
        H = self.hessian(x)
        if H.nnz and kw is not None and w is not None:   # (dF/dx) w
            kw -= (H @ w.reshape(-1)).reshape(-1, 3)
        self.coupling = _enter(H, c_x, system)

    # ------------------------------------------------------------------ safe moves
    def filter_move(self, x: np.ndarray, dx: np.ndarray, first: bool = False) -> np.ndarray:
        """``dx`` with each vertex's move cut to :data:`SAFE` of the distance it may move on its own (the others
        still) without any pair of non-adjacent primitives coming within ``xi`` (per-vertex safe distances,
        Offset Geometric Contact's bound: a vertex far from the rest of the cloth is not held
        back by a pair in contact elsewhere); ``dx`` itself when nothing is cut (``first``, the step's first
        iterate, changes nothing here)."""
        # the cloth's common translation moves no pair closer: the bound is on each vertex's move beside it (a
        # falling sheet is not held back by its own rows); not where some vertices stay (pinned, held: a cut
        # would move them)
        shift = np.zeros(3) if np.any(np.all(dx == 0.0, axis=1)) else dx.mean(axis=0)
        rel = dx - shift
        move = np.sqrt(np.einsum("ij,ij->i", rel, rel))
        reach = float(move.max(initial=0.0))
        if reach <= 0.0:
            return dx
        safe = self._safe_distances(x, INFLATION * reach + self.xi)
        s = np.minimum(1.0, SAFE * safe / np.maximum(move, 1e-300))
        if np.all(s >= 1.0):
            return dx
        return shift + rel * s[:, None]

    def _safe_distances(self, x: np.ndarray, inflation: float) -> np.ndarray:
        """Each vertex's safe distance at ``x`` (N,), m: its least distance to the primitives not adjacent to it,
        less the offset ``xi``, from the pairs within the offset and ``inflation`` (at least INFLATION times the
        longest move; a vertex with nothing that near is capped there and not cut, a pair beyond it cannot close
        that distance in one move) (:func:`~implicit_cloth.kernels.proximity.clearance`). Cached for the last
        ``x``: a Newton iteration filters many moves from one iterate, each no longer than the cached radius
        allows (a larger radius gathers more pairs, and caps higher, so the distances stay valid for every
        shorter move)."""
        if self._safe_key is not None and self._safe_key[0] >= inflation and np.array_equal(self._safe_key[1], x):
            return self._safe
        from ..kernels.proximity import clearance

        radius = inflation + self.xi
        lo = x.min(axis=0) - 1e-9
        hi = x.max(axis=0)
        h = max(radius, self._primitives.edge_length, float(np.max(hi - lo)) / GRID_CELLS)
        dims = np.maximum(np.ceil((hi - lo) / h).astype(np.int64), 1)
        out = np.empty(len(x))
        clearance(np.ascontiguousarray(x, dtype=float), self._primitives.faces, self._primitives.edges, radius,
                  lo, h, dims, out)
        self._safe = out - self.xi
        self._safe_key = (inflation, x.copy())
        return self._safe


class _Primitives:
    """A collision mesh's faces and edges for :func:`~implicit_cloth.kernels.proximity.clearance`, and its mean
    edge length at rest (the proximity grid's least cell)."""

    def __init__(self, mesh: Any) -> None:
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self.edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        rest = np.asarray(mesh.rest_positions)
        self.edge_length = float(np.mean(np.linalg.norm(rest[self.edges[:, 1]] - rest[self.edges[:, 0]], axis=1)))


class ClothFriction(DissipativeTerm):
    """IPC's lagged smoothed friction between layers of cloth (a dissipative :class:`~implicit_cloth.forces.Force`,
    ``collision.self_friction``): on the pairs within the barrier's reach at the step's start, the toolkit's
    ``D(v) = sum mu lambda f0(|T^T v|)`` with each pair's normal force ``lambda`` (the barrier's) and tangent
    basis ``T`` of the step's start, smoothed below the sliding speed ``eps`` (Coulomb's law above it), on the
    pair's relative velocity. Its Hessian (projected to positive semidefinite pair by pair) goes in as the
    barrier's: diagonal blocks into the system, the rest into the solve's product (:attr:`coupling`)."""

    name = "self_friction"

    def __init__(self, mesh: Any, potential: Any, collisions: Any) -> None:
        import ipctk

        self._ipc = ipctk
        self.mesh, self.potential, self.collisions = mesh, potential, collisions
        #: the off-diagonal part of the last Hessian (c_v scaled), for the solve's product; None if none
        self.coupling: sp.csr_matrix | None = None

    def __len__(self) -> int:
        return len(self.collisions)

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """``D(v)``, W (its ``-dD/dv`` is the friction on the cloth)."""
        return float(self.potential(self.collisions, self.mesh, _f(v)))

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        out -= np.asarray(self.potential.gradient(self.collisions, self.mesh, _f(v))).reshape(-1, 3)

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        self.force(x, v, t, f)
        H = sp.csr_matrix(self.potential.hessian(self.collisions, self.mesh, _f(v),
                                                 self._ipc.PSDProjectionMethod.CLAMP))
        self.coupling = _enter(H, c_v, system)


def _enter(H: sp.csr_matrix, scale: float, system: Any) -> sp.csr_matrix | None:
    """``scale H`` (3N, 3N) into the solve: its diagonal blocks (one a vertex) added to ``system``'s, the rest
    returned for the solve's product (None if nothing is off the diagonal blocks)."""
    if not H.nnz:
        return None
    coo = (H * scale).tocoo()
    same = (coo.row // 3) == (coo.col // 3)
    blocks = np.zeros((H.shape[0] // 3, 3, 3))
    np.add.at(blocks, (coo.row[same] // 3, coo.row[same] % 3, coo.col[same] % 3), coo.data[same])
    system.blocks[system.diag_index] += blocks
    off = ~same
    if not np.any(off):
        return None
    return sp.csr_matrix((coo.data[off], (coo.row[off], coo.col[off])), shape=H.shape)


def _f(x: np.ndarray) -> np.ndarray:
    return np.asfortranarray(x, dtype=float)


class ClothContact:
    """The self-contact stage of ``collision.method = "barrier"``: the collision mesh (every piece; adjacent
    primitives are never a pair) and the barrier, built once; :meth:`term` makes a step's term."""

    def __init__(self, model: Any, settings: dict[str, Any], dt: float) -> None:
        try:
            import ipctk
        except ImportError:  # pragma: no cover - the test extra installs it
            from ..errors import SceneError

            raise SceneError("collision.self_collision: the barrier method's self-contact needs the IPC Toolkit "
                             "(pip install 'implicit_cloth[ipc]'), got method = 'barrier'") from None
        self._ipc = ipctk
        faces = np.asarray(model.faces, dtype=np.int64)
        self.mesh = ipctk.CollisionMesh(np.asfortranarray(model.rest_positions), ipctk.edges(faces), faces)
        self.thickness = float(settings["thickness"])
        self.xi = self.dhat = 0.5 * self.thickness
        # the toolkit's barrier is IPC's on squared distances (~dhat^4 where the obstacles' is ~dhat^2): the mean
        # vertex mass over dt^2, over dhat^2, brings its force to the obstacles' at the same gap
        self.kappa = float(np.mean(model.masses)) / (float(dt) ** 2 * self.dhat ** 2)
        self.potential = ipctk.BarrierPotential(self.dhat, self.kappa)
        self._primitives = _Primitives(self.mesh)
        from .obstacles import FRICTION_SPEED

        #: the Coulomb coefficient between layers (``collision.self_friction``) and the friction's sliding speed
        self.mu = float(settings.get("self_friction", 0.0))
        self.eps = float(settings.get("friction_speed", FRICTION_SPEED))
        self.friction_potential = ipctk.FrictionPotential(self.eps) if self.mu > 0.0 else None

    def term(self, x0: np.ndarray) -> ClothBarrier:
        return ClothBarrier(self.mesh, self.potential, self.xi, self.dhat, x0, self._primitives)

    def friction(self, barrier: ClothBarrier, x0: np.ndarray) -> ClothFriction | None:
        """The step's friction between layers, lagged at its start ``x0`` (the pairs ``barrier`` has within reach
        there, their normal forces and tangent planes); None without ``self_friction`` or pairs."""
        if self.friction_potential is None:
            return None
        normal = barrier._collisions_at(x0)
        if not len(normal):
            return None
        tangential = self._ipc.TangentialCollisions()
        tangential.build(self.mesh, _f(x0), normal, self.potential, self.mu)
        return ClothFriction(self.mesh, self.friction_potential, tangential) if len(tangential) else None
