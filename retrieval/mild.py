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

In the detector MILD is the global descriptor ``mild`` (``MildDescriptor``: a frame's ORB descriptors), searched
by ``retrieval.places.HashPlaces`` and followed by the Bayesian filter (``temporal.name: bayes``); the presets
``configs/mild.yaml`` and ``configs/mild_verify.yaml`` (``cae-lcd detect --method mild | mild+verify``) set it up.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.conf import Float, Int
from cae_lcd.core.errors import ConfigError
from cae_lcd.core.images import to_gray_u8
from verify.features import ORB, Features

from .descriptors import DESCRIPTORS, GlobalDescriptor

__all__ = ["MildDescriptor", "MultiIndexHash", "bucket_cap", "brute_force_similarity", "hamming_distances", "phi", "recall_probability",
           "expected_recall", "DESCRIPTOR_BITS"]

DESCRIPTOR_BITS = 256  #: ORB descriptor length
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def hamming_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of packed binary descriptors ``(n, B)`` uint8 -> ``(n,)`` int32."""
    return _popcount(np.bitwise_xor(a, b))


def _popcount(x: np.ndarray) -> np.ndarray:
    """Set bits per row of ``(n, B)`` uint8 -> ``(n,)`` int32."""
    if hasattr(np, "bitwise_count") and x.shape[1] % 8 == 0:  # numpy >= 2: popcount of 64-bit words
        return np.bitwise_count(np.ascontiguousarray(x).view(np.uint64)).sum(axis=1, dtype=np.int32)
    return _POPCOUNT[x].sum(axis=1, dtype=np.int32)


def phi(d: np.ndarray, sigma: float, d0: int) -> np.ndarray:
    """``exp(-d^2 / sigma^2)`` where ``d <= d0``, else 0 (MILD eq. 2)."""
    d = np.asarray(d, np.float64)
    return np.where(d <= d0, np.exp(-(d * d) / (sigma * sigma)), 0.0)


def _substrings(desc: np.ndarray, m: int) -> np.ndarray:
    """``(n, 32)`` uint8 descriptors -> ``(n, m)`` int64 substring keys (``256 / m`` bits each, m in 2..32).

    Bits are read most significant first, so the keys of m = 8, 16, 32 are the big-endian 32/16/8-bit words."""
    desc = np.ascontiguousarray(desc, np.uint8)
    width = DESCRIPTOR_BITS // m
    if width in (8, 16, 32):  # whole bytes: a view, no unpacking
        return desc.view(f">u{width // 8}").astype(np.int64)
    bits = np.unpackbits(desc, axis=1)  # (n, 256)
    weights = (1 << np.arange(width - 1, -1, -1, dtype=np.int64))
    return bits.reshape(len(desc), m, width).astype(np.int64) @ weights


def _key_column(desc: np.ndarray, m: int, t: int) -> np.ndarray:
    """Keys of table ``t`` of ``(n, 32)`` descriptors, ``(n,)`` int64 (one column of ``_substrings``, less memory)."""
    width = DESCRIPTOR_BITS // m
    if width in (8, 16, 32):
        return desc.view(f">u{width // 8}")[:, t].astype(np.int64)
    return _substrings(desc, m)[:, t]


def _equal_substrings(xor: np.ndarray, m: int) -> np.ndarray:
    """``(P, 32)`` XOR of descriptor pairs -> ``(P, m)`` bool: substring ``t`` of both is equal (they share key t)."""
    width = DESCRIPTOR_BITS // m
    if width in (8, 16, 32):
        return np.ascontiguousarray(xor).view(f"u{width // 8}") == 0
    return ~np.unpackbits(xor, axis=1).reshape(len(xor), m, width).any(axis=2)


def _check_descriptors(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BITS // 8 or d.dtype != np.uint8:
        raise ConfigError(f"MILD needs (n, 32) uint8 binary descriptors (ORB); got {d.shape} {d.dtype}")
    return d


def bucket_cap(max_bucket: float, n_features: int, m: int) -> float:
    """Entries holding more features than this are skipped: ``max_bucket`` times the mean number of features per key
    (``n_features / 2^(256/m)``, at least 1); ``inf`` when ``max_bucket`` is 0 (nothing skipped)."""
    if max_bucket <= 0:
        return math.inf
    return max_bucket * max(1.0, n_features / 2.0 ** (DESCRIPTOR_BITS // m))


class _Table:
    """One hash table over a run of features: their ids sorted by key, an entry found by direct addressing (CSR
    offsets, keys of up to ``_DENSE_BITS`` bits) or by binary search in the sorted keys."""

    def __init__(self, keys: np.ndarray, first_id: int, width: int, dense: bool) -> None:
        order = np.argsort(keys, kind="stable")
        self.fids = (order + first_id).astype(np.int64 if first_id + len(keys) >= 2 ** 31 else np.int32)
        self.offsets = np.concatenate([[0], np.cumsum(np.bincount(keys, minlength=1 << width))]) if dense else None
        self.keys = None if dense else keys[order]

    def ranges(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(first position, entry size)`` of each key, ``(nq,)`` int64 each."""
        if self.offsets is not None:
            lo = self.offsets[keys]
            return lo, self.offsets[keys + 1] - lo
        lo = np.searchsorted(self.keys, keys, "left")
        return lo, np.searchsorted(self.keys, keys, "right") - lo


_DENSE_BITS = 16  #: substrings of at most this many bits are looked up by direct addressing (2^16 offsets a table)


class MultiIndexHash:
    """The growing image database of MILD: ``query`` one image against all earlier ones, then ``add`` it.

    Args:
        m: number of hash tables (substrings per descriptor; MILD: 16); must divide 256.
        sigma: phi's width in bits.
        d0: phi is 0 beyond this Hamming distance (MILD: 60).
        max_bucket: entries holding more than ``max_bucket`` times the mean number of features per key are skipped
            at query time (``bucket_cap``); 0: never.
    """

    def __init__(self, m: int = 16, sigma: float = 30.0, d0: int = 60, max_bucket: float = 0.0) -> None:
        if not isinstance(m, int) or m < 1 or DESCRIPTOR_BITS % m or DESCRIPTOR_BITS // m > 62:
            raise ConfigError(f"m must divide 256 into substrings of at most 62 bits; got {m!r}")
        self.m, self.sigma, self.d0, self.max_bucket = m, float(sigma), int(d0), float(max_bucket)
        self._width = DESCRIPTOR_BITS // m
        self._phi = phi(np.arange(DESCRIPTOR_BITS + 1), self.sigma, self.d0)  # phi by distance: a lookup
        self._chunks: list[np.ndarray] = []  # descriptors of the images added since the last query
        self._desc = np.zeros((0, DESCRIPTOR_BITS // 8), np.uint8)  # all features, in insertion order
        self._image_of = np.zeros(0, np.int32)  # feature -> image index
        self._counts: list[int] = []  # features per image
        self._sorted: list[_Table] = []  # per table, over features [0, _n_sorted)
        self._n_sorted = 0
        self._tail: list[_Table] = []  # per table, over the features added since (small: binary search)

    @property
    def n_images(self) -> int:
        return len(self._counts)

    @property
    def n_features(self) -> int:
        return len(self._desc) + sum(len(c) for c in self._chunks)

    def add(self, desc: np.ndarray) -> int:
        """Inserts one image's ``(n, 32)`` uint8 descriptors; returns its image index (0, 1, ...)."""
        d = _check_descriptors(desc)
        self._chunks.append(np.ascontiguousarray(d).copy())
        self._counts.append(len(d))
        return self.n_images - 1

    def _flatten(self) -> None:
        """Moves the images added since the last query into the flat arrays; re-sorts the tables when the unsorted
        tail has grown past a tenth of the sorted part."""
        if not self._chunks:
            return
        first = len(self._counts) - len(self._chunks)
        ids = np.repeat(np.arange(first, len(self._counts), dtype=np.int32), [len(c) for c in self._chunks])
        self._desc = np.concatenate([self._desc, *self._chunks])
        self._image_of = np.concatenate([self._image_of, ids])
        self._chunks = []
        if len(self._desc) - self._n_sorted > self._n_sorted // 10:
            dense = self._width <= _DENSE_BITS
            self._sorted = [_Table(_key_column(self._desc, self.m, t), 0, self._width, dense) for t in range(self.m)]
            self._n_sorted = len(self._desc)
        tail = self._desc[self._n_sorted:]
        self._tail = [_Table(_key_column(tail, self.m, t), self._n_sorted, self._width, False)
                      for t in range(self.m)] if len(tail) else []

    def _lookup(self, qkeys: np.ndarray, cap: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every ``(query feature, stored feature, table)`` whose key in that table is equal, entries holding more
        than ``cap`` features left out; and ``(nq, m)`` True where the query's entry in table t is not skipped."""
        parts = [(t, tables[t], *tables[t].ranges(qkeys[:, t])) for tables in (self._sorted, self._tail) if tables
                 for t in range(self.m)]
        sizes = np.zeros(qkeys.shape, np.int64)
        for t, _, _, size in parts:
            sizes[:, t] += size
        usable = sizes <= cap
        qs, fs, ts = [], [], []
        for t, table, lo, size in parts:
            size = np.where(usable[:, t], size, 0)
            total = int(size.sum())
            if total:
                starts = np.repeat(lo - (np.cumsum(size) - size), size)
                qs.append(np.repeat(np.arange(len(qkeys)), size))
                fs.append(table.fids[starts + np.arange(total)])
                ts.append(np.full(total, t, np.int64))
        if not qs:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, usable
        return np.concatenate(qs), np.concatenate(fs), np.concatenate(ts), usable

    def _scored_pairs(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unique compared pairs ``(query feature, stored feature)`` and their Hamming distances, ``(P,)`` each."""
        self._flatten()
        empty = np.zeros(0, np.int64)
        if len(d) == 0 or len(self._desc) == 0:
            return empty, empty, empty
        qi, fi, ti, usable = self._lookup(_substrings(d, self.m), bucket_cap(self.max_bucket, len(self._desc), self.m))
        if len(qi) == 0:
            return empty, empty, empty
        xor = np.bitwise_xor(d[qi], self._desc[fi])
        # a pair counts once: in the first table where its keys are equal in an entry that was not skipped
        keep = np.argmax(_equal_substrings(xor, self.m) & usable[qi], axis=1) == ti
        return qi[keep], fi[keep], _popcount(xor)[keep]

    def compared_pairs(self, desc: np.ndarray) -> np.ndarray:
        """``(P, 2)`` int64 unique ``(query feature, stored feature)`` pairs that share at least one key."""
        qi, fi, _ = self._scored_pairs(_check_descriptors(desc))
        return np.stack([qi, fi], 1).astype(np.int64)

    def query(self, desc: np.ndarray) -> np.ndarray:
        """Phi'(n, k) of the query image against every stored image, ``(n_images,)`` float64 (eq. 3)."""
        d = _check_descriptors(desc)
        qi, fi, dist = self._scored_pairs(d)
        out = np.bincount(self._image_of[fi], weights=self._phi[dist], minlength=self.n_images) if len(fi) \
            else np.zeros(self.n_images)
        counts = np.asarray(self._counts, np.float64)
        return out / np.maximum(len(d) * counts, 1.0)


def brute_force_similarity(query: np.ndarray, images: list[np.ndarray], m: int = 16, sigma: float = 30.0,
                           d0: int = 60, shared_key_only: bool = True, max_bucket: float = 0.0) -> np.ndarray:
    """Reference: eq. 3 (pairs that share a key; ``shared_key_only``) or eq. 1 (all pairs), pair by pair; with
    ``max_bucket``, a shared key counts only where its entry (over all ``images``) is within ``bucket_cap``."""
    q = _check_descriptors(query)
    keys = [_substrings(_check_descriptors(x), m) if len(x) else np.zeros((0, m), np.int64) for x in [q, *images]]
    qk, image_keys = keys[0], keys[1:]
    cap = bucket_cap(max_bucket, sum(len(x) for x in images), m)
    entry: dict[tuple[int, int], int] = {}
    for ik in image_keys:
        for row in ik:
            for t, key in enumerate(row.tolist()):
                entry[t, key] = entry.get((t, key), 0) + 1
    out = np.zeros(len(images))
    for k, (img, ik) in enumerate(zip(images, image_keys)):
        total = 0.0
        for i in range(len(q)):
            for j in range(len(img)):
                shared = [t for t in range(m) if qk[i, t] == ik[j, t] and entry[t, int(ik[j, t])] <= cap]
                if shared_key_only and not shared:
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


@DESCRIPTORS.register("mild")
class MildDescriptor(GlobalDescriptor):
    """MILD's image description: the frame's ORB descriptors, ``(n, 32)`` uint8 (n <= ``max_features``), searched
    by multi-index hashing (``searched_by = "hash"``), not by cosine. The hashing options live here too, so that
    one section says how MILD describes and compares images."""

    default_conf: dict[str, Any] = {
        "name": "mild",  # global descriptor, by registry name
        "max_features": 800,  # ORB features per image (MILD: 800)
        "min_size": 256,  # frames whose longer side is shorter are enlarged to this first (ORB ignores a 31-pixel
        #                   border, so a 64x32 frame has none); None: never enlarged (the paper)
        "m": 16,  # hash tables = substrings per 256-bit descriptor (MILD: 16 of 16 bits); must divide 256
        "sigma": 30.0,  # phi(d) = exp(-d^2 / sigma^2), d the Hamming distance in bits
        "d0": 60,  # phi is 0 beyond this distance (MILD: 60)
        "max_bucket": 2.0,  # hash entries holding more than this many times the mean features per key are skipped
        #                     (over-full entries carry little information and cost the most); 0: never. 2 vs 0 on
        #                     KITTI 90: same recall, 2.5x faster (BENCHMARKS.md, MILD)
    }
    conf_rules: dict[str, Any] = {"max_features": Int(1, 100_000), "min_size": Int(32, 8192, optional=True),
                                  "m": Int(1, 256), "sigma": Float(0, 256, lo_open=True), "d0": Int(0, 256),
                                  "max_bucket": Float(0)}
    searched_by = "hash"

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        c = self.conf
        MultiIndexHash(c["m"])  # refuses an m that does not divide 256 now, before anything is written
        self.orb = ORB({"max_features": c["max_features"]})
        self.dim = DESCRIPTOR_BITS // 8
        self.identity = f"mild orb{c['max_features']} min_size {c['min_size']}"

    def size_text(self) -> str:
        return f"{self.conf['max_features']} x {DESCRIPTOR_BITS} bits"

    def new_hash(self) -> MultiIndexHash:
        """An empty image database with this descriptor's hashing options."""
        c = self.conf
        return MultiIndexHash(c["m"], c["sigma"], c["d0"], c["max_bucket"])

    def __call__(self, image: np.ndarray, features: Features | None = None,
                 network_image: np.ndarray | None = None) -> np.ndarray:
        gray = to_gray_u8(image)
        small = self.conf["min_size"]
        if small and max(gray.shape) < small:
            scale = small / max(gray.shape)
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(self.orb.extract(gray).descriptors, np.uint8).reshape(-1, self.dim)
