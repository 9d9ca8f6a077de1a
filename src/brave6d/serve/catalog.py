"""The scenes one server serves: a catalog that loads each scene on first use, within a memory bound.

A server serves one bundle or every scene of a dataset release. Each scene is a
:class:`SceneSource`: its name, BOP ``scene_id``, the objects it holds (for ``GET /scenes``
without loading anything), an estimate of the memory it needs once loaded, and a ``locate``
callable that returns its bundle folder (a release unpacks the scene's bundle zip there on
first use; a bundle folder is simply returned). The serve stage makes the source of a bundle
folder (:func:`bundle_scene_source`); a release's sources come from its owner,
``brave6d.dataset.release_scene_sources``, and the command line hands them to :func:`open_scenes`
(serve never imports the dataset stage).

:class:`SceneCatalog` loads a scene (verified bundle, splat renderer, visibility) when an episode
first needs it and keeps it while episodes are open on it. Loaded scenes that no open episode
uses are evicted least-recently-used first when a new scene would exceed the bound: at most
``max_loaded`` scenes and at most ``memory_budget_bytes`` of estimated memory. A scene whose
load would exceed the bound while every loaded scene has open episodes is refused with 503
(:class:`SceneCacheFull`), naming the scenes that hold the memory; the client retries after
closing episodes. Loads of one scene are never done twice at once (a second request waits for
the first); loads of different scenes run concurrently within the bound.

A scene's files are the server's, not the client's: a bundle folder that fails its checks
(tampered, truncated, malformed) is remade once from its source (:attr:`SceneSource.refresh`: a
release unpacks its verified zip again) and verified again; when that fails too, or the source
has no refresh, or locating / unpacking the scene fails (a release error, a full disk), the
request gets 503 (:class:`SceneUnavailable`) naming the scene and the cause, and the server goes
on serving the other scenes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.serve.bundle import (
    MANIFEST,
    MODELS,
    REFERENCE,
    SCENE,
    SPLAT,
    Bundle,
    bundle_scene_name,
    is_bundle,
    load_bundle,
    read_bundle_json,
    read_bundle_manifest,
    read_listed_objects,
)
from brave6d.serve.episodes import EpisodeError, EpisodeNotFound, InvalidAction, SceneServer

log = logging.getLogger(__name__)

#: Estimated resident bytes of a loaded scene per byte of its splat PLY (the renderer keeps ~60
#: float32 per Gaussian, the PLY stores 62), and per byte of its object models and its reference
#: geometry (mesh + ray-casting structure); plus a fixed part. ``benchmarks/serve_scenes.py`` measures the real figure.
SPLAT_BYTES_FACTOR = 1.0
MODEL_BYTES_FACTOR = 6.0
SCENE_FIXED_BYTES = 8 * 2**20


def estimate_scene_bytes(splat_bytes: int, model_bytes: int) -> int:
    """The memory a loaded scene is expected to hold, from its file sizes (see the factors above)."""
    return int(SPLAT_BYTES_FACTOR * splat_bytes + MODEL_BYTES_FACTOR * model_bytes + SCENE_FIXED_BYTES)


def listed_scene_bytes(sizes: Mapping[str, int]) -> int:
    """:func:`estimate_scene_bytes` of a bundle's files listed as path inside the bundle -> bytes (its
    manifest, or a release zip's directory): the splat, and what loads beside it, the object models
    and the reference geometry. The one place that says which files count."""
    splat = sizes.get(SPLAT, 0)
    beside = sum(b for name, b in sizes.items() if name.startswith(f"{MODELS}/") or name == REFERENCE)
    return estimate_scene_bytes(splat, beside)


class SceneCacheFull(EpisodeError):
    """Loading the scene would exceed the memory bound and no loaded scene is free to evict."""

    status = 503


class SceneUnavailable(EpisodeError):
    """The scene's files cannot be located, unpacked, verified or loaded: the server's problem
    (503, with the cause), never the request's. ``cause``: the error behind it."""

    status = 503

    def __init__(self, message: str, field: str | None = None, cause: BaseException | None = None) -> None:
        super().__init__(message, field)
        self.cause = cause


