"""Run health: energies, strain, the energy balance of a step, and the divergence bound.

Energy balance of a step
------------------------
Gravity and the springs are conservative; damping, drag, friction, inelastic
contact and backward Euler's numerical damping only take energy away. So over
any (sub)step from state 0 to state 1 of length ``h``::

    E1 - E0 <= W_ext + allowance
    W_ext = h (P0 + P1) / 2 + W_obstacles

with ``E`` the total energy (kinetic + gravity + springs), ``P`` the power of
the moving pins and of the wind on the drag (:func:`pin_power`,
:meth:`StepMeasures.power`) and ``W_obstacles`` the work the obstacles did,
computed from what they did (contact impulses times the obstacle's velocity at
the contact; 0 for an obstacle that does not move). A step that gains more
created energy from nowhere: a linearised step overshooting, or a contact
treatment that does work. The allowance is a fraction of the energy the step
itself moves about, from the two states only (never from the run's length)::

    allowance = max_energy_growth * E_step
    E_step = max(K0, K1) + max(S0, S1) + |G1 - G0| + |W_ext| + max(U0, U1)

(``K`` kinetic, ``S`` spring, ``G`` gravity energy, ``U`` the energy a contact
potential stores, ``collision.method = "barrier"``), so a cloth at rest has
almost none and a falling one the work gravity does in the step.

Divergence bound
----------------
A run is declared diverged when its state stops being finite (checked every
step) or when, at a kept frame, its total energy has grown by more than
``divergence_factor`` (default 1000, ``simulation.divergence_factor``) times
the run's energy scale, beyond the pins' and the obstacles' work::

    E_total(t) - E_total(0) - W_pins(t) - W_obstacles(t) > divergence_factor * E_scale
    E_scale = E_kin(0) + U_spring(0) + m |g| L + m v_ref^2 / 2
    L       = initial bounding-box diagonal
    v_ref   = max pin speed + wind speed + max initial vertex speed

from the initial state only (the same bound whatever the run's duration), with
``m`` the cloth's mass; when all those terms vanish ``E_scale = m (L / 1 s)^2 / 2``.
A stable run can swing its energy by a few times ``E_scale`` (symplectic
methods do), three orders of magnitude below the bound, while an unstable
explicit run grows exponentially and crosses it within a few steps.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from .model import Model

DEFAULT_DIVERGENCE_FACTOR = 1000.0


def measure(model: Model, x: np.ndarray, v: np.ndarray, t: float | None = None) -> dict[str, float]:
    """Energies (J) and the largest strain of a state.

    Returns
    -------
    dict
        ``kinetic``, ``gravity`` and ``springs`` potentials, ``potential`` (their
        sum), ``total``, and ``max_strain``: the largest ``(l - L0) / L0`` over
        the structural springs (all springs if the cloth has no structural
        ones; 0 without springs). With a membrane (:mod:`implicit_cloth.effects.membrane`) its energy is
        counted with the springs' and ``max_strain`` is the largest of its triangles' principal strains
        (:meth:`~implicit_cloth.effects.membrane.Membrane.principal_strains`: the largest relative stretch in
        any direction) and the structural springs' (the bend springs' are then left out). The dihedral bending's energy
        (:mod:`implicit_cloth.effects.dihedral`) is counted with the springs' too, and so are the soft pins'
        springs' (:mod:`implicit_cloth.effects.pin_springs`, at time ``t`` when given: their targets move).
    """
    pe = model.potential_energy(x)
    kin = model.kinetic_energy(v)
    grav = pe.get("gravity", 0.0)
    spr = pe.get("springs", 0.0)
    strain = 0.0
    s = model.springs
    membrane = next((e for e in model.effects if e.name == "membrane"), None)
    if s is not None and len(s.i) and (membrane is None or "structural" in s.kinds):
        sl = s.kinds.get("structural", slice(0, len(s.i)))
        if sl.stop > sl.start:
            eps = s.strain(x)[sl]
            strain = float(eps.max())
    if membrane is not None:   # its stored energy with the springs', its principal strain with the structural
        spr += pe["membrane"]
        strain = max(strain, float(cast(Any, membrane).principal_strains(x).max()))
    spr += pe.get("bending", 0.0)   # the dihedral bending's (implicit_cloth.effects.dihedral) with the springs'
    if "pin_springs" in pe:          # soft pins' springs, at the state's time ``t`` when given (moving targets)
        soft = next(e for e in model.effects if e.name == "pin_springs")
        spr += cast(Any, soft).energy_at(x, t) if t is not None else pe["pin_springs"]
    return {"kinetic": kin, "gravity": grav, "springs": spr, "potential": grav + spr,
            "total": kin + grav + spr, "max_strain": strain}


def total_energy(model: Model, x: np.ndarray, v: np.ndarray) -> float:
    """Kinetic + gravity + spring energy of a state, J (``measure(...)["total"]`` without the strain)."""
    return model.kinetic_energy(v) + float(sum(model.potential_energy(x).values()))


def energy_scale(model: Model, x: np.ndarray, v: np.ndarray, duration: float | None = None) -> float:
    """The energy scale ``E_scale`` of the divergence bound (module docstring), J.

    From the state alone: ``duration`` is accepted for compatibility and not used (the bound used to
    grow with the square of the run's length).
    """
    e = measure(model, x, v)
    eff = model.scene.data["effects"]
    g = float(np.linalg.norm(eff.get("gravity", [0.0, 0.0, 0.0])))
    wind = float(np.linalg.norm(eff["wind"]["velocity"])) if "wind" in eff else 0.0
    pin_speed = model.pin_speed()
    v_max = float(np.linalg.norm(v, axis=1).max()) if len(v) else 0.0
    L = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    m = model.total_mass
    v_ref = pin_speed + wind + v_max
    scale = e["kinetic"] + e["springs"] + m * g * L + 0.5 * m * v_ref**2
    if scale <= 0.0:
        scale = 0.5 * m * max(L, 1e-3) ** 2
    return scale


class StepMeasures:
    """Energies, strains and external power of states, for the energy balance and the strain bound of steps.

    Through the effects' protocol: the stored (``elastic``) energy of the springs and their strains from one
    evaluation of the spring lengths, the other conservative effects' potentials (gravity), and the power
    the effects bring in from outside (``power``: the wind) with the moving pins'. :meth:`strains` adds the
    membrane's triangles' principal strains to the springs' (measured only where a strain is asked for: the
    barrier's Newton iterates ask for the balance alone). The last two states measured are cached (a step's
    end is the next step's start).
    """

    def __init__(self, model: Model) -> None:
        self.model = model
        self._pins_move = bool(len(model.pinned)) and bool(np.any(model.pin_velocity)) and not model.pins_keyframed
        #: keyframed pins: their work is booked per step from the two states (:func:`pin_step_work`)
        self._pins_keyed = model.pins_keyframed
        self._pin_cache: list[tuple[Any, tuple[np.ndarray, float]]] = []
        self._fields = [e for e in model.effects if e.conservative and not e.elastic]
        self._elastic = [e for e in model.effects if e.elastic and e is not model.springs]
        self._cache: list[tuple[Any, tuple[float, float, float, np.ndarray | None, float]]] = []
        self._membrane: Any = next((e for e in model.effects if e.name == "membrane"), None)
        self._strain_cache: list[tuple[Any, np.ndarray | None]] = []

    def forget(self) -> None:
        """Drop the cached measures (after the state is assigned)."""
        self._cache = []
        self._strain_cache = []

    def strains(self, s: Any) -> np.ndarray | None:
        """The strains the strain bound is checked on: the springs' ``(l - L0) / L0`` (as ``self(s)[3]``), then
        the membrane's triangles' largest principal strains (:meth:`~implicit_cloth.effects.membrane.Membrane.
        principal_strains`), in a fixed order so two states' arrays compare entry by entry; None when the cloth
        has neither."""
        spring = self(s)[3]
        if self._membrane is None:
            return spring
        for state, got in self._strain_cache:
            if state is s:
                return got
        tri = self._membrane.principal_strains(s.x)
        out = tri if spring is None or not len(spring) else np.concatenate([spring, tri])
        self._strain_cache = self._strain_cache[-1:] + [(s, out)]
        return out

    def power(self, s: Any) -> float:
        """Power of the pins and of outside sources through the effects (the wind) on the cloth, W."""
        p = pin_power(self.model, s.x, s.v, s.t) if self._pins_move else 0.0
        return p + float(sum(e.power(s.x, s.v, s.t) for e in self.model.effects))

    def _pin_state(self, s: Any) -> tuple[np.ndarray, float]:
        """The effects' force on the pinned vertices (P, 3), N, and their kinetic energy, J, at state ``s``
        (the last two cached)."""
        for state, got in self._pin_cache:
            if state is s:
                return got
        out = pin_state(self.model, s.x, s.v, s.t)
        self._pin_cache = self._pin_cache[-1:] + [(s, out)]
        return out

    def __call__(self, s: Any) -> tuple[float, float, float, np.ndarray | None, float]:
        """``(kinetic, field, stored)`` energies (J: gravity's, the springs'), spring strains ``(l - L0) / L0``
        (or None) and power (W)."""
        for state, measured in self._cache:
            if state is s:
                return measured
        m = self.model
        kin = m.kinetic_energy(s.v)
        grav = float(sum(e.energy(s.x) for e in self._fields))
        # an energy that depends on time (soft pins' moving targets: energy_at) at the state's own time
        spring = float(sum(e.energy_at(s.x, s.t) if hasattr(e, "energy_at") else e.energy(s.x)
                           for e in self._elastic))
        strain = None
        sp = m.springs
        if sp is not None and len(sp.i):      # spring energy and strains from one evaluation of the lengths
            ext = sp.lengths(s.x) - sp.L0
            spring += 0.5 * float(np.dot(sp.k, ext * ext))
            strain = np.divide(ext, sp.L0, out=np.zeros_like(ext), where=sp.L0 > 0)
        out = (kin, grav, spring, strain, self.power(s))
        self._cache = self._cache[-1:] + [(s, out)]
        return out

    def balance(self, old: Any, new: Any, h: float, obstacle_work: float = 0.0,
                stored: float = 0.0) -> tuple[float, float]:
        """``(gain, E_step)`` of a step (module docstring): energy gained beyond the external work, and the
        energy the step moves about, J (``stored``: the larger of the contact potential's stored energies at
        the step's ends, which it moves about as it does the springs')."""
        k0, g0, s0, _, p0 = self(old)
        k1, g1, s1, _, p1 = self(new)
        w = 0.5 * h * (p0 + p1) + obstacle_work
        if self._pins_keyed:
            w += pin_step_work(self.model, old, new, self._pin_state(old), self._pin_state(new))
        gain = (k1 + g1 + s1) - (k0 + g0 + s0) - w
        e_step = max(k0, k1) + max(s0, s1) + abs(g1 - g0) + abs(w) + stored
        return gain, e_step


def pin_power(model: Model, x: np.ndarray, v: np.ndarray, t: float) -> float:
    """Power delivered to the cloth by its pins, W.

    A pinned vertex moves at constant velocity ``w_p``, so the pin exerts the
    force ``-F_p`` that cancels the effects' force ``F_p`` on it; its power is
    ``P = -sum_p F_p . w_p``.
    """
    if not len(model.pinned) or not np.any(model.pin_velocity):
        return 0.0
    f = model.forces(x, v, t)[model.pinned]
    return -float(np.einsum("ij,ij->", f, model.pin_velocity))


def pin_state(model: Model, x: np.ndarray, v: np.ndarray, t: float) -> tuple[np.ndarray, float]:
    """The effects' force on the pinned vertices (P, 3), N, and their kinetic energy, J."""
    p = model.pinned
    f = model.forces(x, v, t)[p]
    return f, 0.5 * float(np.dot(model.masses[p], np.einsum("ij,ij->i", v[p], v[p])))


def pin_step_work(model: Model, old: Any, new: Any, s0: tuple[np.ndarray, float],
                  s1: tuple[np.ndarray, float]) -> float:
    """Work the pins did on the cloth over a step from state ``old`` to ``new`` (``s0``, ``s1``: their
    :func:`pin_state`), J: keyframed pins, whose velocity changes from step to step.

    The pin holds vertex ``p`` on its path against the effects' force ``F_p`` and gives it the kinetic energy
    it has, so its work is ``dK_p - int F_p . dx_p``, booked with the trapezoid as the constant pins' power
    is: ``W = K_p(1) - K_p(0) - (F_p(0) + F_p(1)) / 2 . (x_p(1) - x_p(0))`` (for a pin of constant velocity
    ``w`` this is ``h (P0 + P1) / 2`` with :func:`pin_power`'s ``P = -F . w``).
    """
    p = model.pinned
    (f0, k0), (f1, k1) = s0, s1
    dx = new.x[p] - old.x[p]
    return (k1 - k0) - 0.5 * float(np.einsum("ij,ij->", f0 + f1, dx))
