"""The numerical back-end of a model: numba (the compiled kernels, the default) or numpy (the reference).

``"numba"`` runs the fused kernels of :mod:`implicit_cloth.kernels` (numba is a dependency of the package);
``"numpy"`` is the reference path, the same passes in numpy, and the fallback; ``"auto"`` (default) picks
numba when it can be imported. The default can be set for a process with the environment
variable ``IMPLICIT_CLOTH_ACCELERATOR`` (``auto``, ``numba`` or ``numpy``) or
:func:`set_default_accelerator`.

The kernels are compiled on first use and kept in numba's cache (``cache=True``, beside the kernels' source in
``__pycache__``), so only the first run of an installation compiles, and only the kernels that run uses: a run
without contact compiles no contact kernel, a V-cycle run no K-cycle, and a run on one thread (the default) none
of the threaded (``parallel=True``) passes of the solver (:func:`implicit_cloth.kernels.pcg._on`), which took as
long to compile as the rest. That first compilation says so once on stderr (:data:`COMPILE_NOTICE`); a run that
finds every kernel it uses in the cache prints nothing.

:func:`get_backend` gives the :class:`Backend` object for a choice: a model resolves it once and
passes it to its system matrix, springs and preconditioner, which dispatch through it.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

ACCELERATORS = ("auto", "numba", "numpy")
_ENV = "IMPLICIT_CLOTH_ACCELERATOR"
_THREADS_ENV = "IMPLICIT_CLOTH_THREADS"
_default: str | None = None
_threads: int | None = None


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


def threads() -> int:
    """Threads the compiled solver may use: :func:`set_threads`, else ``$IMPLICIT_CLOTH_THREADS``, else 1.

    Only the numba back-end uses more than one, and only on multigrid levels of at least
    :func:`thread_min_vertices` vertices (16384 under every threading layer; GNU OpenMP's, which the kernels
    ask numba for first, :mod:`implicit_cloth.kernels.layer`, included):
    the products, smoothing sweeps, transfers, CG's updates and, from 16384 fine vertices, its dot products,
    and the Galerkin refresh; the springs' assembly from the same size. The numbers are the same for every thread
    count: the chunks, not the threads, decide what is summed where, so a run is reproducible bit for bit.
    One thread by default: on the shared 2-core test machine a second thread was slower whenever other work
    held the other core (docs/benchmarks.md, "Both cores: the threading layer"). BLAS threads are a separate setting
    (``Simulator(blas_threads=1)`` by default).
    """
    if _threads is not None:
        return _threads
    raw = os.environ.get(_THREADS_ENV, "").strip()
    if raw:
        try:
            n = int(raw)
        except ValueError:
            raise ValueError(f"{_THREADS_ENV}: must be an integer >= 1, got {raw!r}") from None
        if n < 1:
            raise ValueError(f"{_THREADS_ENV}: must be an integer >= 1, got {raw!r}")
        return n
    return 1


def set_threads(n: int | None) -> None:
    """Set (or with ``None`` reset to the environment's) number of solver threads (see :func:`threads`)."""
    global _threads
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"threads: must be an integer >= 1, got {n!r}")
    _threads = n


@contextmanager
def using_threads(n: int | None) -> Iterator[None]:
    """:func:`set_threads` for the duration of a ``with`` block, the setting before restored after it."""
    global _threads
    before = _threads
    set_threads(n)
    try:
        yield
    finally:
        _threads = before


