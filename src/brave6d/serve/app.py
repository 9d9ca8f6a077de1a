"""The HTTP + WebSocket API of the render server (FastAPI; OpenAPI schema at ``/openapi.json``,
interactive docs at ``/docs``).

Endpoints (all JSON unless noted; errors are ``{"error": message, "field": where, "status": code}``):

=========================================  =====================================================
``GET  /health``                            liveness, device, open episodes
``GET  /bundle``                            scene name, intrinsics, render defaults, objects
                                            (BOP ids, ``world_T_obj``, diameters, symmetries),
                                            collision boxes, workspace, holdout views, versions
``GET  /bundle/models/{obj_id}``            the object model (BOP PLY, millimetres)
``POST /render``                            free view: the splat at a pose (``{pose, scene?, width?,
                                            height?, rgb, depth}``), no episode, no object poses;
                                            any bundle, with or without objects
``POST /episodes``                          reset: new episode, returns the first observation
``GET  /episodes``                          the episodes this server knows
``GET  /episodes/{id}``                     state: pose, counters, target (no images)
``POST /episodes/{id}/set_pose``            teleport to an absolute pose
``POST /episodes/{id}/move``                move with a twist for a duration
``POST /episodes/{id}/estimates``           submit the final pose estimates (current camera
                                            frame) and end the episode
``POST /episodes/{id}/close``               close, returns the episode's totals
``GET  /episodes/{id}/observation.npz``     the last observation as NumPy ``.npz`` (binary:
                                            rgb uint8, depth float32 metres, K, poses, ids)
``WS   /episodes/{id}/ws``                  the same actions as JSON messages
``GET  /viewer/``                           the browser viewer
=========================================  =====================================================

Poses are ``world_T_cam`` (OpenCV camera axes, metres), given as a 4x4 matrix, as
``position`` + ``quaternion_wxyz``, or as ``look_at`` ``{eye, target, up}``. Numbers must be
finite and within the bounds of :mod:`brave6d.serve.limits` (coordinates within 1 km, velocities within
10 m/s and 2 pi rad/s per component, images within 1280 x 960); a matrix must be rigid up to
rounding (``|R^T R - I| <= 1e-3``, ``det R > 0``, bottom row 0 0 0 1; it is then projected onto the
nearest rotation: the one rule for poses made elsewhere, :func:`brave6d.core.transforms.nearest_rigid`);
a quaternion must have norm 1 within 1e-3.

Observations carry RGB (``png`` or ``jpeg``, base64) and depth (``f32``: base64 of
little-endian float32, row-major, metres, 0 = no data), the intrinsics ``K``, ``world_T_cam``
and, per object instance, ``cam_T_obj`` (metres; BOP's ``cam_R_m2c``/``cam_t_m2c`` in mm
follow from it) and its visible fraction. Every response reports ``timings_ms`` (``render``:
the rasterizer call; ``total``: the whole request) and the header ``X-Render-Ms``.

A free view (``POST /render``) is a look at the scene without an episode (a new scan before anyone
annotates it): the same pose forms, image sizes, encodings, timeout and body limit as a reset, and its
pose must be free as a reset's ``start`` must be (inside the workspace, clear of the collision boxes;
else 422 naming ``pose``). Its observation lists no objects: it is the splat and nothing the score uses.

Robustness: request bodies (and WebSocket messages) are limited to ``max_body_bytes``
(413) and read by the one JSON reader, whose every check is linear in the input (one over 64 KiB
on a thread of its own, off the event loop); each action runs under ``request_timeout_s`` (504; a
timed-out action is withdrawn before it changes anything), is withdrawn the same way when its
client disconnects (its render skipped, not drawn) and at shutdown (503):
:mod:`brave6d.serve.inflight`; malformed JSON is 400, invalid values 422, unknown episodes 404,
closed or busy episodes 409, too many open episodes 429; unexpected errors are 500 and the
server keeps serving. A step (``set_pose``/``move``) is one transaction: its observation,
counters and log line are computed first and committed together, so a failed request changes
neither the episode nor its log.

Modes (:mod:`brave6d.serve.modes`): in ``scored`` mode (the default) no reply carries an object's
pose, box, visible fraction or placement (observations list no objects, ``GET /bundle`` no
``world_T_obj``, the ``.npz`` no ``cam_T_obj``); ``training`` serves them all. Every step reply,
``GET /health`` and ``GET /bundle`` say which mode runs.

Access: the ``Host`` header must name 127.0.0.1, localhost or [::1] (any port) or one of
``allowed_hosts`` (else 400: a DNS-rebinding page cannot reach the API); with ``token``, every
request but the viewer's static files and the docs needs ``Authorization: Bearer <token>`` or
``?token=<token>`` (else 401).
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import logging
import secrets
import time
import weakref
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from starlette.datastructures import Headers, QueryParams
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.websockets import WebSocketClose

from brave6d.core.errors import BraveError, NonRigidTransformError, validation_error_field
from brave6d.core.json_input import JsonInputError, JsonLimits, parse_json
from brave6d.core.transforms import look_at, make_transform, nearest_rigid, quat_wxyz_to_matrix, unit_quaternion
from brave6d.serve.bundle import Bundle, load_bundle
from brave6d.serve.limits import (
    MAX_ANGULAR_SPEED_RAD_S,
    MAX_COORD_M,
    MAX_HEIGHT,
    MAX_LINEAR_SPEED_M_S,
    MAX_MOVE_DURATION_S,
    MAX_WIDTH,
    MIN_SIZE,
    ServerLimits,
)
from brave6d.serve.catalog import SceneCatalog, warm_scene
from brave6d.serve.log_digest import LogKey
from brave6d.serve.modes import SCORED, public_bundle
from brave6d.serve.episode_manager import EpisodeManager
from brave6d.serve.episodes import (
    ActionResult,
    EpisodeError,
    EpisodeNotFound,
    RenderedView,
    SceneServer,
)
from brave6d.serve.inflight import InFlight
from brave6d.serve.schema import EncodedImage, ErrorMessage, ObservationMessage, RenderMessage, StepMessage

log = logging.getLogger(__name__)

VIEWER_DIR = Path(__file__).resolve().parent / "viewer"

# ----------------------------------------------------------------------------- request models
Finite = Annotated[float, Field(allow_inf_nan=False)]
Coord = Annotated[float, Field(ge=-MAX_COORD_M, le=MAX_COORD_M, allow_inf_nan=False)]
Vec3 = Annotated[list[Coord], Field(min_length=3, max_length=3, description=f"metres, |x| <= {MAX_COORD_M:g}")]
QuatComponent = Annotated[float, Field(ge=-2.0, le=2.0, allow_inf_nan=False)]
Quat = Annotated[list[QuatComponent], Field(min_length=4, max_length=4)]
Row4 = Annotated[list[Coord], Field(min_length=4, max_length=4)]
Speed = Annotated[float, Field(ge=-MAX_LINEAR_SPEED_M_S, le=MAX_LINEAR_SPEED_M_S, allow_inf_nan=False)]
Linear = Annotated[list[Speed], Field(min_length=3, max_length=3,
                                      description=f"m/s, |v_i| <= {MAX_LINEAR_SPEED_M_S:g}")]
Turn = Annotated[float, Field(ge=-MAX_ANGULAR_SPEED_RAD_S, le=MAX_ANGULAR_SPEED_RAD_S, allow_inf_nan=False)]
Angular = Annotated[list[Turn], Field(min_length=3, max_length=3,
                                      description=f"rad/s, |w_i| <= {MAX_ANGULAR_SPEED_RAD_S:.4g}")]
Duration = Annotated[float, Field(gt=0, le=MAX_MOVE_DURATION_S, allow_inf_nan=False)]
RequestId = Annotated[str, Field(max_length=256)] | Annotated[int, Field(ge=-(2**63), lt=2**63)]
Mat4 = Annotated[list[Row4], Field(min_length=4, max_length=4)]
AgentName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:+\- ]+$",
                                 description="agent name for the leaderboard (letters, digits, _ . : + - space)")]
MAX_ESTIMATES = 100
Width = Annotated[int, Field(ge=MIN_SIZE, le=MAX_WIDTH, description=f"pixels, {MIN_SIZE}..{MAX_WIDTH}")]
Height = Annotated[int, Field(ge=MIN_SIZE, le=MAX_HEIGHT, description=f"pixels, {MIN_SIZE}..{MAX_HEIGHT}")]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class LookAt(_Strict):
    """An OpenCV camera at ``eye`` looking at ``target``; image-up is ``up`` projected (default world +z)."""

    eye: Vec3
    target: Vec3
    up: Vec3 = [0.0, 0.0, 1.0]


class PoseIn(_Strict):
    """``world_T_cam``: exactly one of ``world_T_cam`` (4x4), ``position`` + ``quaternion_wxyz``, ``look_at``."""

    world_T_cam: Mat4 | None = None
    position: Vec3 | None = None
    quaternion_wxyz: Quat | None = None
    look_at: LookAt | None = None

    @model_validator(mode="after")
    def _one_form(self) -> PoseIn:
        forms = [self.world_T_cam is not None, self.position is not None or self.quaternion_wxyz is not None,
                 self.look_at is not None]
        if sum(forms) != 1:
            raise ValueError("give exactly one of: world_T_cam (4x4), position + quaternion_wxyz, look_at")
        if forms[1] and (self.position is None or self.quaternion_wxyz is None):
            raise ValueError("position and quaternion_wxyz go together")
        self.matrix()  # raises ValueError with the reason
        return self

    def matrix(self) -> np.ndarray:
        """The rigid ``world_T_cam``; ``ValueError`` with the reason when the input does not make one."""
        T = self._matrix()
        if not np.all(np.isfinite(T)):
            raise ValueError("the pose is not finite (its values are too large or too small)")
        return T

    def _matrix(self) -> np.ndarray:
        if self.world_T_cam is not None:
            try:
                return nearest_rigid(self.world_T_cam, "world_T_cam")[0]
            except NonRigidTransformError as exc:
                raise ValueError(f"not a rigid transform: {exc}") from None
        if self.look_at is not None:
            try:
                return look_at(self.look_at.eye, self.look_at.target, self.look_at.up)
            except NonRigidTransformError as exc:
                raise ValueError(str(exc)) from None
        try:
            q = unit_quaternion(self.quaternion_wxyz, "quaternion_wxyz", "w, x, y, z")
        except NonRigidTransformError as exc:
            raise ValueError(str(exc)) from None
        return make_transform(quat_wxyz_to_matrix(q), self.position)


class ObsOptions(_Strict):
    rgb: Literal["png", "jpeg", "none"] = Field("png", description="RGB encoding (base64); 'none' omits it")
    depth: Literal["f32", "none"] = Field("f32", description="'f32': base64 of little-endian float32 metres")


class ViewRequest(ObsOptions):
    """What a request for a view names besides its pose: the scene, the image size (the bundle's
    camera scaled to it; omitted: the bundle's render default) and the encodings."""

    scene: Annotated[str, Field(max_length=128)] | Annotated[int, Field(ge=0, lt=2**31)] | None = Field(
        None, description="scene name or BOP scene_id (GET /scenes); may be omitted when the server has one scene")
    width: Width | None = None
    height: Height | None = None


class RenderRequest(ViewRequest):
    """A free view: the splat at ``pose``, no episode (any bundle, with or without objects)."""

    pose: PoseIn


class ResetRequest(ViewRequest):
    target: int | str | None = Field(None, description="target instance: gt_id (int) or object name")
    start: PoseIn | None = Field(None, description="start pose; omitted: a seeded random start around the target")
    seed: Annotated[int, Field(ge=0, lt=2**63)] | None = None
    agent: AgentName | None = None


class EstimateIn(_Strict):
    """One pose estimate, ``cam_T_obj`` in the camera frame of the current view."""

    obj_id: Annotated[int, Field(ge=0)]
    R: Annotated[list[Finite], Field(min_length=9, max_length=9, description="rotation, 9 values row-major")]
    t_m: Annotated[list[Finite], Field(min_length=3, max_length=3, description="translation, metres")]
    score: Finite = 1.0


class SubmitRequest(_Strict):
    """The agent's final estimates (may be empty: the agent found nothing); ends the episode."""

    estimates: Annotated[list[EstimateIn], Field(max_length=MAX_ESTIMATES)]
    agent: AgentName | None = None


class SetPoseRequest(ObsOptions):
    pose: PoseIn


class MoveRequest(ObsOptions):
    linear: Linear = [0.0, 0.0, 0.0]
    angular: Angular = [0.0, 0.0, 0.0]
    duration: Duration = Field(..., description=f"seconds, (0, {MAX_MOVE_DURATION_S:g}]")
    frame: Literal["camera", "world"] = Field("camera", description="see brave6d.serve.geometry")

    @model_validator(mode="after")
    def _moves(self) -> MoveRequest:
        if not any(self.linear) and not any(self.angular):
            raise ValueError("the move does nothing: linear and angular velocities are both zero")
        return self


class WsMessage(ObsOptions):
    op: Literal["set_pose", "move", "get", "close"]
    request_id: RequestId | None = None
    pose: PoseIn | None = None
    linear: Linear | None = None
    angular: Angular | None = None
    duration: Duration | None = None
    frame: Literal["camera", "world"] = "camera"


# ----------------------------------------------------------------------------- encoding
def encode_observation(obs: RenderedView, rgb: str = "png", depth: str = "f32") -> tuple[ObservationMessage, float]:
    """The wire observation of a rendered view and the milliseconds spent encoding."""
    t0 = time.perf_counter()
    rgb_image = depth_image = None
    if rgb != "none":
        bgr = np.ascontiguousarray(obs.rgb[:, :, ::-1])
        ok, buf = (cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1]) if rgb == "png"
                   else cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90]))
        if not ok:
            raise RuntimeError("image encoding failed")
        rgb_image = EncodedImage(encoding=rgb, data=base64.b64encode(buf.tobytes()).decode("ascii"),
                                 shape=list(obs.rgb.shape))
    if depth == "f32":
        d = np.ascontiguousarray(obs.depth, dtype="<f4")
        depth_image = EncodedImage(encoding="f32", data=base64.b64encode(d.tobytes()).decode("ascii"),
                                   shape=list(d.shape))
    out = ObservationMessage(width=obs.camera.width, height=obs.camera.height, K=obs.camera.K,
                             world_T_cam=obs.world_T_cam, rgb=rgb_image, depth=depth_image, objects=list(obs.objects))
    return out, (time.perf_counter() - t0) * 1000.0


