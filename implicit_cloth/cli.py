"""Command-line interface: ``implicit-cloth run SCENE.toml``.

Usage::

    implicit-cloth run SCENE.toml [--out DIR] [--integrator NAME] [--dt S]
                       [--duration S] [--frame-rate HZ] [--no-progress] [--debug]

``run`` simulates a scene and writes ``DIR/trajectory.npz`` (``positions``,
``times``, ``faces``; see :meth:`~implicit_cloth.Trajectory.save`) and
``DIR/report.json`` (the run report plus the normalised scene under
``"scene"``). ``DIR`` defaults to ``out/<scene file stem>``.

Exit codes
----------
0
    The run finished (``status`` ``"ok"``, or ``"warning"`` without ``--strict``: each warning of the
    run's health, e.g. energy created beyond the balance, is one line of the summary and one
    ``implicit-cloth: warning: ...`` line on stderr).
1
    The results could not be produced or written: out of memory (one line
    ``implicit-cloth: error: out of memory ...``) or an operating-system error
    after the run (e.g. a full disk). The two files are written together: a failure leaves
    a previous ``trajectory.npz`` and ``report.json`` as they were and no
    temporary file behind.
2
    Bad input: an invalid or unreadable scene, an invalid override
    (``--dt -1``, ``--integrator nonsense``), an unusable ``--out`` or a usage
    error. One line ``implicit-cloth: error: ...`` on stderr (a traceback too
    with ``--debug``).
3
    The run diverged: the frames kept before it are written to
    ``trajectory.npz``, ``report.json`` has ``status`` ``"diverged"`` and the
    reason, and the reason is printed on stderr.
4
    With ``run --strict``: the run finished with ``status`` ``"warning"`` (its
    results are written as for 0).
130
    Interrupted (Ctrl-C, SIGINT): ``implicit-cloth: interrupted`` on stderr,
    nothing written (a previous pair of outputs stays as it was). The
    interrupt is taken between steps, also on the compiled (numba) path.

Other subcommands: ``bench`` (a benchmark of benchmarks/), ``batch`` (a
parameter sweep, see :mod:`implicit_cloth.batch`), ``export`` (meshes of a
run's frames), ``render`` (pictures of a run) and ``compare`` (plots of a
sweep's summary); each follows the same exit codes, one-line errors and
``--debug``.
"""

from __future__ import annotations

import argparse
import re
import sys
import traceback
import warnings
from pathlib import Path
from typing import Any, NoReturn, Sequence

from . import __version__
from .backend import using_threads
from .errors import DivergenceError, InputError
from .files import write_run
from .integrators import INTEGRATORS
from .integrators.base import NEWTON_FORCING
from .report import RunReport
from .scene import load_scene
from .simulator import Simulator, Trajectory

PROG = "implicit-cloth"

EXIT_OK = 0
EXIT_WRITE_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_WARNING = 4
EXIT_INTERRUPTED = 130


