"""Baraff & Witkin's triangle membrane (BW98 §4.2-4.3, §4.5): stretch in u and v and shear, per triangle.

Notation. Triangle ``t = (x_0, x_1, x_2)`` has rest coordinates ``(u_k, v_k)`` in metres (its rest shape laid
flat, u along the cloth's warp, see :func:`metric_rest_coordinates`). With ``Dx_1 = x_1 - x_0``,
``Dx_2 = x_2 - x_0`` and likewise ``Du``, ``Dv`` (BW98 eq. 9-10)::

    [w_u  w_v] = [Dx_1  Dx_2] [[Du_1  Du_2], [Dv_1  Dv_2]]^-1,   w_u = sum_k b_k x_k,  w_v = sum_k c_k x_k

(``b``, ``c``: constant per triangle, ``b_0 = -(b_1 + b_2)``). The conditions, with BW98's ``b_u = b_v = 1``
(no stretch at rest)::

    C_u = |w_u| - 1     (engineering strain along u)
    C_v = |w_v| - 1     (engineering strain along v)
    C_s = w_u . w_v     (shear: sin of the change of the angle between the u and v threads, for unit w's)

Convention (stiffness as the sheet's in-plane stiffness): with ``A`` the triangle's rest area,

    U = sum_t A (k_u C_u^2 + k_v C_v^2 + k_s C_s^2) / 2                              J
    D = sum_t A (kd_u Cdot_u^2 + kd_v Cdot_v^2 + kd_s Cdot_s^2) / 2,  Cdot = dC/dx . v    W

so the energy per rest area is ``k e^2 / 2`` and ``k_u``, ``k_v``, ``k_s`` are in N/m (a sheet stretched
uniaxially by ``e`` along u, its v threads kept at length, has tension ``k_u e`` per unit width), independent
of the mesh; ``kd`` is in N*s/m (the dissipation per rest area is ``kd (de/dt)^2 / 2``). BW98 write
``C = a (|w_u| - b_u)`` with ``a`` the triangle's rest area and ``E = k_BW C^2 / 2``, so ``k = k_BW a``: their
constant depends on the triangle's size, ours is the sheet's. The force is ``F = -dU/dx - dD/dv``:
the damping force is BW98 §4.5's ``d = -kd A (dC/dx) Cdot`` per condition.

Hessian blocks (what :meth:`Membrane.linearize` assembles, ``c_x d2U/dx2 + c_v d2D/dv2``) per triangle and
corner pair ``(i, j)``::

    A [ b_i b_j (c_x k_u P_u + c_v kd_u n_u n_u^T) + c_i c_j (c_x k_v P_v + c_v kd_v n_v n_v^T)
        + (c_x k_s + c_v kd_s) g_i g_j^T ],    g_i = b_i w_v + c_i w_u,  n = w / |w|,
    P = a I + (1 - a) n n^T,  a = 1 - 1/|w|

(the exact stretch Hessian, a spring's in ``w``). Choices that keep the step's matrix positive (semi)definite
(the step needs an SPD system):

* stretch: ``a`` is clamped at 0 where a thread is compressed (``|w| < 1``), as the springs' transverse term
  (BW98 §5.1; Choi & Ko 2002); exact in tension;
* shear: Gauss-Newton, ``k_s g g^T``: the term ``k_s C_s (b_i c_j + c_i b_j) I`` of the exact Hessian, which is
  indefinite, is dropped; exact where ``C_s = 0`` (no shear);
* the damping's ``dF/dx`` is dropped (BW98 §4.5); its ``dF/dv`` is exact (``D`` is quadratic in ``v``).

``Membrane(..., exact=True)`` assembles the exact Hessian instead (possibly indefinite; for tests). The
product ``(dF/dx) w`` (``kw``) uses the same blocks as the matrix. A thread of zero length (``|w| < 1e-9``)
has no direction: its ``n = 0`` (no force or stiffness from that condition at that instant).

Pattern: :meth:`pairs` gives the three vertex pairs of every triangle, so the blocks are on the system's fixed
pattern whatever the other forces add. Back-ends: numpy (the reference, vectorised over the triangles) and
numba (:mod:`implicit_cloth.kernels.membrane`, one pass), chosen from the system's back-end at :meth:`bind`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from ..assembly import accumulate_product
from ..backend import Backend, get_backend

#: |w| below which a thread has no direction
TINY = 1e-9


def metric_rest_coordinates(rest: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Rest ``(u, v)`` of each triangle's corners, m, (T, 3, 2): its rest shape ``rest[faces]`` laid flat in
    the orthonormal frame of its plane whose first axis is the direction of the texture's u there.

    ``uv`` (T, 3, 2) are the texture coordinates of the corners (any scale: only the direction of u in each
    triangle, and the side v is on, are taken from them). The result is isometric to the rest shape, so the
    rest state has zero strain (``|w_u| = |w_v| = 1``, ``w_u . w_v = 0``), with u along the texture's u (the
    warp) and v across it, on the side of the texture's v. A triangle whose texture coordinates have no area
    takes its first edge as u.
    """
    P = rest[faces]
    E1, E2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    du1, du2 = uv[:, 1, 0] - uv[:, 0, 0], uv[:, 2, 0] - uv[:, 0, 0]
    dv1, dv2 = uv[:, 1, 1] - uv[:, 0, 1], uv[:, 2, 1] - uv[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    scale = np.maximum(np.abs(du1 * dv2) + np.abs(du2 * dv1), 1e-300)
    ok = np.abs(det) > 1e-12 * scale
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    tu = (E1 * dv2[:, None] - E2 * dv1[:, None]) * inv[:, None]      # dx/du on the rest triangle
    tv = (E2 * du1[:, None] - E1 * du2[:, None]) * inv[:, None]      # dx/dv
    n = np.cross(E1, E2)
    n /= np.linalg.norm(n, axis=1)[:, None]
    tu -= np.einsum("ij,ij->i", tu, n)[:, None] * n
    lu = np.linalg.norm(tu, axis=1)
    ok &= lu > 0
    e1 = np.where(ok[:, None], tu / np.where(ok, lu, 1.0)[:, None], E1 / np.linalg.norm(E1, axis=1)[:, None])
    e2 = np.cross(n, e1)
    flip = ok & (np.einsum("ij,ij->i", e2, tv) < 0)
    e2[flip] *= -1.0
    D = P - P[:, :1]
    return np.stack([np.einsum("tkj,tj->tk", D, e1), np.einsum("tkj,tj->tk", D, e2)], axis=2)


class Membrane:
    """BW98's stretch and shear conditions on triangles (see the module's docstring for the equations).

    Parameters
    ----------
    n : int
        Number of vertices.
    faces : (T, 3) int array
        The triangles (of positive rest area).
    rest_uv : (T, 3, 2) float array
        Rest coordinates ``(u, v)`` of each triangle's corners, m.
    stiffness : (T, 3) or (3,) float array
        ``k_u``, ``k_v``, ``k_s`` in N/m (energy per rest area ``k C^2 / 2``).
    damping : (T, 3) or (3,) float array
        ``kd_u``, ``kd_v``, ``kd_s`` in N*s/m (dissipation per rest area ``kd Cdot^2 / 2``).
    exact : bool
        Assemble the exact Hessian (indefinite where a thread is compressed or the triangle sheared) instead of
        the clamped / Gauss-Newton one.
    """

    name = "membrane"
    conservative = True
    elastic = True

    def __init__(self, n: int, faces: np.ndarray, rest_uv: np.ndarray, stiffness: Any, damping: Any,
                 exact: bool = False) -> None:
        self.n = int(n)
        self.faces = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
        T = len(self.faces)
        uv = np.asarray(rest_uv, dtype=float).reshape(T, 3, 2)
        du1, du2 = uv[:, 1, 0] - uv[:, 0, 0], uv[:, 2, 0] - uv[:, 0, 0]
        dv1, dv2 = uv[:, 1, 1] - uv[:, 0, 1], uv[:, 2, 1] - uv[:, 0, 1]
        det = du1 * dv2 - du2 * dv1
        if np.any(det == 0) or not np.all(np.isfinite(det)):
            raise ValueError("membrane: a triangle has no rest area")
        #: rest area of each triangle, m^2
        self.area = 0.5 * np.abs(det)
        b1, b2 = dv2 / det, -dv1 / det          # first column of the inverse of [[Du1 Du2], [Dv1 Dv2]]
        c1, c2 = -du2 / det, du1 / det          # its second column
        #: w_u = sum_k b_k x_k, w_v = sum_k c_k x_k, (T, 3) each, 1/m
        self.b = np.ascontiguousarray(np.stack([-(b1 + b2), b1, b2], axis=1))
        self.c = np.ascontiguousarray(np.stack([-(c1 + c2), c1, c2], axis=1))
        self.k = np.ascontiguousarray(np.broadcast_to(np.asarray(stiffness, dtype=float), (T, 3)))
        self.kd = np.ascontiguousarray(np.broadcast_to(np.asarray(damping, dtype=float), (T, 3)))
        self.exact = bool(exact)
        #: whether any condition damps (a dissipation potential beside the elastic energy)
        self.dissipative = bool(np.any(self.kd))
        # incidence: F = B @ f_corner.reshape(3T, 3) adds each corner's force to its vertex
        self._B = sp.csr_array((np.ones(3 * T), (self.faces.ravel(), np.arange(3 * T))), shape=(self.n, 3 * T))
        self.backend: Backend = get_backend("numpy")
        self._G: sp.csr_array | None = None
        self._bidx: np.ndarray | None = None

    # ------------------------------------------------------------------ geometry
    def deformation(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``w_u``, ``w_v`` of each triangle, (T, 3) each (dimensionless: unit and orthogonal at rest)."""
        X = x[self.faces]
        return np.einsum("tk,tkj->tj", self.b, X), np.einsum("tk,tkj->tj", self.c, X)

    def strains(self, x: np.ndarray) -> np.ndarray:
        """``C_u``, ``C_v``, ``C_s`` of each triangle, (T, 3)."""
        wu, wv = self.deformation(x)
        lu, lv = np.linalg.norm(wu, axis=1), np.linalg.norm(wv, axis=1)
        return np.stack([lu - 1.0, lv - 1.0, np.einsum("ij,ij->i", wu, wv)], axis=1)

    def principal_strains(self, x: np.ndarray) -> np.ndarray:
        """The largest principal strain of each triangle, (T,): ``sqrt(lambda_max(F^T F)) - 1`` with ``F = [w_u
        w_v]`` (3 x 2) its deformation gradient, i.e. the largest relative stretch ``(l - L0) / L0`` of any
        segment drawn in the triangle, whatever its direction. It is at least each thread's ``C_u``, ``C_v`` and
        each edge's strain, and catches a stretch along a diagonal that the threads see only as shear (a
        sheet pulled along its bias). The run's strain measures read it (``max_strain``, the strain bound)."""
        wu, wv = self.deformation(x)
        a = np.einsum("ij,ij->i", wu, wu)
        c = np.einsum("ij,ij->i", wv, wv)
        b = np.einsum("ij,ij->i", wu, wv)
        half = 0.5 * (a - c)
        return np.sqrt(0.5 * (a + c) + np.sqrt(half * half + b * b)) - 1.0

    def _frame(self, x: np.ndarray):
        wu, wv = self.deformation(x)
        lu = np.sqrt(np.einsum("ij,ij->i", wu, wu))
        lv = np.sqrt(np.einsum("ij,ij->i", wv, wv))
        iu = np.divide(1.0, lu, out=np.zeros_like(lu), where=lu > TINY)
        iv = np.divide(1.0, lv, out=np.zeros_like(lv), where=lv > TINY)
        nu, nv = wu * iu[:, None], wv * iv[:, None]
        C = np.stack([lu - 1.0, lv - 1.0, np.einsum("ij,ij->i", wu, wv)], axis=1)
        # g_k = dC_s/dx_k = b_k w_v + c_k w_u, (T, 3 corners, 3)
        g = self.b[:, :, None] * wv[:, None, :] + self.c[:, :, None] * wu[:, None, :]
        return wu, wv, lu, lv, iu, iv, nu, nv, C, g

    def _rates(self, v: np.ndarray, nu, nv, g) -> np.ndarray:
        """``Cdot_u``, ``Cdot_v``, ``Cdot_s`` (T, 3), 1/s."""
        V = v[self.faces]
        return np.stack([np.einsum("ij,ij->i", np.einsum("tk,tkj->tj", self.b, V), nu),
                         np.einsum("ij,ij->i", np.einsum("tk,tkj->tj", self.c, V), nv),
                         np.einsum("tkj,tkj->t", g, V)], axis=1)

    def _corner_forces(self, x: np.ndarray, v: np.ndarray | None, frame=None) -> np.ndarray:
        """Each corner's force (T, 3, 3), N: ``-A (k C + kd Cdot) dC/dx_k`` summed over the conditions."""
        wu, wv, lu, lv, iu, iv, nu, nv, C, g = self._frame(x) if frame is None else frame
        s = self.k * C
        if v is not None and self.dissipative:
            s = s + self.kd * self._rates(v, nu, nv, g)
        s *= -self.area[:, None]
        return ((s[:, 0:1, None] * self.b[:, :, None]) * nu[:, None, :]
                + (s[:, 1:2, None] * self.c[:, :, None]) * nv[:, None, :] + s[:, 2:3, None] * g)

    # ------------------------------------------------------------------ Force
    @property
    def accelerator(self) -> str:
        return self.backend.name

    def energy(self, x: np.ndarray) -> float:
        """``sum_t A (k_u C_u^2 + k_v C_v^2 + k_s C_s^2) / 2``, J."""
        C = self.strains(x)
        return 0.5 * float(np.dot(self.area, np.einsum("tc,tc->t", self.k, C * C)))

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        f = np.zeros_like(out)
        self._add_force(x, None, f)
        out -= f

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """``sum_t A (kd_u Cdot_u^2 + kd_v Cdot_v^2 + kd_s Cdot_s^2) / 2`` at the geometry ``x``, W."""
        if not self.dissipative:
            return 0.0
        wu, wv, lu, lv, iu, iv, nu, nv, C, g = self._frame(x)
        r = self._rates(v, nu, nv, g)
        return 0.5 * float(np.dot(self.area, np.einsum("tc,tc->t", self.kd, r * r)))

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        self._add_force(x, v, out)

    def _add_force(self, x: np.ndarray, v: np.ndarray | None, out: np.ndarray) -> None:
        if self.backend.compiled and out.dtype == np.float64 and out.flags.c_contiguous:
            from ..kernels.membrane import membrane_pass

            c = np.ascontiguousarray
            x = c(x, dtype=float)
            damped = v is not None and self.dissipative
            vv = c(v, dtype=float) if damped else x
            membrane_pass(x, vv, x, False, damped, False, self.exact, self.faces, self.b, self.c, self.area,
                          self.k, self.kd, TINY, 0.0, 0.0, self._no_bidx, np.zeros((0, 3, 3)), out, out)
            return
        out += self._B @ self._corner_forces(x, v).reshape(-1, 3)

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0   # internal: its work is the change of its potential

    def pairs(self) -> np.ndarray:
        """The three vertex pairs of every triangle (unique, sorted)."""
        f = self.faces
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        return np.unique(e, axis=0).reshape(-1, 2)

    @property
    def _no_bidx(self) -> np.ndarray:
        return np.zeros((0, 9), dtype=np.int64)

    def bind(self, system: Any) -> None:
        """Index maps into ``system``'s blocks (corner pair ``(i, j)`` of triangle ``t`` at ``9 t + 3 i + j``)
        and the back-end (the system's)."""
        self.backend = system.backend
        bidx, G = system.element_index(self.faces)
        self._bidx = bidx
        if G is not None:
            self._G = G

    def blocks(self, x: np.ndarray, c_x: float, c_v: float) -> np.ndarray:
        """Each triangle's ``c_x d2U/dx2 + c_v d2D/dv2`` blocks (T, 3, 3, 3, 3) ``[t, i, j]`` (numpy)."""
        wu, wv, lu, lv, iu, iv, nu, nv, C, g = self._frame(x)
        return self._blocks_from_frame(c_x, c_v, lu, lv, iu, iv, nu, nv, C, g)

    def _stretch_a(self, l: np.ndarray, inv: np.ndarray) -> np.ndarray:
        a = np.where(l > TINY, 1.0 - inv, 0.0)
        return a if self.exact else np.maximum(a, 0.0)

    def _blocks_from_frame(self, c_x, c_v, lu, lv, iu, iv, nu, nv, C, g) -> np.ndarray:
        A = self.area
        eye = np.eye(3)[None]
        Q = []
        for col, l, inv, nn in ((0, lu, iu, nu), (1, lv, iv, nv)):
            a = self._stretch_a(l, inv)
            ka = c_x * self.k[:, col]
            nnT = nn[:, :, None] * nn[:, None, :]
            Q.append((A * ka * a)[:, None, None] * eye
                     + (A * (ka * (1.0 - a) + c_v * self.kd[:, col]))[:, None, None] * nnT)
        bb = self.b[:, :, None] * self.b[:, None, :]
        cc = self.c[:, :, None] * self.c[:, None, :]
        X = (bb[:, :, :, None, None] * Q[0][:, None, None] + cc[:, :, :, None, None] * Q[1][:, None, None]
             + (A * (c_x * self.k[:, 2] + c_v * self.kd[:, 2]))[:, None, None, None, None]
             * (g[:, :, None, :, None] * g[:, None, :, None, :]))
        if self.exact:
            bc = self.b[:, :, None] * self.c[:, None, :]
            X += ((A * c_x * self.k[:, 2] * C[:, 2])[:, None, None] * (bc + bc.transpose(0, 2, 1)))[
                :, :, :, None, None] * eye[:, None, None]
        return X

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        """Add ``c_x d2U/dx2 + c_v d2D/dv2`` (the blocks of the module's docstring) to the system's blocks,
        ``(dF/dx) w`` to ``kw`` and the force to ``f``."""
        with_w = kw is not None and w is not None
        if self.backend.compiled:
            from ..kernels.membrane import membrane_pass

            c = np.ascontiguousarray
            x, v = c(x, dtype=float), c(v, dtype=float)
            ww = c(w, dtype=float) if with_w else x
            membrane_pass(x, v, ww, with_w, self.dissipative, True, self.exact, self.faces, self.b, self.c,
                          self.area, self.k, self.kd, TINY, float(c_x), float(c_v), self._bidx, system.blocks,
                          kw if with_w else f, f)
            return
        frame = self._frame(x)
        wu, wv, lu, lv, iu, iv, nu, nv, C, g = frame
        f += self._B @ self._corner_forces(x, v, frame).reshape(-1, 3)
        X = self._blocks_from_frame(c_x, c_v, lu, lv, iu, iv, nu, nv, C, g)   # (T, 3, 3, 3, 3) [t, i, j]
        accumulate_product(self._G, np.ascontiguousarray(X.reshape(-1, 9)), system.blocks.reshape(-1, 9))
        if with_w:
            K = X if (c_x == 1.0 and c_v == 0.0) else self._blocks_from_frame(1.0, 0.0, lu, lv, iu, iv, nu, nv,
                                                                              C, g)
            W = w[self.faces]                                                  # (T, 3, 3) [t, j, :]
            kw -= self._B @ np.einsum("tijab,tjb->tia", K, W).reshape(-1, 3)

    def hessian_vector(self, x: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``(d2U/dx2) w`` with the blocks the system uses (exact ones with ``exact``), (N, 3)."""
        K = self.blocks(x, 1.0, 0.0)
        return self._B @ np.einsum("tijab,tjb->tia", K, w[self.faces]).reshape(-1, 3)


def build(model: Any, spec: list[tuple[np.ndarray, np.ndarray, dict[str, dict[str, float]]]]) -> Membrane:
    """The membrane of the cloth's pieces that ask for it: ``spec`` lists, per such piece, its triangles (indices
    into ``model.faces``), their rest coordinates (T_k, 3, 2) m and its validated ``[cloth.membrane]`` table."""
    k = [np.tile([table[c]["stiffness"] for c in CONDITIONS], (len(idx), 1)) for idx, _, table in spec]
    kd = [np.tile([table[c]["damping"] for c in CONDITIONS], (len(idx), 1)) for idx, _, table in spec]
    faces = model.faces[np.concatenate([idx for idx, _, _ in spec])]
    return Membrane(model.n, faces, np.concatenate([uv for _, uv, _ in spec]), np.concatenate(k), np.concatenate(kd))


#: the conditions of ``[cloth.membrane]``, in the order of the stiffness columns
CONDITIONS = ("stretch_u", "stretch_v", "shear")