#: Levels with at least this many vertices run their passes on threads when more than one is allowed
#: (:func:`threads`) and numba's threading layer is GNU OpenMP's (see
#: :mod:`implicit_cloth.kernels.layer`); below it a parallel region costs more than it saves. Measured
#: (2026-12-06, the hanging peer scene one step a frame, 2 threads against 1): with OpenMP's threads spinning
#: between regions, from 1024 vertices 1.30 / 1.58 / 1.59x at 64² / 128² / 256² (CG's sums still serial;
#: from 16384, 1.0 / 1.3x at 64² / 128²); with them sleeping, as the library sets them, each region pays a
#: wake-up and from 1024 vertices the 32² cloth took 3.4-3.9 ms a step on two threads against 2.4-3.0 on one,
#: the 256² cloth 212-234 against 184-216 from 4096. From 4096 the 64² cloth then gained 1.09x on a quiet
#: machine, but on a busier evening (2026-12-06, a later session, alternating in one process) it lost: the
#: hanging 64² step 15.1-16.4 ms on two threads from 4096 against 13.2-13.7 from 16384 (one thread 14.1-15.5),
#: the shared 64² drape 122-162 against 106 ms a frame, while 128² and 256² were level either way (hanging
#: 55-57 / 251-308 against 53-61 / 259-273 ms, the 128² drape's landing 925 against 871). A second thread on a
#: 4096-vertex level wins at most a tenth and can lose a third, so levels run on threads from 16384 vertices.
THREAD_MIN_VERTICES = 16384
#: The same threshold under TBB's layer or numba's work queue, where a second thread joins a short region late
#: (from 1024 vertices two threads took 2.1x / 1.6x one's time at 64², 0.87x / 1.1x at 128²).
THREAD_MIN_VERTICES_OTHER_LAYERS = 16384


def thread_min_vertices() -> int:
    """The smallest level run on threads, for the threading layer this process runs (launched if need be)."""
    from .kernels import layer

    if layer.launch() == "omp":
        return THREAD_MIN_VERTICES
    return max(THREAD_MIN_VERTICES, THREAD_MIN_VERTICES_OTHER_LAYERS)


#: Chunks every threaded pass is cut into (fixed: the chunks, not the threads, decide what is summed where,
#: so every thread count gives the same numbers).
THREAD_CHUNKS = 8


