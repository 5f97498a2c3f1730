"""The processes' clock: wall-clock seconds that never jump (docs/security.md, "Faults and their outcomes").

A process reads the wall clock once, when this module is imported, and counts on from there with
the monotonic clock:

    now() = wall_0 + (monotonic() - monotonic_0)

so its stamps read as Unix time (the log's, a frame's) yet an NTP step, a hand-set ``date`` or a
daylight-saving mistake after the start moves nothing: every timer, deadline and interval of the
process (the station's control ticks and mission timeouts, the bridge's frame and kinematics stamps)
stays right. The price is that a process does not follow a correction of the wall clock made
while it runs; the monotonic clock's own drift (parts per million) is far below the tolerances
the station and bridge compare stamps with (tens of milliseconds, ``station doctor``'s clock check).

The bridge and the station each have their own ``wall_0``: stamps that cross between them are in
the bridge's clock (frames, states), and the station never subtracts its clock from them but in
``station doctor``'s clock check, which holds a clock stepped before either started.
"""

from __future__ import annotations

import time

_WALL_0 = time.time()
_MONOTONIC_0 = time.monotonic()


def now() -> float:
    """Seconds since the Unix epoch as the wall clock read at import, advanced by the monotonic clock."""
    return _WALL_0 + (time.monotonic() - _MONOTONIC_0)
