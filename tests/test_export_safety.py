"""``brave6d export`` never loses data: what ``--out`` may replace, corrupt capture records and
holdout images, and broken splats (refused at export and when a bundle is loaded or served)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from brave6d.core.atomic import file_sha256
from brave6d.core.errors import BraveError, DataError
from brave6d.core.layout import SceneDir
from brave6d.serve.bundle import BundleError, export_bundle, load_bundle, verify_manifest
from brave6d.serve.toy_scene import make_synthetic_scene, synthetic_splat


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> SceneDir:
    return make_synthetic_scene(tmp_path_factory.mktemp("export_safety"), n_gaussians=3000, n_views=10)


@pytest.fixture()
def scene(template: SceneDir, tmp_path: Path) -> SceneDir:
    """A private copy of the synthetic scene (tests may break it)."""
    copy = SceneDir(tmp_path / "scenes" / "scene")
    shutil.copytree(template.root, copy.root)
    return copy


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> bytes)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def run_cli(*argv: str) -> int:
    from brave6d.cli import main

    return main(["export", *argv])


# ----------------------------------------------------------------------------- item 1: what --out may replace
@pytest.mark.parametrize("force", [False, True])
def test_out_that_is_the_scene_dir_is_refused_even_with_force(scene: SceneDir, force: bool,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(scene.root)
    assert run_cli(str(scene.root), "--out", str(scene.root), *(["--force"] if force else [])) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "is the scene directory" in err
    assert snapshot(scene.root) == before  # capture, calibration, splat, annotation untouched
    assert sorted(p.name for p in scene.root.parent.iterdir()) == ["scene"]  # nothing moved aside


def test_out_that_contains_the_scene_is_refused_even_with_force(scene: SceneDir) -> None:
    parent = scene.root.parent
    before = snapshot(parent)
    with pytest.raises(BraveError, match="contains the scene directory"):
        export_bundle(scene.root, parent, force=True)
    assert snapshot(parent) == before
    assert sorted(p.name for p in parent.parent.iterdir()) == ["scenes"]


@pytest.mark.parametrize("stage", ["capture", "splat", "annotation"])
def test_out_that_is_a_stage_folder_of_the_scene_is_refused_even_with_force(scene: SceneDir, stage: str) -> None:
    before = snapshot(scene.root)
    with pytest.raises(BraveError, match=f"is the scene's {stage}"):
        export_bundle(scene.root, scene.root / stage, force=True)
    assert snapshot(scene.root) == before
    assert sorted(p.name for p in scene.root.iterdir() if stage in p.name) == [stage]


def _make_file(out: Path) -> None:
    out.write_text("my notes\n")


def _make_folder(out: Path) -> None:
    (out / "sub").mkdir(parents=True)
    (out / "results.csv").write_text("a,b\n1,2\n")
    (out / "sub" / "image.png").write_bytes(b"\x89PNG not really")


def _make_foreign_manifest(out: Path) -> None:
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"name": "my web app", "files": ["index.html"]}))
    (out / "index.html").write_text("<html></html>")


def _make_bundle_with_extra_file(out: Path, scene: SceneDir) -> None:
    export_bundle(scene.root, out)
    (out / "notes.txt").write_text("results of my experiment\n")


@pytest.mark.parametrize("kind", ["file", "folder", "foreign manifest", "bundle with an extra file"])
def test_out_that_is_not_a_bundle_is_refused_then_moved_aside_with_force(scene: SceneDir, tmp_path: Path,
                                                                       kind: str) -> None:
    out = tmp_path / "out"
    if kind == "file":
        _make_file(out)
    elif kind == "folder":
        _make_folder(out)
    elif kind == "foreign manifest":
        _make_foreign_manifest(out)
    else:
        _make_bundle_with_extra_file(out, scene)
    before = out.read_bytes() if out.is_file() else snapshot(out)
    with pytest.raises(BraveError, match="--force") as info:
        export_bundle(scene.root, out)
    assert str(out) in str(info.value)
    assert (out.read_bytes() if out.is_file() else snapshot(out)) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "scenes"]  # no staging left behind

    result = export_bundle(scene.root, out, force=True)
    verify_manifest(out)
    assert result.moved_aside is not None and result.moved_aside.parent == tmp_path
    assert result.moved_aside.name.startswith("out.old-")
    moved = result.moved_aside
    assert (moved.read_bytes() if moved.is_file() else snapshot(moved)) == before  # all of it, unchanged
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", "scenes", moved.name])


def test_out_that_is_a_symlink_is_not_followed(scene: SceneDir, tmp_path: Path) -> None:
    real = tmp_path / "real"
    _make_folder(real)
    link = tmp_path / "out"
    link.symlink_to(real, target_is_directory=True)
    before = snapshot(real)
    with pytest.raises(BraveError, match="symbolic link"):
        export_bundle(scene.root, link)
    result = export_bundle(scene.root, link, force=True)
    assert not link.is_symlink() and link.is_dir()
    assert result.moved_aside is not None and result.moved_aside.is_symlink()
    assert snapshot(real) == before


def test_absent_empty_and_bundle_outs_are_replaced_without_force(scene: SceneDir, tmp_path: Path) -> None:
    out = tmp_path / "empty"
    out.mkdir()
    assert export_bundle(scene.root, out).moved_aside is None
    (out / "splat.ply").write_bytes(b"damaged")  # still a bundle (every file listed): replaced
    result = export_bundle(scene.root, out)
    assert result.moved_aside is None
    verify_manifest(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "scenes"]
    # the default place, <scene>/bundle, twice
    assert export_bundle(scene.root).root == scene.bundle_dir
    assert export_bundle(scene.root).moved_aside is None
    assert not [p for p in scene.root.iterdir() if p.name.startswith((".bundle", "bundle."))]


def test_relative_out_names_the_working_directory(scene: SceneDir, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "here"
    out.mkdir()
    monkeypatch.chdir(out)
    result = export_bundle(scene.root, ".")
    assert result.root == out and result.moved_aside is None
    verify_manifest(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here", "scenes"]


def test_cli_force_reports_where_the_old_folder_went(scene: SceneDir, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    _make_folder(out)
    assert run_cli(str(scene.root), "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not a bundle" in err and "--force" in err
    assert run_cli(str(scene.root), "--out", str(out), "--force") == 0
    printed = capsys.readouterr().out
    moved = [p for p in tmp_path.iterdir() if p.name.startswith("out.old-")]
    assert len(moved) == 1 and str(moved[0]) in printed
    assert (moved[0] / "results.csv").read_text() == "a,b\n1,2\n"


# ----------------------------------------------------------------------------- item 5: capture records, holdout images
def test_corrupt_frames_log_is_refused_and_keeps_the_previous_bundle(scene: SceneDir) -> None:
    export_bundle(scene.root)
    before = snapshot(scene.bundle_dir)
    lines = scene.frames_path.read_text().splitlines(keepends=True)
    lines[2] = '{"index": 2, "view_id": "d0_v002", broken\n'
    scene.frames_path.write_text("".join(lines))
    with pytest.raises(DataError, match=r"frames\.jsonl:3: not a JSON record"):
        export_bundle(scene.root)
    assert snapshot(scene.bundle_dir) == before


def test_unreadable_holdout_image_is_an_error_unless_images_are_left_out(scene: SceneDir, tmp_path: Path) -> None:
    shutil.rmtree(scene.root / "undistorted", ignore_errors=True)
    (scene.capture_dir / "rgb" / "000005.png").write_bytes(b"not a png")  # frame 5 is the holdout view
    with pytest.raises(DataError, match=r"000005\.png.*--no-holdout-images"):
        export_bundle(scene.root, tmp_path / "b")
    assert not (tmp_path / "b").exists()
    b = load_bundle(export_bundle(scene.root, tmp_path / "b", include_holdout_images=False).root)
    assert [(h.index, h.image) for h in b.holdout] == [(5, None)]


def test_scene_without_a_capture_exports_without_holdout_views(scene: SceneDir, tmp_path: Path) -> None:
    scene.frames_path.unlink()
    b = load_bundle(export_bundle(scene.root, tmp_path / "b").root)
    assert b.holdout == ()


# ----------------------------------------------------------------------------- item 8: broken splats
def _write_splat(path: Path, splat: object) -> None:
    from brave6d.training import write_ply

    write_ply(path, splat)  # type: ignore[arg-type]


def test_export_refuses_a_splat_with_nan(scene: SceneDir, tmp_path: Path) -> None:
    splat = synthetic_splat(2000, seed=1)
    splat.opacities[100:112] = np.nan
    _write_splat(scene.splat_dir / "point_cloud.ply", splat)
    with pytest.raises(DataError, match=r"point_cloud\.ply: 12 Gaussians have NaN in 'opacity'"):
        export_bundle(scene.root, tmp_path / "b")
    assert not (tmp_path / "b").exists()


def test_export_refuses_a_splat_that_draws_nothing(scene: SceneDir, tmp_path: Path) -> None:
    splat = synthetic_splat(2000, seed=1)
    splat.opacities[:] = -20.0  # every Gaussian below the rasterizer's 1/255 alpha
    _write_splat(scene.splat_dir / "point_cloud.ply", splat)
    with pytest.raises(DataError, match=r"point_cloud\.ply: none of the \d+ Gaussians is visible"):
        export_bundle(scene.root, tmp_path / "b")


def _resign_splat(bundle: Path) -> None:
    """Record the new checksum of the bundle's splat in its manifest (a bundle made by hand or an older export)."""
    path = bundle / "splat.ply"
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["files"]["splat.ply"] = {"sha256": file_sha256(path), "bytes": path.stat().st_size}
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def test_load_refuses_a_bundle_whose_splat_holds_no_gaussians(scene: SceneDir, tmp_path: Path) -> None:
    from plyfile import PlyData, PlyElement

    from brave6d.training.ply import inria_attribute_names

    bundle = export_bundle(scene.root, tmp_path / "b").root
    path = bundle / "splat.ply"
    empty = np.empty(0, dtype=[(name, "<f4") for name in inria_attribute_names()])
    PlyData([PlyElement.describe(empty, "vertex")], text=False).write(str(path))
    _resign_splat(bundle)
    with pytest.raises(BundleError, match=r"splat\.ply: the splat holds no Gaussians"):
        load_bundle(bundle)


