"""A development certificate authority and the certificates of deploy/secure/ (docs/security.md).

Made with the ``cryptography`` package: ECDSA P-256 keys (PKCS#8 PEM), X.509 v3 certificates signed with SHA-256,
the extensions rustls (zenoh's TLS) checks: basic constraints, key usage, extended key usage (server and/or client
authentication), subject alternative names (the host names and addresses a client dials; rustls ignores the common
name there) and key identifiers. zenoh's access control matches a client by its certificate's *common name*.

Layout of a directory (``semloc certs DIR --robot r1``): ``ca.pem`` / ``ca-key.pem`` and, for every identity NAME,
``NAME.pem`` (certificate) / ``NAME-key.pem`` (its private key). ``open_session`` and ``semloc up --secure DIR``
read them by these names; a production PKI lays its files out the same way (docs/security.md).

For development only: one CA key on disk, no revocation list, no hardware keys.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from schemas.base import check_name

CA_NAME = "ca"
BASE_ROUTER = "base-router"
BASE_STATION = "base-station"
OPERATOR = "operator"
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
DEFAULT_DAYS = 365


def robot_router(robot: str) -> str:
    """Identity (file stem and common name) of a robot's router."""
    return f"{check_name(robot, 'robot name')}-router"


def robot_workers(robot: str) -> str:
    """Identity of a robot's workers joining a router over TLS (from a machine without a router of that robot)."""
    return f"{check_name(robot, 'robot name')}-workers"


def certificate_path(directory: str | Path, name: str) -> Path:
    return Path(directory) / f"{name}.pem"


def key_path(directory: str | Path, name: str) -> Path:
    return Path(directory) / f"{name}-key.pem"


@dataclass(frozen=True)
class IdentitySpec:
    """One certificate to issue: its file stem, which is also its common name, where it is used, and the names
    it answers to as a server (None: a client-only certificate)."""

    name: str
    where: str
    server_hosts: tuple[str, ...] | None = None


def layout(robot: str, base_hosts=(), robot_hosts=()) -> list[IdentitySpec]:
    """The identities deploy/secure/ needs for one robot and its base station (docs/security.md has their rights).

    Routers' certificates serve (the name a client dials must be among their hosts; loopback is always there) and
    also authenticate the router when it connects to the other one."""
    return [
        IdentitySpec(BASE_ROUTER, "base station: its router (semloc up deploy/two-machines/base.yaml --secure DIR)",
                     tuple(dict.fromkeys([*base_hosts, *LOCAL_HOSTS]))),
        IdentitySpec(robot_router(robot), f"robot {robot}: its router (semloc up deploy/two-machines/robot.yaml "
                     "--secure DIR)", tuple(dict.fromkeys([*robot_hosts, *LOCAL_HOSTS]))),
        IdentitySpec(robot_workers(robot), f"a worker of {robot} joining over TLS from a machine without a router "
                     f"of {robot} (semloc worker ... --tls DIR/{robot_workers(robot)})"),
        IdentitySpec(BASE_STATION, "read-only tools: dashboards, semloc status / record (--tls DIR/base-station)"),
        IdentitySpec(OPERATOR, "the operator: control queries, e.g. set_initial_pose (--tls DIR/operator)"),
    ]


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "semloc development"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _validity(days: int, start: dt.datetime | None = None) -> tuple[dt.datetime, dt.datetime]:
    """(not before, not after): from ``start`` (default: now, less a few minutes for clocks a little behind)."""
    if days < 1:
        raise ValueError(f"a certificate must be valid for at least one day, got {days}")
    start = start or dt.datetime.now(dt.timezone.utc) - dt.timedelta(minutes=5)
    return start, start + dt.timedelta(days=days)


