"""Many sequences, one command: one after the other in this process, or one Ray task a sequence when asked for
(``workers``: a local Ray; ``address``: a cluster's), one progress bar, and a summary table of all sequences
(``summary.csv`` and ``summary.json`` in the output folder: what each sequence skipped as unreadable, and what
could not be opened).

Each sequence writes its own run folder ``OUT/<sequence name>`` exactly as a single run does, so results are those
of running each sequence alone, and a batch stopped half-way resumes per sequence (finished ones only rewrite their
tables). Ray is the ``[ray]`` extra, imported only here and only when asked for; without it nothing is written.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from pathlib import Path
from typing import Any, Callable

from cae_lcd.core.cluster import start_ray
from cae_lcd.core.conf import ConfigError
from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.core.progress import progress_bar
from cae_lcd.core.threads import cpu_count

__all__ = ["run_batch", "batch_outs", "SUMMARY_COLUMNS"]

log = logging.getLogger(__name__)

#: columns of ``summary.csv``: one row a sequence
SUMMARY_COLUMNS = ("sequence", "frames", "keyframes", "unreadable", "loops", "precision", "recall", "ms_per_frame",
                   "status", "out")


def batch_outs(paths: list[Path], out: Path) -> list[Path]:
    """The run folder of each sequence: ``out/<sequence name>``.

    Raises:
        ConfigError: two sequences of the same name (their run folders would collide).
    """
    names = [p.name if p.is_dir() else p.stem for p in paths]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ConfigError(f"two sequences named {dupes[0]!r}: their run folders in {out} would collide; "
                          "rename one or run them separately")
    return [out / n for n in names]


def _call(task: Callable[[Path, Path], dict[str, Any]], path: Path, out: Path) -> dict[str, Any]:
    """One sequence, in a Ray worker (``task`` travels pickled: a function or a ``functools.partial`` of one)."""
    return task(path, out)


def _row(path: Path, out: Path, summary: dict[str, Any] | None, error: str | None) -> dict[str, Any]:
    if summary is None:
        return {**dict.fromkeys(SUMMARY_COLUMNS), "sequence": str(path), "status": f"error: {error}", "out": str(out)}
    g = summary.get("ground_truth") or {}
    ms = (summary.get("ms_per_frame") or {}).get("total", {}).get("median")
    if summary.get("unreadable"):
        log.warning("%s: %d unreadable frame(s) skipped (their run folder's summary.json names them)", path,
                    summary["unreadable"])
    return {"sequence": str(path), "frames": summary["frames"], "keyframes": summary["keyframes"],
            "unreadable": summary.get("unreadable", 0), "loops": summary["loops"], "precision": g.get("precision"),
            "recall": g.get("recall"),
            "ms_per_frame": None if ms is None else round(ms, 1), "status": "ok", "out": str(out)}


def _write_summary(out: Path, rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, SUMMARY_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(out / "summary.csv", buf.getvalue())
    write_text_atomic(out / "summary.json", json.dumps({"sequences": rows}, indent=1))


def _on_ray(ray: Any, paths: list[Path], outs: list[Path], task: Callable[[Path, Path], dict[str, Any]],
            bar: Any) -> list[dict[str, Any]]:
    """One Ray task a sequence; rows in the order of ``paths``."""
    remote = ray.remote(num_cpus=1, max_retries=0)(_call)
    pending = {remote.remote(task, p, o): k for k, (p, o) in enumerate(zip(paths, outs))}
    rows: list[dict[str, Any]] = [{}] * len(paths)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        k = pending.pop(done[0])
        try:
            rows[k] = _row(paths[k], outs[k], ray.get(done[0]), None)
        except ray.exceptions.RayTaskError as err:
            rows[k] = _failed(paths[k], outs[k], getattr(err, "cause", None) or err)
        bar.update(1)
    return rows


def _here(paths: list[Path], outs: list[Path], task: Callable[[Path, Path], dict[str, Any]],
          bar: Any) -> list[dict[str, Any]]:
    """The sequences one after the other in this process; a sequence that fails is a row, the others still run."""
    rows = []
    for path, out in zip(paths, outs):
        try:
            rows.append(_row(path, out, task(path, out), None))
        except Exception as err:  # noqa: BLE001 - as a Ray task's failure: reported in its row
            rows.append(_failed(path, out, err))
        bar.update(1)
    return rows


def _failed(path: Path, out: Path, err: BaseException) -> dict[str, Any]:
    message = " ".join(str(err).split())[:300]
    log.error("%s failed: %s", path, message)
    return _row(path, out, None, message)


def run_batch(paths: list[Path], out: str | Path, task: Callable[[Path, Path], dict[str, Any]],
              workers: int | None = None, address: str | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Runs ``task(sequence, run_folder)`` for every sequence (in this process, or as Ray tasks) and writes the
    summary table.

    Args:
        paths: the sequences (``retrieval.sequences.find_sequences``).
        out: the output folder; sequence ``p`` runs into ``out/<name of p>`` (resumed when it exists).
        task: ``(sequence path, run folder) -> summary dict`` (``detect.main``'s), a module-level function or a
            ``functools.partial`` of one.
        workers: tasks at once on a local Ray; None with no ``address``: one sequence after the other in this
            process (no Ray); ignored with ``address``.
        address: a Ray cluster's address (``ray://host:10001``, ``auto``); None: a local Ray when ``workers`` is
            given.
        progress: one progress bar over the sequences.

    Returns:
        One row a sequence (``SUMMARY_COLUMNS``), in the order of ``paths``; a sequence that failed has
        ``status`` ``"error: ..."`` and the others still ran.

    Raises:
        ConfigError: a bad ``workers``, colliding sequence names, Ray asked for but missing or unreachable (then
            nothing is written).
    """
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"--workers must be an integer >= 1; got {workers!r}")
    outs = batch_outs(paths, Path(out))
    ray, started = start_ray(address, workers or cpu_count()) if workers is not None or address else (None, False)
    try:
        out = prepare_out_dir(Path(out))
        bar = progress_bar(total=len(paths), desc="sequences", unit="seq", disable=not progress)
        rows = _here(paths, outs, task, bar) if ray is None else _on_ray(ray, paths, outs, task, bar)
        bar.close()
    finally:
        if started:
            ray.shutdown()
    _write_summary(out, rows)
    return rows
