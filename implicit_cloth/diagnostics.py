"""Run health: energies, strain, and the divergence bound.

Divergence bound
----------------
A run is declared diverged when its state stops being finite (checked every
step) or when, at a kept frame, its total energy has grown by more than
``divergence_factor`` (default 1000, ``simulation.divergence_factor``) times
the run's energy scale::

    E_total(t) - E_total(0) - W_pins(t) > divergence_factor * E_scale
    E_scale = E_kin(0) + U_spring(0) + m |g| L + m v_ref^2 / 2
    L       = initial bounding-box diagonal + max pin speed * T + |g| T^2 / 2
    v_ref   = max pin speed + wind speed + max initial vertex speed

with ``W_pins`` the work done on the cloth by moving pins (:func:`pin_power`,
integrated by the trapezoidal rule over each step; 0 when no pin moves),
``m`` the cloth's mass and ``T`` the run's duration (``L`` bounds how far
anything can travel); when all those terms vanish (a cloth at rest with nothing
acting on it) ``E_scale = m (L / T)^2 / 2``.
Total energy includes gravity, so free fall does not count as growth; a stable
run can swing its energy by a few times ``E_scale`` (symplectic methods do),
three orders of magnitude below the bound, while an unstable explicit run
grows exponentially and crosses it within a few steps.
"""

from __future__ import annotations

import numpy as np

from .model import Model

DEFAULT_DIVERGENCE_FACTOR = 1000.0


def measure(model: Model, x: np.ndarray, v: np.ndarray) -> dict[str, float]:
    """Energies (J) and the largest strain of a state.

    Returns
    -------
    dict
        ``kinetic``, ``gravity`` and ``springs`` potentials, ``potential`` (their
        sum), ``total``, and ``max_strain``: the largest ``(l - L0) / L0`` over
        the structural springs (all springs if the cloth has no structural
        ones; 0 without springs).
    """
    pe = model.potential_energy(x)
    kin = model.kinetic_energy(v)
    grav = pe.get("gravity", 0.0)
    spr = pe.get("springs", 0.0)
    strain = 0.0
    s = model.springs
    if s is not None and len(s.i):
        sl = s.kinds.get("structural", slice(0, len(s.i)))
        if sl.stop > sl.start:
            eps = s.strain(x)[sl]
            strain = float(eps.max())
    return {"kinetic": kin, "gravity": grav, "springs": spr, "potential": grav + spr,
            "total": kin + grav + spr, "max_strain": strain}


def total_energy(model: Model, x: np.ndarray, v: np.ndarray) -> float:
    """Kinetic + gravity + spring energy of a state, J (``measure(...)["total"]`` without the strain)."""
    return model.kinetic_energy(v) + float(sum(model.potential_energy(x).values()))


def energy_scale(model: Model, x: np.ndarray, v: np.ndarray, duration: float) -> float:
    """The energy scale ``E_scale`` of the divergence bound (module docstring), J."""
    e = measure(model, x, v)
    eff = model.scene.data["effects"]
    g = float(np.linalg.norm(eff.get("gravity", [0.0, 0.0, 0.0])))
    wind = float(np.linalg.norm(eff["wind"]["velocity"])) if "wind" in eff else 0.0
    pin_speed = float(np.linalg.norm(model.pin_velocity, axis=1).max()) if len(model.pinned) else 0.0
    v_max = float(np.linalg.norm(v, axis=1).max()) if len(v) else 0.0
    diag = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    L = diag + pin_speed * duration + 0.5 * g * duration**2
    m = model.total_mass
    v_ref = pin_speed + wind + v_max
    scale = e["kinetic"] + e["springs"] + m * g * L + 0.5 * m * v_ref**2
    if scale <= 0.0:
        scale = 0.5 * m * (L / duration) ** 2
    return scale


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
