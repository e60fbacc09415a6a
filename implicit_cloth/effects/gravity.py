"""Uniform gravity: ``f_i = m_i g`` (N), potential ``U = -sum_i m_i g . x_i`` (J)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..config.validate import vector


def validate(path: str, value: Any) -> list[float]:
    """``effects.gravity``: a 3-vector, m/s^2."""
    return vector(path, value, 3)


class Gravity:
    """Uniform gravitational acceleration ``g`` (m/s^2) acting on every vertex mass."""

    name = "gravity"
    conservative = True
    dissipative = False
    elastic = False

    def __init__(self, masses: np.ndarray, g) -> None:
        self.g = np.asarray(g, dtype=float)
        self._mg = masses[:, None] * self.g[None, :]

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        out += self._mg

    def energy(self, x: np.ndarray) -> float:
        return -float(np.einsum("ij,ij->", self._mg, x))

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        out -= self._mg

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0   # its work is the change of its potential

    def pairs(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def bind(self, system: Any) -> None:
        pass

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        f += self._mg  # constant force: no Jacobian


def build(model: Any, g: Any, effects: Any = None) -> Gravity:
    """The ``effects.gravity`` term (``effects``: the whole [effects] table, unused)."""
    return Gravity(model.masses, g)
