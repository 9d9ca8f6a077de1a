"""The episode log: one JSONL file per episode, a versioned schema written by the server and read
by scoring (``brave6d.evaluation.metrics``) through :func:`read_episode_log`.

``<log_dir>/<episode_id>.jsonl`` holds one record per line, each time-stamped (UTC, ISO 8601):

* ``reset`` (always the first line, carries :data:`LOG_FORMAT_VERSION` as ``format_version``): the
  target, image size, ``K``, seed, start pose and the target's first ground truth;
* ``set_pose`` / ``move``: the request, the poses before and after, refusal, counters, timings;
* ``submit``: the estimates and everything scoring needs that only the server knows about the
  final view (pose, ``K``, size, depth file beside the log, every object's ground truth);
* ``close``: the totals;
* ``digest`` (version 4, last): the keyed digest of every line before it
  (:mod:`brave6d.serve.log_digest`), written when the episode closes.

Version 1 is the format the server has written since the first release; logs written before
the version field existed carry no ``format_version`` and are exactly version 1, so they are
read as version 1. Version 2 adds the served scene to ``reset`` (``scene``: its name on the
server, ``scene_id``: its BOP scene id in a release, else null), since one server may serve
every scene of a release; a version-1 log reads with both null. Version 3 adds the submit's
``final_view.depth_source``: the geometry the final depth (VSD's test depth) and the visible
fractions were measured on, ``"reference"`` (the bundle's reference geometry) or ``"splat"`` (a
bundle without one); older logs read with None, which means the splat. Version 4 adds the mode the
server ran in (``reset``'s ``mode``: ``"scored"``, where no ground truth reached the agent, or
``"training"``; older logs read with None: their servers served the truth, so they count as
training), the SHA-256 of the final depth image (``final_view.depth_sha256``) and the closing
``digest`` record. Any other version is refused with the file and line. A line that does not
match the schema is an error naming the file, the line and the field; a partial last line (the
server stopped mid-write) is ignored.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import operator
import os
import time as _time
from pathlib import Path
from typing import IO, Annotated, Any, Literal

import numpy as np
from pydantic import Field, TypeAdapter, ValidationError

from brave6d.core.errors import DataError, validation_error_field
from brave6d.core.json_input import JsonInputError, parse_json
from brave6d.serve.log_digest import LogKey, SignedDigest, digest_record_json
from brave6d.serve.modes import Mode
from brave6d.serve.schema import Finite, Matrix3, Matrix4, ObjectState, TargetRef, Vector3, WireModel, matrix_type

#: A rotation as an array, written as 9 numbers row-major (as the log has always held it).
Rotation9 = matrix_type(3, 3, flat=True)

#: The version every new log is written in (the ``format_version`` of its ``reset`` record).
LOG_FORMAT_VERSION = 4
#: The versions :func:`read_episode_log` reads.
READABLE_VERSIONS = (1, 2, 3, 4)
#: File name (beside the log) of the depth image of the view an episode's estimates refer to.
FINAL_DEPTH_SUFFIX = "_final_depth.png"


_last_stamp: tuple[int, str] = (-1, "")


def _now() -> str:
    """The time now (UTC, ISO 8601, milliseconds); the string made once per millisecond."""
    global _last_stamp
    ns = _time.time_ns()
    ms = ns // 1_000_000
    last = _last_stamp
    if last[0] == ms:
        return last[1]
    stamp = (_dt.datetime.fromtimestamp(ms // 1000, _dt.timezone.utc).replace(microsecond=ms % 1000 * 1000)
             .isoformat(timespec="milliseconds"))
    _last_stamp = (ms, stamp)
    return stamp


class _Record(WireModel):
    """Common to every record: written with the time it was made; unknown fields are refused."""

    model_config = WireModel.model_config | {"extra": "forbid"}

    time: str = Field(default_factory=_now)


class ResetRecord(_Record):
    event: Literal["reset"] = "reset"
    format_version: int = LOG_FORMAT_VERSION
    episode_id: str
    bundle: str | None
    agent: str | None
    target: TargetRef
    #: the scene's name on the server and its BOP scene_id (version 2; None in version-1 logs)
    scene: str | None = None
    scene_id: int | None = None
    width: int
    height: int
    K: Matrix3
    seed: int | None
    start: Literal["given", "random"]
    world_T_cam: Matrix4
    timings_ms: dict[str, float]
    #: the target's ground truth in this view (None when the view has no target)
    target_cam_T_obj: Matrix4 | None = None
    target_visib_fract: Finite | None = None
    #: the server's mode (version 4; None in older logs, whose servers served the ground truth)
    mode: Mode | None = None


class ActionRecord(_Record):
    """A ``set_pose`` or ``move``: accepted (the camera moved; ``collided`` when a move stopped
    part-way) or refused (the camera stayed; ``refusal`` says why)."""

    event: Literal["set_pose", "move"]
    step: int
    accepted: bool
    collided: bool
    refusal: dict[str, Any] | None
    requested: dict[str, Any]
    world_T_cam_before: Matrix4
    world_T_cam: Matrix4
    adjustments: int
    move: dict[str, Any] | None
    timings_ms: dict[str, float]
    target_cam_T_obj: Matrix4 | None = None
    target_visib_fract: Finite | None = None


class LoggedEstimate(WireModel):
    """One submitted estimate: ``cam_T_obj`` of ``obj_id`` in the final view's camera frame
    (``R`` 3x3, ``t_m`` metres), with a confidence ``score``."""

    obj_id: int
    R: Rotation9
    t_m: Vector3
    score: Finite = 1.0


class FinalView(WireModel):
    """The view the estimates refer to; ``depth_file`` (uint16 PNG in ``depth_unit``) lies beside the log."""

    world_T_cam: Matrix4
    K: Matrix3
    width: int
    height: int
    depth_file: str | None
    depth_unit: Literal["mm"] = "mm"
    #: what the depth file was measured on (version 3; None in older logs: the splat)
    depth_source: Literal["reference", "splat"] | None = None
    #: SHA-256 of the depth file (version 4; covered by the log's digest)
    depth_sha256: str | None = None


class SubmitRecord(_Record):
    event: Literal["submit"] = "submit"
    episode_id: str
    agent: str | None
    bundle: str | None
    bundle_root: str | None
    target: TargetRef
    estimates: list[LoggedEstimate]
    final_view: FinalView
    objects: list[ObjectState]
    adjustments: int
    steps: int
    refusals: int
    collisions: int
    elapsed_s: Finite | None


class CloseRecord(_Record):
    event: Literal["close"] = "close"
    reason: str
    steps: int
    adjustments: int
    refusals: int
    collisions: int
    duration_s: float
    render_ms_median: float | None
    world_T_cam: Matrix4


class DigestRecord(_Record):
    """The log's last line (version 4): the keyed digest of every line before it, see
    :mod:`brave6d.serve.log_digest` (``key_id`` names the key without revealing it)."""

    event: Literal["digest"] = "digest"
    algorithm: Literal["hmac-sha256"] = "hmac-sha256"
    key_id: str
    lines: int
    digest: str

    def signed(self) -> SignedDigest:
        return SignedDigest(self.key_id, self.lines, self.digest)


AnyRecord = ResetRecord | ActionRecord | SubmitRecord | CloseRecord | DigestRecord
LogRecord = Annotated[AnyRecord, Field(discriminator="event")]
_RECORD = TypeAdapter(LogRecord)


# ----------------------------------------------------------------------------- writing
#: ``json.dumps(..., allow_nan=False)``'s encoder, made once (``dumps`` with an argument makes one a call:
#: 40 us against 28 to encode a step's line here); stateless between calls, so threads share it
_LINE_ENCODER = json.JSONEncoder(allow_nan=False)


def _unencodable(value: Any) -> Any:
    raise TypeError(f"Object of type {value.__class__.__name__} is not JSON serializable")


#: the C encoder behind :data:`_LINE_ENCODER`'s ``encode``, made once (its ``encode`` makes one a call: 1 us
#: of a 1.5 us small field); the same output (no circular check: a server's values hold no cycles, and
#: one would end in RecursionError)
_C_ENCODER = (None if json.encoder.c_make_encoder is None else json.encoder.c_make_encoder(
    None, _unencodable, json.encoder.encode_basestring_ascii, None, ": ", ", ", False, False, False))


def _encode(value: Any) -> str:
    """``_LINE_ENCODER.encode(value)``, through the encoder made once when the C one exists."""
    if _C_ENCODER is None:
        return _LINE_ENCODER.encode(value)
    return "".join(_C_ENCODER(value, 0))


def format_record(record: AnyRecord) -> str:
    """One JSONL line of ``record`` (``ValueError`` for a value that is not finite, so that a step
    can format its record before it changes anything)."""
    return _LINE_ENCODER.encode(record.model_dump(mode="json")) + "\n"


#: JSON of recently written 4x4 matrices, by their float64 bytes: a step's ``world_T_cam_before`` is the
#: previous step's ``world_T_cam`` (a refused one's both), and a float's shortest repr is most of a line's cost
_MATRIX_JSON: dict[bytes, str] = {}
_MATRIX_JSON_MAX = 4096


def _matrix_json(value: Any, field: str) -> str:
    """A 4x4 matrix field's JSON, as ``Matrix4`` serialises it (nested lists of floats) and the line's
    encoder writes it; ``ValueError`` naming the field for another size or a value that is not finite."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.size != 16:
        raise ValueError(f"{field}: must be a 4x4 matrix (16 numbers), got {arr.size}")
    key = arr.tobytes()
    text = _MATRIX_JSON.get(key)
    if text is None:
        try:
            text = _encode(arr.reshape(4, 4).tolist())
        except ValueError:
            raise ValueError(f"{field}: must be finite (NaN and inf are refused)") from None
        if len(_MATRIX_JSON) >= _MATRIX_JSON_MAX:
            _MATRIX_JSON.clear()
        _MATRIX_JSON[key] = text
    return text


