"""A hostile corpus against the readers of bags, videos, TUM, EuRoC and KITTI folders, table-driven like the image
folders' (``tests/cli/test_hostile_inputs.py``), built from the bundled sample's real KITTI frames.

What every case must show: either one ``ConfigError`` naming the file (and line) before any frame is read, or a
sequence whose damaged frames are unreadable (skipped with a warning by ``detect``) while every other frame keeps
its id: frame ``i`` is the intact source's frame ``i``, in the order the frames were taken.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.sequences import open_sequence
from retrieval.sequences.rosbag import IMAGE

N = 60  #: frames in each hostile bag and video
DAMAGED = 25  #: the bag message damaged (0-based: the 26th of 60)
TOPIC = "/cam0/image_raw"


def _write_bag(path: Path, images: list[np.ndarray], stamps: np.ndarray, received: np.ndarray, ros1: bool,
               damaged: tuple[int, ...] = ()) -> None:
    """A bag of ``images`` with header ``stamps`` (s) written at ``received`` (s) times, messages ``damaged``
    garbled past their first bytes (what a cut cable or a bad sector leaves)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with (Writer1(path) if ros1 else Writer2(path, version=9)) as writer:
        conn = writer.add_connection(TOPIC, IMAGE, typestore=store)
        for n in np.argsort(received, kind="stable"):
            t, image = stamps[n], images[n]
            stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
            header = T["std_msgs/msg/Header"](**({"seq": int(n)} if ros1 else {}), stamp=stamp, frame_id="cam0")
            msg = T[IMAGE](header=header, height=image.shape[0], width=image.shape[1], encoding="mono8",
                           is_bigendian=0, step=image.shape[1], data=image.reshape(-1))
            raw = bytes(serialize(msg, IMAGE))
            if n in damaged:
                keep = 0 if ros1 else 4  # ROS 2: the CDR encapsulation header
                raw = raw[:keep] + b"\xff" * 60 + raw[keep + 60:]
            writer.write(conn, int(round(received[n] * 1e9)), raw)


def _bag(ros1: bool, order: str) -> Callable[[Path, list[np.ndarray]], Path]:
    def build(tmp: Path, images: list[np.ndarray]) -> Path:
        stamps = 1000.0 + np.arange(N) * 0.1
        received = stamps.copy()
        damaged: tuple[int, ...] = ()
        if order == "swapped":  # pairs received the wrong way round (each 0.15 s late): 0.1-0.2 s apart
            received[1::4] += 0.15
        else:
            damaged = (DAMAGED,)
        path = tmp / ("rec.bag" if ros1 else "rec")
        _write_bag(path, images[:N], stamps, received, ros1, damaged)
        return path
    return build


def _video(fourcc: str, ext: str) -> Callable[[Path, list[np.ndarray]], Path]:
    def build(tmp: Path, images: list[np.ndarray]) -> Path:
        path = tmp / f"drive{ext}"
        h, w = images[0].shape
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (w, h), isColor=False)
        assert writer.isOpened()
        for image in images[:N]:
            writer.write(image)
        writer.release()
        (tmp / f"intact{ext}").write_bytes(path.read_bytes())
        data = bytearray(path.read_bytes())
        mid = len(data) // 2
        data[mid:mid + 200_000] = bytes(200_000)  # 200 kB zeroed mid-file
        path.write_bytes(bytes(data))
        return path
    return build


def _three_frames(folder: Path, images: list[np.ndarray], line: Callable[[int], str], last: str) -> list[str]:
    """Writes ``images[0..2]`` into ``folder`` as ``k.png``; their list lines ``line(k)``, the last one replaced by
    ``last`` when given."""
    folder.mkdir(parents=True)
    lines = []
    for k in range(3):
        cv2.imwrite(str(folder / f"{k}.png"), images[k])
        lines.append(line(k))
    if last:
        lines[-1] = last
    return lines


def _tum(rgb: str = "", gt: str = "") -> Callable[[Path, list[np.ndarray]], Path]:
    """A 3-frame TUM folder; ``rgb`` replaces the last ``rgb.txt`` line, ``gt`` is appended to ``groundtruth.txt``
    (its lines 2-4 hold good poses)."""
    def build(tmp: Path, images: list[np.ndarray]) -> Path:
        root = tmp / "tum"
        lines = _three_frames(root / "rgb", images, lambda k: f"{k}.0 rgb/{k}.png", rgb)
        (root / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(lines) + "\n")
        (root / "groundtruth.txt").write_text("# t tx ty tz qx qy qz qw\n" + "".join(
            f"{k}.0 {k} 0 0 0 0 0 1\n" for k in range(3)) + gt)
        return root
    return build


