"""The constraints of one step, passed to :meth:`Integrator.step <implicit_cloth.integrators.Integrator.step>`.

Two kinds, both in Baraff & Witkin's vocabulary (BW98 §5.3: a vertex constrained in
0, 1, 2 or 3 directions):

* **Pins**: vertex ``p`` ends the step with the prescribed velocity ``w_p`` (all
  three directions; its position follows ``a_p + w_p t`` exactly; a keyframed pin's
  ``w_p`` is its step's, :meth:`Model.pin_velocity_at <implicit_cloth.model.Model.pin_velocity_at>`).
* **Contacts**: vertex ``i`` ends the step on the plane ``n_i . x_i(t + h) =
  offset_i``, with ``n_i`` the outward unit normal of an obstacle at the end of
  the step. The integrator turns the plane into a prescribed normal velocity with
  its own position update (backward Euler ``x1 = x0 + h v1``; BDF2
  ``x1 = 4/3 x0 - 1/3 x_-1 + 2/3 h v1``), so a contact is met exactly whatever the
  method. Coulomb friction in Baraff & Witkin's vocabulary: a *sticking*
  contact is constrained in all three directions, its tangential velocity that
  of the obstacle (``velocity``) at the contact; a *sliding* one only along
  ``n_i``, with the kinetic friction force ``friction_i`` (N, opposite to its
  sliding, of magnitude ``mu N``) applied in the solve. The collision stage
  chooses which (:meth:`Collider.step <implicit_cloth.collision.Collider.step>`):
  a sticking contact whose tangential impulse exceeds ``mu`` times its normal
  impulse starts to slide, a sliding one whose motion the friction would
  reverse sticks.

What the solve gives back, per vertex, is the constraint impulse
``J = A dv - b`` (N*s; non-zero only in constrained directions): the pins'
reaction and each contact's normal impulse ``J_i . n_i``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


def _empty(*shape: int) -> np.ndarray:
    return np.zeros((0, *shape))


def huber_linearization(rub: np.ndarray, normal: np.ndarray, slip: np.ndarray, speed: np.ndarray,
                        eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed (Huber) Coulomb friction of bound ``rub`` (``mu N``, K) linearised at the sliding direction
    ``slip`` (unit, on the tangent plane of ``normal``; 0 where the contact is held) and ``speed``:
    ``(force, damping)``. Held (or below ``eps``): no constant force and the damping ``mu N / eps`` on the
    tangent plane; sliding: the kinetic force ``-mu N slip`` with the damping ``mu N / speed`` across ``slip``
    (the Huber potential's exact Hessian; positive semi-definite)."""
    P = np.eye(3)[None] - normal[:, :, None] * normal[:, None, :]
    k = rub / np.maximum(speed, eps)
    return -rub[:, None] * slip, k[:, None, None] * (P - slip[:, :, None] * slip[:, None, :])


