"""``station replay LOG.mcap``: re-run the agent on the recorded inputs, compare every decision.

The live loop journals each input it hands to the pilot on ``/station/input`` right after the
input's raw bytes (:mod:`station.run`). Replay rebuilds the configuration and the bridge info
from the log, feeds the journalled inputs in file order to a fresh :class:`station.pilot.Pilot`,
and compares each output, byte for byte in its logged JSON form, with the recorded output of the
same topic and rank. The first mismatch is reported (topic, rank, time, both payloads); a log cut
by a crash is compared up to its end. The run logged a digest of the agent's code: when the code
has changed since, the result says so (a divergence is then expected, not a bug).
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Tuple, Union

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from tqdm import tqdm

from nao_core.config import from_mapping
from nao_core.landmark_map import LandmarkMap
from nao_core.protocol import Frame, FrameMeta, Info, State, decode
from station.config import SECTIONS, StationConfig
from station.mcap_log import LogError, encode_json, read_log
from station.pilot import Pilot, Step
from station.run import code_digest
from station.topics import (
    AGENT_PREFIX,
    CONFIG,
    DECISION,
    FRAME_IMAGE,
    FRAME_META,
    INFO,
    INPUT,
    STATE,
)


def load_setup(path: Union[str, Path]) -> Tuple[StationConfig, Info]:
    """The resolved configuration and the bridge info recorded at the start of a run."""
    config, info, _ = load_recorded(path)
    return config, info


def load_recorded(path: Union[str, Path]) -> Tuple[StationConfig, Info, Optional[str]]:
    """Configuration, bridge info and the digest of the agent's code recorded at the start of a run."""
    record: Optional[Dict[str, Any]] = None
    info: Optional[Info] = None
    for message in read_log(path, topics={CONFIG, INFO}):
        if message.topic == CONFIG:
            record = message.json()
        else:
            info = decode(message.data, Info)
        if record is not None and info is not None:
            break
    if record is None or info is None:
        raise LogError(f"{path}: no {CONFIG if record is None else INFO} message: not a station run log")
    sections = {name: from_mapping(cls, record[name], source=f"{path}:{CONFIG}.{name}") for name, cls in SECTIONS.items()}
    landmarks = from_mapping(LandmarkMap, record["landmarks"], source=f"{path}:{CONFIG}.landmarks")
    return StationConfig(landmarks=landmarks, **sections), info, record.get("code")


def iter_inputs(path: Union[str, Path]) -> Iterator[Tuple[Dict[str, Any], Any]]:
    """(journal entry, input) in processing order: a State, a Frame, or None for ticks and events."""
    state: Optional[State] = None
    meta: Optional[Tuple[FrameMeta, bytes]] = None
    frames: Dict[int, Frame] = {}
    for message in read_log(path, topics={STATE, FRAME_META, FRAME_IMAGE, INPUT}):
        if message.topic == STATE:
            state = decode(message.data, State)
        elif message.topic == FRAME_META:
            meta = (decode(message.data, FrameMeta), message.data)
        elif message.topic == FRAME_IMAGE and meta is not None:
            frames = {meta[0].seq: Frame(meta[0], meta[1], message.proto(CompressedImage).data)}
            meta = None
        elif message.topic == INPUT:
            entry = message.json()
            kind = entry["kind"]
            yield entry, state if kind == "state" else frames.get(entry.get("seq")) if kind == "frame" else None


def feed(pilot: Pilot, entry: Dict[str, Any], payload: Any) -> Step:
    """Hand one journalled input to the pilot, as the live loop did."""
    kind, t = entry["kind"], entry["t"]
    if kind == "state":
        return pilot.on_state(payload, t)
    if kind == "frame":
        if payload is None:
            raise LogError(f"frame {entry.get('seq')} journalled at t={t} is not in the log")
        return pilot.on_frame(payload, t)
    if kind == "tick":
        decision, plan = pilot.tick(t), pilot.replan(t)
        return Step(decision.outputs + plan.outputs, decision.decision)
    if kind == "bridge_lost":
        return pilot.on_bridge_lost(t)
    if kind == "interrupt":
        return pilot.on_interrupt(t, entry["signal"])
    raise LogError(f"unknown input kind {kind!r} at t={t}")


@dataclass
class Divergence:
    topic: str
    rank: int  # index among that topic's outputs
    t: float
    recorded: Optional[str]
    replayed: str


@dataclass
class ReplayResult:
    inputs: int = 0
    compared: int = 0
    decisions: int = 0
    divergence: Optional[Divergence] = None
    unmatched: Dict[str, int] = field(default_factory=dict)  # recorded outputs replay did not produce
    code_changed: bool = False  # the agent's code differs from the run's: a divergence is expected

    @property
    def ok(self) -> bool:
        return self.divergence is None and not self.unmatched

    def as_dict(self) -> Dict[str, Any]:
        return {**dataclasses.asdict(self), "ok": self.ok}


def replay(path: Union[str, Path], progress: bool = False) -> ReplayResult:
    config, info, code = load_recorded(path)
    recorded: Dict[str, List[bytes]] = defaultdict(list)
    for message in read_log(path):
        if message.topic.startswith(AGENT_PREFIX):
            recorded[message.topic].append(message.data)
    pilot = Pilot(config, info)
    result = ReplayResult(code_changed=code != code_digest())
    produced: Dict[str, int] = defaultdict(int)
    log_ended = False
    total = sum(len(v) for v in recorded.values())
    with tqdm(total=total, desc="replay", unit="output", disable=not progress) as bar:
        for entry, payload in iter_inputs(path):
            result.inputs += 1
            for topic, output in feed(pilot, entry, payload).outputs:
                rank = produced[topic]
                produced[topic] += 1
                if rank >= len(recorded[topic]):
                    log_ended = True  # the log was cut after this input: nothing left to compare
                    continue
                replayed = encode_json(output)
                result.compared += 1
                result.decisions += topic == DECISION
                bar.update()
                if replayed != recorded[topic][rank]:
                    result.divergence = Divergence(topic, rank, entry["t"], recorded[topic][rank].decode(), replayed.decode())
                    return result
    if not log_ended:
        result.unmatched = {topic: len(v) - produced[topic] for topic, v in recorded.items() if len(v) > produced[topic]}
    return result
