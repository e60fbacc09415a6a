"""Material presets: per-spring constants in SI units.

A preset gives, for each spring kind, the spring constant ``k`` in N/m of *each*
spring of that kind and the damping coefficient ``kd`` in N*s/m along each
spring, plus an areal density in kg/m^2 that is used when the scene gives
neither ``mass`` nor ``density``.

How a preset maps to the springs
--------------------------------
For a square grid, a row of structural springs of spacing ``a`` carries a
tension per unit width ``T = k (a eps) / a = k eps`` at strain ``eps``, so the
structural ``k`` equals the sheet's 2-D stretch modulus (N/m) and does not
depend on resolution. Shear springs likewise set the in-plane shear resistance.
Bending springs (every other vertex) give a bending resistance that *does*
depend on resolution; the bend values below are tuned for a 1 m cloth at about
32 x 32 vertices. The numbers are representative orders of magnitude chosen so
that the materials rank sensibly (silk softest and lightest, leather and denim
stiff and heavy, rubber stretchy but heavy), not measurements of a fabric.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping


@dataclass(frozen=True)
class SpringParams:
    """Constants of one spring kind.

    Attributes
    ----------
    stiffness : float
        Spring constant k of each spring, N/m.
    damping : float
        Damping coefficient kd along each spring, N*s/m.
    """

    stiffness: float
    damping: float


@dataclass(frozen=True)
class Material:
    """A named cloth material: spring constants per kind and areal density."""

    name: str
    structural: SpringParams
    shear: SpringParams
    bend: SpringParams
    density: float  # kg/m^2

    def springs(self) -> dict[str, SpringParams]:
        return {"structural": self.structural, "shear": self.shear, "bend": self.bend}


def _m(name: str, s: tuple[float, float], sh: tuple[float, float], b: tuple[float, float], rho: float) -> Material:
    return Material(name, SpringParams(*s), SpringParams(*sh), SpringParams(*b), rho)


#: Material presets by name (read-only mapping).
MATERIALS: Mapping[str, Material] = MappingProxyType(
    {
        "cotton": _m("cotton", (5.0e3, 1.0), (5.0e2, 0.5), (2.0e1, 0.1), 0.15),
        "silk": _m("silk", (2.0e3, 0.5), (1.0e2, 0.2), (2.0, 0.02), 0.06),
        "denim": _m("denim", (2.0e4, 2.0), (2.0e3, 1.0), (2.0e2, 0.5), 0.40),
        "leather": _m("leather", (5.0e4, 4.0), (1.0e4, 2.0), (1.0e3, 1.0), 0.90),
        "rubber": _m("rubber", (1.0e3, 0.5), (1.0e3, 0.5), (5.0e1, 0.1), 1.20),
    }
)
