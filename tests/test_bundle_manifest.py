"""A malformed bundle (issue #32 item 8): whatever shape its ``manifest.json``, ``scene.json`` or
``objects.json`` has, every reader (``brave6d serve``, the catalog's estimates, verify, load,
export's replace check) answers one line naming the file and the field (exit status 2), never a
traceback."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.cli import main
from brave6d.serve import BundleError, bundle_scene_source, load_bundle, make_synthetic_bundle
from brave6d.serve.bundle import MANIFEST, not_a_bundle, read_bundle_manifest, verify_manifest
from brave6d.serve.catalog import bundle_memory_bytes

Doc = dict[str, Any]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_synthetic_bundle(tmp_path_factory.mktemp("manifest_scene"), n_gaussians=300, n_views=4)


@pytest.fixture
def bundle(pristine: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(pristine, tmp_path / "bundle"))


def entry(m: Doc) -> Doc:
    return m["files"]["splat.ply"]


def set_entry(m: Doc, value: Any) -> None:
    m["files"]["splat.ply"] = value


# (file, how to break it, the field the message must name)
MALFORMED: list[tuple[str, Callable[[Any], Any], str]] = [
    ("manifest.json", lambda m: [m], "must be a JSON object"),
    ("manifest.json", lambda m: "bundle", "must be a JSON object"),
    ("manifest.json", lambda m: {**m, "files": list(m["files"])}, "field 'files'"),
    ("manifest.json", lambda m: {k: v for k, v in m.items() if k != "files"}, "field 'files'"),
    ("manifest.json", lambda m: {**m, "format": ["brave6d-bundle/1"]}, "field 'format'"),
    ("manifest.json", lambda m: (set_entry(m, "0" * 64), m)[1], "field 'files['splat.ply']'"),
    ("manifest.json", lambda m: (set_entry(m, None), m)[1], "field 'files['splat.ply']'"),
    ("manifest.json", lambda m: (entry(m).update(sha256="xyz"), m)[1], "field 'files['splat.ply'].sha256'"),
    ("manifest.json", lambda m: (entry(m).update(sha256=entry(m)["sha256"].upper()), m)[1],
     "field 'files['splat.ply'].sha256'"),
    ("manifest.json", lambda m: (entry(m).pop("sha256"), m)[1], "field 'files['splat.ply'].sha256'"),
    ("manifest.json", lambda m: (entry(m).update(bytes="12"), m)[1], "field 'files['splat.ply'].bytes'"),
    ("manifest.json", lambda m: (entry(m).update(bytes=1.5), m)[1], "field 'files['splat.ply'].bytes'"),
    ("manifest.json", lambda m: (entry(m).update(bytes=True), m)[1], "field 'files['splat.ply'].bytes'"),
    ("manifest.json", lambda m: (entry(m).update(bytes=-1), m)[1], "field 'files['splat.ply'].bytes'"),
    ("manifest.json", lambda m: (m["files"].update({"models//x.ply": entry(m)}), m)[1],
     "field 'files['models//x.ply']'"),
    ("manifest.json", lambda m: (m["files"].update({"/etc/passwd": entry(m)}), m)[1], "field 'files['/etc/passwd']'"),
    ("scene.json", lambda s: [s], "must be a JSON object"),
    ("scene.json", lambda s: {**s, "name": {"a": 1}}, "field 'name'"),
    ("objects.json", lambda o: [o], "must be a JSON object"),
    ("objects.json", lambda o: {**o, "objects": {"0": o["objects"][0]}}, "field 'objects'"),
    ("objects.json", lambda o: {**o, "objects": [1, 2]}, "field 'objects[0]'"),
    ("objects.json", lambda o: {**o, "objects": [{**o["objects"][0], "obj_id": "one"}]}, "field 'objects[0].obj_id'"),
]
IDS = [f"{f}-{i}" for i, (f, _, _) in enumerate(MALFORMED)]


def break_file(bundle: Path, name: str, change: Callable[[Any], Any]) -> Path:
    path = bundle / name
    path.write_text(json.dumps(change(json.loads(path.read_text()))))
    return path


@pytest.mark.parametrize("name,change,field", MALFORMED, ids=IDS)
def test_serve_names_the_file_and_the_field(bundle: Path, name: str, change: Callable[[Any], Any], field: str,
                                            capsys: pytest.CaptureFixture[str],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    import uvicorn

    monkeypatch.setattr(uvicorn.Server, "run", lambda *a, **k: pytest.fail("the server started"))
    path = break_file(bundle, name, change)
    assert main(["serve", str(bundle), "--device", "cpu", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"brave6d serve: error: {path}: ") and field in err[0], err


@pytest.mark.parametrize("name,change,field", [m for m in MALFORMED if m[0] == MANIFEST],
                         ids=[i for i, m in zip(IDS, MALFORMED) if m[0] == MANIFEST])
def test_every_manifest_reader_names_the_field(bundle: Path, name: str, change: Callable[[Any], Any],
                                               field: str) -> None:
    path = break_file(bundle, name, change)
    for read in (read_bundle_manifest, verify_manifest, bundle_memory_bytes, bundle_scene_source,
                 lambda b: load_bundle(b, verify=False), load_bundle):
        with pytest.raises(BundleError) as info:
            read(bundle)
        assert str(info.value).startswith(f"{path}: ") and field in str(info.value), (read, str(info.value))
    why = not_a_bundle(bundle)  # export refuses to replace it (unless --force, which moves it aside)
    assert why is not None and field in why, why


def test_a_good_manifest_reads_back(bundle: Path) -> None:
    manifest = read_bundle_manifest(bundle)
    assert manifest == json.loads((bundle / MANIFEST).read_text()) and "splat.ply" in manifest["files"]
    assert not_a_bundle(bundle) is None and bundle_memory_bytes(bundle) > (bundle / "splat.ply").stat().st_size


JSON = st.recursive(st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False,
                    allow_infinity=False) | st.text(max_size=70),
                    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=12), kids, max_size=4),
                    max_leaves=12)
ENTRY = st.one_of(JSON, st.fixed_dictionaries({"sha256": JSON, "bytes": JSON}),
                  st.fixed_dictionaries({"sha256": st.just("a" * 64), "bytes": JSON}),
                  st.fixed_dictionaries({"sha256": st.text(alphabet="0123456789abcdefABCDEF", min_size=63,
                                                           max_size=65), "bytes": st.integers(-2, 2**40)}))
MANIFESTS = st.one_of(JSON, st.fixed_dictionaries({"format": st.just("brave6d-bundle/1") | JSON, "files": JSON}),
                      st.fixed_dictionaries({"format": st.just("brave6d-bundle/1"),
                                             "files": st.dictionaries(st.sampled_from(["splat.ply", "models/a.ply", "",
                                                                                       "../x", "a\\b", "c:/x", "./s"]),
                                                                      ENTRY, max_size=3)}))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(manifest=MANIFESTS)
def test_any_manifest_shape_is_read_or_refused_naming_the_file(pristine: Path, tmp_path: Path, manifest: Any) -> None:
    folder = tmp_path / "b"
    folder.mkdir(exist_ok=True)
    (folder / MANIFEST).write_text(json.dumps(manifest))
    try:
        files = read_bundle_manifest(folder)["files"]
    except BundleError as exc:
        assert str(exc).startswith(f"{folder / MANIFEST}: ") and "\n" not in str(exc)
        return
    assert manifest["format"] == "brave6d-bundle/1"
    for rel, e in files.items():
        assert rel and ".." not in rel.split("/") and "\\" not in rel and not rel.startswith("/")
        assert isinstance(e["bytes"], int) and e["bytes"] >= 0 and len(e["sha256"]) == 64
    assert bundle_memory_bytes(folder) >= 0
