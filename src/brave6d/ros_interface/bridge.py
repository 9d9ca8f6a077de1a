"""The ROS-agnostic bridge: one episode at a time over :class:`brave6d.serve.EpisodeManager`, in plain
Python and numpy, for the ROS 1 and ROS 2 nodes.

There is one implementation of episodes (serve's): collisions, refusals, adjustments, twist
integration and the episode log all happen in the manager; the bridge only converts its results
into what a ROS node publishes (:class:`BridgeStep`), estimates from the camera frame into the
manager's form, and scores a submission with :mod:`brave6d.ros_interface.scoring` (which reads the
manager's episode log, as ``brave6d evaluate`` does).

Each step gets one stamp (``stamp_ns``, wall-clock nanoseconds taken when the step's answer is
ready); every message built from that step carries it. A refused action answers the previous
view (the camera did not move) under a new stamp, so every action produces exactly one
observation. Calls are serialised by a lock (ROS callbacks run on several threads).

The manager's mode decides what a step holds: in ``scored`` mode its results carry no ground truth,
so a :class:`BridgeStep` has no objects (no ``gt/`` frame is published, the status lists none) and
only the target's identity (``target_ref``); in ``training`` mode every object's truth.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brave6d.core.errors import BraveError
from brave6d.ros_interface.frames import (
    FRAME_CAMERA_OPTICAL,
    FRAME_WORLD,
    GT_FRAME_PREFIX,
    gt_frame,
    matrix_to_pose,
    pose_to_matrix,
)
from brave6d.ros_interface.scoring import EpisodeScorer
from brave6d.serve import SCORED

if TYPE_CHECKING:
    from brave6d.serve import TargetRef

__all__ = [
    "EpisodeBridge", "BridgeStep", "GroundTruthObject", "Estimate", "EpisodeResult", "EpisodeScorer",
    "FRAME_WORLD", "FRAME_CAMERA_OPTICAL", "GT_FRAME_PREFIX", "gt_frame", "matrix_to_pose", "pose_to_matrix",
]

Matrix4 = NDArray[np.float64]


class BridgeError(BraveError):
    """An agent's request the bridge cannot serve (no episode, bad estimate, ...): one line."""


@dataclass(frozen=True)
class GroundTruthObject:
    """One object instance's ground truth in a view (metres); ``frame`` is its tf frame ``gt/...``."""

    name: str
    obj_id: int
    gt_id: int
    is_target: bool
    world_T_obj: Matrix4
    cam_T_obj: Matrix4
    visib_fract: float | None

    @property
    def frame(self) -> str:
        return gt_frame(self.name, self.gt_id)


@dataclass(frozen=True)
class BridgeStep:
    """The answer to reset / set_pose / move: the view (rgb uint8 HxWx3, depth float32 metres with
    0 = no data, ``K`` of the image), the camera pose, the ground truth and the counters."""

    episode_id: str
    step: int
    accepted: bool
    collided: bool
    refusal: str | None  # the reason in words when refused or stopped part-way, else None
    adjustments: int
    stamp_ns: int
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    K: NDArray[np.float64]
    width: int
    height: int
    world_T_cam: Matrix4
    objects: tuple[GroundTruthObject, ...]
    action: str = "reset"
    refusal_detail: dict[str, Any] | None = None  # serve's Refusal.to_json(): reason, message, box
    move: dict[str, Any] | None = None  # for move: fraction of the duration travelled, substeps, path_m
    target_ref: TargetRef | None = None  # the target's ids and name, in either mode
    mode: str = SCORED

    def target(self) -> GroundTruthObject | None:
        """The target's ground truth (training mode; None in scored mode)."""
        return next((o for o in self.objects if o.is_target), None)

    @property
    def target_frame(self) -> str:
        """The target's ``gt/`` tf frame when it is published (training mode), else ""."""
        tgt = self.target()
        return tgt.frame if tgt is not None else ""

    def status(self) -> dict[str, Any]:
        """The JSON status both nodes publish on ``~status`` (no images; no ground truth when scored)."""
        ref = self.target_ref
        return {"episode_id": self.episode_id, "action": self.action, "step": self.step, "mode": self.mode,
                "accepted": self.accepted, "collided": self.collided, "refusal": self.refusal_detail,
                "adjustments": self.adjustments, "stamp_ns": self.stamp_ns, "move": self.move,
                "target": None if ref is None else {"name": ref.name, "obj_id": ref.obj_id, "gt_id": ref.gt_id,
                                                     "frame": self.target_frame or None},
                "objects": [{"name": o.name, "obj_id": o.obj_id, "gt_id": o.gt_id, "frame": o.frame,
                             "is_target": o.is_target, "visib_fract": o.visib_fract} for o in self.objects],
                "world_T_cam": self.world_T_cam.tolist()}


@dataclass(frozen=True)
class Estimate:
    """A pose estimate: ``cam_T_obj`` in the camera frame of the current view (metres)."""

    obj_id: int
    cam_T_obj: Matrix4
    score: float = 1.0

    @classmethod
    def from_pose(cls, obj_id: int, position: ArrayLike, quaternion_xyzw: ArrayLike, score: float = 1.0,
                  field: str = "estimate") -> Estimate:
        return cls(int(obj_id), pose_to_matrix(position, quaternion_xyzw, field), float(score))


@dataclass(frozen=True)
class EpisodeResult:
    """A submitted episode's score (BOP AR over the episode's target) and its costs."""

    episode_id: str
    ar: float
    ar_vsd: float | None
    ar_mssd: float | None
    ar_mspd: float | None
    adjustments: int
    steps: int
    refusals: int
    submitted: int  # number of estimates handed in
    log: str | None = field(default=None)
    mode: str = SCORED

    def to_json(self) -> dict[str, Any]:
        return {"episode_id": self.episode_id, "ar": self.ar, "ar_vsd": self.ar_vsd, "ar_mssd": self.ar_mssd,
                "ar_mspd": self.ar_mspd, "adjustments": self.adjustments, "steps": self.steps,
                "refusals": self.refusals, "submitted": self.submitted, "log": self.log, "mode": self.mode}


