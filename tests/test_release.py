"""``brave6d release build`` / ``verify`` on a two-scene synthetic dataset: what a release holds,
that verify passes on it, and that an altered, truncated, incomplete or padded release fails
naming the file."""

from __future__ import annotations

import hashlib
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from brave6d.annotation import export_bop, read_scene_gt
from brave6d.core.atomic import write_png
from brave6d.core.layout import SceneDir
from brave6d.cli import main
from brave6d.core.layout import FrameLog, SceneDir
from brave6d.dataset.release import ReleaseError, build_release, read_sha256sums, read_targets, verify_release
from brave6d.serve import export_bundle, load_bundle, make_synthetic_scene

pytestmark = pytest.mark.slow  # the module fixture makes, exports and bundles two scenes (~10 s)

NAME = "synthset"
CITATION = "@misc{synthset, title={A synthetic set}, year={2026}}"


def _add_depth(scene: SceneDir) -> None:
    """Give every frame of a synthetic scene a depth image (the synthetic scene has none)."""
    records = scene.frames()
    scene.frames_path.unlink()
    log = FrameLog(scene.frames_path)
    for r in records:
        rel = f"depth/{r.index:06d}.png"
        write_png(scene.capture_dir / rel, np.full((240, 320), 300 + r.index, dtype=np.uint16))
        log.append(r.model_copy(update={"depth": rel}))


def _make_scene(root: Path, n_views: int, depth: bool, psnr: float | None) -> None:
    scene = make_synthetic_scene(root, n_gaussians=2000, n_views=n_views)
    if depth:
        _add_depth(scene)
    if psnr is not None:
        (scene.splat_dir / "metrics.json").write_text(json.dumps(
            {"holdout": {"psnr": psnr, "ssim": 0.9, "n_views": 1,
                         "per_level": {"0": {"distance_m": 0.3, "psnr": psnr, "ssim": 0.9, "n_views": 1}}}}))
    export_bop(scene.root)
    export_bundle(scene.root)


def _write_dataset(workdir: Path, objects: list[str]) -> None:
    """A dataset.yaml as `brave6d dataset run` leaves it: valid for brave6d.core.dataset_spec, each scene
    entry pointing at its scene directory's scene.yaml (named after the folder), a library whose
    meshes are the scenes' (plus objects no scene uses)."""
    meshes = workdir / "meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    for name in ("scene_a", "scene_b"):
        spec_file = workdir / "scenes" / name / "scene.yaml"
        spec = yaml.safe_load(spec_file.read_text())
        spec["name"] = name
        spec_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    scene_a = SceneDir(workdir / "scenes" / "scene_a")
    cube = scene_a.asset_path("cube_red.ply")
    library = []
    for n in objects:
        in_scene = scene_a.asset_path(f"{n}.ply")
        if not in_scene.is_file():  # an object of the library that no scene shows
            shutil.copyfile(cube, meshes / f"{n}.ply")
        mesh = in_scene if in_scene.is_file() else meshes / f"{n}.ply"
        library.append({"name": n, "category": "toys_office", "mesh": str(mesh.relative_to(workdir)), "scale": 0.001})
    dataset = {"name": NAME, "version": "1.0", "license": "CC-BY-4.0", "citation": CITATION,
               "description": "Two synthetic tabletop scenes sharing two cubes.",
               "objects": library,
               "scenes": [{"spec": "scenes/scene_a/scene.yaml"}, {"spec": "scenes/scene_b/scene.yaml"}]}
    (workdir / "dataset.yaml").write_text(yaml.safe_dump(dataset, sort_keys=False))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("dataset")
    _make_scene(root / "scenes" / "scene_a", 6, depth=True, psnr=27.5)
    _make_scene(root / "scenes" / "scene_b", 5, depth=False, psnr=None)
    _write_dataset(root, ["cube_red", "cube_blue", "mug"])
    return root


