"""The bundle records how its splat was trained (``render.antialiasing``) and the server renders it
so: a mip bundle matches a direct rasterize call with Mip-Splatting's two filters and differs from
classic; an older bundle (no field) loads and renders classic (issue 34)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from brave6d.core.atomic import file_sha256
from brave6d.core.errors import BraveError
from brave6d.core.layout import SceneDir
from brave6d.core.transforms import invert, look_at
from brave6d.serve import SplatRenderer, load_bundle
from brave6d.serve.bundle import RenderDefaults, export_bundle
from brave6d.serve.episodes import SceneServer
from brave6d.serve.toy_scene import make_synthetic_scene, ring_poses
from brave6d.training import apply_filter_3d, compute_filter_3d, rasterize, read_ply, write_ply


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(classic bundle, mip bundle) of the same synthetic scene; the mip splat carries a 3D filter
    from a ring of cameras farther than the test view."""
    root = tmp_path_factory.mktemp("aa")
    scene = make_synthetic_scene(root / "scene", n_gaussians=3000, n_views=6, width=96, height=72)
    classic = export_bundle(scene.root, root / "classic").root
    splat = read_ply(scene.splat_ply_path)
    cam = load_bundle(classic).camera
    viewmats = torch.from_numpy(np.stack([invert(T) for T in ring_poses(8, distance=0.6)])).float()
    splat.filter_3d = compute_filter_3d(torch.from_numpy(splat.means), viewmats,
                                        torch.from_numpy(cam.K).float(), cam.width, cam.height).numpy()
    write_ply(SceneDir(scene.root).splat_ply_path, splat)
    mip = export_bundle(scene.root, root / "mip").root
    return classic, mip


VIEW = look_at((0.46, -0.06, 0.12), (0.46, 0.0, 0.01))  # closer than the filter's cameras


def test_the_bundle_records_the_mode_and_the_server_follows_it(scenes: tuple[Path, Path]) -> None:
    classic, mip = scenes
    for root, mode in ((classic, "classic"), (mip, "mip")):
        bundle = load_bundle(root)
        assert json.loads((root / "scene.json").read_text())["render"]["antialiasing"] == mode
        assert bundle.render.antialiasing == mode
        assert SceneServer(bundle, "cpu", visibility=False).renderer.antialiasing == mode


def test_a_mip_bundle_renders_as_a_direct_rasterize_call_with_both_filters(scenes: tuple[Path, Path]) -> None:
    bundle = load_bundle(scenes[1])
    camera = bundle.camera
    out = SceneServer(bundle, "cpu", visibility=False).renderer.render(VIEW, camera)
    classic = SceneServer(load_bundle(scenes[0]), "cpu", visibility=False).renderer.render(VIEW, camera)
    splat = read_ply(bundle.splat_path)
    scales, opacities = apply_filter_3d(torch.exp(torch.from_numpy(splat.scales)),
                                        torch.sigmoid(torch.from_numpy(splat.opacities)),
                                        torch.from_numpy(splat.filter_3d))
    coeffs = torch.from_numpy(np.concatenate([splat.sh0, splat.shN], axis=1))
    rgb, _, alpha, _ = rasterize(torch.from_numpy(splat.means), torch.from_numpy(splat.quats), scales, opacities,
                                 coeffs, torch.from_numpy(invert(VIEW)).float()[None],
                                 torch.from_numpy(camera.K).float()[None], camera.width, camera.height,
                                 sh_degree=splat.sh_degree, near_plane=bundle.render.near,
                                 far_plane=bundle.render.far, antialiased=True)
    direct = (rgb[0].clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    assert np.abs(out.rgb.astype(int) - direct.astype(int)).max() <= 1
    np.testing.assert_allclose(out.alpha, alpha[0, :, :, 0].numpy(), atol=1e-4)
    assert np.abs(out.rgb.astype(int) - classic.rgb.astype(int)).max() > 10, "mip renders as classic"


def test_an_older_bundle_without_the_field_loads_and_renders_classic(scenes: tuple[Path, Path],
                                                                     tmp_path: Path) -> None:
    import shutil

    old = tmp_path / "old"
    shutil.copytree(scenes[0], old)
    scene_json = json.loads((old / "scene.json").read_text())
    del scene_json["render"]["antialiasing"]
    (old / "scene.json").write_text(json.dumps(scene_json))
    manifest = json.loads((old / "manifest.json").read_text())
    manifest["files"]["scene.json"].update(sha256=file_sha256(old / "scene.json"),
                                           bytes=(old / "scene.json").stat().st_size)
    (old / "manifest.json").write_text(json.dumps(manifest))
    bundle = load_bundle(old)  # checksums verified
    assert bundle.render.antialiasing == "classic"
    server = SceneServer(bundle, "cpu", visibility=False)
    assert server.renderer.antialiasing == "classic"
    same = SplatRenderer(scenes[0] / "splat.ply", "cpu", antialiasing="classic").render(VIEW, bundle.camera)
    np.testing.assert_array_equal(server.renderer.render(VIEW, bundle.camera).rgb, same.rgb)


def test_an_unknown_mode_is_refused_by_name() -> None:
    with pytest.raises(BraveError, match="render.antialiasing"):
        RenderDefaults.from_json({"width": 64, "height": 48, "antialiasing": "msaa"})
