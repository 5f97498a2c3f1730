"""The run log: JSON bytes kept as received, Foxglove protobuf channels, flush, crash-tolerant read."""

from __future__ import annotations

import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from station.mcap_log import McapLog, read_log

SCHEMA = {"title": "nao.Test", "type": "object"}


def test_round_trip_in_write_order_with_bytes_unchanged(tmp_path):
    path = tmp_path / "run.mcap"
    raw = b'{"b": 2,  "a": 1}'  # odd spacing and key order must survive
    with McapLog(path) as log:
        log.json("/state", raw, 10.0, SCHEMA)
        log.proto("/camera/image", CompressedImage(format="jpeg", data=b"\xff\xd8jpeg"), 9.0)  # earlier stamp
        log.json("/decision", {"v": 0.1}, 9.5, SCHEMA)
    messages = list(read_log(path))
    assert [m.topic for m in messages] == ["/state", "/camera/image", "/decision"]  # file order, not time
    assert messages[0].data == raw and messages[0].schema == "nao.Test" and messages[0].encoding == "json"
    assert messages[1].schema == "foxglove.CompressedImage" and messages[1].proto(CompressedImage).data == b"\xff\xd8jpeg"
    assert messages[2].json() == {"v": 0.1} and messages[2].t == pytest.approx(9.5)
    assert [m.topic for m in read_log(path, topics={"/decision"})] == ["/decision"]


def test_flush_interval_bounds_what_a_crash_loses(tmp_path):
    now = [0.0]
    path = tmp_path / "run.mcap"
    log = McapLog(path, flush_interval=1.0, clock=lambda: now[0])
    for i in range(30):
        now[0] = i * 0.1
        log.json("/tick", {"i": i}, now[0], SCHEMA)
        log.maybe_flush()
    # the process dies here: no close(), no summary; flushes happened at t = 1.0, 2.0
    with pytest.warns(UserWarning, match="incomplete MCAP"):
        kept = [m.json()["i"] for m in read_log(path)]
    assert kept == list(range(21))


def test_truncated_file_reads_up_to_last_complete_record(tmp_path):
    path = tmp_path / "run.mcap"
    with McapLog(path, flush_interval=0.0) as log:
        for i in range(200):
            log.json("/tick", {"i": i, "pad": "x" * (i % 17)}, float(i), SCHEMA)
            log.maybe_flush()
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.warns(UserWarning):
        kept = [m.json()["i"] for m in read_log(cut)]
    assert 0 < len(kept) < 200 and kept == list(range(len(kept)))


def test_write_after_close_is_an_error(tmp_path):
    log = McapLog(tmp_path / "run.mcap")
    log.close()
    log.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        log.json("/x", {}, 0.0, SCHEMA)
