"""The release's ``manifest.json`` (owned here): what made the release and what is in it.

``format``, the dataset's name/version/license, creation time, the versions of everything that
made it (python, brave6d, numpy, torch, ... and the git commit when known), counts, the size of
every file, the object library (with which objects have a model) and, per scene, its
``scene_id``, name, views, holdout views, objects, instances, targets and holdout PSNR; and, when
the release ships the dataset's learned model, ``learned_model`` (:mod:`brave6d.dataset.release.learned`);
when it ships the ROS 2 interfaces wheel, ``ros2_interfaces`` (:mod:`brave6d.dataset.release.ros2_wheel`).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Any

from brave6d.core.atomic import read_json
from brave6d.core.names import folder_name_problem
from brave6d.core.provenance import software_versions
from brave6d.dataset.release.collect import ReleaseModel, SceneRelease
from brave6d.dataset.release.formats import FORMAT, bundle_zip
from brave6d.dataset.release.source import ReleaseError, ReleaseSource

PACKAGES = ("brave6d", "numpy", "torch", "scipy", "plyfile", "opencv-contrib-python-headless", "open3d",
            "pycolmap", "gsplat", "fastapi")


def versions() -> dict[str, str]:
    """Versions of python and the packages that make a release (``brave6d.core.provenance``)."""
    return software_versions(PACKAGES)


def scene_entry(s: SceneRelease, release_name: str) -> dict[str, Any]:
    """One scene's entry in the manifest (and in ``dataset_info.json``)."""
    return {"scene_id": s.source.scene_id, "name": s.source.name, "views": len(s.im_ids),
            "holdout_views": len(s.holdout), "holdout_im_ids": s.holdout, "depth": s.has_depth,
            "objects": [{"obj_id": k, "name": v} for k, v in sorted(s.objects.items())],
            "instances": s.instances, "targets": s.targets, "holdout_psnr": s.psnr,
            "levels": [{"level": lv.level, "distance_m": lv.distance_m, "views": lv.views,
                        "holdout_views": lv.holdout_views, "targets": lv.targets, "holdout_psnr": lv.psnr}
                       for lv in s.levels],
            "bundle": bundle_zip(release_name, s.source.scene_id)}


def library_entries(source: ReleaseSource, models: dict[int, ReleaseModel]) -> list[dict[str, Any]]:
    return [{"obj_id": o.obj_id, "name": o.name, "category": o.category, "description": o.description,
             "model": o.obj_id in models,
             "diameter_mm": float(models[o.obj_id].info["diameter"]) if o.obj_id in models else None}
            for o in source.objects]


def make_manifest(source: ReleaseSource, scenes: list[SceneRelease], models: dict[int, ReleaseModel],
                  sizes: dict[str, int], learned: dict[str, Any] | None = None,
                  ros2_interfaces: dict[str, Any] | None = None) -> dict[str, Any]:
    """The manifest's content (``sizes``: bytes of every release file but the manifest and SHA256SUMS;
    ``learned``, ``ros2_interfaces``: the learned model's and the interfaces wheel's entries, when shipped)."""
    manifest = {
        "format": FORMAT, "name": source.name, "version": source.version, "license": source.license,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "versions": versions(),
        "counts": {"scenes": len(scenes), "objects": len(source.objects), "models": len(models),
                   "images": sum(len(s.im_ids) for s in scenes), "instances": sum(s.instances for s in scenes),
                   "targets": sum(s.targets for s in scenes), "holdout_images": sum(len(s.holdout) for s in scenes)},
        "files": {name: {"bytes": n} for name, n in sorted(sizes.items())},
        "total_bytes": sum(sizes.values()),
        "objects": library_entries(source, models),
        "scenes": [scene_entry(s, source.name) for s in scenes],
    }
    if learned is not None:
        manifest["learned_model"] = learned
    if ros2_interfaces is not None:
        manifest["ros2_interfaces"] = ros2_interfaces
    return manifest


def read_manifest(path: Path) -> dict[str, Any]:
    """Read a release manifest, checking the fields ``release verify`` and the server rely on.

    A downloaded manifest is untrusted: its ``name``, ``version`` and scene names become path parts
    (``<name>_bundle_XXXXXX.zip``, the cache's ``<name>-<version>-<digest>/``), so each must pass
    :func:`brave6d.core.names.folder_name_problem`.
    """
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        got = data.get("format") if isinstance(data, dict) else None
        raise ReleaseError(f"{path}: field 'format': {got!r} is not a release manifest ({FORMAT!r})")
    for key in ("name", "version"):
        if (problem := folder_name_problem(data.get(key))) is not None:
            raise ReleaseError(f"{path}: field '{key}': {problem}")
    for key in ("scenes", "objects"):
        if not isinstance(data.get(key), list) or not all(isinstance(e, dict) for e in data[key]):
            raise ReleaseError(f"{path}: field '{key}': a list of objects is required")
    for i, s in enumerate(data["scenes"]):
        for key in ("scene_id", "views"):
            if not isinstance(s.get(key), int):
                raise ReleaseError(f"{path}: field 'scenes[{i}].{key}': an integer is required")
        if not isinstance(s.get("depth"), bool) or not isinstance(s.get("name"), str):
            raise ReleaseError(f"{path}: field 'scenes[{i}]': 'name' (string) and 'depth' (bool) are required")
        if (problem := folder_name_problem(s["name"])) is not None:
            raise ReleaseError(f"{path}: field 'scenes[{i}].name': {problem}")
    for i, o in enumerate(data["objects"]):
        if not isinstance(o.get("obj_id"), int) or not isinstance(o.get("name"), str):
            raise ReleaseError(f"{path}: field 'objects[{i}]': 'obj_id' (integer) and 'name' are required")
    return data
