"""``cae-lcd bench``: measures this machine in one run and writes the tables into BENCHMARKS.md.

Sections (``--sections``; all but ``training`` by default):

- ``stages``: ms/frame by stage (median, p90) of the default detector on KITTI 90 at full resolution (1241x376),
  peak memory (max RSS of a fresh detect process) and bytes stored per keyframe;
- ``encoder``: encoder images/s at batch 1 and 32, channels-last vs contiguous memory, torch threads = all cores;
- ``methods``: the paper config, the default config, a thumbnail-cosine and a tf-idf bag-of-words baseline (same
  verification), on the same frames: precision, recall, max recall at 100 % precision, Recall@k, ms/frame;
- ``index``: search latency, recall@10 against exact search and bytes per code at 10k / 100k stored codes (1M with
  ``--index-sizes`` or ``python -m bench.index_scaling --million``) for each index (flat, fp16, sq8, hnsw, ivfpq),
  over realistic codes (augmented real frames, CAE, whitened; ``bench.index_scaling``);
- ``false-loops``: loops each method reports on KITTI 00 and 07 and on the aliasing stress sets of
  ``bench.aliasing`` (00 then 07, full size and 160x120; 00 then 00 mirrored at 160x120): no revisit, every loop is
  false; while time allows;
- ``training``: "does the learned code earn its place?": shipped weights vs the same network at random init vs a
  64x48 thumbnail vs the shipped weights fine-tuned on Nordland's summer half (unlabeled), single-frame Recall@1/@10
  and the detector's precision/recall, on Nordland summer -> winter, KITTI 90 at 160x120 with a dark, noisy second
  pass and KITTI 90 with a dusk second pass, also through a narrower lens (own section of BENCHMARKS.md; fine-tunes
  for a few minutes, so it is not in the default run).

The tables go between ``<!-- bench:begin -->`` and ``<!-- bench:end -->`` (training: ``bench:training``) of the
output file; everything outside the markers is kept. Run folders go under ``runs/bench/``. ``--quick`` uses tiny
sizes (16 frames cut from the bundled sample, 500/2000 codes) to check the command end to end in < 1 min.

``main`` is the Python API; the command line is ``cae_lcd/cli/bench.py``. Each section is one step below (``_stages``,
``_encoder``, ``_methods``, ``_index``, ``_false_loops``, ``_training``) working on one ``_Bench`` state.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.images import read_image
from cae_lcd.evaluation.ground_truth import read_loop_pairs
from retrieval.baselines import build_vocabulary
from retrieval.detect import SAMPLE_DIR
from retrieval.sequences import open_sequence

from .aliasing import stress_folders
from .common import REPO, Budget, season_frames
from .index_scaling import index_scaling, index_table, realistic_codes
from .methods import false_loops, method_confs, methods_table, run_methods, training_study, training_table
from .speed import encoder_throughput, stage_benchmark, stage_table, system_info, throughput_table

__all__ = ["SECTIONS", "DEFAULT_SECTIONS", "DATA_DIR", "main", "write_section", "make_quick_sequences"]

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


# ------------------------------------------------------------------------------------------ what the bench runs on
@dataclass
class _Data:
    """The sequences, sizes and overrides of one bench run: full KITTI, or the quick cut of the bundled sample."""

    loop_name: str  #: the sequence with revisits (stages, encoder, methods, training), as the tables name it
    loop: Path
    noloop: dict[str, Path]  #: sequences without any revisit (false loops), by name
    vocab_src: Path | list[Path]  #: images for the bag-of-words vocabulary
    vocab_k: int
    vocab_images: int | None
    vocab_label: str  #: where the vocabulary comes from, for the methods notes
    train_src: Path  #: images the quick training study fine-tunes on
    base_dirs: list[Path]  #: sequences whose real codes centre the synthetic index codes
    base_label: str
    sizes: tuple[int, ...]  #: stored-code counts of the index section
    index_real: int  #: augmented real frames encoded for the index section's codes (full run)
    index_kw: dict[str, Any]
    size_note: str  #: the frames' size, "WxH"
    override: dict[str, Any] | None  #: detector conf overrides of every run


def _quick_data(run_dir: Path, index_sizes: Sequence[int] | None) -> _Data:
    q = make_quick_sequences(run_dir / "quick")
    return _Data(loop_name="quick (16 sample frames)", loop=q["loop"], noloop={"quick-noloop": q["noloop"]},
                 vocab_src=q["vocab"], vocab_k=64, vocab_images=None, vocab_label="other sample frames",
                 train_src=q["vocab"][0].parent, base_dirs=[q["loop"]], base_label="the quick frames",
                 sizes=tuple(index_sizes or (500, 2000)), index_real=0,
                 index_kw={"n_queries": 10, "chunk": 500, "cell_time_s": 20.0}, size_note="620x188",
                 override=QUICK_OVERRIDE)


def _full_data(data: str | Path | None, index_sizes: Sequence[int] | None) -> _Data:
    root = Path(data) if data is not None else DATA_DIR
    if not (root / "90").is_dir():
        raise ConfigError(f"KITTI sequences not found under {root} (need 00, 07, 90); pass --data")
    h, w = read_image(open_sequence(root / "90").frames[0]).shape[:2]
    noloop = {"00": root / "00", "07": root / "07", **stress_folders(root, REPO / "runs" / "bench" / "stress")}
    return _Data(loop_name="KITTI 90", loop=root / "90", noloop=noloop,
                 vocab_src=root / "07", vocab_k=1000, vocab_images=80, vocab_label="KITTI 07",
                 train_src=root / "07" / "image_0", base_dirs=[root / "00", root / "07"],
                 base_label="augmented real frames of ../shared, CAE, whitened 256-d",
                 sizes=tuple(index_sizes or (10_000, 100_000)), index_real=5000, index_kw={},
                 size_note=f"{w}x{h}",
                 override=None)


@dataclass
class _Bench:
    """One bench run's state: each section step reads what it needs and adds its results and Markdown."""

    data: _Data
    run_dir: Path
    quick: bool
    budget: Budget
    index_memory_gib: float
    training_epochs: int
    results: dict[str, Any] = field(default_factory=dict)
    md: dict[str, str] = field(default_factory=dict)  #: section -> Markdown, in the order written
    timing: dict[str, float] = field(default_factory=dict)  #: step -> elapsed seconds at its end
    vocab: Path | None = None
    confs: dict[str, dict[str, Any]] = field(default_factory=dict)  #: detector conf by method label
    done: dict[str, dict[str, Any]] = field(default_factory=dict)  #: method label -> summary of a run already made
    false_loops: dict[tuple[str, str], int | str] | None = None
    _encoder: Any = None

    def encoder(self) -> Any:
        """The CAE encoder on the CPU, loaded once."""
        if self._encoder is None:
            import cae

            self._encoder = cae.load_encoder(device="cpu")
        return self._encoder


