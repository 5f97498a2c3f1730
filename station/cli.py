"""`station`: run a mission on a NAO (or the simulated one), check the robot, capture, calibrate,
replay, carve and report.

    station start --robot HOST | --robot sim | --naoqi HOST   [--config FILE ...] [--out DIR]
                  [--max-duration S] [--scenario NAME] [--seed N] [--resolution NAME]
                  [--secure CERT_DIR] [--live [PORT]]
    station doctor --robot HOST | --robot sim | --naoqi HOST     the robot, checked line by line
    station capture (--robot HOST | --naoqi HOST | --log RUN.mcap) -o DIR [--count N]
    station calibrate --pattern 9x6 --square 0.025 IMAGES...    camera intrinsics -> --config file
    station pick-colors NAME IMAGE:X,Y,W,H...                    a colour class -> --config file
    station check-layout --landmarks FILE --object X,Y           where fixes are possible on the orbit -> PNG
    station config [--config FILE ...]                           the resolved configuration
    station replay LOG.mcap | carve LOG.mcap -o model.ply | report LOG.mcap [-o DIR]

Every command takes -v (debug) or -q (warnings only), before or after its name.

Exit codes: 0 success (start: the mission completed, coverage and uncertainty reached);
1 failure (start: object not found or lost, landmarks lost, fall, bridge lost mid-mission,
interrupted, station error; replay: the decisions diverge; doctor: a check failed);
2 configuration, usage or connection error (a bad option or file, the bridge unreachable, or a
bridge the station started exited: its last log lines are printed); 3 (start) the time limit
ended the mission first.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import fcntl
import json
import logging
import signal
import sys
from importlib import metadata
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import yaml

from agent.mesh import save_mesh
from nao_core.clock import now
from nao_core.config import CONFIG_DIR, ConfigError, main_error, read_yaml
from nao_core.protocol import Info
from nao_core.robot_model import load_robot_model
from nao_core.transport import TransportConfig
from station import calibrate, certs, check_layout, logs, pick_colors
from station.config import StationConfig, load_station_config
from station.launch import BridgeFailed, LocalBridge, wait_for_info
from station.link import BridgeLink, Received
from station.mcap_log import LogError, McapLog
from station.replay import replay
from station.result import (
    EXIT_CONFIG,
    EXIT_FAILURE,
    build_result,
    exit_code,
    write_result,
)
from station.run import ControlLoop, RunSummary
from station.topics import LOG

SIM = "sim"
NAOQI_PORT = 9559
LIVE_PORT = 8765
log = logging.getLogger("station.cli")


def version() -> str:
    try:
        return metadata.version("nao-active-recon")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


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


def scenario_names() -> List[str]:
    """The simulator's scenarios, read from config/sim.yaml (the station does not import the simulator)."""
    return sorted(read_yaml(CONFIG_DIR / "sim.yaml", what="the simulator config")["sim"]["scenarios"])


def resolution_names() -> List[str]:
    return sorted(load_robot_model().camera.resolutions)


def _verbosity(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=1, default=argparse.SUPPRESS,
                       help="debug messages")
    group.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=-1, default=argparse.SUPPRESS,
                       help="warnings and errors only")


def _target(parser: argparse.ArgumentParser, required: bool = True) -> argparse._MutuallyExclusiveGroup:
    target = parser.add_mutually_exclusive_group(required=required)
    target.add_argument("--robot", metavar="HOST", help="connect to the bridge on HOST, or 'sim' to start a simulated NAO")
    target.add_argument("--naoqi", metavar="HOST", help="start a bridge here that drives NAOqi at tcp://HOST:9559")
    parser.add_argument("--config", action="append", default=[], metavar="FILE", help="config override(s), merged in order")
    parser.add_argument("--scenario", default="can", choices=scenario_names(), help="simulated object (with --robot sim)")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (with --robot sim)")
    parser.add_argument("--resolution", choices=resolution_names(), help="camera resolution of a bridge the station starts")
    parser.add_argument("--secure", metavar="CERT_DIR", help="mutual TLS with the lab certificates (docs/security.md); "
                        "a bridge the station starts gets the same option")
    parser.add_argument("--insecure", action="store_true", help="no authentication (a bridge started with --insecure); "
                        "by default the station presents the generated credentials (docs/security.md)")
    return target


