"""The run folder that ``detect`` writes and ``evaluate`` and ``bench`` read: the one home of its file names and
columns.

    conf.yaml        the resolved configuration
    calibration.h5   what the calibration chose (``retrieval.calibrate``); a resumed run reuses it
    keyframes.h5     the keyframe database (``retrieval.database``); a killed run resumes from it
    loops.csv        LOOPS_COLUMNS, one row per accepted loop (best match per query)
    candidates.csv   CANDIDATE_COLUMNS, every hypothesis judged (for PR curves)
    summary.json     counts, ms/frame by stage (and precision/recall when the CLI knew the ground truth)
    loop_edges.g2o   one ``EDGE_SE3:QUAT match query`` per accepted loop with a pose (``retrieval.edges``: the query
                     camera in the match camera's frame, translation up to scale, information from the inlier
                     count), preceded by ``VERTEX_SE3:QUAT`` lines with the frames' stored poses when known
    loop_edges.csv   EDGE_COLUMNS, the same edges (sigmas instead of the information matrix)
    loop_edges.json  the same edges with ``R``, ``t``, the information matrix and a note on what they mean
    ground_truth_poses.txt  the sequence's ground-truth poses, one KITTI row a frame (TUM, EuRoC: layouts whose
                     poses are ground truth; ``evaluate`` derives the loop ground truth from them)

Tables and the summary are written to a temporary file and renamed, so a crash never leaves half a file where a
good one was; what is read back is checked (numeric, finite, integer frame ids).
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from core.errors import ConfigError
from core.files import atomic_write, write_text_atomic

from .database import LOG_SUFFIX
from .edges import LoopEdge, rotation_to_quaternion

__all__ = ["RunFolder", "LOOPS_COLUMNS", "CANDIDATE_COLUMNS", "EDGE_COLUMNS", "MAX_FRAME_ID", "read_csv_table"]

log = logging.getLogger(__name__)

LOOPS_COLUMNS = ("query", "match", "score", "matches", "inliers", "seq_score", "confidence")
CANDIDATE_COLUMNS = ("query", "candidate", "score", "matches", "inliers", "seq_score", "confidence", "accepted")
EDGE_COLUMNS = ("query", "match", "inliers", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "sigma_trans", "sigma_rot_rad")
EDGE_NOTE = ("relative pose of the query camera in the match camera's frame (x_match = R x_query + t); t is a unit "
             "direction: the translation is known up to scale only (two images, no depth); information = inliers / "
             "sigma_1^2 per axis (retrieval/edges.py)")  #: what the edge files hold, written into the JSON
MAX_FRAME_ID = 10**9  #: larger frame ids in a table are refused (they would be a damaged file, not a sequence)


def read_csv_table(path: str | Path, columns: tuple[str, ...], id_columns: int = 2) -> np.ndarray:
    """A numeric CSV with a header holding at least ``columns`` -> ``(R, len(columns))`` float64 in that order.

    Args:
        path: the CSV file.
        columns: the columns to read, in this order.
        id_columns: the first this many columns are frame ids: non-negative integers up to ``MAX_FRAME_ID``.

    Raises:
        ConfigError: missing or unreadable file, a missing column, a non-numeric, non-finite or out-of-range value
            (the message names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"not found: {path}")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                raise ConfigError(f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(columns)}")
            rows = []
            for r in reader:
                try:
                    row = [float(r[c]) for c in columns]
                except (TypeError, ValueError):
                    raise ConfigError(f"{path}, line {reader.line_num}: non-numeric value") from None
                ids = row[:id_columns]
                if not np.isfinite(row).all() or any(v < 0 or v > MAX_FRAME_ID or v != int(v) for v in ids):
                    raise ConfigError(f"{path}, line {reader.line_num}: frame ids must be integers in "
                                      f"0..{MAX_FRAME_ID} and scores finite")
                rows.append(row)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise ConfigError(f"cannot read {path}: not a CSV table ({type(err).__name__})") from None
    return np.array(rows, np.float64).reshape(-1, len(columns))


def _file(name: str) -> property:
    """A run folder's file ``name`` as a read-only ``Path`` attribute."""
    return property(lambda self: self.root / name, doc=f"``{name}`` in the run folder")


