"""Checks of the values a caller hands in with a frame: ids, timestamps, poses, intrinsics and depth maps.

One home for them: the Python API (``retrieval.LoopDetector``), the CLI and the fleet server call these, so a value
is refused the same way everywhere, with one ``ConfigError`` line, before anything is computed or written.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from .errors import ConfigError

__all__ = ["MAX_FRAME_ID", "MAX_TIMESTAMP", "MAX_TRANSLATION", "MAX_DEPTH", "ROTATION_TOL", "MIN_FOCAL",
           "MAX_INTRINSIC", "check_frame_id", "check_timestamp", "check_matrix", "check_pose", "check_rigid_pose",
           "check_intrinsics", "decode_depth"]

MAX_FRAME_ID = 2**53  #: ids are in [0, 2**53): exact as a float64 and as a JSON number everywhere
MAX_TIMESTAMP = 1e11  #: |timestamp| in seconds at most this (year 5138 as Unix time)
MAX_TRANSLATION = 1e7  #: a pose's translation at most this far from its map's origin (map units, metres: 10 000 km)
MAX_DEPTH = 1e6  #: a depth value at most this (map units); 0 means "no depth"
ROTATION_TOL = 1e-3  #: ``|R^T R - I|`` and ``|det R - 1|`` at most this for a rigid pose
MIN_FOCAL = 1e-3  #: fx, fy at least this (pixels; normalised cameras have ~1): K^-1 then stays finite on any pixel
MAX_INTRINSIC = 1e7  #: fx, fy, skew, cx, cy at most this in magnitude (pixels)


def check_frame_id(value: Any, what: str = "frame id") -> int:
    """An integer id in ``[0, MAX_FRAME_ID)`` (Python or numpy integer; not bool, not float) -> ``int``.

    Raises:
        ConfigError: another type or out of range.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{what} must be an integer; got {value!r} ({type(value).__name__})")
    if not 0 <= int(value) < MAX_FRAME_ID:
        raise ConfigError(f"{what} must be in 0..2**53-1; got {int(value)}")
    return int(value)


