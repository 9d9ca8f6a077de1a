"""The command line: help lists the stages, errors are one line, the demo runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from brave6d.cli import COMMANDS


def brave6d(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "brave6d.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def test_help_lists_every_command_without_importing_stages() -> None:
    out = brave6d("--help")
    assert out.returncode == 0
    for command in COMMANDS:
        assert command.name in out.stdout
    # --help must stay light: no stage and no heavy library gets imported
    probe = subprocess.run(
        [sys.executable, "-c",
         "import sys; from brave6d.cli import main\n"
         "try: main(['--help'])\nexcept SystemExit: pass\n"
         "heavy = [m for m in ('torch', 'open3d', 'cv2', 'capture', 'training') if m in sys.modules]\n"
         "print('HEAVY', heavy)"],
        capture_output=True, text=True, timeout=120)
    assert "HEAVY []" in probe.stdout, probe.stdout + probe.stderr


def test_malformed_spec_is_one_line_naming_file_and_field(tmp_path: Path, demo_spec_path: Path) -> None:
    data = yaml.safe_load(demo_spec_path.read_text())
    data["capture"]["views_per_distance"] = -5
    bad = tmp_path / "bad_scene.yaml"
    bad.write_text(yaml.safe_dump(data))
    (tmp_path / "meshes").symlink_to(demo_spec_path.parent / "meshes")
    out = brave6d("spec", str(bad))
    assert out.returncode == 2
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, out.stderr
    assert str(bad) in lines[0] and "capture.views_per_distance" in lines[0]
    assert "Traceback" not in out.stderr


def test_spec_command_accepts_demo(demo_spec_path: Path) -> None:
    out = brave6d("spec", str(demo_spec_path))
    assert out.returncode == 0, out.stderr
    assert "is valid" in out.stdout and "hex_nut" in out.stdout


@pytest.mark.slow
def test_init_refuses_to_overwrite(tmp_path: Path, demo_spec_path: Path) -> None:
    assert brave6d("init", str(demo_spec_path), str(tmp_path / "s")).returncode == 0
    again = brave6d("init", str(demo_spec_path), str(tmp_path / "s"))
    assert again.returncode == 2 and "--force" in again.stderr


@pytest.mark.slow
def test_init_force_keeps_the_previous_spec_and_a_failing_spec_changes_nothing(
        tmp_path: Path, demo_spec_path: Path) -> None:
    scene = tmp_path / "s"
    assert brave6d("init", str(demo_spec_path), str(scene)).returncode == 0
    first = (scene / "scene.yaml").read_text()
    assert brave6d("init", str(demo_spec_path), str(scene), "--force").returncode == 0
    assert not list(scene.glob("scene.yaml.old-*"))  # same spec: nothing to keep
    data = yaml.safe_load(demo_spec_path.read_text())
    data["name"] = "renamed_scene"
    (tmp_path / "meshes").symlink_to(demo_spec_path.parent / "meshes")
    changed = tmp_path / "changed.yaml"
    changed.write_text(yaml.safe_dump(data))
    out = brave6d("init", str(changed), str(scene), "--force")
    assert out.returncode == 0, out.stderr
    kept = list(scene.glob("scene.yaml.old-*"))
    assert len(kept) == 1 and kept[0].read_text() == first and str(kept[0]) in out.stdout
    assert "renamed_scene" in (scene / "scene.yaml").read_text()
    data["capture"]["views_per_distance"] = -5
    changed.write_text(yaml.safe_dump(data))
    before = (scene / "scene.yaml").read_text()
    assert brave6d("init", str(changed), str(scene), "--force").returncode == 2
    assert (scene / "scene.yaml").read_text() == before
    assert len(list(scene.glob("scene.yaml.old-*"))) == 1
