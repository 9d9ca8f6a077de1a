"""The two modes of a server, and what each lets reach an agent.

* ``scored`` (the default of ``brave6d serve``, ``brave6d ros1``/``ros2``, ``BraveEnv`` and
  ``BraveVectorEnv``): an agent gets only what the task defines: the target's ids and CAD model,
  the camera's pose, intrinsics and images, refusals and adjustments. No object pose, box, visible
  fraction or placement leaves the server (observations carry no objects, ``GET /bundle`` no
  ``world_T_obj``, ``/tf`` no ``gt/`` frames); the score is known once ``submit`` closes the episode.
* ``training`` (asked for explicitly: ``--training``, ``mode="training"``): the paper's interface,
  every object's ground truth in every observation, for developing and training agents.

The episode log records the mode either way (it always holds the truth scoring needs: it is the
server's file), and ``brave6d evaluate`` ranks scored episodes only.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from brave6d.core.errors import BraveError

SCORED = "scored"
TRAINING = "training"
#: Every mode, the default first.
MODES = (SCORED, TRAINING)
Mode = Literal["scored", "training"]
#: The fields of ``GET /bundle``'s objects a scored server keeps (the target's identity and CAD model).
PUBLIC_OBJECT_FIELDS = ("gt_id", "obj_id", "name", "class", "model", "diameter_mm", "symmetries_discrete_mm",
                        "symmetries_continuous")


def check_mode(mode: str, where: str = "mode") -> Mode:
    """``mode`` when it is one of :data:`MODES`, else a one-line :class:`BraveError` naming ``where``."""
    if mode not in MODES:
        raise BraveError(f"{where}: must be {' or '.join(repr(m) for m in MODES)}, got {mode!r}")
    return mode  # type: ignore[return-value]


def public_bundle(summary: Mapping[str, Any], mode: str) -> dict[str, Any]:
    """``GET /bundle``'s description as ``mode`` shows it: scored keeps of each object only
    :data:`PUBLIC_OBJECT_FIELDS` (no ``world_T_obj``); training shows it all."""
    out = {**summary, "mode": mode}
    if mode == SCORED:
        out["objects"] = [{k: o[k] for k in PUBLIC_OBJECT_FIELDS if k in o} for o in summary.get("objects", [])]
    return out
