"""The simulated NAO in its room: body and head dynamics, odometry, fall, battery, camera, truth.

Time is the real clock (``clock()``, default ``nao_core.clock.now``: wall time that never jumps).
The world advances lazily, under a lock, on every call, in fixed steps of ``dt`` (so a run is a
function of the seed and of the command timeline alone, not of how often it is queried). One step:

* walking velocity u = (v, vy, omega), first-order lag towards the (clamped) command c::

      u <- u + (1 - exp(-dt / tau)) (c - u)

* truth moves by the per-run scaled velocity plus slip, odometry by the nominal one (so odometry
  drifts from truth; it starts at (0, 0, 0) where the robot starts)::

      delta_true = diag(s) u dt + n,   n_xy ~ N(0, sigma_t^2 |u_xy dt|),  n_theta ~ N(0, sigma_r^2 (|u_xy dt| + |omega dt|))
      delta_odom = u dt,               s ~ 1 + N(0, sigma_s^2) per axis, drawn once per run

  each integrated at the mid-step heading: x += R(theta + dtheta / 2) delta_xy; the walls stop the
  true body ``BODY_RADIUS`` from them (no other collisions);
* head joints move towards their targets at ``speed_fraction * max_speed`` each, then
  ``robot.head.clamp``;
* torso sway while walking, of amplitude a = max(|v|/v_max, |vy|/vy_max, |omega|/omega_max) <= 1 and
  phase phi advancing at 2 pi f (f the lateral frequency, one cycle per two steps): the camera is
  moved about the feet by

      Trans(0, a L sin phi, a B (cos 2 phi - 1) / 2) Rx(a rho sin phi) Ry(a psi sin 2 phi)

  in the robot frame (lateral shift L, roll rho at f, pitch psi and bob B at the step frequency 2 f);
  the reported camera transform contains ``reported_fraction`` of it (the joint sensors see most of it);
* a fallen robot lies face down (body pitched by 90 degrees about the feet, camera
  ``fallen_camera_height`` above the floor) and ignores walk commands;
* the battery drains at a constant rate, faster while walking.

Past kinematics. After every step (and every instantaneous change: teleport, fall, stand-up) the
world appends its kinematic state (pose, odometry, head, sway amplitude and phase, fall flag) to a
history of ``dynamics.history`` seconds. The state at time t is the last entry at or before t (the
state a real robot had then, on the step grid), so ``render(at=t)`` draws a frame captured in the
past (the NAOqi stand-in serves frames late) and ``kinematics_at(t)`` gives the sensor readings at
that instant (the truth the bridge's capture-time interpolation is checked against).
"""

from __future__ import annotations

import collections
import math
import numbers
import threading
import time
from typing import Callable, Deque, NamedTuple, Optional, Tuple, Union

import numpy as np

from nao_core.clock import now
from nao_core.geometry import Pose, planar_transform, rot_x, rot_y, wrap_angle
from nao_core.landmark_map import load_landmark_map
from nao_core.records import CameraFrame, RobotState
from nao_core.robot_model import RobotModel, nao_to_optical
from nao_sim.render import Renderer
from nao_sim.scenarios import Scenario, SimConfig, load_sim_config

BODY_RADIUS = 0.15  # m, how close the robot's origin gets to a wall
MOVING = 1e-3  # sway amplitude above which the robot counts as walking
FACE_DOWN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # Ry(+90 deg): up becomes forward


class _Kinematic(NamedTuple):
    """The world's moving state at one instant (an entry of the history)."""

    time: float
    pose: Pose
    odom: Pose
    head: Tuple[float, float]
    amplitude: float
    phase: float
    fallen: bool


class Kinematics(NamedTuple):
    """What the robot's sensors report at ``stamp``: ALMotion getAngles, getTransform, getRobotPosition."""

    stamp: float
    head: Tuple[float, float]  # (HeadYaw, HeadPitch), rad
    T_BC_nao: np.ndarray  # 4x4 camera in FRAME_ROBOT, NAO camera axes (reported: sway x reported_fraction)
    odom: Pose


