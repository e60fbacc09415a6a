"""The ``Force`` interface: every term of a step's incremental potential implements it.

Backward Euler's step is the minimiser of the incremental potential (Martin et al. 2011; Gast et al. 2015;
IPC, Li et al. 2020). In the velocity form the integrators use, with ``x(v) = x_pred + c_v v``::

    Phi(v) = |v - v_hat|_M^2 / 2  +  sum_f U_f(x(v))  +  c_v sum_f D_f(x_k, v)

``U_f`` is a force's potential energy (its *conservative* part: gravity, the springs' elasticity, contact
barriers) and ``D_f`` its dissipation potential, quadratic or convex in ``v`` at a geometry ``x_k`` held
fixed for the step's Newton iteration (its *dissipative* part: spring damping, air drag with its wind,
friction). A force is the negative gradient of both, ``F = -dU/dx - dD/dv``, so ``grad Phi = M (v - v_hat) -
c_v F`` and the Hessian blocks are ``c_x d2U/dx2 + c_v d2D/dv2`` (``c_x = c_v^2``).

Everything that sums forces (assembly, the Newton line search, the energy report, the energy balance) does it
over whatever forces the model has, through this interface (after Bullet's deformable force terms and
newton's solvers): nothing names ``gravity`` or ``springs``. A term is one class with

``name`` (str), ``conservative`` and ``dissipative`` (bool: which parts it has; a spring set with damping has
both; a force with neither, the aerodynamics, has no potential at all: the Newton line search of ``minimize``
takes its work lagged at the iterate), ``elastic`` (bool: its energy is stored in the cloth, >= 0),

``energy(x)``
    ``U(x)``, J (0 without a conservative part).
``gradient(x, t, out)``
    Add ``dU/dx`` (N, 3), N, to ``out`` (nothing without a conservative part).
``dissipation(x, v, t)``
    ``D(x, v)``, W (0 without a dissipative part); ``-dD/dv`` is the force's velocity-dependent part.
``force(x, v, t, out)``
    Add ``F = -dU/dx - dD/dv`` (N, 3), N, to ``out``.
``power(x, v, t)``
    The power an outside source delivers through it (the wind through the drag), W, for the energy balance.
``pairs()``, ``bind(system)``, ``linearize(x, v, t, c_x, c_v, w, system, kw, f)``
    The Hessian blocks on the fixed pattern: its vertex pairs, index maps into the
    :class:`~implicit_cloth.assembly.SystemMatrix`, and the assembly of ``-(c_v dF/dv + c_x dF/dx)`` into the
    system's blocks (with ``(dF/dx) w`` into ``kw`` and the force into ``f``, in one pass).

The derivatives are tested against finite differences with their error order (``tests/test_forces.py``).
"""

from __future__ import annotations

from typing import Any, Iterable, Protocol

import numpy as np


class Force(Protocol):
    name: str
    #: whether it has a potential energy ``U(x)`` (:meth:`energy`)
    conservative: bool
    #: whether it has a dissipation potential ``D(x, v)`` (:meth:`dissipation`)
    dissipative: bool
    #: whether that energy is stored in the cloth (>= 0: the springs), not a field's (gravity)
    elastic: bool

    def energy(self, x: np.ndarray) -> float: ...

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None: ...

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float: ...

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None: ...

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float: ...

    def pairs(self) -> np.ndarray: ...

    def bind(self, system: Any) -> None: ...

    def linearize(self, x: np.ndarray, v: np.ndarray, t: float, c_x: float, c_v: float,
                  w: np.ndarray | None, system: Any, kw: np.ndarray | None, f: np.ndarray) -> None: ...


class ConservativeTerm:
    """What a purely conservative term that adds no pairs to the pattern shares (the contact barriers): no
    dissipation, no outside power, the force the negative of its :meth:`gradient`. A subclass gives ``name``,
    ``energy``, ``gradient`` and ``linearize``."""

    conservative = True
    dissipative = False
    elastic = False

    def energy(self, x: np.ndarray) -> float:  # pragma: no cover - abstract
        raise NotImplementedError

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def dissipation(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0

    def force(self, x: np.ndarray, v: np.ndarray, t: float, out: np.ndarray) -> None:
        g = np.zeros_like(out)
        self.gradient(x, t, g)
        out -= g

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0

    def pairs(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def bind(self, system: Any) -> None:
        pass

    def start_energy(self, x0: np.ndarray) -> float:
        """The energy stored at the step's start ``x0``, J (a term whose potential moves in the step, a moving
        obstacle's barrier, gives it against its start)."""
        return self.energy(x0)


class DissipativeTerm:
    """What a purely dissipative term that adds no pairs to the pattern shares (the contacts' friction): no
    potential energy, no outside power. A subclass gives ``name``, ``dissipation``, ``force`` and
    ``linearize``."""

    conservative = False
    dissipative = True
    elastic = False

    def energy(self, x: np.ndarray) -> float:
        return 0.0

    def gradient(self, x: np.ndarray, t: float, out: np.ndarray) -> None:
        pass

    def power(self, x: np.ndarray, v: np.ndarray, t: float) -> float:
        return 0.0

    def pairs(self) -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def bind(self, system: Any) -> None:
        pass


def energy(forces: Iterable[Force], x: np.ndarray) -> float:
    """``sum_f U_f(x)`` over the conservative forces, J."""
    return float(sum(f.energy(x) for f in forces if f.conservative))


def conservative(forces: Iterable[Force], x: np.ndarray, t: float) -> tuple[float, np.ndarray]:
    """``sum_f U_f(x)`` (J) and the conservative force ``-sum_f dU_f/dx`` (N, 3), N."""
    g = np.zeros_like(x)
    u = 0.0
    for f in forces:
        if f.conservative:
            f.gradient(x, t, g)
            u += f.energy(x)
    np.negative(g, out=g)
    return float(u), g


def dissipation(forces: Iterable[Force], x: np.ndarray, v: np.ndarray, t: float) -> float:
    """``sum_f D_f(x, v)`` over the dissipative forces, W."""
    return float(sum(f.dissipation(x, v, t) for f in forces if f.dissipative))
