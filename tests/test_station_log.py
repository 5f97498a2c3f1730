"""The run log: JSON bytes kept as received, Foxglove protobuf channels, flush, crash-tolerant read;
the console in it as foxglove.Log, the live WebSocket view of it, image annotations, the layout."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import struct
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.Log_pb2 import Log
from websockets.asyncio.client import connect

from station import foxglove, logs
from station.live import LiveServer
from station.mcap_log import McapLog, read_log
from station.topics import LOG

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


# the console in the log, the live view, the layout --------------------------------------------------

LAYOUT = Path(__file__).resolve().parent.parent / "config" / "foxglove" / "layout.json"


def test_console_lines_are_logged_as_foxglove_log_at_their_level(tmp_path, capsys):
    logger = logs.setup(verbosity=-1)  # -q: the console shows warnings only, the log keeps INFO
    path = tmp_path / "run.mcap"
    with McapLog(path) as run_log:
        with logs.attached(logs.LogTopicHandler(lambda message, t: run_log.proto(LOG, message, t))):
            logging.getLogger("station.test").info("phase %s", "search")
            logging.getLogger("station.test").warning("battery low")
            logging.getLogger("station.test").debug("not at -q, not in the log")
        logging.getLogger("station.test").info("after the log closed: console only")
    err = capsys.readouterr().err
    assert err == "station: warning: battery low\n"
    messages = [m.proto(Log) for m in read_log(path, topics={LOG})]
    assert [(m.level, m.message, m.name) for m in messages] == [
        (Log.INFO, "phase search", "station.test"), (Log.WARNING, "battery low", "station.test")]
    assert all(m.timestamp.seconds > 0 and m.file.endswith("test_station_log.py") for m in messages)
    logs.setup(0)
    assert logger.handlers  # console handler replaced, not stacked
    assert sum(getattr(h, "station_console", False) for h in logger.handlers) == 1


def test_live_server_serves_what_the_log_writes_to_a_websocket_client(tmp_path):
    """A real WebSocket client (foxglove.sdk.v1 subprotocol) subscribes to the image and the scene
    channels and receives, for each, the bytes the MCAP log holds."""
    server = LiveServer(port=0)
    image = foxglove.compressed_image(1.0, b"\xff\xd8jpeg")
    scene = foxglove.object_estimate(1.0, np.array([1.0, 0.5, 0.05]), np.diag([1e-3, 2e-3, 1e-4]))
    run_log = McapLog(tmp_path / "run.mcap", sinks=[server])
    run_log.proto("/nao/camera/image", image, 1.0)
    run_log.proto("/scene/object", scene, 1.0)

    async def client() -> dict:
        async with connect(server.url, subprotocols=["foxglove.sdk.v1"]) as ws:
            channels = {}
            while len(channels) < 2:
                message = json.loads(await asyncio.wait_for(ws.recv(), 10))
                if message["op"] == "advertise":
                    channels.update({c["id"]: c for c in message["channels"]})
            by_sub = {i: c for i, c in enumerate(channels.values(), start=1)}
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": c["id"]} for i, c in by_sub.items()]}))
            received = {}
            while len(received) < 2:  # the server applies the subscription asynchronously: write until it arrives
                run_log.proto("/nao/camera/image", image, 2.0)
                run_log.proto("/scene/object", scene, 2.0)
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[0] == 1:  # MessageData: op, subscription u32, time u64, payload
                    sub, log_time = struct.unpack_from("<IQ", frame, 1)
                    received[by_sub[sub]["topic"]] = (by_sub[sub], log_time, frame[13:])
            return received

    try:
        received = asyncio.run(client())
    finally:
        run_log.close()
        server.close()
    channel, log_time, payload = received["/nao/camera/image"]
    assert channel["schemaName"] == "foxglove.CompressedImage" and channel["encoding"] == "protobuf"
    assert payload == image.SerializeToString() and log_time == 2_000_000_000
    channel, _, payload = received["/scene/object"]
    assert channel["schemaName"] == "foxglove.SceneUpdate" and payload == scene.SerializeToString()
    logged = {m.topic: m.data for m in read_log(tmp_path / "run.mcap")}
    assert logged["/scene/object"] == payload  # the live view and the file carry the same bytes


def test_layout_panels_name_the_expected_views():
    topics = foxglove.layout_topics(json.loads(LAYOUT.read_text()))
    assert {"/nao/camera/image", "/nao/camera/annotations", "/scene/trajectory", "/scene/model", "/station/log",
            "/station/estimate", "/agent/coverage", "/nao/cmd/walk"} <= topics


def test_image_annotations_project_the_frame_view():
    """A camera at the origin looking along +x (optical z = world x): a point straight ahead lands
    on the principal point; the two tangent rays straddle it; an outline is kept as given."""
    from agent.camera import CameraModel
    from nao_core.robot_model import load_robot_model

    camera = CameraModel.from_intrinsics(load_robot_model().camera.intrinsics("qvga"))
    T_WC = np.eye(4)
    T_WC[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # columns: the optical axes in world: x_C = -y_W, y_C = -z_W, z_C = x_W
    T_WC[2, 3] = 0.1  # at the aim height: the rays and the predicted point lie on the principal row
    outline = np.array([[10, 20], [11, 21], [12, 22]])
    view = foxglove.FrameView(T_WC=T_WC, outline=outline, bearings=((0.0, 0.0), 0.0, 0.2),
                              landmarks=[("7", (2.0, 0.0, 0.1)), ("behind", (-2.0, 0.0, 0.1))], predicted=(1.0, 0.0))
    ann = foxglove.image_annotations(5.0, camera, view)
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    assert [(p.x, p.y) for p in ann.points[0].points] == [(10, 20), (11, 21), (12, 22)]
    right, left = ann.points[1:3]  # bearings phi - delta/2 (clockwise: right in the image), phi + delta/2
    assert all(p.x < cx - 1 for p in left.points) and all(p.x > cx + 1 for p in right.points)
    assert all(abs(p.y - cy) < 1e-6 for p in left.points)
    assert [t.text for t in ann.texts] == ["7", "object (predicted)"]  # the landmark behind the camera is not drawn
    assert all(abs(c.position.x - cx) < 1e-6 and abs(c.position.y - cy) < 1e-6 for c in ann.circles)
    assert ann.circles[0].timestamp.seconds == 5


def test_trajectory_is_poses_in_world():
    message = foxglove.trajectory(3.0, [(0.0, 0.0, 0.0), (1.0, 2.0, math.pi / 2)])
    assert message.frame_id == "world" and len(message.poses) == 2
    p = message.poses[1]
    assert (p.position.x, p.position.y) == (1.0, 2.0) and p.orientation.z == pytest.approx(math.sqrt(0.5))


def test_scene_model_is_y_up_like_gltf():
    """A tall box (z up in the world) becomes a GLB whose up axis is y: Foxglove shows it upright."""
    import io

    import trimesh

    from station.run import _glb

    class Carver:
        def to_mesh(self):
            return trimesh.creation.box(extents=(0.1, 0.1, 0.3))

    glb = foxglove.model(0.0, _glb(Carver())).entities[0].models[0].data
    extents = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh").extents
    assert extents[1] == pytest.approx(0.3) and extents[2] == pytest.approx(0.1)
