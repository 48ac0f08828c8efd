"""The fleet server's HTTP interface (FastAPI): ``create_app(state_dir, admin_token, conf)``; run it with uvicorn.

Every request carries ``Authorization: Bearer TOKEN``. The admin token (given at start, never stored) registers
robots; a robot's token (``NAME.SECRET``, returned once at registration, stored hashed) lets it write its own
keyframes and read. Bodies are JSON (unknown fields and wrong types refused); images travel base64-encoded (PNG, JPEG,
TIFF, BMP or WebP bytes, their size checked from the header before decoding), a depth map as a base64 ``.npy``
(its declared shape and dtype checked before it is read).

    POST /robots                       admin        {"name"} -> 201 {"name", "token"}
    POST /robots/{name}/keyframes      robot name   {"keyframe", "timestamp", "pose" (3x4 or 4x4), "image",
                                                     "intrinsics"?, "depth"?} -> {"robot", "keyframe", "stored"}
    GET  /robots/{name}/loops          robot name or admin   loop and overlap edges touching the robot
    GET  /robots/{name}/poses?wait=    robot name or admin   corrected keyframe poses in the global frame
    GET  /overlaps                     robot or admin        accepted overlaps (a robot: those involving it)
    GET  /transforms?wait=             robot or admin        merged robots' map-to-global similarities (robot: its own)
    GET  /robots/{name}/trajectory     robot name or admin   ?format=tum|kitti: corrected trajectory (cae_lcd.fleet.export)
    GET  /map                          none (holds no data)  live map page polling the routes above (cae_lcd.fleet.map_page)
    POST /robots/{name}/reset          admin                 {"keep_keyframes"}: recognition restarted, keyframes kept
                                                             or dropped (releases a quarantined robot)
    POST /robots/{name}/retire         admin                 {"keep_keyframes"}: token revoked, keyframes kept/dropped
    POST /robots/{name}/token          admin                 -> 201 {"name", "token"}: a new token, the old revoked
    PUT  /anchor                       admin                 {"name"}: that robot's map becomes the global frame

The global frame is the map of the anchor: the robot of the fleet's first acknowledged keyframe, stored, or the one
the admin names; robots that join later or speak after a silence are merged into it, never the reverse.

Each keyframe runs through place recognition (``cae_lcd.fleet.recognition``) before it is acknowledged; the pose graph is
re-solved in the background, and reads return the latest solution (``wait=true``: one that includes every keyframe
acknowledged so far). State lives under ``state_dir``: ``fleet.sqlite`` (robots, keyframes, edges) and
``robots/NAME/`` (each robot's HDF5 keyframe database and intrinsics). Errors (``Problem``: one line in
``detail``): 400 a bad value, 401 no or a wrong token, 403 a robot's token where the admin's is needed, 404 an
unknown robot or another robot's (alike, so names cannot be probed), 408 a body sent too slowly, 409 a taken name or a
retry of an acknowledged keyframe with other content, 413 a body (bytes or JSON values) or an image too large, 422 a
body that does not fit the schema (``SchemaProblem``: one line, the first errors; unknown fields are one error), 429
too many failed authentications from one address (refused before any hash), a robot's keyframes sent at once
beyond ``limits.keyframes_in_flight`` (refused before decoding), token hashes beyond the server's or the name's
budget (``limits.token_hashes_per_s``, ``robot_hashes_per_s``: before the hash) or request bodies in memory beyond
``limits.max_buffered_mb`` (``cae_lcd.fleet.limits``), 503 a quarantined robot (its files could not be read at start-up:
``cae_lcd.fleet.recognition``; the others are served).
"""

from __future__ import annotations

import base64
import binascii
import hmac
import itertools
import logging
from pathlib import Path
from typing import Annotated, Any, Callable

import numpy as np
from fastapi import Depends, FastAPI, Header, HTTPException, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from cae_lcd.core.checks import MAX_FRAME_ID, check_intrinsics, check_rigid_pose, decode_depth
from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ConflictError, ImageError, LCDError
from cae_lcd.core.images import decode_image, image_header, too_large
from retrieval.descriptors import GlobalDescriptor

from .map_page import map_router
from .limits import AuthThrottle, BodyLimit, HashBudget, InFlight
from .service import ROBOT_NAME, FleetService
from .stores import open_store
from .workers import create_recognizer

__all__ = ["create_app", "KeyframeIn", "RobotIn", "ResetIn", "Problem", "SchemaProblem"]

log = logging.getLogger(__name__)

ADMIN = "\0admin"  #: the caller name of the admin token
MAX_B64 = 48 * 2**20  #: longest base64 string a field may hold (the body limit is usually lower)
MAX_TOKEN = 256  #: longest Authorization header value looked at
MAX_ERRORS = 20  #: schema errors reported in a 422 (the first ones)


