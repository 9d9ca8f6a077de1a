"""The render server's wire format: what one step or free view returns (observation, objects, images).

One definition for the server (which builds these from a rendered view), the OpenAPI docs
(FastAPI's ``response_model``) and the Python client (which validates every reply against them
and adds the decoded images, :mod:`brave6d.serve.client`). The episode log reuses :class:`ObjectState`
and :class:`TargetRef` (:mod:`brave6d.serve.episode_log`).

Matrices are NumPy arrays in Python and nested lists on the wire (``K`` 3x3, poses 4x4, metres,
OpenCV camera axes). Field order is the wire's key order: the browser viewer (``serve/viewer/``)
and existing clients read these names.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, PlainSerializer, PlainValidator, WithJsonSchema


#: A finite float (NaN and inf refused).
Finite = Annotated[float, Field(allow_inf_nan=False)]


def matrix_type(rows: int, cols: int, flat: bool = False) -> Any:
    """A ``rows x cols`` float64 array field: validated finite (nested or flat numbers accepted),
    serialised as nested lists (``flat``: one row-major list)."""

    def validate(value: Any) -> NDArray[np.float64]:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"must be a {rows}x{cols} matrix of numbers") from None
        if arr.size != rows * cols:
            what = f"{rows} numbers" if cols == 1 else f"a {rows}x{cols} matrix ({rows * cols} numbers)"
            raise ValueError(f"must be {what}, got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("must be finite (NaN and inf are refused)")
        return arr.reshape(rows) if cols == 1 else arr.reshape(rows, cols)

    if flat:
        schema: dict[str, Any] = {"type": "array", "minItems": rows * cols, "maxItems": rows * cols,
                                  "items": {"type": "number"}}
    else:
        schema = {"type": "array", "minItems": rows, "maxItems": rows,
                  "items": {"type": "array", "minItems": cols, "maxItems": cols, "items": {"type": "number"}}}

    def serialise(a: NDArray[np.float64]) -> list[Any]:
        arr = np.asarray(a)
        return arr.reshape(-1).tolist() if flat or cols == 1 else arr.tolist()

    return Annotated[NDArray[np.float64], PlainValidator(validate), PlainSerializer(serialise, return_type=list),
                     WithJsonSchema(schema)]


#: A 4x4 rigid transform (metres) as an array; nested lists on the wire.
Matrix4 = matrix_type(4, 4)
#: A 3x3 matrix (intrinsics ``K``, rotations) as an array; nested lists on the wire.
Matrix3 = matrix_type(3, 3)
#: A 3-vector (e.g. a translation in metres) as an array; a list on the wire.
Vector3 = matrix_type(3, 1)


class WireModel(BaseModel):
    """Base of the wire and log models: immutable, NumPy arrays allowed."""

    model_config = ConfigDict(frozen=True, arbitrary_types_allowed=True)


class TargetRef(WireModel):
    """The instance an episode asks for (``gt_id`` = index in BOP's ``scene_gt`` lists)."""

    gt_id: int
    obj_id: int
    name: str


class ObjectState(WireModel):
    """Ground truth of one object instance in one view: ``cam_T_obj`` (metres) and how much of it
    is visible (BOP ``scene_gt_info`` style; all None when the server computes no visibility)."""

    gt_id: int
    obj_id: int
    name: str
    is_target: bool
    cam_T_obj: Matrix4
    px_count_all: int | None = None
    px_count_visib: int | None = None
    visib_fract: Finite | None = None
    bbox_obj: list[int] | None = None
    bbox_visib: list[int] | None = None

    @property
    def cam_R_m2c(self) -> NDArray[np.float64]:
        """BOP's rotation (model to camera)."""
        return self.cam_T_obj[:3, :3]

    @property
    def cam_t_m2c_mm(self) -> NDArray[np.float64]:
        """BOP's translation (millimetres)."""
        return self.cam_T_obj[:3, 3] * 1000.0


class EncodedImage(WireModel):
    """An image on the wire: ``png``/``jpeg`` bytes or ``f32`` (little-endian float32, row-major), base64."""

    encoding: str
    data: str
    shape: list[int]


class ObservationMessage(WireModel):
    """One view: image size, intrinsics, camera pose, images (None when not requested), objects."""

    width: int
    height: int
    K: Matrix3
    world_T_cam: Matrix4
    rgb: EncodedImage | None
    depth: EncodedImage | None
    objects: list[ObjectState]

    def target(self) -> ObjectState | None:
        return next((o for o in self.objects if o.is_target), None)


class StepMessage(WireModel):
    """The reply to ``reset``, ``set_pose`` and ``move``: the outcome and the (new or kept) view.

    ``refusal`` is ``{code, message, ...}`` when the action was refused or stopped; ``target`` is a
    :class:`TargetRef` as a dict (``{}`` when the view has no target); ``move`` says how far a move got;
    ``mode`` is the server's (:mod:`brave6d.serve.modes`: a ``scored`` server's observations list no
    objects; a server older than the modes sent none, and served the truth: ``training``).
    """

    episode_id: str
    action: str
    step: int
    accepted: bool
    collided: bool
    refusal: dict[str, Any] | None
    adjustments: int
    move: dict[str, Any] | None
    target: dict[str, Any]
    observation: ObservationMessage
    timings_ms: dict[str, float]
    mode: str = "training"


class RenderMessage(WireModel):
    """The reply to ``POST /render`` (a free view, no episode): the scene's name and the view of the
    splat; its ``objects`` are always empty (a free view carries no ground truth)."""

    scene: str
    observation: ObservationMessage
    timings_ms: dict[str, float]


class ErrorMessage(BaseModel):
    """Every error reply: ``{error, field, status}``."""

    error: str
    field: str | None = None
    status: int
