"""Coulomb friction and inelastic contact of the contacts an implicit solve held.

Friction lives in the solve, in Baraff & Witkin's vocabulary (see :mod:`implicit_cloth.constraints`): a
*sticking* contact is constrained in all three directions (its tangential velocity the obstacle's), a
*sliding* one only along its normal, with the kinetic force ``-mu N s`` (``N`` its normal force in the last
solve that held it, ``s`` its sliding direction). After each solve :func:`update` compares the constraint
impulses with the friction cone:

* a sticking contact whose tangential impulse exceeds ``mu`` times its normal impulse starts to slide, in the
  direction the impulse held it back from;
* a sliding contact whose tangential velocity relative to the obstacle the friction turned back sticks.

A constant kinetic force that cannot reverse a motion, and a sticking constraint that prescribes the
obstacle's velocity, only take energy away. Within one step a contact changes its state at most once, so
the solves of a step cannot cycle; a contact that the last solve turned back is stopped by
:func:`stop_reversed` (a velocity change that only removes kinetic energy).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..constraints import Constraints, huber_linearization
from .contacts import Planes


def friction_forces(active: Planes, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(stick, force)``: which contacts stick (where ``mu > 0``) and the kinetic force on the sliding ones, N."""
    stick = active.stick & (mu > 0)
    force = np.where(stick[:, None], 0.0, -(mu * np.maximum(active.force, 0.0))[:, None] * active.slip)
    return stick, force


def update(active: Planes, cons: Constraints, J: np.ndarray | None, v: np.ndarray, h: float, mu: np.ndarray,
           switched: np.ndarray) -> np.ndarray:
    """Update the contacts' normal forces and Coulomb states from a solve (in place; module docstring).

    Parameters
    ----------
    active : Planes
        The contacts held in the solve (rows in the order of ``cons.contact``).
    cons : Constraints
        The solve's constraints.
    J : (N, 3) array or None
        The solve's constraint impulse, N*s.
    v : (N, 3) array
        The solve's end velocities, m/s.
    mu : (K,) array
        Each contact's friction coefficient.
    switched : (N,) bool array
        Vertices whose contact changed its state already in this step (updated in place).

    Returns
    -------
    (K,) bool array
        The contacts whose state changed.
    """
    if J is None:
        return np.zeros(len(active), dtype=bool)
    n = cons.normal
    Jc = J[active.idx]
    jn = np.einsum("ij,ij->i", Jc, n)
    active.force = jn / h
    jt = Jc - jn[:, None] * n
    jt_norm = np.sqrt(np.einsum("ij,ij->i", jt, jt))
    rel = v[active.idx] - cons.velocity
    vt = rel - np.einsum("ij,ij->i", rel, n)[:, None] * n
    vt_norm = np.sqrt(np.einsum("ij,ij->i", vt, vt))
    stick = active.stick & (mu > 0)
    free = ~switched[active.idx]
    to_slip = stick & free & (jt_norm > mu * np.maximum(jn, 0.0) * (1.0 + 1e-9) + 1e-15)
    sliding = ~stick & (mu > 0)
    to_stick = sliding & free & (np.einsum("ij,ij->i", vt, active.slip) <= 0.0)
    keep = sliding & ~to_stick & (vt_norm > 0)
    active.slip[to_slip] = -jt[to_slip] / jt_norm[to_slip, None]
    active.slip[keep] = vt[keep] / vt_norm[keep, None]
    active.slip[to_stick] = 0.0
    active.stick = (stick & ~to_slip) | to_stick
    changed = to_slip | to_stick
    switched[active.idx[changed]] = True
    return changed


