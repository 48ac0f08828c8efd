"""Index scaling: build time, memory, search latency and recall@10 against exact search, for 10k to 1M codes.

Codes are realistic (``realistic_codes``): real frames from every data set in ``../shared`` (KITTI 00/07/90,
Nordland), augmented (photometric gain/offset/gamma and a random crop: ``bench.augment``), encoded with the
shipped CAE and whitened as the detector does (a ``cae.whitening.Whitening`` fitted on them, 256-d, unit norm).
Beyond those, codes are derived in the whitened space (``synth_codes``): ``normalize(w * a + (1 - w) * b +
noise)`` for a random real code ``a``, another ``b`` and ``w`` in [0.75, 1], so each derived code is a new view
near a real place, with the real codes' structure rather than the flat similarity of random unit vectors. Queries
are derived again from stored codes. Codes are generated chunk by chunk and added to every index still running,
and the exact top-k of each query is kept over the chunks, so no full copy of the largest set is ever held. An
index whose memory or build/search time would exceed the budget at a size is skipped there (and above), with the
reason in the table.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from retrieval.index import CodeIndex, brute_force_search, create_index

from .common import Budget, md_table

__all__ = ["synth_codes", "realistic_codes", "index_scaling", "index_table", "INDEX_CONFS"]

log = logging.getLogger(__name__)

_INT8_STD = math.sqrt((256**2 - 1) / 12)  # std of uniform random int8

#: the indexes offered (retrieval.index), with the conf the bench runs them with (``hnsw-float32``: the graph over
#: float32 storage, beside the default float16)
INDEX_CONFS: dict[str, dict[str, Any]] = {"flat": {"name": "flat"}, "fp16": {"name": "fp16"},
                                          "sq8": {"name": "sq8"}, "hnsw": {"name": "hnsw"},
                                          "hnsw-float32": {"name": "hnsw", "storage": "flat"},
                                          "ivfpq": {"name": "ivfpq"}}


def synth_codes(base: np.ndarray, n: int, sigma: float, rng: np.random.Generator,
                sources: np.ndarray | None = None) -> np.ndarray:
    """Codes derived from real ones: ``normalize(w * base[i] + (1 - w) * base[j] + noise)`` for ``n`` random (or
    given) rows ``i``, random rows ``j``, ``w`` uniform in [0.75, 1] and noise uniform with std ``sigma``.

    Returns:
        ``(n, D)`` float32, unit rows.
    """
    d = base.shape[1]
    idx = rng.integers(0, len(base), n) if sources is None else np.asarray(sources)
    b = torch.from_numpy(np.ascontiguousarray(base, np.float32))
    w = torch.from_numpy(rng.uniform(0.75, 1.0, (n, 1)).astype(np.float32))
    x = b[torch.from_numpy(idx)] * w + b[torch.from_numpy(rng.integers(0, len(base), n))] * (1 - w)
    noise = torch.frombuffer(bytearray(rng.bytes(n * d)), dtype=torch.int8).view(n, d)
    x.add_(noise, alpha=sigma / _INT8_STD)
    x.div_(torch.linalg.vector_norm(x, dim=1, keepdim=True).clamp_(min=1e-12))
    return x.numpy()


def realistic_codes(n_real: int = 20_000, seed: int = 0, batch: int = 64) -> np.ndarray:
    """``n_real`` augmented real frames of ``../shared`` encoded with the shipped CAE and whitened as the detector
    does (``Whitening.fit`` on them, default dimension and shrinkage).

    Returns:
        ``(n_real, 256)`` float32, unit rows.
    """
    from cae.encode import encode_images
    from cae.whitening import Whitening
    from retrieval.descriptors import create_descriptor

    from .augment import augmented_frames, shared_frames

    encoder = create_descriptor({"name": "cae"}).encoder
    frames, codes = [], []
    for _, image in augmented_frames(shared_frames(), n_real, seed):
        frames.append(image)
        if len(frames) == batch:
            codes.append(encode_images(encoder, frames))
            frames = []
    if frames:
        codes.append(encode_images(encoder, frames))
    raw = np.concatenate(codes)
    log.info("%d real augmented codes encoded", len(raw))
    return Whitening.fit(raw).transform(raw)


def _merge_topk(D: np.ndarray, I: np.ndarray, D2: np.ndarray, I2: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    Dc, Ic = np.concatenate([D, D2], 1), np.concatenate([I, I2], 1)
    order = np.argsort(-Dc, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(Dc, order, 1), np.take_along_axis(Ic, order, 1)


def _bytes_estimate(name: str, dim: int) -> float:
    """Bytes per code before anything is built (replaced by the measured value once an index exists)."""
    return {"flat": 4 * dim, "fp16": 2 * dim, "sq8": dim, "hnsw": 4 * dim + 2 * 32 * 4 * 1.1,
            "ivfpq": 2 * dim + 32 + 8}.get(name, 4 * dim)


def _pilot(conf: dict[str, Any], base: np.ndarray, sigma: float, rng: np.random.Generator,
           n: int = 500) -> dict[str, Any]:
    """Estimates from a throw-away index of ``n`` codes: add seconds per code, one-query latency, bytes per code,
    and the seconds per code of generating codes plus exact ground truth."""
    t0 = time.perf_counter()
    x = synth_codes(base, n, sigma, rng)
    brute_force_search(x[:50], x, 10)
    gen = (time.perf_counter() - t0) / n
    index = create_index(base.shape[1], {**conf, "train_size": n} if conf["name"] == "sq8" else conf)
    t0 = time.perf_counter()
    index.add(x)
    add = (time.perf_counter() - t0) / n
    lat = []
    for q in x[:5]:
        t0 = time.perf_counter()
        index.search(q[None], 10)
        lat.append(time.perf_counter() - t0)
    return {"add_per_code": add, "lat_s": float(np.median(lat)), "lat_n": n, "gen_per_code": gen, "add_s": 0.0,
            "bytes_per_code": _bytes_estimate(conf["name"], base.shape[1])}


@dataclass(frozen=True)
class _Limits:
    """What one index may cost at one size."""

    n_queries: int  #: queries with exact ground truth (fewer when searching them all would not fit)
    memory_gib: float  #: an index larger than this is skipped
    cell_time_s: float  #: an index whose estimated build + search time exceeds this is skipped


def _cell_plan(name: str, e: dict[str, Any], size: int, pos: int, lim: _Limits) -> tuple[str | None, float, int]:
    """Whether index ``name`` (estimates ``e``) goes on from ``pos`` to ``size`` stored codes.

    Returns:
        ``(reason it is skipped or None, estimated build + search seconds, queries to time)``.
    """
    mem = e["bytes_per_code"] * size
    build = e["add_per_code"] * (size - pos) * (math.log(size) / math.log(max(pos, e["lat_n"], 2))
                                                if name == "hnsw" else 1.0)
    per_q = e["lat_s"] * size / e["lat_n"]
    nq = int(min(lim.n_queries, max(5, lim.cell_time_s / 3 / max(per_q, 1e-6))))
    seconds = build + per_q * nq
    if mem > lim.memory_gib * 2**30:
        return f"skipped: {mem / 2**30:.1f} GiB > memory budget {lim.memory_gib:g} GiB", seconds, nq
    if seconds > lim.cell_time_s:
        return f"skipped: build + search ~{seconds:.0f} s > time budget {lim.cell_time_s:g} s", seconds, nq
    return None, seconds, nq


def _prune(alive: dict[str, CodeIndex], st: dict[str, dict[str, Any]], cells: dict[tuple[str, int], dict[str, Any]],
           size: int, pos: int, gen_per_code: float, lim: _Limits, budget: Budget | None) -> None:
    """Drops from ``alive`` (with the reason in ``cells``) each index that would not fit at ``size``: memory,
    then its estimated build + search time, then the bench's time left for the whole size."""
    est_total = gen_per_code * (size - pos)
    for n in list(alive):
        reason, seconds, nq = _cell_plan(n, st[n], size, pos, lim)
        if reason:
            cells[(n, size)] = {"skipped": reason}
            del alive[n]
        else:
            st[n]["nq"] = nq
            est_total += seconds
    if budget is not None and alive and not budget.allows(est_total):
        for n in alive:
            cells[(n, size)] = {"skipped": f"skipped: ~{est_total:.0f} s > bench time left ({budget.left():.0f} s)"}
        alive.clear()


