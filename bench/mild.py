"""MILD beside the CAE detector: ``python -m bench.mild [--parts methods,speed,recall] [--sizes 1000,10000,100000]``.

- ``methods``: ``cae`` (the default), ``mild`` and ``mild+verify`` (``retrieval.methods``) on KITTI 90 and Nordland
  (precision, recall, max recall at 100 % precision, Recall@1, ms/frame) and the loops each reports on KITTI 00 and
  07 (no revisit: all false), side by side in one run.
- ``speed``: one core; MILD's similarity (multi-index hashing, ``MultiIndexHash.query``) and its Bayesian filter per
  query against databases of 1k / 10k / 100k images, ORB extraction timed apart. The databases are real KITTI ORB
  descriptors (800 a frame, every frame of 00, 07 and 90) and, past those 560 frames, copies of them with 12.5 % of
  their bits flipped; queries are real frames. With and without the cap on over-full hash entries.
- ``recall``: P_recall(m, d) (MILD eq. 8) against the Hamming distance for m = 2..32 tables, with R(m) and E(m)
  (eq. 9): the plot a user reads to pick m (``p_recall.png`` in the run folder).

Writes each part's table between ``<!-- bench:mild-PART:begin -->`` and ``<!-- bench:mild-PART:end -->`` of
BENCHMARKS.md.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.images import read_image
from retrieval.methods import METHODS, method_conf
from retrieval.mild import DESCRIPTOR_BITS, MildDescriptor, MultiIndexHash, expected_recall, recall_probability
from retrieval.places import RowTable
from retrieval.temporal import BayesFilter

from .common import detect_run, ground_truth_pairs, md_table, study_parser
from .methods import method_metrics
from .run import write_section

__all__ = ["PARTS", "side_by_side", "query_speed", "recall_analysis", "main"]

log = logging.getLogger(__name__)

PARTS = ("methods", "speed", "recall")
KITTI = ("00", "07", "90")
FLIP_BYTES = 3  #: noisy copies: each bit flipped where 3 random bytes all have it set (p = 1/8)
DEFAULT_CAP = MildDescriptor.default_conf["max_bucket"]
UNCAPPED_UP_TO = 10_000


def side_by_side(data: Path, run_dir: Path) -> tuple[str, dict[str, Any]]:
    """Every method on KITTI 90, Nordland, 00 and 07, in one run; the Markdown table and the metrics."""
    sequences = {"KITTI 90": data / "kitti" / "sequences" / "90", "Nordland (64x32)": data / "nordland"}
    rows, res = [], {}
    for name, seq in sequences.items():
        truth = ground_truth_pairs(seq)
        for method in METHODS:
            log.info("%s: %s", name, method)
            conf = method_conf(method)
            summary = detect_run(seq, run_dir / f"{seq.name}_{method}", conf)
            res[name, method] = m = method_metrics(summary["out"], conf, truth)
            precision = f"{m['precision']:.3f}" if m["detections"] else "n/a (0 loops)"
            rows.append([name, method, f"{precision} / {m['recall']:.3f}",
                         "n/a" if m["r100"] is None else f"{m['r100']:.3f}", f"{m['recall_at_k'][1]:.3f}",
                         f"{m['ms_total']:.1f}"])
    false_loops = []
    for method in METHODS:
        counts = [detect_run(data / "kitti" / "sequences" / s, run_dir / f"noloop_{s}_{method}",
                             method_conf(method))["loops"] for s in ("00", "07")]
        res["no revisit", method] = counts
        false_loops.append([method, str(counts[0]), str(counts[1])])
    table = md_table(["sequence", "method", "precision / recall", "max recall @ 100% P", "Recall@1", "ms/frame"], rows)
    table += "\n\nLoops reported on sequences without a revisit (all false):\n\n" + \
        md_table(["method", "KITTI 00", "KITTI 07"], false_loops)
    return table, res


def _real_descriptors(data: Path) -> tuple[list[np.ndarray], float]:
    """MILD's ORB descriptors of every KITTI frame in ``data`` (00, 07, 90), and the median ms of one extraction."""
    desc = MildDescriptor()
    out, ms = [], []
    for seq in KITTI:
        for path in sorted((data / "kitti" / "sequences" / seq / "image_0").glob("*.png")):
            image = read_image(path)
            t0 = time.perf_counter()
            out.append(desc(image))
            ms.append((time.perf_counter() - t0) * 1e3)
    return out, float(np.median(ms))


def _database(real: list[np.ndarray], size: int, max_bucket: float, rng: np.random.Generator) -> MultiIndexHash:
    """``size`` images: the real ones, then noisy copies of them; sorted once (as a long run leaves it)."""
    index = MultiIndexHash(max_bucket=max_bucket)
    for i in range(size):
        d = real[i % len(real)]
        if i >= len(real):
            mask = rng.integers(0, 256, (FLIP_BYTES, *d.shape), dtype=np.uint8)
            d = d ^ np.bitwise_and.reduce(mask, axis=0)
        index.add(d)
    index.query(real[0])  # the tables are built here, outside the timing
    return index