def check_timestamp(value: Any, what: str = "timestamp") -> float:
    """A finite number of seconds, ``|t| <= MAX_TIMESTAMP`` -> ``float``.

    Raises:
        ConfigError: not a number, NaN/inf or out of range.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value) or abs(float(value)) > MAX_TIMESTAMP:
        raise ConfigError(f"{what} must be a finite number of seconds within +-{MAX_TIMESTAMP:g}; got {value!r}")
    return float(value)


def check_matrix(value: Any, shape: tuple[int, int], what: str) -> np.ndarray:
    """A finite float64 matrix of exactly ``shape``.

    Raises:
        ConfigError: not numbers, another shape, or NaN/inf.
    """
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{what} must be a {shape[0]}x{shape[1]} matrix of numbers; got {type(value).__name__}") \
            from None
    if m.shape != shape or not np.isfinite(m).all():
        raise ConfigError(f"{what} must be a finite {shape[0]}x{shape[1]} matrix; got shape {m.shape}"
                          + ("" if m.shape != shape else " with NaN or inf"))
    return m


def check_pose(value: Any, what: str = "pose") -> np.ndarray:
    """A finite camera-to-world pose given as 3x4, 4x4 or 12 numbers (row-major) -> ``(3, 4)`` float64.

    Raises:
        ConfigError: another shape, not numbers, or NaN/inf.
    """
    try:
        shape = np.shape(value)
    except ValueError:  # a ragged list
        shape = ()
    if shape in ((4, 4), (16,)):
        return check_matrix(np.asarray(value, np.float64).reshape(4, 4)[:3], (3, 4), what)
    if shape == (12,):
        return check_matrix(np.asarray(value, np.float64).reshape(3, 4), (3, 4), what)
    return check_matrix(value, (3, 4), what)


def check_rigid_pose(value: Any, what: str = "pose", tol: float = ROTATION_TOL,
                     max_translation: float = MAX_TRANSLATION) -> np.ndarray:
    """A rigid camera-to-map pose (3x4 or 4x4) -> ``(4, 4)`` float64 whose rotation is projected onto the nearest one.

    Rigid: ``|R^T R - I| <= tol`` (so no scale hides in it), ``det R > 0``, ``|t_i| <= max_translation``, and a 4x4's
    last row is ``0 0 0 1``.

    Raises:
        ConfigError: what is wrong, in one line.
    """
    try:
        rows = len(value)
    except TypeError:
        rows = 0
    if rows == 4:
        M = check_matrix(value, (4, 4), what)
        if np.abs(M[3] - [0, 0, 0, 1]).max() > tol:
            raise ConfigError(f"a 4x4 {what} must end with the row 0 0 0 1")
    else:
        M = check_matrix(value, (3, 4), what)
    R = M[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries past 1e154 overflow R^T R: inf, refused below
        orthonormal = np.abs(R.T @ R - np.eye(3)).max() <= tol
    if not orthonormal or np.linalg.det(R) <= 0:
        raise ConfigError(f"{what}: the 3x3 block must be a rotation (orthonormal within {tol:g}, det +1)")
    if np.abs(M[:3, 3]).max() > max_translation:
        raise ConfigError(f"{what}: translation {np.abs(M[:3, 3]).max():.3g} is beyond {max_translation:g}")
    U, _, Vt = np.linalg.svd(R)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = U @ Vt, M[:3, 3]
    return out


def check_intrinsics(value: Any, what: str = "intrinsics") -> np.ndarray:
    """A pinhole camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, finite, ``fx, fy`` in
    ``[MIN_FOCAL, MAX_INTRINSIC]``, ``|s|, |cx|, |cy| <= MAX_INTRINSIC`` -> ``(3, 3)``.

    Raises:
        ConfigError: another shape, NaN/inf, fx or fy out of range (a singular or near-singular matrix), an entry
            beyond ``MAX_INTRINSIC``, or a last row other than ``0 0 1``.
    """
    K = check_matrix(value, (3, 3), what)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
        raise ConfigError(f"{what} must be a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    if min(K[0, 0], K[1, 1]) < MIN_FOCAL or np.abs(K[:2]).max() > MAX_INTRINSIC:
        raise ConfigError(f"{what}: fx and fy must be in [{MIN_FOCAL:g}, {MAX_INTRINSIC:g}] and |s|, |cx|, |cy| at "
                          f"most {MAX_INTRINSIC:g} pixels")
    return K


def decode_depth(data: bytes, shape: tuple[int, int], what: str = "depth") -> np.ndarray:
    """A ``.npy`` depth map, its header checked before any array is allocated -> ``shape`` float32.

    The declared shape must be ``shape``, the dtype a plain integer or float type, the payload exactly its size;
    values must be finite and in ``[0, MAX_DEPTH]`` (0: no depth).

    Raises:
        ConfigError: not a ``.npy``, another shape or dtype, a short or long payload, or bad values.
    """
    f = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(f)
        read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}[version]
        declared, fortran, dtype = read(f)
    except (ValueError, KeyError, OSError, SyntaxError, TypeError):
        raise ConfigError(f"{what} is not a .npy array (version 1 or 2)") from None
    if tuple(declared) != tuple(shape) or dtype.kind not in "fiu" or dtype.hasobject or dtype.itemsize > 8:
        raise ConfigError(f"{what} must be a numeric {tuple(shape)} array like the image; got {dtype} "
                          f"{tuple(declared)}")
    payload = memoryview(data)[f.tell():]
    if len(payload) != int(np.prod(shape)) * dtype.itemsize:
        raise ConfigError(f"{what}: {len(payload)} bytes of data where its header declares "
                          f"{int(np.prod(shape)) * dtype.itemsize}")
    depth = np.frombuffer(payload, dtype).reshape(shape, order="F" if fortran else "C").astype(np.float32)
    if not np.isfinite(depth).all() or depth.min() < 0 or depth.max() > MAX_DEPTH:
        raise ConfigError(f"{what} values must be finite and in [0, {MAX_DEPTH:g}] (0: no depth)")
    return depth
