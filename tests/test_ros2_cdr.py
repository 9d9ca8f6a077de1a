"""ROS 2 messages over DDS: every message class of ``brave6d.ros_interface.ros2.messages`` serialises to
the same bytes as ``rosbags``' CDR serialiser (the ROS 2 Humble and Jazzy definitions) for the same
values, reads rosbags' bytes back, and crosses a real DDS link (two processes, loopback only) intact.

Values come from hypothesis, driven by rosbags' field definitions (the reference): a field our
class lacks, has in another order or with another CDR type fails the byte comparison.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("cyclonedds")
rosbags_typesys = pytest.importorskip("rosbags.typesys")

from brave6d.ros_interface.ros2 import messages as m  # noqa: E402
from brave6d.ros_interface.ros2.dds import DEFAULT, SENSOR_DATA, DdsDomain, dds_topic_name  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
CLASS_OF = {ros: cls for cls, ros in m.ROS_TYPES.items()}
STORES = {"humble": rosbags_typesys.Stores.ROS2_HUMBLE, "jazzy": rosbags_typesys.Stores.ROS2_JAZZY}


def typestore(store: str) -> Any:
    ts = rosbags_typesys.get_typestore(STORES[store])
    for name, path in m.CUSTOM_MSG_FILES.items():
        ts.register(rosbags_typesys.get_types_from_msg(path.read_text(), name))
    return ts


TYPESTORES = {name: typestore(name) for name in STORES}

# ----------------------------------------------------------------------------- values from rosbags' definitions
INT_RANGES = {"int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-2**15, 2**15 - 1),
              "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
              "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
FINITE = st.floats(allow_nan=False, allow_infinity=False)
# CDR strings end in NUL, so a NUL inside is not representable; any other character is (odd
# lengths included, which moves the alignment of every following field).
TEXT = st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=9)


def base_strategy(name: str) -> st.SearchStrategy:
    if name in INT_RANGES:
        lo, hi = INT_RANGES[name]
        return st.integers(lo, hi)
    if name == "float64":
        return FINITE
    if name == "float32":
        return st.floats(width=32, allow_nan=False, allow_infinity=False)
    if name == "bool":
        return st.booleans()
    if name == "string":
        return TEXT
    raise AssertionError(f"no strategy for base type {name}")


def field_strategy(ts: Any, node: tuple) -> st.SearchStrategy:
    kind, spec = node
    if kind == 1:  # BASE: (type, string bound)
        return base_strategy(spec[0])
    if kind == 2:  # NAME: a nested message
        return message_values(ts, spec)
    sub, length = spec  # ARRAY (3, fixed length) or SEQUENCE (4, length 0: unbounded)
    if kind == 4 and sub == (1, ("uint8", 0)):
        return st.binary(max_size=33)
    elements = field_strategy(ts, sub)
    if kind == 3:
        return st.lists(elements, min_size=length, max_size=length)
    return st.lists(elements, max_size=3)  # empty sequences included


def message_values(ts: Any, ros_type: str) -> st.SearchStrategy:
    """A strategy of ``(ros_type, {field: value})`` trees for one message type."""
    _, fields = ts.fielddefs[ros_type]
    return st.fixed_dictionaries({name: field_strategy(ts, node) for name, node in fields}).map(
        lambda values: (ros_type, values))


def is_tree(value: Any) -> bool:
    return isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], str) and isinstance(value[1], dict)


def build_cyclone(tree: tuple) -> Any:
    ros_type, values = tree

    def conv(v: Any) -> Any:
        if is_tree(v):
            return build_cyclone(v)
        if isinstance(v, list):
            return [conv(x) for x in v]
        return v

    return CLASS_OF[ros_type](**{k: conv(v) for k, v in values.items()})


def build_rosbags(ts: Any, tree: tuple) -> Any:
    ros_type, values = tree
    _, fields = ts.fielddefs[ros_type]
    out = {}
    for name, (kind, spec) in fields:
        v = values[name]
        if kind == 2:
            out[name] = build_rosbags(ts, v)
        elif kind in (3, 4) and spec[0][0] == 1:  # arrays/sequences of base types are numpy arrays
            dtype = {"float64": np.float64, "float32": np.float32, "uint8": np.uint8, "int32": np.int32,
                     "uint32": np.uint32}[spec[0][1][0]]
            out[name] = np.frombuffer(v, dtype=np.uint8) if isinstance(v, bytes) else np.asarray(v, dtype=dtype)
        elif kind in (3, 4):
            out[name] = [build_rosbags(ts, x) for x in v]
        else:
            out[name] = v
    return ts.types[ros_type](**out)


ALL_TYPES = sorted(m.ROS_TYPES.values())


# ----------------------------------------------------------------------------- bytes
@pytest.mark.parametrize("ros_type", ALL_TYPES)
def test_dds_type_names_and_fields_match_ros2(ros_type: str) -> None:
    cls = CLASS_OF[ros_type]
    package, _, name = ros_type.split("/")
    assert cls.__idl_typename__ == f"{package}::msg::dds_::{name}_"
    for store, ts in TYPESTORES.items():
        ours = list(cls.__dataclass_fields__)
        theirs = [f for f, _ in ts.fielddefs[ros_type][1]]
        assert ours == theirs, f"{ros_type} ({store}): fields {ours} != {theirs}"


@pytest.mark.parametrize("store", sorted(STORES))
@pytest.mark.parametrize("ros_type", ALL_TYPES)
@settings(max_examples=25)
@given(data=st.data())
def test_cdr_bytes_equal_rosbags(ros_type: str, store: str, data: st.DataObject) -> None:
    ts = TYPESTORES[store]
    tree = data.draw(message_values(ts, ros_type))
    ours = build_cyclone(tree)
    ref = bytes(ts.serialize_cdr(build_rosbags(ts, tree), ros_type))
    got = ours.serialize()
    assert got[:4] == b"\x00\x01\x00\x00", "ROS 2 writes plain CDR, little endian (XCDR1 encapsulation 0x0001)"
    assert got == ref, f"{ros_type}: cyclonedds bytes differ from rosbags' CDR"
    assert type(ours).deserialize(ref) == ours  # and rosbags' bytes read back to the same values


def test_default_values_equal_ros2_defaults() -> None:
    """A message built with no arguments is ROS 2's default message (identity quaternion included:
    geometry_msgs/Quaternion's w defaults to 1)."""
    ts = TYPESTORES["humble"]
    q = ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    assert m.Quaternion().serialize() == bytes(ts.serialize_cdr(q, "geometry_msgs/msg/Quaternion"))
    assert m.CameraInfo().k == [0.0] * 9 and m.CameraInfo().d == []


