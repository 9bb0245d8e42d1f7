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
irrelevant to the mu + sigma likelihood of :mod:`algorithms.topometric.bayes`).

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

import cv2
import numpy as np
from numpy.typing import NDArray

from algorithms.topometric.features import DESCRIPTOR_BYTES

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
REBUILD_TAIL = 256  # words added since the last index build, searched exhaustively


def _keys(desc: U8) -> NDArray[np.uint16]:
    """(n, 32) 16-bit keys: bytes (0,1), (2,3), ... and, shifted by one byte, (1,2), (3,4), ..., (31,0)."""
    a = desc.astype(np.uint16)
    shifted = np.roll(a, -1, axis=1)
    return np.concatenate([(a[:, 0::2] << 8) | a[:, 1::2], (a[:, 1::2] << 8) | shifted[:, 1::2]], axis=1)


class _WordIndex:
    """Approximate nearest word by multi-index hashing (Norouzi et al., CVPR 2012).

    The 256-bit words are cut into 16-bit keys (two interleaved cuts, 32 keys); a word is a
    candidate for a descriptor when one key is equal, and the nearest candidate by full Hamming
    distance is returned. A pair 20 bits apart shares a key with probability above 0.99, 40 bits
    apart about 0.9; a miss only makes a duplicate word. Words added since the last build (at most
    REBUILD_TAIL) are compared exhaustively; builds are counting sorts, O(W) each.
    """

    def __init__(self) -> None:
        self._n = 0
        self._order: NDArray[np.int64] = np.zeros((0, 0), np.int64)
        self._start: NDArray[np.int64] = np.zeros((0, TABLE_KEYS + 1), np.int64)

    def _build(self, words: U8) -> None:
        keys = _keys(words)
        n, t = keys.shape
        self._order = np.argsort(np.ascontiguousarray(keys.T), axis=1, kind="stable").reshape(-1).astype(np.int64)
        flat = (keys.astype(np.int64) + np.arange(t) * TABLE_KEYS).reshape(-1)
        counts = np.bincount(flat, minlength=t * TABLE_KEYS).reshape(t, TABLE_KEYS)
        start = np.zeros((t, TABLE_KEYS + 1), np.int64)
        np.cumsum(counts, axis=1, out=start[:, 1:])
        self._start = start + (np.arange(t) * n)[:, None]  # offsets into the flat order
        self._n = n

    def nearest(self, desc: U8, words: U8) -> tuple[I64, I64]:
        """Hamming distance and index of the nearest (candidate) word for each descriptor."""
        if len(words) - self._n > REBUILD_TAIL:
            self._build(words)
        q = len(desc)
        tail = np.arange(self._n, len(words))
        if self._n:
            keys = _keys(desc).astype(np.int64)
            tables = np.arange(keys.shape[1])[None, :]
            lo = self._start[tables, keys].reshape(-1)
            cnt = self._start[tables, keys + 1].reshape(-1) - lo
            first = np.repeat(lo - np.cumsum(cnt) + cnt, cnt)
            wi = self._order[first + np.arange(first.size)]
            per_q = cnt.reshape(q, -1).sum(axis=1)
        else:
            wi, per_q = np.zeros(0, np.int64), np.zeros(q, np.int64)
        # candidates grouped by descriptor: the table hits, then the tail
        wi = np.concatenate([wi.reshape(-1), np.tile(tail, q)])
        qi = np.concatenate([np.repeat(np.arange(q), per_q), np.repeat(np.arange(q), tail.size)])
        order = np.argsort(qi, kind="stable")
        qi, wi = qi[order], wi[order]
        dist = np.bitwise_count(desc.view(np.uint64)[qi] ^ words.view(np.uint64)[wi]).sum(axis=1, dtype=np.int64)
        big = np.int64(len(words) + 1)
        key = dist * big + wi  # nearest, ties to the lowest word id
        best = np.full(q, 300 * big, np.int64)
        if key.size:
            starts = np.r_[0, np.cumsum(np.bincount(qi, minlength=q))[:-1]]
            has = np.bincount(qi, minlength=q) > 0
            best[has] = np.minimum.reduceat(key, starts[has])
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
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
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
            dn = d[new]
            near = [sorted(m.trainIdx for m in ms) for ms in self._matcher.radiusMatch(dn, dn, r + 0.5)]
            for a in range(new.size):  # leader clustering over this image's unmatched descriptors
                if ids[new[a]] >= 0:
                    continue
                ids[new[a]] = self._add_word(dn[a])
                close = new[[b for b in near[a] if b > a]]
                ids[close[ids[close] < 0]] = ids[new[a]]
        return ids

    def _add_word(self, descriptor: U8) -> int:
        if self._n_words == len(self._words):
            self._words = np.concatenate([self._words, np.zeros_like(self._words)])
        self._words[self._n_words] = descriptor
        self._postings.append({})
        self._n_words += 1
        return self._n_words - 1

    @staticmethod
    def histogram(word_ids: I64) -> tuple[I64, I64]:
        """Sorted distinct word ids (ignoring -1) and their counts."""
        w, c = np.unique(np.asarray(word_ids, np.int64), return_counts=True)
        keep = w >= 0
        return w[keep], c[keep].astype(np.int64)

    def scores(self, words: I64, counts: I64) -> F64:
        """tf-idf score of every location (n_locations,) for a query histogram; zeros without one."""
        n = self.n_locations
        out = np.zeros(n)
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
            locs.extend(post.keys())
            vals.extend(weight * v for v in post.values())
        if locs:
            out = np.bincount(np.asarray(locs, np.int64), weights=np.asarray(vals), minlength=n)
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
