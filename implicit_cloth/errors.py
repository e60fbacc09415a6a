"""Exceptions and warnings raised by implicit_cloth."""

from __future__ import annotations

from typing import Any


class SceneError(ValueError):
    """A scene (file, dict or keyword) is invalid.

    The message always starts with the dotted path of the offending key and
    names the bad value, e.g. ``cloth.springs.shear.stiffness: must be a finite
    number >= 0, got -5``.
    """


class DivergenceError(RuntimeError):
    """A run produced a non-finite state or an energy beyond the divergence bound.

    Attributes
    ----------
    trajectory : Trajectory
        The frames kept before the divergence (never a NaN frame), with its
        report's ``status`` set to ``"diverged"``.
    reason : str
        One-line reason, e.g. ``"non-finite velocity at t=0.35 s (step 35)"``.
    """

    def __init__(self, reason: str, trajectory: Any = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.trajectory = trajectory


class SolverWarning(RuntimeWarning):
    """A linear solve stopped at its iteration limit before reaching its tolerance."""


class MeshWarning(UserWarning):
    """A mesh file has defects the simulation works around.

    Zero-area triangles (they add no mass), duplicate vertices (vertices are not
    merged, so the pieces are not joined there) and non-manifold edges (they get
    no bend spring). The message starts with ``cloth.mesh:``, names the first
    offending item and the file; the run goes on. A defect that cannot be worked
    around (a vertex that would have no mass, a face index out of range, a
    non-finite coordinate) is a :class:`SceneError` instead.
    """
