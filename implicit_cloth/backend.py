"""The numerical back-end of a model: numpy (the reference) or numba (the optional compiled kernels).

``"numba"`` compiles the fused kernels of :mod:`implicit_cloth.solvers._fused`
(install the ``fast`` extra: ``pip install implicit_cloth[fast]``); ``"numpy"``
is the reference path and the fallback; ``"auto"`` (default) picks numba when
it is installed. The default can be set for a process with the environment
variable ``IMPLICIT_CLOTH_ACCELERATOR`` (``auto``, ``numba`` or ``numpy``) or
:func:`set_default_accelerator`.
"""

from __future__ import annotations

import importlib.util
import os

ACCELERATORS = ("auto", "numba", "numpy")
_ENV = "IMPLICIT_CLOTH_ACCELERATOR"
_default: str | None = None


def numba_available() -> bool:
    """Whether numba can be imported (without importing it)."""
    return importlib.util.find_spec("numba") is not None


def _check(name: str, where: str) -> str:
    if name not in ACCELERATORS:
        raise ValueError(f"{where}: unknown accelerator, expected one of {', '.join(ACCELERATORS)}, got {name!r}")
    return name


def default_accelerator() -> str:
    """The process-wide default: :func:`set_default_accelerator`, else ``$IMPLICIT_CLOTH_ACCELERATOR``, else auto."""
    if _default is not None:
        return _default
    return _check(os.environ.get(_ENV, "auto").strip().lower() or "auto", _ENV)


def set_default_accelerator(name: str | None) -> None:
    """Set (or with ``None`` reset to the environment's) default accelerator for new preconditioners."""
    global _default
    _default = None if name is None else _check(name, "accelerator")


def resolve(name: str | None = None) -> str:
    """``"numba"`` or ``"numpy"`` for a requested accelerator (``None``: the default).

    Raises ``ValueError`` when numba is requested explicitly but not installed.
    """
    name = default_accelerator() if name is None else _check(name, "accelerator")
    if name == "auto":
        return "numba" if numba_available() else "numpy"
    if name == "numba" and not numba_available():
        raise ValueError("accelerator: numba is not installed (pip install 'implicit_cloth[fast]'), got 'numba'")
    return name

