"""What a run log holds beyond its raw messages, for the live loop that writes it and the offline
commands that read it (replay, carve, report): the configuration record with the digest of the
pilot's code, and the journal of the pilot's input events.

Code digest: SHA-256 over (relative path, bytes) of every source file the pilot executes
(:func:`pilot_sources`), so replay can say whether a divergence is expected.

Journal versions: 1 (logs before typed events) journalled a tick once and the pilot planned
inside it; 2 journals ``tick`` and ``replan`` separately. A version-1 ``tick`` is read as a
``Tick`` followed by a ``Replan`` at the same time, the order the live loop used.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Tuple, Union

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from nao_core.config import CONFIG_DIR, from_mapping, load
from nao_core.landmark_map import LandmarkMap
from nao_core.protocol import Frame, FrameMeta, Info, State, decode
from station.config import SECTIONS, StationConfig
from station.events import (
    LIVELINESS_LOST,
    BridgeLost,
    Event,
    FrameReceived,
    Interrupted,
    JournalEntry,
    Replan,
    StateReceived,
    Tick,
)
from station.mcap_log import LogError, read_log
from station.topics import CONFIG, FRAME_IMAGE, FRAME_META, INFO, INPUT, STATE

JOURNAL_VERSION = 2
ROOT = Path(__file__).resolve().parent.parent
# station modules the pilot runs (besides agent/ and nao_core/)
PILOT_MODULES = ("pilot.py", "events.py", "outputs.py", "topics.py", "config.py", "mcap_log.py")


def pilot_sources(root: Path = ROOT) -> List[Path]:
    """Every source file the pilot executes: the algorithms, the core, the pilot and its station modules."""
    return sorted([*(root / "agent").rglob("*.py"), *(root / "nao_core").rglob("*.py"),
                   *(root / "station" / name for name in PILOT_MODULES)])


def code_digest(root: Path = ROOT) -> str:
    digest = hashlib.sha256()
    for path in pilot_sources(root):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def config_record(config: StationConfig) -> Dict[str, Any]:
    """The resolved configuration as logged on /station/config (replay rebuilds it from this), with
    the digest of the pilot's code under ``code`` and the journal version under ``journal``."""
    record: Dict[str, Any] = {name: dataclasses.asdict(getattr(config, name)) for name in config.section_names}
    record["landmarks"] = dataclasses.asdict(config.landmarks)
    record["code"] = code_digest()
    record["journal"] = JOURNAL_VERSION
    return record


@dataclasses.dataclass(frozen=True)
class RunSetup:
    config: StationConfig
    info: Info
    code: Optional[str]  # digest of the pilot's code at the run
    journal: int  # journal version


def load_recorded(path: Union[str, Path]) -> RunSetup:
    """Configuration, bridge info, code digest and journal version recorded at the start of a run."""
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
    sections = {name: _section(name, cls, record.get(name, {}), f"{path}:{CONFIG}.{name}") for name, cls in SECTIONS.items()}
    landmarks = from_mapping(LandmarkMap, record["landmarks"], source=f"{path}:{CONFIG}.landmarks")
    return RunSetup(StationConfig(landmarks=landmarks, **sections), info, record.get("code"), int(record.get("journal", 1)))


def _section(name: str, cls: type, values: Dict[str, Any], source: str) -> Any:
    """A recorded section; keys the code no longer has are left out, keys added since take today's
    defaults from config/ (the code digest then differs: replay says so)."""
    defaults = dataclasses.asdict(load(cls, [CONFIG_DIR / f"{name}.yaml"], section=name))
    return from_mapping(cls, _overlay(defaults, values), source=source)


def _overlay(defaults: Dict[str, Any], recorded: Dict[str, Any]) -> Dict[str, Any]:
    """``defaults`` with every key also in ``recorded`` taken from there, nested mappings key by key."""
    out = {}
    for key, default in defaults.items():
        value = recorded.get(key, default)
        out[key] = _overlay(default, value) if isinstance(default, dict) and isinstance(value, dict) else value
    return out


def iter_events(path: Union[str, Path], journal: int = JOURNAL_VERSION) -> Iterator[Event]:
    """The pilot's input events in the order the live loop handled them."""
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
            entry = from_mapping(JournalEntry, message.json(), source=f"{path}:{INPUT}")
            yield from _events(entry, state, frames, journal)


def _events(entry: JournalEntry, state: Optional[State], frames: Dict[int, Frame], journal: int) -> Iterator[Event]:
    t = entry.t
    if entry.kind == StateReceived.KIND:
        yield StateReceived(t, state)
    elif entry.kind == FrameReceived.KIND:
        if entry.seq not in frames:
            raise LogError(f"frame {entry.seq} journalled at t={t} is not in the log")
        yield FrameReceived(t, frames[entry.seq])
    elif entry.kind == Tick.KIND:
        yield Tick(t)
        if journal < 2:
            yield Replan(t)
    elif entry.kind == Replan.KIND:
        yield Replan(t)
    elif entry.kind == BridgeLost.KIND:
        yield BridgeLost(t, entry.reason or LIVELINESS_LOST)
    else:
        yield Interrupted(t, entry.signal or "")