# --------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``implicit-cloth: error: --dt: invalid float value: 'abc' (see ...)``
    instead of the usage text and the error (exit code 2 either way)."""

    def error(self, message: str) -> NoReturn:
        message = re.sub(r"^argument ([^:]+): ", r"\1: ", " ".join(message.split()))
        self.exit(EXIT_BAD_INPUT, f"{PROG}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (one subparser per subcommand)."""
    parser = _Parser(
        prog=PROG,
        description="Mass-spring cloth simulation with Baraff-Witkin implicit integration.",
        epilog=f"Exit codes: {EXIT_OK} ok, {EXIT_WRITE_FAILED} results could not be written (out of memory, a full "
               f"disk; batch: cases left pending), {EXIT_BAD_INPUT} bad input, {EXIT_DIVERGED} diverged, "
               f"{EXIT_WARNING} finished with warnings (run --strict), {EXIT_INTERRUPTED} interrupted (Ctrl-C).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    run = sub.add_parser(
        "run", help="simulate a scene and write trajectory.npz and report.json",
        description="Simulate a TOML scene. Writes DIR/trajectory.npz (positions, times, faces) and "
                    "DIR/report.json (run report and normalised scene). Options override the scene's "
                    "[simulation] table and are validated like it.",
        epilog="Exit codes: 0 ok (or warning without --strict), 1 results could not be written, 2 bad input, "
               "3 diverged (partial trajectory and report still written), 4 finished with warnings (--strict), "
               "130 interrupted (Ctrl-C; nothing written).",
    )
    run.add_argument("scene", metavar="SCENE.toml", help="scene file")
    run.add_argument("--out", metavar="DIR", default=None,
                     help="output directory (default: out/<scene file stem>)")
    run.add_argument("--integrator", metavar="NAME", default=None,
                     help=f"override simulation.integrator: {', '.join(INTEGRATORS)}")
    run.add_argument("--dt", metavar="S", type=float, default=None, help="override simulation.dt, s")
    run.add_argument("--duration", metavar="S", type=float, default=None,
                     help="override simulation.duration, s")
    run.add_argument("--frame-rate", metavar="HZ", type=float, default=None, dest="frame_rate",
                     help="override simulation.frame_rate, kept frames per simulated second")
    run.add_argument("--threads", metavar="N", type=int, default=None,
                     help="threads of the compiled solver (numba's path; default: $IMPLICIT_CLOTH_THREADS, "
                          "else 1); the same numbers at every count")
    run.add_argument("--no-progress", action="store_true",
                     help="no progress bar (it is only shown when stderr is a terminal)")
    run.add_argument("--strict", action="store_true",
                     help="exit with code 4 when the run's status is 'warning' (energy created, a strain bound "
                          "exceeded, the collision fail-safe, unconverged solves)")
    run.add_argument("--debug", action="store_true", help="print tracebacks of errors")
    run.set_defaults(handler=cmd_run)

    bench = sub.add_parser(
        "bench", help="run a benchmark of benchmarks/ (bench --help lists them)",
        description="Run benchmarks/NAME.py of the source tree (an editable install or a clone).\n"
                    "Options after NAME go to the benchmark (bench NAME --help lists them):\n"
                    "  --quick    a small case end to end, in seconds\n"
                    "  --out DIR  where the results go (default out/bench/NAME; the committed results are in\n"
                    "             benchmarks/results/, written there only with --out benchmarks/results)",
        epilog=_bench_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    bench.add_argument("name", metavar="NAME", help="a benchmark below")
    bench.add_argument("args", nargs=argparse.REMAINDER, help="options passed to the benchmark (e.g. --quick)")
    bench.set_defaults(handler=cmd_bench)

    batch = sub.add_parser(
        "batch", help="run a parameter sweep (locally or on a Dask cluster), resumable",
        description="Run every case of a sweep file (a base scene and the keys to vary) and write "
                    "DIR/<case-id>/{trajectory.npz,report.json} and DIR/summary.{csv,json}. Re-running the "
                    "same command skips finished cases.",
        epilog="Exit codes: 0 every case finished (ok, diverged or failed: see summary.csv), 1 results could "
               "not be written or cases were left pending (run again to resume), 2 bad input, 130 interrupted.",
    )
    batch.add_argument("sweep", metavar="SWEEP.toml", help="sweep file")
    batch.add_argument("--out", metavar="DIR", default=None, help="output directory (default: out/<sweep file stem>)")
    batch.add_argument("--workers", metavar="N", type=int, default=None,
                       help="local worker processes (default: the number of CPUs)")
    batch.add_argument("--scheduler", metavar="ADDRESS", default=None,
                       help="run on a Dask cluster, e.g. tcp://host:8786 (needs the dask extra)")
    batch.add_argument("--retry-failed", action="store_true", help="run again the cases recorded as failed")
    batch.add_argument("--no-progress", action="store_true",
                       help="no progress bar (it is only shown when stderr is a terminal)")
    batch.add_argument("--debug", action="store_true", help="print tracebacks of errors")
    batch.set_defaults(handler=cmd_batch)

    export = sub.add_parser(
        "export", help="write a run for other tools: animated usd, pc2 point cache, glb/gltf; obj/ply per frame",
        description="Export RUN_DIR as an animation other tools open: usd (animation.usd: time-sampled points "
                    "and normals, obstacles' transforms; z-up; needs the usd extra), pc2 (animation.pc2 + "
                    "rest.obj, Blender's Mesh Cache modifier), glb or gltf (animation.glb / .gltf + .bin: "
                    "morph-target animation, obstacles' node animation; y-up), or one mesh per frame: obj "
                    "(normals, UVs; y-up) or ply (normals; z-up). Metres; the run's vertex numbering is kept.",
    )
    export.add_argument("run_dir", metavar="RUN_DIR", help="a run's output directory (run, or a batch case)")
    export.add_argument("--format", default="usd", help="usd | pc2 | glb | gltf | obj | ply (default usd)")
    export.add_argument("--out", metavar="DIR", default=None, help="output directory (default RUN_DIR/export)")
    export.add_argument("--frames", metavar="K", type=int, nargs="+", default=None,
                        help="frame indices to export (negative from the end; default all)")
    export.add_argument("--debug", action="store_true", help="print tracebacks of errors")
    export.set_defaults(handler=cmd_export)

    render = sub.add_parser(
        "render", help="draw a run: PNG of chosen frames and an animated GIF (or MP4)",
        description="Draw RUN_DIR's cloth and obstacles headless: frames.png with the chosen frames side by "
                    "side and movie.gif or movie.mp4. With pyvista (the render extra) a depth-buffered "
                    "picture, the cloth coloured by --color; without it matplotlib's painter's algorithm, "
                    "which is wrong at contacts.",
    )
    render.add_argument("run_dir", metavar="RUN_DIR", help="a run's output directory (run, or a batch case)")
    render.add_argument("--out", metavar="DIR", default=None, help="output directory (default RUN_DIR/render)")
    render.add_argument("--frames", metavar="K", type=int, nargs="+", default=None,
                        help="frames of the PNG (negative from the end; default first, middle, last)")
    render.add_argument("--movie", default="gif", help="gif | mp4 | none (default gif)")
    render.add_argument("--fps", type=float, default=15.0, help="movie frames per second (default 15)")
    render.add_argument("--max-frames", type=int, default=120, dest="max_frames",
                        help="at most this many movie frames, evenly spaced (default 120)")
    render.add_argument("--color", default="solid", help="solid | piece | strain | speed (default solid)")
    render.add_argument("--backend", default="auto", help="auto | pyvista | matplotlib (default auto: pyvista "
                                                          "if installed)")
    render.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), default=[640, 480],
                        help="picture size in pixels (pyvista; default 640 480)")
    render.add_argument("--zoom", type=float, default=1.0, help="camera this many times closer (default 1)")
    render.add_argument("--dpi", type=int, default=80, help="resolution (matplotlib; default 80)")
    render.add_argument("--elev", type=float, default=20.0, help="camera elevation, degrees (default 20)")
    render.add_argument("--azim", type=float, default=-60.0, help="camera azimuth, degrees (default -60)")
    render.add_argument("--no-progress", action="store_true",
                        help="no progress bar (it is only shown when stderr is a terminal)")
    render.add_argument("--debug", action="store_true", help="print tracebacks of errors")
    render.set_defaults(handler=cmd_render)

    compare = sub.add_parser(
        "compare", help="plot a sweep's health figures against a swept key",
        description="Turn DIR/summary.json of a batch into plots DIR/compare/per_case/<metric>_vs_<key>.png "
                    "(with --by KEY: DIR/compare/by_<KEY>/<metric>_vs_<key>.png; the dots of keys written as "
                    "underscores, e.g. by_simulation_integrator/max_strain_vs_simulation_dt.png): each "
                    "health figure against one swept key, one line per group. Needs matplotlib.",
    )
    compare.add_argument("dir", metavar="DIR", help="a batch output directory")
    compare.add_argument("--x", metavar="KEY", default=None,
                         help="swept key on the x axis (default simulation.dt if swept)")
    compare.add_argument("--by", metavar="KEY", default=None,
                         help="one line per value of this swept key (default: per combination of the others)")
    compare.add_argument("--metrics", metavar="NAME", nargs="+", default=None,
                         help="columns to plot (default energy_drift_rel max_strain mean_iterations wall_s)")
    compare.add_argument("--out", metavar="DIR", default=None,
                         help="where to write the plots (default DIR/compare), in its per_case/ or by_<KEY>/ folder")
    compare.add_argument("--debug", action="store_true", help="print tracebacks of errors")
    compare.set_defaults(handler=cmd_compare)
    return parser


