"""The compiled (numba) kernels, the default back-end: :mod:`.assembly`, :mod:`.springs`, :mod:`.pcg`.

Importing one of them (but the plain-Python :mod:`.estimate`) imports numba; nothing imports them
unless the numba back-end (:mod:`implicit_cloth.backend`) is chosen. They import nothing of the
package: plain kernels over arrays, the same arithmetic as the numpy reference paths they stand in for.
"""
