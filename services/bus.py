"""The zenoh bus: session factory, typed publish and query helpers.

Embedded default (no endpoint given): peer mode on loopback, multicast scouting off, rendezvous at the *hub*
endpoint ``tcp/127.0.0.1:7447``: the first process to start listens on it, later ones listen on a free loopback
port and connect to it; zenoh's gossip then meshes the peers directly, so the hub may go away. ``semloc up`` is
the hub of its graph. For real deployments pass ``--connect/--listen/--mode`` or a zenoh config file
(deploy/zenoh-*.json5); peers behind a router must be clients or have listen endpoints (docs/deploy.md).

Secure links (docs/security.md): ``--tls DIR/NAME`` (``BusConfig.tls``) gives a session mutual TLS credentials for
``tls/`` endpoints. A session that cannot connect raises :class:`BusError` with one line naming the endpoint and the
cause (services/security.py), at once rather than retrying in the background.

Pitfall handled here: a process that declared a Python-callback subscriber/queryable hangs at exit unless its
session is closed, so always use ``with open_session(...) as session`` (or close it in ``finally``).

Large frames are published from zenoh shared memory (:class:`FramePublisher`): encoded once, copied once into a
shared buffer, and handed to subscribers on this machine by reference; zenoh copies the buffer onto the wire for
peers that cannot map it (another host, shared memory off). Speed: docs/runtime.md.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Literal

import zenoh
import zenoh.shm
from pydantic import BaseModel, ConfigDict, Field

from schemas import Frame, FrameError, decode, encode
from services.security import BusError, TlsFiles, connection_error, fail_fast

log = logging.getLogger("semloc.bus")

DEFAULT_HUB = "tcp/127.0.0.1:7447"
LOOPBACK_ANY_PORT = "tcp/127.0.0.1:0"


class BusConfig(BaseModel):
    """How a process joins the zenoh network."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["peer", "client", "router"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on")
    zenoh_config: str | None = Field(None, description="a zenoh JSON5 config file; flags above override it")
    hub: str = Field(DEFAULT_HUB, description="rendezvous endpoint used when neither connect nor listen is given")
    multicast: bool = Field(False, description="multicast scouting (off: it fails silently in containers)")
    shared_memory: bool | None = Field(None, description="zenoh shared memory transport (None = zenoh default)")
    lease_ms: int | None = Field(2000, description="link lease: how fast a hung peer is noticed")
    tls: TlsFiles | None = Field(None, description="mutual TLS credentials for tls/ endpoints; the string DIR/NAME "
                                 "means DIR/ca.pem, DIR/NAME.pem, DIR/NAME-key.pem (semloc certs)")


def free_port() -> int:
    """A TCP port free on the loopback interface now, for a local hub's endpoint (``tcp/127.0.0.1:<port>``)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _zenoh_config(bus: BusConfig, listen: list[str], connect: list[str]) -> zenoh.Config:
    config = zenoh.Config.from_file(bus.zenoh_config) if bus.zenoh_config else zenoh.Config()
    config.insert_json5("mode", json.dumps(bus.mode))
    if not bus.zenoh_config or not bus.multicast:
        config.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast))
    if listen:
        # Added to a config file's own listeners (a secure router's TLS endpoint stays beside the graph's hub).
        listed = json.loads(config.get_json("listen/endpoints")) if bus.zenoh_config else []
        listed = listed if isinstance(listed, list) else []  # a dict: zenoh's per-mode default, not the file's
        config.insert_json5("listen/endpoints", json.dumps(list(dict.fromkeys([*listed, *listen]))))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    if bus.shared_memory is not None:
        config.insert_json5("transport/shared_memory/enabled", json.dumps(bus.shared_memory))
    if bus.lease_ms is not None:
        config.insert_json5("transport/link/tx/lease", json.dumps(int(bus.lease_ms)))
    if bus.tls is not None:
        for field, value in bus.tls.zenoh_settings().items():
            config.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    fail_fast(config)
    return config


def _open(config: zenoh.Config) -> zenoh.Session:
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        raise connection_error(config, error) from None


def open_session(bus: BusConfig | None = None) -> zenoh.Session:
    """Open a zenoh session as described by ``bus`` (see the module docstring for the embedded default).

    Raises :class:`BusError` (one line: the endpoint and the cause) when a link cannot be set up."""
    bus = bus or BusConfig()
    if bus.zenoh_config:
        if not Path(bus.zenoh_config).is_file():
            raise FileNotFoundError(f"zenoh config file not found: {bus.zenoh_config}")
        return _open(_zenoh_config(bus, list(bus.listen), list(bus.connect)))
    listen, connect = list(bus.listen), list(bus.connect)
    if not listen and not connect and bus.mode == "peer":
        try:
            session = zenoh.open(_zenoh_config(bus, [bus.hub], []))
            log.info("listening on the hub endpoint %s", bus.hub)
            return session
        except zenoh.ZError:
            connect = [bus.hub]  # somebody else is the hub: join it
    if bus.mode == "peer" and not listen:
        # Peers do not relay for each other: each needs a reachable endpoint of its own to mesh with the others.
        listen = [LOOPBACK_ANY_PORT]
    return _open(_zenoh_config(bus, listen, connect))


def bus_from_env(bus: BusConfig | None = None) -> BusConfig:
    """Apply SEMLOC_CONNECT / SEMLOC_LISTEN (comma-separated), SEMLOC_MODE, SEMLOC_ZENOH_CONFIG, SEMLOC_TLS
    (DIR/NAME) to ``bus``."""
    bus = bus or BusConfig()
    update = {}
    for field, var in (("connect", "SEMLOC_CONNECT"), ("listen", "SEMLOC_LISTEN")):
        if os.environ.get(var):
            update[field] = [e.strip() for e in os.environ[var].split(",") if e.strip()]
    if os.environ.get("SEMLOC_MODE"):
        update["mode"] = os.environ["SEMLOC_MODE"]
    if os.environ.get("SEMLOC_ZENOH_CONFIG"):
        update["zenoh_config"] = os.environ["SEMLOC_ZENOH_CONFIG"]
    if os.environ.get("SEMLOC_TLS"):
        update["tls"] = os.environ["SEMLOC_TLS"]
    return BusConfig.model_validate({**bus.model_dump(), **update})


def add_bus_arguments(parser) -> None:
    """``--mode/--connect/--listen/--zenoh-config/--hub/--tls`` for commands that open a session."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh mode (default peer)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")
    group.add_argument("--hub", metavar="ENDPOINT", help=f"rendezvous endpoint (default {DEFAULT_HUB})")
    group.add_argument("--tls", metavar="DIR/NAME", help="mutual TLS identity for tls/ endpoints: DIR/NAME.pem, "
                       "DIR/NAME-key.pem, DIR/ca.pem (semloc certs; docs/security.md)")