# ------------------------------------------------------------------------------------------------ the sections
def _vocabulary(b: _Bench) -> None:
    d = b.data
    name = f"vocab_k{d.vocab_k}{'_quick' if b.quick else '_07'}.npz"
    b.vocab = build_vocabulary(d.vocab_src, b.run_dir / name, d.vocab_k, max_images=d.vocab_images)


def _stages(b: _Bench) -> None:
    d = b.data
    log.info("stages: default detector on %s", d.loop_name)
    s = stage_benchmark(d.loop, b.run_dir / "methods" / "default", b.confs["default (CAE)"])
    b.done["default (CAE)"] = b.results["stages"] = s
    b.md["stages"] = f"### ms/frame by stage: default config, {d.loop_name} ({d.size_note})\n\n" + stage_table(
        s, d.size_note)


def _encoder(b: _Bench) -> None:
    log.info("encoder throughput")
    frames = [read_image(p) for p in open_sequence(b.data.loop).frames[:32]]
    r = encoder_throughput(b.encoder(), frames, (1, 8) if b.quick else (1, 32), 0.3 if b.quick else 2.0)
    b.results["encoder"] = r
    b.md["encoder"] = "### Encoder throughput (CAE network, CPU)\n\n" + throughput_table(r)


def _methods(b: _Bench) -> None:
    log.info("methods on %s", b.data.loop_name)
    b.results["methods"] = run_methods(b.data.loop, b.run_dir / "methods", b.confs, b.done)


def _index(b: _Bench) -> None:
    d = b.data
    log.info("index scaling over %s codes", "/".join(map(str, d.sizes)))
    base = _real_codes(b.encoder(), d.base_dirs) if b.quick else realistic_codes(d.index_real)
    r = index_scaling(base, d.sizes, memory_gib=b.index_memory_gib, budget=b.budget, base_label=d.base_label,
                      **d.index_kw)
    b.results["index"] = r
    b.md["index"] = "### Index scaling (search one query at a time)\n\n" + index_table(r)


def _false_loops(b: _Bench) -> None:
    ms = {k: v["ms_total"] for k, v in b.results.get("methods", {}).items()}
    b.false_loops = false_loops(b.data.noloop, b.run_dir / "false_loops", b.confs, ms, b.budget)
    b.results["false_loops"] = {f"{k[0]} @ {k[1]}": v for k, v in b.false_loops.items()}


