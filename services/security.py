"""A protected bus (docs/security.md): TLS credentials of a session, one-line connection errors, the secure router
configs of deploy/secure/, and what each endpoint of a graph exposes.

* :class:`TlsFiles`: a CA certificate and this process's own certificate and key (``--tls DIR/NAME`` reads
  ``DIR/ca.pem``, ``DIR/NAME.pem``, ``DIR/NAME-key.pem``: the layout of ``semloc certs``, services/certs.py).
* :func:`connection_error`: zenoh says only "Unable to connect to any of [...]" when a link fails; this looks at the
  endpoint itself (a TCP connection, a TLS handshake with the same files, Python's ``ssl``) and names the cause
  (no client certificate, a certificate of another CA, an expired one, a name the router's certificate does not
  cover, nobody listening...).
* :func:`render_secure_hub_config`: a router config of deploy/secure/ with its access-control rules, for one robot
  and one certificate directory (``semloc up --secure DIR``).
* :func:`endpoint_security`: every endpoint of a graph and what it lets through (``semloc up`` warns about plain
  TCP on a network address; ``--dry-run`` prints them all).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path

import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.config import ConfigError

CA_FILE = "ca.pem"
ACCESS_CONTROL_FILE = "access-control.json5"
PROBE_TIMEOUT_S = 3.0
SECURE_PROTOCOLS = ("tls", "quic")
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")
UNSPECIFIED_HOSTS = ("0.0.0.0", "::", "")


class TlsFiles(BaseModel):
    """Mutual TLS credentials of a session: the CA that the other end's certificate must be signed by, and this
    process's own certificate (its common name is its identity in the routers' access control) and private key.

    Given as a string ``DIR/NAME``: ``DIR/ca.pem``, ``DIR/NAME.pem`` and ``DIR/NAME-key.pem``."""

    model_config = ConfigDict(extra="forbid")

    ca: str = Field(description="CA certificate (PEM) the router's certificate is checked against")
    certificate: str | None = Field(None, description="this process's certificate (PEM)")
    private_key: str | None = Field(None, description="its private key (PEM, unencrypted)")

    @model_validator(mode="before")
    @classmethod
    def _from_identity(cls, value):
        if isinstance(value, (str, Path)):
            return cls.identity_files(value)
        return value

    @model_validator(mode="after")
    def _pair(self) -> "TlsFiles":
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("a TLS certificate and its private key go together: give both or neither")
        return self

    @staticmethod
    def identity_files(identity: str | Path) -> dict:
        identity = Path(identity)
        name = identity.name.removesuffix(".pem")
        if not name or name == "ca":
            raise ValueError(f"TLS identity {identity}: expected DIR/NAME (DIR/NAME.pem, DIR/NAME-key.pem, DIR/ca.pem)")
        return {"ca": str(identity.parent / CA_FILE), "certificate": str(identity.parent / f"{name}.pem"),
                "private_key": str(identity.parent / f"{name}-key.pem")}

    def zenoh_settings(self) -> dict:
        """``transport/link/tls`` of a session that connects with these credentials."""
        settings = {"root_ca_certificate": self.ca}
        if self.certificate:
            settings.update(connect_certificate=self.certificate, connect_private_key=self.private_key,
                            enable_mtls=True)
        return settings


class BusError(ConnectionError):
    """A session could not be opened; the message is one line naming the endpoint and the cause. ``transient``:
    retrying later may help (nobody listening yet) - not so for a credential problem."""

    def __init__(self, message: str, transient: bool = False):
        super().__init__(message)
        self.transient = transient


# ---------------------------------------------------------------------------------------------- endpoints
def endpoint_parts(endpoint: str) -> tuple[str, str, int | None]:
    """(protocol, host or path, port) of a zenoh endpoint such as ``tls/host:7448`` or ``tcp/[::1]:7447#iface=lo``."""
    protocol, _, address = str(endpoint).partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    if protocol in LOCAL_PROTOCOLS:
        return protocol, address, None
    host, _, port = address.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        return protocol, address, None
    return protocol, host.strip("[]"), number


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _tls_settings(config: zenoh.Config) -> dict:
    return json.loads(config.get_json("transport/link/tls"))


