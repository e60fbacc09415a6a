"""Linear air drag, optionally relative to a wind.

``f_i = -c A_i (v_i - w(x_i, t))`` with ``c`` the drag coefficient per unit
area (N*s/m^3) and ``A_i`` the vertex's lumped area (m^2), so that refining
the mesh does not change the total drag. Jacobian: ``dF/dv = -c A_i I`` on the
diagonal (the wind being independent of v); ``dF/dx = 0`` for a uniform wind. A dissipative
:class:`~implicit_cloth.forces.Force`: ``F = -dD/dv`` with ``D = sum_i c A_i |v_i - w|^2 / 2``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..config.validate import number


def validate(path: str, value: Any) -> float:
    """``effects.drag``: the drag coefficient, N*s/m^3, >= 0."""
    return number(path, value, lo=0.0)


class Drag:
    """Linear drag with coefficient ``c`` (N*s/m^3), against an optional wind field."""

    name = "drag"
    conservative = False
    dissipative = True
    elastic = False

    def __init__(self, areas: np.ndarray, c: float, wind: Any = None) -> None:
        self.c = float(c)
        self.wind = wind
        self._cA = (self.c * areas)[:, None]      # N*s/m per vertex

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        rel = v if self.wind is None else v - self.wind.velocity(x, t)
        out -= self._cA * rel

    def energy(self, x: np.ndarray) -> float:
        return 0.0

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        pass

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """``sum_i c A_i |v_i - w|^2 / 2``, W (its ``-dD/dv`` is the drag)."""
        rel = v if self.wind is None else v - self.wind.velocity(x, t)
        return 0.5 * float(np.einsum("i,ij,ij->", self._cA[:, 0], rel, rel))

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        """The wind's power on the cloth through the drag, ``sum_i c A_i w . v_i`` (0 without wind), W."""
        if self.wind is None:
            return 0.0
        w = np.broadcast_to(self.wind.velocity(x, t), v.shape)
        return float(np.einsum("i,ij,ij->", self._cA[:, 0], w, v))

    def pairs(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def bind(self, system: Any) -> None:
        pass   # diagonal blocks only: SystemMatrix.add_diagonal knows where they are

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        # -(c_v dF/dv) = +c_v c A_i I on each diagonal block
        self.force(x, v, t, f)
        system.add_diagonal(c_v * self._cA[:, 0])


def build(model: Any, c: float, effects: dict[str, Any] | None = None) -> Drag:
    """The ``effects.drag`` term, relative to ``effects.wind`` when the table has one."""
    wind = (effects or {}).get("wind")
    field = None
    if wind is not None:
        from .wind import ConstantWind

        field = ConstantWind(wind["velocity"])
    return Drag(model.areas, c, field)
