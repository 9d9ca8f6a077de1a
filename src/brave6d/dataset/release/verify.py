"""``brave6d release verify OUT``: check a release folder completely; the first problem is an error.

In order: every file's checksum against ``SHA256SUMS`` (and no file left out of it), the manifest,
every zip's directory (member names and sizes: :func:`brave6d.dataset.release.zips.open_zip`), every JSON
file inside against its reader (annotation's BOP readers, the release's own), every image and mask
that ``scene_gt``/``scene_camera`` reference, and every PNG of the test split decoded
(:mod:`brave6d.dataset.release.images`: kind by folder, the size of ``camera.json``), object ids (the same
name has the same ``obj_id`` in every scene, in ``models_info`` and in the library), the targets,
every other member's length and CRC, each scene's bundle (every member listed by its own
``manifest.json`` and matching its sha256; then ``brave6d.serve.load_bundle`` on its small files) and, when
the release has one, the synthetic training split (:mod:`brave6d.dataset.release.train_pbr`) and the
learned model (:mod:`brave6d.dataset.release.learned`: its checksum against the manifest, its card) and
the ROS 2 interfaces wheel (:mod:`brave6d.dataset.release.ros2_wheel`: its checksum against the manifest).

A release is untrusted input, so nothing is extracted whole: members are streamed for their
checksums, JSON files and images are read into memory (bounded by :class:`~brave6d.dataset.release.zips.ZipLimits`)
and only the small files a reader needs are written to a temporary folder.
"""

from __future__ import annotations

import hashlib
import tempfile
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from brave6d.annotation import read_models_info, read_ply_mesh, read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.core.atomic import read_json
from brave6d.core.bounded_files import open_regular
from brave6d.core.errors import DataError
from brave6d.core.names import contained_path
from brave6d.core.progress import progress
from brave6d.dataset.release.formats import (CAMERA, DATASET_INFO, HOLDOUT, MANIFEST, SUMS, TARGETS, TARGETS_HOLDOUT,
                                     base_zip, bundle_folder, bundle_zip, models_zip, read_holdout,
                                     read_sha256sums, read_targets, scene_folder, test_zip, train_pbr_zip)
from brave6d.dataset.release.images import decode_png, decode_zip_images, image_kind
from brave6d.dataset.release.learned import check_learned_zip, learned_zip
from brave6d.dataset.release.manifest import read_manifest
from brave6d.dataset.release.ros2_wheel import check_interfaces_wheel
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.train_pbr import check_train_pbr_zip
from brave6d.dataset.release.zips import CheckedZip, open_zip

T = TypeVar("T")

#: Bytes of a splat kept to let ``brave6d.serve.load_bundle`` read its PLY header (the rest is only hashed).
_SPLAT_HEAD = 1 << 16


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
    learned_model: str | None = None  # the learned model's preset (None: the release has none)
    ros2_interfaces: str | None = None  # the ROS 2 interfaces wheel's file name (None: the release has none)


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
    with tempfile.TemporaryDirectory(prefix="brave6d-verify-") as tmp_dir, ExitStack() as stack:
        tmp = Path(tmp_dir)
        opened = {z: stack.enter_context(open_zip(base / z, shown=z)) for z in zips[:3]}
        library = {int(o["obj_id"]): str(o["name"]) for o in manifest["objects"]}
        size = _check_camera(opened[base_zip(name)], name, tmp)
        models = _check_models(opened[models_zip(name)], library, tmp)
        gts = _check_test(opened[test_zip(name)], scenes, library, models, size, tmp)
        _check_base(opened[base_zip(name)], name, scenes, gts, tmp)
        for zf in opened.values():
            zf.check_unread()
        for s in progress(scenes, desc="bundles", unit="bundle"):
            _check_bundle(base, bundle_zip(name, s["scene_id"]), s, library, tmp)
    pbr = train_pbr_zip(name)
    pbr_images = check_train_pbr_zip(base / pbr, models) if pbr in sums else 0
    learned = _check_learned(base, sums, manifest, set(library))
    wheel = check_interfaces_wheel(base, sums, manifest, MANIFEST)
    return VerifyReport(base, len(sums) + 1, sum((base / n).stat().st_size for n in sums), len(scenes),
                        sum(len(g) for k, g in gts.items() if k > 0), len(scenes), pbr_images, learned, wheel)


def _check_learned(base: Path, sums: dict[str, str], manifest: dict[str, Any], library: set[int]) -> str | None:
    """The learned model's zip, when the manifest names one (and none when it does not)."""
    name = learned_zip(manifest["name"])
    entry = manifest.get("learned_model")
    if entry is None:
        if name in sums:
            raise ReleaseError(f"{base / name}: in the release, but {MANIFEST} has no 'learned_model' entry for it")
        return None
    if name not in sums:
        raise ReleaseError(f"{base / name}: required by {MANIFEST} (learned_model) but not in the release")
    return check_learned_zip(base / name, entry, library, MANIFEST)


