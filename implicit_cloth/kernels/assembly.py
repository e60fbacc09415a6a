"""Compiled (numba) passes of :class:`implicit_cloth.assembly.SystemMatrix`: the optional accelerator.

* :func:`blocks_to_csr` is :meth:`SystemMatrix.finalize`'s copy of the
  (n_blocks, 3, 3) block values into the CSR value array, written as the block
  transpose it is (scalar row ``3 r + a`` of block row ``r`` holds the ``a``-th
  row of each of its blocks, in column order), so it streams through both
  arrays and needs no 9 n_blocks permutation index (numpy's reference is
  ``np.take`` through that index).
* :func:`reset_diagonal` zeroes every block and writes ``d_i I`` on the diagonal
  blocks (the mass matrix) in one pass; :func:`add_diagonal` adds ``d_i I``.

Same values as the numpy path (copies, no arithmetic). Each has a threaded twin (``p`` prefix, numba
``prange`` over block rows, each row written by one thread the same way: the same numbers), which the
back-end runs where the solver's passes run on threads (:meth:`implicit_cloth.backend.Backend.threaded`).
Compiled with ``cache=True``. Importing this module imports numba.
"""

from __future__ import annotations

from numba import njit, prange


@njit(cache=True, inline="always")
def _csr_row(r, bptr, blocks, data):
    b0 = bptr[r]
    kr = bptr[r + 1] - b0
    base = 9 * b0
    for a in range(3):
        p = base + 3 * kr * a
        for m in range(kr):
            data[p] = blocks[b0 + m, a, 0]
            data[p + 1] = blocks[b0 + m, a, 1]
            data[p + 2] = blocks[b0 + m, a, 2]
            p += 3


@njit(cache=True)
def blocks_to_csr(bptr, blocks, data):
    """``data[...] = blocks`` in CSR order (see the module docstring); ``bptr`` are the block-row pointers."""
    for r in range(bptr.shape[0] - 1):
        _csr_row(r, bptr, blocks, data)


@njit(cache=True, parallel=True)
def pblocks_to_csr(bptr, blocks, data):
    """:func:`blocks_to_csr` on threads."""
    for r in prange(bptr.shape[0] - 1):
        _csr_row(r, bptr, blocks, data)


@njit(cache=True, inline="always")
def _matvec_row(r, bptr, bcols, blocks, x, y):
    for a in range(3):
        s = 0.0
        for b in range(bptr[r], bptr[r + 1]):
            c = 3 * bcols[b]
            s += blocks[b, a, 0] * x[c]
            s += blocks[b, a, 1] * x[c + 1]
            s += blocks[b, a, 2] * x[c + 2]
        y[3 * r + a] = s


@njit(cache=True)
def block_matvec(bptr, bcols, blocks, x, y):
    """``y = A x`` from the (n_blocks, 3, 3) blocks in block-row order (``bptr``, columns ``bcols`` sorted): each
    scalar row summed over its blocks, then each block's three columns, from 0 (scipy's CSR product of the same
    matrix does the same additions in the same order, without fused multiply-adds: the same numbers)."""
    for r in range(bptr.shape[0] - 1):
        _matvec_row(r, bptr, bcols, blocks, x, y)


@njit(cache=True, parallel=True)
def pblock_matvec(bptr, bcols, blocks, x, y):
    """:func:`block_matvec` on threads (each row's sums as there: the same numbers)."""
    for r in prange(bptr.shape[0] - 1):
        _matvec_row(r, bptr, bcols, blocks, x, y)


@njit(cache=True)
def reset_diagonal(blocks, diag_index, diag):
    """``blocks[:] = 0`` then ``blocks[diag_index[i]] = diag[i] I`` for every vertex i."""
    blocks[:] = 0.0
    for i in range(diag_index.shape[0]):
        b = diag_index[i]
        blocks[b, 0, 0] = diag[i]
        blocks[b, 1, 1] = diag[i]
        blocks[b, 2, 2] = diag[i]


@njit(cache=True, parallel=True)
def preset_diagonal(blocks, diag_index, diag):
    """:func:`reset_diagonal` on threads."""
    flat = blocks.reshape(-1)
    for k in prange(flat.shape[0]):
        flat[k] = 0.0
    for i in prange(diag_index.shape[0]):
        b = diag_index[i]
        blocks[b, 0, 0] = diag[i]
        blocks[b, 1, 1] = diag[i]
        blocks[b, 2, 2] = diag[i]


@njit(cache=True)
def add_diagonal(blocks, diag_index, diag):
    """``blocks[diag_index[i]] += diag[i] I`` for every vertex i."""
    for i in range(diag_index.shape[0]):
        b = diag_index[i]
        blocks[b, 0, 0] += diag[i]
        blocks[b, 1, 1] += diag[i]
        blocks[b, 2, 2] += diag[i]
