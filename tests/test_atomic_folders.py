"""Folder-level safety: moving user data aside never collides, a staged folder is all or nothing."""

from __future__ import annotations

from pathlib import Path

import pytest

from brave6d.atomic import move_aside, staged_folder


def test_move_aside_keeps_every_copy_even_within_one_second(tmp_path: Path) -> None:
    target = tmp_path / "capture"
    moved = []
    for i in range(3):
        target.mkdir()
        (target / "frames.jsonl").write_text(f"run {i}\n")
        moved.append(move_aside(target))
    assert not target.exists()
    assert len(set(moved)) == 3
    assert sorted(p.joinpath("frames.jsonl").read_text() for p in moved) == ["run 0\n", "run 1\n", "run 2\n"]
    assert all(p.parent == tmp_path and p.name.startswith("capture.old-") for p in moved)


def test_staged_folder_replaces_only_on_success(tmp_path: Path) -> None:
    target = tmp_path / "bop"
    with staged_folder(target) as root:
        (root / "a.txt").write_text("first")
    assert (target / "a.txt").read_text() == "first"
    with pytest.raises(RuntimeError):
        with staged_folder(target) as root:
            (root / "a.txt").write_text("second")
            raise RuntimeError("writer failed")
    assert (target / "a.txt").read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["bop"]  # no staging folder left behind