def test_stamps_round_trip() -> None:
    ns = 1_700_000_000_123_456_789
    t = m.stamp_from_ns(ns)
    assert (t.sec, t.nanosec) == (1_700_000_000, 123_456_789)
    assert m.stamp_to_ns(t) == ns


def test_topic_names_get_the_ros2_prefix() -> None:
    assert dds_topic_name("/brave6d/rgb/image_raw") == "rt/brave6d/rgb/image_raw"
    assert dds_topic_name("/tf") == "rt/tf"
    with pytest.raises(Exception, match="fully qualified"):
        dds_topic_name("brave6d/rgb")


# ----------------------------------------------------------------------------- over DDS
SAMPLE_TREES_SEED = 20  # the values sent over DDS are drawn from random.Random(seed + i): reproducible


def sample_messages() -> dict[str, Any]:
    """One message of every type with non-default values (drawn once, reproducibly), plus a
    camera-sized RGB image (fragmented on the wire)."""
    ts = TYPESTORES["humble"]
    out = {}
    for i, ros_type in enumerate(ALL_TYPES):
        rng = random.Random(SAMPLE_TREES_SEED + i)
        out[ros_type] = build_cyclone(draw_reproducibly(ts, ros_type, rng))
    rgb = np.random.default_rng(0).integers(0, 256, size=(240, 320, 3), dtype=np.uint8)
    out["big_image"] = m.Image(header=m.Header(stamp=m.Time(5, 6), frame_id="brave6d_camera_optical_frame"),
                               height=240, width=320, encoding="rgb8", is_bigendian=0, step=960,
                               data=rgb.tobytes())
    return out


