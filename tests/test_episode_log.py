"""The episode log schema (brave6d.serve.episode_log): versioned records, round trip, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.errors import DataError
from brave6d.core.transforms import make_transform
from brave6d.serve import (
    LOG_FORMAT_VERSION,
    ActionRecord,
    CloseRecord,
    EpisodeLog,
    FinalView,
    LoggedEstimate,
    ObjectState,
    ResetRecord,
    SubmitRecord,
    TargetRef,
    read_episode_log,
)

K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
POSE = make_transform(np.eye(3), [0.1, -0.2, 0.3])
OBJ = make_transform(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [0.01, 0.02, 0.25])
TARGET = TargetRef(gt_id=0, obj_id=3, name="nut")


def records() -> list[ResetRecord | ActionRecord | SubmitRecord | CloseRecord]:
    obj = ObjectState(gt_id=0, obj_id=3, name="nut", is_target=True, cam_T_obj=OBJ, px_count_all=120,
                      px_count_visib=60, visib_fract=0.5, bbox_obj=[1, 2, 3, 4], bbox_visib=[1, 2, 3, 2])
    return [
        ResetRecord(episode_id="e1", bundle="b", agent="me", target=TARGET, scene="tabletop", scene_id=1, width=320, height=240, K=K, seed=4,
                    start="random", world_T_cam=POSE, timings_ms={"render": 1.5}, target_cam_T_obj=OBJ,
                    target_visib_fract=0.5),
        ActionRecord(event="move", step=1, accepted=False, collided=True,
                     refusal={"reason": "collision", "message": "hit", "box": "post"},
                     requested={"linear": [0.0, 0.0, 0.1], "angular": [0.0, 0.0, 0.0], "duration": 1.0,
                                "frame": "camera"},
                     world_T_cam_before=POSE, world_T_cam=POSE, adjustments=0, move=None, timings_ms={}),
        SubmitRecord(episode_id="e1", agent="me", bundle="b", bundle_root="/x", target=TARGET,
                     estimates=[LoggedEstimate(obj_id=3, R=OBJ[:3, :3], t_m=OBJ[:3, 3], score=0.25)],
                     final_view=FinalView(world_T_cam=POSE, K=K, width=320, height=240, depth_file="e1_d.png",
                                          depth_source="reference"),
                     objects=[obj], adjustments=0, steps=1, refusals=1, collisions=0, elapsed_s=2.0),
        CloseRecord(reason="submitted", steps=1, adjustments=0, refusals=1, collisions=0, duration_s=2.0,
                    render_ms_median=None, world_T_cam=POSE),
    ]


def write(path: Path, lines: list[str]) -> Path:
    path.write_text("".join(lines))
    return path


def test_round_trip_keeps_every_field(tmp_path: Path) -> None:
    written = records()
    log = EpisodeLog(tmp_path / "e1.jsonl")
    for r in written:
        log.write(r)
    log.close()
    back = read_episode_log(tmp_path / "e1.jsonl")
    assert [type(r) for r in back] == [type(r) for r in written]
    for a, b in zip(written, back):
        assert a.model_dump(mode="json") == b.model_dump(mode="json")
    assert back[0].format_version == LOG_FORMAT_VERSION
    np.testing.assert_array_equal(back[2].estimates[0].R, OBJ[:3, :3])
    np.testing.assert_array_equal(back[2].objects[0].cam_T_obj, OBJ)


def test_log_keeps_the_version_one_layout(tmp_path: Path) -> None:
    """The rotation of an estimate stays 9 numbers row-major, matrices nested lists, as logs always held them."""
    line = json.loads(EpisodeLog.format(records()[2]))
    assert line["estimates"][0]["R"] == OBJ[:3, :3].reshape(-1).tolist()
    assert line["final_view"]["world_T_cam"] == POSE.tolist() and line["event"] == "submit"
    assert json.loads(EpisodeLog.format(records()[0]))["format_version"] == LOG_FORMAT_VERSION == 4


def test_version_one_log_reads_without_a_scene(tmp_path: Path) -> None:
    """Version 2 only added the served scene to ``reset``: a version-1 log reads with it null."""
    lines = [EpisodeLog.format(r) for r in records()]
    head = json.loads(lines[0])
    head["format_version"] = 1
    del head["scene"], head["scene_id"]
    back = read_episode_log(write(tmp_path / "v1.jsonl", [json.dumps(head) + "\n", *lines[1:]]))
    assert back[0].format_version == 1 and back[0].scene is None and back[0].scene_id is None
    assert back[0].target == records()[0].target


def test_version_two_log_reads_without_a_depth_source(tmp_path: Path) -> None:
    """Version 3 only added ``final_view.depth_source``: a version-2 log reads with it None (the splat's)."""
    lines = [EpisodeLog.format(r) for r in records()]
    head, submit = json.loads(lines[0]), json.loads(lines[2])
    head["format_version"] = 2
    del submit["final_view"]["depth_source"]
    back = read_episode_log(write(tmp_path / "v2.jsonl", [json.dumps(head) + "\n", lines[1], json.dumps(submit) + "\n",
                                                          lines[3]]))
    assert back[0].format_version == 2 and back[2].final_view.depth_source is None
    assert read_episode_log(write(tmp_path / "v3.jsonl", lines))[2].final_view.depth_source == "reference"


def test_unversioned_log_reads_as_version_one(tmp_path: Path) -> None:
    lines = [EpisodeLog.format(r) for r in records()]
    head = json.loads(lines[0])
    del head["format_version"]
    old = read_episode_log(write(tmp_path / "old.jsonl", [json.dumps(head) + "\n", *lines[1:]]))
    new = read_episode_log(write(tmp_path / "new.jsonl", lines))
    assert [r.model_dump(mode="json") for r in old] == [r.model_dump(mode="json") for r in new]


@pytest.mark.parametrize("version", [0, 5, "1", True])
def test_unknown_version_names_file_and_line(tmp_path: Path, version: object) -> None:
    lines = [EpisodeLog.format(r) for r in records()]
    head = {**json.loads(lines[0]), "format_version": version}
    path = write(tmp_path / "future.jsonl", [json.dumps(head) + "\n", *lines[1:]])
    with pytest.raises(DataError, match=rf"future\.jsonl:1: episode log format version {version!r} is not supported"):
        read_episode_log(path)


def test_bad_record_names_file_line_and_field(tmp_path: Path) -> None:
    lines = [EpisodeLog.format(r) for r in records()]
    bad = json.loads(lines[2])
    bad["estimates"][0]["t_m"] = [0.0, 0.1]
    path = write(tmp_path / "bad.jsonl", [lines[0], lines[1], json.dumps(bad) + "\n", lines[3]])
    with pytest.raises(DataError, match=r"bad\.jsonl:3: 'submit' record .* field 'estimates\.0\.t_m'"):
        read_episode_log(path)


def test_partial_last_line_is_ignored_but_not_a_broken_middle(tmp_path: Path) -> None:
    lines = [EpisodeLog.format(r) for r in records()]
    assert len(read_episode_log(write(tmp_path / "cut.jsonl", [*lines[:3], lines[3][:20]]))) == 3
    with pytest.raises(DataError, match=r"mid\.jsonl:2: not valid JSON"):
        read_episode_log(write(tmp_path / "mid.jsonl", [lines[0], lines[1][:20] + "\n", lines[2]]))


def test_non_finite_values_are_refused_before_writing() -> None:
    with pytest.raises(ValueError):
        EpisodeLog.format(records()[3].model_copy(update={"duration_s": float("nan")}))


def test_version_three_log_reads_without_a_mode(tmp_path: Path) -> None:
    """Version 4 added ``reset``'s ``mode``, ``final_view.depth_sha256`` and the ``digest`` record: a
    version-3 log reads with them None (its server served the ground truth: scoring reads it as training)."""
    lines = [EpisodeLog.format(r) for r in records()]
    head = {**json.loads(lines[0]), "format_version": 3}
    del head["mode"]
    back = read_episode_log(write(tmp_path / "v3.jsonl", [json.dumps(head) + "\n", *lines[1:]]))
    assert back[0].format_version == 3 and back[0].mode is None and back[2].final_view.depth_sha256 is None


def test_a_signed_log_ends_with_its_digest(tmp_path: Path) -> None:
    from brave6d.serve import DigestRecord, LogKey, check_log_digest

    key = LogKey.random()
    log = EpisodeLog(tmp_path / "e1.jsonl", key)
    for r in records():
        log.write(r)
    log.close()
    back = read_episode_log(tmp_path / "e1.jsonl")
    assert isinstance(back[-1], DigestRecord) and back[-1].key_id == key.key_id and back[-1].lines == 4
    assert check_log_digest(tmp_path / "e1.jsonl", key, "e1", back[-1].signed()).status == "verified"
    assert check_log_digest(tmp_path / "e1.jsonl", LogKey.random(), "e1", back[-1].signed()).status == "unknown key"
    assert "secret" not in repr(key) and key.secret.hex() not in repr(key)
    text = (tmp_path / "e1.jsonl").read_text()
    (tmp_path / "e1.jsonl").write_text(text.replace('"score": 0.25', '"score": 0.26'))
    with pytest.raises(DataError, match="episode e1: the log does not match the digest"):
        check_log_digest(tmp_path / "e1.jsonl", key, "e1", back[-1].signed())
    unsigned = EpisodeLog(tmp_path / "e2.jsonl")  # no key: no digest record
    unsigned.write(records()[0])
    unsigned.close()
    assert [r.event for r in read_episode_log(tmp_path / "e2.jsonl")] == ["reset"]
