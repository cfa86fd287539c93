"""Runtime frames: ``Status`` (a worker's periodic counters and health), ``LauncherStatus`` (a launcher's view of
its nodes), ``Ack`` (a generic reply to a command query) and ``LogRequest`` / ``LogTail`` (the nodes' logs, asked
of their launcher by ``semloc logs``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from schemas.base import Frame, KeyName, Sub

Count = Annotated[int, Field(ge=0)]
# running: healthy; degraded: alive but failing (see Status.state_reason); stalled: its main loop made no progress
# (reported by the worker itself, or decided by the launcher when its Status stops arriving).
WorkerState = Literal["starting", "running", "degraded", "stalled", "stopping", "stopped"]
# A node as its launcher sees it: a worker state from its last Status, or down (no process: exited, waiting to be
# restarted, or finished).
NodeState = Literal["starting", "running", "degraded", "stalled", "stopping", "stopped", "down"]
OneLine = Annotated[str, Field(max_length=1024, pattern=r"^[^\n]*$")]


class InputStats(Sub):
    key: str
    policy: Literal["latest", "lossless"]
    received: Count = 0
    processed: Count = 0
    dropped: Count = Field(0, description="discarded by a full latest queue (its oldest frame)")
    overflow: Count = Field(0, description="refused by a full lossless queue (the arriving frame)")
    rejected: Count = 0
    rejected_reasons: dict[str, Count] = Field(default_factory=dict, description="rejected, per FrameError.reason")
    errors: Count = 0
    queued: Count = 0
    rate_hz: Annotated[float, Field(ge=0)] | None = Field(
        None, description="sustained rate: frames handled per second while they flowed, over the last 10 s (None: "
                          "fewer than two)")
    handler_ms: Annotated[float, Field(ge=0)] | None = Field(
        None, description="mean handler time over the same frames; 1000 / handler_ms is the rate the input could "
                          "sustain alone")
    recovered: Count = Field(0, description="a recoverable input's frames that arrived late: sent while the link was "
                                            "down, asked for when it returned")
    missed: Count = Field(0, description="a recoverable input's frames gone for good (beyond the publisher's cache)")
    already_held: Count = Field(0, description="frames a restored worker's publishers still kept that its state "
                                               "already held (not handled again)")
    lost_in_transit: Count = Field(0, description="frames their publisher numbered that never arrived (gaps in "
                                                  "Header.seq): dropped on the way, e.g. by a thin link")


class OutputStats(Sub):
    key: str
    published: Count = 0


class PersistenceStats(Sub):
    """A stateful worker's crash-safe state (docs/runtime.md): ``restored`` from a snapshot at start, journal
    records ``replayed`` after it, snapshots written since, records journaled since the last one, and ``note``: one
    line on what happened to the state at start (e.g. an unreadable snapshot set aside)."""

    restored: bool = False
    replayed: Count = 0
    snapshots: Count = 0
    journal_records: Count = 0
    set_aside: list[Annotated[str, Field(max_length=4096)]] = Field(default_factory=list, max_length=16)
    note: OneLine = ""


class MemoryStats(Sub):
    """A worker's memory (services/memory.py): resident now and at its peak, and the limit it is nearest to reach
    (a cgroup's, an rlimit, the machine's RAM; found at its start) with what counts towards it now (a cgroup's usage
    less its inactive file cache, the address space or data segment, the machine's RAM in use)."""

    rss_bytes: Count | None = None
    peak_bytes: Count | None = None
    limit_bytes: Count | None = None
    limit_source: OneLine = ""
    used_bytes: Count | None = None
    near_limit: bool = Field(False, description="used_bytes reached the worker's memory_high_fraction of limit_bytes "
                                                "(it is degraded, and a SIGKILL now is taken for an OOM kill)")


class Status(Frame, schema="semloc.Status", version=1, max_bytes=1 << 20):
    """Counters and health of one worker since it started. ``received`` = payloads that arrived; ``rejected`` =
    payloads that failed decoding or validation (``schemas.FrameError``); ``dropped`` = frames discarded by a full
    ``latest`` queue; ``overflow`` = frames refused by a full ``lossless`` queue; ``errors`` = exceptions raised by
    the worker's handlers; ``processed`` = handler calls that returned. Latency = time from arrival to the end of
    the handler, over the last 1,000 frames. ``state_reason`` says why the state is degraded or stalled;
    ``restarts`` / ``restart_reason`` come from the launcher (0 / "" when started by hand)."""

    worker: str
    kind: str
    state: WorkerState
    state_reason: OneLine = ""
    pid: Count
    host: str = ""
    started_ns: Count
    uptime_s: Annotated[float, Field(ge=0)]
    received: Count = 0
    processed: Count = 0
    dropped: Count = 0
    overflow: Count = 0
    rejected: Count = 0
    errors: Count = 0
    queries: Count = 0
    latency_p50_ms: float | None = None
    latency_p95_ms: float | None = None
    inputs: dict[str, InputStats] = Field(default_factory=dict)
    outputs: dict[str, OutputStats] = Field(default_factory=dict)
    last_error: OneLine = Field("", description="the last error in one line (full tracebacks are in the log)")
    last_error_ns: Count = Field(0, description="when it happened (wall clock, ns; 0: never)")
    restarts: Count = 0
    restart_reason: OneLine = ""
    details: dict[str, str | float | int | bool | None] = Field(
        default_factory=dict, max_length=64, description="the worker's own figures (e.g. the loop closure's "
                                                         "calibration and the precision it expects)")
    bus_transports: Count = Field(0, description="zenoh transports (peers, routers) open now")
    bus_lost: Count = Field(0, description="times the last transport closed: the worker was cut off the bus")
    bus_regained: Count = Field(0, description="times a transport opened again after such a loss")
    persistence: PersistenceStats | None = Field(None, description="state snapshots and journal (stateful workers)")
    write_failures: Count = Field(0, description="writes of its files that failed (a full or read-only disk); "
                                                 "state_reason names each file failing now")
    busy_fraction: Annotated[float, Field(ge=0, le=1)] | None = Field(
        None, description="share of the last 10 s spent in input handlers (near 1: this stage limits its outputs' "
                          "rate; None: not reported)")
    memory: MemoryStats | None = Field(None, description="its memory and limit (None: not reported)")


class NodeHealth(Sub):
    """One node of a launcher: its process and how the launcher last saw it."""

    worker: str = Field(description="the worker's name on the bus (semloc/<robot>/<worker>/...)")
    robot: str
    kind: str
    state: NodeState
    state_reason: OneLine = ""
    pid: Count | None = None
    restarts: Count = 0
    restart_reason: OneLine = ""
    last_exit: int | None = Field(None, description="exit code of its last process (negative: killed by a signal)")
    heartbeat_age_s: Annotated[float, Field(ge=0)] | None = Field(None, description="seconds since its last Status")
    finished: bool = Field(False, description="will not be started again")
    oom_kills: Count = Field(0, description="its processes killed by the kernel for want of memory (a SIGKILL it did "
                                            "not send, with an OOM kill counted in its memory cgroup or its last "
                                            "Status near its limit)")


class LauncherStatus(Frame, schema="semloc.LauncherStatus", version=1, max_bytes=1 << 20):
    """A launcher's view of its nodes (``semloc up``), published periodically and answered on
    ``keys.launcher_nodes``: the only witness of a node that cannot speak for itself (stopped, hung, dead)."""

    launcher: KeyName
    graph: str
    pid: Count
    host: str = ""
    nodes: dict[str, NodeHealth] = Field(default_factory=dict)
    router_links: Count | None = Field(None, description="other zenoh routers its hub, a router, has a link up to now "
                                       "(None: its hub is no router)")
    router_links_lost: Count = Field(0, description="times its last link up to another router closed or fell silent")
    router_links_regained: Count = Field(0, description="times one was up again after that")
    router_link_down_s: Annotated[float, Field(ge=0)] | None = Field(
        None, description="seconds without a link up to another router: since the last one closed or last answered, "
        "or since the start for a hub that connects to one (None: one is up, or none is awaited)")


class Ack(Frame, schema="semloc.Ack", version=1, max_bytes=64 << 10):
    """A reply to a command query (e.g. relocalize): whether it was accepted, and why not."""

    ok: bool
    message: Annotated[str, Field(max_length=4096)] = ""


class LogRequest(Frame, schema="semloc.LogRequest", version=1, max_bytes=64 << 10):
    """What ``semloc logs`` asks a launcher for: the last ``tail_bytes`` of each node's log (of ``node`` only, if
    given), or, for a node in ``offsets``, what its log holds from that byte on (following it)."""

    node: Annotated[str, Field(max_length=128)] = Field("", description="one node's log only ('': every node's)")
    offsets: dict[Annotated[str, Field(max_length=128)], Count] = Field(
        default_factory=dict, max_length=1024, description="node -> byte offset to read from (instead of the tail)")
    tail_bytes: Annotated[int, Field(ge=0, le=1 << 20)] = 8192


class LogChunk(Sub):
    """A piece of one node's log file: bytes [start, end) as text (invalid UTF-8 replaced)."""

    start: Count
    end: Count
    text: Annotated[str, Field(max_length=4 << 20)] = ""


class LogTail(Frame, schema="semloc.LogTail", version=1, max_bytes=8 << 20):
    """A launcher's answer to a LogRequest: its graph, and the asked piece of each node's log (a node without a
    log file - run with ``--console`` - is absent)."""

    launcher: KeyName
    graph: str
    logs: dict[str, LogChunk] = Field(default_factory=dict)
