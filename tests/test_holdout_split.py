"""The holdout split has one file (``splat/holdout.json``, written by training) and one reader
(``brave6d.training.read_holdout``); a scene trained before the file existed gets the trainer's rule."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brave6d.core.errors import DataError
from brave6d.core.layout import FrameLog, FrameRecord, SceneDir
from brave6d.training import HeldOutView, holdout_split, read_holdout, write_holdout


def _scene(root: Path, levels: list[int]) -> SceneDir:
    scene = SceneDir(root)
    log = FrameLog(scene.frames_path)
    for i, level in enumerate(levels):
        log.append(FrameRecord(index=i, view_id=f"d{level}_v{i:03d}", distance_level=level, distance_m=0.2 + 0.1 * level,
                               rgb=f"rgb/{i:06d}.png", base_T_tcp=np.eye(4).tolist(), joints=[0.0] * 6,
                               timestamp=float(i)))
    return scene


@settings(max_examples=30, deadline=None)
@given(held=st.lists(st.tuples(st.integers(0, 10_000), st.text(min_size=1, max_size=12)), max_size=20,
                     unique_by=lambda v: v[0]))
def test_what_training_writes_is_what_every_reader_reads(held: list[tuple[int, str]], tmp_path_factory) -> None:
    scene = SceneDir(tmp_path_factory.mktemp("split"))
    views = [HeldOutView(i, v) for i, v in held]
    path = write_holdout(scene, views)
    assert path == scene.holdout_split_path == scene.root / "splat" / "holdout.json"
    split = read_holdout(scene)
    assert split.recorded
    assert split.views == tuple(sorted(views, key=lambda v: v.index))
    assert split.indices == sorted(i for i, _ in held)


def test_a_scene_trained_before_the_file_gets_the_trainers_rule(tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    levels = [0] * 12 + [1] * 9
    scene = _scene(tmp_path, levels)
    # an older trainer's metrics.json, with a key the old exporter guessed at: no longer read
    scene.metrics_path.parent.mkdir(parents=True)
    scene.metrics_path.write_text(json.dumps({"holdout": [0, 1, 2]}))
    with caplog.at_level(logging.WARNING):
        split = read_holdout(scene)
    assert not split.recorded
    assert split.indices == holdout_split(scene.frames())[1] == [6, 16]
    assert [v.view_id for v in split.views] == ["d0_v006", "d1_v016"]
    assert "holdout.json: missing" in caplog.text and "trainer's rule" in caplog.text
    # once training recorded its split, that is what is read (here: a split the rule would not make)
    write_holdout(scene, [HeldOutView(3, "d0_v003")])
    assert read_holdout(scene).indices == [3] and read_holdout(scene).recorded


def test_neither_a_split_nor_a_capture_is_named(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r"holdout\.json: no holdout split, and no capture .*frames\.jsonl"):
        read_holdout(SceneDir(tmp_path))


@pytest.mark.parametrize(("content", "problem"), [
    ("[]", "must be a JSON object"),
    ("{not json", "not valid JSON"),
    (json.dumps({"views": []}), "field 'format'"),
    (json.dumps({"format": "brave6d-holdout/2", "views": []}), "field 'format'"),
    (json.dumps({"format": "brave6d-holdout/1"}), "field 'views'"),
    (json.dumps({"format": "brave6d-holdout/1", "views": [{"index": -1, "view_id": "a"}]}), r"field 'views\[0\]\.index'"),
    (json.dumps({"format": "brave6d-holdout/1", "views": [{"index": "3", "view_id": "a"}]}), r"field 'views\[0\]\.index'"),
    (json.dumps({"format": "brave6d-holdout/1", "views": [{"index": 3}]}), r"field 'views\[0\]\.view_id'"),
    (json.dumps({"format": "brave6d-holdout/1", "views": [{"index": 3, "view_id": "a", "x": 1}]}), r"views\[0\]\.x"),
    (json.dumps({"format": "brave6d-holdout/1", "views": [{"index": 3, "view_id": "a"}, {"index": 3, "view_id": "b"}]}),
     r"field 'views\[1\]\.index': frame 3 is listed twice"),
])
def test_a_bad_split_file_is_named_with_its_field(tmp_path: Path, content: str, problem: str) -> None:
    scene = _scene(tmp_path, [0] * 10)  # a capture the rule could use: a bad file is still an error, not a fallback
    scene.holdout_split_path.parent.mkdir(parents=True)
    scene.holdout_split_path.write_text(content)
    with pytest.raises(DataError, match=rf"holdout\.json: .*{problem}"):
        read_holdout(scene)
