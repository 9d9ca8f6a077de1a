"""Python client of the render server (httpx): returns NumPy arrays, raises on errors.

    from brave6d.serve.client import BraveClient

    with BraveClient("http://127.0.0.1:8765") as client:
        step = client.reset(target="hex_nut", width=320, height=240, seed=0)
        obs = step.observation                      # rgb (H, W, 3) uint8, depth (H, W) float32 m
        step = client.move(linear=(0, 0, 0.05), duration=1.0)   # 5 cm forward (camera frame)
        if not step.accepted:
            print("refused:", step.refusal["message"])
        client.submit([PoseEstimate(obj_id=1, cam_T_obj=my_estimate, score=0.9)], agent="mine")
        # (submit ends the episode; client.close() ends one without estimates)
        view = client.render(world_T_cam, width=320, height=240)   # a free view, no episode

Poses are ``world_T_cam`` 4x4 arrays (OpenCV camera axes, metres). A refused action is not an
error: it returns a :class:`StepResult` with ``accepted == False``. HTTP errors (4xx/5xx) raise
:class:`ServerError` with the server's message, field and status. A server started with a
token (``brave6d serve --token``) needs it: ``BraveClient(url, token=...)`` or ``$BRAVE6D_TOKEN``.

The server is not trusted: every reply is read within :class:`~brave6d.serve.replies.ClientLimits`
(size as sent and decompressed, JSON depth and number length, image headers before decoding, the
``.npz`` directory and ``.npy`` headers) and every call ends by its deadline (``timeout`` seconds,
the whole call, however the server drips its bytes); a reply that breaks a limit raises
:class:`ReplyError` in one line (:mod:`brave6d.serve.replies`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Self, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pydantic import ValidationError

from brave6d.core.errors import BraveError, validation_error_field
from brave6d.serve.replies import (ClientLimits, ReplyError, call_deadline, deadline_transport, decode_depth, decode_rgb,
                                   one_line, parse_reply, read_body, read_npz)
from brave6d.serve.schema import ObjectState, ObservationMessage, RenderMessage, StepMessage

M = TypeVar("M", ObservationMessage, StepMessage, RenderMessage)

DEFAULT_URL = "http://127.0.0.1:8765"
#: Environment variable holding the server's token (the same one ``brave6d serve`` reads).
TOKEN_ENV = "BRAVE6D_TOKEN"


class ServerError(BraveError):
    """The server answered with an error (4xx/5xx)."""

    def __init__(self, status: int, message: str, field: str | None = None) -> None:
        super().__init__(f"server error {status}: {message}")
        self.status = status
        self.message = message
        self.field = field


@dataclass(frozen=True)
class Observation:
    """A view as the client sees it: the wire :class:`brave6d.serve.schema.ObservationMessage` (sizes, ``K``,
    ``world_T_cam`` and objects, matrices as arrays) plus its decoded images (``rgb`` (H, W, 3) uint8,
    ``depth`` (H, W) float32 metres, 0 = no data; None when not requested)."""

    message: ObservationMessage
    rgb: NDArray[np.uint8] | None
    depth: NDArray[np.float32] | None

    @property
    def width(self) -> int:
        return self.message.width

    @property
    def height(self) -> int:
        return self.message.height

    @property
    def K(self) -> NDArray[np.float64]:
        return self.message.K

    @property
    def world_T_cam(self) -> NDArray[np.float64]:
        return self.message.world_T_cam

    @property
    def objects(self) -> list[ObjectState]:
        return self.message.objects

    def target(self) -> ObjectState | None:
        return self.message.target()


@dataclass(frozen=True)
class StepResult:
    """A step reply: the wire :class:`brave6d.serve.schema.StepMessage` with its observation decoded."""

    message: StepMessage
    observation: Observation

    @property
    def episode_id(self) -> str:
        return self.message.episode_id

    @property
    def action(self) -> str:
        return self.message.action

    @property
    def step(self) -> int:
        return self.message.step

    @property
    def accepted(self) -> bool:
        return self.message.accepted

    @property
    def collided(self) -> bool:
        return self.message.collided

    @property
    def refusal(self) -> dict[str, Any] | None:
        return self.message.refusal

    @property
    def adjustments(self) -> int:
        return self.message.adjustments

    @property
    def move(self) -> dict[str, Any] | None:
        return self.message.move

    @property
    def timings_ms(self) -> dict[str, float]:
        return self.message.timings_ms

    @property
    def target(self) -> dict[str, Any]:
        return self.message.target

    @property
    def mode(self) -> str:
        """The server's mode: ``"scored"`` (no ground truth in the observation) or ``"training"``."""
        return self.message.mode


@dataclass(frozen=True)
class PoseEstimate:
    """An agent's estimate of one object's pose in the camera frame of the current view
    (``cam_T_obj`` 4x4, metres, OpenCV axes), with a confidence ``score`` (higher = surer)."""

    obj_id: int
    cam_T_obj: NDArray[np.float64]
    score: float = 1.0

    def to_json(self) -> dict[str, Any]:
        T = np.asarray(self.cam_T_obj, dtype=np.float64).reshape(4, 4)
        return {"obj_id": int(self.obj_id), "R": T[:3, :3].reshape(-1).tolist(), "t_m": T[:3, 3].tolist(),
                "score": float(self.score)}


