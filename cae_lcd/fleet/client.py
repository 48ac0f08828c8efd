"""A small Python client of the fleet server (``cae_lcd.fleet.server``), on httpx.

Example:
    >>> admin = FleetClient("http://127.0.0.1:8765", ADMIN_TOKEN)  # doctest: +SKIP
    >>> robot = FleetClient("http://127.0.0.1:8765", admin.register("A"))  # doctest: +SKIP
    >>> robot.submit_keyframe("A", 0, 0.0, pose_3x4, png_bytes)  # doctest: +SKIP
"""

from __future__ import annotations

import base64
import io
import logging
from typing import Any

import httpx
import numpy as np

from cae_lcd.core.errors import LCDError

__all__ = ["FleetClient", "FleetError"]

log = logging.getLogger(__name__)


class FleetError(LCDError):
    """The server refused a request; the message holds the HTTP status and the server's one-line reason."""


class FleetClient:
    """Calls the fleet server with one token.

    Args:
        base_url: e.g. ``http://127.0.0.1:8765`` (ignored when ``client`` is given).
        token: the admin token or a robot's token.
        client: an ``httpx.Client`` to use (e.g. FastAPI's ``TestClient``); None: a new one on ``base_url``.
        timeout: seconds per request.
    """

    def __init__(self, base_url: str, token: str, client: httpx.Client | None = None, timeout: float = 30.0) -> None:
        self._http = client if client is not None else httpx.Client(base_url=base_url, timeout=timeout)
        self._headers = {"Authorization": f"Bearer {token}"}

    def _call(self, method: str, path: str, body: dict[str, Any] | None = None,
              params: dict[str, Any] | None = None) -> Any:
        response = self._http.request(method, path, json=body, headers=self._headers, params=params)
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail")
            except ValueError:
                detail = response.text[:200]
            raise FleetError(f"{method} {path}: HTTP {response.status_code}: {detail}")
        return response.json()

    def register(self, name: str) -> str:
        """(Admin) registers robot ``name``; returns its token."""
        return self._call("POST", "/robots", {"name": name})["token"]

    def submit_keyframe(self, robot: str, keyframe: int, timestamp: float, pose: np.ndarray, image: bytes,
                        intrinsics: np.ndarray | None = None, depth: np.ndarray | None = None) -> bool:
        """Sends one keyframe: ``pose`` (3x4 or 4x4), ``image`` PNG/JPEG bytes, optional ``(3, 3)`` intrinsics and
        ``(H, W)`` depth map. Returns True when the server stored it, False for a retry it already had."""
        body: dict[str, Any] = {"keyframe": int(keyframe), "timestamp": float(timestamp),
                                "pose": np.asarray(pose, float).tolist(), "image": base64.b64encode(image).decode()}
        if intrinsics is not None:
            body["intrinsics"] = np.asarray(intrinsics, float).tolist()
        if depth is not None:
            buf = io.BytesIO()
            np.save(buf, np.asarray(depth, np.float32), allow_pickle=False)
            body["depth"] = base64.b64encode(buf.getvalue()).decode()
        return bool(self._call("POST", f"/robots/{robot}/keyframes", body)["stored"])

    def loops(self, robot: str) -> list[dict[str, Any]]:
        return self._call("GET", f"/robots/{robot}/loops")

    def poses(self, robot: str, wait: bool = False) -> dict[int, np.ndarray]:
        """Corrected keyframe poses: keyframe id -> ``(4, 4)`` camera-to-global pose (the latest solution;
        ``wait``: one that includes every keyframe acknowledged so far)."""
        rows = self._call("GET", f"/robots/{robot}/poses", params={"wait": wait})
        return {p["keyframe"]: np.array(p["pose"]) for p in rows}

    def overlaps(self) -> list[dict[str, Any]]:
        return self._call("GET", "/overlaps")

    def transforms(self, wait: bool = False) -> dict[str, np.ndarray]:
        """Robot -> ``(4, 4)`` map-to-global similarity matrix (``wait``: as for ``poses``)."""
        return {r: np.array(m) for r, m in self._call("GET", "/transforms", params={"wait": wait}).items()}

    # ------------------------------------------------------------------------------------ admin (the admin token)
    def reset(self, robot: str, keep_keyframes: bool = True) -> int:
        """(Admin) restarts the robot's recognition (releases a quarantined robot); returns the keyframes dropped."""
        return int(self._call("POST", f"/robots/{robot}/reset", {"keep_keyframes": keep_keyframes})["dropped"])

    def retire(self, robot: str, keep_keyframes: bool = True) -> int:
        """(Admin) revokes the robot's token; returns the keyframes dropped."""
        return int(self._call("POST", f"/robots/{robot}/retire", {"keep_keyframes": keep_keyframes})["dropped"])

    def rotate_token(self, robot: str) -> str:
        """(Admin) a new token for the robot (the old one revoked)."""
        return self._call("POST", f"/robots/{robot}/token")["token"]

    def set_anchor(self, robot: str) -> None:
        """(Admin) makes the robot's map frame the global frame."""
        self._call("PUT", "/anchor", {"name": robot})
