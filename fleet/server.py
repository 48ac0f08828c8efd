"""The fleet server's HTTP interface (FastAPI): ``create_app(state_dir, admin_token, conf)``; run it with uvicorn.

Every request carries ``Authorization: Bearer TOKEN``. The admin token (given at start, never stored) registers
robots; a robot's token (``NAME.SECRET``, returned once at registration, stored hashed) lets it write its own
keyframes and read. Bodies are JSON; images travel base64-encoded (PNG or JPEG bytes), a depth map as a base64 ``.npy``.

    POST /robots                       admin        {"name"} -> 201 {"name", "token"}
    POST /robots/{name}/keyframes      robot name   {"keyframe", "timestamp", "pose" (3x4 or 4x4), "image",
                                                     "intrinsics"?, "depth"?} -> {"robot", "keyframe", "stored"}
    GET  /robots/{name}/loops          robot name or admin   loop and overlap edges touching the robot
    GET  /robots/{name}/poses?wait=    robot name or admin   corrected keyframe poses in the global frame
    GET  /overlaps                     any robot or admin    accepted overlaps
    GET  /transforms?wait=             any robot or admin    each merged robot's map-to-global similarity

Each keyframe runs through place recognition (``fleet.recognition``) before it is acknowledged; the pose graph is
re-solved in the background, and reads return the latest solution (``wait=true``: one that includes every keyframe
acknowledged so far). State lives under ``state_dir``: ``fleet.sqlite`` (robots, keyframes, edges) and
``robots/NAME/`` (each robot's HDF5 keyframe database and intrinsics). Errors: 400 a bad value (one line in
``detail``), 401 no or a wrong token, 403 another robot's data, 404 an unknown robot, 409 a taken name, 413 a body
or an image too large, 422 a body that does not fit the schema.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import io
import logging
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from fastapi import Depends, FastAPI, Header, HTTPException, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from core.conf import ConfigError
from core.errors import LCDError
from retrieval.descriptors import GlobalDescriptor

from .service import FleetService
from .stores import open_store
from .workers import create_recognizer

__all__ = ["create_app", "KeyframeIn", "RobotIn"]

log = logging.getLogger(__name__)

ADMIN = "\0admin"  #: the caller name of the admin token


class RobotIn(BaseModel):
    name: str


class KeyframeIn(BaseModel):
    keyframe: int = Field(ge=0)
    timestamp: float
    pose: list[list[float]] = Field(max_length=4)  #: 3x4 or 4x4 camera-to-map pose in the robot's own map
    image: str  #: base64 PNG or JPEG bytes
    intrinsics: list[list[float]] | None = Field(default=None, max_length=3)  #: 3x3 camera matrix
    depth: str | None = None  #: base64 .npy of a (H, W) depth map, the image's size


def _decode_b64(text: str, what: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise HTTPException(400, f"{what} is not valid base64") from None


def _decode_keyframe(body: KeyframeIn, max_pixels: int) -> tuple[np.ndarray, np.ndarray | None,
                                                                  np.ndarray | None]:
    """The image, intrinsics and depth of a keyframe body, checked; raises HTTP 400 (413: too large) with one line."""
    raw = np.frombuffer(_decode_b64(body.image, "image"), np.uint8)
    if raw.size >= 24 and raw[:8].tobytes() == b"\x89PNG\r\n\x1a\n":  # refuse a huge PNG before decoding it
        width, height = (int.from_bytes(raw[16:20].tobytes(), "big"), int.from_bytes(raw[20:24].tobytes(), "big"))
        if width * height > max_pixels:
            raise HTTPException(413, f"image has {width}x{height} pixels; at most {max_pixels} are accepted")
    image = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if image is None:
        raise HTTPException(400, "image is not a readable PNG or JPEG")
    if image.shape[0] * image.shape[1] > max_pixels:
        raise HTTPException(413, f"image has {image.shape[1]}x{image.shape[0]} pixels; at most {max_pixels} are "
                                 "accepted")
    K = None
    if body.intrinsics is not None:
        K = _matrix(body.intrinsics, (3, 3), "intrinsics")
    depth = None
    if body.depth is not None:
        try:
            depth = np.load(io.BytesIO(_decode_b64(body.depth, "depth")), allow_pickle=False)
        except (OSError, ValueError):
            raise HTTPException(400, "depth is not a .npy array") from None
        if depth.shape != image.shape[:2] or depth.dtype.kind not in "fiu":
            raise HTTPException(400, f"depth must be a numeric {image.shape[:2]} array like the image; got "
                                     f"{depth.dtype} {depth.shape}")
    return image, K, depth


def _matrix(value: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    """A finite float matrix of ``shape``; HTTP 400 otherwise."""
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise HTTPException(400, f"{what} must be a {'x'.join(map(str, shape))} matrix of numbers") from None
    if m.shape != shape or not np.isfinite(m).all():
        raise HTTPException(400, f"{what} must be a finite {'x'.join(map(str, shape))} matrix; got shape {m.shape}")
    return m


def _pose(value: list[list[float]]) -> np.ndarray:
    """A 3x4 or 4x4 pose; HTTP 400 otherwise."""
    rows = len(value)
    if rows not in (3, 4):
        raise HTTPException(400, f"pose must be a 3x4 or 4x4 matrix; got {rows} rows")
    return _matrix(value, (rows, 4), "pose")


def _size_limit(app: FastAPI, max_bytes: int) -> None:
    """Refuses request bodies over ``max_bytes`` (413) by their Content-Length, and bodies without one (411)."""

    @app.middleware("http")
    async def limit(request: Request, call_next: Any) -> Any:
        length = request.headers.get("content-length")
        if length is None and request.method in ("POST", "PUT", "PATCH"):
            return JSONResponse({"detail": "a request body needs a Content-Length"}, status_code=411)
        if length is not None and (not length.isdigit() or int(length) > max_bytes):
            return JSONResponse({"detail": f"request body over {max_bytes} bytes"}, status_code=413)
        return await call_next(request)


def create_app(state_dir: str | Path, admin_token: str, conf: dict[str, Any] | None = None,
               recognition: dict[str, Any] | None = None, recognize: bool = True,
               descriptor: GlobalDescriptor | None = None, store: str | None = None, workers: int = 1,
               ray_address: str | None = None) -> FastAPI:
    """The fleet server over the state in ``state_dir`` (created if missing, continued if present).

    Args:
        state_dir: folder of the server's state.
        admin_token: the token that registers robots (not stored).
        conf: overrides of ``FleetService.default_conf``.
        recognition: overrides of ``FleetRecognizer.default_conf``.
        recognize: False: no place recognition (keyframes are only acknowledged; edges come through the service).
        descriptor: an already built global descriptor to share (None: built once for this server).
        store: where robots, keyframes and edges live: a ``postgresql://`` URL or a SQLite file (None:
            ``state_dir/fleet.sqlite``; ``fleet.stores.open_store``).
        workers: > 1: robots sharded over that many Ray workers (``fleet.workers``); 1: in this process.
        ray_address: a Ray cluster for the workers (None: a local Ray when ``workers`` > 1).

    Raises:
        ConfigError: an empty admin token or a bad conf. DatabaseError: a damaged or foreign state file.
    """
    if not admin_token:
        raise ConfigError("the admin token must not be empty")
    recognizer = create_recognizer(state_dir, recognition, descriptor, workers, ray_address) if recognize else None
    try:
        service = FleetService(open_store(state_dir, store), conf, recognizer)
    except BaseException:
        if recognizer is not None:
            recognizer.close()
        raise
    app = FastAPI(title="cae-lcd fleet server", on_shutdown=[service.close])
    app.state.service = service
    _size_limit(app, int(service.conf["limits"]["max_request_mb"] * 2**20))
    app.add_exception_handler(RequestValidationError, _one_line_422)
    caller, owner_or_admin = _auth(service, admin_token)
    _write_routes(app, service, caller, owner_or_admin)
    _read_routes(app, service, caller, owner_or_admin)
    return app


async def _one_line_422(request: Request, exc: RequestValidationError) -> JSONResponse:
    """Schema errors as one line (``"body.keyframe: Input should be greater than or equal to 0"``), like the others;
    the details stay in ``errors``."""
    lines = [".".join(str(p) for p in e.get("loc", ())) + ": " + str(e.get("msg", "invalid")) for e in exc.errors()]
    return JSONResponse(status_code=422, content={"detail": "; ".join(lines) or "invalid request",
                                                  "errors": jsonable_encoder(exc.errors())})


def _auth(service: FleetService, admin_token: str) -> tuple[Callable[..., str], Callable[[str, str], None]]:
    """The ``caller`` dependency (token -> robot name or ``ADMIN``; 401) and the ``owner_or_admin`` check (404, 403).
    """

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

    return caller, owner_or_admin


def _write_routes(app: FastAPI, service: FleetService, caller: Callable[..., str],
                  owner_or_admin: Callable[[str, str], None]) -> None:
    """``POST /robots`` and ``POST /robots/{name}/keyframes``."""
    max_pixels = service.conf["limits"]["max_image_pixels"]

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
        pose = _pose(body.pose)
        image, K, depth = _decode_keyframe(body, max_pixels)
        try:
            stored = service.submit_keyframe(name, body.keyframe, body.timestamp, pose, image, K, depth)
        except LCDError as err:
            raise HTTPException(400, str(err)) from None
        return {"robot": name, "keyframe": body.keyframe, "stored": stored}


def _read_routes(app: FastAPI, service: FleetService, caller: Callable[..., str],
                 owner_or_admin: Callable[[str, str], None]) -> None:
    """Loops, poses, overlaps and transforms."""

    @app.get("/robots/{name}/loops")
    def loops(name: str, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return [{"kind": e.kind, "a": [e.robot_a, e.keyframe_a], "b": [e.robot_b, e.keyframe_b],
                 "relative": e.relative.matrix().tolist(), "score": e.score}
                for e in service.store.edges(robot=name) if e.kind != "odometry"]

    @app.get("/robots/{name}/poses")
    def poses(name: str, wait: bool = False, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return service.poses(name, wait)

    @app.get("/overlaps")
    def overlaps(who: str = Depends(caller)) -> list[dict[str, Any]]:
        return [{"robot_a": o.robot_a, "robot_b": o.robot_b, "transform": o.transform.matrix().tolist(),
                 "matches": o.matches, "accepted": o.accepted} for o in service.store.overlaps()]

    @app.get("/transforms")
    def transforms(wait: bool = False, who: str = Depends(caller)) -> dict[str, list[list[float]]]:
        service.optimize(wait)
        return {robot: T.matrix().tolist() for robot, T in service.store.transforms().items()}

