"""Bridges the station starts itself: the simulated NAO (``--robot sim``) or a NAOqi bridge
running on the station machine (``--naoqi``), on loopback, on a free port.

The bridge is a child process in its own session (a Ctrl-C in the terminal reaches the station
only, which stops the robot first and then the bridge). It is terminated on every exit path:
``close`` (SIGTERM, then SIGKILL after a grace period) from the station's ``finally``, and, on
Linux, the kernel sends it SIGTERM if the station dies without cleaning up (PR_SET_PDEATHSIG).
"""

from __future__ import annotations

import ctypes
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import IO, Optional, Sequence

PR_SET_PDEATHSIG = 1


def free_port() -> int:
    """A TCP port on loopback that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass  # not Linux: close() still runs on every orderly exit


class LocalBridge:
    """``nao-bridge <backend args> --listen tcp/127.0.0.1:PORT`` as a child process."""

    def __init__(self, backend_args: Sequence[str], log_path: Path, port: Optional[int] = None):
        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.command = [sys.executable, "-m", "nao_bridge.cli", *backend_args, "--listen", self.endpoint]
        self._log: IO[bytes] = open(log_path, "wb")
        self.process = subprocess.Popen(
            self.command, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, preexec_fn=_die_with_parent,
        )

    def exit_code(self) -> Optional[int]:
        return self.process.poll()

    def close(self, grace: float = 5.0) -> Optional[int]:
        """Terminate the bridge (it stops the robot on SIGTERM); idempotent. Returns its exit code."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(grace)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        return self.process.returncode
