"""Protocol messages: JSON objects (state, commands, info, truth) and the binary frame envelope.

Every message carries ``"v": PROTOCOL_VERSION`` and ``"type"``. JSON messages are UTF-8 objects
with exactly the fields of their dataclass (plus ``v`` and ``type``); a field with a default (only
fields added after the first logs: ``State``'s lease fields, ``FrameMeta.stamp_std``) may be absent
and then takes its default. A frame is::

    b"NAOF" | version: u8 | meta_len: u32 little-endian | meta JSON (FrameMeta) | JPEG bytes

Decoding is strict and every rejection raises :class:`ProtocolError` with a ``reason`` from
:data:`REASONS` (what the bridge counts) and a detail naming the field. Checks, in order: size,
magic and version byte (frames), UTF-8 and JSON syntax, NaN/Infinity (not JSON, but Python's
parser accepts them), ``v``, ``type``, missing and unknown fields, then types and ranges of the
values through the project's strict converter (``nao_core.config.from_mapping``) with the
``bounds`` declared on each field. Protocol bounds are wide sanity limits; clamping to the robot's
limits is the bridge's job, after decoding. Whatever else goes wrong inside the decoder on hostile
input (``RecursionError`` from deep nesting, ``ValueError`` from an integer of more than 4,300
digits, ``OverflowError`` from an integer too large for a float) is a ``ProtocolError`` too:
nothing but ProtocolError ever leaves :func:`decode`, :func:`decode_any` or :func:`decode_frame`.

Commands carry the ``lease`` the bridge granted to the one station that owns the robot
(``lease.request`` / ``lease.reply`` on the ``lease`` queryable, docs/protocol.md).
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from dataclasses import dataclass, field
from typing import (
    Any,
    ClassVar,
    Dict,
    Literal,
    NamedTuple,
    Optional,
    Tuple,
    Type,
    TypeVar,
    Union,
)

from nao_core.config import ConfigError, bounds, from_mapping
from nao_core.protocol.schema import message_schema
from nao_core.robot_model import CameraIntrinsics, RobotModel

PROTOCOL_VERSION = 1
MAX_JSON_BYTES = 64 * 1024
MAX_META_BYTES = 8 * 1024
MAX_FRAME_BYTES = 8 * 1024 * 1024
MAX_SEQ = 2**53 - 1  # exact in every JSON implementation
MAX_ID_CHARS = 64  # station ids and lease secrets (hex)
FRAME_MAGIC = b"NAOF"
_FRAME_HEADER = struct.Struct("<4sBI")
_JPEG_SOI = b"\xff\xd8"

REASONS = (
    "oversize",  # payload larger than the limit for its kind
    "magic",  # frame does not start with FRAME_MAGIC
    "version",  # frame version byte or "v" is not PROTOCOL_VERSION
    "encoding",  # not UTF-8, not JSON, not an object, truncated frame, not JPEG
    "type",  # "type" missing, unknown or not the one expected on this key
    "missing_field",
    "unknown_field",
    "non_finite",  # NaN or +-Infinity anywhere
    "bad_value",  # wrong JSON type or out of the protocol bounds
)

Pose2 = Tuple[float, float, float]
Matrix4 = Tuple[
    float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float,
]  # fmt: skip


class ProtocolError(ValueError):
    """A message was rejected; ``reason`` is one of REASONS, the message names what was wrong."""

    def __init__(self, reason: str, detail: str):
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class WalkCommand:
    """Walk at (vx, vy, omega) until ``ttl`` seconds after arrival (clock-independent).

    The forward speed is ``vx``, not ``v``: ``v`` is every message's protocol version.
    """

    TYPE: ClassVar[str] = "cmd.walk"
    seq: int = field(metadata=bounds(0, MAX_SEQ))  # strictly increasing per station session
    vx: float = field(metadata=bounds(-1.0, 1.0))  # forward, m/s
    vy: float = field(metadata=bounds(-1.0, 1.0))  # left, m/s (0 for unicycle walking)
    omega: float = field(metadata=bounds(-5.0, 5.0))  # counter-clockwise, rad/s
    ttl: float = field(metadata=bounds(0.0, 10.0))  # s after arrival
    lease: str  # the secret of the station's lease (LeaseReply.lease)


@dataclass(frozen=True)
class HeadCommand:
    """Move the head to (yaw, pitch) at a fraction of the maximum joint speed."""

    TYPE: ClassVar[str] = "cmd.head"
    seq: int = field(metadata=bounds(0, MAX_SEQ))
    yaw: float = field(metadata=bounds(-3.2, 3.2))  # rad
    pitch: float = field(metadata=bounds(-3.2, 3.2))  # rad, down > 0 (NAO HeadPitch)
    speed: float = field(metadata=bounds(0.01, 1.0))  # fraction of the maximum speed
    lease: str  # the secret of the station's lease (LeaseReply.lease)


@dataclass(frozen=True)
class LeaseRequest:
    """Asked on the bridge's ``lease`` queryable: take the robot (first come) or hand it back.

    ``station`` is the id in the station's liveliness token ``station/alive/<station>``: the
    lease lives as long as that token. Taking the lease is also how a station re-arms the robot
    after ``station_lost``.
    """

    TYPE: ClassVar[str] = "lease.request"
    op: Literal["take", "release"]
    station: str  # 1-64 characters from [0-9a-z]
    lease: str  # "" to take; the secret to release


@dataclass(frozen=True)
class LeaseReply:
    """The bridge's answer: ``granted`` with the secret that commands must carry, or the reason not."""

    TYPE: ClassVar[str] = "lease.reply"
    granted: bool
    lease: str  # the secret ("" when refused or released)
    reason: str  # "granted", "released", "held" (another station owns it), "no_token", "bad_lease"


