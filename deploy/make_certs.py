#!/usr/bin/env python3
"""Create the fleet's certificate authority and one certificate per identity.

Usage::

    python deploy/make_certs.py DIR --robots r1 r2 r3 [--router-host 192.168.1.10 ...]
    python deploy/make_certs.py DIR --scenario scenarios/paper_three_robots.toml

Every Zenoh node of a secure deployment authenticates with mutual TLS: its
certificate's common name (CN) is its identity, and the router's access
control grants rights by that name (``secure_router/access.py``).  Identities are the
robot ids (the agent and the ``epuck_link`` of robot R both use R), plus
``tracker``, ``supervisor``, ``operator`` (``fleet goal``), ``router``, and for the
fleet's ROS 2 face ``ros2`` (``python -m ros2_link``) and ``ros_client`` (ROS 2 tools
such as ``ros2 topic echo`` or RViz; the router grants these two anything only when it
is given a ROS domain).

Layout written into DIR::

    DIR/ca.pem              CA certificate (public)
    DIR/ca.key              CA private key, mode 0600: keep it on the admin machine only
    DIR/<name>/cert.pem     certificate of <name>, CN=<name>, signed by the CA
    DIR/<name>/key.pem      its private key, mode 0600 (directory mode 0700)
    DIR/<name>/ca.pem       copy of the CA certificate

so ``DIR/<name>/`` is everything the machine running <name> needs.  Running the
script again on the same DIR reuses the CA and adds the identities that are
missing; existing ones are kept unless ``--force`` is given (then they are
re-issued by the same CA).  ``--new-ca`` refuses to touch a DIR that already
has a CA, so a second, unrelated CA can be made for tests.

Keys are ECDSA P-256 in PKCS#8 PEM, certificates X.509 v3 with SHA-256.  The
router's certificate carries subject alternative names for ``localhost``,
``127.0.0.1`` and every ``--router-host`` (the name or address the robots
connect to: Zenoh checks it against the certificate).  Needs the
``cryptography`` package.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import os
import re
import sys
import tomllib
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
"""Identity names: the robot-id pattern of ground/wire.py."""
SERVICES = ("tracker", "supervisor", "operator", "router", "ros2", "ros_client")
"""Identities made besides the robots."""
ROUTER = "router"


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` created with ``mode`` (never readable by others, even briefly)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(tmp, mode)  # in case the umask cut bits we want (0644 for certificates)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "epuck-fleet"),
                      x509.NameAttribute(NameOID.COMMON_NAME, cn)])  # fmt: skip


def _key_usage(ca: bool) -> x509.KeyUsage:
    """digitalSignature, plus keyCertSign and cRLSign for a CA."""
    off = ("content_commitment", "key_encipherment", "data_encipherment", "key_agreement")
    return x509.KeyUsage(
        digital_signature=True, key_cert_sign=ca, crl_sign=ca, encipher_only=False, decipher_only=False,
        **dict.fromkeys(off, False),
    )  # fmt: skip


def make_ca(days: int, cn: str = "epuck-fleet CA") -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A self-signed CA valid for ``days`` days from now."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(_name(cn))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(ski, critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_leaf(
    cn: str,
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    days: int,
    hosts: list[str],
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate with CN ``cn`` for client and server authentication, signed by the CA.

    ``hosts``: DNS names or IP addresses put in the subject alternative name
    (only the router's certificate needs them: clients check the router's name)."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
    )
    if hosts:
        names: list[x509.GeneralName] = []
        for h in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                names.append(x509.DNSName(h))
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())


def robots_of(scenario: Path) -> list[str]:
    """The robot ids of a scenario file (``[[robots]] id = ...``)."""
    with scenario.open("rb") as f:
        doc = tomllib.load(f)
    robots = doc.get("robots")
    if not isinstance(robots, list) or not all(isinstance(r, dict) and "id" in r for r in robots):
        raise ValueError(f"{scenario}: expected [[robots]] tables with an id")
    return [str(r["id"]) for r in robots]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path, help="output directory (created if missing)")
    ap.add_argument("--robots", nargs="*", default=[], help="robot ids (certificate common names)")
    ap.add_argument("--scenario", type=Path, help="also take the robot ids of this scenario TOML")
    ap.add_argument("--router-host", action="append", default=[],
                    help="name or IP address the clients use to reach the router (repeatable)")  # fmt: skip
    ap.add_argument("--days", type=int, default=365, help="validity of the identity certificates [days]")
    ap.add_argument("--ca-days", type=int, default=3650, help="validity of a new CA [days]")
    ap.add_argument("--no-services", action="store_true",
                    help=f"make only the robots' certificates, not {', '.join(SERVICES)}")  # fmt: skip
    ap.add_argument("--new-ca", action="store_true", help="refuse to reuse an existing CA in DIR")
    ap.add_argument("--force", action="store_true", help="re-issue identities that already exist")
    args = ap.parse_args(argv)

    names = list(args.robots)
    if args.scenario is not None:
        try:
            names += robots_of(args.scenario)
        except (OSError, ValueError, tomllib.TOMLDecodeError) as e:
            print(f"make_certs: error: {e}", file=sys.stderr)
            return 2
    if not args.no_services:
        names += list(SERVICES)
    names = list(dict.fromkeys(names))  # unique, in order
    bad = [n for n in names if not NAME.match(n)]
    if bad:
        print(f"make_certs: error: identity names {bad} must match {NAME.pattern}", file=sys.stderr)
        return 2
    if not names:
        print("make_certs: error: nothing to make (give --robots or --scenario)", file=sys.stderr)
        return 2
    if args.days <= 0 or args.ca_days <= 0:
        print("make_certs: error: --days and --ca-days must be positive", file=sys.stderr)
        return 2

    out: Path = args.dir
    out.mkdir(parents=True, exist_ok=True)
    ca_cert_path, ca_key_path = out / "ca.pem", out / "ca.key"
    if ca_cert_path.exists() or ca_key_path.exists():
        if args.new_ca:
            print(f"make_certs: error: {out} already has a CA (--new-ca)", file=sys.stderr)
            return 2
        ca_key = serialization.load_pem_private_key(ca_key_path.read_bytes(), password=None)
        ca_cert = x509.load_pem_x509_certificate(ca_cert_path.read_bytes())
        if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
            print(f"make_certs: error: {ca_key_path} is not an EC key", file=sys.stderr)
            return 2
        print(f"reusing the CA in {out}", file=sys.stderr)
    else:
        ca_key, ca_cert = make_ca(args.ca_days)
        _write(ca_key_path, _key_pem(ca_key), 0o600)
        _write(ca_cert_path, _cert_pem(ca_cert), 0o644)
        print(f"new CA in {out}", file=sys.stderr)

    made, kept = [], []
    for n in names:
        d = out / n
        if (d / "cert.pem").exists() and not args.force:
            kept.append(n)
            continue
        d.mkdir(mode=0o700, exist_ok=True)
        os.chmod(d, 0o700)
        hosts = ["localhost", "127.0.0.1", *args.router_host] if n == ROUTER else []
        key, cert = make_leaf(n, ca_key, ca_cert, args.days, list(dict.fromkeys(hosts)))
        _write(d / "key.pem", _key_pem(key), 0o600)
        _write(d / "cert.pem", _cert_pem(cert), 0o644)
        _write(d / "ca.pem", _cert_pem(ca_cert), 0o644)
        made.append(n)
    print(f"made {made}" + (f", kept {kept} (use --force to re-issue)" if kept else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
