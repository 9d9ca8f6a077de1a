"""scripts/setup.sh refuses a disk that cannot hold the install before it starts, naming the folder and
the shortfall (CI once stopped half way through pip with "No space left on device")."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _copy_setup(tmp_path: Path) -> Path:
    (tmp_path / "scripts").mkdir()
    shutil.copy(REPO / "scripts" / "setup.sh", tmp_path / "scripts" / "setup.sh")
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_setup_refuses_a_disk_too_small_and_names_the_folder(tmp_path: Path) -> None:
    root = _copy_setup(tmp_path)
    more_than_any_disk_mb = str(10**12)
    result = subprocess.run(["bash", "scripts/setup.sh"], cwd=root, capture_output=True, text=True,
                            env={"PATH": "/usr/bin:/bin", "BRAVE6D_SETUP_FREE_MB": more_than_any_disk_mb},
                            timeout=120)
    assert result.returncode == 1
    assert str(root) in result.stderr and f"needs about {more_than_any_disk_mb} MB" in result.stderr
    assert "MB free" in result.stderr
    assert not (root / ".venv").exists()  # refused before anything was made


def test_setup_with_an_installed_venv_checks_nothing_more(tmp_path: Path) -> None:
    """A second run with an unchanged pyproject.toml only checks its stamp, whatever the disk holds."""
    root = _copy_setup(tmp_path)
    stamp = root / ".venv" / ".brave6d-installed"
    stamp.parent.mkdir()
    digest = subprocess.run(["sha256sum", "pyproject.toml"], cwd=root, capture_output=True, text=True,
                            check=True).stdout.split()[0]
    stamp.write_text(digest + "\n")
    result = subprocess.run(["bash", "scripts/setup.sh"], cwd=root, capture_output=True, text=True,
                            env={"PATH": "/usr/bin:/bin", "BRAVE6D_SETUP_FREE_MB": str(10**12)},
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert "MB free" not in result.stderr
