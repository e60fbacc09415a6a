"""Strain limiting after Provot 1995 ("Deformation constraints in a mass-spring model ..."), optional.

After each step, every spring stretched beyond ``(1 + max_strain) L0`` is
shortened back to that length by moving its two end vertices towards each
other along the spring, in proportion to their inverse masses (a pinned vertex
has inverse mass 0 and never moves; a spring between two pinned vertices is
left alone)::

    e   = l - (1 + max_strain) L0 > 0,   n = (x_j - x_i) / l
    dx_i = + w_i / (w_i + w_j) e n,      dx_j = - w_j / (w_i + w_j) e n

The bound is two-sided for the in-plane springs (structural and shear): one
shorter than ``(1 - max_compression) L0`` is lengthened to it by the same
formula with ``e = l - (1 - max_compression) L0 < 0`` (``max_compression``
defaults to ``max_strain``; 1 is no lower bound). Bend springs, which shorten
whenever the cloth folds, and tethers have none. Why: where the bounds cannot
all hold together (a moving obstacle holds part of a pinned cloth beyond the
pins' reach, its contact planes kept in every pass), one-sided passes shorten
the stretched springs by crushing the in-plane springs next to them, and the
model's linear springs count that compression as energy: on a 32² cloth that a
sphere at 10 m/s drags, up to 13 J added inside one limiting call, 254 J over
the attempted substeps of a 1 s run, hidden in the substep's balance by the
solve's dissipation; with the lower bound 0.4 J. The price: in such a jam the
stretch left at the impact steps is larger (32² at 5 m/s: 1.66x against 1.11x),
and the report says so (a ``strain`` warning).

Springs are visited in colour classes (Gauss-Seidel by colours, as
Provot visits them one by one): the springs of one class share no vertex, so a
whole class is corrected at once with one vectorised update, exactly, and the
next class sees the result. The classes are built once (a vectorised greedy
colouring: in each round every uncoloured spring whose random priority is the
largest among the uncoloured springs at both its ends joins the new class).
A pass visits every class; passes repeat until no spring is beyond the bound
(relative excess below :attr:`StrainLimiter.tolerance` = 1e-7) or
``iterations`` passes are done. Since the two
ends of a spring move by inverse-mass shares, ``m_i dx_i + m_j dx_j = 0``: the
limiting conserves linear momentum (pins aside). Velocities are corrected
consistently with ``x1 = x0 + h v1``: ``v1 += (x1_limited - x1) / h``, so the
limited state is the one a step of ``h`` would have produced.

Applied after the integrator's step (a post-step projection, as Provot's), it
is not the constrained equilibrium of the implicit system: next to a limited
spring the implicit solve's coupling leaves a small bias in the strain of the
unlimited springs (measured on a 2 x 8 hanging chain, k = 20 N/m,
``max_strain = 0.2``, ``dt = 0.01`` s: 0.184 instead of the static 0.172 for
the spring just below the limited ones, the others within 1e-4). A spring between two pinned
vertices, or of rest length 0, is never limited.

Tethers (``tethers = true``, the default; "long range attachments", Kim, Chentanez & Müller 2012). Passes of
local corrections carry a pull across the cloth one spring per pass, so a cloth pinned at a few points and
dragged far (a fast obstacle) ends its passes with the whole excess in the springs next to the pins (96²,
a sphere at 20 m/s: 6x after 1000 passes, 1.9x after 5000). Every vertex that a path of limitable springs
joins to a pinned vertex is also tied to the nearest such pin ``p`` by a one-sided constraint
``|x_i - x_p| <= (1 + max_strain) d_ip``, ``d_ip`` the shortest rest-length path along those springs
(Dijkstra). It is implied by the springs' own bounds (the triangle inequality along that path), so it never
forbids a state the springs allow; visited first in every pass, it moves the vertex (the pin has inverse
mass 0) and brings a far-dragged cloth back within reach of its pins at once.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .model import Model, State


class StrainLimiter:
    """Provot strain limiting of a model's springs (module docstring).

    Parameters
    ----------
    model : Model
    settings : dict
        The normalised ``simulation.strain_limit`` table: ``max_strain``
        (relative stretch ``(l - L0) / L0`` allowed, > 0), ``max_compression`` (relative shortening of the
        in-plane springs allowed, default ``max_strain``; 1: none), ``iterations`` (most correction passes per
        step) and ``tethers``.

    Attributes
    ----------
    stats : dict
        Since construction or the start of the last :meth:`Simulator.run`: ``steps_limited`` (steps that moved
        a vertex),
        ``springs_limited`` (springs found outside their bounds before each step's
        first pass, summed), ``max_iterations`` (most passes in a step),
        ``max_strain_after`` (largest strain left after a step, over all
        springs).
    """

    def __init__(self, model: Model, settings: dict[str, Any]) -> None:
        self.model = model
        self.max_strain = float(settings["max_strain"])
        self.iterations = int(settings["iterations"])
        w = model.inv_masses.copy()
        w[model.pinned] = 0.0
        i, j, L0, _, planar = limited_springs(model)
        self.i, self.j, self.L0 = i, j, L0
        self.limit = (1.0 + self.max_strain) * L0
        #: the in-plane springs' (structural and shear) compression bound; 1: none
        self.max_compression = float(settings.get("max_compression", min(self.max_strain, 1.0)))
        lower = np.where(planar, (1.0 - self.max_compression) * L0, 0.0)   # 0: no bound
        self.lower = lower
        self.wi, self.wj = w[i], w[j]
        self.share_i = self.wi / np.maximum(self.wi + self.wj, np.finfo(float).tiny)
        self.share_j = 1.0 - self.share_i
        self.classes = _colour_classes(self.i, self.j, model.n)
        pins = model.pinned if settings.get("tethers", True) else np.zeros(0, dtype=np.int64)   # no pins: no tethers
        ti, tp, td = _tethers(self.i, self.j, L0, w, pins, model.n)
        #: the constraints the passes visit: the tethers (one class), then the springs (their colour classes)
        nt = len(ti)
        self._all = (np.concatenate([ti, self.i]), np.concatenate([tp, self.j]),
                     np.concatenate([(1.0 + self.max_strain) * td, self.limit]), np.concatenate([np.zeros(nt), lower]),
                     np.concatenate([np.ones(nt), self.share_i]), np.concatenate([np.zeros(nt), self.share_j]),
                     ([np.arange(nt)] if nt else []) + [c + nt for c in self.classes])
        self.n_tethers = nt
        #: after :meth:`apply`: how far each contact plane pushed its vertex along its normal, m
        self.pushed = np.zeros(0)
        #: a spring counts as over-stretched when l > (1 + tolerance) (1 + max_strain) L0
        self.tolerance = 1e-7
        self.reset_stats()

    def reset_stats(self) -> None:
        """Zero :attr:`stats` (a run reports its own)."""
        self.stats = {"steps_limited": 0, "springs_limited": 0, "max_iterations": 0, "max_strain_after": 0.0}

    def apply(self, new: State, h: float, planes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> int:
        """Limit the springs of ``new`` in place (positions, then velocities); returns the passes made.

        ``planes`` = ``(idx, n, offset)``: contact planes ``n . x_idx >= offset`` (the collision stage's) that
        every pass keeps: a vertex a correction moved below its plane is put back on it (as position-based
        dynamics interleaves collision constraints), so limiting never pushes the cloth into an obstacle.
        Afterwards :attr:`pushed` holds how far each plane pushed its vertex out along its normal over all
        passes, m (the obstacle's impulse on it is ``m pushed / h`` along the normal: its work is the caller's).
        """
        x = new.x
        if not len(self.i) or not (np.all(np.isfinite(x)) and np.all(np.isfinite(new.v))):
            return 0
        lengths = self.model.backend.spring_lengths
        l = lengths(x, self.i, self.j)
        over = (l - self.limit > self.tolerance * self.limit) | (self.lower - l > self.tolerance * self.limit)
        passes = 0
        self.pushed = np.zeros(0 if planes is None else len(planes[0]))
        if over.any():                  # else the tethers hold too: they are implied by the springs' bounds
            x_in = x.copy()
            i, j, limit, lower, share_i, share_j, classes = self._all
            passes, _, self.pushed = self.model.backend.limit_strain(x, i, j, limit, share_i, share_j, classes,
                                                                     self.tolerance, self.iterations, planes,
                                                                     lower)
            if passes:
                new.v += (x - x_in) / h
                self.stats["steps_limited"] += 1
        self.stats["springs_limited"] += int(over.sum())
        self.stats["max_iterations"] = max(self.stats["max_iterations"], passes)
        after = float(((lengths(x, self.i, self.j) - self.L0) / self.L0).max())
        self.stats["max_strain_after"] = max(self.stats["max_strain_after"], after)
        return passes


def limited_springs(model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The springs strain limiting bounds (a rest length and an end that can move): their ends ``i``,
    ``j``, rest lengths, stiffnesses and whether each is in-plane (structural or shear: the ones with a
    compression bound)."""
    s = model.springs
    if s is None:
        none = np.zeros(0, dtype=np.int64)
        return none, none, np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool)
    w = model.inv_masses.copy()
    w[model.pinned] = 0.0
    keep = np.flatnonzero((s.L0 > 0) & ((w[s.i] + w[s.j]) > 0))   # springs that can be corrected
    planar = np.zeros(len(s.L0), dtype=bool)
    for kind in ("structural", "shear"):
        if kind in s.kinds:
            planar[s.kinds[kind]] = True
    c = np.ascontiguousarray
    return c(s.i[keep], dtype=np.int64), c(s.j[keep], dtype=np.int64), s.L0[keep], s.k[keep], planar[keep]


