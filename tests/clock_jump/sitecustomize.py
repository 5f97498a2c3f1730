"""Test-only: a process started with this folder on PYTHONPATH reads a wall clock that the test steps.

``time.time()`` returns the real wall clock plus the seconds written in the file named by
``CLOCK_OFFSET_FILE`` (re-read at most every 50 ms of monotonic time), as an NTP step or a
hand-set ``date`` would move it (tests/test_station_mission.py). The monotonic clock is untouched.
"""

import os
import time

_path = os.environ.get("CLOCK_OFFSET_FILE")
if _path:
    _wall = time.time
    _state = {"offset": 0.0, "read": -1.0}

    def _stepped_time() -> float:
        if time.monotonic() - _state["read"] >= 0.05:
            _state["read"] = time.monotonic()
            try:
                with open(_path) as f:
                    _state["offset"] = float(f.read() or 0.0)
            except (OSError, ValueError):
                pass
        return _wall() + _state["offset"]

    time.time = _stepped_time