def _methods_md(b: _Bench) -> str:
    """The methods table, with the false-loop columns when that section ran (so it is written after it)."""
    d = b.data
    fl_names = tuple(d.noloop) if b.false_loops is not None else ()
    notes = (f"\n\n- Same frames, same run; every method is followed by the same SIFT ratio-test + RANSAC "
             f"verification and its own policy. Max recall at 100 % precision sweeps the best candidate's "
             f"inliers per query (cosine where the config has no geometric check). Recall@k: retrieval alone.\n"
             f"- bovw: {d.vocab_k} words, faiss k-means on SIFT of {d.vocab_label} (tf-idf, idf from the same images"
             f"{'' if b.quick else '; its false-loop count on 07 is in-domain'}); thumbnail: grey 64x48, "
             f"zero-mean, unit norm.")
    if fl_names:
        notes += (" False loops: loops reported on sequences without any revisit; 'not run (time)' = left out "
                  "to stay within the time budget.")
    return (f"### Methods side by side: {d.loop_name}\n\n"
            + methods_table(b.results["methods"], b.confs, b.false_loops, fl_names) + notes)


def _training(b: _Bench) -> None:
    d = b.data
    sets = _quick_study_sets(d) if b.quick else _study_sets(b.run_dir, d)
    tune = {"epochs": 1 if b.quick else b.training_epochs, "patience": 0, "threads": 2,
            **({"batch_size": 8, "max_images": 24} if b.quick else {})}
    log.info("training study on %s (fine-tuning for %d epochs)", ", ".join(s.name for s in sets), tune["epochs"])
    r = training_study(sets, b.run_dir / "training", tune, override=d.override)
    b.results["training"] = r
    tuned = "; ".join(f"{name}: {t['images']} images, {t['epochs_run']} epochs, {t['s_per_epoch']:.0f} s an epoch, "
                      f"{t['wall_s']:.0f} s in all" for name, t in r["tuned"].items())
    b.md["training"] = ("### Does the learned code earn its place? Shipped weights, random weights, a thumbnail and "
                        "fine-tuned weights where conditions change\n\n" + training_table(r)
                        + "\n\n- Single frame: each frame of the second traversal against every frame at least "
                        "`search.exclude_recent` (50) frames older, first traversal and its own alike, codes whitened "
                        "by a PCA fitted on the sequence's own codes (256-d at most, as the detector), cosine, no "
                        "temporal filter. "
                        "Detector: the default config, only the descriptor differs (calibrated; max recall at 100 % "
                        "precision swept on its confidence).\n- Fine-tuned: `cae-lcd train --images DIR --init "
                        f"shipped`, 2 torch threads, without labels ({tuned or 'none'}).\n- "
                        "`cae-lcd bench --training-study`.")


def _quick_study_sets(d: _Data) -> list[Any]:
    """The quick cut of the bundled sample (8 frames, then 8 revisiting them), fine-tuned on other sample frames."""
    from .methods import StudySet

    return [StudySet("quick (16 sample frames)", d.loop, 8, read_loop_pairs(d.loop / "loops.txt"), d.train_src)]


LENS = 0.8  #: the narrower lens of the training study's last set: the centre share of each side (a 1.25x zoom)


