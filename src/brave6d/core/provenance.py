"""What made an output: the Python and package versions and the git commit, written into bundle
and release manifests so that a user can tell which software produced the files they hold."""

from __future__ import annotations

import platform
import subprocess
from collections.abc import Iterable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def software_versions(packages: Iterable[str]) -> dict[str, str]:
    """``{"python": ..., <package>: <version or "not installed">, "git_commit": ...}`` from package
    metadata (imports nothing); ``git_commit`` only when the code runs from a git checkout."""
    out = {"python": platform.python_version()}
    for pkg in packages:
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    try:
        res = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=5, check=False)
        if res.returncode == 0:
            out["git_commit"] = res.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return out
