"""The pilot's inputs as typed events, and their journal form on ``/station/input``.

Every event carries the station time ``t`` at which it was handled. The live loop builds events
from what the bridge sent and hands each to ``Pilot.handle`` (journalling it first); replay
rebuilds the same events from the journal (:mod:`station.runlog`) and hands them to a fresh pilot.
A tick is two events, handled in this order in both: ``Tick`` (the mission's decision; the live
loop sends its commands at once) then ``Replan`` (the planner, when due).

Journal entry: ``{"kind": KIND, "t": t}`` plus ``seq`` (a frame: its payload is the logged frame
of that sequence number) or ``signal`` (an interrupt). States and frames are not copied into the
journal: their raw bytes are logged just before the entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Dict, Literal, Optional, Type, Union

from nao_core.protocol import Frame, State
from nao_core.protocol.schema import record_schema
from station.mcap_log import encode_json

LIVELINESS_LOST = "the bridge went away (liveliness token lost)"


@dataclass(frozen=True)
class StateReceived:
    KIND: ClassVar[str] = "state"
    t: float
    state: State


@dataclass(frozen=True)
class FrameReceived:
    KIND: ClassVar[str] = "frame"
    t: float
    frame: Frame


@dataclass(frozen=True)
class Tick:
    KIND: ClassVar[str] = "tick"
    t: float


@dataclass(frozen=True)
class Replan:
    KIND: ClassVar[str] = "replan"
    t: float


@dataclass(frozen=True)
class BridgeLost:
    KIND: ClassVar[str] = "bridge_lost"
    t: float
    reason: str = LIVELINESS_LOST


@dataclass(frozen=True)
class Interrupted:
    KIND: ClassVar[str] = "interrupt"
    t: float
    signal: str


Event = Union[StateReceived, FrameReceived, Tick, Replan, BridgeLost, Interrupted]
EVENTS: Dict[str, Type[Event]] = {cls.KIND: cls for cls in (StateReceived, FrameReceived, Tick, Replan, BridgeLost, Interrupted)}


@dataclass(frozen=True)
class JournalEntry:
    """One line of the journal (``/station/input``)."""

    NAME: ClassVar[str] = "station.Input"
    kind: Literal[tuple(EVENTS)]  # type: ignore[valid-type]
    t: float
    seq: Optional[int] = None
    signal: Optional[str] = None
    reason: Optional[str] = None  # bridge_lost: why (older logs: none, the liveliness token)

    @classmethod
    def of(cls, event: Event) -> "JournalEntry":
        return cls(event.KIND, event.t, seq=event.frame.meta.seq if isinstance(event, FrameReceived) else None,
                   signal=event.signal if isinstance(event, Interrupted) else None,
                   reason=event.reason if isinstance(event, BridgeLost) else None)

    def to_json(self) -> bytes:
        fields = {"kind": self.kind, "t": self.t, "seq": self.seq, "signal": self.signal, "reason": self.reason}
        return encode_json({k: v for k, v in fields.items() if v is not None})

    @classmethod
    def schema(cls):
        return record_schema(cls, cls.NAME)
