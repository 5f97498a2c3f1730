"""The real robot behind :class:`RobotBackend`: NAOqi services reached through libqi (``qi``).

Services and calls (NAOqi 2.x API):

* ALVideoDevice: ``subscribeCamera(name, 0 = top, resolution id, colour space id, fps)``, then a
  ``getImageRemote(handle)`` loop; ``unsubscribe(handle)`` on close. An image is the 12-field list
  ``[width, height, layers, colour space, stamp s, stamp us, buffer, camera id, 4 angles]``; the
  buffer arrives as ``bytes``/``bytearray`` or, through the Python binding, as latin-1 text.
  YUV422 is packed YUYV (2 bytes per pixel) and converted with ``cv2.COLOR_YUV2BGR_YUYV``.
  A frame whose stamp equals the previous one is a duplicate (the camera has not produced a new
  image yet) and is skipped.
* ALMotion: ``move(vx, vy, omega)`` (m/s, m/s, rad/s), ``stopMove``, ``setAngles`` for HeadYaw and
  HeadPitch, ``getAngles(names, True)``, ``getRobotPosition(True)`` (odometry),
  ``getTransform("CameraTop", 2 = FRAME_ROBOT, True)`` (NAO camera axes, converted once with
  ``nao_to_optical``), ``moveIsActive``, ``wakeUp`` and ``rest``.
* ALMemory: ``subscriber("robotHasFallen")`` and ``subscriber("ALMotion/RobotIsFalling")``
  signals latch the fall flag; ``getData`` for the initial fall flag and the battery charge.
* ALAutonomousLife ``setState("disabled")`` and ALRobotPosture ``goToPosture("StandInit", speed)``
  at start, ``rest`` on close, each configurable.

Only ALMotion, ALVideoDevice and ALMemory's ``getData``/``insertData`` are required. A NAOqi without
the rest (a virtual robot, a stand-in) runs with one warning each, naming what is lost: no
ALAutonomousLife or ALRobotPosture, the start skips that step; no ``ALMemory.subscriber``, the fall
keys are polled with ``getData`` at every state read; a key ``getData`` does not know (an event never
raised, a robot without the battery key) reads as not fallen, or as an unknown charge (``None``).
Without ``ALMotion.moveIsActive`` walking is taken as commanded, without ``killMove`` an
unconfirmed stop escalates to ``stopMove`` and ``rest``, without ``wakeUp`` the robot is taken as
standing (``OPTIONAL_MOTION``); without ``ALVideoDevice.subscribeCamera`` the camera is subscribed
with the older ``subscribe`` (the active camera). Images answered in
another colour space than asked are decoded when it is RGB (11), YUV (10) or luma only (0, grey);
images of another size than subscribed, with the same aspect, are resized to it (one warning);
another aspect drops the frame with an error naming both sizes.

Clocks. Image stamps are the robot's clock; the bridge's is ``nao_core.clock.now()`` (wall time
that never jumps). The offset between them is measured two ways:

* Probe (preferred): the sampler writes a counter to ALMemory (``CLOCK_PROBE_KEY``) between bridge
  times t0 and t1 and reads the robot's stamp s of that write with ``ALMemory.getTimestamp``. The
  robot stamped it inside [t0, t1], so

      offset_j = (t0 + t1) / 2 - s_j,    |error_j| <= (t1 - t0) / 2,

  and of the last ``clock_probe_window`` probes the one with the shortest round trip is kept (NTP's
  clock filter). Frames are then stamped s_k + offset, independent of the camera's latency.
* Camera bound: with r_k the bridge time at which image k was received, r_k - s_k = offset +
  latency_k, latency_k >= L_min (``camera_latency_min``, 0 if unknown), so

      offset_cam = min_{k in last N frames} (r_k - s_k) - L_min

  is never early and is late by the smallest excess latency seen; a clock step is forgotten after N.

The probe is used while it agrees with the camera: the smallest latency it implies,
min_k (r_k - s_k) - offset_probe, must lie in [-(t1 - t0) / 2, ``camera_latency_max``]. Otherwise
(ALMemory and the camera stamp on different clocks, or a robot without ``getTimestamp``):

* synchronized clocks: when min_k (r_k - s_k) itself lies in [L_min, ``camera_latency_max``], the
  robot's stamps are already on the bridge clock (NTP on both, or one machine) and frames keep them
  (offset 0): a clock off by a fraction of a second and no faster camera would pass too, but an
  unsynchronized clock is off by far more;
* else frames take offset_cam, late by the shortest latency above L_min;

with one warning naming which.

Exposure. A stamp names one instant of an exposure of 5-30 ms, which while the camera turns is
not the instant the image shows (its middle). Stamped frames (probe or synchronized clocks) are
therefore stamped s_k + offset - e, with e the exposure offset their images show against the
kinematics (nao_bridge/camera_latency.py), learnt in [-``exposure_offset_max``,
``exposure_offset_max``]; frames on the camera bound get e within their latency.

Each frame says how far its stamp may be from the instant its image shows (``stamp_std``, for the
station's filter: a turning camera's bearing errs by the turn rate times it): ``LEARNT_STD`` once
its estimator has ``min_pairs`` turning pairs; before, ``unlearnt_latency_std`` on the camera bound
(late by the whole latency) and ``exposure_offset_max`` / sqrt(3) on stamped frames (an offset
anywhere in +-``exposure_offset_max``).

Capture-time kinematics. NAOqi does not return the joint angles with an image, and the image
arrives tens of ms after its capture, while the torso rolls and the head turns. A sampler thread
reads ``getAngles``, ``getTransform`` and ``getRobotPosition`` at ``kinematics_rate`` into a
:class:`KinematicsHistory` (``nao_bridge.capture_kinematics``), and each frame's head angles, T_BC
and odometry are interpolated to its capture stamp. A frame whose stamp is outside the history (or
in a gap of it) is dropped and counted by reason in ``kinematics_dropped``.
"""

