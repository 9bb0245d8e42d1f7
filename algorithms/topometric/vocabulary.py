"""Incremental binary bag of visual words with a tf-idf inverted index over locations.

Filliat (ICRA 2007) [1]_ builds the dictionary online: a descriptor farther than a threshold from
every word becomes a new word, so no offline training is needed; Bazeille and Filliat keep that
incremental dictionary in mapping mode and freeze it in navigation mode [2]_ (section III-B). Here
words are BRIEF-32 descriptors and the distance is Hamming's; a word keeps the descriptor that
created it (no running mean: the binary mean is ill-defined and it keeps replays bit-identical).

Locations are scored by tf-idf voting through an inverted index (word -> {location: count}), so a
query costs O(words hit + postings of those words), not O(locations x words):

    score(L) = sum_w  c_q(w) c_L(w) idf(w)^2 / ||c_L||,   idf(w) = log(N / N_w),

N the number of locations, N_w those containing w, ||c_L|| the L2 norm of L's word counts
(without idf, so it needs no update when N changes; the query's own norm is a common factor,
irrelevant to the mu + sigma likelihood of :mod:`slamreplay.algorithms.topometric.bayes`).

References
----------
.. [1] D. Filliat, "A visual bag of words method for interactive qualitative localization and
   mapping", ICRA 2007.
.. [2] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, section III-A and III-B.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.topometric.features import DESCRIPTOR_BYTES

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class VocabularyConfig:
    """Attributes
    ----------
    word_radius_bits : a descriptor within this Hamming distance (of 256 bits) of its nearest word
        is that word; farther, it becomes a new word (mapping) or is dropped (navigation). BRIEF of
        one point seen twice at 320x240 is typically 10-40 bits apart, unrelated ones about 128.
    """

    word_radius_bits: int = 48

    def __post_init__(self) -> None:
        if not 0 <= self.word_radius_bits < 8 * DESCRIPTOR_BYTES:
            raise ValueError(f"word_radius_bits must be in [0, 256), got {self.word_radius_bits}")


TABLE_KEYS = 1 << 16
N_TABLES = DESCRIPTOR_BYTES  # two cuts of 16 two-byte keys
TAIL_WORDS = 64  # words added since the last merge, searched exhaustively
SMALL_WORDS = 4096  # the small table level is merged into the big one beyond max(this, big / 8) words


def _keys(desc: U8) -> NDArray[np.uint16]:
    """(n, 32) 16-bit keys: bytes (0,1), (2,3), ... and, shifted by one byte, (1,2), (3,4), ..., (31,0)."""
    a = desc.astype(np.uint16)
    shifted = np.roll(a, -1, axis=1)
    return np.concatenate([(a[:, 0::2] << 8) | a[:, 1::2], (a[:, 1::2] << 8) | shifted[:, 1::2]], axis=1)


def _table_keys(desc: U8) -> I64:
    """(n, 32) keys made distinct across tables (table t adds t * 2^16), so one sorted array holds all."""
    return _keys(desc).astype(np.int64) + np.arange(N_TABLES, dtype=np.int64) * TABLE_KEYS


def _columns(desc: U8) -> NDArray[np.uint64]:
    """(4, n) the descriptors as four 64-bit columns (1-D gathers are several times faster than rows)."""
    return np.ascontiguousarray(np.ascontiguousarray(desc).view(np.uint64).T)


def _hamming(a: NDArray[np.uint64], ai: I64, b: NDArray[np.uint64], bi: I64) -> I64:
    """Hamming distances between columns ``a[:, ai]`` and ``b[:, bi]`` (broadcast)."""
    out = np.zeros(np.broadcast_shapes(ai.shape, bi.shape), np.int64)
    for k in range(4):
        out += np.bitwise_count(a[k][ai] ^ b[k][bi])
    return out


class _Level:
    """The hash tables of a range of words as one sorted array of (table key, word id) entries.

    ``dense`` also keeps, for every table key, where its entries start (a lookup is then two reads
    instead of a binary search); worth it for the big level, rebuilt rarely.
    """

    def __init__(self, dense: bool = False) -> None:
        self.keys = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self._dense = dense
        self._start = np.zeros(N_TABLES * TABLE_KEYS + 1, np.int64) if dense else None

    def insert(self, keys: I64, ids: I64) -> None:
        """Add entries (merge of two sorted arrays: O(size), no full sort)."""
        order = np.argsort(keys, kind="stable")
        keys, ids = keys[order], ids[order]
        at = np.searchsorted(self.keys, keys, side="right")
        self.keys = np.insert(self.keys, at, keys)
        self.ids = np.insert(self.ids, at, ids)
        if self._dense:
            counts = np.bincount(self.keys, minlength=N_TABLES * TABLE_KEYS)
            self._start = np.concatenate([[0], np.cumsum(counts)])

    def _ranges(self, flat: I64) -> tuple[I64, I64]:
        if self._start is not None:
            lo = self._start[flat]
            return lo, self._start[flat + 1] - lo
        order = np.argsort(flat)  # sorted queries sweep the array once (numpy resumes from the last hit)
        lo, hi = np.empty_like(flat), np.empty_like(flat)
        lo[order] = np.searchsorted(self.keys, flat[order], side="left")
        hi[order] = np.searchsorted(self.keys, flat[order], side="right")
        return lo, hi - lo

    def best(self, qkeys: I64, dcols: NDArray[np.uint64], wcols: NDArray[np.uint64], big: np.int64) -> I64:
        """Per query row of ``qkeys`` (q, 32): min of ``distance * big + word id`` over the words sharing a key."""
        q = len(qkeys)
        out = np.full(q, 300 * big, np.int64)
        if self.keys.size == 0:
            return out
        lo, cnt = self._ranges(qkeys.reshape(-1))
        total = int(cnt.sum())
        if total == 0:
            return out
        first = np.repeat(lo - np.cumsum(cnt) + cnt, cnt)  # candidates stay grouped by query
        wi = self.ids[first + np.arange(total)]
        per_q = cnt.reshape(q, -1).sum(axis=1)
        qi = np.repeat(np.arange(q), per_q)
        has = per_q > 0
        starts = (np.cumsum(per_q) - per_q)[has]
        out[has] = np.minimum.reduceat(_hamming(dcols, qi, wcols, wi) * big + wi, starts)
        return out


class _WordIndex:
    """Approximate nearest word by multi-index hashing (Norouzi et al., CVPR 2012).

    The 256-bit words are cut into 16-bit keys (two interleaved cuts, 32 keys); a word is a
    candidate for a descriptor when one key is equal, and the nearest candidate by full Hamming
    distance is returned. A pair 20 bits apart shares a key with probability above 0.99, 40 bits
    apart about 0.9; a miss only makes a duplicate word. The tables are kept as sorted arrays in two
    levels, as a log-structured merge: the last words (at most TAIL_WORDS) are compared
    exhaustively, then merged into a small level (a merge costs its size), which is merged into
    the big level when it exceeds an eighth of it; so no step rebuilds the whole index.
    """

    def __init__(self) -> None:
        self._big, self._small = _Level(dense=True), _Level()
        self._n_big = 0  # words [0, n_big) are in the big level, [n_big, n_small) in the small one
        self._n_small = 0
        self._cols = np.zeros((4, 0), np.uint64)  # the words as columns (see _columns)

    def _sync(self, words: U8) -> None:
        n = len(words)
        if n > self._cols.shape[1]:
            self._cols = np.concatenate([self._cols, _columns(words[self._cols.shape[1]:])], axis=1)
        if n - self._n_small <= TAIL_WORDS:
            return
        ids = np.arange(self._n_small, n, dtype=np.int64)
        self._small.insert(_table_keys(words[self._n_small:]).reshape(-1), np.repeat(ids, N_TABLES))
        self._n_small = n
        if n - self._n_big > max(SMALL_WORDS, self._n_big // 8):
            self._big.insert(self._small.keys, self._small.ids)
            self._small = _Level()
            self._n_big = n

    def nearest(self, desc: U8, words: U8) -> tuple[I64, I64]:
        """Hamming distance and index of the nearest (candidate) word for each descriptor."""
        self._sync(words)
        big = np.int64(len(words) + 1)  # key = distance * big + id: nearest, ties to the lowest id
        dcols = _columns(desc)
        best = np.full(len(desc), 300 * big, np.int64)
        if self._n_small:
            qkeys = _table_keys(desc)
            best = np.minimum(best, self._big.best(qkeys, dcols, self._cols, big))
            best = np.minimum(best, self._small.best(qkeys, dcols, self._cols, big))
        if self._n_small < len(words):
            tail = np.arange(self._n_small, len(words), dtype=np.int64)
            dist = _hamming(dcols, np.arange(len(desc))[:, None], self._cols, tail[None, :])
            best = np.minimum(best, (dist * big + tail[None, :]).min(axis=1))
        return best // big, best % big


class Vocabulary:
    """Words, their inverted index over locations, and per-location word counts.

    Parameters
    ----------
    cfg : VocabularyConfig
    words : (W, 32) uint8 initial words (e.g. from a saved map); none by default.
    """

    def __init__(self, cfg: VocabularyConfig = VocabularyConfig(), words: U8 | None = None) -> None:
        self.cfg = cfg
        init = np.zeros((0, DESCRIPTOR_BYTES), np.uint8) if words is None else np.asarray(words, np.uint8)
        if init.ndim != 2 or init.shape[1] != DESCRIPTOR_BYTES:
            raise ValueError(f"words must be (W, {DESCRIPTOR_BYTES}) uint8, got shape {init.shape}")
        self._words = np.zeros((max(1024, 2 * len(init)), DESCRIPTOR_BYTES), np.uint8)
        self._words[: len(init)] = init
        self._n_words = len(init)
        self._postings: list[dict[int, int]] = [{} for _ in range(len(init))]
        self._loc_words: list[dict[int, int]] = []
        self._loc_norm: list[float] = []
        self._index = _WordIndex()

    @property
    def n_words(self) -> int:
        return self._n_words

    @property
    def n_locations(self) -> int:
        return len(self._loc_words)

    @property
    def words(self) -> U8:
        """(W, 32) uint8, a copy."""
        return self._words[: self._n_words].copy()

    def quantize(self, descriptors: U8, learn: bool) -> I64:
        """Word id of each descriptor (n,), adding new words when ``learn``; -1 where none is near.

        Parameters
        ----------
        descriptors : (n, 32) uint8 BRIEF descriptors.
        learn : mapping mode: descriptors with no word within ``word_radius_bits`` create words
            (greedily, in order, so that close new descriptors of one image share a word).
        """
        d = np.ascontiguousarray(descriptors, dtype=np.uint8)
        if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
            raise ValueError(f"descriptors must be (n, {DESCRIPTOR_BYTES}) uint8, got shape {d.shape}")
        ids = np.full(len(d), -1, np.int64)
        if len(d) == 0:
            return ids
        r = self.cfg.word_radius_bits
        if self._n_words:
            dist, nearest = self._index.nearest(d, self._words[: self._n_words])
            hit = dist <= r
            ids[hit] = nearest[hit]
        if not learn:
            return ids
        new = np.flatnonzero(ids < 0)
        if new.size:
            cols = _columns(d[new])
            m = np.arange(new.size)
            near = _hamming(cols, m[:, None], cols, m[None, :]) <= r
            label = np.full(new.size, -1, np.int64)
            leaders: list[int] = []
            for a in range(new.size):  # leader clustering, in order, over this image's unmatched descriptors
                if label[a] < 0:  # all earlier ones are labelled: the unlabelled close ones come later
                    label[near[a] & (label < 0)] = len(leaders)
                    leaders.append(a)
            ids[new] = self._n_words + label
            self._add_words(d[new[leaders]])
        return ids

    def _add_words(self, descriptors: U8) -> None:
        n = self._n_words + len(descriptors)
        if n > len(self._words):
            grown = np.zeros((max(n, 2 * len(self._words)), DESCRIPTOR_BYTES), np.uint8)
            grown[: self._n_words] = self._words[: self._n_words]
            self._words = grown
        self._words[self._n_words:n] = descriptors
        self._postings.extend({} for _ in range(len(descriptors)))
        self._n_words = n

    @staticmethod
    def histogram(word_ids: I64) -> tuple[I64, I64]:
        """Sorted distinct word ids (ignoring -1) and their counts."""
        w, c = np.unique(np.asarray(word_ids, np.int64), return_counts=True)
        keep = w >= 0
        return w[keep], c[keep].astype(np.int64)

    def scores(self, words: I64, counts: I64) -> F64:
        """tf-idf score of every location (n_locations,) for a query histogram; zeros without one."""
        n = self.n_locations
        out: F64 = np.zeros(n)
        if n == 0 or len(words) == 0:
            return out
        locs: list[int] = []
        vals: list[float] = []
        log_n = math.log(n)
        for w, c in zip(words.tolist(), counts.tolist(), strict=True):
            post = self._postings[w] if w < self._n_words else {}
            if not post or len(post) == n:
                continue  # in every location: idf = 0
            idf = log_n - math.log(len(post))
            weight = c * idf * idf
            locs.extend(post)
            vals.extend(map(weight.__mul__, post.values()))  # = weight * v, without a generator frame per value
        if locs:
            out = np.bincount(np.asarray(locs, np.int64), weights=np.asarray(vals), minlength=n).astype(np.float64)
            out /= np.asarray(self._loc_norm)
        return out

    def add_location(self, words: I64, counts: I64) -> int:
        """Index a new location with this word histogram; returns its id."""
        loc = self.n_locations
        self._loc_words.append({})
        self._loc_norm.append(1.0)
        self.update_location(loc, words, counts)
        return loc

    def update_location(self, loc: int, words: I64, counts: I64) -> None:
        """Add an image's words to location ``loc`` (an accepted loop closure, paper section III-A)."""
        if not 0 <= loc < self.n_locations:
            raise ValueError(f"loc must be in [0, {self.n_locations}), got {loc}")
        hist = self._loc_words[loc]
        for w, c in zip(np.asarray(words).tolist(), np.asarray(counts).tolist(), strict=True):
            if not 0 <= w < self._n_words:
                raise ValueError(f"words: id {w} is not in the vocabulary of {self._n_words} words")
            hist[w] = hist.get(w, 0) + c
            self._postings[w][loc] = hist[w]
        self._loc_norm[loc] = max(math.sqrt(sum(v * v for v in hist.values())), 1.0)

    def location_histogram(self, loc: int) -> tuple[I64, I64]:
        """Word ids (sorted) and counts of location ``loc``."""
        hist = self._loc_words[loc]
        w = np.array(sorted(hist), np.int64)
        return w, np.array([hist[k] for k in w.tolist()], np.int64)
