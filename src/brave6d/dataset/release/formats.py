"""The release's own files, owned here: names of the zips and of the folders inside them,
``SHA256SUMS``, the BOP19 target lists and the per-scene ``holdout.json``.

Layout of a release folder (BOP's download layout: unzip the base zip, then the others into the
folder it makes)::

    <name>_base.zip           <name>/dataset_info.json, camera.json, test_targets_bop19.json,
                              test_targets_bop19_holdout.json, README.md (the dataset card)
    <name>_models.zip         models/obj_XXXXXX.ply (mm), models/models_info.json
    <name>_test_all.zip       test/XXXXXX/{rgb,depth,mask,mask_visib}/, scene_camera.json,
                              scene_gt.json, scene_gt_info.json, holdout.json
    <name>_bundle_XXXXXX.zip  bundles/XXXXXX/ (the scene's render-server bundle)
    <name>_train_pbr.zip      train_pbr/XXXXXX/ (the synthetic training split; only when the dataset has one)
    <name>_learned.zip        learned/model.pt, card.json, MODEL_CARD.md (the dataset's learned model; only
                              when it has one: :mod:`brave6d.dataset.release.learned`)
    manifest.json, README.md, SHA256SUMS
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from brave6d.annotation import BOP19_MIN_VISIB_FRACT
from brave6d.core.atomic import atomic_write_text, read_json
from brave6d.core.bounded_files import read_regular
from brave6d.core.names import relative_path_problem
from brave6d.dataset.release.source import ReleaseError

FORMAT = "brave6d-release/1"
SPLIT = "test"
MANIFEST = "manifest.json"
SUMS = "SHA256SUMS"
CARD = "README.md"
DATASET_INFO = "dataset_info.json"
CAMERA = "camera.json"
TARGETS = "test_targets_bop19.json"
TARGETS_HOLDOUT = "test_targets_bop19_holdout.json"
HOLDOUT = "holdout.json"
SCENE_JSONS = ("scene_camera.json", "scene_gt.json", "scene_gt_info.json")
#: BOP19 targets: instances with at least this visible fraction (the BOP format's owner defines it).
MIN_VISIB_FRACT = BOP19_MIN_VISIB_FRACT
_SUM_LINE = re.compile(r"^([0-9a-f]{64}) [ *](.+)$")
#: Largest ``SHA256SUMS`` read (a line per file: a release of a million files is about 100 MB).
MAX_SUMS_BYTES = 256 * 2**20


def base_zip(name: str) -> str:
    return f"{name}_base.zip"


def models_zip(name: str) -> str:
    return f"{name}_models.zip"


def test_zip(name: str) -> str:
    return f"{name}_test_all.zip"


def bundle_zip(name: str, scene_id: int) -> str:
    return f"{name}_bundle_{scene_id:06d}.zip"


def scene_folder(scene_id: int) -> str:
    """``test/XXXXXX`` inside the test zip (and the unzipped dataset)."""
    return f"{SPLIT}/{scene_id:06d}"


def bundle_folder(scene_id: int) -> str:
    """``bundles/XXXXXX`` inside a bundle zip (and the unzipped dataset)."""
    return f"bundles/{scene_id:06d}"


# ----------------------------------------------------------------------------- SHA256SUMS
def write_sha256sums(path: Path, digests: Mapping[str, str]) -> Path:
    """``sha256sum`` format (``<hex>  <name>``, names sorted), so ``sha256sum -c SHA256SUMS`` checks it."""
    lines = "".join(f"{digests[name]}  {name}\n" for name in sorted(digests))
    return atomic_write_text(path, lines)


def read_sha256sums(path: Path) -> dict[str, str]:
    """``{relative name: hex digest}`` from a ``sha256sum`` file; a malformed line is an error naming it."""
    if not path.is_file():
        raise ReleaseError(f"{path}: not found; not a release folder (build one with 'brave6d release build')")
    out: dict[str, str] = {}
    text = read_regular(path, MAX_SUMS_BYTES, what="checksums", error=ReleaseError)
    for n, line in enumerate(text.decode("utf-8", errors="replace").splitlines(), start=1):
        if not line.strip():
            continue
        m = _SUM_LINE.match(line)
        if m is None:
            raise ReleaseError(f"{path}:{n}: not a sha256sum line ('<64 hex digits>  <file name>')")
        name = m.group(2)
        problem = relative_path_problem(name)  # the one rule of names inside a folder
        if problem is not None or name in out:
            raise ReleaseError(f"{path}:{n}: file name {name[:200]!r} is outside the release or listed twice"
                               f"{f' ({problem})' if problem else ''}")
        out[name] = m.group(1)
    return out


# ----------------------------------------------------------------------------- targets and holdout
def bop19_targets(scene_id: int, gt_obj_ids: Mapping[int, list[int]], visib: Mapping[int, list[float]],
                  im_ids: Iterable[int] | None = None) -> list[dict[str, int]]:
    """BOP19 targets of one scene: per image and object, the number of instances with
    ``visib_fract >= 0.1`` (images or objects without such an instance are left out)."""
    out = []
    for im_id in sorted(gt_obj_ids if im_ids is None else im_ids):
        counts = Counter(obj for obj, v in zip(gt_obj_ids[im_id], visib[im_id]) if v >= MIN_VISIB_FRACT)
        out += [{"im_id": im_id, "inst_count": counts[obj], "obj_id": obj, "scene_id": scene_id}
                for obj in sorted(counts)]
    return out


def dump_targets(targets: list[dict[str, int]]) -> str:
    """BOP's targets file: a JSON list, one target per line."""
    return "[\n" + ",\n".join("  " + json.dumps(t, sort_keys=True) for t in targets) + "\n]\n"


