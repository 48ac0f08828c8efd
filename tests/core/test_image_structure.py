"""cae_lcd.core.images.check_structure (issue 29): hostile files built here (small, generated) whose decoding would cost far
more than their size says are refused in one line before any decoder runs, in a bounded time; honest files of every
kind pass; the decoders' own messages go to the log, not to stderr."""

from __future__ import annotations

import re
import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import MAX_JPEG_SCANS, check_structure, decode_image

SIDE = 4000  #: the audit's 4000 x 4000 grey image (16 Mpixel: the fleet server's limit)


@pytest.fixture(scope="module")
def progressive():
    """A 4000 x 4000 grey progressive JPEG of smooth content (~75 kB)."""
    rng = np.random.default_rng(0)
    image = cv2.resize((rng.random((100, 100)) * 40 + 100).astype(np.uint8), (SIDE, SIDE))
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_QUALITY, 30])[1].tobytes()


def repeated_scans(data: bytes, times: int) -> bytes:
    """The audit's file: the smallest scan (with the Huffman table before it) repeated ``times`` times before the end
    marker."""
    starts = [m.start() for m in re.finditer(b"\xff\xc4", data)] + [len(data) - 2]
    pieces = [data[a:b] for a, b in zip(starts, starts[1:]) if b"\xff\xda" in data[a:b]]
    return data[:-2] + min(pieces, key=len) * times + b"\xff\xd9"


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def timed_refusal(data: bytes, match: str) -> float:
    start = time.process_time()
    with pytest.raises(ImageError, match=match):
        decode_image(data, "hostile", max_pixels=16_000_000, known_header=True)
    return time.process_time() - start


class TestHostileFiles:
    def test_a_jpeg_of_1000_repeated_scans_is_refused_at_once(self, progressive):
        hostile = repeated_scans(progressive, 1000)  # decoded, 40-50 s of CPU (audit)
        assert len(hostile) < 2_000_000
        assert timed_refusal(hostile, f"more than {MAX_JPEG_SCANS} scans") < 0.5

    def test_a_jpeg_claiming_more_pixels_than_its_data_is_refused(self):
        small = cv2.imencode(".jpg", np.full((96, 320), 128, np.uint8))[1].tobytes()
        data = bytearray(small)
        sof = data.find(b"\xff\xc0")
        data[sof + 5:sof + 9] = struct.pack(">HH", SIDE, SIDE)  # the header claims 4000 x 4000
        assert timed_refusal(bytes(data), "bytes of coded data where its declared size needs") < 0.5

    def test_a_cut_jpeg_and_an_arithmetic_one_are_refused(self, progressive):
        timed_refusal(progressive[:len(progressive) // 2], "cut short")
        data = bytearray(progressive)
        sof = data.find(b"\xff\xc2")
        data[sof + 1] = 0xCA  # progressive, arithmetic coding
        timed_refusal(bytes(data), "SOF10 is not accepted")

    def test_a_png_of_100000_text_chunks_is_refused_at_once(self):
        honest = cv2.imencode(".png", np.zeros((64, 64), np.uint8))[1].tobytes()
        text = png_chunk(b"tEXt", b"k\0v") * 100_000  # decoded, 5.8 s (audit)
        hostile = honest[:33] + text + honest[33:]
        assert timed_refusal(hostile, "more than 256 chunks") < 0.5

    def test_a_png_claiming_more_pixels_than_deflate_can_hold_is_refused(self):
        data = bytearray(cv2.imencode(".png", np.zeros((64, 64), np.uint8))[1].tobytes())
        ihdr = bytes(data[12:16]) + struct.pack(">II", SIDE, SIDE) + bytes(data[24:29])
        data[12:33] = ihdr + struct.pack(">I", zlib.crc32(ihdr))
        timed_refusal(bytes(data), "bytes of pixel data where its declared size needs")


class TestHonestFiles:
    @pytest.mark.parametrize("ext, params", [(".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
                                             (".png", []), (".png", [cv2.IMWRITE_PNG_COMPRESSION, 9])])
    def test_real_and_extreme_honest_files_pass(self, sample_image, ext, params):
        for image in (sample_image(0), np.zeros((SIDE, SIDE), np.uint8)):  # a real frame, the most compressible
            data = cv2.imencode(ext, image, params)[1].tobytes()
            check_structure(data, "JPEG" if ext == ".jpg" else "PNG")
            assert decode_image(data, "honest", known_header=True).shape[:2] == image.shape[:2]

    def test_the_decoders_messages_go_to_the_log_not_stderr(self, progressive, capfd, caplog):
        """libjpeg warns on stderr of a progression it finds odd; a server's stderr is its own."""
        odd = repeated_scans(progressive, 3)  # within the scan limit, but libjpeg complains
        capfd.readouterr()
        decode_image(odd, "odd", known_header=True)
        assert capfd.readouterr().err == ""
        assert any(re.search("image decoder: .*progression", r.getMessage()) for r in caplog.records)
