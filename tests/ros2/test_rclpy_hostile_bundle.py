"""``brave6d ros2`` on a bundle whose manifest holds a 5000-digit integer (issue #44 class 1, the ROS 2
path: before the one JSON reader the node answered "internal error" or tracebacked): one line naming
the file and field, exit status 2."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

pytestmark = pytest.mark.slow


def test_a_5000_digit_integer_in_the_bundle_is_one_line_at_node_start(bundle_dir: Path, tmp_path: Path) -> None:
    bundle = Path(shutil.copytree(bundle_dir, tmp_path / "bundle"))
    text = (bundle / "manifest.json").read_text()
    (bundle / "manifest.json").write_text(re.sub(r'"bytes": \d+', '"bytes": ' + "9" * 5000, text, count=1))
    out = subprocess.run([sys.executable, "-m", "brave6d.cli", "ros2", str(bundle), "--device", "cpu",
                          "--log-dir", str(tmp_path / "episodes")], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2, out.stdout[-2000:] + out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert "manifest.json" in lines[0] and "a number of 5000 characters" in lines[0], lines[0]
