"""Correctness of the Gaussian rasterizer (issue 5).

The compiled CPU backend is checked against the pure-torch reference (forward within
1e-4; gradients against autograd of the reference run in float64), the projection and SH
against gsplat's own pure-torch functions (``gsplat.cuda._torch_impl``, used as a third-party
reference), and the densification info against training's strategy and gsplat's DefaultStrategy.
Robustness (property-based) tests live in test_rasterizer_robustness.py.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brave6d.core.camera import PinholeCamera
from brave6d.training.rasterizer import RasterBackendError, RasterInputError, rasterize
from brave6d.training.rasterizer import kernels
from brave6d.training.rasterizer.reference import project, rasterize_reference

FWD_ATOL = 1e-4
GRAD_RTOL = 1e-3


def _rotation_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def make_scene(
    seed: int,
    n: int = 150,
    n_cams: int = 2,
    width: int = 64,
    height: int = 48,
    sh_degree: int | None = None,
    per_camera_colors: bool = False,
    spread: float = 1.0,
    opacity: tuple = (0.1, 0.9),
    scale_px: tuple = (0.7, 6.0),
):
    """Random but plausible scene: Gaussians in front of the cameras, screen radii from
    about 2 to 20 px, a few off-screen or beyond the Jacobian clamp (spread > 1)."""
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    z = 2.0 + 3.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * spread * width / f * z
    y = (torch.rand(n, generator=g) - 0.5) * spread * height / f * z
    means = torch.stack([x, y, z], dim=-1)
    sig_px = scale_px[0] * (scale_px[1] / scale_px[0]) ** torch.rand(n, 3, generator=g)
    scales = sig_px * z[:, None] / f
    quats = torch.randn(n, 4, generator=g)
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    lead = (n_cams, n) if per_camera_colors else (n,)
    if sh_degree is None:
        colors = torch.rand(lead + (3,), generator=g)
    else:
        colors = 0.4 * torch.randn(lead + (16, 3), generator=g)
    viewmats, Ks = [], []
    for c in range(n_cams):
        vm = torch.eye(4)
        vm[:3, :3] = _rotation_y(0.08 * c)
        vm[:3, 3] = torch.tensor([0.15 * c, -0.05 * c, 0.1 * c])
        viewmats.append(vm)
        cx = width / 2 + 3.0 * c
        cy = height / 2 - 2.0 * c
        Ks.append(torch.tensor([[f, 0.0, cx], [0.0, f * 1.05, cy], [0.0, 0.0, 1.0]]))
    backgrounds = torch.rand(n_cams, 3, generator=g)
    return {
        "means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
        "viewmats": torch.stack(viewmats), "Ks": torch.stack(Ks), "width": width, "height": height,
        "backgrounds": backgrounds, "sh_degree": sh_degree,
    }


def _call(fn, scene, **overrides):
    """Call ``fn`` (rasterize or the reference) on a scene, with some arguments replaced."""
    args = {**scene, **overrides}
    return fn(
        args["means"], args["quats"], args["scales"], args["opacities"], args["colors"],
        args["viewmats"], args["Ks"], args["width"], args["height"],
        sh_degree=args["sh_degree"], backgrounds=args["backgrounds"],
        antialiased=args.get("antialiased", False),
    )


FORWARD_CASES = {
    "rgb": {"seed": 0},
    "rgb-odd-size": {"seed": 1, "width": 37, "height": 29, "n": 80},
    "per-camera-colors": {"seed": 2, "per_camera_colors": True},
    "sh0": {"seed": 3, "sh_degree": 0},
    "sh1": {"seed": 4, "sh_degree": 1},
    "sh2": {"seed": 5, "sh_degree": 2},
    "sh3": {"seed": 6, "sh_degree": 3},
    "sh3-per-camera": {"seed": 7, "sh_degree": 3, "per_camera_colors": True},
    "off-screen-and-clamped": {"seed": 8, "spread": 3.0, "n": 200},
    "opaque-dense": {"seed": 9, "n": 300, "opacity": (0.8, 1.0), "scale_px": (2.0, 8.0)},
    "single-camera-large": {"seed": 10, "n": 400, "n_cams": 1, "width": 96, "height": 72},
}


@pytest.mark.parametrize("case", sorted(FORWARD_CASES))
def test_forward_matches_reference(case):
    scene = make_scene(**FORWARD_CASES[case])
    with torch.no_grad():
        rgb, depth, alpha, info = _call(rasterize, scene)
        rgb_r, depth_r, alpha_r, info_r = _call(rasterize_reference, scene)
    assert rgb.shape == rgb_r.shape == (scene["viewmats"].shape[0], scene["height"], scene["width"], 3)
    assert alpha.shape == depth.shape == rgb.shape[:-1] + (1,)
    assert (alpha > 0.5).float().mean() > 0.05, "scene too empty to test anything"
    torch.testing.assert_close(rgb, rgb_r, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(alpha, alpha_r, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(depth, depth_r, atol=FWD_ATOL, rtol=FWD_ATOL)
    assert torch.equal(info["radii"], info_r["radii"])
    vis = info["visible"]
    torch.testing.assert_close(info["means2d"][vis], info_r["means2d"][vis], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(info["conics"][vis], info_r["conics"][vis], atol=1e-6, rtol=1e-4)


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


GRAD_CASES = {
    "rgb": {"seed": 20},
    "rgb-odd-size-one-camera": {"seed": 21, "n_cams": 1, "width": 41, "height": 27, "n": 90},
    "sh1": {"seed": 22, "sh_degree": 1},
    "sh3": {"seed": 23, "sh_degree": 3},
    "sh2-per-camera": {"seed": 24, "sh_degree": 2, "per_camera_colors": True},
    # one camera: the SH backward writes each Gaussian's gradient once (no accumulation);
    # the spread leaves some Gaussians culled, whose gradient must still be zero
    "sh2-one-camera": {"seed": 27, "sh_degree": 2, "n_cams": 1, "n": 150, "spread": 2.0},
    "sh3-one-camera": {"seed": 28, "sh_degree": 3, "n_cams": 1, "n": 150},
    "clamped-jacobian": {"seed": 25, "spread": 2.5, "n": 200},
    "opaque-dense": {"seed": 26, "n": 250, "opacity": (0.7, 0.99), "scale_px": (2.0, 7.0)},
}


@pytest.mark.parametrize("case", sorted(GRAD_CASES))
def test_gradients_match_reference_autograd(case):
    """CPU kernel (float32) vs autograd through the reference in float64, on the same
    float32 inputs, with a random linear loss on RGB, depth and alpha."""
    scene = make_scene(**GRAD_CASES[case])
    names = ["means", "quats", "scales", "opacities", "colors", "backgrounds"]
    g = torch.Generator().manual_seed(99)
    c, h, w = scene["viewmats"].shape[0], scene["height"], scene["width"]
    weights = [torch.randn(c, h, w, k, generator=g, dtype=torch.float64) for k in (3, 1, 1)]

    def grads(fn, dtype):
        leaves = {k: scene[k].to(dtype).clone().requires_grad_(True) for k in names}
        cams = {k: scene[k].to(dtype) for k in ("viewmats", "Ks")}
        outs = _call(fn, scene, **leaves, **cams)
        loss = sum((o.double() * wt).sum() for o, wt in zip(outs[:3], weights))
        loss.backward()
        return {k: v.grad for k, v in leaves.items()}

    g_cpu = grads(rasterize, torch.float32)
    g_ref = grads(rasterize_reference, torch.float64)
    for k in names:
        assert g_ref[k].norm() > 0, f"{k}: reference gradient is zero, test is vacuous"
        err = _rel_err(g_cpu[k], g_ref[k])
        assert err < GRAD_RTOL, f"{k}: relative gradient error {err:.2e}"


def test_gradients_with_tiles_that_have_intersections_but_no_contributors():
    """Regression: a thin diagonal Gaussian's bounding box reaches tiles where none of its
    pixels passes the alpha threshold; those tiles must not disturb other tiles' gradients."""
    scene = make_scene(27, n=60, n_cams=1, width=64, height=48, spread=0.4)
    needle_quat = torch.tensor([[math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)]])
    scene["means"] = torch.cat([scene["means"], torch.tensor([[0.0, 0.0, 3.0]])])
    scene["quats"] = torch.cat([scene["quats"], needle_quat])
    scene["scales"] = torch.cat([scene["scales"], torch.tensor([[2.0, 0.01, 0.01]])])
    scene["opacities"] = torch.cat([scene["opacities"], torch.tensor([0.05])])
    scene["colors"] = torch.cat([scene["colors"], torch.tensor([[1.0, 0.0, 0.0]])])
    names = ["means", "quats", "scales", "opacities", "colors"]
    g = torch.Generator().manual_seed(5)
    weight = torch.randn(1, 48, 64, 3, generator=g, dtype=torch.float64)

    def grads(fn, dtype):
        leaves = {k: scene[k].to(dtype).clone().requires_grad_(True) for k in names}
        cams = {k: scene[k].to(dtype) for k in ("viewmats", "Ks")}
        rgb = _call(fn, scene, **leaves, **cams)[0]
        (rgb.double() * weight).sum().backward()
        return {k: v.grad for k, v in leaves.items()}

    g_cpu = grads(rasterize, torch.float32)
    g_ref = grads(rasterize_reference, torch.float64)
    for k in names:
        err = _rel_err(g_cpu[k], g_ref[k])
        assert err < GRAD_RTOL, f"{k}: relative gradient error {err:.2e}"


