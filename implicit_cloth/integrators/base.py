"""Integrator interface and the pieces shared by the implicit methods.

The step contract (after newton's ``SolverBase.step``)::

    new_state, info = integrator.step(state, h, constraints)

``constraints`` (:class:`~implicit_cloth.constraints.Constraints`, a value: pins
and contacts with their prescribed motion and friction; ``None`` means the
model's pins only) is read, never kept; ``info`` (:class:`StepInfo`) carries the
solver's figures and, for the implicit methods, the constraint impulse
``info.constraint_impulse`` (N, 3) of the solve. Nothing else passes between the
integrator and its caller.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .. import forces
from ..constraints import Constraints
from ..model import Model, State
from ..solvers import BlockJacobi, Filter, filtered_pcg, make_preconditioner

#: Relative accuracy of the Newton corrections' linear solves (inexact Newton: the next iteration corrects it).
NEWTON_FORCING = 0.1
#: Newton stops when a correction is this small relative to the step's velocity change (M-norm).
NEWTON_TOLERANCE = 1e-2
#: A step whose smoothed friction is solved to convergence (``collision.friction_newton``) is done when the
#: friction's linearisation at the iterate is off the law by at most this fraction of the friction bounds
#: (:meth:`Constraints.friction_error`), or its correction's mass-weighted rms speed is below this fraction of
#: the sliding speed.
FRICTION_TOLERANCE = 0.01
#: Such a step's Newton iterations stop, unconverged, at the first iterate (after the first) whose friction error
#: is more than this fraction of the one before: they are not contracting, and the caller keeps the step's first
#: solve, as it does after ``friction_newton`` iterations that miss the law. (When the continuation iterated the
#: springs too, before 2026-12-06, 173 of the shared 32² drape's 326 continuations missed the law after up to 6
#: iterations: 713 solves, half the run's, thrown away; see :meth:`ImplicitIntegrator._friction_newton`.)
FRICTION_CONTRACTION = 0.5
#: The line search of such a step: at most this many force evaluations for the least potential along the
#: Newton direction, stopping when its slope is this fraction of the slope at the start.
LINE_ITERATIONS = 12
LINE_TOLERANCE = 1e-3
#: Most Newton iterations of a step solved as the minimiser of its incremental potential (:meth:`minimize`).
MINIMIZE_ITERATIONS = 30
#: ...which stop once a correction's mass-weighted rms speed is below this fraction of the step's velocity change
#: or below :data:`MINIMIZE_FLOOR` (m/s). The springs' clamped Hessian (compressed springs) makes the iterations
#: converge linearly, by about 4x each on the stiff hanging cloth: a tighter tolerance costs an iteration per 4x
#: (32² drape on a sphere at dt 1/60 over 1.5 s: 4.8 solves a step at 0.1 and 1e-3 m/s, 7.8 at 1e-2 and 1e-3).
MINIMIZE_TOLERANCE = 0.1
MINIMIZE_FLOOR = 1e-3
#: Passes of the contacts' safe-move filters over a Newton direction before it is scaled down as a whole.
FILTER_PASSES = 3
#: Solves of a Newton iteration whose direction a contact cut (:meth:`ImplicitIntegrator._contact_direction`).
ARRIVAL_ROUNDS = 3
#: Halvings of a line search before the iteration gives up.
LINE_SEARCH_HALVINGS = 30


@dataclass
class StepInfo:
    """What one step did: solver figures (implicit methods) and where its time went (s)."""

    iterations: int = 0
    residual: float = 0.0
    converged: bool = True
    t_assembly: float = 0.0
    t_setup: float = 0.0
    t_solve: float = 0.0
    #: collision figures of the step (a CollisionInfo), when the scene has obstacles
    collision: Any = None
    #: the impulse (N, 3), N*s, the constraints applied over the step in the last solve when it had contacts
    #: (``h F_c`` with ``A dv - b = c_v F_c``; non-zero only in constrained directions); None otherwise
    constraint_impulse: np.ndarray | None = None
    #: linear solves made in the step (an implicit step with contacts may solve more than once)
    solves: int = 0
    #: Newton iterations of the step (implicit methods; 1 = one linearisation, BW98)
    newton_iterations: int = 0
    #: what :attr:`balance` evaluates (None: 0), set by a linear step with contacts: the force evaluation is made
    #: only where it is read (the collider reads its last round's; on the shared 64² drape's landing 1.2 of
    #: the 4.9 a frame the steps set)
    balance_of: Callable[[], float] | None = field(default=None, repr=False)
    #: linear solves and CG iterations of the attempts adaptive stepping discarded (redone with Newton iterations
    #: or a smaller step; booked by :meth:`StepController.advance <implicit_cloth.adaptive.StepController.advance>`),
    #: which ``solves`` and ``iterations`` leave out
    discarded_solves: int = 0
    discarded_iterations: int = 0
    #: smoothed friction solved to convergence (``collision.friction_newton``): whether the step's friction
    #: met its law (True), or the Newton iterations did not get it there and the step is the first solve's
    #: (False); None without it, and when the caller's ``redone`` skipped them (:meth:`ImplicitIntegrator.step`)
    friction_converged: bool | None = None
    #: whether the contacts' pending friction bounds (:attr:`Constraints.pending`: new contacts) were set from the
    #: step's first solve, so that its friction iterations solved theirs too
    pending_bounds: bool = False
    #: the pins' work on the cloth through self-contact in the step (self-collision's :attr:`SelfInfo.work
    #: <implicit_cloth.selfcontact.SelfInfo.work>`), J; booked in the energy balance like the pins' own
    self_work: float = 0.0
    #: the work the contact potential did on the cloth in the step (``collision.method = "barrier"``),
    #: ``U_c(x0) - U_c(x1)``, J: the energy balance books the energy the barrier stores or gives back
    contact_work: float = 0.0
    #: the larger of the energies the contact potential stores at the step's start and end, J: energy the step
    #: moves about, as the springs' is (the balance's allowance is a share of it)
    contact_stored: float = 0.0

    @property
    def balance(self) -> float:
        """rms over the free vertices (neither pinned nor in contact) of the step's nonlinear residual as an
        acceleration, ``|M (v1 - v_hat) - c_v F(x1, v1)| / (c_v m)``, m/s², when a linear step had contacts
        (else 0); one force evaluation each time it is read (:attr:`balance_of`)."""
        return 0.0 if self.balance_of is None else self.balance_of()

    @property
    def external_work(self) -> float:
        """The work on the cloth the step's energy balance books beside the pins' spring forces, J: the
        obstacles' (:attr:`collision`'s ``work``) and the pins' through self-contact (:attr:`self_work`)."""
        return (self.collision.work if self.collision is not None else 0.0) + self.self_work + self.contact_work

    @property
    def attempted_solves(self) -> int:
        """Every linear solve made for the step, the discarded attempts' included."""
        return self.solves + self.discarded_solves

    @property
    def attempted_iterations(self) -> int:
        """Every CG iteration made for the step, the discarded attempts' included."""
        return self.iterations + self.discarded_iterations

    def absorb(self, other: "StepInfo") -> None:
        """Add another solve of the same step: iterations and times summed, residual the largest."""
        self.iterations += other.iterations
        self.residual = max(self.residual, other.residual)
        self.converged = self.converged and other.converged
        self.t_assembly += other.t_assembly
        self.t_setup += other.t_setup
        self.t_solve += other.t_solve
        self.solves += other.solves
        self.newton_iterations = max(self.newton_iterations, other.newton_iterations)


