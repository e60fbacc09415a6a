"""Primitive obstacles: signed distance, outward normal, sharp features and continuous sweeps.

Every shape is described in its own *local* frame (centre at the origin, the
shape's axis along +z) and placed in the world by a :class:`RigidMotion` (position
and rotation at time ``t``: :class:`Motion` for a constant velocity and angular
velocity, :class:`KeyframedMotion` for keyframes). All functions take local points
``p`` as (K, 3) arrays, metres, and are vectorised over K.

Signed distance ``phi(p)`` (m) is negative inside, zero on the surface and
equals the Euclidean distance to the surface everywhere, so ``|grad phi| = 1``
(an *exact* signed distance, not a bound). Its gradient is the outward unit
normal; at a sharp feature (a box corner or edge, the cone's apex or rim) the
normal of an outside point is the direction from the nearest surface point to
the point, which is exact at tips and edges.

Continuous sweeps (:func:`sweep`): the earliest ``s`` in ``[0, 1]`` at which
the point ``p(s) = p0 + s (p1 - p0)`` comes within ``r`` of the shape,
``phi(p(s)) = r``. Sphere and plane: closed form (a quadratic and a linear
equation). Box, capsule, cone: conservative advancement on the exact signed
distance, ``s_{k+1} = s_k + (phi(p(s_k)) - r) / |p1 - p0|``, which never steps
past the surface because ``phi`` is 1-Lipschitz, so the point at the returned
``s`` is never inside the inflated shape.

Sharp features (convex shapes only): ``feature_points`` (box corners, cone apex
and rim) and ``feature_edges`` (box edges, cone rim as a polygon inscribed in
the circle). A cloth triangle can be pierced by a corner, and a cloth edge can
slide across a box edge, with every cloth vertex outside: these features are
tested against cloth triangles and edges by :mod:`implicit_cloth.collision.ccd`.
Smooth shapes (sphere, capsule, plane) have none: a cloth triangle whose
vertices are at distance ``>= r`` from a surface of curvature radius ``R`` dips
at most ``L^2 / (8 R)`` (``L`` its longest edge) towards it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

#: Segments of the polygon that stands for the cone's base rim as a sharp feature.
CONE_RIM_SEGMENTS = 64
#: Conservative advancement stops within this fraction of r (or 1e-9 m) of the inflated surface.
SWEEP_TOLERANCE = 1e-3
#: Most conservative-advancement iterations (grazing sweeps converge slowly; the sweep then stops early).
SWEEP_MAX_ITERATIONS = 100


def _norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", a, a))


#: Golden-section steps for the nearest point of an edge (0.618^30 ~ 5e-7 of the edge).
GOLDEN_STEPS = 30


def golden_minimum(shape: Shape, a0: np.ndarray, a1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter ``a`` (K,) and value (K,) m of the smallest signed distance along segments a0 -> a1.

    The signed distance of a convex shape is convex, so along a segment it has one
    minimum, found by golden-section search (:data:`GOLDEN_STEPS` steps).
    """
    d = a1 - a0
    lo, hi = np.zeros(len(a0)), np.ones(len(a0))
    g = 0.5 * (np.sqrt(5.0) - 1.0)
    m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1 = shape.distance(a0 + m1[:, None] * d)
    f2 = shape.distance(a0 + m2[:, None] * d)
    for _ in range(GOLDEN_STEPS):
        left = f1 < f2                       # the minimum lies in [lo, m2], else in [m1, hi]
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
        n1 = np.where(left, hi - g * (hi - lo), m2)
        n2 = np.where(left, m1, lo + g * (hi - lo))
        fn = shape.distance(a0 + np.where(left, n1, n2)[:, None] * d)
        f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
        m1, m2 = n1, n2
    a = 0.5 * (lo + hi)
    ends = np.column_stack([shape.distance(a0), shape.distance(a1), shape.distance(a0 + a[:, None] * d)])
    best = np.argmin(ends, axis=1)
    a = np.choose(best, [np.zeros(len(a0)), np.ones(len(a0)), a])
    return a, ends[np.arange(len(a0)), best]


