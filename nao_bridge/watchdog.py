"""The robot-side watchdog: stops the walk when the bridge's heartbeats stop (docs/bridge.md).

It runs on the NAO itself, with what a stock NAO V6 has (NAOqi 2.8, Python 2.7, its ``qi``
module; no pip), so this file is written in the subset of Python that runs on 2.7 and 3.x
(checked by ``vermin`` in tests/test_bridge.py) and imports nothing but the standard library and
``qi``. ``nao-bridge install-watchdog nao.local`` copies it to the robot and starts it there.

Protocol, all through NAOqi's ALMemory (reachable by both sides whatever the network):

* the bridge writes an increasing counter to ``HEARTBEAT_KEY`` every heartbeat period;
* the watchdog, every ``period`` seconds, reads it and writes its own increasing counter to
  ``WATCHDOG_KEY`` (the bridge refuses to walk a remote NAO while that counter stands still);
* with t_c the watchdog's clock when the heartbeat last changed, at time t the robot must stop iff
  t - t_c >= timeout; the watchdog then calls ``ALMotion.stopMove`` once, again every period
  while ``moveIsActive()`` says the robot still walks, counts its stops in ``STOPS_KEY``, and
  after ``rest_after`` seconds of silence (0 = never) calls ``ALMotion.rest``.

The worst-case stop delay after the bridge's last heartbeat is timeout + period (+ one NAOqi call),
whatever froze: the bridge process, the machine it runs on, or the network between it and NAOqi.
A heartbeat that changes again re-arms the watchdog (the bridge has its own rules for walking).

    python watchdog.py [--url tcp://127.0.0.1:9559] [--timeout 0.3] [--period 0.05] [--rest-after 0]
"""

from __future__ import print_function

import argparse
import logging
import sys
import time

HEARTBEAT_KEY = "NaoActiveRecon/BridgeHeartbeat"
WATCHDOG_KEY = "NaoActiveRecon/WatchdogCount"
STOPS_KEY = "NaoActiveRecon/WatchdogStops"

log = logging.getLogger("nao_watchdog")
_clock = getattr(time, "monotonic", time.time)  # Python 2.7 has no monotonic clock


class Watchdog(object):
    """One decision per :meth:`tick`; ``memory`` and ``motion`` are ALMemory and ALMotion proxies."""

    def __init__(self, memory, motion, timeout, rest_after=0.0, clock=_clock):
        if not timeout > 0:
            raise ValueError("timeout must be positive, got %r" % (timeout,))
        self.memory = memory
        self.motion = motion
        self.timeout = float(timeout)
        self.rest_after = float(rest_after)
        self.clock = clock
        self.count = 0
        self.stops = 0
        self._beat = None
        self._changed_at = None
        self._stopped = False
        self._rested = False

    def _read_beat(self):
        try:
            return self.memory.getData(HEARTBEAT_KEY)
        except RuntimeError:  # the key does not exist until a bridge wrote it
            return None

    def tick(self):
        """Publish the watchdog's counter, read the heartbeat, stop if it is silent; return the state."""
        now = self.clock()
        self.count += 1
        self.memory.insertData(WATCHDOG_KEY, self.count)
        beat = self._read_beat()
        if beat is not None and beat != self._beat:
            self._beat, self._changed_at = beat, now
            self._stopped = self._rested = False
            return "ok"
        if self._changed_at is None:
            return "waiting"  # no bridge has ever spoken: nothing to guard
        silent = now - self._changed_at
        if silent < self.timeout:
            return "ok"
        if not self._stopped or self.motion.moveIsActive():
            self.motion.stopMove()
            self.stops += 1
            self.memory.insertData(STOPS_KEY, self.stops)
            if not self._stopped:
                log.warning("no heartbeat from the bridge for %.3f s: stopMove", silent)
            self._stopped = True
        if self.rest_after > 0 and silent >= self.rest_after and not self._rested:
            log.warning("no heartbeat for %.1f s: rest", silent)
            self.motion.rest()
            self._rested = True
        return "stopped"


def connect(url):
    import qi  # NAOqi's own module on the robot, libqi's wheel elsewhere

    session = qi.Session()
    session.connect(url)
    return session


def run(url, timeout, period, rest_after, should_stop=lambda: False):
    """Tick every ``period`` s until ``should_stop()``; reconnect when NAOqi goes away."""
    watchdog = None
    next_tick = _clock()
    while not should_stop():
        try:
            if watchdog is None:
                session = connect(url)
                watchdog = Watchdog(session.service("ALMemory"), session.service("ALMotion"), timeout, rest_after)
                log.info("watching %s: stop after %.3f s without a heartbeat", url, timeout)
            watchdog.tick()
        except Exception as exc:  # noqa: BLE001 - the watchdog must outlive any NAOqi hiccup
            log.error("watchdog: %s", exc)
            watchdog = None
        next_tick = max(next_tick + period, _clock())
        time.sleep(max(0.0, next_tick - _clock()))


def main(argv=None):
    parser = argparse.ArgumentParser(description="Stop the NAO's walk when the bridge's heartbeats stop.")
    parser.add_argument("--url", default="tcp://127.0.0.1:9559", help="NAOqi endpoint (the robot itself)")
    parser.add_argument("--timeout", type=float, default=0.3, help="s without a heartbeat before stopMove")
    parser.add_argument("--period", type=float, default=0.05, help="s between checks")
    parser.add_argument("--rest-after", type=float, default=0.0, help="s without a heartbeat before rest (0: never)")
    args = parser.parse_args(argv)
    if not (args.timeout > 0 and 0 < args.period <= args.timeout and args.rest_after >= 0):
        parser.error("need timeout > 0, 0 < period <= timeout and rest-after >= 0")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s watchdog: %(message)s")
    try:
        run(args.url, args.timeout, args.period, args.rest_after)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