def _check_sums(base: Path) -> dict[str, str]:
    sums = read_sha256sums(base / SUMS)
    present = {p.relative_to(base).as_posix() for p in base.rglob("*") if p.is_file() or p.is_symlink()} - {SUMS}
    for name in sorted(present - set(sums)):
        raise ReleaseError(f"{base / name}: not listed in {SUMS} (a file that is not part of the release)")
    for name in sorted(set(sums) - present):
        raise ReleaseError(f"{base / name}: listed in {SUMS} but missing")
    for name in progress(sorted(sums), desc="checksums", unit="file"):
        try:
            path = contained_path(base, name, f"{base / SUMS}: file {name!r}")  # no link, inside the release
        except DataError as exc:
            raise ReleaseError(str(exc)) from None
        with open_regular(path, error=ReleaseError) as handle:  # a FIFO or a device is refused, never read
            digest = hashlib.file_digest(handle, "sha256").hexdigest()
        if digest != sums[name]:
            raise ReleaseError(f"{base / name}: sha256 {digest[:12]}... does not match {SUMS} "
                               f"({sums[name][:12]}...); the file was altered or truncated")
    return sums


def _check_camera(zf: CheckedZip, name: str, tmp: Path) -> tuple[int, int]:
    """The release's ``camera.json`` (base zip); returns its image size (width, height)."""
    camera = zf.run_reader(read_json, f"{name}/{CAMERA}", tmp)
    for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"):
        if not isinstance(camera, dict) or not isinstance(camera.get(key), (int, float)):
            raise ReleaseError(f"{zf.shown}:{name}/{CAMERA}: field '{key}': a number is required")
    return int(camera["width"]), int(camera["height"])


def _check_models(zf: CheckedZip, library: dict[int, str], tmp: Path) -> dict[int, Any]:
    info = zf.run_reader(read_models_info, "models/models_info.json", tmp)
    for obj_id in sorted(info):
        if obj_id not in library:
            raise ReleaseError(f"{zf.shown}:models/models_info.json: obj_id {obj_id} is not in the object library "
                               f"of {MANIFEST}")
        zf.run_reader(read_ply_mesh, f"models/obj_{obj_id:06d}.ply", tmp)
    return info


def _check_test(zf: CheckedZip, scenes: list[dict[str, Any]], library: dict[int, str], models: dict[int, Any],
                size: tuple[int, int], tmp: Path) -> dict[int, dict[int, list[int]]]:
    """Check every scene folder; returns ``{scene_id: {im_id: [obj_id per gt]}}`` (and holdout under -id)."""
    zip_name = zf.shown
    names = set(zf.names)
    out: dict[int, dict[int, list[int]]] = {}
    for s in scenes:
        sid, folder = s["scene_id"], scene_folder(s["scene_id"])
        gt = zf.run_reader(read_scene_gt, f"{folder}/scene_gt.json", tmp)
        cam = zf.run_reader(read_scene_camera, f"{folder}/scene_camera.json", tmp)
        info = zf.run_reader(read_scene_gt_info, f"{folder}/scene_gt_info.json", tmp)
        holdout = zf.run_reader(read_holdout, f"{folder}/{HOLDOUT}", tmp)
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
        decode_zip_images(zf, folder, size)
        out[sid] = {im: [g.obj_id for g in gts] for im, gts in gt.items()}
        out[-sid] = {im: [] for im in holdout}
    return out


def _check_base(zf: CheckedZip, name: str, scenes: list[dict[str, Any]], gts: dict[int, dict[int, list[int]]],
                tmp: Path) -> None:
    info = zf.run_reader(read_json, f"{name}/{DATASET_INFO}", tmp)
    ids = [s.get("scene_id") for s in info.get("scenes", [])] if isinstance(info, dict) else None
    if ids != [s["scene_id"] for s in scenes]:
        raise ReleaseError(f"{zf.shown}:{name}/{DATASET_INFO}: field 'scenes': scene ids {ids} differ from "
                           f"{MANIFEST}'s")
    for member, holdout_only in ((TARGETS, False), (TARGETS_HOLDOUT, True)):
        shown = f"{zf.shown}:{name}/{member}"
        for i, t in enumerate(zf.run_reader(lambda p, s=shown: read_targets(p, s), f"{name}/{member}", tmp)):
            ims = gts.get(t["scene_id"], {})
            if t["im_id"] not in ims or t["obj_id"] not in ims[t["im_id"]]:
                raise ReleaseError(f"{shown}: target [{i}] (scene {t['scene_id']}, image {t['im_id']}, obj_id "
                                   f"{t['obj_id']}) is not in that scene's scene_gt.json")
            if holdout_only and t["im_id"] not in gts.get(-t["scene_id"], {}):
                raise ReleaseError(f"{shown}: target [{i}]: image {t['im_id']} of scene {t['scene_id']} is not a "
                                   "holdout image")


