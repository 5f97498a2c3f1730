"""`station`: run a mission on a NAO (or the simulated one), replay, carve and report from its log.

    station start --robot HOST | --robot sim | --naoqi HOST   [--config FILE ...] [--out DIR]
                  [--max-duration S] [--scenario can|remote|figure] [--seed N] [--resolution qvga|vga]
                  [--secure CERT_DIR]
    station replay LOG.mcap
    station carve LOG.mcap -o model.ply [--resolution M] [--tolerance K]
    station report LOG.mcap [-o DIR]

Exit codes of ``start``: 0 the mission completed (coverage and uncertainty reached), 3 the time
limit ended it first, 1 any other outcome (object not found or lost, landmarks lost, fall, bridge
lost, interrupted, station error), 2 a configuration or usage error. ``replay`` exits 1 when the
replayed decisions diverge from the recorded ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import signal
import sys
from pathlib import Path
from typing import List, Optional

import yaml

from agent.mesh import save_mesh
from nao_core.config import ConfigError, main_error
from nao_core.transport import TransportConfig
from station.config import StationConfig, load_station_config
from station.launch import LocalBridge
from station.link import BridgeLink, BridgeUnavailable
from station.mcap_log import LogError, McapLog
from station.replay import replay
from station.report import write_report
from station.result import EXIT_FAILURE, build_result, exit_code, write_result
from station.run import ControlLoop, RunSummary

SIM = "sim"
NAOQI_PORT = 9559


def positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def parse_args(argv: Optional[List[str]]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="station", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    start = sub.add_parser("start", help="run a mission")
    target = start.add_mutually_exclusive_group(required=True)
    target.add_argument("--robot", metavar="HOST", help="connect to the bridge on HOST, or 'sim' to start a simulated NAO")
    target.add_argument("--naoqi", metavar="HOST", help="start a bridge here that drives NAOqi at tcp://HOST:9559")
    start.add_argument("--config", action="append", default=[], metavar="FILE", help="config override(s), merged in order")
    start.add_argument("--out", type=Path, help="output folder (default runs/<timestamp>)")
    start.add_argument("--max-duration", type=positive_float, metavar="S", help="mission time limit, s")
    start.add_argument("--scenario", default="can", help="simulated object (with --robot sim): can, remote, figure")
    start.add_argument("--seed", type=int, default=0, help="simulator seed (with --robot sim)")
    start.add_argument("--resolution", help="camera resolution of a bridge the station starts (qvga, vga)")
    start.add_argument("--secure", metavar="CERT_DIR", help="mutual TLS with the lab certificates (docs/security.md); "
                       "a bridge the station starts gets the same option")

    rep = sub.add_parser("replay", help="re-run the agent on a log and compare its decisions")
    rep.add_argument("log", type=Path)

    carve = sub.add_parser("carve", help="carve the model offline from a log")
    carve.add_argument("log", type=Path)
    carve.add_argument("-o", "--output", type=Path, default=Path("model.ply"), help="mesh file (.ply, .stl, .obj, .glb)")
    carve.add_argument("--resolution", type=positive_float, metavar="M", help="voxel edge, m (default: the run's)")
    carve.add_argument("--tolerance", type=non_negative_int, metavar="K", help="views that may call a voxel empty before it goes")

    report = sub.add_parser("report", help="write the figures of a run")
    report.add_argument("log", type=Path)
    report.add_argument("-o", "--out", type=Path, help="folder for the PNGs (default: the log's folder)")
    return parser.parse_args(argv)


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    try:
        if args.command == "start":
            return start(args)
        if args.command == "replay":
            return replay_command(args)
        if args.command == "carve":
            return carve_command(args)
        return report_command(args)
    except ConfigError as exc:
        return main_error(exc)
    except (LogError, OSError, ValueError) as exc:  # unreadable log, refused volume, ...: one line, no traceback
        print(f"station {args.command}: {exc}", file=sys.stderr)
        return EXIT_FAILURE


# start --------------------------------------------------------------------------------------------


class Interrupts:
    """SIGINT/SIGTERM set a flag the control loop reads (the robot is stopped by the loop)."""

    def __init__(self) -> None:
        self.signal_name: Optional[str] = None
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._handle)

    def _handle(self, signum: int, _frame) -> None:
        self.signal_name = self.signal_name or signal.Signals(signum).name

    def __call__(self) -> Optional[str]:
        return self.signal_name


def start(args: argparse.Namespace) -> int:
    config = load_station_config(args.config)
    if args.max_duration is not None:
        config = dataclasses.replace(config, mission=dataclasses.replace(config.mission, max_duration=args.max_duration))
    resolution = args.resolution or config.station.resolution
    out = args.out or Path("runs") / datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    interrupts = Interrupts()
    bridge: Optional[LocalBridge] = None
    link: Optional[BridgeLink] = None
    try:
        if args.robot and args.robot != SIM:
            endpoint = f"tcp/{args.robot}:{config.station.port}"
        else:
            bridge = LocalBridge(_bridge_args(args, config, resolution, out), out / "bridge.log")
            endpoint = bridge.endpoint
        print(f"station: connecting to the bridge at {endpoint}", file=sys.stderr)
        link = BridgeLink(_transport(args, config, endpoint), config.station.robot_name)
        info, info_bytes = link.fetch_info(config.station.bridge_timeout)
        link.start()
        if args.resolution and info.resolution != args.resolution:
            print(f"station: note: --resolution {args.resolution} ignored: the bridge at {endpoint} runs {info.resolution}",
                  file=sys.stderr)
        print(f"station: {info.backend} bridge {info.bridge_version}, {info.robot.name}, {info.resolution}; "
              f"mission starts (time limit {config.mission.max_duration:g} s)", file=sys.stderr)
        log = McapLog(out / "run.mcap", config.station.flush_interval)
        try:
            summary = ControlLoop(config, link, info, info_bytes, log, interrupts).run()
        finally:
            log.close()
    except BridgeUnavailable as exc:
        summary = RunSummary(outcome="bridge_unavailable", reason=str(exc), success=False, frames_received=0,
                             frames_processed=0, duration=0.0, carver=None, carving_error=None, x=None, P=None)
        print(f"station: {exc}", file=sys.stderr)
    finally:
        if link is not None:
            link.close()
        if bridge is not None:
            bridge.close()
    return _outputs(summary, out, resolution)


def _transport(args: argparse.Namespace, config: StationConfig, endpoint: str) -> TransportConfig:
    name, lease = config.station.robot_name, config.station.lease_ms
    if args.secure:
        return TransportConfig.secure("station", args.secure, robot=name, connect=(endpoint,), lease_ms=lease)
    return TransportConfig(connect=(endpoint,), lease_ms=lease, robot=name)


def _bridge_args(args: argparse.Namespace, config: StationConfig, resolution: str, out: Path) -> List[str]:
    bridge: dict = {"name": config.station.robot_name, "resolution": resolution}
    if config.robot_overrides:
        bridge["robot"] = str(Path(config.robot_overrides[-1]).resolve())
    override = out / "bridge.yaml"
    override.write_text(yaml.safe_dump({"bridge": bridge}))
    backend = ["--sim", "--scenario", args.scenario, "--seed", str(args.seed)] if args.robot == SIM else \
        ["--naoqi", args.naoqi if "://" in args.naoqi else f"tcp://{args.naoqi}:{NAOQI_PORT}"]
    secure = ["--secure", args.secure] if args.secure else []
    return [*backend, *secure, "--config", str(override)]


def _outputs(summary: RunSummary, out: Path, resolution: str) -> int:
    files = {}
    log_path = out / "run.mcap"
    if log_path.exists():
        files["log"] = log_path.name
    mesh = None
    if summary.carver is not None:
        mesh = summary.carver.to_mesh()
        for name in ("model.ply", "model.glb"):
            files[name.replace(".", "_")] = save_mesh(mesh, out / name).name
        files["voxels"] = summary.carver.save_npz(out / "voxels.npz").name
    if log_path.exists():
        try:
            files["report"] = [p.name for p in write_report(log_path, out, mesh)]
        except Exception as exc:  # noqa: BLE001 - a figure must never cost the result
            files["report_error"] = f"{type(exc).__name__}: {exc}"
    result = build_result(summary, log_path, files, resolution)
    write_result(result, out / "result.json")
    code = exit_code(summary.outcome)
    print(f"station: {result['status']} ({summary.outcome}): {summary.reason}", file=sys.stderr)
    print(f"station: outputs in {out.resolve()}")
    return code


# offline tools ------------------------------------------------------------------------------------


def replay_command(args: argparse.Namespace) -> int:
    result = replay(args.log, progress=True)
    print(json.dumps(result.as_dict(), indent=2))
    if result.ok:
        print(f"replay: {result.compared} outputs ({result.decisions} decisions) from {result.inputs} inputs reproduced exactly",
              file=sys.stderr)
        return 0
    if result.code_changed:
        print("replay: note: the agent's code changed since this run (code digest differs)", file=sys.stderr)
    if result.divergence is not None:
        d = result.divergence
        print(f"replay: first divergence on {d.topic} #{d.rank} at t={d.t:.3f}", file=sys.stderr)
    else:
        print(f"replay: recorded outputs not reproduced: {result.unmatched}", file=sys.stderr)
    return EXIT_FAILURE


def carve_command(args: argparse.Namespace) -> int:
    from station.carve import carve_log

    carver = carve_log(args.log, args.resolution, args.tolerance)
    path = save_mesh(carver.to_mesh(), args.output)
    print(json.dumps({"mesh": str(path), "pitch": carver.pitch, "views": carver.views_added,
                      "metrics": dataclasses.asdict(carver.metrics())}, indent=2))
    return 0


def report_command(args: argparse.Namespace) -> int:
    for path in write_report(args.log, args.out or args.log.parent):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
