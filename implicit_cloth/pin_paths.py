"""Paths of pinned vertices: constant velocity or keyframes.

A pin group with ``keyframes`` (``cloth.pins[k].keyframes``: ``{time, translation, rotation}``) moves its
vertices rigidly: vertex ``p`` of the group is at::

    target_p(t) = c + R(t) (x_p(0) - c) + T(t)

with ``c`` the group's centroid at t = 0, ``T(t)`` the translation interpolated linearly between keys and
``R(t)`` the rotation of the rotation vector interpolated linearly between keys (each
key's ``rotation``: axis times angle, rad, about ``c``). For keys turning about one fixed axis that is a
constant angular velocity about it, the same motion as the keyframed obstacles' spherical interpolation
(:class:`~implicit_cloth.collision.shapes.KeyframedMotion`); for keys about different axes the two differ
(the rotation vector's components are interpolated independently, as an animation channel would be, and a
turn of more than pi between keys is not taken the shorter way round). Before the first key, when it is later
than t = 0, the group moves from its place at t = 0 (an implicit key ``{time = 0}``) to the first key; after
the last pose.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def rotation_matrix(r: np.ndarray) -> np.ndarray:
    """``exp([r]x)``, the rotation of rotation vector ``r`` (Rodrigues), (3, 3)."""
    th = float(np.linalg.norm(r))
    K = _skew(r)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


def angular_velocity(r: np.ndarray, rdot: np.ndarray) -> np.ndarray:
    """The world angular velocity of ``R(t) = exp([r(t)]x)`` when ``r`` changes at ``rdot``: ``J_l(r) rdot``."""
    th = float(np.linalg.norm(r))
    K = _skew(r)
    if th < 1e-8:
        J = np.eye(3) + 0.5 * K
    else:
        J = np.eye(3) + (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K
    return J @ rdot


class Keyframes:
    """Piecewise-linear translation ``T(t)`` (m) and rotation vector ``r(t)`` (rad) through validated keys
    (module docstring): ``pose(t) -> (T, R)`` and ``twist(t) -> (dT/dt, omega)`` of the segment starting at
    ``t`` (0 after the last key)."""

    def __init__(self, keys: list[dict[str, Any]]) -> None:
        keys = list(keys)
        if keys[0]["time"] > 0.0:
            keys.insert(0, {"time": 0.0, "translation": [0.0, 0.0, 0.0], "rotation": [0.0, 0.0, 0.0]})
        self.times = np.array([k["time"] for k in keys], dtype=float)
        self.T = np.array([k["translation"] for k in keys], dtype=float).reshape(-1, 3)
        self.r = np.array([k["rotation"] for k in keys], dtype=float).reshape(-1, 3)

    def _at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n = len(self.times)
        if n == 1 or t >= self.times[-1]:
            z = np.zeros(3)
            return self.T[-1], self.r[-1], z, z
        k = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, n - 2))
        dt = self.times[k + 1] - self.times[k]
        a = (max(t, self.times[0]) - self.times[k]) / dt
        dT = (self.T[k + 1] - self.T[k]) / dt
        dr = (self.r[k + 1] - self.r[k]) / dt
        return (1.0 - a) * self.T[k] + a * self.T[k + 1], (1.0 - a) * self.r[k] + a * self.r[k + 1], dT, dr

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        T, r, _, _ = self._at(t)
        return T, rotation_matrix(r)

    def twist(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        _, r, dT, dr = self._at(t)
        return dT, angular_velocity(r, dr)

    def max_rates(self) -> tuple[float, float]:
        """The largest translation speed (m/s) and rotation-vector rate (rad/s) over the segments."""
        if len(self.times) < 2:
            return 0.0, 0.0
        dt = np.diff(self.times)[:, None]
        return (float(np.linalg.norm(np.diff(self.T, axis=0) / dt, axis=1).max()),
                float(np.linalg.norm(np.diff(self.r, axis=0) / dt, axis=1).max()))


class PinPaths:
    """The paths of rows of a pinned set: ``targets(t)`` (R, 3) m and their velocity ``rates(t)`` (R, 3) m/s.

    ``groups``: ``(rows, velocity, keyframes)`` per group, ``rows`` indices into ``anchors`` (the rows' places
    at t = 0, (R, 3)), ``velocity`` (3,) m/s for a constant-velocity group (``keyframes`` None) or the
    validated keyframes (velocity unused).
    """

    def __init__(self, anchors: np.ndarray, groups: list[tuple[np.ndarray, Any, list[dict[str, Any]] | None]]):
        self.anchors = np.asarray(anchors, dtype=float).copy()
        self.velocity = np.zeros_like(self.anchors)
        self._keyed: list[tuple[np.ndarray, Keyframes]] = []
        for rows, vel, keys in groups:
            rows = np.asarray(rows, dtype=np.int64)
            if keys is None:
                self.velocity[rows] = np.asarray(vel, dtype=float)
            else:
                self._keyed.append((rows, Keyframes(keys)))
        self._centres = [self.anchors[rows].mean(axis=0) for rows, _ in self._keyed]

    @property
    def keyframed(self) -> bool:
        return bool(self._keyed)

    def targets(self, t: float) -> np.ndarray:
        """Each row's place at time ``t``, (R, 3) m."""
        out = self.anchors + self.velocity * t
        for (rows, motion), c in zip(self._keyed, self._centres):
            T, R = motion.pose(float(t))
            out[rows] = c + (self.anchors[rows] - c) @ R.T + T
        return out

    def rates(self, t: float) -> np.ndarray:
        """Each row's velocity at time ``t`` (a keyframed row's: of the segment starting at ``t``), (R, 3) m/s."""
        out = self.velocity.copy()
        for (rows, motion), c in zip(self._keyed, self._centres):
            _, R = motion.pose(float(t))
            u, w = motion.twist(float(t))
            out[rows] = u + np.cross(w, (self.anchors[rows] - c) @ R.T)
        return out

    def max_speed(self) -> float:
        """A bound of the rows' speeds over the whole path, m/s (the rotation's from its vector's rate: exact
        about a fixed axis)."""
        s = float(np.linalg.norm(self.velocity, axis=1).max()) if len(self.velocity) else 0.0
        for (rows, motion), c in zip(self._keyed, self._centres):
            r = float(np.linalg.norm(self.anchors[rows] - c, axis=1).max())
            u, w = motion.max_rates()
            s = max(s, u + r * w)
        return s

    def reanchor(self, x: np.ndarray, t: float) -> None:
        """Make the paths pass through ``x`` (R, 3) at time ``t`` (the groups' motions kept)."""
        x = np.asarray(x, dtype=float)
        self.anchors = x - self.velocity * t
        for k, (rows, motion) in enumerate(self._keyed):
            T, R = motion.pose(float(t))
            c = x[rows].mean(axis=0) - T        # the centroid moves by T only (R turns about it)
            self.anchors[rows] = c + (x[rows] - T - c) @ R
            self._centres[k] = c
