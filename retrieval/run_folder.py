"""The run folder that ``detect`` writes and ``evaluate`` and ``bench`` read: the one home of its file names and
columns.

    conf.yaml        the resolved configuration
    calibration.h5   what the calibration chose (``retrieval.calibrate``); a resumed run reuses it
    keyframes.h5     the keyframe database (``retrieval.database``); a killed run resumes from it
    loops.csv        LOOPS_COLUMNS then the two frames' keys (``FrameKeys``: timestamp and id in the source), one row
                     per accepted loop (best match per query)
    candidates.csv   CANDIDATE_COLUMNS then the two frames' keys, every hypothesis judged (for PR curves)
    loops_tum.txt    ``t_query t_match`` a loop (seconds, the sequence's own stamps), to join with a TUM trajectory
    loop_edges_tum.txt  ``t_query t_match tx ty tz qx qy qz qw`` an edge: the relative pose keyed by the stamps
    summary.json     counts, ms/frame by stage (and precision/recall when the CLI knew the ground truth)
    loop_edges.g2o   one ``EDGE_SE3:QUAT match query`` per accepted loop with a pose (``retrieval.edges``: the query
                     camera in the match camera's frame, a unit translation whose length is unobserved, information
                     from the inliers' residuals), preceded by ``VERTEX_SE3:QUAT`` lines with the frames' stored
                     poses when known
    loop_edges.csv   EDGE_COLUMNS then the frames' keys, the same edges (sigmas instead of the information matrix)
    loop_edges.json  the same edges with ``R``, ``t``, the information matrix, the frames' keys, the frame they are in
                     (``camera``, or ``body`` with ``detect --edge-frame body``: ``T_body_camera``) and a note on what
                     they mean
    ground_truth_poses.txt  the sequence's ground-truth camera poses in the data set's own world, one KITTI row a
                     frame (TUM, EuRoC: layouts whose poses are ground truth; ``evaluate`` derives the loop ground
                     truth from them across the gravity axis, ``cae_lcd.evaluation.ground_truth.up_axis``)

Tables and the summary are written to a temporary file and renamed, so a crash never leaves half a file where a
good one was; what is read back is checked (numeric, finite, integer frame ids).
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from cae_lcd.core.errors import ConfigError, printable
from cae_lcd.core.files import atomic_write, write_text_atomic

from .database import LOG_SUFFIX
from .edges import LoopEdge, body_edges, body_poses, rotation_to_quaternion

__all__ = ["RunFolder", "FrameKeys", "LOOPS_COLUMNS", "CANDIDATE_COLUMNS", "EDGE_COLUMNS", "MAX_FRAME_ID",
           "read_csv_table", "key_columns"]

log = logging.getLogger(__name__)

LOOPS_COLUMNS = ("query", "match", "score", "matches", "inliers", "seq_score", "confidence")
CANDIDATE_COLUMNS = ("query", "candidate", "score", "matches", "inliers", "seq_score", "confidence", "accepted")
EDGE_COLUMNS = ("query", "match", "inliers", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "metric", "sigma_rot_rad",
                "sigma_dir_rad", "sigma_px")
EDGE_NOTE = ("relative pose of the query camera in the match camera's frame (x_match = R x_query + t), camera axes "
             "x right, y down, z forward. Unless 'metric', t is a unit direction: its length is unobserved (two "
             "images, no depth) and the information says so (1e-6 along t). Information: g2o order (translation, "
             "rotation vector in radians, as gtsam.readG2o reads it), from the inliers' Sampson residuals times "
             "retrieval/edges.py MODEL_VARIANCE; rank 5 without scale")  #: what the edge files hold, in the JSON
#: the JSON's note for edges written in the body frame (``detect --edge-frame body``)
EDGE_NOTE_BODY = ("relative pose of the query body in the match body's frame (T_body = T_BS T_camera T_BS^-1, T_BS "
                  "the camera's pose on the body: 'T_body_camera'), the information through T_BS's adjoint. Unless "
                  "'metric', t is R_BS t_camera + (I - R) t_BS with t_camera a unit direction: unobserved along "
                  "R_BS t_camera (1e-6), where any baseline's length lies. Information: g2o order (translation, "
                  "rotation vector in radians, as gtsam.readG2o reads it), from the inliers' Sampson residuals times "
                  "retrieval/edges.py MODEL_VARIANCE; rank 5 without scale")


def key_columns(a: str, b: str) -> tuple[str, ...]:
    """The frame-key columns that follow a table's numeric ones, for its two frames ``a`` and ``b``."""
    return (f"{a}_time", f"{b}_time", f"{a}_source", f"{b}_source")