def listed_endpoints(config: zenoh.Config, path: str) -> list[str]:
    """A config's endpoint list; [] when the file leaves zenoh's per-mode default."""
    value = json.loads(config.get_json(path))
    return [str(e) for e in value] if isinstance(value, list) else []


# ---------------------------------------------------------------------------------------------- errors
def check_tls_files(settings: dict, endpoint: str) -> None:
    """BusError if the connect-side TLS files of ``endpoint`` cannot work: no CA, a file missing, not PEM, a key
    that is not the certificate's, or the certificate outside its validity period."""
    ca, certificate, key = (settings.get(k) for k in ("root_ca_certificate", "connect_certificate",
                                                         "connect_private_key"))
    for label, path in (("CA certificate", ca), ("certificate", certificate), ("private key", key)):
        if path and not Path(path).is_file():
            raise BusError(f"cannot connect to {endpoint}: TLS {label} {path} does not exist")
    if not ca:
        raise BusError(f"cannot connect to {endpoint}: a tls/ endpoint needs TLS credentials (--tls DIR/NAME: "
                       "DIR/ca.pem, DIR/NAME.pem, DIR/NAME-key.pem)")
    try:
        _context(settings, check_hostname=False)
    except ssl.SSLError as error:
        raise BusError(f"cannot connect to {endpoint}: TLS files {certificate or ca}: {error.reason or error}") \
            from None
    if certificate:
        from cryptography import x509

        cert = x509.load_pem_x509_certificate(Path(certificate).read_bytes())
        now = dt.datetime.now(dt.timezone.utc)
        if now > cert.not_valid_after_utc:
            raise BusError(f"cannot connect to {endpoint}: this client's certificate {certificate} expired on "
                           f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC")
        if now < cert.not_valid_before_utc:
            raise BusError(f"cannot connect to {endpoint}: this client's certificate {certificate} is not valid "
                           f"before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC")


def _context(settings: dict, check_hostname: bool) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = check_hostname
    context.load_verify_locations(settings["root_ca_certificate"])
    if settings.get("connect_certificate"):
        context.load_cert_chain(settings["connect_certificate"], settings["connect_private_key"])
    return context


# What a router's TLS alert means for this client (OpenSSL's reason codes).
_ALERTS = {
    "TLSV13_ALERT_CERTIFICATE_REQUIRED": "the router requires a client certificate (--tls DIR/NAME)",
    "TLSV1_ALERT_UNKNOWN_CA": "the router does not trust this client's certificate (signed by another CA)",
    "SSLV3_ALERT_BAD_CERTIFICATE": "the router rejected this client's certificate",
    "SSLV3_ALERT_CERTIFICATE_EXPIRED": "the router rejected this client's certificate: expired",
    "SSLV3_ALERT_UNSUPPORTED_CERTIFICATE": "the router rejected this client's certificate: unsupported (not for "
                                           "client authentication?)",
    "SSLV3_ALERT_CERTIFICATE_REVOKED": "the router rejected this client's certificate: revoked",
}


def _probe(protocol: str, host: str, port: int, settings: dict, verify_name: bool) -> tuple[str | None, bool]:
    """(cause, transient) of a failed connection, found by connecting to the endpoint ourselves; cause None: the
    TLS handshake went through and the router said nothing against this client."""
    try:
        raw = socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S)
    except socket.gaierror:
        return f"cannot resolve host {host!r}", True
    except ConnectionRefusedError:
        return "connection refused (nothing listens there)", True
    except TimeoutError:
        return f"no answer within {PROBE_TIMEOUT_S:.0f} s", True
    except OSError as error:
        return error.strerror or str(error), True
    with raw:
        if protocol != "tls":
            return "the connection opens but the zenoh session is refused (a TLS listener? then tls/ and --tls)", False
        try:
            context = _context(settings, check_hostname=verify_name)
            with context.wrap_socket(raw, server_hostname=host) as tls:
                # TLS 1.3: the router judges the client's certificate after the client's side of the handshake, so
                # its verdict (an alert) comes with the first read; an accepted client hears nothing.
                tls.settimeout(0.5)
                try:
                    tls.recv(1)
                except TimeoutError:
                    return None, False
        except ssl.SSLCertVerificationError as error:
            message = str(error.verify_message or error.reason)
            if "Hostname mismatch" in message or "IP address mismatch" in message:
                return f"the router's certificate is not valid for {host!r} (dial one of the names it was issued " \
                       "for)", False
            if "expired" in message:
                return "the router's certificate has expired", False
            return f"the router's certificate is not signed by {settings['root_ca_certificate']} ({message})", False
        except ssl.SSLError as error:
            reason = str(error.reason or "")
            if reason == "WRONG_VERSION_NUMBER":
                return "the endpoint does not speak TLS (a tcp/ endpoint?)", False
            return _ALERTS.get(reason, f"TLS handshake failed: {reason or error}"), False
        except (ConnectionError, TimeoutError, OSError) as error:
            return f"the router closed the TLS connection ({error})", False
    return "the router closed the connection", False