def parse_args(argv: Optional[List[str]]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="station", description=__doc__.split("\n\n")[0],
                                     epilog=__doc__[__doc__.index("Exit codes"):],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"station {version()}")
    _verbosity(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        _verbosity(p)
        return p

    start = command("start", "run a mission")
    _target(start)
    start.add_argument("--out", type=Path, help="output folder (default runs/<timestamp>)")
    start.add_argument("--max-duration", type=positive_float, metavar="S", help="mission time limit, s (also bounds the wait for the bridge)")
    start.add_argument("--live", nargs="?", type=int, const=LIVE_PORT, metavar="PORT",
                       help=f"serve the mission to Foxglove on ws://127.0.0.1:PORT (default {LIVE_PORT}) while it runs")
    start.add_argument("--live-host", default="127.0.0.1", metavar="ADDR", help="address of the live server (0.0.0.0: every interface)")

    doctor = command("doctor", "check the robot: bridge or NAOqi, camera, clock, battery, landmarks")
    _target(doctor)
    doctor.add_argument("--seconds", type=positive_float, default=3.0, help="how long to watch frames and states, s")

    capture = command("capture", "save camera frames from the robot or from a run log (for calibrate, pick-colors)")
    _target(capture, required=False).add_argument("--log", type=Path, metavar="RUN.mcap", help="extract the frames of a run log")
    capture.add_argument("-o", "--out", type=Path, required=True, help="folder for the JPEG files")
    capture.add_argument("--count", type=non_negative_int, default=20, help="frames to save (0: all of a log)")
    capture.add_argument("--every", type=positive_float, default=1.0, metavar="S", help="at most one frame per S seconds")

    calibrate.add_arguments(command("calibrate", "camera intrinsics from chessboard images, as a --config file"))
    pick_colors.add_arguments(command("pick-colors", "a colour class from sample regions, as a --config file"))
    check_layout.add_arguments(command("check-layout", "predict where the landmarks give fixes on the orbit, with a PNG"))
    certs.add_arguments(command("make-certs", "a lab CA and the certificates of the bridge, the station and a viewer (--secure)"))

    config = command("config", "print the resolved configuration and which file set each key")
    config.add_argument("--config", action="append", default=[], metavar="FILE", help="config override(s), merged in order")
    config.add_argument("--json", action="store_true", help="JSON instead of a table")

    rep = command("replay", "re-run the agent on a log and compare its decisions")
    rep.add_argument("log", type=Path)

    carve = command("carve", "carve the model offline from a log")
    carve.add_argument("log", type=Path)
    carve.add_argument("-o", "--output", type=Path, default=Path("model.ply"), help="mesh file (.ply, .stl, .obj, .glb)")
    carve.add_argument("--resolution", type=positive_float, metavar="M", help="voxel edge, m (default: the run's)")
    carve.add_argument("--tolerance", type=non_negative_int, metavar="K", help="views that may call a voxel empty before it goes")

    report = command("report", "write the figures of a run")
    report.add_argument("log", type=Path)
    report.add_argument("-o", "--out", type=Path, help="folder for the PNGs (default: the log's folder)")
    args = parser.parse_args(argv)
    args.verbosity = getattr(args, "verbosity", 0)
    return args


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    logs.setup(args.verbosity)
    from station import capture, doctor
    from station.config import print_config

    commands = {
        "start": start, "doctor": doctor.run, "capture": capture.run, "calibrate": calibrate.run,
        "pick-colors": pick_colors.run, "check-layout": check_layout.run, "make-certs": certs.run, "config": print_config, "replay": replay_command,
        "carve": carve_command, "report": report_command,
    }
    try:
        return commands[args.command](args)
    except ConfigError as exc:
        return main_error(exc)
    except BridgeFailed as exc:
        _report_bridge_failure(exc)
        return EXIT_CONFIG
    except (LogError, OSError, ValueError) as exc:  # unreadable log, refused volume, ...: one line, no traceback
        log.error("%s: %s", args.command, exc)
        return EXIT_FAILURE


def _report_bridge_failure(exc: BridgeFailed) -> None:
    log.error("%s", exc)
    for line in exc.lines:
        log.error("bridge: %s", line)


# connecting -------------------------------------------------------------------------------------


@contextlib.contextmanager
def connected(args: argparse.Namespace, config: StationConfig, out: Path, timeout: float
              ) -> Iterator[Tuple[BridgeLink, Info, bytes, Optional[LocalBridge]]]:
    """The link to the robot's bridge (started here for ``--robot sim`` and ``--naoqi``), its info
    fetched; raises :class:`BridgeFailed` (exit 2) when it cannot be reached or a started bridge exits."""
    bridge: Optional[LocalBridge] = None
    link: Optional[BridgeLink] = None
    try:
        if args.robot and args.robot != SIM:
            endpoint = f"tcp/{args.robot}:{config.station.port}"
        else:
            resolution = args.resolution or config.station.resolution
            bridge = LocalBridge(_bridge_args(args, config, resolution, out), out / "bridge.log")
            endpoint = bridge.endpoint
        log.info("connecting to the bridge at %s", endpoint)
        try:
            link = BridgeLink(_transport(args, config, endpoint), config.station.robot_name, config.station.watchdog_grace)
        except Exception as exc:  # BridgeUnavailable: the session cannot open
            raise BridgeFailed(str(exc)) from None
        info, info_bytes = wait_for_info(link.fetch_info, timeout, bridge)
        yield link, info, info_bytes, bridge
    finally:
        if link is not None:
            link.close()
        if bridge is not None:
            bridge.close()


# start --------------------------------------------------------------------------------------------

LOCK_FILE = ".station.lock"


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


@contextlib.contextmanager
def claimed(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on the run folder ``out`` (``.station.lock``, released when the process
    ends however it ends): two missions writing one run.mcap would interleave their chunks and
    leave neither log readable. A folder in use is a ConfigError naming it."""
    path = out / LOCK_FILE
    with open(path, "a+b") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(f"{out}: another station is writing a mission into this folder (it holds {path}); "
                              "give this one its own --out") from None
        yield


def start(args: argparse.Namespace) -> int:
    config = load_station_config(args.config)
    if args.max_duration is not None:
        config = dataclasses.replace(config, mission=dataclasses.replace(config.mission, max_duration=args.max_duration))
    resolution = args.resolution or config.station.resolution
    out = args.out or Path("runs") / datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    with claimed(out):
        return _mission(args, config, resolution, out)


def _mission(args: argparse.Namespace, config: StationConfig, resolution: str, out: Path) -> int:
    """``station start`` in the claimed folder ``out``: the bridge, the loop, the log and the outputs."""
    interrupts = Interrupts()
    console = logs.LogTopicHandler()  # the console from here on goes into the run log too
    logging.getLogger(logs.LOGGER).addHandler(console)
    live = None
    if args.live is not None:
        from station.live import LiveServer

        live = LiveServer(args.live_host, args.live)
    died: List[int] = []
    summary: Optional[RunSummary] = None
    timeout = min(config.station.bridge_timeout, config.mission.max_duration)
    try:
        with connected(args, config, out, timeout) as (link, info, info_bytes, bridge):
            if bridge is not None:  # its exit ends the mission at once (the loop sees the bridge lost)
                bridge.watch(lambda code: (died.append(code), link.inbox.put(
                    Received("bridge_lost", now(), f"the bridge process exited with code {code}".encode()))))
            link.start()
            if args.resolution and info.resolution != args.resolution:
                log.warning("--resolution %s ignored: the bridge runs %s", args.resolution, info.resolution)
            log.info("%s bridge %s, %s, %s; mission starts (time limit %g s)", info.backend, info.bridge_version,
                     info.robot.name, info.resolution, config.mission.max_duration)
            run_log = McapLog(out / "run.mcap", config.station.flush_interval, sinks=[live] if live else [])
            try:
                console.bind(lambda message, t: run_log.proto(LOG, message, t))
                summary = ControlLoop(config, link, info, info_bytes, run_log, interrupts).run()
            finally:
                console.bind(lambda message, t: None)  # the outcome lines come after the log is closed
                run_log.close()
            if died:
                raise BridgeFailed(f"the bridge exited with code {died[0]} during the mission (its log: {bridge.log_path})",
                                   bridge.last_lines())
    except BridgeFailed as exc:
        _report_bridge_failure(exc)
        if summary is None:
            summary = RunSummary(outcome="bridge_unavailable", reason=str(exc), success=False, frames_received=0,
                                 frames_processed=0, duration=0.0, carver=None, carving_error=None, x=None, P=None)
        code = _outputs(summary, out, resolution)
        return EXIT_CONFIG if code != 0 else code
    finally:
        logging.getLogger(logs.LOGGER).removeHandler(console)
        if live is not None:
            live.close()
    return _outputs(summary, out, resolution)


def _transport(args: argparse.Namespace, config: StationConfig, endpoint: str) -> TransportConfig:
    name, lease = config.station.robot_name, config.station.lease_ms
    if args.secure:
        return TransportConfig.secure("station", args.secure, robot=name, connect=(endpoint,), lease_ms=lease)
    if args.insecure:
        return TransportConfig(connect=(endpoint,), lease_ms=lease, robot=name)
    return TransportConfig.with_credentials("station", connect=(endpoint,), lease_ms=lease, robot=name)


def _bridge_args(args: argparse.Namespace, config: StationConfig, resolution: str, out: Path) -> List[str]:
    bridge: dict = {"name": config.station.robot_name, "resolution": resolution}
    if config.robot_overrides:
        bridge["robot"] = str(Path(config.robot_overrides[-1]).resolve())
    override = out / "bridge.yaml"
    override.write_text(yaml.safe_dump({"bridge": bridge}))
    backend = ["--sim", "--scenario", args.scenario, "--seed", str(args.seed)] if args.robot == SIM else \
        ["--naoqi", args.naoqi if "://" in args.naoqi else f"tcp://{args.naoqi}:{NAOQI_PORT}"]
    secure = ["--secure", args.secure] if args.secure else ["--insecure"] if args.insecure else []
    level = {1: "DEBUG", -1: "WARNING"}.get(args.verbosity, "INFO")
    return [*backend, *secure, "--config", str(override), "--log-level", level]


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
            from station.report import write_report  # matplotlib: imported by the commands that draw only

            files["report"] = [p.name for p in write_report(log_path, out, mesh)]
        except Exception as exc:  # noqa: BLE001 - a figure must never cost the result
            files["report_error"] = f"{type(exc).__name__}: {exc}"
    result = build_result(summary, log_path, files, resolution)
    write_result(result, out / "result.json")
    code = exit_code(summary.outcome)
    log.info("%s (%s): %s", result["status"], summary.outcome, summary.reason)
    log.info("outputs in %s", out.resolve())
    return code


# offline tools ------------------------------------------------------------------------------------


def replay_command(args: argparse.Namespace) -> int:
    result = replay(args.log, progress=True)
    print(json.dumps(result.as_dict(), indent=2))
    if result.ok:
        log.info("replay: %d outputs (%d decisions) from %d inputs reproduced exactly",
                 result.compared, result.decisions, result.inputs)
        return 0
    if result.code_changed:
        log.warning("replay: the agent's code changed since this run (code digest differs)")
    if result.divergence is not None:
        d = result.divergence
        log.error("replay: first divergence on %s #%d at t=%.3f", d.topic, d.rank, d.t)
    else:
        log.error("replay: recorded outputs not reproduced: %s", result.unmatched)
    return EXIT_FAILURE


def carve_command(args: argparse.Namespace) -> int:
    from station.carve import carve_log

    carver = carve_log(args.log, args.resolution, args.tolerance)
    path = save_mesh(carver.to_mesh(), args.output)
    print(json.dumps({"mesh": str(path), "pitch": carver.pitch, "views": carver.views_added,
                      "metrics": dataclasses.asdict(carver.metrics())}, indent=2))
    return 0


def report_command(args: argparse.Namespace) -> int:
    from station.report import write_report

    for path in write_report(args.log, args.out or args.log.parent):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
