"""D-SLAM's information matrix I and vector i (eq. 6 of [1]_), stored exactly sparse in 2x2 blocks.

Block ``(a, b)`` couples features ``a`` and ``b``; it is nonzero only when the two were observed
together (section 3.2): eq. (10) adds ``grad H^T R^-1 grad H``, dense over the features of one
scan and zero elsewhere, and there is no prediction step to fill the matrix in.

Storage: the upper-triangle blocks live in one growing array addressed by a dict, with the
neighbour sets of each feature. For products, the matrix is a CSR ``base`` (rebuilt from the
blocks) plus a CSR ``delta`` holding the increments since: rebuilding ``base`` costs O(nnz) and
happens when ``delta`` exceeds a fixed fraction of it, so the cost per update stays O(1)
amortised while every product sees exactly I.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, eqs. (6), (10), sections 3.2-3.3.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
DELTA_FRACTION = 0.125  # rebuild the CSR base when the increments exceed this share of its entries
DELTA_MIN_ENTRIES = 4096


def dofs(features: I64 | list[int]) -> I64:
    """The 2k state indices (x, y interleaved) of k features."""
    f = np.asarray(features, dtype=np.int64)
    return np.stack([2 * f, 2 * f + 1], -1).reshape(-1)


class InformationMatrix:
    """The sparse information matrix I (2N, 2N) and vector i (2N,) of N features."""

    def __init__(self) -> None:
        self.n = 0
        self._vec = np.zeros(64)
        self._values = np.zeros((64, 2, 2))
        self._rows = np.zeros(64, dtype=np.int64)
        self._cols = np.zeros(64, dtype=np.int64)
        self._slots: dict[tuple[int, int], int] = {}
        self._diag: list[int] = []
        self.neighbours: list[set[int]] = []
        self._base: sp.csr_matrix | None = None
        self._delta: list[tuple[I64, I64, F64]] = []  # COO rows, columns, values of each increment
        self._delta_entries = 0
        self._delta_csr: sp.csr_matrix | None = None

    @property
    def vector(self) -> F64:
        """The information vector i (2N,), a read-only view."""
        v = self._vec[: 2 * self.n]
        v.flags.writeable = False
        return v

    @property
    def blocks(self) -> int:
        """Stored upper-triangle blocks, diagonal included."""
        return len(self._slots)

    @property
    def nnz_blocks(self) -> int:
        """Nonzero 2x2 blocks of the full symmetric matrix: N diagonal + 2 per link."""
        return self.n + 2 * (len(self._slots) - self.n)

    def add_features(self, k: int) -> I64:
        """Append ``k`` features with zero information; returns their indices."""
        new = np.arange(self.n, self.n + k, dtype=np.int64)
        self.n += k
        while len(self._vec) < 2 * self.n:
            self._vec = np.concatenate([self._vec, np.zeros_like(self._vec)])
        for f in new.tolist():
            self._diag.append(self._slot(f, f))
            self.neighbours.append(set())
        return new

    def _slot(self, a: int, b: int) -> int:
        key = (a, b) if a <= b else (b, a)
        slot = self._slots.get(key)
        if slot is None:
            slot = len(self._slots)
            if slot == len(self._values):
                self._values = np.concatenate([self._values, np.zeros_like(self._values)])
                self._rows = np.concatenate([self._rows, np.zeros_like(self._rows)])
                self._cols = np.concatenate([self._cols, np.zeros_like(self._cols)])
            self._slots[key] = slot
            self._rows[slot], self._cols[slot] = key
            if a != b:
                self.neighbours[a].add(b)
                self.neighbours[b].add(a)
        return slot

    def add(self, features: I64, d_matrix: F64, d_vector: F64) -> None:
        """Eq. (10): ``I += d_matrix`` and ``i += d_vector`` on the dofs of ``features`` (k,).

        ``d_matrix`` (2k, 2k) must be symmetric; it links every pair of the k features.
        """
        f = np.asarray(features, dtype=np.int64)
        k = len(f)
        if d_matrix.shape != (2 * k, 2 * k) or d_vector.shape != (2 * k,):
            raise ValueError(f"d_matrix must be ({2 * k}, {2 * k}) and d_vector ({2 * k},), "
                             f"got {d_matrix.shape} and {d_vector.shape}")
        if len(np.unique(f)) != k or np.any(f < 0) or np.any(f >= self.n):
            raise ValueError(f"features must be distinct indices in [0, {self.n}), got {f.tolist()}")
        idx = dofs(f)
        self._vec[idx] += d_vector
        fl = f.tolist()
        for p in range(k):
            for q in range(p, k):
                a, b = fl[p], fl[q]
                block = d_matrix[2 * p:2 * p + 2, 2 * q:2 * q + 2]
                slot = self._slot(a, b)  # may grow (replace) the value array: look it up first
                self._values[slot] += block if a <= b else block.T
        self._delta.append((np.repeat(idx, idx.size), np.tile(idx, idx.size),
                            np.array(d_matrix, dtype=np.float64).reshape(-1)))
        self._delta_entries += idx.size**2
        self._delta_csr = None

    def diagonal_blocks(self, features: I64 | None = None) -> F64:
        """The diagonal blocks I_ff (k, 2, 2) of ``features`` (all when None)."""
        diag = np.asarray(self._diag, dtype=np.int64)
        return self._values[diag if features is None else diag[np.asarray(features, dtype=np.int64)]].copy()

    def _build_base(self) -> None:
        nb = len(self._slots)
        rows, cols, vals = self._rows[:nb], self._cols[:nb], self._values[:nb]
        off = rows != cols
        ii, jj = np.meshgrid([0, 1], [0, 1], indexing="ij")
        r = np.concatenate([(2 * rows[:, None, None] + ii).reshape(-1),
                            (2 * cols[off][:, None, None] + jj).reshape(-1)])
        c = np.concatenate([(2 * cols[:, None, None] + jj).reshape(-1),
                            (2 * rows[off][:, None, None] + ii).reshape(-1)])
        v = np.concatenate([vals.reshape(-1), vals[off].reshape(-1)])
        self._base = sp.csr_matrix((v, (r, c)), shape=(2 * self.n, 2 * self.n))
        self._delta.clear()
        self._delta_entries = 0
        self._delta_csr = None

    def matrices(self) -> tuple[sp.csr_matrix, sp.csr_matrix | None]:
        """``(base, delta)`` CSR matrices (2N, 2N) with ``I = base + delta`` (delta None when zero)."""
        base_nnz = 0 if self._base is None else self._base.nnz
        if self._base is None or self._delta_entries > max(DELTA_MIN_ENTRIES, DELTA_FRACTION * base_nnz):
            self._build_base()
        assert self._base is not None
        shape = (2 * self.n, 2 * self.n)
        if self._base.shape != shape:  # features added since the build: their rows are still zero
            pad = np.full(shape[0] - self._base.shape[0], self._base.indptr[-1])
            self._base = sp.csr_matrix((self._base.data, self._base.indices,
                                        np.concatenate([self._base.indptr, pad])), shape=shape)
        if not self._delta:
            return self._base, None
        if self._delta_csr is None or self._delta_csr.shape != shape:
            r, c, v = (np.concatenate(parts) for parts in zip(*self._delta, strict=True))
            self._delta_csr = sp.csr_matrix((v, (r, c)), shape=shape)
        return self._base, self._delta_csr

    def matvec(self, x: F64) -> F64:
        """I @ x for x (2N,) or (2N, k)."""
        base, delta = self.matrices()
        return base @ x if delta is None else base @ x + delta @ x

    def row_entries(self, idx: I64) -> tuple[I64, I64, F64]:
        """The stored entries of rows ``idx`` of I as COO triplets: (position in ``idx``, column, value).

        Entries of ``base`` and ``delta`` are listed separately (a column may appear twice: add them).
        """
        out = []
        for mat in self.matrices():
            if mat is None:
                continue
            starts, ends = mat.indptr[idx], mat.indptr[idx + 1]
            lengths = ends - starts
            total = int(lengths.sum())
            offsets = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
            pos = np.arange(total) + offsets
            out.append((np.repeat(np.arange(len(idx)), lengths), mat.indices[pos].astype(np.int64), mat.data[pos]))
        rows, cols, vals = (np.concatenate(parts) for parts in zip(*out, strict=True))
        return rows, cols, vals

    def csc(self) -> sp.csc_matrix:
        """I as one CSC matrix (for a direct solve)."""
        base, delta = self.matrices()
        return (base if delta is None else base + delta).tocsc()

    def links(self) -> I64:
        """Feature pairs (L, 2), a < b, with a nonzero off-diagonal block: the links of Fig. 3(c)."""
        nb = len(self._slots)
        off = self._rows[:nb] != self._cols[:nb]
        return np.stack([self._rows[:nb][off], self._cols[:nb][off]], -1)

    def sparsity_image(self, max_pixels: int = 512) -> NDArray[np.uint8]:
        """The block sparsity pattern (Fig. 3(d)) as a (k, k) uint8 image, 255 = nonzero block.

        With more than ``max_pixels`` features, each pixel covers a square of blocks and is lit
        when any of them is nonzero.
        """
        scale = max(1, -(-self.n // max_pixels))
        size = max(1, -(-self.n // scale))
        img = np.zeros((size, size), dtype=np.uint8)
        nb = len(self._slots)
        r, c = self._rows[:nb] // scale, self._cols[:nb] // scale
        img[r, c] = 255
        img[c, r] = 255
        return img