@dataclass(frozen=True)
class SceneObject:
    """An object of a scene as listed before the scene is loaded."""

    obj_id: int
    name: str
    category: str | None = None


@dataclass(frozen=True)
class SceneSource:
    """One scene a server can serve (see the module docstring); ``locate()`` returns its bundle folder."""

    name: str
    scene_id: int | None
    objects: tuple[SceneObject, ...]
    memory_bytes: int
    locate: Callable[[], Path]
    origin: str  # where it comes from, for messages and ``GET /scenes``
    #: Makes the bundle folder again from its source (a release's zip, checked against SHA256SUMS)
    #: when the folder ``locate()`` gave fails its checks; None: the folder is the source itself.
    refresh: Callable[[], Path] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "scene_id": self.scene_id, "origin": self.origin,
                "objects": [{"obj_id": o.obj_id, "name": o.name, "category": o.category} for o in self.objects],
                "memory_mb_estimate": round(self.memory_bytes / 2**20, 1)}


#: ``(BUNDLE_OR_RELEASE, cache folder or None) -> its scene sources``: what the command line hands a
#: serving command (``brave serve``, ``ros1``, ``ros2``; :func:`brave6d.commands.scenes.scene_sources`).
SourcesOf = Callable[[Path, Path | None], Sequence[SceneSource]]


def bundle_memory_bytes(folder: Path) -> int:
    """:func:`estimate_scene_bytes` of a bundle folder (from the sizes its manifest lists)."""
    return listed_scene_bytes({name: v["bytes"] for name, v in read_bundle_manifest(folder)["files"].items()})


def bundle_scene_source(folder: Path | str, scene_id: int | None = None) -> SceneSource:
    """The :class:`SceneSource` of one bundle folder (its manifest must exist; it is verified on load).
    A malformed manifest, ``scene.json`` or ``objects.json`` raises :class:`BundleError` naming the
    file and the field."""
    root = Path(folder)
    if not root.exists():
        raise BraveError(f"{root}: no such bundle")
    if not is_bundle(root):
        raise BraveError(f"{root}: not a bundle (no {MANIFEST} and {SPLAT}); give a bundle folder written by "
                         "'brave6d export' or a release folder written by 'brave6d release build'")
    scene_name = bundle_scene_name(root, read_bundle_json(root, SCENE))
    objects = tuple(SceneObject(o["obj_id"], o["name"], o.get("class")) for o in read_listed_objects(root))
    return SceneSource(scene_name, scene_id, objects, bundle_memory_bytes(root), lambda: root, str(root))


@dataclass
class _Loaded:
    scene: SceneServer
    source: SceneSource
    pins: int = 0
    permanent: bool = False  # a scene handed in loaded (never evicted, not counted as an episode)
    last_used: float = field(default_factory=time.monotonic)


@dataclass
class CatalogStats:
    """What the catalog did: loads (with their seconds), evictions, refusals."""

    loads: int = 0
    evictions: int = 0
    refusals: int = 0
    load_seconds: dict[str, list[float]] = field(default_factory=dict)


