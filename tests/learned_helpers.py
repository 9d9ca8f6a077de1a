"""Shared by the learned-estimator tests: a BOP models folder for a scene spec's objects, a tiny
train_pbr of the demo scene, and an untrained model (what every "fails for an untrained model"
assertion compares against)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brave6d.annotation import dump_bop_json, load_mesh
from brave6d.annotation.models import model_info_mm, write_ply
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
    out.mkdir(parents=True, exist_ok=True)
    info = {}
    for obj_id, obj in enumerate(sorted(spec.objects, key=lambda o: o.name), start=1):
        mesh = load_mesh(spec_path.parent / obj.mesh)
        vertices_mm = np.asarray(mesh.vertices) * obj.scale * 1000.0
        write_ply(out / f"obj_{obj_id:06d}.ply", vertices_mm, mesh.faces, mesh.vertex_colors)
        sym = obj.symmetry
        discrete = [np.asarray(m, dtype=np.float64).reshape(4, 4) for m in (sym.discrete if sym else [])]
        continuous = [(axis, (0.0, 0.0, 0.0)) for axis in (sym.continuous_axes if sym else [])]
        info[obj_id] = model_info_mm(vertices_mm, discrete, continuous)
    (out / "models_info.json").write_text(dump_bop_json(info))
    return out


def untrained_model(preset: LearnPreset, obj_ids: list[int], seed: int = 0) -> LearnedModel:
    """A model with freshly initialised networks (objects of 20 mm radius)."""
    import torch

    torch.manual_seed(seed)
    det, pose = Detector(len(obj_ids), preset.detector_width), CoordinateNet(len(obj_ids), preset.pose_width)
    objects = {o: ObjectNorm(o, k, np.zeros(3), 20.0, 40.0) for k, o in enumerate(obj_ids)}
    return LearnedModel(preset.to_json(), objects, det.state_dict(), pose.state_dict(), "untrained")