def stop_reversed(active: Planes, cons: Constraints, after: Any) -> None:
    """Sliding contacts that the last solve's friction turned back (sticking since :func:`update`) take the
    obstacle's tangential velocity (positions kept; from the next step on they stick)."""
    if not cons.n_contacts:
        return
    pos = np.full(len(after.v), -1, dtype=np.int64)
    pos[cons.contact] = np.arange(cons.n_contacts)
    r = pos[active.idx]
    now = (r >= 0) & ~cons.stick[np.maximum(r, 0)] & active.stick
    if not np.any(now):
        return
    k = r[now]
    i = cons.contact[k]
    n, u = cons.normal[k], cons.velocity[k]
    rel = after.v[i] - u
    after.v[i] -= rel - np.einsum("ij,ij->i", rel, n)[:, None] * n


def inelastic(active: Planes, cons: Constraints, carried: np.ndarray, before: Any, after: Any,
              restitution: float, masses: np.ndarray) -> float:
    """Held contacts still approaching the obstacle at the end of the step take its normal velocity; those new
    in this step that were approaching at its start leave with it less ``restitution`` times their approach
    speed (velocities only: the positions stay on the planes). Only takes energy away (``restitution <= 1``).

    Returns the work of these velocity changes against the obstacles' motion, J.
    """
    i, n, u = cons.contact, cons.normal, cons.velocity
    target = np.einsum("ij,ij->i", u, n)
    if restitution > 0:
        w = np.einsum("ij,ij->i", before.v[i] - u, n)
        bounce = ~np.isin(i, carried) & (w < 0)
        target[bounce] -= restitution * w[bounce]
        active.force[np.isin(active.idx, i[bounce])] = -1.0          # bouncing off: not carried
    change = np.maximum(target - np.einsum("ij,ij->i", after.v[i], n), 0.0)
    if not np.any(change):
        return 0.0
    dv = change[:, None] * n
    after.v[i] += dv
    return float(np.einsum("i,ij,ij->", masses[i], dv, u))