def step_json(result: ActionResult, opts: ObsOptions, t_start: float) -> dict[str, Any]:
    """The JSON body of a step reply (a :class:`brave6d.serve.schema.StepMessage`)."""
    obs, enc_ms = encode_observation(result.observation, opts.rgb, opts.depth)
    target = result.target
    timings = {**result.timings_ms, "encode": enc_ms, "total": (time.perf_counter() - t_start) * 1000.0}
    return StepMessage(
        episode_id=result.episode_id, action=result.action, step=result.step, accepted=result.accepted,
        collided=result.collided, refusal=result.refusal.to_json() if result.refusal else None,
        adjustments=result.adjustments, move=result.move,
        target={"gt_id": target.gt_id, "obj_id": target.obj_id, "name": target.name} if target else {},
        observation=obs, timings_ms=timings, mode=result.mode).model_dump()


def render_json(view: RenderedView, scene: str, opts: ObsOptions, t_start: float) -> dict[str, Any]:
    """The JSON body of a free view's reply (a :class:`brave6d.serve.schema.RenderMessage`)."""
    obs, enc_ms = encode_observation(view, opts.rgb, opts.depth)
    timings = {**view.timings_ms, "encode": enc_ms, "total": (time.perf_counter() - t_start) * 1000.0}
    return RenderMessage(scene=scene, observation=obs, timings_ms=timings).model_dump()


