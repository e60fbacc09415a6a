"""The run report as typed records: what ``Simulator.run`` reports, read and written in one place.

``Simulator.run`` builds the report as a dict (``traj.report``); :meth:`RunReport.from_dict`
reads it (or a ``report.json``) into dataclasses and :meth:`RunReport.to_dict` writes it
back, key for key, so that ``RunReport.from_dict(d).to_dict() == d`` for every report the
simulator makes (a test checks it). A reader uses the fields (``report.solver.mean_iterations``)
instead of ``dict.get`` with a default, so a key that goes missing or changes its name is a
:class:`ReportError` naming it, not a silent default.

Extending the schema: add a field with a default to the record (a default keeps older
``report.json`` files readable), add the key where ``Simulator.run`` builds the dict, and
raise :data:`SCHEMA_VERSION` when a reader must tell old files from new ones. Keys a record
does not know are kept in its ``extra`` dict and written back unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, TypeVar

from .errors import InputError

__all__ = ["SCHEMA_VERSION", "AdaptiveReport", "CollisionReport", "DivergenceBound", "Frames", "ReportError",
           "RunReport", "SolverReport", "StrainLimitReport"]

#: Version of the report's layout, written to ``report.json`` as ``schema_version``. 2: ``status`` may be
#: ``"warning"``, with ``health`` and ``energy_balance``; solver, adaptive and collision figures of the
#: contact treatment (solves per step, Newton redos, fallback corrections).
SCHEMA_VERSION = 2

R = TypeVar("R", bound="Record")


class ReportError(InputError):
    """A run report lacks a key, or a key holds the wrong kind of value (``report.solver.tolerance: missing``)."""


@dataclass
class Record:
    """Base of the report's records: a dataclass read from and written to a dict of the same keys."""

    #: field name -> record type, for fields that hold a nested record (or None)
    NESTED: ClassVar[dict[str, type[Record]]] = {}

    extra: dict[str, Any] = field(default_factory=dict, kw_only=True)

    @classmethod
    def from_dict(cls: type[R], data: Mapping[str, Any], path: str = "report") -> R:
        """Read ``data``; a missing required key or a non-table is a :class:`ReportError` naming its path."""
        if not isinstance(data, Mapping):
            raise ReportError(path, "must be a table", data)
        known = {f.name: f for f in dataclasses.fields(cls) if f.name != "extra"}
        kwargs: dict[str, Any] = {}
        for name, f in known.items():
            if name not in data:
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    raise ReportError(f"{path}.{name}", "missing")
                continue
            value = data[name]
            nested = cls.NESTED.get(name)
            if nested is not None and value is not None:
                value = nested.from_dict(value, f"{path}.{name}")
            kwargs[name] = value
        kwargs["extra"] = {k: v for k, v in data.items() if k not in known}
        return cls(**kwargs)

    def to_dict(self) -> dict[str, Any]:
        """The dict this record was read from (fields in declaration order, then ``extra``)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.name == "extra":
                continue
            value = getattr(self, f.name)
            if f.name in self.OPTIONAL_KEYS and value is None:
                continue
            out[f.name] = value.to_dict() if isinstance(value, Record) else value
        out.update(self.extra)
        return out

    #: fields left out of :meth:`to_dict` when None (keys the simulator writes only when they apply)
    OPTIONAL_KEYS: ClassVar[frozenset[str]] = frozenset()


@dataclass
class SolverReport(Record):
    """Implicit methods' linear solves over the run."""

    tolerance: float
    max_iterations_allowed: int
    preconditioner: str
    #: which implementation ran the preconditioned CG: "numba" or "numpy"
    accelerator: str
    mean_iterations: float
    max_iterations: int
    max_residual: float
    unconverged_steps: int
    #: Newton iterations of a step's first attempt (``solver.newton_iterations``; 1: one linearisation)
    newton_iterations: int = 1
    #: linear solves per step (contact rounds and Newton iterations included)
    mean_solves: float = 1.0
    #: most Newton iterations any step took
    max_newton_iterations: int = 1
    #: threads the compiled solver could use (``implicit_cloth.backend.threads()``; 1 on the numpy path)
    threads: int = 1
    #: BLAS threads while stepping (``Simulator(blas_threads=...)``; None: not limited)
    blas_threads: int | None = 1
    #: numba's threading layer the compiled solver's parallel regions ran on (``"omp"`` first, see
    #: :mod:`implicit_cloth.kernels.layer`); None on the numpy path or when no parallel region ran
    threading_layer: str | None = None
    #: the tolerance of the solves of steps with contacts (``solver.contact_tolerance``; absent in reports
    #: written before it existed)
    contact_tolerance: float | None = None
    #: linear solves and CG iterations per step of every attempt, those adaptive stepping discarded (redone
    #: with Newton iterations or a smaller step) included (None in reports written before they existed)
    mean_attempted_solves: float | None = None
    mean_attempted_iterations: float | None = None
    #: True when a CG breakdown made the multigrid damp its coarse smoothers to their matrices for the rest of
    #: the run (``Multigrid.protect``); absent otherwise
    smoothers_damped: bool | None = None
    #: the multigrid's cycle (``solver.cycle``: "V" or "K"); None without a multigrid (block Jacobi) and in
    #: reports written before it existed
    cycle: str | None = None

    OPTIONAL_KEYS: ClassVar[frozenset[str]] = frozenset({"contact_tolerance", "mean_attempted_solves",
                                                         "mean_attempted_iterations", "threading_layer",
                                                         "smoothers_damped", "cycle"})