Watchdog = Literal[
    "idle", "walking", "deadman", "fallen", "station_lost", "shutdown", "stop_failed", "no_robot_watchdog"
]


@dataclass(frozen=True)
class State:
    """The robot's state, published by the bridge at 10-50 Hz."""

    TYPE: ClassVar[str] = "state"
    stamp: float = field(metadata=bounds(0.0))  # bridge clock (nao_core.clock.now()), s
    odom: Pose2  # odometry pose (x, y, theta), m, rad
    head_yaw: float
    head_pitch: float
    walking: bool
    fallen: bool  # latched: walk commands are refused once fallen
    battery: Optional[float] = field(metadata=bounds(0.0, 1.0))  # charge fraction, None when the robot gives none
    cmd_age: Optional[float] = field(metadata=bounds(0.0))  # s since the last accepted walk command
    watchdog: Watchdog  # why the robot is (not) walking
    rejected: Dict[str, int] = field(metadata=bounds(0))  # malformed messages per ProtocolError reason
    ignored: Dict[str, int] = field(metadata=bounds(0))  # valid commands not acted on, per cause
    # Added with the lease and confirmed stops (issue 14). The bridge always sends them; a state
    # recorded before (an older log) lacks them and decodes with these defaults: no owner, no stop
    # failure, no robot-side watchdog ("off").
    owner: Optional[str] = None  # station id holding the lease, None when nobody does
    stop_failures: int = field(default=0, metadata=bounds(0))  # stop attempts that failed or were not confirmed
    robot_watchdog: Literal["off", "ok", "missing"] = "off"  # the watchdog process on the robot (nao_bridge.watchdog)


@dataclass(frozen=True)
class FrameMeta:
    """What was measured at a frame's capture time (the frame envelope's JSON part)."""

    TYPE: ClassVar[str] = "frame"
    seq: int = field(metadata=bounds(0, MAX_SEQ))
    stamp: float = field(metadata=bounds(0.0))  # capture time, bridge clock, s
    width: int = field(metadata=bounds(1, 8192))
    height: int = field(metadata=bounds(1, 8192))
    encoding: Literal["jpeg"]
    head_yaw: float
    head_pitch: float
    T_BC: Matrix4  # camera in robot at capture, optical convention, row by row
    odom: Pose2  # odometry pose at capture
    resolution: str  # camera resolution name in the robot model, e.g. "vga"
    # s, how far the stamp may be from the instant the image shows (docs/frames.md); 0 in logs before it
    stamp_std: float = field(default=0.0, metadata=bounds(0.0, 10.0))