def _tethers(i: np.ndarray, j: np.ndarray, L0: np.ndarray, w: np.ndarray, pinned: np.ndarray, n: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each movable vertex joined to a pinned one by limitable springs ``(i, j, L0)``: ``(vertex, its nearest
    pin, the rest length of the shortest path between them)`` (module docstring, "Tethers")."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    pins = np.unique(np.asarray(pinned, dtype=np.int64))
    empty = np.zeros(0, dtype=np.int64)
    if not len(pins) or not len(i):
        return empty, empty, np.zeros(0)
    g = csr_matrix((np.concatenate([L0, L0]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))
    dist, _, src = dijkstra(g, directed=False, indices=pins, min_only=True, return_predecessors=True)
    v = np.flatnonzero(np.isfinite(dist) & (dist > 0) & (w > 0) & (src >= 0))
    return v.astype(np.int64), src[v].astype(np.int64), dist[v]


def _colour_classes(i: np.ndarray, j: np.ndarray, n: int, seed: int = 0) -> list[np.ndarray]:
    """Split springs (i, j) into classes of springs that share no vertex (greedy, vectorised per round).

    Each round, every remaining spring whose (seeded random, distinct) priority is the largest among the
    remaining springs at both its ends forms part of the new class; those springs are pairwise disjoint.
    The number of rounds is about the largest vertex degree (tens for cloth), not the number of springs.
    """
    prio = np.random.default_rng(seed).permutation(len(i)).astype(np.int64)
    remaining = np.arange(len(i))
    classes = []
    while len(remaining):
        top = np.full(n, -1, dtype=np.int64)
        np.maximum.at(top, i[remaining], prio[remaining])
        np.maximum.at(top, j[remaining], prio[remaining])
        p = prio[remaining]
        win = (top[i[remaining]] == p) & (top[j[remaining]] == p)
        classes.append(remaining[win])
        remaining = remaining[~win]
    return classes