@pytest.fixture(scope="module")
def release(workdir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("release") / "out"
    build_release(workdir, out)
    return out


@pytest.fixture()
def copy(release: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(release, tmp_path / "copy"))


def _resum(root: Path) -> None:
    """Recompute SHA256SUMS after a deliberate change, so that the deeper checks are reached."""
    names = read_sha256sums(root / "SHA256SUMS")
    lines = [f"{hashlib.sha256((root / n).read_bytes()).hexdigest()}  {n}\n" for n in sorted(names)]
    (root / "SHA256SUMS").write_text("".join(lines))


def _rewrite_zip(path: Path, drop: str | None = None, replace: dict[str, bytes] | None = None) -> None:
    tmp = path.with_suffix(".tmp")
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(tmp, "w") as dst:
        for info in src.infolist():
            if info.filename != drop:
                dst.writestr(info, (replace or {}).get(info.filename, src.read(info)))
    tmp.replace(path)


def test_release_holds_bop_splits_bundles_and_card(release: Path, workdir: Path) -> None:
    files = sorted(p.name for p in release.iterdir())
    assert files == sorted(["README.md", "SHA256SUMS", "manifest.json", f"{NAME}_base.zip", f"{NAME}_models.zip",
                            f"{NAME}_test_all.zip", f"{NAME}_bundle_000001.zip", f"{NAME}_bundle_000002.zip"])
    assert set(read_sha256sums(release / "SHA256SUMS")) == set(files) - {"SHA256SUMS"}
    with zipfile.ZipFile(release / f"{NAME}_test_all.zip") as zf:
        names = set(zf.namelist())
        gt_b = json.loads(zf.read("test/000002/scene_gt.json"))
        holdout_a = json.loads(zf.read("test/000001/holdout.json"))
    assert {"test/000001/rgb/000000.png", "test/000001/depth/000005.png", "test/000001/mask/000005_000001.png",
            "test/000001/mask_visib/000000_000000.png", "test/000002/rgb/000004.png",
            "test/000002/scene_camera.json", "test/000002/scene_gt_info.json"} <= names
    assert not any(n.startswith("test/000002/depth/") for n in names)  # scene_b has no depth
    assert "test/000002/rgb/000005.png" not in names
    assert sorted(gt_b) == [str(i) for i in range(5)]
    manifest = json.loads((release / "manifest.json").read_text())
    bundle_a = load_bundle(workdir / "scenes" / "scene_a" / "bundle")
    assert holdout_a["im_ids"] == sorted(h.index for h in bundle_a.holdout) == manifest["scenes"][0]["holdout_im_ids"]
    assert holdout_a["im_ids"]
    # the reference geometry travels in the bundle zip of the scene with depth, with its manifest entry
    with zipfile.ZipFile(release / f"{NAME}_bundle_000001.zip") as zf:
        listed = json.loads(zf.read("bundles/000001/manifest.json"))["files"]
        assert "reference.ply" in listed and "bundles/000001/reference.ply" in zf.namelist()
        assert hashlib.sha256(zf.read("bundles/000001/reference.ply")).hexdigest() == listed["reference.ply"]["sha256"]
    with zipfile.ZipFile(release / f"{NAME}_bundle_000002.zip") as zf:  # scene_b has no depth: no reference
        assert not any(n.endswith("reference.ply") for n in zf.namelist())
    with zipfile.ZipFile(release / f"{NAME}_models.zip") as zf:
        assert sorted(zf.namelist()) == ["models/models_info.json", "models/obj_000001.ply", "models/obj_000002.ply"]
    with zipfile.ZipFile(release / f"{NAME}_base.zip") as zf:
        camera = json.loads(zf.read(f"{NAME}/camera.json"))
        info = json.loads(zf.read(f"{NAME}/dataset_info.json"))
        targets = json.loads(zf.read(f"{NAME}/test_targets_bop19.json"))
        held = json.loads(zf.read(f"{NAME}/test_targets_bop19_holdout.json"))
    assert (camera["width"], camera["height"]) == (320, 240) and camera["cx"] == pytest.approx(160.0)
    assert [s["scene_id"] for s in info["scenes"]] == [1, 2] and info["citation"] == CITATION
    assert {t["scene_id"] for t in targets} == {1, 2} and all(t["inst_count"] == 1 for t in targets)
    assert held and {(t["scene_id"], t["im_id"]) for t in held} <= {(1, i) for i in holdout_a["im_ids"]} | \
        {(2, i) for i in manifest["scenes"][1]["holdout_im_ids"]}
    n_held = sum(len(s["holdout_im_ids"]) for s in manifest["scenes"])
    assert manifest["counts"] == {"scenes": 2, "objects": 3, "models": 2, "images": 11, "instances": 22,
                                  "targets": len(targets), "holdout_images": n_held}
    assert set(manifest["files"]) == set(files) - {"SHA256SUMS", "manifest.json"}
    assert manifest["versions"]["numpy"] == np.__version__ and manifest["versions"]["python"]
    assert [o["model"] for o in manifest["objects"]] == [True, True, False]
    card = (release / "README.md").read_text()
    for needle in ("CC-BY-4.0", CITATION, "27.50 dB", "bop_toolkit_lib", "brave6d serve", "scene_b",
                   f"unzip {NAME}_models.zip -d {NAME}"):
        assert needle in card, needle


def test_zips_stream_files_unchanged(release: Path, workdir: Path) -> None:
    scene = workdir / "scenes" / "scene_a"
    with zipfile.ZipFile(release / f"{NAME}_test_all.zip") as zf:
        assert zf.read("test/000001/rgb/000003.png") == (scene / "annotation/bop/test/000001/rgb/000003.png").read_bytes()
        assert zf.getinfo("test/000001/rgb/000003.png").compress_type == zipfile.ZIP_STORED
        assert read_scene_gt(scene / "annotation/bop/test/000001/scene_gt.json")  # the source the zip holds
        assert zf.read("test/000001/scene_gt.json") == (scene / "annotation/bop/test/000001/scene_gt.json").read_bytes()
    with zipfile.ZipFile(release / f"{NAME}_bundle_000001.zip") as zf:
        assert zf.read("bundles/000001/splat.ply") == (scene / "bundle" / "splat.ply").read_bytes()


def test_verify_passes_and_sha256sum_agrees(release: Path) -> None:
    report = verify_release(release)
    assert (report.scenes, report.images, report.bundles) == (2, 11, 2)
    if shutil.which("sha256sum"):
        import subprocess

        res = subprocess.run(["sha256sum", "-c", "SHA256SUMS"], cwd=release, capture_output=True, text=True)
        assert res.returncode == 0, res.stdout + res.stderr


def test_build_is_reproducible_and_refuses_a_non_empty_out(workdir: Path, release: Path, tmp_path: Path) -> None:
    with pytest.raises(ReleaseError, match="not empty.*--force"):
        build_release(workdir, release)
    again = tmp_path / "again"
    build_release(workdir, again)
    same = {n for n, d in read_sha256sums(again / "SHA256SUMS").items()
            if d == read_sha256sums(release / "SHA256SUMS")[n]}
    assert same >= {f"{NAME}_test_all.zip", f"{NAME}_models.zip", f"{NAME}_bundle_000001.zip", "README.md"}
    (again / "notes.txt").write_text("mine")
    result = build_release(workdir, again, force=True)
    assert result.moved_aside is not None and (result.moved_aside / "notes.txt").read_text() == "mine"
    assert not (again / "notes.txt").exists()
    with pytest.raises(ReleaseError, match="work directory"):
        build_release(workdir, workdir, force=True)


@pytest.mark.parametrize("victim", ["README.md", "manifest.json", "SHA256SUMS", f"{NAME}_base.zip",
                                    f"{NAME}_models.zip", f"{NAME}_test_all.zip", f"{NAME}_bundle_000002.zip"])
def test_one_altered_byte_is_caught_naming_the_file(copy: Path, victim: str) -> None:
    path = copy / victim
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(ReleaseError) as info:
        verify_release(copy)
    assert victim in str(info.value)


def test_truncated_zip_is_caught(copy: Path) -> None:
    path = copy / f"{NAME}_test_all.zip"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ReleaseError, match=f"{NAME}_test_all.zip: sha256"):
        verify_release(copy)
    _resum(copy)  # even with matching checksums the zip itself is refused
    with pytest.raises(ReleaseError, match=f"{NAME}_test_all.zip: not a readable zip"):
        verify_release(copy)


