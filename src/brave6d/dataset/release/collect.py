"""Gather, per scene, what the release takes from it, and check it before anything is written.

For each scene directory: its BOP export (``annotation/bop/``, read through annotation's
readers), the held-out views (the bundle's ``holdout.json``, read through ``brave6d.serve.load_bundle``,
which verifies the bundle), the distance level of each view (``capture/frames.jsonl``) and the
holdout PSNR (``splat/metrics.json``). Checks: the export's three JSON files list the same
images, every referenced image and mask exists, every object's BOP ``obj_id`` is its position in
the dataset's library, and the scenes' models of one object agree.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.annotation import (BopLayout, load_annotation, read_models_info, read_ply_mesh, read_scene_camera,
                        read_scene_gt, read_scene_gt_info)
from brave6d.core.atomic import file_sha256, read_json
from brave6d.core.errors import DataError
from brave6d.core.layout import SceneDir
from brave6d.dataset.release.formats import MIN_VISIB_FRACT
from brave6d.dataset.release.source import ReleaseError, ReleaseSource, SceneSource


@dataclass(frozen=True)
class LevelStats:
    """Statistics of one capture distance level of a scene."""

    level: int
    distance_m: float | None
    views: int
    holdout_views: int
    targets: int
    psnr: float | None


@dataclass
class SceneRelease:
    """What the release takes from one scene (paths into the scene directory) and its statistics."""

    source: SceneSource
    layout: BopLayout
    bundle_root: Path
    im_ids: list[int]
    gt_obj_ids: dict[int, list[int]]
    visib: dict[int, list[float]]
    holdout: list[int]
    holdout_view_ids: list[str]
    has_depth: bool
    objects: dict[int, str]  # obj_id -> name
    psnr: float | None
    levels: list[LevelStats] = field(default_factory=list)

    @property
    def instances(self) -> int:
        return sum(len(v) for v in self.gt_obj_ids.values())

    @property
    def targets(self) -> int:
        return sum(1 for vs in self.visib.values() for v in vs if v >= MIN_VISIB_FRACT)

    def image_files(self) -> list[tuple[Path, str]]:
        """``(source file, path inside the scene folder)`` of every image and mask, in image order."""
        out = []
        lay = self.layout
        for im_id in self.im_ids:
            out.append((lay.rgb_path(im_id), f"rgb/{im_id:06d}.png"))
            if self.has_depth:
                out.append((lay.depth_path(im_id), f"depth/{im_id:06d}.png"))
            for gt_id in range(len(self.gt_obj_ids[im_id])):
                out.append((lay.mask_path(im_id, gt_id), f"mask/{im_id:06d}_{gt_id:06d}.png"))
                out.append((lay.mask_visib_path(im_id, gt_id), f"mask_visib/{im_id:06d}_{gt_id:06d}.png"))
        return out


def collect_scene(scene_source: SceneSource, release: ReleaseSource) -> SceneRelease:
    """Read and check one scene (see the module docstring); errors name the scene's file."""
    from brave6d.serve import load_bundle

    scene = SceneDir(scene_source.root)
    layout = BopLayout.of_scene(scene)
    gt = read_scene_gt(layout.scene_gt_path)
    cams = read_scene_camera(layout.scene_camera_path)
    info = read_scene_gt_info(layout.scene_gt_info_path)
    for path, ids in ((layout.scene_camera_path, cams), (layout.scene_gt_info_path, info)):
        if set(ids) != set(gt):
            odd = sorted(set(ids) ^ set(gt))[:3]
            raise ReleaseError(f"{path}: lists other images than {layout.scene_gt_path.name} (e.g. {odd})")
    for im_id, entries in gt.items():
        if len(info[im_id]) != len(entries):
            raise ReleaseError(f"{layout.scene_gt_info_path}: image {im_id} has {len(info[im_id])} entries, "
                               f"{layout.scene_gt_path.name} has {len(entries)}")
    im_ids = sorted(gt)
    if not im_ids:
        raise ReleaseError(f"{layout.scene_gt_path}: no images; export the scene's BOP ground truth again")
    objects = _library_ids(scene, gt, release)
    depth = [layout.depth_path(i).is_file() for i in im_ids]
    if any(depth) and not all(depth):
        missing = im_ids[depth.index(False)]
        raise ReleaseError(f"{layout.depth_path(missing)}: depth missing for this image while other images have one")
    try:
        bundle = load_bundle(scene.bundle_dir)
    except DataError as exc:
        raise ReleaseError(f"scene {scene_source.name}: {exc} (run 'brave6d export {scene.root}')") from None
    for o in bundle.objects:
        if objects.get(o.obj_id, o.name) != o.name or release.obj_id_of(o.name) != o.obj_id:
            raise ReleaseError(f"{scene.bundle_dir}/objects.json: object {o.name!r} has obj_id {o.obj_id}, the "
                               f"dataset library gives it {release.obj_id_of(o.name)}; export the bundle again")
    held = sorted((h.index, h.view_id) for h in bundle.holdout if h.index in gt)
    rel = SceneRelease(scene_source, layout, bundle.root, im_ids,
                       {i: [g.obj_id for g in gt[i]] for i in im_ids},
                       {i: [g.visib_fract for g in info[i]] for i in im_ids},
                       [i for i, _ in held], [v for _, v in held], all(depth), objects, None)
    for src, _ in rel.image_files():
        if not src.is_file():
            raise ReleaseError(f"{src}: referenced by {layout.scene_gt_path.name} but missing; export the BOP "
                               "ground truth again")
    rel.psnr, level_psnr = _holdout_psnr(scene)
    rel.levels = _levels(scene, rel, level_psnr)
    return rel


