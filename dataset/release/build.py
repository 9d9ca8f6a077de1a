"""``brave6d release build WORKDIR OUT``: package a dataset's scenes as a BOP-style release.

Everything is read and checked first (:mod:`dataset.release.collect`); the zips are then streamed
into a staging folder beside ``OUT`` that is renamed into place at the end (all or nothing).
``OUT`` must be absent or empty; anything else is refused unless ``force``, and then moved aside
to ``<OUT>.old-<time>`` (never deleted) once the new release is complete.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotation import dump_bop_json
from brave6d.atomic import atomic_write_json, atomic_write_text, file_sha256, move_aside, read_json, staged_folder
from brave6d.progress import progress
from dataset.release.card import render_card
from dataset.release.collect import ReleaseModel, SceneRelease, collect_models, collect_scene
from dataset.release.formats import (CAMERA, CARD, DATASET_INFO, HOLDOUT, MANIFEST, SCENE_JSONS, SPLIT, SUMS,
                                     TARGETS, TARGETS_HOLDOUT, base_zip, bop19_targets, bundle_folder, bundle_zip,
                                     dump_targets, holdout_json, models_zip, scene_folder, test_zip,
                                     train_pbr_zip, write_sha256sums)
from dataset.release.manifest import library_entries, make_manifest, scene_entry
from dataset.release.source import ReleaseError, ReleaseSource, load_release_source
from dataset.release.train_pbr import synthetic_split, train_pbr_files
from dataset.release.zips import write_zip

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReleaseResult:
    """What a build wrote: the folder, its files (name -> bytes) and where an old ``OUT`` went."""

    root: Path
    sizes: dict[str, int]
    scenes: int
    images: int
    moved_aside: Path | None = None

    @property
    def total_bytes(self) -> int:
        return sum(self.sizes.values())


def build_release(workdir: Path | str, out: Path | str, *, force: bool = False) -> ReleaseResult:
    """Build the release of dataset work directory ``workdir`` into ``out`` (see the module docstring)."""
    source = load_release_source(workdir)
    target = Path(out)
    move = _check_out(target, source.workdir, force)
    scenes = [collect_scene(s, source) for s in progress(source.scenes, total=len(source.scenes),
                                                           desc="release: check scenes", unit="scene")]
    models = collect_models(scenes)
    camera = _camera(scenes)
    sizes: dict[str, int] = {}
    moved = None
    with staged_folder(target) as stage:
        write_zip(stage / test_zip(source.name), _test_files(scenes), _test_texts(scenes), desc="test split")
        write_zip(stage / models_zip(source.name),
                  [(m.path, f"models/{m.path.name}") for _, m in sorted(models.items())],
                  [("models/models_info.json", dump_bop_json({k: m.info for k, m in models.items()}))],
                  desc="models")
        split = synthetic_split(source.workdir)  # WORKDIR/synth/train_pbr from `brave6d synth`, when there is one
        if split is not None:
            write_zip(stage / train_pbr_zip(source.name), train_pbr_files(split, models), desc="train_pbr split")
        for s in scenes:
            name = bundle_zip(source.name, s.source.scene_id)
            root = s.bundle_root
            files = [(p, f"{bundle_folder(s.source.scene_id)}/{p.relative_to(root).as_posix()}")
                     for p in sorted(root.rglob("*")) if p.is_file()]
            write_zip(stage / name, files, desc=f"bundle {s.source.name}")
        sizes = {p.name: p.stat().st_size for p in stage.iterdir()}
        card = render_card(source, scenes, models, sizes)
        write_zip(stage / base_zip(source.name), [(camera, f"{source.name}/{CAMERA}")],
                  _base_texts(source, scenes, models, card), desc="base")
        sizes[base_zip(source.name)] = (stage / base_zip(source.name)).stat().st_size
        atomic_write_text(stage / CARD, card)
        sizes[CARD] = (stage / CARD).stat().st_size
        atomic_write_json(stage / MANIFEST, make_manifest(source, scenes, models, sizes))
        sizes[MANIFEST] = (stage / MANIFEST).stat().st_size
        digests = {name: file_sha256(stage / name) for name in progress(sorted(sizes), desc="SHA256SUMS", unit="file")}
        write_sha256sums(stage / SUMS, digests)
        sizes[SUMS] = (stage / SUMS).stat().st_size
        if move:
            moved = move_aside(target)
            log.warning("%s was not empty: moved aside to %s", target, moved)
    return ReleaseResult(target, sizes, len(scenes), sum(len(s.im_ids) for s in scenes), moved)


def _check_out(target: Path, workdir: Path, force: bool) -> bool:
    """Refuse an ``OUT`` that would lose data; True when it must be moved aside (``force``)."""
    out, work = target.resolve(), workdir.resolve()
    if out == work or out in work.parents:
        raise ReleaseError(f"{target}: OUT is (or contains) the dataset work directory {workdir}; "
                           "choose a folder of its own")
    if work / "scenes" in (out, *out.parents):
        raise ReleaseError(f"{target}: OUT lies inside the dataset's scenes folder; choose a folder of its own")
    if target.is_symlink() or (target.exists() and not target.is_dir()):
        what = "a symbolic link" if target.is_symlink() else "a file"
    elif target.is_dir() and next(target.iterdir(), None) is not None:
        what = "a folder that is not empty"
    else:
        return False
    if not force:
        raise ReleaseError(f"{target}: is {what}; build writes into an absent or empty folder: choose another OUT, "
                           f"or pass --force to move it aside (to {target.name}.old-<time>, nothing is deleted)")
    return True


def _camera(scenes: list[SceneRelease]) -> Path:
    """The first scene's BOP ``camera.json``; all scenes must share its image size."""
    first = scenes[0].layout.camera_path
    ref = read_json(first)
    for s in scenes[1:]:
        cam = read_json(s.layout.camera_path)
        if (cam.get("width"), cam.get("height")) != (ref.get("width"), ref.get("height")):
            raise ReleaseError(f"{s.layout.camera_path}: image size {cam.get('width')}x{cam.get('height')} differs "
                               f"from {first} ({ref.get('width')}x{ref.get('height')}); a release has one image size")
        if any(abs(float(cam.get(k, 0)) - float(ref.get(k, 0))) > 1e-6 for k in ("fx", "fy", "cx", "cy")):
            log.warning("%s: intrinsics differ from %s; camera.json holds the first scene's, every image's own "
                        "cam_K is in scene_camera.json", s.layout.camera_path, first)
    return first


