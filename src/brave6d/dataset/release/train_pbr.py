"""The synthetic training split in a release: pack ``WORKDIR/synth/train_pbr/`` as
``<name>_train_pbr.zip`` when the work directory has one, and verify that zip.

Both sides read the split's JSON files through annotation's BOP readers (the format's owner) and
check that every image the ``scene_gt.json`` files list has its rgb, depth and masks, and that
every ``obj_id`` has a model in the release's models zip. The layouts are those annotation's split
reader (``read_bop_split``) reads: colour in ``rgb/`` as PNG or JPEG (``RGB_SUFFIXES``; BlenderProc
writes JPEG), a grey-only folder (``gray/``) refused naming it, and every image's ``depth_scale`` in
``scene_camera.json`` (mm per depth unit: 1 as brave6d writes, 0.1 as BlenderProc does; a missing one
is refused, never taken as mm). Every image is checked too (:mod:`brave6d.dataset.release.images`):
its header and end when packing (a damaged synthetic image is not packed), decoded when verifying
(the pixel limit checked from the header first); all images of one ``train_pbr/XXXXXX`` folder share
one size.
The zip is read through :func:`brave6d.dataset.release.zips.open_zip` (names, sizes, streamed CRCs).
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from brave6d.annotation import COCO_FILE, RGB_SUFFIXES, read_scene_camera, read_scene_gt, read_scene_gt_info, \
    read_scene_gt_coco, split_scene_folders
from brave6d.core.errors import DataError
from brave6d.dataset.release.formats import SYNTH_DIR, TRAIN_PBR
from brave6d.dataset.release.images import check_jpeg_file, check_png_file, decode_zip_images, decode_zip_jpegs, \
    image_kind, is_rgb_jpeg
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import open_zip

_FOLDER = re.compile(rf"^{TRAIN_PBR}/(\d{{6}})/")


def synthetic_split(workdir: Path) -> Path | None:
    """``WORKDIR/synth/train_pbr`` when the work directory has a synthetic split, else None."""
    root = Path(workdir) / SYNTH_DIR / TRAIN_PBR
    return root if root.is_dir() else None


def train_pbr_files(split: Path, models: Mapping[int, Any]) -> list[tuple[Path, str]]:
    """``(file, member)`` of every file of the split (sorted), after checking it (module docstring)."""
    try:
        folders = split_scene_folders(split, "; run 'brave6d synth' again")
    except DataError as exc:
        raise ReleaseError(str(exc)) from exc
    strays = sorted(set(split.iterdir()) - set(folders))
    if strays:  # verify refuses any member outside train_pbr/XXXXXX/: never pack one
        raise ReleaseError(f"{strays[0]}: not a scene folder (six digits) of the synthetic split; move it out of "
                           f"{split} (the release packs train_pbr/XXXXXX/ folders only)")
    for folder in folders:
        files = sorted(p for p in folder.rglob("*") if p.is_file())
        members = {p.relative_to(folder).as_posix() for p in files}
        _check_folder(folder.name, lambda name, reader, f=folder: _read_local(reader, f / name), members, models,
                      str(folder))
        size = None
        for p in files:
            rel = p.relative_to(folder).as_posix()
            kind = image_kind(rel)
            if kind is not None:
                size = check_png_file(p, kind, size)
            elif is_rgb_jpeg(rel):
                size = check_jpeg_file(p, size)
    return [(p, f"{TRAIN_PBR}/{p.relative_to(split).as_posix()}") for p in sorted(split.rglob("*")) if p.is_file()]


def check_train_pbr_zip(path: Path, models: Mapping[int, Any]) -> int:
    """Verify a release's ``<name>_train_pbr.zip``; returns the number of images."""
    with open_zip(path, inside=TRAIN_PBR, shown=path.name) as zf, \
            tempfile.TemporaryDirectory(prefix="brave6d-verify-pbr-") as tmp:
        by_folder: dict[str, set[str]] = {}
        for name in zf.names:
            m = _FOLDER.match(name)
            if m is None:
                raise ReleaseError(f"{path.name}: member {name}: lies outside {TRAIN_PBR}/XXXXXX/")
            by_folder.setdefault(m.group(1), set()).add(name[m.end():])
        images = 0
        for folder, members in sorted(by_folder.items()):
            def read(name: str, reader: Callable[[Path], Any], f: str = folder) -> Any:
                return zf.run_reader(reader, f"{TRAIN_PBR}/{f}/{name}", Path(tmp))

            images += _check_folder(folder, read, members, models, f"{path.name}:{TRAIN_PBR}/{folder}")
            _, size = decode_zip_jpegs(zf, f"{TRAIN_PBR}/{folder}", Path(tmp))
            decode_zip_images(zf, f"{TRAIN_PBR}/{folder}", size)
        zf.check_unread()
    return images


def _read_local(reader: Callable[[Path], Any], file: Path) -> Any:
    if not file.is_file():
        raise ReleaseError(f"{file}: missing")
    try:
        return reader(file)
    except DataError as exc:  # annotation's readers: one line naming the file and field, as a release error
        raise ReleaseError(str(exc)) from None


def _read_cameras(path: Path) -> dict[int, Any]:
    """``scene_camera.json`` with every image's ``depth_scale`` required: the split always has depth."""
    return read_scene_camera(path, require_depth_scale=True)


def _check_folder(folder: str, read: Callable[[str, Callable[[Path], Any]], Any], members: set[str],
                  models: Mapping[int, Any], where: str) -> int:
    """Check one ``train_pbr/XXXXXX`` folder; returns its number of images."""
    if not any(m.startswith("rgb/") for m in members) and any(m.startswith("gray/") for m in members):
        raise ReleaseError(f"{where}/gray: grey images (gray/) are not packed: the synthetic split needs colour "
                           f"images in rgb/ ({' or '.join(RGB_SUFFIXES)})")
    gt = read("scene_gt.json", read_scene_gt)
    for name, reader in (("scene_camera.json", _read_cameras), ("scene_gt_info.json", read_scene_gt_info)):
        ids = read(name, reader)
        if set(ids) != set(gt):
            raise ReleaseError(f"{where}/{name}: lists other images than scene_gt.json "
                               f"(e.g. {sorted(set(ids) ^ set(gt))[:3]})")
    if COCO_FILE in members:  # BlenderProc's COCO masks: packed as they are, their RLE and images checked
        coco = read(COCO_FILE, read_scene_gt_coco)
        if not set(coco) <= set(gt):
            raise ReleaseError(f"{where}/{COCO_FILE}: lists images scene_gt.json does not "
                               f"(e.g. {sorted(set(coco) - set(gt))[:3]})")
    for im_id, gts in sorted(gt.items()):
        rgb = [f"rgb/{im_id:06d}{suffix}" for suffix in RGB_SUFFIXES]
        needed = [next((r for r in rgb if r in members), rgb[0]), f"depth/{im_id:06d}.png"]
        for gt_id, g in enumerate(gts):
            if g.obj_id not in models:
                raise ReleaseError(f"{where}/scene_gt.json: image {im_id} instance {gt_id}: obj_id {g.obj_id} has no "
                                   "model in the release (no scene of the dataset shows that object)")
            needed += [f"mask/{im_id:06d}_{gt_id:06d}.png", f"mask_visib/{im_id:06d}_{gt_id:06d}.png"]
        for rel in needed:
            if rel not in members:
                raise ReleaseError(f"{where}/{rel}: missing (image {im_id} is listed in scene_gt.json)")
    return len(gt)
