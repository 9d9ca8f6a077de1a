"""The package's floors and the stages' public APIs (docs/ARCHITECTURE.md): every exported name
resolves, importing a stage stays cheap, no stage reaches into another stage's modules, the core
imports no stage and nothing below the top floor imports it."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "src" / "brave6d"
STAGE_NAMES = ("capture", "calibration", "annotation", "training", "serve", "evaluation", "dataset",
               "ros_interface", "synth")
STAGES = tuple(f"brave6d.{s}" for s in STAGE_NAMES)
PACKAGES = (*STAGES, "brave6d.evaluation.metrics", "brave6d.evaluation.agents", "brave6d.evaluation.report",
            "brave6d.evaluation.learned", "brave6d.evaluation.agents.learned",
            "brave6d.dataset.release")
#: The floor above the stages: the command line and the pipeline that drives the stages.
TOP = ("brave6d.cli", "brave6d.init_cli", "brave6d.spec_cli", "brave6d.pipeline", "brave6d.commands")
HEAVY = ("torch", "open3d", "fastapi", "trimesh", "numba", "pycolmap", "matplotlib")


@pytest.mark.parametrize("package", PACKAGES)
def test_every_exported_name_resolves(package: str) -> None:
    module = importlib.import_module(package)
    names = list(getattr(module, "__all__", ()))
    assert names, f"{package} declares no public API (__all__)"
    missing = [n for n in names if not hasattr(module, n)]
    assert not missing, f"{package}.__all__ names that do not resolve: {missing}"


@pytest.mark.parametrize("package", [p for p in PACKAGES if p not in ("brave6d.capture", "brave6d.calibration")])
def test_importing_a_lazy_package_loads_nothing_heavy(package: str) -> None:
    code = f"import sys, {package}; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"import {package} loaded {out.stdout.strip()}"


def _stage_of(module: str) -> str | None:
    """``brave6d.serve`` for ``brave6d.serve.app``; None for the core, the top floor or anything else."""
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) >= 2 and parts[0] == "brave6d" and parts[1] in STAGE_NAMES else None


def _imports(folder: Path) -> list[tuple[Path, int, str]]:
    """``(file, line, module)`` of every absolute import in the Python files under ``folder``."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found += [(path, node.lineno, node.module)]
            elif isinstance(node, ast.Import):
                found += [(path, node.lineno, alias.name) for alias in node.names]
    return found


def _cross_stage_imports(stage: str) -> list[str]:
    """``file:line: module`` for every import of another stage's submodule (``from brave6d.serve.app import``)."""
    folder = PACKAGE / stage.split(".", 1)[1]
    return [f"{path.relative_to(PACKAGE.parent)}:{line}: {module}" for path, line, module in _imports(folder)
            if (other := _stage_of(module)) is not None and other != stage and module != other
            and module not in PACKAGES]


@pytest.mark.parametrize("stage", STAGES)
def test_stages_import_only_each_others_public_names(stage: str) -> None:
    assert not _cross_stage_imports(stage), "\n".join(_cross_stage_imports(stage))


def test_the_import_check_sees_a_cross_stage_import(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake = tmp_path / "brave6d" / "serve"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text("def f():\n    from brave6d.training.trainer import Trainer\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "brave6d")
    assert _cross_stage_imports("brave6d.serve") == ["brave6d/serve/bad.py:2: brave6d.training.trainer"]


#: The stages in the order their imports run: a stage imports (through public names) only stages
#: before it. The dataset stage, last, runs them all; nothing imports evaluation but the two that
#: score (ros_interface's scoring) and report (dataset's report) on top of it.
STAGE_ORDER = ("capture", "calibration", "annotation", "synth", "training", "serve", "evaluation", "ros_interface",
               "dataset")


def _backward_imports(package: Path = PACKAGE) -> list[str]:
    """``file:line: module`` for every import (module or function level) of a stage later in
    :data:`STAGE_ORDER` than the importing file's stage."""
    bad = []
    for stage in STAGE_ORDER:
        for path, line, module in _imports(package / stage):
            other = _stage_of(module)
            if other is not None and STAGE_ORDER.index(other.split(".")[1]) > STAGE_ORDER.index(stage):
                bad.append(f"{path.relative_to(package)}:{line}: {module}")
    return bad


def test_the_stage_order_lists_every_stage() -> None:
    assert sorted(STAGE_ORDER) == sorted(STAGE_NAMES)


def test_serve_imports_no_dataset_module() -> None:
    """A release's scenes reach the server through the command line (``brave6d.commands.scenes``),
    which asks ``brave6d.dataset`` for them: the serve stage never imports the dataset stage."""
    bad = [f"{path.relative_to(PACKAGE)}:{line}: {module}" for path, line, module in _imports(PACKAGE / "serve")
           if module == "brave6d.dataset" or module.startswith("brave6d.dataset.")]
    assert not bad, "serve reaches up to the dataset stage:\n" + "\n".join(bad)


def test_imports_run_forward_through_the_stages() -> None:
    bad = _backward_imports()
    assert not bad, f"a stage imports a later one (order: {' -> '.join(STAGE_ORDER)}):\n" + "\n".join(bad)


def test_the_order_check_sees_a_backward_import(tmp_path: Path) -> None:
    for stage in STAGE_ORDER:
        (tmp_path / stage).mkdir()
    (tmp_path / "serve" / "late.py").write_text("def f():\n    from brave6d.dataset import release_scene_sources\n")
    (tmp_path / "dataset" / "fine.py").write_text("from brave6d.serve import load_bundle\n")
    assert _backward_imports(tmp_path) == ["serve/late.py:2: brave6d.dataset"]


def test_the_core_imports_no_stage_and_not_the_top_floor() -> None:
    bad = [f"{path.name}:{line}: {module}" for path, line, module in _imports(PACKAGE / "core")
           if _stage_of(module) or module.startswith(TOP)]
    assert not bad, bad


def test_no_stage_imports_the_top_floor() -> None:
    """Stages name the run's context through the core; only ``dataset``, which runs the pipeline once
    per scene, may import ``brave6d.pipeline``; nothing below the command line imports it."""
    bad = [f"{path.relative_to(PACKAGE)}:{line}: {module}" for stage in STAGE_NAMES
           for path, line, module in _imports(PACKAGE / stage)
           if module.startswith(TOP) and not (stage == "dataset" and module.startswith("brave6d.pipeline"))]
    bad += [f"pipeline/{path.name}:{line}: {module}" for path, line, module in _imports(PACKAGE / "pipeline")
            if module.startswith(("brave6d.cli", "brave6d.init_cli", "brave6d.spec_cli"))]
    assert not bad, "a stage reaches up to the command line or the pipeline:\n" + "\n".join(bad)


def test_the_installed_package_has_one_top_level_name() -> None:
    """Everything lives under ``brave6d``: nothing else in ``src/`` that an install would put
    beside it in site-packages."""
    assert sorted(p.name for p in (ROOT / "src").iterdir() if not p.name.endswith(".egg-info")) == ["brave6d"]
    assert not [s for s in STAGE_NAMES if (ROOT / s).exists()], "a stage folder is left at the repository's top"


def test_tests_and_benchmarks_import_no_private_names() -> None:
    """They may import a stage's modules directly, but not its ``_private`` names (``from brave6d.x import _y``)."""
    bad = []
    for folder in (ROOT / "tests", ROOT / "benchmarks"):
        for path in sorted(folder.glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("brave6d"):
                    bad += [f"{path.relative_to(ROOT)}:{node.lineno}: {node.module}.{a.name}" for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "\n".join(bad)
