"""nao_core.clock: Unix seconds that follow the monotonic clock, not steps of the wall clock."""

from __future__ import annotations

import time

from nao_core import clock


def test_now_reads_as_the_wall_clock_and_ignores_its_steps(monkeypatch):
    assert abs(clock.now() - time.time()) < 1.0  # Unix time, as the logs and stamps expect
    before = clock.now()
    wall = time.time
    for step in (3600.0, -7200.0):
        monkeypatch.setattr(time, "time", lambda: wall() + step)
        t = clock.now()
        assert before <= t < before + 1.0  # neither forward nor back by the step
        before = t
    time.sleep(0.05)
    assert clock.now() - before >= 0.05  # and it advances with the monotonic clock
