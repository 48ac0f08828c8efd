"""Reading images and converting them to what the stages take, for every camera a user brings.

Accepted images (numpy arrays, as ``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` returns them):
grey ``(H, W)``, grey ``(H, W, 1)``, BGR ``(H, W, 3)``, BGRA ``(H, W, 4)``; dtype uint8, uint16 (any bit depth up
to 16: 10-, 12- and 14-bit data stored in 16-bit words are scaled by their own range), other integer types (signed
data is stretched over its own range), bool, or float (in [0, 1], or scaled by its own range when larger); at least
8x8 pixels and at most ``MAX_IMAGE_PIXELS``.
"""

from __future__ import annotations

import hashlib
import io
import logging
import math
import os
import re
import stat
import struct
import tempfile
import threading
import warnings
from pathlib import Path

import cv2
import numpy as np

from .errors import ImageError

__all__ = ["IMAGE_EXTENSIONS", "MAX_IMAGE_PIXELS", "MIN_IMAGE_SIDE", "natural_key", "image_entries", "read_image", "read_file",
           "decode_image", "image_header", "HEADER_FORMATS", "check_structure", "too_large", "MAX_JPEG_SCANS",
           "MAX_PNG_CHUNKS", "fingerprint", "check_image", "to_uint8", "to_gray_u8", "to_rgb_u8", "resize_square"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
MAX_IMAGE_PIXELS = 1 << 27  #: larger images are refused before decoding (134 Mpixel: 11585x11585; 4K is 8.3)
MIN_IMAGE_SIDE = 8  #: smaller images are refused (no feature, no edge can be measured)
MAX_JPEG_SCANS = 32  #: a JPEG of more scans is refused before decoding (``check_structure``; libjpeg writes 6 to 10
#                      for a progressive file; each scan costs up to ~40 ms on 16 Mpixel: 1000 took 40-50 s)
MAX_PNG_CHUNKS = 256  #: a PNG of more chunks besides its pixel data (IDAT) is refused (100 000 text chunks: 5.8 s)
DEFLATE_MAX_RATIO = 1032  #: deflate never expands more than this: a PNG's pixel data needs at least raw / this bytes

log = logging.getLogger(__name__)


def natural_key(path: str | Path) -> tuple:
    """A sort key that orders numbers in names as numbers: ``1.png, 2.png, 10.png`` (text order would put ``10``
    before ``2``); names equal as numbers (``01``, ``1``) fall back to text order."""
    text = str(path)
    parts = re.split(r"(\d+)", text)  # text, digits, text, ...: the same kind at the same position
    return tuple(int(t) if i % 2 else t for i, t in enumerate(parts)), text


def image_entries(folder: str | Path, recursive: bool = False) -> list[Path]:
    """Every entry below ``folder`` whose name has an image extension, in natural order of their paths (numbers in
    names compared as numbers, ``natural_key``: ``2.png`` before ``10.png``).

    Entries that are not readable regular files (broken symbolic links, FIFOs, folders named like images) are
    listed too, so that the caller can report and count them (``read_image`` refuses them with a clear message);
    a folder named like an image is still searched when ``recursive``.
    """
    folder = Path(folder)
    entries = folder.rglob("*") if recursive else folder.iterdir()
    return sorted((p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS), key=natural_key)


def _kind(path: Path) -> str | None:
    """Why ``path`` is not a regular file we can read (None when it is one)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "broken symbolic link" if os.path.islink(path) else "missing file"
    except OSError as err:
        return f"cannot stat ({err.strerror})"
    if stat.S_ISDIR(mode):
        return "a folder, not an image file"
    if not stat.S_ISREG(mode):
        return "not a regular file (FIFO, socket or device)"
    return None


def read_file(path: str | Path) -> bytes:
    """The bytes of an image file; never blocks on a FIFO.

    Raises:
        ImageError: missing, not a regular file, unreadable or empty.
    """
    path = Path(path)
    why = _kind(path)
    if why is not None:
        raise ImageError(f"cannot read image {path}: {why}")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ImageError(f"cannot read image {path}: {err.strerror or err}") from None
    if not data:
        raise ImageError(f"cannot read image {path}: empty file")
    return data


def fingerprint(data: bytes) -> str:
    """``"<size>:<16 hex digits>"``: size and BLAKE2b hash of a file's bytes (what the keyframe database records)."""
    return f"{len(data)}:{hashlib.blake2b(data, digest_size=8).hexdigest()}"


HEADER_FORMATS = ("PNG", "JPEG", "TIFF", "BMP", "WEBP", "PPM")  #: formats whose size ``image_header`` reads


def _header(data: bytes) -> tuple[str, int, int, int] | None:
    """``(format, width, height, EXIF orientation 1-8)`` from an image file's header without decoding it (Pillow
    reads headers lazily); None when the header is not one of ``HEADER_FORMATS`` or cannot be parsed."""
    try:
        from PIL import Image

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data), formats=list(HEADER_FORMATS)) as im:
                w, h = im.size
                orientation = 1
                if im.format in _EXIF_IN_HEADER:  # a PNG's eXIf may follow its pixels: Pillow would decode them
                    try:
                        orientation = int(im.getexif().get(_ORIENTATION, 1))
                    except Exception:  # noqa: BLE001 - a damaged EXIF block: the pixels as stored
                        orientation = 1
                return str(im.format), int(w), int(h), orientation if orientation in _ORIENT else 1
    except Exception as err:  # noqa: BLE001 - any header Pillow cannot parse: unknown
        if type(err).__name__ == "DecompressionBombError":  # Pillow's own limit: its message has the size
            found = re.search(r"\((\d+) pixels\)", str(err))
            return "?", int(found.group(1)) if found else MAX_IMAGE_PIXELS + 1, 1, 1
        return None