@dataclass(frozen=True)
class Info:
    """The bridge's answer on the ``info`` queryable."""

    TYPE: ClassVar[str] = "info"
    bridge_version: str
    backend: str  # "naoqi" or "sim"
    robot: RobotModel  # model name, camera, head and walk limits (``from_mapping(RobotModel, ...)``)
    resolution: str
    intrinsics: CameraIntrinsics  # of ``resolution``
    fps: float = field(metadata=bounds(0.0))
    state_rate_hz: float = field(metadata=bounds(0.0))
    deadman_s: float = field(metadata=bounds(0.0))


Vector3 = Tuple[float, float, float]
Row4 = Tuple[float, float, float, float]


@dataclass(frozen=True)
class TruthPart:
    shape: str  # "cylinder" or "box"
    centre: Vector3  # in the object frame, m
    size: Vector3  # cylinder (diameter, diameter, height), box extents, m
    yaw: float


@dataclass(frozen=True)
class TruthObject:
    kind: str  # "cylinder", "box", "composite"
    centre: Tuple[float, float]  # on the floor, world, m
    yaw: float
    radius: float  # smallest vertical cylinder about the centre that holds the object, m
    height: float
    parts: Tuple[TruthPart, ...]


@dataclass(frozen=True)
class TruthCamera:
    stamp: float  # capture time of the last rendered frame, bridge clock
    T_WC: Tuple[Row4, Row4, Row4, Row4]  # true camera pose in the world, optical convention


@dataclass(frozen=True)
class Truth:
    """Simulator ground truth (``SimWorld.truth()``; tests and reports only, never the estimator)."""

    TYPE: ClassVar[str] = "sim.truth"
    scenario: str
    seed: int
    stamp: float = field(metadata=bounds(0.0))
    robot_pose: Pose2  # true robot pose in the world
    odom_origin: Pose2  # world pose where odometry reads (0, 0, 0)
    odom: Pose2  # what odometry reports
    speed_scale: Vector3  # per-run walking speed scale errors
    fallen: bool
    camera: Optional[TruthCamera]  # None before the first frame
    object: TruthObject


MESSAGE_TYPES: Dict[str, Type[Any]] = {
    c.TYPE: c for c in (WalkCommand, HeadCommand, LeaseRequest, LeaseReply, State, FrameMeta, Info, Truth)
}
M = TypeVar("M")


class Frame(NamedTuple):
    meta: FrameMeta
    meta_json: bytes  # as received: what the station logs
    jpeg: bytes


def json_schema(cls: type) -> Dict[str, Any]:
    """The JSON Schema of a message class (for MCAP channels with encoding ``jsonschema``)."""
    return message_schema(cls, PROTOCOL_VERSION)


def to_dict(message: Any) -> Dict[str, Any]:
    return {"v": PROTOCOL_VERSION, "type": message.TYPE, **dataclasses.asdict(message)}


def encode(message: Any) -> bytes:
    """Compact UTF-8 JSON of a message (raises ValueError on NaN/inf: never sent)."""
    return json.dumps(to_dict(message), separators=(",", ":"), allow_nan=False).encode("utf-8")


def decode(payload: Union[bytes, bytearray, memoryview], cls: Type[M]) -> M:
    """Strictly decode a JSON message of class ``cls`` (raises ProtocolError)."""
    if len(payload) > MAX_JSON_BYTES:
        raise ProtocolError("oversize", f"{cls.TYPE}: {len(payload)} bytes > {MAX_JSON_BYTES}")
    return _guarded(bytes(payload), cls)


def decode_any(payload: Union[bytes, bytearray, memoryview]) -> Any:
    """Decode a JSON message of whatever type it declares (raises ProtocolError)."""
    if len(payload) > MAX_JSON_BYTES:
        raise ProtocolError("oversize", f"{len(payload)} bytes > {MAX_JSON_BYTES}")
    return _guarded(bytes(payload), None)


def encode_frame(meta: FrameMeta, jpeg: bytes) -> bytes:
    meta_json = encode(meta)
    return _FRAME_HEADER.pack(FRAME_MAGIC, PROTOCOL_VERSION, len(meta_json)) + meta_json + jpeg