# --------------------------------------------------------------------------- helpers
def _error(message: str, debug: bool = False) -> None:
    """Print the one-line error (after the traceback of the exception being handled, with --debug)."""
    if debug:
        traceback.print_exc(file=sys.stderr)
    print(f"{PROG}: error: {message}", file=sys.stderr)


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _fmt_e(x: float) -> str:
    return f"{x:.6g}"


def _summary(traj: Trajectory, npz: Path, js: Path) -> str:
    r = RunReport.from_dict(traj.report)
    fr = r.frames
    ms = 1e3 * r.wall_time / r.steps if r.steps else float("nan")
    lines = [
        f"integrator   {r.integrator}",
        f"dt           {r.dt:g} s",
        f"vertices     {r.n_vertices} ({r.n_pinned} pinned)",
        f"steps        {r.steps}",
        f"frames       {len(traj)} (t = {traj.times[0]:g} .. {traj.times[-1]:g} s)",
        f"wall time    {r.wall_time:.3f} s ({ms:.3g} ms/step)",
    ]
    if fr.total:
        lines.append(
            f"final energy kinetic {_fmt_e(fr.kinetic[-1])} J, gravity {_fmt_e(fr.gravity[-1])} J, "
            f"springs {_fmt_e(fr.springs[-1])} J, total {_fmt_e(fr.total[-1])} J")
        lines.append(f"max strain   {max(fr.max_strain):.4g}")
    lines += _section_lines(r)
    lines.append(f"status       {r.status}" + (f" ({r.reason})" if r.status == "diverged" and r.reason else ""))
    for w in r.health:
        lines.append(f"warning      {w['message']}")
    lines.append(f"trajectory   {npz}")
    lines.append(f"report       {js}")
    return "\n".join(lines)


