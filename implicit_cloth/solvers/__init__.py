"""Linear solvers for the implicit integrators."""

from __future__ import annotations

from typing import Any

from ..backend import numba_available, set_default_accelerator
from ..config.registry import PRECONDITIONERS
from .pcg import BlockJacobi, Filter, SolveResult, filtered_pcg

# solver.preconditioner: the names scene validation accepts, the default first
PRECONDITIONERS.register("multigrid", default=True)
PRECONDITIONERS.register("block_jacobi")
PRECONDITIONERS.register("multigrid_smoothed")

__all__ = ["BlockJacobi", "Filter", "SolveResult", "filtered_pcg", "make_preconditioner", "numba_available",
           "set_default_accelerator"]


def make_preconditioner(name: str, model: Any, accelerator: str | None = None):
    """Preconditioner by its scene name (``solver.preconditioner``) for a model.

    ``"multigrid"`` (default): geometric multigrid for grid cloths, smoothed
    aggregation for meshes (:mod:`implicit_cloth.solvers.multigrid`), run by
    the compiled kernels when ``accelerator`` resolves to ``"numba"``
    (:mod:`implicit_cloth.backend`; ``None``: the process default).
    ``"block_jacobi"``: 3x3 block Jacobi (numpy only). ``"multigrid_smoothed"``: the same multigrid with its
    prolongations smoothed every step from the level matrices (3x3 blocks on the geometric pattern; fewer
    iterations on curved and wrinkled cloths, a dearer refresh; see :class:`.multigrid.SmoothedProlongation`).
    """
    if name == "block_jacobi":
        return BlockJacobi(model.n)
    if name in ("multigrid", "multigrid_smoothed"):
        from .multigrid import for_model

        return for_model(model, accelerator, smoothed=name == "multigrid_smoothed")
    raise ValueError(f"solver.preconditioner: unknown preconditioner, got {name!r}")
