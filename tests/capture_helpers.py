"""A small capture scene for tests: the demo scene with a small camera and few views."""

from __future__ import annotations

from pathlib import Path

import yaml

from brave6d.core.layout import SceneDir, init_scene_dir


def small_scene(tmp_path: Path, demo_spec_path: Path, views: int = 4, distances: tuple[float, ...] = (0.3, 0.45),
                width: int = 160, height: int = 100) -> SceneDir:
    """The demo scene with a small camera and few views, so that a capture takes seconds."""
    data = yaml.safe_load(demo_spec_path.read_text())
    data["camera"].update({"width": width, "height": height})
    data["capture"].update({"distances_m": list(distances), "views_per_distance": views})
    spec = tmp_path / "spec" / "scene.yaml"
    spec.parent.mkdir(exist_ok=True)
    if not (spec.parent / "meshes").exists():
        (spec.parent / "meshes").symlink_to(demo_spec_path.parent / "meshes")
    spec.write_text(yaml.safe_dump(data))
    return init_scene_dir(tmp_path / "scene", spec)