@dataclass(frozen=True)
class Constraints:
    """Pins and contacts of one step (module docstring).

    Attributes
    ----------
    pinned : (P,) int array
        Fully constrained vertices.
    pin_velocity : (P, 3) array
        Their end velocity, m/s.
    contact : (K,) int array
        Vertices in contact (distinct, none of them pinned).
    normal : (K, 3) array
        Outward unit normals.
    offset : (K,) array
        End-of-step plane ``normal . x = offset``, m.
    velocity : (K, 3) array
        Obstacle velocity at each contact, m/s.
    stick : (K,) bool array
        Sticking contacts (tangential velocity prescribed: the obstacle's).
    friction : (K, 3) array
        Kinetic friction force on sliding contacts, N (0 on sticking ones).
    damping : (K, 3, 3) array
        Friction damping of each contact, N*s/m, symmetric and tangential (smoothed friction: the force
        ``-damping (v - velocity)`` in the solve, beside ``friction``; empty when there is none).
    rub : (K,) array
        Smoothed friction solved to convergence (``collision.friction_newton``): each contact's friction
        bound ``mu N``, N; empty when the friction is linearised once (``friction`` and ``damping`` then say
        all). With it, ``friction`` and ``damping`` are the friction's linearisation at some velocity and
        :meth:`relinearized` moves it (:meth:`friction_force`, :meth:`friction_potential`: the law itself).
    slide_speed : float
        Its sliding speed ``eps``, m/s (``collision.friction_speed``).
    pending : (K,) array
        With ``rub``: the friction coefficient ``mu`` of each contact whose bound waits for this step's first
        solve (a new contact, no normal force yet: its bound becomes ``mu`` times that solve's normal force before
        the friction's Newton iterations), 0 for the others; empty when none waits.
    """

    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    pin_velocity: np.ndarray = field(default_factory=lambda: _empty(3))
    contact: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    normal: np.ndarray = field(default_factory=lambda: _empty(3))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    velocity: np.ndarray = field(default_factory=lambda: _empty(3))
    stick: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    friction: np.ndarray = field(default_factory=lambda: _empty(3))
    damping: np.ndarray = field(default_factory=lambda: _empty(3, 3))
    rub: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slide_speed: float = 0.0
    pending: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def of_pins(cls, model) -> "Constraints":
        """The model's pins only."""
        return cls(np.asarray(model.pinned, dtype=np.int64), np.asarray(model.pin_velocity, dtype=float))

    def with_contacts(self, idx: np.ndarray, normal: np.ndarray, offset: np.ndarray, velocity: np.ndarray,
                      stick: np.ndarray | None = None, friction: np.ndarray | None = None,
                      damping: np.ndarray | None = None, rub: np.ndarray | None = None,
                      slide_speed: float = 0.0, pending: np.ndarray | None = None) -> "Constraints":
        """These pins with the given contacts (replacing any contacts); by default frictionless."""
        idx = np.asarray(idx, dtype=np.int64)
        st = np.zeros(len(idx), dtype=bool) if stick is None else np.asarray(stick, dtype=bool)
        fr = np.zeros((len(idx), 3)) if friction is None else np.asarray(friction, dtype=float)
        dm = _empty(3, 3) if damping is None else np.asarray(damping, dtype=float)
        rb = np.zeros(0) if rub is None else np.asarray(rub, dtype=float)
        pd = np.zeros(0) if pending is None or not np.any(pending) else np.asarray(pending, dtype=float)
        return Constraints(self.pinned, self.pin_velocity, idx, np.asarray(normal, dtype=float),
                           np.asarray(offset, dtype=float), np.asarray(velocity, dtype=float), st, fr, dm, rb,
                           float(slide_speed), pd)

    def with_pins(self, idx: np.ndarray, velocity: np.ndarray) -> "Constraints":
        """These constraints with vertices ``idx`` (not pinned already, in no contact) also prescribed to end the
        step with ``velocity`` (K, 3), as pins are (self-collision's re-solve)."""
        return replace(self, pinned=np.concatenate([self.pinned, np.asarray(idx, dtype=np.int64)]),
                       pin_velocity=np.concatenate([self.pin_velocity,
                                                    np.asarray(velocity, dtype=float).reshape(-1, 3)]))

    @property
    def n_contacts(self) -> int:
        return len(self.contact)

    @property
    def damped(self) -> bool:
        """Whether the contacts carry a friction damping (smoothed friction)."""
        return len(self.damping) > 0

    @property
    def nonlinear(self) -> bool:
        """Whether the contacts' smoothed friction is solved to convergence (``rub`` given)."""
        return len(self.rub) > 0

    def tangential(self, v: np.ndarray) -> np.ndarray:
        """The contacts' tangential velocities (K, 3) relative to the obstacle, from the cloth velocities ``v``."""
        rel = v[self.contact] - self.velocity
        return rel - np.einsum("ij,ij->i", rel, self.normal)[:, None] * self.normal

    def _slip(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`tangential` and its speeds (K,)."""
        vt = self.tangential(v)
        return vt, np.sqrt(np.einsum("ij,ij->i", vt, vt))

    def _linearised_force(self, v: np.ndarray) -> np.ndarray:
        return self.friction + self.damping_force(v) if self.damped else self.friction

    def friction_force(self, v: np.ndarray) -> np.ndarray:
        """The contacts' friction force at the cloth velocities ``v`` (K, 3), N: with ``rub``, smoothed Coulomb
        ``-mu N v_t / max(|v_t|, eps)`` (Huber); otherwise ``friction`` plus the damping force."""
        if self.nonlinear:
            vt, s = self._slip(v)
            return -(self.rub / np.maximum(s, self.slide_speed))[:, None] * vt
        return self._linearised_force(v)

    def friction_potential(self, v: np.ndarray) -> float:
        """Dissipation potential of the smoothed friction at ``v``, W: ``sum mu N f(|v_t|)`` with Huber's
        ``f(s) = s^2 / (2 eps)`` below ``eps`` and ``s - eps / 2`` above (convex; minus its gradient is
        :meth:`friction_force`). 0 without ``rub``."""
        if not self.nonlinear:
            return 0.0
        _, s = self._slip(v)
        e = self.slide_speed
        return float(np.dot(self.rub, np.where(s <= e, 0.5 * s * s / e, s - 0.5 * e)))

    def friction_error(self, v: np.ndarray) -> float:
        """How far the linearised friction (``friction`` and ``damping``) is from the law at ``v``, relative to
        the friction bounds: ``|F(v) - F_lin(v)| / |mu N|`` over all the contacts (0 without ``rub``; 0 when
        every contact's speed stayed in the branch and direction it was linearised in)."""
        if not self.nonlinear:
            return 0.0
        err = self.friction_force(v) - self._linearised_force(v)
        bound = float(np.dot(self.rub, self.rub))
        return float(np.sqrt(np.einsum("ij,ij->", err, err) / bound)) if bound > 0 else 0.0

    def relinearized(self, v: np.ndarray) -> "Constraints":
        """These constraints with the smoothed friction linearised at ``v`` (exactly: the Hessian of the Huber
        potential, positive semi-definite): below ``eps`` no constant force and the damping ``mu N / eps`` on the
        tangent plane; above it the kinetic force ``-mu N t`` and the damping ``mu N / |v_t|`` across ``t``
        (``t`` the sliding direction). Unchanged without ``rub``."""
        if not self.nonlinear:
            return self
        vt, s = self._slip(v)
        t = np.where((s <= self.slide_speed)[:, None], 0.0, vt / np.maximum(s, 1e-300)[:, None])
        force, D = huber_linearization(self.rub, self.normal, t, s, self.slide_speed)
        return replace(self, friction=force, damping=D)

    def with_pending_bounds(self, impulse: np.ndarray, h: float) -> "Constraints":
        """These constraints with the waiting contacts' friction bounds (``pending``) set from a solve's
        constraint ``impulse`` (N, 3), N*s, over the step ``h``: ``mu max(J . n, 0) / h``; unchanged when none
        waits."""
        if not len(self.pending):
            return self
        jn = np.einsum("ij,ij->i", impulse[self.contact], self.normal) / h
        rub = np.where(self.pending > 0.0, self.pending * np.maximum(jn, 0.0), self.rub)
        return replace(self, rub=rub, pending=np.zeros(0))

    def damping_force(self, v: np.ndarray) -> np.ndarray:
        """The contacts' friction damping force at the cloth velocities ``v`` (N, 3): ``-damping (v - u)``,
        (K, 3), N."""
        return -np.einsum("kij,kj->ki", self.damping, v[self.contact] - self.velocity)

    def filter_blocks(self) -> np.ndarray:
        """``S_i``: ``I - n_i n_i^T`` of sliding contacts, 0 of sticking ones, (K, 3, 3)."""
        n = self.normal
        S = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        S[self.stick] = 0.0
        return S

    def end_velocity(self, normal_speed: np.ndarray) -> np.ndarray:
        """The constrained part of the contacts' end velocities, (K, 3): ``normal_speed n`` plus, for sticking
        contacts, the obstacle's tangential velocity."""
        n = self.normal
        u = self.velocity
        ut = u - np.einsum("ij,ij->i", u, n)[:, None] * n
        return normal_speed[:, None] * n + np.where(self.stick[:, None], ut, 0.0)
