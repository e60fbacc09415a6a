"""The user-facing driver: :class:`Simulator` steps a scene, :class:`Trajectory` holds a run."""

from __future__ import annotations

import contextlib
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from . import diagnostics
from .adaptive import AdaptiveStats, StepController
from .errors import DivergenceError, SolverWarning
from .integrators import make_integrator
from .files import save_npz
from .interrupt import deferred_interrupt
from .model import Model, State
from .config.validate import number as _number
from .scene import Scene, load_scene
from .scene import check_run_length as _run_length


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
        Overrides of the ``[solver]`` table (``tolerance``, ``max_iterations``,
        ``preconditioner``).
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
            self.integrator = make_integrator(self.integrator_name, self.model, scene.data["solver"])
        x = self.model.rest_positions.copy()
        v = np.broadcast_to(np.asarray(scene.data["cloth"]["velocity"], dtype=float), x.shape).copy()
        self.model.apply_pins(x, v, 0.0)
        self.state = State(x, v, 0.0)
        self.collider: Any = None
        if scene.data["obstacles"]:   # fcl and the collision code are imported only for obstacles
            from .collision import Collider

            self.collider = Collider(scene.data["obstacles"], scene.data["collision"], self.model)
        self.last_step: Any = None
        self.blas_threads = blas_threads
        #: adaptive step control (``simulation.adaptive.enabled``), else None
        self.adaptive: StepController | None = None
        if sim["adaptive"]["enabled"]:
            scale = diagnostics.energy_scale(self.model, x, v, sim["duration"])
            self.adaptive = StepController(self.model, sim["adaptive"], scale)
        #: Provot strain limiting (``[simulation.strain_limit]``), else None
        self.strain_limiter: Any = None
        if "strain_limit" in sim:
            from .strain_limit import StrainLimiter   # only scenes that declare it import it

            self.strain_limiter = StrainLimiter(self.model, sim["strain_limit"])

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
        """After the state is assigned: integrator history, suspended adaptive criteria and resting contacts are forgotten."""
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
    def _substep(self, state: State, h: float) -> tuple[State, Any]:
        """One integrator step of ``h`` seconds from ``state``, then strain limiting if declared.

        The unit that adaptive stepping discards and redoes with a smaller ``h``: with obstacles, the resting
        contacts enter the solve as constraints and the collision response corrects the result, so every
        substep (and every retry) is collision-free and the adaptive criteria judge the corrected state.
        """
        if self.collider is not None:
            self.collider.constrain(self.integrator, state)
        new, info = self.integrator.step(state, h)
        if self.collider is not None:
            work = self.collider.constraint_work(self.integrator, state.v, new.v)
        if self.strain_limiter is not None:
            self.strain_limiter.apply(new, h)
        if self.collider is not None and np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v)):
            # last, so that nothing after it moves the cloth into an obstacle; corrects new.x, new.v in place
            # (BDF2 keeps them as history)
            e_before = diagnostics.total_energy(self.model, new.x, new.v)
            info.collision = self.collider.respond(state, new, h, self.integrator)
            info.collision.work = work + diagnostics.total_energy(self.model, new.x, new.v) - e_before
        return new, info

    def _advance(self) -> Any:
        with np.errstate(over="ignore", invalid="ignore"):   # a blow-up is reported below, not warned
            if self.adaptive is None:
                new, info = self._substep(self.state, self.dt)
            else:
                new, info = self.adaptive.advance(self.state, self.dt, self._substep)
        if not (np.all(np.isfinite(new.x)) and np.all(np.isfinite(new.v))):
            raise _NonFinite(f"non-finite state at t={new.t:.6g} s")
        self.state = new
        self.last_step = info
        return info

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of ``dt``.

        Raises
        ------
        DivergenceError
            If a step produces a non-finite state (the state stays at the last finite step).
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n: must be an integer >= 0, got {n!r}")
        with _blas_threads(self.blas_threads):
            for _ in range(int(n)):
                try:
                    self._advance()
                except _NonFinite as exc:
                    raise DivergenceError(str(exc)) from None

    def run(self, duration: float | None = None, frame_rate: float | None = None,
            progress: bool = False) -> Trajectory:
        """Simulate ``duration`` seconds from the current state, keeping frames.

        Frames are kept at ``t0 + k / frame_rate`` for ``k = 0, 1, ...`` up to and
        including ``t0 + duration`` (at the nearest step when ``dt`` does not
        divide them; every step when ``frame_rate >= 1/dt``).

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
        factor = sim.get("divergence_factor", diagnostics.DEFAULT_DIVERGENCE_FACTOR)
        dt = self.dt
        n_steps = max(1, int(round(duration / dt)))
        keep = _frame_steps(n_steps, dt, duration, frame_rate)
        model = self.model
        e0 = diagnostics.measure(model, self.state.x, self.state.v)
        scale = diagnostics.energy_scale(model, self.state.x, self.state.v, n_steps * dt)
        bound = factor * scale
        if self.adaptive is not None:   # the energy criterion uses this run's scale; counters start afresh
            self.adaptive.energy_scale = scale
            self.adaptive.stats = AdaptiveStats()
            self.adaptive.window_min_step = math.inf
        if self.strain_limiter is not None:
            self.strain_limiter.reset_stats()

        pins_move = bool(len(model.pinned)) and bool(np.any(model.pin_velocity))
        pin_work, pin_p = 0.0, diagnostics.pin_power(model, self.state.x, self.state.v, self.state.t)
        frames: dict[str, list[float]] = {k: [] for k in (
            "time", "kinetic", "gravity", "springs", "potential", "total", "pin_work", "max_strain",
            "solver_iterations", "solver_residual", "min_step", "t_assembly", "t_setup", "t_solve", "t_other")}
        col = _CollisionTotals() if self.collider is not None else None
        if col is not None:
            frames["t_collision"] = []
        positions: list[np.ndarray] = []
        totals = {"steps": 0, "iterations": 0, "max_iterations": 0, "max_residual": 0.0, "unconverged_steps": 0}
        acc = {"it": 0, "res": 0.0, "t_assembly": 0.0, "t_setup": 0.0, "t_solve": 0.0, "t_other": 0.0}

        def keep_frame(m: dict[str, float]) -> None:
            positions.append(self.state.x.copy())
            frames["time"].append(self.state.t)
            for k in ("kinetic", "gravity", "springs", "potential", "total", "max_strain"):
                frames[k].append(m[k])
            frames["pin_work"].append(pin_work)
            frames["solver_iterations"].append(acc["it"])
            frames["solver_residual"].append(acc["res"])
            frames["min_step"].append(dt)
            if self.adaptive is not None and math.isfinite(self.adaptive.window_min_step):
                frames["min_step"][-1] = self.adaptive.window_min_step
                self.adaptive.window_min_step = math.inf
            for k in ("t_assembly", "t_setup", "t_solve", "t_other"):
                frames[k].append(acc[k])
                acc[k] = 0.0
            if col is not None:
                frames["t_collision"].append(col.frame_time)
                col.frame_time = 0.0
            acc["it"], acc["res"] = 0, 0.0

        status, reason = "ok", ""
        wall0 = time.perf_counter()
        keep_frame(e0)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=n_steps, unit="step", desc=f"{self.integrator_name} dt={dt:g}", leave=False)
        next_frame = 1
        stack = contextlib.ExitStack()
        try:
            stack.enter_context(_blas_threads(self.blas_threads))
            stop = stack.enter_context(deferred_interrupt())   # Ctrl-C raised between steps, not in numba code
            for s in range(1, n_steps + 1):
                stop.check()
                ts = time.perf_counter()
                try:
                    info = self._advance()
                except _NonFinite as exc:
                    status, reason = "diverged", f"{exc} (step {s} of {n_steps})"
                    break
                if pins_move:   # trapezoidal work of the pins over this step
                    p_new = diagnostics.pin_power(model, self.state.x, self.state.v, self.state.t)
                    pin_work += 0.5 * dt * (pin_p + p_new)
                    pin_p = p_new
                totals["steps"] += 1
                totals["iterations"] += info.iterations
                totals["max_iterations"] = max(totals["max_iterations"], info.iterations)
                totals["max_residual"] = max(totals["max_residual"], info.residual)
                totals["unconverged_steps"] += int(not info.converged)
                acc["it"] = max(acc["it"], info.iterations)
                acc["res"] = max(acc["res"], info.residual)
                acc["t_assembly"] += info.t_assembly
                acc["t_setup"] += info.t_setup
                acc["t_solve"] += info.t_solve
                if col is not None:
                    col.add(info.collision)
                    acc["t_other"] -= info.collision.t_collision
                if next_frame < len(keep) and s == keep[next_frame]:
                    m = diagnostics.measure(model, self.state.x, self.state.v)
                    growth = m["total"] - e0["total"] - pin_work - (col.work if col is not None else 0.0)
                    if growth > bound:
                        status = "diverged"
                        reason = (f"energy grew by {growth:.3g} J (beyond the pins' and obstacles' work) "
                                  f"at t={self.state.t:.6g} s "
                                  f"(step {s} of {n_steps}), beyond the bound {bound:.3g} J "
                                  f"= {factor:g} x energy scale {scale:.3g} J")
                        break
                    acc["t_other"] += time.perf_counter() - ts - info.t_assembly - info.t_setup - info.t_solve
                    keep_frame(m)
                    next_frame += 1
                else:
                    acc["t_other"] += time.perf_counter() - ts - info.t_assembly - info.t_setup - info.t_solve
                if bar is not None:
                    bar.update(1)
        finally:
            stack.close()
            if bar is not None:
                bar.close()
        wall = time.perf_counter() - wall0

        report = {
            "status": status,
            "reason": reason,
            "integrator": self.integrator_name,
            "dt": dt,
            "duration": duration,
            "frame_rate": frame_rate,
            "effects": list(model.effect_names),
            "n_vertices": model.n,
            "n_springs": {k: sl.stop - sl.start for k, sl in model.springs.kinds.items()} if model.springs else {},
            "n_pinned": int(len(model.pinned)),
            "total_mass": model.total_mass,
            "steps": totals["steps"],
            "solver": None,
            "divergence_bound": {"factor": factor, "energy_scale": scale, "bound": bound},
            "wall_time": wall,
            "timing": {k: float(np.sum(frames[k])) for k in ("t_assembly", "t_setup", "t_solve", "t_other")},
            "frames": frames,
            "adaptive": None,
            "strain_limit": None,
        }
        if self.adaptive is not None:
            a, st = self.adaptive, self.adaptive.stats
            report["adaptive"] = {
                "max_halvings": a.max_halvings, "grow_after": a.grow_after, "max_strain": a.max_strain,
                "max_energy_growth": a.max_energy_growth, "retry_unconverged": a.retry_unconverged,
                "substeps": st.substeps, "retries": st.retries, "forced": st.forced,
                "failures": dict(st.failures), "min_step": st.min_step if math.isfinite(st.min_step) else dt,
            }
        if self.strain_limiter is not None:
            report["strain_limit"] = {"max_strain": self.strain_limiter.max_strain,
                                      "iterations": self.strain_limiter.iterations, **self.strain_limiter.stats}
        if col is not None:
            report["timing"]["t_collision"] = col.time
            report["collision"] = col.report(self.collider)
        if self.integrator.implicit:
            n = max(totals["steps"], 1)
            report["solver"] = {
                "tolerance": self.integrator.tolerance,
                "max_iterations_allowed": self.integrator.max_iterations,
                "preconditioner": self.integrator.precond.name,
                # which implementation ran the preconditioned CG: "numba" (the fast extra) or "numpy"
                "accelerator": getattr(self.integrator.precond, "accelerator", "numpy"),
                "mean_iterations": totals["iterations"] / n,
                "max_iterations": totals["max_iterations"],
                "max_residual": totals["max_residual"],
                "unconverged_steps": totals["unconverged_steps"],
            }
            if totals["unconverged_steps"]:
                warnings.warn(
                    f"the linear solver did not reach tolerance {self.integrator.tolerance:g} in "
                    f"{totals['unconverged_steps']} of {totals['steps']} steps (max residual "
                    f"{totals['max_residual']:.3g}); raise solver.max_iterations or reduce dt",
                    SolverWarning, stacklevel=2)
        traj = Trajectory(np.array(positions), np.array(frames["time"]), model.faces.copy(), report)
        if status == "diverged":
            raise DivergenceError(reason, traj)
        return traj


class _CollisionTotals:
    """Run totals of the collision stage (the report's "collision" section)."""

    def __init__(self) -> None:
        self.steps = self.contacts = self.candidates = self.failsafe_steps = self.failsafe_vertices = 0
        self.max_resting = 0
        self.max_penetration = 0.0
        self.time = self.frame_time = 0.0
        self.toi = math.inf
        self.work = 0.0

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
            "work": self.work,
            "time": self.time,
            "mean_time_per_step": self.time / n,
        }


_CONTROLLER: Any = None


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
