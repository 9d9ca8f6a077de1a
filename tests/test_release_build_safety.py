"""``release build`` packs the scenes' own files only (issue 32, item 3) and cleans what a killed
build left (item 12): a bundle zip holds exactly the bundle's manifest and the files it lists; a
symbolic link anywhere build packs from (bundle, BOP export, models, synthetic split) is refused,
naming it; a build SIGKILLed mid-way leaves a staging folder that the next build removes, while a
staging folder whose owner still runs is kept."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from lock_holder import kill_holder, spawn_holder
from test_release import NAME, workdir  # noqa: F401 - test_release's two-scene dataset, made once here too

from brave6d.annotation import BopLayout
from brave6d.core.layout import SceneDir
from brave6d.dataset.release import ReleaseError, build_release, verify_release

pytestmark = pytest.mark.slow  # two exported, bundled scenes (~10 s) and a build per test

ROOT = Path(__file__).resolve().parent.parent
SECRET = b"the key to the lab's cluster"


@pytest.fixture()
def work(workdir: Path, tmp_path: Path) -> Path:  # noqa: F811
    """A copy of the dataset to spoil, and a secret file outside it."""
    (tmp_path / "secret.txt").write_bytes(SECRET)
    return Path(shutil.copytree(workdir, tmp_path / "work", symlinks=True))


def _bop(work: Path, scene: str = "scene_a") -> BopLayout:
    return BopLayout.of_scene(SceneDir(work / "scenes" / scene))


def _link_to_a_copy(path: Path, where: Path) -> Path:
    """Replace ``path`` by a symbolic link to a copy of it at ``where`` (same bytes: every checksum agrees)."""
    where.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(path, where)
    path.unlink()
    path.symlink_to(where)
    return path


def test_a_bundle_zip_holds_exactly_the_listed_files(work: Path, tmp_path: Path) -> None:
    bundle = work / "scenes" / "scene_a" / "bundle"
    (bundle / "stolen.txt").symlink_to(tmp_path / "secret.txt")  # a link nobody listed
    (bundle / "notes.txt").write_text("a stray file\n")  # not listed either
    build_release(work, tmp_path / "out")
    from brave6d.serve import load_bundle

    listed = set(load_bundle(bundle).manifest["files"])
    with zipfile.ZipFile(tmp_path / "out" / f"{NAME}_bundle_000001.zip") as zf:
        names = set(zf.namelist())
        assert all(SECRET not in zf.read(n) for n in names)
    assert names == {f"bundles/000001/{n}" for n in listed | {"manifest.json"}}


def test_a_listed_bundle_file_that_is_a_link_is_refused(work: Path, tmp_path: Path) -> None:
    bundle = work / "scenes" / "scene_a" / "bundle"
    linked = _link_to_a_copy(bundle / "scene.json", bundle / ".scene.json.real")  # verifies: same bytes, inside
    with pytest.raises(ReleaseError, match=rf"{linked}: is a symbolic link"):
        build_release(work, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_bundle_folder_that_is_a_link_is_refused(work: Path, tmp_path: Path) -> None:
    """Issue #44, class 6: the folder itself linked to a copy elsewhere (every file inside verifies)."""
    bundle = work / "scenes" / "scene_a" / "bundle"
    shutil.move(bundle, tmp_path / "elsewhere")
    bundle.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ReleaseError, match=rf"{bundle}: is a symbolic link \(to {tmp_path / 'elsewhere'}\)"):
        build_release(work, tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("victim", ["rgb image", "mask", "rgb folder", "scene_gt.json", "model"])
def test_a_link_in_the_bop_export_is_refused(work: Path, tmp_path: Path, victim: str) -> None:
    lay = _bop(work)
    elsewhere = tmp_path / "elsewhere"
    if victim == "rgb folder":
        rgb = lay.rgb_path(0).parent
        shutil.copytree(rgb, elsewhere / "rgb")
        shutil.rmtree(rgb)
        rgb.symlink_to(elsewhere / "rgb")
        expected = rf"{lay.rgb_path(0)}: lies outside {lay.root}"
    else:
        path = {"rgb image": lay.rgb_path(1), "mask": lay.mask_path(1, 0), "scene_gt.json": lay.scene_gt_path,
                "model": lay.model_path(1)}[victim]
        _link_to_a_copy(path, elsewhere / path.name)
        expected = rf"{path}: is a symbolic link"
    with pytest.raises(ReleaseError, match=expected):
        build_release(work, tmp_path / "out")


def test_a_link_in_the_synthetic_split_is_refused(work: Path, tmp_path: Path) -> None:
    split = work / "synth" / "train_pbr"
    shutil.copytree(_bop(work).scene_dir, split / "000000")  # a valid split: scene_a's images (with depth)
    (split / "000000" / "rgb" / "000001.png").unlink()
    (split / "000000" / "rgb" / "000001.png").symlink_to(tmp_path / "secret.txt")
    with pytest.raises(ReleaseError, match=rf"{split}/000000/rgb/000001.png: is a symbolic link"):
        build_release(work, tmp_path / "out")


PAUSED_BUILD = """
import sys, time
import brave6d.dataset.release.build as build
real = build.write_zip
def write_then_stop(*args, **kwargs):
    real(*args, **kwargs)
    print("one zip written", flush=True)
    time.sleep(3600)
build.write_zip = write_then_stop
build.build_release(sys.argv[1], sys.argv[2])
"""


def test_the_next_build_removes_what_a_killed_build_left(work: Path, tmp_path: Path,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    build = subprocess.Popen([sys.executable, "-c", PAUSED_BUILD, str(work), str(out)], stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True, env=env, cwd=ROOT)
    assert build.stdout is not None and build.stdout.readline() == "one zip written\n"
    build.send_signal(signal.SIGKILL)  # mid-build: one zip in its staging folder
    build.wait()
    build.stdout.close()
    left = [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp-") and p.is_dir()]
    assert len(left) == 1 and any(left[0].iterdir()) and not out.exists()
    live = tmp_path / ".out.tmp-0live0ne"  # the staging folder of a build that still runs
    live.mkdir()
    holder, _ = spawn_holder(tmp_path / ".out.tmp-0live0ne.owner")
    try:
        with caplog.at_level("WARNING", logger="brave6d.core.atomic"):
            build_release(work, out)
        assert not left[0].exists()
        assert f"removed {left[0]}, the staging folder of" in caplog.text and f"(pid {build.pid})" in caplog.text
        assert live.is_dir()
    finally:
        kill_holder(holder)
    assert verify_release(out).scenes == 2
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".out.")) == [
        ".out.tmp-0live0ne", ".out.tmp-0live0ne.owner"]  # kept until a staging of out finds its owner gone


def test_write_zip_never_reads_through_a_link(tmp_path: Path) -> None:
    """The last line of defence: a file checked by build and then swapped for a link is not packed."""
    from brave6d.dataset.release.source import ReleaseError
    from brave6d.dataset.release.zips import write_zip

    secret = tmp_path / "secret.txt"
    secret.write_text("private")
    real = tmp_path / "real.json"
    real.write_text("{}")
    write_zip(tmp_path / "ok.zip", [(real, "a/real.json")])
    real.unlink()
    real.symlink_to(secret)
    with pytest.raises(ReleaseError, match=rf"{real}: is a symbolic link"):
        write_zip(tmp_path / "bad.zip", [(real, "a/real.json")])
