"""The RTDE wire format (Universal Robots' Real-Time Data Exchange, protocol version 2), server side.

Owns everything about RTDE bytes: the 3-byte header (uint16 size including the header, uint8
type, big-endian), the message types, the controller's variable table (names and types, as UR's
RTDE guide lists them), recipe setup (ids handed out 1, 2, ... in order, as a controller does; a
name the controller does not know answers ``NOT_FOUND``, an input another connection already
writes answers ``IN_USE``) and the packing of data packages. Every read is bounded: a message is
at most 65535 bytes by construction, a recipe at most :data:`MAX_RECIPE_FIELDS` names, and a
data package must have exactly its recipe's size.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

PROTOCOL_VERSION = 2
HEADER = struct.Struct(">HB")
MAX_MESSAGE = 65535
#: No controller recipe comes near this; a longer name list is refused, not parsed further.
MAX_RECIPE_FIELDS = 256
#: The highest output frequency an e-Series controller serves (Hz).
MAX_FREQUENCY_HZ = 500.0

# message types (ASCII letters, as in UR's guide)
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")
MESSAGE_NAMES = {REQUEST_PROTOCOL_VERSION: "request protocol version", GET_URCONTROL_VERSION: "get urcontrol version",
                 TEXT_MESSAGE: "text message", DATA_PACKAGE: "data package", SETUP_OUTPUTS: "setup outputs",
                 SETUP_INPUTS: "setup inputs", START: "start", PAUSE: "pause"}

# value types: struct format and the name the controller answers with
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}


def _outputs() -> dict[str, str]:
    table = {
        "timestamp": "DOUBLE", "target_q": "VECTOR6D", "target_qd": "VECTOR6D", "target_qdd": "VECTOR6D",
        "target_current": "VECTOR6D", "target_moment": "VECTOR6D", "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D",
        "actual_current": "VECTOR6D", "joint_control_output": "VECTOR6D", "actual_TCP_pose": "VECTOR6D",
        "actual_TCP_speed": "VECTOR6D", "actual_TCP_force": "VECTOR6D", "target_TCP_pose": "VECTOR6D",
        "target_TCP_speed": "VECTOR6D", "actual_digital_input_bits": "UINT64", "joint_temperatures": "VECTOR6D",
        "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
        "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE",
        "actual_joint_voltage": "VECTOR6D", "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
        "safety_status_bits": "UINT32", "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
        "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE", "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
        "tool_mode": "UINT32", "tool_analog_input_types": "UINT32", "tool_analog_input0": "DOUBLE",
        "tool_analog_input1": "DOUBLE", "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE", "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32", "ft_raw_wrench": "VECTOR6D", "payload": "DOUBLE",
        "payload_cog": "VECTOR3D", "payload_inertia": "VECTOR6D", "script_control_line": "UINT32",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    }
    for i in range(48):
        table[f"output_int_register_{i}"] = "INT32"
        table[f"output_double_register_{i}"] = "DOUBLE"
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


def _inputs() -> dict[str, str]:
    table = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE", "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8", "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8", "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(48):
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


#: What a controller can send (name -> type).
OUTPUT_TYPES: dict[str, str] = _outputs()
#: What a client may write (name -> type).
INPUT_TYPES: dict[str, str] = _inputs()

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")


class ProtocolError(Exception):
    """A client broke the RTDE protocol (the connection is refused or closed, naming why)."""


@dataclass(frozen=True)
class Recipe:
    """A set-up recipe: its id, the variable names and their types, and its packed size."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in self.types))

    @property
    def size(self) -> int:
        return self.struct.size

    def unpack(self, payload: bytes) -> dict[str, Any]:
        """Values of a data package's payload (without the recipe id byte); exact size required."""
        if len(payload) != self.size:
            raise ProtocolError(f"data package for recipe {self.recipe_id} has {len(payload)} bytes, its recipe "
                                f"({len(self.names)} fields) needs {self.size}")
        flat = list(self.struct.unpack(payload))
        out: dict[str, Any] = {}
        for name, typ in zip(self.names, self.types):
            n = _count(typ)
            out[name] = flat[0] if n == 1 else flat[:n]
            del flat[:n]
        return out

    def pack(self, values: Mapping[str, Any]) -> bytes:
        """A data package's payload (recipe id byte first) from ``values`` (every name required)."""
        flat: list[Any] = []
        for name, typ in zip(self.names, self.types):
            v = values[name]
            if _count(typ) == 1:
                flat.append(v)
            else:
                flat.extend(v)
        return bytes([self.recipe_id]) + self.struct.pack(*flat)


def _count(typ: str) -> int:
    fmt = TYPE_FORMATS[typ]
    return int(fmt[:-1]) if len(fmt) > 1 else 1


def frame(msg_type: int, payload: bytes = b"") -> bytes:
    """One RTDE message: header + payload."""
    size = HEADER.size + len(payload)
    if size > MAX_MESSAGE:
        raise ProtocolError(f"message of {size} bytes exceeds RTDE's {MAX_MESSAGE}")
    return HEADER.pack(size, msg_type) + payload


def parse_header(header: bytes) -> tuple[int, int]:
    """(payload length, message type) of a 3-byte header; refuses sizes below the header's own."""
    size, msg_type = HEADER.unpack(header)
    if size < HEADER.size:
        raise ProtocolError(f"message header claims {size} bytes, less than the header itself")
    return size - HEADER.size, msg_type


def split_names(payload: bytes) -> list[str]:
    """The comma-separated variable names of a setup request (a trailing comma, as ur-rtde sends, is fine)."""
    try:
        text = payload.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("recipe names are not ASCII") from None
    names = text.split(",")
    if names and names[-1] == "":
        names.pop()
    if not names:
        raise ProtocolError("recipe with no variable names")
    if len(names) > MAX_RECIPE_FIELDS:
        raise ProtocolError(f"recipe with {len(names)} names (at most {MAX_RECIPE_FIELDS})")
    return names


def resolve(names: Sequence[str], table: Mapping[str, str], in_use: Iterable[str] = ()) -> list[str]:
    """The controller's answer per name: its type, ``NOT_FOUND`` or (inputs) ``IN_USE``."""
    busy = set(in_use)
    out = []
    for name in names:
        if not _NAME.match(name) or name not in table:
            out.append("NOT_FOUND")
        elif name in busy:
            out.append("IN_USE")
        else:
            out.append(table[name])
    return out


def text_message(message: str, source: str = "brave6d-ur-emulator", level: int = 3) -> bytes:
    """A protocol-2 text message (level 0 exception, 1 error, 2 warning, 3 info)."""
    m = message.encode("ascii", "replace")[:255]
    s = source.encode("ascii", "replace")[:255]
    return frame(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


def controller_version_payload(version: tuple[int, int, int, int]) -> bytes:
    return struct.pack(">IIII", *version)


def output_setup_request(payload: bytes) -> tuple[float, list[str]]:
    """(frequency, names) of a protocol-2 output setup request."""
    if len(payload) < 8:
        raise ProtocolError("output setup without its 8-byte frequency")
    (frequency,) = struct.unpack(">d", payload[:8])
    if not (0.0 < frequency <= MAX_FREQUENCY_HZ):
        raise ProtocolError(f"output frequency {frequency!r} Hz outside (0, {MAX_FREQUENCY_HZ:g}]")
    return frequency, split_names(payload[8:])
