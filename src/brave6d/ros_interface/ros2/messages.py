"""ROS 2 message types as Cyclone DDS ``IdlStruct`` dataclasses, byte-compatible with ROS 2.

ROS 2 (through ``rmw_cyclonedds_cpp`` and the other DDS RMWs) puts a message ``pkg/msg/Name`` on
the wire as the DDS type ``pkg::msg::dds_::Name_`` in plain CDR (XCDR1, final extensibility,
little-endian encapsulation ``00 01 00 00``), with no XTypes type information: endpoints match on
the type name alone. Each class below declares that exact type name and the fields of the
message definition in their order with their CDR types, so an ``rclpy`` node sees standard
messages. ``tests/test_ros2_cdr.py`` checks every class's bytes against ``rosbags``' CDR
serialisation of the same values (Humble and Jazzy definitions).

``Image.data`` (``uint8[]``) is declared ``sequence[uint8]`` (the type object Cyclone announces)
but held as ``bytes``: :class:`Image` writes it in one copy (cyclonedds would pack one Python int
per byte, ~50 ms for a 640x480 RGB image) and reads it back as ``bytes``.

The package ``brave6d_msgs`` (``ObjectEstimate``, ``ObjectEstimateArray``) is ours: its ``.msg``
definitions ship in ``ros_interface/ros2/msg/`` (and are read from there by :data:`CUSTOM_MSG_FILES`).
"""

import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from cyclonedds.idl import IdlStruct
from cyclonedds.idl._support import Endianness
from cyclonedds.idl.types import float64, int32, sequence, uint8, uint32
from cyclonedds.idl.types import array as idl_array