BUS_FLAGS = ("mode", "connect", "listen", "zenoh_config", "hub", "tls")


def bus_from_args(args, base: BusConfig | None = None) -> BusConfig:
    bus = bus_from_env(base)
    update = {}
    for field in BUS_FLAGS:
        value = getattr(args, field, None)
        if value:
            update[field] = value
    return BusConfig.model_validate({**bus.model_dump(), **update})


def uses_shared_memory(bus: BusConfig) -> bool:
    """Whether a session opened with ``bus`` has zenoh's shared-memory transport on (flag, config file, default)."""
    if bus.shared_memory is not None:
        return bool(bus.shared_memory)
    config = zenoh.Config.from_file(bus.zenoh_config) if bus.zenoh_config else zenoh.Config()
    return bool(json.loads(config.get_json("transport/shared_memory/enabled")))


# Frames smaller than this travel as plain bytes: a shared buffer costs more than copying them.
SHM_MIN_BYTES = 64 << 10
# One pool per process, shared by its publishers. A buffer returns to the pool when every subscriber has dropped
# it (the runtime copies a payload out on arrival). Frames in flight hold their buffers and zenoh's queues hold
# many small shared-memory messages, so a full pool is the back-pressure: a blocking publisher waits up to
# SHM_WAIT_S for room (as congestion control BLOCK would), then sends plain bytes; a dropping one sends bytes.
SHM_POOL_BYTES = 64 << 20
SHM_WAIT_S = 1.0
_SHM_RETRY_S = 0.0002
_shm_pool: "zenoh.shm.ShmProvider | None" = None
_shm_pool_lock = threading.Lock()
_SHM_POLICY = zenoh.shm.GarbageCollect(zenoh.shm.Defragment())


def _shared_memory_pool() -> "zenoh.shm.ShmProvider":
    global _shm_pool
    with _shm_pool_lock:
        if _shm_pool is None:
            _shm_pool = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES)
        return _shm_pool


