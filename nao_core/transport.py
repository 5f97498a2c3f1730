"""Zenoh sessions for the bridge, the station and viewers: one place that turns options into a zenoh.Config.

Practice (docs/security.md and docs/protocol.md, checked with eclipse-zenoh 1.10): peer mode on every side, multicast and gossip
scouting off, explicit listen (bridge) and connect (station, viewer) endpoints, and a short link
lease (1.5 s, 4 keep-alives per lease) so that a frozen peer is noticed within the lease (its
liveliness tokens then disappear). Shared-memory transport is off: frames are small, and with it
on every closed session to a peer on the same host left that peer's segment mapped (one file
descriptor leaked per station session, found by tests/test_soak.py). ``insert_json5`` takes JSON5
literals, hence ``json.dumps``.

Secure by default (docs/security.md). Out of the box every session authenticates with Zenoh's
user/password (``credentials``): a file of ``user:password`` lines for ``bridge``, ``station`` and
``viewer``, generated with random passwords on first use (:func:`ensure_credentials`, mode 0600,
``~/.config/nao-active-recon/credentials`` unless ``$NAO_RECON_CREDENTIALS`` says otherwise). The
listener (the bridge) accepts every user in it and applies its access policy by user name; a
connecting side presents its own ``user``'s line. Plain mode (no authentication at all) must be
asked for (``nao-bridge --insecure``); :func:`exposure` tells whether a configuration listens on a
non-loopback interface without authentication. Mutual TLS adds up to three layers:

* TLS with mutual authentication: every link is ``tls/``; both ends present a certificate signed by
  the lab CA (``station make-certs``) and reject any other; ``transport/link/protocols`` admits
  TLS only, so no plain link can be opened or accepted.
* Optional user/password authentication (``transport/auth/usrpwd``): this side's credentials and
  the ``user:password`` dictionary of the peers it accepts. Zenoh checks them on the listening
  side only: the bridge authenticates the station and viewers, not the other way round.
* An access-control policy (``access_control``, deny by default) from ``config/zenoh/acl_<role>.yaml``,
  which needs TLS or user/password (something must tell the peers apart). Key expressions there are written with ``{robot}`` for the robot's name. A
  subject lists the identities a peer must prove, all of them: ``cert_common_names`` (from its
  certificate) and, on the bridge, ``usernames``; without user/password the ``usernames`` are
  dropped, so the certificate alone identifies a peer.
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import yaml
import zenoh

from nao_core.config import CONFIG_DIR, ConfigError, bounds
from nao_core.protocol.keys import RobotKeys

ROLES = ("bridge", "station", "viewer")
DEFAULT_CREDENTIALS = "~/.config/nao-active-recon/credentials"
CREDENTIALS_ENV = "NAO_RECON_CREDENTIALS"


def credentials_path(path: Optional[str] = None) -> Path:
    """``path``, else ``$NAO_RECON_CREDENTIALS``, else the default, with ``~`` expanded."""
    return Path(path or os.environ.get(CREDENTIALS_ENV) or DEFAULT_CREDENTIALS).expanduser()


def ensure_credentials(path: Union[str, Path]) -> Dict[str, str]:
    """The ``user: password`` of every role in ``path``, creating the file on first use.

    Creation is atomic (a private temporary file hard-linked to ``path``): when two processes
    start at once (a station and the bridge it launches) both read the same passwords.
    """
    path = Path(path)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        text = "".join(f"{role}:{secrets.token_hex(16)}\n" for role in ROLES)
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        try:
            os.link(temporary, path)
        except FileExistsError:
            pass  # another process won the race: use its file
        finally:
            temporary.unlink()
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the credentials: {exc.strerror or exc}") from None
    users = dict(line.split(":", 1) for line in lines if ":" in line)
    missing = [role for role in ROLES if not users.get(role)]
    if missing:
        raise ConfigError(f"{path}: credentials file has no password for {', '.join(missing)} "
                          "(lines user:password; delete it to generate a new one)")
    return users


@dataclass(frozen=True)
class TlsFiles:
    """PEM files for mutual TLS: the lab CA, this side's certificate and its private key."""

    root_ca: str
    certificate: str
    private_key: str
    verify_name_on_connect: bool = True  # the listener's certificate must name the host connected to