def image_header(data: bytes) -> tuple[str, int, int] | None:
    """``(format, width, height)`` from an image file's header without decoding it (Pillow reads headers lazily);
    None when the header is not one of ``HEADER_FORMATS`` or cannot be parsed."""
    header = _header(data)
    return None if header is None else header[:3]


_EXIF_IN_HEADER = ("JPEG", "WEBP")  #: formats whose EXIF orientation is applied here (OpenCV turns a TIFF itself)
_ORIENTATION = 0x0112  #: the EXIF tag of how the stored pixels are to be turned for display
_ORIENT: dict[int, tuple[int | None, int | None]] = {  # EXIF orientation -> (cv2.flip code, cv2.rotate code), in turn
    1: (None, None), 2: (1, None), 3: (None, cv2.ROTATE_180), 4: (0, None),
    5: (1, cv2.ROTATE_90_COUNTERCLOCKWISE), 6: (None, cv2.ROTATE_90_CLOCKWISE),
    7: (1, cv2.ROTATE_90_CLOCKWISE), 8: (None, cv2.ROTATE_90_COUNTERCLOCKWISE)}


def _upright(img: np.ndarray, orientation: int) -> np.ndarray:
    """The stored pixels turned as their EXIF ``orientation`` says (as a viewer shows them; ``cv2.IMREAD_UNCHANGED``
    ignores it)."""
    flip, rotate = _ORIENT.get(orientation, (None, None))
    if flip is not None:
        img = cv2.flip(img, flip)
    return img if rotate is None else cv2.rotate(img, rotate)


_JPEG_ENTROPY_END = re.compile(rb"\xff(?![\x00\xd0-\xd7\xff])")  #: the marker that ends a scan's coded data
_JPEG_SOF_HUFFMAN = (0xC0, 0xC1, 0xC2)  #: baseline, extended and progressive Huffman: the codings accepted


