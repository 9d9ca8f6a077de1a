"""Miniature end-to-end run of `brave6d demo --quick`: every stage runs and its figures make sense.

Each stage prints ``[i/n] <stage> done in <s> s  key=value, ...`` on stderr; the figures are
checked against what the miniature run must reach (bounds with margin) and against each
other where two stages report the same thing.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from brave6d.core.atomic import read_json
from brave6d.pipeline import QUICK_CAPTURE, STAGES
from brave6d.pipeline.demo import DEMO_SPEC

STAGE_LINE = re.compile(r"^\[(\d+)/(\d+)\] (\S+)\s+done in ([0-9.]+) s  (.*)$")


def stage_figures(stderr: str) -> dict[str, dict[str, str]]:
    """``{stage: {figure: text}}`` from the demo's progress lines."""
    stages: dict[str, dict[str, str]] = {}
    for line in stderr.splitlines():
        match = STAGE_LINE.match(line)
        if match:
            pairs = (item.split("=", 1) for item in match.group(5).split(", "))
            stages[match.group(3)] = {key: value for key, value in pairs}
    return stages


def test_stage_lines_parse() -> None:
    stderr = ("[1/2] scene        validate ...\n"
              "[1/2] scene        done in 0.1 s  objects=4, effects=none\n"
              "noise\n[2/2] train        done in 12.5 s  holdout PSNR=13.52, steps=150\n")
    assert stage_figures(stderr) == {"scene": {"objects": "4", "effects": "none"},
                                     "train": {"holdout PSNR": "13.52", "steps": "150"}}


@pytest.mark.slow
def test_quick_demo_runs_every_stage(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "brave6d.cli", "demo", "--quick", "--workdir", str(tmp_path)],
                         capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-4000:]
    fig = stage_figures(out.stderr)
    assert list(fig) == [stage.name for stage in STAGES], out.stderr[-4000:]
    for stage in STAGES:  # the summary table lists every stage as done
        assert re.search(rf"^\|\s*{stage.name}\s*\|\s*ok\s*\|", out.stdout, re.MULTILINE), out.stdout

    n_objects = len(yaml.safe_load(DEMO_SPEC.read_text())["objects"])
    assert int(fig["scene"]["objects"]) == n_objects

    calib = fig["calibrate"]
    assert float(calib["intrinsics RMS px"]) < 0.3
    assert float(calib["hand-eye RMS px"]) < 0.5
    assert float(calib["error vs truth mm"]) < 1.0  # the full demo reaches ~0.16 mm, the miniature ~0.3
    assert float(calib["error vs truth deg"]) < 0.1

    capture = fig["capture"]
    frames = int(capture["frames"])
    requested = len(QUICK_CAPTURE["distances_m"]) * QUICK_CAPTURE["views_per_distance"]
    assert 10 <= frames <= requested
    assert sum(int(n) for n in capture["per ring"].split("/")) == frames

    annotation = fig["annotate"]
    assert int(annotation["objects"]) == n_objects
    assert int(annotation["views"]) == frames
    assert float(annotation["align rms mm"]) < 1.0
    mean_iou, min_iou = (float(x) for x in annotation["mask IoU vs sim (mean/min)"].split("/"))
    assert mean_iou > 0.9 and min_iou > 0.5

    train = fig["train"]
    assert int(train["steps"]) == 150
    assert float(train["holdout PSNR"]) > 12.0  # ~13.5 dB for the miniature run (150 steps, 1/4 resolution)

    export = fig["export"]
    assert int(export["gaussians"]) == int(train["gaussians"])  # the bundle carries the trained model
    assert int(export["objects"]) == n_objects

    serve = fig["serve"]
    assert int(serve["adjustments"]) >= 1
    assert int(serve["refusals"]) == 1  # the scripted episode tries one teleport into the table
    start_m, final_m = (float(d) for d in serve["distance m"].split("->"))
    assert final_m < start_m  # it approached the target

    learn = fig["learn"]  # a tiny train_pbr rendered and a model trained on it, scored on its held-out images
    from brave6d.evaluation.learned.demo import QUICK_HELDOUT_IMAGES, QUICK_IMAGES

    assert int(learn["train_pbr images"]) == QUICK_IMAGES and learn["preset"] == "tiny"
    assert int(learn["rendered"]) == QUICK_IMAGES + QUICK_HELDOUT_IMAGES  # and a split apart that the card is scored on
    assert int(learn["held-out images"]) == QUICK_HELDOUT_IMAGES
    assert 0.0 <= float(learn["held-out AR true box"]) <= 1.0 and float(learn["train s"]) > 0
    assert (tmp_path / "learned" / "model" / "model.pt").is_file() and (tmp_path / "learned" / "model" / "card.json").is_file()

    evaluate = fig["evaluate"]
    from brave6d.evaluation.agents import ABLATION_AGENTS, POLICIES

    # every registered agent but the ablations, one episode per object; the ablations played apart
    assert int(evaluate["episodes"]) == (len(POLICIES) - len(ABLATION_AGENTS)) * n_objects
    ablation = read_json(tmp_path / "evaluation" / "ablation" / "leaderboard.json")
    assert {a["agent"] for a in ablation["agents"]} == set(ABLATION_AGENTS) and len(ablation["episodes"]) == \
        len(ABLATION_AGENTS) * n_objects
    assert 0.2 < float(evaluate["AR active"]) <= 1.0 and 0.2 < float(evaluate["AR static"]) <= 1.0
    assert float(evaluate["mean adjustments"]) > 0  # the active agent moved the camera
    assert 0.0 <= float(evaluate["AR learned-active"]) <= 1.0 and 0.0 <= float(evaluate["AR learned-static"]) <= 1.0

    assert fig["report"]["incomplete"] == "none"
    assert (tmp_path / "report" / "report.md").is_file()
    learned = read_json(tmp_path / "report" / "measurements" / "learned.json")  # the learned estimator, real vs splat
    targets = [o for p in learned["points"] for o in p["objects"]]
    assert learned["status"] == "complete" and targets
    assert all(0.0 <= o[f"{side}_true_box_rgb_ar"] <= 1.0 for o in targets for side in ("real", "splat"))
    page = (tmp_path / "report" / "report.md").read_text()
    assert "## 10. The learned estimator" in page and re.search(r"\| learned-active-closeness +\| closeness", page)
    assert "Active minus static, **paired by start**" in page  # section 5