from __future__ import annotations

import collections
import functools
import ipaddress
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Counter, Deque, Dict, List, Literal, Optional, Sequence, Set, Tuple, Union

import cv2
import numpy as np
import qi

from nao_bridge.backend import RobotBackend
from nao_bridge.camera_latency import LEARNT_STD, LatencyEstimator, camera_heading
from nao_bridge.capture_kinematics import KinematicSample, KinematicsHistory
from nao_bridge.watchdog import HEARTBEAT_KEY, WATCHDOG_KEY
from nao_core.clock import now
from nao_core.config import bounds
from nao_core.naoqi_api import (
    BATTERY_KEY,
    CLOCK_PROBE_KEY,
    COLOR_SPACE_IDS,
    FALL_KEYS,
    FRAME_ROBOT,
    HEAD_JOINTS,
    RESOLUTION_IDS,
    RGB_COLOR_SPACE,
    TOP_CAMERA,
    Y_COLOR_SPACE,
    YUV_COLOR_SPACE,
    error_line,
)
from nao_core.records import CameraFrame, RobotState
from nao_core.robot_model import RobotModel, nao_to_optical

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class NaoqiParams:
    """NAOqi options of the bridge (``bridge.naoqi`` in config/bridge.yaml)."""

    color_space: Literal["yuv422", "bgr"]
    disable_autonomous_life: bool
    stand_init_at_start: bool
    stand_init_speed: float = field(metadata=bounds(0.05, 1.0))
    rest_on_exit: bool
    use_sensors: bool  # odometry and head angles from sensors rather than commands
    clock_window: int = field(metadata=bounds(1, 100000))  # frames in the offset minimum
    camera_latency_min: float = field(metadata=bounds(0.0, 1.0))  # s, shortest capture-to-receive latency
    camera_latency_max: float = field(metadata=bounds(0.0, 10.0))  # s, longest plausible shortest latency
    exposure_offset_max: float = field(metadata=bounds(0.0, 0.5))  # s, farthest a stamped image's scene lies from its stamp
    unlearnt_latency_std: float = field(metadata=bounds(0.0, 10.0))  # s, a camera-bound stamp's error before the latency is learnt
    clock_probe_rate: float = field(metadata=bounds(0.0, 100.0))  # Hz of ALMemory clock probes (0: camera only)
    clock_probe_window: int = field(metadata=bounds(1, 100000))  # probes in the shortest-round-trip choice
    kinematics_rate: float = field(metadata=bounds(5.0, 1000.0))  # Hz, head/T_BC/odometry sampling
    kinematics_history: float = field(metadata=bounds(0.2, 60.0))  # s of samples kept
    kinematics_max_gap: float = field(metadata=bounds(0.001, 5.0))  # s, widest gap interpolated over
    client_name: str


