"""The scenes of a release, for the render server: ``brave6d serve RELEASE`` serves every scene of it.

The command line (``brave6d.commands.scenes``) asks :func:`release_scene_sources` for them and
hands them to the server: the serve stage never imports this stage.

Two forms of a release are served:

* the release folder ``brave6d release build`` wrote (zips, ``manifest.json``, ``SHA256SUMS``):
  each scene's ``<name>_bundle_XXXXXX.zip`` is checked against ``SHA256SUMS`` and unpacked into a
  cache folder the first time the scene is needed (never into the release folder, which ``release
  verify`` keeps free of other files); later servers reuse the unpacked bundle;
* the unzipped dataset (the ``<name>/`` folder BOP users make, with ``dataset_info.json`` and
  ``bundles/XXXXXX/``): bundles are served in place.

Either way each scene's objects carry the library's category, and its memory estimate comes from
the file sizes (the zip's directory or the bundle's manifest) without reading the splat.

A release is untrusted: each bundle zip's directory is checked at start (member names, sizes:
:func:`brave6d.dataset.release.zips.open_zip`) and unpacked only by that module's safe unpacker. The cache
folder is checked at start too: made when missing; a file, a folder that cannot be written or a
disk without room for the largest bundle not unpacked yet is an error naming the folder. A scene's
``SceneSource.refresh`` unpacks its bundle again from the zip (checked against ``SHA256SUMS``
again), for when the unpacked folder fails its checks.
"""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path
from typing import Any

from brave6d.core.atomic import file_sha256, read_json, staged_folder
from brave6d.dataset.release.formats import DATASET_INFO, MANIFEST, SUMS, bundle_folder, bundle_zip, read_sha256sums
from brave6d.dataset.release.manifest import read_manifest
from brave6d.dataset.release.source import ReleaseError
from brave6d.dataset.release.zips import check_free_space, open_zip

#: The file in an unpacked bundle folder naming the sha256 of the zip it was unpacked from.
STAMP = ".unpacked-from"

#: Where unpacked bundles go unless a cache folder is given: ``$BRAVE6D_CACHE``, else
#: ``$XDG_CACHE_HOME/brave6d``, else ``~/.cache/brave6d``.
CACHE_ENV = "BRAVE6D_CACHE"


def default_cache_dir() -> Path:
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "brave6d"


def release_scene_sources(root: Path | str, cache_dir: Path | str | None = None) -> list[Any]:
    """One ``brave6d.serve.SceneSource`` per scene of the release at ``root`` (see the module docstring)."""
    from brave6d.serve import MANIFEST as BUNDLE_MANIFEST
    from brave6d.serve import SPLAT

    base = Path(root)
    if (base / MANIFEST).is_file() and (base / SUMS).is_file():
        return _zipped_sources(base, Path(cache_dir) if cache_dir is not None else None)
    if (base / DATASET_INFO).is_file() and (base / "bundles").is_dir():
        return _unzipped_sources(base)
    raise ReleaseError(f"{base}: neither a bundle ({BUNDLE_MANIFEST} + {SPLAT}), a release folder ({MANIFEST} + "
                       f"{SUMS}, from 'brave6d release build') nor an unzipped release ({DATASET_INFO} + bundles/)")


def _categories(objects: list[dict[str, Any]]) -> dict[int, str | None]:
    return {int(o["obj_id"]): o.get("category") for o in objects}


def _scene_objects(scene: dict[str, Any], categories: dict[int, str | None]) -> tuple[Any, ...]:
    from brave6d.serve import SceneObject

    return tuple(SceneObject(int(o["obj_id"]), str(o["name"]), categories.get(int(o["obj_id"])))
                 for o in scene.get("objects", []))


def _zipped_sources(base: Path, cache_dir: Path | None) -> list[Any]:
    from brave6d.serve import SceneSource, listed_scene_bytes

    manifest = read_manifest(base / MANIFEST)
    sums = read_sha256sums(base / SUMS)
    digest = file_sha256(base / MANIFEST)[:12]
    root = cache_dir or default_cache_dir()
    # name and version come from a downloaded manifest.json: read_manifest checked each as a folder name
    cache = root / f"{manifest['name']}-{manifest['version']}-{digest}"
    categories = _categories(manifest["objects"])
    out, unpackers = [], []
    for scene in manifest["scenes"]:
        sid = int(scene["scene_id"])
        zip_path = base / bundle_zip(manifest["name"], sid)
        if bundle_zip(manifest["name"], sid) not in sums:
            raise ReleaseError(f"{base / SUMS}: does not list {zip_path.name} (scene {scene['name']!r})")
        if not zip_path.is_file():
            raise ReleaseError(f"{zip_path}: the bundle of scene {scene['name']!r} is missing from the release")
        unpacker = _Unpacker(zip_path, sums[zip_path.name], bundle_folder(sid), cache)
        memory = listed_scene_bytes(unpacker.sizes())
        unpackers.append(unpacker)
        out.append(SceneSource(str(scene["name"]), sid, _scene_objects(scene, categories),
                               memory, unpacker, str(zip_path), refresh=unpacker.refresh))
    _check_cache(root, max((u for u in unpackers if not u.unpacked()), key=lambda u: u.bytes, default=None))
    return out


