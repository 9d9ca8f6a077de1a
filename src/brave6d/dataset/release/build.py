"""``brave6d release build WORKDIR OUT``: package a dataset's scenes as a BOP-style release.

Everything is read and checked first (:mod:`brave6d.dataset.release.collect`); the zips are then streamed
into a staging folder beside ``OUT`` that is renamed into place at the end (all or nothing; the
staging folder of a build that was killed is removed by the next one, :func:`brave6d.core.atomic.staged_folder`).
``OUT`` must be absent or empty; anything else is refused unless ``force``, and then moved aside
to ``<OUT>.old-<time>`` (never deleted) once the new release is complete.

When a ROS 2 Python is at hand the release also ships the ROS 2 interfaces wheel for agents
(:mod:`brave6d.dataset.release.ros2_wheel`; without one the log says so and the build goes on).

A release packs the scenes' own files and nothing a link points to: a scene's bundle zip holds
exactly its manifest and the files the manifest lists (verified by ``brave6d.serve.load_bundle``), and
every file packed (bundle, test split images and masks, models, camera, the synthetic split, the
learned model) must
be a regular file, not a symbolic link, inside its folder once the links on its way are followed;
anything else is refused, naming the file.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from brave6d.annotation import dump_bop_json
from brave6d.core.atomic import atomic_write_json, atomic_write_text, file_sha256, move_aside, read_json, staged_folder
from brave6d.core.errors import DataError
from brave6d.core.progress import progress
from brave6d.dataset.release.card import render_card
from brave6d.dataset.release.collect import ReleaseModel, SceneRelease, collect_models, collect_scene
from brave6d.dataset.release.formats import (CAMERA, CARD, DATASET_INFO, HOLDOUT, MANIFEST, SCENE_JSONS, SPLIT, SUMS,
                                     TARGETS, TARGETS_HOLDOUT, base_zip, bop19_targets, bundle_folder, bundle_zip,
                                     dump_targets, holdout_json, models_zip, scene_folder, test_zip,
                                     train_pbr_zip, write_sha256sums)
from brave6d.dataset.release.learned import learned_entry, learned_model, learned_zip
from brave6d.dataset.release.manifest import library_entries, make_manifest, scene_entry
from brave6d.dataset.release.ros2_wheel import build_interfaces_wheel
from brave6d.dataset.release.source import ReleaseError, ReleaseSource, load_release_source
from brave6d.dataset.release.train_pbr import synthetic_split, train_pbr_files
from brave6d.dataset.release.zips import write_zip

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
    move = _check_out(target, source.workdir, force, [s.root for s in source.scenes])
    scenes = [collect_scene(s, source) for s in progress(source.scenes, total=len(source.scenes),
                                                           desc="release: check scenes", unit="scene")]
    models = collect_models(scenes)
    camera = _confined([(_camera(scenes), f"{source.name}/{CAMERA}")], scenes[0].layout.root)
    test_files, model_files = _test_files(scenes), _model_files(scenes, models)
    split = synthetic_split(source.workdir)  # WORKDIR/synth/train_pbr from `brave6d synth`, when there is one
    if split is not None:
        _refuse_links(split.rglob("*"), split)  # before train_pbr_files reads a single byte through a link
    split_files = _confined(train_pbr_files(split, models), split) if split is not None else []
    model_dir = learned_model(source.workdir)  # WORKDIR/learned/model from `brave6d dataset run`, when there is one
    learned_files, learned = ([], None) if model_dir is None else \
        learned_entry(model_dir, {o.obj_id for o in source.objects}, learned_zip(source.name))
    if model_dir is not None:
        _confined(learned_files, model_dir)
    bundles = {s.source.scene_id: _bundle_files(s) for s in progress(scenes, desc="release: check bundles",
                                                                      unit="bundle")}
    sizes: dict[str, int] = {}
    moved = None
    with staged_folder(target) as stage:
        write_zip(stage / test_zip(source.name), test_files, _test_texts(scenes), desc="test split")
        write_zip(stage / models_zip(source.name), model_files,
                  [("models/models_info.json", dump_bop_json({k: m.info for k, m in models.items()}))],
                  desc="models")
        if split is not None:
            write_zip(stage / train_pbr_zip(source.name), split_files, desc="train_pbr split")
        if learned is not None:
            write_zip(stage / learned_zip(source.name), learned_files, desc="learned model")
        for s in scenes:
            write_zip(stage / bundle_zip(source.name, s.source.scene_id), bundles[s.source.scene_id],
                      desc=f"bundle {s.source.name}")
        ros2 = build_interfaces_wheel(stage)  # for agents' own environments; None (logged) without ROS 2
        sizes = {p.name: p.stat().st_size for p in stage.iterdir()}
        card = render_card(source, scenes, models, sizes)
        write_zip(stage / base_zip(source.name), camera,
                  _base_texts(source, scenes, models, card), desc="base")
        sizes[base_zip(source.name)] = (stage / base_zip(source.name)).stat().st_size
        atomic_write_text(stage / CARD, card)
        sizes[CARD] = (stage / CARD).stat().st_size
        atomic_write_json(stage / MANIFEST, make_manifest(source, scenes, models, sizes, learned, ros2))
        sizes[MANIFEST] = (stage / MANIFEST).stat().st_size
        digests = {name: file_sha256(stage / name) for name in progress(sorted(sizes), desc="SHA256SUMS", unit="file")}
        write_sha256sums(stage / SUMS, digests)
        sizes[SUMS] = (stage / SUMS).stat().st_size
        if move:
            moved = move_aside(target)
            log.warning("%s was not empty: moved aside to %s", target, moved)
    return ReleaseResult(target, sizes, len(scenes), sum(len(s.im_ids) for s in scenes), moved)


def _check_out(target: Path, workdir: Path, force: bool, scene_roots: Sequence[Path] = ()) -> bool:
    """Refuse an ``OUT`` that would lose data; True when it must be moved aside (``force``).
    ``scene_roots``: the scene directories, also captured ones that lie outside the work directory."""
    out, work = target.resolve(), workdir.resolve()
    if out == work or out in work.parents:
        raise ReleaseError(f"{target}: OUT is (or contains) the dataset work directory {workdir}; "
                           "choose a folder of its own")
    if work / "scenes" in (out, *out.parents):
        raise ReleaseError(f"{target}: OUT lies inside the dataset's scenes folder; choose a folder of its own")
    for root in scene_roots:
        scene = root.resolve()
        if scene in (out, *out.parents) or out in scene.parents:
            raise ReleaseError(f"{target}: OUT is, contains or lies inside the scene directory {root}; "
                               "choose a folder of its own")
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


def _confined(files: list[tuple[Path, str]], root: Path) -> list[tuple[Path, str]]:
    """``files`` (``(file, member)``) once each is checked to be a real file of ``root``: not a
    symbolic link, and inside ``root`` with every link on its way followed. A link placed in a
    scene would otherwise ship whatever it points to."""
    _refuse_links((src for src, _ in files), root)
    return files


def _refuse_links(paths: Iterable[Path], root: Path) -> None:
    """Refuse ``root`` when it is itself a symbolic link (a bundle folder linked to one elsewhere
    would pass every check below), and each of ``paths`` that is a link or resolves outside it."""
    if root.is_symlink():
        raise ReleaseError(f"{root}: is a symbolic link (to {os.readlink(root)}); a release packs only the "
                           "scene's own files: put the folder itself there")
    base = root.resolve()
    for path in paths:
        if path.is_symlink():
            raise ReleaseError(f"{path}: is a symbolic link (to {os.readlink(path)}); a release packs only the "
                               "scene's own files: put the file itself there")
        if not path.resolve().is_relative_to(base):
            raise ReleaseError(f"{path}: lies outside {root} (a folder on its way is a symbolic link to "
                               f"{path.resolve().parent}); a release packs only the scene's own files")


def _bundle_files(s: SceneRelease) -> list[tuple[Path, str]]:
    """Exactly the bundle's manifest and the files it lists (verified again by ``brave6d.serve.load_bundle``,
    which also refuses a listed name that climbs out), each a real file of the bundle folder."""
    from brave6d.serve import MANIFEST as BUNDLE_MANIFEST  # the bundle's own manifest: it lists every other file
    from brave6d.serve import load_bundle

    root = s.bundle_root
    _refuse_links([root / BUNDLE_MANIFEST], root)
    try:
        listed = load_bundle(root).manifest["files"]
    except DataError as exc:
        raise ReleaseError(f"scene {s.source.name}: {exc} (run 'brave6d export {s.source.root}')") from None
    names = sorted({BUNDLE_MANIFEST, *listed}, key=PurePosixPath)
    folder = bundle_folder(s.source.scene_id)
    return _confined([(root / name, f"{folder}/{name}") for name in names], root)


def _model_files(scenes: list[SceneRelease], models: dict[int, ReleaseModel]) -> list[tuple[Path, str]]:
    """Each model once, checked to be a real file of the BOP export it comes from."""
    roots = {s.layout.model_path(obj_id): s.layout.root for s in scenes for obj_id in s.objects}
    out = []
    for _, m in sorted(models.items()):
        out += _confined([(m.path, f"models/{m.path.name}")], roots[m.path])
    return out


def _test_files(scenes: list[SceneRelease]) -> list[tuple[Path, str]]:
    out = []
    for s in scenes:
        folder = scene_folder(s.source.scene_id)
        files = [(s.layout.scene_dir / name, f"{folder}/{name}") for name in SCENE_JSONS]
        out += _confined(files + [(src, f"{folder}/{rel}") for src, rel in s.image_files()], s.layout.root)
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