def _a_number(value: Any) -> Any:
    """Refuses text and booleans where a number is expected ("16" is not 16); 16.0 stays 16, as JSON Schema says."""
    if isinstance(value, (str, bytes, bool)):
        raise ValueError("must be a JSON number, not a string or a boolean")
    return value


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # unknown fields and "16" for an int are refused

    @model_validator(mode="before")
    @classmethod
    def _known_fields(cls, data: Any) -> Any:
        """Refuses unknown fields in one error (pydantic would make one per field: a body of 2 million unknown keys
        became a 180 MB answer after 40 s and 3.7 GB)."""
        unknown = [k for k in data if k not in cls.model_fields] if isinstance(data, dict) else []
        if unknown:
            raise ValueError(f"unknown fields {', '.join(repr(str(k)[:40]) for k in unknown[:5])}"
                             + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""))
        return data


class RobotIn(_Strict):
    name: str = Field(pattern=f"^{ROBOT_NAME}$")  #: 1 to 64 letters, digits, _ and -


#: a matrix row of exactly its length, bounded before its items are validated (one error, not one per item): the
#: schema says what the server enforces (a 3x0 pose was schema-valid, then 400)
Row3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Row4 = Annotated[list[float], Field(min_length=4, max_length=4)]


class KeyframeIn(_Strict):
    keyframe: Annotated[int, BeforeValidator(_a_number)] = Field(ge=0, lt=MAX_FRAME_ID, strict=False)  #: increasing
    timestamp: float  #: seconds, finite, never less than the robot's previous keyframe's
    pose: list[Row4] = Field(min_length=3, max_length=4)  #: 3x4 or 4x4 rigid camera-to-map pose
    image: str = Field(max_length=MAX_B64)  #: base64 PNG, JPEG, TIFF, BMP or WebP bytes
    intrinsics: list[Row3] | None = Field(default=None, max_length=3)  #: 3x3 camera matrix
    depth: str | None = Field(default=None, max_length=MAX_B64)  #: base64 .npy of a (H, W) depth map, the image's size


class ResetIn(_Strict):
    keep_keyframes: bool = True  #: keep the robot's stored keyframes (poses, edges) in the map; false: drop them


class Problem(BaseModel):
    """Every refusal: one line saying why."""

    detail: str


class SchemaProblem(Problem):
    """A body, path or query that does not fit the schema (422): one line, and pydantic's first errors
    (``MAX_ERRORS``)."""

    errors: list[dict[str, Any]]


_PROBLEMS: dict[int | str, dict[str, Any]] = {
    400: {"model": Problem, "description": "a bad value"},
    401: {"model": Problem, "description": "no or a wrong token"},
    403: {"model": Problem, "description": "the admin token is needed"},
    404: {"model": Problem, "description": "no such robot (or not this token's)"},
    408: {"model": Problem, "description": "the body came too slowly"},
    409: {"model": Problem, "description": "a taken name, or a retry with other content"},
    413: {"model": Problem, "description": "a body or an image too large"},
    503: {"model": Problem, "description": "the robot is quarantined: its files could not be read (an admin resets "
                                            "or drops it)"},
    422: {"model": SchemaProblem, "description": "does not fit the schema"},
    429: {"model": Problem, "description": "too many failed authentications from this address, token checks now "
                                            "(the server's or this name's budget), keyframes of this robot at once, "
                                            "or request bodies from this address in memory"},
}


