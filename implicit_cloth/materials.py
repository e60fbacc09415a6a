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

Membrane values (BW98's triangle membrane, :mod:`implicit_cloth.effects.membrane`)
-----------------------------------------------------------------------------------
``Material.membrane`` gives the in-plane stiffness of the sheet in N/m for the
conditions ``stretch_u`` (warp), ``stretch_v`` (weft) and ``shear`` (energy per
area ``k C^2 / 2``), where a published measurement was found for the fabric, and
None otherwise (a scene that asks such a preset for its membrane values must
then give them). They are used only when a scene has a ``[cloth.membrane]``
table. Conversion from Kawabata's KES-FB1 tensile and shear test (which reports
the mean of the warp and weft directions):

* tensile: the test loads the strip to ``Fm = 500 gf/cm = 490.3 N/m`` and
  reports the strain there, ``EMT`` (%), and the linearity ``LT`` (the tensile
  energy ``WT`` over that of a straight line to the same point). The linear
  stiffness with the measured energy at ``EMT`` is ``k = 2 WT / EMT^2 =
  LT Fm / EMT`` (N/m; the secant stiffness is ``Fm / EMT``);
* shear: ``G`` in gf/cm/degree is the shear force per unit length per degree of
  shear angle; ``k_s = G x 0.980665 N/m x 180/pi = 56.19 G`` N/m per radian,
  our ``C_s`` being the sine of the shear angle (the angle at small shear).

The damping (N*s/m) is the preset's structural (stretch) and shear springs'
``kd``, which on a square grid damp the same strain rate per unit width; the
measurements give none (KES's hysteresis is rate-independent).

Bending modulus (the dihedral bending, :mod:`implicit_cloth.effects.dihedral`)
-----------------------------------------------------------------------------
``Material.bending`` is the sheet's bending modulus ``B`` in N m (bending
moment per unit width per unit curvature; energy per area ``B kappa^2 / 2``)
where a published measurement was found, and None otherwise (a scene asking
such a preset for it with ``[cloth.bending] model = "dihedral"`` must give
``stiffness``). Kawabata's KES-FB2 pure bending test reports the bending
rigidity ``B`` in gf cm^2/cm (the mean of warp and weft), the same quantity:
``1 gf cm^2/cm = 1 gf cm = 9.80665e-3 N x 1e-2 m = 9.80665e-5 N m``
(:func:`kes_bending`). No damping comes with it (KES's bending hysteresis 2HB
is rate-independent): the preset's dihedral damping is 0.
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
class MembraneParams:
    """The membrane's constants (:mod:`implicit_cloth.effects.membrane`), N/m and N*s/m per condition."""

    stretch_u: SpringParams
    stretch_v: SpringParams
    shear: SpringParams

    def conditions(self) -> dict[str, SpringParams]:
        return {"stretch_u": self.stretch_u, "stretch_v": self.stretch_v, "shear": self.shear}


@dataclass(frozen=True)
class Material:
    """A named cloth material: spring constants per kind, areal density and, where measured, the membrane's
    in-plane stiffness (None: no published measurement here)."""

    name: str
    structural: SpringParams
    shear: SpringParams
    bend: SpringParams
    density: float  # kg/m^2
    membrane: MembraneParams | None = None
    #: the bending modulus ``B`` in N m (the dihedral bending), None without a published measurement here
    bending: float | None = None

    def springs(self) -> dict[str, SpringParams]:
        return {"structural": self.structural, "shear": self.shear, "bend": self.bend}


def _m(name: str, s: tuple[float, float], sh: tuple[float, float], b: tuple[float, float], rho: float,
       membrane: tuple[float, float, float] | None = None, bending: float | None = None) -> Material:
    """A preset; ``membrane``: ``(k_u, k_v, k_s)`` in N/m, damped with the springs' ``kd``; ``bending``: ``B`` in
    N m."""
    mem = None
    if membrane is not None:
        mem = MembraneParams(SpringParams(membrane[0], s[1]), SpringParams(membrane[1], s[1]),
                             SpringParams(membrane[2], sh[1]))
    return Material(name, SpringParams(*s), SpringParams(*sh), SpringParams(*b), rho, mem, bending)


#: KES-FB1's tensile load, 500 gf/cm in N/m
KES_TENSILE_LOAD = 500 * 9.80665e-3 / 0.01


def kes_stretch(emt_percent: float, lt: float) -> float:
    """The linear stretch stiffness (N/m) with the tensile energy KES-FB1 measures: ``LT Fm / EMT``."""
    return lt * KES_TENSILE_LOAD / (emt_percent / 100.0)


def kes_shear(g: float) -> float:
    """KES-FB1's shear stiffness ``G`` (gf/cm/degree) as N/m per radian."""
    return g * 9.80665e-3 / 0.01 * 180.0 / 3.141592653589793


def kes_bending(b: float) -> float:
    """KES-FB2's bending rigidity ``B`` (gf cm^2/cm) as the bending modulus in N m."""
    return b * 9.80665e-3 * 1e-2


# Denim (the only preset with a measurement here, see docs/scene.md "Materials"): the KES-FB values of fabric A
# of "Regenerated Cellulose-Based Denim Fabric for Tropical Regions: An Analytical Study on Making Denim
# Comfortable", Journal of Textiles (Hindawi), 2016, article ID 4614168, Table 5 ("Primary hand values",
# https://www.hindawi.com/journals/jtex/2016/4614168/tab5/):
# EMT 5.515 %, LT 0.712, G 2.180 gf/cm/degree -> k_u = k_v = 6330 N/m, k_s = 122.5 N/m.
_DENIM_MEMBRANE = (kes_stretch(5.515, 0.712), kes_stretch(5.515, 0.712), kes_shear(2.180))
# and its bending rigidity in the same table (row 5, "Bending rigidity (B)", fabric A): B = 0.172 gf cm^2/cm
# -> 1.687e-5 N m.
_DENIM_BENDING = kes_bending(0.172)


#: Material presets by name (read-only mapping).
MATERIALS: Mapping[str, Material] = MappingProxyType(
    {
        "cotton": _m("cotton", (5.0e3, 1.0), (5.0e2, 0.5), (2.0e1, 0.1), 0.15),
        "silk": _m("silk", (2.0e3, 0.5), (1.0e2, 0.2), (2.0, 0.02), 0.06),
        "denim": _m("denim", (2.0e4, 2.0), (2.0e3, 1.0), (2.0e2, 0.5), 0.40, _DENIM_MEMBRANE, _DENIM_BENDING),
        "leather": _m("leather", (5.0e4, 4.0), (1.0e4, 2.0), (1.0e3, 1.0), 0.90),
        "rubber": _m("rubber", (1.0e3, 0.5), (1.0e3, 0.5), (5.0e1, 0.1), 1.20),
    }
)
