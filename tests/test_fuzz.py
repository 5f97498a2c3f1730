"""Property-based fuzzing (hypothesis) of every decoder of outside input: no crash, no bad value through.

Targets: the wire protocol's strict decoders (every JSON message type, ``decode_any``, the frame
envelope), the YAML config loader (``nao_core.config.load`` on the bridge, station and transport
sections), the landmark map loader and the station's MCAP log reader. Inputs are random bytes and
text, and structure-aware mutations of valid samples (a field replaced by a hostile value, a key
added or removed, NaN and infinities as JSON literals, bit flips and cuts in a valid log).

Properties: a decoder returns a valid object or raises its documented error (ProtocolError,
ConfigError; the log reader warns and yields the complete records); what it returns re-encodes
(so holds no NaN or infinity) and keeps every declared bound. Nothing else may escape.

Budget: each of the 7 targets runs ``CI_EXAMPLES`` (300) derandomized examples in the default
suite: 2,100 generated inputs, about 5,100 decoder calls, plus 150 hostile commands through the
real bridge, in about 30 s on this machine. The ``slow`` twins (``pytest -m slow
tests/test_fuzz.py``, for ``make fuzz``) run ``LONG_EXAMPLES`` (20,000) random examples per target.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import math
import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import pytest
import yaml
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nao_bridge.bridge import BridgeParams
from nao_core.config import CONFIG_DIR, ConfigError, load
from nao_core.landmark_map import LandmarkMap, load_landmark_map
from nao_core.protocol import (
    FRAME_MAGIC,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    HeadCommand,
    ProtocolError,
    RobotKeys,
    WalkCommand,
    decode,
    decode_any,
    decode_frame,
    encode,
    to_dict,
)
from nao_core.transport import TransportConfig, open_session
from station.config import StationParams
from station.mcap_log import McapLog, read_log
from tests.test_protocol import samples
from tests.zenoh_peers import bridge_on_standin, free_port, wait_until

CI_EXAMPLES = int(os.environ.get("FUZZ_CI_EXAMPLES", "300"))
LONG_EXAMPLES = int(os.environ.get("FUZZ_LONG_EXAMPLES", "20000"))
_SCRATCH_DIR = tempfile.TemporaryDirectory(prefix="fuzz-")  # removed when the test process ends
SCRATCH = Path(_SCRATCH_DIR.name)  # one file per target, rewritten per example

# -- hostile values ---------------------------------------------------------------------------------

NON_FINITE = ("NaN", "Infinity", "-Infinity", "1e999", "-1e999")
scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["", "nan", "inf", "1e309", "-0", "\u0000", "cmd.walk", "jpeg", "vga", "deny"]),
)
json_values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=5)), max_leaves=20)


def dumps(value: Any) -> bytes:
    """JSON with NaN and infinities written as the literals a hostile peer would send."""
    return json.dumps(value, allow_nan=True).encode("utf-8")


@st.composite
def mutated(draw, valid: Dict[str, Any]) -> Dict[str, Any]:
    """``valid`` with one to three leaves replaced by hostile values, keys dropped or added."""
    data = json.loads(json.dumps(valid))
    for _ in range(draw(st.integers(1, 3))):
        node, key = data, None
        while node:  # walk down to a random leaf or container
            key = draw(st.sampled_from(list(node) if isinstance(node, dict) else range(len(node))))
            if not isinstance(node[key], (dict, list)) or draw(st.booleans()):
                break
            node, key = node[key], None
        action = draw(st.sampled_from(["replace", "drop", "add"]))
        if key is None or action == "add":
            if isinstance(node, dict):
                node[draw(st.text(max_size=8))] = draw(json_values)
        elif action == "drop":
            del node[key]
        else:
            node[key] = draw(json_values)
    return data


def check_message(message: Any) -> None:
    """A decoded message re-encodes (no NaN/inf) and keeps every declared bound."""
    encode(message)
    for item in dataclasses.fields(message):
        value = getattr(message, item.name)
        lo, hi = item.metadata.get("bounds", (None, None))
        for number in _numbers(value):
            assert math.isfinite(number)
            assert (lo is None or number >= lo) and (hi is None or number <= hi), (item.name, number)


def _numbers(value: Any):
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield value
    elif isinstance(value, (tuple, list)):
        for item in value:
            yield from _numbers(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _numbers(item)


# -- targets ----------------------------------------------------------------------------------------

VALID = {type(m).TYPE: m for m in samples()}
FRAME_SAMPLE = VALID["frame"]
JPEG = b"\xff\xd8\xff\xe0" + bytes(16) + b"\xff\xd9"


def fuzz_message_bytes(data: bytes) -> None:
    for cls in MESSAGE_TYPES.values():
        try:
            check_message(decode(data, cls))
        except ProtocolError:
            pass
    try:
        check_message(decode_any(data))
    except ProtocolError:
        pass


def fuzz_message_fields(case: Tuple[str, Dict[str, Any], bool]) -> None:
    type_name, data, as_literal = case
    payload = dumps(data)
    if as_literal:  # a number written as a non-finite literal
        payload = re.sub(rb"(?<![\w.\"])-?\d+\.\d+(?:[eE][-+]?\d+)?(?![\w.])", b"NaN", payload, count=1)  # a whole number token
    try:
        message = decode(payload, MESSAGE_TYPES[type_name])
    except ProtocolError:
        return
    check_message(message)


def fuzz_frame(case: Tuple[bytes, bytes, int]) -> None:
    meta, tail, version = case
    for payload in (meta + tail, FRAME_MAGIC + bytes([version]) + len(meta).to_bytes(4, "little") + meta + tail):
        try:
            frame = decode_frame(payload)
        except ProtocolError:
            continue
        check_message(frame.meta)
        assert frame.jpeg.startswith(b"\xff\xd8")


def _write(name: str, text: str) -> Path:
    path = SCRATCH / name
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    return path


def _load_quietly(call: Callable[[], Any]) -> None:
    try:
        call()
    except ConfigError:
        pass


def fuzz_config_text(text: str) -> None:
    path = _write("config.yaml", text)
    for cls, section in ((BridgeParams, "bridge"), (StationParams, "station"), (TransportConfig, "transport")):
        _load_quietly(lambda: load(cls, [path], section=section))
    _load_quietly(lambda: load_landmark_map(path))


def fuzz_config_structure(case: Tuple[str, Dict[str, Any]]) -> None:
    section, data = case
    path = _write("mutated.yaml", yaml.safe_dump(data, allow_unicode=True))
    cls = {"bridge": BridgeParams, "station": StationParams, "landmarks": LandmarkMap}[section]
    try:
        params = load(cls, [path], section=None if section == "landmarks" else section)
    except ConfigError:
        return
    _check_params(params)


def _check_params(value: Any) -> None:
    """Every number in a loaded config is finite and within its field's bounds, recursively."""
    if not dataclasses.is_dataclass(value):
        return
    for item in dataclasses.fields(value):
        field_value = getattr(value, item.name)
        lo, hi = item.metadata.get("bounds", (None, None))
        for number in _numbers(field_value):
            assert math.isfinite(number) and (lo is None or number >= lo) and (hi is None or number <= hi)
        for nested in field_value if isinstance(field_value, tuple) else (field_value,):
            _check_params(nested)