# ALMotion methods a stand-in or a virtual robot may lack -> what the bridge does without them
OPTIONAL_MOTION = {
    "wakeUp": "the robot is taken as already stiff and standing",
    "moveIsActive": "walking is taken as commanded, so a stop counts as confirmed once stopMove returns",
    "killMove": "a stop that moveIsActive does not confirm is escalated with stopMove, then rest",
}

# colour space id -> (bytes per pixel, OpenCV conversion to BGR or None)
DECODERS = {COLOR_SPACE_IDS["bgr"]: (3, None), COLOR_SPACE_IDS["yuv422"]: (2, cv2.COLOR_YUV2BGR_YUYV),
            RGB_COLOR_SPACE: (3, cv2.COLOR_RGB2BGR), YUV_COLOR_SPACE: (3, cv2.COLOR_YUV2BGR),
            Y_COLOR_SPACE: (1, cv2.COLOR_GRAY2BGR)}


def image_to_bgr(width: int, height: int, color_space: int, buffer: Union[bytes, bytearray, str]) -> np.ndarray:
    """A NAOqi image buffer (bytes or latin-1 text) in BGR, RGB or packed YUV422 -> H x W x 3 BGR."""
    raw = buffer.encode("latin-1") if isinstance(buffer, str) else bytes(buffer)
    if color_space not in DECODERS:
        raise ValueError(f"image colour space {color_space}: expected one of {sorted(DECODERS)}")
    layers, conversion = DECODERS[color_space]
    if len(raw) != width * height * layers:
        raise ValueError(f"image buffer of {len(raw)} bytes, expected {width}x{height}x{layers}")
    pixels = np.frombuffer(raw, np.uint8).reshape(height, width, layers)
    return pixels.copy() if conversion is None else cv2.cvtColor(pixels, conversion)


def on_this_machine(host: str) -> bool:
    """Whether every address ``host`` resolves to is this machine's: a loopback address, or one a socket
    can bind here (an interface's own, the unspecified one). A name that does not resolve is not."""
    try:
        addresses = socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)
    except (OSError, UnicodeError):
        return False
    for family, kind, _, _, address in addresses:
        if ipaddress.ip_address(address[0].split("%", 1)[0]).is_loopback:
            continue
        try:
            with socket.socket(family, kind) as probe:
                probe.bind((address[0], 0) + tuple(address[2:]))
        except OSError:
            return False
    return bool(addresses)


class ClockOffset:
    """Robot clock -> bridge clock: minimum of (receive time - robot stamp) over a window, less ``latency_min``."""

    def __init__(self, window: int, latency_min: float = 0.0):
        self._samples: Deque[float] = collections.deque(maxlen=window)
        self._latency_min = latency_min

    def update(self, robot_stamp: float, received: float) -> float:
        """Record one image; return its capture time on the bridge clock."""
        self._samples.append(received - robot_stamp)
        return robot_stamp + self.bound - self._latency_min

    @property
    def bound(self) -> float:
        """min (r_k - s_k) over the window: the offset is at most this (latencies are not negative)."""
        return min(self._samples)


