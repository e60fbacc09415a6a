"""Ctrl-C between steps: a SIGINT handler that defers the interrupt out of compiled code.

Python raises KeyboardInterrupt from its SIGINT handler at the next bytecode it runs. When that is the moment a
numba function returns, the exception is set while the compiled call reports success, and CPython turns it
into ``SystemError: CPUDispatcher(...) returned a result with an exception set`` (a traceback and exit 1
instead of exit 130, or in a program a SystemError instead of KeyboardInterrupt). :meth:`Simulator.step
<implicit_cloth.Simulator.step>` and :meth:`Simulator.run <implicit_cloth.Simulator.run>` step inside
:func:`deferred_interrupt`: there the first SIGINT only sets a flag, and
:meth:`DeferredInterrupt.check` (called between steps, in Python) raises the KeyboardInterrupt; a second SIGINT
raises at once, as usual. The handler is installed only in the main thread and only over Python's default
handler (a program's own SIGINT handling is left alone).
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType


class DeferredInterrupt:
    """Context manager holding the deferred SIGINT flag (see the module's docstring)."""

    def __init__(self) -> None:
        self.pending = False
        self._previous: object = None
        self._installed = False

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if self.pending:            # the second Ctrl-C: do not wait for the step to end
            raise KeyboardInterrupt
        self.pending = True

    def check(self) -> None:
        """Raise KeyboardInterrupt if a SIGINT arrived since the context was entered."""
        if self.pending:
            self.pending = False
            raise KeyboardInterrupt

    def __enter__(self) -> "DeferredInterrupt":
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._previous = signal.signal(signal.SIGINT, self._handler)
            self._installed = True
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)   # type: ignore[arg-type]
            self._installed = False
        if kind is None:
            self.check()            # a SIGINT after the last check is not lost


def deferred_interrupt() -> DeferredInterrupt:
    """A :class:`DeferredInterrupt` to use as ``with deferred_interrupt() as stop: ... stop.check()``."""
    return DeferredInterrupt()
