"""``station capture``: camera frames as JPEG files, for ``station calibrate`` and ``station pick-colors``.

From the robot (``--robot HOST``, ``--robot sim``, ``--naoqi HOST``): the frames the bridge
publishes, at most one per ``--every`` seconds, until ``--count`` are saved. From a run log
(``--log RUN.mcap``): the ``/nao/camera/image`` messages, with the same spacing by log time. The
JPEG bytes are written unchanged (``frame_0001.jpg``, ...), so the images are what the pilot saw.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Iterator, Tuple

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from nao_core.config import ConfigError
from nao_core.protocol import ProtocolError, decode_frame
from station.mcap_log import LogError, read_log
from station.topics import FRAME_IMAGE

log = logging.getLogger("station.capture")


def log_frames(path: Path) -> Iterator[Tuple[float, bytes]]:
    """(log time, JPEG) of every camera image of a run log."""
    for message in read_log(path, topics={FRAME_IMAGE}):
        yield message.t, message.proto(CompressedImage).data


def robot_frames(link, deadline: float) -> Iterator[Tuple[float, bytes]]:
    """(arrival time, JPEG) of the frames the bridge sends until ``deadline`` (monotonic)."""
    while time.monotonic() < deadline:
        try:
            link.inbox.get(timeout=min(0.5, max(0.01, deadline - time.monotonic())))
        except Exception:  # queue.Empty: keep waiting until the deadline
            continue
        for received in link.take_frames():
            try:
                yield received.t, decode_frame(received.payload).jpeg
            except ProtocolError as exc:
                log.warning("frame rejected: %s", exc)


def save(frames: Iterator[Tuple[float, bytes]], out: Path, count: int, every: float) -> int:
    """Write at most ``count`` (0: all) frames spaced by ``every`` s; returns how many were written."""
    out.mkdir(parents=True, exist_ok=True)
    written, last = 0, -float("inf")
    for t, jpeg in frames:
        if t - last < every:
            continue
        last = t
        written += 1
        (out / f"frame_{written:04d}.jpg").write_bytes(jpeg)
        log.debug("saved frame_%04d.jpg", written)
        if written == count:
            break
    return written


def run(args: argparse.Namespace) -> int:
    if args.log is not None:
        if args.robot or args.naoqi:
            raise ConfigError("capture: give either --log or a robot (--robot/--naoqi), not both")
        written = save(log_frames(args.log), args.out, args.count, args.every)
        if written == 0:
            raise LogError(f"{args.log}: no {FRAME_IMAGE} messages")
    else:
        if not (args.robot or args.naoqi):
            raise ConfigError("capture: give --log RUN.mcap, --robot HOST or --naoqi HOST")
        if args.count == 0:
            raise ConfigError("capture: --count 0 (all) needs --log")
        from station.cli import connected
        from station.config import load_station_config

        config = load_station_config(args.config)
        args.out.mkdir(parents=True, exist_ok=True)
        with connected(args, config, args.out, config.station.bridge_timeout) as (link, info, _, _bridge):
            link.start()
            patience = args.count * max(args.every, 1.0 / max(info.fps, 0.1)) + config.station.bridge_timeout
            written = save(robot_frames(link, time.monotonic() + patience), args.out, args.count, args.every)
        if written < args.count:
            log.error("capture: %d of %d frames within %.0f s: is the camera running? (station doctor)", written, args.count, patience)
            return 1
    log.info("capture: %d frames in %s", written, args.out)
    return 0