def _library_ids(scene: SceneDir, gt: dict[int, Any], release: ReleaseSource) -> dict[int, str]:
    """``{obj_id: name}`` of the objects in the scene's ground truth; each id must be the library's."""
    annotation = load_annotation(scene)
    names = {o.obj_id: o.name for o in annotation.objects}
    used = sorted({g.obj_id for gts in gt.values() for g in gts})
    out = {}
    for obj_id in used:
        name = names.get(obj_id)
        if name is None:
            raise ReleaseError(f"{scene.objects_path}: obj_id {obj_id} of the BOP export is not "
                               "an annotated object; export the BOP ground truth again")
        if release.obj_id_of(name) != obj_id:
            want = release.obj_id_of(name)
            why = "is not in the dataset's object library" if want is None else f"is obj_id {want} in the library"
            raise ReleaseError(f"{scene.objects_path}: object {name!r} has obj_id {obj_id} but "
                               f"{why} ({release.workdir / 'dataset.yaml'}); annotate the scene with the library's ids")
        out[obj_id] = name
    return out


def _holdout_psnr(scene: SceneDir) -> tuple[float | None, dict[int, float]]:
    """Holdout PSNR of the scene's training, overall and per distance level (None/empty when not trained)."""
    path = scene.metrics_path
    if not path.is_file():
        return None, {}
    data = read_json(path)
    hold = data.get("holdout") if isinstance(data, dict) else None
    if not isinstance(hold, dict):
        return None, {}
    levels = {}
    for key, entry in (hold.get("per_level") or {}).items():
        if isinstance(entry, dict) and isinstance(entry.get("psnr"), (int, float)):
            levels[int(key)] = float(entry["psnr"])
    psnr = hold.get("psnr")
    return (float(psnr) if isinstance(psnr, (int, float)) else None), levels


def _levels(scene: SceneDir, rel: SceneRelease, psnr: dict[int, float]) -> list[LevelStats]:
    frames = {r.index: r for r in scene.frames()} if scene.frames_path.is_file() else {}
    by_level: dict[int, list[int]] = defaultdict(list)
    distance: dict[int, float | None] = {}
    for im_id in rel.im_ids:
        r = frames.get(im_id)
        level = r.distance_level if r is not None else -1
        by_level[level].append(im_id)
        distance[level] = r.distance_m if r is not None else None
    held = set(rel.holdout)
    return [LevelStats(lvl, distance[lvl], len(ims), sum(1 for i in ims if i in held),
                       sum(1 for i in ims for v in rel.visib[i] if v >= MIN_VISIB_FRACT), psnr.get(lvl))
            for lvl, ims in sorted(by_level.items())]


# ----------------------------------------------------------------------------- models
@dataclass(frozen=True)
class ReleaseModel:
    obj_id: int
    path: Path
    info: dict[str, Any]


def collect_models(scenes: list[SceneRelease]) -> dict[int, ReleaseModel]:
    """One model (mm) per ``obj_id`` across the scenes' BOP exports; copies must agree."""
    out: dict[int, ReleaseModel] = {}
    for s in scenes:
        infos = read_models_info(s.layout.models_info_path)
        for obj_id in sorted(s.objects):
            path = s.layout.model_path(obj_id)
            if obj_id not in infos:
                raise ReleaseError(f"{s.layout.models_info_path}: no entry for obj_id {obj_id} of the ground truth")
            if not path.is_file():
                raise ReleaseError(f"{path}: model of obj_id {obj_id} missing; export the BOP ground truth again")
            first = out.get(obj_id)
            if first is None:
                out[obj_id] = ReleaseModel(obj_id, path, infos[obj_id])
            elif not _same_model(first, path, infos[obj_id]):
                raise ReleaseError(f"{path}: model of obj_id {obj_id} differs from {first.path}; one object must "
                                   "have one mesh and scale in every scene of the dataset")
    return out


def _same_model(first: ReleaseModel, path: Path, info: dict[str, Any]) -> bool:
    if file_sha256(first.path) == file_sha256(path):
        return True
    a, b = read_ply_mesh(first.path), read_ply_mesh(path)
    if a.vertices.shape != b.vertices.shape or not np.array_equal(a.faces, b.faces):
        return False
    d1, d2 = float(first.info["diameter"]), float(info["diameter"])
    return bool(np.allclose(a.vertices, b.vertices, atol=1e-3)) and abs(d1 - d2) <= 1e-3
