"""The newcomer's pages stay true: every relative link of the README and docs/ reaches a file,
every ``brave6d COMMAND`` they show is a command, and every ``src/brave6d/...`` path they name exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from brave6d.cli import COMMANDS

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "src" / "brave6d" / "serve" / "README.md"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_reach_a_file(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    broken = [target for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
              if "://" not in target and not (page.parent / target).exists()]
    assert not broken, f"{page.name}: links to missing files: {broken}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_named_source_paths_exist(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    missing = sorted({p for p in re.findall(r"src/brave6d/[\w/]+\.\w+", text) if not (ROOT / p).exists()})
    assert not missing, f"{page.name}: names files that do not exist: {missing}"


def test_the_readme_shows_only_real_commands() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    shown = set(re.findall(r"^brave6d ([a-z0-9]+)", text, flags=re.M)) | set(re.findall(r"`brave6d ([a-z0-9]+)", text))
    assert shown, "the README shows no command"
    assert shown <= {c.name for c in COMMANDS}, f"not commands: {sorted(shown - {c.name for c in COMMANDS})}"
    assert "bash scripts/demo.sh" in text and "bash scripts/test.sh" in text  # the two set-up commands
    assert len(text.splitlines()) <= 160, "the README is a newcomer's page: details go to docs/"
