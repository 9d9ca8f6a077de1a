"""Folder-level safety: moving user data aside never collides, a staged folder is all or nothing."""

from __future__ import annotations

from pathlib import Path

import pytest

from brave6d.core.atomic import move_aside, staged_folder


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


def test_atomic_files_and_staged_folders_get_the_permissions_open_and_mkdir_give(tmp_path: Path) -> None:
    """mkstemp/mkdtemp make 0600/0700; written data must be as readable as a plain open()/mkdir()."""
    import stat

    from brave6d.core.atomic import atomic_write_text, staged_folder

    plain_file, plain_dir = tmp_path / "plain.txt", tmp_path / "plain_dir"
    plain_file.write_text("x")
    plain_dir.mkdir()
    atomic = atomic_write_text(tmp_path / "atomic.txt", "x")
    with staged_folder(tmp_path / "staged") as staging:
        (staging / "f").write_text("x")
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(atomic) == mode(plain_file)
    assert mode(tmp_path / "staged") == mode(plain_dir)
