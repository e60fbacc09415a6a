"""Soft pins: zero-length springs from vertices to their pins' paths (``cloth.pins[k].stiffness``).

A pin table with ``stiffness = K`` (N/m, > 0) does not constrain its vertices; each is pulled towards its
target ``p(t)`` (the path an exact pin of the same table would follow: fixed, constant ``velocity`` or
``keyframes``, :mod:`implicit_cloth.pin_paths`) by::

    U = sum_p K_p |x_p - p(t)|^2 / 2                 (J; stored in the cloth: elastic)
    D = sum_p c_p |v_p - p'(t)|^2 / 2                (W; ``damping = c``, N*s/m, default 0)
    F_p = -K_p (x_p - p(t)) - c_p (v_p - p'(t))

Hessian blocks ``K_p I`` and ``c_p I`` on the diagonal, solved implicitly with the other forces. The implicit
steps linearise the force in time too (:meth:`PinSprings.rate`, ``dF/dt = K p'``; backward Euler's and BDF2's
right-hand sides take ``h dF/dt`` beside ``h dF/dx v``), so the spring pulls towards the target at the step's
end: a soft pin following a target at constant velocity ``w`` sits where the other forces on it balance the
spring (``m g / K`` below the target under gravity alone), without lagging a step behind.

Energy balance: ``U`` depends on time through the target. Its change at a fixed ``x`` is work the moving
target does on the cloth, booked as outside power (:meth:`PinSprings.power`)::

    P = -dU/dt - (c (v - p')) . p' = F . p'

(the spring's and the damper's force on the cloth times the target's velocity; 0 for a fixed target), and
the stored energy of a state is ``U`` at its own time (:meth:`PinSprings.energy_at`). :meth:`energy`
(the protocol's, without a time) is ``U`` at the time of the last force, gradient or linearisation asked for.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..pin_paths import PinPaths


class PinSprings:
    """Zero-length springs of stiffness ``k`` (S,) N/m and damping ``c`` (S,) N*s/m from vertices ``idx`` (S,)
    to the rows of ``paths`` (:class:`~implicit_cloth.pin_paths.PinPaths`)."""

    name = "pin_springs"
    conservative = True
    elastic = True

    def __init__(self, n: int, idx: np.ndarray, k: np.ndarray, c: np.ndarray, paths: PinPaths) -> None:
        self.n = int(n)
        self.idx = np.asarray(idx, dtype=np.int64)
        self.k = np.asarray(k, dtype=float)
        self.c = np.asarray(c, dtype=float)
        self.paths = paths
        self.dissipative = bool(np.any(self.c))
        self._kdiag = np.bincount(self.idx, weights=self.k, minlength=self.n)
        self._cdiag = np.bincount(self.idx, weights=self.c, minlength=self.n)
        self.t = 0.0

    # ------------------------------------------------------------------ targets
    def _stretch(self, x: np.ndarray, t: float) -> np.ndarray:
        self.t = float(t)
        return x[self.idx] - self.paths.targets(t)

    def _slip(self, v: np.ndarray, t: float) -> np.ndarray:
        return v[self.idx] - self.paths.rates(t)

    def reanchor(self, x: np.ndarray, t: float) -> None:
        """Make the targets pass through ``x[idx]`` at time ``t`` (positions assigned)."""
        self.paths.reanchor(x[self.idx], t)

    # ------------------------------------------------------------------ the Force protocol
    def energy_at(self, x: np.ndarray, t: float) -> float:
        """``U`` at time ``t``, J."""
        e = x[self.idx] - self.paths.targets(t)
        return 0.5 * float(np.einsum("i,ij,ij->", self.k, e, e))

    def energy(self, x: np.ndarray) -> float:
        return self.energy_at(x, self.t)

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        np.add.at(out, self.idx, self.k[:, None] * self._stretch(x, t))

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        if not self.dissipative:
            return 0.0
        s = self._slip(v, t)
        return 0.5 * float(np.einsum("i,ij,ij->", self.c, s, s))

    def _force_rows(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        f = -self.k[:, None] * self._stretch(x, t)
        if self.dissipative:
            f -= self.c[:, None] * self._slip(v, t)
        return f

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        np.add.at(out, self.idx, self._force_rows(x, v, t))

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """The moving targets' power on the cloth, ``sum_p F_p . p'(t)``, W (0 for fixed targets)."""
        rate = self.paths.rates(t)
        if not np.any(rate):
            return 0.0
        return float(np.einsum("ij,ij->", self._force_rows(x, v, t), rate))

    def rate(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        """Add ``dF/dt`` at fixed ``(x, v)``, ``K p'(t)`` (N/s; the targets move piecewise at constant velocity:
        the damper's ``c p''`` is 0), for the implicit step's first-order change of the force over the step."""
        np.add.at(out, self.idx, self.k[:, None] * self.paths.rates(t))

    def pairs(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def bind(self, system: Any) -> None:
        pass   # diagonal blocks only

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        # -(c_x dF/dx + c_v dF/dv) = (c_x K + c_v c) I on each diagonal block
        self.force(x, v, t, f)
        system.add_diagonal(c_x * self._kdiag + c_v * self._cdiag)
        if kw is not None and w is not None:
            kw -= self._kdiag[:, None] * w


def build(model: Any, groups: list[tuple[list[int], list[float], Any, float, float]]) -> PinSprings:
    """The soft pins of ``model`` (:attr:`Model.soft_pins`: ``(vertices, velocity, keyframes or None,
    stiffness, damping)`` per group), their targets from the rest positions."""
    idx: list[int] = []
    k: list[float] = []
    c: list[float] = []
    spec: list[tuple[np.ndarray, Any, Any]] = []
    for verts, vel, keys, stiff, damp in groups:
        rows = np.arange(len(idx), len(idx) + len(verts))
        idx += list(verts)
        k += [stiff] * len(verts)
        c += [damp] * len(verts)
        spec.append((rows, vel, keys))
    idx_a = np.asarray(idx, dtype=np.int64)
    return PinSprings(model.n, idx_a, np.asarray(k), np.asarray(c), PinPaths(model.rest_positions[idx_a], spec))