@dataclass(frozen=True)
class UserPassword:
    """This side's credentials, and the file of ``user:password`` lines of the peers it accepts."""

    user: str
    password: str
    dictionary_file: Optional[str] = None

    def __post_init__(self) -> None:
        if not self.user or not self.password:
            raise ValueError("user/password authentication needs a non-empty user and password")


@dataclass(frozen=True)
class TransportConfig:
    listen: Tuple[str, ...] = ()  # e.g. ("tcp/[::]:7447",)
    connect: Tuple[str, ...] = ()  # e.g. ("tcp/nao.local:7447",)
    lease_ms: int = field(default=1500, metadata=bounds(200, 60000))
    keep_alive: int = field(default=4, metadata=bounds(1, 100))  # keep-alives per lease
    tls: Optional[TlsFiles] = None
    usrpwd: Optional[UserPassword] = None
    acl_file: Optional[str] = None  # access-control policy (YAML, top-level key access_control)
    robot: str = "nao"  # substituted for {robot} in the policy's key expressions
    credentials: Optional[str] = None  # user:password file, generated on first use ("default": credentials_path())
    user: str = "station"  # the line of ``credentials`` this side presents when it connects

    def __post_init__(self) -> None:
        RobotKeys(self.robot)  # validates the name
        if self.tls is not None:
            plain = [e for e in (*self.listen, *self.connect) if not e.startswith("tls/")]
            if plain:
                raise ValueError(f"endpoint {plain[0]!r}: with TLS every endpoint must be tls/<host>:<port>")
        if self.user not in ROLES:
            raise ValueError(f"user {self.user!r}: expected one of {list(ROLES)}")
        if self.acl_file is not None and self.tls is None and self.usrpwd is None and self.credentials is None:
            raise ValueError("an access-control policy needs TLS or user/password: something must tell the peers apart")

    @property
    def authenticated(self) -> bool:
        """Whether a peer must prove who it is before it gets a link."""
        return self.tls is not None or self.usrpwd is not None or self.credentials is not None

    def resolved(self) -> "TransportConfig":
        """With ``credentials`` turned into user/password (and, on a listener, the bridge's policy)."""
        if self.credentials is None or self.usrpwd is not None:
            return self
        path = credentials_path(None if self.credentials == "default" else self.credentials)
        users = ensure_credentials(path)
        listener = bool(self.listen)
        usrpwd = UserPassword(self.user, users[self.user], str(path) if listener else None)
        acl = self.acl_file or (str(CONFIG_DIR / "zenoh" / "acl_bridge.yaml") if listener else None)
        return dataclasses.replace(self, usrpwd=usrpwd, acl_file=acl)

    @classmethod
    def with_credentials(cls, user: str, *, listen: Tuple[str, ...] = (), connect: Tuple[str, ...] = (),
                         credentials: str = "default", lease_ms: int = 1500, robot: str = "nao") -> "TransportConfig":
        """The default security: user/password from the (generated) credentials file."""
        return cls(listen=listen, connect=connect, lease_ms=lease_ms, robot=robot, credentials=credentials, user=user)

    @classmethod
    def secure(cls, role: str, cert_dir: Union[str, Path], *, robot: str = "nao", listen: Tuple[str, ...] = (),
               connect: Tuple[str, ...] = (), usrpwd: Optional[UserPassword] = None,
               acl_file: Union[str, Path, None] = None, lease_ms: int = 1500) -> "TransportConfig":
        """Mutual TLS with ``cert_dir/{ca,<role>}.pem`` and ``<role>.key``, plus the role's policy.

        ``tcp/`` endpoints are turned into ``tls/`` endpoints on the same address, so a CLI can
        build its usual endpoints and pass ``--secure`` through. The policy defaults to
        ``config/zenoh/acl_<role>.yaml``.
        """
        if role not in ROLES:
            raise ValueError(f"role {role!r}: expected one of {list(ROLES)}")
        cert_dir = Path(cert_dir)
        tls = TlsFiles(str(cert_dir / "ca.pem"), str(cert_dir / f"{role}.pem"), str(cert_dir / f"{role}.key"))
        policy = Path(acl_file) if acl_file is not None else CONFIG_DIR / "zenoh" / f"acl_{role}.yaml"
        return cls(listen=tuple(map(_over_tls, listen)), connect=tuple(map(_over_tls, connect)), lease_ms=lease_ms,
                   tls=tls, usrpwd=usrpwd, acl_file=str(policy), robot=robot)


