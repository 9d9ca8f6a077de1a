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

from brave6d.errors import BraveError, DataError
from brave6d.layout import SceneDir
from serve.bundle import BundleError, export_bundle, load_bundle, sha256_file, verify_manifest
from serve.synthetic import make_synthetic_scene, synthetic_splat


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
    from training import write_ply

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
    manifest["files"]["splat.ply"] = {"sha256": sha256_file(path), "bytes": path.stat().st_size}
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def test_load_refuses_a_bundle_whose_splat_holds_no_gaussians(scene: SceneDir, tmp_path: Path) -> None:
    from plyfile import PlyData, PlyElement

    from training.ply import inria_attribute_names

    bundle = export_bundle(scene.root, tmp_path / "b").root
    path = bundle / "splat.ply"
    empty = np.empty(0, dtype=[(name, "<f4") for name in inria_attribute_names()])
    PlyData([PlyElement.describe(empty, "vertex")], text=False).write(str(path))
    _resign_splat(bundle)
    with pytest.raises(BundleError, match=r"splat\.ply: the splat holds no Gaussians"):
        load_bundle(bundle)


def test_serving_refuses_a_bundle_whose_splat_has_nan(scene: SceneDir, tmp_path: Path) -> None:
    from serve.app import create_app
    from serve.renderer import SplatRenderer

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

    from serve.splat_check import check_splat
    from training import read_ply

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
