"""Shared fixtures: paths to real images (the bundled sample, ../shared KITTI) and session-cached heavy work.

Real images only: the bundled sample ``retrieval/sample`` (100 KITTI frames, 620x188, with calib, times, poses and
ground-truth loops) and ``../shared/datasets/kitti``. Heavy work (loading the encoder, SIFT on a few frames) is done
once per session.
"""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).parents[1]
SHARED = Path(__file__).parents[1].parent / "shared"
SAMPLE_DIR = REPO / "retrieval" / "sample"
KITTI_SEQUENCES = SHARED / "datasets" / "kitti" / "sequences"
NORDLAND = SHARED / "datasets" / "nordland"
# A Nordland station where the train waits in both seasons: summer frames 206-241 and winter 705-745 are one stop
# each (the winter train waits 3 frames longer); NORDLAND_FRAMES holds them and the frames around them.
NORDLAND_FRAMES = (*range(150, 260), *range(680, 760))

# Sample frames 55 and 5 are a true revisit (retrieval/sample/loops.txt holds "55 5"); 55 and 30 are far apart.
TRUE_PAIR = (55, 5)
FAR_PAIR = (55, 30)

# Detector overrides where detection quality is judged on the bundled sample: the decision fixed for the run
# (``calibration.online: false``: ``detect`` calibrates on a look-ahead pass, the API with a store runs the fixed
# policy, min_inliers 50): the sample's revisit starts at frame 50, before the online warm-up of the default window
# (2 x 50 frames) ends. The online default (``detect`` and a store calibrating themselves) is tested with a shorter
# window in tests/retrieval/test_online.py and tests/cli/test_detect.py.
DETECT_CONF: dict = {"calibration": {"online": False}}


def sample_frame_path(i: int) -> Path:
    return SAMPLE_DIR / "image_0" / f"{i:06d}.jpg"


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    """The bundled sample sequence folder (KITTI layout)."""
    assert (SAMPLE_DIR / "image_0").is_dir(), "bundled sample missing from retrieval/sample"
    return SAMPLE_DIR


@pytest.fixture(scope="session")
def sample_frames(sample_dir):
    """Sorted paths of the 100 sample frames."""
    frames = sorted((sample_dir / "image_0").glob("*.jpg"))
    assert len(frames) == 100
    return frames


@pytest.fixture(scope="session")
def sample_image():
    """``sample_image(i)`` -> grey uint8 ``(188, 620)`` frame ``i`` of the sample (read once, cached)."""
    from cae_lcd.core.images import read_image

    cache: dict[int, np.ndarray] = {}

    def get(i: int) -> np.ndarray:
        if i not in cache:
            cache[i] = read_image(sample_frame_path(i))
        return cache[i].copy()

    return get


@pytest.fixture(scope="session")
def sample_K(sample_dir):
    from retrieval.sequences import read_kitti_calib

    return read_kitti_calib(sample_dir / "calib.txt")


@pytest.fixture(scope="session")
def sample_poses(sample_dir):
    """``(100, 3, 4)`` ground-truth poses of the bundled sample's frames."""
    from retrieval.sequences import read_kitti_poses

    return read_kitti_poses(sample_dir / "poses.txt")


@pytest.fixture(scope="session")
def sample_seq(sample_dir):
    from retrieval.sequences import open_sequence

    return open_sequence(sample_dir)


@pytest.fixture(scope="session")
def kitti_sequences() -> Path:
    """``../shared/datasets/kitti/sequences`` (skips when the shared data set is absent)."""
    if not KITTI_SEQUENCES.is_dir():
        pytest.skip(f"shared KITTI data not found at {KITTI_SEQUENCES} (../shared is absent)")
    return KITTI_SEQUENCES


@pytest.fixture(scope="session")
def kitti_image(kitti_sequences):
    """``kitti_image(seq, i)`` -> frame ``i`` of ``../shared/datasets/kitti/sequences/<seq>`` (full resolution)."""
    from cae_lcd.core.images import read_image

    def get(seq: str, i: int) -> np.ndarray:
        path = kitti_sequences / seq / "image_0" / f"{i:06d}.png"
        if not path.is_file():
            pytest.skip(f"{path} not found")
        return read_image(path)

    return get


