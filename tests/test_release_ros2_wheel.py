"""A release ships the ROS 2 interfaces wheel for agents (issue 45, item 3) when a ROS 2 Python can build
it: the file beside the zips, its entry (name, sha256, version) in the manifest, a row in the card;
``release verify`` rejects an altered wheel and one the manifest does not name. Without ROS 2 the
build says why in its log and ships the rest. The wheel here is packed by the interfaces module's
own writer from a stub package (the real build, 30 s of gcc, is tested in tests/ros2)."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_release import _resum, _rewrite_zip, workdir  # noqa: F401 - test_release's two-scene dataset

from brave6d.core.atomic import file_sha256
from brave6d.dataset.release import ReleaseError, build_release, read_manifest, verify_release
from brave6d.dataset.release import ros2_wheel
from brave6d.ros_interface.ros2 import interfaces

pytestmark = pytest.mark.slow  # test_release's fixture (~10 s) and a few builds


def stub_build_wheel(out_dir: Path, *, python: str = sys.executable, **_: object) -> Path:
    """A wheel laid out as the real one (the module's writer), holding a stub ``brave6d_msgs``."""
    stage = out_dir.parent / ".stub-stage"
    (stage / "py" / "brave6d_msgs").mkdir(parents=True)
    (stage / "py" / "brave6d_msgs" / "__init__.py").write_text('"""stub"""\n')
    (stage / "lib").mkdir()
    wheel = interfaces._write_wheel(out_dir, stage, interfaces.wheel_version(), "cp311-cp311-linux_x86_64",
                                    ["ros-rclpy~=9.1.2"])
    shutil.rmtree(stage)
    return wheel


@pytest.fixture(scope="module")
def release(workdir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:  # noqa: F811
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ros2_wheel, "ros2_python", lambda: sys.executable)
        mp.setattr(interfaces, "build_ros2_interfaces_wheel", stub_build_wheel)
        out = tmp_path_factory.mktemp("release") / "out"
        build_release(workdir, out)
    return out


def wheel_of(root: Path) -> Path:
    wheels = list(root.glob("*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_release_ships_the_wheel_with_its_checksum_in_the_manifest(release: Path) -> None:
    wheel = wheel_of(release)
    entry = read_manifest(release / "manifest.json")["ros2_interfaces"]
    assert entry == {"wheel": wheel.name, "sha256": file_sha256(wheel), "version": interfaces.wheel_version(),
                     "tag": "cp311-cp311-linux_x86_64"}
    assert f"`{wheel.name}`" in (release / "README.md").read_text()
    assert verify_release(release).ros2_interfaces == wheel.name


def test_verify_rejects_an_altered_wheel_and_one_the_manifest_does_not_name(release: Path, tmp_path: Path) -> None:
    altered = Path(shutil.copytree(release, tmp_path / "altered"))
    _rewrite_zip(wheel_of(altered), replace={"brave6d_msgs/__init__.py": b"import os\n"})
    _resum(altered)
    with pytest.raises(ReleaseError, match=r"\.whl: sha256 .* does not match manifest.json's ros2_interfaces.sha256"):
        verify_release(altered)

    unnamed = Path(shutil.copytree(release, tmp_path / "unnamed"))
    manifest = json.loads((unnamed / "manifest.json").read_text())
    del manifest["ros2_interfaces"]
    (unnamed / "manifest.json").write_text(json.dumps(manifest))
    _resum(unnamed)
    with pytest.raises(ReleaseError, match=r"\.whl: in the release, but manifest.json has no 'ros2_interfaces' entry"):
        verify_release(unnamed)


def test_without_ros2_the_build_says_why_and_ships_the_rest(workdir: Path, tmp_path: Path,  # noqa: F811
                                                            monkeypatch: pytest.MonkeyPatch,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    bare = tmp_path / "bare"  # a Python without the ROS 2 wheels, named as the ROS 2 one
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(bare)], check=True)
    monkeypatch.setenv(ros2_wheel.ROS2_PYTHON_ENV, str(bare / "bin" / "python"))
    with caplog.at_level(logging.WARNING, logger=ros2_wheel.__name__):
        build_release(workdir, tmp_path / "out")
    assert "no ROS 2 interfaces wheel" in caplog.text and "pip install ros-rclpy" in caplog.text
    assert not list((tmp_path / "out").glob("*.whl"))
    assert "ros2_interfaces" not in read_manifest(tmp_path / "out" / "manifest.json")
    assert verify_release(tmp_path / "out").ros2_interfaces is None

    monkeypatch.delenv(ros2_wheel.ROS2_PYTHON_ENV)
    monkeypatch.setattr(ros2_wheel.importlib.util, "find_spec", lambda name, *a: None)
    assert ros2_wheel.ros2_python() is None


def _with_member(release: Path, tmp_path: Path, member: str, data: bytes) -> Path:
    """A copy of ``release`` whose wheel also holds ``member`` (the wheel, the manifest's entry and
    SHA256SUMS made again: a hostile author re-signs what they change)."""
    import zipfile

    copy = Path(shutil.copytree(release, tmp_path / "copy"))
    wheel = wheel_of(copy)
    with zipfile.ZipFile(wheel, "a") as zf:
        zf.writestr(member, data)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["ros2_interfaces"]["sha256"] = file_sha256(wheel)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    _resum(copy)
    return copy


@pytest.mark.parametrize("member, says", [
    ("evil.pth", "a .pth file"),
    ("brave6d_msgs/deep/evil.pth", "a .pth file"),
    ("sitecustomize.py", "a top-level module"),
    (f"brave6d_ros2_interfaces-{interfaces.wheel_version()}.data/scripts/brave6d-evil", "install hooks"),
    (f"brave6d_ros2_interfaces-{interfaces.wheel_version()}.data/purelib/evil.py", "install hooks"),
    (f"brave6d_ros2_interfaces-{interfaces.wheel_version()}.dist-info/entry_points.txt", "entry points"),
    ("usercustomize/__init__.py", "is not a Python package name"),
])
def test_verify_refuses_a_wheel_that_would_run_code_once_installed(release: Path, tmp_path: Path, member: str,
                                                                   says: str) -> None:
    """A ``.pth`` file in site-packages runs its import lines at every Python start; verify passed a
    wheel carrying one (issue 65, class 5). It never installs the wheel either way."""
    copy = _with_member(release, tmp_path, member, b"import os; os.system('touch /tmp/pwned')\n")
    with pytest.raises(ReleaseError) as info:
        verify_release(copy)
    assert f"{member}: " in str(info.value) and says in str(info.value) and "\n" not in str(info.value)
