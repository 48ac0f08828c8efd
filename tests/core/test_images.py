"""``cae_lcd.core.images``: listing and reading image files safely and converting every dtype and layout a camera gives."""

import os

import cv2
import numpy as np
import pytest

from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import (MAX_IMAGE_PIXELS, check_image, decode_image, fingerprint, image_entries, read_image,
                         to_gray_u8, to_uint8)


@pytest.fixture(scope="module")
def grey(sample_image):
    return sample_image(10)  # (188, 620) uint8


class TestToUint8:
    def test_bit_depths(self, grey):
        np.testing.assert_array_equal(to_uint8(grey.astype(np.uint16) * 257), grey)
        ten = to_uint8(grey.astype(np.uint16) * 4)  # 10-bit (max 1020)
        assert np.abs(ten.astype(int) - grey).max() <= 1
        np.testing.assert_array_equal(to_uint8(grey.astype(np.float32) / 255.0), grey)


class TestToGrayU8:
    def test_bgr_and_16bit(self, grey):
        np.testing.assert_array_equal(to_gray_u8(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)), grey)
        np.testing.assert_array_equal(to_gray_u8(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)), grey)
        np.testing.assert_array_equal(to_gray_u8(grey.astype(np.uint16) * 257), grey)
        assert to_gray_u8(grey[:, :, None]).shape == grey.shape


class TestReadImage:
    def test_reads_sample_unchanged(self, sample_dir):
        img = read_image(sample_dir / "image_0" / "000000.jpg")
        assert img.shape == (188, 620) and img.dtype == np.uint8

    def test_reads_16bit_png(self, tmp_path, grey):
        img16 = grey.astype(np.uint16) * 257
        cv2.imwrite(str(tmp_path / "x16.png"), img16)
        back = read_image(tmp_path / "x16.png")
        assert back.dtype == np.uint16
        np.testing.assert_array_equal(back, img16)

    def test_corrupt_file(self, tmp_path):
        bad = tmp_path / "x.png"
        bad.write_bytes(b"\x89PNG this is not really an image \x00\x01\x02" * 10)
        with pytest.raises(ImageError, match="x.png") as err:
            read_image(bad)
        assert "corrupt" in str(err.value) or "decode" in str(err.value)

    def test_missing_and_empty(self, tmp_path):
        with pytest.raises(ImageError, match="missing"):
            read_image(tmp_path / "nope.png")
        (tmp_path / "empty.png").write_bytes(b"")
        with pytest.raises(ImageError, match="empty"):
            read_image(tmp_path / "empty.png")
        with pytest.raises(ImageError):
            read_image(tmp_path)  # a folder

    def test_a_name_not_utf8_is_escaped_in_the_message(self, tmp_path):
        bad = tmp_path / os.fsdecode(b"frame\xfe.png")  # Python keeps the byte as a lone surrogate
        bad.write_bytes(b"\x89PNG" + b"x" * 40)
        with pytest.raises(ImageError) as err:
            read_image(bad)
        assert "frame\\udcfe.png" in str(err.value) and str(err.value).encode("utf-8")  # writable to a UTF-8 log


class TestToUint8Dtypes:
    def test_signed_with_negatives_stretched(self, grey):
        signed = grey.astype(np.int16) * 100 - 12000
        out = to_uint8(signed)
        assert out.dtype == np.uint8 and out.min() == 0 and out.max() == 255
        assert np.corrcoef(out.ravel(), grey.ravel())[0, 1] > 0.999  # same picture

    def test_int32_nonnegative_like_uint16(self, grey):
        np.testing.assert_array_equal(to_uint8(grey.astype(np.int32) * 257), grey)

    def test_float_beyond_one_and_nan(self, grey):
        f = grey.astype(np.float32) * 16.0  # 12-bit data stored as float
        assert np.abs(to_uint8(f).astype(int) - grey).max() <= 1
        f[0, 0] = np.nan
        assert to_uint8(f)[0, 0] == 0

    def test_bool(self):
        img = np.zeros((10, 10), bool)
        img[2:5] = True
        assert set(np.unique(to_uint8(img))) == {0, 255}

    @pytest.mark.parametrize("bad, error", [
        ("a.png", "numpy array"), (np.zeros((7, 100), np.uint8), "too small"),
        (np.zeros((20, 20), np.complex64), "dtype"), (np.zeros((20, 20, 5), np.uint8), "shape"),
    ])
    def test_check_image_refuses(self, bad, error):
        with pytest.raises(ImageError, match=error):
            check_image(bad)