class FramePublisher:
    """Publishes encoded frames on one key expression (from one thread at a time).

    Frames of at least ``SHM_MIN_BYTES`` go through a shared-memory buffer when ``shared_memory`` is on: the frame
    is encoded into a reused bytearray, copied once into the buffer, and zenoh passes the buffer itself to local
    subscribers. Putting the bytes themselves makes zenoh copy them again and carry them over the link; that way
    the semloc path reached only 0.54x raw zenoh's throughput of 640x480x3 frames (benchmarks/bus.py). With shared
    memory off, or no room in the pool (see ``SHM_WAIT_S``), the bytes are put as they are.
    """

    def __init__(self, session: zenoh.Session, key: str, *, block: bool = True, shared_memory: bool = True):
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self.key, self.block = key, bool(block)
        self.publisher = session.declare_publisher(key, congestion_control=congestion)
        self.shared_memory = bool(shared_memory)
        self.shm_frames = 0  # frames sent from shared memory
        self.shm_fallbacks = 0  # large frames sent as bytes because the pool had no room
        # Reused for every frame: no 1 MB allocation (and page faults) per camera frame.
        self._buffer = bytearray()

    def put_frame(self, frame: Frame) -> None:
        """Encode and publish ``frame`` (raises FrameError if it cannot be encoded)."""
        self.put_bytes(encode(frame, into=self._buffer))

    def put_bytes(self, payload: bytes | bytearray) -> None:
        """Publish already-encoded bytes (e.g. a received frame forwarded as is)."""
        size = len(payload)
        if self.shared_memory and SHM_MIN_BYTES <= size <= SHM_POOL_BYTES:
            buffer = self._allocate(size)
            if buffer is not None:
                buffer[0:size] = payload  # ZShmMut takes bytes or bytearray only (no buffer protocol in 1.10)
                self.publisher.put(zenoh.ZBytes(buffer))
                self.shm_frames += 1
                return
            self.shm_fallbacks += 1
        self.publisher.put(payload)

    def _allocate(self, size: int):
        pool = _shared_memory_pool()
        deadline = None
        while True:
            try:
                return pool.alloc(size, _SHM_POLICY)
            except zenoh.ZError:  # no room: the pool's buffers are all in flight
                if not self.block:
                    return None
                now = time.monotonic()
                deadline = deadline or now + SHM_WAIT_S
                if now >= deadline:
                    return None
                time.sleep(_SHM_RETRY_S)

    def undeclare(self) -> None:
        self.publisher.undeclare()


def payload_bytes(payload: zenoh.ZBytes) -> bytes:
    """A received payload as bytes (one copy). A shared-memory payload is copied straight out of its buffer:
    ``to_bytes()`` zero-fills its result before copying, a third dearer for 1 MB (measured here)."""
    shared = payload.as_shm()
    return bytes(shared) if shared is not None else payload.to_bytes()


def publish(session: zenoh.Session, key: str, frame: Frame, *, block: bool = True) -> None:
    """Encode and put one frame (``block``: wait for room rather than drop under congestion)."""
    congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
    session.put(key, encode(frame), congestion_control=congestion)


def query(
    session: zenoh.Session,
    key: str,
    request: Frame | None = None,
    reply_type: type[Frame] | tuple[type[Frame], ...] | None = None,
    timeout: float = 2.0,
    every_reply: bool = False,
) -> list[Frame]:
    """Ask every queryable matching ``key`` and return the decoded replies.

    ``every_reply``: no consolidation of the replies (zenoh's default keeps one per key) and every matching
    queryable asked, e.g. for a wildcard over many workers. Raises :class:`QueryError` when every answer was an
    error reply, :class:`schemas.FrameError` when a reply does not decode (or is not of ``reply_type``). No answer
    within ``timeout`` gives an empty list."""
    kwargs = {"timeout": float(timeout)}
    if every_reply:
        kwargs.update(consolidation=zenoh.ConsolidationMode.NONE, target=zenoh.QueryTarget.ALL)
    if request is not None:
        kwargs["payload"] = encode(request)
    frames = []
    errors = []
    for reply in session.get(key, **kwargs):
        if reply.ok is not None:
            frames.append(decode(payload_bytes(reply.ok.payload), expected=reply_type))
        else:
            message = reply.err.payload.to_string()
            if message != "Timeout":  # zenoh 1.x's reply when queryables did not answer in time: no answer
                errors.append(message)
    if errors and not frames:
        raise QueryError(f"query {key} failed: {'; '.join(errors)}")
    return frames


class QueryError(RuntimeError):
    """Every queryable that answered replied with an error."""


def ask(session: zenoh.Session, key: str, request: Frame | None = None,
        reply_type: type[Frame] | tuple[type[Frame], ...] | None = None, wait: float = 5.0) -> list[Frame]:
    """:func:`query` (every matching queryable, each reply) from a session just opened: asked again until something
    answers or ``wait`` seconds have passed, since a new session meshes with the others' over a few hundred
    milliseconds and a query sent before reaches nobody. An empty list: nothing answered. The operator's commands
    (``semloc localize``, ``logs``, ``stop``) use it."""
    deadline = time.monotonic() + wait
    while True:
        remaining = deadline - time.monotonic()
        replies = query(session, key, request, reply_type=reply_type, timeout=max(0.5, remaining), every_reply=True)
        if replies or remaining <= 0:
            return replies
        time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))


__all__ = [
    "BUS_FLAGS",
    "BusConfig",
    "BusError",
    "ask",
    "DEFAULT_HUB",
    "FrameError",
    "FramePublisher",
    "QueryError",
    "TlsFiles",
    "add_bus_arguments",
    "bus_from_args",
    "bus_from_env",
    "open_session",
    "payload_bytes",
    "publish",
    "query",
    "uses_shared_memory",
]