def _test_files(scenes: list[SceneRelease]) -> list[tuple[Path, str]]:
    out = []
    for s in scenes:
        folder = scene_folder(s.source.scene_id)
        out += [(s.layout.scene_dir / name, f"{folder}/{name}") for name in SCENE_JSONS]
        out += [(src, f"{folder}/{rel}") for src, rel in s.image_files()]
    return out


def _test_texts(scenes: list[SceneRelease]) -> list[tuple[str, str]]:
    return [(f"{scene_folder(s.source.scene_id)}/{HOLDOUT}", holdout_json(s.holdout, s.holdout_view_ids))
            for s in scenes]


def _base_texts(source: ReleaseSource, scenes: list[SceneRelease], models: dict[int, ReleaseModel],
                card: str) -> list[tuple[str, str]]:
    targets, held = [], []
    for s in scenes:
        sid = s.source.scene_id
        targets += bop19_targets(sid, s.gt_obj_ids, s.visib)
        held += bop19_targets(sid, s.gt_obj_ids, s.visib, s.holdout)
    info: dict[str, Any] = {
        "name": source.name, "version": source.version, "license": source.license, "citation": source.citation,
        "description": source.description, "split": SPLIT,
        "pixel_convention": "cam_K and camera.json cx, cy: BOP's (pixel centres at +0.5); subtract 0.5 for OpenCV",
        "units": "millimetres (models, translations, depth with depth_scale 1.0)",
        "objects": library_entries(source, models),
        "scenes": [scene_entry(s, source.name) for s in scenes],
    }
    n = source.name
    return [(f"{n}/{DATASET_INFO}", json.dumps(info, indent=2) + "\n"), (f"{n}/{TARGETS}", dump_targets(targets)),
            (f"{n}/{TARGETS_HOLDOUT}", dump_targets(held)), (f"{n}/{CARD}", card)]
