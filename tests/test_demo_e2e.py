"""Miniature end-to-end run of `brave6d demo --quick`: every stage's wiring, as CI runs it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from brave6d.demo import STAGES


@pytest.mark.slow
def test_quick_demo_runs_every_stage(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "brave6d.cli", "demo", "--quick", "--workdir", str(tmp_path)],
                         capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-4000:]
    for stage in STAGES:
        assert f"] {stage.name}" in out.stderr and "done in" in out.stderr
        assert f"| {stage.name}" in out.stdout, out.stdout
    assert (tmp_path / "scene" / "scene.yaml").is_file()
