"""The wire protocol between the bridge and the station (docs/protocol.md).

Key expressions (:class:`RobotKeys`), message classes with strict decoding, the binary frame
envelope and the JSON Schemas of every message type. Imported by the bridge and the station.
"""

from .keys import RobotKeys
from .messages import (
    FRAME_MAGIC,
    MAX_FRAME_BYTES,
    MAX_JSON_BYTES,
    MAX_META_BYTES,
    MAX_SEQ,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    REASONS,
    Frame,
    FrameMeta,
    HeadCommand,
    Info,
    ProtocolError,
    SimObject,
    State,
    Truth,
    WalkCommand,
    decode,
    decode_any,
    decode_frame,
    encode,
    encode_frame,
    json_schema,
    to_dict,
)

__all__ = [
    "FRAME_MAGIC",
    "MAX_FRAME_BYTES",
    "MAX_JSON_BYTES",
    "MAX_META_BYTES",
    "MAX_SEQ",
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "REASONS",
    "Frame",
    "FrameMeta",
    "HeadCommand",
    "Info",
    "ProtocolError",
    "RobotKeys",
    "SimObject",
    "State",
    "Truth",
    "WalkCommand",
    "decode",
    "decode_any",
    "decode_frame",
    "encode",
    "encode_frame",
    "json_schema",
    "to_dict",
]
