"""The station's Zenoh link to one bridge: info, frames, state, truth, liveliness, commands.

Everything the bridge sends lands in one inbox, in arrival order, stamped with the station clock
when it arrived; the control loop drains it. Frame bytes go to a mailbox and only a wake-up goes
through the inbox: the loop takes every frame that arrived since its last pass, logs them all and
processes only the newest, so a slow pass never builds a backlog of stale frames, and callbacks
never block Zenoh's receive thread. The bridge's liveliness token going away
(crash, exit, or a frozen peer after the link lease) becomes a ``bridge_lost`` event; the
station declares its own token ``station/alive/<id>`` so the bridge can stop the robot when the
station goes away.

One owner: :meth:`BridgeLink.start` takes the bridge's lease (first come) and every command
carries its secret; :meth:`close` hands it back. A lease lost to ``station_lost`` is never taken
again silently: :meth:`rearm` is the explicit re-arm. A state saying the bridge could not
confirm a stop (``watchdog == "stop_failed"``) becomes a ``bridge_lost`` event with that reason
as payload, so the mission aborts; so does a bridge that keeps refusing to walk because the
robot-side watchdog it requires does not answer (``watchdog == "no_robot_watchdog"`` for
``watchdog_grace`` s): the reason says how to install it or opt out.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import List, Optional, Tuple

import zenoh

from nao_core.clock import now
from nao_core.protocol import (
    HeadCommand,
    Info,
    LeaseReply,
    LeaseRequest,
    ProtocolError,
    RobotKeys,
    State,
    WalkCommand,
    decode,
    encode,
)
from nao_core.transport import TransportConfig, open_session


@dataclass(frozen=True)
class Received:
    kind: str  # 'frame', 'state', 'truth', 'bridge_lost'
    t: float  # station clock at arrival, s
    payload: bytes = b""


class BridgeUnavailable(RuntimeError):
    """The bridge could not be reached, did not answer its info query or refused the lease."""


NO_ROBOT_WATCHDOG = ("no_robot_watchdog: the bridge refuses to walk the robot because the robot-side watchdog "
                     "does not answer; install it (nao-bridge install-watchdog HOST) or start the bridge with "
                     "--without-watchdog (docs/security.md)")


class BridgeLink:
    def __init__(self, transport: TransportConfig, robot_name: str, watchdog_grace: Optional[float] = None):
        """``transport``: connect endpoint(s), lease, and for a lab network TLS (``TransportConfig.secure``);
        ``watchdog_grace``: s a bridge may refuse to walk for want of the robot-side watchdog
        (``station.watchdog_grace``; None: no limit)."""
        self.endpoint = ", ".join(transport.connect)
        self.keys = RobotKeys(robot_name)
        try:
            self.session = open_session(transport)
        except zenoh.ZError as exc:
            raise BridgeUnavailable(f"cannot open a Zenoh session to {self.endpoint}: {exc}") from None
        self.inbox: "queue.Queue[Received]" = queue.Queue()
        self._frame_lock = threading.Lock()
        self._frames: List[Received] = []  # arrived since the last take_frames()
        self._declared: list = []
        self._seq = 0
        self.station_id = str(self.session.zid())
        self.lease = ""
        self._abort_reported = False  # a bridge_lost for this lease (stop_failed, no robot watchdog) is in the inbox
        self._watchdog_grace = watchdog_grace
        self._no_watchdog_since: Optional[float] = None  # station clock of the first state in a run saying so

    def fetch_info(self, timeout: float) -> Tuple[Info, bytes]:
        """The bridge's info and its bytes as received; retries until ``timeout`` (s)."""
        deadline = time.monotonic() + timeout
        last_error = "no reply"
        while time.monotonic() < deadline:
            for reply in self.session.get(self.keys.info, timeout=min(1.0, max(0.1, deadline - time.monotonic()))):
                if reply.ok is None:
                    last_error = f"error reply: {reply.err.payload.to_bytes()[:200]!r}"
                    continue
                payload = reply.ok.payload.to_bytes()
                return decode(payload, Info), payload
            time.sleep(0.1)
        raise BridgeUnavailable(f"no info from the bridge at {self.endpoint} on {self.keys.info} within {timeout:g} s ({last_error})")

    def start(self, lease_timeout: float = 5.0) -> None:
        """Subscribe to everything, declare the station's liveliness token and take the lease."""
        sub = self.session.declare_subscriber
        self._declared += [
            sub(self.keys.camera_top, self._on_frame),
            sub(self.keys.state, self._on_state),
            sub(self.keys.sim_truth, lambda s: self._put("truth", s)),
            self.session.liveliness().declare_subscriber(self.keys.alive, self._on_alive, history=True),
            self.session.liveliness().declare_token(self.keys.station_token(self.station_id)),
        ]
        block = zenoh.CongestionControl.BLOCK
        self._walk = self.session.declare_publisher(self.keys.cmd_walk, congestion_control=block)
        self._head = self.session.declare_publisher(self.keys.cmd_head, congestion_control=block)
        self.rearm(lease_timeout)

    def rearm(self, timeout: float = 5.0) -> None:
        """Take the bridge's lease (first come): the explicit (re-)arm. Raises BridgeUnavailable.

        ``no_token`` (the bridge has not seen this station's token yet) is retried until ``timeout``;
        ``held`` (another station owns the robot) is final.
        """
        deadline = time.monotonic() + timeout
        reason = "no reply"
        while True:
            reply = self._lease_query(LeaseRequest(op="take", station=self.station_id, lease=""),
                                      min(1.0, max(0.1, deadline - time.monotonic())))
            if reply is not None:
                if reply.granted:
                    self.lease, self._seq = reply.lease, 0
                    self._abort_reported = False
                    return
                reason = reply.reason
                if reason == "held":
                    raise BridgeUnavailable(f"the bridge at {self.endpoint} is commanded by another station "
                                            "(it must release the lease first)")
            if time.monotonic() >= deadline:
                raise BridgeUnavailable(f"no lease from the bridge at {self.endpoint} within {timeout:g} s ({reason})")
            time.sleep(0.05)

    def release(self) -> None:
        """Hand the lease back (the explicit hand-over to another station)."""
        if self.lease:
            self._lease_query(LeaseRequest(op="release", station=self.station_id, lease=self.lease), 1.0)
            self.lease = ""

    def _lease_query(self, request: LeaseRequest, timeout: float):
        for reply in self.session.get(self.keys.lease, payload=encode(request), timeout=timeout):
            if reply.ok is not None:
                try:
                    return decode(reply.ok.payload.to_bytes(), LeaseReply)
                except ProtocolError:
                    return None
        return None

    def take_frames(self) -> List[Received]:
        with self._frame_lock:
            frames, self._frames = self._frames, []
        return frames

    def send_walk(self, vx: float, vy: float, omega: float, ttl: float) -> WalkCommand:
        command = WalkCommand(seq=self._next_seq(), vx=vx, vy=vy, omega=omega, ttl=ttl, lease=self.lease)
        self._walk.put(encode(command))
        return command

    def send_head(self, yaw: float, pitch: float, speed: float) -> HeadCommand:
        command = HeadCommand(seq=self._next_seq(), yaw=yaw, pitch=pitch, speed=speed, lease=self.lease)
        self._head.put(encode(command))
        return command

    def close(self) -> None:
        """Release the lease, undeclare everything (the token disappears), close the session. Idempotent."""
        try:
            self.release()
        except zenoh.ZError:
            pass
        declared, self._declared = self._declared, []
        for entity in reversed(declared):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        try:
            self.session.close()
        except zenoh.ZError:
            pass

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _put(self, kind: str, sample: zenoh.Sample) -> None:
        self.inbox.put(Received(kind, now(), sample.payload.to_bytes()))

    def _on_state(self, sample: zenoh.Sample) -> None:
        received = Received("state", now(), sample.payload.to_bytes())
        self.inbox.put(received)
        try:
            watchdog = decode(received.payload, State).watchdog
        except ProtocolError:
            return  # the control loop logs and counts it
        if watchdog == "no_robot_watchdog":
            self._no_watchdog_since = self._no_watchdog_since or received.t
        else:
            self._no_watchdog_since = None
        if self._abort_reported:
            return
        if watchdog == "stop_failed":
            self._abort_reported = True
            self.inbox.put(Received("bridge_lost", received.t, b"stop_failed: the bridge cannot confirm a stop"))
        elif (self._watchdog_grace is not None and self._no_watchdog_since is not None
              and received.t - self._no_watchdog_since >= self._watchdog_grace):
            self._abort_reported = True
            self.inbox.put(Received("bridge_lost", received.t, NO_ROBOT_WATCHDOG.encode()))

    def _on_frame(self, sample: zenoh.Sample) -> None:
        with self._frame_lock:
            self._frames.append(Received("frame", now(), sample.payload.to_bytes()))
        self.inbox.put(Received("frame", now()))  # wakes the loop; the bytes are in the mailbox

    def _on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.inbox.put(Received("bridge_lost", now()))