def format_action(*, event: str, step: int, accepted: bool, collided: bool, refusal: dict[str, Any] | None,
                  requested: dict[str, Any], world_T_cam_before: Any, world_T_cam: Any, adjustments: int,
                  move: dict[str, Any] | None, timings_ms: dict[str, float], target_cam_T_obj: Any = None,
                  target_visib_fract: float | None = None, time: str | None = None) -> str:
    """The JSONL line of the :class:`ActionRecord` with these fields, byte for byte what
    ``format_record(ActionRecord(...))`` writes (tested: any values; the line reads back as a valid
    record), made without building the model: the fields are checked as the model checks them
    (``event``, types, 4x4 finite matrices, finite numbers: ``ValueError`` before anything is written)
    and the line is joined from its fields' JSON as the encoder joins a dict's, a matrix written
    before reused (:data:`_MATRIX_JSON`). Why: the vector env writes one line per agent and step."""
    if event not in ("set_pose", "move"):
        raise ValueError(f"event: must be 'set_pose' or 'move', got {event!r}")
    for name, flag in (("accepted", accepted), ("collided", collided)):
        if not isinstance(flag, (bool, np.bool_)):
            raise ValueError(f"{name}: must be a bool, got {type(flag).__name__}")
    for name, mapping, optional in (("refusal", refusal, True), ("requested", requested, False), ("move", move, True),
                                    ("timings_ms", timings_ms, False)):
        if not (isinstance(mapping, dict) or (optional and mapping is None)):
            raise ValueError(f"{name}: must be a mapping, got {type(mapping).__name__}")
    if target_visib_fract is not None and isinstance(target_visib_fract, (bool, np.bool_)):
        raise ValueError("target_visib_fract: must be a number")
    # the encoder's JSON of each field: ints, bools, null and floats as it writes them (repr), the dicts
    # in two encoder calls, the matrices from _matrix_json
    stamp = f'"{_now()}"' if time is None else _encode(str(time))
    fract = "null"
    if target_visib_fract is not None:
        value = float(target_visib_fract)
        if not math.isfinite(value):
            raise ValueError("target_visib_fract: must be finite (NaN and inf are refused)")
        fract = float.__repr__(value)
    dicts = _encode({"refusal": refusal, "requested": requested})[1:-1]
    more = _encode({"move": move, "timings_ms": {str(k): float(v) for k, v in timings_ms.items()}})[1:-1]
    target = "null" if target_cam_T_obj is None else _matrix_json(target_cam_T_obj, "target_cam_T_obj")
    flags = ("true" if accepted else "false", "true" if collided else "false")
    return (f'{{"time": {stamp}, "event": "{event}", "step": {int.__repr__(operator.index(step))}, '
            f'"accepted": {flags[0]}, "collided": {flags[1]}, {dicts}, '
            f'"world_T_cam_before": {_matrix_json(world_T_cam_before, "world_T_cam_before")}, '
            f'"world_T_cam": {_matrix_json(world_T_cam, "world_T_cam")}, '
            f'"adjustments": {int.__repr__(operator.index(adjustments))}, {more}, '
            f'"target_cam_T_obj": {target}, "target_visib_fract": {fract}}}\n')