def _decode_b64(text: str, what: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise HTTPException(400, f"{what} is not valid base64") from None


def _decode_keyframe(body: KeyframeIn, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                                  np.ndarray | None]:
    """The pose, image, intrinsics and depth of a keyframe body, each checked before it is decoded or used; raises
    HTTP 400 (413: too large) with one line."""
    try:
        pose = check_rigid_pose(body.pose, "pose")
        K = None if body.intrinsics is None else check_intrinsics(body.intrinsics)
    except ConfigError as err:
        raise HTTPException(400, str(err)) from None
    raw = _decode_b64(body.image, "image")
    header = image_header(raw)
    if header is not None and header[1] * header[2] > max_pixels:
        raise HTTPException(413, too_large(header, max_pixels))
    try:
        image = decode_image(raw, "image", max_pixels, known_header=True)
        depth = None if body.depth is None else decode_depth(_decode_b64(body.depth, "depth"), image.shape[:2])
    except (ImageError, ConfigError) as err:
        raise HTTPException(400, str(err)) from None
    return pose, image, K, depth


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
            ``state_dir/fleet.sqlite``; ``cae_lcd.fleet.stores.open_store``).
        workers: > 1: robots sharded over that many Ray workers (``cae_lcd.fleet.workers``); 1: in this process.
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
    limits = service.conf["limits"]
    app.add_middleware(BodyLimit, max_bytes=int(limits["max_request_mb"] * 2**20),
                       timeout_s=limits["body_timeout_s"], max_values=limits["max_json_values"],
                       max_buffered=int(limits["max_buffered_mb"] * 2**20))
    app.add_exception_handler(RequestValidationError, _one_line_422)
    throttle = AuthThrottle(limits["auth_failures"], limits["auth_window_s"])
    budget = HashBudget(limits["token_hashes_per_s"], limits["token_hash_burst"], limits["robot_hashes_per_s"],
                        limits["robot_hash_burst"])
    caller, owner_or_admin = _auth(service, admin_token, throttle, budget)
    _write_routes(app, service, caller, owner_or_admin)
    _read_routes(app, service, caller, owner_or_admin)
    _admin_routes(app, service, caller)
    app.include_router(map_router(service, caller, owner_or_admin, _PROBLEMS))  # GET /map, GET /robots/{name}/trajectory
    return app


async def _one_line_422(request: Request, exc: RequestValidationError) -> JSONResponse:
    """Schema errors as one line (``"body.keyframe: Input should be greater than or equal to 0"``), like the others;
    the details stay in ``errors`` (``SchemaProblem``)."""
    first = list(itertools.islice(exc.errors(), MAX_ERRORS))
    lines = [".".join(str(p) for p in e.get("loc", ())) + ": " + str(e.get("msg", "invalid")) for e in first]
    errors = [{k: v for k, v in e.items() if k in ("type", "loc", "msg")} for e in first]
    return JSONResponse(status_code=422, content={"detail": "; ".join(lines)[:2000] or "invalid request",
                                                  "errors": jsonable_encoder(errors)})


def _auth(service: FleetService, admin_token: str, throttle: AuthThrottle,
          budget: HashBudget) -> tuple[Callable[..., str], Callable[[str, str], None]]:
    """The ``caller`` dependency (token -> robot name or ``ADMIN``; 401; 429 before any hash after too many failures
    from the address, or past the server's or the name's hash budget; a token verified before needs no hash) and the
    ``owner_or_admin`` check (404 alike for a missing robot and another robot's; 503 a quarantined robot)."""

    def caller(request: Request, authorization: str = Header(default="", max_length=MAX_TOKEN)) -> str:
        token = authorization.removeprefix("Bearer ").strip()
        if token and hmac.compare_digest(token.encode(), admin_token.encode()):
            return ADMIN
        name = token.split(".", 1)[0]
        if name and service.known_token(name, token):
            return name
        client = request.client.host if request.client else "?"
        if throttle.blocked(client):
            raise HTTPException(429, "too many failed authentications from this address; wait and retry")
        if name and not budget.take(name[:64]):
            raise HTTPException(429, "too many token checks at the moment; retry in a second")
        if not name or not service.authenticate(name, token):
            throttle.failed(client)
            raise HTTPException(401, "missing or wrong token")
        return name

    def owner_or_admin(name: str, who: str) -> None:
        if who not in (name, ADMIN) or not service.has_robot(name):
            raise HTTPException(404, f"no robot {name!r}")
        if name in service.quarantined:
            raise HTTPException(503, f"robot {name!r} is quarantined: {service.quarantined[name]}; an admin resets "
                                     "it (POST /robots/{name}/reset)")

    return caller, owner_or_admin


def _write_routes(app: FastAPI, service: FleetService, caller: Callable[..., str],
                  owner_or_admin: Callable[[str, str], None]) -> None:
    """``POST /robots`` and ``POST /robots/{name}/keyframes``."""
    max_pixels = service.conf["limits"]["max_image_pixels"]
    in_flight = InFlight(service.conf["limits"]["keyframes_in_flight"])

    @app.post("/robots", status_code=201, responses=_PROBLEMS)
    def register(body: RobotIn, who: str = Depends(caller)) -> dict[str, str]:
        if who != ADMIN:
            raise HTTPException(403, "only the admin token registers robots")
        try:
            token = service.register(body.name)
        except ConfigError as err:
            raise HTTPException(409 if "already registered" in str(err) else 400, str(err)) from None
        return {"name": body.name, "token": token}

    @app.post("/robots/{name}/keyframes", responses=_PROBLEMS)
    def submit(name: str, body: KeyframeIn, who: str = Depends(caller)) -> dict[str, Any]:
        if who != name:  # the admin reads, but only the robot itself writes its keyframes
            raise HTTPException(404, f"no robot {name!r}")
        owner_or_admin(name, who)
        if not in_flight.acquire(name):  # before decoding: a queued keyframe would hold its decoded image
            raise HTTPException(429, f"robot {name!r} has {in_flight.limit} keyframes in flight; retry once answered")
        try:
            pose, image, K, depth = _decode_keyframe(body, max_pixels)
            stored = service.submit_keyframe(name, body.keyframe, body.timestamp, pose, image, K, depth)
        except ConflictError as err:
            raise HTTPException(409, str(err)) from None
        except LCDError as err:
            raise HTTPException(400, str(err)) from None
        finally:
            in_flight.release(name)
        return {"robot": name, "keyframe": body.keyframe, "stored": stored}


