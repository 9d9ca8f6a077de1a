"""``brave6d release verify OUT``: check a release folder completely; the first problem is an error.

In order: every file's checksum against ``SHA256SUMS`` (and no file left out of it), the manifest,
every zip's CRCs, every JSON file inside against its reader (annotation's BOP readers, the
release's own), every image and mask that ``scene_gt``/``scene_camera`` reference, object ids
(the same name has the same ``obj_id`` in every scene, in ``models_info`` and in the library),
the targets, that each scene's bundle loads (``serve.load_bundle`` verifies its manifest) and, when
the release has one, the synthetic training split (:mod:`dataset.release.train_pbr`).
"""

from __future__ import annotations

import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from annotation import read_models_info, read_ply_mesh, read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.atomic import file_sha256, read_json
from brave6d.errors import DataError
from brave6d.progress import progress
from dataset.release.formats import (CAMERA, DATASET_INFO, HOLDOUT, MANIFEST, SUMS, TARGETS, TARGETS_HOLDOUT,
                                     base_zip, bundle_folder, bundle_zip, models_zip, read_holdout,
                                     read_sha256sums, read_targets, scene_folder, test_zip, train_pbr_zip)
from dataset.release.manifest import read_manifest
from dataset.release.source import ReleaseError
from dataset.release.train_pbr import check_train_pbr_zip
from dataset.release.zips import member_outside

T = TypeVar("T")


@dataclass(frozen=True)
class VerifyReport:
    """What a successful verification checked."""

    root: Path
    files: int
    bytes: int
    scenes: int
    images: int
    bundles: int
    train_pbr_images: int = 0  # images of the synthetic training split (0: the release has none)


def verify_release(root: Path | str) -> VerifyReport:
    """Verify the release folder ``root`` (see the module docstring); raises :class:`ReleaseError`."""
    base = Path(root)
    if not base.is_dir():
        raise ReleaseError(f"{base}: release folder not found")
    sums = _check_sums(base)
    if MANIFEST not in sums:
        raise ReleaseError(f"{base / SUMS}: does not list {MANIFEST}")
    manifest = read_manifest(base / MANIFEST)
    name = manifest["name"]
    scenes = manifest["scenes"]
    zips = [base_zip(name), models_zip(name), test_zip(name), *(bundle_zip(name, s["scene_id"]) for s in scenes)]
    for z in zips:
        if z not in sums:
            raise ReleaseError(f"{base / z}: required by {MANIFEST} but not in the release")
    with tempfile.TemporaryDirectory(prefix="brave6d-verify-") as tmp_dir:
        tmp = Path(tmp_dir)
        opened = {z: _open_zip(base / z) for z in zips}
        try:
            library = {int(o["obj_id"]): str(o["name"]) for o in manifest["objects"]}
            models = _check_models(opened[models_zip(name)], models_zip(name), library, tmp)
            gts = _check_test(opened[test_zip(name)], test_zip(name), scenes, library, models, tmp)
            _check_base(opened[base_zip(name)], base_zip(name), name, scenes, gts, tmp)
        finally:
            for zf in opened.values():
                zf.close()
        for s in progress(scenes, desc="bundles", unit="bundle"):
            _check_bundle(base / bundle_zip(name, s["scene_id"]), s, library, tmp)
    pbr = train_pbr_zip(name)
    pbr_images = check_train_pbr_zip(base / pbr, models) if pbr in sums else 0
    return VerifyReport(base, len(sums) + 1, sum((base / n).stat().st_size for n in sums), len(scenes),
                        sum(len(g) for k, g in gts.items() if k > 0), len(scenes), pbr_images)


def _check_sums(base: Path) -> dict[str, str]:
    sums = read_sha256sums(base / SUMS)
    present = {p.relative_to(base).as_posix() for p in base.rglob("*") if p.is_file() or p.is_symlink()} - {SUMS}
    for name in sorted(present - set(sums)):
        raise ReleaseError(f"{base / name}: not listed in {SUMS} (a file that is not part of the release)")
    for name in sorted(set(sums) - present):
        raise ReleaseError(f"{base / name}: listed in {SUMS} but missing")
    for name in progress(sorted(sums), desc="checksums", unit="file"):
        digest = file_sha256(base / name)
        if digest != sums[name]:
            raise ReleaseError(f"{base / name}: sha256 {digest[:12]}... does not match {SUMS} "
                               f"({sums[name][:12]}...); the file was altered or truncated")
    return sums