def test_missing_view_is_caught(copy: Path) -> None:
    _rewrite_zip(copy / f"{NAME}_test_all.zip", drop="test/000002/rgb/000003.png")
    _resum(copy)
    with pytest.raises(ReleaseError, match="test/000002/rgb/000003.png: missing"):
        verify_release(copy)


def test_inconsistent_obj_id_and_bad_json_are_caught(copy: Path) -> None:
    with zipfile.ZipFile(copy / f"{NAME}_test_all.zip") as zf:
        gt = json.loads(zf.read("test/000002/scene_gt.json"))
    gt["0"][1]["obj_id"] = 1  # cube_blue labelled as cube_red's id in one image: still consistent ids...
    gt["1"][0]["obj_id"] = 3  # ...but obj_id 3 (the library's mug) has no model
    _rewrite_zip(copy / f"{NAME}_test_all.zip", replace={"test/000002/scene_gt.json": json.dumps(gt).encode()})
    _resum(copy)
    with pytest.raises(ReleaseError, match="test/000002/scene_gt.json: image 1 instance 0: obj_id 3 has no model"):
        verify_release(copy)
    _rewrite_zip(copy / f"{NAME}_test_all.zip", replace={"test/000002/scene_gt.json": b"{\"0\": [{\"obj_id\": 1}]}"})
    _resum(copy)
    with pytest.raises(ReleaseError, match="test_all.zip:test/000002/scene_gt.json: image 0 instance 0: needs"):
        verify_release(copy)