class Integrator:
    """Maps ``(state, h, constraints)`` to the state one step of ``h`` seconds later.

    Subclasses implement :meth:`step`. Every method uses the same force code
    (:meth:`~implicit_cloth.model.Model.forces` / ``linearize``) and honours pins
    exactly: pinned vertices end each step at ``a_p + w_p t`` with velocity ``w_p``.
    Explicit methods honour pins only; contacts are the implicit methods' (the
    collision stage corrects an explicit step afterwards).
    """

    name = ""
    implicit = False
    #: other names of the method, suggested as this one in an error ("did you mean"), never accepted
    aliases: tuple[str, ...] = ()

    def __init__(self, model: Model, solver: dict[str, Any] | None = None) -> None:
        self.model = model

    def reset(self) -> None:
        """Forget any history (called when the state is assigned or dt changes)."""

    def step(self, state: State, h: float,
             constraints: Constraints | None = None) -> tuple[State, StepInfo]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _accel(self, x: np.ndarray, v: np.ndarray, t: float, info: StepInfo) -> np.ndarray:
        t0 = time.perf_counter()
        a = self.model.accelerations(x, v, t)
        info.t_assembly += time.perf_counter() - t0
        return a

    def _finish(self, x: np.ndarray, v: np.ndarray, t: float) -> State:
        self.model.apply_pins(x, v, t)
        return State(x, v, t)


@dataclass
class Scheme:
    """One implicit step's linear system and position update, before the constraints.

    ``A dv = b`` with ``A = M - c_v dF/dv - c_x dF/dx`` linearised at ``x``, ``v``; the end
    position is ``x_pred + beta (v + dv)``. The nonlinear equation the step approximates is
    ``M (v1 - v_hat) = c_v F(x_pred + beta v1, v1)`` (``beta = c_v``, ``c_x = c_v^2``).
    """

    c_x: float
    c_v: float
    b: np.ndarray
    x_pred: np.ndarray
    beta: float
    v_hat: np.ndarray


@dataclass
class _Linearization:
    """The last assembled system, reused when the same ``(state, h)`` is solved again with other constraints."""

    state: State
    h: float
    scheme: Scheme
    version: int                           # SystemMatrix.version when it was assembled