def _open_zip(path: Path) -> zipfile.ZipFile:
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ReleaseError(f"{path}: not a readable zip ({exc})") from None
    try:
        bad = zf.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:  # zlib/truncation errors
        zf.close()
        raise ReleaseError(f"{path}: corrupt zip ({exc})") from None
    if bad is not None:
        zf.close()
        raise ReleaseError(f"{path}: member {bad}: CRC check failed (the zip is corrupt)")
    return zf


def _extract(zf: zipfile.ZipFile, zip_name: str, member: str, tmp: Path) -> Path:
    try:
        zf.getinfo(member)
    except KeyError:
        raise ReleaseError(f"{zip_name}: {member}: missing") from None
    return Path(zf.extract(member, tmp / zip_name))


def _read(reader: Callable[[Path], T], zf: zipfile.ZipFile, zip_name: str, member: str, tmp: Path) -> T:
    """Run a file reader on a zip member; its errors name ``zip:member`` rather than the temporary file."""
    path = _extract(zf, zip_name, member, tmp)
    try:
        return reader(path)
    except DataError as exc:
        raise ReleaseError(str(exc).replace(str(path), f"{zip_name}:{member}")) from None


def _check_models(zf: zipfile.ZipFile, zip_name: str, library: dict[int, str], tmp: Path) -> dict[int, Any]:
    info = _read(read_models_info, zf, zip_name, "models/models_info.json", tmp)
    for obj_id in sorted(info):
        if obj_id not in library:
            raise ReleaseError(f"{zip_name}:models/models_info.json: obj_id {obj_id} is not in the object library "
                               f"of {MANIFEST}")
        _read(read_ply_mesh, zf, zip_name, f"models/obj_{obj_id:06d}.ply", tmp)
    return info


def _check_test(zf: zipfile.ZipFile, zip_name: str, scenes: list[dict[str, Any]], library: dict[int, str],
                models: dict[int, Any], tmp: Path) -> dict[int, dict[int, list[int]]]:
    """Check every scene folder; returns ``{scene_id: {im_id: [obj_id per gt]}}`` (and holdout under -id)."""
    names = set(zf.namelist())
    out: dict[int, dict[int, list[int]]] = {}
    for s in scenes:
        sid, folder = s["scene_id"], scene_folder(s["scene_id"])
        gt = _read(read_scene_gt, zf, zip_name, f"{folder}/scene_gt.json", tmp)
        cam = _read(read_scene_camera, zf, zip_name, f"{folder}/scene_camera.json", tmp)
        info = _read(read_scene_gt_info, zf, zip_name, f"{folder}/scene_gt_info.json", tmp)
        holdout = _read(read_holdout, zf, zip_name, f"{folder}/{HOLDOUT}", tmp)
        for other, ids in (("scene_camera.json", cam), ("scene_gt_info.json", info)):
            if set(ids) != set(gt):
                odd = sorted(set(ids) ^ set(gt))[:3]
                raise ReleaseError(f"{zip_name}:{folder}/{other}: lists other images than scene_gt.json (e.g. {odd})")
        if len(gt) != s["views"]:
            raise ReleaseError(f"{zip_name}:{folder}/scene_gt.json: {len(gt)} images, {MANIFEST} says {s['views']}")
        if not set(holdout) <= set(gt):
            raise ReleaseError(f"{zip_name}:{folder}/{HOLDOUT}: image {sorted(set(holdout) - set(gt))[0]} is not in "
                               "scene_gt.json")
        scene_objects = {int(o["obj_id"]): o["name"] for o in s.get("objects", [])}
        for im_id in sorted(gt):
            needed = [f"rgb/{im_id:06d}.png"] + ([f"depth/{im_id:06d}.png"] if s["depth"] else [])
            if len(info[im_id]) != len(gt[im_id]):
                raise ReleaseError(f"{zip_name}:{folder}/scene_gt_info.json: image {im_id} has {len(info[im_id])} "
                                   f"entries, scene_gt.json has {len(gt[im_id])}")
            for gt_id, g in enumerate(gt[im_id]):
                needed += [f"mask/{im_id:06d}_{gt_id:06d}.png", f"mask_visib/{im_id:06d}_{gt_id:06d}.png"]
                where = f"{zip_name}:{folder}/scene_gt.json: image {im_id} instance {gt_id}: obj_id {g.obj_id}"
                if g.obj_id not in models:
                    raise ReleaseError(f"{where} has no model in models_info.json")
                if scene_objects.get(g.obj_id) != library.get(g.obj_id):
                    raise ReleaseError(f"{where} is {scene_objects.get(g.obj_id)!r} in this scene but "
                                       f"{library.get(g.obj_id)!r} in the object library ({MANIFEST})")
            for rel in needed:
                if f"{folder}/{rel}" not in names:
                    raise ReleaseError(f"{zip_name}: {folder}/{rel}: missing (image {im_id} is referenced by "
                                       "scene_gt.json and scene_camera.json)")
        out[sid] = {im: [g.obj_id for g in gts] for im, gts in gt.items()}
        out[-sid] = {im: [] for im in holdout}
    return out


