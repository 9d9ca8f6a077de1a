"""A user's detector or pose estimator named on a command line: ``MODULE:FACTORY`` (``FACTORY`` a
callable of no arguments in an importable module, e.g. ``my_lab.pose:make_estimator``) or one of the
built-in names of :data:`BUILT_IN` (``learned``: the trained model of ``--learned-model``;
``learned-onnx``: the same model's ONNX export run by ONNX Runtime, ``brave6d learn export-onnx``;
``registration``: the weight-free depth registration, a pose estimator only)."""

from __future__ import annotations

import importlib
from typing import Any

from brave6d.core.errors import BraveError
from brave6d.evaluation.estimators.protocol import Detector, PoseEstimator

#: The built-in implementations by name, and what each can be.
BUILT_IN = {"learned": ("detector", "pose_estimator"), "learned-onnx": ("detector", "pose_estimator"),
            "registration": ("pose_estimator",)}
#: The built-in names that need the trained model (``AgentSetup.learned_model``).
NEEDS_MODEL = ("learned", "learned-onnx")
_INTERFACES = {"detector": Detector, "pose_estimator": PoseEstimator}


def load_factory(spec: str, role: str) -> Any:
    """The object ``FACTORY()`` returns for ``spec`` = ``MODULE:FACTORY``, checked to implement ``role``
    (``detector`` or ``pose_estimator``); one line naming ``spec`` when it does not load or does not fit."""
    if role not in _INTERFACES:
        raise ValueError(f"role must be one of {', '.join(_INTERFACES)}, got {role!r}")
    module_name, sep, attr = str(spec).partition(":")
    if not sep or not module_name.strip() or not attr.strip():
        raise BraveError(f"{role} {spec!r}: expected MODULE:FACTORY (e.g. my_lab.pose:make_estimator) or one of "
                         f"{', '.join(k for k, v in BUILT_IN.items() if role in v)}")
    try:
        target: Any = importlib.import_module(module_name.strip())
    except ImportError as exc:
        raise BraveError(f"{role} {spec!r}: cannot import {module_name!r} ({exc})") from None
    for part in attr.strip().split("."):
        if not hasattr(target, part):
            raise BraveError(f"{role} {spec!r}: module {module_name!r} has no {attr!r}")
        target = getattr(target, part)
    if not callable(target):
        raise BraveError(f"{role} {spec!r}: {attr!r} is not callable (give a factory of no arguments)")
    made = target()
    check_role(made, role, spec)
    return made


def check_role(obj: Any, role: str, source: str) -> None:
    """One line naming ``source`` when ``obj`` lacks the methods of ``role``'s interface."""
    interface = _INTERFACES[role]
    if not isinstance(obj, interface):
        need = "detect(image, K, obj_id=None)" if role == "detector" else \
            "add_model(obj_id, vertices_m, faces) and estimate(image, depth_m, K, detection)"
        raise BraveError(f"{role} {source}: a {type(obj).__name__} is not a {interface.__name__} (it needs {need}; "
                         "see brave6d.evaluation.estimators)")