def timing_headers(timings_ms: dict[str, float]) -> dict[str, str]:
    """``X-Render-Ms`` and ``Server-Timing`` of a reply whose body reports ``timings_ms``."""
    render = timings_ms.get("render", 0.0)
    return {"X-Render-Ms": f"{render:.2f}",
            "Server-Timing": f"render;dur={render:.2f}, total;dur={timings_ms.get('total', 0.0):.2f}"}


#: Bytes of an ``observation.npz`` reply handed to the connection at a time (see
#: :func:`npz_reply_chunks` and :mod:`brave6d.serve.connections`).
NPZ_CHUNK_BYTES = 256 * 1024


def observation_npz(obs: RenderedView) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, rgb=obs.rgb, depth=obs.depth.astype(np.float32, copy=False), K=obs.camera.K,
             world_T_cam=obs.world_T_cam,
             cam_T_obj=np.stack([o.cam_T_obj for o in obs.objects]) if obs.objects else np.zeros((0, 4, 4)),
             gt_id=np.array([o.gt_id for o in obs.objects], dtype=np.int64),
             obj_id=np.array([o.obj_id for o in obs.objects], dtype=np.int64),
             visib_fract=np.array([o.visib_fract if o.visib_fract is not None else np.nan for o in obs.objects]))
    return buf.getvalue()


