"""The time-to-quality benchmark's arithmetic: when a PSNR level is reached, and configurations."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SPEC = importlib.util.spec_from_file_location(
    "time_to_quality", Path(__file__).resolve().parent.parent / "benchmarks" / "time_to_quality.py")
ttq = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(ttq)  # type: ignore[union-attr]

POINTS = [{"psnr": 20.0, "time_s": 0.0, "cpu_s": 0.0}, {"psnr": 26.0, "time_s": 10.0, "cpu_s": 18.0},
          {"psnr": 28.0, "time_s": 20.0, "cpu_s": 38.0}, {"psnr": 27.5, "time_s": 30.0, "cpu_s": 58.0}]


def test_time_to_a_level_interpolates_between_evaluations() -> None:
    assert ttq.time_to(POINTS, 27.0, "time_s") == pytest.approx(15.0)
    assert ttq.time_to(POINTS, 27.0, "cpu_s") == pytest.approx(28.0)
    assert ttq.time_to(POINTS, 28.0, "time_s") == pytest.approx(20.0)  # reached exactly at an evaluation
    assert ttq.time_to(POINTS, 19.0, "time_s") == 0.0  # already there at the start
    assert ttq.time_to(POINTS, 30.0, "time_s") is None  # never reached (a later dip does not count)


def test_configurations_parse_to_typed_preset_overrides() -> None:
    assert ttq.parse_config("new=fast,steps=1000,downscale=4,grow_grad2d=2e-4,max_gaussians=none") == (
        "new", "fast", {"steps": 1000, "downscale": 4, "grow_grad2d": 2e-4, "max_gaussians": None})
    with pytest.raises(SystemExit, match="'stepz' is not a Preset field"):
        ttq.parse_config("x=fast,stepz=3")
    with pytest.raises(SystemExit, match="NAME=PRESET"):
        ttq.parse_config("fast")