class TestReadImageHostile:
    @pytest.mark.parametrize("keep", [0.3, 0.6, 0.99])
    def test_truncated_png_one_message_nothing_on_stderr(self, tmp_path, grey, capfd, keep):
        """A PNG cut short (a copy interrupted): libpng printed its own line to stderr beside our warning."""
        data = cv2.imencode(".png", grey)[1].tobytes()
        (tmp_path / "cut.png").write_bytes(data[: int(len(data) * keep)])
        capfd.readouterr()
        with pytest.raises(ImageError, match="truncated PNG"):
            read_image(tmp_path / "cut.png")
        assert capfd.readouterr().err == ""
        (tmp_path / "whole.png").write_bytes(data + b"trailing bytes after IEND")
        np.testing.assert_array_equal(read_image(tmp_path / "whole.png"), grey)

    def test_not_regular_files(self, tmp_path):
        (tmp_path / "dir.png").mkdir()
        (tmp_path / "link.png").symlink_to(tmp_path / "missing.png")
        os.mkfifo(tmp_path / "fifo.png")  # reading it would block forever
        for name, why in (("dir.png", "a folder"), ("link.png", "broken symbolic link"), ("fifo.png", "FIFO")):
            with pytest.raises(ImageError, match=why):
                read_image(tmp_path / name)
        assert [p.name for p in image_entries(tmp_path)] == ["dir.png", "fifo.png", "link.png"]

    def test_decompression_bomb_refused_before_decoding(self):
        import struct
        import zlib

        data = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
        ihdr = data[12:29]
        ihdr[4:12] = struct.pack(">II", 40000, 40000)
        data[12:29] = ihdr
        data[29:33] = struct.pack(">I", zlib.crc32(bytes(ihdr)))
        with pytest.raises(ImageError, match=f"too large: its header declares 1600000000 pixels; at most "
                                             f"{MAX_IMAGE_PIXELS} pixels"):  # not "40000x1": the count alone
            decode_image(bytes(data), "bomb.png")

    @pytest.mark.parametrize("ext", [".png", ".jpg", ".tiff", ".bmp", ".webp"])
    def test_every_format_is_sized_from_its_header_before_decoding(self, sample_image, ext, monkeypatch):
        from cae_lcd.core.images import image_header

        image = sample_image(0)
        data = cv2.imencode(ext, image)[1].tobytes()
        assert image_header(data)[1:] == (image.shape[1], image.shape[0])

        def no_decoding(*args):
            raise AssertionError("decoded before its size was checked")

        monkeypatch.setattr(cv2, "imdecode", no_decoding)
        with pytest.raises(ImageError, match="too large"):
            decode_image(data, f"frame{ext}", max_pixels=image.shape[0] * image.shape[1] - 1)

    def test_a_huge_jpeg_header_is_refused_without_decoding(self, sample_dir):
        data = bytearray((sample_dir / "image_0" / "000000.jpg").read_bytes())
        sof = data.find(b"\xff\xc0")
        data[sof + 5:sof + 9] = (65500).to_bytes(2, "big") * 2  # height, width
        with pytest.raises(ImageError, match="too large"):
            decode_image(bytes(data[:400]), "bomb.jpg")  # 400 bytes that claim 4.3 Gpixel

    def test_an_unknown_header_is_refused_when_one_is_required(self):
        with pytest.raises(ImageError, match="PNG or JPEG"):
            decode_image(b"GIF89a" + bytes(40), "x.gif", known_header=True)

    def test_fingerprint(self, sample_dir):
        data = (sample_dir / "image_0" / "000000.jpg").read_bytes()
        fp = fingerprint(data)
        assert fp.startswith(f"{len(data)}:") and len(fp.split(":")[1]) == 16
        assert fingerprint(data[:-1] + b"x") != fp


class TestImageEntries:
    def test_numbers_in_names_sort_as_numbers(self, tmp_path, grey):
        """A camera that writes ``1.png ... 12.png`` (no zero padding): frame 10 comes after 9, not after 1."""
        for n in (1, 10, 2, 12, 9, 11):
            assert cv2.imwrite(str(tmp_path / f"{n}.png"), grey[:16, :16])
        (tmp_path / "notes.txt").write_text("not a frame")
        assert [p.name for p in image_entries(tmp_path)] == ["1.png", "2.png", "9.png", "10.png", "11.png", "12.png"]

    def test_padded_names_and_prefixes_keep_their_order(self, tmp_path, grey):
        names = ["000000.png", "000001.png", "000010.png", "cam_b_2.png", "cam_b_10.png", "cam_c_1.png"]
        for name in reversed(names):
            assert cv2.imwrite(str(tmp_path / name), grey[:16, :16])
        assert [p.name for p in image_entries(tmp_path)] == names


class TestExifOrientation:
    @pytest.mark.parametrize("orientation", range(1, 9))
    @pytest.mark.parametrize("channels", [1, 3])
    @pytest.mark.parametrize("fmt", ["WEBP", "TIFF"])
    def test_turned_as_a_viewer_shows_it(self, grey, orientation, channels, fmt):
        """A phone or action camera stores its pixels as the sensor read them and says in EXIF how to turn them;
        ``cv2.IMREAD_UNCHANGED`` ignores it in a JPEG or WebP (the frame reached the encoder on its side) and
        applies it in a TIFF (not twice). Pillow's ``exif_transpose`` is the reference (lossless files: exact)."""
        import io

        from PIL import Image, ImageOps

        img = grey[:60, :90] if channels == 1 else np.dstack([grey[:60, :90], grey[:60, :90] // 2,
                                                            np.tile(np.arange(90, dtype=np.uint8), (60, 1))])
        exif = Image.Exif()
        exif[0x0112] = orientation
        buf = io.BytesIO()
        Image.fromarray(img if channels == 1 else img[:, :, ::-1]).save(buf, fmt, exif=exif, lossless=True)
        want = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(buf.getvalue()))))
        got = decode_image(buf.getvalue())
        np.testing.assert_array_equal(got if channels == 1 else got[:, :, ::-1], want)

    def test_jpeg_rotated_upright(self, sample_dir, tmp_path):
        from PIL import Image

        exif = Image.Exif()
        exif[0x0112] = 6  # stored turned a quarter to the left: show it turned a quarter to the right
        Image.open(sample_dir / "image_0" / "000003.jpg").transpose(Image.Transpose.ROTATE_90).save(
            tmp_path / "a.jpg", exif=exif, quality=95)
        upright = read_image(sample_dir / "image_0" / "000003.jpg").astype(int)
        got = read_image(tmp_path / "a.jpg")
        assert got.shape == upright.shape and np.abs(got.astype(int) - upright).mean() < 3
