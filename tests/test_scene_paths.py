"""One owner for the paths several stages read: ``SceneDir`` builds every path of a scene
directory, ``brave6d.serve.bundle`` names every file of a bundle and answers ``is_bundle``."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from brave6d.core.layout import SceneDir

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "src" / "brave6d"
LAYOUT = PACKAGE / "core" / "layout.py"

#: A bundle's file names, and the modules allowed to spell them: the bundle's owner; the release's
#: own ``manifest.json`` (another format that happens to share the name) is spelled by its owner.
BUNDLE_NAMES = {"manifest.json": ("serve/bundle.py", "dataset/release/formats.py"), "splat.ply": ("serve/bundle.py",),
                "scene.json": ("serve/bundle.py",)}


def _scene_folders() -> set[str]:
    """The folder properties of ``SceneDir`` and ``CaptureLayout`` (``splat_dir``, ``capture_dir``, ...)."""
    return set(re.findall(r"def (\w+_dir)\(self\)", LAYOUT.read_text(encoding="utf-8")))


def _is_scene_root(node: ast.expr) -> bool:
    """``scene.root``, ``ctx.scene.root``, ``self.scene.root``: the root of a scene directory."""
    if not (isinstance(node, ast.Attribute) and node.attr == "root"):
        return False
    owner = node.value
    return (isinstance(owner, ast.Name) and owner.id == "scene") or (isinstance(owner, ast.Attribute)
                                                                   and owner.attr == "scene")


def hand_built_scene_paths(package: Path = PACKAGE) -> list[str]:
    """``file:line: expression`` for each ``<scene folder> / "name"`` (a literal or an f-string)
    outside ``brave6d.core.layout``."""
    folders = _scene_folders()
    found = []
    for path in sorted(package.rglob("*.py")):
        if path.resolve() == LAYOUT.resolve():
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)
                    and isinstance(node.right, (ast.Constant, ast.JoinedStr))):
                continue
            left = node.left
            if (isinstance(left, ast.Attribute) and left.attr in folders) or _is_scene_root(left):
                found.append(f"{path.relative_to(package)}:{node.lineno}: {ast.unparse(node)}")
    return found


def bundle_names_spelled_elsewhere(package: Path = PACKAGE) -> list[str]:
    """``file:line: 'name'`` for each string that is (or ends in ``/``) a bundle file's name, outside
    the modules :data:`BUNDLE_NAMES` allows."""
    found = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                for name, owners in BUNDLE_NAMES.items():
                    if (node.value == name or node.value.endswith("/" + name)) and rel not in owners:
                        found.append(f"{rel}:{node.lineno}: {node.value!r}")
    return found


def test_every_scene_path_is_built_by_scenedir() -> None:
    found = hand_built_scene_paths()
    assert not found, "scene-directory paths built by hand (add a SceneDir property):\n" + "\n".join(found)


def test_the_scene_path_check_sees_a_path_built_by_hand(tmp_path: Path) -> None:
    (tmp_path / "stage").mkdir()
    (tmp_path / "stage" / "bad.py").write_text(
        "def f(scene, ctx, i):\n"
        "    a = scene.splat_dir / 'metrics.json'\n"
        "    b = ctx.scene.root / 'bundle'\n"
        "    c = scene.capture.sim_truth_dir / f'{i:06d}.png'\n"
        "    d = scene.capture.file('rgb/000000.png')\n"  # through the layout: fine
        "    e = self.root / 'camera.json'\n")  # another format's own root (a BOP layout): not a scene's
    assert [f.split(": ", 1)[0] for f in hand_built_scene_paths(tmp_path)] == [
        "stage/bad.py:2", "stage/bad.py:3", "stage/bad.py:4"]


def test_bundle_file_names_live_in_the_bundle_module() -> None:
    found = bundle_names_spelled_elsewhere()
    assert not found, "bundle file names spelled outside serve/bundle.py (import them from brave6d.serve):\n" + \
        "\n".join(found)


def test_the_bundle_name_check_sees_a_literal(tmp_path: Path) -> None:
    (tmp_path / "stage").mkdir()
    (tmp_path / "stage" / "bad.py").write_text("def f(folder):\n    return (folder / 'manifest.json').is_file(), "
                                               "f'{folder}/splat.ply', 'the splat.ply is missing'\n")
    assert sorted(bundle_names_spelled_elsewhere(tmp_path)) == ["stage/bad.py:2: '/splat.ply'",
                                                                "stage/bad.py:2: 'manifest.json'"]


def test_scenedir_paths_stay_inside_the_scene(tmp_path: Path) -> None:
    scene = SceneDir(tmp_path / "scene")
    props = [name for name in dir(SceneDir) if isinstance(getattr(SceneDir, name), property)]
    assert len(props) > 30
    for name in props:
        value = getattr(scene, name)
        if isinstance(value, Path):
            assert value.is_relative_to(scene.root) and value != scene.root, name
    assert scene.holdout_split_path.relative_to(scene.root).as_posix() == "splat/holdout.json"
    assert scene.metrics_path.relative_to(scene.root).as_posix() == "splat/metrics.json"


@pytest.mark.parametrize(("files", "expected"), [
    (("manifest", "splat"), True), (("manifest",), False), (("splat",), False), ((), False),
])
def test_is_bundle_wants_a_manifest_and_a_splat(tmp_path: Path, files: tuple[str, ...], expected: bool) -> None:
    from brave6d.serve import MANIFEST, SPLAT, is_bundle

    folder = tmp_path / "b"
    folder.mkdir()
    for name in files:
        (folder / {"manifest": MANIFEST, "splat": SPLAT}[name]).write_text("x")
    assert is_bundle(folder) is expected
    assert not is_bundle(tmp_path / "missing")
    (tmp_path / "file").write_text("x")
    assert not is_bundle(tmp_path / "file")