# --------------------------------------------------------------------------- smoothed friction
def smooth_model(active: Planes, mu: np.ndarray, normal: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed Coulomb friction of the contacts, linearised as each one's state says: ``(force, damping)``.

    The force is Huber's smoothing of Coulomb's, ``-mu N v_t / max(|v_t|, eps)`` (``v_t`` the tangential
    velocity relative to the obstacle, ``eps`` the sliding speed ``collision.friction_speed``): the gradient
    of a convex dissipation potential, so it only takes energy away. A *held* contact (``active.stick``) is
    linearised in its viscous branch, the damping ``mu N / eps`` on the tangent plane and no constant part
    (its force ``-(mu N / eps) v_t`` stays within the cone while ``|v_t| <= eps``); a *sliding* one at its
    sliding velocity ``speed * slip``: the kinetic force ``-mu N slip``, constant along ``slip``, with the
    damping ``mu N / speed`` across it that turns its direction. ``N`` is the contact's normal force in the
    last solve that held it (0 for a new contact: no friction until a solve has held it). Returns the constant
    forces (K, 3), N, and the symmetric positive semi-definite damping blocks (K, 3, 3), N*s/m.
    """
    held = active.stick | (active.speed <= 0.0)
    t = active.slip - np.einsum("ij,ij->i", active.slip, normal)[:, None] * normal   # on this step's plane
    tn = np.sqrt(np.einsum("ij,ij->i", t, t))
    held |= tn < 1e-12
    t = np.where(held[:, None], 0.0, t / np.maximum(tn, 1e-300)[:, None])
    return huber_linearization(mu * np.maximum(active.force, 0.0), normal, t,
                               np.where(held, 0.0, active.speed), eps)


def smooth_update(active: Planes, cons: Constraints, J: np.ndarray | None, v: np.ndarray, h: float,
                  mu: np.ndarray, eps: float, switched: np.ndarray) -> np.ndarray:
    """Smoothed friction after a solve (in place): the contacts' normal forces from its impulse and their states.

    * a held contact that the solve left sliding faster than ``eps`` (its viscous force then exceeds the cone)
      slides, at its end velocity;
    * a sliding contact whose motion the solve reversed (its kinetic force pushed along the motion: energy
      from nowhere) is held;
    * a sliding contact slower than ``eps`` is held from the next step on; the others take their end velocity
      as their sliding velocity.

    A state changes at most once a step for each vertex (``switched``, updated in place: so the solves of a
    step cannot cycle), twice for a new contact (its first solve, without friction, then sliding). Returns the
    contacts whose state changed: the step is solved again for them.
    """
    if J is None or not cons.n_contacts:
        return np.zeros(len(active), dtype=bool)
    n = cons.normal
    jn = np.einsum("ij,ij->i", J[active.idx], n)
    was_new = active.force == 0.0
    active.force = jn / h
    vt = cons.tangential(v)
    speed = np.sqrt(np.einsum("ij,ij->i", vt, vt))
    rub = mu * np.maximum(active.force, 0.0) > 0
    free = ~switched[active.idx] & rub
    held = active.stick | (active.speed <= 0.0)
    to_slide = held & free & (speed > eps)
    reversed_ = ~held & (np.einsum("ij,ij->i", vt, active.slip) <= 0.0)
    to_hold = reversed_ & free
    slow = ~held & ~reversed_ & (speed <= eps)
    keep = ~held & ~reversed_ & ~slow
    move = to_slide | keep
    active.slip[move] = vt[move] / speed[move, None]
    active.speed[move] = speed[move]
    stop = to_hold | slow
    active.slip[stop] = 0.0
    active.speed[stop] = 0.0
    active.stick = (held & ~to_slide) | stop
    changed = to_slide | to_hold
    # A new contact had no friction in the solve that found its normal force: it is solved again as it slides,
    # and may change once more in the step (its kinetic force may reverse it there: it is then held).
    first = was_new & to_slide
    switched[active.idx[changed & ~first]] = True
    return changed


def newton_update(active: Planes, cons: Constraints, J: np.ndarray | None, v: np.ndarray, h: float,
                  mu: np.ndarray, eps: float, switched: np.ndarray) -> np.ndarray:
    """Smoothed friction solved to convergence, after a solve (in place): the contacts' normal forces from its
    impulse, and the tangential speeds and directions their next step's first solve is linearised at
    (held below ``eps``). No state rules: the solve's Newton iterations found the friction at these normal
    forces. Returns the contacts that had no normal force before and have friction now (their step is solved
    again once with it: ``switched``, updated in place), but for those whose friction the step's own Newton
    iterations already solved at the first solve's normal force (:attr:`Constraints.pending`; the collider
    marks them ``switched`` first)."""
    if J is None or not cons.n_contacts:
        return np.zeros(len(active), dtype=bool)
    jn = np.einsum("ij,ij->i", J[active.idx], cons.normal)
    was_new = active.force == 0.0
    active.force = jn / h
    vt = cons.tangential(v)
    speed = np.sqrt(np.einsum("ij,ij->i", vt, vt))
    slow = speed <= eps
    active.speed = np.where(slow, 0.0, speed)
    active.slip = np.where(slow[:, None], 0.0, vt / np.maximum(speed, 1e-300)[:, None])
    active.stick = slow
    first = was_new & (mu * np.maximum(active.force, 0.0) > 0) & ~switched[active.idx]
    switched[active.idx[first]] = True
    return first


def stop_reversed_smooth(active: Planes, cons: Constraints, after: Any) -> None:
    """Contacts whose kinetic friction the last solve reversed (it pushed along the motion) stop their
    tangential motion relative to the obstacle (velocities only: it only takes energy away) and are held."""
    if not cons.n_contacts or not np.any(cons.friction):
        return
    rel_t = cons.tangential(after.v)
    back = np.einsum("ij,ij->i", rel_t, cons.friction) > 0
    if not np.any(back):
        return
    after.v[cons.contact[back]] -= rel_t[back]
    pos = np.full(len(after.v), -1, dtype=np.int64)
    pos[active.idx] = np.arange(len(active))
    r = pos[cons.contact[back]]
    r = r[r >= 0]
    active.stick[r] = True
    active.slip[r] = 0.0
    active.speed[r] = 0.0