def set_numba_threads() -> None:
    """Let numba's parallel regions use :func:`implicit_cloth.backend.threads` threads (at most its pool)."""
    from numba import config, set_num_threads

    pool = int(config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    set_num_threads(max(1, min(threads(), pool)))


@contextmanager
def one_numba_thread() -> Iterator[None]:
    """Numba's parallel regions on one thread for the duration of a ``with`` block (the count before restored
    after it): a kernel compiled as a parallel region for its speed on one thread (numba's parallel lowering
    vectorises loops its serial lowering does not), on a cloth below :func:`thread_min_vertices`."""
    from numba import get_num_threads, set_num_threads

    before = get_num_threads()
    set_num_threads(1)
    try:
        yield
    finally:
        set_num_threads(before)


def resolve(name: str | None = None) -> str:
    """``"numba"`` or ``"numpy"`` for a requested accelerator (``None``: the default).

    Raises ``ValueError`` when numba is requested explicitly but not installed.
    """
    name = default_accelerator() if name is None else _check(name, "accelerator")
    if name == "auto":
        return "numba" if numba_available() else "numpy"
    if name == "numba" and not numba_available():
        raise ValueError("accelerator: numba is not installed (a dependency of implicit_cloth: pip install numba), "
                         "got 'numba'")
    return name


#: What the first compilation of a process says on stderr (once; nothing when every kernel comes from the cache).
COMPILE_NOTICE = "implicit_cloth: compiling numba kernels (first run only, cached afterwards)..."
_notice: object = None


def announce_compiles() -> None:
    """Say :data:`COMPILE_NOTICE` on stderr at the first numba compilation of this process, once.

    A listener on numba's ``numba:compile`` event, which numba fires only when it compiles, never when it loads
    a kernel from its cache: so a run with a warm cache says nothing, and a cold one says it once, before the
    wait. Installed by the numba back-end (:class:`NumbaBackend`), idempotent.
    """
    global _notice
    if _notice is not None:
        return
    from numba.core import event

    class _Notice(event.Listener):
        said = False

        def on_start(self, ev: event.Event) -> None:
            if not self.said:
                self.said = True
                print(COMPILE_NOTICE, file=sys.stderr, flush=True)

        def on_end(self, ev: event.Event) -> None:
            pass

    _notice = _Notice()
    event.register("numba:compile", _notice)



class BackendMismatch(RuntimeError):
    """A compiled path was asked to work on data it was not set up for (a bug in the caller, never a fallback)."""


class Backend:
    """The numerical back-end of a model, resolved once (:func:`get_backend`) and passed to what it builds.

    The assembly (:class:`~implicit_cloth.assembly.SystemMatrix`), the springs and the multigrid
    preconditioner dispatch through it: this class is the numpy reference; :class:`NumbaBackend`
    runs the same passes compiled. ``name`` is what the run report calls it.
    """

    name = "numpy"
    #: whether the compiled kernels run (the springs and the multigrid PCG choose their path from it)
    compiled = False

    def threaded(self, n: int) -> bool:
        """Whether passes over a cloth of ``n`` vertices run on threads (never on numpy's path)."""
        return False

    def __repr__(self) -> str:
        return f"Backend({self.name!r})"

    # ----------------------------------------------------------------- assembly passes
    def reset_diagonal(self, blocks: np.ndarray, diag_index: np.ndarray, d: np.ndarray) -> None:
        """Zero every block, then set diagonal block i to ``d[i] I``."""
        blocks.fill(0.0)
        self.add_diagonal(blocks, diag_index, d)

    def add_diagonal(self, blocks: np.ndarray, diag_index: np.ndarray, d: np.ndarray) -> None:
        """Add ``d[i] I`` to diagonal block i."""
        for a in range(3):
            blocks[diag_index, a, a] += d

    def blocks_to_csr(self, blocks: np.ndarray, bptr: np.ndarray, perm: np.ndarray, data: np.ndarray) -> None:
        """Copy the (n_blocks, 3, 3) block values into a CSR value array (``perm``: the numpy path's index)."""
        np.take(blocks.reshape(-1), perm, out=data)

    # ----------------------------------------------------------------- springs
    def spring_lengths(self, x: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``|x_j - x_i|`` of every spring, m."""
        d = x[j] - x[i]
        return np.sqrt(np.einsum("ij,ij->i", d, d))

    # ----------------------------------------------------------------- strain limiting
    def limit_strain(self, x: np.ndarray, i: np.ndarray, j: np.ndarray, limit: np.ndarray, share_i: np.ndarray,
                     share_j: np.ndarray, classes: list[np.ndarray], tolerance: float, max_passes: int,
                     planes: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
                     lower: np.ndarray | None = None) -> tuple[int, int, np.ndarray]:
        """Provot's passes over ``x`` in place (:mod:`implicit_cloth.strain_limit`): at most ``max_passes``
        Gauss-Seidel passes over the colour ``classes``, each correcting the springs outside their bounds at its
        start (longer than ``limit``, or shorter than ``lower`` where given) and then putting the vertices of
        ``planes`` = ``(idx, n, offset)`` below their plane back on it.
        Returns ``(passes made, springs outside their bounds before the first, how far each plane pushed its
        vertex along its normal over all passes, m)``."""
        first = passes = 0
        pushed = np.zeros(0 if planes is None else len(planes[0]))
        tiny = np.finfo(float).tiny
        lo = np.zeros(len(i)) if lower is None else lower
        for it in range(max_passes):
            d = x[j] - x[i]
            l = np.sqrt(np.einsum("ij,ij->i", d, d))
            over = (l - limit > tolerance * limit) | (lo - l > tolerance * limit)
            if it == 0:
                first = int(over.sum())
            if not over.any():
                break
            passes += 1
            for cls in classes:          # Gauss-Seidel over the colour classes (a few tens of them)
                cls = cls[over[cls]]
                if not len(cls):
                    continue
                iv, jv = i[cls], j[cls]
                d = x[jv] - x[iv]
                l = np.sqrt(np.einsum("ij,ij->i", d, d))
                e = np.where(l > limit[cls], l - limit[cls], np.minimum(l - lo[cls], 0.0))
                corr = (e / np.maximum(l, tiny))[:, None] * d   # e n: shortens (e > 0) or lengthens (e < 0)
                x[iv] += share_i[cls][:, None] * corr   # no vertex twice in a class: plain indexing
                x[jv] -= share_j[cls][:, None] * corr
            if planes is not None:
                ci, cn, co = planes
                below = np.maximum(co - np.einsum("ij,ij->i", cn, x[ci]), 0.0)
                x[ci] += below[:, None] * cn
                pushed += below
        return passes, first, pushed


class NumbaBackend(Backend):
    """The compiled kernels: the same passes as :class:`Backend`, same values."""

    name = "numba"
    compiled = True

    def __init__(self) -> None:
        from .kernels import assembly as _kernels  # noqa: F401  (imports numba; kernels compile or load from cache on use)

        announce_compiles()

    def threaded(self, n: int) -> bool:
        """Whether the compiled passes over a cloth of ``n`` vertices run on threads: more than one allowed
        (:func:`threads`) and ``n`` at least the multigrid's threaded level size
        (:func:`thread_min_vertices`); numba's thread count set if so. The
        threaded passes give the serial ones' numbers."""
        if threads() <= 1 or n < thread_min_vertices():
            return False
        set_numba_threads()
        return True

    def reset_diagonal(self, blocks: np.ndarray, diag_index: np.ndarray, d: np.ndarray) -> None:
        from .kernels.assembly import preset_diagonal, reset_diagonal

        (preset_diagonal if self.threaded(len(diag_index)) else reset_diagonal)(blocks, diag_index, d)

    def add_diagonal(self, blocks: np.ndarray, diag_index: np.ndarray, d: np.ndarray) -> None:
        from .kernels.assembly import add_diagonal

        add_diagonal(blocks, diag_index, d)

    def blocks_to_csr(self, blocks: np.ndarray, bptr: np.ndarray, perm: np.ndarray, data: np.ndarray) -> None:
        from .kernels.assembly import blocks_to_csr, pblocks_to_csr

        (pblocks_to_csr if self.threaded(len(bptr) - 1) else blocks_to_csr)(bptr, blocks, data)

    def block_matvec(self, blocks: np.ndarray, bptr: np.ndarray, bcols: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``A x`` from the blocks themselves (the CSR product's numbers, without the CSR copy)."""
        from .kernels.assembly import block_matvec, pblock_matvec

        y = np.empty(len(x))
        (pblock_matvec if self.threaded(len(bptr) - 1) else block_matvec)(bptr, bcols, blocks, x, y)
        return y

    def spring_lengths(self, x: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        from .kernels.springs import spring_lengths

        out = np.empty(len(i))
        spring_lengths(np.ascontiguousarray(x, dtype=float), i, j, out)
        return out

    def limit_strain(self, x: np.ndarray, i: np.ndarray, j: np.ndarray, limit: np.ndarray, share_i: np.ndarray,
                     share_j: np.ndarray, classes: list[np.ndarray], tolerance: float, max_passes: int,
                     planes: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
                     lower: np.ndarray | None = None) -> tuple[int, int, np.ndarray]:
        from .kernels.strain import empty_planes, limit_passes

        ci, cn, co = empty_planes() if planes is None else planes
        order = np.concatenate(classes) if classes else np.zeros(0, dtype=np.int64)
        pushed = np.zeros(len(ci))
        lo = np.zeros(len(i)) if lower is None else np.ascontiguousarray(lower, dtype=float)
        passes, first = limit_passes(x, i, j, lo, limit, share_i, share_j, order, np.zeros(len(i), dtype=np.bool_),
                                     float(tolerance), int(max_passes), np.asarray(ci, dtype=np.int64),
                                     np.ascontiguousarray(cn, dtype=float), np.ascontiguousarray(co, dtype=float),
                                     pushed)
        return int(passes), int(first), pushed


_BACKENDS: dict[str, Backend] = {}


def get_backend(name: str | Backend | None = None) -> Backend:
    """The back-end for a requested accelerator (``None``: the process default, see :func:`resolve`).

    One object per back-end and process; a :class:`Backend` is returned as it is.
    """
    if isinstance(name, Backend):
        return name
    key = resolve(name)
    if key not in _BACKENDS:
        _BACKENDS[key] = NumbaBackend() if key == "numba" else Backend()
    return _BACKENDS[key]