def _section_lines(r: RunReport) -> list[str]:
    """Summary lines of the report's optional sections: solver, adaptive, strain limit, collision."""
    lines = []
    s = r.solver
    if s:
        newton = (f", Newton corrections included: those are solved to {NEWTON_FORCING:g}"
                  if s.max_newton_iterations > 1 else "")
        attempts = (f"; every attempt: {s.mean_attempted_solves:.2f} solves and {s.mean_attempted_iterations:.1f} "
                    f"iterations a step" if s.mean_attempted_solves is not None
                    and s.mean_attempted_solves > s.mean_solves else "")
        lines.append(
            f"solver       {s.preconditioner} PCG ({s.accelerator}{', K-cycle' if s.cycle == 'K' else ''}), "
            f"iterations mean {s.mean_iterations:.1f} / "
            f"max {s.max_iterations}, tolerance {s.tolerance:g} on the error of dv (max relative residual "
            f"{s.max_residual:.3g}{newton}), unconverged steps {s.unconverged_steps}{attempts}")
    a = r.adaptive
    if a:
        lines.append(f"adaptive     {a.substeps} substeps, {a.retries} retries (halved), {a.newton_retries} redone "
                     f"with Newton iterations, {a.forced} forced, smallest step {a.min_step:g} s")
    sl = r.strain_limit
    if sl and sl.method == "barrier":
        lines.append(f"strain limit {sl.max_strain:g} (barrier): {sl.springs_limited} springs within its reach at "
                     f"the end of {sl.steps_limited} steps, max strain {sl.max_strain_after:.4g}")
    elif sl:
        lines.append(f"strain limit {sl.max_strain:g}: {sl.springs_limited} over-stretched springs in "
                     f"{sl.steps_limited} steps, max strain after limiting {sl.max_strain_after:.4g}")
    c = r.collision
    if c:
        lines.append(
            f"collision    {', '.join(c.obstacles)}: {c.contacts} contacts, {c.mean_candidates:.0f} "
            f"candidates/step, {c.mean_solves:.2f} solves/step, max penetration {c.max_penetration:.3g} m, "
            f"fail-safe steps {c.failsafe_steps}, obstacles' work {c.work:.3g} J, "
            f"{1e3 * c.mean_time_per_step:.1f} ms/step")
    return lines