def _unit(a: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """Rows of ``a`` normalised; zero rows become ``fallback`` (default +z)."""
    n = _norm(a)
    out = np.empty_like(a)
    ok = n > 1e-300
    out[ok] = a[ok] / n[ok, None]
    out[~ok] = (0.0, 0.0, 1.0) if fallback is None else fallback
    return out


# --------------------------------------------------------------------------- motion
class RigidMotion:
    """Rigid motion of an obstacle: ``x = c(t) + R(t) p`` for a local point ``p``.

    The collision code asks a motion only through these methods, each vectorised
    over times: ``t`` is a float (results for that instant) or a (K,) array (one
    result per row, e.g. per contact time). Subclasses implement :meth:`pose` and
    :meth:`twist`.

    Within one time step the collision code treats the obstacle's motion relative
    to the cloth as linear: the cloth's start and end positions are moved into the
    obstacle's frame at ``pose(t0)`` and ``pose(t1)`` and joined by a straight
    path there. A motion whose velocity changes inside a step (a keyframe of
    :class:`KeyframedMotion` between ``t0`` and ``t1``) is then approximated by
    its chord from ``pose(t0)`` to ``pose(t1)``; contact points, normals and
    obstacle velocities at a time of impact ``tc`` still use the exact
    ``pose(tc)`` and ``twist(tc)``.
    """

    @property
    def moving(self) -> bool:
        """Whether the obstacle ever moves."""
        raise NotImplementedError

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Centre ``c(t)`` (..., 3) m and rotation matrix ``R(t)`` (..., 3, 3) at time(s) ``t`` (s)."""
        raise NotImplementedError

    def twist(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Velocity of the centre ``dc/dt`` (..., 3) m/s and angular velocity ``omega`` (..., 3) rad/s.

        ``omega`` is in world axes: ``dR/dt = [omega]x R``.
        """
        raise NotImplementedError

    def to_local(self, x: np.ndarray, t) -> np.ndarray:
        """World points (K, 3) to local coordinates ``R^T (x - c)`` at time ``t`` (float or (K,))."""
        c, R = self.pose(t)
        if R.ndim == 2:
            return (x - c) @ R
        return np.einsum("kji,kj->ki", R, x - c)

    def to_world(self, p: np.ndarray, t) -> np.ndarray:
        """Local points (K, 3) to world coordinates ``c + R p`` at time ``t`` (float or (K,))."""
        c, R = self.pose(t)
        if R.ndim == 2:
            return p @ R.T + c
        return np.einsum("kij,kj->ki", R, p) + c

    def point_velocity(self, x: np.ndarray, t) -> np.ndarray:
        """Velocity (K, 3) m/s of the obstacle's material point at world ``x``: ``dc/dt + omega x (x - c)``."""
        c, _ = self.pose(t)
        v, w = self.twist(t)
        return v + np.cross(w, x - c)


@dataclass
class Motion(RigidMotion):
    """Constant twist: ``c(t) = center + velocity t`` (m), ``R(t) = exp(t [omega]x) R0``.

    A constant angular velocity ``omega`` (rad/s, world frame) about the moving centre.
    """

    center: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def moving(self) -> bool:
        return bool(np.any(self.velocity) or np.any(self.angular_velocity))

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        c = self.center + t[..., None] * self.velocity
        if np.any(self.angular_velocity):
            R = Rotation.from_rotvec(t[..., None] * self.angular_velocity).as_matrix() @ self.rotation
        else:
            R = np.broadcast_to(self.rotation, t.shape + (3, 3))
        return c, R

    def twist(self, t) -> tuple[np.ndarray, np.ndarray]:
        shape = np.shape(t) + (3,)
        return np.broadcast_to(self.velocity, shape), np.broadcast_to(self.angular_velocity, shape)


class KeyframedMotion(RigidMotion):
    """Piecewise motion through keys ``(t_k, c_k, Q_k)``: ``c(t)`` piecewise linear, ``R(t) = Q(t) R0``.

    Between keys ``t_k <= t < t_{k+1}`` the centre moves at the constant velocity
    ``(c_{k+1} - c_k) / (t_{k+1} - t_k)`` and the key rotation ``Q`` turns by
    spherical linear interpolation (:class:`scipy.spatial.transform.Slerp`) at the
    constant world angular velocity ``omega_k = log(Q_{k+1} Q_k^T) / (t_{k+1} - t_k)``
    (the shorter way round: a turn of more than pi between two keys needs a key
    in between). ``R0`` is the shape's own orientation, ``Q_k`` each key's
    rotation on top of it, about the centre. Before the first key the obstacle
    rests at it, after the last at the last. At a key's time the velocity is that
    of the segment starting there.

    Parameters
    ----------
    times : (n,) array
        Strictly increasing key times, s, n >= 2.
    centers : (n, 3) array
        The centre at each key, m.
    rotvecs : (n, 3) array
        Each key's rotation vector (axis * angle), rad.
    rotation : (3, 3) array
        The shape's own orientation ``R0``.
    """

    def __init__(self, times, centers, rotvecs, rotation=None) -> None:
        from scipy.spatial.transform import Slerp

        self.times = np.asarray(times, dtype=float)
        self.centers = np.asarray(centers, dtype=float)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        if len(self.times) < 2 or np.any(np.diff(self.times) <= 0):
            raise ValueError("keyframe times must be at least two, strictly increasing")
        keys = Rotation.from_rotvec(np.asarray(rotvecs, dtype=float))
        self._slerp = Slerp(self.times, keys)
        dt = np.diff(self.times)
        self._velocity = np.diff(self.centers, axis=0) / dt[:, None]                  # (n-1, 3) m/s
        self._omega = (keys[1:] * keys[:-1].inv()).as_rotvec() / dt[:, None]         # (n-1, 3) rad/s

    @property
    def moving(self) -> bool:
        return bool(np.any(self._velocity) or np.any(self._omega))

    def _segment(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Times clamped to the keys' span, and the segment index of each (the one starting at or before it)."""
        tc = np.clip(np.asarray(t, dtype=float), self.times[0], self.times[-1])
        k = np.clip(np.searchsorted(self.times, tc, side="right") - 1, 0, len(self.times) - 2)
        return tc, k

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        tc, k = self._segment(t)
        a = (tc - self.times[k]) / (self.times[k + 1] - self.times[k])
        a = a[..., None]
        c = (1.0 - a) * self.centers[k] + a * self.centers[k + 1]   # exactly the keys at a = 0 and 1
        R = self._slerp(tc).as_matrix() @ self.rotation
        return c, R

    def twist(self, t) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        _, k = self._segment(t)
        inside = ((t >= self.times[0]) & (t < self.times[-1]))[..., None]
        return np.where(inside, self._velocity[k], 0.0), np.where(inside, self._omega[k], 0.0)


# --------------------------------------------------------------------------- shapes
def _across(n: np.ndarray, axis: np.ndarray | None) -> np.ndarray:
    """``I - n n^T`` (less ``a a^T`` for the unit or zero ``axis`` rows), (K, 3, 3)."""
    H = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    if axis is not None:
        H -= axis[:, :, None] * axis[:, None, :]
    return H


class Shape:
    """A primitive in its local frame. Subclasses implement :meth:`closest`."""

    name = ""
    #: Local points of sharp corners or tips, (P, 3).
    feature_points: np.ndarray = np.zeros((0, 3))
    #: Local sharp edges as (E, 2, 3) segments.
    feature_edges: np.ndarray = np.zeros((0, 2, 3))
    #: Half-extents of the local bounding box (inf for the plane).
    half_extent: np.ndarray = np.zeros(3)
    #: Whether the surface away from its sharp features is flat (box, plane): a straight cloth edge whose
    #: ends are outside then comes nearer only at a feature (tested as such), never between them.
    flat = False
    #: Whether :meth:`distance` is the exact Euclidean signed distance, so 1-Lipschitz: a point within ``d`` of
    #: another is at most ``d`` nearer the surface (contact detection's edge test skips the edges it rules out).
    exact_distance = False

    def segment_minimum(self, a0: np.ndarray, a1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parameter ``a`` (K,) and value (K,) m of the smallest signed distance along segments ``a0 -> a1``.

        Golden-section search on the (convex) signed distance; shapes with a closed form override it.
        """
        return golden_minimum(self, a0, a1)

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance (K,) m, outward unit normal (K, 3) and nearest surface point (K, 3)."""
        raise NotImplementedError

    def distance(self, p: np.ndarray) -> np.ndarray:
        return self.closest(p)[0]

    def distance_hessian(self, p: np.ndarray, n: np.ndarray, c: np.ndarray) -> np.ndarray | None:
        """The signed distance's Hessian ``d2 phi / dp2`` (K, 3, 3) at points ``p`` outside the shape (their
        normals ``n`` and nearest points ``c`` from :meth:`closest`), or None where the shape does not give it (the
        contact's Hessian then drops its curvature term). Outside a convex shape it is positive semidefinite:
        ``1 / rho`` across the normal in each direction the surface curves, ``rho`` the radius of curvature plus
        the distance."""
        return None

    def sweep(self, p0: np.ndarray, p1: np.ndarray, r: float) -> np.ndarray:
        """Earliest ``s`` in [0, 1] with ``phi(p0 + s (p1 - p0)) <= r``; ``inf`` where there is none.

        Conservative advancement (see the module notes); subclasses with a closed form override it.
        """
        d = p1 - p0
        speed = _norm(d)
        s = np.zeros(len(p0))
        gap = self.distance(p0) - r
        tol = max(SWEEP_TOLERANCE * r, 1e-9)
        active = gap > tol
        for _ in range(SWEEP_MAX_ITERATIONS):
            idx = np.flatnonzero(active)
            if not len(idx):
                break
            step = np.where(speed[idx] > 0, gap[idx] / np.maximum(speed[idx], 1e-300), np.inf)
            s[idx] += step
            gone = s[idx] > 1.0
            s[idx[gone]] = np.inf
            active[idx[gone]] = False
            live = idx[~gone]
            g = self.distance(p0[live] + s[live, None] * d[live]) - r
            gap[live] = g
            active[live[g <= tol]] = False
        # still advancing after the cap (a grazing path): stop where it got to, which is outside
        # the inflated shape and near it, so that a later hit is never missed
        return s


class Sphere(Shape):
    name = "sphere"
    exact_distance = True

    def __init__(self, radius: float) -> None:
        self.radius = float(radius)
        self.half_extent = np.full(3, self.radius)

    def closest(self, p):
        n = _unit(p)
        return _norm(p) - self.radius, n, self.radius * n

    def distance(self, p):
        return _norm(p) - self.radius

    def distance_hessian(self, p, n, c):
        return _across(n, None) / np.maximum(_norm(p), 1e-300)[:, None, None]

    def segment_minimum(self, a0, a1):
        """Closed form: the segment's point nearest to the centre."""
        d = a1 - a0
        dd = np.einsum("ij,ij->i", d, d)
        a = np.clip(-np.einsum("ij,ij->i", a0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        return a, _norm(a0 + a[:, None] * d) - self.radius

    def sweep(self, p0, p1, r):
        """Closed form: smallest root of ``|p0 + s d|^2 = (R + r)^2`` in [0, 1]."""
        d = p1 - p0
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", p0, d)
        rr = (self.radius + r) ** 2
        c = np.einsum("ij,ij->i", p0, p0) - rr
        s = np.full(len(p0), np.inf)
        s[c <= 0] = 0.0
        disc = b * b - a * c
        ok = (c > 0) & (a > 0) & (disc >= 0) & (b < 0)
        root = (-b[ok] - np.sqrt(disc[ok])) / a[ok]
        s[np.flatnonzero(ok)[root <= 1.0]] = root[root <= 1.0]
        return s


class Plane(Shape):
    """The half-space ``z <= 0`` of the local frame (outward normal +z)."""

    name = "plane"
    flat = True

    def __init__(self) -> None:
        self.half_extent = np.full(3, np.inf)

    def closest(self, p):
        n = np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape).copy()
        q = p.copy()
        q[:, 2] = 0.0
        return p[:, 2].copy(), n, q

    def distance_hessian(self, p, n, c):
        return np.zeros((len(p), 3, 3))

    def sweep(self, p0, p1, r):
        """Closed form: ``p0_z + s (p1_z - p0_z) = r``."""
        z0, z1 = p0[:, 2] - r, p1[:, 2] - r
        s = np.full(len(p0), np.inf)
        s[z0 <= 0] = 0.0
        hit = (z0 > 0) & (z1 <= 0)
        s[hit] = z0[hit] / (z0[hit] - z1[hit])
        return s


class Box(Shape):
    """Axis-aligned box of full extents ``size`` centred at the origin of its local frame."""

    name = "box"
    flat = True

    def __init__(self, size) -> None:
        self.h = 0.5 * np.asarray(size, dtype=float)
        self.half_extent = self.h.copy()
        signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=float)
        self.feature_points = signs * self.h
        edges = []
        for a in range(3):                          # 4 edges parallel to each axis
            b, c = [k for k in range(3) if k != a]
            for sb in (-1, 1):
                for sc in (-1, 1):
                    e = np.zeros((2, 3))
                    e[:, a] = (-self.h[a], self.h[a])
                    e[:, b] = sb * self.h[b]
                    e[:, c] = sc * self.h[c]
                    edges.append(e)
        self.feature_edges = np.array(edges)

    def distance(self, p):
        q = np.abs(p) - self.h
        return _norm(np.maximum(q, 0.0)) + np.minimum(q.max(axis=1), 0.0)

    def closest(self, p):
        h = self.h
        q = np.abs(p) - h
        sgn = np.where(p < 0, -1.0, 1.0)
        outside = np.any(q > 0, axis=1)
        qp = np.maximum(q, 0.0)
        d_out = _norm(qp)
        phi = np.where(outside, d_out, np.max(q, axis=1))
        c = np.clip(p, -h, h)                        # nearest point for outside points
        n = _unit(p - c)
        ins = np.flatnonzero(~outside)
        if len(ins):
            ax = np.argmax(q[ins], axis=1)
            n[ins] = 0.0
            n[ins, ax] = sgn[ins, ax]
            c[ins] = p[ins]
            c[ins, ax] = sgn[ins, ax] * h[ax]
        return phi, n, c

    def distance_hessian(self, p, n, c):
        """Outside: ``(P - n n^T) / phi``, ``P`` the projector on the axes the nearest point is clipped in (a face:
        0; an edge: a cylinder's; a corner: a sphere's)."""
        q = np.abs(p) - self.h
        clipped = (q > 0).astype(float)
        H = clipped[:, :, None] * np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        phi = np.sqrt(np.einsum("ij,ij->i", np.maximum(q, 0.0), np.maximum(q, 0.0)))
        H /= np.maximum(phi, 1e-300)[:, None, None]
        H[~np.any(q > 0, axis=1)] = 0.0
        return H


class Capsule(Shape):
    """Points within ``radius`` of the segment from ``-height/2`` to ``+height/2`` on the local z axis."""

    name = "capsule"
    exact_distance = True

    def __init__(self, radius: float, height: float) -> None:
        self.radius, self.height = float(radius), float(height)
        self.half_extent = np.array([self.radius, self.radius, self.radius + 0.5 * self.height])

    def distance(self, p):
        z = p[:, 2] - np.clip(p[:, 2], -0.5 * self.height, 0.5 * self.height)
        return np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + z * z) - self.radius

    def segment_minimum(self, a0, a1):
        """Closed form: the nearest points of the segment and the capsule's axis."""
        from .ccd import segment_closest

        q0 = np.zeros_like(a0)
        q1 = np.zeros_like(a0)
        q0[:, 2], q1[:, 2] = -0.5 * self.height, 0.5 * self.height
        a, b = segment_closest(a0, a1, q0, q1)
        gap = a0 + a[:, None] * (a1 - a0) - (q0 + b[:, None] * (q1 - q0))
        return a, _norm(gap) - self.radius

    def closest(self, p):
        a = np.zeros_like(p)
        a[:, 2] = np.clip(p[:, 2], -0.5 * self.height, 0.5 * self.height)
        n = _unit(p - a, fallback=np.array([1.0, 0.0, 0.0]))
        return _norm(p - a) - self.radius, n, a + self.radius * n

    def distance_hessian(self, p, n, c):
        """``(I - n n^T - e_z e_z^T) / rho`` beside the cylinder (``rho`` the distance to the axis), a sphere's
        about the end beyond it."""
        side = np.abs(p[:, 2]) < 0.5 * self.height
        axis = np.where(side[:, None], np.array([0.0, 0.0, 1.0]), 0.0)
        rho = _norm(p - (c - self.radius * n))
        return _across(n, axis) / np.maximum(rho, 1e-300)[:, None, None]


class Cone(Shape):
    """Solid cone: base disc of ``radius`` at local z = 0 (its centre at the origin), apex at z = ``height``.

    The signed distance is that of the cross-section triangle ``(0,0), (R,0), (0,H)``
    in the (rho, z) half-plane, rho = sqrt(x^2 + y^2), to its two boundary
    segments (base and slant), negative inside.
    """

    name = "cone"
    exact_distance = True     # (the cross-section's, exact for a solid of revolution)

    def __init__(self, radius: float, height: float) -> None:
        self.radius, self.height = float(radius), float(height)
        self.half_extent = np.array([self.radius, self.radius, self.height])   # about (0, 0, 0): z in [0, H]
        k = CONE_RIM_SEGMENTS
        ang = 2 * np.pi * np.arange(k) / k
        rim = np.stack([self.radius * np.cos(ang), self.radius * np.sin(ang), np.zeros(k)], axis=1)
        self.feature_points = np.vstack([[0.0, 0.0, self.height], rim])
        self.feature_edges = np.stack([rim, np.roll(rim, -1, axis=0)], axis=1)

    def distance(self, p):
        R, H = self.radius, self.height
        rho = np.hypot(p[:, 0], p[:, 1])
        z = p[:, 2]
        db = np.hypot(rho - np.minimum(rho, R), z)                        # to the base disc's segment
        u = np.clip(((R - rho) * R + z * H) / (R * R + H * H), 0.0, 1.0)  # along the slant from (R, 0)
        ds = np.hypot(rho - R + u * R, z - u * H)
        dist = np.minimum(db, ds)
        inside = (z >= 0) & (rho / R + z / H <= 1.0)
        return np.where(inside, -dist, dist)

    def closest(self, p):
        R, H = self.radius, self.height
        rho = np.hypot(p[:, 0], p[:, 1])
        z = p[:, 2]
        # base segment (0,0)-(R,0)
        b_rho = np.clip(rho, 0.0, R)
        db = np.stack([rho - b_rho, z], axis=1)
        # slant segment (R,0)-(0,H)
        e = np.array([-R, H])
        u = np.clip(((rho - R) * e[0] + z * e[1]) / (e @ e), 0.0, 1.0)
        s_rho, s_z = R + u * e[0], u * e[1]
        ds = np.stack([rho - s_rho, z - s_z], axis=1)
        nb, ns = _norm(db), _norm(ds)
        use_b = nb <= ns
        dist = np.where(use_b, nb, ns)
        c_rho = np.where(use_b, b_rho, s_rho)
        c_z = np.where(use_b, 0.0, s_z)
        inside = (z >= 0) & (rho / R + z / H <= 1.0)
        phi = np.where(inside, -dist, dist)
        # 2-D outward normal: from the nearest point to p outside, reversed inside; exactly on the
        # surface, the face normal of the nearest segment
        g = np.stack([rho - c_rho, z - c_z], axis=1)
        g = np.where(inside[:, None], -g, g)
        face = np.where(use_b[:, None], np.array([0.0, -1.0]), np.array([H, R]) / np.hypot(H, R))
        gn = _norm(g)
        small = gn <= 1e-12 * max(R, H)
        g[small] = face[small]
        g /= _norm(g)[:, None]
        er = np.zeros((len(p), 2))
        er[:, 0] = 1.0
        on_axis = rho > 1e-300
        er[on_axis] = p[on_axis, :2] / rho[on_axis, None]
        n = np.column_stack([g[:, :1] * er, g[:, 1]])
        c = np.column_stack([c_rho[:, None] * er, c_z])
        return phi, n, c

    def aabb_center(self) -> np.ndarray:
        return np.array([0.0, 0.0, 0.5 * self.height])


#: A direction is outside a mesh feature's normal cone when its faces (or edges) lie on both sides of the plane
#: normal to it by more than this cosine (about 3 degrees)
CONE_TOLERANCE = 0.05


class MeshShape(Shape):
    """A triangle mesh obstacle (any file trimesh reads), two-sided: the cloth stays on the side it is on.

    No signed distance: contacts are found by the box broad phase
    (:mod:`~implicit_cloth.collision.broadphase`) and the exact point-triangle
    and edge-edge tests of :mod:`~implicit_cloth.collision.ccd`. Every mesh
    vertex and edge is treated as a sharp feature, holding the cloth only along
    the directions of its normal cone (:meth:`edge_cone`, :meth:`vertex_cone`).
    """

    name = "mesh"

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from . import broadphase

        self.vertices = np.asarray(vertices, dtype=float)
        self.faces = np.asarray(faces, dtype=np.int64)
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        e.sort(axis=1)
        self.edges, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.ravel()
        self.face_edges = inv.reshape(3, -1).T                       # (F, 3) edge indices of each face
        self.bounds = (self.vertices.min(axis=0), self.vertices.max(axis=0))
        self.half_extent = np.maximum(np.abs(self.bounds[0]), np.abs(self.bounds[1]))
        n = np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                     self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]])
        self.face_normals = n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        self.feature_points = self.vertices
        self.feature_edges = self.vertices[self.edges]
        self.index = broadphase.TriangleIndex(self.vertices, self.faces)
        # each edge's two faces' third vertices (-1: a boundary edge), for the edges' normal cones
        opp = np.full((len(self.edges), 2), -1, dtype=np.int64)
        third = self.faces[:, [2, 0, 1]].T.ravel()                   # opposite edges (v0 v1), (v1 v2), (v2 v0)
        order = np.argsort(inv, kind="stable")
        grouped = inv[order]
        rank = np.arange(len(order)) - np.searchsorted(grouped, grouped)   # an edge's first, second face (manifold)
        for j in (0, 1):
            opp[grouped[rank == j], j] = third[order][rank == j]
        self.edge_opposite = opp
        # each vertex's edges (CSR), for the vertices' normal cones
        ends = np.concatenate([self.edges, self.edges[:, ::-1]])
        ends = ends[np.argsort(ends[:, 0], kind="stable")]
        self.vertex_start = np.searchsorted(ends[:, 0], np.arange(len(self.vertices) + 1))
        self.vertex_neighbours = ends[:, 1]
        # closed (every edge in exactly two faces): the mesh has an inside
        self.closed = bool(np.all(np.bincount(inv, minlength=len(self.edges)) == 2))

    def edge_cone(self, edge: np.ndarray, n: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether each direction ``n`` (K, 3) from the point ``q`` of mesh edge ``edge`` (K,) lies in the edge's
        normal cone, on either side (the mesh is two-sided): both of its faces on one side of the plane through
        ``q`` normal to ``n`` (a boundary edge: always). Outside it, the point ``q + d n`` is nearer to a face than
        to the edge (on a convex surface), and a contact along ``n`` holds the cloth across the surface."""
        return self._cone(n, q, self.edge_opposite[edge])

    def vertex_cone(self, vertex: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Whether each direction ``n`` (K, 3) lies in the normal cone of mesh vertex ``vertex`` (K,), on either
        side: every edge from the vertex on one side of the plane through it normal to ``n``."""
        start, stop = self.vertex_start[vertex], self.vertex_start[vertex + 1]
        count = stop - start
        rows = np.repeat(np.arange(len(vertex)), count)
        first = np.repeat(start - np.r_[0, count.cumsum()[:-1]], count)     # row r's j-th: start_r + j
        nb = self.vertex_neighbours[first + np.arange(count.sum())]
        d = self.vertices[nb] - self.vertices[vertex][rows]
        c = np.einsum("ij,ij->i", n[rows], d) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        lo = np.full(len(vertex), np.inf)
        hi = np.full(len(vertex), -np.inf)
        np.minimum.at(lo, rows, c)
        np.maximum.at(hi, rows, c)
        return ~((lo < -CONE_TOLERANCE) & (hi > CONE_TOLERANCE))

    def _cone(self, n: np.ndarray, q: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Whether the mesh vertices ``others`` (K, m; -1: none) lie on one side of the planes through ``q`` normal
        to ``n`` (cosines within :data:`CONE_TOLERANCE` count as on the plane)."""
        c = np.zeros(others.shape)
        for j in range(others.shape[1]):            # the edge's two faces
            d = self.vertices[np.maximum(others[:, j], 0)] - q
            c[:, j] = np.where(others[:, j] >= 0,
                               np.einsum("ij,ij->i", n, d) / np.maximum(np.linalg.norm(d, axis=1), 1e-300), 0.0)
        return ~((c.min(axis=1) < -CONE_TOLERANCE) & (c.max(axis=1) > CONE_TOLERANCE))

    def depth(self, p: np.ndarray) -> np.ndarray:
        """Depth (K,) m of local points inside the mesh: the distance to the nearest face of the points inside
        (winding number above one half), 0 outside and everywhere for an open mesh."""
        out = np.zeros(len(p))
        if not self.closed or not len(p):
            return out
        lo, hi = self.bounds
        cand = np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))
        if not len(cand):
            return out
        tri = self.vertices[self.faces]
        inside = cand[np.abs(_winding(p[cand], tri)) > 0.5]
        if len(inside):
            from .ccd import point_triangle_closest

            k, f = len(inside), len(tri)
            P = np.repeat(p[inside], f, axis=0)
            q, _ = point_triangle_closest(P, np.tile(tri[:, 0], (k, 1)), np.tile(tri[:, 1], (k, 1)),
                                          np.tile(tri[:, 2], (k, 1)))
            out[inside] = np.linalg.norm(P - q, axis=1).reshape(k, f).min(axis=1)
        return out


def _winding(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Generalised winding numbers (K,) of points ``p`` with respect to triangles ``tri`` (F, 3, 3).

    The sum of the triangles' signed solid angles over 4 pi (Van Oosterom & Strackee 1983): about 1 inside a
    closed, outward-oriented mesh, 0 outside.
    """
    out = np.zeros(len(p))
    step = max(1, 2_000_000 // max(len(tri), 1))
    for s in range(0, len(p), step):              # chunks of points: memory, not a per-point loop
        a = tri[None, :, 0] - p[s:s + step, None]
        b = tri[None, :, 1] - p[s:s + step, None]
        c = tri[None, :, 2] - p[s:s + step, None]
        la, lb, lc = _norm(a), _norm(b), _norm(c)
        num = np.einsum("kfi,kfi->kf", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("kfi,kfi->kf", a, b) * lc + np.einsum("kfi,kfi->kf", b, c) * la \
            + np.einsum("kfi,kfi->kf", c, a) * lb
        out[s:s + step] = np.arctan2(num, den).sum(axis=1) / (2.0 * np.pi)
    return out


def local_aabb(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners of the shape's local bounding box, m."""
    if isinstance(shape, MeshShape):
        return shape.bounds
    if isinstance(shape, Cone):
        return np.array([-shape.radius, -shape.radius, 0.0]), np.array([shape.radius, shape.radius, shape.height])
    return -shape.half_extent, shape.half_extent


def rotation_to_axis(axis) -> np.ndarray:
    """Rotation matrix taking local +z to the unit vector along ``axis``."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, a)
    s, c = np.linalg.norm(v), float(z @ a)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return Rotation.from_rotvec(v / s * np.arctan2(s, c)).as_matrix()


def _motion(spec: dict, center: np.ndarray, R: np.ndarray) -> RigidMotion:
    """Keyframed motion if the table has ``keyframes``, else constant velocity and angular velocity."""
    keys = spec.get("keyframes")
    if keys:
        return KeyframedMotion([k["time"] for k in keys], [k["center"] for k in keys],
                               [k["rotation"] for k in keys], R)
    return Motion(center, R, np.asarray(spec["velocity"], dtype=float),
                  np.asarray(spec["angular_velocity"], dtype=float))


def placement(spec: dict) -> RigidMotion:
    """The rigid motion (pose at every time) of one validated ``[[obstacles]]`` table, without its shape.

    The local frame of each shape: see its class (sphere, box and capsule centred at the origin, the cone's base
    centre at the origin and its apex on +z, the plane's surface z = 0 with outward normal +z, a mesh in its
    file's coordinates times ``scale``).
    """
    kind = spec["shape"]
    if kind == "plane":
        return _motion(spec, np.asarray(spec["point"], float), rotation_to_axis(spec["normal"]))
    if kind == "mesh":
        return _motion(spec, np.asarray(spec["translation"], float), Rotation.from_rotvec(spec["rotation"]).as_matrix())
    if kind == "box":
        R = Rotation.from_rotvec(spec["rotation"]).as_matrix()
    elif kind in ("capsule", "cone"):
        R = rotation_to_axis(spec["axis"])
    else:
        R = np.eye(3)
    return _motion(spec, np.asarray(spec["center"], dtype=float), R)


def build(spec: dict) -> tuple[Shape, RigidMotion]:
    """The shape and its motion from one validated ``[[obstacles]]`` table."""
    kind = spec["shape"]
    if kind == "plane":
        shape: Shape = Plane()
    elif kind == "sphere":
        shape = Sphere(spec["radius"])
    elif kind == "box":
        shape = Box(spec["size"])
    elif kind == "capsule":
        shape = Capsule(spec["radius"], spec["height"])
    elif kind == "cone":
        shape = Cone(spec["radius"], spec["height"])
    elif kind == "mesh":
        from ..geometry import load_obstacle_mesh

        verts, faces = load_obstacle_mesh(spec["path"])
        shape = MeshShape(verts * spec["scale"], faces)
    else:  # pragma: no cover - validation refuses other shapes
        raise ValueError(f"unknown obstacle shape {kind!r}")
    return shape, placement(spec)