class EpisodeLog:
    """Append-only JSONL log of one episode (one flushed line per record; fsync on close).

    ``path`` None: a log that writes nothing (a server started without a log folder). With ``key``,
    every line is fed into the log's keyed digest, and :meth:`close` appends the ``digest`` record.
    """

    def __init__(self, path: Path | None, key: LogKey | None = None) -> None:
        self.path = path
        self._handle: IO[str] | None = None
        self._key = key
        self._mac = key.mac() if key is not None and path is not None else None
        self._lines = 0
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            # newline="\n": the bytes on disk are the ones the digest saw
            self._handle = open(path, "a", encoding="utf-8", newline="\n")  # noqa: SIM115 - kept open

    @property
    def writes(self) -> bool:
        """False for a log without a file: its lines go nowhere, so its callers need not make them."""
        return self._handle is not None

    @staticmethod
    def format(record: ResetRecord | ActionRecord | SubmitRecord | CloseRecord) -> str:
        return format_record(record)

    def append(self, line: str) -> None:
        """Append a line made by :meth:`format` and flush it."""
        if self._handle is None:
            return
        self._handle.write(line)
        self._handle.flush()
        if self._mac is not None:
            self._mac.update(line.encode("utf-8"))
            self._lines += line.count("\n")

    def write(self, record: ResetRecord | ActionRecord | SubmitRecord | CloseRecord) -> None:
        self.append(self.format(record))

    def close(self, sign: bool = True) -> None:
        """Close the file; with a key (and ``sign``), after appending the ``digest`` record."""
        if self._handle is not None:
            if sign and self._mac is not None and self._key is not None:
                record = DigestRecord(**digest_record_json(self._key, self._mac, self._lines))
                self._handle.write(format_record(record))
                self._handle.flush()
                self._mac = None
            try:
                os.fsync(self._handle.fileno())
            except OSError:
                pass
            self._handle.close()
            self._handle = None