def dds_type_name(ros_type: str) -> str:
    """``'sensor_msgs/msg/Image'`` -> ``'sensor_msgs::msg::dds_::Image_'`` (rmw's DDS type name)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def _zeros(n: int) -> Any:
    return field(default_factory=lambda: [0.0] * n)


# ----------------------------------------------------------------------------- builtin_interfaces
@dataclass
class Time(IdlStruct, typename=dds_type_name("builtin_interfaces/msg/Time")):
    sec: int32 = 0
    nanosec: uint32 = 0


# ----------------------------------------------------------------------------- std_msgs
@dataclass
class Header(IdlStruct, typename=dds_type_name("std_msgs/msg/Header")):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename=dds_type_name("std_msgs/msg/String")):
    data: str = ""


# ----------------------------------------------------------------------------- geometry_msgs
@dataclass
class Point(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Point")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Vector3(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Vector3")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Quaternion")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Pose")):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/PoseStamped")):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class PoseArray(IdlStruct, typename=dds_type_name("geometry_msgs/msg/PoseArray")):
    header: Header = field(default_factory=Header)
    poses: sequence[Pose] = field(default_factory=list)


@dataclass
class Twist(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Twist")):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/TwistStamped")):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class Transform(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Transform")):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/TransformStamped")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


# ----------------------------------------------------------------------------- tf2_msgs
@dataclass
class TFMessage(IdlStruct, typename=dds_type_name("tf2_msgs/msg/TFMessage")):
    transforms: sequence[TransformStamped] = field(default_factory=list)


# ----------------------------------------------------------------------------- sensor_msgs
@dataclass
class Image(IdlStruct, typename=dds_type_name("sensor_msgs/msg/Image")):
    header: Header = field(default_factory=Header)
    height: uint32 = 0
    width: uint32 = 0
    encoding: str = ""
    is_bigendian: uint8 = 0
    step: uint32 = 0
    data: sequence[uint8] = b""  # bytes (see the module docstring)

    def serialize(self, buffer: Any = None, endianness: Any = None, use_version_2: bool | None = None) -> bytes:
        """CDR of this image; ``data`` (the last field) is appended as raw bytes after its length.
        Plain little-endian XCDR1 only (what ROS 2 uses); anything else goes the generic way."""
        if buffer is not None or endianness not in (None, Endianness.Little) or use_version_2:
            return super().serialize(buffer, endianness, use_version_2)
        data = bytes(self.data)
        head = IdlStruct.serialize(replace(self, data=b""))  # ends with the empty sequence's length, 0
        return head[:-4] + struct.pack("<I", len(data)) + data

    @classmethod
    def deserialize(cls, data: bytes, has_header: bool = True, use_version_2: bool | None = None) -> "Image":
        """An image from its CDR; plain little-endian XCDR1 parsed directly (``data`` sliced as
        bytes, no per-byte Python ints), anything else the generic way."""
        if not (has_header and bytes(data[:2]) == b"\x00\x01" and not use_version_2):
            msg = super().deserialize(data, has_header, use_version_2)
            msg.data = bytes(msg.data)
            return msg
        body = memoryview(data)[4:]  # CDR alignment is relative to the end of the encapsulation header
        pos = 0

        def take(fmt: str) -> Any:
            nonlocal pos
            size = struct.calcsize(fmt)
            pos = (pos + size - 1) & ~(size - 1) if size > 1 else pos
            (value,) = struct.unpack_from(fmt, body, pos)
            pos += size
            return value

        def take_string() -> str:
            nonlocal pos
            n = take("<I")
            text = bytes(body[pos:pos + n - 1]).decode("utf-8")
            pos += n
            return text

        sec, nanosec = take("<i"), take("<I")
        frame_id = take_string()
        height, width = take("<I"), take("<I")
        encoding = take_string()
        is_bigendian = take("<B")
        step = take("<I")
        n = take("<I")
        if pos + n > len(body):
            raise ValueError(f"sensor_msgs/Image: data says {n} bytes, only {len(body) - pos} left")
        return cls(Header(Time(sec, nanosec), frame_id), height, width, encoding, is_bigendian, step,
                   bytes(body[pos:pos + n]))


@dataclass
class RegionOfInterest(IdlStruct, typename=dds_type_name("sensor_msgs/msg/RegionOfInterest")):
    x_offset: uint32 = 0
    y_offset: uint32 = 0
    height: uint32 = 0
    width: uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(IdlStruct, typename=dds_type_name("sensor_msgs/msg/CameraInfo")):
    header: Header = field(default_factory=Header)
    height: uint32 = 0
    width: uint32 = 0
    distortion_model: str = ""
    d: sequence[float64] = field(default_factory=list)
    k: idl_array[float64, 9] = _zeros(9)
    r: idl_array[float64, 9] = _zeros(9)
    p: idl_array[float64, 12] = _zeros(12)
    binning_x: uint32 = 0
    binning_y: uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)


# ----------------------------------------------------------------------------- brave6d_msgs (ours)
@dataclass
class ObjectEstimate(IdlStruct, typename=dds_type_name("brave6d_msgs/msg/ObjectEstimate")):
    obj_id: int32 = 0
    pose: Pose = field(default_factory=Pose)
    score: float64 = 0.0


@dataclass
class ObjectEstimateArray(IdlStruct, typename=dds_type_name("brave6d_msgs/msg/ObjectEstimateArray")):
    header: Header = field(default_factory=Header)
    estimates: sequence[ObjectEstimate] = field(default_factory=list)


#: ROS type name of every class above (``rosbags`` and ``ros2 topic`` spell them this way).
ROS_TYPES: dict[type[IdlStruct], str] = {
    Time: "builtin_interfaces/msg/Time", Header: "std_msgs/msg/Header", String: "std_msgs/msg/String",
    Point: "geometry_msgs/msg/Point", Vector3: "geometry_msgs/msg/Vector3",
    Quaternion: "geometry_msgs/msg/Quaternion", Pose: "geometry_msgs/msg/Pose",
    PoseStamped: "geometry_msgs/msg/PoseStamped", PoseArray: "geometry_msgs/msg/PoseArray",
    Twist: "geometry_msgs/msg/Twist", TwistStamped: "geometry_msgs/msg/TwistStamped",
    Transform: "geometry_msgs/msg/Transform", TransformStamped: "geometry_msgs/msg/TransformStamped",
    TFMessage: "tf2_msgs/msg/TFMessage", Image: "sensor_msgs/msg/Image",
    RegionOfInterest: "sensor_msgs/msg/RegionOfInterest", CameraInfo: "sensor_msgs/msg/CameraInfo",
    ObjectEstimate: "brave6d_msgs/msg/ObjectEstimate", ObjectEstimateArray: "brave6d_msgs/msg/ObjectEstimateArray",
}

#: The ``.msg`` definitions of our own package, shipped beside this module.
MSG_DIR = Path(__file__).resolve().parent / "msg"
CUSTOM_MSG_FILES: dict[str, Path] = {
    "brave6d_msgs/msg/ObjectEstimate": MSG_DIR / "ObjectEstimate.msg",
    "brave6d_msgs/msg/ObjectEstimateArray": MSG_DIR / "ObjectEstimateArray.msg",
}


def stamp_from_ns(stamp_ns: int) -> Time:
    """A ``builtin_interfaces/Time`` from integer nanoseconds (REP 103: seconds + nanoseconds)."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_to_ns(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
