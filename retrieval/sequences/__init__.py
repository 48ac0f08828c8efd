"""Sequence readers, one module a layout, chosen automatically by ``open_sequence`` (the one place that knows
layouts): a ROS 1 / ROS 2 bag (``rosbag``), a video file (``video``), a TUM RGB-D folder (``tum``), a EuRoC / ASL
folder (``euroc``), a KITTI odometry sequence or a plain folder of images (``kitti``).

A ``Sequence`` gives its frames in order (``read_frame(i)``, lazily), and when known timestamps ``(N,)``, poses
``(N, 3, 4)`` camera-to-world, intrinsics ``K (3, 3)`` and its ground truth: a loop pairs file (KITTI's
``loops.txt``), or poses that are ground truth (TUM, EuRoC: ``poses_are_truth``), from which the loops are derived
with a distance and a gap (``cae_lcd.evaluation.ground_truth``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.images import image_entries

from .base import FrameStream, Sequence, read_numbers, read_stamped_names
from .euroc import is_euroc, open_euroc
from .kitti import CAMERAS, kitti_metadata_file, open_folder, read_kitti_calib, read_kitti_poses, read_times
from .rosbag import is_bag, open_bag
from .tum import is_tum, open_tum
from .video import MAX_STRIDE, is_video, open_video

__all__ = ["Sequence", "FrameStream", "Layout", "LAYOUTS", "open_sequence", "find_sequences", "read_kitti_calib", "read_kitti_poses",
           "read_numbers", "read_stamped_names", "read_times", "kitti_metadata_file", "CAMERAS", "OPTIONS"]

log = logging.getLogger(__name__)

#: what each option of ``open_sequence`` is, for the message when a layout does not take it
OPTIONS = {"camera": "--camera (a KITTI camera folder)", "topic": "--topic (a bag's image topic)",
           "stride": "--stride (every n-th frame of a video)"}


@dataclass(frozen=True)
class Layout:
    name: str
    matches: Callable[[Path], bool]  #: whether a path is of this layout (looked at in ``LAYOUTS`` order)
    open: Callable[..., Sequence]  #: ``open(path, **options)``
    options: tuple[str, ...] = ()  #: the ``open_sequence`` options it takes (``OPTIONS``)


#: the layouts, in the order they are tried: the first that matches opens the path
LAYOUTS = (
    Layout("rosbag", is_bag, open_bag, ("topic",)),
    Layout("video", is_video, open_video, ("stride",)),
    Layout("tum", is_tum, open_tum),
    Layout("euroc", is_euroc, open_euroc),
    Layout("folder", Path.is_dir, open_folder, ("camera",)),  # KITTI or a plain folder of images: last
)


def open_sequence(path: str | Path, camera: str | None = None, topic: str | None = None,
                  stride: int = 1) -> Sequence:
    """Opens a sequence of any layout in ``LAYOUTS``.

    Args:
        path: a sequence folder (KITTI, TUM, EuRoC, images), a bag (file or ROS 2 folder) or a video file.
        camera: KITTI camera folder (``"image_0"``, ``"image_2"``); None picks the first present.
        topic: a bag's image topic; None takes the bag's only one.
        stride: a video's frames taken: every ``stride``-th (>= 1).

    Raises:
        ConfigError: a missing path, an unknown layout, an option the layout does not take, no frames, or
            metadata that cannot be parsed.
    """
    root = Path(path)
    if not root.exists():
        raise ConfigError(f"sequence not found: {root}")
    if isinstance(stride, bool) or not isinstance(stride, int) or not 1 <= stride <= MAX_STRIDE:
        raise ConfigError(f"--stride must be an integer from 1 to {MAX_STRIDE}; got {stride!r}")
    layout = next((lay for lay in LAYOUTS if lay.matches(root)), None)
    if layout is None:
        raise ConfigError(f"{root} is not a sequence: pass a folder of images (KITTI, TUM, EuRoC), a bag "
                          f"(.bag, .db3, .mcap or a ROS 2 bag folder) or a video file")
    given: dict[str, Any] = {k: v for k, v in (("camera", camera), ("topic", topic), ("stride", stride))
                             if v is not None and not (k == "stride" and v == 1)}
    refused = [OPTIONS[k] for k in given if k not in layout.options]
    if refused:
        raise ConfigError(f"{root} is a {layout.name} sequence: {', '.join(refused)} does not apply to it")
    return layout.open(root, **given)


def _is_sequence(path: Path) -> bool:
    """Whether ``path`` is one sequence: a bag, a video, TUM, EuRoC, KITTI (a camera folder) or a folder holding
    images itself."""
    if any(lay.matches(path) for lay in LAYOUTS[:-1]):
        return True
    return path.is_dir() and (any((path / c).is_dir() for c in CAMERAS) or bool(image_entries(path)))


def find_sequences(root: str | Path) -> list[Path] | None:
    """The sequences a collection holds, in name order; None when ``root`` is one sequence itself.

    A collection is a folder that is no sequence but whose entries are (``kitti/sequences/`` holding ``00``,
    ``07``, ...), or a ``.txt`` list file of sequence paths, one a line (``#`` comments; relative to the file).

    Raises:
        ConfigError: a list naming a missing path, or a folder that holds no sequence.
    """
    root = Path(root)
    if root.is_file() and root.suffix.lower() == ".txt":
        try:
            lines = root.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"cannot read sequence list {root}: {getattr(err, 'strerror', None) or err}") from None
        paths = [root.parent / ln.split("#")[0].strip() for ln in lines if ln.split("#")[0].strip()]
        missing = [str(p) for p in paths if not p.exists()]
        if missing or not paths:
            raise ConfigError(f"{root}: " + (f"no such sequence {missing[0]}" if missing else "lists no sequence"))
        return paths
    if not root.is_dir() or _is_sequence(root):
        return None
    entries = sorted(p for p in root.iterdir() if not p.name.startswith("."))
    found = [p for p in entries if _is_sequence(p)]
    if not found:
        raise ConfigError(f"no images found in {root}, and no sequence inside it")
    empty = [p.name for p in entries if p.is_dir() and p not in found]
    if empty:
        log.warning("%s: %d folder(s) hold no sequence and are left out: %s", root, len(empty),
                    ", ".join(empty[:10]) + (", ..." if len(empty) > 10 else ""))
    return found
