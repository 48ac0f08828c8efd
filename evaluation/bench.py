"""``cae-lcd bench``: measures this machine in one run and writes the tables into BENCHMARKS.md.

Sections (``--sections``; all but ``training`` by default):

- ``stages``: ms/frame by stage (median, p90) of the default detector on KITTI 90 at full resolution (1241x376),
  peak memory (max RSS of a fresh detect process) and bytes stored per keyframe;
- ``encoder``: encoder images/s at batch 1 and 32, channels-last vs contiguous memory, torch threads = all cores;
- ``methods``: the paper config, the default config, a thumbnail-cosine and a tf-idf bag-of-words baseline (same
  verification), on the same frames: precision, recall, max recall at 100 % precision, Recall@k, ms/frame;
- ``index``: search latency, recall@10 against exact search and bytes per code at 10k / 100k / 1M stored codes for
  each index (flat, fp16, sq8, hnsw), over synthetic codes built around real CAE codes;
- ``false-loops``: loops each method reports on KITTI 00 and 07 (no revisit: all false), while time allows;
- ``training``: "does training help?": shipped vs random vs other-data weights (own section of BENCHMARKS.md;
  trains for a few minutes, so it is not in the default run).

The tables go between ``<!-- bench:begin -->`` and ``<!-- bench:end -->`` (training: ``bench:training``) of the
output file; everything outside the markers is kept. Run folders go under ``runs/bench/``. ``--quick`` uses tiny
sizes (16 frames cut from the bundled sample, 500/2000 codes) to check the command end to end in < 1 min.
"""

from __future__ import annotations

import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cae.cli import api_defaults
from cae.conf import ConfigError
from cae.preprocess import read_image
from retrieval.baselines import build_vocabulary
from retrieval.sequences import open_sequence, read_loop_pairs

from .bench_common import REPO, Budget
from .bench_index import index_scaling, index_table
from .bench_methods import false_loops, method_confs, methods_table, run_methods, training_study, training_table
from .bench_speed import encoder_throughput, stage_benchmark, stage_table, system_info, throughput_table

__all__ = ["SECTIONS", "DEFAULT_SECTIONS", "DATA_DIR", "main", "write_section", "make_quick_sequences", "add_parser"]

log = logging.getLogger(__name__)

SECTIONS = ("stages", "encoder", "methods", "index", "false-loops", "training")
DEFAULT_SECTIONS = SECTIONS[:-1]
DATA_DIR = REPO.parent / "shared" / "datasets" / "kitti" / "sequences"  #: ../shared KITTI sequences
HEADER = ("# Benchmarks\n\nMeasured on one machine; `cae-lcd bench` rewrites the generated sections between its "
          "markers.\n")
QUICK_OVERRIDE = {"search": {"exclude_recent": 8}}  # the quick sequences have 12-16 frames


def write_section(path: str | Path, body: str, name: str = "") -> Path:
    """Replaces the text between ``<!-- bench[:name]:begin -->`` and ``<!-- bench[:name]:end -->`` in ``path``.

    A missing file is created with a short header; a file without the markers gets them appended. Text outside
    the markers is kept byte for byte.
    """
    path = Path(path)
    tag = f"bench:{name}" if name else "bench"
    begin, end = f"<!-- {tag}:begin -->", f"<!-- {tag}:end -->"
    text = path.read_text() if path.is_file() else HEADER
    block = f"{begin}\n{body.strip()}\n{end}"
    i, j = text.find(begin), text.find(end)
    if i >= 0 and j > i:
        text = text[:i] + block + text[j + len(end):]
    else:
        if i >= 0 or j >= 0:
            raise ConfigError(f"{path}: unbalanced markers {begin} / {end}; fix the file by hand")
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _copy_frames(src: Path, indices: Sequence[int], dst: Path, loops: np.ndarray | None) -> Path:
    """A KITTI-layout sequence of the bundled sample's frames ``indices`` (renumbered), with calib/times/poses and
    the ground-truth pairs among them."""
    shutil.rmtree(dst, ignore_errors=True)
    (dst / "image_0").mkdir(parents=True)
    for n, i in enumerate(indices):
        shutil.copyfile(src / "image_0" / f"{i:06d}.jpg", dst / "image_0" / f"{n:06d}.jpg")
    shutil.copyfile(src / "calib.txt", dst / "calib.txt")
    for name in ("times.txt", "poses.txt"):
        lines = (src / name).read_text().splitlines()
        (dst / name).write_text("\n".join(lines[i] for i in indices) + "\n")
    if loops is not None:
        new = {old: n for n, old in enumerate(indices)}
        pairs = [f"{new[a]} {new[b]}" for a, b in loops.tolist() if a in new and b in new]
        (dst / "loops.txt").write_text("\n".join(pairs) + "\n")
    return dst


