"""``station replay LOG.mcap``: re-run the agent on the recorded events, compare every output.

The live loop journals each event it hands to the pilot on ``/station/input`` right after the
event's raw bytes (:mod:`station.run`). Replay rebuilds the configuration and the bridge info
from the log (:mod:`station.runlog`), hands the journalled events in file order to a fresh
:class:`station.pilot.Pilot` through the same ``handle``, and compares each output record, byte
for byte in its logged JSON form, with the recorded output of the same topic and rank. The first
mismatch is reported (topic, rank, time, both payloads); a log cut by a crash is compared up to
its end. The run logged a digest of the pilot's code: when the code has changed since, the result
says so (a divergence is then expected, not a bug).
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

from tqdm import tqdm

from nao_core.protocol import ProtocolError
from station.mcap_log import LogError, read_log
from station.pilot import Pilot
from station.runlog import code_digest, iter_events, load_recorded
from station.topics import AGENT_PREFIX, DECISION


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
    unreadable: Optional[str] = None  # a recorded input today's code cannot read (e.g. an older protocol)

    @property
    def ok(self) -> bool:
        return self.divergence is None and not self.unmatched and self.unreadable is None

    def as_dict(self) -> Dict[str, Any]:
        return {**dataclasses.asdict(self), "ok": self.ok}


def replay(path: Union[str, Path], progress: bool = False) -> ReplayResult:
    setup = load_recorded(path)
    recorded: Dict[str, List[bytes]] = defaultdict(list)
    for message in read_log(path):
        if message.topic.startswith(AGENT_PREFIX):
            recorded[message.topic].append(message.data)
    pilot = Pilot(setup.config, setup.info)
    result = ReplayResult(code_changed=setup.code != code_digest())
    produced: Dict[str, int] = defaultdict(int)
    log_ended = False
    total = sum(len(v) for v in recorded.values())
    events = iter_events(path, setup.journal)
    with tqdm(total=total, desc="replay", unit="output", disable=not progress) as bar:
        while True:
            try:
                event = next(events, None)
            except (ProtocolError, LogError) as exc:  # compared so far; the rest cannot be replayed
                result.unreadable = f"after {result.inputs} inputs: {exc}"
                return result
            if event is None:
                break
            result.inputs += 1
            for output in pilot.handle(event).outputs:
                topic = output.TOPIC
                rank = produced[topic]
                produced[topic] += 1
                if rank >= len(recorded[topic]):
                    log_ended = True  # the log was cut after this input: nothing left to compare
                    continue
                replayed = output.to_json()
                result.compared += 1
                result.decisions += topic == DECISION
                bar.update()
                if replayed != recorded[topic][rank]:
                    result.divergence = Divergence(topic, rank, event.t, recorded[topic][rank].decode(), replayed.decode())
                    return result
    if not log_ended:
        result.unmatched = {topic: len(v) - produced[topic] for topic, v in recorded.items() if len(v) > produced[topic]}
    return result