def test_means2d_gradient_matches_reference():
    """info['means2d'].grad (what densification reads) equals the reference's."""
    scene = make_scene(30)
    outs = []
    for fn, dtype in ((rasterize, torch.float32), (rasterize_reference, torch.float64)):
        s = {k: (v.to(dtype) if torch.is_tensor(v) else v) for k, v in scene.items()}
        s["means"].requires_grad_(True)
        rgb, depth, alpha, info = _call(fn, s)
        info["means2d"].retain_grad()
        (rgb.sum() + 0.1 * depth.sum() + alpha.sum()).backward()
        outs.append(info["means2d"].grad)
    assert _rel_err(outs[0], outs[1]) < GRAD_RTOL


# ---------------------------------------------------------------- 2D mip filter (antialiased)
# Gaussians from far below a pixel to several pixels: the compensation ranges over (0, 1).
AA_CASES = {
    "rgb-two-cameras": {"seed": 50, "scale_px": (0.05, 4.0)},
    "sh3-one-camera": {"seed": 51, "sh_degree": 3, "n_cams": 1, "scale_px": (0.05, 4.0)},
    "opaque-dense": {"seed": 52, "n": 300, "opacity": (0.7, 0.99), "scale_px": (0.1, 6.0)},
}


@pytest.mark.parametrize("case", sorted(AA_CASES))
def test_antialiased_forward_matches_reference(case):
    scene = {**make_scene(**AA_CASES[case]), "antialiased": True}
    with torch.no_grad():
        rgb, depth, alpha, info = _call(rasterize, scene)
        rgb_r, depth_r, alpha_r, info_r = _call(rasterize_reference, scene)
        rgb_classic = _call(rasterize, scene, antialiased=False)[0]
    assert (rgb - rgb_classic).abs().max() > 0.05, "the mip filter changed nothing: test is vacuous"
    torch.testing.assert_close(rgb, rgb_r, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(alpha, alpha_r, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(depth, depth_r, atol=FWD_ATOL, rtol=FWD_ATOL)
    assert torch.equal(info["radii"], info_r["radii"])
    vis = info["visible"]
    torch.testing.assert_close(info["opacities"][vis], info_r["opacities"][vis].float(),
                               atol=1e-5, rtol=1e-4)
    # the compensated opacity never exceeds the opacity; tiny Gaussians fade
    base = scene["opacities"][None].expand_as(info["opacities"])
    assert bool((info["opacities"] <= base + 1e-7).all())
    assert float((info["opacities"][vis] / base[vis]).min()) < 0.2


@pytest.mark.parametrize("case", sorted(AA_CASES))
def test_antialiased_gradients_match_reference_autograd(case):
    """As test_gradients_match_reference_autograd, through the opacity compensation: the CPU
    kernel in float32 against autograd of the reference in float64."""
    scene = {**make_scene(**AA_CASES[case]), "antialiased": True}
    names = ["means", "quats", "scales", "opacities", "colors", "backgrounds"]
    g = torch.Generator().manual_seed(98)
    c, h, w = scene["viewmats"].shape[0], scene["height"], scene["width"]
    weights = [torch.randn(c, h, w, k, generator=g, dtype=torch.float64) for k in (3, 1, 1)]

    def grads(fn, dtype, antialiased=True):
        leaves = {k: scene[k].to(dtype).clone().requires_grad_(True) for k in names}
        cams = {k: scene[k].to(dtype) for k in ("viewmats", "Ks")}
        outs = _call(fn, scene, **leaves, **cams, antialiased=antialiased)
        loss = sum((o.double() * wt).sum() for o, wt in zip(outs[:3], weights))
        loss.backward()
        return {k: v.grad for k, v in leaves.items()}

    g_cpu = grads(rasterize, torch.float32)
    g_ref = grads(rasterize_reference, torch.float64)
    g_classic = grads(rasterize_reference, torch.float64, antialiased=False)
    assert _rel_err(g_classic["scales"], g_ref["scales"]) > 10 * GRAD_RTOL, "vacuous: same as classic"
    for k in names:
        assert g_ref[k].norm() > 0, f"{k}: reference gradient is zero, test is vacuous"
        err = _rel_err(g_cpu[k], g_ref[k])
        assert err < GRAD_RTOL, f"{k}: relative gradient error {err:.2e}"


def test_antialiased_compensation_is_gsplats_definition():
    """One Gaussian seen head-on: cov2d = (f s / z)^2 I, so the compensation is
    (v / (v + eps2d)) with v = (f s / z)^2 (the sqrt of the determinant ratio of a 2x2)."""
    f, z = 100.0, 2.0
    vm, K = torch.eye(4)[None], torch.tensor([[[f, 0.0, 16.0], [0.0, f, 16.0], [0.0, 0.0, 1.0]]])
    for sigma_px in (0.1, 0.3, 1.0, 5.0):  # 0.01 px: opacity 3e-4 < 1/255, culled
        s = sigma_px * z / f
        _, _, _, info = rasterize(torch.tensor([[0.0, 0.0, z]]), torch.tensor([[1.0, 0, 0, 0]]),
                                  torch.full((1, 3), s), torch.tensor([1.0]), torch.ones(1, 3),
                                  vm, K, 33, 33, antialiased=True)
        v = sigma_px**2
        assert float(info["opacities"][0, 0]) == pytest.approx(v / (v + 0.3), rel=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("seed, scale_px, antialiased", [(80, (0.7, 6.0), False), (81, (0.05, 5.0), False),
                                                         (81, (0.05, 5.0), True)])
def test_cuda_backend_matches_cpu(seed, scale_px, antialiased, record_property):
    """gsplat's classic and antialiased modes against the CPU kernels (sub-pixel Gaussians too);
    the largest differences go into the JUnit XML (benchmarks/gpu_checks.py reports them)."""
    scene = {**make_scene(seed, n=300, sh_degree=3, scale_px=scale_px), "antialiased": antialiased}
    cuda = {k: (v.cuda() if torch.is_tensor(v) else v) for k, v in scene.items()}
    rgb, depth, alpha, _ = _call(rasterize, scene)
    rgb_c, depth_c, alpha_c, info_c = _call(rasterize, cuda)
    assert info_c["backend"] == "cuda"
    for name, a, b in (("rgb", rgb_c, rgb), ("alpha", alpha_c, alpha), ("depth", depth_c, depth)):
        record_property(f"max_abs_diff_{name}", float((a.cpu() - b).abs().max()))
    torch.testing.assert_close(rgb_c.cpu(), rgb, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(alpha_c.cpu(), alpha, atol=FWD_ATOL, rtol=0)
    torch.testing.assert_close(depth_c.cpu(), depth, atol=FWD_ATOL, rtol=FWD_ATOL)


CUDA_GRAD_RTOL = 5e-3  # float32 on both sides, and gsplat's backward sums with atomics in any order


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("seed, antialiased", [(82, False), (83, True)])
def test_cuda_gradients_match_cpu(seed, antialiased, record_property):
    """gsplat's backward against the CPU kernels' (whose gradients match float64 autograd of the
    reference, above), with the same random linear loss on RGB, depth and alpha; each relative
    error goes into the JUnit XML (benchmarks/gpu_checks.py reports them)."""
    scene = {**make_scene(seed, n=200, sh_degree=2), "antialiased": antialiased}
    names = ["means", "quats", "scales", "opacities", "colors", "backgrounds"]
    g = torch.Generator().manual_seed(98)
    c, h, w = scene["viewmats"].shape[0], scene["height"], scene["width"]
    weights = [torch.randn(c, h, w, k, generator=g, dtype=torch.float64) for k in (3, 1, 1)]

    def grads(device: str) -> dict[str, torch.Tensor]:
        on = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in scene.items()}
        leaves = {k: on[k].clone().requires_grad_(True) for k in names}
        outs = _call(rasterize, on, **leaves)
        loss = sum((o.double() * wt.to(device)).sum() for o, wt in zip(outs[:3], weights))
        loss.backward()
        return {k: v.grad.detach().cpu() for k, v in leaves.items()}

    g_cpu, g_cuda = grads("cpu"), grads("cuda")
    errors = {k: _rel_err(g_cuda[k], g_cpu[k]) for k in names}
    for k, err in errors.items():
        record_property(f"grad_rel_err_{k}", err)
    for k in names:
        assert g_cpu[k].norm() > 0, f"{k}: CPU gradient is zero, test is vacuous"
        assert torch.isfinite(g_cuda[k]).all(), f"{k}: non-finite CUDA gradient"
    assert max(errors.values()) < CUDA_GRAD_RTOL, errors


# ---------------------------------------------------------------- gsplat's own functions
# gsplat's private pure-torch module is a third-party reference here, not part of our API.


def _gsplat_torch_impl():
    return pytest.importorskip("gsplat.cuda._torch_impl")


@pytest.mark.parametrize("seed", [40, 41, 42])
def test_projection_matches_gsplat_torch_impl(seed):
    impl = _gsplat_torch_impl()
    scene = make_scene(seed, n=300, spread=2.5)
    covars, _ = impl._quat_scale_to_covar_preci(scene["quats"], scene["scales"], compute_preci=False)
    radii_g, means2d_g, depths_g, conics_g, _ = impl._fully_fused_projection(
        scene["means"], covars, scene["viewmats"], scene["Ks"], scene["width"], scene["height"],
        eps2d=0.3, near_plane=0.01, far_plane=1e10,
    )
    np_ = lambda t: t.detach().contiguous().numpy()
    radii, means2d, depths, conics = kernels.project_fwd(
        np_(scene["means"]), np_(scene["quats"]), np_(scene["scales"]), np_(scene["opacities"]),
        False, np_(scene["viewmats"]), np_(scene["Ks"]), scene["width"], scene["height"],
        0.3, 0.01, 1e10,
    )
    radii, means2d, depths, conics = map(torch.from_numpy, (radii, means2d, depths, conics))
    valid_g = (radii_g > 0).all(-1)
    valid = (radii > 0).all(-1)
    assert valid_g.sum() > 50
    assert torch.equal(valid, valid_g)
    # ceil() of a float32 vs float64 radius may differ by one pixel in rare cases
    assert (radii - radii_g).abs().max() <= 1
    assert (radii != radii_g).float().mean() < 0.01
    torch.testing.assert_close(means2d[valid], means2d_g[valid], atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(depths[valid], depths_g[valid], atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(conics[valid], conics_g[valid], atol=1e-6, rtol=1e-4)
    # the reference's projection agrees too (same conventions, torch ops)
    radii_r, _means2d_r, _depths_r, conics_r, _comp_r = project(
        scene["means"], scene["quats"], scene["scales"], None, scene["viewmats"], scene["Ks"],
        scene["width"], scene["height"],
    )
    assert torch.equal((radii_r > 0).all(-1), valid_g)
    torch.testing.assert_close(conics_r[valid], conics_g[valid], atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_match_gsplat_torch_impl(degree):
    impl = _gsplat_torch_impl()
    scene = make_scene(50 + degree, n=200, sh_degree=3)
    radii = torch.ones(1, 200, 2, dtype=torch.int32)
    campos = torch.tensor([[0.3, -0.2, -0.5]])
    colors = kernels.sh_fwd(
        degree, scene["means"].numpy(), campos.numpy(), scene["colors"][None].contiguous().numpy(),
        radii.numpy(),
    )
    dirs = scene["means"] - campos
    expected = impl._spherical_harmonics(degree, dirs, scene["colors"])
    torch.testing.assert_close(torch.from_numpy(colors[0]), expected, atol=1e-5, rtol=1e-5)


def test_sh_degree_zero_is_constant_colour():
    scene = make_scene(55, sh_degree=0)
    coeffs = scene["colors"].clone()
    coeffs[:, 1:] = 123.0  # higher bands must be ignored at degree 0
    rgb, _, _, _ = _call(rasterize, scene, colors=coeffs)
    rgb_dc, _, _, _ = _call(
        rasterize, scene, colors=torch.clamp_min(coeffs[:, 0] * 0.28209479177387814 + 0.5, 0.0),
        sh_degree=None,
    )
    torch.testing.assert_close(rgb, rgb_dc, atol=1e-5, rtol=0)


# ---------------------------------------------------------------- densification info


def _densify_with(strategy, absgrad: bool) -> None:
    """Three steps of rendering, backward and ``strategy`` on one camera; checks the info it reads."""
    scene = make_scene(60, n=120, n_cams=1)
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(scene["means"].clone()),
        "scales": torch.nn.Parameter(torch.log(scene["scales"])),
        "quats": torch.nn.Parameter(scene["quats"].clone()),
        "opacities": torch.nn.Parameter(torch.logit(scene["opacities"])),
        "colors": torch.nn.Parameter(scene["colors"].clone()),
    })
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    target = torch.rand(1, scene["height"], scene["width"], 3, generator=torch.Generator().manual_seed(1))
    n_start = len(params["means"])
    for step in range(3):
        rgb, _depth, _alpha, info = rasterize(
            params["means"], params["quats"], torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]), params["colors"], scene["viewmats"], scene["Ks"],
            scene["width"], scene["height"], absgrad=absgrad,
        )
        assert info["radii"].shape == (1, len(params["means"]), 2)
        assert info["radii"].dtype == torch.int32
        assert info["means2d"].shape == (1, len(params["means"]), 2)
        assert info["gaussian_ids"] is None and info["n_cameras"] == 1
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (rgb - target).abs().mean().backward()
        grad = info["means2d"].absgrad if absgrad else info["means2d"].grad
        assert grad is not None and grad.shape == info["means2d"].shape
        visible = info["visible"][0]
        assert torch.all(grad[0][~visible] == 0)
        assert (grad[0][visible].norm(dim=-1) > 0).float().mean() > 0.5
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        if step == 0:
            assert torch.equal(state["count"], visible.float())
            # the statistic is the norm of the gradient in [-1, 1] screen units, on visible Gaussians only
            screen = grad[0] * torch.tensor([scene["width"] / 2.0, scene["height"] / 2.0])
            torch.testing.assert_close(state["grad2d"], torch.where(visible, screen.norm(dim=-1), 0.0))
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad()
    assert len(params["means"]) > n_start, "densification should have grown the model"


def test_info_drives_the_training_densification():
    from brave6d.training.presets import Densification
    from brave6d.training.strategy import DensifyStrategy

    _densify_with(DensifyStrategy(Densification(refine_start=1, refine_every=2, reset_every=10_000, grow_grad2d=1e-7,
                                                grow_scale3d=1e-3)), absgrad=False)


@pytest.mark.slow
def test_info_drives_gsplat_default_strategy_with_absgrad():
    """``info`` stays compatible with gsplat's own strategy (AbsGS included), the third-party reference."""
    strategy_mod = pytest.importorskip("gsplat.strategy")
    _densify_with(strategy_mod.DefaultStrategy(refine_start_iter=1, refine_every=2, reset_every=10_000,
                                               grow_grad2d=1e-7, grow_scale3d=1e-3, absgrad=True), absgrad=True)


# ---------------------------------------------------------------- API and input checks


def test_public_api_and_reexport():
    from brave6d import training

    assert training.rasterize is rasterize
    scene = make_scene(70, n=50)
    rgb, depth, alpha, info = _call(rasterize, scene)
    c, n = scene["viewmats"].shape[0], 50
    assert rgb.dtype == depth.dtype == alpha.dtype == torch.float32
    assert info["visible"].dtype == torch.bool and info["visible"].shape == (c, n)
    assert info["depths"].shape == (c, n) and info["conics"].shape == (c, n, 3)
    assert info["width"] == scene["width"] and info["height"] == scene["height"]
    assert bool(((alpha >= 0) & (alpha <= 1)).all())


def test_float64_inputs_render_in_float32_and_get_float64_grads():
    scene = make_scene(71, n=40)
    means = scene["means"].double().requires_grad_(True)
    rgb, _, _, _ = _call(rasterize, scene, means=means)
    assert rgb.dtype == torch.float32
    rgb.sum().backward()
    assert means.grad.dtype == torch.float64 and means.grad.abs().sum() > 0


def test_rendering_is_deterministic():
    scene = make_scene(72, n=200)
    results = []
    for _ in range(2):
        means = scene["means"].clone().requires_grad_(True)
        rgb, depth, alpha, _ = _call(rasterize, scene, means=means)
        (rgb.sum() + depth.sum() + alpha.sum()).backward()
        results.append((rgb, depth, alpha, means.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_results_do_not_depend_on_the_thread_count():
    """Tiles are scheduled dynamically, but gradients are reduced in a fixed order."""
    numba = pytest.importorskip("numba")
    scene = make_scene(78, n=300)
    before = numba.get_num_threads()
    results = []
    try:
        for threads in sorted({1, before}):
            numba.set_num_threads(threads)
            leaves = {k: scene[k].clone().requires_grad_(True) for k in ("means", "opacities")}
            rgb, depth, alpha, _ = _call(rasterize, scene, **leaves)
            (rgb.sum() + depth.sum() + alpha.sum()).backward()
            results.append((rgb, depth, alpha, leaves["means"].grad, leaves["opacities"].grad))
    finally:
        numba.set_num_threads(before)
    for a, b in zip(results[0], results[-1]):
        assert torch.equal(a, b)


def test_absgrad_bounds_the_screen_space_gradient():
    scene = make_scene(79, n=150, n_cams=1)
    means = scene["means"].clone().requires_grad_(True)
    rgb, _, _, info = rasterize(means, scene["quats"], scene["scales"], scene["opacities"],
                                scene["colors"], scene["viewmats"], scene["Ks"], scene["width"],
                                scene["height"], absgrad=True)
    info["means2d"].retain_grad()
    (rgb * torch.randn_like(rgb)).sum().backward()
    grad, absgrad = info["means2d"].grad, info["means2d"].absgrad
    assert absgrad.shape == grad.shape
    assert torch.all(absgrad >= grad.abs() - 1e-5)
    assert (absgrad > grad.abs() + 1e-4).any(), "per-pixel signs should cancel somewhere"


def test_background_shows_through_and_is_differentiable():
    scene = make_scene(73, n=30)
    bg = scene["backgrounds"].clone().requires_grad_(True)
    rgb, _, alpha, _ = _call(rasterize, scene, backgrounds=bg)
    rgb.sum().backward()
    expected = (1.0 - alpha).sum(dim=(1, 2))  # d(sum rgb)/d(bg_c) = sum of transmittance
    torch.testing.assert_close(bg.grad, expected.expand(-1, 3), rtol=1e-5, atol=1e-3)


def test_nan_and_inf_are_rejected_with_the_tensor_name():
    scene = make_scene(74, n=20)
    for name, value in (("means", float("nan")), ("scales", float("inf")),
                        ("opacities", float("nan")), ("quats", float("-inf")),
                        ("colors", float("nan")), ("viewmats", float("nan")), ("Ks", float("inf"))):
        bad = scene[name].clone()
        bad.view(-1)[:2] = value
        with pytest.raises(RasterInputError, match=f"`{name}` contains 2 NaN/inf"):
            _call(rasterize, scene, **{name: bad})


@pytest.mark.parametrize(
    "override, message",
    [
        ({"quats": torch.zeros(5, 4)}, "quats"),
        ({"opacities": torch.zeros(20, 1)}, "opacities"),
        ({"colors": torch.zeros(20, 4)}, "colors"),
        ({"colors": torch.zeros(20, 3), "sh_degree": 1}, "colors"),
        ({"colors": torch.zeros(20, 3, 3), "sh_degree": 2}, "sh_degree=2 needs"),
        ({"sh_degree": 4, "colors": torch.zeros(20, 25, 3)}, "sh_degree"),
        ({"Ks": torch.zeros(1, 3, 3)}, "Ks"),
        ({"width": 0}, "width"),
        ({"backgrounds": torch.zeros(2, 4)}, "backgrounds"),
        ({"means": torch.zeros(20, 3, dtype=torch.float16)}, "half precision"),
    ],
)
def test_bad_shapes_and_arguments_are_rejected(override, message):
    scene = make_scene(75, n=20)
    with pytest.raises(RasterInputError, match=message):
        _call(rasterize, scene, **override)


def test_bad_camera_and_planes_are_rejected():
    scene = make_scene(76, n=10)
    Ks = scene["Ks"].clone()
    Ks[0, 0, 0] = 0.0
    with pytest.raises(RasterInputError, match="focal"):
        _call(rasterize, scene, Ks=Ks)
    with pytest.raises(RasterInputError, match="near_plane"):
        rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                  scene["colors"], scene["viewmats"], scene["Ks"], 64, 48, near_plane=2.0,
                  far_plane=1.0)


def test_backend_selection():
    scene = make_scene(77, n=10)
    with pytest.raises(RasterInputError, match="backend"):
        rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                  scene["colors"], scene["viewmats"], scene["Ks"], 64, 48, backend="opengl")
    _, _, _, info = rasterize(scene["means"], scene["quats"], scene["scales"],
                              scene["opacities"], scene["colors"], scene["viewmats"],
                              scene["Ks"], 64, 48, backend="auto")
    assert info["backend"] == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(RasterBackendError, match="CUDA"):
            rasterize(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                      scene["colors"], scene["viewmats"], scene["Ks"], 64, 48, backend="cuda")


# ---------------------------------------------------------------- pixel-centre convention
def _alpha_centroid(alpha: torch.Tensor) -> tuple[float, float]:
    """Intensity centroid ``(u, v)`` of an (H, W) image, pixel ``(u, v)`` at integer coordinates."""
    a = alpha.double()
    v, u = torch.meshgrid(torch.arange(a.shape[0], dtype=torch.float64),
                          torch.arange(a.shape[1], dtype=torch.float64), indexing="ij")
    return float((a * u).sum() / a.sum()), float((a * v).sum() / a.sum())


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(u=st.floats(30.0, 66.0), v=st.floats(24.0, 48.0), z=st.floats(0.3, 3.0))
def test_a_point_renders_centred_at_its_opencv_projection(u: float, v: float, z: float) -> None:
    """A tiny isotropic Gaussian at X renders centred at K @ X (OpenCV pixel centres at integer
    coordinates, the convention of the project's K and of the simulator's rays) within 0.05 px.

    Rendered through ``rasterize`` with the camera's own K, as the trainer, the holdout
    evaluation and the server call it; the old code (K handed to gsplat's +0.5 convention
    unconverted) put the centroid 0.5 px up and left.
    """
    camera = PinholeCamera(96, 72, 180.0, 170.0, 47.3, 35.6)
    X = torch.tensor([[(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z]])
    sigma = 1.5 * z / camera.fx  # 1.5 px on the image (plus eps2d)
    K = torch.from_numpy(camera.K).float()[None]
    _, _, alpha, _ = rasterize(X, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.full((1, 3), sigma),
                               torch.tensor([0.8]), torch.ones(1, 3), torch.eye(4)[None], K,
                               camera.width, camera.height, backend="cpu")
    cu, cv = _alpha_centroid(alpha[0, :, :, 0])
    assert abs(cu - u) < 0.05 and abs(cv - v) < 0.05, (cu - u, cv - v)
