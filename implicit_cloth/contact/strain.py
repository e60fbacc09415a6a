"""Strain limiting as a term of the step's incremental potential (``collision.method = "barrier"`` with
``[simulation.strain_limit]``), after Codimensional IPC's strain-limiting barrier (Li et al. 2021), on springs.

* :class:`StrainBarrier` (conservative): IPC's barrier (:mod:`implicit_cloth.contact.barrier`) on each spring's
  room to stretch, ``g = (1 + max_strain) L0 - l``, and on an in-plane spring's room to shorten,
  ``g = l - (1 - max_compression) L0`` (structural and shear springs, as the projection's lower bound; none when
  ``max_compression = 1``), active within ``dhat =`` :data:`REACH` of the bound's range (``REACH max_strain L0``)
  and infinite at the bound: no iterate, and so no step, leaves a spring beyond it. Its stiffness is the spring's
  own ``k`` (at least the mean vertex mass over ``dt^2``), so the barrier adds at most about a third of the
  spring's force inside its reach and holds any pull near the bound. The Hessian of a function of the length,
  ``E'' u u^T + E' / l (I - u u^T)``, sits on the springs' own blocks of the fixed pattern (the transverse part
  clamped at 0 where the shortening barrier pushes outward: projected Newton).
* :meth:`StrainBarrier.step_limit`: the largest share of a Newton iterate's move along which no spring closes more
  than :data:`SAFE` of its room (exact: a spring's squared length is a quadratic in the share), so the line
  search starts where its energy is finite.
* A spring the step starts beyond its bound (a state given stretched) has its bound for the step moved out to
  its length plus half the reach; so has a spring the step's first iterate puts beyond it (pins moving apart, a
  moving obstacle carrying vertices it would pass through: :meth:`StrainBarrier.admit`). The step's strain
  check then reports it (the ``strain`` warning). The next step starts from the bound the last one ended with,
  drawn back toward the spring's own as far as the barrier's energy allows (:meth:`StrainLimit.term`: no energy
  appears between steps), so a spring let out comes back under its bound as it relaxes.

Unlike the projection (:mod:`implicit_cloth.strain_limit`), this is the constrained step itself (one
minimisation with the springs, contact and friction), not a correction after it: no tethers or passes are needed
(``iterations`` and ``tethers`` are the projection's and are not used), and the energy the barrier stores is
booked by the step's energy balance with the contacts'.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..forces import ConservativeTerm
from . import barrier

#: The barrier reaches this share of the bound's range in from the bound (``REACH max_strain L0``).
REACH = 0.25
#: A line search's first point closes at most this share of a spring's room to its bound.
SAFE = 0.9
#: Recent steps' end states whose bounds the stage keeps for a step starting there (:meth:`StrainLimit.term`).
ENDS_KEPT = 8
#: A spring the step starts (or its first iterate puts) beyond its bound is bounded at its length plus this share
#: of the reach, for the step.
ADMIT = 0.5


class StrainLimit:
    """The strain-limiting stage of ``collision.method = "barrier"``: the limited springs and their bounds, built
    once; :meth:`term` makes a step's :class:`StrainBarrier`. Its settings and :attr:`stats` are the
    projection's (:class:`~implicit_cloth.strain_limit.StrainLimiter`), for the run's report."""

    def __init__(self, model: Any, settings: dict[str, Any], dt: float) -> None:
        self.model = model
        self.max_strain = float(settings["max_strain"])
        self.max_compression = float(settings.get("max_compression", min(self.max_strain, 1.0)))
        self.iterations = int(settings.get("iterations", 0))
        #: the projection's tethers: none here (the barrier's solve is global)
        self.n_tethers = 0
        from ..strain_limit import limited_springs

        self.i, self.j, L0, k, planar = limited_springs(model)
        self.L0 = L0
        self.upper = (1.0 + self.max_strain) * L0
        self.reach_up = REACH * self.max_strain * L0
        #: the in-plane springs' least length (0: no bound) and the shortening barrier's reach
        shortens = planar & (self.max_compression < 1.0)
        self.lower = np.where(shortens, (1.0 - self.max_compression) * L0, 0.0)
        self.reach_down = np.where(shortens, REACH * self.max_compression * L0, 0.0)
        floor = float(np.mean(model.masses)) / float(dt) ** 2
        self.kappa = np.maximum(k, floor)
        self._blocks: tuple[Any, tuple[np.ndarray, ...]] | None = None
        #: the bounds recent steps ended with, with their end positions (a step starts from the state a step
        #: accepted; its attempts adaptive stepping redoes end elsewhere)
        self._ends: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.reset_stats()

    def blocks(self, system: Any) -> tuple[np.ndarray, ...]:
        """The limited springs' (i, i), (j, j), (i, j) and (j, i) block indices in ``system`` (whose pattern holds
        the springs), kept for the last system."""
        if self._blocks is None or self._blocks[0] is not system:
            self._blocks = (system, (system.diag_index[self.i], system.diag_index[self.j],
                                     system.block_index(self.i, self.j), system.block_index(self.j, self.i)))
        return self._blocks[1]

    def reset_stats(self) -> None:
        self.stats = {"steps_limited": 0, "springs_limited": 0, "max_iterations": 0, "max_strain_after": 0.0}

    def term(self, x0: np.ndarray) -> "StrainBarrier":
        """The step's barrier from ``x0`` (the step's start): a bound the last step moved out is drawn back toward
        its own value as far as the barrier stays at the energy the last step ended with (to ``l + dhat``, where the
        barrier holds nothing, or to the bound itself; so the barrier's energy is continuous from one step to the
        next, and a spring let out comes back under its bound as it relaxes), and moved out for the springs ``x0``
        has beyond it."""
        last = next(((u, lo) for x1, u, lo in reversed(self._ends) if np.array_equal(x1, x0)), None)
        if last is None:            # a state no step ended at (the run's start, positions set): the bounds as given
            return StrainBarrier(self, x0)
        lengths = self.model.backend.spring_lengths(x0, self.i, self.j)
        upper = np.maximum(self.upper, np.minimum(last[0], lengths + self.reach_up))
        lower = np.minimum(self.lower, np.maximum(last[1], lengths - self.reach_down))
        return StrainBarrier(self, x0, upper, lower)

    def count(self, term: "StrainBarrier", x1: np.ndarray) -> None:
        """Book a step that ended at ``x1`` in :attr:`stats` (a step with a spring within the barrier's reach), and
        keep its bounds for the next step's."""
        self._ends = self._ends[-(ENDS_KEPT - 1):] + [(x1.copy(), term.upper, term.lower)]
        active = term.active(x1)
        if active:
            self.stats["steps_limited"] += 1
            self.stats["springs_limited"] += active


class StrainBarrier(ConservativeTerm):
    """The strain limit for one step (a :class:`~implicit_cloth.forces.Force`; module docstring)."""

    name = "strain_limit"

    def __init__(self, stage: StrainLimit, x0: np.ndarray, upper: np.ndarray | None = None,
                 lower: np.ndarray | None = None) -> None:
        self.stage = stage
        self.upper = (stage.upper if upper is None else upper).copy()
        self.lower = (stage.lower if lower is None else lower).copy()
        self.admit(x0)

    def pairs(self) -> np.ndarray:
        """The limited springs (on the springs' own pattern: the system holds their blocks already)."""
        return np.stack([self.stage.i, self.stage.j], axis=1)

    def lengths(self, x: np.ndarray) -> np.ndarray:
        st = self.stage
        return st.model.backend.spring_lengths(x, st.i, st.j)

    def admit(self, x: np.ndarray) -> None:
        """Move the bounds of the springs ``x`` has beyond them out to their lengths there plus :data:`ADMIT` of
        the reach (the step's start, or its first iterate)."""
        st = self.stage
        lengths = self.lengths(x)
        over = lengths >= self.upper
        if np.any(over):
            self.upper[over] = lengths[over] + ADMIT * st.reach_up[over]
        under = (st.reach_down > 0) & (lengths <= self.lower)
        if np.any(under):
            self.lower[under] = np.maximum(lengths[under] - ADMIT * st.reach_down[under], 0.0)

    def _gaps(self, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.upper - lengths, lengths - self.lower

    def _near(self, up: np.ndarray, down: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which springs' rooms ``up`` (to stretch) and ``down`` (to shorten, where bounded) are within reach."""
        st = self.stage
        return up < st.reach_up, (st.reach_down > 0) & (down < st.reach_down)

    def active(self, x: np.ndarray) -> int:
        """Springs within the barrier's reach at ``x``."""
        near_up, near_down = self._near(*self._gaps(self.lengths(x)))
        return int(np.count_nonzero(near_up | near_down))

    def energy(self, x: np.ndarray) -> float:
        st = self.stage
        up, down = self._gaps(self.lengths(x))
        if np.any(up <= 0.0) or np.any((st.reach_down > 0) & (down <= 0.0)):
            return np.inf
        near_up, near_down = self._near(up, down)
        return (float(np.sum(st.kappa[near_up] * barrier.value(up[near_up], st.reach_up[near_up])))
                + float(np.sum(st.kappa[near_down] * barrier.value(down[near_down], st.reach_down[near_down]))))

    def _derivatives(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The springs within reach at ``x``: their indices, lengths, directions ``u = (x_j - x_i) / l`` and the
        energy's first and second derivatives in the length ``E'(l)``, ``E''(l)``."""
        st = self.stage
        lengths = self.lengths(x)
        up, down = self._gaps(lengths)
        near_up, near_down = self._near(up, down)
        idx = np.flatnonzero(near_up | near_down)
        if not len(idx):
            z = np.zeros(0)
            return idx, z, np.zeros((0, 3)), z, z
        l = lengths[idx]
        k = st.kappa[idx]
        d1, d2 = np.zeros(len(idx)), np.zeros(len(idx))
        on = near_up[idx]
        if np.any(on):   # g = upper - l: dE/dl = -k b'(g), d2E/dl2 = k b''(g)
            r = st.reach_up[idx][on]
            d1[on] -= k[on] * barrier.first(up[idx][on], r)
            d2[on] += k[on] * barrier.second(up[idx][on], r)
        on = near_down[idx]
        if np.any(on):   # g = l - lower: dE/dl = k b'(g)
            r = st.reach_down[idx][on]
            d1[on] += k[on] * barrier.first(down[idx][on], r)
            d2[on] += k[on] * barrier.second(down[idx][on], r)
        u = (x[st.j[idx]] - x[st.i[idx]]) / l[:, None]
        return idx, l, u, d1, d2

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        idx, _, u, d1, _ = self._derivatives(x)
        if len(idx):
            st = self.stage
            g = d1[:, None] * u                   # dE/dx_j; dE/dx_i = -g
            np.add.at(out, st.j[idx], g)
            np.add.at(out, st.i[idx], -g)

    def linearize(self, x, v, t, c_x, c_v, w, system, kw, f) -> None:
        """The force into ``f`` and ``c_x`` times the Hessian's blocks into ``system``: per spring
        ``C = alpha I + beta u u^T`` with ``alpha = max(E' / l, 0)`` and ``beta = E'' - alpha`` (c_x scaled),
        + on the (i, i), (j, j) blocks and - on (i, j), (j, i); ``(dF/dx) w`` into ``kw``."""
        idx, l, u, d1, d2 = self._derivatives(x)
        if not len(idx):
            return
        st = self.stage
        g = d1[:, None] * u
        np.add.at(f, st.j[idx], -g)
        np.add.at(f, st.i[idx], g)
        alpha = np.maximum(d1 / l, 0.0)
        beta = d2 - alpha
        X = beta[:, None, None] * u[:, :, None] * u[:, None, :]
        X[:, 0, 0] += alpha
        X[:, 1, 1] += alpha
        X[:, 2, 2] += alpha
        ii, jj, ij, ji = (b[idx] for b in st.blocks(system))
        blocks, cX = system.blocks, c_x * X
        np.add.at(blocks, ii, cX)
        np.add.at(blocks, jj, cX)
        np.add.at(blocks, ij, -cX)
        np.add.at(blocks, ji, -cX)
        if kw is not None and w is not None:
            dw = w[st.j[idx]] - w[st.i[idx]]
            kdw = np.einsum("kab,kb->ka", X, dw)      # -(dF_j/dx) w: the Hessian's product
            np.add.at(kw, st.j[idx], -kdw)
            np.add.at(kw, st.i[idx], kdw)

    def step_limit(self, x: np.ndarray, dx: np.ndarray) -> float:
        """The largest ``a <= 1`` with no spring closing more than :data:`SAFE` of its room to its bound along
        ``x + s dx``, ``0 <= s <= a`` (1 if none comes that near). The squared length ``|e + s de|^2`` is a convex
        quadratic in ``s``: lengthening it meets the stretch bound at its larger root, shortening it the
        compression bound at its smaller one."""
        st = self.stage
        e = x[st.j] - x[st.i]
        de = dx[st.j] - dx[st.i]
        a2 = np.einsum("ij,ij->i", de, de)
        moving = a2 > 0.0
        if not np.any(moving):
            return 1.0
        b = np.einsum("ij,ij->i", e, de)
        c0 = np.einsum("ij,ij->i", e, e)
        lengths = np.sqrt(c0)
        up, down = self._gaps(lengths)
        out = 1.0
        # stretch: |e + s de| <= upper - (1 - SAFE) up, reachable within s <= 1 only if the move is that long
        top = self.upper - (1.0 - SAFE) * up
        reach = moving & (lengths + np.sqrt(a2) > top)
        if np.any(reach):
            a, bb, cc = a2[reach], b[reach], c0[reach] - top[reach] ** 2
            s = (-bb + np.sqrt(np.maximum(bb * bb - a * cc, 0.0))) / a
            out = min(out, float(s.min()))
        bottom = self.lower + (1.0 - SAFE) * down
        reach = moving & (st.reach_down > 0) & (b < 0.0) & (lengths - np.sqrt(a2) < bottom)
        if np.any(reach):
            a, bb, cc = a2[reach], b[reach], c0[reach] - bottom[reach] ** 2
            disc = bb * bb - a * cc
            hit = disc >= 0.0
            if np.any(hit):
                s = (-bb[hit] - np.sqrt(disc[hit])) / a[hit]
                out = min(out, float(s.min()))
        return max(min(out, 1.0), 0.0)