# --------------------------------------------------------------------------- run
def cmd_run(args: argparse.Namespace) -> int:
    """``implicit-cloth run``: simulate, write outputs, print a summary."""
    if args.threads is None:
        return _cmd_run(args)
    if args.threads < 1:
        _error(f"--threads: must be an integer >= 1, got {args.threads}")
        return EXIT_BAD_INPUT
    with using_threads(args.threads):
        return _cmd_run(args)


def _cmd_run(args: argparse.Namespace) -> int:
    debug = bool(args.debug)
    scene_path = Path(args.scene)
    out = Path(args.out) if args.out is not None else Path("out") / scene_path.stem

    overrides: dict[str, Any] = {}
    for key in ("integrator", "dt", "duration", "frame_rate"):
        val = getattr(args, key)
        if val is not None:
            overrides[key] = val
    try:
        with warnings.catch_warnings(record=True) as loading:   # e.g. MeshWarning: one line each
            warnings.simplefilter("default")
            scene = load_scene(scene_path)
            # Overrides go through Simulator's keywords, i.e. through scene validation.
            sim = Simulator(scene, **overrides)
    except InputError as exc:
        _error(_one_line(exc), debug)
        return EXIT_BAD_INPUT
    finally:
        for w in loading:
            print(f"{PROG}: warning: {_one_line(w.message)}", file=sys.stderr)

    if out.exists() and not out.is_dir():
        _error(f"--out: {str(out)!r} exists and is not a directory")
        return EXIT_BAD_INPUT
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _error(f"--out: cannot create output directory {str(out)!r} ({exc.strerror or exc})", debug)
        return EXIT_BAD_INPUT

    progress = (not args.no_progress) and sys.stderr.isatty()
    scene_data = sim.scene.data
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            traj = sim.run(progress=progress)
        code = EXIT_OK
    except DivergenceError as exc:
        traj = exc.trajectory
        code = EXIT_DIVERGED
        if traj is None:  # not produced by Simulator.run, but be safe
            _error(f"diverged: {_one_line(exc.reason)}", debug)
            return code
    except InputError as exc:
        _error(_one_line(exc), debug)
        return EXIT_BAD_INPUT
    finally:
        for w in caught:  # e.g. SolverWarning: one line each, not a source location
            print(f"{PROG}: warning: {_one_line(w.message)}", file=sys.stderr)

    try:
        npz, js = write_run(out, traj, scene_data)
    except OSError as exc:
        _error(f"cannot write results to {str(out)!r} ({exc.strerror or exc})", debug)
        return EXIT_WRITE_FAILED

    print(_summary(traj, npz, js), flush=True)
    if code == EXIT_DIVERGED:
        print(f"{PROG}: diverged: {_one_line(traj.report.get('reason', ''))}", file=sys.stderr)
    for w in traj.report.get("health") or []:
        print(f"{PROG}: warning: {_one_line(w['message'])}", file=sys.stderr)
    if code == EXIT_OK and args.strict and traj.report.get("status") == "warning":
        return EXIT_WARNING
    return code


def benchmarks_dir() -> Path:
    """The source tree's benchmarks/ folder (beside the package in a clone or editable install)."""
    return Path(__file__).resolve().parents[1] / "benchmarks"


#: Short names of benchmarks (``implicit-cloth bench contact`` runs benchmarks/contact_energy.py).
BENCH_ALIASES = {"contact": "contact_energy"}