class SceneCatalog:
    """The scenes of one server, loaded lazily within a memory bound (see the module docstring)."""

    def __init__(self, sources: Sequence[SceneSource], *, device: str = "auto", max_loaded: int | None = None,
                 memory_budget_bytes: int | None = None, warm_up: bool = True,
                 load_scene: Callable[[Bundle, str], SceneServer] | None = None) -> None:
        if not sources:
            raise BraveError("no scenes to serve")
        names = [s.name for s in sources]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise BraveError(f"two scenes are named {dup[0]!r}: scene names must be unique within a server")
        if max_loaded is not None and max_loaded < 1:
            raise BraveError(f"max_loaded must be at least 1, got {max_loaded}")
        too_big = [s for s in sources if memory_budget_bytes is not None and s.memory_bytes > memory_budget_bytes]
        if too_big:
            s = too_big[0]
            raise BraveError(f"scene {s.name!r} needs about {s.memory_bytes / 2**20:.0f} MB, more than the memory "
                             f"budget of {memory_budget_bytes / 2**20:.0f} MB: raise --max-memory-mb")
        self.sources: tuple[SceneSource, ...] = tuple(sources)
        self.device = device
        self.max_loaded = max_loaded
        self.memory_budget_bytes = memory_budget_bytes
        self.warm_up = warm_up
        self._load_scene = load_scene or _default_load
        self._loaded: OrderedDict[str, _Loaded] = OrderedDict()
        self._loading: dict[str, int] = {}  # name -> reserved bytes
        self._bundles: dict[str, Bundle] = {}  # verified bundles (small: no splat in memory)
        self._cond = threading.Condition()
        self.stats = CatalogStats()

    @classmethod
    def of_scene(cls, scene: SceneServer) -> SceneCatalog:
        """A catalog of one scene that is already loaded (never evicted)."""
        b = scene.bundle
        source = SceneSource(b.name, None, tuple(SceneObject(o.obj_id, o.name, o.class_name) for o in b.objects),
                             0, lambda: b.root, str(b.root))
        catalog = cls([source], device=scene.device)
        catalog._loaded[b.name] = _Loaded(scene, source, pins=1, permanent=True)
        catalog._bundles[b.name] = b
        return catalog

    # -------------------------------------------------------------- lookup
    def names(self) -> list[str]:
        return [s.name for s in self.sources]

    def source(self, key: str | int | None) -> SceneSource:
        """The scene named ``key`` (a name, or a BOP ``scene_id``); None: the only scene, if there is one."""
        if key is None:
            if len(self.sources) == 1:
                return self.sources[0]
            raise InvalidAction(f"this server serves {len(self.sources)} scenes: name one in 'scene' "
                                f"(one of {self.names()})", "scene")
        for s in self.sources:
            if (isinstance(key, str) and s.name == key) or (isinstance(key, int) and not isinstance(key, bool)
                                                           and s.scene_id == key):
                return s
        if isinstance(key, str) and key.isascii() and key.isdigit():  # "²".isdigit(), but int("²") fails
            return self.source(int(key))
        raise EpisodeNotFound(f"no scene {key!r} on this server (scenes: {self.names()})", "scene")

    def loaded_names(self) -> list[str]:
        with self._cond:
            return list(self._loaded)

    def loaded_scenes(self) -> list[SceneServer]:
        with self._cond:
            return [e.scene for e in self._loaded.values()]

    def device_name(self) -> str:
        """The device scenes render on (``cpu``/``cuda``), resolved from ``device``."""
        loaded = self.loaded_scenes()
        if loaded:
            return loaded[0].device
        from brave6d.training import resolve_device

        return resolve_device(self.device).type

    def loaded_bytes(self) -> int:
        with self._cond:
            return self._used_bytes()

    def _used_bytes(self) -> int:
        """Estimated bytes of the loaded scenes and of those being loaded (call with the lock held)."""
        return sum(e.source.memory_bytes for e in self._loaded.values()) + sum(self._loading.values())

    # -------------------------------------------------------------- loading
    def acquire(self, key: str | int | None) -> SceneServer:
        """The loaded scene ``key`` (loading it first when needed), pinned until :meth:`release`."""
        src = self.source(key)
        with self._cond:
            while True:
                entry = self._loaded.get(src.name)
                if entry is not None:
                    entry.pins += 1
                    entry.last_used = time.monotonic()
                    self._loaded.move_to_end(src.name)
                    return entry.scene
                if src.name in self._loading:
                    self._cond.wait()
                    continue
                self._make_room(src)
                self._loading[src.name] = src.memory_bytes
                break
        t0 = time.perf_counter()
        try:
            scene = self._load(src)
        except BaseException:
            with self._cond:
                self._loading.pop(src.name, None)
                self._cond.notify_all()
            raise
        seconds = time.perf_counter() - t0
        with self._cond:
            self._loading.pop(src.name, None)
            self._loaded[src.name] = _Loaded(scene, src, pins=1)
            self.stats.loads += 1
            self.stats.load_seconds.setdefault(src.name, []).append(seconds)
            self._cond.notify_all()
        log.info("scene %s loaded in %.2f s (%d Gaussians)", src.name, seconds, scene.renderer.num_gaussians)
        return scene

    def release(self, scene: SceneServer) -> None:
        """Unpin a scene returned by :meth:`acquire` (it stays loaded until room is needed)."""
        with self._cond:
            for entry in self._loaded.values():
                if entry.scene is scene:
                    entry.pins = max(0, entry.pins - 1)
                    entry.last_used = time.monotonic()
                    break
            self._cond.notify_all()

    def bundle(self, key: str | int | None) -> Bundle:
        """The scene's bundle (loaded scene's, else read and verified from its folder; no renderer)."""
        return self._bundle(self.source(key))

    def _bundle(self, src: SceneSource, *, again: bool = False) -> Bundle:
        """The scene's verified bundle: known, else located and verified (:meth:`_verified`);
        ``again``: verified again even when known (its files failed to load)."""
        with self._cond:
            known = None if again else self._bundles.get(src.name)
        if known is not None:
            return known
        bundle = self._verified(src)  # its own name may differ: the source's name is the scene's
        with self._cond:
            if again:
                self._bundles[src.name] = bundle
            return self._bundles.setdefault(src.name, bundle)

    def _verified(self, src: SceneSource) -> Bundle:
        """The scene's bundle folder, located and verified; a folder that fails its checks is remade
        once from the source (``src.refresh``: a release unpacks its verified zip again) and verified
        again. What still fails, or cannot be located or unpacked, is :class:`SceneUnavailable`."""
        try:
            return load_bundle(self._folder(src, src.locate))
        except (BraveError, OSError) as exc:
            if isinstance(exc, SceneUnavailable):
                raise
            if src.refresh is None:
                raise _unavailable(src, exc, "its files fail their checks and it has no source to remake them "
                                             "from") from None
            log.warning("scene %s: %s; remaking its bundle folder from %s", src.name, exc, src.origin)
        try:
            return load_bundle(self._folder(src, src.refresh))
        except SceneUnavailable:
            raise
        except (BraveError, OSError) as exc:
            raise _unavailable(src, exc, f"its bundle folder was remade from {src.origin} and still fails") from None

    @staticmethod
    def _folder(src: SceneSource, make: Callable[[], Path]) -> Path:
        """``make()`` (the source's locate or refresh); an error there is :class:`SceneUnavailable`."""
        try:
            return make()
        except (BraveError, OSError) as exc:
            raise _unavailable(src, exc, "its bundle cannot be located or unpacked") from None

    def _fits(self, need: int) -> bool:
        count = len(self._loaded) + len(self._loading) + 1
        return ((self.max_loaded is None or count <= self.max_loaded)
                and (self.memory_budget_bytes is None or self._used_bytes() + need <= self.memory_budget_bytes))

    def _make_room(self, src: SceneSource) -> None:
        """Evict unpinned scenes (least recently used first) until ``src`` fits; else :class:`SceneCacheFull`."""
        while not self._fits(src.memory_bytes):
            free = [name for name, e in self._loaded.items() if e.pins == 0]
            if not free:
                self.stats.refusals += 1
                busy = ", ".join(f"{n} ({e.pins} open)" for n, e in self._loaded.items()) or "none"
                budget = (f"{self.memory_budget_bytes / 2**20:.0f} MB" if self.memory_budget_bytes is not None
                          else "no memory budget")
                raise SceneCacheFull(
                    f"cannot load scene {src.name!r} (~{src.memory_bytes / 2**20:.0f} MB): the server is at its bound "
                    f"({self.max_loaded or 'any number of'} scenes, {budget}) and every loaded scene has open "
                    f"episodes: {busy}; close episodes and retry", "scene")
            victim = min(free, key=lambda n: self._loaded[n].last_used)
            del self._loaded[victim]
            self.stats.evictions += 1
            log.info("scene %s evicted (memory bound)", victim)

    def _load(self, src: SceneSource) -> SceneServer:
        try:
            scene = self._load_scene(self._bundle(src), self.device)
        except (BraveError, OSError) as exc:  # files verified earlier changed since: verify (and remake) again
            if isinstance(exc, EpisodeError):
                raise
            log.warning("scene %s: %s; verifying its bundle again", src.name, exc)
            try:
                scene = self._load_scene(self._bundle(src, again=True), self.device)
            except EpisodeError:
                raise
            except (BraveError, OSError) as again:
                raise _unavailable(src, again, "its verified bundle does not load") from None
        return warm_scene(scene) if self.warm_up else scene

    def describe(self) -> dict[str, Any]:
        """What ``GET /scenes`` returns: every scene, whether it is loaded, and the bound."""
        with self._cond:
            loaded = {n: e for n, e in self._loaded.items()}
            loading = set(self._loading)
            scenes = []
            for s in self.sources:
                e = loaded.get(s.name)
                times = self.stats.load_seconds.get(s.name, [])
                scenes.append({**s.to_json(), "loaded": e is not None, "loading": s.name in loading,
                               "open_episodes": (e.pins - int(e.permanent)) if e is not None else 0,
                               "gaussians": e.scene.renderer.num_gaussians if e is not None else None,
                               "load_s": times[-1] if times else None})
            return {"scenes": scenes, "device": self.device,
                    "bound": {"max_loaded": self.max_loaded,
                              "memory_budget_mb": (None if self.memory_budget_bytes is None
                                                   else round(self.memory_budget_bytes / 2**20, 1)),
                              "loaded_mb_estimate": round(sum(e.source.memory_bytes for e in loaded.values()) / 2**20,
                                                          1)},
                    "stats": {"loads": self.stats.loads, "evictions": self.stats.evictions,
                              "refusals": self.stats.refusals}}


