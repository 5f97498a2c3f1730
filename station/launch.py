"""Bridges the station starts itself: the simulated NAO (``--robot sim``) or a NAOqi bridge
running on the station machine (``--naoqi``), on loopback, on a free port.

The bridge is a child process in its own session (a Ctrl-C in the terminal reaches the station
only, which stops the robot first and then the bridge). It is terminated on every exit path:
``close`` (SIGTERM, then SIGKILL after a grace period) from the station's ``finally``, and, on
Linux, the kernel sends it SIGTERM if the station dies without cleaning up (PR_SET_PDEATHSIG).

The station watches it: :meth:`LocalBridge.watch` runs a thread blocked in ``wait()`` that calls
back the moment the bridge exits (a bad scenario, an unreachable NAOqi, a crash), so the station
stops waiting for it at once and prints :meth:`LocalBridge.last_lines` of ``bridge.log``.
"""

from __future__ import annotations

import ctypes
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any, Callable, List, Optional, Sequence, Tuple

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
        self.log_path = log_path
        self._closing = False
        self._log: IO[bytes] = open(log_path, "wb")
        self.process = subprocess.Popen(
            self.command, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, preexec_fn=_die_with_parent,
        )

    def exit_code(self) -> Optional[int]:
        return self.process.poll()

    def watch(self, on_exit: Callable[[int], None]) -> None:
        """Call ``on_exit(exit code)`` from a daemon thread when the bridge exits (unless :meth:`close` ended it)."""

        def wait() -> None:
            code = self.process.wait()
            if not self._closing:
                on_exit(code)

        threading.Thread(target=wait, name="bridge-watch", daemon=True).start()

    def last_lines(self, n: int = 5) -> List[str]:
        """The last ``n`` non-empty lines the bridge wrote (stdout and stderr)."""
        self._log.flush()
        try:
            text = self.log_path.read_bytes()[-8192:].decode("utf-8", "replace")
        except OSError:
            return []
        return [line for line in text.splitlines() if line.strip()][-n:]

    def close(self, grace: float = 5.0) -> Optional[int]:
        """Terminate the bridge (it stops the robot on SIGTERM); idempotent. Returns its exit code."""
        self._closing = True
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(grace)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        return self.process.returncode


class BridgeFailed(ConnectionError):
    """The bridge could not be reached, or a bridge the station started exited (message and its last log lines)."""

    def __init__(self, message: str, lines: Sequence[str] = ()):
        super().__init__(message)
        self.lines = list(lines)


def wait_for_info(fetch: Callable[[float], Tuple[Any, bytes]], timeout: float, bridge: Optional[LocalBridge],
                  step: float = 0.5) -> Tuple[Any, bytes]:
    """``fetch(t)`` (``BridgeLink.fetch_info``) in slices of at most ``step`` s until ``timeout``,
    giving up at the first slice after a started bridge exited: a dead bridge costs at most ``step``."""
    deadline = time.monotonic() + timeout
    while True:
        if bridge is not None and bridge.exit_code() is not None:
            raise BridgeFailed(f"the bridge exited with code {bridge.exit_code()} (its log: {bridge.log_path})",
                               bridge.last_lines())
        remaining = deadline - time.monotonic()
        try:
            return fetch(max(0.1, min(step, remaining)))
        except Exception as exc:  # BridgeUnavailable: retry until the deadline
            if time.monotonic() >= deadline:
                raise BridgeFailed(re.sub(r"within [0-9.e-]+ s", f"within {timeout:g} s", str(exc))) from None