class NpzFiles:
    """``observation.npz`` of each observation that is asked for, made once and kept while the
    observation lives (an episode's last view): concurrent requests for it share one copy."""

    def __init__(self) -> None:
        self._files: dict[int, tuple[weakref.ref[RenderedView], bytes]] = {}

    def get(self, obs: RenderedView) -> bytes:
        held = self._files.get(id(obs))
        if held is not None and held[0]() is obs:
            return held[1]
        data = observation_npz(obs)
        self._files[id(obs)] = (weakref.ref(obs), data)
        weakref.finalize(obs, self._files.pop, id(obs), None)
        return data


def npz_reply_chunks(data: bytes, chunk: int = NPZ_CHUNK_BYTES) -> Iterator[memoryview]:
    """``data`` in views of ``chunk`` bytes (no copies): a reply streamed this way leaves the bytes
    shared by every connection that asks for them, and a connection whose client does not read
    holds one chunk in its buffer, not a copy of the whole file."""
    view = memoryview(data)
    for i in range(0, len(view), chunk):
        yield view[i:i + chunk]


# ----------------------------------------------------------------------------- WebSocket messages
def echo_request_id(raw: Any) -> str | int | None:
    """The ``request_id`` of a WebSocket message when it can be echoed as JSON (a string of at
    most 256 characters or a 64-bit integer), else None: a NaN or a huge float is not echoed."""
    rid = raw.get("request_id") if isinstance(raw, dict) else None
    if isinstance(rid, str) and len(rid) <= 256:
        return rid
    if isinstance(rid, int) and not isinstance(rid, bool) and -(2**63) <= rid < 2**63:
        return rid
    return None