def test_unlisted_and_missing_files_are_caught(copy: Path) -> None:
    (copy / "extra.txt").write_text("x")
    with pytest.raises(ReleaseError, match="extra.txt: not listed in SHA256SUMS"):
        verify_release(copy)
    (copy / "extra.txt").unlink()
    (copy / "README.md").unlink()
    with pytest.raises(ReleaseError, match="README.md: listed in SHA256SUMS but missing"):
        verify_release(copy)


def test_targets_reader_names_the_field(tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    path.write_text(json.dumps([{"scene_id": 1, "im_id": 0, "obj_id": 0, "inst_count": 1}]))
    with pytest.raises(ReleaseError, match=r"target \[0\] field 'obj_id'"):
        read_targets(path)


def test_library_order_must_match_the_scenes_obj_ids(workdir: Path, tmp_path: Path) -> None:
    other = tmp_path / "work"
    shutil.copytree(workdir, other, symlinks=True)
    _write_dataset(other, ["cube_blue", "cube_red"])
    with pytest.raises(ReleaseError, match="object 'cube_red' has obj_id 1 but is obj_id 2 in the library"):
        build_release(other, tmp_path / "out")


def test_cli_prints_one_line_and_exits_2(copy: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["release", "verify", str(copy)]) == 0
    assert "OK" in capsys.readouterr().out
    path = copy / "manifest.json"
    path.write_bytes(path.read_bytes().replace(b"\"version\"", b"\"versiom\"", 1))
    assert main(["release", "verify", str(copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "manifest.json: sha256" in err


def test_public_api_resolves_and_import_is_cheap() -> None:
    import subprocess
    import sys

    import brave6d.dataset.release as release_pkg

    assert all(hasattr(release_pkg, n) for n in release_pkg.__all__)
    code = ("import sys, brave6d.dataset.release; print(','.join(m for m in ('torch', 'open3d', 'fastapi', 'trimesh') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "", out.stdout + out.stderr


# ----------------------------------------------------------------------------- serving a release
def _episode(manager: object, scene: str | int, shift_m: float) -> str:
    """An episode on ``scene`` whose estimate is the target's true pose shifted by ``shift_m``."""
    r = manager.reset(scene=scene, seed=3, width=160, height=120)  # type: ignore[attr-defined]
    target = r.observation.target()
    T = target.cam_T_obj.copy()
    T[0, 3] += shift_m
    manager.submit(r.episode_id, [{"obj_id": target.obj_id, "R": T[:3, :3].reshape(-1).tolist(),  # type: ignore[attr-defined]
                                   "t_m": T[:3, 3].tolist(), "score": 1.0}], "agent")
    return r.episode_id


def test_serve_every_scene_of_a_release(release: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from brave6d.commands.scenes import scene_sources
    from brave6d.serve import EpisodeManager, open_scenes

    cache = tmp_path / "cache"
    catalog = open_scenes(scene_sources(release, cache), device="cpu", warm_up=False)
    assert catalog.names() == ["scene_a", "scene_b"] and [s.scene_id for s in catalog.sources] == [1, 2]
    assert {o.category for s in catalog.sources for o in s.objects} == {"toys_office"}
    assert not list(cache.rglob("splat.ply"))  # nothing unpacked before a scene is used
    manager = EpisodeManager(catalog, tmp_path / "logs", mode="training")  # the episodes submit the truth
    _episode(manager, "scene_b", 0.0)
    assert [p.parent.name for p in cache.rglob("splat.ply")] == ["000002"]  # only the scene used
    _episode(manager, 1, 0.05)
    splat = next(p for p in cache.rglob("splat.ply") if p.parent.name == "000001")
    stamp = splat.stat().st_mtime_ns
    again = open_scenes(scene_sources(release, cache), device="cpu", warm_up=False)
    again.bundle("scene_a")
    assert splat.stat().st_mtime_ns == stamp  # the unpacked bundle is reused, not unpacked again

    assert main(["evaluate", str(tmp_path / "logs"), "--out", str(tmp_path / "board"), "--mode", "training"]) == 0
    assert "2 training episodes ranked on 2 scene(s) (scene_a, scene_b)" in capsys.readouterr().out
    rows = (tmp_path / "board" / "per_scene.csv").read_text().splitlines()
    ar = {r.split(",")[1]: float(r.split(",")[4]) for r in rows[1:]}
    assert set(ar) == {"scene_a", "scene_b"} and ar["scene_b"] > ar["scene_a"]  # the 5 cm miss scores less
    assert (tmp_path / "board" / "per_category.csv").read_text().splitlines()[1].startswith("agent,toys_office,2,")


def test_serving_refuses_an_altered_bundle_zip(copy: Path, tmp_path: Path) -> None:
    from brave6d.commands.scenes import scene_sources
    from brave6d.serve import EpisodeManager, SceneUnavailable, open_scenes

    zip_path = copy / f"{NAME}_bundle_000001.zip"
    data = bytearray(zip_path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    zip_path.write_bytes(bytes(data))
    manager = EpisodeManager(open_scenes(scene_sources(copy, tmp_path / "cache"), device="cpu", warm_up=False), None)
    with pytest.raises(SceneUnavailable, match=rf"{NAME}_bundle_000001\.zip: sha256 .* does not match SHA256SUMS"):
        manager.reset(scene="scene_a", seed=0)  # the server's failure (503), not the client's
    assert manager.reset(scene="scene_b", seed=0).accepted  # the other scene still serves
    assert [p.parent.name for p in (tmp_path / "cache").rglob("splat.ply")] == ["000002"]  # nothing half-unpacked


def test_serve_the_unzipped_release(release: Path, tmp_path: Path) -> None:
    """The layout BOP users make: unzip the base zip, then the others into the folder it made."""
    from brave6d.commands.scenes import scene_sources
    from brave6d.serve import EpisodeManager, open_scenes

    with zipfile.ZipFile(release / f"{NAME}_base.zip") as zf:
        zf.extractall(tmp_path)
    for z in sorted(release.glob("*.zip")):
        if z.name != f"{NAME}_base.zip":
            with zipfile.ZipFile(z) as zf:
                zf.extractall(tmp_path / NAME)
    catalog = open_scenes(scene_sources(tmp_path / NAME), device="cpu", warm_up=False)
    assert catalog.names() == ["scene_a", "scene_b"]
    assert catalog.source("scene_b").locate() == tmp_path / NAME / "bundles" / "000002"
    assert EpisodeManager(catalog, None).reset(scene="scene_b", seed=0).accepted
    shutil.rmtree(tmp_path / NAME / "bundles" / "000001")
    with pytest.raises(ReleaseError, match=rf"bundles/000001: the bundle of scene 'scene_a' is missing"):
        scene_sources(tmp_path / NAME)