def connection_error(config: zenoh.Config, error: Exception) -> BusError:
    """A one-line BusError for a failed ``zenoh.open(config)``: the first connect endpoint that fails, and why."""
    zenoh_message = (str(error).split(" at /", 1)[0].strip().splitlines() or [type(error).__name__])[0]
    settings = _tls_settings(config)
    verify_name = settings.get("verify_name_on_connect") is not False
    connecting = json.loads(config.get_json("mode")) != "router" and "listener" not in zenoh_message
    for endpoint in listed_endpoints(config, "connect/endpoints") if connecting else []:
        protocol, host, port = endpoint_parts(endpoint)
        if protocol in ("tcp", "tls") and port is not None:
            cause, transient = _probe(protocol, host, port, settings, verify_name)
            cause = cause or "TLS is fine; the zenoh session itself was refused"
            return BusError(f"cannot connect to {endpoint}: {cause}", transient=transient)
    return BusError(f"cannot open a zenoh session: {zenoh_message}", transient=True)


def link_problems(config_file: str | Path) -> list[str]:
    """Why a router with this config cannot link to the routers it dials over TLS, one line each (nothing when
    all is well). A router retries in the background without a word: ``semloc up`` says it once at start."""
    config = zenoh.Config.from_file(str(config_file))
    settings = _tls_settings(config)
    problems = []
    for endpoint in listed_endpoints(config, "connect/endpoints"):
        protocol, host, port = endpoint_parts(endpoint)
        if protocol != "tls" or port is None:
            continue
        try:
            check_tls_files(settings, endpoint)
        except BusError as error:
            problems.append(str(error))
            continue
        cause, _ = _probe(protocol, host, port, settings, settings.get("verify_name_on_connect") is not False)
        if cause:
            problems.append(f"cannot connect to {endpoint}: {cause} (zenoh keeps trying)")
    return problems


def fail_fast(config: zenoh.Config) -> None:
    """A client or peer with TLS connect endpoints gives up at once when a link fails (zenoh's peer default is to
    retry forever in the background: a refused certificate would look like an empty bus); then
    :func:`connection_error` says why. Routers keep retrying (the other machine may come up later)."""
    mode = json.loads(config.get_json("mode"))
    endpoints = listed_endpoints(config, "connect/endpoints")
    if mode != "router" and any(endpoint_parts(e)[0] in SECURE_PROTOCOLS for e in endpoints):
        config.insert_json5("connect/timeout_ms", "0")
        config.insert_json5("connect/exit_on_failure", "true")
        for endpoint in endpoints:
            if endpoint_parts(endpoint)[0] in SECURE_PROTOCOLS:
                check_tls_files(_tls_settings(config), endpoint)


