"""Linear solvers for the implicit integrators."""

from .pcg import BlockJacobi, Filter, SolveResult, filtered_pcg

__all__ = ["BlockJacobi", "Filter", "SolveResult", "filtered_pcg", "make_preconditioner"]


def make_preconditioner(name: str, n: int):
    """Preconditioner by its scene name (``solver.preconditioner``)."""
    if name == "block_jacobi":
        return BlockJacobi(n)
    raise ValueError(f"solver.preconditioner: unknown preconditioner, got {name!r}")
