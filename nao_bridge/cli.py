"""`nao-bridge`: run the bridge on a real NAO (NAOqi) or on the simulated one.

    nao-bridge --naoqi tcp://HOST:9559 [--listen tcp/[::]:7447] [--name nao] [--config FILE ...]
    nao-bridge --sim [--scenario can] [--seed 0] [--listen ...] [--name nao] [--config FILE ...]

``--secure CERT_DIR`` switches the session to mutual TLS with the bridge's access policy
(``TransportConfig.secure``, docs/security.md).

Exit codes: 0 after a clean stop (SIGINT, SIGTERM), 1 when the robot or the network cannot be
reached, 2 on a configuration or usage error (one line, never a traceback).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import sys
import threading
from typing import List, Optional

from nao_bridge.backend import RobotBackend
from nao_bridge.bridge import Bridge, BridgeParams
from nao_core.config import CONFIG_DIR, ConfigError, load, main_error
from nao_core.robot_model import RobotModel, load_robot_model
from nao_core.transport import TransportConfig

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
    try:
        if args.secure:
            transport = TransportConfig.secure(
                "bridge", args.secure, robot=name, listen=listen, lease_ms=params.transport.lease_ms
            )
        else:
            transport = dataclasses.replace(params.transport, listen=listen, robot=name)
    except ValueError as exc:
        raise ConfigError(f"transport: {exc}") from None
    return dataclasses.replace(params, name=name, transport=transport)


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


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        params = load_params(args)
        model = load_model(params)
        backend = make_backend(args, params, model)
    except ConfigError as exc:
        return main_error(exc)
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