class _CodeStream:
    """The stored codes, generated chunk by chunk, with the queries and their exact top-k over everything so far
    (no full float32 copy of the largest set is ever held)."""

    def __init__(self, base: np.ndarray, sigma: float, rng: np.random.Generator, chunk: int, n_queries: int,
                 k: int) -> None:
        self.base, self.sigma, self.rng, self.chunk, self.n_queries, self.k = base, sigma, rng, chunk, n_queries, k
        self.pos = 0  #: codes generated so far
        self.xq: np.ndarray | None = None  #: queries: perturbed copies of stored codes of the first chunk
        self.D_gt = self.I_gt = np.zeros((0, k))  #: exact top-k similarities and ids of each query

    def _next(self, m: int) -> np.ndarray:
        x = synth_codes(self.base, m, self.sigma, self.rng)
        if self.xq is None:
            src = self.rng.choice(m, min(self.n_queries, m), replace=False)
            self.xq = synth_codes(x, len(src), self.sigma / 2, self.rng, sources=src)
            self.D_gt = np.full((len(self.xq), self.k), -np.inf, np.float32)
            self.I_gt = np.full((len(self.xq), self.k), -1, np.int64)
        D2, I2 = brute_force_search(self.xq, x, self.k)
        self.D_gt, self.I_gt = _merge_topk(self.D_gt, self.I_gt, D2, np.where(I2 >= 0, I2 + self.pos, -1), self.k)
        return x

    def grow(self, size: int, indexes: dict[str, CodeIndex], st: dict[str, dict[str, Any]]) -> float:
        """Generates codes up to ``size`` and adds them to ``indexes`` (timed into ``st[name]["add_s"]``).

        Returns:
            Seconds per code of generating codes plus exact ground truth.
        """
        t_gen, grown = 0.0, size - self.pos
        while self.pos < size:
            t0 = time.perf_counter()
            x = self._next(min(self.chunk, size - self.pos))
            t_gen += time.perf_counter() - t0
            for n, index in indexes.items():
                t0 = time.perf_counter()
                index.add(x)
                st[n]["add_s"] += time.perf_counter() - t0
            self.pos += len(x)
        return t_gen / grown

    def exact_sims(self) -> tuple[float, float]:
        """Mean exact cosine of the queries' top-1 and top-k."""
        return float(self.D_gt[:, 0].mean()), float(self.D_gt[:, self.k - 1].mean())


