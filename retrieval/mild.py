"""MILD's image similarity by multi-index hashing of binary descriptors (Han & Fang, ICME 2017), clean-room from
the paper, and its recall-probability analysis.

Each 256-bit descriptor (32 bytes) is cut into ``m`` disjoint substrings of ``256 / m`` bits; substring ``t`` is the
key of hash table ``t``. Two descriptors are *compared* when they share at least one key (same bits in the same
substring). The similarity of query image ``n`` to an earlier image ``k`` is (eq. 3)::

    Phi'(n, k) = 1 / (|F_n| |F_k|) * sum over compared pairs (i in F_n, j in F_k) of phi(d_ij)
    phi(d) = exp(-d^2 / sigma^2) if d <= d0 else 0       (d: Hamming distance)

Eq. 1 is the same sum over *all* pairs; pairs with ``d < m`` always share a key (``m`` substrings cannot all
hold one of fewer than ``m`` differing bits), so both agree on close pairs. Hash entries holding more than
``max_bucket`` features are skipped (their keys carry little information and cost the most).

Speed: every table is a pair of flat arrays (keys, feature ids) kept sorted by key; a query looks up all its keys
with one ``np.searchsorted`` per table and scores the compared pairs in one vectorised pass (XOR + popcount by a
byte table). A pair found in several tables is counted once, in the first table where it matches (no sort of the
pairs). Inserted images go to a small sorted tail that is merged into the big sorted tables when it grows past a
tenth of them, so inserting stays cheap as the map grows. ``brute_force_similarity`` is the reference the fast path
is tested against.

    >>> index = MultiIndexHash(m=16)
    >>> sims = index.query(desc_n)        # (images,) Phi' against every image added so far   # doctest: +SKIP
    >>> index.add(desc_n)                 # the database grows online: query, then insert      # doctest: +SKIP
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from core.errors import ConfigError

__all__ = ["MultiIndexHash", "brute_force_similarity", "hamming_distances", "phi", "recall_probability",
           "expected_recall", "DESCRIPTOR_BITS"]

DESCRIPTOR_BITS = 256  #: ORB descriptor length
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def hamming_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of packed binary descriptors ``(n, B)`` uint8 -> ``(n,)`` int32."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1, dtype=np.int32)


def phi(d: np.ndarray, sigma: float, d0: int) -> np.ndarray:
    """``exp(-d^2 / sigma^2)`` where ``d <= d0``, else 0 (MILD eq. 2)."""
    d = np.asarray(d, np.float64)
    return np.where(d <= d0, np.exp(-(d * d) / (sigma * sigma)), 0.0)


def _substrings(desc: np.ndarray, m: int) -> np.ndarray:
    """``(n, 32)`` uint8 descriptors -> ``(n, m)`` int64 substring keys (``256 / m`` bits each, m in 2..32)."""
    bits = np.unpackbits(np.ascontiguousarray(desc, np.uint8), axis=1)  # (n, 256)
    width = DESCRIPTOR_BITS // m
    weights = (1 << np.arange(width - 1, -1, -1, dtype=np.int64))
    return bits.reshape(len(desc), m, width).astype(np.int64) @ weights


def _check_descriptors(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BITS // 8 or d.dtype != np.uint8:
        raise ConfigError(f"MILD needs (n, 32) uint8 binary descriptors (ORB); got {d.shape} {d.dtype}")
    return d


class MultiIndexHash:
    """The growing image database of MILD: ``query`` one image against all earlier ones, then ``add`` it.

    Args:
        m: number of hash tables (substrings per descriptor; MILD: 16); must divide 256.
        sigma: phi's width in bits.
        d0: phi is 0 beyond this Hamming distance (MILD: 60).
        max_bucket: entries with more features than this are skipped at query time (0: never).
    """

    def __init__(self, m: int = 16, sigma: float = 30.0, d0: int = 60, max_bucket: int = 0) -> None:
        if not isinstance(m, int) or m < 1 or DESCRIPTOR_BITS % m or DESCRIPTOR_BITS // m > 62:
            raise ConfigError(f"m must divide 256 into substrings of at most 62 bits; got {m!r}")
        self.m, self.sigma, self.d0, self.max_bucket = m, float(sigma), int(d0), int(max_bucket)
        self._chunks: list[tuple[np.ndarray, np.ndarray]] = []  # (descriptors, keys) per image, in order
        self._desc = np.zeros((0, DESCRIPTOR_BITS // 8), np.uint8)  # all features (rebuilt lazily from _chunks)
        self._keys = np.zeros((0, m), np.int64)  # feature -> its m keys
        self._image_of = np.zeros(0, np.int64)  # feature -> image index
        self._counts: list[int] = []  # features per image
        self._n_flat = 0  # features already in the flat arrays above
        self._sorted: list[tuple[np.ndarray, np.ndarray]] = []  # per table: (sorted keys, feature ids)
        self._n_sorted = 0  # features in the big sorted tables
        self._tail: list[tuple[np.ndarray, np.ndarray]] = []  # the same for the features added since (small)

    @property
    def n_images(self) -> int:
        return len(self._counts)

    def add(self, desc: np.ndarray) -> int:
        """Inserts one image's ``(n, 32)`` uint8 descriptors; returns its image index (0, 1, ...)."""
        d = _check_descriptors(desc)
        self._chunks.append((d.copy(), _substrings(d, self.m)))
        self._counts.append(len(d))
        return self.n_images - 1

    def _flatten(self) -> None:
        """Moves the images added since the last query into the flat arrays; re-sorts the tables when the unsorted
        tail has grown past a tenth of the sorted part."""
        if not self._chunks:
            return
        ids = np.repeat(np.arange(len(self._counts) - len(self._chunks), len(self._counts)),
                        [len(c[0]) for c in self._chunks])
        self._desc = np.concatenate([self._desc, *(c[0] for c in self._chunks)])
        self._keys = np.concatenate([self._keys, *(c[1] for c in self._chunks)])
        self._image_of = np.concatenate([self._image_of, ids])
        self._chunks = []
        if len(self._desc) - self._n_sorted > self._n_sorted // 10:
            self._sorted, self._n_sorted = _sorted_tables(self._keys, 0), len(self._desc)
        self._tail = _sorted_tables(self._keys[self._n_sorted:], self._n_sorted)

    def _lookup(self, qkeys: np.ndarray, t: int) -> np.ndarray:
        """``(P, 2)`` (query feature, stored feature) whose key ``t`` is equal (over-full entries skipped)."""
        found = [np.zeros((0, 2), np.int64)]
        for tables in (self._sorted, self._tail):
            if not tables:
                continue
            keys, fids = tables[t]
            lo = np.searchsorted(keys, qkeys[:, t], "left")
            size = np.searchsorted(keys, qkeys[:, t], "right") - lo
            if size.any():
                qi = np.repeat(np.arange(len(qkeys)), size)
                offsets = np.arange(size.sum()) - np.repeat(np.cumsum(size) - size, size)
                found.append(np.stack([qi, fids[np.repeat(lo, size) + offsets]], 1))
        pairs = np.concatenate(found)
        if self.max_bucket and len(pairs):
            pairs = pairs[self._bucket_sizes(qkeys[pairs[:, 0], t], t) <= self.max_bucket]
        return pairs

    def compared_pairs(self, desc: np.ndarray) -> np.ndarray:
        """``(P, 2)`` int64 unique ``(query feature, stored feature)`` pairs that share at least one key."""
        d = _check_descriptors(desc)
        self._flatten()
        if len(d) == 0 or len(self._desc) == 0:
            return np.zeros((0, 2), np.int64)
        qkeys = _substrings(d, self.m)
        found = []
        for t in range(self.m):
            pairs = self._lookup(qkeys, t)
            if t and len(pairs):  # counted once: in the first table where the pair matches
                earlier = np.any(self._keys[pairs[:, 1], :t] == qkeys[pairs[:, 0], :t], axis=1)
                if self.max_bucket:  # a match in a skipped (over-full) entry did not count there
                    earlier &= self._counted_before(qkeys, pairs, t)
                pairs = pairs[~earlier]
            found.append(pairs)
        return np.concatenate(found)

    def _counted_before(self, qkeys: np.ndarray, pairs: np.ndarray, t: int) -> np.ndarray:
        """For pairs found in table ``t``: True where an earlier table matched them in an entry that is not
        over-full (so they were counted there)."""
        out = np.zeros(len(pairs), bool)
        for s in range(t):
            same = self._keys[pairs[:, 1], s] == qkeys[pairs[:, 0], s]
            if same.any():
                sizes = self._bucket_sizes(qkeys[pairs[same, 0], s], s)
                out[np.flatnonzero(same)[sizes <= self.max_bucket]] = True
        return out

    def _bucket_sizes(self, keys: np.ndarray, t: int) -> np.ndarray:
        """Entries of table ``t`` holding each of ``keys`` (sorted part and unsorted tail)."""
        size = np.zeros(len(keys), np.int64)
        for tables in (self._sorted, self._tail):
            if tables:
                sk = tables[t][0]
                size += np.searchsorted(sk, keys, "right") - np.searchsorted(sk, keys, "left")
        return size

    def query(self, desc: np.ndarray) -> np.ndarray:
        """Phi'(n, k) of the query image against every stored image, ``(n_images,)`` float64 (eq. 3)."""
        d = _check_descriptors(desc)
        out = np.zeros(self.n_images)
        pairs = self.compared_pairs(d)
        if len(pairs) == 0:
            return out
        w = phi(hamming_distances(d[pairs[:, 0]], self._desc[pairs[:, 1]]), self.sigma, self.d0)
        np.add.at(out, self._image_of[pairs[:, 1]], w)
        counts = np.asarray(self._counts, np.float64)
        return out / np.maximum(len(d) * counts, 1.0)


