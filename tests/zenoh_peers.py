"""Helpers for tests with real Zenoh sessions on loopback: free ports, lab certificates, waiting."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Callable

from tools.make_certs import make_lab_certificates


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def lab_certificates(folder: Path) -> Path:
    """A fresh lab CA with bridge, station and viewer certificates in ``folder``."""
    make_lab_certificates(folder)
    return folder


def wait_until(condition: Callable[[], bool], timeout: float, poll: float = 0.01) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` seconds pass; return whether it held."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return condition()