def _integrate(pose: np.ndarray, dx: float, dy: float, dtheta: float) -> None:
    mid = pose[2] + 0.5 * dtheta
    c, s = math.cos(mid), math.sin(mid)
    pose[0] += c * dx - s * dy
    pose[1] += s * dx + c * dy
    pose[2] = math.remainder(pose[2] + dtheta, 2.0 * math.pi)


class SimWorld:
    """A simulated NAO in a room with landmarks and one object; thread-safe.

    ``scenario`` is a name in the config (``can``, ``remote``, ``figure``) or a ``Scenario``.
    """

    def __init__(
        self,
        scenario: Union[str, Scenario],
        robot_model: RobotModel,
        resolution: str = "qvga",
        seed: int = 0,
        config: Optional[SimConfig] = None,
        clock: Callable[[], float] = now,
    ):
        self.config = config or load_sim_config()
        self.scenario_name = scenario if isinstance(scenario, str) else "custom"
        self.scenario = self.config.scenario(scenario) if isinstance(scenario, str) else scenario
        self.robot = robot_model
        self.resolution = resolution
        self.seed = seed
        self.landmarks = load_landmark_map(self.config.landmark_path)
        self.renderer = Renderer(
            robot_model.camera.intrinsics(resolution),
            self.config.room,
            self.landmarks,
            self.scenario,
            self.config.noise.pixel_sigma,
            self.config.noise.gain_sigma,
            seed,
            self.config.noise.blur_sigma,
            self.config.noise.exposure,
            self.config.noise.response_gamma,
        )
        dyn = self.config.dynamics
        self._dyn = dyn
        roll, pitch = self.config.noise.mount_error
        self._mount = rot_x(roll) @ rot_y(pitch)  # the camera on its mount, in NAO camera axes: never reported
        self._rng = np.random.default_rng(seed)
        self.speed_scale = 1.0 + self._rng.normal(0.0, 1.0, 3) * np.asarray(dyn.speed_scale_sigma)
        self.start_pose = self._start_pose()
        self._clock = clock
        self._lock = threading.Lock()
        self._start_time = clock()
        self._steps = 0  # world time = start time + steps * dt
        self._time = self._start_time
        self._pose = np.array(self.start_pose)
        self._odom = np.zeros(3)
        self._command = np.zeros(3)
        self._velocity = np.zeros(3)
        self._head = np.zeros(2)
        self._head_target = np.zeros(2)
        self._head_speed = 0.0
        self._phase = 0.0
        self._amplitude = 0.0
        self._fallen = False
        self._battery = dyn.battery_initial
        self._frames = 0
        self._last_render: Optional[Tuple[float, np.ndarray]] = None
        self._history: Deque[_Kinematic] = collections.deque(maxlen=max(2, math.ceil(dyn.history / dyn.timestep) + 1))
        self._remember()

    def _start_pose(self) -> Pose:
        sc = self.scenario
        distance = self._rng.uniform(*sc.start_distance)
        azimuth = self._rng.uniform(*sc.start_azimuth)
        x = sc.position[0] + distance * math.cos(azimuth)
        y = sc.position[1] + distance * math.sin(azimuth)
        heading = azimuth + math.pi + self._rng.normal(0.0, sc.start_heading_sigma)
        return x, y, math.remainder(heading, 2.0 * math.pi)

    # -- dynamics ----------------------------------------------------------------------------

    def _advance(self) -> None:
        """Step the world up to the clock (caller holds the lock)."""
        dt = self._dyn.timestep
        # the tolerance absorbs rounding in the clock's sums, so a step is never lost to polling
        steps = max(math.floor((self._clock() - self._start_time) / dt + 1e-6) - self._steps, 0)
        if self._at_rest():  # nothing moves: only the battery drains, in one go (the history holds)
            self._battery = max(0.0, self._battery - steps * dt * self._dyn.battery_drain_idle)
            self._steps += steps
            self._time = self._start_time + self._steps * dt
        else:
            for _ in range(steps):
                self._step(dt)
                self._steps += 1
                self._time = self._start_time + self._steps * dt
                self._remember()

    def _remember(self) -> None:
        """Append the current kinematic state to the history (caller holds the lock)."""
        self._history.append(_Kinematic(
            self._time, _pose_tuple(self._pose), _pose_tuple(self._odom), (float(self._head[0]), float(self._head[1])),
            self._amplitude, self._phase, self._fallen,
        ))

    def _state_at(self, t: Optional[float]) -> _Kinematic:
        """The kinematic state at world time ``t`` (now if None): the last history entry at or before it."""
        if t is None:
            return self._history[-1]
        if not math.isfinite(t) or t >= self._time + self._dyn.timestep:  # within the current step is now
            raise ValueError(f"time {t!r} is not in the past of the world (now {self._time:.3f})")
        for entry in reversed(self._history):
            if entry.time <= t + 1e-9:
                return entry
        raise ValueError(
            f"time {t:.3f} is {self._history[0].time - t:.3f} s before the kept history "
            f"(dynamics.history = {self._dyn.history} s)"
        )

    def _at_rest(self) -> bool:
        return not (self._command.any() or self._velocity.any() or self._amplitude) and bool(
            (self._head == self._head_target).all()
        )

    def _step(self, dt: float) -> None:
        dyn = self._dyn
        tau = dyn.velocity_time_constant
        gain = 1.0 if tau == 0.0 else 1.0 - math.exp(-dt / tau)
        self._velocity += gain * (self._command - self._velocity)
        if not self._command.any() and np.abs(self._velocity).max() < 1e-6:
            self._velocity[:] = 0.0  # stopped: end the exponential tail
        nominal = self._velocity * dt
        if nominal.any():
            ds = math.hypot(nominal[0], nominal[1])
            true = self.speed_scale * nominal
            true[:2] += self._rng.normal(0.0, dyn.slip_translation * math.sqrt(ds), 2)
            true[2] += self._rng.normal(0.0, dyn.slip_rotation * math.sqrt(ds + abs(nominal[2])))
            _integrate(self._pose, *true)
            inside = self.config.room.half_size - BODY_RADIUS  # the walls stop the body; odometry walks on
            self._pose[:2] = np.clip(self._pose[:2], -inside, inside)
            _integrate(self._odom, *nominal)
        limits = self.robot.walk
        self._amplitude = min(1.0, max(
            abs(self._velocity[0]) / max(limits.v_max, 1e-9),
            abs(self._velocity[1]) / max(limits.vy_max, 1e-9),
            abs(self._velocity[2]) / max(limits.omega_max, 1e-9),
        ))
        walking = self._amplitude > MOVING
        if walking:
            self._phase = math.remainder(self._phase + 2.0 * math.pi * dyn.sway.frequency * dt, 2.0 * math.pi)
        step = self._head_speed * dt
        self._head += np.clip(self._head_target - self._head, -step, step)
        self._head[:] = self.robot.head.clamp(*self._head)
        self._battery = max(0.0, self._battery - dt * (dyn.battery_drain_idle + walking * dyn.battery_drain_walking))

    def _body(self, state: _Kinematic, fraction: float) -> np.ndarray:
        """Torso motion applied to the head kinematics: the fall, else ``fraction`` of the sway."""
        if state.fallen:
            T = np.eye(4)
            T[:3, :3] = FACE_DOWN
            T[2, 3] = self._dyn.fallen_camera_height + self.robot.camera.offset[0]  # camera at that height
            return T
        sway, a, phi = self._dyn.sway, state.amplitude * fraction, state.phase
        T = rot_x(a * sway.roll * math.sin(phi)) @ rot_y(a * sway.pitch * math.sin(2.0 * phi))
        T[1, 3] = a * sway.lateral * math.sin(phi)
        T[2, 3] = a * sway.bob * 0.5 * (math.cos(2.0 * phi) - 1.0)
        return T

    def _camera_nao(self, state: _Kinematic, fraction: float) -> np.ndarray:
        return self._body(state, fraction) @ self.robot.camera_in_robot_nao(*state.head)

    # -- commands ------------------------------------------------------------------------------

    def walk(self, v: float, vy: float, omega: float) -> None:
        """Walk at (v, vy, omega) (m/s, m/s, rad/s), clamped to the walk limits; ignored once fallen."""
        _check_finite(v=v, vy=vy, omega=omega)
        with self._lock:
            self._advance()
            if not self._fallen:
                self._command[:] = self.robot.walk.clamp(v, vy, omega)

    def stop_walking(self) -> None:
        """Command zero velocity; the walk decelerates with the velocity lag."""
        with self._lock:
            self._advance()
            self._command[:] = 0.0

    def set_head(self, yaw: float, pitch: float, speed_fraction: float) -> None:
        """Move the head towards (yaw, pitch) (clamped) at ``speed_fraction`` of the maximum joint speed."""
        _check_finite(yaw=yaw, pitch=pitch, speed_fraction=speed_fraction)
        if not 0.0 < speed_fraction <= 1.0:
            raise ValueError(f"speed_fraction must be in (0, 1], got {speed_fraction}")
        with self._lock:
            self._advance()
            self._head_target[:] = self.robot.head.clamp(yaw, pitch)
            self._head_speed = speed_fraction * self.robot.head.max_speed

    def inject_fall(self) -> None:
        """The robot falls now: walking stops at once and walk commands are ignored."""
        with self._lock:
            self._advance()
            self._fallen = True
            self._command[:] = 0.0
            self._velocity[:] = 0.0
            self._amplitude = 0.0
            self._remember()

    def stand_up(self) -> None:
        """Recover from a fall (as ALRobotPosture.goToPosture would), where the robot lies."""
        with self._lock:
            self._advance()
            self._fallen = False
            self._remember()

    def teleport(self, pose: Pose, head: Optional[Tuple[float, float]] = None) -> None:
        """Test hook: put the robot at the true ``pose`` at rest (head at ``head``); odometry is untouched."""
        _check_finite(x=pose[0], y=pose[1], theta=pose[2])
        with self._lock:
            self._advance()
            self._pose[:] = pose
            self._command[:] = 0.0
            self._velocity[:] = 0.0
            self._amplitude = 0.0
            if head is not None:
                self._head[:] = self._head_target[:] = self.robot.head.clamp(*head)
            self._remember()

    # -- readings ------------------------------------------------------------------------------

    def head_angles(self) -> Tuple[float, float]:
        with self._lock:
            self._advance()
            return float(self._head[0]), float(self._head[1])

    def odometry(self) -> Pose:
        """Odometry pose (x, y, theta) in the odometry frame (the start pose is (0, 0, 0))."""
        with self._lock:
            self._advance()
            return _pose_tuple(self._odom)

    def true_pose(self) -> Pose:
        """True robot pose (x, y, theta) in the world."""
        with self._lock:
            self._advance()
            return _pose_tuple(self._pose)

    def velocity(self) -> Tuple[float, float, float]:
        """Current nominal walking velocity (v, vy, omega) after the lag."""
        with self._lock:
            self._advance()
            return _pose_tuple(self._velocity)

    def is_walking(self) -> bool:
        with self._lock:
            self._advance()
            return self._walking()

    def _walking(self) -> bool:
        return bool(self._command.any()) or self._amplitude > MOVING

    def is_fallen(self) -> bool:
        with self._lock:
            self._advance()
            return self._fallen

    def battery(self) -> float:
        with self._lock:
            self._advance()
            return self._battery

    def state(self) -> RobotState:
        """All the robot's readings at one instant."""
        with self._lock:
            self._advance()
            return RobotState(
                stamp=self._time,
                odom=_pose_tuple(self._odom),
                head_yaw=float(self._head[0]),
                head_pitch=float(self._head[1]),
                walking=self._walking(),
                fallen=self._fallen,
                battery=self._battery,
            )

    def camera_in_robot_nao(self) -> np.ndarray:
        """Reported camera pose in the robot frame, NAO convention (ALMotion.getTransform("CameraTop", 2, True))."""
        with self._lock:
            self._advance()
            return self._camera_nao(self._state_at(None), self._dyn.sway.reported_fraction)

    def kinematics_at(self, t: float) -> Kinematics:
        """The sensor readings at past world time ``t`` (within ``dynamics.history``); ValueError outside it."""
        with self._lock:
            self._advance()
            state = self._state_at(t)
            T = self._camera_nao(state, self._dyn.sway.reported_fraction)
            stamp = self._grid(t)
        return Kinematics(stamp, state.head, T, state.odom)

    def _grid(self, t: float) -> float:
        """``t`` rounded down to the step grid (the instant whose state holds at t), at most now."""
        dt = self._dyn.timestep
        return min(self._start_time + math.floor((t - self._start_time) / dt + 1e-6) * dt, self._time)

    def render(self, at: Optional[float] = None) -> CameraFrame:
        """A camera frame captured now, or at past world time ``at`` (within ``dynamics.history``), with
        the head angles, reported T_BC (optical) and odometry of its capture; ValueError outside the history."""
        with self._lock:
            self._advance()
            state = self._state_at(at)
            stamp = self._time if at is None else self._grid(at)
            T_BC = nao_to_optical(self._camera_nao(state, self._dyn.sway.reported_fraction))
            T_WC = self._true_camera(state)
            R_open = self._shutter_opened(stamp)
            self._frames += 1
            index = self._frames
            self._last_render = (stamp, T_WC)
        image = self.renderer.render(T_WC, index, R_open)
        yaw, pitch = state.head
        return CameraFrame(image=image, stamp=stamp, head_yaw=yaw, head_pitch=pitch, T_BC=T_BC, odom=state.odom)

    def _true_camera(self, state: _Kinematic) -> np.ndarray:
        """T_WC of the camera as it truly is (the whole sway, the mount error)."""
        return planar_transform(*state.pose) @ nao_to_optical(self._camera_nao(state, 1.0) @ self._mount)

    def _shutter_opened(self, stamp: float) -> Optional[np.ndarray]:
        """R_WC when the shutter of a frame stamped ``stamp`` opened (``noise.shutter`` before it); None
        without a shutter time or before the kept history (caller holds the lock)."""
        shutter = self.config.noise.shutter
        if shutter <= 0.0 or stamp - shutter < self._history[0].time:
            return None
        return self._true_camera(self._state_at(stamp - shutter))[:3, :3]

    def truth(self) -> dict:
        """Ground truth, JSON-able: robot, odometry origin, camera at the last render, object, scenario."""
        with self._lock:
            self._advance()
            sc = self.scenario
            camera = None
            if self._last_render is not None:
                camera = {"stamp": self._last_render[0], "T_WC": self._last_render[1].tolist()}
            return {
                "scenario": self.scenario_name,
                "seed": self.seed,
                "stamp": self._time,
                "robot_pose": list(_pose_tuple(self._pose)),
                "odom_origin": list(self.start_pose),
                "odom": list(_pose_tuple(self._odom)),
                "speed_scale": [float(s) for s in self.speed_scale],
                "fallen": self._fallen,
                "camera": camera,
                "object": {
                    "kind": sc.kind,
                    "centre": list(sc.position),
                    "yaw": sc.yaw,
                    "radius": sc.radius,
                    "height": sc.height,
                    "parts": [
                        {"shape": p.shape, "centre": list(p.centre), "size": list(p.size), "yaw": p.yaw} for p in sc.parts
                    ],
                },
            }


def orbit_pose(rng: np.random.Generator, centre: Tuple[float, float]) -> Pose:
    """A pose on the pilot's orbit round ``centre``: 0.6-1.1 m from it at an azimuth U(-pi, pi),
    heading at it within N(0, 0.2 rad) (the still views of tests and benchmarks)."""
    d, az = rng.uniform(0.6, 1.1), rng.uniform(-math.pi, math.pi)
    return (centre[0] + d * math.cos(az), centre[1] + d * math.sin(az), wrap_angle(az + math.pi + rng.normal(0.0, 0.2)))


def _pose_tuple(a: np.ndarray) -> Pose:
    return float(a[0]), float(a[1]), float(a[2])


def _check_finite(**values: float) -> None:
    for name, value in values.items():
        if not isinstance(value, numbers.Real) or isinstance(value, bool) or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
