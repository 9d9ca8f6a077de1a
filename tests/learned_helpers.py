"""Shared by the learned-estimator tests: a BOP models folder for a scene spec's objects, a tiny
train_pbr of the demo scene, and an untrained model (what every "fails for an untrained model"
assertion compares against)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brave6d.annotation import write_bop_models
from brave6d.core.spec import load_scene_spec
from brave6d.evaluation.learned.model_file import LearnedModel, ObjectNorm
from brave6d.evaluation.learned.networks import CoordinateNet, Detector
from brave6d.evaluation.learned.presets import LearnPreset

ROOT = Path(__file__).resolve().parent.parent
DEMO_SPEC = ROOT / "data" / "demo" / "scene.yaml"


def write_models(spec_path: Path, out: Path) -> Path:
    """``out/obj_XXXXXX.ply`` (mm) and ``models_info.json`` of the spec's objects, obj_ids by sorted
    name (as ``brave6d synth`` and the BOP export number a scene's objects)."""
    spec = load_scene_spec(spec_path)
    objects = sorted(spec.objects, key=lambda o: o.name)
    return write_bop_models(out, [(obj_id, spec_path.parent / o.mesh, float(o.scale), o.symmetry)
                                  for obj_id, o in enumerate(objects, start=1)])


def untrained_model(preset: LearnPreset, obj_ids: list[int], seed: int = 0) -> LearnedModel:
    """A model with freshly initialised networks (objects of 20 mm radius)."""
    import torch

    torch.manual_seed(seed)
    det, pose = Detector(len(obj_ids), preset.detector_width), CoordinateNet(len(obj_ids), preset.pose_width)
    objects = {o: ObjectNorm(o, k, np.zeros(3), 20.0, 40.0) for k, o in enumerate(obj_ids)}
    return LearnedModel(preset.to_json(), objects, det.state_dict(), pose.state_dict(), "untrained")