def _check_cache(cache: Path, largest: _Unpacker | None) -> None:
    """The cache folder exists (made when missing), can be written, and holds the largest bundle
    not unpacked yet (``largest``); else an error naming the folder and what is wrong."""
    if cache.exists() and not cache.is_dir():
        raise ReleaseError(f"{cache}: the cache folder is a file, not a folder; give --cache-dir a folder")
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReleaseError(f"{cache}: the cache folder cannot be made ({exc.strerror or exc}); give --cache-dir "
                           "a folder this user can write") from None
    try:
        fd, probe = tempfile.mkstemp(dir=cache, prefix=".write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ReleaseError(f"{cache}: the cache folder is not writable ({exc.strerror or exc}); give --cache-dir "
                           "a folder this user can write") from None
    if largest is not None:
        check_free_space(cache, largest.bytes, f"unpacking {largest.zip_path.name} (the largest bundle)")


class _Unpacker:
    """Returns a scene's unpacked bundle folder, unpacking its zip (checked against SHA256SUMS)
    into the cache the first time; a half-unpacked folder never appears (staged, then renamed).
    ``refresh()`` unpacks it again whatever the stamp says (the folder failed its checks)."""

    def __init__(self, zip_path: Path, sha256: str, folder: str, cache: Path) -> None:
        self.zip_path, self.sha256, self.folder, self.cache = zip_path, sha256, folder, cache
        self.target = cache / folder
        self.bytes = 0  # unpacked size, from the zip's directory (sizes())
        self._lock = threading.Lock()

    def sizes(self) -> dict[str, int]:
        """Uncompressed bytes of each member, by its path inside the bundle folder (the zip's
        directory only, checked); a zip without the splat is refused."""
        from brave6d.serve import SPLAT

        prefix = f"{self.folder}/"
        with open_zip(self.zip_path, inside=self.folder) as zf:
            sizes = {n[len(prefix):]: zf.size(n) for n in zf.names if n.startswith(prefix)}
            self.bytes = sum(zf.size(n) for n in zf.names)
        if not sizes.get(SPLAT):
            raise ReleaseError(f"{self.zip_path}: holds no {prefix}{SPLAT}")
        return sizes

    def unpacked(self) -> bool:
        """The folder was unpacked from this very zip (its stamp says so)."""
        stamp = self.target / STAMP
        return stamp.is_file() and stamp.read_text().strip() == self.sha256

    def __call__(self) -> Path:
        with self._lock:
            return self.target if self.unpacked() else self._unpack()

    def refresh(self) -> Path:
        """Unpack the bundle again from its zip, checked against SHA256SUMS again (the stamp is ignored)."""
        with self._lock:
            return self._unpack()

    def _unpack(self) -> Path:
        digest = file_sha256(self.zip_path)
        if digest != self.sha256:
            raise ReleaseError(f"{self.zip_path}: sha256 {digest[:12]}... does not match {SUMS} "
                               f"({self.sha256[:12]}...); the release was modified or is incomplete")
        try:
            with open_zip(self.zip_path, inside=self.folder) as zf, staged_folder(self.target) as stage:
                try:
                    zf.extract(stage, strip=self.folder)
                except ReleaseError as exc:  # name the bundle folder, not its hidden staging sibling
                    raise ReleaseError(str(exc).replace(str(stage), str(self.target))) from None
                (stage / STAMP).write_text(self.sha256 + "\n")
        except OSError as exc:  # the stage itself, the stamp (the unpacker names its own errors)
            raise ReleaseError(f"{self.cache}: cannot unpack {self.zip_path.name} here "
                               f"({exc.strerror or exc})") from None
        return self.target


def _unzipped_sources(base: Path) -> list[Any]:
    from brave6d.serve import SceneSource, bundle_scene_source, is_bundle

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
        if not is_bundle(folder):
            raise ReleaseError(f"{folder}: the bundle of scene {name!r} is missing (unzip "
                               f"{bundle_zip(str(info.get('name')), sid)} here)")
        found = bundle_scene_source(folder, sid)
        out.append(SceneSource(name, sid, _scene_objects(scene, categories) or found.objects, found.memory_bytes,
                               found.locate, str(folder)))
    return out
