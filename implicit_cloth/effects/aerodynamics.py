"""Per-triangle aerodynamic drag and lift (``[effects.aerodynamics]``), quadratic in the relative air speed.

After the per-triangle air model of Keckeisen et al. 2004 ("Interactive cloth simulation in virtual
environments") and the common graphics form of it (a flat plate's pressure ``rho C |u|^2 A / 2`` on the area
it presents to the air): each triangle ``t`` sees the air at its mean velocity, the force on it is split
equally between its three corners.

Notation, per triangle with corners ``x_0, x_1, x_2`` and velocities ``v_0, v_1, v_2``::

    u = (v_0 + v_1 + v_2) / 3 - w              relative velocity of the triangle in the air, m/s (w: the
                                               uniform effects.wind, 0 without), s = |u|, u^ = u / s
    N = (x_1 - x_0) x (x_2 - x_0),  A = |N| / 2,  n = N / |N|   current area (m^2) and unit normal
    a = u . n                                  normal component of u (a = s cos(theta))
    c_d = rho C_d / 2,  c_l = rho C_l / 2      (rho: air_density, kg/m^3; C_d, C_l dimensionless)

    F_drag = -c_d A s a n                      along the normal, against the normal motion
    F_lift = -c_l A a (s n - a u^)             perpendicular to u, in the plane of n and u
    F_t = F_drag + F_lift,   each corner gets F_t / 3                                    N

A triangle moving face-on (``u = s n``) gets the drag ``rho C_d A s^2 / 2`` and no lift; edge-on (``a = 0``)
nothing. At an angle ``theta`` between ``u`` and ``n`` the drag's magnitude is ``c_d A s^2 cos(theta)`` and the
lift's ``c_l A s^2 cos(theta) sin(theta)`` (largest at 45 degrees: ``rho C_l A s^2 / 4``), directed along
``-(n - (n . u^) u^)`` times the sign of ``a``: the normal pressure's component across the flow. The force is
the same for either orientation of a triangle (``n -> -n`` leaves it unchanged).

Energy. The force is neither conservative nor the gradient of a dissipation potential in ``v`` (its
Jacobian ``dF/du`` is not symmetric), so ``conservative = dissipative = False``: it has no ``energy`` and
:meth:`Aerodynamics.dissipation` returns 0 (it is not part of the steps' incremental potential ``Phi``; see
:mod:`implicit_cloth.forces`). Its power on the cloth is ``sum_t F_t . (u_t + w)`` with ``F_t . u_t =
-c_d A s a^2 <= 0`` (the lift does no work relative to the air), so the work the cloth can gain from the air is at
most ``sum_t F_t . w``: that is :meth:`Aerodynamics.power`, the wind's power, which the energy balance books as
work from outside (as :class:`~implicit_cloth.effects.drag.Drag`'s). In still air it is 0 and the force only
takes energy away.

Jacobian. With respect to ``u`` (each corner's ``du/dv_j = I / 3``, so every corner pair's block is
``J / 9``)::

    J = dF_t/du = -A [ c_d (a n u^T + s n n^T) + c_l (a n u^T + s n n^T - (a^2 / s)(I - u^ u^T) - 2 a u^ n^T) ]

(0 at ``s = 0``, where the force is of second order). It is not symmetric and its symmetric part is
indefinite, while the step needs a symmetric positive (semi)definite system; the step's blocks take its
normal-normal part ``-(n^T J n) n n^T / 9 = A [c_d (s + a^2 / s) + c_l s (1 - a^2 / s^2)^2] n n^T / 9``
(``>= 0``): exact for the dominant motion, the triangle's velocity along its normal, and the rest of the force
explicit in the solve. ``Aerodynamics(..., exact=True)`` assembles ``-J / 9`` itself (for tests). The force's
dependence on the geometry (``A n``) is not linearised: ``dF/dx`` is left out of the blocks and of ``(dF/dx) w``,
as the membrane's damping's (BW98 section 4.5).

Back-ends: numpy (the reference, vectorised over the triangles) and numba
(:mod:`implicit_cloth.kernels.aerodynamics`, one pass), chosen from the system's back-end at :meth:`bind`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from ..assembly import accumulate_product
from ..backend import Backend, get_backend
from ..config.validate import check_keys, number
from ..errors import SceneError

#: keys of ``[effects.aerodynamics]`` and the defaults of the optional ones
KEYS = ("drag", "lift", "air_density")
DEFAULTS = {"drag": 0.0, "lift": 0.0, "air_density": 1.2}
#: |N| (twice the area, m^2) and |u| (m/s) below which a triangle has no normal / sees no air
TINY = 1e-12


def validate(path: str, value: Any) -> dict[str, float]:
    """``effects.aerodynamics``: ``drag`` (C_d) and ``lift`` (C_l), dimensionless, >= 0 (at least one given; the
    other 0), and ``air_density`` (kg/m^3, > 0, default 1.2)."""
    check_keys(path, value, KEYS)
    if "drag" not in value and "lift" not in value:
        raise SceneError(f"{path}.drag", "missing (give the drag coefficient C_d and/or the lift coefficient "
                                         "C_l, dimensionless, e.g. drag = 1.0)")
    out = dict(DEFAULTS)
    for key in ("drag", "lift"):
        if key in value:
            out[key] = number(f"{path}.{key}", value[key], lo=0.0)
    if "air_density" in value:
        out["air_density"] = number(f"{path}.air_density", value["air_density"], lo=0.0, lo_open=True)
    return out


class Aerodynamics:
    """Per-triangle drag and lift (see the module's docstring for the equations).

    Parameters
    ----------
    n : int
        Number of vertices.
    faces : (T, 3) int array
        The triangles.
    drag, lift : float
        ``C_d`` and ``C_l``, dimensionless.
    air_density : float
        ``rho``, kg/m^3.
    wind : object with ``velocity(x, t)`` or None
        The uniform wind (:class:`~implicit_cloth.effects.wind.ConstantWind`).
    exact : bool
        Assemble the exact ``-dF/dv`` (not symmetric) instead of its normal-normal part.
    """

    name = "aerodynamics"
    conservative = False
    dissipative = False
    elastic = False

    def __init__(self, n: int, faces: np.ndarray, drag: float, lift: float, air_density: float = 1.2,
                 wind: Any = None, exact: bool = False) -> None:
        self.n = int(n)
        self.faces = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
        T = len(self.faces)
        self.c_d = 0.5 * float(air_density) * float(drag)      # kg/m^3
        self.c_l = 0.5 * float(air_density) * float(lift)
        self.wind = wind
        self.exact = bool(exact)
        # incidence: F = B @ f_corner.reshape(3T, 3) adds each corner's force to its vertex
        self._B = sp.csr_array((np.ones(3 * T), (self.faces.ravel(), np.arange(3 * T))), shape=(self.n, 3 * T))
        self.backend: Backend = get_backend("numpy")
        self._G: sp.csr_array | None = None
        self._bidx = np.zeros((0, 9), dtype=np.int64)

    def _w(self, x: np.ndarray, t: float) -> np.ndarray:
        if self.wind is None:
            return np.zeros(3)
        return np.asarray(self.wind.velocity(x, t), dtype=float).reshape(3)

    # ------------------------------------------------------------------ numpy reference
    def _frame(self, x: np.ndarray, v: np.ndarray, t: float):
        """Per triangle: ``A`` (T,), ``n`` (T, 3), ``u`` (T, 3), ``s`` (T,), ``a`` (T,)."""
        X = x[self.faces]
        N = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
        L = np.sqrt(np.einsum("ij,ij->i", N, N))
        n = N * np.divide(1.0, L, out=np.zeros_like(L), where=L > TINY)[:, None]
        u = v[self.faces].mean(axis=1) - self._w(x, t)
        s = np.sqrt(np.einsum("ij,ij->i", u, u))
        a = np.einsum("ij,ij->i", u, n)
        return 0.5 * L, n, u, s, a

    def triangle_forces(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """``F_t`` of every triangle (T, 3), N (each corner gets a third)."""
        A, n, u, s, a = self._frame(x, v, t)
        uh = u * np.divide(1.0, s, out=np.zeros_like(s), where=s > TINY)[:, None]
        return -(A * a)[:, None] * ((self.c_d + self.c_l) * s[:, None] * n - self.c_l * a[:, None] * uh)

    def jacobians(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """``J = dF_t/du`` of every triangle (T, 3, 3) (exact, not symmetric), N*s/m."""
        A, n, u, s, a = self._frame(x, v, t)
        ok = s > TINY
        inv = np.divide(1.0, s, out=np.zeros_like(s), where=ok)
        uh = u * inv[:, None]
        nu = n[:, :, None] * uh[:, None, :]
        nn = n[:, :, None] * n[:, None, :]
        un = uh[:, :, None] * n[:, None, :]
        P = np.eye(3)[None] - uh[:, :, None] * uh[:, None, :]
        c = self.c_d + self.c_l
        J = (c * (a[:, None, None] * nu + s[:, None, None] * nn)
             - self.c_l * ((a * a * inv)[:, None, None] * P + 2.0 * a[:, None, None] * un))
        return np.where(ok[:, None, None], -A[:, None, None] * J, 0.0)

    def _normal_stiffness(self, A, n, s, a) -> np.ndarray:
        """``-n^T J n = A [c_d (s + a^2/s) + c_l s (1 - a^2/s^2)^2]`` (T,), N*s/m, >= 0."""
        ok = s > TINY
        inv = np.divide(1.0, s, out=np.zeros_like(s), where=ok)
        q = 1.0 - a * a * inv * inv
        return np.where(ok, A * (self.c_d * (s + a * a * inv) + self.c_l * s * q * q), 0.0)

    def blocks(self, x: np.ndarray, v: np.ndarray, t: float, c_v: float) -> np.ndarray:
        """Each triangle's block ``-c_v dF_i/dv_j`` (the same for its 9 corner pairs), (T, 3, 3): the exact one
        with ``exact``, else its normal-normal part."""
        if self.exact:
            return -(c_v / 9.0) * self.jacobians(x, v, t)
        A, n, u, s, a = self._frame(x, v, t)
        k = (c_v / 9.0) * self._normal_stiffness(A, n, s, a)
        return k[:, None, None] * (n[:, :, None] * n[:, None, :])

    # ------------------------------------------------------------------ Force
    @property
    def accelerator(self) -> str:
        return self.backend.name

    def energy(self, x: np.ndarray) -> float:
        return 0.0

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        pass

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """0: the force has no dissipation potential (see the module's docstring)."""
        return 0.0

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        if self.backend.compiled and out.dtype == np.float64 and out.flags.c_contiguous:
            self._pass(x, v, t, False, 0.0, None, out)
            return
        Ft = self.triangle_forces(x, v, t) / 3.0
        out += self._B @ np.repeat(Ft, 3, axis=0)

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """The wind's power on the cloth through the force, ``sum_t F_t . w`` (0 without wind), W: the force's
        power on the cloth less ``sum_t F_t . u_t <= 0``."""
        if self.wind is None:
            return 0.0
        w = self._w(x, t)
        if not np.any(w):
            return 0.0
        return float(self.triangle_forces(x, v, t).sum(axis=0) @ w)

    def pairs(self) -> np.ndarray:
        """The three vertex pairs of every triangle (unique, sorted)."""
        f = self.faces
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        return np.unique(e, axis=0).reshape(-1, 2)

    def bind(self, system: Any) -> None:
        """Index maps into ``system``'s blocks (corner pair ``(i, j)`` of triangle ``t`` at ``9 t + 3 i + j``)
        and the back-end (the system's)."""
        self.backend = system.backend
        bidx, G = system.element_index(self.faces)
        self._bidx = bidx
        self._G = G

    def _pass(self, x, v, t, with_blocks, c_v, blocks, f) -> None:
        from ..kernels.aerodynamics import aerodynamics_pass

        c = np.ascontiguousarray
        aerodynamics_pass(c(x, dtype=float), c(v, dtype=float), self._w(x, t), self.faces, self.c_d, self.c_l,
                          TINY, with_blocks, self.exact, float(c_v), self._bidx,
                          blocks if blocks is not None else np.zeros((0, 3, 3)), f)

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        """Add ``-c_v dF/dv`` (the blocks of the module's docstring) to the system's blocks and the force to
        ``f``; ``dF/dx`` is left out (nothing added to ``kw``)."""
        if self.backend.compiled:
            self._pass(x, v, t, c_v != 0.0, c_v, system.blocks, f)
            return
        self.force(x, v, t, f)
        if c_v == 0.0:
            return
        X = np.repeat(self.blocks(x, v, t, c_v), 9, axis=0)             # (9T, 3, 3): each corner pair
        accumulate_product(self._G, np.ascontiguousarray(X.reshape(-1, 9)), system.blocks.reshape(-1, 9))


def build(model: Any, value: dict[str, float], effects: dict[str, Any] | None = None) -> Aerodynamics:
    """The ``effects.aerodynamics`` term on the cloth's triangles of positive rest area, relative to
    ``effects.wind`` when the table has one."""
    from ..cloth import degenerate_faces

    wind = (effects or {}).get("wind")
    field = None
    if wind is not None:
        from .wind import ConstantWind

        field = ConstantWind(wind["velocity"])
    faces = model.faces[~degenerate_faces(model.rest_positions, model.faces)]
    return Aerodynamics(model.n, faces, value["drag"], value["lift"], value["air_density"], field)