def _euroc(csv: str = "", gt: str | None = None) -> Callable[[Path, list[np.ndarray]], Path]:
    """A 3-frame EuRoC folder; ``csv`` replaces the last ``data.csv`` line; ``gt`` is the ground truth's data lines
    (None: three good ones)."""
    def build(tmp: Path, images: list[np.ndarray]) -> Path:
        cam = tmp / "MH" / "mav0" / "cam0"
        lines = _three_frames(cam / "data", images, lambda k: f"{k}000000000,{k}.png", csv)
        (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "\n".join(lines) + "\n")
        truth = cam.parent / "state_groundtruth_estimate0"
        truth.mkdir()
        body = "".join(f"{k}000000000,{k},0,0,1,0,0,0\n" for k in range(3)) if gt is None else gt
        (truth / "data.csv").write_text("#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z\n" + body)
        return cam.parents[1]
    return build


def _kitti_poses(tmp: Path, images: list[np.ndarray]) -> Path:
    root = tmp / "seq"
    (root / "image_0").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(root / "image_0" / f"{k:06d}.png"), images[k])
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 2 0 0 0 0 2 0\n1 0 0 0 0 1 0 0 0 0 1 0\n")
    return root


@dataclass(frozen=True)
class Case:
    build: Callable[[Path, list[np.ndarray]], Path]
    error: str = ""  #: the ConfigError expected at open (a fragment), or "" when the sequence opens
    options: dict = field(default_factory=dict)  #: ``open_sequence`` options
    unreadable: tuple[int, ...] = ()  #: frames that must be unreadable (bags: exactly these)
    lossy: bool = False  #: a lossy video: frames compared with the intact video's, unreadable ones at least one
    warns: str = ""  #: a fragment of a warning logged at open


CASES = {
    "ros2 bag, message 25 of 60 damaged": Case(_bag(False, "damaged"), unreadable=(DAMAGED,),
                                                warns="without a readable header stamp"),
    "ros1 bag, message 25 of 60 damaged": Case(_bag(True, "damaged"), unreadable=(DAMAGED,),
                                                warns="without a readable header stamp"),
    "ros2 bag received out of order": Case(_bag(False, "swapped"), warns="ordered by the stamps"),
    "ros1 bag received out of order": Case(_bag(True, "swapped"), warns="ordered by the stamps"),
    "mjpg avi, 200 kB zeroed mid-file": Case(_video("MJPG", ".avi"), lossy=True),
    "mjpg mkv, 200 kB zeroed mid-file": Case(_video("MJPG", ".mkv"), lossy=True),
    # FFmpeg's AVI reader numbers the packets it finds: the index maps them back (frames 31-35 lost or coded
    # against a lost one, frame 30 decoded half)
    "ffv1 avi, 200 kB zeroed mid-file": Case(_video("FFV1", ".avi"), lossy=True, warns="not where the file's index"),
    "mpeg-4 avi, 200 kB zeroed mid-file": Case(_video("mp4v", ".avi"), lossy=True,
                                               warns="not where the file's index"),
    "video, --stride 2**63": Case(_video("MJPG", ".avi"), error="--stride must be an integer from 1 to",
                                  options={"stride": 9223372036854775808}),
    "euroc ground truth, header only": Case(_euroc(gt=""), warns="holds no pose"),
    "euroc ground truth, zero quaternion": Case(_euroc(gt="0,0,0,0,0,0,0,0\n"), error="data.csv, line 2: the "
                                                "quaternion (columns 5-8) has norm 0"),
    "euroc ground truth, 5 columns": Case(_euroc(gt="0,0,0,0,1\n"), error="line 2: expected at least 8 columns"),
    "tum ground truth, zero quaternion": Case(_tum(gt="3.0 0 0 0 0 0 0 0\n"), error="groundtruth.txt, line 5: the "
                                              "quaternion (columns 5-8) has norm 0"),
    "tum ground truth, quaternion of norm 2": Case(_tum(gt="3.0 0 0 0 0 0 0 2\n"), error="line 5: the quaternion"),
    "tum ground truth, NaN position": Case(_tum(gt="3.0 nan 0 0 0 0 0 1\n"), error="line 5: NaN or infinite"),
    "tum rgb.txt, path up and out": Case(_tum(rgb="2.0 ../../etc/passwd.png"),
                                         error="rgb.txt, line 4: '../../etc/passwd.png' leaves the sequence's folder"),
    "tum rgb.txt, absolute path": Case(_tum(rgb="2.0 /etc/x.png"), error="line 4: '/etc/x.png' leaves"),
    "euroc data.csv, path up and out": Case(_euroc(csv="2000000000,../../../x.png"), error="data.csv, line 4: "
                                            "'../../../x.png' leaves the sequence's folder"),
    "kitti poses, not a rotation": Case(_kitti_poses, error="poses.txt, line 2: the pose's 3x3 block is not a "
                                        "rotation"),
}