def _read_routes(app: FastAPI, service: FleetService, caller: Callable[..., str],
                 owner_or_admin: Callable[[str, str], None]) -> None:
    """Loops, poses, overlaps and transforms."""

    @app.get("/robots/{name}/loops", responses=_PROBLEMS)
    def loops(name: str, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return [{"kind": e.kind, "a": [e.robot_a, e.keyframe_a], "b": [e.robot_b, e.keyframe_b],
                 "relative": e.relative.matrix().tolist(), "score": e.score}
                for e in service.store.edges(robot=name) if e.kind != "odometry"]

    @app.get("/robots/{name}/poses", responses=_PROBLEMS)
    def poses(name: str, wait: bool = False, who: str = Depends(caller)) -> list[dict[str, Any]]:
        owner_or_admin(name, who)
        return service.poses(name, wait)

    @app.get("/overlaps", responses=_PROBLEMS)
    def overlaps(who: str = Depends(caller)) -> list[dict[str, Any]]:
        """Accepted overlaps: every one for the admin token, those involving the robot for a robot's."""
        return [{"robot_a": o.robot_a, "robot_b": o.robot_b, "transform": o.transform.matrix().tolist(),
                 "matches": o.matches, "accepted": o.accepted} for o in service.store.overlaps()
                if who in (ADMIN, o.robot_a, o.robot_b)]

    @app.get("/transforms", responses=_PROBLEMS)
    def transforms(wait: bool = False, who: str = Depends(caller)) -> dict[str, list[list[float]]]:
        """Each merged robot's map-to-global transform for the admin token; a robot's own for a robot's."""
        service.optimize(wait)
        return {robot: T.matrix().tolist() for robot, T in service.store.transforms().items()
                if who in (ADMIN, robot)}


def _admin_routes(app: FastAPI, service: FleetService, caller: Callable[..., str]) -> None:
    """What a fleet operator does with the admin token (each audited in the log by ``FleetService``): reset or retire
    a robot, rotate its token, name the anchor."""

    def admin_on(name: str, who: str) -> None:
        if who != ADMIN:
            raise HTTPException(403, "only the admin token may do this")
        if not service.has_robot(name):
            raise HTTPException(404, f"no robot {name!r}")

    def run(action: Callable[[], Any]) -> Any:
        try:
            return action()
        except ConflictError as err:
            raise HTTPException(409, str(err)) from None
        except LCDError as err:
            raise HTTPException(400, str(err)) from None

    @app.post("/robots/{name}/reset", responses=_PROBLEMS)
    def reset(name: str, body: ResetIn, who: str = Depends(caller)) -> dict[str, Any]:
        """Restarts the robot's recognition from nothing (its folder moved aside; a quarantined robot is released);
        its stored keyframes kept or dropped."""
        admin_on(name, who)
        return {"robot": name, "dropped": run(lambda: service.reset(name, body.keep_keyframes))}

    @app.post("/robots/{name}/retire", responses=_PROBLEMS)
    def retire(name: str, body: ResetIn, who: str = Depends(caller)) -> dict[str, Any]:
        """Revokes the robot's token (its name stays taken); its stored keyframes kept or dropped."""
        admin_on(name, who)
        return {"robot": name, "dropped": run(lambda: service.retire(name, body.keep_keyframes))}

    @app.post("/robots/{name}/token", status_code=201, responses=_PROBLEMS)
    def rotate(name: str, who: str = Depends(caller)) -> dict[str, str]:
        """A new token for the robot (the old one revoked at once; a retired robot is active again)."""
        admin_on(name, who)
        return {"name": name, "token": run(lambda: service.rotate_token(name))}

    @app.put("/anchor", responses=_PROBLEMS)
    def anchor(body: RobotIn, who: str = Depends(caller)) -> dict[str, str]:
        """Makes the robot's map frame the global frame: every map is re-expressed in it."""
        admin_on(body.name, who)
        run(lambda: service.set_anchor(body.name))
        return {"anchor": body.name}
