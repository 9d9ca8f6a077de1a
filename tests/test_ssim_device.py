"""The SSIM fused on the device (issue #46 item 2): Triton kernels for the value and its gradient,
proven on the CPU through Triton's interpreter against the reference SSIM (autograd through five
convolutions), and compiled ahead of time for sm_90 here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from brave6d.training.losses import photometric_loss, ssim
from brave6d.training.ssim_device import can_fuse_on_device, compile_ssim_kernels, device_ssim

HERE = Path(__file__).resolve().parent
pytest.importorskip("triton")


@pytest.mark.slow
def test_kernels_through_the_interpreter_equal_the_reference_ssim(tmp_path: Path) -> None:
    out = tmp_path / "ssim.json"
    proc = subprocess.run([sys.executable, str(HERE / "ssim_interpreter_cases.py"), str(out)],
                          env={**os.environ, "TRITON_INTERPRET": "1"}, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    cases = json.loads(out.read_text())
    drawn = cases.pop("hypothesis")
    assert len(cases) == 9 and len(drawn) >= 4
    for name, r in [*cases.items(), *((f"drawn {d['seed']} {d['shape']}", d) for d in drawn)]:
        assert r["finite"], name
        assert abs(r["device"] - r["reference"]) <= 1e-6, (name, r)
        assert r["grad_max_diff"] <= 1e-5 * r["grad_max"] + 1e-6, (name, r)
    assert cases["both-constant"]["device"] == pytest.approx(1.0, abs=1e-6)
    assert cases["black-vs-white"]["device"] < 1e-4


def test_kernels_compile_for_h100_h200_without_a_gpu() -> None:
    asm = compile_ssim_kernels(arch=90)
    for name in ("fwd", "bwd"):
        assert f".entry ssim_{name}_kernel" in asm[name]["ptx"] and ".target sm_90" in asm[name]["ptx"]
        assert len(asm[name]["cubin"]) > 1000


def test_which_pairs_fuse_on_the_device() -> None:
    a, b = torch.rand(8, 8, 3), torch.rand(8, 8, 3)
    interpreted = os.environ.get("TRITON_INTERPRET") == "1"
    assert can_fuse_on_device(a, b) is interpreted  # CPU tensors: only under the interpreter
    assert not can_fuse_on_device(a.double(), b.double())
    assert not can_fuse_on_device(a, b.requires_grad_(True))
    assert not can_fuse_on_device(a[None], b[None].detach())
    if not interpreted:
        with pytest.raises(ValueError, match="device_ssim: needs one"):
            device_ssim(a, b.detach())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_photometric_loss_takes_the_fused_ssim(record_property) -> None:
    g = torch.Generator().manual_seed(0)
    render = torch.rand(200, 320, 3, generator=g).cuda().requires_grad_(True)
    target = torch.rand(200, 320, 3, generator=g).cuda()
    assert can_fuse_on_device(render, target)
    value = device_ssim(render, target)
    value.backward()
    grad = render.grad.clone()
    render.grad = None
    want = ssim(render, target)
    want.backward()
    assert abs(float(value) - float(want)) < 1e-6
    diff = float((grad - render.grad).abs().max())
    record_property("ssim_grad_max_diff", diff)
    assert diff <= 1e-5 * float(render.grad.abs().max()) + 1e-7
    _, _, s = photometric_loss(render, target)
    assert s.grad_fn is not None and "DeviceSSIM" in type(s.grad_fn).__name__