@dataclass
class DivergenceBound(Record):
    """The energy bound beyond which a run is stopped as diverged: ``bound = factor x energy_scale``, J."""

    factor: float
    energy_scale: float
    bound: float


@dataclass
class AdaptiveReport(Record):
    """Adaptive step control: its settings and what it did."""

    max_halvings: int
    grow_after: int
    max_strain: float
    max_energy_growth: float
    retry_unconverged: bool
    substeps: int
    retries: int
    forced: int
    failures: dict[str, int]
    min_step: float
    #: Newton iterations of a redone step (1: halve at once)
    newton_iterations: int = 1
    #: substeps redone at the same step with Newton iterations
    newton_retries: int = 0
    #: accepted substeps per nominal step
    substeps_per_step: float = 1.0


@dataclass
class StrainLimitReport(Record):
    """Provot strain limiting: its settings and what it did."""

    max_strain: float
    iterations: int
    steps_limited: int
    springs_limited: int
    max_iterations: int
    max_strain_after: float
    #: vertices tied to their nearest pin (0: ``tethers = false``, no pins, or a report from before tethers)
    tethers: int = 0
    #: the in-plane springs' compression bound (1: none, as in a report from before the bound)
    max_compression: float = 1.0
    #: "projection" (Provot's passes after the step) or "barrier" (a term of the step's solve, ``collision.method =
    #: "barrier"``: ``springs_limited`` counts the springs within the barrier's reach at a step's end)
    method: str = "projection"


@dataclass
class CollisionReport(Record):
    """The collision stage's totals over the run."""

    obstacles: list[str]
    thickness: float
    contacts: int
    mean_contacts: float
    candidates: int
    mean_candidates: float
    max_resting_contacts: int
    earliest_toi: float | None
    max_penetration: float
    failsafe_steps: int
    failsafe_vertices: int
    #: the obstacles' work on the cloth, J: contact impulses times the obstacles' velocity there
    work: float
    time: float
    mean_time_per_step: float
    #: linear solves per step (implicit methods: contact rounds and Newton iterations included)
    mean_solves: float = 1.0
    #: corrections of the geometric response after the solves (implicit methods)
    fallback_corrections: int = 0


@dataclass
class Frames(Record):
    """One list per quantity, one entry per kept frame (see "Report" in docs/scene.md)."""

    OPTIONAL_KEYS: ClassVar[frozenset[str]] = frozenset({"t_collision"})

    time: list[float]
    kinetic: list[float]
    gravity: list[float]
    springs: list[float]
    potential: list[float]
    total: list[float]
    pin_work: list[float]
    max_strain: list[float]
    solver_iterations: list[int]
    solver_residual: list[float]
    min_step: list[float]
    t_assembly: list[float]
    t_setup: list[float]
    t_solve: list[float]
    t_other: list[float]
    #: scenes with obstacles only
    t_collision: list[float] | None = None


@dataclass
class RunReport(Record):
    """The report of one run (``traj.report``; ``report.json`` adds ``scene`` and ``schema_version``)."""

    NESTED: ClassVar[dict[str, type[Record]]] = {
        "solver": SolverReport, "divergence_bound": DivergenceBound, "frames": Frames,
        "adaptive": AdaptiveReport, "strain_limit": StrainLimitReport, "collision": CollisionReport}
    OPTIONAL_KEYS: ClassVar[frozenset[str]] = frozenset({"collision", "warnings", "scene", "schema_version",
                                                         "energy_balance"})

    #: "ok"; "warning" when a step broke the energy balance or the strain bound, the collision fail-safe fired
    #: or a solve did not converge (see ``health``); "diverged"
    status: str
    reason: str
    integrator: str
    dt: float
    duration: float
    frame_rate: float
    effects: list[str]
    n_vertices: int
    n_springs: dict[str, int]
    n_pinned: int
    total_mass: float
    steps: int
    solver: SolverReport | None
    divergence_bound: DivergenceBound
    wall_time: float
    timing: dict[str, float]
    frames: Frames
    adaptive: AdaptiveReport | None
    strain_limit: StrainLimitReport | None
    #: scenes with obstacles only
    collision: CollisionReport | None = None
    #: what went wrong, one entry per criterion: ``criterion`` ("energy", "strain", "failsafe", "solver"),
    #: ``count`` (steps), ``first_time`` (s), ``worst`` (J, strain, vertices or residual) and ``message``
    health: list[dict[str, Any]] = field(default_factory=list)
    #: the per-step energy balance's setting and where it was checked
    energy_balance: dict[str, Any] | None = None
    #: one line per warning raised during the run (batch cases record them; None: not recorded)
    warnings: list[str] | None = None
    #: the normalised scene (report.json only)
    scene: dict[str, Any] | None = None
    #: the layout's version (report.json only; None: a report from memory, or a file from before versions)
    schema_version: int | None = None

    def energy_drift(self) -> float | None:
        """``E_total(end) - E_total(0) - W_pins(end)``, J (None without frames)."""
        fr = self.frames
        if not fr.total:
            return None
        return fr.total[-1] - fr.total[0] - (fr.pin_work[-1] if fr.pin_work else 0.0)

    def for_file(self, scene: Mapping[str, Any] | None) -> dict[str, Any]:
        """The dict written to ``report.json``: this report with the normalised scene and the schema version."""
        out = self.to_dict()
        out["scene"] = dict(scene) if scene is not None else None
        out["schema_version"] = SCHEMA_VERSION
        return out