def _same(a: np.ndarray, b: np.ndarray, lossy: bool) -> bool:
    return a.shape == b.shape and (np.abs(a.astype(int) - b.astype(int)).mean() < 2 if lossy else
                                   np.array_equal(a, b))


@pytest.mark.parametrize("name", list(CASES))
def test_reader_case(name, tmp_path, sample_images, caplog):
    case = CASES[name]
    path = case.build(tmp_path, sample_images)
    caplog.set_level(logging.WARNING)
    if case.error:
        with pytest.raises(ConfigError) as err:
            open_sequence(path, **case.options)
        assert case.error in str(err.value) and "\n" not in str(err.value), str(err.value)
        return
    seq = open_sequence(path, **case.options)
    if case.warns:
        assert any(case.warns in r.getMessage() for r in caplog.records), caplog.text
    if seq.kind in ("euroc", "tum"):
        assert seq.poses is None and len(seq) == 3
        return
    if case.lossy:  # the intact video's frames, as decoded: MJPG is lossy
        intact = open_sequence(path.with_name("intact" + path.suffix))
        truth = [intact.read_frame(i)[0] for i in range(len(intact))]
    else:
        truth = sample_images[:N]
    assert len(seq) == N
    frames = [seq.read_frame(i)[0] for i in range(N)]
    bad = [i for i, f in enumerate(frames) if not isinstance(f, np.ndarray)]
    if case.lossy:
        assert bad and bad[-1] < N - 10, bad  # the damaged stretch is reported, the frames after it are read
    else:
        assert bad == list(case.unreadable)
    good = [i for i in range(N) if i not in bad]
    shifted = [i for i in good if any(_same(frames[i], truth[j], case.lossy) for j in range(N) if j != i)]
    assert not shifted, f"frames {shifted} hold the source's frames of other ids"
    own = [i for i in good if _same(frames[i], truth[i], case.lossy)]
    assert len(own) >= len(good) - case.lossy, "only the frame the damage begins in may be decoded half"
    if seq.kind == "rosbag":
        np.testing.assert_allclose(seq.timestamps, 1000.0 + np.arange(N) * 0.1, atol=1e-6)


def test_a_damaged_avi_reads_the_same_in_any_order(tmp_path, sample_images):
    """A damaged FFV1 AVI is read forward only (FFmpeg's seek lands by the index, then counts packets again):
    frames asked for out of order or with a stride are the frames read in order. The frame the damage begins in,
    decoded half, is left out of the comparison: FFmpeg's concealment fills it from whatever it decoded last."""
    path = CASES["ffv1 avi, 200 kB zeroed mid-file"].build(tmp_path, sample_images)
    in_order = [open_sequence(path).read_frame(i)[0] for i in range(N)]
    half = {i for i, f in enumerate(in_order) if isinstance(f, np.ndarray) and not np.array_equal(f, sample_images[i])}
    assert len(half) <= 1, half
    seq, strided = open_sequence(path), open_sequence(path, stride=7)
    for i in [*np.random.default_rng(0).permutation(N)]:
        got, want = seq.read_frame(int(i))[0], in_order[i]
        assert isinstance(got, np.ndarray) == isinstance(want, np.ndarray)
        assert not isinstance(want, np.ndarray) or i in half or np.array_equal(got, want), i
    for i in range(len(strided)):
        got, want = strided.read_frame(i)[0], in_order[7 * i]
        assert not isinstance(want, np.ndarray) or 7 * i in half or np.array_equal(got, want), i


@pytest.mark.parametrize("name, args", [("video, --stride 2**63", ["--stride", "9223372036854775808"]),
                                        ("tum ground truth, zero quaternion", []),
                                        ("tum rgb.txt, path up and out", [])])
def test_cli_refuses_before_writing(name, args, tmp_path, sample_images, capsys):
    """Through ``cae-lcd detect``: exit 2, one ``error:`` line naming the file or option, no run folder."""
    from cae_lcd.cli.main import main

    path = CASES[name].build(tmp_path, sample_images)
    code = main(["detect", str(path), "--out", str(tmp_path / "run"), "--no-progress", *args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert CASES[name].error in lines[0]
    assert not (tmp_path / "run").exists()


def test_a_reader_warning_is_said_once_a_run(tmp_path, sample_images, caplog):
    """``detect`` opened the sequence twice (to check its ground truth, then to run): every reader warning was
    printed twice. A TUM ground truth that ends before the last frame."""
    from cae_lcd.cli.main import main

    root = _tum()(tmp_path, sample_images)
    (root / "groundtruth.txt").write_text("0.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    caplog.set_level(logging.WARNING)
    assert main(["detect", str(root), "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    said = [r.getMessage() for r in caplog.records if "outside the ground truth's time range" in r.getMessage()]
    assert len(said) == 1, said