def _jpeg_structure(data: bytes) -> str | None:
    """Why a JPEG would cost more than its size says (None: it would not): a coding other than Huffman (arithmetic
    coding packs a large flat image in a few bytes), more than ``MAX_JPEG_SCANS`` scans, no end marker (cut short:
    libjpeg invents the rest), or less coded data than its declared size needs (one bit per 8x8 block of each
    component at least: a DC code)."""
    pos, scans, coded, blocks = 2, 0, 0, None
    while pos + 2 <= len(data):
        if data[pos] != 0xFF:
            return "bytes where a marker should be"
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0xD9:  # EOI
            break
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:
            pos += 2
            continue
        length = struct.unpack(">H", data[pos + 2:pos + 4])[0] if pos + 4 <= len(data) else 0
        end = pos + 2 + length
        if length < 2 or end > len(data):
            return "a segment runs past the end of the file"
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if marker not in _JPEG_SOF_HUFFMAN:
                return f"coding SOF{marker - 0xC0} is not accepted (baseline or progressive Huffman only)"
            blocks = _jpeg_blocks(data[pos + 4:end])
        if marker == 0xDA:
            scans += 1
            if scans > MAX_JPEG_SCANS:
                return f"more than {MAX_JPEG_SCANS} scans"
            found = _JPEG_ENTROPY_END.search(data, end)
            if found is None:
                return "cut short (no end marker)"
            coded += found.start() - end
            end = found.start()
        pos = end
    else:
        return "cut short (no end marker)"
    if blocks is not None and coded * 8 < blocks:
        return f"{coded} bytes of coded data where its declared size needs at least {_ceil_div(blocks, 8)}"
    return None


def _jpeg_blocks(sof: bytes) -> int:
    """8x8 blocks of every component of a JPEG frame header (SOF payload), as its size declares them."""
    if len(sof) < 6:
        return 0
    height, width, count = struct.unpack(">HHB", sof[1:6])
    comps = [(sof[6 + 3 * i + 1] >> 4, sof[6 + 3 * i + 1] & 15) for i in range(count) if 6 + 3 * i + 2 < len(sof)]
    if not comps:
        return 0
    hmax, vmax = max(max(h for h, _ in comps), 1), max(max(v for _, v in comps), 1)
    return sum(_ceil_div(_ceil_div(width * h, hmax), 8) * _ceil_div(_ceil_div(height * v, vmax), 8)
               for h, v in comps)


