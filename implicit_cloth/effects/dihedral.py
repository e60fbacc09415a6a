"""Dihedral bending on the hinges of the triangle mesh (discrete shells: Grinspun et al. 2003; Bridson et al.
2003; Tamstorf & Grinspun 2013), with BW98 §4.5's damping of the condition's rate.

Notation. A hinge is an interior edge shared by exactly two triangles: the edge ``(x_0, x_1)`` oriented as in
its first triangle ``(x_0, x_1, x_2)``, and the wing ``x_3`` of the other triangle. With ``e = x_1 - x_0``::

    n_1 = e x (x_2 - x_0),   n_2 = (x_3 - x_0) x e,   theta = atan2((n_1 x n_2) . e / |e|, n_1 . n_2)

``theta`` is the signed angle between the two triangles' normals (0 for a flat hinge; its sign tells the side it
folds to), in ``(-pi, pi]`` (atan2: robust at every angle, unlike ``acos``). The rest angle ``theta_0`` is the
rest mesh's (0 for a flat grid); ``theta - theta_0`` is wrapped into ``(-pi, pi]``.

Energy and dissipation, with the bending modulus ``B`` (N m) and damping ``B_d`` (N m s)::

    U = sum_e B w_e (theta_e - theta_0e)^2 / 2,      D = sum_e B_d w_e thetadot_e^2 / 2,
    w_e = |e_0|^2 / A_e,     thetadot = (d theta / dx) . v

with ``|e_0|`` the rest edge length and ``A_e`` the rest area of the hinge's two triangles together
(dimensionless ``w_e``). The constant: a sheet bent into a cylinder of radius R stores the continuum plate's
``B kappa^2 / 2 = B / (2 R^2)`` per unit area, at every resolution (``tests/test_dihedral.py``). On the grids
(square cells cut by one diagonal) bent along either axis it is exact: the edges along the axis bend by
``h / R``, have ``w = h^2 / h^2 = 1``, one per cell of area ``h^2``, the others stay flat; on a mesh of
equilateral triangles, for any direction of the axis, it converges to it with the dual area ``A_e / 3`` per
hinge. Discrete shells write ``k_b 3 |e|^2 / A_e (theta - theta_0)^2`` (Grinspun et al. 2003, Tamstorf &
Grinspun 2013): the same energy with ``k_b = B / 6``.

Gradient (exact; Bridson et al. 2003 with this orientation), ``h_k`` the heights of the wings over the edge::

    d theta / dx_2 = -|e| n_1 / |n_1|^2,   d theta / dx_3 = -|e| n_2 / |n_2|^2,
    d theta / dx_0 = -(1 - s_1) g_2 - (1 - s_2) g_3,   d theta / dx_1 = -s_1 g_2 - s_2 g_3,
    s_k = (x_{k+1} - x_0) . e / |e|^2  (where the wing projects on the edge)

Force ``F = -dU/dx - dD/dv = -w (B (theta - theta_0) + B_d thetadot) g``. Hessian blocks (what
:meth:`Dihedral.linearize` assembles), per hinge and vertex pair ``(i, j)``::

    (c_x B + c_v B_d) w g_i g_j^T

Gauss-Newton for the stiffness: the term ``B w (theta - theta_0) d2 theta / dx2`` of the exact Hessian is
dropped (it is indefinite), so the blocks are positive semidefinite; exact where ``theta = theta_0`` (a flat
grid at rest, where the step's matrix matters most). The damping's ``dF/dv`` is exact (``D`` is quadratic in
``v``); its ``dF/dx`` is dropped (BW98 §4.5). The product ``(dF/dx) w`` uses the same blocks. A hinge whose
edge or a triangle has no length or area at an instant (``|e|`` or ``|n_k|`` below 1e-12 of the rest) has no
force or stiffness then.

Pattern: :meth:`pairs` gives all six pairs of each hinge's four vertices: the two wings are joined by no
triangle edge, so they are added to the system's fixed pattern here. Back-ends: numpy (the reference,
vectorised over the hinges) and numba (:mod:`implicit_cloth.kernels.dihedral`, one pass), chosen from the
system's back-end at :meth:`bind`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from ..assembly import accumulate_product
from ..backend import Backend, get_backend

#: relative size below which an edge or a triangle has no direction
TINY = 1e-12


def hinges(faces: np.ndarray) -> np.ndarray:
    """The hinges ``(x_0, x_1, x_2, x_3)`` of a triangle mesh, (H, 4): every edge shared by exactly two triangles,
    oriented as in the first of them (lower index), its third vertex ``x_2`` and the other's ``x_3``. Edges of
    one triangle (the border) or of more than two (non-manifold) have no hinge."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    T = len(faces)
    # each face's three oriented edges and the vertex opposite each, in face order
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    opp = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    face = np.concatenate([np.arange(T)] * 3)
    key = np.sort(np.stack([a, b], 1), axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    inner = np.flatnonzero(counts[inverse] == 2)
    order = inner[np.lexsort((face[inner], inverse[inner]))]      # the two of each edge, first face first
    first, second = order[0::2], order[1::2]
    out = np.stack([a[first], b[first], opp[first], opp[second]], 1)
    return out[np.argsort(inverse[first], kind="stable")].astype(np.int64).reshape(-1, 4)


def dihedral_angles(x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Each hinge's signed angle ``theta`` (H,), rad (see the module's docstring)."""
    x0, x1, x2, x3 = (x[h[:, k]] for k in range(4))
    e = x1 - x0
    n1 = np.cross(e, x2 - x0)
    n2 = np.cross(x3 - x0, e)
    le = np.linalg.norm(e, axis=1)
    sin = np.einsum("ij,ij->i", np.cross(n1, n2), e) / np.where(le > 0, le, 1.0)
    return np.arctan2(sin, np.einsum("ij,ij->i", n1, n2))


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles into ``(-pi, pi]``."""
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


class Dihedral:
    """Bending of the hinges (see the module's docstring for the equations).

    Parameters
    ----------
    n : int
        Number of vertices.
    hinges : (H, 4) int array
        ``(x_0, x_1, x_2, x_3)`` of each hinge (:func:`hinges`).
    rest : (N, 3) float array
        Rest positions, m: each hinge's rest angle, edge length and area.
    stiffness, damping : float or (H,) float array
        Bending modulus ``B`` (N m) and damping ``B_d`` (N m s).
    flat : bool
        Rest angles 0 (a flat rest shape) instead of the rest mesh's.
    """

    name = "bending"
    conservative = True
    elastic = True

    def __init__(self, n: int, hinges: np.ndarray, rest: np.ndarray, stiffness: Any, damping: Any,
                 flat: bool = False) -> None:
        self.n = int(n)
        self.hinges = np.ascontiguousarray(np.asarray(hinges, dtype=np.int64).reshape(-1, 4))
        H = len(self.hinges)
        h = self.hinges
        rest = np.asarray(rest, dtype=float)
        x0, x1, x2, x3 = (rest[h[:, k]] for k in range(4))
        e = x1 - x0
        area = 0.5 * (np.linalg.norm(np.cross(e, x2 - x0), axis=1) + np.linalg.norm(np.cross(x3 - x0, e), axis=1))
        if np.any(area <= 0) or not np.all(np.isfinite(area)):
            raise ValueError("dihedral: a hinge has no rest area")
        #: rest edge length (m) and the two triangles' rest area (m^2) of each hinge
        self.length = np.linalg.norm(e, axis=1)
        self.area = area
        #: ``w_e = |e_0|^2 / A_e`` (dimensionless)
        self.weight = np.ascontiguousarray(self.length ** 2 / area)
        #: rest angles, rad
        self.theta0 = np.zeros(H) if flat else np.ascontiguousarray(dihedral_angles(rest, h))
        self.k = np.ascontiguousarray(np.broadcast_to(np.asarray(stiffness, dtype=float), (H,)))
        self.kd = np.ascontiguousarray(np.broadcast_to(np.asarray(damping, dtype=float), (H,)))
        #: whether it damps (a dissipation potential beside the elastic energy)
        self.dissipative = bool(np.any(self.kd))
        #: |e|^2 and |n|^2 below these have no direction (relative to the rest)
        self.tiny_e = np.ascontiguousarray(TINY * self.length ** 2)
        self.tiny_n = np.ascontiguousarray(TINY * (2.0 * area) ** 2)
        # incidence: F = B @ f_corner.reshape(4H, 3)
        self._B = sp.csr_array((np.ones(4 * H), (h.ravel(), np.arange(4 * H))), shape=(self.n, 4 * H))
        self.backend: Backend = get_backend("numpy")
        self._G: sp.csr_array | None = None
        self._bidx: np.ndarray | None = None

    # ------------------------------------------------------------------ geometry
    def angles(self, x: np.ndarray) -> np.ndarray:
        """``theta`` of each hinge (H,), rad."""
        return dihedral_angles(x, self.hinges)

    def _frame(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``theta - theta_0`` (H,) and ``d theta / dx`` (H, 4, 3) (zero where a hinge is degenerate)."""
        h = self.hinges
        x0, x1, x2, x3 = (x[h[:, k]] for k in range(4))
        e = x1 - x0
        a, b = x2 - x0, x3 - x0
        n1 = np.cross(e, a)
        n2 = np.cross(b, e)
        ee = np.einsum("ij,ij->i", e, e)
        q1 = np.einsum("ij,ij->i", n1, n1)
        q2 = np.einsum("ij,ij->i", n2, n2)
        ok = (ee > self.tiny_e) & (q1 > self.tiny_n) & (q2 > self.tiny_n)
        le = np.sqrt(ee)
        sin = np.einsum("ij,ij->i", np.cross(n1, n2), e) / np.where(ok, le, 1.0)
        theta = np.arctan2(sin, np.einsum("ij,ij->i", n1, n2))
        one = np.where(ok, 1.0, 0.0)
        g2 = -(one * le / np.where(ok, q1, 1.0))[:, None] * n1
        g3 = -(one * le / np.where(ok, q2, 1.0))[:, None] * n2
        s1 = np.einsum("ij,ij->i", a, e) / np.where(ok, ee, 1.0)
        s2 = np.einsum("ij,ij->i", b, e) / np.where(ok, ee, 1.0)
        g0 = -(1.0 - s1)[:, None] * g2 - (1.0 - s2)[:, None] * g3
        g1 = -s1[:, None] * g2 - s2[:, None] * g3
        return np.where(ok, wrap(theta - self.theta0), 0.0), np.stack([g0, g1, g2, g3], axis=1)

    def _rates(self, v: np.ndarray, g: np.ndarray) -> np.ndarray:
        return np.einsum("hkj,hkj->h", g, v[self.hinges])

    # ------------------------------------------------------------------ Force
    @property
    def accelerator(self) -> str:
        return self.backend.name

    def energy(self, x: np.ndarray) -> float:
        """``sum_e B w_e (theta_e - theta_0e)^2 / 2``, J."""
        d = wrap(self.angles(x) - self.theta0)
        return 0.5 * float(np.dot(self.k * self.weight, d * d))

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        f = np.zeros_like(out)
        self._add_force(x, None, f)
        out -= f

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """``sum_e B_d w_e thetadot_e^2 / 2`` at the geometry ``x``, W."""
        if not self.dissipative:
            return 0.0
        _, g = self._frame(x)
        r = self._rates(v, g)
        return 0.5 * float(np.dot(self.kd * self.weight, r * r))

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        self._add_force(x, v, out)

    def _corner_forces(self, x: np.ndarray, v: np.ndarray | None, frame=None) -> np.ndarray:
        d, g = self._frame(x) if frame is None else frame
        s = self.k * d
        if v is not None and self.dissipative:
            s = s + self.kd * self._rates(v, g)
        return -(self.weight * s)[:, None, None] * g

    def _add_force(self, x: np.ndarray, v: np.ndarray | None, out: np.ndarray) -> None:
        if self.backend.compiled and out.dtype == np.float64 and out.flags.c_contiguous:
            from ..kernels.dihedral import dihedral_pass

            c = np.ascontiguousarray
            x = c(x, dtype=float)
            damped = v is not None and self.dissipative
            vv = c(v, dtype=float) if damped else x
            dihedral_pass(x, vv, x, False, damped, False, self.hinges, self.weight, self.theta0, self.k, self.kd,
                          self.tiny_e, self.tiny_n, 0.0, 0.0, np.zeros((0, 16), dtype=np.int64),
                          np.zeros((0, 3, 3)), out, out)
            return
        out += self._B @ self._corner_forces(x, v).reshape(-1, 3)

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0   # internal: its work is the change of its potential

    def pairs(self) -> np.ndarray:
        """All six vertex pairs of every hinge (unique, sorted): the triangles' edges and the wings' pair."""
        h = self.hinges
        e = np.concatenate([h[:, [i, j]] for i in range(4) for j in range(i + 1, 4)])
        return np.unique(np.sort(e, axis=1), axis=0).reshape(-1, 2)

    def bind(self, system: Any) -> None:
        """Index maps into ``system``'s blocks (vertex pair ``(i, j)`` of hinge ``e`` at ``16 e + 4 i + j``) and the
        back-end (the system's)."""
        self.backend = system.backend
        bidx, G = system.element_index(self.hinges)
        self._bidx = bidx
        if G is not None:
            self._G = G

    def blocks(self, x: np.ndarray, c_x: float, c_v: float) -> np.ndarray:
        """Each hinge's ``(c_x B + c_v B_d) w g_i g_j^T`` blocks (H, 4, 4, 3, 3) ``[e, i, j]`` (numpy)."""
        _, g = self._frame(x)
        return self._blocks(g, c_x, c_v)

    def _blocks(self, g: np.ndarray, c_x: float, c_v: float) -> np.ndarray:
        s = (c_x * self.k + c_v * self.kd) * self.weight
        return s[:, None, None, None, None] * (g[:, :, None, :, None] * g[:, None, :, None, :])

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        """Add ``(c_x B + c_v B_d) w g g^T`` to the system's blocks, ``(dF/dx) w`` (the same Gauss-Newton blocks
        times ``w``) to ``kw`` and the force to ``f``."""
        with_w = kw is not None and w is not None
        if self.backend.compiled:
            from ..kernels.dihedral import dihedral_pass

            c = np.ascontiguousarray
            x, v = c(x, dtype=float), c(v, dtype=float)
            ww = c(w, dtype=float) if with_w else x
            dihedral_pass(x, v, ww, with_w, self.dissipative, True, self.hinges, self.weight, self.theta0, self.k,
                          self.kd, self.tiny_e, self.tiny_n, float(c_x), float(c_v), self._bidx, system.blocks,
                          kw if with_w else f, f)
            return
        frame = self._frame(x)
        _, g = frame
        f += self._B @ self._corner_forces(x, v, frame).reshape(-1, 3)
        X = self._blocks(g, c_x, c_v)
        accumulate_product(self._G, np.ascontiguousarray(X.reshape(-1, 9)), system.blocks.reshape(-1, 9))
        if with_w:
            gw = np.einsum("hkj,hkj->h", g, w[self.hinges])
            kw -= self._B @ ((self.k * self.weight * gw)[:, None, None] * g).reshape(-1, 3)


def build(model: Any, spec: list[tuple[np.ndarray, dict[str, Any]]]) -> Dihedral:
    """The hinges of the cloth's pieces that ask for ``[cloth.bending] model = "dihedral"``: ``spec`` lists, per
    such piece, its triangles of positive rest area (vertex triples, rows of ``model.faces``) and its validated
    table (``stiffness`` N m, ``damping`` N m s, ``rest_angle`` "mesh" or "flat")."""
    hs, k, kd, flat = [], [], [], []
    for faces, table in spec:
        h = hinges(faces)
        hs.append(h)
        k.append(np.full(len(h), table["stiffness"]))
        kd.append(np.full(len(h), table["damping"]))
        flat.append(np.full(len(h), table.get("rest_angle", "mesh") == "flat"))
    h = np.concatenate(hs) if hs else np.zeros((0, 4), dtype=np.int64)
    out = Dihedral(model.n, h, model.rest_positions, np.concatenate(k), np.concatenate(kd))
    fl = np.concatenate(flat)
    out.theta0[fl] = 0.0
    return out
