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