def ws_dump(reply: dict[str, Any]) -> str:
    """``reply`` as strict JSON text (no NaN/inf); a reply that has none becomes a 500 error object."""
    try:
        return json.dumps(reply, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        log.error("unserialisable WebSocket reply: %s", exc)
        return json.dumps({"error": f"internal error: the reply is not valid JSON ({exc})", "field": None,
                           "status": 500, "request_id": echo_request_id(reply)})


# ----------------------------------------------------------------------------- errors
def _error(status: int, message: str, field: str | None = None, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": message, "field": field, "status": status}, status_code=status, headers=headers)


def validation_error_body(errors: list[dict[str, Any]]) -> tuple[int, str, str | None]:
    """(status, message, field) of pydantic/FastAPI validation errors (malformed JSON -> 400)."""
    if not errors:
        return 422, "invalid request", None
    err = errors[0]
    if err.get("type") == "json_invalid":
        ctx = err.get("ctx", {}) or {}
        return 400, f"malformed JSON: {ctx.get('error', err.get('msg'))}", "body"
    if err.get("type") == "missing" and tuple(err.get("loc", ())) == ("body",):
        return 400, "malformed JSON: the request needs a JSON object body", "body"
    field, msg = validation_error_field(errors, dotted=True)
    if err.get("type") in ("finite_number",):
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        msg = "must be a finite number (NaN and inf are refused)" + more
    return 422, f"{field}: {msg}" if field else msg, field or None


#: The request models other front ends (the ROS 2 node) validate with, by action.
REQUEST_MODELS: dict[str, type[BaseModel]] = {"reset": ResetRequest, "set_pose": SetPoseRequest,
                                              "move": MoveRequest, "submit": SubmitRequest}


def request_json_limits(limits: ServerLimits) -> JsonLimits:
    """The JSON limits of a request body or WebSocket message: the body size, and NaN / inf let
    through to the fields' validators (which name the field: 422)."""
    return JsonLimits(max_bytes=limits.max_body_bytes, finite=False)


#: Request bodies and WebSocket messages larger than this are parsed on the app's parser thread, off
#: the event loop: while one is read (a 1 MiB body takes about 0.1 s to refuse) the loop serves the others.
PARSE_OFF_LOOP_BYTES = 64 * 1024


async def parse_request_json(data: bytes | str, where: str, limits: ServerLimits, parser: Any) -> Any:
    """``data`` through the one JSON reader with :func:`request_json_limits`; a document over
    :data:`PARSE_OFF_LOOP_BYTES` is parsed in ``parser`` (a one-thread pool: large bodies take turns,
    and the event loop never waits for one). Every check of the reader is linear in the input."""
    if len(data) <= PARSE_OFF_LOOP_BYTES:
        return parse_json(data, where, request_json_limits(limits))
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(parser, parse_json, data, where, request_json_limits(limits))


#: The ASGI ``receive`` of the HTTP request whose handler runs (set by :class:`_JsonRoute`), so that
#: an action can be withdrawn when its client disconnects (:mod:`brave6d.serve.inflight`).
_REQUEST_RECEIVE: ContextVar[Callable[[], Any] | None] = ContextVar("brave6d_request_receive", default=None)


class _JsonRequest(Request):
    """A request whose JSON body is read by the one JSON reader (:mod:`brave6d.core.json_input`):
    a body over its depth or number limits is 400 naming the place, never 500."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            try:
                self._json = await parse_request_json(await self.body(), "body", self.app.state.limits,
                                                      self.app.state.json_parser)
            except JsonInputError as exc:
                raise StarletteHTTPException(400, f"malformed JSON: {str(exc).removeprefix('body: ')}") from None
        return self._json


class _JsonRoute(APIRoute):
    """The routes' class: each handler gets a :class:`_JsonRequest`, and its actions watch the
    request's connection (:data:`_REQUEST_RECEIVE`)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route(request: Request) -> Response:
            token = _REQUEST_RECEIVE.set(request.receive)
            try:
                return await handler(_JsonRequest(request.scope, request.receive))
            finally:
                _REQUEST_RECEIVE.reset(token)
        return route


def validate_request(action: str, fields: dict[str, Any], where: str | None = None) -> Any:
    """``fields`` checked as the HTTP API checks the body of ``action`` (reset, set_pose, move,
    submit): the same limits and the same one-line messages (``BraveError``, prefixed by ``where``)."""
    try:
        return REQUEST_MODELS[action].model_validate(fields)
    except ValidationError as exc:
        message = validation_error_body(list(exc.errors()))[1]
        raise BraveError(f"{where}: {message}" if where else message) from None


class BodyLimitMiddleware:
    """Refuse HTTP request bodies larger than ``limit`` bytes with 413 (checked on the declared
    length and on the bytes actually received; the body is buffered, then replayed)."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope.get("method") in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None:
            try:
                too_big = int(declared) > self.limit
            except ValueError:
                too_big = False
            if too_big:
                await self._reject(scope, receive, send)
                return
        chunks = []
        size = 0
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            size += len(body)
            if size > self.limit:
                await self._reject(scope, receive, send)
                return
            chunks.append(body)
            more = message.get("more_body", False)
        data = b"".join(chunks)
        sent = False

        async def replay() -> dict[str, Any]:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": data, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _reject(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        response = _error(413, f"request body larger than {self.limit} bytes", "body", {"Connection": "close"})
        await response(scope, receive, send)


# ----------------------------------------------------------------------------- access control
#: ``Host`` header values always accepted (with any port): this machine's loopback names. Any
#: other name must be allowed explicitly, so that a DNS-rebinding page cannot reach the API.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")
#: Paths served without the token: the viewer's static files (the page then calls the API with the
#: token from its own URL) and the API documentation.
PUBLIC_PATHS = ("/viewer", "/docs", "/redoc", "/openapi.json")
#: Shortest token accepted (characters).
MIN_TOKEN_CHARS = 16


def check_token(token: str) -> str:
    """``token`` when it is long enough to be a secret, else :class:`BraveError` saying how to make one."""
    if len(token) < MIN_TOKEN_CHARS or token != token.strip():
        raise BraveError(f"the token must have at least {MIN_TOKEN_CHARS} characters and no surrounding spaces "
                         "(make one with: python -c 'import secrets; print(secrets.token_urlsafe())')")
    return token


def _is_public(path: str) -> bool:
    return path == "/" or any(path == p or path.startswith(p + "/") for p in PUBLIC_PATHS)


class TokenMiddleware:
    """Require ``token`` on every HTTP request and WebSocket outside :data:`PUBLIC_PATHS`: as
    ``Authorization: Bearer <token>`` or as the query parameter ``token`` (browsers can set no
    header on a WebSocket or a beacon). Missing or wrong: 401 (a WebSocket handshake is denied
    with the same 401 where the server supports it, else closed with 1008)."""

    def __init__(self, app: Any, token: str) -> None:
        self.app = app
        self.token = check_token(token).encode()

    def _authorised(self, scope: dict[str, Any]) -> bool:
        auth = Headers(scope=scope).get("authorization", "")
        scheme, _, given = auth.partition(" ")
        if scheme.lower() != "bearer":
            given = QueryParams(scope.get("query_string", b"").decode("latin-1")).get("token", "")
        return secrets.compare_digest(given.strip().encode(), self.token)

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket") or _is_public(scope["path"]) or self._authorised(scope):
            await self.app(scope, receive, send)
            return
        message = "missing or wrong token: send 'Authorization: Bearer <token>' (or '?token=<token>')"
        if scope["type"] == "websocket" and "websocket.http.response" not in scope.get("extensions", {}):
            await WebSocketClose(code=1008, reason=message)(scope, receive, send)
            return
        await _error(401, message, "token", {"WWW-Authenticate": "Bearer"})(scope, receive, send)


# ----------------------------------------------------------------------------- the app
def create_app(bundle: Bundle | Path | str | SceneCatalog, *, device: str = "auto", log_dir: Path | str | None = None,
               limits: ServerLimits = ServerLimits(), scene: SceneServer | None = None,
               verify: bool = True, warm_up: bool = True, allowed_hosts: Sequence[str] = (),
               token: str | None = None, mode: str = SCORED, log_key: LogKey | str | None = "default",
               visibility_stride: int = 1) -> FastAPI:
    """The FastAPI app serving ``bundle``: a loaded :class:`Bundle` or a bundle folder (verified,
    loaded now), or a :class:`brave6d.serve.catalog.SceneCatalog` of several scenes (loaded on first use).

    Requests must name one of :data:`LOOPBACK_HOSTS` or ``allowed_hosts`` (``"*"``: any;
    ``"*.example.org"``: its subdomains) in their ``Host`` header, else 400; with ``token``,
    every request outside :data:`PUBLIC_PATHS` must carry it (see :class:`TokenMiddleware`).
    ``mode`` (``"scored"`` or ``"training"``), ``log_key`` and ``visibility_stride`` are the :class:`EpisodeManager`'s.
    """
    if token is not None:
        check_token(token)
    if isinstance(bundle, SceneCatalog):
        catalog = bundle
    else:
        if not isinstance(bundle, Bundle):
            bundle = load_bundle(bundle, verify=verify)
        scene = scene if scene is not None else SceneServer(bundle, device)
        if warm_up:
            warm_scene(scene)
        catalog = SceneCatalog.of_scene(scene)
    single = catalog.sources[0].name if len(catalog.sources) == 1 else None
    manager = EpisodeManager(catalog, log_dir, max_episodes=limits.max_episodes,
                             idle_timeout_s=limits.idle_timeout_s, lock_timeout_s=limits.request_timeout_s,
                             mode=mode, log_key=log_key, visibility_stride=visibility_stride)
    executor = ThreadPoolExecutor(max_workers=limits.workers, thread_name_prefix="brave6d-serve")
    inflight = InFlight(executor, limits.request_timeout_s)
    json_parser = ThreadPoolExecutor(max_workers=1, thread_name_prefix="brave6d-json")
    npz_files = NpzFiles()

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
        inflight.drain()
        manager.close_all()
        executor.shutdown(wait=False, cancel_futures=True)
        json_parser.shutdown(wait=False, cancel_futures=True)

    app = FastAPI(
        lifespan=lifespan,
        title="BRAVE-6D render server",
        version="1",
        description="Move a camera through a trained 3D Gaussian Splatting scene and get RGB-D views (with "
                    "ground-truth object poses in training mode only). World = robot base frame, metres, OpenCV "
                    "camera axes; errors are {error, field, status}. See serve/app.py.",
    )
    app.router.route_class = _JsonRoute  # every route below reads its body through the one JSON reader
    app.state.manager = manager
    app.state.scenes = catalog
    app.state.scene = scene if not isinstance(bundle, SceneCatalog) else None
    app.state.bundle = bundle if isinstance(bundle, Bundle) else None
    app.state.limits = limits
    app.state.executor = executor
    app.state.json_parser = json_parser
    app.state.inflight = inflight
    app.state.drain = inflight.drain  # brave6d.serve.runner's server calls it when its shutdown starts
    app.add_middleware(BodyLimitMiddleware, limit=limits.max_body_bytes)
    if token is not None:
        app.add_middleware(TokenMiddleware, token=token)
    # outermost: a request for a host name this server does not answer to gets nothing else
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=[*LOOPBACK_HOSTS, *allowed_hosts], www_redirect=False)

    # -------------------------------------------------------------- error handlers
    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        status, msg, field = validation_error_body(list(exc.errors()))
        return _error(status, msg, field)

    @app.exception_handler(EpisodeError)
    async def _episode(request: Request, exc: EpisodeError) -> JSONResponse:
        return _error(exc.status, str(exc), exc.field)

    @app.exception_handler(BraveError)
    async def _brave(request: Request, exc: BraveError) -> JSONResponse:
        return _error(422, str(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no such endpoint: {request.method} {request.url.path}"
        if exc.status_code == 405:
            detail = f"method {request.method} not allowed on {request.url.path}"
        return _error(exc.status_code, detail)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("internal error on %s %s", request.method, request.url.path)
        return _error(500, f"internal error: {type(exc).__name__}: {exc}")

    async def run_action(fn: Any, *args: Any, **kwargs: Any) -> Any:
        """Run a blocking action in the pool, withdrawn (nothing committed) when its client goes (499),
        on timeout (504) or at shutdown (503): :class:`brave6d.serve.inflight.InFlight`."""
        return await inflight.run(fn, *args, receive=_REQUEST_RECEIVE.get(), **kwargs)

    def respond(result: ActionResult, opts: ObsOptions, t0: float, status: int = 200) -> JSONResponse:
        body = step_json(result, opts, t0)
        return JSONResponse(body, status_code=status, headers=timing_headers(body["timings_ms"]))

    err = {400: {"model": ErrorMessage}, 404: {"model": ErrorMessage}, 409: {"model": ErrorMessage},
           413: {"model": ErrorMessage}, 422: {"model": ErrorMessage}, 429: {"model": ErrorMessage},
           503: {"model": ErrorMessage}, 504: {"model": ErrorMessage}}

    # -------------------------------------------------------------- routes
    @app.get("/", include_in_schema=False)
    def root(request: Request) -> RedirectResponse:
        query = request.url.query  # keeps ?token=... for the viewer
        return RedirectResponse("/viewer/" + (f"?{query}" if query else ""))

    @app.get("/health", summary="liveness")
    def health() -> dict[str, Any]:
        loaded = catalog.loaded_scenes()
        return {"status": "ok", "mode": manager.mode, "bundle": single, "scenes": len(catalog.sources),
                "loaded_scenes": catalog.loaded_names(), "device": catalog.device_name(),
                "gaussians": sum(s.renderer.num_gaussians for s in loaded), "episodes_open": manager.open_count(),
                "renders": sum(s.renderer.renders for s in loaded)}

    @app.get("/scenes", summary="the scenes this server serves (loaded or not), and its memory bound")
    def get_scenes() -> dict[str, Any]:
        return catalog.describe()

    @app.get("/bundle", summary="what a scene's bundle holds (objects, intrinsics, collision boxes, ...)",
             responses=err)
    async def get_bundle(scene: str | None = None) -> dict[str, Any]:
        loop = asyncio.get_running_loop()
        b = await loop.run_in_executor(executor, catalog.bundle, scene)  # a release's scene may be unpacked first
        return {**public_bundle(b.summary(), manager.mode), "scene_id": catalog.source(scene).scene_id,
                "device": catalog.device_name(),
                "limits": {"min_size": MIN_SIZE, "max_width": MAX_WIDTH, "max_height": MAX_HEIGHT,
                           "max_move_duration_s": MAX_MOVE_DURATION_S, "max_coord_m": MAX_COORD_M,
                           "max_linear_speed_m_s": MAX_LINEAR_SPEED_M_S,
                           "max_angular_speed_rad_s": MAX_ANGULAR_SPEED_RAD_S, "max_body_bytes": limits.max_body_bytes,
                           "request_timeout_s": limits.request_timeout_s, "max_episodes": limits.max_episodes}}

    @app.get("/bundle/models/{obj_id}", summary="object model (BOP PLY, mm)", responses=err)
    async def get_model(obj_id: int, scene: str | None = None) -> FileResponse:
        loop = asyncio.get_running_loop()
        b = await loop.run_in_executor(executor, catalog.bundle, scene)
        for o in b.objects:
            if o.obj_id == obj_id:
                return FileResponse(b.model_path(o), media_type="application/octet-stream",
                                    filename=Path(o.model).name)
        raise EpisodeNotFound(f"no object with obj_id {obj_id} (known: {sorted({o.obj_id for o in b.objects})})",
                              "obj_id")

    @app.post("/episodes", status_code=201, response_model=StepMessage, responses=err, summary="reset: start an episode")
    async def reset(req: ResetRequest) -> JSONResponse:
        t0 = time.perf_counter()
        start = req.start.matrix() if req.start is not None else None
        result = await run_action(manager.reset, scene=req.scene, target=req.target, width=req.width, height=req.height,
                                  start=start, seed=req.seed, agent=req.agent)
        return respond(result, req, t0, 201)

    @app.post("/render", response_model=RenderMessage, responses=err,
              summary="free view: the splat at a pose, without an episode (any bundle, with or without objects)")
    async def render(req: RenderRequest) -> JSONResponse:
        t0 = time.perf_counter()
        view = await run_action(manager.render, req.pose.matrix(), scene=req.scene, width=req.width,
                                height=req.height)
        body = render_json(view, catalog.source(req.scene).name, req, t0)
        return JSONResponse(body, headers=timing_headers(body["timings_ms"]))

    @app.get("/episodes", summary="list episodes")
    def list_episodes() -> dict[str, Any]:
        return {"episodes": manager.list()}

    @app.get("/episodes/{episode_id}", responses=err, summary="episode state (no images)")
    def get_episode(episode_id: str) -> dict[str, Any]:
        return manager.get(episode_id).state()

    @app.post("/episodes/{episode_id}/set_pose", response_model=StepMessage, responses=err,
              summary="teleport the camera to an absolute pose")
    async def set_pose(episode_id: str, req: SetPoseRequest) -> JSONResponse:
        t0 = time.perf_counter()
        manager.get(episode_id)
        result = await run_action(manager.set_pose, episode_id, req.pose.matrix())
        return respond(result, req, t0)

    @app.post("/episodes/{episode_id}/move", response_model=StepMessage, responses=err,
              summary="move with a constant twist, stopping at the first collision")
    async def move(episode_id: str, req: MoveRequest) -> JSONResponse:
        t0 = time.perf_counter()
        manager.get(episode_id)
        result = await run_action(manager.move, episode_id, req.linear, req.angular, req.duration, req.frame)
        return respond(result, req, t0)

    @app.post("/episodes/{episode_id}/estimates", responses=err,
              summary="submit the final pose estimates (current camera frame) and end the episode")
    async def submit(episode_id: str, req: SubmitRequest) -> dict[str, Any]:
        manager.get(episode_id)
        return await run_action(manager.submit, episode_id, [e.model_dump() for e in req.estimates], req.agent)

    @app.post("/episodes/{episode_id}/close", responses=err, summary="close an episode")
    async def close(episode_id: str) -> dict[str, Any]:
        manager.get(episode_id)
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(executor, manager.close, episode_id)

    @app.get("/episodes/{episode_id}/observation.npz", responses=err, summary="last observation as .npz",
             response_class=Response)
    def get_npz(episode_id: str) -> Response:
        ep = manager.get(episode_id)
        if ep.shown is None:
            return _error(409, "no observation yet")
        data = npz_files.get(ep.shown)  # scored: the view without its objects
        return StreamingResponse(npz_reply_chunks(data), media_type="application/octet-stream",
                                 headers={"Content-Disposition": f'attachment; filename="{episode_id}.npz"',
                                          "Content-Length": str(len(data))})

    @app.websocket("/episodes/{episode_id}/ws")
    async def ws(websocket: WebSocket, episode_id: str) -> None:
        await websocket.accept()
        try:
            manager.get(episode_id)
        except EpisodeError as exc:
            await websocket.send_json({"error": str(exc), "field": exc.field, "status": exc.status})
            await websocket.close(code=4404)
            return
        while True:
            try:
                text = await websocket.receive_text()
            except WebSocketDisconnect:
                return
            except (KeyError, RuntimeError):  # a binary frame or a closed socket
                await websocket.close(code=1003)
                return
            try:
                reply = await _ws_handle(text, episode_id)
            except Exception as exc:  # keep the socket: answer with the error object
                log.exception("internal error on the WebSocket of %s", episode_id)
                reply = {"error": f"internal error: {type(exc).__name__}: {exc}", "field": None, "status": 500}
            await websocket.send_text(ws_dump(reply))
            if reply.get("action") == "close" and "error" not in reply:
                await websocket.close()
                return

    async def _ws_handle(text: str, episode_id: str) -> dict[str, Any]:
        t0 = time.perf_counter()
        if len(text.encode("utf-8")) > limits.max_body_bytes:
            return {"error": f"message larger than {limits.max_body_bytes} bytes", "field": "message", "status": 413}
        request_id = None
        try:
            raw = await parse_request_json(text, "message", limits, json_parser)  # the one JSON reader
            request_id = echo_request_id(raw)
            msg = WsMessage.model_validate(raw)
        except ValidationError as exc:
            status, m, field = validation_error_body(exc.errors(include_url=False))
            return {"error": m, "field": field, "status": status, "request_id": request_id}
        except JsonInputError as exc:
            return {"error": f"malformed JSON: {str(exc).removeprefix('message: ')}", "field": "message", "status": 400}
        try:
            if msg.op == "get":
                ep = manager.get(episode_id)
                return {**ep.state(), "action": "get", "request_id": request_id}
            if msg.op == "close":
                loop = asyncio.get_running_loop()
                out = await loop.run_in_executor(executor, manager.close, episode_id)
                return {**out, "action": "close", "request_id": request_id}
            if msg.op == "set_pose":
                if msg.pose is None:
                    return {"error": "set_pose needs 'pose'", "field": "pose", "status": 422, "request_id": request_id}
                result = await run_action(manager.set_pose, episode_id, msg.pose.matrix())
            else:
                if msg.duration is None:
                    return {"error": "move needs 'duration'", "field": "duration", "status": 422,
                            "request_id": request_id}
                lin = msg.linear or [0.0, 0.0, 0.0]
                ang = msg.angular or [0.0, 0.0, 0.0]
                if not any(lin) and not any(ang):
                    return {"error": "the move does nothing: linear and angular velocities are both zero",
                            "field": "linear", "status": 422, "request_id": request_id}
                result = await run_action(manager.move, episode_id, lin, ang, msg.duration, msg.frame)
            return {**step_json(result, msg, t0), "request_id": request_id}
        except EpisodeError as exc:
            return {"error": str(exc), "field": exc.field, "status": exc.status, "request_id": request_id}
        except BraveError as exc:
            return {"error": str(exc), "field": None, "status": 422, "request_id": request_id}
        except Exception as exc:  # keep the socket alive
            log.exception("internal error on the WebSocket of %s", episode_id)
            return {"error": f"internal error: {type(exc).__name__}: {exc}", "field": None, "status": 500,
                    "request_id": request_id}

    if VIEWER_DIR.is_dir():
        app.mount("/viewer", StaticFiles(directory=VIEWER_DIR, html=True), name="viewer")
    return app