def _unavailable(src: SceneSource, exc: BaseException, why: str) -> SceneUnavailable:
    """The 503 of a scene the server cannot serve: its name, what went wrong and the cause."""
    cause = str(exc) or type(exc).__name__
    return SceneUnavailable(f"scene {src.name!r} cannot be served ({why}): {cause}", "scene", exc)


def _default_load(bundle: Bundle, device: str) -> SceneServer:
    return SceneServer(bundle, device)


def warm_scene(scene: SceneServer) -> SceneServer:
    """``scene`` after one small render (compiled kernels loaded), so its first episode is not slow."""
    from brave6d.serve.renderer import lookat_default

    b = scene.bundle
    target = b.objects[0].world_T_obj[:3, 3] if b.objects else np.zeros(3)
    try:
        scene.renderer.warm_up(b.camera, lookat_default(b.start, target))
    except BraveError:
        pass
    return scene


def open_scenes(scenes: Sequence[SceneSource] | Path | str, *, device: str = "auto", max_loaded: int | None = None,
                max_memory_mb: float | None = None, warm_up: bool = True) -> SceneCatalog:
    """The catalog of ``scenes``: the sources the command line assembled (a bundle's, or every
    scene of a release: ``brave6d.dataset.release_scene_sources``), or one bundle folder."""
    budget = None if max_memory_mb is None else int(max_memory_mb * 2**20)
    sources = [bundle_scene_source(scenes)] if isinstance(scenes, (str, Path)) else list(scenes)
    return SceneCatalog(sources, device=device, max_loaded=max_loaded, memory_budget_bytes=budget, warm_up=warm_up)