def _stamp() -> int:
    return time.time_ns()


class EpisodeBridge:
    """One agent's episodes on an :class:`brave6d.serve.EpisodeManager`, one at a time: a reset closes the
    episode still open. ``width``/``height`` set the image size (default: the bundle's)."""

    def __init__(self, manager: Any, *, agent: str = "ros", width: int | None = None, height: int | None = None,
                 scorer: EpisodeScorer | None = None) -> None:
        self.manager = manager
        self.agent = agent
        self.width = width
        self.height = height
        self._scorer = scorer
        self._episode: str | None = None
        self._open = False
        self._lock = threading.RLock()

    @property
    def episode_id(self) -> str | None:
        return self._episode

    @property
    def scorer(self) -> EpisodeScorer:
        if self._scorer is None:
            self._scorer = EpisodeScorer()
        return self._scorer

    def _current(self) -> str:
        if self._episode is None or not self._open:
            raise BridgeError("no open episode: call reset first" if self._episode is None else
                              f"episode {self._episode} has ended (submitted or closed): call reset")
        return self._episode

    def _step(self, result: Any) -> BridgeStep:
        obs = result.observation
        T = np.asarray(obs.world_T_cam, dtype=np.float64)
        objects = tuple(
            GroundTruthObject(o.name, int(o.obj_id), int(o.gt_id), bool(o.is_target), T @ np.asarray(o.cam_T_obj),
                              np.asarray(o.cam_T_obj, dtype=np.float64),
                              None if o.visib_fract is None else float(o.visib_fract))
            for o in obs.objects)
        ref = result.refusal
        return BridgeStep(
            episode_id=result.episode_id, step=int(result.step), accepted=bool(result.accepted),
            collided=bool(result.collided), refusal=None if ref is None else ref.message,
            adjustments=int(result.adjustments), stamp_ns=_stamp(), rgb=obs.rgb, depth_m=obs.depth,
            K=np.asarray(obs.camera.K, dtype=np.float64), width=int(obs.camera.width),
            height=int(obs.camera.height), world_T_cam=T, objects=objects, action=result.action,
            refusal_detail=None if ref is None else ref.to_json(), move=result.move, target_ref=result.target,
            mode=result.mode)

    # ------------------------------------------------------------------ actions
    def reset(self, scene: str | int | None = None, target: int | str | None = None, seed: int | None = None,
              start: ArrayLike | None = None) -> BridgeStep:
        """Start an episode (closing the open one): ``start`` a free world_T_cam, else a seeded random start."""
        with self._lock:
            if self._episode is not None and self._open:
                self.close()
            r = self.manager.reset(scene=scene, target=target, seed=seed, width=self.width, height=self.height,
                                   start=None if start is None else np.asarray(start, dtype=np.float64),
                                   agent=self.agent)
            self._episode, self._open = r.episode_id, True
            return self._step(r)

    def set_pose(self, world_T_cam: ArrayLike) -> BridgeStep:
        """Teleport the camera (optical frame) to ``world_T_cam`` (metres, world = robot base)."""
        with self._lock:
            eid = self._current()
            return self._step(self.manager.set_pose(eid, np.asarray(world_T_cam, dtype=np.float64)))

    def move(self, linear: ArrayLike, angular: ArrayLike, duration: float, frame: str = "camera") -> BridgeStep:
        """Apply a constant twist (m/s, rad/s; ``frame`` "camera" or "world") for ``duration`` seconds."""
        with self._lock:
            eid = self._current()
            return self._step(self.manager.move(eid, np.asarray(linear, dtype=np.float64),
                                                np.asarray(angular, dtype=np.float64), float(duration), frame))

    def submit(self, estimates: list[Estimate]) -> EpisodeResult:
        """Hand in the estimates (camera frame of the current view), end the episode and score it."""
        with self._lock:
            eid = self._current()
            payload = []
            for i, e in enumerate(estimates):
                T = np.asarray(e.cam_T_obj, dtype=np.float64)
                if T.shape != (4, 4):
                    raise BridgeError(f"estimates.{i}.cam_T_obj: must be 4x4, got shape {T.shape}")
                payload.append({"obj_id": int(e.obj_id), "R": T[:3, :3].reshape(-1).tolist(),
                                "t_m": T[:3, 3].tolist(), "score": float(e.score)})
            scene_name = self.manager.get(eid).scene_name
            out = self.manager.submit(eid, payload, self.agent)
            self._open = False
            log_dir = self.manager.log_dir
            if log_dir is None:
                raise BridgeError("the episode was submitted but cannot be scored: the episode manager keeps "
                                  "no log (give it a log_dir)")
            log_path = Path(log_dir) / f"{eid}.jsonl"
            score = self.scorer.score(log_path, self.manager.scenes.bundle(scene_name))
            return EpisodeResult(eid, score.ar, score.ar_vsd, score.ar_mssd, score.ar_mspd,
                                 int(out["adjustments"]), int(out["steps"]), int(out["refusals"]),
                                 int(out["estimates"]), str(log_path), str(out.get("mode", self.manager.mode)))

    def close(self) -> dict[str, Any]:
        """Close the open episode without a submission (nothing to do when none is open)."""
        with self._lock:
            if self._episode is None or not self._open:
                return {"episode_id": self._episode, "closed": True, "reason": "no open episode"}
            self._open = False
            return self.manager.close(self._episode, "closed by the agent")