@dataclass(frozen=True)
class FrameKeys:
    """What joins a frame id to the user's own data: its timestamp (seconds, the sequence's own clock) and its id in
    the source (a file name relative to the sequence, a video frame number, a bag message index on the topic)."""

    times: np.ndarray | None = None  #: (N,) seconds by frame id; None when the sequence has none
    sources: Sequence[str] = field(default=())  #: (N,) ids in the source by frame id; empty: unknown

    def time(self, i: int) -> str:
        """Frame ``i``'s timestamp as written (nanosecond digits), "" when unknown."""
        return f"{float(self.times[i]):.9f}" if self.times is not None and 0 <= i < len(self.times) else ""

    def source(self, i: int) -> str:
        """Frame ``i``'s id in the source as written: a file name's undecodable bytes (kept by Python as lone
        surrogates) as ``\\udcff`` escapes, so that the tables stay UTF-8; "" when unknown."""
        if not 0 <= i < len(self.sources):
            return ""
        return printable(str(self.sources[i]))

    def row(self, a: int, b: int) -> list[str]:
        """The key columns of a pair (``key_columns``' order)."""
        return [self.time(a), self.time(b), self.source(a), self.source(b)]
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
    loops_tum = _file("loops_tum.txt")
    edges_tum = _file("loop_edges_tum.txt")

    def check_resumable(self) -> None:
        """Refuses a folder that holds results but no keyframe database (nor its write-ahead log): files a run would
        overwrite without resuming anything (another tool's ``loops.csv``, a run whose database was removed).

        Raises:
            ConfigError: naming the files found.
        """
        if self.database.exists() or self.database.with_name(self.database.name + LOG_SUFFIX).exists():
            return
        found = [p.name for p in (self.conf, self.loops, self.candidates, self.summary, self.ground_truth_poses,
                                  self.edges_g2o, self.edges_csv, self.edges_json, self.loops_tum, self.edges_tum)
                 if p.exists()]
        if found:
            raise ConfigError(f"{self.root} holds {', '.join(found)} but no keyframes.h5 (not a run to resume): "
                              "choose another --out, or remove them")

    def write_ground_truth_poses(self, poses: np.ndarray) -> Path:
        """Writes ``(N, 3, 4)`` camera-to-world poses as a KITTI poses file (12 numbers a line); returns its path."""
        rows = np.asarray(poses, np.float64).reshape(-1, 12)
        write_text_atomic(self.ground_truth_poses, "".join(" ".join(f"{v:.9g}" for v in r) + "\n" for r in rows))
        return self.ground_truth_poses

    def write_tables(self, results: Iterable[tuple[int, np.ndarray, int]],
                     keys: FrameKeys | None = None) -> np.ndarray:
        """Writes ``loops.csv`` and ``candidates.csv`` from ``(query, candidates (k, 6), loop)`` rows (as
        ``KeyframeDatabase.results`` gives them), each row followed by its frames' keys, and ``loops_tum.txt``;
        returns the loops ``(L, 2)``.

        Every row is read before anything is written: a damaged database leaves the old tables as they were.
        """
        rows = list(results)
        keys = keys if keys is not None else FrameKeys()
        loops = []
        with atomic_write(self.loops, newline="") as f_loops, atomic_write(self.candidates, newline="") as f_c:
            wl, wc = csv.writer(f_loops), csv.writer(f_c)
            wl.writerow(LOOPS_COLUMNS + key_columns("query", "match"))
            wc.writerow(CANDIDATE_COLUMNS + key_columns("query", "candidate"))
            for q, candidates, loop in rows:
                for cid, score, matches, inliers, seq_score, confidence in candidates:
                    row = [q, int(cid), f"{score:.6f}", int(matches), int(inliers), f"{seq_score:.6f}",
                           f"{confidence:.4f}"]
                    wc.writerow(row + [int(int(cid) == loop)] + keys.row(q, int(cid)))
                    if int(cid) == loop:
                        wl.writerow(row + keys.row(q, loop))
                        loops.append((q, loop))
        loops_arr = np.array(loops, np.int64).reshape(-1, 2)
        self._write_tum(self.loops_tum, "t_query t_match", keys,
                        [(q, m, []) for q, m in loops_arr])
        return loops_arr

    def _write_tum(self, path: Path, header: str, keys: FrameKeys,
                   rows: list[tuple[int, int, list[float]]]) -> None:
        """A TUM-style text file: a ``#`` header, then ``t_a t_b values...`` a row (none without timestamps)."""
        if keys.times is None:
            write_text_atomic(path, f"# {header}\n# the sequence has no timestamps: no rows\n")
            return
        lines = [f"# {header}\n"] + [" ".join([keys.time(int(a)), keys.time(int(b)), *(f"{v:.9g}" for v in vals)])
                                     + "\n" for a, b, vals in rows]
        write_text_atomic(path, "".join(lines))

    def read_loops(self) -> np.ndarray:
        """``(L, 7)`` float64 rows of ``LOOPS_COLUMNS``."""
        return read_csv_table(self.loops, LOOPS_COLUMNS)

    def read_candidates(self) -> np.ndarray | None:
        """``(C, 8)`` float64 rows of ``CANDIDATE_COLUMNS``; None when the run has no candidates.csv."""
        return read_csv_table(self.candidates, CANDIDATE_COLUMNS) if self.candidates.is_file() else None

    def write_edges(self, edges: list[LoopEdge], poses: np.ndarray | None = None,
                    keys: FrameKeys | None = None, T_body_camera: np.ndarray | None = None) -> None:
        """Writes ``loop_edges.g2o``, ``.csv``, ``.json`` and ``loop_edges_tum.txt`` (see the module doc).

        Args:
            edges: the loops' relative poses in the camera's frame (``retrieval.edges.loop_edges``).
            poses: ``(n, 3, 4)`` camera-to-world poses by frame id (NaN where unknown), for the g2o vertices; None:
                edges only.
            keys: the frames' timestamps and ids in the source, written beside each edge.
            T_body_camera: ``(4, 4)`` the camera's pose on the body (EuRoC's ``T_BS``, camera -> body): edges and
                vertices written in the body's frame (``retrieval.edges.body_edges``, ``body_poses``), the files
                saying so (the JSON's ``frame``, ``T_body_camera`` and note); None: the camera's.
        """
        body = T_body_camera is not None
        if body:
            edges, poses = body_edges(edges, T_body_camera), body_poses(poses, T_body_camera)
        keys = keys if keys is not None else FrameKeys()
        ids = sorted({e.match for e in edges} | {e.query for e in edges})
        vertices = [] if poses is None else [i for i in ids if i < len(poses) and np.isfinite(poses[i]).all()]
        g2o = []
        for i in vertices:
            q = rotation_to_quaternion(poses[i][:, :3])
            g2o.append(f"VERTEX_SE3:QUAT {i} " + " ".join(f"{v:.9g}" for v in (*poses[i][:, 3], *q)))
        rows, items, tum = [], [], []
        for e in edges:
            info = e.information()
            upper = info[np.triu_indices(6)]
            pose = [*e.t, *e.quaternion()]
            g2o.append(f"EDGE_SE3:QUAT {e.match} {e.query} " + " ".join(f"{v:.9g}" for v in pose)
                       + " " + " ".join(f"{v:.9g}" for v in upper))
            sig = e.sigmas()
            rows.append([e.query, e.match, e.inliers, *(f"{v:.9g}" for v in pose), int(e.metric),
                         *(f"{v:.6g}" for v in (*sig, e.sigma_px)), *keys.row(e.query, e.match)])
            items.append({"query": e.query, "match": e.match, "inliers": e.inliers, "R": e.R.tolist(),
                          "t": e.t.tolist(), "metric": e.metric, "information": info.tolist(),
                          "sigma_px": None if not np.isfinite(e.sigma_px) else e.sigma_px,
                          **dict(zip(key_columns("query", "match"), keys.row(e.query, e.match)))})
            tum.append((e.query, e.match, pose))
        write_text_atomic(self.edges_g2o, "".join(line + "\n" for line in g2o))
        with atomic_write(self.edges_csv, newline="") as f:
            w = csv.writer(f)
            w.writerow(EDGE_COLUMNS + key_columns("query", "match"))
            w.writerows(rows)
        head = {"frame": "body", "T_body_camera": np.asarray(T_body_camera).tolist(), "note": EDGE_NOTE_BODY} \
            if body else {"frame": "camera", "note": EDGE_NOTE}
        write_text_atomic(self.edges_json, json.dumps({**head, "edges": items}, indent=1))
        what = "body" if body else "camera"
        self._write_tum(self.edges_tum, f"t_query t_match tx ty tz qx qy qz qw (the query {what} in the match "
                        f"{what}'s frame; t up to scale unless loop_edges.csv says metric)", keys, tum)

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
                             np.array(d["R"], np.float64).reshape(3, 3), np.array(d["t"], np.float64).reshape(3),
                             np.array(d["information"], np.float64).reshape(6, 6), bool(d.get("metric", False)),
                             float("nan") if d.get("sigma_px") is None else float(d["sigma_px"]))
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