def read_targets(path: Path, shown: str | None = None) -> list[dict[str, int]]:
    """A targets file: a list of ``{scene_id, im_id, obj_id, inst_count}`` with positive integers."""
    name = shown or str(path)
    data = _read(path, name)
    if not isinstance(data, list):
        raise ReleaseError(f"{name}: expected a JSON list of targets")
    for i, t in enumerate(data):
        if not isinstance(t, dict):
            raise ReleaseError(f"{name}: target [{i}]: expected an object")
        for key in ("scene_id", "im_id", "obj_id", "inst_count"):
            value = t.get(key)
            if not isinstance(value, int) or isinstance(value, bool) or value < (0 if key == "im_id" else 1):
                raise ReleaseError(f"{name}: target [{i}] field '{key}': expected a positive integer, got {value!r}")
    return data


def holdout_json(im_ids: list[int], view_ids: list[str]) -> str:
    """A scene's ``holdout.json``: the image ids (and capture view ids) held out of the splat's training."""
    return json.dumps({"im_ids": im_ids, "view_ids": view_ids}, indent=2) + "\n"


def read_holdout(path: Path, shown: str | None = None) -> list[int]:
    """The held-out image ids of a scene's ``holdout.json``."""
    name = shown or str(path)
    data = _read(path, name)
    ids = data.get("im_ids") if isinstance(data, dict) else None
    if not isinstance(ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in ids):
        raise ReleaseError(f"{name}: field 'im_ids': expected a list of integer image ids")
    return ids


def _read(path: Path, shown: str) -> Any:
    try:
        return read_json(path)
    except ReleaseError:
        raise
    except Exception as exc:  # DataError names the (temporary) path: name the release member instead
        raise ReleaseError(str(exc).replace(str(path), shown)) from None


# ----------------------------------------------------------------------------- the synthetic training split
#: The BOP split name of the synthetic training images (``brave6d synth``).
TRAIN_PBR = "train_pbr"
#: Where a dataset work directory holds its synthetic split: ``WORKDIR/synth/train_pbr/`` (written by
#: ``brave6d synth WORKDIR/dataset.yaml WORKDIR/synth --images N``).
SYNTH_DIR = "synth"


def train_pbr_zip(name: str) -> str:
    """``<name>_train_pbr.zip``: ``train_pbr/XXXXXX/`` folders (BOP's PBR layout)."""
    return f"{name}_train_pbr.zip"
