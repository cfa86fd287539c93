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
peers that cannot map it (another host, shared memory off). The pool is sized from the frames the process sends and
from what /dev/shm has free; without room the frames go as bytes, counted (:class:`SharedMemoryPool`). Speed and
memory: docs/runtime.md.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Literal

import zenoh
import zenoh.ext
import zenoh.shm
from pydantic import BaseModel, ConfigDict, Field

from schemas import Frame, FrameError, decode, encode, peek_header
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
    shared_memory: bool | None = Field(None, description="zenoh shared memory transport (None = zenoh default, on); "
                                       "false: every frame as bytes (a container with a small /dev/shm)")
    shm_pool_frames: int = Field(4, ge=1, description="a process's shared-memory pool holds this many of the first "
                                 "large frame it sends (64 KB or more)")
    shm_pool_max_mb: float = Field(64.0, gt=0, description="at most this many MiB per process, and never more than "
                                   "/dev/shm has free (less 4 MiB)")
    shm_small_frames: bool = Field(False, description="zenoh's own second pool (16 MiB per process) for messages of "
                                   "3-64 KB; off: they are copied")
    lease_ms: int | None = Field(2000, description="link lease: how fast a hung peer is noticed")
    block_wait_ms: int | None = Field(
        500, gt=0, description="a blocking message waits at most this long for room on a link, then the link is "
        "closed (lost, as by the lease); None: zenoh's 5 s (docs/deploy.md, 'When the link drops')")
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
    # zenoh's "transport optimization" copies every message of 3 KB or more into a pool of its own: 16 MiB more per
    # process, committed, made without looking at /dev/shm, and when it cannot be made its half-made file fills
    # /dev/shm until the process ends (no zenoh session on the machine can open then). Frames below SHM_MIN_BYTES are
    # meant to be copied; larger ones come from SharedMemoryPool.
    config.insert_json5("transport/shared_memory/transport_optimization/enabled", json.dumps(bus.shm_small_frames))
    if bus.lease_ms is not None:
        config.insert_json5("transport/link/tx/lease", json.dumps(int(bus.lease_ms)))
    if bus.block_wait_ms is not None:
        # A router forwarding a blocking message to a link that takes nothing (a radio out of range, before its
        # lease ends) holds one of its few receiving threads meanwhile: with two held, it forwards nothing at all,
        # for its local processes either, until the wait ends.
        config.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                            json.dumps(int(bus.block_wait_ms) * 1000))
    if bus.tls is not None:
        for field, value in bus.tls.zenoh_settings().items():
            config.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    fail_fast(config)
    return config


