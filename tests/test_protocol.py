"""Wire protocol: round trips, strict rejection of every malformed kind, schemas that agree with the decoder."""

from __future__ import annotations

import dataclasses
import json
import struct

import cv2
import jsonschema
import numpy as np
import pytest

from nao_core.config import from_mapping
from nao_core.protocol import (
    FRAME_MAGIC,
    MAX_FRAME_BYTES,
    MAX_JSON_BYTES,
    MESSAGE_TYPES,
    REASONS,
    FrameMeta,
    HeadCommand,
    Info,
    LeaseReply,
    LeaseRequest,
    ProtocolError,
    RobotKeys,
    State,
    Truth,
    WalkCommand,
    decode,
    decode_any,
    decode_frame,
    encode,
    encode_frame,
    json_schema,
    to_dict,
)
from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld

MODEL = load_robot_model()
EYE = tuple(float(x) for x in np.eye(4).ravel())
WORLD = SimWorld("figure", MODEL, resolution="qvga", seed=3)
WORLD.render()
TRUTH = from_mapping(Truth, WORLD.truth())  # what the bridge publishes for the simulator


def samples():
    """One valid message of every type (lease messages last: tests index the others)."""
    return _samples() + [LeaseRequest(op="take", station="27f7", lease=""),
                         LeaseReply(granted=True, lease="0f3a", reason="granted")]


def _samples():
    return [
        WalkCommand(seq=7, vx=0.08, vy=-0.01, omega=0.3, ttl=0.5, lease="0f3a"),
        HeadCommand(seq=3, yaw=0.4, pitch=-0.1, speed=0.2, lease="0f3a"),
        State(
            stamp=1.7e9, odom=(0.1, -0.2, 0.3), head_yaw=0.1, head_pitch=0.05, walking=True, fallen=False,
            battery=0.8, cmd_age=None, watchdog="walking", rejected={"bad_value": 2}, ignored={},
            owner="27f7", stop_failures=0, robot_watchdog="off",
        ),
        FrameMeta(
            seq=1, stamp=1.7e9, width=640, height=480, encoding="jpeg", head_yaw=0.2, head_pitch=0.1,
            T_BC=EYE, odom=(0.0, 0.0, 0.0), resolution="vga", stamp_std=0.008,
        ),
        Info(
            bridge_version="0.1.0", backend="sim", robot=MODEL, resolution="vga",
            intrinsics=MODEL.camera.intrinsics("vga"), fps=15.0, state_rate_hz=20.0, deadman_s=0.3,
        ),
        TRUTH,
    ]


def test_a_state_without_battery_charge_round_trips_and_a_charge_out_of_range_is_refused():
    """A robot that reports no charge (nao_bridge.naoqi_backend) sends ``battery: null``."""
    state = next(m for m in samples() if isinstance(m, State))
    unknown = dataclasses.replace(state, battery=None)
    assert decode(encode(unknown), State) == unknown
    with pytest.raises(ProtocolError, match="battery"):
        decode(encode(state).replace(b'"battery":0.8', b'"battery":1.5'), State)


@pytest.mark.parametrize("message", samples(), ids=lambda m: m.TYPE)
def test_round_trip_is_exact_and_type_checked(message):
    payload = encode(message)
    assert decode(payload, type(message)) == message
    assert decode_any(payload) == message
    other = WalkCommand if not isinstance(message, WalkCommand) else HeadCommand
    with pytest.raises(ProtocolError) as err:
        decode(payload, other)
    assert err.value.reason == "type"


@pytest.mark.parametrize("message", samples(), ids=lambda m: m.TYPE)
def test_encoded_messages_validate_against_their_schema(message):
    schema = json_schema(type(message))
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(json.loads(encode(message)), schema)


def test_schema_and_decoder_agree_on_bounds_and_fields():
    schema = json_schema(WalkCommand)
    good = to_dict(WalkCommand(seq=1, vx=0.0, vy=0.0, omega=0.0, ttl=1.0, lease=""))
    for bad in ({**good, "vx": 1.5}, {**good, "extra": 1}, {k: v for k, v in good.items() if k != "ttl"}, {**good, "v": 2}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)
        with pytest.raises(ProtocolError):
            decode(json.dumps(bad).encode(), WalkCommand)
    assert set(MESSAGE_TYPES) == {"cmd.walk", "cmd.head", "lease.request", "lease.reply", "state", "frame", "info", "sim.truth"}


def walk_dict(**changes):
    data = {"v": 1, "type": "cmd.walk", "seq": 1, "vx": 0.05, "vy": 0.0, "omega": 0.1, "ttl": 0.5, "lease": ""}
    data.update(changes)
    return data


def drop(key):
    data = walk_dict()
    del data[key]
    return data


