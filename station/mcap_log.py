"""The run log: one MCAP file with JSON (jsonschema) and protobuf (Foxglove) channels.

Writing: every channel is registered on first use with its schema; JSON payloads that arrived on
the wire are logged as the received bytes, unchanged. The ``mcap`` writer keeps messages in
memory until a chunk fills, so :meth:`McapLog.maybe_flush` closes the chunk in progress about once
a second (``flush_interval``): a crash loses at most that much. The writer is shared by the
control loop and the carving worker, hence the lock. Sinks (:class:`LogSink`, e.g. the live
Foxglove server of :mod:`station.live`) receive every channel and message as they are written.

Reading: :func:`read_log` yields messages in file order (the order they were written, which is
the order the station processed them: replay depends on it). A file cut by a crash has no
summary or footer; ``make_reader`` then fails, and the file is read linearly up to the last
complete record, with a warning.
"""

from __future__ import annotations

import json
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Optional, Protocol, Sequence, Tuple, Union

from google.protobuf.message import Message as ProtoMessage
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from nao_core.clock import now

JsonPayload = Union[bytes, Dict[str, Any]]


class LogError(ValueError):
    """The log lacks what a tool needs (names the log and what is missing)."""


def encode_json(payload: Dict[str, Any]) -> bytes:
    """Compact JSON as logged (replay compares outputs in this form, byte for byte)."""
    return json.dumps(payload, separators=(",", ":")).encode()


def to_ns(t: float) -> int:
    return int(round(t * 1e9))


class LogSink(Protocol):
    """Receives what the log writes: each channel once (before its first message), then its messages."""

    def channel(self, topic: str, message_encoding: str, schema_name: str, schema_encoding: str, schema: bytes) -> None: ...

    def message(self, topic: str, data: bytes, log_time_ns: int) -> None: ...


class McapLog:
    """Append-only run log. ``t`` arguments are station-clock seconds (``nao_core.clock.now()``)."""

    def __init__(self, path: Union[str, Path], flush_interval: float = 1.0, clock: Callable[[], float] = now,
                 sinks: Sequence[LogSink] = ()):
        self.path = Path(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="nao-active-recon station")
        self._channels: Dict[str, int] = {}
        self._schemas: Dict[Tuple[str, str], int] = {}
        self._lock = threading.Lock()
        self._flush_interval = flush_interval
        self._clock = clock
        self._last_flush = clock()
        self._closed = False
        self._sinks = tuple(sinks)

    def json(self, topic: str, payload: JsonPayload, t: float, schema: Dict[str, Any]) -> None:
        """Log a JSON message: ``bytes`` are logged as they are, a dict is serialized."""
        data = payload if isinstance(payload, bytes) else encode_json(payload)
        name = schema.get("title", topic)
        with self._lock:
            channel = self._channel(topic, "json", name, "jsonschema", lambda: json.dumps(schema).encode())
            self._add(topic, channel, data, t)

    def proto(self, topic: str, message: ProtoMessage, t: float) -> None:
        """Log a protobuf message (Foxglove schemas are named ``foxglove.<Name>``)."""
        with self._lock:
            name = message.DESCRIPTOR.full_name
            channel = self._channel(topic, "protobuf", name, "protobuf",
                                    lambda: build_file_descriptor_set(type(message)).SerializeToString())
            self._add(topic, channel, message.SerializeToString(), t)

    def maybe_flush(self) -> bool:
        """Write the chunk in progress to disk when ``flush_interval`` has passed; True if flushed."""
        with self._lock:
            now = self._clock()
            if self._closed or now - self._last_flush < self._flush_interval:
                return False
            self._writer.flush()
            self._last_flush = now
            return True

    def close(self) -> None:
        """Write the summary and the footer. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> "McapLog":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _channel(self, topic: str, encoding: str, schema_name: str, schema_encoding: str, schema: Callable[[], bytes]) -> int:
        """The topic's channel id, registering it (and its schema, once per name) on first use."""
        if topic not in self._channels:
            key = (schema_name, schema_encoding)
            data = schema()
            if key not in self._schemas:
                self._schemas[key] = self._writer.register_schema(schema_name, schema_encoding, data)
            self._channels[topic] = self._writer.register_channel(topic, encoding, self._schemas[key])
            for sink in self._sinks:
                sink.channel(topic, encoding, schema_name, schema_encoding, data)
        return self._channels[topic]

    def _add(self, topic: str, channel: int, data: bytes, t: float) -> None:
        if self._closed:
            raise RuntimeError(f"{self.path}: log already closed")
        stamp = to_ns(t)
        self._writer.add_message(channel, log_time=stamp, data=data, publish_time=stamp)
        for sink in self._sinks:
            sink.message(topic, data, stamp)


@dataclass(frozen=True)
class LogMessage:
    topic: str
    t: float  # log time, s
    data: bytes
    encoding: str  # 'json' or 'protobuf'
    schema: str  # schema name

    def json(self) -> Any:
        return json.loads(self.data)

    def proto(self, cls: type) -> Any:
        message = cls()
        message.ParseFromString(self.data)
        return message


def read_log(path: Union[str, Path], topics: Optional[set] = None) -> Iterator[LogMessage]:
    """Messages of the log in file order (all topics, or those in ``topics``).

    A log without a valid summary (cut by a crash, or damaged) is read linearly with a warning,
    up to the last complete record. Damage inside an indexed log raises :class:`LogError`.
    """
    with open(path, "rb") as stream:
        try:
            reader = make_reader(stream)
            summary = reader.get_summary()
            if summary is None:
                raise McapError("no summary")
        except Exception as exc:  # noqa: BLE001 - any damage to the summary: fall back to the linear read
            warnings.warn(f"{path}: incomplete MCAP ({exc!r}); reading it linearly up to the last complete record")
            stream.seek(0)
            yield from _linear(stream, topics)
            return
        try:
            for schema, channel, message in reader.iter_messages(topics=list(topics) if topics else None,
                                                                 log_time_order=False):
                yield _message(schema, channel, message)
        except Exception as exc:  # noqa: BLE001 - a damaged chunk behind a valid summary
            raise LogError(f"{path}: damaged MCAP data: {_short(exc)}") from None


def _short(exc: Exception, limit: int = 200) -> str:
    """An exception named in one line: a parser's message may quote kilobytes of the damaged bytes."""
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} characters)"


def _linear(stream, topics: Optional[set]) -> Iterator[LogMessage]:
    schemas: Dict[int, Schema] = {}
    channels: Dict[int, Channel] = {}
    try:
        for record in StreamReader(stream, skip_magic=False).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if topics is None or channel.topic in topics:
                    yield _message(schemas.get(channel.schema_id), channel, record)
    except Exception:  # noqa: BLE001 - the truncated or damaged tail may fail anywhere in the record parser
        return


def _message(schema: Optional[Schema], channel: Channel, message: Message) -> LogMessage:
    return LogMessage(
        topic=channel.topic,
        t=message.log_time * 1e-9,
        data=bytes(message.data),
        encoding=channel.message_encoding,
        schema=schema.name if schema else "",
    )
