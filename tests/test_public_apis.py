"""The stages' public APIs (docs/ARCHITECTURE.md): every exported name resolves, importing a
stage stays cheap, and no stage reaches into another stage's modules."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("capture", "calibration", "annotation", "training", "serve", "evaluation", "ros_interface")
PACKAGES = (*STAGES, "evaluation.metrics", "evaluation.agents", "evaluation.report")
HEAVY = ("torch", "open3d", "fastapi", "trimesh", "numba", "pycolmap", "matplotlib")


@pytest.mark.parametrize("package", PACKAGES)
def test_every_exported_name_resolves(package: str) -> None:
    module = importlib.import_module(package)
    names = list(getattr(module, "__all__", ()))
    assert names, f"{package} declares no public API (__all__)"
    missing = [n for n in names if not hasattr(module, n)]
    assert not missing, f"{package}.__all__ names that do not resolve: {missing}"


@pytest.mark.parametrize("package", [p for p in PACKAGES if p not in ("capture", "calibration")])
def test_importing_a_lazy_package_loads_nothing_heavy(package: str) -> None:
    code = f"import sys, {package}; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"import {package} loaded {out.stdout.strip()}"


def _stage_of(module: str) -> str | None:
    top = module.split(".")[0]
    return top if top in STAGES else None


def _cross_stage_imports(stage: str) -> list[str]:
    """``file:line: module`` for every import of another stage's submodule (``from serve.app import``)."""
    bad = []
    for path in sorted((ROOT / stage).rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                modules = [node.module]
            elif isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            else:
                continue
            for module in modules:
                other = _stage_of(module)
                if other is not None and other != stage and "." in module and module not in PACKAGES:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {module}")
    return bad


@pytest.mark.parametrize("stage", STAGES)
def test_stages_import_only_each_others_public_names(stage: str) -> None:
    assert not _cross_stage_imports(stage), "\n".join(_cross_stage_imports(stage))


def test_the_import_check_sees_a_cross_stage_import(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake = tmp_path / "serve"
    fake.mkdir()
    (fake / "bad.py").write_text("def f():\n    from training.trainer import Trainer\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _cross_stage_imports("serve") == ["serve/bad.py:2: training.trainer"]


def test_the_shared_core_imports_no_stage() -> None:
    bad = []
    for path in sorted((ROOT / "brave6d").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and _stage_of(node.module):
                bad.append(f"{path.name}:{node.lineno}: {node.module}")
            elif isinstance(node, ast.Import):
                bad += [f"{path.name}:{node.lineno}: {a.name}" for a in node.names if _stage_of(a.name)]
    assert not bad, bad