def make_ca(common_name: str = "semloc development CA", days: int = 5 * DEFAULT_DAYS):
    """(private key, self-signed CA certificate)."""
    key = ec.generate_private_key(ec.SECP256R1())
    not_before, not_after = _validity(days)
    public = key.public_key()
    certificate = (
        x509.CertificateBuilder().subject_name(_name(common_name)).issuer_name(_name(common_name))
        .public_key(public).serial_number(x509.random_serial_number())
        .not_valid_before(not_before).not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, certificate


def _alternative_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def issue(ca_key, ca_certificate, common_name: str, *, server_hosts=None, days: int = DEFAULT_DAYS,
          start: dt.datetime | None = None):
    """(private key, certificate) of ``common_name`` signed by the CA, valid ``days`` from ``start`` (default now):
    client authentication always, server authentication too when ``server_hosts`` (DNS names or IP addresses) are
    given."""
    if not common_name:
        raise ValueError("a certificate needs a common name")
    key = ec.generate_private_key(ec.SECP256R1())
    not_before, not_after = _validity(days, start)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    builder = (
        x509.CertificateBuilder().subject_name(_name(common_name)).issuer_name(ca_certificate.subject)
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(not_before).not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    if server_hosts:
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
        builder = builder.add_extension(
            x509.SubjectAlternativeName([_alternative_name(h) for h in server_hosts]), critical=False)
    builder = builder.add_extension(x509.ExtendedKeyUsage(usages), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())


def _write_key(path: Path, key) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    # Created owner-only from the start: never world-readable, not even for a moment.
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as file:
        file.write(data)


def _write_certificate(path: Path, certificate) -> None:
    path.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))


def load_ca(directory: str | Path):
    """(private key, certificate) of the CA kept in ``directory``."""
    directory = Path(directory)
    certificate = x509.load_pem_x509_certificate(certificate_path(directory, CA_NAME).read_bytes())
    key = serialization.load_pem_private_key(key_path(directory, CA_NAME).read_bytes(), password=None)
    return key, certificate


@dataclass(frozen=True)
class Written:
    """One file of the layout and what was done to it: "created", "renewed" or "kept"."""

    path: Path
    action: str
    where: str


def write_layout(directory: str | Path, robot: str, *, base_hosts=(), robot_hosts=(), days: int = DEFAULT_DAYS,
                 renew: tuple[str, ...] = ()) -> list[Written]:
    """Create the CA (if ``directory`` has none) and every certificate of :func:`layout` that is missing; those
    named in ``renew`` are issued again (same common name, new key: rotation). Existing files are otherwise kept,
    so a second robot can be added to the same CA."""
    directory = Path(directory)
    specs = layout(robot, base_hosts, robot_hosts)
    unknown = sorted(set(renew) - {s.name for s in specs})
    if unknown:
        raise ValueError(f"cannot renew {', '.join(unknown)}: the identities are {', '.join(s.name for s in specs)}")
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)  # the CA key lives here
    written = []
    ca_where = "every machine: the CA certificate that every TLS link is checked against"
    if certificate_path(directory, CA_NAME).exists() or key_path(directory, CA_NAME).exists():
        ca_key, ca_certificate = load_ca(directory)
        written.append(Written(certificate_path(directory, CA_NAME), "kept", ca_where))
    else:
        ca_key, ca_certificate = make_ca(days=max(days, 5 * DEFAULT_DAYS))
        _write_key(key_path(directory, CA_NAME), ca_key)
        _write_certificate(certificate_path(directory, CA_NAME), ca_certificate)
        written.append(Written(certificate_path(directory, CA_NAME), "created", ca_where))
    written.append(Written(key_path(directory, CA_NAME), "kept" if written[0].action == "kept" else "created",
                           "nowhere: keep it offline; only `semloc certs` reads it, to issue certificates"))
    for spec in specs:
        cert_file, key_file = certificate_path(directory, spec.name), key_path(directory, spec.name)
        exists = cert_file.exists() and key_file.exists()
        if exists and spec.name not in renew:
            written.append(Written(cert_file, "kept", spec.where))
            continue
        key, certificate = issue(ca_key, ca_certificate, spec.name, server_hosts=spec.server_hosts, days=days)
        _write_key(key_file, key)
        _write_certificate(cert_file, certificate)
        written.append(Written(cert_file, "renewed" if exists else "created", spec.where))
    return written


def write_identity(directory: str | Path, name: str, ca_key, ca_certificate, *, server_hosts=None,
                   days: int = DEFAULT_DAYS, start: dt.datetime | None = None) -> None:
    """Issue one certificate ``name`` (common name) into ``directory`` with the given CA (e.g. an identity of
    another CA, or one whose validity is over, for tests)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    key, certificate = issue(ca_key, ca_certificate, name, server_hosts=server_hosts, days=days, start=start)
    _write_key(key_path(directory, name), key)
    _write_certificate(certificate_path(directory, name), certificate)


def common_name(path: str | Path) -> str:
    """The common name of the certificate in ``path``."""
    certificate = x509.load_pem_x509_certificate(Path(path).read_bytes())
    names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""