def decode_observation(data: dict[str, Any] | ObservationMessage, what: str = "reply",
                       limits: ClientLimits = ClientLimits()) -> Observation:
    """An observation from the server's JSON (validated against :class:`brave6d.serve.schema.ObservationMessage`),
    its images decoded within ``limits`` (:mod:`brave6d.serve.replies`; ``what`` names the request in errors)."""
    message = data if isinstance(data, ObservationMessage) else _validated(ObservationMessage, data, what)
    rgb = None if message.rgb is None else decode_rgb(message.rgb, message.width, message.height, what, limits)
    depth = None if message.depth is None else decode_depth(message.depth, message.width, message.height, what, limits)
    return Observation(message, rgb, depth)


def decode_step(data: dict[str, Any], what: str = "reply", limits: ClientLimits = ClientLimits()) -> StepResult:
    """A step reply from the server's JSON (validated against :class:`brave6d.serve.schema.StepMessage`)."""
    message = _validated(StepMessage, data, what)
    return StepResult(message, decode_observation(message.observation, what, limits))


def _validated(model: type[M], data: dict[str, Any], what: str = "reply") -> M:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        field, message = validation_error_field(exc.errors(include_url=False))
        raise ReplyError(f"{what}: the server's reply does not match {model.__name__} (client and server versions "
                         f"differ?): field '{one_line(field or '<root>', 80)}': {one_line(message, 200)}") from None


def _given(**fields: Any) -> dict[str, Any]:
    """The ``fields`` that are not None: a request body leaves out what the caller did not give."""
    return {key: value for key, value in fields.items() if value is not None}


def pose_json(pose: ArrayLike | dict[str, Any]) -> dict[str, Any]:
    """A 4x4 ``world_T_cam`` (array) or an already formed pose dict -> the API's pose object."""
    if isinstance(pose, dict):
        return pose
    return {"world_T_cam": np.asarray(pose, dtype=np.float64).reshape(4, 4).tolist()}