def bench_names(folder: Path | None = None) -> dict[str, str]:
    """The benchmarks ``bench`` runs, each with the first line of its docstring: ``benchmarks/NAME.py`` (not
    ``_*.py``, helpers; not the studies and tools in subfolders, run as scripts)."""
    folder = benchmarks_dir() if folder is None else folder
    if not folder.is_dir():
        return {}
    return {p.stem: _first_doc_line(p) for p in sorted(folder.glob("*.py")) if not p.stem.startswith("_")}


def _first_doc_line(path: Path) -> str:
    """The first line of a script's docstring, read without importing it ("" without one)."""
    m = re.match(r'(?:\s|#[^\n]*\n)*[rR]?"""\s*([^\n]*?)\s*(?:"""|\n)', path.read_text(encoding="utf-8"))
    return m.group(1) if m else ""


def _bench_epilog() -> str:
    names = bench_names()
    if not names:
        return "No benchmarks/ folder beside the package: run from a clone with pip install -e ."
    aliases = {v: k for k, v in BENCH_ALIASES.items()}
    width = max(len(n) for n in names) + 2
    lines = [f"  {n:<{width}}{d}" + (f" (also: bench {aliases[n]})" if n in aliases else "")
             for n, d in names.items()]
    return "benchmarks (NAME):\n" + "\n".join(lines)


def cmd_bench(args: argparse.Namespace) -> int:
    folder = benchmarks_dir()
    names = list(bench_names(folder))
    if not names:
        _error(f"no benchmarks/ folder beside the package ({folder}); run from a clone with pip install -e .")
        return EXIT_BAD_INPUT
    name = BENCH_ALIASES.get(args.name, args.name)
    if name not in names:
        _error(f"bench: unknown benchmark {args.name!r} (available: {', '.join(names)})")
        return EXIT_BAD_INPUT
    import importlib

    sys.path.insert(0, str(folder))
    try:
        module = importlib.import_module(name)
        return int(module.main(list(args.args)) or 0)
    except SystemExit as exc:  # the benchmark's own argument errors
        return exc.code if isinstance(exc.code, int) else EXIT_BAD_INPUT
    finally:
        sys.path.remove(str(folder))


# --------------------------------------------------------------------------- batch, export, render, compare
def _out_dir(out: Path, debug: bool) -> bool:
    """Create the output directory; print the one-line error and return False if it is unusable."""
    if out.exists() and not out.is_dir():
        _error(f"--out: {str(out)!r} exists and is not a directory")
        return False
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _error(f"--out: cannot create output directory {str(out)!r} ({exc.strerror or exc})", debug)
        return False
    return True


def _missing_extra(exc: ImportError, extra: str, debug: bool) -> int:
    _error(f"this command needs the optional package {exc.name or exc} (pip install "
           f"'implicit_cloth[{extra}]')", debug)
    return EXIT_BAD_INPUT


def cmd_batch(args: argparse.Namespace) -> int:
    """``implicit-cloth batch``: run a sweep's unfinished cases, write the summary, print the counts."""
    from .batch import load_sweep, run_sweep

    debug = bool(args.debug)
    if args.workers is not None and args.workers < 1:
        _error(f"--workers: must be an integer >= 1, got {args.workers}")
        return EXIT_BAD_INPUT
    try:
        sweep = load_sweep(args.sweep)
    except InputError as exc:
        _error(_one_line(exc), debug)
        return EXIT_BAD_INPUT
    out = Path(args.out) if args.out is not None else Path("out") / Path(args.sweep).stem
    if not _out_dir(out, debug):
        return EXIT_BAD_INPUT
    progress = (not args.no_progress) and sys.stderr.isatty()
    # an InputError here: the output directory is locked, or the scheduler cannot be reached
    code, result = _guarded(lambda: run_sweep(
        sweep, out, workers=args.workers, scheduler=args.scheduler, retry_failed=args.retry_failed,
        progress=progress, on_note=lambda m: print(f"{PROG}: warning: {_one_line(m)}", file=sys.stderr)),
        debug, f"results to {str(out)!r}")
    if code is not None:
        return code
    c = result.counts
    print(f"cases        {len(sweep.cases)}: {c['ok']} ok, {c['warning']} warning, {c['diverged']} diverged, "
          f"{c['failed']} failed, "
          f"{c['pending']} pending ({result.skipped} already finished before this run)")
    print(f"summary      {result.summary[0]}")
    print(f"             {result.summary[1]}", flush=True)
    if c["pending"]:
        _error(f"{c['pending']} cases were not run; run the same command again to resume")
        return EXIT_WRITE_FAILED
    return EXIT_OK


