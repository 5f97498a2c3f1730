"""Make a lab certificate authority and the certificates of the bridge, the station and a viewer.

Uses the ``openssl`` command (1.1.1 or 3.x, or LibreSSL), not a Python package: it is already on
every Linux and macOS machine, on the robot and in CI, it adds no dependency to the project, and a
lab administrator can audit or repeat each step by hand (``docs/security.md`` lists them).

Output, in ``--out`` (default ``certs/``)::

    ca.pem, ca.key                 the lab CA (keep ca.key offline; only ca.pem is distributed)
    bridge.pem, bridge.key         common name "bridge"; SANs = the robot's --host names, localhost
    station.pem, station.key       common name "station"
    viewer.pem, viewer.key         common name "viewer" (may watch, may not command)

Keys are ECDSA P-256 in PKCS#8; certificates are X.509 v3 with subjectAltName, key usage and
both TLS server and client extended key usage (with mutual TLS each side proves who it is). The
access-control policies (``config/zenoh/acl_*.yaml``) name subjects by these common names.

    station make-certs --out certs --host nao.local --host 192.168.1.42
"""

from __future__ import annotations

import argparse
import ipaddress
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List, Optional, Sequence

ROLES = ("bridge", "station", "viewer")
CURVE = "prime256v1"


class CertError(RuntimeError):
    """openssl is missing or refused a step; the message carries its reason."""


def _openssl(*args: str) -> None:
    if shutil.which("openssl") is None:
        raise CertError("the 'openssl' command is not installed (apt-get install openssl)")
    done = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {done.stderr.strip()}")


def _subject_alt_names(names: Sequence[str]) -> str:
    entries = []
    for name in dict.fromkeys(names):  # unique, in order
        try:
            entries.append(f"IP:{ipaddress.ip_address(name)}")
        except ValueError:
            entries.append(f"DNS:{name}")
    return ",".join(entries)


def _new_key(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", f"ec_paramgen_curve:{CURVE}", "-out", str(path))
    path.chmod(0o600)


def make_ca(out: Path, days: int, name: str = "nao-active-recon lab CA") -> None:
    key, cert = out / "ca.key", out / "ca.pem"
    _new_key(key)
    with tempfile.NamedTemporaryFile("w", suffix=".cnf", delete=False) as ext:
        ext.write("[ca]\nbasicConstraints=critical,CA:TRUE,pathlen:0\nkeyUsage=critical,keyCertSign,cRLSign\n"
                  "subjectKeyIdentifier=hash\n")
    try:
        _openssl("req", "-x509", "-new", "-key", str(key), "-sha256", "-days", str(days), "-subj", f"/CN={name}",
                 "-config", ext.name, "-extensions", "ca", "-out", str(cert))
    finally:
        Path(ext.name).unlink()


def make_leaf(out: Path, role: str, names: Sequence[str], days: int) -> None:
    """Key and certificate for ``role`` (its common name), signed by the CA in ``out``."""
    key, csr, cert = out / f"{role}.key", out / f"{role}.csr", out / f"{role}.pem"
    _new_key(key)
    with tempfile.NamedTemporaryFile("w", suffix=".cnf", delete=False) as ext:
        ext.write("[req]\ndistinguished_name=dn\n[dn]\n[leaf]\nbasicConstraints=critical,CA:FALSE\n"
                  "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n"
                  f"subjectAltName={_subject_alt_names(names)}\nauthorityKeyIdentifier=keyid\n")
    try:
        _openssl("req", "-new", "-key", str(key), "-subj", f"/CN={role}", "-config", ext.name, "-out", str(csr))
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(out / "ca.pem"), "-CAkey", str(out / "ca.key"),
                 "-CAcreateserial", "-sha256", "-days", str(days), "-extfile", ext.name, "-extensions", "leaf",
                 "-out", str(cert))
    finally:
        Path(ext.name).unlink()
        csr.unlink(missing_ok=True)


def make_lab_certificates(out: Path, hosts: Sequence[str] = (), days: int = 825, force: bool = False,
                          roles: Sequence[str] = ROLES) -> List[Path]:
    """Create the CA (unless one is already in ``out``) and a certificate per role; return the files."""
    out.mkdir(parents=True, exist_ok=True)
    existing = [out / f"{role}.pem" for role in roles if (out / f"{role}.pem").exists()]
    if existing and not force:
        raise CertError(f"{existing[0]} exists; pass --force to replace the certificates in {out}")
    if force or not (out / "ca.key").exists():
        make_ca(out, days)
    for role in roles:
        names = [*hosts, "localhost", "127.0.0.1", "::1"] if role == "bridge" else [role]
        make_leaf(out, role, names, days)
    (out / "ca.srl").unlink(missing_ok=True)
    return sorted(out.iterdir())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("certs"), help="output folder (default: certs)")
    parser.add_argument("--host", action="append", default=[],
                        help="a name or address the station uses to reach the robot (repeatable), e.g. nao.local")
    parser.add_argument("--days", type=_positive_days, default=825, help="validity in days (default: 825)")
    parser.add_argument("--force", action="store_true", help="replace a CA and certificates already in --out")


def _positive_days(text: str) -> int:
    days = int(text)
    if days < 1:
        raise argparse.ArgumentTypeError(f"--days must be at least 1, got {text}")
    return days


def run(args: argparse.Namespace) -> int:
    """``station make-certs``: exit 0 with the files listed, 1 when openssl or the file system refused."""
    try:
        files = make_lab_certificates(args.out, args.host, args.days, args.force)
    except (CertError, OSError) as exc:
        print(f"make-certs: {exc}", file=sys.stderr)
        return 1
    print("\n".join(str(f) for f in files))
    print("copy ca.pem, bridge.pem and bridge.key to the robot; keep ca.key off the network", file=sys.stderr)
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    """The same as ``station make-certs`` (kept for ``python -m station.certs``)."""
    parser = argparse.ArgumentParser(prog="station make-certs", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
