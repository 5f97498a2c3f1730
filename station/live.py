"""``station start --live``: the run log's messages served as they are written, through the Foxglove
SDK's WebSocket server, so Foxglove (``ws://HOST:PORT``, the layout in config/foxglove/layout.json)
shows the mission while it runs.

:class:`LiveServer` is a :class:`station.mcap_log.LogSink`: each log channel becomes an SDK channel
with the same topic, message encoding and schema (protobuf descriptor set or JSON Schema), and
each message is logged on it with the same log time, so the live view and the MCAP file carry the
same bytes. The server has its own SDK context (no global state: two servers never mix). A
client that subscribes late sees the messages written from then on; the scene, the landmarks and
the calibration are re-sent by the control loop as they change.
"""

from __future__ import annotations

import logging
import threading
from typing import Dict

import foxglove

log = logging.getLogger("station.live")


class LiveServer:
    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "nao-active-recon station"):
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        self.host = host
        self.port = self.server.port
        self._channels: Dict[str, foxglove.Channel] = {}
        self._lock = threading.Lock()
        log.info("live view on ws://%s:%d (Foxglove: open connection, Foxglove WebSocket)", host, self.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def channel(self, topic: str, message_encoding: str, schema_name: str, schema_encoding: str, schema: bytes) -> None:
        with self._lock:
            self._channels[topic] = foxglove.Channel(
                topic, schema=foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema),
                message_encoding=message_encoding, context=self.context,
            )

    def message(self, topic: str, data: bytes, log_time_ns: int) -> None:
        self._channels[topic].log(data, log_time=log_time_ns)

    def close(self) -> None:
        """Stop the server (idempotent)."""
        with self._lock:
            channels, self._channels = self._channels, {}
        for channel in channels.values():
            channel.close()
        self.server.stop()