def make_quick_sequences(dst: str | Path) -> dict[str, Any]:
    """Tiny sequences cut from the bundled sample: ``loop`` (8 first-pass + 8 revisiting frames, ground truth),
    ``noloop`` (12 first-pass frames, no revisit) and ``vocab`` (other frames, for the visual vocabulary)."""
    from retrieval.detect import SAMPLE_DIR

    dst = Path(dst)
    loops = read_loop_pairs(SAMPLE_DIR / "loops.txt")
    return {"loop": _copy_frames(SAMPLE_DIR, [*range(0, 8), *range(50, 58)], dst / "loop", loops),
            "noloop": _copy_frames(SAMPLE_DIR, list(range(30, 42)), dst / "noloop", None),
            "vocab": [SAMPLE_DIR / "image_0" / f"{i:06d}.jpg" for i in range(62, 100, 2)]}


def _real_codes(encoder: Any, folders: Sequence[Path]) -> np.ndarray:
    import cae

    frames = [p for f in folders for p in open_sequence(f).frames]
    return np.concatenate([cae.encode_images(encoder, [read_image(p) for p in frames[i:i + 32]])
                           for i in range(0, len(frames), 32)])


def main(out: str | Path = "BENCHMARKS.md", run_dir: str | Path = "runs/bench", quick: bool = False,
         sections: Sequence[str] | None = None, data: str | Path | None = None, budget_s: float = 540.0,
         index_memory_gib: float = 6.0, index_sizes: Sequence[int] | None = None,
         training_epochs: int = 5) -> dict[str, Any]:
    """Runs the benchmark and writes its tables into ``out`` between the bench markers.

    Args:
        out: Markdown file to update (created if missing).
        run_dir: folder for the detect runs, the vocabulary and checkpoints (rewritten).
        quick: tiny sizes (bundled sample, 500/2000 codes): checks the command, numbers mean little.
        sections: subset of ``SECTIONS``; None = ``DEFAULT_SECTIONS`` (everything but ``training``).
        data: KITTI ``sequences`` folder holding 00, 07 and 90; None = ``../shared/datasets/kitti/sequences``.
        budget_s: wall-clock budget; optional parts (1M codes, false-loop runs) are skipped when they would not fit.
        index_memory_gib: an index larger than this is not built (e.g. 1M float32 codes = 15.3 GiB).
        index_sizes: stored-code counts; None = 10k, 100k, 1M (quick: 500, 2000).
        training_epochs: epochs of the "trained on other data" weights in the training study.

    Returns:
        ``{"markdown": {section: text}, "results": {...}, "seconds": float, "out": str}``.
    """
    budget = Budget(budget_s)
    sections = tuple(DEFAULT_SECTIONS if sections is None else sections)
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"unknown bench section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    info = system_info()
    if quick:
        q = make_quick_sequences(run_dir / "quick")
        seq_loop, seq_noloop = {"name": "quick (16 sample frames)", "path": q["loop"]}, {"quick-noloop": q["noloop"]}
        vocab_src, vocab_k, override, base_dirs = q["vocab"], 64, QUICK_OVERRIDE, [q["loop"]]
        vocab_images, base_label = None, "the quick frames"
        sizes = tuple(index_sizes or (500, 2000))
        index_kw = {"n_queries": 10, "chunk": 500, "cell_time_s": 20.0}
        size_note = "620x188"
    else:
        root = Path(data) if data is not None else DATA_DIR
        if not (root / "90").is_dir():
            raise ConfigError(f"KITTI sequences not found under {root} (need 00, 07, 90); pass --data")
        seq_loop, seq_noloop = {"name": "KITTI 90", "path": root / "90"}, {"00": root / "00", "07": root / "07"}
        vocab_src, vocab_k, override, base_dirs = root / "07", 1000, None, [root / "00", root / "07"]
        vocab_images, base_label = 80, "KITTI 00 + 07"
        sizes = tuple(index_sizes or (10_000, 100_000, 1_000_000))
        index_kw = {}
        h, w = read_image(open_sequence(root / "90").frames[0]).shape[:2]
        size_note = f"{w}x{h}"
    md: dict[str, str] = {}
    results: dict[str, Any] = {"system": info}
    timing: dict[str, float] = {}  # section -> elapsed seconds at its end
    vocab = None
    if "methods" in sections or "false-loops" in sections:
        vocab = build_vocabulary(vocab_src, run_dir / f"vocab_k{vocab_k}{'_quick' if quick else '_07'}.npz", vocab_k,
                                 max_images=vocab_images)
        timing["vocabulary"] = budget.elapsed()
    confs = method_confs(vocab or "", override)
    done: dict[str, dict[str, Any]] = {}

    if "stages" in sections:
        log.info("stages: default detector on %s", seq_loop["name"])
        s = stage_benchmark(seq_loop["path"], run_dir / "methods" / "default", confs["default (CAE)"])
        done["default (CAE)"] = s
        results["stages"] = s
        md["stages"] = (f"### ms/frame by stage: default config, {seq_loop['name']} ({size_note})\n\n"
                        + stage_table(s, size_note))
        timing["stages"] = budget.elapsed()
    encoder = None
    if "encoder" in sections or "index" in sections:
        import cae

        encoder = cae.load_encoder(device="cpu")
    if "encoder" in sections:
        log.info("encoder throughput")
        frames = [read_image(p) for p in open_sequence(seq_loop["path"]).frames[:32]]
        r = encoder_throughput(encoder, frames, (1, 8) if quick else (1, 32), 0.3 if quick else 2.0)
        results["encoder"] = r
        md["encoder"] = "### Encoder throughput (CAE network, CPU)\n\n" + throughput_table(r)
        timing["encoder"] = budget.elapsed()
    if "methods" in sections:
        log.info("methods on %s", seq_loop["name"])
        r = run_methods(seq_loop["path"], run_dir / "methods", confs, done)
        results["methods"] = r
        timing["methods"] = budget.elapsed()
    if "index" in sections:
        log.info("index scaling over %s codes", "/".join(map(str, sizes)))
        base = _real_codes(encoder, base_dirs)
        r = index_scaling(base, sizes, memory_gib=index_memory_gib, budget=budget, base_label=base_label, **index_kw)
        results["index"] = r
        md["index"] = "### Index scaling (search one query at a time)\n\n" + index_table(r)
        timing["index"] = budget.elapsed()
    fl, fl_names = None, ()
    if "false-loops" in sections:
        ms = {k: v["ms_total"] for k, v in results.get("methods", {}).items()}
        fl = false_loops(seq_noloop, run_dir / "false_loops", confs, ms, budget)
        fl_names = tuple(seq_noloop)
        results["false_loops"] = {f"{k[0]} @ {k[1]}": v for k, v in fl.items()}
        timing["false-loops"] = budget.elapsed()
    if "methods" in sections:
        notes = (f"\n\n- Same frames, same run; every method is followed by the same SIFT ratio-test + RANSAC "
                 f"verification and its own policy. Max recall at 100 % precision sweeps the best candidate's "
                 f"inliers per query (cosine where the config has no geometric check). Recall@k: retrieval alone.\n"
                 f"- bovw: {vocab_k} words, faiss k-means on SIFT of "
                 f"{'other sample frames' if quick else 'KITTI 07'} (tf-idf, idf from the same images"
                 f"{'' if quick else '; its false-loop count on 07 is in-domain'}); thumbnail: grey 64x48, "
                 f"zero-mean, unit norm.")
        if fl_names:
            notes += (" False loops: loops reported on sequences without any revisit; 'not run (time)' = left out "
                      "to stay within the time budget.")
        md["methods"] = (f"### Methods side by side: {seq_loop['name']}\n\n"
                         + methods_table(results["methods"], confs, fl, fl_names) + notes)
    if "training" in sections:
        train_src = q["vocab"][0].parent if quick else Path(vocab_src) / "image_0"
        log.info("training study (trains on %s for %d epochs)", train_src, training_epochs)
        r = training_study(seq_loop["path"], train_src, run_dir / "training", 1 if quick else training_epochs,
                           max_images=24 if quick else None, override=override)
        results["training"] = r
        md["training"] = (f"### Does training help? {seq_loop['name']}, default config, only the weights differ\n\n"
                          + training_table(r) + "\n\n- Recall@k: retrieval stage alone (before verification). Max "
                          "recall at 100 % precision: sweep on inliers. `cae-lcd bench --training-study`.")
        timing["training"] = budget.elapsed()
    seconds = budget.elapsed()
    prev, spent = 0.0, []
    for name, t in timing.items():
        spent.append(f"{name} {t - prev:.0f} s")
        prev = t
    head = (f"Generated by `cae-lcd bench{' --quick' if quick else ''}` on {time.strftime('%Y-%m-%d %H:%M')}: "
            f"{info['cpu']}, {info['cores']} cores, load average {info['load_avg'][0]:.1f} at start (shared machine: "
            f"timings are noisy), torch {info['torch']}, faiss {info['faiss']}. Total {seconds:.0f} s "
            f"(budget {budget_s:.0f} s: {', '.join(spent)}).")
    if quick:
        head += " **Quick mode: tiny sizes, the numbers are not meaningful.**"
    main_md = [md[s] for s in ("stages", "encoder", "methods", "index") if s in md]
    if main_md:
        write_section(out, "## Generated by `cae-lcd bench`\n\n" + head + "\n\n" + "\n\n".join(main_md))
    if "training" in md:
        write_section(out, "## Generated by `cae-lcd bench --training-study`\n\n" + head + "\n\n" + md["training"],
                      "training")
    log.info("bench done in %.0f s; wrote %s", seconds, out)
    return {"markdown": md, "results": results, "seconds": seconds, "out": str(out), "head": head}