def _valid_log() -> bytes:
    path = SCRATCH / "valid.mcap"
    with McapLog(path, flush_interval=0.0) as log:
        for i in range(40):
            log.json("/state", encode(VALID["state"]), 100.0 + 0.05 * i, {"title": "nao.State", "type": "object"})
            log.json("/decision", {"i": i}, 100.0 + 0.05 * i, {"title": "x", "type": "object"})
            log.maybe_flush()
    return path.read_bytes()


VALID_LOG = _valid_log()
HEADER_BYTES = 64  # magic and header record: a shorter file is treated as corrupt (below)
VALID_MESSAGES = [(m.topic, m.data) for m in read_log(SCRATCH / "valid.mcap")]


def fuzz_log_cut(cut: int) -> None:
    """A log cut anywhere after its header (a crash mid-write) reads as a prefix of what was written."""
    path = SCRATCH / "cut.mcap"
    path.write_bytes(VALID_LOG[:cut])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        kept = [(m.topic, m.data) for m in read_log(path)]
    assert kept == VALID_MESSAGES[: len(kept)]


def fuzz_log_corrupt(case: Tuple[int, bytes]) -> None:
    """Flipped bits: the reader warns and yields what it can, or raises a clear ValueError (station's LogError)."""
    cut, flip_at, noise = case
    data = bytearray(VALID_LOG[:cut])
    for i, byte in enumerate(noise):
        data[(flip_at + i) % len(data)] ^= byte  # (cut >= 1)
    path = SCRATCH / "corrupt.mcap"
    path.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        try:
            for message in read_log(path):
                assert isinstance(message.topic, str) and isinstance(message.data, bytes)
        except ValueError:
            pass


def _section(name: str) -> Dict[str, Any]:
    return yaml.safe_load((CONFIG_DIR / f"{name}.yaml").read_text())


