"""The dataset card (``README.md`` of a release): what is in it, statistics, license, citation,
and how to load it with bop_toolkit and serve it."""

from __future__ import annotations

from brave6d.core.progress import format_table
from brave6d.dataset.release.collect import ReleaseModel, SceneRelease
from brave6d.dataset.release.formats import (TARGETS, TARGETS_HOLDOUT, base_zip, bundle_folder, bundle_zip, models_zip,
                                     test_zip, train_pbr_zip)
from brave6d.dataset.release.learned import learned_zip
from brave6d.dataset.release.source import ReleaseSource


def _table(headers: list[str], rows: list[list[object]]) -> str:
    """A Markdown table (``brave6d.core.progress.format_table``) of the cells as written; None is blank."""
    return format_table(headers, [["" if c is None else str(c) for c in row] for row in rows])


def _db(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f} dB"


def _mb(n: int | None) -> str:
    if n is None:
        return "this file"
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


def render_card(source: ReleaseSource, scenes: list[SceneRelease], models: dict[int, ReleaseModel],
                sizes: dict[str, int]) -> str:
    """The card's Markdown (``sizes``: bytes of the zips written before the base zip)."""
    n = source.name
    files = [[f"`{base_zip(n)}`", "`" + n + "/`: `dataset_info.json`, `camera.json`, "
              f"`{TARGETS}`, `{TARGETS_HOLDOUT}`, this card", _mb(sizes.get(base_zip(n)))],
             [f"`{models_zip(n)}`", "`models/obj_XXXXXX.ply` (mm), `models/models_info.json`",
              _mb(sizes.get(models_zip(n)))],
             [f"`{test_zip(n)}`", "`test/XXXXXX/`: rgb, depth, mask, mask_visib, scene_camera.json, scene_gt.json, "
              "scene_gt_info.json, holdout.json", _mb(sizes.get(test_zip(n)))]]
    if train_pbr_zip(n) in sizes:  # the synthetic training split (brave6d synth), when the dataset has one
        files.append([f"`{train_pbr_zip(n)}`", "`train_pbr/XXXXXX/`: synthetic training images (rgb, depth, mask, "
                      "mask_visib, scene_camera.json, scene_gt.json, scene_gt_info.json)", _mb(sizes[train_pbr_zip(n)])])
    if learned_zip(n) in sizes:  # the dataset's learned model (brave6d dataset run), when it has one
        files.append([f"`{learned_zip(n)}`", "`learned/`: the learned estimator trained on the object library's "
                      "synthetic train_pbr (`model.pt`, `card.json`, `MODEL_CARD.md`)", _mb(sizes[learned_zip(n)])])
    for wheel in sorted(name for name in sizes if name.endswith(".whl")):  # ROS 2 interfaces, when built
        files.append([f"`{wheel}`", "ROS 2 interfaces (`brave6d_msgs`, `tf2_msgs`) for an agent's own environment: "
                      "`pip install` it (docs/ROS.md)", _mb(sizes[wheel])])
    files += [[f"`{bundle_zip(n, s.source.scene_id)}`", f"`{bundle_folder(s.source.scene_id)}/`: render-server "
               f"bundle of scene {s.source.name}", _mb(sizes.get(bundle_zip(n, s.source.scene_id)))] for s in scenes]
    objects = [[o.obj_id, o.name, o.category, f"{models[o.obj_id].info['diameter']:.1f}" if o.obj_id in models
                else "no model (in no scene)", o.description] for o in source.objects]
    per_scene = [[s.source.scene_id, s.source.name, len(s.im_ids), len(s.holdout),
                  ", ".join(f"{v} ({k})" for k, v in sorted(s.objects.items())), s.instances, s.targets,
                  "yes" if s.has_depth else "no", _db(s.psnr)] for s in scenes]
    per_level = [[s.source.scene_id, lv.level, "?" if lv.distance_m is None else f"{lv.distance_m:.2f}", lv.views,
                  lv.holdout_views, lv.targets, _db(lv.psnr)] for s in scenes for lv in s.levels]
    total = sum(len(s.im_ids) for s in scenes)
    first = scenes[0].source.scene_id
    return f"""# {n} (version {source.version})

{source.description or "A BRAVE-6D dataset."}

{len(scenes)} scenes, {len(source.objects)} objects, {total} images, {sum(s.instances for s in scenes)} annotated
instances, {sum(s.targets for s in scenes)} BOP19 targets (instances with a visible fraction of at least 0.1),
{sum(len(s.holdout) for s in scenes)} held-out images. Made by the BRAVE-6D pipeline (`brave6d release build`);
`manifest.json` lists the versions of everything that made it, the counts and the size of every file.

## Files

{_table(["file", "contents", "size"], files)}

`SHA256SUMS` holds the checksum of every file: `sha256sum -c SHA256SUMS`, or `brave6d release verify DIR`,
which also opens every zip and checks every JSON file, image reference, object id and bundle.

## Objects

The same `obj_id` in every scene (its position in the dataset's object library).

{_table(["obj_id", "name", "category", "diameter (mm)", "description"], objects)}

## Scenes

Holdout PSNR: the scene's 3D Gaussian Splatting model rendered at the views held out of its training,
against the captured images (`splat/metrics.json` of the scene).

{_table(["scene_id", "name", "images", "holdout", "objects (obj_id)", "instances", "targets", "depth",
         "holdout PSNR"], per_scene)}

Per capture distance level:

{_table(["scene_id", "level", "distance (m)", "images", "holdout", "targets", "holdout PSNR"], per_level)}

**Holdout views.** The images whose views were held out of the splat's training are listed in each scene's
`test/XXXXXX/holdout.json` (`im_ids`, and the capture's `view_ids`); `{TARGETS_HOLDOUT}` holds the BOP19
targets on those images only (score on them to compare with methods that saw the splat), `{TARGETS}` the
targets on every image.

## Load it with bop_toolkit

The layout is BOP's: unzip the base zip, then the others into the folder it makes.

```bash
unzip {base_zip(n)}
unzip {models_zip(n)} -d {n}
unzip {test_zip(n)} -d {n}
```

```python
from bop_toolkit_lib import inout
scene = "{n}/test/{first:06d}"
gt = inout.load_scene_gt(f"{{scene}}/scene_gt.json")
cams = inout.load_scene_camera(f"{{scene}}/scene_camera.json")
model = inout.load_ply("{n}/models/obj_000001.ply")
```

`cam_K` (and `camera.json`'s `cx`, `cy`) follow BOP's pixel convention, in which bop_toolkit's renderers
draw: **subtract 0.5 from cx and cy to use OpenCV functions (e.g. `solvePnP`) on the images.** Depth images
are uint16 millimetres (`depth_scale` 1.0); models and translations are in millimetres. bop_toolkit's
`dataset_params` does not know this dataset's name: add an entry for it (models `models/`, split `test`,
image size from `camera.json`) or use `inout` directly as above.

## Serve it

```bash
unzip {bundle_zip(n, first)} -d {n}
brave6d serve {n}/{bundle_folder(first)}
```

The bundle checks its own checksums on load; see the BRAVE-6D README for agents and the Python client.
The server runs scored: no object pose, box or visible fraction reaches an agent, and each episode's
log (in `episodes/` beside the bundle) records the mode and is signed with the server's key;
`brave6d evaluate episodes/` ranks those episodes. `--training` serves the ground truth for developing
agents (its episodes are never ranked). The bundle itself holds the objects' placements
(`objects.json`): a result others can trust runs the agent where it cannot read the bundle.

## License

{source.license}

## Citation

```bibtex
{source.citation}
```
"""