def _measure(index: CodeIndex, e: dict[str, Any], xq: np.ndarray, I_gt: np.ndarray, k: int,
             size: int) -> dict[str, Any]:
    """Times ``e["nq"]`` queries one at a time; recall@k and top-1 against the exact ``I_gt``. Updates the
    estimates ``e`` for the next size; returns the table cell."""
    if "measured_bytes" not in e:  # serialising is a copy: do it once, at the smallest size
        e["bytes_per_code"] = e["measured_bytes"] = index.bytes_per_code()
    lat, found = [], []
    for q in xq[: e["nq"]]:
        t0 = time.perf_counter()
        found.append(index.search(q[None], k)[1][0])
        lat.append(time.perf_counter() - t0)
    I_arr = np.stack(found)
    recall = float(np.mean([len(set(a) & set(b)) / k for a, b in zip(I_arr, I_gt[: len(I_arr)])]))
    top1 = float(np.mean(I_arr[:, 0] == I_gt[: len(I_arr), 0]))
    # the next size's build is estimated from the adds alone: a trained index learns its quantisers once
    e.update(add_per_code=(e["add_s"] - getattr(index, "train_seconds", 0.0)) / size, lat_s=float(np.median(lat)),
             lat_n=size)
    return {"ms": e["lat_s"] * 1e3, "recall": recall, "top1": top1, "queries": len(I_arr),
            "bytes_per_code": e["bytes_per_code"], "build_s": e["add_s"], "gib": e["bytes_per_code"] * size / 2**30}