def _guarded(call: Any, debug: bool, writing: str, extra: str | None = None) -> tuple[int | None, Any]:
    """Run ``call()`` the command line's way; returns ``(exit code or None when it succeeded, its result)``.

    An InputError (a SceneError, a bad flag or directory) is its one line and exit 2; an OSError is
    ``cannot write <writing> (...)`` and exit 1; an ImportError, when ``extra`` names the optional extra
    that provides it, says how to install it (exit 2).
    Warnings raised meanwhile are printed as one line each.
    """
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            return None, call()
    except ImportError as exc:
        if extra is None:
            raise
        return _missing_extra(exc, extra, debug), None
    except InputError as exc:
        _error(_one_line(exc), debug)
        return EXIT_BAD_INPUT, None
    except OSError as exc:
        _error(f"cannot write {writing} ({exc.strerror or exc})", debug)
        return EXIT_WRITE_FAILED, None
    finally:
        for w in caught:
            print(f"{PROG}: warning: {_one_line(w.message)}", file=sys.stderr)


def cmd_export(args: argparse.Namespace) -> int:
    """``implicit-cloth export``: per-frame meshes of a run."""
    from .export import export_run

    debug = bool(args.debug)
    if args.out is not None and not _out_dir(Path(args.out), debug):
        return EXIT_BAD_INPUT
    code, files = _guarded(lambda: export_run(args.run_dir, args.format, out=args.out, frames=args.frames),
                           debug, "meshes", extra="usd")
    if code is not None:
        return code
    where = files[0].parent if files else args.out
    print(f"wrote {len(files)} {args.format} file{'s' if len(files) != 1 else ''} to {where}", flush=True)
    return EXIT_OK


def _plots(args: argparse.Namespace, make: Any) -> int:
    """render and compare: check the extra and ``--out``, run ``make()`` guarded, print the files written."""
    debug = bool(args.debug)
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        return _missing_extra(exc, "render", debug)
    if args.out is not None and not _out_dir(Path(args.out), debug):
        return EXIT_BAD_INPUT
    code, files = _guarded(make, debug, "pictures", extra="render")
    if code is not None:
        return code
    for f in files:
        print(f)
    return EXIT_OK


def cmd_render(args: argparse.Namespace) -> int:
    """``implicit-cloth render``: PNG of chosen frames and a movie of a run."""
    def make():
        from .render import render_run

        return render_run(args.run_dir, out=args.out, frames=args.frames, movie=args.movie, fps=args.fps,
                          max_movie_frames=args.max_frames, dpi=args.dpi, elev=args.elev, azim=args.azim,
                          backend=args.backend, color=args.color, pixels=tuple(args.size), zoom=args.zoom,
                          progress=(not args.no_progress) and sys.stderr.isatty())
    return _plots(args, make)


def cmd_compare(args: argparse.Namespace) -> int:
    """``implicit-cloth compare``: plots of a sweep's summary."""
    def make():
        from .compare import compare_sweep

        return compare_sweep(args.dir, x=args.x, by=args.by, metrics=args.metrics, plots=args.out)
    return _plots(args, make)


# --------------------------------------------------------------------------- entry point
def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors (2), --help and --version (0)
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else EXIT_BAD_INPUT)
    try:
        return int(args.handler(args))
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SystemError as exc:      # a second Ctrl-C inside compiled code (see implicit_cloth.interrupt)
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            print(f"{PROG}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        raise
    except MemoryError:
        _error(f"out of memory while running {args.command} (a smaller cloth.resolution, fewer kept frames "
               "or a shorter run needs less)", bool(getattr(args, "debug", False)))
        return EXIT_WRITE_FAILED


if __name__ == "__main__":
    sys.exit(main())
