"""The fleet server's HTTP interface (FastAPI): ``create_app(state_dir, admin_token, conf)``; run it with uvicorn.

Every request carries ``Authorization: Bearer TOKEN``. The admin token (given at start, never stored) registers
robots; a robot's token (``NAME.SECRET``, returned once at registration, stored hashed) lets it write its own
keyframes and read. Bodies are JSON; images travel base64-encoded (PNG or JPEG bytes), a depth map as a base64 ``.npy``.

    POST /robots                       admin        {"name"} -> 201 {"name", "token"}
    POST /robots/{name}/keyframes      robot name   {"keyframe", "timestamp", "pose" (3x4 or 4x4), "image",
                                                     "intrinsics"?, "depth"?} -> {"robot", "keyframe", "stored"}
    GET  /robots/{name}/loops          robot name or admin   loop and overlap edges touching the robot
    GET  /robots/{name}/poses          robot name or admin   corrected keyframe poses in the global frame
    GET  /overlaps                     any robot or admin    accepted overlaps
    GET  /transforms                   any robot or admin    each merged robot's map-to-global similarity

State lives under ``state_dir`` (``fleet.sqlite``, ``fleet.store``). Errors: 400 a bad value (one line in
``detail``), 401 no or a wrong token, 403 another robot's data, 404 an unknown robot, 409 a taken name.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import io
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from fastapi import Depends, FastAPI, Header, HTTPException
from pydantic import BaseModel, Field

from core.conf import ConfigError

from .service import FleetService
from .store import SQLiteStore

__all__ = ["create_app", "KeyframeIn", "RobotIn"]

log = logging.getLogger(__name__)

ADMIN = "\0admin"  #: the caller name of the admin token


class RobotIn(BaseModel):
    name: str


class KeyframeIn(BaseModel):
    keyframe: int = Field(ge=0)
    timestamp: float
    pose: list[list[float]]  #: 3x4 or 4x4 camera-to-map pose in the robot's own map
    image: str  #: base64 PNG or JPEG bytes
    intrinsics: list[list[float]] | None = None  #: 3x3 camera matrix
    depth: str | None = None  #: base64 .npy of a (H, W) depth map, the image's size


def _decode_b64(text: str, what: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise HTTPException(400, f"{what} is not valid base64") from None


def _check_keyframe(body: KeyframeIn) -> None:
    """Decodes the image (and depth) and checks shapes; raises HTTP 400 with one line."""
    raw = np.frombuffer(_decode_b64(body.image, "image"), np.uint8)
    image = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if image is None:
        raise HTTPException(400, "image is not a readable PNG or JPEG")
    if body.intrinsics is not None and np.asarray(body.intrinsics).shape != (3, 3):
        raise HTTPException(400, "intrinsics must be a 3x3 matrix")
    if body.depth is not None:
        try:
            depth = np.load(io.BytesIO(_decode_b64(body.depth, "depth")), allow_pickle=False)
        except (OSError, ValueError):
            raise HTTPException(400, "depth is not a .npy array") from None
        if depth.shape != image.shape[:2]:
            raise HTTPException(400, f"depth must be {image.shape[:2]} like the image; got {depth.shape}")


def create_app(state_dir: str | Path, admin_token: str, conf: dict[str, Any] | None = None) -> FastAPI:
    """The fleet server over the state in ``state_dir`` (created if missing, continued if present).

    Args:
        state_dir: folder of the server's state.
        admin_token: the token that registers robots (not stored).
        conf: overrides of ``FleetService.default_conf``.

    Raises:
        ConfigError: an empty admin token or a bad conf. DatabaseError: a damaged or foreign state file.
    """
    if not admin_token:
        raise ConfigError("the admin token must not be empty")
    service = FleetService(SQLiteStore(Path(state_dir) / "fleet.sqlite"), conf)
    app = FastAPI(title="cae-lcd fleet server")
    app.state.service = service

    def caller(authorization: str = Header(default="")) -> str:
        token = authorization.removeprefix("Bearer ").strip()
        if token and hmac.compare_digest(token.encode(), admin_token.encode()):
            return ADMIN
        name = token.split(".", 1)[0]
        if not name or not service.authenticate(name, token):
            raise HTTPException(401, "missing or wrong token")
        return name

    def owner_or_admin(name: str, who: str) -> None:
        if name not in service.store.robots():
            raise HTTPException(404, f"no robot {name!r}")
        if who not in (name, ADMIN):
            raise HTTPException(403, f"this token cannot access robot {name!r}")

    @app.post("/robots", status_code=201)
    def register(body: RobotIn, who: str = Depends(caller)) -> dict[str, str]:
        if who != ADMIN:
            raise HTTPException(403, "only the admin token registers robots")
        if body.name in service.store.robots():
            raise HTTPException(409, f"robot {body.name!r} is already registered")
        try:
            token = service.register(body.name)
        except ConfigError as err:
            raise HTTPException(400, str(err)) from None
        return {"name": body.name, "token": token}

    @app.post("/robots/{name}/keyframes")
    def submit(name: str, body: KeyframeIn, who: str = Depends(caller)) -> dict[str, Any]:
        owner_or_admin(name, who)
        if who != name:
            raise HTTPException(403, "only the robot itself submits its keyframes")
        _check_keyframe(body)
        try:
            stored = service.submit_keyframe(name, body.keyframe, body.timestamp, np.asarray(body.pose))
        except ConfigError as err:
            raise HTTPException(400, str(err)) from None
        return {"robot": name, "keyframe": body.keyframe, "stored": stored}

    @app.get("/robots/{name}/loops")
    def loops(name: str, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return [{"kind": e.kind, "a": [e.robot_a, e.keyframe_a], "b": [e.robot_b, e.keyframe_b],
                 "relative": e.relative.matrix().tolist(), "score": e.score}
                for e in service.store.edges(robot=name) if e.kind != "odometry"]

    @app.get("/robots/{name}/poses")
    def poses(name: str, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return service.poses(name)

    @app.get("/overlaps")
    def overlaps(who: str = Depends(caller)) -> list[dict[str, Any]]:
        return [{"robot_a": o.robot_a, "robot_b": o.robot_b, "transform": o.transform.matrix().tolist(),
                 "matches": o.matches, "accepted": o.accepted} for o in service.store.overlaps()]

    @app.get("/transforms")
    def transforms(who: str = Depends(caller)) -> dict[str, list[list[float]]]:
        service.optimize()
        return {robot: T.matrix().tolist() for robot, T in service.store.transforms().items()}

    return app
