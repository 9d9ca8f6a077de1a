"""The scenes of a release, for the render server: ``brave6d serve RELEASE`` serves every scene of it.

Two forms of a release are served:

* the release folder ``brave6d release build`` wrote (zips, ``manifest.json``, ``SHA256SUMS``):
  each scene's ``<name>_bundle_XXXXXX.zip`` is checked against ``SHA256SUMS`` and unpacked into a
  cache folder the first time the scene is needed (never into the release folder, which ``release
  verify`` keeps free of other files); later servers reuse the unpacked bundle;
* the unzipped dataset (the ``<name>/`` folder BOP users make, with ``dataset_info.json`` and
  ``bundles/XXXXXX/``): bundles are served in place.

Either way each scene's objects carry the library's category, and its memory estimate comes from
the file sizes (the zip's directory or the bundle's manifest) without reading the splat.
"""

from __future__ import annotations

import os
import threading
import zipfile
from pathlib import Path
from typing import Any

from brave6d.atomic import file_sha256, read_json, staged_folder
from dataset.release.formats import DATASET_INFO, MANIFEST, SUMS, bundle_folder, bundle_zip, read_sha256sums
from dataset.release.manifest import read_manifest
from dataset.release.source import ReleaseError
from dataset.release.zips import member_outside

#: Where unpacked bundles go unless a cache folder is given: ``$BRAVE6D_CACHE``, else
#: ``$XDG_CACHE_HOME/brave6d``, else ``~/.cache/brave6d``.
CACHE_ENV = "BRAVE6D_CACHE"


def default_cache_dir() -> Path:
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "brave6d"


def release_scene_sources(root: Path | str, cache_dir: Path | str | None = None) -> list[Any]:
    """One ``serve.SceneSource`` per scene of the release at ``root`` (see the module docstring)."""
    base = Path(root)
    if (base / MANIFEST).is_file() and (base / SUMS).is_file():
        return _zipped_sources(base, Path(cache_dir) if cache_dir is not None else None)
    if (base / DATASET_INFO).is_file() and (base / "bundles").is_dir():
        return _unzipped_sources(base)
    raise ReleaseError(f"{base}: neither a bundle (manifest.json + splat.ply), a release folder ({MANIFEST} + {SUMS}, "
                       f"from 'brave6d release build') nor an unzipped release ({DATASET_INFO} + bundles/)")


def _categories(objects: list[dict[str, Any]]) -> dict[int, str | None]:
    return {int(o["obj_id"]): o.get("category") for o in objects}


def _scene_objects(scene: dict[str, Any], categories: dict[int, str | None]) -> tuple[Any, ...]:
    from serve import SceneObject

    return tuple(SceneObject(int(o["obj_id"]), str(o["name"]), categories.get(int(o["obj_id"])))
                 for o in scene.get("objects", []))


def _zipped_sources(base: Path, cache_dir: Path | None) -> list[Any]:
    from serve import SceneSource, estimate_scene_bytes

    manifest = read_manifest(base / MANIFEST)
    sums = read_sha256sums(base / SUMS)
    digest = file_sha256(base / MANIFEST)[:12]
    cache = (cache_dir or default_cache_dir()) / f"{manifest['name']}-{manifest.get('version', '0')}-{digest}"
    categories = _categories(manifest["objects"])
    out = []
    for scene in manifest["scenes"]:
        sid = int(scene["scene_id"])
        zip_path = base / bundle_zip(manifest["name"], sid)
        if bundle_zip(manifest["name"], sid) not in sums:
            raise ReleaseError(f"{base / SUMS}: does not list {zip_path.name} (scene {scene['name']!r})")
        if not zip_path.is_file():
            raise ReleaseError(f"{zip_path}: the bundle of scene {scene['name']!r} is missing from the release")
        splat, models = _zip_sizes(zip_path, bundle_folder(sid))
        locate = _Unpacker(zip_path, sums[zip_path.name], bundle_folder(sid), cache)
        out.append(SceneSource(str(scene["name"]), sid, _scene_objects(scene, categories),
                               estimate_scene_bytes(splat, models), locate, str(zip_path)))
    return out


def _zip_sizes(path: Path, folder: str) -> tuple[int, int]:
    """Uncompressed bytes of the splat and of the models in a bundle zip (its directory only)."""
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
    except (zipfile.BadZipFile, OSError) as exc:
        raise ReleaseError(f"{path}: not a readable zip ({exc})") from None
    splat = sum(i.file_size for i in infos if i.filename == f"{folder}/splat.ply")
    models = sum(i.file_size for i in infos if i.filename.startswith(f"{folder}/models/"))
    if splat == 0:
        raise ReleaseError(f"{path}: holds no {folder}/splat.ply")
    return splat, models


class _Unpacker:
    """Returns a scene's unpacked bundle folder, unpacking its zip (checked against SHA256SUMS)
    into the cache the first time; a half-unpacked folder never appears (staged, then renamed)."""

    def __init__(self, zip_path: Path, sha256: str, folder: str, cache: Path) -> None:
        self.zip_path, self.sha256, self.folder, self.cache = zip_path, sha256, folder, cache
        self.target = cache / folder
        self._lock = threading.Lock()

    def __call__(self) -> Path:
        with self._lock:
            stamp = self.target / ".unpacked-from"
            if stamp.is_file() and stamp.read_text().strip() == self.sha256:
                return self.target
            digest = file_sha256(self.zip_path)
            if digest != self.sha256:
                raise ReleaseError(f"{self.zip_path}: sha256 {digest[:12]}... does not match {SUMS} "
                                   f"({self.sha256[:12]}...); the release was modified or is incomplete")
            with zipfile.ZipFile(self.zip_path) as zf:
                bad = member_outside(zf.namelist(), self.folder)
                if bad is not None:
                    raise ReleaseError(f"{self.zip_path}: member {bad} lies outside {self.folder}/")
                with staged_folder(self.target) as stage:
                    prefix = len(self.folder) + 1
                    for info in zf.infolist():
                        if info.is_dir():
                            continue
                        out = stage / info.filename[prefix:]
                        out.parent.mkdir(parents=True, exist_ok=True)
                        with zf.open(info) as src, open(out, "wb") as dst:
                            while chunk := src.read(1 << 20):
                                dst.write(chunk)
                    (stage / ".unpacked-from").write_text(self.sha256 + "\n")
            return self.target


def _unzipped_sources(base: Path) -> list[Any]:
    from serve import SceneSource, bundle_scene_source

    info = read_json(base / DATASET_INFO)
    if not isinstance(info, dict) or not isinstance(info.get("scenes"), list):
        raise ReleaseError(f"{base / DATASET_INFO}: field 'scenes': a list is required")
    categories = _categories(info.get("objects", []))
    out = []
    for i, scene in enumerate(info["scenes"]):
        try:
            sid, name = int(scene["scene_id"]), str(scene["name"])
        except (KeyError, TypeError, ValueError):
            raise ReleaseError(f"{base / DATASET_INFO}: field 'scenes[{i}]': 'scene_id' and 'name' are required") from None
        folder = base / bundle_folder(sid)
        if not (folder / "manifest.json").is_file():
            raise ReleaseError(f"{folder}: the bundle of scene {name!r} is missing (unzip "
                               f"{bundle_zip(str(info.get('name')), sid)} here)")
        found = bundle_scene_source(folder, sid)
        out.append(SceneSource(name, sid, _scene_objects(scene, categories) or found.objects, found.memory_bytes,
                               found.locate, str(folder)))
    return out