@dataclass(frozen=True)
class RunFolder:
    """The files of one run (see the module doc)."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    conf = _file("conf.yaml")
    calibration = _file("calibration.h5")
    database = _file("keyframes.h5")
    loops = _file("loops.csv")
    candidates = _file("candidates.csv")
    summary = _file("summary.json")
    ground_truth_poses = _file("ground_truth_poses.txt")
    edges_g2o = _file("loop_edges.g2o")
    edges_csv = _file("loop_edges.csv")
    edges_json = _file("loop_edges.json")

    def check_resumable(self) -> None:
        """Refuses a folder that holds results but no keyframe database (nor its write-ahead log): files a run would
        overwrite without resuming anything (another tool's ``loops.csv``, a run whose database was removed).

        Raises:
            ConfigError: naming the files found.
        """
        if self.database.exists() or self.database.with_name(self.database.name + LOG_SUFFIX).exists():
            return
        found = [p.name for p in (self.conf, self.loops, self.candidates, self.summary, self.ground_truth_poses,
                                  self.edges_g2o, self.edges_csv, self.edges_json) if p.exists()]
        if found:
            raise ConfigError(f"{self.root} holds {', '.join(found)} but no keyframes.h5 (not a run to resume): "
                              "choose another --out, or remove them")

    def write_ground_truth_poses(self, poses: np.ndarray) -> Path:
        """Writes ``(N, 3, 4)`` camera-to-world poses as a KITTI poses file (12 numbers a line); returns its path."""
        rows = np.asarray(poses, np.float64).reshape(-1, 12)
        write_text_atomic(self.ground_truth_poses, "".join(" ".join(f"{v:.9g}" for v in r) + "\n" for r in rows))
        return self.ground_truth_poses

    def write_tables(self, results: Iterable[tuple[int, np.ndarray, int]]) -> np.ndarray:
        """Writes ``loops.csv`` and ``candidates.csv`` from ``(query, candidates (k, 6), loop)`` rows (as
        ``KeyframeDatabase.results`` gives them); returns the loops ``(L, 2)``.

        Every row is read before anything is written: a damaged database leaves the old tables as they were.
        """
        rows = list(results)
        loops = []
        with atomic_write(self.loops, newline="") as f_loops, atomic_write(self.candidates, newline="") as f_c:
            wl, wc = csv.writer(f_loops), csv.writer(f_c)
            wl.writerow(LOOPS_COLUMNS)
            wc.writerow(CANDIDATE_COLUMNS)
            for q, candidates, loop in rows:
                for cid, score, matches, inliers, seq_score, confidence in candidates:
                    row = [q, int(cid), f"{score:.6f}", int(matches), int(inliers), f"{seq_score:.6f}",
                           f"{confidence:.4f}"]
                    wc.writerow(row + [int(int(cid) == loop)])
                    if int(cid) == loop:
                        wl.writerow(row)
                        loops.append((q, loop))
        return np.array(loops, np.int64).reshape(-1, 2)

    def read_loops(self) -> np.ndarray:
        """``(L, 7)`` float64 rows of ``LOOPS_COLUMNS``."""
        return read_csv_table(self.loops, LOOPS_COLUMNS)

    def read_candidates(self) -> np.ndarray | None:
        """``(C, 8)`` float64 rows of ``CANDIDATE_COLUMNS``; None when the run has no candidates.csv."""
        return read_csv_table(self.candidates, CANDIDATE_COLUMNS) if self.candidates.is_file() else None

    def write_edges(self, edges: list[LoopEdge], poses: np.ndarray | None = None) -> None:
        """Writes ``loop_edges.g2o``, ``.csv`` and ``.json`` (see the module doc).

        Args:
            edges: the loops' relative poses (``retrieval.edges.loop_edges``).
            poses: ``(n, 3, 4)`` camera-to-world poses by frame id (NaN where unknown), for the g2o vertices; None:
                edges only.
        """
        ids = sorted({e.match for e in edges} | {e.query for e in edges})
        vertices = [] if poses is None else [i for i in ids if i < len(poses) and np.isfinite(poses[i]).all()]
        g2o = []
        for i in vertices:
            q = rotation_to_quaternion(poses[i][:, :3])
            g2o.append(f"VERTEX_SE3:QUAT {i} " + " ".join(f"{v:.9g}" for v in (*poses[i][:, 3], *q)))
        rows, items = [], []
        for e in edges:
            info = e.information()
            upper = info[np.triu_indices(6)]
            g2o.append(f"EDGE_SE3:QUAT {e.match} {e.query} " + " ".join(f"{v:.9g}" for v in (*e.t, *e.quaternion()))
                       + " " + " ".join(f"{v:.9g}" for v in upper))
            sig = 1.0 / np.sqrt(np.diag(info))
            rows.append([e.query, e.match, e.inliers, *(f"{v:.9g}" for v in (*e.t, *e.quaternion(), sig[0], sig[3]))])
            items.append({"query": e.query, "match": e.match, "inliers": e.inliers, "R": e.R.tolist(),
                          "t": e.t.tolist(), "information": info.tolist()})
        write_text_atomic(self.edges_g2o, "".join(line + "\n" for line in g2o))
        with atomic_write(self.edges_csv, newline="") as f:
            w = csv.writer(f)
            w.writerow(EDGE_COLUMNS)
            w.writerows(rows)
        write_text_atomic(self.edges_json, json.dumps({"note": EDGE_NOTE, "edges": items}, indent=1))

    def read_edges(self) -> np.ndarray:
        """``(E, 12)`` float64 rows of ``EDGE_COLUMNS``."""
        return read_csv_table(self.edges_csv, EDGE_COLUMNS)

    def read_edge_list(self) -> list[LoopEdge]:
        """The edges of ``loop_edges.json`` as ``LoopEdge`` objects.

        Raises:
            ConfigError: a missing or malformed file.
        """
        try:
            items = json.loads(self.edges_json.read_text(encoding="utf-8"))["edges"]
            return [LoopEdge(int(d["query"]), int(d["match"]), int(d["inliers"]),
                             np.array(d["R"], np.float64).reshape(3, 3), np.array(d["t"], np.float64).reshape(3))
                    for d in items]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"cannot read {self.edges_json}: {type(err).__name__}") from None

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_text_atomic(self.summary, json.dumps(summary, indent=1))

    def read_summary(self) -> dict[str, Any]:
        """The summary; ``{}`` with a warning when it is missing or unreadable (nothing depends on it alone)."""
        if not self.summary.is_file():
            return {}
        try:
            data = json.loads(self.summary.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            log.warning("cannot read %s (%s); going on without it", self.summary, type(err).__name__)
            return {}
        if not isinstance(data, dict):
            log.warning("%s is not a JSON object; going on without it", self.summary)
            return {}
        return data