#: indexes measured by default. ``ivfpq`` is left out: learning OPQ + IVF-PQ takes minutes on 2 cores (271 s on the
#: first 10k codes under load, BENCHMARKS.md "Issue 18"), too long for ``cae-lcd bench``; it is registered and
#: tested (``tests/retrieval/test_index.py``) and measured with ``--names ... ivfpq``.
DEFAULT_NAMES: tuple[str, ...] = ("flat", "fp16", "sq8", "hnsw")


def _index_confs(names: Sequence[str], chunk: int) -> dict[str, dict[str, Any]]:
    confs = {n: dict(INDEX_CONFS.get(n, {"name": n})) for n in names}
    if "sq8" in confs:  # learn the quantiser from the first chunk, so every size reported is quantised
        confs["sq8"]["train_size"] = min(chunk, 1000)
    if "ivfpq" in confs:  # the same for IVF-PQ: lists about 4 sqrt(first chunk), trained on it
        confs["ivfpq"].update(train_size=chunk, nlist=max(16, int(4 * math.sqrt(chunk)) // 16 * 16))
    return confs


def index_scaling(base: np.ndarray, sizes: Sequence[int] = (10_000, 100_000, 1_000_000),
                  names: Sequence[str] = DEFAULT_NAMES, n_queries: int = 50, k: int = 10,
                  sigma: float = 0.01, chunk: int = 10_000, memory_gib: float = 6.0, cell_time_s: float = 90.0,
                  budget: Budget | None = None, seed: int = 0, base_label: str = "KITTI 00 + 07") -> dict[str, Any]:
    """Measures every index at every size (nested: the first ``sizes[i]`` codes of one stream).

    Args:
        base: ``(B, D)`` real unit codes the synthetic ones are drawn around.
        sizes: stored-code counts, increasing.
        names: index registry names.
        n_queries: queries with exact ground truth (each is timed alone, as the detector searches).
        k: recall@k cut-off.
        sigma: per-dimension noise std of the stored codes.
        chunk: codes generated at a time.
        memory_gib: an index larger than this is skipped at that size.
        cell_time_s: an index whose estimated build + search time at a size exceeds this is skipped there.
        budget: the bench's overall budget: a size that would not fit in what is left is skipped.
        seed: seeds codes and queries.
        base_label: where ``base`` comes from (for the table's note).

    Returns:
        ``{"cells": {(name, size): {...}}, "sizes", "names", "sigma", "k", "exact_sims": {size: (top1, topk)}}``.
    """
    sizes = sorted(int(s) for s in sizes)
    rng = np.random.default_rng(seed)
    chunk = min(chunk, sizes[0])
    confs = _index_confs(names, chunk)
    st = {n: _pilot(confs[n], base, sigma, rng) for n in names}  # add s/code, latency, bytes/code: estimates
    gen_per_code = st[names[0]]["gen_per_code"] if names else 0.0
    alive = {n: create_index(base.shape[1], c) for n, c in confs.items()}
    lim = _Limits(n_queries, memory_gib, cell_time_s)
    stream = _CodeStream(base, sigma, rng, chunk, n_queries, k)
    cells: dict[tuple[str, int], dict[str, Any]] = {}
    exact_sims: dict[int, tuple[float, float]] = {}
    for size in sizes:
        _prune(alive, st, cells, size, stream.pos, gen_per_code, lim, budget)
        if not alive:
            break
        gen_per_code = stream.grow(size, alive, st)
        exact_sims[size] = stream.exact_sims()
        for n in alive:  # (no loop variable holds an index: one dropped at the next size is freed at once)
            c = cells[(n, size)] = _measure(alive[n], st[n], stream.xq, stream.I_gt, k, size)
            log.info("index %s @ %d: %.2f ms/query, recall@%d %.3f (%d queries)", n, size, c["ms"], k, c["recall"],
                     c["queries"])
    for n in names:
        for s in sizes:
            cells.setdefault((n, s), {"skipped": "skipped (see the size below)"})
    return {"cells": cells, "sizes": sizes, "names": list(names), "sigma": sigma, "k": k, "exact_sims": exact_sims,
            "n_queries": n_queries, "base": len(base), "base_label": base_label, "memory_gib": memory_gib,
            "cell_time_s": cell_time_s}


def _size_label(n: int) -> str:
    return f"{n // 1_000_000}M" if n >= 1_000_000 and n % 1_000_000 == 0 else (
        f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else str(n))


def index_table(res: dict[str, Any]) -> str:
    """Markdown: one row per index and size."""
    k = res["k"]
    rows = []
    for n in res["names"]:
        for s in res["sizes"]:
            c = res["cells"].get((n, s), {"skipped": "not run"})
            if "skipped" in c:
                rows.append([n, _size_label(s), c["skipped"], "", "", "", ""])
            else:
                rows.append([n, _size_label(s), f"{c['ms']:.2f}", f"{c['recall']:.3f}", f"{c['top1']:.2f}",
                             f"{c['bytes_per_code']:.0f}", f"{c['gib']:.2f} GiB, built in {c['build_s']:.1f} s, "
                             f"{c['queries']} queries"])
    sims = ", ".join(f"{_size_label(s)}: {a:.3f} / {b:.3f}" for s, (a, b) in res["exact_sims"].items())
    return (md_table(["index", "codes", "ms/query (median)", f"recall@{k}", "top-1 = exact", "bytes/code", "notes"],
                     rows)
            + f"\n\n- {res['base']} real codes ({res['base_label']}); more derived from them in the whitened space "
            f"(w * a + (1 - w) * b, w in [0.75, 1], + noise sigma {res['sigma']:g} per dimension, re-normalised); "
            f"queries derived again from stored codes. recall@{k} = overlap of the index's top-{k} with the "
            f"exact float32 top-{k} (brute force over all chunks). Mean exact cosine of the top-1 / top-{k}: {sims}.\n"
            f"- One query at a time (as the detector searches). Budgets: {res['memory_gib']:g} GiB per index, "
            f"{res['cell_time_s']:g} s per index and size (estimated from the size below).")


def main(sizes: Sequence[int] = (10_000, 100_000), n_real: int = 5000, out: str | Path = "runs/bench/index",
         names: Sequence[str] = DEFAULT_NAMES, memory_gib: float = 6.0,
         cell_time_s: float = 300.0) -> dict[str, Any]:
    """Realistic codes, every index at every size; writes ``index.json`` and ``index.md`` into ``out``."""
    base = realistic_codes(n_real)
    res = index_scaling(base, sizes, names, memory_gib=memory_gib, cell_time_s=cell_time_s,
                        base_label=f"{n_real} augmented real frames of ../shared, CAE, whitened 256-d")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "index.md").write_text("### Index scaling (search one query at a time)\n\n" + index_table(res) + "\n")
    (out / "index.json").write_text(json.dumps({**res, "cells": {f"{n}@{s}": c for (n, s), c in res["cells"].items()}},
                                               indent=1, default=float))
    return res


if __name__ == "__main__":
    import argparse

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(prog="python -m bench.index_scaling", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000], help="stored-code counts")
    ap.add_argument("--million", action="store_true", help="add 1,000,000 to --sizes (long: for a quiet machine)")
    ap.add_argument("--real", type=int, default=5000, help="augmented real frames encoded (issue: 20000)")
    ap.add_argument("--names", nargs="+", default=list(DEFAULT_NAMES),
                    help="index registry names (ivfpq too: see DEFAULT_NAMES)")
    ap.add_argument("--out", default="runs/bench/index")
    a = ap.parse_args()
    main(sorted(set(a.sizes) | ({1_000_000} if a.million else set())), a.real, a.out, a.names)
    print((Path(a.out) / "index.md").read_text())