def _sorted_tables(keys: np.ndarray, first_id: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per table: the keys sorted, and the feature ids (``first_id`` + row) in that order."""
    out = []
    for t in range(keys.shape[1]):
        order = np.argsort(keys[:, t], kind="stable")
        out.append((keys[order, t], order + first_id))
    return out


def brute_force_similarity(query: np.ndarray, images: list[np.ndarray], m: int = 16, sigma: float = 30.0,
                           d0: int = 60, shared_key_only: bool = True) -> np.ndarray:
    """Reference: eq. 3 (pairs that share a key; ``shared_key_only``) or eq. 1 (all pairs), pair by pair."""
    q = _check_descriptors(query)
    qk = _substrings(q, m) if len(q) else np.zeros((0, m), np.int64)
    out = np.zeros(len(images))
    for k, img in enumerate(images):
        img = _check_descriptors(img)
        ik = _substrings(img, m) if len(img) else np.zeros((0, m), np.int64)
        total = 0.0
        for i in range(len(q)):
            for j in range(len(img)):
                if shared_key_only and not np.any(qk[i] == ik[j]):
                    continue
                total += float(phi(hamming_distances(q[i:i + 1], img[j:j + 1]), sigma, d0)[0])
        out[k] = total / max(len(q) * len(img), 1)
    return out


@lru_cache(maxsize=None)
def _stirling2(n: int, k: int) -> int:
    """Stirling number of the second kind S(n, k) (exact integer)."""
    if n == k:
        return 1
    if k == 0 or k > n:
        return 0
    return k * _stirling2(n - 1, k) + _stirling2(n - 1, k - 1)


def recall_probability(m: int, d: int) -> float:
    """P_recall(m, d) = 1 - m! S(d, m) / m^d (MILD eq. 8): the probability that two descriptors ``d`` bits apart
    share at least one of ``m`` substrings, when each differing bit falls in a substring chosen uniformly."""
    if d < m:
        return 1.0
    return 1.0 - (math.factorial(m) * _stirling2(d, m)) / (m ** d)  # exact integers, then one division


def expected_recall(m: int, mean: float, std: float, d_max: int = DESCRIPTOR_BITS) -> float:
    """``sum_d P_recall(m, d) N(d; mean, std)`` over d = 0..d_max (MILD eq. 9): R(m) with inlier distances
    N(32, 10), E(m) (the share of outlier pairs compared, i.e. the cost) with outlier distances N(128, 20)."""
    d = np.arange(d_max + 1)
    w = np.exp(-0.5 * ((d - mean) / std) ** 2)
    w /= w.sum()
    return float(sum(recall_probability(m, int(x)) * float(p) for x, p in zip(d, w) if p > 1e-12))