meta_json = st.one_of(
    st.binary(max_size=200),
    mutated(to_dict(FRAME_SAMPLE)).map(dumps),
    st.just(encode(FRAME_SAMPLE)),
)
TARGETS: Dict[str, Tuple[st.SearchStrategy, Callable[[Any], None]]] = {
    "message-bytes": (st.one_of(st.binary(max_size=300), st.text(max_size=200).map(str.encode)), fuzz_message_bytes),
    "message-fields": (
        st.sampled_from(sorted(VALID)).flatmap(lambda name: st.tuples(
            st.just(name), mutated(to_dict(VALID[name])), st.booleans())),
        fuzz_message_fields,
    ),
    "frame": (st.tuples(meta_json, st.one_of(st.just(JPEG), st.binary(max_size=64)),
                        st.sampled_from([PROTOCOL_VERSION, 0, 2, 255])), fuzz_frame),
    "config-text": (st.one_of(st.text(max_size=300), st.sampled_from([
        "bridge: {transport: {lease_ms: .nan}}", "station: {port: !!float inf}", "bridge: *x",
        "landmarks: [{id: 1, kind: aruco, dictionary: DICT_4X4_50, size: 1e999, position: [0, 0, 0]}]",
        "station: !!python/object/apply:os.system ['true']", "\ufeffstation: {}", "---\n...\n---",
    ])), fuzz_config_text),
    "config-structure": (st.sampled_from(["bridge", "station", "landmarks"]).flatmap(lambda name: st.tuples(
        st.just(name), mutated(_section(name) if name != "landmarks" else
                               yaml.safe_load((CONFIG_DIR / "landmarks" / "sim_room.yaml").read_text())))),
        fuzz_config_structure),
    "log-cut": (st.integers(HEADER_BYTES, len(VALID_LOG)), fuzz_log_cut),
}
CORRUPT_LOGS = (st.tuples(st.integers(1, len(VALID_LOG)), st.integers(0, len(VALID_LOG)), st.binary(max_size=8)),
                fuzz_log_corrupt)


def run_given(strategy: st.SearchStrategy, check: Callable[[Any], None], examples: int,
              derandomize: bool = True) -> None:
    budget = settings(max_examples=examples, deadline=None, derandomize=derandomize, database=None,
                      suppress_health_check=list(HealthCheck))
    budget(given(strategy)(check))()


def run(target: str, examples: int, derandomize: bool) -> None:
    strategy, check = CORRUPT_LOGS if target == "log-corrupt" else TARGETS[target]
    run_given(strategy, check, examples, derandomize)


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_fuzz(target):
    run(target, CI_EXAMPLES, derandomize=True)


@pytest.mark.slow
@pytest.mark.timeout(3600)  # 20000 examples: longer than the suite's 300 s per test on a slow machine
@pytest.mark.parametrize("target", sorted(TARGETS))
def test_fuzz_long(target):
    run(target, LONG_EXAMPLES, derandomize=False)


def test_fuzz_corrupt_log():
    run("log-corrupt", CI_EXAMPLES, derandomize=True)


# -- through the real bridge: hostile commands never move the robot ----------------------------------