# ---------------------------------------------------------------------------------------------- secure routers
def secure_hub_endpoint(hub: str) -> str:
    """The hub (where this machine's nodes join their router) under ``--secure``: loopback or a Unix socket. An
    unspecified address (0.0.0.0) becomes 127.0.0.1; any other network address is refused - other machines come
    in over the secure config's TLS listener."""
    protocol, host, port = endpoint_parts(hub)
    if protocol in LOCAL_PROTOCOLS or (protocol == "tcp" and is_loopback(host)):
        return hub
    if protocol == "tcp" and host in UNSPECIFIED_HOSTS and port is not None:
        return f"tcp/127.0.0.1:{port}"
    raise ConfigError(f"--secure: the hub {hub} is not a loopback or unixsock-stream endpoint: this machine's nodes "
                      "join their router there in plain text; other machines use the secure config's TLS listener")


def secure_overrides(graph) -> dict:
    """Graph overrides under ``--secure``: the hub on loopback (see :func:`secure_hub_endpoint`). ``graph``: a
    services.launcher.Graph; ConfigError if it has no hub or no ``secure_hub_zenoh_config``."""
    if not graph.secure_hub_zenoh_config:
        raise ConfigError(f"--secure: graph {graph.name!r} has no secure_hub_zenoh_config (deploy/secure/, "
                          "docs/security.md)")
    if not graph.hub:
        raise ConfigError(f"--secure: graph {graph.name!r} has no hub: the secure config is the hub's")
    return {"hub": secure_hub_endpoint(graph.hub)}


def use_secure_hub(launcher, certificates: str | Path) -> Path:
    """Make the launcher's hub session the graph's secure router: its ``secure_hub_zenoh_config`` rendered for the
    graph's robot and the certificates in ``certificates``, written to the run directory (call before start)."""
    graph = launcher.graph
    path = render_secure_hub_config(graph.secure_hub_zenoh_config, graph.robot, certificates,
                                    launcher.run_dir / "hub-zenoh.json")
    graph.hub_zenoh_config = str(path)
    return path


def render_secure_hub_config(template: str | Path, robot: str, certificates: str | Path, output: str | Path) -> Path:
    """Write the router config ``template`` (deploy/secure/*-router.json5) with its access control (the
    ``access-control.json5`` beside it) for ``robot`` and the certificate directory ``certificates``: ``${ROBOT}``
    and ``${PKI}`` replaced. ConfigError if a file is missing or the result is not a valid zenoh config."""
    from schemas.base import check_name

    template, certificates = Path(template), Path(certificates).resolve()
    acl = template.parent / ACCESS_CONTROL_FILE
    for path in (template, acl):
        if not path.is_file():
            raise ConfigError(f"--secure: {path} does not exist")
    if not certificates.is_dir():
        raise ConfigError(f"--secure: no certificate directory {certificates} (make one with `semloc certs "
                          f"{certificates} --robot {robot}`)")
    robot = check_name(robot, "robot name")

    def fill(text: str) -> str:
        return text.replace("${ROBOT}", robot).replace("${PKI}", str(certificates))

    try:
        config = zenoh.Config.from_json5(fill(template.read_text()))
        config.insert_json5("access_control", fill(acl.read_text()))
    except zenoh.ZError as error:
        raise ConfigError(f"--secure: {template} or {acl}: {str(error).split(' at /', 1)[0]}") from None
    settings = _tls_settings(config)
    for field in ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
                  "connect_private_key"):
        if settings.get(field) and not Path(settings[field]).is_file():
            raise ConfigError(f"--secure: {settings[field]} does not exist (make the certificates with `semloc "
                              f"certs {certificates} --robot {robot}`)")
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(str(config) + "\n")
    return output


# ---------------------------------------------------------------------------------------------- what is exposed
@dataclass(frozen=True)
class EndpointSecurity:
    """One endpoint of a graph: who uses it (``hub listens``, ``hub connects``, ``node camera connects``), and
    what protects it. ``exposed``: plain text on a network address (anyone who reaches it can use the bus)."""

    role: str
    endpoint: str
    protection: str
    exposed: bool = False

    def line(self) -> str:
        return f"{self.role:28s} {self.endpoint:34s} {self.protection}"