class ImplicitIntegrator(Integrator):
    """Shared machinery of the implicit methods: assembly, constraints, preconditioner, filtered PCG.

    Subclasses give :meth:`_scheme` (their linear system and position update); the
    constraints (pins, contacts and contact friction) are applied here the same way for
    every method.
    """

    implicit = True

    def __init__(self, model: Model, solver: dict[str, Any] | None = None) -> None:
        super().__init__(model, solver)
        from ..scene import DEFAULTS  # the [solver] table's defaults, for a solver given without them

        opts: dict[str, Any] = {**DEFAULTS["solver"], **(solver or {})}
        self.tolerance = float(opts["tolerance"])
        #: the tolerance of the solves of a step with contacts (at most ``tolerance``; default ``tolerance``):
        #: their impulses, ``A dv - b`` at the contacts, decide sticking and sliding (``[solver]
        #: contact_tolerance``)
        self.contact_tolerance = min(self.tolerance, float(opts.get("contact_tolerance", self.tolerance)))
        self.max_iterations = int(opts["max_iterations"])
        #: Newton iterations of a step (1: one linearisation, BW98); a caller may ask for more per step
        self.newton_iterations = int(opts["newton_iterations"])
        self.precond = make_preconditioner(opts["preconditioner"], model)
        if opts.get("cycle", "V") != "V":
            if not hasattr(self.precond, "cycle"):
                raise ValueError(f"solver.cycle = {opts['cycle']!r} needs a multigrid preconditioner, not "
                                 f"{self.precond.name!r}")
            self.precond.cycle = opts["cycle"]
        self._mass3 = np.repeat(model.masses, 3)
        self._pins = Constraints.of_pins(model)
        self._lin: _Linearization | None = None
        #: (contact vertices, c_v times their friction damping blocks) the system matrix holds on top of its
        #: assembly (smoothed friction; None: none)
        self._held_damping: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self._lin = None

    def _hold_damping(self, c: Constraints, c_v: float) -> None:
        """Make the system matrix hold ``c_v`` times the contacts' friction damping blocks on its diagonal (and
        no earlier contacts'), then finalize it."""
        want = (c.contact, c_v * c.damping) if c.n_contacts and c.damped else None
        have = self._held_damping
        if want is None and have is None:
            return
        sysm = self.model.system
        if have is not None:
            np.subtract.at(sysm.blocks, sysm.diag_index[have[0]], have[1])
        if want is not None:
            np.add.at(sysm.blocks, sysm.diag_index[want[0]], want[1])
        sysm.finalize_lazy()
        self._held_damping = want

    def _scheme(self, state: State, h: float, info: StepInfo) -> Scheme:  # pragma: no cover - abstract
        raise NotImplementedError

    def _linearize(self, x, v, t, c_x, c_v, w, info: StepInfo):
        t0 = time.perf_counter()
        out = self.model.linearize(x, v, t, c_x, c_v, w, lazy=True)   # the CSR copy only if a product needs it
        info.t_assembly += time.perf_counter() - t0
        return out

    def _system(self, state: State, h: float, c: Constraints, info: StepInfo) -> tuple[Scheme, Any, np.ndarray]:
        """The scheme, the finalized matrix and the right-hand side (with the contacts' kinetic friction)."""
        sysm = self.model.system
        lin = self._lin
        if lin is None or lin.state is not state or lin.h != h or lin.version != sysm.version:
            scheme = self._scheme(state, h, info)              # assembles and finalizes
            self._held_damping = None
            lin = self._lin = _Linearization(state, h, scheme, sysm.version)
        scheme = lin.scheme
        self._hold_damping(c, scheme.c_v)
        lin.version = sysm.version
        b = scheme.b
        if c.n_contacts and (np.any(c.friction) or c.damped):
            b = b.copy()
            b[c.contact] += scheme.c_v * c.friction
            if c.damped:     # the damping force is linear in v: c_v F(v0 + dv) = c_v F(v0) - c_v d dv
                b[c.contact] += scheme.c_v * c.damping_force(state.v)
        return scheme, sysm, b

    def step(self, state: State, h: float, constraints: Constraints | None = None,
             guess: np.ndarray | None = None, newton: int | None = None,
             start: np.ndarray | None = None,
             redone: Callable[[np.ndarray], bool] | None = None,
             done: Callable[[np.ndarray, np.ndarray], bool] | None = None) -> tuple[State, StepInfo]:
        """One step under ``constraints`` (the model's pins when None).

        ``guess`` warm-starts the first solve's free part; ``newton`` (default ``solver.newton_iterations``)
        is the most Newton iterations: 1 is Baraff & Witkin's single linearisation, more continue with
        :meth:`_newton` from its result. ``start``: end velocities (N, 3) of an earlier attempt at this step
        to continue from with ``newton`` Newton iterations instead (their constrained components are first
        set to what ``constraints`` prescribe). With smoothed friction solved to convergence (``c.rub``), the
        Newton iterations follow the first solve only where its friction is off the law at its result
        (:data:`FRICTION_TOLERANCE`). ``redone``: called with the first solve's constraint impulse (N, 3), N*s,
        in such a step; True says the caller will solve the step again whatever the friction does (it releases a
        contact that pulls its vertex), so the friction's Newton iterations are not run and the step is the
        first solve's, with :attr:`StepInfo.friction_converged` None (on the shared 64² drape over 2 s, 0.96 of
        the 2.98 correction solves a frame were made for rounds the collider then threw away). ``done``: the
        caller's test of an end state ``(x1, v1)`` that ends the Newton iterations of a step without contacts
        (adaptive stepping's energy and strain criteria: once the iterate passes them, more iterations would not
        change the step's verdict).
        """
        c = self._pins if constraints is None else constraints
        info = StepInfo(newton_iterations=1)
        scheme, A, b = self._system(state, h, c, info)
        v = state.v
        z = np.zeros_like(v)
        if len(c.pinned):
            z[c.pinned] = c.pin_velocity - v[c.pinned]
        if c.n_contacts:
            n = c.normal
            # end on the plane n . x1 = offset, with x1 = x_pred + beta v1
            vn1 = (c.offset - np.einsum("ij,ij->i", n, scheme.x_pred[c.contact])) / scheme.beta
            z[c.contact] = c.end_velocity(vn1) - v[c.contact]
            filt = Filter(self.model.n, c.pinned, c.contact, c.filter_blocks())
        else:
            filt = Filter(self.model.n, c.pinned)
        iters = self.newton_iterations if newton is None else int(newton)
        if start is not None:
            # the constrained components of v0 + z, the free ones of the earlier attempt
            v1 = v + z + filt.apply((start - v - z).reshape(-1)).reshape(-1, 3)
            info.newton_iterations = 0
            return self._newton(state, h, c, scheme, v1, filt, max(iters, 1), info, done)
        dv = self._solve(A, b, z, filt, info, guess, self.contact_tolerance if c.n_contacts else None)
        # smoothed friction solved to convergence: Newton only where the solve left a contact's friction off its
        # linearisation (its speed across the sliding speed, or its direction turned)
        nonlinear = c.n_contacts > 0 and c.nonlinear
        if iters > 1 and np.all(np.isfinite(dv)) and not nonlinear:
            return self._newton(state, h, c, scheme, v + dv, filt, iters - 1, info, done)
        v1 = v + dv
        x1 = scheme.x_pred + scheme.beta * v1
        if c.n_contacts:   # A dv - b = c_v F_c: the constraint force F_c over the step h is the impulse
            info.constraint_impulse = (A @ dv.reshape(-1) - b.reshape(-1)).reshape(-1, 3) * (h / scheme.c_v)
            info.balance_of = self._balance_of(scheme, c, x1, v1, state.t + h)
        if nonlinear and iters > 1 and redone is not None and info.constraint_impulse is not None \
                and redone(info.constraint_impulse):
            return self._finish(x1, v1, state.t + h), info     # solved again by the caller: no friction iterations
        if nonlinear and len(c.pending) and iters > 1 and info.constraint_impulse is not None:
            c = c.with_pending_bounds(info.constraint_impulse, h)  # new contacts: friction at this solve's force
            info.pending_bounds = True
        if nonlinear:
            info.friction_converged = bool(c.friction_error(v1) <= FRICTION_TOLERANCE)
            if iters > 1 and not info.friction_converged and np.all(np.isfinite(dv)):
                # Newton iterations on the friction alone where the solve left it off its law, the springs at
                # the step's linearisation; kept only if they meet the law, else the step is this first solve's,
                # for the caller's state rules
                met = self._friction_newton(state, h, c, scheme, filt, dv, iters - 1, info)
                info.friction_converged = met is not None
                if met is not None:
                    dv, c_met, newton_its = met
                    v1 = v + dv
                    x1 = scheme.x_pred + scheme.beta * v1
                    _, A, b = self._system(state, h, c_met, info)    # the law's linearisation at v1: exact there
                    info.constraint_impulse = (A @ dv.reshape(-1) - b.reshape(-1)).reshape(-1, 3) * (h / scheme.c_v)
                    info.balance_of = self._balance_of(scheme, c, x1, v1, state.t + h)
                    info.newton_iterations += newton_its
        return self._finish(x1, v1, state.t + h), info

    def _friction_newton(self, state: State, h: float, c: Constraints, scheme: Scheme, filt: Filter,
                         dv: np.ndarray, iterations: int,
                         info: StepInfo) -> tuple[np.ndarray, Constraints, int] | None:
        """Continue a step whose smoothed friction (``c.rub``) the first solve ``dv`` left off its law by Newton
        iterations on the friction alone: the springs and the other forces stay linearised at the step's start
        (Baraff & Witkin's single linearisation, the matrix ``A0`` and right-hand side ``b0`` of the first
        solve without the friction), the friction is the law itself. That is the minimum of the convex

            Phi(dv) = dv^T A0 dv / 2 - b0^T dv + c_v sum mu N f(|v_t(v0 + dv)|)

        (``f`` Huber's, :meth:`Constraints.friction_potential`) over the velocities the constraints allow.
        Each iteration linearises the friction exactly at the iterate (:meth:`Constraints.relinearized`), solves
        ``(A0 + c_v D_k) d = -grad Phi`` (the same filtered PCG) and steps to the least ``Phi`` along ``d`` on
        ``0 < a <= 1`` (:func:`_segment_root`; ``Phi`` is convex, so every iteration lowers it). Stops when the
        friction's linearisation holds at the iterate (:data:`FRICTION_TOLERANCE`) or the correction is below
        that fraction of the sliding speed, and the last correction's own error is within the step's tolerance
        of ``dv``: the first correction is solved to :data:`NEWTON_FORCING`, each later one to
        ``tolerance |dv| / |last correction|`` (between the tolerance and that forcing), and a law met with a
        correction too large for its forcing takes one more (a cloth creeping on a tilted plane: its first
        step's correction is its whole slide, and 10 % of it put the creep 2 % off its closed form). Gives up
        (None) when the law is not met after ``iterations``, or once the friction's error stops contracting
        (:data:`FRICTION_CONTRACTION`).

        Why the springs stay linearised: iterating them too (:meth:`_newton`, the continuation until
        2026-12-06) stalls while the cloth folds (the compressed springs' clamped Hessian: corrections of
        2-6 cm/s not shrinking), so most continuations missed the law and were thrown away (the shared 64²
        drape over 2 s: 176 of 231, half the run's solves). What the linearisation leaves in the springs is the
        same as in a step without contacts: the collider's balance-driven refinement and adaptive stepping's
        energy balance see it (``collision.newton_iterations``, :class:`~implicit_cloth.adaptive.StepController`).

        Returns the velocity change, the constraints with the friction linearised at its end and the
        iterations taken; None when the law was not met.
        """
        cv = scheme.c_v
        v0 = state.v
        M = self.model.masses[:, None]
        floor = FRICTION_TOLERANCE * c.slide_speed * np.sqrt(float(np.sum(M)))
        tol = self.contact_tolerance
        forcing = max(tol, NEWTON_FORCING)
        last_err: float | None = None
        met = False
        for k in range(iterations):
            v = v0 + dv
            ck = c.relinearized(v)
            _, A, b = self._system(state, h, ck, info)
            r = A @ dv.reshape(-1) - b.reshape(-1)      # grad Phi at dv: the linearisation is exact at v
            # only the contacts' diagonal damping blocks changed since the last solve: the coarse levels kept
            # (on the shared 64² drape 7 % more CG iterations, 14 % less time in these solves)
            d = self._solve(A, -r.reshape(-1, 3), np.zeros_like(v), filt, info, tolerance=forcing,
                            diagonal_only=True)
            slope = float(np.dot(filt.apply(r), d.reshape(-1)))
            if not np.isfinite(slope) or slope >= 0.0:
                break
            dc = d[c.contact]
            # d^T A0 d: the system holds c_v D_k beside A0
            dAd = float(np.dot(d.reshape(-1), A @ d.reshape(-1))) \
                - cv * float(np.einsum("kij,ki,kj->", ck.damping, dc, dc))
            lin = slope + cv * float(np.einsum("ij,ij->", c.friction_force(v), dc))

            a = _segment_root(_model_slope(c, cv, v, d, lin, dAd), slope)
            dv = dv + a * d
            err = ck.friction_error(v0 + dv)
            met = a * np.sqrt(float(np.einsum("ij,ij->", M * d, d))) <= floor or err <= FRICTION_TOLERANCE
            # the correction's own error (its solve's relative tolerance) within the step's tolerance of dv
            size, whole = a * float(np.linalg.norm(d)), float(np.linalg.norm(dv))
            if met and forcing * size <= tol * whole:
                return dv, c.relinearized(v0 + dv), k + 1
            if not met and last_err is not None and err > FRICTION_CONTRACTION * last_err:
                return None
            last_err = err
            # the next correction, at most this one's size, solved so that its error stays within tol |dv|
            forcing = float(np.clip(tol * whole / max(size, 1e-300), tol, NEWTON_FORCING))
        if met:                                         # the law met, the last correction's error above tol
            return dv, c.relinearized(v0 + dv), iterations
        return None

    def _balance_of(self, scheme: Scheme, c: Constraints, x1: np.ndarray, v1: np.ndarray,
                    t1: float) -> Callable[[], float]:
        """:meth:`_balance` of the end state ``x1``, ``v1`` as they are now (copied: the step's :meth:`_finish`
        puts the pinned vertices on their paths in place), evaluated when called."""
        x1, v1 = x1.copy(), v1.copy()
        return lambda: self._balance(scheme, c, x1, v1, t1)

    def _balance(self, scheme: Scheme, c: Constraints, x1: np.ndarray, v1: np.ndarray, t1: float) -> float:
        """:attr:`StepInfo.balance` of the end state ``x1``, ``v1`` (one force evaluation)."""
        free = np.ones(self.model.n, dtype=bool)
        free[c.pinned] = False
        free[c.contact] = False
        if not np.any(free):
            return 0.0
        m = self.model.masses[free, None]
        r = m * (v1[free] - scheme.v_hat[free]) - scheme.c_v * self._forces(x1, v1, t1, c)[free]
        return float(np.sqrt(np.mean(np.einsum("ij,ij->i", r, r) / m[:, 0] ** 2))) / scheme.c_v

    # ------------------------------------------------------------------ nonlinear solve
    def _forces(self, x: np.ndarray, v: np.ndarray, t: float, c: Constraints) -> np.ndarray:
        f = self.model.forces(x, v, t)
        if c.n_contacts:
            self._add_friction(f, c, v)
        return f

    @staticmethod
    def _add_friction(f: np.ndarray, c: Constraints, v: np.ndarray) -> None:
        """Add the contacts' friction force at ``v`` to ``f`` (in place; the linearised one term by term)."""
        if c.nonlinear:
            f[c.contact] += c.friction_force(v)
            return
        f[c.contact] += c.friction
        if c.damped:
            f[c.contact] += c.damping_force(v)

    @staticmethod
    def _done(done: Callable[[np.ndarray, np.ndarray], bool] | None, c: Constraints, scheme: Scheme,
              v: np.ndarray) -> bool:
        """The caller's ``done`` of a step without contacts at the iterate ``v`` (False without one)."""
        return done is not None and not c.n_contacts and done(scheme.x_pred + scheme.beta * v, v)

    def _conservative(self, x: np.ndarray, t: float) -> tuple[float, np.ndarray]:
        """Potential energy (J) and conservative force (N) of the model's conservative forces at ``x``."""
        return forces.conservative(self.model.effects, x, t)

    def _potential(self, x: np.ndarray) -> float:
        return forces.energy(self.model.effects, x)

    def _newton(self, state: State, h: float, c: Constraints, scheme: Scheme, v: np.ndarray, filt: Filter,
                iterations: int, info: StepInfo,
                done: Callable[[np.ndarray, np.ndarray], bool] | None = None) -> tuple[State, StepInfo]:
        """Continue the step by Newton iterations with a line search on the incremental potential.

        The step's nonlinear equation ``R(v) = M (v - v_hat) - c_v F(x(v), v) = 0``, ``x(v) = x_pred + c_v v``,
        is the stationarity of the incremental potential (Martin et al. 2011; Gast et al. 2015)::

            Phi(v) = |v - v_hat|_M^2 / 2 + U(x(v)) + c_v D(v)

        with ``U`` the model's conservative forces' energy and ``D`` the dissipation potential of the forces
        linear in the velocity (spring damping, drag with its wind) and of the constant ones (kinetic friction),
        their geometry taken at the current iterate (:mod:`implicit_cloth.forces`). Each iteration solves
        ``A_k d = -R(v_k)`` (the same filtered PCG and constraints, constrained components 0: every iterate
        meets the constraints the first solve met) and backtracks ``v_k + a d`` from ``a = 1`` until ``Phi``
        decreases enough (Armijo, ``1e-4``), so no iteration can raise it. Stops when ``|a d| <= tolerance
        |v - v0|``, after ``iterations``, or when the line search fails (the iterate is kept).
        Returns the step's state and figures.

        Smoothed friction solved to convergence (``c.rub`` given: ``collision.friction_newton``) is re-linearised
        at every iterate (:meth:`Constraints.relinearized`, the Huber potential's exact Hessian), its
        dissipation potential enters ``Phi`` exactly (not as an affine force), the step length is the least
        ``Phi`` along ``d`` (:meth:`_line_minimum`, then the same Armijo test), and the iterations also stop once
        the friction's linearisation holds at the iterate (:data:`FRICTION_TOLERANCE`), or, unconverged, once
        its error stops contracting (:data:`FRICTION_CONTRACTION`).
        """
        M = self.model.masses[:, None]
        t1 = state.t + h
        cv = scheme.c_v
        A = None
        nonlinear = c.n_contacts > 0 and c.nonlinear
        met = False
        # a correction this small (rms m/s) ends a friction solve too: a fraction of the sliding speed
        floor = FRICTION_TOLERANCE * c.slide_speed * np.sqrt(float(np.sum(M))) if nonlinear else 0.0
        last_err: float | None = None
        for _ in range(iterations):
            x = scheme.x_pred + cv * v
            A, f, _ = self._linearize(x, v, t1, scheme.c_x, cv, None, info)
            self._held_damping = None
            f_model = f.copy()
            if c.n_contacts:
                c = c.relinearized(v)        # smoothed friction solved to convergence: its Hessian at v
                self._add_friction(f, c, v)
                if c.damped:
                    self._hold_damping(c, cv)
            self._lin = None          # the matrix no longer holds the step's first linearisation
            R = M * (v - scheme.v_hat) - cv * f
            R_free = filt.apply(R.copy().reshape(-1))
            d = self._solve(A, -R, np.zeros_like(v), filt, info, tolerance=max(self.tolerance, NEWTON_FORCING))
            slope = float(np.dot(R_free, d.reshape(-1)))
            if not np.isfinite(slope) or slope >= 0.0:
                break
            u0, p0 = self._conservative(x, t1)
            if nonlinear:
                # the model's forces are affine in v (f_w + G v) but for the conservative part; the friction's
                # dissipation potential enters the line search exactly (below)
                f_nc = f_model - p0
                Gd = self.model.forces(x, v + d, t1) - f_model
                d0 = c.friction_potential(v)
            else:
                f_nc = f - p0                                      # affine in v: f_nc(v) = f_w + G v
                Gd = self._forces(x, v + d, t1, c) - f             # G d
            dGd = float(np.einsum("ij,ij->", d, Gd))
            dMd = float(np.einsum("ij,ij->", M * d, d))
            lin = float(np.einsum("ij,ij->", M * (v - scheme.v_hat), d)) - cv * float(np.einsum("ij,ij->", f_nc, d))
            a = 1.0
            if nonlinear:      # the friction's kinks along d: the minimiser on the segment, not a halving
                a = self._line_minimum(x, v, d, c, cv, lin, dMd - cv * dGd, t1, slope)
            accepted = False
            for _ls in range(12):
                dphi = a * lin + 0.5 * a * a * (dMd - cv * dGd) + self._potential(x + a * cv * d) - u0
                if nonlinear:
                    dphi += cv * (c.friction_potential(v + a * d) - d0)
                if dphi <= 1e-4 * a * slope:
                    accepted = True
                    break
                a *= 0.5
            if not accepted:
                break
            v = v + a * d
            info.newton_iterations += 1
            step = a * np.sqrt(dMd)
            err = c.friction_error(v) if nonlinear else 0.0
            met = nonlinear and (step <= floor or err <= FRICTION_TOLERANCE)
            if nonlinear and not met and last_err is not None and err > FRICTION_CONTRACTION * last_err:
                break                                   # not contracting: given up, the caller keeps the first solve
            last_err = err
            if met or step <= NEWTON_TOLERANCE * np.sqrt(float(np.einsum("ij,ij->", M * (v - state.v),
                                                                         v - state.v))) \
                    or self._done(done, c, scheme, v):
                break
        if nonlinear:
            info.friction_converged = met
        if c.n_contacts:   # the constraint force at the last iterate: F_c = (M (v - v_hat) - c_v F) / c_v
            x = scheme.x_pred + cv * v
            Rc = M * (v - scheme.v_hat) - cv * self._forces(x, v, t1, c)
            info.constraint_impulse = Rc * (h / cv)
        v1 = v.copy()
        return self._finish(scheme.x_pred + scheme.beta * v1, v1, t1), info

    def minimize(self, state: State, h: float, terms: list[Any], pins: Constraints | None = None,
                 iterations: int = MINIMIZE_ITERATIONS,
                 done: Callable[[np.ndarray, np.ndarray, float], bool] | None = None) -> tuple[State, StepInfo]:
        """One step as the minimiser of its incremental potential with the extra force ``terms`` (contact,
        friction: :class:`~implicit_cloth.forces.Force` objects) beside the model's own
        (:mod:`implicit_cloth.forces`)::

            Phi(v) = |v - v_hat|_M^2 / 2 + sum_f U_f(x(v)) + c_v sum_f D_f(x_k, v),   x(v) = x_pred + c_v v

        Projected Newton: each iteration assembles every force's Hessian blocks at the iterate (the system's
        fixed pattern; the contact terms add diagonal blocks, and self-contact a coupling the CG's product adds),
        solves ``A d = -grad Phi`` by the filtered PCG with the pins exact (their components 0) and cuts each
        vertex's part of the direction to what the terms allow its path (``filter_move(x, c_v d)``: no iterate
        crosses a contact). A cut direction that still lowers ``Phi`` at full length is taken; otherwise the
        contacts enter the direction (:meth:`_contact_direction`: a vertex arriving at an obstacle constrained
        along its normal to where the barrier will hold it, the rest solved again). Then backtracking until
        ``Phi`` decreases enough (Armijo). The first iterate is the start velocity cut the same way from
        ``x_pred``. Stops when the Newton correction's mass-weighted rms speed is below
        :data:`MINIMIZE_TOLERANCE` of the step's velocity change or :data:`MINIMIZE_FLOOR`, when ``done(x1, v,
        decrement)`` says so (the caller's test of the end state and of Newton's predicted decrease of ``Phi``,
        half the slope: the simulator's energy balance), or after ``iterations``. Every iterate lowers ``Phi``, in
        which contact is conservative and friction dissipative (a force with neither potential, the aerodynamics,
        enters ``Phi`` as its work lagged at the iterate, ``-c_v F(x_k, v_k) . (v - v_k)``: its slope is the
        residual's); backward Euler on a potential that is not convex
        (compressed springs, a barrier over a curved surface) can still gain energy, which the step's energy
        balance checks.
        """
        c = self._pins if pins is None else pins
        info = StepInfo(newton_iterations=0)
        scheme = self._scheme(state, h, info)
        self._lin = None
        self._held_damping = None
        cv, t1 = scheme.c_v, state.t + h
        M = self.model.masses[:, None]
        every = list(self.model.effects) + list(terms)
        bounds = _PathBounds(terms, cv)
        filt = Filter(self.model.n, c.pinned)
        v = state.v.copy()
        if len(c.pinned):
            v[c.pinned] = c.pin_velocity
        # the first iterate: the start velocity, each vertex as far as the contacts allow from x_pred (v = 0)
        x0 = scheme.x_pred
        v = bounds.cut(x0, v, first=True)
        # forces with neither a potential nor a dissipation potential (the aerodynamics): in Phi as their work
        # lagged at the iterate, -c_v F(x_k, v_k) . (w - v_k), so that Phi's slope there is the residual's
        unpotential = [e for e in self.model.effects if not e.conservative and not e.dissipative]
        if bounds.limits:
            v = self._first_within_limits(bounds, c, M, scheme, every, x0, v, t1, unpotential)
        v = bounds.start(x0, v)
        bounds.admit(x0 + cv * v)   # a bound the first iterate's carried vertices break is moved out for the step
        floor = MINIMIZE_FLOOR * np.sqrt(float(np.sum(M)))
        sysm = self.model.system
        diag0 = np.empty((self.model.n, 3, 3)) if terms else None   # the diagonal blocks without the contacts'
        for _ in range(iterations):
            x = x0 + cv * v
            t0 = time.perf_counter()
            A, f, _ = self.model.linearize(x, v, t1, scheme.c_x, cv, None, lazy=True)
            if diag0 is not None:
                np.take(sysm.blocks, sysm.diag_index, axis=0, out=diag0)
            for term in terms:
                term.linearize(x, v, t1, scheme.c_x, cv, None, sysm, None, f)
            sysm.finalize_lazy()
            coupling = [term.coupling for term in terms if getattr(term, "coupling", None) is not None]
            info.t_assembly += time.perf_counter() - t0
            R = M * (v - scheme.v_hat) - cv * f
            d = self._solve(A, -R, np.zeros_like(v), filt, info, tolerance=max(self.tolerance, NEWTON_FORCING),
                            coupling=coupling)
            R_free = filt.apply(R.copy().reshape(-1))
            slope = float(np.dot(R_free, d.reshape(-1)))
            if not np.isfinite(slope) or slope >= 0.0:
                break

            phi = _step_potential(M, scheme.v_hat, every, x0, cv, t1, x, v, unpotential)

            cut = bounds.cut(x, d)
            if cut is d:
                a = bounds.limit(x, d)
                a = _armijo(phi, v, d, a, slope, settle=a < 1.0)
            else:
                # the cut direction taken as it is where it lowers the potential at full or half length
                slope_c = float(np.dot(R_free, cut.reshape(-1)))
                a = bounds.limit(x, cut)
                a = _armijo(phi, v, cut, a, slope_c, halvings=2, settle=a < 1.0) if slope_c < 0.0 else 0.0
                if a > 0.0:
                    d, slope = cut, slope_c
                else:
                    found = self._contact_direction(A, R, R_free, x, d, cut, c, bounds, info, coupling, diag0)
                    if found is None:
                        break
                    d, slope, a = found
                    limited = bounds.limit(x, d, a)
                    a = _armijo(phi, v, d, limited, slope, settle=limited < a)
            if a <= 0.0:
                break
            v = v + a * d
            info.newton_iterations += 1
            # converged when the Newton correction itself is small, not the step a contact's bound cut it to
            step = np.sqrt(float(np.einsum("ij,ij->", M * d, d)))
            change = np.sqrt(float(np.einsum("ij,ij->", M * (v - state.v), v - state.v)))
            if step <= max(MINIMIZE_TOLERANCE * change, floor):
                break
            if done is not None and done(x0 + scheme.beta * v, v, -0.5 * slope):
                break
        x1 = x0 + scheme.beta * v
        return self._finish(x1, v, t1), info

    @staticmethod
    def _first_within_limits(bounds: "_PathBounds", c: Constraints, M: np.ndarray, scheme: Scheme,
                             every: list[Any], x0: np.ndarray, v: np.ndarray, t1: float,
                             unpotential: list[Any]) -> np.ndarray:
        """:meth:`minimize`'s first iterate ``v`` under the terms that bound a move as a whole (the strain limit):
        the pinned vertices on their paths (their bounds moved out where those alone break them,
        ``admit``), the free vertices' velocities scaled by the largest share the bounds allow, then halved
        while the step's potential still decreases (the start velocity carried into a bound would leave the
        springs against it, where Newton only creeps back out)."""
        cv = scheme.c_v
        base = np.zeros_like(v)
        base[c.pinned] = v[c.pinned]
        free = v - base
        xb = x0 + cv * base
        bounds.admit(xb)
        a = bounds.limit(xb, free)
        if a >= 1.0:
            return v
        phi = _step_potential(M, scheme.v_hat, every, x0, cv, t1, x0, v, unpotential)
        return base + _halved_while_lower(phi, base, free, a, phi(base + a * free)) * free

    def _contact_direction(self, A: Any, R: np.ndarray, R_free: np.ndarray, x: np.ndarray, d: np.ndarray,
                           cut: np.ndarray, c: Constraints, bounds: "_PathBounds", info: StepInfo,
                           coupling: list[Any], contact_free_diag: np.ndarray | None = None
                           ) -> tuple[np.ndarray, float, float] | None:
        """A Newton direction ``d`` some of whose vertices' paths a contact cut (``cut``: :meth:`_PathBounds.cut`),
        made one the contacts allow: the vertices cut against an obstacle constrained in its normal only, to
        arrive within the barrier's reach (:meth:`ObstacleBarrier.normal_targets
        <implicit_cloth.contact.obstacles.ObstacleBarrier.normal_targets>`), free to slide; the others cut
        (self-contact) prescribed their cut move; the rest of the cloth's direction solved again with those
        (the filtered PCG's prescribed components, BW98 section 5.3). Cutting a direction vertex by vertex
        leaves the uncut vertices moving as if the cut ones moved all the way (springs stretched: the line search
        then backtracks to a few percent); solved again, the cloth's direction accounts for the contacts.

        Returns the direction, its slope and the largest step its paths allow; None when no descent direction
        was found. Falls back to the cut direction (when it descends) or to the cut vertices held still."""
        n = self.model.n
        cv = bounds.c_v
        ratio = _kept(d, cut)
        cutv = np.flatnonzero(ratio < 1.0 - 1e-9)
        tol = max(self.tolerance, NEWTON_FORCING)
        if len(cutv) and not bounds.scaled and ARRIVAL_ROUNDS > 0:
            # the cut vertices constrained and the rest solved again, the vertices that direction's paths cut added,
            # until a direction is whole or after ARRIVAL_ROUNDS solves
            pos, move, full = np.zeros((0,), dtype=np.int64), cv * cut, d
            # a cut vertex's stiffness (N/m) along any direction, from the system's diagonal block without the
            # contact terms (the inertia and the springs): the smallest eigenvalue, over c_x
            sysm = self.model.system
            blocks = sysm.blocks[sysm.diag_index] if contact_free_diag is None else contact_free_diag
            stiffness = np.zeros(n)
            nrm_all, mn_all = np.zeros((0, 3)), np.zeros(0)
            fixed, fixed_z = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
            last: np.ndarray | None = None
            for _round in range(ARRIVAL_ROUNDS):
                stiffness[cutv] = np.linalg.eigvalsh(blocks[cutv])[:, 0] / (cv * cv)
                idx, nrm, move_n = bounds.normal_targets(x, move, np.setdiff1d(cutv, np.union1d(pos, fixed)),
                                                         cv * full, stiffness)
                others = np.setdiff1d(cutv, np.union1d(np.union1d(pos, fixed), idx))
                pos, nrm_all, mn_all = (np.concatenate([pos, idx]), np.concatenate([nrm_all, nrm]),
                                        np.concatenate([mn_all, move_n]))
                fixed, fixed_z = np.concatenate([fixed, others]), np.concatenate([fixed_z, move[others] / cv])
                z = np.zeros((n, 3))
                z[fixed] = fixed_z
                z[pos] = nrm_all * (mn_all / cv)[:, None]
                S = np.eye(3)[None] - nrm_all[:, :, None] * nrm_all[:, None, :]
                sub = Filter(n, np.union1d(c.pinned, fixed), pos, S)
                d2 = self._solve(A, -R, z, sub, info, tolerance=tol, coupling=coupling)
                slope2 = float(np.dot(R_free, d2.reshape(-1)))
                if not np.isfinite(slope2) or slope2 >= 0.0:
                    break
                cut2 = bounds.cut(x, d2)
                if cut2 is d2:
                    return d2, slope2, 1.0
                if bounds.scaled:
                    break
                new = np.setdiff1d(np.flatnonzero(_kept(d2, cut2) < 1.0 - 1e-9), np.union1d(pos, fixed))
                last = cut2
                if not len(new):
                    break
                cutv, move, full = new, cv * cut2, d2
            if last is not None:        # the last solve's direction, cut where it still is, if it descends
                slope3 = float(np.dot(R_free, last.reshape(-1)))
                if np.isfinite(slope3) and slope3 < 0.0:
                    return last, slope3, 1.0
        # the cut direction, if it still descends; else the Newton direction of the other vertices, the cut ones
        # held, scaled down until every path allows it
        slope_t = float(np.dot(R_free, cut.reshape(-1)))
        if np.isfinite(slope_t) and slope_t < 0.0:
            return cut, slope_t, 1.0
        held = np.flatnonzero(ratio < (1.0 - 1e-9) * float(ratio[ratio < np.inf].max(initial=0.0)))
        sub = Filter(n, np.union1d(c.pinned, held))
        d = self._solve(A, -R, np.zeros_like(d), sub, info, tolerance=tol, coupling=coupling)
        slope = float(np.dot(sub.apply(R.copy().reshape(-1)), d.reshape(-1)))
        if not np.isfinite(slope) or slope >= 0.0:
            return None
        return d, slope, bounds.uniform(x, d)

    def _line_minimum(self, x: np.ndarray, v: np.ndarray, d: np.ndarray, c: Constraints, cv: float, lin: float,
                      quad: float, t1: float, slope: float) -> float:
        """Where the incremental potential is least along ``v + a d`` on ``0 < a <= 1`` (smoothed friction solved
        to convergence; 1 when it still decreases there).

        Its derivative ``g(a) = lin + a quad - c_v (f_c(x + a c_v d) . d + F_fr(v + a d) . d)`` (``f_c`` the
        conservative forces, ``F_fr`` the friction law, ``lin`` and ``quad`` the affine forces' part) is negative
        at 0 (``slope``); a Newton step from a sliding contact's constant kinetic force overshoots the point
        where the contact stops (past it the friction turns): a halving line search then needs about
        ``log2(speed / eps)`` iterations for it, the root of ``g`` (regula falsi, Illinois) a few force
        evaluations.
        """
        def g(a: float) -> float:
            _, fc = self._conservative(x + a * cv * d, t1)
            fr = c.friction_force(v + a * d)
            return lin + a * quad - cv * (float(np.einsum("ij,ij->", fc, d))
                                          + float(np.einsum("ij,ij->", fr, d[c.contact])))
        return _segment_root(g, slope)

    def _solve(self, A, b: np.ndarray, z: np.ndarray, filt: Filter, info: StepInfo,
               guess: np.ndarray | None = None, tolerance: float | None = None,
               diagonal_only: bool = False, coupling: list[Any] | None = None) -> np.ndarray:
        """Solve ``A dv = b`` with the constrained components of ``dv`` prescribed (``z``) through ``filt``.

        ``diagonal_only``: only diagonal blocks changed since the last solve, with the same filter (the friction's
        Newton corrections): the multigrid refreshes its fine level only (:meth:`Multigrid.refresh_diagonal
        <implicit_cloth.solvers.multigrid.Multigrid.refresh_diagonal>`)."""
        t0 = time.perf_counter()
        if diagonal_only and hasattr(self.precond, "refresh_diagonal"):
            self.precond.refresh_diagonal(self.model.system, filt)
        else:
            self.precond.setup(self.model.system, filt)
        t1 = time.perf_counter()

        op, compiled = A, None
        if coupling:   # couplings off the system's pattern (self-contact): the product adds them, in numpy
            op, compiled = _Coupled(A, coupling), False

        def solve():
            return filtered_pcg(op, b.reshape(-1), z.reshape(-1), filt, self.precond,
                                self.tolerance if tolerance is None else tolerance, self.max_iterations,
                                mass=self._mass3, rule=self.precond.stopping_rule,
                                guess=None if guess is None else guess.reshape(-1), compiled=compiled)
        dv, res = solve()
        protect = getattr(self.precond, "protect", None)
        if not res.converged and res.iterations < self.max_iterations and protect is not None and protect():
            # CG broke down: the V-cycle is not positive definite (a coarse smoother amplifying); the multigrid
            # now damps its coarse smoothers to their matrices (multigrid.SMOOTHER_RHO): solved again, the
            # broken solve's iterations counted
            info.iterations += res.iterations
            info.solves += 1
            dv, res = solve()                    # (its set-up again counted in the solve's time)
        if coupling and not res.converged and res.iterations < self.max_iterations:
            # a coupled solve (self-contact) that broke down on the V-cycle (set up without the coupling, it
            # can stop being positive definite against the coupled matrix): solved again on block Jacobi,
            # positive definite on any SPD matrix, to the guaranteed bound
            info.iterations += res.iterations
            info.solves += 1
            jacobi = BlockJacobi(self.model.n)
            jacobi.setup(self.model.system, filt)
            dv, res = filtered_pcg(op, b.reshape(-1), z.reshape(-1), filt, jacobi,
                                   self.tolerance if tolerance is None else tolerance, self.max_iterations,
                                   mass=self._mass3, rule=jacobi.stopping_rule, compiled=False)
        info.t_setup += t1 - t0
        info.t_solve += time.perf_counter() - t1
        info.iterations += res.iterations
        info.residual = max(info.residual, res.residual)
        info.converged = info.converged and res.converged
        info.solves += 1
        return dv.reshape(-1, 3)