def _check_base(zf: zipfile.ZipFile, zip_name: str, name: str, scenes: list[dict[str, Any]],
                gts: dict[int, dict[int, list[int]]], tmp: Path) -> None:
    camera = _read(read_json, zf, zip_name, f"{name}/{CAMERA}", tmp)
    for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"):
        if not isinstance(camera, dict) or not isinstance(camera.get(key), (int, float)):
            raise ReleaseError(f"{zip_name}:{name}/{CAMERA}: field '{key}': a number is required")
    info = _read(read_json, zf, zip_name, f"{name}/{DATASET_INFO}", tmp)
    ids = [s.get("scene_id") for s in info.get("scenes", [])] if isinstance(info, dict) else None
    if ids != [s["scene_id"] for s in scenes]:
        raise ReleaseError(f"{zip_name}:{name}/{DATASET_INFO}: field 'scenes': scene ids {ids} differ from "
                           f"{MANIFEST}'s")
    for member, holdout_only in ((TARGETS, False), (TARGETS_HOLDOUT, True)):
        shown = f"{zip_name}:{name}/{member}"
        for i, t in enumerate(_read(lambda p, s=shown: read_targets(p, s), zf, zip_name, f"{name}/{member}", tmp)):
            ims = gts.get(t["scene_id"], {})
            if t["im_id"] not in ims or t["obj_id"] not in ims[t["im_id"]]:
                raise ReleaseError(f"{shown}: target [{i}] (scene {t['scene_id']}, image {t['im_id']}, obj_id "
                                   f"{t['obj_id']}) is not in that scene's scene_gt.json")
            if holdout_only and t["im_id"] not in gts.get(-t["scene_id"], {}):
                raise ReleaseError(f"{shown}: target [{i}]: image {t['im_id']} of scene {t['scene_id']} is not a "
                                   "holdout image")


def _check_bundle(path: Path, scene: dict[str, Any], library: dict[int, str], tmp: Path) -> None:
    from serve import load_bundle

    folder = bundle_folder(scene["scene_id"])
    target = tmp / "bundles" / path.stem
    with zipfile.ZipFile(path) as zf:
        bad = member_outside(zf.namelist(), folder)
        if bad is not None:
            raise ReleaseError(f"{path}: member {bad} lies outside {folder}/")
        zf.extractall(target)
    try:
        bundle = load_bundle(target / folder)
    except DataError as exc:
        raise ReleaseError(f"{path}: the bundle does not load: {str(exc).replace(str(target), path.name)}") from None
    for o in bundle.objects:
        if library.get(o.obj_id) != o.name:
            raise ReleaseError(f"{path}: {folder}/objects.json: object {o.name!r} has obj_id {o.obj_id}, which is "
                               f"{library.get(o.obj_id)!r} in the object library ({MANIFEST})")