MALFORMED = [
    ("oversize", b"{" + b" " * MAX_JSON_BYTES + b"}"),
    ("encoding", b"\xff\xfe not utf-8"),
    ("encoding", b'{"v": 1, "type": "cmd.walk"'),
    ("encoding", b"[1, 2, 3]"),
    ("version", json.dumps(walk_dict(v=2)).encode()),
    ("version", json.dumps(walk_dict(v=True)).encode()),
    ("version", json.dumps(drop("v")).encode()),
    ("type", json.dumps(walk_dict(type="cmd.head")).encode()),
    ("type", json.dumps(drop("type")).encode()),
    ("missing_field", json.dumps(drop("omega")).encode()),
    ("unknown_field", json.dumps(walk_dict(speed=1.0)).encode()),
    ("non_finite", b'{"v":1,"type":"cmd.walk","seq":1,"vx":NaN,"vy":0,"omega":0,"ttl":0.5,"lease":""}'),
    ("non_finite", b'{"v":1,"type":"cmd.walk","seq":1,"vx":0,"vy":-Infinity,"omega":0,"ttl":0.5,"lease":""}'),
    ("non_finite", b'{"v":1,"type":"cmd.walk","seq":1,"vx":0,"vy":0,"omega":1e400,"ttl":0.5,"lease":""}'),
    ("bad_value", json.dumps(walk_dict(vx="fast")).encode()),
    ("bad_value", json.dumps(walk_dict(seq=1.5)).encode()),
    ("bad_value", json.dumps(walk_dict(seq=-1)).encode()),
    ("bad_value", json.dumps(walk_dict(vx=True)).encode()),
    ("bad_value", json.dumps(walk_dict(vx=2.0)).encode()),
    ("bad_value", json.dumps(walk_dict(omega=-6.0)).encode()),
    ("bad_value", json.dumps(walk_dict(ttl=-0.1)).encode()),
    ("bad_value", json.dumps(walk_dict(ttl=60.0)).encode()),
]


@pytest.mark.parametrize("reason, payload", MALFORMED, ids=[f"{r}-{i}" for i, (r, _) in enumerate(MALFORMED)])
def test_malformed_walk_commands_are_rejected_with_their_reason(reason, payload):
    assert reason in REASONS
    with pytest.raises(ProtocolError) as err:
        decode(payload, WalkCommand)
    assert err.value.reason == reason


def test_error_names_the_field():
    with pytest.raises(ProtocolError, match="vx"):
        decode(json.dumps(walk_dict(vx=2.0)).encode(), WalkCommand)
    with pytest.raises(ProtocolError, match="omega"):
        decode(json.dumps(drop("omega")).encode(), WalkCommand)
    with pytest.raises(ProtocolError, match="speed"):
        decode(json.dumps({"v": 1, "type": "cmd.head", "seq": 1, "yaw": 0, "pitch": 0, "speed": 0, "lease": ""}).encode(), HeadCommand)


def test_encode_refuses_non_finite_values():
    with pytest.raises(ValueError):
        encode(WalkCommand(seq=1, vx=float("nan"), vy=0.0, omega=0.0, ttl=1.0, lease=""))


