"""Fixed-pattern block-sparse system matrix.

The implicit integrators solve ``A dv = b`` with ``A = M - c_v dF/dv - c_x dF/dx``
(a 3N x 3N matrix made of 3x3 blocks). Its block pattern depends only on the
cloth's topology, so it is built once: the diagonal blocks plus one block for
each ordered pair of vertices coupled by a force term. Every step only refills
the values:

1. each effect writes its 3x3 blocks into :attr:`SystemMatrix.blocks`
   (shape ``(n_blocks, 3, 3)``) through index maps it computed once at bind time
   (:meth:`block_index`), typically with one sparse scatter product, and
2. :meth:`SystemMatrix.finalize` gathers the blocks into the value array of a
   CSR matrix whose ``indptr``/``indices`` never change (no COO->CSR
   conversion, no Python loop over springs).

:meth:`~SystemMatrix.reset_diagonal`, :meth:`~SystemMatrix.add_diagonal` and
:meth:`~SystemMatrix.finalize` run through the matrix's :class:`~implicit_cloth.backend.Backend`
(the model's): numpy is the reference, numba runs compiled passes
(:mod:`implicit_cloth.kernels.assembly`) with the same values.

CSR rather than BSR: scipy's CSR mat-vec was measured 5-10 % faster here.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .backend import Backend, get_backend


class SystemMatrix:
    """A 3N x 3N sparse matrix with a fixed 3x3 block pattern.

    Parameters
    ----------
    n : int
        Number of vertices.
    pairs : (P, 2) int array
        Vertex pairs coupled by some force term. Both ``(i, j)`` and ``(j, i)``
        blocks are created; duplicates and self-pairs are merged.
    accelerator : Backend, {"auto", "numba", "numpy"} or None
        The back-end of :meth:`reset_diagonal`, :meth:`add_diagonal` and :meth:`finalize`
        (a model passes its own; ``None``: the process default, see :mod:`implicit_cloth.backend`).
    """

    def __init__(self, n: int, pairs: np.ndarray, accelerator: str | Backend | None = None) -> None:
        self.n = int(n)
        #: the back-end the matrix is assembled with (the springs bound to it follow it)
        self.backend = get_backend(accelerator)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        diag = np.arange(n, dtype=np.int64)
        rows = np.concatenate([diag, pairs[:, 0], pairs[:, 1]])
        cols = np.concatenate([diag, pairs[:, 1], pairs[:, 0]])
        keys = np.unique(rows * n + cols)            # sorted by (row, col)
        self._keys = keys
        brow, bcol = keys // n, keys % n
        self.n_blocks = len(keys)
        self.block_rows, self.block_cols = brow, bcol
        counts = np.bincount(brow, minlength=n)
        bptr = np.concatenate([[0], np.cumsum(counts)])
        self.diag_index = self.block_index(diag, diag)
        #: (n_blocks, 3, 3) block values, refilled every step
        self.blocks = np.zeros((self.n_blocks, 3, 3))
        #: block-row pointers: row i's blocks are ``bptr[i]:bptr[i+1]`` (columns ``block_cols``, sorted)
        self.bptr = bptr.astype(np.int64)
        #: bumped by every :meth:`finalize`: tells whether :attr:`csr` still holds the values a consumer saw
        self.version = 0

        # CSR structure: scalar row 3*i + a holds, for each block (i, c) in block
        # row i (in column order, position m), the entries 3*c + 0..2.
        k_row = counts[brow]                          # blocks in this block's row
        m_in_row = np.arange(self.n_blocks) - bptr[brow]
        a = np.arange(3)[None, :, None]
        b = np.arange(3)[None, None, :]
        dest = (9 * bptr[brow])[:, None, None] + a * (3 * k_row)[:, None, None] \
            + 3 * m_in_row[:, None, None] + b           # (n_blocks, 3, 3)
        self._perm = np.empty(9 * self.n_blocks, dtype=np.int64)
        self._perm[dest.ravel()] = np.arange(9 * self.n_blocks)   # csr.data = blocks.ravel()[perm]
        indptr = np.concatenate([[0], np.cumsum(np.repeat(3 * counts, 3))]).astype(np.int64)
        cols_scalar = np.empty(9 * self.n_blocks, dtype=np.int64)
        cols_scalar[dest.ravel()] = (3 * bcol[:, None, None] + b + 0 * a).ravel()
        self._csr = sp.csr_array(
            (np.zeros(9 * self.n_blocks), cols_scalar, indptr), shape=(3 * n, 3 * n))
        self._csr.has_sorted_indices = True
        #: whether the CSR values are the blocks' of the last finalize (False after :meth:`finalize_lazy`)
        self._csr_current = True

    @property
    def csr(self) -> sp.csr_array:
        """The matrix as CSR (the same object every step), its values those of the last finalize: copied from
        the blocks here on the first read after a :meth:`finalize_lazy`."""
        if not self._csr_current:
            self.backend.blocks_to_csr(self.blocks, self.bptr, self._perm, self._csr.data)
            self._csr_current = True
        return self._csr

    @property
    def shape(self) -> tuple[int, int]:
        return (3 * self.n, 3 * self.n)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        """``A @ x`` with the values of the last finalize: through :attr:`csr` when it is current, else (after a
        :meth:`finalize_lazy`, the compiled back-end) from the blocks themselves, the same numbers without the
        copy (a contact step's impulses and friction iterations: on the shared 64² drape the copy and the CSR
        product took 4.1 ms a frame)."""
        matvec = getattr(self.backend, "block_matvec", None)
        if self._csr_current or matvec is None or x.ndim != 1 or x.dtype != np.float64:
            return self.csr @ x
        return matvec(self.blocks, self.bptr, self.block_cols, np.ascontiguousarray(x))

    @property
    def accelerator(self) -> str:
        """The back-end's name: "numba" (compiled passes) or "numpy" (reference)."""
        return self.backend.name

    def block_index(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Positions in :attr:`blocks` of the blocks ``(i, j)`` (which must be in the pattern)."""
        q = np.asarray(i, dtype=np.int64) * self.n + np.asarray(j, dtype=np.int64)
        idx = np.searchsorted(self._keys, q)
        if np.any(idx >= len(self._keys)) or np.any(self._keys[np.minimum(idx, len(self._keys) - 1)] != q):
            raise ValueError("block not in the sparsity pattern")
        return idx

    def has_blocks(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Whether each block ``(i, j)`` is in the pattern, (K,) bool."""
        q = np.asarray(i, dtype=np.int64) * self.n + np.asarray(j, dtype=np.int64)
        if not len(self._keys):
            return np.zeros(len(q), dtype=bool)
        pos = np.minimum(np.searchsorted(self._keys, q), len(self._keys) - 1)
        return self._keys[pos] == q

    def pair_scatter(self, pairs: np.ndarray) -> sp.csr_array:
        """Scatter operator for symmetric pair blocks.

        Returns ``G`` of shape ``(n_blocks, P)`` such that ``G @ C.reshape(P, 9)``
        adds ``+C_p`` to blocks ``(i, i)`` and ``(j, j)`` and ``-C_p`` to blocks
        ``(i, j)`` and ``(j, i)`` of every pair ``p = (i, j)``, the structure of a
        two-point interaction whose force depends on ``x_j - x_i`` (for a
        symmetric ``C_p``).
        """
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        i, j = pairs[:, 0], pairs[:, 1]
        p = np.arange(len(pairs))
        rows = np.concatenate([self.block_index(i, i), self.block_index(j, j),
                               self.block_index(i, j), self.block_index(j, i)])
        vals = np.concatenate([np.ones(2 * len(p)), -np.ones(2 * len(p))])
        return sp.csr_array((vals, (rows, np.tile(p, 4))), shape=(self.n_blocks, len(pairs)))

    def element_index(self, elements: np.ndarray) -> tuple[np.ndarray, sp.csr_array | None]:
        """Where the blocks of elements of ``m`` vertices (triangles, hinges) go: ``(E, m * m)`` positions in
        :attr:`blocks`, element ``e``'s vertex pair ``(i, j)`` at ``[e, m i + j]`` (every pair must be in the
        pattern), and for the numpy back-end the scatter ``G`` (``n_blocks`` x ``E m^2``) with ``G @ X.reshape(-1,
        9)`` adding each element's blocks ``X[e, i, j]`` to them (None for the compiled one)."""
        elements = np.asarray(elements, dtype=np.int64)
        m = elements.shape[1]
        rows = np.repeat(elements, m, axis=1)          # (E, m^2): i of (i, j) = (0,0) (0,1) ... (1,0) ...
        cols = np.tile(elements, (1, m))
        bidx = np.ascontiguousarray(self.block_index(rows.ravel(), cols.ravel()).reshape(-1, m * m))
        if self.backend.compiled:
            return bidx, None
        k = bidx.size
        return bidx, sp.csr_array((np.ones(k), (bidx.ravel(), np.arange(k))), shape=(self.n_blocks, k))

    def reset(self) -> None:
        """Zero all block values."""
        self.blocks.fill(0.0)

    def reset_diagonal(self, d: np.ndarray) -> None:
        """Zero all block values, then set diagonal block i to ``d[i] I`` (e.g. the lumped mass matrix).

        Parameters
        ----------
        d : (N,) float array
            The diagonal values (kg for the mass matrix).
        """
        self.backend.reset_diagonal(self.blocks, self.diag_index, self._diagonal_values(d, "reset_diagonal"))

    def add_diagonal(self, d: np.ndarray) -> None:
        """Add ``d[i] I`` to diagonal block i (e.g. ``c_v c A_i`` of linear drag), ``d`` of shape (N,)."""
        self.backend.add_diagonal(self.blocks, self.diag_index, self._diagonal_values(d, "add_diagonal"))

    def _diagonal_values(self, d: np.ndarray, what: str) -> np.ndarray:
        d = np.ascontiguousarray(d, dtype=float)
        if d.shape != (self.n,):
            raise ValueError(f"{what}: expected {self.n} diagonal values, got shape {d.shape}")
        return d

    def finalize(self) -> sp.csr_array:
        """Copy the block values into the CSR matrix and return it (same object every step).

        Bumps :attr:`version`.
        """
        self.backend.blocks_to_csr(self.blocks, self.bptr, self._perm, self._csr.data)
        self._csr_current = True
        self.version += 1
        return self._csr

    def finalize_lazy(self) -> "SystemMatrix":
        """:meth:`finalize` without the copy, which the first read of :attr:`csr` (or ``self @ x``) makes: the
        compiled solver reads the blocks themselves, so a step that needs no CSR product (a free cloth's) skips
        one pass over the matrix (10 ms a step at 256²). Returns the matrix itself, which multiplies like the
        CSR one. The blocks must then stay as they are until that read or the next finalize."""
        self._csr_current = False
        self.version += 1
        return self

    def diagonal_blocks(self) -> np.ndarray:
        """The (N, 3, 3) diagonal blocks (a view-free copy)."""
        return self.blocks[self.diag_index]


def accumulate_product(G: sp.csr_array, X: np.ndarray, Y: np.ndarray) -> None:
    """``Y += G @ X`` for CSR ``G`` and C-contiguous 2-D ``X``, ``Y``, without a temporary.

    Uses scipy's compiled CSR kernel directly (twice as fast at 256² as
    ``Y += G @ X``, which allocates and page-faults a fresh result every step);
    falls back to the public product if that kernel is unavailable.
    """
    try:
        from scipy.sparse import _sparsetools

        _sparsetools.csr_matvecs(G.shape[0], G.shape[1], X.shape[1], G.indptr, G.indices, G.data,
                                 X.reshape(-1), Y.reshape(-1))
    except (ImportError, AttributeError, TypeError, ValueError):  # pragma: no cover - scipy internals moved
        Y += G @ X