class BraveClient:
    """Synchronous client of one server; remembers the current episode (``episode_id``)."""

    def __init__(self, base_url: str = DEFAULT_URL, timeout: float = 120.0, rgb: str = "png", depth: str = "f32",
                 transport: Any = None, token: str | None = None, limits: ClientLimits | None = None) -> None:
        """``token``: the server's token (default ``$BRAVE6D_TOKEN``; none when unset). ``timeout``: the
        seconds one call may take in all (its deadline); ``limits``: what a reply may hold (default
        :class:`ClientLimits` with that deadline)."""
        import httpx

        self.limits = limits if limits is not None else ClientLimits(deadline_s=timeout)
        token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        headers = {"Accept-Encoding": "identity"}  # a compressed reply is still read, within the limits
        if token is not None:
            headers["Authorization"] = f"Bearer {token}"
        kwargs: dict[str, Any] = {"base_url": base_url, "timeout": timeout, "headers": headers,
                                  "transport": transport if transport is not None else deadline_transport()}
        self._http = httpx.Client(**kwargs)
        self.rgb = rgb
        self.depth = depth
        self.episode_id: str | None = None
        self.scene: str | int | None = None  # the scene of the last reset (None: the server's only scene)

    # -------------------------------------------------------------- plumbing
    def _request(self, method: str, path: str, **kwargs: Any) -> bytes:
        """The body of the reply to ``method path``, read within :attr:`limits` and by the call's
        deadline; an error status raises :class:`ServerError`, a reply this client refuses
        :class:`ReplyError`."""
        import httpx

        what = f"{method} {path.split('?')[0][:100]}"
        try:
            with call_deadline(self.limits.deadline_s), self._http.stream(method, path, **kwargs) as r:
                body = read_body(r, self.limits, what)
                status = r.status_code
        except httpx.TimeoutException:
            raise ReplyError(f"{what}: no whole reply within the call's deadline of {self.limits.deadline_s:g} s "
                             "(the server is slow, overloaded or holds the reply back)") from None
        if status >= 400:
            try:
                err = parse_reply(body, self.limits, what)
            except ReplyError:
                err = None
            if isinstance(err, dict):
                field = err.get("field")
                raise ServerError(status, one_line(err.get("error", err)), one_line(field, 100) if field else None)
            raise ServerError(status, one_line(body[:300].decode("utf-8", "replace")))
        return body

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        """The JSON reply to ``method path`` (:meth:`_request`) through the one JSON reader."""
        return parse_reply(self._request(method, path, **kwargs), self.limits, f"{method} {path.split('?')[0][:100]}")

    def _dict(self, method: str, path: str, **kwargs: Any) -> dict[str, Any]:
        """:meth:`_json` when the reply is a JSON object, else :class:`ReplyError`."""
        out = self._json(method, path, **kwargs)
        if not isinstance(out, dict):
            raise ReplyError(f"{method} {path.split('?')[0][:100]}: the server's reply is not a JSON object")
        return out

    def _eid(self, episode_id: str | None) -> str:
        eid = episode_id or self.episode_id
        if eid is None:
            raise BraveError("no episode: call reset() first")
        return eid

    def _opts(self) -> dict[str, Any]:
        return {"rgb": self.rgb, "depth": self.depth}

    # -------------------------------------------------------------- API
    def health(self) -> dict[str, Any]:
        return self._dict("GET", "/health")

    def scenes(self) -> dict[str, Any]:
        """The scenes the server serves (``GET /scenes``: names, scene ids, objects, loaded or not)."""
        return self._dict("GET", "/scenes")

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]:
        """A scene's bundle description (``scene`` may be omitted when the server has one)."""
        params = {"scene": str(scene)} if scene is not None else None
        return self._dict("GET", "/bundle", params=params)

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes:
        """The object's model file (BOP PLY, mm)."""
        params = {"scene": str(scene)} if scene is not None else None
        return self._request("GET", f"/bundle/models/{obj_id}", params=params)

    def render(self, pose: ArrayLike | dict[str, Any], width: int | None = None, height: int | None = None,
               scene: str | int | None = None) -> Observation:
        """A free view (``POST /render``): the splat of ``scene`` at ``pose`` (a 4x4 ``world_T_cam`` or a
        pose dict), no episode, no object poses; works on a bundle without objects."""
        body = {"pose": pose_json(pose), **self._opts(), **_given(scene=scene, width=width, height=height)}
        reply = _validated(RenderMessage, self._dict("POST", "/render", json=body), "POST /render")
        return decode_observation(reply.observation, "POST /render", self.limits)

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              start: ArrayLike | dict[str, Any] | None = None, seed: int | None = None,
              agent: str | None = None, scene: str | int | None = None) -> StepResult:
        """Start an episode on ``scene`` (name or scene_id; may be omitted when the server has one)
        at ``target``; ``agent`` names the agent on the leaderboard."""
        body = {**self._opts(), **_given(scene=scene, target=target, width=width, height=height, seed=seed,
                                          agent=agent)}
        if start is not None:
            body["start"] = pose_json(start)
        step = decode_step(self._dict("POST", "/episodes", json=body), "POST /episodes", self.limits)
        self.episode_id = step.episode_id
        self.scene = scene
        return step

    def set_pose(self, world_T_cam: ArrayLike | dict[str, Any], episode_id: str | None = None) -> StepResult:
        body = {"pose": pose_json(world_T_cam), **self._opts()}
        path = f"/episodes/{self._eid(episode_id)}/set_pose"
        return decode_step(self._dict("POST", path, json=body), f"POST {path}", self.limits)

    def move(self, linear: ArrayLike = (0.0, 0.0, 0.0), angular: ArrayLike = (0.0, 0.0, 0.0), duration: float = 1.0,
             frame: str = "camera", episode_id: str | None = None) -> StepResult:
        body = {"linear": [float(v) for v in np.asarray(linear, dtype=float).reshape(3)],
                "angular": [float(v) for v in np.asarray(angular, dtype=float).reshape(3)],
                "duration": float(duration), "frame": frame, **self._opts()}
        path = f"/episodes/{self._eid(episode_id)}/move"
        return decode_step(self._dict("POST", path, json=body), f"POST {path}", self.limits)

    def state(self, episode_id: str | None = None) -> dict[str, Any]:
        return self._dict("GET", f"/episodes/{self._eid(episode_id)}")

    def observation_npz(self, episode_id: str | None = None) -> dict[str, NDArray[Any]]:
        """The last observation as arrays (rgb, depth, K, world_T_cam, cam_T_obj, gt_id, obj_id, visib_fract)."""
        path = f"/episodes/{self._eid(episode_id)}/observation.npz"
        return read_npz(self._request("GET", path), f"GET {path}", self.limits)

    def submit(self, estimates: list[PoseEstimate | dict[str, Any]], agent: str | None = None,
               episode_id: str | None = None) -> dict[str, Any]:
        """Hand in the final estimates (camera frame of the current view) and end the episode;
        returns the episode's totals. Dicts are sent as given (``{obj_id, R (9), t_m (3), score}``)."""
        eid = self._eid(episode_id)
        body: dict[str, Any] = {"estimates": [e.to_json() if isinstance(e, PoseEstimate) else e for e in estimates]}
        if agent is not None:
            body["agent"] = agent
        out = self._dict("POST", f"/episodes/{eid}/estimates", json=body)
        if eid == self.episode_id:
            self.episode_id = None
        return out

    def close(self, episode_id: str | None = None) -> dict[str, Any]:
        """Close the episode (the current one by default); returns its totals."""
        eid = self._eid(episode_id)
        out = self._dict("POST", f"/episodes/{eid}/close")
        if eid == self.episode_id:
            self.episode_id = None
        return out

    def disconnect(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()
