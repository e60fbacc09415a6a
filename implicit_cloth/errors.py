"""Exceptions and warnings raised by implicit_cloth."""

from __future__ import annotations

from typing import Any


class NoValue:
    """The type of :data:`NO_VALUE`: "no value given" (``None`` is a value a key can have)."""

    def __repr__(self) -> str:
        return "NO_VALUE"

    def __reduce__(self) -> str:   # unpickles as the module's singleton
        return "NO_VALUE"


NO_VALUE = NoValue()


def show(value: Any) -> str:
    """The value as it was given (repr, so that '1.0' and 1.0 differ), shortened to one readable line."""
    try:
        text = " ".join(repr(value).split())
    except ValueError:   # an int beyond Python's str conversion limit (4300 digits)
        return f"an integer of about {int(value).bit_length() * 0.30103:.0f} digits"
    return text if len(text) <= 80 else text[:60] + " ... " + text[-15:]


class InputError(ValueError):
    """Bad input: a scene key, a sweep key, a command-line flag or an output directory.

    Reads ``"{path}: {message}, got {value}"`` (``", got ..."`` only when a value
    is given). The parts are kept as attributes so that a caller can re-word the
    error (a sweep names its own key instead of the scene's) without parsing it.

    ``InputError("path: message")`` (one string) is accepted too: ``path`` is then
    the text before the first ``": "``.

    Attributes
    ----------
    path : str
        Dotted path of the offending key (``cloth.springs.shear.stiffness``), or the flag (``--out``).
    message : str
        What is wrong (``must be a finite number >= 0``).
    value : Any
        The value given, or :data:`NO_VALUE`.
    """

    def __init__(self, path: str, message: str | None = None, value: Any = NO_VALUE) -> None:
        if message is None:
            path, sep, message = str(path).partition(": ")
            if not sep:
                path, message = "", path
        self.path, self.message, self.value = path, message, value
        text = f"{path}: {message}" if path else message
        if value is not NO_VALUE:
            text += f", got {show(value)}"
        super().__init__(text)

    def __reduce__(self) -> tuple[Any, ...]:   # picklable with its fields (batch workers send errors back)
        return (type(self), (self.path, self.message, self.value))


class SceneError(InputError):
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
