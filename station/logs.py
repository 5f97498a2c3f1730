"""The station's console and its copy in the run log.

Every station module logs through ``logging.getLogger("station.<module>")``. :func:`setup` gives
the ``station`` logger one stderr handler whose level the command line sets::

    -q -> WARNING,   (default) -> INFO,   -v -> DEBUG

and a line reads ``station: message`` (``station: warning: message`` above INFO). While a run log
is open, :class:`LogTopicHandler` writes the same records, at the same level, as ``foxglove.Log``
messages on ``/station/log``, so the console of a mission is in its MCAP and in the live view.
"""

from __future__ import annotations

import logging
import sys
from typing import Callable, List, Optional, Tuple

from foxglove_schemas_protobuf.Log_pb2 import Log

LOGGER = "station"
FOXGLOVE_LEVEL = {
    logging.DEBUG: Log.DEBUG, logging.INFO: Log.INFO, logging.WARNING: Log.WARNING,
    logging.ERROR: Log.ERROR, logging.CRITICAL: Log.FATAL,
}


class ConsoleFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        level = "" if record.levelno <= logging.INFO else f"{record.levelname.lower()}: "
        return f"{LOGGER}: {level}{record.getMessage()}"


def level_for(verbosity: int) -> int:
    """-q (verbosity -1) WARNING, default INFO, -v (1 or more) DEBUG."""
    return logging.WARNING if verbosity < 0 else logging.DEBUG if verbosity > 0 else logging.INFO


def setup(verbosity: int = 0) -> logging.Logger:
    """Configure the ``station`` logger for a command line run (idempotent: replaces its console handler)."""
    logger = logging.getLogger(LOGGER)
    for handler in [h for h in logger.handlers if getattr(h, "station_console", False)]:
        logger.removeHandler(handler)
    console = logging.StreamHandler(sys.stderr)
    console.station_console = True  # type: ignore[attr-defined]
    console.setFormatter(ConsoleFormatter())
    console.setLevel(level_for(verbosity))
    logger.addHandler(console)
    logger.setLevel(min(level_for(verbosity), logging.INFO))  # the run log keeps INFO even with -q
    logger.propagate = False
    return logger


def foxglove_log(record: logging.LogRecord) -> Log:
    """One log record as a ``foxglove.Log`` message."""
    message = Log(level=FOXGLOVE_LEVEL.get(record.levelno, Log.UNKNOWN), message=record.getMessage(),
                  name=record.name, file=record.pathname, line=record.lineno)
    message.timestamp.FromNanoseconds(int(round(record.created * 1e9)))
    return message


class LogTopicHandler(logging.Handler):
    """Forwards the station's log records to ``write(message, t)`` (the run log's /station/log);
    records from before :meth:`bind` (the log not open yet) are kept and written at bind time."""

    def __init__(self, write: Optional[Callable[[Log, float], None]] = None, level: int = logging.INFO):
        super().__init__(level)
        self._write = write
        self._early: List[Tuple[Log, float]] = []

    def bind(self, write: Callable[[Log, float], None]) -> None:
        early, self._early = self._early, []
        for message, t in early:
            write(message, t)
        self._write = write

    def emit(self, record: logging.LogRecord) -> None:
        if self._write is None:
            self._early.append((foxglove_log(record), record.created))
            return
        try:
            self._write(foxglove_log(record), record.created)
        except Exception:  # noqa: BLE001 - a closed log must never break the console
            self.handleError(record)


class attached:
    """``with attached(handler):`` the handler receives the station's records inside the block."""

    def __init__(self, handler: logging.Handler, logger: Optional[logging.Logger] = None):
        self.handler = handler
        self.logger = logger or logging.getLogger(LOGGER)

    def __enter__(self) -> logging.Handler:
        self.logger.addHandler(self.handler)
        return self.handler

    def __exit__(self, *exc: object) -> None:
        self.logger.removeHandler(self.handler)