def _check_bundle(base: Path, zip_name: str, scene: dict[str, Any], library: dict[int, str], tmp: Path) -> None:
    """A bundle zip: its ``manifest.json`` read by serve's one reader, every member listed by it and
    matching its size and sha256 (streamed); then ``brave6d.serve.load_bundle`` on its JSON files and the
    splat's PLY header."""
    from brave6d.serve import HOLDOUT_IMAGES as BUNDLE_HOLDOUT_IMAGES
    from brave6d.serve import MANIFEST as BUNDLE_MANIFEST
    from brave6d.serve import SPLAT, load_bundle

    folder = bundle_folder(scene["scene_id"])
    with open_zip(base / zip_name, inside=folder, shown=zip_name) as zf, \
            tempfile.TemporaryDirectory(prefix="bundle-", dir=tmp) as tmp_bundle:
        target = Path(tmp_bundle)
        listed = _bundle_files(zf, folder, target)
        head = b""
        for member, entry in listed.items():
            digest, kept = _digest(zf, member, _SPLAT_HEAD if member == f"{folder}/{SPLAT}" else 0)
            head = kept or head
            if digest != entry["sha256"]:
                raise ReleaseError(f"{zip_name}:{member}: sha256 {digest[:12]}... does not match "
                                   f"{folder}/{BUNDLE_MANIFEST} ({str(entry['sha256'])[:12]}...); the bundle was altered")
        for member in listed:  # the holdout images: decoded (kind and pixel limit from the header first)
            if member.startswith(f"{folder}/{BUNDLE_HOLDOUT_IMAGES}/") and image_kind(member) is not None:
                decode_png(zf.read(member), "rgb", f"{zip_name}:{member}")
        small = [m for m in listed if m.count("/") == folder.count("/") + 1 and m.endswith(".json")]
        zf.extract(target, small, strip=folder)
        (target / SPLAT).write_bytes(head[:head.find(b"end_header\n") + 11] if b"end_header\n" in head else head)
        bundle = _bundle_call(load_bundle, target, zip_name, folder, verify=False)  # files checked above
    for o in bundle.objects:
        if library.get(o.obj_id) != o.name:
            raise ReleaseError(f"{zip_name}: {folder}/objects.json: object {o.name!r} has obj_id {o.obj_id}, which is "
                               f"{library.get(o.obj_id)!r} in the object library ({MANIFEST})")
        if f"{folder}/{o.model}" not in listed:
            raise ReleaseError(f"{zip_name}: {folder}/objects.json: model {o.model} of object {o.name!r} is not in "
                               f"the bundle's {BUNDLE_MANIFEST}")


def _bundle_call(fn: Callable[..., T], target: Path, zip_name: str, folder: str, **kwargs: Any) -> T:
    """``fn(target, **kwargs)`` (serve's bundle readers), its errors naming ``zip:folder`` instead of
    the temporary folder the bundle's small files were unpacked to."""
    try:
        return fn(target, **kwargs)
    except DataError as exc:
        raise ReleaseError(f"{zip_name}: the bundle does not load: "
                           f"{str(exc).replace(str(target), f'{zip_name}:{folder}')}") from None


def _bundle_files(zf: CheckedZip, folder: str, target: Path) -> dict[str, dict[str, Any]]:
    """``{member: manifest entry}`` of every file the bundle's ``manifest.json`` lists (read by
    ``brave6d.serve.read_bundle_manifest``, the format's one reader, from ``target``, where it is unpacked);
    every member of the zip must be one of them (or the manifest itself), of the size it gives."""
    from brave6d.serve import MANIFEST as BUNDLE_MANIFEST
    from brave6d.serve import read_bundle_manifest

    zf.extract(target, [f"{folder}/{BUNDLE_MANIFEST}"], strip=folder)
    files = _bundle_call(read_bundle_manifest, target, zf.shown, folder)["files"]
    listed = {f"{folder}/{rel}": entry for rel, entry in files.items()}
    present = set(zf.names)
    for member in zf.names:
        if member != f"{folder}/{BUNDLE_MANIFEST}" and member not in listed:
            raise ReleaseError(f"{zf.shown}: member {member}: not listed in the bundle's {BUNDLE_MANIFEST}")
    for member, entry in listed.items():
        if member not in present:
            raise ReleaseError(f"{zf.shown}:{member}: missing (listed in {folder}/{BUNDLE_MANIFEST})")
        if entry["bytes"] != zf.size(member):
            raise ReleaseError(f"{zf.shown}:{member}: {zf.size(member)} bytes, {folder}/{BUNDLE_MANIFEST} says "
                               f"{entry['bytes']}")
    return listed


def _digest(zf: CheckedZip, member: str, keep: int = 0) -> tuple[str, bytes]:
    """The member's sha256 (streamed) and its first ``keep`` bytes."""
    digest, head = hashlib.sha256(), b""
    for piece in zf.chunks(member):
        digest.update(piece)
        if len(head) < keep:
            head += piece[:keep - len(head)]
    return digest.hexdigest(), head
