"""benchmarks/gpu_checks.py, the prepared run for a session lent a GPU: its wiring end to end on the
CPU (the CUDA parts reported as not run), how it reads the GPU-only tests' results, and its report."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("gpu_checks_benchmark", ROOT / "benchmarks" / "gpu_checks.py")
gpu_checks = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gpu_checks)


@pytest.mark.slow
def test_the_run_trains_and_renders_on_the_cpu_and_says_the_cuda_parts_did_not_run(tmp_path: Path) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present: the CPU-only report does not apply")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_checks.py"), "run", "--out", str(out),
                           "--skip-tests", "--steps", "6", "--cpu-steps", "6", "--width", "160",
                           "--views-per-ring", "3", "--gaussians", "2000", "--repeats", "2",
                           "--learned-bundle", str(tmp_path / "not-prepared")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads((out / "gpu_checks.json").read_text())
    assert report["cuda"] is None and "gsplat_build" not in report and "tests" not in report
    assert set(report["training"]) == {"cpu"} and set(report["render"]) == {"cpu"}
    train = report["training"]["cpu"]
    assert train["ok"] and train["steps"] == 6 and train["image_size"] == [80, 50]
    assert math.isfinite(train["holdout_psnr"]) and train["s_per_step"] > 0
    render = report["render"]["cpu"]
    assert render["ok"] and render["gaussians"] == 2000 and render["ms_median"] > 0
    assert render["ms_expected_depth"] > 0 and render["size"] == [640, 400]
    assert render["median_over_expected"] == pytest.approx(render["ms_median"] / render["ms_expected_depth"])
    vector = report["vector_env"]["cpu"]  # issue #46 item 4's wiring: 8 agents, batched vs loop
    assert vector["ok"] and [r["agents"] for r in vector["rows"]] == [8] and vector["size"] == [320, 240]
    assert vector["rows"][0]["env_batched"] > 0 and vector["rows"][0]["render_loop"] > 0
    assert "| vector env, 320x240" in (out / "gpu_checks.md").read_text()
    page = (out / "gpu_checks.md").read_text()
    assert "no CUDA GPU: CUDA parts not run" in page and "| cpu | 6 |" in page
    assert report["same_step"] is None  # nothing to compare without a GPU
    # the learned step without its prepared split: said, not a failure of the other checks
    assert not report["learned"]["cpu"]["ok"] and "skipped (no prepared split" in page
    # issue #68's targets open the page, none measured without a GPU; each step's seconds close it
    assert page.index("| issue #68's target |") < page.index("| training (toy plane")
    assert len(report["targets"]) == 6 and all(t["met"] is None and "no CUDA GPU" in t["text"]
                                               for t in report["targets"])
    assert {"3 training cpu", "4 render cpu", "5 vector env cpu", "6 learned cpu"} <= set(report["step_seconds"])
    assert "Seconds per step: 3 training cpu" in page and "of the call's budget" in page


def test_the_gpu_only_tests_are_counted_and_their_measurements_read(tmp_path: Path) -> None:
    """run_tests reads pytest's JUnit XML: which GPU-only tests ran, failed or skipped, and what
    they recorded; a test of another name does not count as a GPU test."""
    (tmp_path / "test_fake_gpu.py").write_text(
        "import pytest\n"
        "def test_cuda_backend_matches_cpu(record_property):\n"
        "    record_property('max_abs_diff_rgb', 2.5e-6)\n"
        "def test_cuda_gradients_match_cpu(record_property):\n"
        "    record_property('grad_rel_err_means', 0.02)\n"
        "    assert False, 'too far'\n"
        "@pytest.mark.skip(reason='needs a CUDA GPU')\n"
        "def test_cuda_gradients_match_cpu_again():\n"
        "    pass\n"
        "def test_cuda_without_gpu_is_a_clear_error():\n"
        "    pass\n")
    counts = gpu_checks.run_tests(tmp_path, (str(tmp_path / "test_fake_gpu.py"),))
    assert counts["exit"] == 1 and counts["tests"] == 4 and counts["failures"] == 1 and counts["skipped"] == 1
    assert counts["cuda_tests_run"] == 2 and counts["cuda_tests_skipped"] == 1
    assert counts["cuda_tests_failed"] == ["test_cuda_gradients_match_cpu"]
    assert counts["measured"] == {"test_cuda_backend_matches_cpu": {"max_abs_diff_rgb": 2.5e-6},
                                  "test_cuda_gradients_match_cpu": {"grad_rel_err_means": 0.02}}
    page = gpu_checks.markdown({"cuda": {"name": "NVIDIA H100"}, "torch": "2.11", "python": "3.12", "commit": "abc",
                                "tests": counts, "training": {}, "render": {}})
    assert "CUDA tests FAILED: test_cuda_gradients_match_cpu" in page and "grad_rel_err_means 2.00e-02" in page


def test_cpu_and_gpu_training_are_compared_at_the_same_step() -> None:
    """The CPU's shorter run against the GPU's at the last step both scored, not at their ends."""
    gpu = {"ok": True, "points": [{"step": 0, "train_time_s": 0.0, "holdout_psnr": 10.0},
                                  {"step": 300, "train_time_s": 6.0, "holdout_psnr": 20.0},
                                  {"step": 600, "train_time_s": 12.0, "holdout_psnr": 24.0}]}
    cpu = {"ok": True, "points": [{"step": 0, "train_time_s": 0.0, "holdout_psnr": 10.0},
                                  {"step": 300, "train_time_s": 90.0, "holdout_psnr": 20.1}]}
    same = gpu_checks.same_step_ratio({"cuda": gpu, "cpu": cpu})
    assert same == {"step": 300, "cpu_s": 90.0, "cuda_s": 6.0, "speedup": 15.0, "psnr_cpu": 20.1, "psnr_cuda": 20.0}
    assert gpu_checks.same_step_ratio({"cuda": {**gpu, "ok": False}, "cpu": cpu}) is None
    assert gpu_checks.same_step_ratio({"cuda": gpu, "cpu": {**cpu, "points": cpu["points"][:1]}}) is None


def test_the_learned_step_trains_the_carried_split_without_open3d_and_is_scored_here(tmp_path: Path) -> None:
    """Step 5: ``prepare`` renders and reads the split here (Open3D), the GPU machine (no Open3D)
    trains it from the carried arrays and times each network, and ``score-learned`` scores the model
    it returned; a machine without the prepared split reports the step as skipped."""
    bundle = tmp_path / "learned"
    made = gpu_checks.prepare_learned(bundle, images=12)
    assert made["images"] == 12 and made["instances"] > 0 and made["mb"] < 3
    data, models, source = gpu_checks.load_learned_bundle(bundle)
    assert source["width"] == 320 and len(data.split(True)) == 1 and sorted(data.objects) == [1, 2, 3, 4]
    assert all(im.rgb.shape == (200, 320, 3) and im.rgb_crop is im.rgb for im in data.images)
    assert all(inst.coords.shape[:2] == inst.mask.shape and inst.mask.any() for inst in data.instances)
    gpu_checks.save_learned_bundle(data, models, tmp_path / "again", source)  # what it reads, it writes back
    again, _, _ = gpu_checks.load_learned_bundle(tmp_path / "again")
    assert again.digest == data.digest and len(again.instances) == len(data.instances)
    assert all((a.coords == b.coords).all() and (a.mask == b.mask).all() and a.box == b.box and a.region == b.region
               for a, b in zip(again.instances, data.instances))
    assert all((a.rgb == b.rgb).all() and (a.K == b.K).all() and a.instances == b.instances and a.heldout == b.heldout
               for a, b in zip(again.images, data.images))

    device_out = tmp_path / "device"
    code = ("import json, sys; sys.modules['open3d'] = None  # as on the GPU machine\n"
            f"sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); import gpu_checks as g; from pathlib import Path\n"
            f"r = g.train_learned_check(Path({str(bundle)!r}), Path({str(device_out)!r}), 'cpu', 20)\n"
            f"b = g.train_learned_check(Path({str(bundle)!r}), Path({str(device_out)!r}), 'cpu', 20, 'bf16')\n"
            f"g.write_report(Path({str(device_out)!r}), {{'cuda': None, 'torch': '', 'python': '', 'commit': '',"
            " 'learned': {'cpu': r, 'cpu bf16': b}})\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = json.loads((device_out / "gpu_checks.json").read_text())["learned"]["cpu"]
    assert run["ok"] and run["steps"] == 20 and "heldout" not in run and "open3d" in run["heldout_skipped"]
    assert all(run["seconds"][k] > 0 and run["steps_per_s"][k] > 0 for k in ("detector", "pose"))
    assert all(math.isfinite(v) for v in run["losses"].values()) and (device_out / run["model"]).is_file()
    page = (device_out / "gpu_checks.md").read_text()
    assert "| cpu | 20 |" in page and "not scored" in page and "held-out scoring skipped: open3d" in page
    bf16 = json.loads((device_out / "gpu_checks.json").read_text())["learned"]["cpu bf16"]
    assert bf16["ok"] and bf16["precision"] == "bf16" and bf16["model"] != run["model"], bf16
    assert all(math.isfinite(v) for v in bf16["losses"].values()) and "| cpu bf16 | 20 |" in page

    report = gpu_checks.score_returned(device_out, tmp_path / "scored", bundle)
    held = report["learned"]["cpu"]["heldout"]
    assert held["images"] == 1 and set(held["detection_recall_iou50"]) == {"1", "2", "3", "4"}
    assert 0 <= held["pose_ar"]["true_box_rgb"] <= 1 and "heldout_skipped" not in report["learned"]["cpu"]
    assert "not scored" not in (tmp_path / "scored" / "gpu_checks.md").read_text()

    missing = gpu_checks.train_learned_check(tmp_path / "nothing", tmp_path / "o", "cpu", 20)
    assert not missing["ok"] and "prepare" in missing["skipped"]
    assert "learned estimator on cpu: skipped (no prepared split" in "\n".join(
        gpu_checks.learned_markdown({"cpu": missing}, None))
    assert gpu_checks.learned_ratio({"cuda": {**run, "seconds": {"detector": 2.0, "pose": 1.0}}, "cpu": run}) == {
        "detector": run["seconds"]["detector"] / 2.0, "pose": run["seconds"]["pose"] / 1.0}


def test_a_whole_split_travels_as_jpeg_and_trains_a_long_run(tmp_path: Path) -> None:
    """Step 7's split (``prepare --learned-full``): a train_pbr read with the fast preset's widths,
    its images as JPEG (close to the PNGs, far smaller), coordinates and boxes exact, no depth;
    trained from the carried arrays (here on the CPU, a few steps) into the model step 7 returns."""
    from learned_helpers import DEMO_SPEC, write_models

    from brave6d.evaluation.learned import get_learn_preset, load_training_data
    from brave6d.synth import SynthOptions, synthesize

    synthesize(DEMO_SPEC, tmp_path / "synth", SynthOptions(images=6, seed=0, width=640, height=400))
    models = write_models(DEMO_SPEC, tmp_path / "models")
    made = gpu_checks.prepare_learned_full(tmp_path / "synth", models, tmp_path / "full")
    assert made["images"] == 6 and made["instances"] > 0
    data, _, source = gpu_checks.load_learned_bundle(tmp_path / "full")
    fast = get_learn_preset("fast")
    read = load_training_data(tmp_path / "synth", models, fast.work_width, fast.heldout_every, show_progress=False,
                              crop_width=fast.crop_source_width)
    assert source["jpeg_quality"] == gpu_checks.LEARNED_FULL_JPEG and data.digest == read.digest
    assert not (tmp_path / "full" / "depth").exists()
    for a, b in zip(data.images, read.images):
        assert a.rgb.shape == b.rgb.shape == (200, 320, 3) and a.rgb_crop.shape == b.rgb_crop.shape == (400, 640, 3)
        assert np.abs(a.rgb_crop.astype(int) - b.rgb_crop.astype(int)).mean() < 6.0  # JPEG 90 4:4:4 on sensor noise
        assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() < 4.0  # made again from it, area-filtered
        assert not np.array_equal(a.rgb_crop, b.rgb_crop)  # but a loss: JPEG, not the PNG's pixels
        np.testing.assert_array_equal(a.K, b.K)
    assert all(np.array_equal(a.coords, b.coords) and a.box == b.box and a.box_crop == b.box_crop
               for a, b in zip(data.instances, read.instances))
    png_bytes = sum(f.stat().st_size for f in (tmp_path / "synth").rglob("rgb/*.png"))
    assert made["mb"] * 1e6 < 0.6 * png_bytes, (made["mb"], png_bytes)
    run = gpu_checks.train_learned_full(tmp_path / "full", tmp_path / "out", (4, 6), device="cpu")
    assert run["ok"] and run["steps"] == {"detector": 4, "pose": 6} and (tmp_path / "out" / run["model"]).is_file()
    assert all(math.isfinite(v) for v in run["losses"].values())
    assert "on the whole split (6 images" in "\n".join(gpu_checks.learned_full_markdown(run))
    # back here: scored on every image of another split (here the training one, for the wiring)
    (tmp_path / "out" / "gpu_checks.json").write_text(json.dumps({"cuda": None, "torch": "", "python": "",
                                                                   "commit": "", "learned_full": run}))
    scored = gpu_checks.score_returned(tmp_path / "out", tmp_path / "scored", tmp_path / "no-small-split",
                                       tmp_path / "synth", models)["learned_full"]["heldout"]
    assert scored["images"] == 6 and 0.0 <= scored["pose_ar"]["true_box_rgb"] <= 1.0
    assert "never trained on: AR given true boxes" in (tmp_path / "scored" / "gpu_checks.md").read_text()
    missing = gpu_checks.train_learned_full(tmp_path / "nothing", tmp_path / "out", (4, 6), device="cpu")
    assert not missing["ok"] and "prepare --learned-full" in missing["skipped"]


@pytest.mark.parametrize("text", ["4800", "a:b", "0:10", "10:-1", "1:2:3"])
def test_the_long_runs_steps_are_two_positive_numbers(text: str) -> None:
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="DETECTOR:POSE|positive"):
        gpu_checks._steps_pair(text)
    assert gpu_checks._steps_pair("4800:16000") == (4800, 16000)


def gpu_report(**parts: object) -> dict:
    """A GPU run's report as run() builds it, with the figures of the targets' rows."""
    report = {"cuda": {"name": "NVIDIA H100"}, "torch": "2.11", "python": "3.12", "commit": "abc", "render": {},
              "tests": {"exit": 0, "seconds": 30.0,
                        "measured": {gpu_checks.LEAN_STEP_TEST: {"host_syncs_per_step": 3.5}}},
              "training": {"cuda": {"ok": True, "steps": 2000, "holdout_psnr": 27.9}},
              "reference_loop": {"ok": True, "window": [320, 2000], "project_over_reference": 5.0 / 4.1,
                                 "project": {"ms_per_step": 5.0, "syncs_per_step": 4.8, "gaussians": 9,
                                             "holdout_psnr": 27.9},
                                 "reference": {"ms_per_step": 4.1, "syncs_per_step": None, "gaussians": 9,
                                               "holdout_psnr": 27.0}},
              "vector_env": {"cuda": {"ok": True, "size": [320, 240], "depth_mode": "median", "rows": [
                  {"agents": 8, "env_batched": 400.0, "env_loop": 150.0, "render_batched": 800.0, "render_loop": 200.0},
                  {"agents": 64, "env_batched": 1100.0, "env_loop": 200.0, "render_batched": 900.0,
                   "render_loop": 210.0}]}}}
    return {**report, **parts}


def test_the_report_puts_each_of_issue_68s_figures_beside_its_target() -> None:
    rows = {r["target"]: r for r in gpu_checks.issue_targets(gpu_report())}
    assert [(r["measured"], r["met"]) for r in rows.values()] == [
        (5.0, False), (pytest.approx(1.2195, abs=1e-4), True), (4.8, False), (3.5, True), (1100.0, True), (27.9, True)]
    assert rows["fast step on the toy plane"]["text"] == "5.00 ms (steps 320-2000)"
    assert rows["64 agents at 320x240, agent steps/s"]["text"] == "1100 batched (200 as a loop)"
    assert rows["holdout PSNR, toy plane, 2000 steps"]["goal"] == ">= 27.87 dB (within 0.1 of 27.97)"
    page = gpu_checks.markdown({**gpu_report(), "training": {}, "step_seconds": {"1 gsplat build": 61.0}})
    assert "| fast step on the toy plane | 5.00 ms (steps 320-2000) | <= 4.5 ms | **no** |" in page
    assert "| host syncs per step, lean-step test | 3.5 | <= 4 | yes |" in page
    assert "Seconds per step: 1 gsplat build 61; total 61 of the call's budget" in page
    # what a run did not measure is said, with why, and counts as neither met nor missed
    short = {r["target"]: r for r in gpu_checks.issue_targets(gpu_report(
        reference_loop={"ok": False, "exit": 1}, vector_env={}, tests=None,
        training={"cuda": {"ok": True, "steps": 500, "holdout_psnr": 25.0}}))}
    assert all(r["met"] is None for r in short.values())
    assert short["fast step on the toy plane"]["text"] == "not measured: the step failed (exit 1)"
    assert "step not run (--skip-vector-env" in short["64 agents at 320x240, agent steps/s"]["text"]
    assert "step not run (--skip-tests" in short["host syncs per step, lean-step test"]["text"]
    assert short["holdout PSNR, toy plane, 2000 steps"]["text"].startswith("not comparable: 500 steps")


def test_step_7_runs_only_in_a_call_of_its_own(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        gpu_checks.main(["run", "--out", str(tmp_path), "--learned-full-steps", "4800:16000"])
    assert exc.value.code == 2 and "runs in a device call of its own: add --learned-full-only" in capsys.readouterr().err
    assert not (tmp_path / "gpu_checks.json").exists()