def decode_frame(payload: Union[bytes, bytearray, memoryview]) -> Frame:
    """Strictly decode a frame envelope (raises ProtocolError)."""
    data = bytes(payload)
    if len(data) > MAX_FRAME_BYTES:
        raise ProtocolError("oversize", f"frame: {len(data)} bytes > {MAX_FRAME_BYTES}")
    if len(data) < _FRAME_HEADER.size:
        raise ProtocolError("encoding", f"frame: {len(data)} bytes, shorter than the {_FRAME_HEADER.size}-byte header")
    magic, version, meta_len = _FRAME_HEADER.unpack_from(data)
    if magic != FRAME_MAGIC:
        raise ProtocolError("magic", f"frame: starts with {magic!r}, expected {FRAME_MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise ProtocolError("version", f"frame: version byte {version}, expected {PROTOCOL_VERSION}")
    if meta_len > MAX_META_BYTES:
        raise ProtocolError("oversize", f"frame: meta length {meta_len} > {MAX_META_BYTES}")
    start = _FRAME_HEADER.size
    if start + meta_len > len(data):
        raise ProtocolError("encoding", f"frame: meta length {meta_len} runs past the end ({len(data)} bytes)")
    meta_json = data[start : start + meta_len]
    meta = _guarded(meta_json, FrameMeta)
    jpeg = data[start + meta_len :]
    if not jpeg.startswith(_JPEG_SOI):
        raise ProtocolError("encoding", "frame: image bytes do not start with a JPEG start-of-image marker")
    return Frame(meta, meta_json, jpeg)


def _reject_constant(name: str) -> float:
    raise ProtocolError("non_finite", f"{name} is not a finite number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ProtocolError("non_finite", f"{text[:20]} overflows to {value}")
    return value


def _guarded(data: bytes, cls: Optional[type]) -> Any:
    """:func:`_from_json`, with every other exception of the parser and converter as a ProtocolError."""
    expected = cls.TYPE if cls is not None else "message"
    try:
        return _from_json(data, cls)
    except ProtocolError:
        raise
    except RecursionError:
        raise ProtocolError("encoding", f"{expected}: nested too deeply") from None
    except (OverflowError, ValueError, TypeError, ArithmeticError) as exc:
        raise ProtocolError("bad_value", f"{expected}: {type(exc).__name__}: {str(exc)[:100]}") from None


def _from_json(data: bytes, cls: Optional[type]) -> Any:
    expected = cls.TYPE if cls is not None else "message"
    try:
        obj = json.loads(data.decode("utf-8"), parse_constant=_reject_constant, parse_float=_finite_float)
    except UnicodeDecodeError as exc:
        raise ProtocolError("encoding", f"{expected}: not UTF-8 ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise ProtocolError("encoding", f"{expected}: not JSON ({exc.msg} at char {exc.pos})") from None
    if not isinstance(obj, dict):
        raise ProtocolError("encoding", f"{expected}: expected a JSON object, got {type(obj).__name__}")
    version = obj.pop("v", None)
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError("version", f"{expected}: v is {version!r}, expected {PROTOCOL_VERSION}")
    kind = obj.pop("type", None)
    if cls is None:
        if not isinstance(kind, str) or kind not in MESSAGE_TYPES:
            raise ProtocolError("type", f"type {kind!r} is not one of {sorted(MESSAGE_TYPES)}")
        cls = MESSAGE_TYPES[kind]
    elif kind != cls.TYPE:
        raise ProtocolError("type", f"type {kind!r}, expected {cls.TYPE!r}")
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    required = {f.name for f in dataclasses.fields(cls)
                if f.init and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    missing = sorted(required - set(obj))
    if missing:
        raise ProtocolError("missing_field", f"{cls.TYPE}: missing {', '.join(missing)}")
    unknown = sorted(set(obj) - names)
    if unknown:
        raise ProtocolError("unknown_field", f"{cls.TYPE}: unknown {', '.join(map(str, unknown))}")
    try:
        message = from_mapping(cls, obj, source=cls.TYPE)
    except ConfigError as exc:
        raise ProtocolError("bad_value", str(exc)[:200]) from None
    for name in ("lease", "station"):
        value = getattr(message, name, "")
        if value and (len(value) > MAX_ID_CHARS or not (value.isascii() and value.isalnum())):
            raise ProtocolError("bad_value", f"{cls.TYPE}: {name} must be at most {MAX_ID_CHARS} letters or digits")
    return message