def query_speed(data: Path, sizes: tuple[int, ...], caps: tuple[float, ...] = (0.0, DEFAULT_CAP),
                n_queries: int = 20) -> tuple[str, dict[str, Any]]:
    """Median ms per query (similarity, filter) by database size and cap, on one core; the table and the numbers.
    No cap is measured up to ``UNCAPPED_UP_TO`` images only (beyond, one query compares ~10^8 pairs: GBs)."""
    cv2.setNumThreads(1)
    real, orb_ms = _real_descriptors(data)
    queries = real[:: max(1, len(real) // n_queries)][:n_queries]
    rows, res = [], {}
    for size in sizes:
        for cap in (c for c in caps if c > 0 or size <= UNCAPPED_UP_TO):
            t0 = time.perf_counter()
            index = _database(real, size, cap, np.random.default_rng(0))
            build_s = time.perf_counter() - t0
            sim_ms, filt_ms, pairs = [], [], []
            ids = np.arange(index.n_images)
            for n, q in enumerate(queries):
                t0 = time.perf_counter()
                row = index.query(q)
                sim_ms.append((time.perf_counter() - t0) * 1e3)
                filt, source = BayesFilter(), RowTable()
                source.set(size + n, ids, row)
                t0 = time.perf_counter()
                filt.update(size + n, ids, source)
                filt_ms.append((time.perf_counter() - t0) * 1e3)
                pairs.append(len(index.compared_pairs(q)))
            res[size, cap] = {"similarity_ms": float(np.median(sim_ms)), "filter_ms": float(np.median(filt_ms)),
                              "pairs": float(np.median(pairs)), "build_s": build_s}
            r = res[size, cap]
            rows.append([f"{size:,}", "none" if cap == 0 else f"{cap:g} x mean entry", f"{r['pairs']:,.0f}",
                         f"{r['similarity_ms']:.1f}", f"{r['filter_ms']:.1f}",
                         f"{r['similarity_ms'] + r['filter_ms']:.1f}", f"{build_s:.0f}"])
            log.info("%d images, cap %g: %s", size, cap, r)
            del index
    table = md_table(["images in the database", "over-full entries skipped", "descriptor pairs compared",
                      "similarity ms", "Bayes filter ms", "similarity + filter ms", "build s"], rows)
    return table + f"\n\nORB extraction (800 features, KITTI 1241x376, one core): {orb_ms:.1f} ms a frame, apart " \
                   "from the figures above.", {"orb_ms": orb_ms, **{f"{k[0]}@{k[1]}": v for k, v in res.items()}}


def recall_analysis(run_dir: Path, ms: tuple[int, ...] = (2, 4, 8, 16, 32)) -> tuple[str, Path]:
    """P_recall curves (plot) and R(m) / E(m) (table): the cost/recall trade-off of the number of tables."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = np.arange(0, 161)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for m in ms:
        ax.plot(d, [recall_probability(m, int(x)) for x in d], label=f"m = {m} ({DESCRIPTOR_BITS // m}-bit keys)")
    for mean, std, label in ((32, 10, "inliers N(32, 10)"), (128, 20, "outliers N(128, 20)")):
        ax.axvspan(mean - std, mean + std, alpha=0.12, color="green" if mean == 32 else "red", label=label)
    ax.set(xlabel="Hamming distance d between two descriptors (bits)", ylabel="P_recall(m, d)",
           title="MILD eq. 8: chance that two descriptors share a hash key")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "p_recall.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    rows = [[str(m), f"{DESCRIPTOR_BITS // m}", f"{expected_recall(m, 32, 10):.3f}",
             f"{expected_recall(m, 128, 20):.2e}"] for m in ms]
    return md_table(["m (tables)", "bits a key", "R(m): inlier pairs compared", "E(m): outlier pairs compared (cost)"],
                    rows), path


def main(data: Path, run_dir: Path, out: Path | None, parts: tuple[str, ...] = PARTS,
         sizes: tuple[int, ...] = (1000, 10_000, 100_000)) -> dict[str, Any]:
    """Runs the chosen parts; writes each part's tables into ``out`` (sections ``mild-methods``, ``mild-speed``,
    ``mild-recall``, so that one part can be measured again alone)."""
    res: dict[str, Any] = {}
    for part in parts:
        t0 = time.perf_counter()
        if part == "methods":
            table, res[part] = side_by_side(data, run_dir)
            head = "Same data, same commands (`cae-lcd detect PATH --method cae|mild|mild+verify`), one run:"
        elif part == "speed":
            table, res[part] = query_speed(data, sizes)
            head = "Query time on one core (`MultiIndexHash.query` + `BayesFilter.update`), one run:"
        elif part == "recall":
            table, res[part] = recall_analysis(run_dir)
            head = f"Recall probability (eq. 8-9; the plot: `{res[part]}`):"
        else:
            raise ValueError(f"unknown part {part!r}; choose from {', '.join(PARTS)}")
        body = f"#### MILD: {part} (`python -m bench.mild --parts {part}`)\n\n{head}\n\n{table}\n\n" \
               f"{time.perf_counter() - t0:.0f} s."
        if out is not None:
            write_section(out, body, f"mild-{part}")
        log.info("\n%s", body)
    return res


def _cli() -> None:
    ap = study_parser(__doc__, "runs/bench/mild")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {','.join(PARTS)}")
    ap.add_argument("--sizes", default="1000,10000,100000", help="database sizes (images) for the speed part")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    main(args.data, args.run_dir, Path(args.out) if args.out else None, tuple(args.parts.split(",")),
         tuple(int(s) for s in args.sizes.split(",")))


if __name__ == "__main__":
    _cli()
