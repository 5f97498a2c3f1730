"""`nao-bridge`: run the bridge on a real NAO (NAOqi) or on the simulated one.

    nao-bridge --naoqi tcp://HOST:9559 [--listen tcp/[::]:7447] [--name nao] [--config FILE ...]
    nao-bridge --sim [--scenario can] [--seed 0] [--listen ...] [--name nao] [--config FILE ...]

    nao-bridge install-watchdog HOST [--timeout 0.3] [--rest-after 0] [--user nao]

Secure by default (docs/security.md): the session authenticates peers with the user/password
file generated on first use and applies the bridge's access policy; ``--secure CERT_DIR``
switches to mutual TLS with the same policy. ``--insecure`` drops authentication: listening
beyond loopback without authentication is refused unless it is given, and warned about at every
start. Walking a remote NAO needs the robot-side watchdog (``install-watchdog``) to answer;
``--without-watchdog`` overrides that, loudly.

Exit codes: 0 after a clean stop (SIGINT, SIGTERM), 1 when the robot or the network cannot be
reached, 2 on a configuration or usage error (one line, never a traceback).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shlex
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import List, Optional

from nao_bridge.backend import RobotBackend
from nao_bridge.bridge import Bridge, BridgeParams
from nao_core.config import CONFIG_DIR, ConfigError, load, main_error
from nao_core.robot_model import RobotModel, load_robot_model
from nao_core.transport import TransportConfig, exposure

log = logging.getLogger("nao_bridge")


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("nao-active-recon")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


def parse_args(argv: Optional[List[str]]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="nao-bridge", description=__doc__.splitlines()[0])
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument("--naoqi", metavar="URL", help="NAOqi endpoint of the robot, e.g. tcp://nao.local:9559")
    target.add_argument("--sim", action="store_true", help="drive the simulated NAO")
    parser.add_argument("--scenario", default="can", help="simulator scenario (with --sim): can, remote, figure")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (with --sim)")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT", help="Zenoh endpoint(s), e.g. tcp/[::]:7447")
    parser.add_argument("--name", help="robot name: keys live under nao/<name>/")
    parser.add_argument("--secure", metavar="CERT_DIR", help="mutual TLS and the bridge's access policy (docs/security.md)")
    parser.add_argument("--insecure", action="store_true",
                        help="no authentication, no access policy: anyone who reaches the port drives the robot")
    parser.add_argument("--without-watchdog", action="store_true",
                        help="walk a remote NAO although the robot-side watchdog does not answer (unsafe)")
    parser.add_argument("--config", action="append", default=[], metavar="FILE", help="bridge config override(s) (top-level key bridge), merged in order")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("-v", dest="log_level", action="store_const", const="DEBUG", help="--log-level DEBUG")
    parser.add_argument("-q", dest="log_level", action="store_const", const="WARNING", help="--log-level WARNING")
    parser.add_argument("--version", action="version", version=f"nao-bridge {_version()}")
    return parser.parse_args(argv)


def load_params(args: argparse.Namespace) -> BridgeParams:
    params = load(BridgeParams, [CONFIG_DIR / "bridge.yaml", *args.config], section="bridge")
    name = args.name or params.name
    listen = tuple(args.listen) if args.listen else params.transport.listen
    if args.secure and args.insecure:
        raise ConfigError("--secure and --insecure: choose one")
    try:
        if args.secure:
            transport = TransportConfig.secure(
                "bridge", args.secure, robot=name, listen=listen, lease_ms=params.transport.lease_ms
            )
        elif args.insecure:
            transport = TransportConfig(listen=listen, lease_ms=params.transport.lease_ms, robot=name)
        else:
            transport = dataclasses.replace(params.transport, listen=listen, robot=name)
    except ValueError as exc:
        raise ConfigError(f"transport: {exc}") from None
    warning = exposure(transport)
    if warning is not None and not args.insecure:
        raise ConfigError(f"transport: listening on {', '.join(transport.listen)} without authentication: "
                          "give --insecure to accept that (docs/security.md)")
    watchdog = "off" if args.without_watchdog else params.robot_watchdog
    return dataclasses.replace(params, name=name, transport=transport, robot_watchdog=watchdog)


def load_model(params: BridgeParams) -> RobotModel:
    """NAO V6 merged with ``bridge.robot`` (a robot model file, relative to config/ or absolute)."""
    model = load_robot_model([CONFIG_DIR / params.robot] if params.robot else [])
    try:
        model.camera.intrinsics(params.resolution)
    except KeyError as exc:
        raise ConfigError(f"bridge.resolution: {exc.args[0]}") from None
    return model


def make_backend(args: argparse.Namespace, params: BridgeParams, model: RobotModel) -> RobotBackend:
    if args.sim:
        from nao_bridge.sim_backend import SimBackend

        try:
            return SimBackend.in_new_world(args.scenario, model, params.resolution, args.seed, params.fps)
        except KeyError as exc:
            raise ConfigError(f"--scenario: {exc.args[0]}") from None
    from nao_bridge.naoqi_backend import NaoqiBackend

    return NaoqiBackend(args.naoqi, model, params.naoqi, params.resolution, params.fps)


REMOTE_DIR = "nao-active-recon"


def install_watchdog(argv: List[str]) -> int:
    """Copy nao_bridge/watchdog.py to the robot over scp and (re)start it there over ssh."""
    parser = argparse.ArgumentParser(prog="nao-bridge install-watchdog", description=install_watchdog.__doc__)
    parser.add_argument("host", help="the robot, e.g. nao.local")
    parser.add_argument("--user", default="nao", help="ssh user on the robot (default: nao)")
    parser.add_argument("--timeout", type=float, default=0.3, help="s without a heartbeat before stopMove")
    parser.add_argument("--rest-after", type=float, default=0.0, help="s without a heartbeat before rest (0: never)")
    parser.add_argument("--python", default="python", help="the robot's Python (2.7 on a NAO V6)")
    parser.add_argument("--ssh", default="ssh", help=argparse.SUPPRESS)
    parser.add_argument("--scp", default="scp", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not (args.timeout > 0 and args.rest_after >= 0):
        parser.error("need --timeout > 0 and --rest-after >= 0")
    target = f"{args.user}@{args.host}"
    period = min(0.05, args.timeout / 4)
    start = (
        f"cd ~/{REMOTE_DIR} && {{ [ -f watchdog.pid ] && kill $(cat watchdog.pid) 2>/dev/null; true; }}; "
        f"nohup {shlex.quote(args.python)} watchdog.py --timeout {args.timeout:g} --period {period:g} "
        f"--rest-after {args.rest_after:g} >watchdog.log 2>&1 </dev/null & echo $! > watchdog.pid; "
        "sleep 1; kill -0 $(cat watchdog.pid) && echo watchdog running, pid $(cat watchdog.pid)"
    )
    source = Path(__file__).with_name("watchdog.py")
    steps = [[args.ssh, target, f"mkdir -p {REMOTE_DIR}"],
             [args.scp, str(source), f"{target}:{REMOTE_DIR}/watchdog.py"],
             [args.ssh, target, start]]
    for step in steps:
        try:
            done = subprocess.run(step, stdin=subprocess.DEVNULL, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as exc:
            print(f"install-watchdog: {step[0]}: {exc}", file=sys.stderr)
            return 1
        if done.returncode != 0:
            print(f"install-watchdog: `{shlex.join(step)}` failed (exit {done.returncode}); "
                  f"see {REMOTE_DIR}/watchdog.log on the robot", file=sys.stderr)
            return 1
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["install-watchdog"]:
        return install_watchdog(argv[1:])
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        params = load_params(args)
        model = load_model(params)
        backend = make_backend(args, params, model)
    except ConfigError as exc:
        return main_error(exc)
    warning = exposure(params.transport)
    if warning is not None or args.insecure:
        log.warning("%s", warning or "INSECURE: no authentication and no access policy (--insecure)")
    if args.without_watchdog and backend.remote:
        log.warning("UNSAFE: --without-watchdog: nothing on the robot stops it if this machine or its link "
                    "to NAOqi freezes (nao-bridge install-watchdog %s)", args.naoqi)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda num, _frame: stop.set())
    bridge = Bridge(backend, model, params, "sim" if args.sim else "naoqi")
    try:
        bridge.start()
    except ConfigError as exc:  # e.g. a missing certificate file
        bridge.close()
        return main_error(exc)
    except Exception as exc:  # noqa: BLE001 - unreachable robot, busy port: one line, exit 1
        log.error("cannot start: %s", str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
        bridge.close()
        return 1
    try:
        while not stop.wait(0.5):
            pass
    finally:
        log.info("stopping")
        bridge.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
