"""The pilot's outputs: one typed record per ``/agent/*`` topic, with its JSON encoding and schema.

Each record class names its topic (``TOPIC``) and its schema title (``NAME``) once; the schema is
derived from the dataclass (``nao_core.protocol.schema.record_schema``), and the encoding is the
record's fields in declaration order as compact JSON (:func:`station.mcap_log.encode_json`), the
form replay compares byte for byte. ``OUTPUTS`` maps every topic to its record class.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Dict, List, Literal, Optional, Tuple, Type

from agent.mission import Phase
from nao_core.protocol.schema import record_schema
from station.mcap_log import encode_json
from station.topics import COVERAGE, DECISION, EKF, FRAME_REJECTED, KEYFRAME, MEASUREMENT, PLAN, POSE, SELF_CALIBRATION

Vec3 = Tuple[float, float, float]
Matrix16 = Tuple[float, ...]  # a 4 x 4 transform, row-major
Matrix9 = Tuple[float, ...]  # a 3 x 3 camera matrix K, row-major

PhaseName = Literal[tuple(phase.value for phase in Phase)]  # type: ignore[misc]
FrameStep = Literal["decode", "localization", "calibration", "perception", "filter", "coverage", "keyframe"]


class Record:
    """Base of the output records: topic, schema name, JSON encoding."""

    TOPIC: ClassVar[str]
    NAME: ClassVar[str]

    def to_json(self) -> bytes:
        return encode_json(dataclasses.asdict(self))

    @classmethod
    def schema(cls) -> Dict[str, Any]:
        return record_schema(cls, cls.NAME)


@dataclass(frozen=True)
class DecisionRecord(Record):
    """Every tick: the phase, the walk and head commands (None: none sent), stop, outcome, reason."""

    TOPIC: ClassVar[str] = DECISION
    NAME: ClassVar[str] = "agent.Decision"
    t: float
    phase: PhaseName
    walk: Optional[Vec3]
    head: Optional[Tuple[float, float]]
    stop: bool
    outcome: Optional[str]
    reason: str


@dataclass(frozen=True)
class PoseRecord(Record):
    """Robot pose at a frame's capture (world frame once anchored by a landmark fix, else odometry)."""

    TOPIC: ClassVar[str] = POSE
    NAME: ClassVar[str] = "agent.Pose"
    t: float
    seq: int
    stamp: float
    pose: Vec3
    odom: Vec3
    landmark_fix: bool
    T_WC: Matrix16
    T_BC: Matrix16
    anchored: bool  # False: ``pose`` is the odometry (no landmark fix yet)


@dataclass(frozen=True)
class MeasurementRecord(Record):
    """Camera (cx, cy, psi), bearing phi, width delta (None: cut silhouette), the filter's verdict."""

    TOPIC: ClassVar[str] = MEASUREMENT
    NAME: ClassVar[str] = "agent.Measurement"
    t: float
    seq: int
    cam: Vec3
    phi: float
    delta: Optional[float]
    accepted: bool
    nis: Optional[float]
    reason: str


@dataclass(frozen=True)
class EkfRecord(Record):
    """The object estimate x = (x, y, r), its covariance and the filter's counters after an update."""

    TOPIC: ClassVar[str] = EKF
    NAME: ClassVar[str] = "agent.ObjectEstimate"
    t: float
    x: Optional[Vec3]
    P: Optional[Tuple[Vec3, Vec3, Vec3]]
    stats: Dict[str, int]


@dataclass(frozen=True)
class CoverageRecord(Record):
    TOPIC: ClassVar[str] = COVERAGE
    NAME: ClassVar[str] = "agent.Coverage"
    t: float
    fraction: float


@dataclass(frozen=True)
class PlanRecord(Record):
    """One replan: the turn-rate sequence, the command, the cost and its weighted terms."""

    TOPIC: ClassVar[str] = PLAN
    NAME: ClassVar[str] = "agent.Plan"
    t: float
    omegas: List[float]
    command: Vec3
    cost: float
    terms: Dict[str, float]
    evaluations: int
    coverage: float


@dataclass(frozen=True)
class KeyframeRecord(Record):
    """A carving keyframe: frame seq, viewing azimuth, T_WC, the predicted pixel that picked the blob, its quality
    (agent/keyframes.py), and the camera matrix it was seen with (None in logs before self-calibration: the bridge's)."""

    TOPIC: ClassVar[str] = KEYFRAME
    NAME: ClassVar[str] = "agent.Keyframe"
    t: float
    seq: int
    azimuth: float
    T_WC: Matrix16
    predicted_uv: Optional[Tuple[float, float]]
    quality: float
    K: Optional[Matrix9] = None


@dataclass(frozen=True)
class CalibrationRecord(Record):
    """A self-calibration estimate applied (agent/self_calibration.py): the corrected K, the error
    c = (s_x, s_y, d_u, d_v) of the configured one with its standard deviations, the fixes and their RMS (px),
    the markers' edge shift e and its standard deviation (px; agent/marker_corners.py)."""

    TOPIC: ClassVar[str] = SELF_CALIBRATION
    NAME: ClassVar[str] = "agent.Calibration"
    t: float
    K: Matrix9
    error: Tuple[float, float, float, float]
    std: Tuple[float, float, float, float]
    fixes: int
    rms_px: float
    edge_shift_px: Optional[float] = None  # logs before the edge shift: none
    edge_shift_std_px: Optional[float] = None


@dataclass(frozen=True)
class FrameRejectedRecord(Record):
    """A frame dropped because a per-frame step raised: the step, the error, failures in a row."""

    TOPIC: ClassVar[str] = FRAME_REJECTED
    NAME: ClassVar[str] = "agent.FrameRejected"
    t: float
    seq: int
    step: FrameStep
    reason: str
    in_a_row: int


OUTPUTS: Dict[str, Type[Record]] = {cls.TOPIC: cls for cls in (
    DecisionRecord, PoseRecord, MeasurementRecord, EkfRecord, CoverageRecord, PlanRecord, KeyframeRecord,
    FrameRejectedRecord, CalibrationRecord)}