def _ceil_div(a: int, b: int) -> int:
    """``ceil(a / b)`` of integers."""
    return -(-a // b)


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  #: colour type -> samples per pixel


def _png_structure(data: bytes) -> str | None:
    """Why a PNG would cost more than its size says (None: it would not): a chunk running past the end, more than
    ``MAX_PNG_CHUNKS`` chunks besides IDAT, no IEND, or less pixel data than its declared size needs through deflate
    (``DEFLATE_MAX_RATIO``)."""
    pos, others, idat, raw = 8, 0, 0, 0
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if pos + 12 + length > len(data):
            return "a chunk runs past the end of the file"
        if kind == b"IHDR" and length >= 13:
            width, height, depth, colour = struct.unpack(">IIBB", data[pos + 8:pos + 18])
            raw = height * (1 + _ceil_div(width * _PNG_CHANNELS.get(colour, 1) * depth, 8))
        elif kind == b"IDAT":
            idat += length
        elif kind == b"IEND":
            break
        else:
            others += 1
            if others > MAX_PNG_CHUNKS:
                return f"more than {MAX_PNG_CHUNKS} chunks besides its pixel data"
        pos += 12 + length
    else:
        return "cut short (no IEND chunk)"
    if idat * DEFLATE_MAX_RATIO < raw:
        return f"{idat} bytes of pixel data where its declared size needs at least {_ceil_div(raw, DEFLATE_MAX_RATIO)}"
    return None


_STRUCTURE = {"JPEG": _jpeg_structure, "PNG": _png_structure}  #: format -> its structure check


def check_structure(data: bytes, fmt: str, name: str | Path = "<bytes>") -> None:
    """Refuses, before any decoder runs, a file whose decoding would cost more than its size says: a JPEG of many
    scans, of arithmetic coding, cut short or with less coded data than its declared size needs; a PNG of many
    chunks, cut short or with too little pixel data for its size (other formats: nothing checked).

    Raises:
        ImageError: one line, what is wrong.
    """
    check = _STRUCTURE.get(fmt)
    why = None if check is None else check(data)
    if why is not None:
        raise ImageError(f"cannot decode {name}: {fmt} {why}")


_STDERR_LOCK = threading.Lock()  #: one captured decoder at a time (file descriptor 2 is the process's)


def _imdecode_logged(data: bytes) -> np.ndarray | None:
    """``cv2.imdecode`` with what the decoders write to the process's stderr (libjpeg's, libpng's warnings) sent to
    this module's log instead, one record a line."""
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        saved = os.dup(2)
        try:
            os.dup2(capture.fileno(), 2)
            try:
                return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
            capture.seek(0)
            for line in capture.read(4096).decode("utf-8", "replace").splitlines():
                if line.strip():
                    log.warning("image decoder: %s", line.strip()[:300])


def too_large(header: tuple, max_pixels: int, what: str = "image") -> str:
    """The one-line refusal of ``what`` whose ``header`` (format, width, height, ...) declares more than
    ``max_pixels``: its width and height when the header gave them, else its pixel count alone."""
    fmt, width, height = header[:3]
    size = f"{width}x{height} ({width * height} pixels)" if fmt != "?" else f"{width * height} pixels"
    return f"{what} too large: its header declares {size}; at most {max_pixels} pixels are accepted"


def decode_image(data: bytes, name: str | Path = "<bytes>", max_pixels: int = MAX_IMAGE_PIXELS,
                 known_header: bool = False) -> np.ndarray:
    """Decodes image file bytes unchanged (grey or colour, 8- or 16-bit), after checking its size in its header, and
    turned upright as its EXIF orientation says (a phone's or action camera's JPEG shows as a viewer shows it).

    Args:
        data: the file's bytes. name: what messages call it. max_pixels: larger images are refused (from the header
            when it can be read, before any pixel is decoded). known_header: refuse files whose header is not one of
            ``HEADER_FORMATS``, and files whose decoding would cost more than their size says (``check_structure``),
            with the decoders' own messages sent to this module's log (a server's input: no decoder runs on a file
            whose size is unknown; its stderr stays its own).

    Raises:
        ImageError: corrupt, unsupported, larger than ``max_pixels`` or smaller than 8x8.
    """
    header = _header(data)
    if header is None and known_header:
        raise ImageError(f"{name} is not a readable PNG or JPEG (or TIFF, BMP, WebP, PPM) file")
    if header is not None and header[1] * header[2] > max_pixels:
        raise ImageError(too_large(header, max_pixels, f"image {name}"))
    if header is not None and header[0] == "PNG" and data.rfind(b"IEND") < 0:  # libpng would print to stderr
        raise ImageError(f"cannot decode image {name}: truncated PNG (no IEND chunk)")
    if known_header:
        check_structure(data, header[0], name)
    try:
        img = _imdecode_logged(data) if known_header else cv2.imdecode(np.frombuffer(data, np.uint8),
                                                                        cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise ImageError(f"cannot decode image {name}: {str(err).strip().splitlines()[-1][:160]}") from None
    if img is None or img.size == 0:
        raise ImageError(f"cannot decode image {name}: corrupt or unsupported format")
    if img.shape[0] * img.shape[1] > max_pixels:
        raise ImageError(f"image {name} too large: {img.shape[0] * img.shape[1]} pixels (limit {max_pixels})")
    check_image(img, name)
    return img if header is None or header[3] == 1 else _upright(img, header[3])


def read_image(path: str | Path) -> np.ndarray:
    """Reads an image file unchanged (grey or colour, 8- or 16-bit).

    Raises:
        ImageError: the file is missing, not a regular file, unreadable, corrupt, too large or too small.
    """
    return decode_image(read_file(path), path)


def check_image(image: object, name: str | Path = "image") -> np.ndarray:
    """Checks that ``image`` is an image array we can interpret (type, layout, size, dtype) and returns it.

    Raises:
        ImageError: what is wrong, e.g. ``image must be a numpy array (H, W[, C]); got str``.
    """
    if not isinstance(image, np.ndarray):
        hint = " (read files with cae_lcd.core.images.read_image)" if isinstance(image, (str, Path)) else ""
        raise ImageError(f"{name} must be a numpy array (H, W[, C]); got {type(image).__name__}{hint}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise ImageError(f"{name}: unsupported image shape {image.shape}; expected (H, W), (H, W, 1), (H, W, 3) "
                         "or (H, W, 4)")
    h, w = image.shape[:2]
    if h < MIN_IMAGE_SIDE or w < MIN_IMAGE_SIDE:
        raise ImageError(f"{name} too small: {w}x{h} pixels (need at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE})")
    if h * w > MAX_IMAGE_PIXELS:
        raise ImageError(f"{name} too large: {w}x{h} pixels (limit {MAX_IMAGE_PIXELS})")
    if not (image.dtype == np.bool_ or np.issubdtype(image.dtype, np.integer)
            or np.issubdtype(image.dtype, np.floating)):
        raise ImageError(f"{name}: unsupported dtype {image.dtype}; expected an integer, bool or float image")
    return image


def _bit_scale(top: float) -> float:
    """255 / (2^bits - 1) for the smallest bit depth (>= 8) that holds ``top``."""
    bits = max(8, int(math.ceil(math.log2(top + 1)))) if top > 0 else 8
    return 255.0 / (2.0**bits - 1.0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Converts any accepted dtype to uint8, keeping the channel layout.

    uint16 (and any unsigned data) is scaled by its bit depth, inferred from the maximum value (a 12-bit image with
    max 4095 maps to 255), so 10/12/14-bit sensors look like 8-bit ones. Signed data with negative values is
    stretched over its own range. Floats in [0, 1] are scaled by 255, larger ones like integers; NaN counts as 0.
    """
    if image.dtype == np.uint8:
        return image
    check_image(image)
    if image.dtype == np.bool_:
        return image.astype(np.uint8) * np.uint8(255)
    if image.dtype == np.uint16:
        return cv2.convertScaleAbs(image, alpha=_bit_scale(int(image.max())))
    img = image.astype(np.float32) if np.issubdtype(image.dtype, np.floating) else image.astype(np.float64)
    if np.issubdtype(image.dtype, np.floating):
        finite = np.isfinite(img)
        if not finite.all():
            img = np.where(finite, img, 0.0).astype(np.float32)
    lo, hi = float(img.min()), float(img.max())
    if lo < 0:
        scaled = (img - lo) * (255.0 / (hi - lo) if hi > lo else 0.0)
    elif np.issubdtype(image.dtype, np.floating) and hi <= 1.0:
        scaled = img * 255.0
    else:
        scaled = img * _bit_scale(hi)
    return np.clip(scaled + 0.5, 0, 255).astype(np.uint8)


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Any accepted image -> grey uint8 ``(H, W)``."""
    img = to_uint8(check_image(image))
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img)


def to_rgb_u8(image: np.ndarray) -> np.ndarray:
    """Any accepted image -> RGB uint8 ``(H, W, 3)``; grey is replicated to three channels."""
    img = to_uint8(check_image(image))
    if img.ndim == 2 or img.shape[2] == 1:
        return cv2.cvtColor(np.ascontiguousarray(img.reshape(img.shape[:2])), cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def resize_square(image: np.ndarray, size: int) -> np.ndarray:
    """Resizes to ``size x size`` (aspect not kept, as in the paper): area averaging down, bilinear up."""
    h, w = image.shape[:2]
    interp = cv2.INTER_AREA if (h >= size and w >= size) else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(image), (size, size), interpolation=interp)