def exposure(options: TransportConfig) -> Optional[str]:
    """A warning when ``options`` listens beyond loopback with no authentication, else None."""
    if options.authenticated:
        return None
    exposed = [e for e in options.listen if not _loopback(e)]
    if not exposed:
        return None
    return (f"INSECURE: listening on {', '.join(exposed)} with no authentication: anyone who reaches "
            "this port can drive the robot (docs/security.md)")


def _loopback(endpoint: str) -> bool:
    """Whether a ``proto/host:port`` endpoint only listens on the loopback interface."""
    address = endpoint.split("/", 1)[-1].split("#", 1)[0].rsplit(":", 1)[0].strip("[]")
    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False  # a host name or an interface: assume reachable


def _over_tls(endpoint: str) -> str:
    return "tls/" + endpoint[len("tcp/"):] if endpoint.startswith("tcp/") else endpoint


def _readable(path: str, what: str) -> str:
    if not Path(path).is_file():
        raise ConfigError(f"{path}: {what}: no such file (make one with `nao-bridge make-certs`)")
    return str(Path(path).resolve())


def access_control(options: TransportConfig) -> Dict[str, Any]:
    """The ``access_control`` section from the policy file, for this robot and these identities."""
    assert options.acl_file is not None
    path = options.acl_file
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict) or set(data) != {"access_control"} or not isinstance(data["access_control"], dict):
        raise ConfigError(f"{path}: expected a single top-level mapping 'access_control'")
    section = json.loads(json.dumps(data["access_control"]).replace("{robot}", options.robot))
    subjects = section.get("subjects") or []
    if not all(isinstance(s, dict) for s in subjects):
        raise ConfigError(f"{path}: access_control.subjects: expected a list of mappings")
    if options.usrpwd is None:  # no user name is proven: the certificate alone identifies a peer
        subjects = [{k: v for k, v in s.items() if k != "usernames"} for s in subjects]
    if options.tls is None:  # no certificate: the user name alone identifies a peer
        subjects = [{k: v for k, v in s.items() if k != "cert_common_names"} for s in subjects]
    section["subjects"] = subjects
    return section


def zenoh_config(options: TransportConfig) -> zenoh.Config:
    options = options.resolved()
    config = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "listen/endpoints": list(options.listen),
        "connect/endpoints": list(options.connect),
        "transport/link/tx/lease": options.lease_ms,
        "transport/link/tx/keep_alive": options.keep_alive,
        "transport/shared_memory/enabled": False,
    }
    if options.tls is not None:
        tls = options.tls
        ca = _readable(tls.root_ca, "CA certificate")
        cert = _readable(tls.certificate, "certificate")
        key = _readable(tls.private_key, "private key")
        settings.update({
            "transport/link/protocols": ["tls"],
            "transport/link/tls/root_ca_certificate": ca,
            "transport/link/tls/listen_certificate": cert,
            "transport/link/tls/listen_private_key": key,
            "transport/link/tls/connect_certificate": cert,
            "transport/link/tls/connect_private_key": key,
            "transport/link/tls/enable_mtls": True,
            "transport/link/tls/verify_name_on_connect": tls.verify_name_on_connect,
        })
    if options.usrpwd is not None:
        settings["transport/auth/usrpwd/user"] = options.usrpwd.user
        settings["transport/auth/usrpwd/password"] = options.usrpwd.password
        if options.usrpwd.dictionary_file is not None:
            settings["transport/auth/usrpwd/dictionary_file"] = _readable(options.usrpwd.dictionary_file,
                                                                         "user/password dictionary")
    if options.acl_file is not None:
        settings["access_control"] = access_control(options)
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            source = options.acl_file if key == "access_control" else "transport options"
            raise ConfigError(f"{source}: {key}: rejected by zenoh: {exc}") from None
    return config


def open_session(options: TransportConfig) -> zenoh.Session:
    """Open a peer session with the given endpoints and security.

    Raises ConfigError for a missing certificate, key, dictionary or bad policy, and zenoh.ZError
    with zenoh's reason when the session cannot open (e.g. the listen port is taken).
    """
    return zenoh.open(zenoh_config(options))
