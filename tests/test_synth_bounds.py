"""``brave6d synth``'s bounds (issue #32, item 6): image size, workers, images and seed are checked
at start, naming the flag, before anything is written; a size that cannot fit in memory is refused
with the estimate."""

from __future__ import annotations

import argparse
import contextlib
import io
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_synth import _scene_yaml

import brave6d.synth.limits as limits
from brave6d.core.errors import BraveError
from brave6d.synth import SynthOptions, synthesize
from brave6d.synth.cli import configure

ROOT = Path(__file__).resolve().parent.parent


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="brave6d synth")
    configure(parser)
    return parser.parse_args(["spec.yaml", "out", *argv])


@pytest.mark.parametrize("flags", [["--width", "20000", "--height", "20000"], ["--workers", "100000"],
                                   ["--width", "0"], ["--width", "nan"], ["--height", "inf"],
                                   ["--images", "0"], ["--seed", "-1"]],
                         ids=lambda f: " ".join(f))
def test_cli_refuses_an_out_of_range_flag_naming_it_and_writes_nothing(flags: list[str], tmp_path: Path) -> None:
    spec = _scene_yaml(tmp_path, 32, 24)
    out = tmp_path / "out"
    images = [] if "--images" in flags else ["--images", "1"]
    run = subprocess.run([sys.executable, "-m", "brave6d.cli", "synth", str(spec), str(out), *images, *flags],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 2, (run.returncode, run.stderr[-2000:])
    assert f"argument {flags[0]}:" in run.stderr
    assert "Traceback" not in run.stderr
    assert not out.exists()


flag_bounds = {"--width": (limits.MIN_SIDE, limits.MAX_SIDE), "--height": (limits.MIN_SIDE, limits.MAX_SIDE),
               "--workers": (1, limits.MAX_WORKERS), "--images": (1, limits.MAX_IMAGES),
               "--seed": (0, limits.MAX_SEED)}


@settings(max_examples=60)
@given(st.sampled_from(sorted(flag_bounds)), st.one_of(st.integers(-2 ** 70, 2 ** 70),
                                                       st.sampled_from(["nan", "inf", "-inf", "1e9", "4.5", "", "x"])))
def test_parse_time_bounds_accept_exactly_the_range(flag: str, value: int | str) -> None:
    low, high = flag_bounds[flag]
    argv = ["--images", "1", flag, str(value)] if flag != "--images" else [flag, str(value)]
    if isinstance(value, int) and low <= value <= high:
        assert getattr(_parse(argv), flag.lstrip("-")) == value
    else:
        err = io.StringIO()
        with pytest.raises(SystemExit) as exc, contextlib.redirect_stderr(err):
            _parse(argv)
        assert exc.value.code == 2 and f"argument {flag}:" in err.getvalue()


@settings(max_examples=60)
@given(st.sampled_from(["width", "height", "workers", "images", "seed"]), st.integers(-2 ** 70, 2 ** 70))
def test_api_options_use_the_same_bounds_as_the_flags(field: str, value: int) -> None:
    low, high = flag_bounds[f"--{field}"]
    kwargs: dict[str, object] = {"images": 1, field: value}
    if low <= value <= high:
        assert getattr(SynthOptions(**kwargs), field) == value  # type: ignore[arg-type]
    else:
        with pytest.raises(BraveError, match=f"--{field} must be"):
            SynthOptions(**kwargs)  # type: ignore[arg-type]


def test_api_options_refuse_a_non_integer() -> None:
    for bad in (640.5, "640", True, float("nan")):
        with pytest.raises(BraveError, match="--width must be"):
            SynthOptions(images=1, width=bad)  # type: ignore[arg-type]


def test_memory_estimate_grows_with_pixels_and_workers() -> None:
    one = limits.render_memory_bytes(640, 480)
    assert limits.render_memory_bytes(1280, 960) > one > limits.render_memory_bytes(320, 240) > 0
    # the measured cost (~400 B/pixel on top of a worker's ~380 MiB) is inside the estimate
    assert limits.render_memory_bytes(1920, 1080) >= 380 * 2 ** 20 + 400 * 1920 * 1080


def test_a_size_that_does_not_fit_in_memory_is_refused_with_the_estimate(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    spec = _scene_yaml(tmp_path, 32, 24)
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 2 * 2 ** 30)
    monkeypatch.setattr(limits, "usable_cpus", lambda: 8)
    out = tmp_path / "out"
    with pytest.raises(BraveError, match=r"--width.*GiB") as exc:
        synthesize(spec, out, SynthOptions(images=4, workers=1, width=4096, height=4096))
    assert "2.0 GiB available" in str(exc.value)
    with pytest.raises(BraveError, match=r"--workers 4 .*GiB"):
        synthesize(spec, out, SynthOptions(images=4, workers=4, width=1024, height=768))
    assert not out.exists()


def test_far_more_workers_than_cpus_are_refused_naming_the_flag(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    spec = _scene_yaml(tmp_path, 32, 24)
    monkeypatch.setattr(limits, "usable_cpus", lambda: 3)
    with pytest.raises(BraveError, match=r"--workers 13 .*3 CPU"):
        synthesize(spec, tmp_path / "out", SynthOptions(images=13, workers=13))
    assert not (tmp_path / "out").exists()
    with caplog.at_level("WARNING", logger="brave6d.synth.limits"):
        limits.check_machine(32, 24, 12, 12, "--width/--height")  # 4 per core: allowed, with a warning
    assert "--workers 12 on 3 CPU core(s)" in caplog.text


def test_a_spec_camera_larger_than_the_cap_is_refused_naming_the_flags(tmp_path: Path) -> None:
    spec = _scene_yaml(tmp_path, 6000, 4000)
    with pytest.raises(BraveError, match=r"6000x4000.*--width") as exc:
        synthesize(spec, tmp_path / "out", SynthOptions(images=1))
    assert str(spec) in str(exc.value)
    assert not (tmp_path / "out").exists()


def test_running_out_of_memory_while_rendering_is_one_clear_error(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import brave6d.synth.run

    def no_memory(*_args: object) -> None:
        raise MemoryError

    spec = _scene_yaml(tmp_path, 32, 24)
    monkeypatch.setattr(brave6d.synth.run, "render_image", no_memory)
    with pytest.raises(BraveError, match=r"32x24 images with --workers 1 ran out of memory.*GiB per worker"):
        synthesize(spec, tmp_path / "out", SynthOptions(images=1))