@pytest.fixture(scope="session")
def encoder():
    """The shipped encoder on the CPU (loaded once)."""
    import cae

    return cae.load_encoder(device="cpu")


@pytest.fixture(scope="session")
def nordland_codes(encoder):
    """``{frame_id: raw (4096,) code}`` of the real Nordland frames ``NORDLAND_FRAMES`` (64x32; skips when the shared
    data set is absent), encoded once per session."""
    from cae_lcd.core.images import read_image
    from retrieval.descriptors import create_descriptor

    if not (NORDLAND / "images").is_dir():
        pytest.skip(f"shared Nordland data not found at {NORDLAND} (../shared is absent)")
    descriptor = create_descriptor({"name": "cae"}, encoder=encoder)
    codes = descriptor.encode_batch([read_image(NORDLAND / "images" / f"{i:06d}.png") for i in NORDLAND_FRAMES])
    return dict(zip(NORDLAND_FRAMES, codes))


@pytest.fixture(scope="session")
def sift_features(sample_image):
    """``sift_features(i)`` -> default SIFT ``Features`` of sample frame ``i`` (computed once per frame)."""
    from verify.features import SIFT

    sift = SIFT()
    cache = {}

    def get(i: int):
        if i not in cache:
            cache[i] = sift.extract(sample_image(i))
        return cache[i]

    return get


def _copy_sample_frames(indices, dst: Path, transform=None, ext: str = ".jpg") -> list[Path]:
    """Copies sample frames ``indices`` into ``dst`` as ``000000.ext, 000001.ext, ...`` (optionally transformed
    and re-encoded with OpenCV)."""
    import cv2

    from cae_lcd.core.images import read_image

    dst.mkdir(parents=True, exist_ok=True)
    out = []
    for n, i in enumerate(indices):
        path = dst / f"{n:06d}{ext}"
        if transform is None and ext == ".jpg":
            shutil.copyfile(sample_frame_path(i), path)
        else:
            img = read_image(sample_frame_path(i))
            if transform is not None:
                img = transform(img)
            assert cv2.imwrite(str(path), img)
        out.append(path)
    return out


@pytest.fixture(scope="session")
def copy_sample_frames():
    """``copy_sample_frames(indices, dst, transform=None, ext=".jpg")`` -> paths of the copies, renumbered from 0."""
    return _copy_sample_frames


@pytest.fixture(scope="session")
def detect_conf() -> dict:
    """Detector overrides used where detection quality is judged (``DETECT_CONF``: the defaults)."""
    return copy.deepcopy(DETECT_CONF)


def detect_args(detect_conf: dict, folder: Path) -> list[str]:
    """``--config FILE`` for non-empty detector overrides (written into ``folder``), else nothing."""
    if not detect_conf:
        return []
    path = folder / "detect.yaml"
    path.write_text(yaml.safe_dump(detect_conf))
    return ["--config", str(path)]


@pytest.fixture(scope="session")
def detect_config_args(tmp_path_factory, detect_conf) -> list[str]:
    """The ``cae-lcd detect`` arguments that select ``DETECT_CONF`` (none with the defaults)."""
    return detect_args(detect_conf, tmp_path_factory.mktemp("config"))


@pytest.fixture(scope="session")
def cli_sample_run(tmp_path_factory, detect_config_args):
    """``cae-lcd detect --out OUT`` on the bundled sample (no PATH), in-process, one uninterrupted run.

    Shared by the detector and CLI tests. Returns ``(exit_code, out_dir)``.
    """
    from cae_lcd.cli.main import main

    out = tmp_path_factory.mktemp("cli_sample") / "run"
    code = main(["detect", "--out", str(out), *detect_config_args, "--no-progress"])
    return code, out


@pytest.fixture(scope="session")
def local_postgres():
    """A PostgreSQL server of this session (``cae_lcd.fleet.pg_local.LocalPostgres``), stopped at the end; skips with the
    reason where PostgreSQL is not installed."""
    from cae_lcd.fleet.pg_local import LocalPostgres, postgres_available

    why = postgres_available()
    if why:
        pytest.skip(why)
    with LocalPostgres() as pg:
        yield pg