class _PathBounds:
    """The safe-move filters of the force terms that have them (``filter_move(x, dx)``: each vertex's move
    ``dx`` cut to what keeps it off every contact), applied to a Newton direction in velocities (moves
    ``c_v d``), one after the other until none cuts further."""

    def __init__(self, terms: list[Any], c_v: float) -> None:
        self.terms = [f for f in terms if hasattr(f, "filter_move")]
        #: the terms that bound a move as a whole (``step_limit(x, dx)``: the strain limit)
        self.limits = [f for f in terms if hasattr(f, "step_limit")]
        #: the terms whose bounds move out for a step's first iterate (``admit(x)``)
        self.admitting = [f for f in terms if hasattr(f, "admit")]
        self.c_v = c_v
        #: whether the last :meth:`cut` scaled the direction as a whole (its filters did not settle)
        self.scaled = False

    def cut(self, x: np.ndarray, d: np.ndarray, first: bool = False) -> np.ndarray:
        """``d`` with each vertex's part cut to what every filter allows from ``x`` (``d`` itself if none cuts);
        after :data:`FILTER_PASSES` passes that still cut, scaled down as a whole instead. ``first``: the step's
        first iterate (the filters' ``first``)."""
        self.scaled = False
        if not self.terms:
            return d
        move = self.c_v * d
        cut = False
        for _ in range(FILTER_PASSES):
            changed = False
            for f in self.terms:
                new = f.filter_move(x, move, first)
                if new is not move:
                    move, changed = new, True
            if not changed:
                return move / self.c_v if cut else d
            cut = True
        self.scaled = True
        return self.uniform(x, d, first) * d

    def limit(self, x: np.ndarray, d: np.ndarray, a: float = 1.0) -> float:
        """``a``, or less where a term that bounds a move as a whole (``step_limit``) allows only a shorter share
        of ``a d`` from ``x`` (a line search's first point; every shorter one is allowed too)."""
        for f in self.limits:
            if a <= 0.0:
                break
            a *= f.step_limit(x, self.c_v * a * d)
        return a

    def admit(self, x: np.ndarray) -> None:
        """Let the terms that can move their bounds out for the step (the strain limit) admit positions ``x``
        (the step's first iterate, or its pins alone)."""
        for f in self.admitting:
            f.admit(x)

    def normal_targets(self, x: np.ndarray, move: np.ndarray, idx: np.ndarray, full: np.ndarray,
                       stiffness: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of the vertices ``idx`` whose ``move`` (cut) ends near an obstacle: those vertices, the obstacle's
        normal there and the move along it that brings each to its arrival gap (the terms'
        ``normal_targets``; a vertex two terms claim keeps the first's)."""
        out_i, out_n, out_m = [np.zeros(0, dtype=np.int64)], [np.zeros((0, 3))], [np.zeros(0)]
        left = np.asarray(idx, dtype=np.int64)
        for f in self.terms:
            if not hasattr(f, "normal_targets") or not len(left):
                continue
            i, nrm, m = f.normal_targets(x, move, left, full, stiffness)
            out_i.append(i)
            out_n.append(nrm)
            out_m.append(m)
            left = np.setdiff1d(left, i)
        return np.concatenate(out_i), np.concatenate(out_n), np.concatenate(out_m)

    def start(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The first iterate ``v`` (already cut from ``x``, the predicted positions) with the moves the terms that
        have ``start(x, dx)`` set instead (a moving obstacle carries the vertices it would pass through)."""
        move = start = self.c_v * v
        for f in self.terms:
            if hasattr(f, "start"):
                move = f.start(x, move)
        return v if move is start else move / self.c_v

    def allowed(self, x: np.ndarray, d: np.ndarray, first: bool = False) -> bool:
        move = self.c_v * d
        return all(f.filter_move(x, move, first) is move for f in self.terms)

    def uniform(self, x: np.ndarray, d: np.ndarray, first: bool = False) -> float:
        """The largest ``a = 2^-k`` (``k <`` :data:`LINE_SEARCH_HALVINGS`) with ``a d`` allowed to every vertex
        whole, by bisection on ``k`` (each filter checks paths from ``x``: a shorter move along ``d`` is a prefix
        of a longer one, allowed where that is; the fallback's moves are mostly cut to ``2^-20`` or so, which
        halving found in twenty checks of every path, bisection in seven); 0 if none is."""
        if not self.terms or self.allowed(x, d, first):
            return 1.0
        lo, hi = 0, LINE_SEARCH_HALVINGS - 1      # 2^-lo is not allowed; 2^-hi is, once checked
        if not self.allowed(x, 2.0 ** -hi * d, first):
            return 0.0
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self.allowed(x, 2.0 ** -mid * d, first):
                hi = mid
            else:
                lo = mid
        return 2.0 ** -hi


class _Coupled:
    """``A + sum C_k``: the system matrix and couplings off its pattern (anything with ``@``)."""

    def __init__(self, A: Any, coupling: list[Any]) -> None:
        self.A, self.coupling = A, coupling
        self.shape = A.shape

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        y = self.A @ x
        for C in self.coupling:
            y = y + C @ x
        return y


def _kept(d: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """Per vertex, the fraction of its part of the direction ``d`` that ``cut`` keeps (inf where ``d`` is 0)."""
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(norm > 0, np.sqrt(np.einsum("ij,ij->i", cut, cut)) / np.where(norm > 0, norm, 1.0), np.inf)


def _step_potential(M: np.ndarray, v_hat: np.ndarray, every: list[Any], x0: np.ndarray, cv: float, t1: float,
                    x_lag: np.ndarray, v_lag: np.ndarray, lagged: list[Any]) -> Callable[[np.ndarray], float]:
    """:meth:`ImplicitIntegrator.minimize`'s ``Phi(w) = |w - v_hat|_M^2 / 2 + sum_f U_f(x0 + c_v w) + c_v sum_f
    D_f(x_lag, w, t1)``, less ``c_v F(x_lag, v_lag) . (w - v_lag)`` for the ``lagged`` forces (those with neither
    potential: their work lagged at the iterate ``v_lag``, so that ``Phi``'s slope there is the residual's)."""
    f_lag = None
    if lagged:
        f_lag = np.zeros_like(v_lag)
        for e in lagged:
            e.force(x_lag, v_lag, t1, f_lag)

    at_lag: list[float] = []    # Phi at the iterate, once (each line search from it starts there)

    def phi(w: np.ndarray) -> float:
        if w is v_lag and at_lag:
            return at_lag[0]
        p = (0.5 * float(np.einsum("ij,ij->", M * (w - v_hat), w - v_hat))
             + forces.energy(every, x0 + cv * w) + cv * forces.dissipation(every, x_lag, w, t1))
        if f_lag is not None:
            p -= cv * float(np.einsum("ij,ij->", f_lag, w - v_lag))
        if w is v_lag:
            at_lag.append(p)
        return p

    return phi


def _armijo(phi: Callable[[np.ndarray], float], v: np.ndarray, d: np.ndarray, a: float, slope: float,
            halvings: int = LINE_SEARCH_HALVINGS, settle: bool = False) -> float:
    """Backtracking from ``a`` until ``phi(v + a d) <= phi(v) + 1e-4 a slope``; 0 when it does not within
    ``halvings`` tries. ``settle`` (``a`` is a bound's, short of the full step): once accepted, halved on while
    ``phi`` still decreases, so that the step ends near the least ``phi`` along ``d`` rather than where the bound
    stopped it (next to a barrier's wall, where Newton then only creeps back out)."""
    if a <= 0.0:
        return 0.0
    p0 = phi(v)
    for _ in range(halvings):
        p = phi(v + a * d)
        if p <= p0 + 1e-4 * a * slope:
            break
        a *= 0.5
    else:
        return 0.0
    return _halved_while_lower(phi, v, d, a, p, halvings) if settle else a


def _halved_while_lower(phi: Callable[[np.ndarray], float], v: np.ndarray, d: np.ndarray, a: float, p: float,
                        halvings: int = LINE_SEARCH_HALVINGS) -> float:
    """``a`` (``phi(v + a d) = p``) halved while ``phi`` still decreases, at most ``halvings`` times."""
    for _ in range(halvings):
        q = phi(v + 0.5 * a * d)
        if not q < p:
            break
        a, p = 0.5 * a, q
    return a


def _model_slope(c: Constraints, cv: float, v: np.ndarray, d: np.ndarray, lin: float, dAd: float) -> Any:
    """``a -> d Phi(dv + a d) / da`` of :meth:`ImplicitIntegrator._friction_newton`'s function: ``lin + a dAd`` from
    the linearised forces, minus ``c_v`` times the friction law's force at ``v + a d`` along ``d``."""
    dc = d[c.contact]

    def g(a: float) -> float:
        return lin + a * dAd - cv * float(np.einsum("ij,ij->", c.friction_force(v + a * d), dc))
    return g


def _segment_root(g: Any, slope: float) -> float:
    """Where a convex function of ``a`` with derivative ``g`` (``g(0) = slope < 0``) is least on ``0 < a <= 1``:
    1 when ``g(1) <= 0``, else the root of ``g`` by regula falsi (Illinois), to :data:`LINE_TOLERANCE` of the
    slope, in at most :data:`LINE_ITERATIONS` evaluations."""
    lo, g_lo, hi, g_hi = 0.0, slope, 1.0, g(1.0)
    if not np.isfinite(g_hi) or g_hi <= 0.0:
        return 1.0
    side = 0
    a = hi
    for _ in range(LINE_ITERATIONS):
        a = (lo * g_hi - hi * g_lo) / (g_hi - g_lo)
        ga = g(a)
        if abs(ga) <= LINE_TOLERANCE * abs(slope):
            break
        if ga > 0:
            hi, g_hi = a, ga
            if side == -1:
                g_lo *= 0.5
            side = -1
        else:
            lo, g_lo = a, ga
            if side == 1:
                g_hi *= 0.5
            side = 1
    return a
