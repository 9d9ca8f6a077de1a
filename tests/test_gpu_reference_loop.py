"""``benchmarks/gpu_reference_loop.py`` (issue #46 item 3) wired on the CPU: both loops train the same
start on a tiny toy scene and report their windows (its figures come from a GPU, via gpu_checks)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.training.toy_scenes import plane_views, write_scene

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_reference_loop_runs_both_loops_on_the_cpu(tmp_path: Path) -> None:
    cam = PinholeCamera(48, 30, 38.4, 38.4, 23.5, 14.5)
    write_scene(tmp_path / "scene", cam, plane_views(cam, [0.25, 0.35], 3))
    out = tmp_path / "loop.json"
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_reference_loop.py"), str(tmp_path / "scene"),
                           "--steps", "14", "--from-step", "4", "--sync-steps", "2", "--device", "cpu",
                           "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["window"] == [6, 14] and report["device"] == "cpu"
    for name in ("project", "reference"):
        r = report[name]
        assert r["timed_steps"] == 8 and r["ms_per_step"] > 0 and r["gaussians"] > 0, name
        assert r["syncs_per_step"] is None  # counted on a GPU only
        assert math.isfinite(r["holdout_psnr"]) and r["holdout_psnr"] > 5, name
    assert report["project"]["lean"] is False
    assert report["project_over_reference"] == pytest.approx(
        report["project"]["ms_per_step"] / report["reference"]["ms_per_step"])
