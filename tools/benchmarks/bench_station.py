"""Station: frame-to-command latency, CPU and log size during a simulated mission at VGA 15 fps.

A ``nao-bridge --sim`` process on loopback (VGA, 15 fps) and the station's control loop in this
process. Latency: from a frame's arrival at the station (Zenoh callback) to the walk command sent
on the tick that follows its processing (perception, localization, EKF, mission, head servo); the
planner runs after the tick's commands are sent, its duration is reported apart. CPU: this process's user + system time (the station, with its carving thread) over
the wall time. Log size: run.mcap bytes per minute of mission.
"""

from __future__ import annotations

import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from nao_core.transport import TransportConfig
from station.config import load_station_config
from station.launch import LocalBridge
from station.link import BridgeLink
from station.mcap_log import McapLog
from station.run import ControlLoop

DURATION = 60.0  # s of mission
COMMAND = ".venv/bin/python -m tools.bench --only station"


def measure(duration: float = DURATION, resolution: str = "vga") -> dict:
    config = load_station_config()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "bridge.yaml").write_text(f"bridge:\n  resolution: {resolution}\n  fps: 15.0\n")
        bridge = LocalBridge(["--sim", "--scenario", "can", "--config", str(out / "bridge.yaml")], out / "bridge.log")
        # the started bridge has the default security (docs/security.md): the station user and password
        transport = TransportConfig.with_credentials("station", connect=(bridge.endpoint,), lease_ms=config.station.lease_ms)
        link = BridgeLink(transport, config.station.robot_name)
        try:
            info, info_bytes = link.fetch_info(config.station.bridge_timeout)
            link.start()
            log = McapLog(out / "run.mcap", config.station.flush_interval)
            deadline = time.monotonic() + duration
            loop = ControlLoop(config, link, info, info_bytes, log, lambda: "SIGINT" if time.monotonic() > deadline else None)
            cpu0, wall0 = _cpu(), time.monotonic()
            summary = loop.run()
            cpu, wall = _cpu() - cpu0, time.monotonic() - wall0
            log.close()
            size = (out / "run.mcap").stat().st_size
        finally:
            link.close()
            bridge.close()
    latency = 1000 * np.asarray(loop.latencies)
    plan = 1000 * np.asarray(loop.plan_times or [np.nan])
    return {
        "plans": len(loop.plan_times), "plan_p50": float(np.median(plan)), "plan_max": float(plan.max()),
        "frames": summary.frames_received, "processed": summary.frames_processed, "commands": latency.size,
        "p50": float(np.percentile(latency, 50)), "p99": float(np.percentile(latency, 99)), "max": float(latency.max()),
        "cpu": 100 * cpu / wall, "wall": wall, "mb_per_min": size / 1e6 / (wall / 60), "outcome": summary.outcome,
    }


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run() -> str:
    m = measure()
    return "\n".join([
        "## Station: frame-to-command latency, CPU, log size",
        "",
        "A simulated mission (`nao-bridge --sim`, scenario `can`, VGA at 15 fps) on loopback, the station's control",
        "loop in the benchmark process. Latency is from a frame's arrival at the station to the walk command sent",
        "after it was processed (perception, localization, EKF, mission tick, head servo); the planner runs right after",
        "the tick's commands are out (once per planner period), so its time is listed apart. CPU is the",
        "station process (loop + carving thread) over wall time. The machine is shared (2 cores, other engineers' jobs):",
        "timings are noisy. Target: p99 <= 50 ms.",
        "",
        f"Command: `{COMMAND}`",
        "",
        "| frames received | frames processed | commands timed | latency p50 (ms) | p99 (ms) | max (ms) | replans | replan p50 / max (ms) | station CPU (% of one core) | log (MB/min) | mission outcome |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        f"| {m['frames']} | {m['processed']} | {m['commands']} | {m['p50']:.1f} | {m['p99']:.1f} | {m['max']:.1f} | "
        f"{m['plans']} | {m['plan_p50']:.0f} / {m['plan_max']:.0f} | {m['cpu']:.0f} | {m['mb_per_min']:.1f} | {m['outcome']} ({m['wall']:.0f} s) |",
    ])
