"""Linear solvers for the implicit integrators."""

from __future__ import annotations

from typing import Any

from .pcg import BlockJacobi, Filter, SolveResult, filtered_pcg

__all__ = ["BlockJacobi", "Filter", "SolveResult", "filtered_pcg", "make_preconditioner"]


def make_preconditioner(name: str, model: Any):
    """Preconditioner by its scene name (``solver.preconditioner``) for a model.

    ``"multigrid"`` (default): geometric multigrid for grid cloths, smoothed
    aggregation for meshes (:mod:`implicit_cloth.solvers.multigrid`).
    ``"block_jacobi"``: 3x3 block Jacobi.
    """
    if name == "block_jacobi":
        return BlockJacobi(model.n)
    if name == "multigrid":
        from .multigrid import for_model

        return for_model(model)
    raise ValueError(f"solver.preconditioner: unknown preconditioner, got {name!r}")