def draw_reproducibly(ts: Any, ros_type: str, rng: random.Random) -> tuple:
    """A value tree like :func:`message_values`, drawn from ``rng`` (hypothesis' ``example()``
    is not for tests), with odd-length strings, empty and non-empty sequences."""
    _, fields = ts.fielddefs[ros_type]
    values = {}
    for name, (kind, spec) in fields:
        values[name] = draw_field(ts, (kind, spec), rng)
    return ros_type, values


def draw_field(ts: Any, node: tuple, rng: random.Random) -> Any:
    kind, spec = node
    if kind == 1:
        t = spec[0]
        if t in INT_RANGES:
            lo, hi = INT_RANGES[t]
            return rng.randint(lo, hi)
        if t == "float64":
            return rng.uniform(-1e6, 1e6)
        if t == "bool":
            return rng.random() < 0.5
        if t == "string":
            return "x" * rng.choice([1, 3, 5]) + "é"
        raise AssertionError(t)
    if kind == 2:
        return draw_reproducibly(ts, spec, rng)
    sub, length = spec
    if kind == 4 and sub == (1, ("uint8", 0)):
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 11)))
    n = length if kind == 3 else rng.randint(1, 3)
    return [draw_field(ts, sub, rng) for _ in range(n)]


def topic_of(key: str) -> str:
    return "/brave6d_test/" + key.replace("/msg/", "/").replace("/", "_")


def qos_of(key: str) -> Any:
    return SENSOR_DATA if key in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "big_image") else DEFAULT


CHILD = textwrap.dedent("""
    import json, sys, time
    from brave6d.ros_interface.ros2 import messages as m
    from brave6d.ros_interface.ros2.dds import DdsDomain, DEFAULT, SENSOR_DATA
    domain_id, spec = int(sys.argv[1]), json.loads(sys.argv[2])
    classes = {cls.__name__: cls for cls in m.ROS_TYPES}
    qos = {"default": DEFAULT, "sensor_data": SENSOR_DATA}
    with DdsDomain(domain_id) as dds:
        readers = {t: dds.reader(t, classes[c], qos[q]) for t, (c, q) in spec.items()}
        print("ready", flush=True)
        got, deadline = {}, time.monotonic() + 20
        while len(got) < len(readers) and time.monotonic() < deadline:
            for t, r in readers.items():
                if t not in got:
                    for s in r.take(N=1):
                        got[t] = s.serialize().hex()
            time.sleep(0.005)
        print(json.dumps(got), flush=True)
""")


@pytest.mark.slow
def test_every_message_crosses_dds_on_loopback(tmp_path: Path) -> None:
    """Writer here, readers in a second process, same random domain id, loopback-only Cyclone
    configuration: each received message equals the sent one."""
    messages = sample_messages()
    domain_id = random.randrange(100, 200)
    spec = {topic_of(k): (type(v).__name__, qos_of(k).name) for k, v in messages.items()}
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(domain_id), json.dumps(spec)], cwd=REPO, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        with DdsDomain(domain_id) as dds:
            writers = {k: dds.writer(topic_of(k), type(v), qos_of(k)) for k, v in messages.items()}
            deadline = time.monotonic() + 10
            while any(w.get_publication_matched_status().current_count == 0 for w in writers.values()):
                assert time.monotonic() < deadline, "the reader process was not discovered on loopback"
                time.sleep(0.01)
            for _ in range(3):  # best-effort topics: a repeat covers a sample lost before the reader was ready
                for k, v in messages.items():
                    writers[k].write(v)
                time.sleep(0.05)
            out, err = child.communicate(timeout=30)
    finally:
        child.kill()
    received = json.loads(out.strip().splitlines()[-1])
    for k, v in messages.items():
        assert topic_of(k) in received, f"{k}: nothing received ({err[-500:]})"
        assert type(v).deserialize(bytes.fromhex(received[topic_of(k)])) == v, f"{k}: received a different message"