def jpeg_of(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", image)
    assert ok
    return buf.tobytes()


def test_frame_round_trip_keeps_meta_bytes_and_image():
    meta = samples()[3]
    image = np.zeros((48, 64, 3), np.uint8)
    image[10:20, 30:40] = (0, 0, 255)
    jpeg = jpeg_of(image)
    frame = decode_frame(encode_frame(meta, jpeg))
    assert frame.meta == meta
    assert frame.meta_json == encode(meta)
    assert frame.jpeg == jpeg
    decoded = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == image.shape and decoded[15, 35, 2] > 200


def frame_with(header: bytes = b"", meta: bytes = b"", jpeg: bytes = b"\xff\xd8\xff\xe0") -> bytes:
    meta = meta or encode(samples()[3])
    header = header or struct.pack("<4sBI", FRAME_MAGIC, 1, len(meta))
    return header + meta + jpeg


@pytest.mark.parametrize(
    "reason, payload",
    [
        ("oversize", frame_with(jpeg=b"\xff\xd8" + bytes(MAX_FRAME_BYTES))),
        ("encoding", FRAME_MAGIC + b"\x01"),
        ("magic", frame_with(header=struct.pack("<4sBI", b"JPEG", 1, 10))),
        ("version", frame_with(header=struct.pack("<4sBI", FRAME_MAGIC, 2, 10))),
        ("oversize", frame_with(header=struct.pack("<4sBI", FRAME_MAGIC, 1, 1 << 30))),
        ("encoding", frame_with(header=struct.pack("<4sBI", FRAME_MAGIC, 1, 5000), meta=b"{}")),
        ("encoding", frame_with(jpeg=b"PNG")),
        ("missing_field", frame_with(meta=json.dumps({"v": 1, "type": "frame", "seq": 1}).encode())),
        ("bad_value", frame_with(meta=encode(samples()[3]).replace(b'"jpeg"', b'"png"'))),
    ],
)
def test_malformed_frames_are_rejected(reason, payload):
    with pytest.raises(ProtocolError) as err:
        decode_frame(payload)
    assert err.value.reason == reason


def test_frame_meta_needs_sixteen_matrix_entries():
    data = to_dict(samples()[3])
    data["T_BC"] = data["T_BC"][:15]
    with pytest.raises(ProtocolError, match="T_BC"):
        decode_frame(frame_with(meta=json.dumps(data).encode()))


def test_sim_truth_keeps_the_world_ground_truth():
    truth = decode(encode(TRUTH), Truth)
    raw = WORLD.truth()
    assert truth.robot_pose == pytest.approx(raw["robot_pose"])
    assert np.allclose(truth.camera.T_WC, raw["camera"]["T_WC"])
    assert len(truth.object.parts) == 6 and truth.object.kind == "composite"


def test_info_reply_rebuilds_the_robot_model():
    info = decode(encode(samples()[4]), Info)
    assert info.robot == MODEL
    assert info.robot.walk.clamp(1.0, 0.0, 0.0)[0] == MODEL.walk.v_max


def test_keys_live_under_the_robot_name_and_names_are_checked():
    keys = RobotKeys("nao2")
    assert keys.camera_top == "nao/nao2/camera/top"
    assert keys.station_alive == "nao/nao2/station/alive/*"
    assert keys.station_token("ab12") == "nao/nao2/station/alive/ab12" and keys.lease == "nao/nao2/lease"
    assert {keys.state, keys.cmd_walk, keys.cmd_head, keys.info, keys.alive, keys.sim_truth} == {
        "nao/nao2/state", "nao/nao2/cmd/walk", "nao/nao2/cmd/head", "nao/nao2/info", "nao/nao2/alive", "nao/nao2/sim/truth",
    }
    for bad in ("", "a/b", "*", "x" * 65):
        with pytest.raises(ValueError):
            RobotKeys(bad)


@pytest.mark.parametrize("payload, reason", [
    (b"[" * 50_000, "encoding"),  # RecursionError inside json
    (b'{"v":1,"type":"cmd.walk","seq":' + b"9" * 5000 + b',"vx":0,"vy":0,"omega":0,"ttl":1,"lease":""}', "bad_value"),
    (b'{"v":1,"type":"cmd.walk","seq":1,"vx":' + b"9" * 400 + b',"vy":0,"omega":0,"ttl":1,"lease":""}', "bad_value"),
    (b'{"v":1,"type":"cmd.walk","seq":1,"vx":0,"vy":0,"omega":0,"ttl":1,"lease":"not hex!"}', "bad_value"),
])
def test_every_parser_failure_is_a_protocol_error(payload, reason):
    with pytest.raises(ProtocolError) as caught:
        decode(payload, WalkCommand)
    assert caught.value.reason == reason
    with pytest.raises(ProtocolError):
        decode_any(payload)


ADDED_STATE_FIELDS = {"owner": None, "stop_failures": 0, "robot_watchdog": "off"}  # issue 14, documented defaults


def test_a_state_recorded_before_the_lease_decodes_with_the_documented_defaults():
    state = samples()[2]
    old = {k: v for k, v in json.loads(encode(state)).items() if k not in ADDED_STATE_FIELDS}
    decoded = decode(json.dumps(old).encode(), State)
    assert {name: getattr(decoded, name) for name in ADDED_STATE_FIELDS} == ADDED_STATE_FIELDS
    assert decoded == dataclasses.replace(state, **ADDED_STATE_FIELDS)  # every other field as sent
    # only those fields may be absent: older fields and every command field stay required
    with pytest.raises(ProtocolError) as err:
        decode(json.dumps({k: v for k, v in old.items() if k != "watchdog"}).encode(), State)
    assert err.value.reason == "missing_field"
    with pytest.raises(ProtocolError) as err:
        decode(json.dumps(drop("lease")).encode(), WalkCommand)
    assert err.value.reason == "missing_field"


def test_a_frame_recorded_before_stamp_std_decodes_as_exact_and_a_negative_one_is_refused():
    """``FrameMeta.stamp_std`` (docs/frames.md) is absent from older logs: 0, which the station's
    filter reads as its own floor ``station.stamp_sigma``, as it did then."""
    meta = next(m for m in samples() if isinstance(m, FrameMeta))
    old = {k: v for k, v in json.loads(encode(meta)).items() if k != "stamp_std"}
    assert decode(json.dumps(old).encode(), FrameMeta) == dataclasses.replace(meta, stamp_std=0.0)
    with pytest.raises(ProtocolError) as err:
        decode(json.dumps({**old, "stamp_std": -0.1}).encode(), FrameMeta)
    assert err.value.reason == "bad_value"
