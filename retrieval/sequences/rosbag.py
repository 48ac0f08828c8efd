"""ROS 1 (``.bag``) and ROS 2 bags (a folder with ``metadata.yaml``, or one ``.db3`` / ``.mcap`` file), read with
``rosbags`` (pure Python, no ROS install; the ``[ros]`` extra).

One image topic (``sensor_msgs/Image``: mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8/16;
``sensor_msgs/CompressedImage``: any image file format) is the sequence: ``--topic`` names it, or the bag's only
image topic is taken. Frames are in the order of the messages' header stamps, the time each image was taken (a
bag's messages are stored in the order they were received, which a network can swap), and timestamps are those
stamps (the bag's receive times where they are all unset). A damaged message is one unreadable frame: its stamp,
when it cannot be read, is its receive time shifted as the others' are, and the frame is skipped with a warning
when it is read. Intrinsics come from a ``CameraInfo`` topic when present (the one beside the image topic,
else the only one). Frames are read lazily, one message at a time, by index: a bag is never loaded whole.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import check_image, decode_image, fingerprint
from verify.camera import CameraModel, distortion_model

from .base import Sequence

__all__ = ["BAG_SUFFIXES", "BagFrames", "frame_order", "is_bag", "open_bag", "image_from_message", "write_image_bag"]

log = logging.getLogger(__name__)

BAG_SUFFIXES = (".bag", ".db3", ".mcap")  #: a ROS 1 bag, or one ROS 2 storage file
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

#: ``sensor_msgs/Image`` encoding -> (pixel dtype, channels, OpenCV conversion to BGR or grey, None: as stored).
#: ROS names a Bayer pattern by its first row, OpenCV by its second: ROS rggb is OpenCV's BayerBG.
ENCODINGS: dict[str, tuple[type, int, int | None]] = {
    "mono8": (np.uint8, 1, None), "8uc1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None), "16uc1": (np.uint16, 1, None),
    "bgr8": (np.uint8, 3, None), "8uc3": (np.uint8, 3, None), "rgb8": (np.uint8, 3, cv2.COLOR_RGB2BGR),
    "bgra8": (np.uint8, 4, cv2.COLOR_BGRA2BGR), "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2BGR),
    "bgr16": (np.uint16, 3, None), "rgb16": (np.uint16, 3, cv2.COLOR_RGB2BGR),
    **{f"bayer_{p}{bits}": (np.uint8 if bits == 8 else np.uint16, 1, code)
       for p, code in (("rggb", cv2.COLOR_BayerBG2BGR), ("bggr", cv2.COLOR_BayerRG2BGR),
                       ("gbrg", cv2.COLOR_BayerGR2BGR), ("grbg", cv2.COLOR_BayerGB2BGR)) for bits in (8, 16)},
}


def is_bag(root: Path) -> bool:
    """A ``.bag``, ``.db3`` or ``.mcap`` file, or a ROS 2 bag folder (``metadata.yaml`` inside)."""
    return (root.is_file() and root.suffix.lower() in BAG_SUFFIXES) or (root / "metadata.yaml").is_file()


def _rosbags() -> Any:
    try:
        from rosbags import highlevel, typesys
    except ImportError:
        raise ConfigError("reading bags needs the 'rosbags' package: pip install 'cae-loop-closure[ros]'") from None
    return highlevel, typesys


def _open_reader(path: Path) -> Any:
    highlevel, typesys = _rosbags()
    reader = highlevel.AnyReader([path], default_typestore=typesys.get_typestore(typesys.Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags' errors (AnyReaderError, ReaderError, OSError) alike
        raise ConfigError(f"cannot read bag {path}: {' '.join(str(err).split())[:200]}") from None
    return reader


def image_from_message(msg: Any, msgtype: str, name: str) -> tuple[np.ndarray, bytes]:
    """A ``sensor_msgs/Image`` or ``CompressedImage`` -> ``(image (H, W) or (H, W, 3) BGR, its payload bytes)``.

    Raises:
        ImageError: an unknown encoding, a payload of the wrong size, or an image that cannot be decoded.
    """
    data = np.asarray(msg.data, np.uint8).tobytes()
    if msgtype == COMPRESSED:
        return decode_image(data, name), data
    enc = str(msg.encoding).lower()
    if enc not in ENCODINGS:
        raise ImageError(f"{name}: unsupported encoding {msg.encoding!r} (known: {', '.join(ENCODINGS)})")
    dtype, ch, code = ENCODINGS[enc]
    h, w, step, size = int(msg.height), int(msg.width), int(msg.step), np.dtype(dtype).itemsize
    if h < 1 or w < 1 or step < w * ch * size or len(data) < h * step:
        raise ImageError(f"{name}: {len(data)} bytes do not hold {w}x{h} {enc} pixels with step {step}")
    rows = np.frombuffer(data, np.uint8, h * step).reshape(h, step)[:, :w * ch * size]
    image = rows.copy().view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")).astype(dtype)
    image = image.reshape(h, w, ch) if ch > 1 else image.reshape(h, w)
    return check_image(image if code is None else cv2.cvtColor(image, code), name), data


def _image_topic(reader: Any, path: Path, topic: str | None) -> Any:
    """The connection of the image topic to read."""
    images = [c for c in reader.connections if c.msgtype in (IMAGE, COMPRESSED)]
    listed = ", ".join(sorted({c.topic for c in images})) or "none"
    if topic is not None:
        found = [c for c in images if c.topic == topic]
        if not found:
            raise ConfigError(f"{path} has no image topic {topic}; image topics: {listed}")
        return found[0]
    if len({c.topic for c in images}) != 1:
        raise ConfigError(f"{path}: choose the image topic with --topic; image topics: {listed}")
    return images[0]


def _camera_info(reader: Any, image_topic: str) -> CameraModel | None:
    """The camera of the ``CameraInfo`` topic beside ``image_topic`` (or the bag's only one): ``K``, and its ``D``
    with ``distortion_model`` (``verify.camera``); None when none."""
    infos = [c for c in reader.connections if c.msgtype == CAMERA_INFO]
    beside = [c for c in infos if c.topic.rsplit("/", 1)[0] == image_topic.rsplit("/", 1)[0]]
    conns = beside or (infos if len(infos) == 1 else [])
    if not conns:  # (no connections would mean every message to rosbags)
        return None
    for conn, _, raw in reader.messages(connections=conns[:1]):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception:  # noqa: BLE001 - a damaged message, as for images
            log.warning("%s: the first CameraInfo message cannot be read; not used", conn.topic)
            return None
        K = np.asarray(getattr(msg, "k", getattr(msg, "K", ())), np.float64).reshape(-1)
        K = K.reshape(3, 3) if K.size == 9 else np.zeros((3, 3))
        if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0):
            log.warning("%s: CameraInfo K is not a camera matrix (finite, fx and fy > 0); not used", conn.topic)
            return None
        D = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), np.float64).reshape(-1)
        try:
            model = distortion_model(msg.distortion_model or "plumb_bob", D.tolist(), f"{conn.topic} CameraInfo")
            return CameraModel(K, *model, source=f"{conn.topic} CameraInfo")
        except ConfigError as err:
            log.warning("%s; the distortion is not used", err)
            return CameraModel(K, source=f"{conn.topic} CameraInfo")
    return None


class BagFrames:
    """The messages of one image topic, read by index (each thread reads through its own open bag)."""

    def __init__(self, path: Path, topic: str, msgtype: str, stamps_ns: np.ndarray,
                 same: np.ndarray | None = None, index: np.ndarray | None = None) -> None:
        self.path, self.topic, self.msgtype = path, topic, msgtype
        self.stamps_ns = stamps_ns  #: (N,) int64 the bag's receive times, the index used to find a message
        #: (N,) how many earlier-received messages of the topic share frame i's receive time (None: in receive order)
        self.same = same
        #: (N,) frame i's message index on the topic in receive order (None: frames in receive order)
        self.index = index
        self._local = threading.local()

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def name(self, i: int) -> str:
        return f"{self.topic}@{int(self.stamps_ns[i])}"

    def source_id(self, i: int) -> str:
        """The message's index on the topic in the order the bag received them (0 = its first message)."""
        return str(i if self.index is None else int(self.index[i]))

    def _message(self, i: int) -> Any:
        reader = getattr(self._local, "reader", None)
        if reader is None:
            reader = self._local.reader = _open_reader(self.path)
        conns = [c for c in reader.connections if c.topic == self.topic and c.msgtype == self.msgtype]
        if not conns:
            raise ImageError(f"{self.name(i)}: topic gone from {self.path}")
        t = int(self.stamps_ns[i])
        same = int(self.same[i]) if self.same is not None else int(np.sum(self.stamps_ns[:i] == t))
        for k, (conn, _, raw) in enumerate(reader.messages(connections=conns, start=t, stop=t + 1)):
            if k == same:
                return reader.deserialize(raw, conn.msgtype)
        raise ImageError(f"{self.name(i)}: message not found in {self.path}")

    def read(self, i: int) -> tuple[np.ndarray | ImageError, str]:
        try:
            msg = self._message(i)
        except ImageError as err:
            return err, ""
        except Exception as err:  # noqa: BLE001 - a damaged message: skipped and counted like a bad file
            return ImageError(f"{self.name(i)}: cannot deserialize: {' '.join(str(err).split())[:160]}"), ""
        data = np.asarray(msg.data, np.uint8).tobytes()
        try:
            image, data = image_from_message(msg, self.msgtype, self.name(i))
        except ImageError as err:
            return err, fingerprint(data)
        return image, fingerprint(data)


def _stamps(reader: Any, conn: Any) -> tuple[np.ndarray, np.ndarray]:
    """The topic's receive times ``(N,)`` int64 ns and header stamps ``(N,)`` seconds (NaN where a damaged message's
    header cannot be read), one message at a time, in receive order."""
    received, stamps = [], []
    for c, t, raw in reader.messages(connections=[conn]):
        try:
            stamp = reader.deserialize(raw, c.msgtype).header.stamp
            value = stamp.sec + stamp.nanosec * 1e-9
        except Exception:  # noqa: BLE001 - a damaged message: its frame is reported when it is read
            value = np.nan
        received.append(t)
        stamps.append(value)
    return np.array(received, np.int64), np.array(stamps, np.float64)


def frame_order(received: np.ndarray, stamps: np.ndarray, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """The frames' order (indices into receive order) ``(N,)`` and their timestamps ``(N,)`` seconds, from receive
    times ``(N,)`` ns and header stamps ``(N,)`` s (NaN: unreadable, 0: unset).

    Frames go in header-stamp order (receive order among equal stamps); a message whose stamp is unreadable or
    unset, among others that are set, takes its receive time shifted by the median of the others' stamp minus
    receive time; when no stamp is set the receive times are the timestamps (from 0).
    """
    rx = received * 1e-9
    known = np.isfinite(stamps) & (stamps != 0)
    if not known.any():
        log.warning("%s: header stamps unset; using the bag's receive times", topic)
        return np.arange(len(received)), rx - rx[0] if len(rx) else rx
    if not known.all():
        log.warning("%s: %d message(s) without a readable header stamp; placed by their receive time", topic,
                    int(np.sum(~known)))
    times = np.where(known, stamps, rx + float(np.median(stamps[known] - rx[known])))
    order = np.argsort(times, kind="stable")
    if np.any(order != np.arange(len(order))):
        log.warning("%s: messages received out of the order of their header stamps; frames ordered by the stamps",
                    topic)
    return order, times[order]


def open_bag(root: Path, topic: str | None = None) -> Sequence:
    """Opens one image topic of a ROS 1 or ROS 2 bag as a sequence, frames in header-stamp order.

    Raises:
        ConfigError: not a readable bag, no such image topic (or several and none chosen), or no message on it.
    """
    reader = _open_reader(root)
    try:
        conn = _image_topic(reader, root, topic)
        received, stamps = _stamps(reader, conn)
        camera = _camera_info(reader, conn.topic)
    finally:
        reader.close()
    if not len(received):
        raise ConfigError(f"{root}: no message on {conn.topic}")
    order, times = frame_order(received, stamps, conn.topic)
    same = np.zeros(len(received), np.int64)  # how many earlier messages share each one's receive time
    seen: dict[int, int] = {}
    for k, t in enumerate(received.tolist()):
        same[k] = seen.get(t, 0)
        seen[t] = int(same[k]) + 1
    if camera is None:
        log.info("%s: no CameraInfo; the fundamental matrix is used", root)
    return Sequence(root, [], timestamps=times, K=None if camera is None else camera.K, kind="rosbag",
                    camera=camera, stream=BagFrames(root, conn.topic, conn.msgtype, received[order], same[order],
                                                    order))


def _camera_info_message(typestore: Any, header: Any, K: np.ndarray, h: int, w: int,
                         distortion: tuple[str, np.ndarray] = ("plumb_bob", np.zeros(5))) -> Any:
    cls = typestore.types[CAMERA_INFO]
    upper = "K" in cls.__dataclass_fields__  # ROS 1 names the matrices D, K, R, P
    mats = {"d": np.asarray(distortion[1], np.float64), "k": K.reshape(-1), "r": np.eye(3).reshape(-1),
            "p": np.hstack([K, np.zeros((3, 1))]).reshape(-1)}
    roi = typestore.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False)
    return cls(header=header, height=h, width=w, distortion_model=distortion[0], binning_x=0, binning_y=0, roi=roi,
               **{(k.upper() if upper else k): v.astype(np.float64) for k, v in mats.items()})


def write_image_bag(path: Path, images: list[np.ndarray], times: np.ndarray, topic: str = "/cam0/image_raw",
                    K: np.ndarray | None = None, ros1: bool = False, encoding: str = "mono8",
                    distortion: tuple[str, np.ndarray] = ("plumb_bob", np.zeros(5))) -> None:
    """Writes ``images`` (grey ``(H, W)`` uint8, or BGR ``(H, W, 3)`` with ``encoding="bgr8"``) at ``times`` ``(N,)``
    seconds as ``sensor_msgs/Image`` on ``topic``, with a ``CameraInfo`` beside it when ``K`` is given (its
    ``distortion_model`` and ``D``: ``distortion``): a ROS 2 bag
    folder (sqlite3 storage, or mcap when ``path`` ends in ``.mcap``) or a ROS 1 ``.bag`` with ``ros1``.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    writer = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=(
        StoragePlugin.MCAP if path.suffix == ".mcap" else StoragePlugin.SQLITE3))
    with writer:
        cam = writer.add_connection(topic, IMAGE, typestore=store)
        info = None if K is None else writer.add_connection(topic.rsplit("/", 1)[0] + "/camera_info", CAMERA_INFO,
                                                            typestore=store)
        for n, (image, t) in enumerate(zip(images, times)):
            stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
            header = T["std_msgs/msg/Header"](**({"seq": n} if ros1 else {}), stamp=stamp, frame_id="cam0")
            h, w = image.shape[:2]
            msg = T[IMAGE](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                           step=image.strides[0], data=np.ascontiguousarray(image).reshape(-1).view(np.uint8))
            ns = int(round(t * 1e9))
            writer.write(cam, ns, serialize(msg, IMAGE))
            if info is not None:
                writer.write(info, ns, serialize(_camera_info_message(store, header, K, h, w, distortion),
                                                 CAMERA_INFO))
