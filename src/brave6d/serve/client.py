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
"""

from __future__ import annotations

import base64
import io
import os
from dataclasses import dataclass
from typing import Any, Self, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pydantic import ValidationError

from brave6d.core.errors import BraveError
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


def decode_observation(data: dict[str, Any] | ObservationMessage) -> Observation:
    """An observation from the server's JSON (validated against :class:`brave6d.serve.schema.ObservationMessage`)."""
    message = data if isinstance(data, ObservationMessage) else _validated(ObservationMessage, data)
    rgb = None
    if message.rgb is not None:
        import cv2

        buf = np.frombuffer(base64.b64decode(message.rgb.data), dtype=np.uint8)
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
    depth = None
    if message.depth is not None:
        h, w = message.depth.shape
        depth = np.frombuffer(base64.b64decode(message.depth.data), dtype="<f4").reshape(h, w).astype(np.float32)
    return Observation(message, rgb, depth)


def decode_step(data: dict[str, Any]) -> StepResult:
    """A step reply from the server's JSON (validated against :class:`brave6d.serve.schema.StepMessage`)."""
    message = _validated(StepMessage, data)
    return StepResult(message, decode_observation(message.observation))


def _validated(model: type[M], data: dict[str, Any]) -> M:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise BraveError(f"the server's reply does not match {model.__name__} (client and server versions "
                         f"differ?): {exc}") from None


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
                 transport: Any = None, token: str | None = None) -> None:
        """``token``: the server's token (default ``$BRAVE6D_TOKEN``; none when unset)."""
        import httpx

        token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        kwargs: dict[str, Any] = {"base_url": base_url, "timeout": timeout}
        if token is not None:
            kwargs["headers"] = {"Authorization": f"Bearer {token}"}
        if transport is not None:
            kwargs["transport"] = transport
        self._http = httpx.Client(**kwargs)
        self.rgb = rgb
        self.depth = depth
        self.episode_id: str | None = None
        self.scene: str | int | None = None  # the scene of the last reset (None: the server's only scene)

    # -------------------------------------------------------------- plumbing
    def _request(self, method: str, path: str, **kwargs: Any) -> Any:
        r = self._http.request(method, path, **kwargs)
        if r.status_code >= 400:
            try:
                body = r.json()
                raise ServerError(r.status_code, str(body.get("error", body)), body.get("field"))
            except ValueError:
                raise ServerError(r.status_code, r.text[:200]) from None
        return r

    def _eid(self, episode_id: str | None) -> str:
        eid = episode_id or self.episode_id
        if eid is None:
            raise BraveError("no episode: call reset() first")
        return eid

    def _opts(self) -> dict[str, Any]:
        return {"rgb": self.rgb, "depth": self.depth}

    # -------------------------------------------------------------- API
    def health(self) -> dict[str, Any]:
        return self._request("GET", "/health").json()

    def scenes(self) -> dict[str, Any]:
        """The scenes the server serves (``GET /scenes``: names, scene ids, objects, loaded or not)."""
        return self._request("GET", "/scenes").json()

    def bundle(self, scene: str | int | None = None) -> dict[str, Any]:
        """A scene's bundle description (``scene`` may be omitted when the server has one)."""
        params = {"scene": str(scene)} if scene is not None else None
        return self._request("GET", "/bundle", params=params).json()

    def model(self, obj_id: int, scene: str | int | None = None) -> bytes:
        """The object's model file (BOP PLY, mm)."""
        params = {"scene": str(scene)} if scene is not None else None
        return self._request("GET", f"/bundle/models/{obj_id}", params=params).content

    def render(self, pose: ArrayLike | dict[str, Any], width: int | None = None, height: int | None = None,
               scene: str | int | None = None) -> Observation:
        """A free view (``POST /render``): the splat of ``scene`` at ``pose`` (a 4x4 ``world_T_cam`` or a
        pose dict), no episode, no object poses; works on a bundle without objects."""
        body = {"pose": pose_json(pose), **self._opts(), **_given(scene=scene, width=width, height=height)}
        reply = _validated(RenderMessage, self._request("POST", "/render", json=body).json())
        return decode_observation(reply.observation)

    def reset(self, target: int | str | None = None, width: int | None = None, height: int | None = None,
              start: ArrayLike | dict[str, Any] | None = None, seed: int | None = None,
              agent: str | None = None, scene: str | int | None = None) -> StepResult:
        """Start an episode on ``scene`` (name or scene_id; may be omitted when the server has one)
        at ``target``; ``agent`` names the agent on the leaderboard."""
        body = {**self._opts(), **_given(scene=scene, target=target, width=width, height=height, seed=seed,
                                          agent=agent)}
        if start is not None:
            body["start"] = pose_json(start)
        step = decode_step(self._request("POST", "/episodes", json=body).json())
        self.episode_id = step.episode_id
        self.scene = scene
        return step

    def set_pose(self, world_T_cam: ArrayLike | dict[str, Any], episode_id: str | None = None) -> StepResult:
        body = {"pose": pose_json(world_T_cam), **self._opts()}
        return decode_step(self._request("POST", f"/episodes/{self._eid(episode_id)}/set_pose", json=body).json())

    def move(self, linear: ArrayLike = (0.0, 0.0, 0.0), angular: ArrayLike = (0.0, 0.0, 0.0), duration: float = 1.0,
             frame: str = "camera", episode_id: str | None = None) -> StepResult:
        body = {"linear": [float(v) for v in np.asarray(linear, dtype=float).reshape(3)],
                "angular": [float(v) for v in np.asarray(angular, dtype=float).reshape(3)],
                "duration": float(duration), "frame": frame, **self._opts()}
        return decode_step(self._request("POST", f"/episodes/{self._eid(episode_id)}/move", json=body).json())

    def state(self, episode_id: str | None = None) -> dict[str, Any]:
        return self._request("GET", f"/episodes/{self._eid(episode_id)}").json()

    def observation_npz(self, episode_id: str | None = None) -> dict[str, NDArray[Any]]:
        """The last observation as arrays (rgb, depth, K, world_T_cam, cam_T_obj, gt_id, obj_id, visib_fract)."""
        content = self._request("GET", f"/episodes/{self._eid(episode_id)}/observation.npz").content
        with np.load(io.BytesIO(content)) as npz:
            return {k: npz[k] for k in npz.files}

    def submit(self, estimates: list[PoseEstimate | dict[str, Any]], agent: str | None = None,
               episode_id: str | None = None) -> dict[str, Any]:
        """Hand in the final estimates (camera frame of the current view) and end the episode;
        returns the episode's totals. Dicts are sent as given (``{obj_id, R (9), t_m (3), score}``)."""
        eid = self._eid(episode_id)
        body: dict[str, Any] = {"estimates": [e.to_json() if isinstance(e, PoseEstimate) else e for e in estimates]}
        if agent is not None:
            body["agent"] = agent
        out = self._request("POST", f"/episodes/{eid}/estimates", json=body).json()
        if eid == self.episode_id:
            self.episode_id = None
        return out

    def close(self, episode_id: str | None = None) -> dict[str, Any]:
        """Close the episode (the current one by default); returns its totals."""
        eid = self._eid(episode_id)
        out = self._request("POST", f"/episodes/{eid}/close").json()
        if eid == self.episode_id:
            self.episode_id = None
        return out

    def disconnect(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()
