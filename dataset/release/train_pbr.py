"""The synthetic training split in a release: pack ``WORKDIR/synth/train_pbr/`` as
``<name>_train_pbr.zip`` when the work directory has one, and verify that zip.

Both sides read the split's JSON files through annotation's BOP readers (the format's owner) and
check that every image the ``scene_gt.json`` files list has its rgb, depth and masks, and that
every ``obj_id`` has a model in the release's models zip.
"""

from __future__ import annotations

import re
import tempfile
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from annotation import read_scene_camera, read_scene_gt, read_scene_gt_info
from brave6d.errors import DataError
from dataset.release.formats import SYNTH_DIR, TRAIN_PBR
from dataset.release.source import ReleaseError

_FOLDER = re.compile(rf"^{TRAIN_PBR}/(\d{{6}})/")


def synthetic_split(workdir: Path) -> Path | None:
    """``WORKDIR/synth/train_pbr`` when the work directory has a synthetic split, else None."""
    root = Path(workdir) / SYNTH_DIR / TRAIN_PBR
    return root if root.is_dir() else None


def train_pbr_files(split: Path, models: Mapping[int, Any]) -> list[tuple[Path, str]]:
    """``(file, member)`` of every file of the split (sorted), after checking it (module docstring)."""
    folders = sorted(p for p in split.iterdir() if p.is_dir())
    if not folders:
        raise ReleaseError(f"{split}: the synthetic split holds no image folders; run 'brave6d synth' again")
    for folder in folders:
        members = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
        _check_folder(folder.name, lambda name, reader, f=folder: _read_local(reader, f / name), members, models,
                      str(folder))
    return [(p, f"{TRAIN_PBR}/{p.relative_to(split).as_posix()}") for p in sorted(split.rglob("*")) if p.is_file()]


def check_train_pbr_zip(path: Path, models: Mapping[int, Any]) -> int:
    """Verify a release's ``<name>_train_pbr.zip``; returns the number of images."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ReleaseError(f"{path}: not a readable zip ({exc})") from None
    with zf, tempfile.TemporaryDirectory(prefix="brave6d-verify-pbr-") as tmp:
        if zf.testzip() is not None:
            raise ReleaseError(f"{path}: a member fails its CRC check (the zip is corrupt)")
        by_folder: dict[str, set[str]] = {}
        for name in zf.namelist():
            m = _FOLDER.match(name)
            if m is None:
                raise ReleaseError(f"{path}: member {name} lies outside {TRAIN_PBR}/XXXXXX/")
            by_folder.setdefault(m.group(1), set()).add(name[m.end():])
        images = 0
        for folder, members in sorted(by_folder.items()):
            def read(name: str, reader: Callable[[Path], Any], f: str = folder) -> Any:
                member = f"{TRAIN_PBR}/{f}/{name}"
                if member not in zf.namelist():
                    raise ReleaseError(f"{path.name}:{member}: missing")
                local = Path(zf.extract(member, tmp))
                try:
                    return reader(local)
                except DataError as exc:
                    raise ReleaseError(str(exc).replace(str(local), f"{path.name}:{member}")) from None

            images += _check_folder(folder, read, members, models, f"{path.name}:{TRAIN_PBR}/{folder}")
    return images


def _read_local(reader: Callable[[Path], Any], file: Path) -> Any:
    if not file.is_file():
        raise ReleaseError(f"{file}: missing")
    return reader(file)


def _check_folder(folder: str, read: Callable[[str, Callable[[Path], Any]], Any], members: set[str],
                  models: Mapping[int, Any], where: str) -> int:
    """Check one ``train_pbr/XXXXXX`` folder; returns its number of images."""
    gt = read("scene_gt.json", read_scene_gt)
    for name, reader in (("scene_camera.json", read_scene_camera), ("scene_gt_info.json", read_scene_gt_info)):
        ids = read(name, reader)
        if set(ids) != set(gt):
            raise ReleaseError(f"{where}/{name}: lists other images than scene_gt.json "
                               f"(e.g. {sorted(set(ids) ^ set(gt))[:3]})")
    for im_id, gts in sorted(gt.items()):
        needed = [f"rgb/{im_id:06d}.png", f"depth/{im_id:06d}.png"]
        for gt_id, g in enumerate(gts):
            if g.obj_id not in models:
                raise ReleaseError(f"{where}/scene_gt.json: image {im_id} instance {gt_id}: obj_id {g.obj_id} has no "
                                   "model in the release (no scene of the dataset shows that object)")
            needed += [f"mask/{im_id:06d}_{gt_id:06d}.png", f"mask_visib/{im_id:06d}_{gt_id:06d}.png"]
        for rel in needed:
            if rel not in members:
                raise ReleaseError(f"{where}/{rel}: missing (image {im_id} is listed in scene_gt.json)")
    return len(gt)