# ----------------------------------------------------------------------------- reading
def _first_error(exc: ValidationError) -> str:
    loc, msg = validation_error_field(exc.errors(include_url=False), dotted=True, skip=1)  # skip the record's tag
    return f"field '{loc}': {msg}" if loc else msg


def read_episode_log(path: Path | str) -> list[AnyRecord]:
    """The records of an episode log, validated against the schema of its version.

    Errors (:class:`DataError`) name the file and line: a line that is not JSON (except a partial
    last line, which is ignored), a first record that is not ``reset``, a version this reader does
    not know, a record that does not match the schema, a ``digest`` record that is not the last.
    """
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DataError(f"{p}: episode log not found") from None
    except UnicodeDecodeError as exc:
        raise DataError(f"{p}: not a UTF-8 text file ({exc})") from None
    raws: list[tuple[int, dict[str, Any]]] = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            raw = parse_json(line, f"{p}:{n}")  # the one JSON reader: size, depth and number limits
        except JsonInputError as exc:
            if n == len(lines) and exc.syntax:  # a partial last line: the server was stopped mid-write
                break
            raise
        if not isinstance(raw, dict):
            raise DataError(f"{p}:{n}: a record must be a JSON object")
        raws.append((n, raw))
    if raws:
        _check_header(raws[0][1], p, raws[0][0])
    records: list[AnyRecord] = []
    for n, raw in raws:
        if records and isinstance(records[-1], DigestRecord):
            raise DataError(f"{p}:{n}: a record after the log's 'digest' record: lines were added after the "
                            "server closed the log")
        try:
            records.append(_RECORD.validate_python(raw))
        except ValidationError as exc:
            raise DataError(f"{p}:{n}: '{raw.get('event')}' record does not match the episode log schema "
                            f"(version {LOG_FORMAT_VERSION}): {_first_error(exc)}") from None
    if not records:
        raise DataError(f"{p}: empty episode log")
    return records


def _check_header(raw: dict[str, Any], path: Path, line: int) -> None:
    if raw.get("event") != "reset":
        raise DataError(f"{path}:{line}: not an episode log (the first record must be a 'reset' event, "
                        f"got {raw.get('event')!r})")
    version = raw.get("format_version", 1)  # logs written before the field existed are version 1
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        raise DataError(f"{path}:{line}: episode log format version {version!r} is not supported (this reader "
                        f"reads version {', '.join(map(str, READABLE_VERSIONS))}); score it with the brave6d "
                        "release that wrote it")