def _protection(endpoint: str, settings: dict, listening: bool) -> tuple[str, bool]:
    protocol, host, _ = endpoint_parts(endpoint)
    if protocol in LOCAL_PROTOCOLS:
        return "local socket (this host)", False
    if protocol in SECURE_PROTOCOLS:
        if listening:
            if settings.get("enable_mtls"):
                return f"mutual TLS: clients need a certificate of {settings.get('root_ca_certificate')}", False
            return "TLS, but clients need no certificate (enable_mtls off): anyone may connect", True
        if settings.get("connect_certificate"):
            return f"mutual TLS as {settings['connect_certificate']}", False
        return "TLS, no client certificate", False
    if is_loopback(host):
        return "plain, loopback only (this host)", False
    return "PLAIN on a network address: whoever reaches it may read and write every key", True


def endpoint_security(graph, node_buses: dict[str, dict]) -> tuple[list[EndpointSecurity], str]:
    """(every endpoint of a graph with its protection, the hub's access control in words). ``graph``: a
    services.launcher.Graph; ``node_buses``: each node's bus settings (``connect``, ``listen``, ``tls``)."""
    hub_config = graph.hub_zenoh_config
    config = zenoh.Config.from_file(str(hub_config)) if hub_config else zenoh.Config()
    settings = _tls_settings(config)
    rows = []
    if graph.hub:
        listen = list(dict.fromkeys([graph.hub, *listed_endpoints(config, "listen/endpoints")]))
        for endpoint in listen:
            rows.append(EndpointSecurity("hub listens", endpoint, *_protection(endpoint, settings, True)))
        for endpoint in listed_endpoints(config, "connect/endpoints"):
            rows.append(EndpointSecurity("hub connects", endpoint, *_protection(endpoint, settings, False)))
    for name, bus in node_buses.items():
        tls = bus.get("tls")
        node_settings = TlsFiles.model_validate(tls).zenoh_settings() if tls else {}
        for endpoint in bus.get("listen") or []:
            rows.append(EndpointSecurity(f"node {name} listens", endpoint,
                                         *_protection(endpoint, node_settings, True)))
        for endpoint in bus.get("connect") or []:
            rows.append(EndpointSecurity(f"node {name} connects", endpoint,
                                         *_protection(endpoint, node_settings, False)))
    acl = json.loads(config.get_json("access_control"))
    if not graph.hub:
        access = "no hub: the nodes' own zenoh configs decide"
    elif acl.get("enabled"):
        access = (f"access control on, default {acl.get('default_permission')}: {len(acl.get('rules') or [])} "
                  f"rules, {len(acl.get('subjects') or [])} subjects")
    else:
        access = "access control off: every connected process may publish and query every key"
    return rows, access


# The host the shipped robot routers dial (deploy/two-machines/, deploy/secure/robot-router.json5) until the operator
# puts the base station's address there; zenoh would retry it in the background without a word.
PLACEHOLDER_HOST = "BASE_HOST"


def placeholder_endpoints(rows: list[EndpointSecurity], hub_config) -> list[str]:
    """One line per endpoint still naming the placeholder host; ``hub_config``: the hub's zenoh config file."""
    return [f"{row.role} {row.endpoint}: put the base station's address for {PLACEHOLDER_HOST} in {hub_config} "
            f"(in a copy of the graph's folder: docs/deploy.md, \"Several machines\")"
            for row in rows if endpoint_parts(row.endpoint)[1] == PLACEHOLDER_HOST]


def exposure_warnings(rows: list[EndpointSecurity]) -> list[str]:
    """One line per endpoint that listens in plain text on a network address."""
    return [f"{row.role} {row.endpoint}: {row.protection} (semloc up --secure DIR: docs/security.md)"
            for row in rows if row.exposed]
