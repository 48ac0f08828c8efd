"""The camera: a pinhole ``K`` with, optionally, a lens distortion model whose keypoints are undistorted before the
geometric check (``verify.geometry``), and where it comes from (``--intrinsics``, ``--camera-info FILE``, EuRoC's
``sensor.yaml``, a bag's ``CameraInfo``).

Distortion models (``DISTORTION_MODELS``), with the names other tools give them:

- ``radtan``: OpenCV's radial-tangential ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (ROS ``plumb_bob`` and
  ``rational_polynomial``, Kalibr and EuRoC ``radtan`` / ``radial-tangential``); undistorted with
  ``cv2.undistortPoints``;
- ``equidistant``: the Kannala-Brandt fisheye ``k1 k2 k3 k4`` (ROS and Kalibr ``equidistant``, OpenCV ``fisheye``);
  undistorted with ``cv2.fisheye.undistortPoints``;
- ``none``: a pinhole.

Camera files ``read_camera_file`` reads (YAML; OpenCV's ``%YAML:1.0`` line is skipped):

- ROS ``camera_info`` (``camera_calibration``'s output): ``camera_matrix: {data: [9 numbers]}``,
  ``distortion_model``, ``distortion_coefficients: {data: [...]}``;
- a Kalibr camchain: ``cam0: {intrinsics: [fu, fv, cu, cv], distortion_model, distortion_coeffs, T_cam_imu}``
  (the first camera, ``cam0``, unless the file has one other);
- EuRoC's ``sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model``, ``distortion_coefficients``,
  ``T_BS: {data: [16 numbers]}``;
- the small documented form, the same keys as EuRoC's::

      intrinsics: [fx, fy, cx, cy]      # pixels
      distortion_model: equidistant     # none | radtan | equidistant (and the aliases above)
      distortion_coefficients: [k1, k2, k3, k4]
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import yaml

from cae_lcd.core.checks import check_intrinsics
from cae_lcd.core.conf import ConfigError

__all__ = ["CameraModel", "DISTORTION_MODELS", "MODEL_NAMES", "read_camera_file", "camera_from_options",
           "undistort_points", "parse_intrinsics", "distortion_model"]

DISTORTION_MODELS = ("none", "radtan", "equidistant")  #: the models ``geometry.distortion_model`` takes
#: what other tools call them -> ours
MODEL_NAMES = {"none": "none", "pinhole": "none", "radtan": "radtan", "radial-tangential": "radtan",
               "plumb_bob": "radtan", "rational_polynomial": "radtan", "equidistant": "equidistant",
               "fisheye": "equidistant", "kannala_brandt": "equidistant", "equi": "equidistant"}
#: how many coefficients each model takes
COEFFICIENTS = {"none": (0,), "radtan": (4, 5, 8), "equidistant": (4,)}
#: the undistortion's fixed-point iterations: OpenCV's default (5 for radtan) leaves pixels of error at a strong
#: lens's image corners (EuRoC's k1 = -0.28)
_ITERATIONS = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9)


@dataclass(frozen=True)
class CameraModel:
    """A camera: intrinsics, lens distortion, and where it sits on the body when known."""

    K: np.ndarray  #: (3, 3) pinhole intrinsics
    model: str = "none"  #: one of ``DISTORTION_MODELS``
    coefficients: tuple[float, ...] = ()  #: the model's coefficients (``COEFFICIENTS``)
    T_body_camera: np.ndarray | None = field(default=None, repr=False)  #: (4, 4) camera -> body (EuRoC T_BS)
    source: str = ""  #: where it was read

    def geometry_conf(self) -> dict[str, Any]:
        """The ``geometry`` conf section that makes the verifier undistort keypoints with this model."""
        return {"distortion_model": self.model, "distortion_coefficients": [float(c) for c in self.coefficients]}


def distortion_model(name: Any, coefficients: Sequence[float], where: str) -> tuple[str, tuple[float, ...]]:
    """A distortion model name (any alias) and its coefficients, checked -> ``(model, coefficients)``; radtan with
    all-zero coefficients (or none) is a pinhole (an equidistant lens with zero coefficients is not: ``r = f theta``).
    """
    key = str(name if name is not None else "none").strip().lower()
    if key not in MODEL_NAMES:
        raise ConfigError(f"{where}: unknown distortion model {name!r}; known: {', '.join(MODEL_NAMES)}")
    model = MODEL_NAMES[key]
    try:
        coefs = tuple(float(c) for c in (coefficients or ()))
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: distortion coefficients must be numbers") from None
    if not np.isfinite(coefs).all() or any(abs(c) > 1e3 for c in coefs):
        raise ConfigError(f"{where}: distortion coefficients must be finite, |c| <= 1000")
    if model == "none" or (model == "radtan" and not any(coefs)):
        return "none", ()
    if len(coefs) not in COEFFICIENTS[model]:
        raise ConfigError(f"{where}: the {model} model takes {' or '.join(map(str, COEFFICIENTS[model]))} "
                          f"coefficients, got {len(coefs)}")
    return model, coefs


def parse_intrinsics(text: str | Sequence[float], where: str = "--intrinsics") -> np.ndarray:
    """``"fx,fy,cx,cy"`` (or four numbers) -> ``K (3, 3)``.

    Raises:
        ConfigError: not four finite numbers with fx, fy > 0.
    """
    try:
        values = [float(v) for v in (text.split(",") if isinstance(text, str) else text)]
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be four numbers fx,fy,cx,cy; got {text!r}") from None
    if len(values) != 4:
        raise ConfigError(f"{where} must be four numbers fx,fy,cx,cy; got {len(values)}")
    fx, fy, cx, cy = values
    return check_intrinsics(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), where)


def _matrix(value: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    """A matrix given as ``{rows, cols, data}`` (ROS, EuRoC), nested lists (Kalibr) or a flat list."""
    data = value.get("data") if isinstance(value, dict) else value
    try:
        arr = np.asarray(data, np.float64).reshape(shape)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected a {shape[0]}x{shape[1]} matrix") from None
    if not np.isfinite(arr).all():
        raise ConfigError(f"{where}: the matrix holds NaN or infinite values")
    return arr


def _load_yaml(path: Path) -> dict[str, Any]:
    try:  # OpenCV writes a '%YAML:1.0' directive (and '!!opencv-matrix' tags) that PyYAML refuses
        text = "\n".join(ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("%"))
        data = yaml.safe_load(text.replace("!!opencv-matrix", ""))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot read camera file {path}: {type(err).__name__}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a camera file (a YAML mapping)")
    return data


def read_camera_file(path: str | Path, camera: str | None = None) -> CameraModel:
    """A ROS ``camera_info`` YAML, a Kalibr camchain, a EuRoC ``sensor.yaml`` or the small form (module doc).

    Args:
        camera: a camchain's camera (``cam0``, ``cam1``); None: ``cam0``, or the only one.

    Raises:
        ConfigError: an unreadable file, one of none of these forms, or values out of range (file named).
    """
    path = Path(path)
    data = _load_yaml(path)
    cams = sorted(k for k, v in data.items()
                  if isinstance(k, str) and re.fullmatch(r"cam\d+", k) and isinstance(v, dict))
    if cams:  # Kalibr camchain
        name = camera or ("cam0" if "cam0" in cams else cams[0])
        if name not in cams:
            raise ConfigError(f"{path} has no camera {name}; cameras: {', '.join(cams)}")
        d = data[name]
        model, coefs = distortion_model(d.get("distortion_model"), d.get("distortion_coeffs", ()),
                                        f"{path} {name}")
        T = d.get("T_cam_imu")
        T_body = None if T is None else np.linalg.inv(_matrix(T, (4, 4), f"{path} {name} T_cam_imu"))
        return CameraModel(parse_intrinsics(d.get("intrinsics", ()), f"{path} {name} intrinsics"), model, coefs,
                           T_body, str(path))
    if "camera_matrix" in data:  # ROS camera_info
        K = check_intrinsics(_matrix(data["camera_matrix"], (3, 3), f"{path} camera_matrix"), f"{path} camera_matrix")
        dist = data.get("distortion_coefficients")
        model, coefs = distortion_model(data.get("distortion_model", "plumb_bob"),
                                        dist.get("data", ()) if isinstance(dist, dict) else (dist or ()), str(path))
        return CameraModel(K, model, coefs, None, str(path))
    if "intrinsics" in data:  # EuRoC sensor.yaml, or the small form
        model, coefs = distortion_model(data.get("distortion_model", "none"),
                                        data.get("distortion_coefficients", ()), str(path))
        T = data.get("T_BS")
        return CameraModel(parse_intrinsics(data["intrinsics"], f"{path} intrinsics"), model, coefs,
                           None if T is None else _matrix(T, (4, 4), f"{path} T_BS"), str(path))
    raise ConfigError(f"{path}: not a camera file: expected a ROS camera_info (camera_matrix), a Kalibr camchain "
                      "(cam0: ...) or 'intrinsics: [fx, fy, cx, cy]'")


def camera_from_options(intrinsics: str | Sequence[float] | None = None,
                        camera_info: str | Path | None = None) -> CameraModel | None:
    """The camera a user gave: ``--camera-info FILE`` and/or ``--intrinsics fx,fy,cx,cy`` (which overrides the
    file's ``K``, keeping its distortion); None when neither is given.

    Raises:
        ConfigError: as ``read_camera_file`` and ``parse_intrinsics``.
    """
    cam = read_camera_file(camera_info) if camera_info is not None else None
    if intrinsics is None:
        return cam
    K = parse_intrinsics(intrinsics)
    return CameraModel(K, "none", (), None, "--intrinsics") if cam is None else CameraModel(
        K, cam.model, cam.coefficients, cam.T_body_camera, f"{cam.source} with --intrinsics")


def undistort_points(pts: np.ndarray, K: np.ndarray, model: str, coefficients: Sequence[float]) -> np.ndarray:
    """``(M, 2)`` distorted pixel coordinates -> ``(M, 2)`` where a pinhole camera ``K`` would see them.

    ``model`` one of ``DISTORTION_MODELS`` (``"none"``, or no coefficients: the points as they are).
    """
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    if model == "none" or not len(pts):
        return pts
    src = np.ascontiguousarray(pts).reshape(-1, 1, 2)
    D = np.asarray(coefficients, np.float64)
    K = np.asarray(K, np.float64)
    out = (cv2.fisheye.undistortPoints(src, K, D, P=K, criteria=_ITERATIONS) if model == "equidistant"
           else cv2.undistortPoints(src, K, D, R=None, P=K, criteria=_ITERATIONS))
    return out.reshape(-1, 2)
