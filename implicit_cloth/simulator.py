"""The user-facing driver: :class:`Simulator` steps a scene, :class:`Trajectory` holds a run."""

from __future__ import annotations

import contextlib
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from . import diagnostics
from .adaptive import AdaptiveStats, StepController
from .backend import threads
from .config.validate import number as _number
from .constraints import Constraints
from .errors import DivergenceError, SceneError, SolverWarning
from .files import save_npz
from .integrators import ImplicitIntegrator, make_integrator
from .interrupt import deferred_interrupt
from .model import Model, State
from .scene import Scene, load_scene, self_collision
from .scene import check_run_length as _run_length
from .solvers import auto_preconditioner


class Trajectory:
    """Kept frames of a run.

    Attributes
    ----------
    positions : (F, N, 3) array
        Vertex positions at each kept frame, m.
    times : (F,) array
        Simulated time of each frame, s.
    faces : (T, 3) int array
        The cloth's triangles.
    report : dict
        Run report: per-frame energies, strain, solver figures and timings,
        plus the integrator, dt, active effects and ``status``.
    """

    def __init__(self, positions: np.ndarray, times: np.ndarray, faces: np.ndarray,
                 report: dict[str, Any] | None = None) -> None:
        self.positions = positions
        self.times = times
        self.faces = faces
        self.report = report if report is not None else {}

    def __len__(self) -> int:
        return len(self.times)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write ``positions``, ``times`` and ``faces`` to a ``.npz`` file (atomically)."""
        return save_npz(path, positions=self.positions, times=self.times, faces=self.faces)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "Trajectory":
        """Read a trajectory written by :meth:`save` (the report is not part of the file)."""
        with np.load(path) as z:
            return cls(z["positions"], z["times"], z["faces"])

    def __repr__(self) -> str:
        return f"Trajectory({len(self)} frames, {self.positions.shape[1]} vertices, status={self.report.get('status')})"


def _frame_steps(n_steps: int, dt: float, duration: float, frame_rate: float) -> np.ndarray:
    """Step indices kept as frames: t = 0, 1/frame_rate, ... and the end, at the nearest step."""
    if frame_rate * dt >= 1.0:
        return np.arange(n_steps + 1)
    k = np.arange(int(math.floor(duration * frame_rate + 1e-9)) + 1)
    steps = np.rint(k / (frame_rate * dt)).astype(np.int64)
    return np.unique(np.clip(np.append(steps, n_steps), 0, n_steps))


class Simulator:
    """Simulate a scene with one of the integrators.

    Parameters
    ----------
    scene : Scene, mapping or path
        The scene (a TOML path is loaded with :func:`~implicit_cloth.load_scene`).
    integrator : str, optional
        One of :data:`~implicit_cloth.INTEGRATORS`; overrides ``simulation.integrator``.
    dt : float, optional
        Time step, s; overrides ``simulation.dt``.
    solver : mapping, optional
        Overrides of the ``[solver]`` table (``tolerance``, ``contact_tolerance``,
        ``max_iterations``, ``preconditioner``, ``newton_iterations``).
    blas_threads : int or None, default 1
        BLAS threads used while stepping (``None`` leaves numpy's setting).
        One thread is faster here: the solver's dot products are short.
    **simulation
        Other ``[simulation]`` overrides (``duration``, ``frame_rate``,
        ``divergence_factor``).

    Examples
    --------
    >>> sim = Simulator(scene, integrator="backward_euler", dt=0.01)
    >>> sim.step(10)
    >>> traj = sim.run(duration=2.0)
    """

    def __init__(self, scene: Scene | Mapping[str, Any] | str | os.PathLike[str], integrator: str | None = None,
                 dt: float | None = None, solver: Mapping[str, Any] | None = None,
                 blas_threads: int | None = 1, **simulation: Any) -> None:
        if isinstance(scene, (str, os.PathLike)):
            scene = load_scene(scene)
        elif not isinstance(scene, Scene):
            scene = Scene.from_dict(scene)
        overrides = dict(simulation)
        if integrator is not None:
            overrides["integrator"] = integrator
        if dt is not None:
            overrides["dt"] = dt
        sections: dict[str, Any] = {"simulation": overrides} if overrides else {}
        if solver is not None:   # Scene.replace checks it is a table (SceneError naming `solver` otherwise)
            sections["solver"] = solver
        if sections:
            scene = scene.replace(**sections)
        self.scene = scene
        sim = scene.data["simulation"]
        self.integrator_name: str = sim["integrator"]
        self.dt: float = sim["dt"]
        with _blas_threads(blas_threads):   # set-up (multigrid hierarchy, coarse factor) on the same threads
            self.model = Model(scene)
            solver_opts = scene.data["solver"]
            if solver_opts.get("preconditioner") == "auto":   # the multigrid for this cloth and its contacts
                linear = not sim["adaptive"]["enabled"] and int(solver_opts.get("newton_iterations", 1)) <= 1
                solver_opts = {**solver_opts, "preconditioner": auto_preconditioner(
                    self.model, bool(scene.data["obstacles"]), self_collision(scene.data), linear)}
            self.integrator = make_integrator(self.integrator_name, self.model, solver_opts)
        x = self.model.rest_positions.copy()
        v = self.model.initial_velocity.copy()
        self.model.apply_pins(x, v, 0.0)
        self.state = State(x, v, 0.0)
        self._pins = Constraints.of_pins(self.model)
        #: the last keyframed step's pins ``(state, h, constraints)`` (:meth:`_step_pins`)
        self._keyed_pins: tuple[State, float, Constraints] | None = None
        #: the last single linearisation without obstacles: (state, h, pins, end velocities), for its retry
        self._linear: tuple[State, float, Constraints, np.ndarray] | None = None
        self.collider: Any = None
        #: whether contact is a barrier energy in the step's one Newton solve (``collision.method = "barrier"``)
        self.barrier = (scene.data["collision"] or {}).get("method", "rounds") == "barrier"
        if self.barrier:
            _check_barrier(scene.data, self.integrator.implicit)
        if scene.data["obstacles"] and self.barrier:
            from .contact import ObstacleContact

            self.collider = ObstacleContact(scene.data["obstacles"], scene.data["collision"], self.model, self.dt)
        elif scene.data["obstacles"]:   # the collision code is imported only for obstacles
            from .collision import Collider

            self.collider = Collider(scene.data["obstacles"], scene.data["collision"], self.model)
        #: self-contact as a barrier in the step's solve (``method = "barrier"`` and ``self_collision = true``)
        self.cloth_contact: Any = None
        if self.barrier and self_collision(scene.data):
            from .contact.cloth import ClothContact

            self.cloth_contact = ClothContact(self.model, scene.data["collision"], self.dt)
        #: self-collision (``[collision] self_collision = true``), else None: its code is imported only then
        self.self_collider: Any = None
        if self_collision(scene.data) and not self.barrier:
            from .selfcontact import SelfCollider

            self.self_collider = SelfCollider(self.model, scene.data["collision"])
        self.last_step: Any = None
        self.blas_threads = blas_threads
        #: adaptive step control (``simulation.adaptive.enabled``), else None
        self.adaptive: StepController | None = None
        if sim["adaptive"]["enabled"]:
            self.adaptive = StepController(self.model, sim["adaptive"], self.integrator.implicit)
        #: energies and strains of states, for the energy balance and the strain bound of every step
        self.measures = self.adaptive.measures if self.adaptive is not None else diagnostics.StepMeasures(self.model)
        self._energy_growth = float(sim["adaptive"]["max_energy_growth"])
        #: whether every step is checked (adaptive stepping, implicit methods, obstacles); else kept frames only
        self._checks_steps = (self.adaptive is not None or self.integrator.implicit or self.collider is not None
                               or self.self_collider is not None or self.cloth_contact is not None)
        #: the strain no step may leave: strain limiting's ``max_strain`` if declared, else adaptive's
        self.strain_bound = float(sim["strain_limit"]["max_strain"] if "strain_limit" in sim
                                  else sim["adaptive"]["max_strain"])
        self.health = Health()
        #: strain limiting (``[simulation.strain_limit]``), else None: Provot's projection after the step, or with
        #: ``method = "barrier"`` a barrier in the step's solve (:attr:`strain_contact`, the same object)
        self.strain_limiter: Any = _strain_limiting(self.model, sim, self.barrier, self.dt)
        self.strain_contact: Any = self.strain_limiter if self.barrier else None

    # ------------------------------------------------------------------ state access
    @property
    def positions(self) -> np.ndarray:
        """Vertex positions (N, 3), m. Assigning sets the state; pins then follow the assigned positions."""
        return self.state.x

    @positions.setter
    def positions(self, x: Any) -> None:
        x = self._checked(x, "positions")
        self.model.set_pin_anchors(x, self.state.t)
        self.state = State(x, self.state.v.copy(), self.state.t)
        self._reset_history()

    @property
    def velocities(self) -> np.ndarray:
        """Vertex velocities (N, 3), m/s. Assigning sets the state (pinned vertices keep their pin velocity)."""
        return self.state.v

    @velocities.setter
    def velocities(self, v: Any) -> None:
        v = self._checked(v, "velocities")
        x = self.state.x.copy()
        self.model.apply_pins(x, v, self.state.t)
        self.state = State(x, v, self.state.t)
        self._reset_history()

    def _reset_history(self) -> None:
        """After the state is assigned: integrator history, suspended adaptive criteria and held contacts are
        forgotten."""
        self.integrator.reset()
        if self.adaptive is not None:
            self.adaptive.reset()
        if self.collider is not None:
            self.collider.reset()

    @property
    def time(self) -> float:
        """Simulated time, s."""
        return self.state.t

    def _checked(self, a: Any, what: str) -> np.ndarray:
        a = np.array(a, dtype=float)
        if a.shape != (self.model.n, 3):
            raise ValueError(f"{what}: must have shape ({self.model.n}, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: must be finite, got {int((~np.isfinite(a)).sum())} non-finite values")
        return a

    # ------------------------------------------------------------------ stepping
    def _substep(self, state: State, h: float, newton: int | None = None) -> tuple[State, Any]:
        """One step of ``h`` from ``state`` (:meth:`_obstacle_substep`), then self-collision if declared (it
        corrects the proposed state after the obstacles, without moving the vertices they hold).

        With an implicit method, the vertices self-collision moved are then prescribed their corrected motion
        and the step is solved again (with the obstacles), so that their neighbours follow within the step
        instead of being left behind by a large step (springs stretched at each correction: energy from
        nowhere); self-collision corrects what that solve proposes.

        A proposal that adaptive stepping would discard as it comes from the solve (its energy balance, strain
        or solve fails, and a Newton redo or a smaller step is left) is returned uncorrected, so discarded and
        redone, only more accurately: at an impact the first attempt at the full step can propose ends 10 cm
        a step away, whose self-collision search alone took 30 s on a 128² crumple. (Self-collision's
        correction could in principle have made such a proposal pass; the redo costs a solve, not accuracy.)
        At the smallest step nothing is skipped.
        """
        new, info = self._obstacle_substep(state, h, newton)
        sc = self.self_collider
        if sc is None:
            return new, info
        if self.adaptive is not None and self.adaptive.redone(state, new, info, h, newton):
            return new, info        # redone (smaller or with Newton) without correcting it first
        resolve = None
        if isinstance(self.integrator, ImplicitIntegrator):
            first = info

            def resolve(idx: np.ndarray, vel: np.ndarray) -> State:
                nonlocal info
                again, info = self._obstacle_substep(state, h, newton, self._step_pins(state, h).with_pins(idx, vel))
                info.absorb(first)
                if info.collision is not None and first.collision is not None:
                    info.collision.t_collision += first.collision.t_collision
                return again

        new = sc.step(state, new, h, self.collider, resolve)
        info.self_work = sc.last_work
        return new, info

    def _step_pins(self, state: State, h: float) -> Constraints:
        """The pins of the step of ``h`` from ``state``: the model's constant ones as they are; keyframed ones
        with this step's velocities (:meth:`Model.pin_velocity_at`: each ends the step on its path), the same
        object for the same ``(state, h)``."""
        if not self.model.pins_keyframed:
            return self._pins
        last = self._keyed_pins
        if last is not None and last[0] is state and last[1] == h:
            return last[2]
        c = Constraints(self._pins.pinned, self.model.pin_velocity_at(state.x, state.t, h))
        self._keyed_pins = (state, h, c)
        return c

    def _obstacle_substep(self, state: State, h: float, newton: int | None = None,
                          pins: Constraints | None = None) -> tuple[State, Any]:
        """One integrator step of ``h`` seconds from ``state``, with contacts and strain limiting if declared.

        The unit that adaptive stepping discards and redoes (with Newton iterations, or a smaller ``h``).
        With obstacles and an implicit method the contacts are constraints of the solve
        (:meth:`Collider.step`); an explicit step is corrected by the geometric response afterwards. Either
        way every substep (and every retry) is collision-free and the adaptive criteria judge the
        corrected state. ``newton``: Newton iterations asked for (None: the solver's setting).
        """
        col = self.collider
        pins = self._step_pins(state, h) if pins is None else pins
        if self.barrier and (col is not None or self.cloth_contact is not None or self.strain_contact is not None):
            return self._barrier_step(state, h, pins)
        if col is not None and self.integrator.implicit:
            return col.step(self.integrator, state, h, pins, self.strain_limiter, newton)
        if isinstance(self.integrator, ImplicitIntegrator):
            new, info = self._implicit_step(state, h, pins, newton)
        else:
            new, info = self.integrator.step(state, h)
        if self.strain_limiter is not None:
            self.strain_limiter.apply(new, h)
        if col is not None and np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v)):
            # last, so that nothing after it moves the cloth into an obstacle; corrects new.x, new.v in place
            info.collision = col.respond(state, new, h)
        return new, info

    def _barrier_step(self, state: State, h: float, pins: Constraints) -> tuple[State, Any]:
        """``collision.method = "barrier"``: detect (a :class:`~implicit_cloth.contact.Contacts` value at the
        step's start), solve (the step's incremental potential with the contact terms, one Newton solve:
        :meth:`~implicit_cloth.integrators.base.ImplicitIntegrator.minimize`), check (the figures the report and
        the energy balance read)."""
        from .collision.context import CollisionInfo

        col, cloth = self.collider, self.cloth_contact
        integ = self.integrator
        assert isinstance(integ, ImplicitIntegrator)
        t0 = time.perf_counter()
        contacts = col.detect(state.x, state.t, h) if col is not None else None
        terms = col.terms(contacts, state.x, state.t, h) if col is not None else []
        if cloth is not None:
            terms.append(cloth.term(state.x))
            friction = cloth.friction(terms[-1], state.x)
            if friction is not None:
                terms.append(friction)
        strain = self.strain_contact.term(state.x) if self.strain_contact is not None else None
        if strain is not None:
            terms.append(strain)
        t_detect = time.perf_counter() - t0
        share = NEWTON_ENERGY_SHARE * self._energy_growth

        # the stored energies at the step's start, once (every Newton iterate's balance books them)
        start = [f.start_energy(state.x) if f.conservative else 0.0 for f in terms]
        stored0 = float(sum(start))

        def stored(x1: np.ndarray) -> float:
            # the larger of the contact potential's stored energies at the step's ends (energy it moves about)
            return max(stored0, float(sum(f.energy(x1) for f in terms if f.conservative)))

        def contact_work(x1: np.ndarray, v1: np.ndarray) -> float:
            # what the barriers gave back (and moving obstacles' work through them and friction)
            return sum(f.step_work(state.x, x1, v1, h) if hasattr(f, "step_work")
                       else e0 - f.energy(x1) for f, e0 in zip(terms, start)
                       if f.conservative or hasattr(f, "step_work"))

        def done(x1: np.ndarray, v1: np.ndarray, decrement: float) -> bool:
            # Newton's next decrease of the step's potential is below a share of the energy balance's allowance,
            # and the iterate creates no energy (its balance, the contacts' work booked as the step books it)
            gain, e_step = self.measures.balance(state, State(x1, v1, state.t + h), h, contact_work(x1, v1))
            return decrement <= share * e_step and gain <= 0.0
        new, info = integ.minimize(state, h, terms, pins, done=done)
        t0 = time.perf_counter()
        if np.all(np.isfinite(new.x)):
            info.contact_work = contact_work(new.x, new.v)
            info.contact_stored = stored(new.x)
            if strain is not None:
                self.strain_contact.count(strain, new.x)
        if col is not None and contacts is not None:
            depth = max((float(col.depths(k, new.x, new.t)[col.free].max(initial=0.0))
                         for k in range(len(col.obstacles))), default=0.0)
            info.collision = CollisionInfo(contacts=len(contacts), resting=terms[0].active(new.x), rounds=1,
                                           max_penetration=depth, solves=info.solves,
                                           t_collision=t_detect + time.perf_counter() - t0)
        return new, info

    def _retry_done(self, state: State, h: float,
                    newton: int | None) -> Callable[[np.ndarray, np.ndarray], bool] | None:
        """For adaptive stepping's Newton retry of the step from ``state`` (``newton`` given): the test that ends
        its iterations once the iterate passes the energy balance, when that is what it is redone for: more
        iterations would not change the verdict. None otherwise."""
        adaptive = self.adaptive
        if newton is None or adaptive is None or adaptive.retry_for != {"energy"}:
            return None

        def done(x1: np.ndarray, v1: np.ndarray) -> bool:
            return adaptive.passes(state, State(x1, v1, state.t + h), h)
        return done

    def _implicit_step(self, state: State, h: float, pins: Constraints, newton: int | None) -> tuple[State, Any]:
        """The integrator's step without obstacles. A step redone with Newton iterations (adaptive stepping's
        energy or strain retry) after its single linearisation from the same state, ``h`` and pins continues
        from that linearisation's end velocities: the Newton iterations' first solve is that linearisation
        (:meth:`~implicit_cloth.integrators.base.ImplicitIntegrator.step`), so solving it again would only
        repeat it."""
        integ = self.integrator
        assert isinstance(integ, ImplicitIntegrator)
        last = self._linear
        self._linear = None
        done = self._retry_done(state, h, newton)
        if (newton is not None and newton > 1 and last is not None and last[0] is state and last[1] == h
                and last[2] is pins):
            new, info = integ.step(state, h, pins, newton=newton - 1, start=last[3], done=done)
            info.newton_iterations += 1
            return new, info
        new, info = integ.step(state, h, pins, newton=newton, done=done)
        if newton is None and integ.newton_iterations == 1 and self.strain_limiter is None:
            self._linear = (state, h, pins, new.v.copy())
        return new, info

    def _advance(self) -> Any:
        with np.errstate(over="ignore", invalid="ignore"):   # a blow-up is reported below, not warned
            if self.adaptive is None:
                old = self.state
                new, info = self._substep(old, self.dt)
                if self._checks_steps and np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v)):
                    gain, e_step = self.measures.balance(old, new, self.dt, info.external_work, info.contact_stored)
                    if gain > self._energy_growth * e_step:
                        self.health.add("energy", new.t, gain)
            else:
                new, info = self.adaptive.advance(self.state, self.dt, self._substep)
        if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
            raise _NonFinite(f"non-finite state at t={new.t:.6g} s")
        if self._checks_steps:
            self._check_strain(self.state, new)
        self.state = new
        self.last_step = info
        return info

    def _check_strain(self, old: State, s: State) -> None:
        """Record a step that left a spring or a membrane triangle beyond the scene's strain bound (strain
        limiting's ``max_strain`` if declared, else adaptive's) longer than it found it (a spring relaxing from a
        stretch it was given is not the step's doing). A triangle's strain is its largest principal strain
        (:meth:`~implicit_cloth.diagnostics.StepMeasures.strains`)."""
        strain = self.measures.strains(s)
        if strain is None or not len(strain):
            return
        top = float(strain.max())
        self.health.max_strain = max(self.health.max_strain, top)
        bound = self.strain_bound * (1.0 + STRAIN_TOLERANCE) + STRAIN_TOLERANCE
        if top > bound:
            before = self.measures.strains(old)
            grew = (strain > bound) & (strain > before)
            if np.any(grew):
                self.health.add("strain", s.t, float(strain[grew].max()))

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of ``dt``.

        Raises
        ------
        DivergenceError
            If a step produces a non-finite state (the state stays at the last finite step).
        KeyboardInterrupt
            On Ctrl-C (SIGINT), taken between steps as in :meth:`run` (:mod:`implicit_cloth.interrupt`): the state
            is the last whole step's.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n: must be an integer >= 0, got {n!r}")
        with _blas_threads(self.blas_threads), deferred_interrupt() as stop:   # Ctrl-C between steps only
            for _ in range(int(n)):
                stop.check()
                try:
                    self._advance()
                except _NonFinite as exc:
                    raise DivergenceError(str(exc)) from None

    def run(self, duration: float | None = None, frame_rate: float | None = None,
            progress: bool = False, on_frame: Callable[[State], None] | None = None) -> Trajectory:
        """Simulate ``duration`` seconds from the current state, keeping frames.

        Frames are kept at ``t0 + k / frame_rate`` for ``k = 0, 1, ...`` up to and
        including ``t0 + duration`` (at the nearest step when ``dt`` does not
        divide them; every step when ``frame_rate >= 1/dt``); ``on_frame(state)``, if given, is called
        with the state (positions, velocities, time; not to be modified) at every kept frame. The report's
        ``status`` is ``"ok"`` when every step met the energy balance and the
        strain bound, ``"warning"`` otherwise (``report["health"]`` says which
        criterion, when first and by how much).

        Raises
        ------
        SceneError
            If ``duration`` or ``frame_rate`` is not a finite number > 0, or the run
            would exceed the scene's step or frame limits (same messages as the
            ``[simulation]`` table).
        DivergenceError
            On a non-finite state or energy growth beyond the divergence bound
            (:mod:`implicit_cloth.diagnostics`); ``err.trajectory`` holds the
            frames kept before it, with ``report["status"] == "diverged"``.
        """
        sim = self.scene.data["simulation"]
        duration = sim["duration"] if duration is None else duration
        frame_rate = sim["frame_rate"] if frame_rate is None else frame_rate
        duration = _number("simulation.duration", duration, lo=0.0, lo_open=True)
        frame_rate = _number("simulation.frame_rate", frame_rate, lo=0.0, lo_open=True)
        _run_length({"dt": self.dt, "duration": duration, "frame_rate": frame_rate})
        rec = _Recorder(self, duration, frame_rate, sim.get("divergence_factor", diagnostics.DEFAULT_DIVERGENCE_FACTOR),
                        on_frame)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=rec.n_steps, unit="step", desc=f"{self.integrator_name} dt={self.dt:g}", leave=False)
        try:
            with _blas_threads(self.blas_threads), deferred_interrupt() as stop:   # Ctrl-C between steps only
                for s in range(1, rec.n_steps + 1):
                    stop.check()
                    ts = time.perf_counter()
                    try:
                        info = self._advance()
                    except _NonFinite as exc:
                        rec.diverge(f"{exc} (step {s} of {rec.n_steps})")
                        break
                    if not rec.after_step(s, info, ts):
                        break
                    if bar is not None:
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        traj = rec.trajectory()
        if traj.report["status"] == "diverged":
            raise DivergenceError(traj.report["reason"], traj)
        return traj


#: Relative slack of the strain bound (the solver's and the limiter's tolerances).
STRAIN_TOLERANCE = 1e-3
#: A barrier step's Newton iterations stop once the next one would lower the step's potential by less than this
#: share of the energy balance's allowance (``adaptive.max_energy_growth`` of the energy the step moves about)
#: and the iterate creates no energy.
NEWTON_ENERGY_SHARE = 1.0

#: Report criteria of the run health, in the order they are listed.
HEALTH_CRITERIA: tuple[str, ...] = ("energy", "strain", "failsafe", "self_collision", "solver")


def _strain_limiting(model: Model, sim: Mapping[str, Any], barrier: bool, dt: float) -> Any:
    """The scene's strain limiting (``[simulation.strain_limit]``; None without): a barrier term of the step's
    solve with ``collision.method = "barrier"`` (:class:`~implicit_cloth.contact.strain.StrainLimit`, whose
    settings and counts report as the projection's), else Provot's projection. Imported only when declared."""
    if "strain_limit" not in sim:
        return None
    if barrier:
        from .contact.strain import StrainLimit

        return StrainLimit(model, sim["strain_limit"], dt)
    from .strain_limit import StrainLimiter

    return StrainLimiter(model, sim["strain_limit"])


def _check_barrier(data: Mapping[str, Any], implicit: bool) -> None:
    """What ``collision.method = "barrier"`` does not cover yet: a clear error naming the key."""
    if not implicit:
        raise SceneError(f"collision.method: 'barrier' minimises the implicit step's potential; it needs an "
                         f"implicit integrator (backward_euler, bdf2), got {data['simulation']['integrator']!r}")


class Health:
    """What went wrong in a run, per criterion: how often, when first, the worst amount.

    ``energy``: a step gained energy beyond the balance (J); ``strain``: a step ended with a spring beyond
    the scene's strain bound (the strain); ``failsafe``: the collision fail-safe froze vertices (how many);
    ``solver``: a linear solve did not reach its tolerance (the residual).
    """

    UNITS = {"energy": "J", "strain": "", "failsafe": "vertices", "solver": ""}

    def __init__(self) -> None:
        self.events: dict[str, dict[str, float]] = {}
        self.max_strain = 0.0

    def add(self, criterion: str, t: float, amount: float, count: int = 1) -> None:
        ev = self.events.setdefault(criterion, {"count": 0, "first_time": float(t), "worst": float(amount)})
        ev["count"] += count
        ev["first_time"] = min(ev["first_time"], float(t))
        ev["worst"] = max(ev["worst"], float(amount))

    def messages(self, strain_bound: float, energy_growth: float) -> list[dict[str, Any]]:
        what = {
            "energy": lambda e: (f"energy created: {e['count']} steps gained more than the pins', wind's and "
                                 f"obstacles' work plus {energy_growth:g} x the step's energy, first at "
                                 f"t={e['first_time']:.4g} s, at worst {e['worst']:.3g} J"),
            "strain": lambda e: (f"strain bound {strain_bound:g} exceeded in {e['count']} steps, first at "
                                 f"t={e['first_time']:.4g} s, at worst {e['worst']:.3g}"),
            "failsafe": lambda e: (f"collision fail-safe fired in {e['count']} steps (vertices frozen to an "
                                   f"obstacle), first at t={e['first_time']:.4g} s"),
            "self_collision": lambda e: (f"self-collision's impact zones left {e['worst']:g} impacts unresolved in "
                                         f"{e['count']} steps, first at t={e['first_time']:.4g} s"),
            "solver": lambda e: (f"linear solve unconverged in {e['count']} steps, first at "
                                 f"t={e['first_time']:.4g} s, largest residual {e['worst']:.3g}"),
        }
        return [{"criterion": c, **self.events[c], "message": what[c](self.events[c])}
                for c in HEALTH_CRITERIA if c in self.events]


class _Recorder:
    """Kept frames, run totals and the report of one :meth:`Simulator.run`."""

    FRAME_KEYS = ("time", "kinetic", "gravity", "springs", "potential", "total", "pin_work", "max_strain",
                  "solver_iterations", "solver_residual", "min_step", "t_assembly", "t_setup", "t_solve", "t_other")

    def __init__(self, sim: "Simulator", duration: float, frame_rate: float, factor: float,
                 on_frame: Callable[[State], None] | None = None) -> None:
        self.sim = sim
        self.on_frame = on_frame
        self.duration, self.frame_rate, self.factor = duration, frame_rate, factor
        model, st = sim.model, sim.state
        self.dt = sim.dt
        self.n_steps = max(1, int(round(duration / self.dt)))
        self.keep = _frame_steps(self.n_steps, self.dt, duration, frame_rate)
        self.e0 = diagnostics.measure(model, st.x, st.v, st.t)
        self.scale = diagnostics.energy_scale(model, st.x, st.v)
        self.bound = factor * self.scale
        sim.health = Health()
        if sim.adaptive is not None:   # counters start afresh
            sim.adaptive.stats = AdaptiveStats()
            sim.adaptive.window_min_step = math.inf
        if sim.strain_limiter is not None:
            sim.strain_limiter.reset_stats()
        if sim.self_collider is not None:
            sim.self_collider.totals.reset(st)
        self.pins_keyed = model.pins_keyframed    # keyframed pins: work booked per step from the two states
        self.pins_move = bool(len(model.pinned)) and bool(np.any(model.pin_velocity)) and not self.pins_keyed
        self.pin_work, self.pin_p = 0.0, diagnostics.pin_power(model, st.x, st.v, st.t)
        self.pin_last = (st.copy(), diagnostics.pin_state(model, st.x, st.v, st.t)) if self.pins_keyed else None
        #: soft pins with moving targets: their targets' work (trapezoid of their power) is the pins' work too
        self.soft = next((e for e in model.effects if e.name == "pin_springs"), None)
        self.soft_p = self.soft.power(st.x, st.v, st.t) if self.soft is not None else 0.0
        self.frames: dict[str, list[float]] = {k: [] for k in self.FRAME_KEYS}
        self.col = _CollisionTotals() if sim.collider is not None else None
        if self.col is not None:
            self.frames["t_collision"] = []
        self.positions: list[np.ndarray] = []
        self.totals = {"steps": 0, "iterations": 0, "max_iterations": 0, "max_residual": 0.0,
                       "unconverged_steps": 0, "solves": 0, "max_newton": 0, "attempted_solves": 0,
                       "attempted_iterations": 0}
        self.acc = {"it": 0, "res": 0.0, "t_assembly": 0.0, "t_setup": 0.0, "t_solve": 0.0, "t_other": 0.0}
        self.status, self.reason = "ok", ""
        self.next_frame = 1
        self.wall0 = time.perf_counter()
        self.keep_frame(self.e0)

    def keep_frame(self, m: dict[str, float]) -> None:
        sim, fr, acc = self.sim, self.frames, self.acc
        if self.on_frame is not None:
            self.on_frame(sim.state)
        self.positions.append(sim.state.x.copy())
        fr["time"].append(sim.state.t)
        for k in ("kinetic", "gravity", "springs", "potential", "total", "max_strain"):
            fr[k].append(m[k])
        fr["pin_work"].append(self.pin_work)
        fr["solver_iterations"].append(acc["it"])
        fr["solver_residual"].append(acc["res"])
        fr["min_step"].append(self.dt)
        ad = sim.adaptive
        if ad is not None and math.isfinite(ad.window_min_step):
            fr["min_step"][-1] = ad.window_min_step
            ad.window_min_step = math.inf
        for k in ("t_assembly", "t_setup", "t_solve", "t_other"):
            fr[k].append(acc[k])
            acc[k] = 0.0
        if self.col is not None:
            fr["t_collision"].append(self.col.frame_time)
            self.col.frame_time = 0.0
        acc["it"], acc["res"] = 0, 0.0

    def diverge(self, reason: str) -> None:
        self.status, self.reason = "diverged", reason

    def after_step(self, s: int, info: Any, ts: float) -> bool:
        """Book step ``s``; keep a frame when due. False when the run diverged."""
        sim, model, tot, acc = self.sim, self.sim.model, self.totals, self.acc
        if self.pins_move:   # trapezoidal work of the pins over this step, and through self-contact
            p_new = diagnostics.pin_power(model, sim.state.x, sim.state.v, sim.state.t)
            self.pin_work += 0.5 * self.dt * (self.pin_p + p_new) + info.self_work
            self.pin_p = p_new
        elif self.pin_last is not None:
            new = sim.state
            s1 = diagnostics.pin_state(model, new.x, new.v, new.t)
            self.pin_work += diagnostics.pin_step_work(model, self.pin_last[0], new, self.pin_last[1], s1) \
                + info.self_work
            self.pin_last = (new.copy(), s1)
        if self.soft is not None:
            p_soft = self.soft.power(sim.state.x, sim.state.v, sim.state.t)
            self.pin_work += 0.5 * self.dt * (self.soft_p + p_soft)
            self.soft_p = p_soft
        tot["steps"] += 1
        tot["iterations"] += info.iterations
        tot["max_iterations"] = max(tot["max_iterations"], info.iterations)
        tot["max_residual"] = max(tot["max_residual"], info.residual)
        tot["solves"] += info.solves
        tot["attempted_solves"] += info.attempted_solves
        tot["attempted_iterations"] += info.attempted_iterations
        tot["max_newton"] = max(tot["max_newton"], info.newton_iterations)
        if not info.converged:
            tot["unconverged_steps"] += 1
            sim.health.add("solver", sim.state.t, info.residual)
        acc["it"] = max(acc["it"], info.iterations)
        acc["res"] = max(acc["res"], info.residual)
        acc["t_assembly"] += info.t_assembly
        acc["t_setup"] += info.t_setup
        acc["t_solve"] += info.t_solve
        if self.col is not None:
            self.col.add(info.collision)
            acc["t_other"] -= info.collision.t_collision
            if info.collision.failsafe:
                sim.health.add("failsafe", sim.state.t, info.collision.failsafe)
        frame = self.next_frame < len(self.keep) and s == self.keep[self.next_frame]
        m = diagnostics.measure(model, sim.state.x, sim.state.v, sim.state.t) if frame else None
        acc["t_other"] += time.perf_counter() - ts - info.t_assembly - info.t_setup - info.t_solve
        if m is None:
            return True
        growth = m["total"] - self.e0["total"] - self.pin_work - (self.col.work if self.col is not None else 0.0)
        if growth > self.bound:
            self.diverge(f"energy grew by {growth:.3g} J (beyond the pins' and obstacles' work) "
                         f"at t={sim.state.t:.6g} s (step {s} of {self.n_steps}), beyond the bound {self.bound:.3g} J "
                         f"= {self.factor:g} x energy scale {self.scale:.3g} J")
            return False
        if not sim._checks_steps and m["max_strain"] > sim.strain_bound * (1 + STRAIN_TOLERANCE) + STRAIN_TOLERANCE:
            sim.health.add("strain", sim.state.t, m["max_strain"])
        self.keep_frame(m)
        self.next_frame += 1
        return True

    def trajectory(self) -> Trajectory:
        sim = self.sim
        report = self.report(time.perf_counter() - self.wall0)
        return Trajectory(np.array(self.positions), np.array(self.frames["time"]), sim.model.faces.copy(), report)

    def report(self, wall: float) -> dict[str, Any]:
        sim, model, fr, tot = self.sim, self.sim.model, self.frames, self.totals
        health = sim.health
        if sim.adaptive is not None:
            for c, ev in sim.adaptive.stats.forced_events.items():
                if c in ("energy", "strain"):
                    health.add(c, ev["first_time"], ev["worst"], int(ev["count"]))
        self_report = sim.self_collider.report(sim.state, health) if sim.self_collider is not None else None
        warnings_ = health.messages(sim.strain_bound, sim._energy_growth)
        status, reason = self.status, self.reason
        if status == "ok" and warnings_:
            status, reason = "warning", "; ".join(w["message"] for w in warnings_)
        report: dict[str, Any] = {
            "status": status,
            "reason": reason,
            "health": warnings_,
            "integrator": sim.integrator_name,
            "dt": self.dt,
            "duration": self.duration,
            "frame_rate": self.frame_rate,
            "effects": list(model.effect_names),
            "n_vertices": model.n,
            **({"pieces": [{"vertices": list(vr), "faces": list(fr)}
                           for vr, fr in zip(model.pieces, model.piece_faces)]}
               if isinstance(sim.scene.data["cloth"], list) else {}),
            "n_springs": {k: sl.stop - sl.start for k, sl in model.springs.kinds.items()} if model.springs else {},
            "n_pinned": int(len(model.pinned)),
            "total_mass": model.total_mass,
            "steps": tot["steps"],
            "solver": None,
            "divergence_bound": {"factor": self.factor, "energy_scale": self.scale, "bound": self.bound},
            "energy_balance": {"max_energy_growth": sim._energy_growth, "checked": "every step" if sim._checks_steps
                               else "kept frames (divergence bound only)"},
            "wall_time": wall,
            "timing": {k: float(np.sum(fr[k])) for k in ("t_assembly", "t_setup", "t_solve", "t_other")},
            "frames": fr,
            "adaptive": None,
            "strain_limit": None,
        }
        if sim.adaptive is not None:
            a, st = sim.adaptive, sim.adaptive.stats
            report["adaptive"] = {
                "max_halvings": a.max_halvings, "grow_after": a.grow_after, "max_strain": a.max_strain,
                "max_energy_growth": a.max_energy_growth, "retry_unconverged": a.retry_unconverged,
                "newton_iterations": a.newton_iterations,
                "substeps": st.substeps, "retries": st.retries, "newton_retries": st.newton_retries,
                "forced": st.forced, "failures": dict(st.failures),
                "min_step": st.min_step if math.isfinite(st.min_step) else self.dt,
                "substeps_per_step": st.substeps / max(tot["steps"], 1),
            }
        if sim.strain_limiter is not None:
            stats = dict(sim.strain_limiter.stats)
            if sim._checks_steps:   # after the whole step (collisions included), not only after limiting
                stats["max_strain_after"] = health.max_strain
            report["strain_limit"] = {"max_strain": sim.strain_limiter.max_strain,
                                      "max_compression": sim.strain_limiter.max_compression,
                                      "iterations": sim.strain_limiter.iterations,
                                      "tethers": sim.strain_limiter.n_tethers,
                                      "method": "barrier" if sim.strain_contact is not None else "projection",
                                      **stats}
        if self.col is not None:
            report["timing"]["t_collision"] = self.col.time
            report["collision"] = self.col.report(sim.collider)
        if self_report is not None:
            report["self_collision"] = self_report
            report["timing"]["t_self_collision"] = self_report["time"]
        integ = sim.integrator
        if isinstance(integ, ImplicitIntegrator):
            n = max(tot["steps"], 1)
            report["solver"] = {
                "tolerance": integ.tolerance,
                "contact_tolerance": integ.contact_tolerance,
                "max_iterations_allowed": integ.max_iterations,
                "preconditioner": integ.precond.name,
                "cycle": getattr(integ.precond, "cycle", None),
                # which implementation ran the preconditioned CG: "numba" (the default) or "numpy"
                "accelerator": getattr(integ.precond, "accelerator", "numpy"),
                "newton_iterations": integ.newton_iterations,
                "mean_iterations": tot["iterations"] / n,
                "max_iterations": tot["max_iterations"],
                "max_residual": tot["max_residual"],
                "unconverged_steps": tot["unconverged_steps"],
                "mean_solves": tot["solves"] / n,
                # every solve and CG iteration made, those of the attempts adaptive stepping discarded included
                "mean_attempted_solves": tot["attempted_solves"] / n,
                "mean_attempted_iterations": tot["attempted_iterations"] / n,
                "max_newton_iterations": tot["max_newton"],
                "threads": threads() if getattr(integ.precond, "compiled", False) else 1,
                "blas_threads": sim.blas_threads,
            }
            layer = _threading_layer(integ.precond)
            if layer is not None:                    # (the numpy path, or no parallel region ran: left out)
                report["solver"]["threading_layer"] = layer
            if getattr(integ.precond, "damped", False):   # a breakdown protected the multigrid (left out: none)
                report["solver"]["smoothers_damped"] = True
            if tot["unconverged_steps"]:
                warnings.warn(
                    f"the linear solver did not reach tolerance {integ.tolerance:g}"
                    + (f" ({integ.contact_tolerance:g} in steps with contacts)"
                       if integ.contact_tolerance < integ.tolerance
                       and (sim.collider is not None or sim.self_collider is not None) else "") + " in "
                    f"{tot['unconverged_steps']} of {tot['steps']} steps (max residual "
                    f"{tot['max_residual']:.3g}); raise solver.max_iterations or reduce dt",
                    SolverWarning, stacklevel=4)
        return report


class _CollisionTotals:
    """Run totals of the collision stage (the report's "collision" section)."""

    def __init__(self) -> None:
        self.steps = self.contacts = self.candidates = self.failsafe_steps = self.failsafe_vertices = 0
        self.max_resting = 0
        self.max_penetration = 0.0
        self.time = self.frame_time = 0.0
        self.toi = math.inf
        self.work = 0.0
        self.solves = self.fallback = 0

    def add(self, c: Any) -> None:
        self.steps += 1
        self.contacts += c.contacts
        self.candidates += c.candidates
        self.max_resting = max(self.max_resting, c.resting)
        self.failsafe_steps += int(c.failsafe > 0)
        self.failsafe_vertices += c.failsafe
        self.max_penetration = max(self.max_penetration, c.max_penetration)
        self.time += c.t_collision
        self.frame_time += c.t_collision
        self.work += c.work
        self.solves += c.solves
        self.fallback += c.fallback
        if c.toi == c.toi:   # not nan
            self.toi = min(self.toi, c.toi)

    def report(self, collider: Any) -> dict[str, Any]:
        n = max(self.steps, 1)
        return {
            "obstacles": [o.shape.name for o in collider.obstacles],
            "thickness": collider.thickness,
            "contacts": self.contacts,
            "mean_contacts": self.contacts / n,
            "candidates": self.candidates,
            "mean_candidates": self.candidates / n,
            "max_resting_contacts": self.max_resting,
            "earliest_toi": self.toi if math.isfinite(self.toi) else None,
            "max_penetration": self.max_penetration,
            "failsafe_steps": self.failsafe_steps,
            "failsafe_vertices": self.failsafe_vertices,
            # implicit methods: linear solves per step (one, plus one per round that found new contacts, plus
            # Newton iterations), and the corrections the geometric response made after them
            "mean_solves": self.solves / n,
            "fallback_corrections": self.fallback,
            "work": self.work,
            "time": self.time,
            "mean_time_per_step": self.time / n,
        }


_CONTROLLER: Any = None


def _threading_layer(precond) -> str | None:
    """numba's threading layer the compiled solver's parallel regions ran on (None: numpy, or none ran)."""
    if not getattr(precond, "compiled", False):
        return None
    from .kernels import layer

    return layer.current()


def _blas_threads(n: int | None):
    """Context limiting BLAS threads to ``n`` while setting up and stepping (None: leave them as they are).

    Both NumPy's and SciPy's own OpenBLAS (loaded with ``scipy.linalg``) are limited.

    The solver's many short dot products ran 3-10x slower with OpenBLAS's
    default two threads than with one on a 2-core machine (and a 64x64 step
    1.2x slower), so stepping uses one BLAS thread by default.
    """
    global _CONTROLLER
    if n is None:
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        import scipy.linalg  # noqa: F401  (loads SciPy's own OpenBLAS first, so that the controller sees it)
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=n, user_api="blas")


class _NonFinite(Exception):
    """Internal: a step produced NaN or inf (the state was not committed)."""