@pytest.mark.serial  # the bridge process on the stand-in
def test_hostile_commands_through_the_bridge_never_move_the_robot():
    """Malformed walk and head commands on the wire: all rejected and counted, no ALMotion call."""
    hostile = st.one_of(st.binary(max_size=200), mutated(to_dict(VALID["cmd.walk"])).map(dumps),
                        mutated(to_dict(VALID["cmd.head"])).map(dumps))
    port = free_port()
    with bridge_on_standin(TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)), seed=3, fps=2.0) as (bridge, standin):
        session = open_session(TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        try:
            token = session.liveliness().declare_token(RobotKeys("nao").station_token("fuzzer"))
            assert wait_until(lambda: bridge.station_alive, 5.0)
            head_calls = len(standin.calls_to("ALMotion.setAngles"))
            sent: List[bytes] = []

            def send(payload: bytes) -> None:
                kinds = [cls for cls in (WalkCommand, HeadCommand) if _decodes(payload, cls)]
                for key, cls in ((RobotKeys("nao").cmd_walk, WalkCommand), (RobotKeys("nao").cmd_head, HeadCommand)):
                    if cls not in kinds:  # only what the decoder refuses: a valid command may move the robot
                        session.put(key, payload)
                        sent.append(payload)

            run_given(hostile, send, CI_EXAMPLES // 2)
            assert wait_until(lambda: sum(bridge.rejected.values()) == len(sent), 10.0), (len(sent), bridge.rejected)
            assert standin.calls_to("ALMotion.move") == []
            assert len(standin.calls_to("ALMotion.setAngles")) == head_calls
            token.undeclare()
        finally:
            session.close()


def _hostile(i: int) -> bytes:
    """The i-th of a fixed cycle of hostile payloads: the shapes that once escaped the decoder."""
    walk = '"v":1,"type":"cmd.walk","seq":{},"vx":{},"vy":0,"omega":0,"ttl":1,"lease":"{}"'
    shapes = [
        b"[" * (50_000 + i % 7),  # deep nesting: RecursionError in json
        b'{"a":' * 20_000 + b"1" + b"}" * 20_000,
        ("{" + walk.format("9" * 5000, 0, "") + "}").encode(),  # > 4300 digits: ValueError
        ("{" + walk.format(1, "9" * 400, "") + "}").encode(),  # int -> float: OverflowError
        ("{" + walk.format(1, "1e999", "") + "}").encode(),  # overflows to inf
        ("{" + walk.format(2**64, 0, "x" * 200) + "}").encode(),  # seq and lease out of bounds
        bytes((i * 7 + k) % 256 for k in range(64)),  # binary noise
        b'{"v":1,"type":"cmd.walk"' + b',"x":1' * 5000 + b"}",
    ]
    return shapes[i % len(shapes)]


def _rss_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.serial  # the bridge process on the stand-in
def test_flood_of_hostile_messages_is_counted_logged_little_and_keeps_memory_flat():
    """10,000 hostile messages on every key the bridge listens to: 0 crashes, 0 motions, all counted,
    log under 100 KB (one line per reason per second), memory growth under 10 MB."""
    count, log_limit, memory_limit = 10_000, 100_000, 10 * 2**20
    keys = RobotKeys("nao")
    port = free_port()
    written = io.StringIO()
    handler = logging.StreamHandler(written)
    logger = logging.getLogger("nao_bridge")
    logger.addHandler(handler)
    try:
        with bridge_on_standin(TransportConfig(listen=(f"tcp/127.0.0.1:{port}",)), seed=5, fps=2.0) as (bridge, standin):
            session = open_session(TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)))
            try:
                token = session.liveliness().declare_token(keys.station_token("flooder"))
                assert wait_until(lambda: bridge.station_alive, 5.0)
                for i in range(200):  # warm-up: allocator and Zenoh buffers reach their working size
                    session.put(keys.cmd_walk, _hostile(i), congestion_control=zenoh.CongestionControl.BLOCK)
                assert wait_until(lambda: sum(bridge.rejected.values()) == 200, 20.0)
                log_before = written.tell()
                lease_queries, before = 0, 0
                for i in range(count):
                    if i == count // 2:  # buffers have grown to their working size: from here on, flat
                        assert wait_until(lambda: sum(bridge.rejected.values()) == 200 + i, 60.0)
                        before = _rss_bytes()
                    payload = _hostile(i)
                    if i % 50 == 0:  # the lease queryable too (a query is a round trip: fewer of them)
                        list(session.get(keys.lease, payload=payload, timeout=2.0))
                        lease_queries += 1
                    else:
                        session.put(keys.cmd_walk if i % 2 else keys.cmd_head, payload,
                                    congestion_control=zenoh.CongestionControl.BLOCK)  # none lost on the way
                assert wait_until(lambda: sum(bridge.rejected.values()) == 200 + count, 60.0), dict(bridge.rejected)
                growth, log_bytes = _rss_bytes() - before, written.tell() - log_before
                assert bridge._threads and all(t.is_alive() for t in bridge._threads), "a bridge thread died"
                assert standin.calls_to("ALMotion.move") == [] and standin.calls_to("ALMotion.setAngles") == []
                assert bridge.owner is None and lease_queries == count // 50
                assert log_bytes < log_limit, log_bytes
                assert growth < memory_limit, growth
                token.undeclare()
            finally:
                session.close()
    finally:
        logger.removeHandler(handler)


def _decodes(payload: bytes, cls: type) -> bool:
    try:
        decode(payload, cls)
        return True
    except ProtocolError:
        return False


# -- hostile YAML the random search does not reach ---------------------------------------------------


def test_deeply_nested_yaml_is_a_config_error():
    path = _write("deep.yaml", "landmarks: " + "[" * 5000 + "]" * 5000)
    with pytest.raises(ConfigError):
        load_landmark_map(path)


def test_yaml_alias_expansion_is_refused():
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    lines += [f"{chr(97 + i)}: &{chr(97 + i)} [{', '.join(['*' + chr(96 + i)] * 9)}]" for i in range(1, 4)]
    path = _write("laughs.yaml", "\n".join(lines) + "\nlandmarks: *d\n")
    with pytest.raises(ConfigError, match="alias"):
        load_landmark_map(path)
