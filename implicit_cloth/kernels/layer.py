"""The numba threading layer the kernels' parallel regions run on: GNU OpenMP's first.

The kernels' parallel regions are short: one level's pass of a V-cycle takes 0.05-1.3 ms at 256², and a
CG iteration opens about twenty of them. Measured on the 2-core test machine (2026-12-06, numba 0.68; ``python
benchmarks/threads_layer.py``): under TBB's layer (numba's first choice when ``libtbb`` is installed, as
Blender's Debian package installs it) a second thread joined a 0.15 ms region too late to take any of its
work, so short regions ran no faster on two threads than on one; under OpenMP's, whose threads wait
spinning a moment before they sleep, the same region ran twice as fast. So, unless the user chose a layer
(``NUMBA_THREADING_LAYER`` or ``NUMBA_THREADING_LAYER_PRIORITY`` in the environment, or
``numba.config.THREADING_LAYER`` set before), numba tries ``omp``, then ``tbb``, then ``workqueue``, and
takes the first that loads. This is set on import of :mod:`implicit_cloth.kernels.pcg`, before any of
its parallel regions can launch the layer (numba chooses it at the first one, once per process).

GNU OpenMP is not fork-safe: a process that ran a parallel region and then forks must not run one in the
child (numba stops such a child). The batch runner starts its workers by ``spawn``; a program that forks
its own workers after simulating can set ``NUMBA_THREADING_LAYER=tbb``.
"""

from __future__ import annotations

import os

import numpy as np
from numba import config, njit, prange

#: the order the layers are tried in, when the user chose none
PRIORITY = ["omp", "tbb", "workqueue"]

_ENV = ("NUMBA_THREADING_LAYER", "NUMBA_THREADING_LAYER_PRIORITY")
if not any(os.environ.get(k) for k in _ENV) and config.THREADING_LAYER == "default":  # type: ignore[attr-defined]
    config.THREADING_LAYER_PRIORITY = list(PRIORITY)  # type: ignore[attr-defined]


@njit(parallel=True, cache=True)
def _touch(a):
    for i in prange(len(a)):
        a[i] = i


def launch() -> str:
    """The layer this process's parallel regions run on, launching it (with a tiny region) if none has yet."""
    name = current()
    if name is None:
        _touch(np.zeros(2))
        name = current()
    return str(name)


def current() -> str | None:
    """The layer this process's parallel regions run on, or None before the first one launched it."""
    from numba import threading_layer

    try:
        return str(threading_layer())
    except ValueError:
        return None
