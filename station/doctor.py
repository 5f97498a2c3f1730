"""``station doctor``: the robot checked line by line before a mission, each line PASS or FAIL with
the fix to try.

Checks, in order (a failed connection stops there):

* NAOqi (``--naoqi HOST``): a libqi session to tcp://HOST:9559 and ``ALSystem.systemVersion()``;
* the bridge: its info (backend, version, robot model, resolution) within ``bridge_timeout``;
* the camera: frames during ``--seconds``, their rate against the bridge's fps (at least half of
  it: below that the filter runs on stale frames), and the first one decodes at the resolution;
* the clock offset: median over frames of (station arrival - bridge capture stamp); the bridge
  drops walk commands older than their TTL, so |offset| must stay below ``station.walk_ttl``;
* the battery (``station.doctor_min_battery``), fallen, the bridge's watchdog state;
* landmarks visible now: a landmark pose fix (``RobotLocalizer.measure``) on the newest frame;
* the object in view: a silhouette of ``perception.object_color`` on it, or the other colour classes'
  largest ones there (``object_check``: an object of another colour than configured).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import cv2
import numpy as np

from agent.camera import CameraModel
from agent.localization import RobotLocalizer
from agent.perception import extract_silhouette, free_classes, largest_area
from agent.tone_curve import in_light
from nao_core.naoqi_api import error_line
from nao_core.protocol import ProtocolError, State, decode, decode_frame
from station.config import StationConfig, load_station_config
from station.launch import BridgeFailed

log = logging.getLogger("station.doctor")
NAOQI_PORT = 9559


@dataclass(frozen=True)
class Check:
    name: str
    ok: bool
    detail: str
    fix: str = ""

    def line(self) -> str:
        return f"{'PASS' if self.ok else 'FAIL'}  {self.name}: {self.detail}" + ("" if self.ok or not self.fix else f"  -> fix: {self.fix}")


def naoqi_check(host: str) -> Check:
    url = host if "://" in host else f"tcp://{host}:{NAOQI_PORT}"
    try:
        import qi

        session = qi.Session()
        session.connect(url)
    except Exception as exc:  # noqa: BLE001 - libqi raises RuntimeError for every failure
        return Check("NAOqi", False, f"{url}: {error_line(exc)}",
                     "is the robot on (chest button), on this network (press the chest button: it says its IP), port 9559 open?")
    try:
        version = f"NAOqi {session.service('ALSystem').systemVersion()}"
    except Exception as exc:  # noqa: BLE001 - a NAOqi without ALSystem (a stand-in): reachable all the same
        version = f"version unknown ({error_line(exc)})"
    finally:
        session.close()
    return Check("NAOqi", True, f"{url}, {version}")


def watch(link, seconds: float) -> tuple:
    """Frames (arrival t, Frame) and states received during ``seconds``."""
    frames, states = [], []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            event = link.inbox.get(timeout=0.2)
            if event.kind == "state":
                states.append(decode(event.payload, State))
        except Exception:  # noqa: BLE001 - queue.Empty, or a state that fails decoding (counted as missing)
            pass
        for received in link.take_frames():
            try:
                frames.append((received.t, decode_frame(received.payload)))
            except ProtocolError:
                pass
    return frames, states


def robot_checks(config: StationConfig, info, frames: list, states: List[State], seconds: float) -> List[Check]:
    checks = []
    rate = len(frames) / seconds
    camera_ok = rate >= 0.5 * info.fps and len(frames) > 0
    checks.append(Check("camera rate", camera_ok, f"{len(frames)} frames in {seconds:g} s = {rate:.1f}/s (bridge fps {info.fps:g})",
                        "another program holds the camera (stop naoqi_driver / Choregraphe video), or the network is slow: use qvga"))
    image = None
    if frames:
        image = cv2.imdecode(np.frombuffer(frames[-1][1].jpeg, np.uint8), cv2.IMREAD_COLOR)
        size_ok = image is not None and image.shape[:2] == (info.intrinsics.height, info.intrinsics.width)
        checks.append(Check("camera frame", size_ok, f"{'decodes' if image is not None else 'does not decode'} at "
                            f"{info.intrinsics.width}x{info.intrinsics.height}", "restart the bridge; check --resolution"))
        offset = statistics.median(t - f.meta.stamp for t, f in frames)
        checks.append(Check("clock offset", abs(offset) < config.station.walk_ttl,
                            f"{offset * 1000:+.0f} ms (station arrival - robot capture)",
                            "synchronize the clocks (NTP on the robot and here: `date` on both should agree)"))
    if states:
        s = states[-1]
        if s.battery is None:  # a robot without the battery key (a virtual robot, a stand-in): nothing to check
            checks.append(Check("battery", True, "not reported by the robot", ""))
        else:
            checks.append(Check("battery", s.battery >= config.station.doctor_min_battery, f"{s.battery:.0%}", "charge the robot"))
        checks.append(Check("fallen", not s.fallen, "lying" if s.fallen else "standing",
                            "stand the robot up and restart the bridge (a fall is latched)"))
        checks.append(Check("watchdog", s.watchdog not in ("stop_failed", "no_robot_watchdog"), s.watchdog,
                            "the robot's fall manager or the bridge's stop is not working: see docs/bridge.md"))
    else:
        checks.append(Check("state", False, "no robot state received", "the bridge cannot read ALMemory: see its log"))
    if image is not None:
        image = in_light(image, info.robot.camera.response_gamma)  # as the mission reads it (station/pilot.py)
        localizer = RobotLocalizer(config.localization, config.landmarks, CameraModel.from_intrinsics(info.intrinsics),
                                   config.perception)
        T_BC = np.asarray(frames[-1][1].meta.T_BC, dtype=float).reshape(4, 4)
        fix = localizer.measure(image, T_BC)
        unmapped = localizer.detector.diagnosis(min_frames=1)  # the markers in view that the map does not hold
        detail = (f"landmarks {', '.join(map(str, fix.landmark_ids))} give a pose fix ({fix.rms_px:.1f} px)" if fix
                  else f"no pose fix ({localizer.no_fix_reason or 'no landmark seen'})" + (f"; {unmapped}" if unmapped else ""))
        checks.append(Check("landmarks visible", fix is not None, detail,
                            f"turn the robot towards the landmarks of {config.station.landmark_map}, or fix the map (docs/frames.md)"))
        checks.append(object_check(config, image))
    return checks


def object_check(config: StationConfig, image: np.ndarray) -> Check:
    """A silhouette of the object's colour class in the frame; failing, the largest silhouettes of the classes
    neither the object's nor the map's balls' (agent/perception.py): an object of another colour than
    configured is named."""
    perception = config.perception
    silhouette = extract_silhouette(image, perception)
    if silhouette is not None:
        return Check("object in view", True, f"a {perception.object_color} silhouette of {silhouette.area} px", "")
    areas = {c: largest_area(image, perception, c) for c in free_classes(perception, config.landmarks.ball_colors)}
    seen = ", ".join(f"{c} ({a} px)" for c, a in sorted(areas.items(), key=lambda item: -item[1]) if a)
    return Check("object in view", False, f"no {perception.object_color} silhouette" + (f"; in view: {seen}" if seen else ""),
                 f"put the object a metre in front of the robot; if it is not {perception.object_color}, set "
                 f"perception.object_color (docs/perception.md), and check its class with station pick-colors")


def run(args: argparse.Namespace) -> int:
    """Prints one line per check; 0 if all pass, 1 if one fails, 2 if the robot cannot be reached."""
    from station.cli import connected

    config = load_station_config(args.config)
    checks: List[Check] = []
    if args.naoqi:
        checks.append(naoqi_check(args.naoqi))
        print(checks[-1].line(), flush=True)
        if not checks[-1].ok:
            return 2
    try:
        with tempfile.TemporaryDirectory(prefix="station-doctor-") as out, \
                connected(args, config, Path(out), config.station.bridge_timeout) as (link, info, _, _bridge):
            checks.append(Check("bridge", True, f"{info.backend} bridge {info.bridge_version}, {info.robot.name}, "
                                f"{info.resolution}, deadman {info.deadman_s:g} s"))
            print(checks[-1].line(), flush=True)
            link.start()
            frames, states = watch(link, args.seconds)
    except BridgeFailed as exc:
        print(Check("bridge", False, str(exc), "start it: nao-bridge --naoqi tcp://ROBOT:9559 (docs/first-day.md); "
                    "check the port (station.port) and the firewall").line())
        for line in exc.lines:
            print(f"      bridge: {line}")
        return 2
    for check in robot_checks(config, info, frames, states, args.seconds):
        checks.append(check)
        print(check.line(), flush=True)
    failed = [c.name for c in checks if not c.ok]
    log.info("doctor: %s", f"{len(failed)} check(s) failed: {', '.join(failed)}" if failed else "all checks passed")
    return 1 if failed else 0