class ClockProbe:
    """Robot clock -> bridge clock from stamped writes: of the last ``window`` probes, the one with the
    shortest round trip gives offset = (t0 + t1) / 2 - s, within half that round trip."""

    def __init__(self, window: int):
        self._probes: Deque[Tuple[float, float]] = collections.deque(maxlen=window)  # (round trip, offset)

    def add(self, sent: float, answered: float, robot_stamp: float) -> None:
        """A write sent at bridge time ``sent``, acknowledged at ``answered``, stamped ``robot_stamp`` by the robot."""
        if answered >= sent:
            self._probes.append((answered - sent, 0.5 * (sent + answered) - robot_stamp))

    def best(self) -> Optional[Tuple[float, float]]:
        """(offset, its error bound) of the shortest round trip, or None before the first probe."""
        if not self._probes:
            return None
        round_trip, offset = min(self._probes)
        return offset, 0.5 * round_trip


class NaoqiBackend(RobotBackend):
    """A NAO reached at ``url`` (e.g. ``tcp://nao.local:9559``)."""

    def __init__(self, url: str, model: RobotModel, params: NaoqiParams, resolution: str, fps: float):
        model.camera.intrinsics(resolution)  # KeyError naming the resolution if the model lacks it
        if resolution not in RESOLUTION_IDS:
            raise ValueError(f"NAOqi resolution {resolution!r}: expected one of {sorted(RESOLUTION_IDS)}")
        self.url = url
        self.model = model
        self.params = params
        self.resolution = resolution
        self.fps = fps
        self._session: Optional[Any] = None
        self._camera: Optional[str] = None
        self._fall_links: List[tuple] = []
        self._polled_fall_keys: List[str] = []  # fall keys without an ALMemory subscriber: read at every state
        self._warned: Set[str] = set()
        self._fallen = threading.Event()
        self._clock = ClockOffset(params.clock_window, params.camera_latency_min)
        self._probe = ClockProbe(params.clock_probe_window)
        self._probe_count = 0
        self._next_probe = -math.inf  # time.monotonic() of the next clock probe; inf once probing failed
        self.clock_source = "camera"  # "probe" while the probe's offset agrees with the camera bound, "synchronized"
        self._warned_reasons: Set[str] = set()
        self._last_stamp: Optional[tuple] = None
        self._closed = False
        self._close_lock = threading.Lock()
        self.duplicates = 0
        period = 1.0 / params.kinematics_rate
        self.kinematics = KinematicsHistory(max(2, math.ceil(params.kinematics_history / period)), params.kinematics_max_gap)
        self.kinematics_dropped: Counter[str] = collections.Counter()  # frames without capture-time kinematics, by reason
        self._sampler: Optional[threading.Thread] = None
        self._stop_sampling = threading.Event()
        intrinsics = model.camera.intrinsics(resolution)
        self.image_size = (int(intrinsics.width), int(intrinsics.height))
        focal, width = float(np.asarray(intrinsics.K)[0, 0]), int(intrinsics.width)
        self.latency = LatencyEstimator(params.camera_latency_max, focal, width)  # frames on the camera bound
        self.exposure = LatencyEstimator(params.exposure_offset_max, focal, width, min_latency=-params.exposure_offset_max)  # stamped
        self._logged_tau: Dict[LatencyEstimator, Optional[float]] = {self.latency: None, self.exposure: None}  # last told in the log
        self._unlearnt: Optional[Tuple[LatencyEstimator, np.ndarray, float]] = None  # the last frame, its estimator and uncorrected stamp
        self._last_drop_log = -math.inf
        self._walk_commanded = False  # the last walk command was not a stop: "walking" without moveIsActive
        self._motion_lacks: Set[str] = set()  # of OPTIONAL_MOTION, found missing at start

    def start(self) -> None:
        session = qi.Session()
        try:
            session.connect(self.url)
        except RuntimeError as exc:
            raise ConnectionError(f"cannot reach NAOqi at {self.url}: {exc}") from None
        self._session = session
        self.motion = session.service("ALMotion")
        self.video = session.service("ALVideoDevice")
        self.memory = session.service("ALMemory")
        if self.params.disable_autonomous_life:
            self._optional("ALAutonomousLife", lambda: session.service("ALAutonomousLife").setState("disabled"),
                           "autonomous life stays as it is and may move the head or the body during the mission")
        self._motion_lacks = {method for method in OPTIONAL_MOTION if not hasattr(self.motion, method)}
        for method in sorted(self._motion_lacks):
            log.warning("NAOqi ALMotion.%s unavailable: %s", method, OPTIONAL_MOTION[method])
        if "wakeUp" not in self._motion_lacks:
            self.motion.wakeUp()
        if self.params.stand_init_at_start:
            self._optional("ALRobotPosture",
                           lambda: session.service("ALRobotPosture").goToPosture("StandInit", self.params.stand_init_speed),
                           "the robot walks from the posture wakeUp left it in")
        for key in FALL_KEYS:
            try:
                subscriber = self.memory.subscriber(key)
                self._fall_links.append((subscriber, subscriber.signal.connect(self._on_fall_event)))
            except Exception as exc:  # noqa: BLE001 - an ALMemory without subscriber: poll the key instead
                self._polled_fall_keys.append(key)
                log.warning("NAOqi ALMemory.subscriber(%r) failed (%s): the key is polled at every state read", key,
                            error_line(exc))
            self._read_fall_key(key)
        self._sample_kinematics()  # the first sample precedes every image; a failure here fails the start
        self._sampler = threading.Thread(target=self._sample_loop, name="naoqi-kinematics", daemon=True)
        self._sampler.start()
        time.sleep(2.0 / self.params.kinematics_rate)  # the history spans the first capture, even one stamped early
        subscription = (RESOLUTION_IDS[self.resolution], COLOR_SPACE_IDS[self.params.color_space], int(round(self.fps)))
        if hasattr(self.video, "subscribeCamera"):
            self._camera = self.video.subscribeCamera(self.params.client_name, TOP_CAMERA, *subscription)
        else:  # the NAOqi 1.x call, on the active camera (the top one unless changed)
            log.warning("NAOqi ALVideoDevice.subscribeCamera unavailable: subscribed with subscribe() to the active camera")
            self._camera = self.video.subscribe(self.params.client_name, *subscription)
        log.info("NAOqi at %s: camera %s %s at %g fps", self.url, self.resolution, self.params.color_space, self.fps)

    def _optional(self, service: str, step: Callable[[], Any], lost: str) -> None:
        """Run a start step that needs a service a bare NAOqi may lack; without it, warn what is lost."""
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - a virtual robot or a stand-in without the service
            log.warning("NAOqi %s unavailable (%s): %s", service, error_line(exc), lost)

    def _read_memory(self, key: str) -> Any:
        """``ALMemory.getData(key)``, or None when the key is unknown (warned once per key)."""
        try:
            return self.memory.getData(key)
        except RuntimeError as exc:
            if key not in self._warned:
                self._warned.add(key)
                log.warning("NAOqi ALMemory has no %r yet (%s): read as unknown", key, error_line(exc))
            return None

    def _read_fall_key(self, key: str) -> None:
        if self._read_memory(key):
            self._on_fall_event(True)

    def _sample_kinematics(self) -> None:
        """One sample of head angles, camera transform and odometry, stamped mid-way through the reads."""
        sensors = self.params.use_sensors
        before = now()
        yaw, pitch = self.motion.getAngles(HEAD_JOINTS, sensors)
        T_nao = np.asarray(self.motion.getTransform("CameraTop", FRAME_ROBOT, sensors), float).reshape(4, 4)
        odom = self.motion.getRobotPosition(sensors)
        after = now()
        values = np.concatenate([[yaw, pitch], T_nao.ravel(), np.asarray(odom, float)[:3]])
        if not np.isfinite(values).all():
            raise ValueError(f"non-finite reading: head {yaw}, {pitch}, odometry {odom}, camera transform {T_nao.tolist()}")
        self.kinematics.add(KinematicSample(
            0.5 * (before + after), (float(yaw), float(pitch)), T_nao, (float(odom[0]), float(odom[1]), float(odom[2]))
        ))
        self._probe_clock()

    def _probe_clock(self) -> None:
        """A stamped ALMemory write every 1 / ``clock_probe_rate`` s (module docstring, Clocks)."""
        if self.params.clock_probe_rate <= 0.0 or time.monotonic() < self._next_probe:
            return
        self._next_probe = time.monotonic() + 1.0 / self.params.clock_probe_rate
        self._probe_count += 1
        try:
            sent = now()
            self.memory.insertData(CLOCK_PROBE_KEY, self._probe_count)
            answered = now()
            value, seconds, micros = self.memory.getTimestamp(CLOCK_PROBE_KEY)
        except Exception as exc:  # noqa: BLE001 - an ALMemory without insertData or getTimestamp: the camera bound alone
            self._next_probe = math.inf
            log.warning("NAOqi clock probe unavailable (%s): frames stamped by the camera's latency bound", exc)
            return
        if int(value) == self._probe_count:  # not overwritten by another client in between
            self._probe.add(sent, answered, float(seconds) + 1e-6 * float(micros))

    def _sample_loop(self) -> None:
        """Sample at ``kinematics_rate`` until close; a failing read is logged (at most once a second) and retried."""
        period = 1.0 / self.params.kinematics_rate
        due = time.monotonic()
        last_error = -math.inf
        while True:
            try:
                self._sample_kinematics()
            except Exception as exc:  # noqa: BLE001 - a lost robot link must not kill the sampler
                if time.monotonic() - last_error > 1.0:
                    last_error = time.monotonic()
                    log.error("NAOqi kinematics sample failed: %s", exc)
            due += period
            wait = due - time.monotonic()
            if wait < 0.0:  # behind (slow calls): sample again at once and keep the period from now
                due, wait = time.monotonic(), 0.0
            if self._stop_sampling.wait(wait):
                return

    def _stop_sampler(self) -> None:
        self._stop_sampling.set()
        if self._sampler is not None:
            self._sampler.join(timeout=5.0)

    def _on_fall_event(self, value: Any) -> None:
        if value:
            if not self._fallen.is_set():
                log.warning("NAOqi reports a fall")
            self._fallen.set()

    def grab_frame(self, timeout: float) -> Optional[CameraFrame]:
        deadline = time.monotonic() + timeout
        poll = 0.25 / max(self.fps, 1.0)
        while True:
            image = self.video.getImageRemote(self._camera)
            received = now()
            if image and len(image) >= 7:
                robot_stamp = (int(image[4]), int(image[5]))
                if robot_stamp != self._last_stamp:
                    self._last_stamp = robot_stamp
                    frame = self._frame(image, robot_stamp[0] + 1e-6 * robot_stamp[1], received)
                    if frame is not None:
                        return frame
                else:
                    self.duplicates += 1
            if time.monotonic() + poll > deadline:
                return None
            time.sleep(poll)

    def _frame(self, image: Sequence[Any], robot_stamp: float, received: float) -> Optional[CameraFrame]:
        """The frame with its kinematics at the capture stamp; None (counted) if the history has none there."""
        stamp = self._capture_stamp(robot_stamp, received)
        bgr = self._to_subscribed_size(image_to_bgr(int(image[0]), int(image[1]), int(image[3]), image[6]))
        # learnt a frame late, when the history holds the instants after its stamp that an exposure may show
        learner = self.latency if self.clock_source == "camera" else self.exposure
        pending, self._unlearnt = self._unlearnt, (learner, bgr, stamp + learner.tau)  # the stamp before its correction
        if pending is not None and pending[0] is learner:
            self._learn_latency(*pending)
        # a capture newer than the newest sample: wait for the next one, as long as a gap is tolerated
        kin = self.kinematics.wait_at(stamp, self.params.kinematics_max_gap)
        if isinstance(kin, str):
            self.kinematics_dropped[kin] += 1
            if time.monotonic() - self._last_drop_log > 1.0:  # at most once a second
                self._last_drop_log = time.monotonic()
                log.warning("NAOqi frame at %.3f dropped: %s; dropped so far %s", stamp, kin, dict(self.kinematics_dropped))
            return None
        return CameraFrame(
            image=bgr,
            stamp=stamp,
            head_yaw=kin.head[0],
            head_pitch=kin.head[1],
            T_BC=nao_to_optical(kin.T),
            odom=kin.odom,
            stamp_std=self._stamp_std(learner),
        )

    def _stamp_std(self, learner: LatencyEstimator) -> float:
        """s: how far a frame's stamp may be from the instant its image shows (module docstring, Exposure)."""
        if learner.learnt:
            return LEARNT_STD
        return self.params.unlearnt_latency_std if learner is self.latency else self.params.exposure_offset_max / math.sqrt(3.0)

    def _to_subscribed_size(self, bgr: np.ndarray) -> np.ndarray:
        """The image at the subscribed resolution. A NAOqi answering another size of the same sensor
        (the same aspect) is resized, which keeps the pinhole model (every NAO resolution bins the
        whole sensor); another aspect raises ``ValueError`` naming both sizes."""
        width, height = self.image_size
        got_height, got_width = bgr.shape[:2]
        if (got_width, got_height) == (width, height):
            return bgr
        if got_width * height != got_height * width:
            raise ValueError(f"image of {got_width}x{got_height}: not the {width}x{height} ({self.resolution}) "
                             "subscribed, nor the same aspect")
        self._warn_once("size", f"NAOqi serves {got_width}x{got_height} images for the {width}x{height} "
                         f"({self.resolution}) subscription: resized to {width}x{height}")
        return cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA if got_width > width else cv2.INTER_LINEAR)

    def _learn_latency(self, learner: LatencyEstimator, bgr: np.ndarray, stamp: float) -> None:
        """Feed a latency estimator (nao_bridge/camera_latency.py: the camera bound's latency, or a stamped
        frame's exposure offset) the frame, its uncorrected stamp and the camera's headings over the history."""
        samples = self.kinematics.samples()
        if len(samples) < 2:
            return
        stamps = np.array([k.stamp for k in samples])
        odom = np.array([k.odom for k in samples])
        headings = camera_heading(odom[:, 2], np.array([k.T for k in samples]))
        position = [np.interp(stamp, stamps, odom[:, i]) for i in (0, 1)]
        learner.add(bgr, stamp, (stamps, np.unwrap(headings)), position)
        told = self._logged_tau[learner]
        if learner.learnt and (told is None or abs(learner.tau - told) >= 0.005):
            self._logged_tau[learner] = learner.tau
            what = "before the camera bound" if learner is self.latency else "before their NAOqi stamps (the exposure's middle)"
            log.info("NAOqi frames from their images: stamped %.0f ms %s (%d turning pairs)", 1e3 * learner.tau, what,
                     learner.pairs_used)

    def _capture_stamp(self, robot_stamp: float, received: float) -> float:
        """The frame's capture time on the bridge clock: by the probe while it agrees with the camera
        bound; without it, the robot's stamp itself when the clocks agree, else the camera bound; less
        the latency or exposure offset the images show (module docstring)."""
        camera_stamp = self._clock.update(robot_stamp, received)
        probe = self._probe.best()
        if probe is not None:
            offset, error = probe
            shortest_latency = self._clock.bound - offset
            if -error - 1e-3 <= shortest_latency <= self.params.camera_latency_max:
                self.clock_source = "probe"
                return robot_stamp + offset - self.exposure.tau
            self._warn_once("negative" if shortest_latency < 0.0 else "too long",
                             f"NAOqi clock probe disagrees with the camera (shortest latency {shortest_latency:.3f} s): "
                             "ALMemory and the camera stamp on different clocks?")
        if self.params.camera_latency_min <= self._clock.bound <= self.params.camera_latency_max:
            self.clock_source = "synchronized"  # robot stamps already on the bridge clock, as NTP keeps them
            self._warn_once("synchronized", f"NAOqi image stamps agree with this clock (shortest latency "
                             f"{self._clock.bound:.3f} s): clocks taken as synchronized, frames stamped as the robot stamps them")
            return robot_stamp - self.exposure.tau
        self.clock_source = "camera"
        self._warn_once("camera", "NAOqi robot clock off this one and no clock probe: frames stamped by the camera's "
                         "latency bound less the latency its images show (docs/frames.md)")
        return camera_stamp - self.latency.tau

    def _warn_once(self, reason: str, message: str) -> None:
        if reason not in self._warned_reasons:
            self._warned_reasons.add(reason)
            log.warning(message)

    def walk(self, v: float, vy: float, omega: float) -> None:
        self.motion.move(float(v), float(vy), float(omega))
        self._walk_commanded = (v, vy, omega) != (0.0, 0.0, 0.0)

    def stop_walking(self) -> None:
        self.motion.stopMove()
        self._walk_commanded = False

    @functools.cached_property
    def remote(self) -> bool:
        """Whether NAOqi runs on another machine (a robot): the robot-side watchdog is then required."""
        return not on_this_machine(self.url.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]"))

    def move_is_active(self) -> bool:
        if "moveIsActive" in self._motion_lacks:
            return self._walk_commanded
        return bool(self.motion.moveIsActive())

    def kill_move(self) -> None:
        if "killMove" in self._motion_lacks:
            self.stop_walking()
        else:
            self.motion.killMove()

    def rest(self) -> None:
        self.motion.rest()

    def heartbeat(self, count: int) -> None:
        self.memory.insertData(HEARTBEAT_KEY, int(count))

    def watchdog_count(self) -> Optional[int]:
        try:
            return int(self.memory.getData(WATCHDOG_KEY))
        except RuntimeError:  # the key does not exist: no watchdog ever ran on this robot
            return None

    def set_head(self, yaw: float, pitch: float, speed_fraction: float) -> None:
        self.motion.setAngles(HEAD_JOINTS, [float(yaw), float(pitch)], float(speed_fraction))

    def read_state(self) -> RobotState:
        odom = self.motion.getRobotPosition(self.params.use_sensors)
        yaw, pitch = self.motion.getAngles(HEAD_JOINTS, self.params.use_sensors)
        for key in self._polled_fall_keys:
            self._read_fall_key(key)
        charge = self._read_memory(BATTERY_KEY)
        battery = float(charge) if isinstance(charge, (int, float)) and math.isfinite(charge) else None
        return RobotState(
            stamp=now(),
            odom=(float(odom[0]), float(odom[1]), float(odom[2])),
            head_yaw=float(yaw),
            head_pitch=float(pitch),
            walking=self.move_is_active(),
            fallen=self._fallen.is_set(),
            battery=None if battery is None else min(max(battery, 0.0), 1.0),
        )

    def close(self) -> None:
        with self._close_lock:
            if self._closed or self._session is None:
                self._closed = True
                return
            self._closed = True
        steps = [("stopMove", self.motion.stopMove), ("stop the kinematics sampler", self._stop_sampler)]
        steps += [("disconnect fall signal", lambda s=s, k=k: s.signal.disconnect(k)) for s, k in self._fall_links]
        if self._camera is not None:
            steps.append(("unsubscribe camera", lambda: self.video.unsubscribe(self._camera)))
        if self.params.rest_on_exit:
            steps.append(("rest", self.motion.rest))
        steps.append(("close session", self._session.close))
        for name, step in steps:  # each step runs even when an earlier one failed
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - a dead robot link must not stop the shutdown
                log.error("NAOqi close: %s failed: %s", name, exc)
