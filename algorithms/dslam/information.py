"""D-SLAM's information matrix I and vector i (eq. 6 of [1]_), stored exactly sparse in 2x2 blocks.

Block ``(a, b)`` couples features ``a`` and ``b``; it is nonzero only when the two were observed
together (section 3.2): eq. (10) adds ``grad H^T R^-1 grad H``, dense over the features of one
scan and zero elsewhere, and there is no prediction step to fill the matrix in.

Storage: the upper-triangle blocks live in one growing array (capacity doubling) addressed by a
dict keyed by feature pair, and each feature keeps the list of its neighbours with the slots of
the shared blocks. An update by eq. (10) on k features writes k(k+1)/2 blocks in place: O(k^2),
whatever N. Local operations (the recovery of the features near the robot,
:mod:`slamreplay.algorithms.dslam.recovery`) read the blocks of a set of rows through the neighbour lists,
in time proportional to the blocks read. Only global operations (a full PCG or a direct solve,
which are O(N) or more anyway) assemble a CSR matrix, cached until the next update.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, eqs. (6), (10), sections 3.2-3.3.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def dofs(features: I64 | list[int]) -> I64:
    """The 2k state indices (x, y interleaved) of k features."""
    f = np.asarray(features, dtype=np.int64)
    out = np.empty(2 * len(f), dtype=np.int64)
    out[0::2] = 2 * f
    out[1::2] = out[0::2] + 1
    return out


def _grown(a: NDArray, size: int) -> NDArray:  # type: ignore[type-arg]
    """``a`` with room for at least ``size`` rows (capacity doubling; the new rows are zero)."""
    if len(a) >= size:
        return a
    out = np.zeros((max(size, 2 * len(a)),) + a.shape[1:], dtype=a.dtype)
    out[: len(a)] = a
    return out


class InformationMatrix:
    """The sparse information matrix I (2N, 2N) and vector i (2N,) of N features."""

    def __init__(self) -> None:
        self.n = 0
        self._vec = np.zeros(64)
        self._values = np.zeros((64, 2, 2))
        self._rows = np.zeros(64, dtype=np.int64)
        self._cols = np.zeros(64, dtype=np.int64)
        self._slots: dict[tuple[int, int], int] = {}
        self._diag = np.zeros(32, dtype=np.int64)  # slot of each feature's diagonal block
        self.neighbours: list[set[int]] = []
        self._adj: list[list[int]] = []  # per feature: neighbours, then (same order) the shared slots
        self._adj_slots: list[list[int]] = []
        self.version = 0  # incremented by every update
        self._csr: tuple[int, sp.csr_matrix] | None = None

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

    @property
    def nbytes(self) -> int:
        """Bytes of the numeric arrays (blocks, their indices, i): O(N + links)."""
        return self._vec.nbytes + self._values.nbytes + self._rows.nbytes + self._cols.nbytes + self._diag.nbytes

    def add_features(self, k: int) -> I64:
        """Append ``k`` features with zero information; returns their indices."""
        new = np.arange(self.n, self.n + k, dtype=np.int64)
        self.n += k
        self._vec = _grown(self._vec, 2 * self.n)
        self._diag = _grown(self._diag, self.n)
        for f in new.tolist():
            self.neighbours.append(set())
            self._adj.append([])
            self._adj_slots.append([])
            self._diag[f] = self._slot(f, f)
        self.version += 1
        return new

    def _slot(self, a: int, b: int) -> int:
        key = (a, b) if a <= b else (b, a)
        slot = self._slots.get(key)
        if slot is None:
            slot = len(self._slots)
            if slot == len(self._values):
                self._values = _grown(self._values, slot + 1)
                self._rows = _grown(self._rows, slot + 1)
                self._cols = _grown(self._cols, slot + 1)
            self._slots[key] = slot
            self._rows[slot], self._cols[slot] = key
            if a != b:
                self.neighbours[a].add(b)
                self.neighbours[b].add(a)
                self._adj[a].append(b)
                self._adj_slots[a].append(slot)
                self._adj[b].append(a)
                self._adj_slots[b].append(slot)
        return slot

    def add(self, features: I64, d_matrix: F64, d_vector: F64) -> None:
        """Eq. (10): ``I += d_matrix`` and ``i += d_vector`` on the dofs of ``features`` (k,).

        ``d_matrix`` (2k, 2k) must be symmetric; it links every pair of the k features. O(k^2).
        """
        f = np.asarray(features, dtype=np.int64)
        k = len(f)
        if d_matrix.shape != (2 * k, 2 * k) or d_vector.shape != (2 * k,):
            raise ValueError(f"d_matrix must be ({2 * k}, {2 * k}) and d_vector ({2 * k},), "
                             f"got {d_matrix.shape} and {d_vector.shape}")
        fl = f.tolist()
        if len(set(fl)) != k or any(a < 0 or a >= self.n for a in fl):
            raise ValueError(f"features must be distinct indices in [0, {self.n}), got {fl}")
        self._vec[dofs(f)] += d_vector
        p, q = np.triu_indices(k)
        slots = np.fromiter((self._slot(fl[a], fl[b]) for a, b in zip(p.tolist(), q.tolist(), strict=True)),
                            dtype=np.int64, count=len(p))
        blocks = np.asarray(d_matrix, dtype=np.float64).reshape(k, 2, k, 2).transpose(0, 2, 1, 3)[p, q]
        flip = f[p] > f[q]
        blocks[flip] = blocks[flip].transpose(0, 2, 1)
        self._values[slots] += blocks  # one slot per pair: no repeated index
        self.version += 1

    def diagonal_blocks(self, features: I64 | list[int] | None = None) -> F64:
        """The diagonal blocks I_ff (k, 2, 2) of ``features`` (all when None)."""
        diag = self._diag[: self.n]
        return self._values[diag if features is None else diag[np.asarray(features, dtype=np.int64)]].copy()

    def row_blocks(self, features: list[int]) -> tuple[I64, I64, F64]:
        """The stored blocks of the block rows ``features``: (position in ``features``, column feature, I_fg (2, 2)).

        Each block row lists its diagonal block and one block per neighbour; O(blocks read).
        """
        cols_l: list[int] = []
        slots_l: list[int] = []
        lengths = np.empty(len(features), dtype=np.int64)
        diag = self._diag
        for k, f in enumerate(features):
            cols_l.append(f)
            cols_l.extend(self._adj[f])
            slots_l.append(int(diag[f]))
            slots_l.extend(self._adj_slots[f])
            lengths[k] = len(self._adj[f]) + 1
        cols = np.array(cols_l, dtype=np.int64)
        slots = np.array(slots_l, dtype=np.int64)
        pos = np.repeat(np.arange(len(features)), lengths)
        vals = self._values[slots]
        flip = np.asarray(features, dtype=np.int64)[pos] > cols  # stored as (min, max): transpose
        vals[flip] = vals[flip].transpose(0, 2, 1)
        return pos, cols, vals

    def csr(self) -> sp.csr_matrix:
        """I as a CSR matrix (2N, 2N), assembled from the blocks and cached until the next update."""
        if self._csr is not None and self._csr[0] == self.version:
            return self._csr[1]
        nb = len(self._slots)
        rows, cols, vals = self._rows[:nb], self._cols[:nb], self._values[:nb]
        off = rows != cols
        ii, jj = np.meshgrid([0, 1], [0, 1], indexing="ij")
        r = np.concatenate([(2 * rows[:, None, None] + ii).reshape(-1),
                            (2 * cols[off][:, None, None] + jj).reshape(-1)])
        c = np.concatenate([(2 * cols[:, None, None] + jj).reshape(-1),
                            (2 * rows[off][:, None, None] + ii).reshape(-1)])
        v = np.concatenate([vals.reshape(-1), vals[off].reshape(-1)])
        mat = sp.csr_matrix((v, (r, c)), shape=(2 * self.n, 2 * self.n))
        self._csr = (self.version, mat)
        return mat

    def matvec(self, x: F64) -> F64:
        """I @ x for x (2N,) or (2N, k): a global product (assembles the CSR matrix when stale)."""
        return cast(F64, self.csr() @ x)

    def csc(self) -> sp.csc_matrix:
        """I as one CSC matrix (for a direct solve)."""
        return self.csr().tocsc()

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