def _open_or_without_shm(config: zenoh.Config) -> zenoh.Session:
    """``zenoh.open(config)``; if zenoh cannot make the session's shared-memory segment (12 KB in /dev/shm: full, or
    too small), the session is opened without shared memory and :data:`SHARED_MEMORY` says why (never a crash)."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        if _SHM_SEGMENT_ERROR not in str(error) or not json.loads(config.get_json("transport/shared_memory/enabled")):
            raise
        SHARED_MEMORY.refuse(f"zenoh could not make its session segment in {SHM_DIR} "
                             f"({_free_bytes() / 2**20:.1f} MiB free)")
        config.insert_json5("transport/shared_memory/enabled", "false")
        return zenoh.open(config)


def _open(config: zenoh.Config) -> zenoh.Session:
    try:
        return _open_or_without_shm(config)
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
            session = _open_or_without_shm(_zenoh_config(bus, [bus.hub], []))
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
# A blocking publisher whose pool is full waits up to SHM_WAIT_S for a buffer to come back (as congestion control
# BLOCK would), then sends bytes; a dropping one sends bytes at once. Frames in flight hold their buffers.
SHM_WAIT_S = 1.0
_SHM_RETRY_S = 0.0002
_SHM_POLICY = zenoh.shm.GarbageCollect(zenoh.shm.Defragment())
SHM_DIR = "/dev/shm"
# Left free in /dev/shm by a pool: other processes' session segments (12 KB each) and zenoh's buffer headers
# (1.25 MiB per process using shared memory, made after the pool).
SHM_RESERVE_BYTES = 4 << 20
_PAGE = 4096
_SHM_SEGMENT_ERROR = "Unable to create POSIX shm segment"


def _free_bytes() -> int:
    try:
        stat = os.statvfs(SHM_DIR)
    except OSError:
        return 0
    return stat.f_bavail * stat.f_frsize


def _unlink_orphans(before: set[str]) -> None:
    """Remove the segment files a failed pool creation left in SHM_DIR (zenoh leaves its half-made file, which holds
    what it took of /dev/shm until the process ends): new files no process holds open, zenoh's own test of an
    orphan (it runs it only when a process makes its first segment, which a full /dev/shm refuses)."""
    new = {os.path.join(SHM_DIR, name) for name in set(os.listdir(SHM_DIR)) - before if name.endswith(".zenoh")}
    if not new:
        return
    for fd_dir in Path("/proc").glob("[0-9]*/fd"):
        try:
            for fd in fd_dir.iterdir():
                new.discard(os.readlink(fd))
        except OSError:  # the process ended, or is not ours to look at
            continue
    for path in new:
        with contextlib.suppress(OSError):
            os.unlink(path)


class SharedMemoryPool:
    """The process's pool of shared-memory buffers for large frames, shared by its publishers.

    Made at the first frame of ``SHM_MIN_BYTES`` or more, for ``BusConfig.shm_pool_frames`` such frames, at most
    ``shm_pool_max_mb`` and what /dev/shm has free less ``SHM_RESERVE_BYTES`` (a pool's pages are all committed when
    it is made: it costs its size in RAM). Never made again: a frame larger than the pool goes as bytes. When there is
    no room for one frame, or zenoh fails, frames go as bytes, each counted by reason (``fallbacks``), and
    :meth:`details` says why in the worker's Status; a full /dev/shm is looked at again on later frames."""

    def __init__(self):
        self.provider: "zenoh.shm.ShmProvider | None" = None
        self.capacity = 0
        self.frame_bytes = 0  # the frame it was sized for
        self.frames = 0  # frames given a buffer of it
        self.fallbacks: dict[str, int] = {}  # large frames sent as bytes, per reason
        self.refused = ""  # why this process has no shared memory at all ("": it may have)
        self.unavailable = ""  # why there is no pool yet ("": none tried, or made)
        self._lock = threading.Lock()

    def refuse(self, reason: str) -> None:
        """No shared memory for this process's sessions (zenoh could not make their segment)."""
        log.warning("shared memory off: %s; every frame goes as bytes", reason)
        self.refused = reason

    def count_fallback(self, reason: str) -> None:
        with self._lock:
            self.fallbacks[reason] = self.fallbacks.get(reason, 0) + 1

    def _make(self, size: int, bus: BusConfig) -> None:
        per_frame = -(-size // _PAGE) * _PAGE  # each buffer starts on a page
        wanted = min(bus.shm_pool_frames * per_frame, int(bus.shm_pool_max_mb * 2**20))
        room = _free_bytes() - SHM_RESERVE_BYTES
        capacity = min(wanted, room) // _PAGE * _PAGE
        if capacity < per_frame:
            free = max(room + SHM_RESERVE_BYTES, 0) / 2**20
            self._unavailable(f"shm_pool_max_mb {bus.shm_pool_max_mb:g} holds no frame of {size} B"
                              if wanted < per_frame else f"{SHM_DIR} has {free:.1f} MiB free, less than a frame of "
                              f"{size} B and the {SHM_RESERVE_BYTES >> 20} MiB left for others")
            return
        before = set(os.listdir(SHM_DIR))
        try:
            self.provider = zenoh.shm.ShmProvider.default_backend(capacity)
        except zenoh.ZError as error:
            _unlink_orphans(before)
            self._unavailable(f"zenoh could not make a pool of {capacity} B in {SHM_DIR}: "
                              f"{str(error).split(' at /')[0]}")
            return
        self.capacity, self.frame_bytes, self.unavailable = capacity, size, ""
        if capacity < wanted:
            log.warning("shared-memory pool of %.1f MiB, not %.1f: %s has no more room", capacity / 2**20,
                        wanted / 2**20, SHM_DIR)

    def _unavailable(self, why: str) -> None:
        if why != self.unavailable:  # said once, not at every frame
            log.warning("no shared-memory pool: %s; large frames go as bytes", why)
        self.unavailable = why

    def allocate(self, size: int, bus: BusConfig, block: bool):
        """A buffer of ``size`` bytes (None: send the frame as bytes; counted here)."""
        with self._lock:
            if self.provider is None and not self.refused:
                self._make(size, bus)
            provider = self.provider
        if provider is None:
            self.count_fallback("no session shared memory" if self.refused else "no pool")
            return None
        if size > self.capacity:
            self.count_fallback("larger than the pool")
            return None
        deadline = None
        while True:
            try:
                buffer = provider.alloc(size, _SHM_POLICY)
            except zenoh.ZError:  # no room: the pool's buffers are all in flight
                now = time.monotonic()
                deadline = deadline or now + SHM_WAIT_S
                if not block or now >= deadline:
                    self.count_fallback("pool full")
                    return None
                time.sleep(_SHM_RETRY_S)
                continue
            with self._lock:
                self.frames += 1
            return buffer

    def details(self, enabled: bool | None) -> dict[str, str | int]:
        """For a worker's Status: whether its large frames travel in shared memory, the pool, and the fallbacks
        (``enabled``: the session's setting, None before it opened)."""
        if enabled is False:
            state = "off (bus.shared_memory or the zenoh config)"
        elif self.refused:
            state = f"off: {self.refused}"
        elif self.provider is not None:
            state = f"pool {self.capacity / 2**20:.1f} MiB for frames of {self.frame_bytes} B"
        elif self.unavailable:
            state = f"no pool: {self.unavailable}"
        else:
            state = "on, no pool (no frame of 64 KB or more sent)"
        with self._lock:
            fallbacks = dict(self.fallbacks)
        return {"shared_memory": state, "shm_frames": self.frames, "shm_fallbacks": sum(fallbacks.values()),
                **{f"shm_fallbacks: {why}": count for why, count in sorted(fallbacks.items())}}


SHARED_MEMORY = SharedMemoryPool()  # one per process


def stream_qos(bulk: bool) -> tuple[zenoh.CongestionControl, zenoh.Priority]:
    """(congestion control, priority) of a stream. A bulk one (images, heatmaps: large, and each consumer can do
    without some) is dropped where a link is congested, by every router on the way, and sent after every other
    stream: on a thin link between two machines it never holds its publisher's loop, nor delays the small frames
    behind it (odometry, heatlines, poses, status: they wait for room, docs/deploy.md "A thin link")."""
    if bulk:
        return zenoh.CongestionControl.DROP, zenoh.Priority.DATA_LOW
    return zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA


class NumberedPublisher:
    """A plain zenoh publisher whose samples carry its id and their number (source info). zenoh adds neither by
    itself (a recoverable publisher adds its own); with them a subscriber tells two publishers of one key apart
    (Input._count_gap): two workers with one name, a replay beside the worker it recorded, two replays."""

    def __init__(self, publisher: zenoh.Publisher):
        self.publisher, self.sn = publisher, 0

    def put(self, payload) -> None:
        self.sn += 1
        self.publisher.put(payload, source_info=zenoh.SourceInfo(self.publisher.id, self.sn))


class FramePublisher:
    """Publishes encoded frames on one key expression (from one thread at a time).

    Frames of at least ``SHM_MIN_BYTES`` go through a shared-memory buffer when shared memory is on: the frame is
    encoded into a reused bytearray, copied once into a buffer of the process's :data:`SHARED_MEMORY` pool, and
    zenoh passes the buffer itself to local subscribers. Putting the bytes themselves makes zenoh copy them again
    and carry them over the link; that way the semloc path reached only 0.54x raw zenoh's throughput of 640x480x3
    frames (benchmarks/bus.py). With shared memory off, or no buffer to be had (see :class:`SharedMemoryPool`), the
    bytes are put as they are.
    """

    def __init__(self, session: zenoh.Session, key: str, *, bulk: bool = False, bus: BusConfig | None = None,
                 recover: int = 0):
        congestion, priority = stream_qos(bulk)
        self.key, self.block = key, not bulk
        # A recoverable one is declared with its first frame: its cache is sized from the frame's size.
        self.publisher = (None if recover > 0 else
                          session.declare_publisher(key, congestion_control=congestion, priority=priority))
        self._recoverable = (session, congestion, priority, recover)
        self.bus = bus or BusConfig()
        # not a recoverable one's: its cache would hold the pool's buffers, and the camera's wait for one
        self.shared_memory = uses_shared_memory(self.bus) and not recover
        self.shm_frames = 0  # frames sent from shared memory
        self.shm_fallbacks = 0  # large frames sent as bytes (no pool, no room, larger than the pool)
        # Reused for every frame: no 1 MB allocation (and page faults) per camera frame.
        self._buffer = bytearray()
        self._numbered = None if self.publisher is None else NumberedPublisher(self.publisher)

    def put_frame(self, frame: Frame) -> None:
        """Encode and publish ``frame`` (raises FrameError if it cannot be encoded)."""
        self.put_bytes(encode(frame, into=self._buffer))

    def put_bytes(self, payload: bytes | bytearray) -> None:
        """Publish already-encoded bytes (e.g. a received frame forwarded as is)."""
        size = len(payload)
        if self.publisher is None:
            session, congestion, priority, recover = self._recoverable
            kept = recover_cache(recover, size)
            self.publisher = declare_recoverable_publisher(session, self.key, congestion, kept, priority)
            log.info("%s keeps its last %d frames for a link gap (%d of %d kB)", self.key, kept, size >> 10,
                     kept * size >> 10)
        if self.shared_memory and size >= SHM_MIN_BYTES:
            buffer = SHARED_MEMORY.allocate(size, self.bus, self.block)
            if buffer is not None:
                buffer[0:size] = payload  # ZShmMut takes bytes or bytearray only (no buffer protocol in 1.10)
                self._numbered.put(zenoh.ZBytes(buffer))
                self.shm_frames += 1
                return
            self.shm_fallbacks += 1
        if self._recoverable[3] > 0:
            # its publication time, kept in the cache: a restored subscriber asks for the recent ones (CacheHistory)
            self.publisher.put(payload, timestamp=self._recoverable[0].new_timestamp())
        else:
            self._numbered.put(payload)

    def undeclare(self) -> None:
        if self.publisher is not None:
            self.publisher.undeclare()


# A recoverable stream (docs/deploy.md, "When the link drops"): the publisher numbers its samples and keeps its last
# ones; a subscriber that finds numbers missing (the first sample after a gap) asks the publisher's cache for them and
# delivers everything in publication order; it also asks this often for anything after the last it got (the last
# samples before a publisher fell silent). Not zenoh's heartbeat instead: a subscriber whose first news of a
# publisher is a heartbeat fetches its whole cache, so a consumer started late would get motion from before it.
RECOVERY_QUERY_S = 1.0
# The RAM one stream's cache may take, and a subscriber's backlog of what it recovered: a stream of big frames keeps
# fewer (64 heatmaps of 1 MB, not 300), so a cut longer than that loses its oldest frames, counted as missed.
RECOVER_BUDGET_BYTES = 64 << 20


def recover_cache(frames: int, frame_bytes: int) -> int:
    """The frames a recoverable publisher keeps: ``frames`` at most, within RECOVER_BUDGET_BYTES of frames of
    ``frame_bytes`` (its first one's size: a stream's frames are about the same size), at least one."""
    return max(1, min(int(frames), RECOVER_BUDGET_BYTES // max(1, int(frame_bytes))))


def declare_recoverable_publisher(session: zenoh.Session, key: str, congestion: zenoh.CongestionControl,
                                  samples: int, priority: zenoh.Priority = zenoh.Priority.DATA):
    """A publisher keeping its last ``samples`` samples for :func:`declare_recoverable_subscriber` to ask for."""
    # publisher_detection: a liveliness token under the key, by which a restored subscriber finds its cache
    return zenoh.ext.declare_advanced_publisher(
        session, key, congestion_control=congestion, priority=priority, cache=zenoh.ext.CacheConfig(int(samples)),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None),
        publisher_detection=True)


def declare_recoverable_subscriber(session: zenoh.Session, key: str, callback, on_missed,
                                   history: "CacheHistory | None" = None) -> tuple:
    """(subscriber, its miss listener): a subscriber that gets back, in order, what a recoverable publisher sent
    while it could not be reached; ``on_missed(n)`` for samples gone for good (no longer in the publisher's cache).
    Nothing from before it first heard a publisher, unless ``history`` (made with ``callback``) asks the caches.
    A plain publisher's samples arrive as a plain subscriber's do. Undeclare both."""
    recovery = zenoh.ext.RecoveryConfig(periodic_queries=datetime.timedelta(seconds=RECOVERY_QUERY_S), heartbeat=None)
    deliver = callback if history is None else history.on_sample
    subscriber = zenoh.ext.declare_advanced_subscriber(session, key, deliver, recovery=recovery)
    return subscriber, subscriber.sample_miss_listener(lambda miss: on_missed(int(miss.nb)))


def declare_cached_subscriber(session: zenoh.Session, key: str, callback):
    """A subscriber that also gets what publishers with a cache (zenoh-ext advanced publishers: rmw_zenoh's
    transient-local ones) kept from before it, or its link, was there: asked at the start and from each publisher
    heard later. Not for a recoverable stream across a cut (a live sample that comes first makes zenoh-ext drop the
    cache's answer: :class:`CacheHistory`); for a topic sent once and kept, e.g. ROS 2's /tf_static."""
    return zenoh.ext.declare_advanced_subscriber(session, key, callback,
                                                 history=zenoh.ext.HistoryConfig(detect_late_publishers=True))


# How long a publisher's cache may take to answer; the live samples wait meanwhile.
HISTORY_WAIT_S = 5.0
# A restored subscriber asks a cache for what was published from this long before the newest capture stamp its
# state holds of the stream: a frame is published after its capture, on a clock that may lag the capturing machine's
# (zenoh's clocks tolerate 500 ms between machines: uhlc's default). The frames of that margin the state holds cost
# their bytes on the link and are dropped (the runtime's ``already_held``); a lag beyond it costs a second question.
HISTORY_MARGIN_S = 0.5


class CacheHistory:
    """What the recoverable publishers of ``key`` still keep that a subscriber restored from a state misses, passed
    to ``callback`` ahead of the live samples (services/runtime.py drops what the state holds). Every sample waits
    here until :meth:`start`; then each publisher's cache, present or heard later (its liveliness token, or a live
    sample of it that came first: a link that returns), is asked once (again when next heard if it answered nothing),
    the samples arriving meanwhile waiting behind its answer. Not zenoh-ext's history
    (``HistoryConfig(detect_late_publishers=True)``): it drops a late publisher's cache when a live sample of it comes
    first, and across a link cut in zenoh 1.10.2 the live samples came 6 ms after the token, the answer a round trip
    later (docs/results/2026-12-07-restart-during-cut.md)."""

    def __init__(self, session: zenoh.Session, key: str, callback):
        self.session, self.key, self.callback = session, key, callback
        self._lock = threading.Lock()
        self._waiting: list = []  # samples behind the caches being asked, in order
        self._started = False
        self._asking = 0  # caches asked that have not answered
        self._draining = False
        self._asking_all = False  # every publisher is asked (start)
        self._asked: set[tuple[str, str]] = set()  # publishers (zid, eid) asked (again if none answered)
        self._last_sn: dict[tuple[str, str], int] = {}  # publisher -> the last number passed on: an answer overlaps
        # the live samples
        self._held: dict[tuple[str, str], int] = {}  # (robot, stream) -> the newest stamp the state holds of it
        self.detector = None  # the liveliness subscriber: undeclare it

    def on_sample(self, sample) -> None:
        with self._lock:
            selector = self._new_publisher(sample) if self._started else ""
            # behind anything waiting too: an answer put in whose thread has not yet passed it on (_ask, start). Gone
            # first, the live sample would have the whole answer dropped as passed already (_pass: numbers below its)
            wait = bool(selector) or not self._started or self._asking or self._draining or bool(self._waiting)
            if wait:
                self._waiting.append(sample)
        if selector:
            self._ask_later(selector)
        elif not wait:
            self._pass(sample)

    def _new_publisher(self, sample) -> str:
        """(holding the lock) The selector of the cache of ``sample``'s publisher if it is to be asked and was not:
        counted as being asked. Its live sample may come before its token (the two take different paths)."""
        publisher = publisher_of(sample) if self._asking_all else None
        if publisher is None or publisher in self._asked:
            return ""
        self._asked.add(publisher)
        self._asking += 1
        return f"{sample.key_expr}/@adv/pub/{publisher[0]}/{publisher[1]}/**"

    def _ask_later(self, selector: str) -> None:
        threading.Thread(target=self._ask, args=(selector,), name="semloc-history", daemon=True).start()

    def start(self, ask: bool, held: dict[tuple[str, str], int] | None = None) -> None:
        """From now on ask (``ask``) every recoverable publisher's cache, or none; the samples held go on. ``held``:
        (robot, stream) -> the newest stamp the state holds of it; a publisher of one (its key the stream, as every
        semloc output's) is asked for what it published from HISTORY_MARGIN_S before that stamp, then for the two
        before its answer's first until the answer reaches a frame held (none missed between: a stream's frames are
        published in order), then for all before; any other for all it keeps."""
        self._held = dict(held or {})
        if ask:
            self._asking_all = True
            tokens = f"{self.key}/@adv/pub/**"
            self.detector = self.session.liveliness().declare_subscriber(tokens, self._on_publisher)
            for reply in self.session.liveliness().get(tokens, timeout=HISTORY_WAIT_S):
                if reply.ok is not None:
                    self._on_publisher(reply.ok)
        with self._lock:
            self._started = True
            asks = [selector for selector in map(self._new_publisher, self._waiting) if selector]
        for selector in asks:
            self._ask_later(selector)
        self._drain()

    def _on_publisher(self, token) -> None:
        name = str(token.key_expr)
        publisher = _cache_publisher(name)
        with self._lock:
            if token.kind != zenoh.SampleKind.PUT or publisher is None or publisher in self._asked:
                return
            self._asked.add(publisher)
            self._asking += 1
        self._ask_later(name)

    def _ask(self, name: str) -> None:
        started = time.monotonic()
        stream = name.split("/@adv/", 1)[0]
        newest = next((stamp for (_, held), stamp in self._held.items() if held == stream), None)
        if newest is None:
            answer = self._get(name)
        else:
            since = max(0, newest - int(HISTORY_MARGIN_S * 1e9))
            answer = self._get(f"{name}?_time=[{_utc(since)}..]")
            for limit in (";_max=2", ""):  # the two before its first, then all before
                if self._reaches_held(answer):
                    break
                first = answer[0].timestamp.get_time() + datetime.timedelta(microseconds=1) if answer else None
                answer = _merge(self._get(f"{name}?_time=[..{_utc(first)}]{limit}"), answer)
        with self._lock:
            waited = len(self._waiting)
            self._waiting[:0] = answer  # ahead of the live samples that arrived meanwhile
            self._asking -= 1
            if not answer:
                # No sample: the cache may not have been reached (asked during a link cut whose loss zenoh had not
                # noticed yet, its token still seen), or it holds nothing yet. Asked again when next heard (its
                # token back, its next live sample), or the frames it kept for us were never asked for again.
                self._asked.discard(_cache_publisher(name))
        # what the answer cost: on a thin link its bytes delay everything behind them
        log.info("history of %s: %d samples, %d kB in %.1f s; %d live samples waited", name, len(answer),
                 sum(len(sample.payload) for sample in answer) >> 10, time.monotonic() - started, waited)
        self._drain()

    def _get(self, selector: str) -> list:
        """The samples a cache answers ``selector`` with, in publication order."""
        answer = []
        try:
            # the cache answers under the stream's key, not the token's it was asked on
            for reply in self.session.get(selector, timeout=HISTORY_WAIT_S, accept_replies=zenoh.ReplyKeyExpr.ANY,
                                          consolidation=zenoh.ConsolidationMode.NONE, target=zenoh.QueryTarget.ALL):
                if reply.ok is not None:
                    answer.append(reply.ok)
                elif reply.err.payload.to_string() == "Timeout":
                    # what had not come by then is lost, uncounted: the newest a restored worker missed
                    log.warning("history %s: the answer was cut after %g s (%d samples came)", selector,
                                HISTORY_WAIT_S, len(answer))
        except zenoh.ZError as error:  # the session closing
            log.debug("history %s not asked: %s", selector, error)
        return sorted(answer, key=_sn)

    def _reaches_held(self, answer: list) -> bool:
        """Whether ``answer`` (in order) needs nothing from before it: its first frame is one the state holds, or its
        publisher does not stamp its samples (an older semloc: its cache ignored the time asked for, and answered
        all)."""
        if answer and answer[0].timestamp is None:
            return True
        header = peek_header(payload_bytes(answer[0].payload)) if answer else None
        return header is not None and header[2] <= self._held.get(header[:2], -1)

    def _drain(self) -> None:
        with self._lock:
            if self._draining:
                return
            self._draining = True
        while True:
            with self._lock:
                if not self._started or self._asking or not self._waiting:
                    self._draining = False
                    return
                batch, self._waiting = self._waiting, []
            for sample in batch:
                self._pass(sample)

    def _pass(self, sample) -> None:
        publisher = publisher_of(sample)
        if publisher is not None and sample.source_info.source_sn is not None:
            last = self._last_sn.get(publisher)
            if last is not None and sample.source_info.source_sn <= last:
                return  # in a cache's answer and live both
            self._last_sn[publisher] = sample.source_info.source_sn
        self.callback(sample)

    def undeclare(self) -> None:
        if self.detector is not None:
            self.detector.undeclare()


def publisher_of(sample) -> tuple[str, str] | None:
    """(zid, eid) of the publisher of a sample carrying its source (zenoh's EntityGlobalId objects of two samples of
    one publisher are neither equal nor hash alike)."""
    info = sample.source_info
    if info is None or info.source_id is None:
        return None
    return str(info.source_id.zid), str(info.source_id.eid)


def _cache_publisher(name: str) -> tuple[str, str] | None:
    """(zid, eid) of the publisher a cache's key names (``<key>/@adv/pub/<zid>/<eid>/...``), None if it names none."""
    parts = name.split("/@adv/pub/", 1)[-1].split("/")
    return (parts[0], parts[1]) if len(parts) >= 2 else None


def _sn(sample) -> int:
    return sample.source_info.source_sn if sample.source_info and sample.source_info.source_sn is not None else 0


def _merge(before: list, answer: list) -> list:
    """``before`` then ``answer``, a sample in both once (an inclusive time bound asks for one again)."""
    first = _sn(answer[0]) if answer else None
    return [sample for sample in before if first is None or _sn(sample) < first] + answer


def _utc(when: "int | datetime.datetime | None") -> str:
    """A time bound of a zenoh selector's ``_time`` (RFC 3339, UTC) from nanoseconds or a datetime; "" for None."""
    if when is None:
        return ""
    if isinstance(when, datetime.datetime):
        return when.astimezone(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(when // 10**9)) + f".{when % 10**9:09d}Z"


def payload_bytes(payload: zenoh.ZBytes) -> bytes:
    """A received payload as bytes (one copy). A shared-memory payload is copied straight out of its buffer:
    ``to_bytes()`` zero-fills its result before copying, a third dearer for 1 MB (measured here)."""
    shared = payload.as_shm()
    return bytes(shared) if shared is not None else payload.to_bytes()


def publish(session: zenoh.Session, key: str, frame: Frame, *, bulk: bool = False) -> None:
    """Encode and put one frame, with the quality of service of its kind of stream (:func:`stream_qos`)."""
    congestion, priority = stream_qos(bulk)
    session.put(key, encode(frame), congestion_control=congestion, priority=priority)


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
    "NumberedPublisher",
    "QueryError",
    "SHARED_MEMORY",
    "SharedMemoryPool",
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