def test_serving_refuses_a_bundle_whose_splat_has_nan(scene: SceneDir, tmp_path: Path) -> None:
    from brave6d.serve.app import create_app
    from brave6d.serve.renderer import SplatRenderer

    bundle = export_bundle(scene.root, tmp_path / "b").root
    splat = synthetic_splat(2000, seed=1)
    splat.means[:, 1] = np.nan  # every Gaussian: the renderer would have nothing left to draw
    _write_splat(bundle / "splat.ply", splat)
    _resign_splat(bundle)
    with pytest.raises(DataError, match=r"splat\.ply: \d+ Gaussians have NaN in 'y'"):
        SplatRenderer(bundle / "splat.ply", device="cpu")
    with pytest.raises(DataError, match=r"splat\.ply: \d+ Gaussians have NaN in 'y'"):
        create_app(bundle, device="cpu")


_FIELDS = {"means": 3, "sh0": 3, "shN": 9, "opacities": 1, "scales": 3, "quats": 4}


def _non_finite_properties(path: Path) -> set[str]:
    """The vertex properties of a PLY file that hold a NaN or inf (read with plyfile, independently)."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    return {name for name in v.dtype.names if not np.isfinite(v[name]).all()}


@given(field=st.sampled_from(sorted(_FIELDS)), row=st.integers(0, 49), column=st.integers(0, 8),
       value=st.sampled_from([np.nan, np.inf, -np.inf]), extra_rows=st.sets(st.integers(0, 49), max_size=5))
def test_any_non_finite_value_is_refused_naming_its_ply_property(field: str, row: int, column: int, value: float,
                                                                 extra_rows: set[int]) -> None:
    import tempfile

    from brave6d.serve.splat_check import check_splat
    from brave6d.training import read_ply

    splat = synthetic_splat(1000, sh_degree=1, seed=2)
    for name in _FIELDS:
        setattr(splat, name, getattr(splat, name)[:50].copy())
    rows = sorted({row} | extra_rows)
    getattr(splat, field).reshape(50, -1)[rows, column % _FIELDS[field]] = value
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "point_cloud.ply"
        _write_splat(path, splat)
        (name,) = _non_finite_properties(path)
        with pytest.raises(DataError) as info:
            check_splat(read_ply(path), path)
    kind = "NaN" if np.isnan(value) else "inf"
    count = len(rows)
    message = str(info.value)
    assert message.startswith(f"{path}: {count} Gaussian{'s have' if count > 1 else ' has'} {kind} in '{name}'"), \
        message
    assert "\n" not in message
