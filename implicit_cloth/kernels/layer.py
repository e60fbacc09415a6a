"""The numba threading layer the kernels' parallel regions run on: GNU OpenMP's first.

The kernels' parallel regions are short: one level's pass of a V-cycle takes 0.05-1.3 ms at 256², and a
CG iteration opens about twenty of them. Measured on the 2-core test machine (2026-12-06, numba 0.68; ``python
benchmarks/studies/threads_layer.py``): under TBB's layer (numba's first choice when ``libtbb`` is installed, as
Blender's Debian package installs it) a second thread joined a 0.15 ms region too late to take any of its
work, so short regions ran no faster on two threads than on one; under OpenMP's the same region ran twice
as fast. So, unless the user chose a layer
(``NUMBA_THREADING_LAYER`` or ``NUMBA_THREADING_LAYER_PRIORITY`` in the environment, or
``numba.config.THREADING_LAYER`` set before), numba tries ``omp``, then ``tbb``, then ``workqueue``, and
takes the first that loads. This is set on import of :mod:`implicit_cloth.kernels.pcg`, before any of
its parallel regions can launch the layer (numba chooses it at the first one, once per process).

Its threads wait for work sleeping (``OMP_WAIT_POLICY=PASSIVE``, unless the user set a policy): spinning,
two threads became nine times slower than one whenever the other core was busy (see :data:`WAIT_POLICY`).

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

#: GNU OpenMP's threads wait at a region's end by sleeping, unless the user set a policy
#: (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT``). libgomp's own default spins first: with the other core busy
#: (another process, a second batch worker) each of the V-cycle's regions then waited for a descheduled
#: spinning thread, and two threads took 9 times one thread's time (128² peer scene: 450 against 48 ms a
#: step); sleeping, 52 against 48, while on free cores it is 4-8 % slower than spinning (30.4 against 27.8 ms;
#: ``benchmarks/results/threads_layer.md``).
#: Read by libgomp when it loads (numba's first parallel region); no effect if it was loaded before.
WAIT_POLICY = "PASSIVE"
if not os.environ.get("OMP_WAIT_POLICY") and not os.environ.get("GOMP_SPINCOUNT"):
    os.environ["OMP_WAIT_POLICY"] = WAIT_POLICY


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
