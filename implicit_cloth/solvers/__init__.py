"""Linear solvers for the implicit integrators."""

from __future__ import annotations

from typing import Any

from ..backend import numba_available, set_default_accelerator
from ..config.registry import PRECONDITIONERS
from .pcg import BlockJacobi, Filter, SolveResult, filtered_pcg

# solver.preconditioner: the names scene validation accepts, the default first
PRECONDITIONERS.register("auto", default=True)
PRECONDITIONERS.register("multigrid")
PRECONDITIONERS.register("block_jacobi")
PRECONDITIONERS.register("multigrid_smoothed")

__all__ = ["AUTO_SMOOTHED_CONTACT_MIN_VERTICES", "AUTO_SMOOTHED_LINEAR_MIN_VERTICES", "AUTO_SMOOTHED_MIN_VERTICES",
           "BlockJacobi", "Filter", "SolveResult", "auto_preconditioner", "filtered_pcg", "make_preconditioner",
           "numba_available", "set_default_accelerator"]

#: ``"auto"`` smooths the prolongations of a grid cloth without contacts from this many vertices (128²). Measured
#: on the shared hanging scene (docs/benchmarks.md, "The refresh chunked by coarse rows"): one step a frame, one
#: thread, 72.1 -> 58.8 ms a frame at 128², on two 361 -> 240 at 256²; with the default step control 175 -> 153
#: at 128²; at 64² a tie (13.9 / 13.4), at 32² slower (3.9 / 4.2).
AUTO_SMOOTHED_MIN_VERTICES = 16384
#: ... and of a grid cloth among obstacles from this many (32²). Undamped, the smoothed multigrid took more solves a
#: frame on the shared drape (64² 170 -> 219 ms, 128² 1.6 -> 2.7 s): CG breaking down on an indefinite V-cycle (a
#: coarse level's smoother amplifying, multigrid.SMOOTHER_RHO) and adaptive stepping halving the steps. With each
#: coarse level's damping following its matrix, the smoothed multigrid takes about half the plain one's CG
#: iterations a solve on the drape and the drape's run costs less: docs/benchmarks.md, "Coarse smoothers that
#: contract". From 32² with the contacts' constrained directions weighed by the vertices' masses in its coarse
#: levels: the shared 32² drape, two simulators alternating in one process, 120 frames, two threads, 17.3-18.2 against
#: 18.7-20.2 ms a frame on a quiet machine (31.7 against 51.8 CG iterations a frame, 3.61 against 3.21 solves);
#: docs/benchmarks.md, "The contacts weighed by their masses in the coarse levels".
AUTO_SMOOTHED_CONTACT_MIN_VERTICES = 1024
#: (A mesh cloth among obstacles as well, from the same count, its prolongations smoothed
#: aggregation's: an irregular 64² / 32² mesh dropped on the shared drape's sphere, two simulators alternating
#: in one process, 120 frames, two threads, 97.0 against 130.1 / 23.1 against 30.9 ms a frame, 100 against 167 /
#: 76 against 129 CG iterations a frame. A free mesh cloth keeps the plain multigrid: not measured.)
#: ... and of a free grid cloth from this many (64²) when every step is one linear solve (fixed steps, one
#: linearisation: ``simulation.adaptive.enabled = false``, ``solver.newton_iterations = 1``). With the set-up's
#: lists read in order the smoothed multigrid's 8 CG iterations a step beat the plain one's 15 on the
#: shared 64² hanging cloth, one step a frame: 12.7 against 13.4-14.0 ms a frame on one thread, 9.3-9.4 against
#: 10.9 on two; with the default step control it still lost on one thread (20.0 against 18.7-18.9: its Newton
#: redos' corrections, 4-6 iterations each, pay a full set-up each). docs/benchmarks.md, "The smoothed set-up's
#: passes over memory".
AUTO_SMOOTHED_LINEAR_MIN_VERTICES = 4096


def auto_preconditioner(model: Any, contacts: bool = False, self_collision: bool = False,
                        linear_steps: bool = False) -> str:
    """What ``solver.preconditioner = "auto"`` (the default) runs for a model: ``"multigrid_smoothed"`` for a
    cloth of at least :data:`AUTO_SMOOTHED_CONTACT_MIN_VERTICES` vertices in a scene with obstacles
    (``contacts``; a grid or a mesh), or a grid cloth of at least :data:`AUTO_SMOOTHED_LINEAR_MIN_VERTICES` when
    every step is one linear solve (``linear_steps``) or :data:`AUTO_SMOOTHED_MIN_VERTICES`, without
    ``self_collision`` (not measured there); else ``"multigrid"``."""
    grid = getattr(getattr(model, "geometry", None), "grid_shape", None) is not None
    least = (AUTO_SMOOTHED_CONTACT_MIN_VERTICES if contacts
             else AUTO_SMOOTHED_LINEAR_MIN_VERTICES if linear_steps else AUTO_SMOOTHED_MIN_VERTICES)
    return "multigrid_smoothed" if (grid or contacts) and not self_collision and model.n >= least else "multigrid"


def make_preconditioner(name: str, model: Any, accelerator: str | None = None):
    """Preconditioner by its scene name (``solver.preconditioner``) for a model.

    ``"multigrid"``: geometric multigrid for grid cloths, smoothed
    aggregation for meshes (:mod:`implicit_cloth.solvers.multigrid`), run by
    the compiled kernels when ``accelerator`` resolves to ``"numba"``
    (:mod:`implicit_cloth.backend`; ``None``: the process default).
    ``"block_jacobi"``: 3x3 block Jacobi (numpy only). ``"multigrid_smoothed"``: the same multigrid with its
    prolongations smoothed every step from the level matrices (3x3 blocks on the geometric pattern; fewer
    iterations on curved and wrinkled cloths, a dearer refresh; see :class:`.multigrid.SmoothedProlongation`).
    ``"auto"`` (default): one of the two multigrids, by :func:`auto_preconditioner` (the simulator resolves it
    knowing the scene's contacts; here as for a scene without).
    """
    if name == "auto":
        name = auto_preconditioner(model)
    if name == "block_jacobi":
        return BlockJacobi(model.n)
    if name in ("multigrid", "multigrid_smoothed"):
        from .multigrid import for_model

        return for_model(model, accelerator, smoothed=name == "multigrid_smoothed")
    raise ValueError(f"solver.preconditioner: unknown preconditioner, got {name!r}")