_DEFAULTS = api_defaults(main)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("bench", help="measure speed, memory, index scaling and methods on this machine; "
                                     "write BENCHMARKS.md", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=_DEFAULTS["out"], help="Markdown file to update (default %(default)s)")
    p.add_argument("--run-dir", default=_DEFAULTS["run_dir"], help="folder for runs (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="tiny sizes (< 1 min): checks the command end to end")
    p.add_argument("--sections", help=f"comma-separated subset of {','.join(SECTIONS)} "
                                      f"(default: all but training)")
    p.add_argument("--skip-scale", action="store_true", help="leave out the index scaling section")
    p.add_argument("--training-study", action="store_true",
                   help="run only the training study (a few minutes; its own section of the output file)")
    p.add_argument("--data", help="KITTI sequences folder with 00, 07, 90 "
                                  "(default: ../shared/datasets/kitti/sequences)")
    p.add_argument("--budget-s", type=float, default=_DEFAULTS["budget_s"],
                   help="time budget in seconds; optional parts are skipped to fit (default %(default)s)")
    p.add_argument("--index-memory-gib", type=float, default=_DEFAULTS["index_memory_gib"],
                   help="largest index built, GiB (default %(default)s)")
    p.add_argument("--index-sizes", help="comma-separated stored-code counts (default 10000,100000,1000000)")
    p.add_argument("--training-epochs", type=int, default=_DEFAULTS["training_epochs"],
                   help="epochs for the other-data weights of the training study (default %(default)s)")
    p.set_defaults(func=_run)


def _run(args: Any) -> None:
    sections = tuple(s.strip() for s in args.sections.split(",")) if args.sections else DEFAULT_SECTIONS
    if args.training_study:
        sections = ("training",)
    if args.skip_scale:
        sections = tuple(s for s in sections if s != "index")
    sizes = tuple(int(s) for s in args.index_sizes.split(",")) if args.index_sizes else None
    res = main(args.out, args.run_dir, args.quick, sections, args.data, args.budget_s, args.index_memory_gib, sizes,
               args.training_epochs)
    sys.stdout.write(res["head"] + "\n\n" + "\n\n".join(res["markdown"].values()) + "\n")