def _study_sets(run_dir: Path, d: _Data) -> list[Any]:
    """Nordland summer -> winter (fine-tuned on a folder of links to the summer half), the same with its winter
    frames darkened (``bench.augment.darken``) and at half their resolution (``bench.augment.coarse``), KITTI 90 at
    160x120 with a dark, noisy second pass, and KITTI 90 at full size with a dusk second pass, also seen through a
    narrower lens (``LENS``: another camera than the one that mapped)."""
    from .aliasing import dark_proxy_folder, dusk_folder, plain_folder
    from .augment import coarse, darken
    from .methods import StudySet

    nordland = d.loop.parent.parent.parent / "nordland"
    if not (nordland / "images").is_dir():
        raise ConfigError(f"the training study needs {nordland} (Nordland, summer and winter)")
    summer = run_dir / "nordland_summer"
    summer.mkdir(parents=True, exist_ok=True)
    for src in season_frames(nordland, "summer"):
        link = summer / src.name
        if not link.exists():
            link.symlink_to(src.resolve())
    frames90 = list(open_sequence(d.loop).frames)
    truth90 = read_loop_pairs(d.loop / "loops.txt")
    frames, n_summer = list(open_sequence(nordland).frames), len(season_frames(nordland, "summer"))
    truth = read_loop_pairs(nordland / "loops.txt")
    rng = np.random.default_rng(0)
    dark = plain_folder(run_dir / "study_nordland_dark", frames, None, lambda image: darken(image, rng), n_summer)
    half = plain_folder(run_dir / "study_nordland_half", frames, None, coarse, n_summer)
    return [StudySet("Nordland summer -> winter (64x32)", nordland, n_summer, truth, summer),
            StudySet("Nordland, winter frames darkened", dark, n_summer, truth),
            StudySet("Nordland, winter frames at half resolution", half, n_summer, truth),
            StudySet("KITTI 90 at 160x120, second pass dark and noisy",
                     dark_proxy_folder(run_dir / "study_k90_160_dark", frames90), len(frames90) // 2, truth90),
            StudySet("KITTI 90 (1241x376), second pass at dusk", dusk_folder(run_dir / "study_k90_dusk", frames90),
                     len(frames90) // 2, truth90),
            StudySet(f"KITTI 90 (1241x376), second pass at dusk through a narrower lens (centre {LENS:.0%})",
                     dusk_folder(run_dir / "study_k90_dusk_lens", frames90, lens=LENS), len(frames90) // 2, truth90)]


#: the section steps, in the order they run (methods' table waits for false-loops' column; see ``main``)
_STEPS: dict[str, Callable[[_Bench], None]] = {"stages": _stages, "encoder": _encoder, "methods": _methods,
                                              "index": _index, "false-loops": _false_loops, "training": _training}


# ---------------------------------------------------------------------------------------------- the report
def _head(b: _Bench, seconds: float) -> str:
    """The line above the tables: when, on what machine, and where the time went."""
    info = b.results["system"]
    prev, spent = 0.0, []
    for name, t in b.timing.items():
        spent.append(f"{name} {t - prev:.0f} s")
        prev = t
    head = (f"Generated by `cae-lcd bench{' --quick' if b.quick else ''}` on {time.strftime('%Y-%m-%d %H:%M')}: "
            f"{info['cpu']}, {info['cores']} cores, load average {info['load_avg'][0]:.1f} at start (shared machine: "
            f"timings are noisy), torch {info['torch']}, faiss {info['faiss']}. Total {seconds:.0f} s "
            f"(budget {b.budget.seconds:.0f} s: {', '.join(spent)}).")
    if b.quick:
        head += " **Quick mode: tiny sizes, the numbers are not meaningful.**"
    return head


def _write(out: str | Path, md: dict[str, str], head: str) -> None:
    """The main tables between the bench markers of ``out``; the training study between its own."""
    main_md = [md[s] for s in ("stages", "encoder", "methods", "index") if s in md]
    if main_md:
        write_section(out, "## Generated by `cae-lcd bench`\n\n" + head + "\n\n" + "\n\n".join(main_md))
    if "training" in md:
        write_section(out, "## Generated by `cae-lcd bench --training-study`\n\n" + head + "\n\n" + md["training"],
                      "training")


def _check_sections(sections: Sequence[str] | None) -> tuple[str, ...]:
    sections = tuple(DEFAULT_SECTIONS if sections is None else sections)
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"unknown bench section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    return sections


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
        index_sizes: stored-code counts; None = 10k, 100k (quick: 500, 2000).
        training_epochs: epochs of the fine-tuning in the training study.

    Returns:
        ``{"markdown": {section: text}, "results": {...}, "seconds": float, "out": str, "head": str}``.
    """
    budget = Budget(budget_s)
    sections = _check_sections(sections)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    info = system_info()  # before anything runs: the load average "at start"
    setup = _quick_data(run_dir, index_sizes) if quick else _full_data(data, index_sizes)
    b = _Bench(setup, run_dir, quick, budget, index_memory_gib, training_epochs, results={"system": info})
    if "methods" in sections or "false-loops" in sections:
        _vocabulary(b)
        b.timing["vocabulary"] = budget.elapsed()
    b.confs = method_confs(b.vocab or "", setup.override)
    for name, step in _STEPS.items():
        if name in sections:
            step(b)
            b.timing[name] = budget.elapsed()
        if name == "false-loops" and "methods" in sections:
            b.md["methods"] = _methods_md(b)
    seconds = budget.elapsed()
    head = _head(b, seconds)
    _write(out, b.md, head)
    log.info("bench done in %.0f s; wrote %s", seconds, out)
    return {"markdown": b.md, "results": b.results, "seconds": seconds, "out": str(out), "head": head}
