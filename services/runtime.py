"""The worker runtime shared by every semloc service. User guide: docs/runtime.md.

A worker is a subclass of :class:`Worker` in ``services/workers/<kind>.py`` exposing ``WORKER = TheClass``::

    class EchoConfig(WorkerConfig):
        source: str = "semloc/robot/camera/front/image"

    class Echo(Worker):
        Config = EchoConfig

        def setup(self):
            self.out = self.output("copy", "semloc/robot/echo/image", Image)
            self.input("image", self.config.source, Image, self.on_image, policy="latest", depth=2)

        def on_image(self, frame: Image):
            self.out.publish(frame)

Threading model: zenoh delivers samples on its own threads; the runtime decodes them there (counting rejects),
queues them per input (bounded; a full queue never holds zenoh's thread), and calls every handler, query handler
and timer on the worker's **main thread**, one at a time, so worker code needs no locks. A handler that raises is
counted (``errors``, or ``rejected`` for :class:`schemas.FrameError`) and the worker goes on. The worker's
``Status`` says whether it is running, degraded or stalled, and why (docs/runtime.md, "Status, liveliness,
health").
"""

from __future__ import annotations

import collections
import ctypes
import dataclasses
import functools
import json
import logging
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import zenoh
from pydantic import BaseModel, ConfigDict, Field

from schemas import (Frame, FrameError, Header, InputStats, MemoryStats, OutputStats, PersistenceStats, Status, decode,
                     encode, keys, peek_header)
from schemas.base import check_name
from semloc_core.io.atomic import remove_partial_writes, replace_text
from semloc_core.io.errors import FileFormatError
from services import memory
from services.bus import (RECOVER_BUDGET_BYTES, SHARED_MEMORY, BusConfig, CacheHistory, FramePublisher, QueryError,
                          declare_cached_subscriber, declare_recoverable_subscriber, open_session, payload_bytes,
                          publisher_of, query, uses_shared_memory)
from services.config import CONFIG_ERROR_EXIT, ConfigError
from services.journal import Journal
from services.state import State, StateError, load_state, refused_write, save_state, set_aside
from services.viz import RerunConfig, open_recording

Policy = Literal["latest", "lossless"]
DEFAULT_DEPTH = {"latest": 2, "lossless": 256}
LATENCY_WINDOW = 1000
QUERY_QUEUE = 64
# latest_input: a value not answered at start is asked for again after this long, then at doubling intervals up to
# the longest, until one arrives.
LATEST_ASK_FIRST_S, LATEST_ASK_MAX_S = 0.05, 2.0
WRITE_RETRY_FIRST_S = 1.0  # a failed state snapshot is tried again after this, then twice as long each time
LOG_WRITES = "log"  # write_failed's name for the worker's log
# A lossless frame may be handled on zenoh's delivery thread (see Input._on_sample) only while its handler has been
# this quick: meanwhile every other delivery to this process waits.
FAST_PATH_MAX_S = 0.001
HANDLER_TIME_WEIGHT = 0.2  # of the newest call in the running average of an input's handler time
RATE_WINDOW_S = 10.0  # Status's sustained rates, handler times and busy fraction: over the last this many seconds
# An input that lost more than this share of a stream's frames on the way (gaps in their numbering) over the window,
# and at least TRANSIT_LOSS_MIN of them, is degraded: a thin link drops images by design, a few now and then are not
# worth an alarm. Numbering gaps larger than MAX_TRANSIT_GAP, or more streams than MAX_STREAMS_PER_INPUT, are not
# believed (a sender's header is untrusted): the stream starts over.
TRANSIT_LOSS_DEGRADED = 0.1
TRANSIT_LOSS_MIN = 3
MAX_TRANSIT_GAP = 100_000
MAX_STREAMS_PER_INPUT = 1024
# A snapshot's meta entry (the runtime's, beside the worker's): per input, the newest stamp of each stream it holds
STATE_HOLDS = "__state_holds__"
LAST_ERROR_CHARS = 300
# Set by the launcher for a restarted node: how many times it was restarted, and why the last time.
RESTARTS_ENV, RESTART_REASON_ENV = "SEMLOC_RESTARTS", "SEMLOC_RESTART_REASON"
# Set by the launcher: the workers (robot/name, comma-separated) the new process's session meets before its setup
# (Worker._meet_started_after): those its first start was held for (start_after), those running at a restart.
START_AFTER_ENV = "SEMLOC_START_AFTER"
MEET_TIMEOUT_S = 10.0  # then it goes on without those not met, with a warning (one stopped meanwhile is never met)


def retain_freed_memory(trim_threshold: int = 128 << 20, mmap_threshold: int = 32 << 20) -> bool:
    """glibc only: keep freed heap memory for reuse instead of handing it back to the kernel at once.

    Every received frame is copied into a fresh bytes object (zenoh offers no way to copy into a reused buffer) and
    freed when its handler is done. With glibc's dynamic thresholds a few frames in flight trim the heap again and
    again, and each copy page-faults its megabyte back in: the receive copy took twice as long (measured with
    benchmarks/bus.py). Up to ``trim_threshold`` bytes of free memory stay in each malloc arena; allocations below
    ``mmap_threshold`` come from the heap (larger ones are still mapped and unmapped on their own). Skipped when MALLOC_TRIM_THRESHOLD_ / MALLOC_MMAP_THRESHOLD_ are set.
    Returns whether the thresholds were set."""
    if os.environ.get("MALLOC_TRIM_THRESHOLD_") or os.environ.get("MALLOC_MMAP_THRESHOLD_"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's <malloc.h>
    trimmed = mallopt(M_TRIM_THRESHOLD, int(trim_threshold))
    return bool(trimmed) and bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)))


def check_robot(frame: Frame, robot: str | None) -> None:
    """FrameError ``robot`` unless ``frame``'s header names ``robot`` (None: any robot), the robot its key names: a
    frame of another robot there is a misconfiguration or an attack, and taking it would mix two robots' data."""
    if robot is not None and frame.header.robot != robot:
        raise FrameError(f"a frame of robot {frame.header.robot!r} on robot {robot!r}'s key", reason="robot")


class UnusableState(RuntimeError):
    """The state snapshot cannot be used and ``on_corrupt_state`` is ``stop``."""


class StateNotWritable(RuntimeError):
    """Restoring the state snapshot needs a write its disk refuses: the snapshot is kept, the worker exits (code 1)
    and its launcher starts it again."""


class InputOverride(BaseModel):
    """Graph-file / config override of a declared input (rewire a key, change its queue)."""

    model_config = ConfigDict(extra="forbid")
    key: str | None = None
    policy: Policy | None = None
    depth: int | None = Field(None, ge=1, le=100_000)
    recover: bool | None = Field(None, description="ask a recoverable publisher for what it sent while out of reach")


class OutputOverride(BaseModel):
    model_config = ConfigDict(extra="forbid")
    key: str | None = None
    recover: int | None = Field(None, ge=0, le=100_000, description="frames kept at most for subscribers that missed "
                                "them (a link gap; 0: none; default: the stream's, keys.RECOVERABLE_STREAMS)")
    bulk: bool | None = Field(None, description="dropped under network congestion and sent after the other streams "
                              "(true: images, heatmaps), or waited for (false)")


class WorkerConfig(BaseModel):
    """Fields every worker has; a worker's own ``Config`` subclasses this and adds its fields."""

    model_config = ConfigDict(extra="forbid")

    robot: str = Field(keys.DEFAULT_ROBOT, description="robot namespace of every key")
    name: str | None = Field(None, description="instance name (default: the worker kind)")
    bus: BusConfig = Field(default_factory=BusConfig)
    rerun: RerunConfig = Field(default_factory=RerunConfig)
    status_period_s: float = Field(1.0, gt=0, description="Status publication period")
    state_dir: str | None = Field(None, description="where state snapshots live (None: no snapshots)")
    snapshot_period_s: float | None = Field(30.0, gt=0, description="periodic state snapshot (also on stop)")
    journal_commit_s: float = Field(0.5, gt=0, le=60, description="journal records are made durable (fsync) this "
                                    "often")
    journal_replay_s: float = Field(0.5, gt=0, description="snapshot as soon as the journal's records took this "
                                    "long to apply (bounds the replay at a restart)")
    on_corrupt_state: Literal["empty", "stop"] = Field(
        "empty", description="a snapshot that cannot be used is set aside (renamed *.corrupt-<time>); then 'empty': "
                             "start with an empty state and report it; 'stop': exit 2")
    run_dir: str | None = Field(None, description="where the config snapshot of this run is written")
    inputs: dict[str, InputOverride] = Field(default_factory=dict)
    outputs: dict[str, OutputOverride] = Field(default_factory=dict)
    log_level: str = "INFO"
    degraded_after_failures: int = Field(5, ge=1, description="degraded when this many handler or timer calls in a "
                                                               "row raised")
    degraded_silence_s: float | None = Field(30.0, gt=0, description="degraded when inputs keep arriving and "
                                                                     "nothing is published for this long (None: never)")
    stalled_after_s: float = Field(60.0, gt=0, description="stalled when the main loop made no progress for this "
                                                           "long (a handler, timer or query that does not return)")
    memory_high_fraction: float | None = Field(
        0.9, gt=0, le=1, description="degraded when what counts towards a memory limit (a cgroup's, an rlimit, the "
        "machine's RAM) reaches this fraction of it; the arrays its settings size up front must fit below it at the "
        "start (else exit 2). None: never degraded, the arrays checked against the whole limit")

    def memory_needs(self) -> dict[str, int]:
        """The arrays these settings make the worker allocate up front: what (naming the settings) -> bytes. Checked
        against its memory limits before ``setup`` (services.memory.check_room); none by default."""
        return {}


def one_line(message: str, limit: int = LAST_ERROR_CHARS) -> str:
    """``message`` on one line (whitespace runs collapsed), cut to ``limit`` characters."""
    line = " ".join(str(message).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def restart_info(environ=None) -> tuple[int, str]:
    """(restarts, reason) the launcher passed to this process (0, "" when started otherwise)."""
    environ = os.environ if environ is None else environ
    try:
        restarts = max(0, int(environ.get(RESTARTS_ENV, "0")))
    except ValueError:
        restarts = 0
    return restarts, one_line(environ.get(RESTART_REASON_ENV, ""))


@dataclasses.dataclass
class _Persistence:
    """The worker's side of ``PersistenceStats`` (status frames are immutable)."""

    restored: bool = False
    replayed: int = 0
    snapshots: int = 0
    journal_records: int = 0
    set_aside: list[str] = dataclasses.field(default_factory=list)
    note: str = ""


class _Percentiles:
    def __init__(self, size: int = LATENCY_WINDOW):
        self._values: collections.deque[float] = collections.deque(maxlen=size)

    def add(self, value: float) -> None:
        self._values.append(value)

    def p50_p95(self) -> tuple[float | None, float | None]:
        values = list(self._values)
        if not values:
            return None, None
        p50, p95 = np.percentile(values, [50, 95])
        return float(p50), float(p95)


class Input:
    """A subscription with a bounded queue. Counters are updated by the runtime; read them freely.

    zenoh's delivery thread is never held by a full queue: a ``latest`` input drops its oldest frame (``dropped``),
    a ``lossless`` one refuses the arriving frame (``overflow``). Either way the publisher and every other
    subscriber, in this process or another, go on at their own pace."""

    def __init__(self, worker: "Worker", name: str, key: str, frame_type, handler, policy: Policy, depth: int,
                 raw: bool = False, decoder: Callable[..., Any] | None = None,
                 check: Callable[[Frame], None] | None = None, any_robot: bool = False, attachment: bool = False):
        if policy not in DEFAULT_DEPTH:
            raise ValueError(f"input {name!r}: policy must be 'latest' or 'lossless', got {policy!r}")
        if depth < 1:
            raise ValueError(f"input {name!r}: depth must be >= 1")
        self.worker, self.name, self.key, self.frame_type = worker, name, key, frame_type
        self.handler, self.policy, self.depth, self.raw, self.check = handler, policy, depth, raw, check
        self.decoder, self.attachment = decoder, attachment
        # the robot every frame's header must name: the key's (a foreign decoder's payloads carry no semloc header)
        self.robot = None if any_robot or decoder is not None else keys.robot_of(key)
        self.deliver = (lambda pair: handler(*pair)) if raw else handler
        self.what = f"input {name}"
        self.received = self.processed = self.dropped = self.overflow = self.rejected = self.errors = 0
        self.rejected_reasons: collections.Counter[str] = collections.Counter()
        self.queue: collections.deque = collections.deque()
        # Frames the main thread took off the queue and has not yet handed to the handler (a lossless batch): they
        # still count against the depth, so memory stays at most `depth` frames waiting plus the one in the handler.
        self.held = 0
        self.handler_s: float | None = None  # running average of the handler's time (None: never called yet)
        self.recent: collections.deque = collections.deque(maxlen=4096)  # (end, seconds) of handled frames
        self.lost_at: collections.deque = collections.deque(maxlen=4096)  # when frames were dropped or refused
        # False for inputs that ask for no output (slowly changing state, poses, odometry): exempt from the silence
        # check, and left out of the worker's latency percentiles
        self.drives_output = True
        self.subscriber = None
        # a recoverable input: a plain subscription beside it counts what arrived live (the rest was recovered)
        self.recover_handles: tuple = ()
        self.live = self.missed = 0
        # publisher (zid, eid) -> the highest sequence number the counting subscription got
        self.live_sn: dict[tuple[str, str], int] = {}
        self.delivered = self.classed_recovered = 0  # frames the recoverable subscription delivered, taken as recovered
        # recovered frames queued or in the handler: beyond depth and the policy, never dropped for a live one; and
        # a lossless input's live frames that arrived behind them (``behind``): they wait for the gap the link
        # returned, not for a worker too slow for the stream, so they take no room of the depth either (after a
        # 10 s cut at 10 Hz a 20 ms handler takes 2 s over the gap's 100 frames: 20 live ones come meanwhile).
        # Both within RECOVER_BUDGET_BYTES (their bytes: ``backlog_bytes``); live frames that come once the
        # recovered ones are handled count against ``depth`` again.
        self.backlog = self.behind = self.backlog_bytes = 0
        # (robot, stream) -> the newest stamp journaled of it: what a snapshot holds (Worker.journal_write)
        self.journaled: dict[tuple[str, str], int] = {}
        # after a restore: what its state held, dropped before the handler (a cache's history), until a newer frame
        self.state_holds: dict[tuple[str, str], int] = {}
        self.already_held = 0
        self.history: CacheHistory | None = None  # a restored worker's recoverable input: the caches' history
        # Gaps in each stream's numbering (Header.seq): frames its publisher sent that never came (a thin or
        # congested link between machines drops them: services.bus.stream_qos). Per (robot, stream) and publisher
        # (two publishers of one stream number their frames apart: interleaved, they are no loss), bounded.
        self.lost_in_transit = 0
        # (when, stream, frames lost just before it, its publisher) of each frame that arrived, for the health's window
        self.arrivals: collections.deque = collections.deque(maxlen=8192)
        self._last_seq: dict[tuple[str, str], int] = {}
        # frames refused or rejected since the last one accepted: they arrived, the gap they leave is not a loss (per
        # input: of an input of several streams, a loss right after one may go uncounted)
        self._refused_unseen = 0

    def _count_gap(self, header, publisher: tuple[str, str] | None) -> None:
        """Note ``header``'s place in its stream from ``publisher`` (the sample's (zid, eid); None: it names none,
        numbered with the stream's other such frames); a jump past the next number counts the frames between as lost
        on the way. A number at or before the last one (a publisher started again, a replay), or one implausibly far
        ahead (untrusted), starts the stream over."""
        stream = (header.robot, header.stream) + (publisher or ())
        with self.worker._wake:
            last = self._last_seq.get(stream)
            if last is None and len(self._last_seq) >= MAX_STREAMS_PER_INPUT:
                self._last_seq.clear()
            self._last_seq[stream] = header.seq
            lost = header.seq - last - 1 if last is not None and last + 1 < header.seq <= last + 1 + MAX_TRANSIT_GAP \
                else 0
            lost, self._refused_unseen = max(0, lost - self._refused_unseen), 0
            self.lost_in_transit += lost
            self.arrivals.append((time.monotonic(), header.stream, lost, publisher))

    def losing_in_transit(self, now: float) -> list[str]:
        """Its streams that lost more than TRANSIT_LOSS_DEGRADED of their frames on the way (and at least
        TRANSIT_LOSS_MIN) over the last RATE_WINDOW_S, each with its counts."""
        counts: dict[str, list[int]] = {}
        for at, stream, lost, _ in list(self.arrivals):
            if at >= now - RATE_WINDOW_S:
                count = counts.setdefault(stream, [0, 0])
                count[0], count[1] = count[0] + lost, count[1] + 1 + lost
        return [f"{stream} {lost} of {sent}" for stream, (lost, sent) in counts.items()
                if lost >= TRANSIT_LOSS_MIN and lost > TRANSIT_LOSS_DEGRADED * sent]

    def shared_streams(self, now: float) -> list[str]:
        """Its streams whose frames came from publishers taking turns over the last RATE_WINDOW_S (frames naming none
        count as one publisher), each with how many: two at once. One turn is not (a publisher restarted: the new one
        follows the old)."""
        heard: dict[str, set] = {}
        turns: collections.Counter[str] = collections.Counter()
        last: dict[str, tuple[str, str] | None] = {}
        for at, stream, _, publisher in list(self.arrivals):
            if at >= now - RATE_WINDOW_S:
                heard.setdefault(stream, set()).add(publisher)
                turns[stream] += last.get(stream, publisher) != publisher
                last[stream] = publisher
        return [f"{len(publishers)} publishers on {stream}" for stream, publishers in heard.items()
                if turns[stream] >= 2]

    def _on_live(self, sample) -> None:
        publisher = publisher_of(sample)
        with self.worker._wake:
            self.live += 1
            if publisher is not None and sample.source_info.source_sn is not None:
                self.live_sn[publisher] = max(sample.source_info.source_sn, self.live_sn.get(publisher, -1))

    def _recovered_size(self, sample) -> int:
        """A frame's size if it was recovered, else 0: the live subscription has had a later one of its publisher
        (it was held back while the gap before it was fetched), or the recoverable one has delivered two or more
        frames the live one has not (a periodic query's; a live frame reaches both, in either order)."""
        if not self.recover_handles:
            return 0
        publisher = publisher_of(sample)
        with self.worker._wake:
            self.delivered += 1
            behind = publisher is not None and sample.source_info.source_sn is not None and \
                sample.source_info.source_sn < self.live_sn.get(publisher, -1)
            if not behind and self.delivered - self.live - self.classed_recovered < 2:
                return 0
            self.classed_recovered += 1
        return max(1, len(sample.payload))

    def _room(self, sample, size: int) -> int:
        """What a lossless input's frame takes room of: the budget, ``size`` (its bytes) if recovered, minus its bytes
        if a live one behind recovered ones (``backlog``); the depth, 0, if another live one."""
        return size or (-max(1, len(sample.payload)) if self.backlog else 0)

    def _full(self, room: int) -> bool:
        """No room for a lossless input's frame (``room``: :meth:`_room`): a live one beyond ``depth`` live ones not
        behind a backlog, one of or behind a backlog beyond RECOVER_BUDGET_BYTES of those."""
        if room:
            return self.backlog_bytes + abs(room) > RECOVER_BUDGET_BYTES
        return len(self.queue) + self.held - self.backlog - self.behind >= self.depth

    def done(self, room: int) -> None:
        """A frame taken off the queue goes to the handler (``room``: what it took room of, :meth:`_room`; a latest
        input's recovered frame's bytes)."""
        self.held -= 1
        if room:
            with self.worker._wake:
                if room > 0:
                    self.backlog -= 1
                else:
                    self.behind -= 1
                self.backlog_bytes -= abs(room)

    def note_journaled(self, header) -> None:
        """A frame of ``header`` (robot, stream, stamp_ns) changed the state: the next snapshot holds it."""
        stream = header[:2]
        if header[2] > self.journaled.get(stream, -1):
            if stream not in self.journaled and len(self.journaled) >= MAX_STREAMS_PER_INPUT:
                self.journaled.clear()
            self.journaled[stream] = header[2]

    def held_by_state(self, frame) -> bool:
        """Whether the restored state holds ``frame`` already (counted): at or before the newest stamp of its stream
        it held. The caches' history comes in order, so a newer frame ends the check for its stream."""
        stream = (frame.header.robot, frame.header.stream)
        held = self.state_holds.get(stream)
        if held is None:
            return False
        if frame.header.stamp_ns > held:
            del self.state_holds[stream]
            return False
        with self.worker._wake:
            self.already_held += 1
        return True

    def _on_missed(self, count: int) -> None:
        with self.worker._wake:
            self.missed += count
        self.worker.logger.warning("%s: %d frame(s) missed for good (beyond the publisher's cache)", self.what, count)

    def _on_sample(self, sample) -> None:
        arrived = time.monotonic()
        worker = self.worker
        # what the frame takes room of (a lossless input's: _room; a latest input's: a recovered frame's bytes)
        room = size = self._recovered_size(sample)
        if self.policy == "lossless":
            if (self.handler_s is not None and self.handler_s <= FAST_PATH_MAX_S and not self.queue and not self.held
                    and worker._owner.acquire(blocking=False)):
                # The main thread is idle, nothing of this input waits and its handler is quick: handle the frame
                # right here. Handing it over to the main thread costs two thread switches and a fight for the GIL
                # per frame (0.6x raw zenoh's throughput of 640x480x3 frames, benchmarks/bus.py). Only for a quick
                # handler: meanwhile zenoh's other deliveries to this process wait. A handler that turns slow runs
                # here once; its average then takes the input off this path until it is quick again.
                try:
                    if not self.queue and not self.held and not worker._stopping.is_set():
                        item = self._decode(sample)
                        if item is not None:
                            with worker._wake:
                                self.received += 1
                            worker._work_arrived(self, arrived)
                            worker._handle(self, arrived, item)
                        return
                finally:
                    worker._owner.release()
            if self._full(self._room(sample, size)):
                self._refuse(size)  # full: refused before the payload is even copied
                return
        # zenoh thread: decode here so bad payloads never take a queue slot and are counted even under load.
        item = self._decode(sample)
        if item is None:
            return
        with worker._wake:
            if self.policy == "lossless":
                room = self._room(sample, size)  # under the lock: the backlog ahead may be handled by now
                if self._full(room):
                    self._refuse(room, locked=True)
                    return
            self.received += 1
            if self.policy == "latest" and not room:
                live = [i for i, queued in enumerate(self.queue) if not queued[2]] if self.backlog else self.queue
                for index in reversed(range(max(0, len(live) - self.depth + 1))):  # the oldest live ones
                    del self.queue[live[index] if self.backlog else index]
                    self.dropped += 1
                    self.lost_at.append(arrived)
            elif room and self.policy == "latest" and self.backlog_bytes + room > RECOVER_BUDGET_BYTES:
                self._refuse(room, locked=True)
                return
            if room > 0:
                self.backlog += 1
            elif room < 0:
                self.behind += 1
            self.backlog_bytes += abs(room)
            self.queue.append((arrived, item, room))
            worker._wake.notify_all()
        worker._work_arrived(self, arrived)

    def _refuse(self, size: int = 0, locked: bool = False) -> None:
        """Count a frame a full lossless queue refuses (never wait: a held delivery thread stalls every other
        subscription of the session and, through zenoh's congestion control, the publisher). Logs the 1st, 10th,
        100th... overflow. A recovered frame (``size`` > 0) beyond the backlog's budget is ``missed``."""
        if not locked:
            with self.worker._wake:
                self._refuse(size, locked=True)
            return
        if size > 0:
            self.missed += 1
            if self.missed == 10 ** (len(str(self.missed)) - 1):
                self.worker.logger.warning("%s: recovered backlog full (%d MB): %d frame(s) missed so far", self.what,
                                           RECOVER_BUDGET_BYTES >> 20, self.missed)
            return
        self.received += 1
        self.overflow += 1
        self._refused_unseen += 1
        self.lost_at.append(time.monotonic())
        if self.overflow == 10 ** (len(str(self.overflow)) - 1):
            self.worker.logger.warning("%s: lossless queue full (%d frames, or %d MB behind a recovered backlog): %d "
                                       "frame(s) refused so far", self.what, self.depth, RECOVER_BUDGET_BYTES >> 20,
                                       self.overflow)

    def timed(self, seconds: float) -> None:
        """One more handler call took ``seconds`` (the running average decides the fast path)."""
        previous = self.handler_s
        self.handler_s = seconds if previous is None else previous + HANDLER_TIME_WEIGHT * (seconds - previous)

    def _decode(self, sample):
        """The handler's argument for a sample (the frame, or (frame, payload) if raw), or None if the payload is
        rejected (then counted as received and rejected; the caller counts an accepted one)."""
        payload = payload_bytes(sample.payload)
        try:
            if self.decoder is None:
                frame = decode(payload, expected=self.frame_type)
            elif self.attachment:
                frame = self.decoder(payload, None if sample.attachment is None else sample.attachment.to_bytes())
            else:
                frame = self.decoder(payload)
            self.accept(frame)
            if self.decoder is None:  # a foreign payload's header is made up here: no numbering to follow
                self._count_gap(frame.header, publisher_of(sample))
        except FrameError as error:
            with self.worker._wake:  # counters under the lock: zenoh may deliver on several threads
                self.received += 1
                self._refused_unseen += 1
                self.count_rejected(error)
            self.worker._note_error(f"{self.name}: rejected payload on {sample.key_expr}: {error}", quiet=True)
            return None
        return (frame, payload) if self.raw else frame

    def accept(self, frame) -> None:
        """The input's boundary checks of a decoded frame: its robot, then the worker's ``check`` (FrameError)."""
        check_robot(frame, self.robot)
        if self.check is not None:
            self.check(frame)

    def count_rejected(self, error: FrameError) -> None:
        """One more rejected frame, counted under its reason (the caller holds the worker's lock)."""
        self.rejected += 1
        self.rejected_reasons[getattr(error, "reason", "invalid")] += 1

    def window(self, now: float) -> tuple[float | None, float | None, float]:
        """Over the frames handled in the last RATE_WINDOW_S: (their rate while they flowed, Hz; mean handler
        time, ms; handler seconds in all)."""
        recent = [(end, seconds) for end, seconds in list(self.recent) if end >= now - RATE_WINDOW_S]
        if not recent:
            return None, None, 0.0
        busy = sum(seconds for _, seconds in recent)
        span = recent[-1][0] - recent[0][0]
        rate = (len(recent) - 1) / span if len(recent) > 1 and span > 0 else None
        return rate, 1e3 * busy / len(recent), busy

    def demand(self, now: float) -> tuple[int, int, float]:
        """Over the last RATE_WINDOW_S: (frames that arrived and were handled or lost, those lost (dropped or
        refused), the handler seconds they asked for: the handled ones' own, a typical one's (the median) for each
        lost one; not the mean, which a few long calls inflate, and those are what a burst of drops comes from)."""
        since = now - RATE_WINDOW_S
        handled = [seconds for end, seconds in list(self.recent) if end >= since]
        lost = sum(1 for at in list(self.lost_at) if at >= since)
        typical = float(np.median(handled)) if handled else self.handler_s or 0.0
        return len(handled) + lost, lost, sum(handled) + lost * typical

    @property
    def waiting(self) -> int:
        """Frames queued for the handler (a worker may leave deferred work until none waits)."""
        return len(self.queue) + self.held

    def stats(self) -> InputStats:
        rate, handler_ms, _ = self.window(time.monotonic())
        return InputStats(key=self.key, policy=self.policy, received=self.received, processed=self.processed,
                          dropped=self.dropped, overflow=self.overflow, rejected=self.rejected,
                          rejected_reasons=dict(self.rejected_reasons), errors=self.errors,
                          queued=self.waiting, rate_hz=rate, handler_ms=handler_ms,
                          recovered=max(0, self.received - self.live - self.already_held)
                          if self.recover_handles else 0, missed=self.missed, already_held=self.already_held,
                          lost_in_transit=self.lost_in_transit)


class Output:
    """A typed publisher. ``header(stamp_ns)`` makes the next header of this stream; ``publish(frame)`` sends."""

    def __init__(self, worker: "Worker", name: str, key: str, frame_type, bulk: bool, recover: int = 0):
        self.worker, self.name, self.key, self.frame_type = worker, name, key, frame_type
        self._frames = FramePublisher(worker.session, key, bulk=bulk, bus=worker.config.bus, recover=recover)
        self.robot = keys.robot_of(self.key) or worker.robot  # its frames name their key's robot: consumers check
        self.published = 0
        self.seq = 0

    @property
    def publisher(self):
        """The zenoh publisher (a recoverable output's: None until its first frame)."""
        return self._frames.publisher

    def header(self, stamp_ns: int | None = None, frame_id: str = "") -> Header:
        """Header for the next frame: the robot of the output's key, the key as stream, the next sequence number."""
        header = Header(robot=self.robot, stream=self.key, seq=self.seq,
                        stamp_ns=time.time_ns() if stamp_ns is None else int(stamp_ns), frame_id=frame_id)
        return header

    def publish(self, frame: Frame) -> None:
        if self.frame_type is not None and not isinstance(frame, self.frame_type):
            raise TypeError(f"output {self.name!r} publishes {self.frame_type.__name__}, got {type(frame).__name__}")
        if self.worker.replaying:  # replayed input was published before the restart
            return
        self._frames.put_frame(frame)
        self.published += 1
        self.seq = max(self.seq, frame.header.seq) + 1
        self.worker._published()

    def publish_bytes(self, payload: bytes | bytearray) -> None:
        """Publish an already-encoded frame (e.g. forwarding the bytes received)."""
        if self.worker.replaying:
            return
        self._frames.put_bytes(payload)
        self.published += 1
        self.worker._published()

    def stats(self) -> OutputStats:
        return OutputStats(key=self.key, published=self.published)


class _Queryable:
    """A command query: its request is decoded and checked on zenoh's thread (a bad one is answered with the
    reason and counted, like an input's rejected frame), then the handler runs on the main thread. Counted in
    the worker's status as the input ``query:<name>``."""

    def __init__(self, worker: "Worker", name: str, key: str, handler, frame_type, check=None):
        self.worker, self.name, self.key, self.handler, self.frame_type = worker, name, key, handler, frame_type
        self.check = check
        self.robot = keys.robot_of(key)  # the robot a request's header must name
        self.queryable = None
        self.received = self.processed = self.dropped = self.rejected = self.errors = 0
        self.rejected_reasons: collections.Counter[str] = collections.Counter()

    def _request(self, query):
        """The decoded, checked request (None for a query that takes none); FrameError when it is bad."""
        payload = query.payload
        data = payload_bytes(payload) if payload is not None else b""
        if self.frame_type is None:
            if data:
                raise FrameError(f"query {self.key} takes no request, got {len(data)} bytes", reason="schema")
            return None
        if not data:
            raise FrameError(f"query {self.key} needs a {self.frame_type.schema_name} request", reason="schema")
        request = decode(data, expected=self.frame_type)
        self.accept(request)
        return request

    def accept(self, request: Frame) -> None:
        """The boundary checks of a decoded request: its robot, then the worker's ``check`` (FrameError)."""
        check_robot(request, self.robot)
        if self.check is not None:
            self.check(request)

    def _on_query(self, query) -> None:
        worker = self.worker
        try:
            request = self._request(query)
        except FrameError as error:
            with worker._wake:
                self.received += 1
                self.count_rejected(error)
            worker._note_error(f"query {self.name}: rejected: {error}", quiet=True)
            query.reply_err(f"FrameError({error.reason}): {error}".encode())
            query.drop()
            return
        with worker._wake:
            self.received += 1
            if len(worker._queries) >= QUERY_QUEUE or worker._stopping.is_set():
                self.dropped += 1
                query.reply_err(b"worker busy or stopping")
                query.drop()
                return
            worker._queries.append((self, query, request))
            worker._wake.notify_all()

    def count_rejected(self, error: FrameError) -> None:
        """One more rejected request, under its reason (the caller holds the worker's lock)."""
        self.rejected += 1
        self.rejected_reasons[getattr(error, "reason", "invalid")] += 1

    def stats(self) -> InputStats:
        return InputStats(key=self.key, policy="lossless", received=self.received, processed=self.processed,
                          dropped=self.dropped, rejected=self.rejected, rejected_reasons=dict(self.rejected_reasons),
                          errors=self.errors)


class BusWatch:
    """Counts the zenoh transports a session has open (of the kinds in ``kinds``, e.g. {"router"}: a router's links
    to other routers; default every kind), from zenoh's transport events, and logs a lost and a regained bus: the
    last transport up closing or falling silent (``lost``) and one up again after that (``regained``).
    ``cut_off_since``: since when none is up (monotonic; None while one is), or, after :meth:`expect`, since when one
    is awaited. zenoh closes a transport whose peer went silent only by its lease, and not while lossless messages
    wait for it: a transport that answered :meth:`heard` once and not for ``quiet_s`` since (:meth:`check_silence`)
    is ``silent``, not up, until something crosses it again."""

    def __init__(self, logger: logging.Logger, kinds: frozenset[str] | None = None, what: str = "bus"):
        self.logger = logger
        self.kinds = kinds
        self.what = what
        self.open: set[str] = set()
        self.silent: dict[str, float] = {}  # of those open, the ones nothing crossed for quiet_s -> since when
        self.lost = self.regained = 0
        self.cut_off_since: float | None = None
        self._heard: dict[str, float] = {}  # an open transport's peer -> when something last crossed it
        self._listener = None
        self._lock = threading.Lock()

    @property
    def up(self) -> set[str]:
        return self.open - self.silent.keys()

    def expect(self) -> None:
        """One is awaited from now on (a router connecting to another): cut off until it opens."""
        with self._lock:
            if not self.open and self.cut_off_since is None:
                self.cut_off_since = time.monotonic()

    def watch(self, session: zenoh.Session) -> None:
        self._listener = session.info.declare_transport_events_listener(self._on_event, history=True)

    def heard(self, zid: str, since: float) -> None:
        """The transport to ``zid`` carried something both ways from ``since`` (monotonic) on: the time a probe it
        answered was sent. Not the answer's arrival: a router behind with what it received (lossless messages
        waiting for a silent link) reads what crossed before the silence for seconds after it began."""
        with self._lock:
            if zid not in self.open:
                return
            self._heard[zid] = max(since, self._heard.get(zid, since))
            # A probe sent before it was found silent, answered late (from a backlog), says nothing of it now.
            if zid in self.silent and since >= self.silent[zid]:
                del self.silent[zid]
                self._went_up(f"{zid} answering again")

    def check_silence(self, quiet_s: float) -> None:
        """Mark silent each transport nothing crossed for ``quiet_s`` since it was :meth:`heard`."""
        now = time.monotonic()
        with self._lock:
            for zid, at in self._heard.items():
                if zid in self.silent or now - at <= quiet_s:
                    continue
                self.silent[zid] = now
                if not self.up:
                    self._went_down(at, f"nothing crossed the transport to {zid} for {now - at:.1f} s, zenoh "
                                        "keeps it open")

    def _went_up(self, why: str) -> None:
        """One is up after none was (the caller holds the lock)."""
        if self.cut_off_since is None or len(self.up) != 1:
            self.logger.info("%s: %s (%d up)", self.what, why, len(self.up))
            return
        self.regained += 1 if self.lost else 0  # not the first one awaited since the start (expect)
        self.logger.log(logging.WARNING if self.lost else logging.INFO, "%s %s after %.1f s: %s", self.what,
                        "regained" if self.lost else "up", time.monotonic() - self.cut_off_since, why)
        self.cut_off_since = None

    def _went_down(self, since: float, why: str) -> None:
        """The last one up closed or fell silent (the caller holds the lock)."""
        self.lost += 1
        self.cut_off_since = since
        self.logger.warning("%s lost: %s, and none is left", self.what, why)

    def _on_event(self, event) -> None:
        if self.kinds is not None and str(event.transport.whatami) not in self.kinds:
            return
        zid = str(event.transport.zid)
        peer = f"{event.transport.whatami} {zid}"
        with self._lock:
            was_up = bool(self.up)
            if event.kind == zenoh.SampleKind.PUT:
                self.open.add(zid)
                self._went_up(f"transport to {peer} opened")
                return
            self.open.discard(zid)
            self.silent.pop(zid, None)
            self._heard.pop(zid, None)
            if was_up and not self.up:  # a silent one closing was counted when it fell silent
                self._went_down(time.monotonic(), f"the transport to {peer} closed")
            else:
                self.logger.info("%s: transport to %s closed (%d up)", self.what, peer, len(self.up))

    def close(self) -> None:
        if self._listener is not None:
            self._listener.undeclare()
            self._listener = None


class Worker:
    """Base class of a worker process. Override :meth:`setup` (declare inputs, outputs, queryables, timers);
    optionally :meth:`run` (source workers), :meth:`snapshot` / :meth:`restore` (crash-safe state) and
    :meth:`teardown`."""

    Config: ClassVar[type[WorkerConfig]] = WorkerConfig
    kind: ClassVar[str] = ""  # the module name under services/workers (set by the loader)

    def __init__(self, config: WorkerConfig):
        self.config = config
        self.robot = check_name(config.robot, "robot name")
        self.name = check_name(config.name or self.kind or type(self).__name__.lower(), "worker name")
        self.logger = logging.getLogger(f"semloc.{self.name}")
        self.session: zenoh.Session | None = None
        self.rerun = None  # rerun.RecordingStream when rerun output is on
        self._inputs: list[Input] = []
        self._outputs: list[Output] = []
        self._queryables: list[_Queryable] = []
        self._timers: list[list] = []  # [next_due, period, callback]
        self._queries: collections.deque = collections.deque()
        self._wake = threading.Condition()
        # Held by whoever runs worker code: the main thread, except while it waits idle in spin_once (then
        # zenoh's thread may take it to run a lossless delivery at once). Worker code never runs twice at a time.
        self._owner = threading.Lock()
        self._owner.acquire()
        self._stopping = threading.Event()
        self._latency = _Percentiles()
        self._state: str = "starting"
        self._started_ns = time.time_ns()
        self._started_monotonic = time.monotonic()
        self._last_error = ""
        self._last_error_ns = 0
        self._error_count_logged = 0
        self.queries_served = 0
        self._restarts, self._restart_reason = restart_info()
        # Health (see health()): written by whichever thread runs worker code, read by the status thread.
        self._progress = time.monotonic()  # the main loop last turned, or worker code last returned
        self._busy: tuple[float, str] | None = None  # (since, what) while worker code runs
        self._handling: float | None = None  # since when an input's handler runs (busy and falling behind count it)
        self._failures_in_a_row = 0
        self._unanswered_since: float | None = None  # first input frame since the last publication
        self._last_work_input = 0.0
        self._skipped: dict[str, list] = {}  # why -> [frames skipped, when last]: work the worker cannot do yet
        self._bus = BusWatch(self.logger)
        self._shared_memory: bool | None = None  # the session's, for the status (its zenoh config file read once)
        self._rr_entity_root = f"/{self.robot}/{self.name}"
        # crash-safe state: the journal of records since the last snapshot, and what to replay them with
        self._journal: Journal | None = None
        self._journal_streams: dict[str, tuple[Input | _Queryable, Callable[[Any], Any]]] = {}
        self._journal_cost_s = 0.0  # handler time of the records journaled since the last snapshot
        self._handler_started = time.monotonic()
        self._replaying = False
        self._persistence = _Persistence()
        self._has_state = False  # a snapshot or journal to restore at start: recoverable inputs may ask the caches
        # Files it cannot write (a full or read-only disk): what -> the reason, shown until a write of it succeeds.
        self._write_failing: dict[str, str] = {}
        self.write_failures = 0  # failed writes since the start
        self._journal_lost = False  # a record could not be journaled: journaling waits for the next snapshot
        self._set_aside_pending: list[Path] = []  # an unusable snapshot's files the disk refused to rename yet
        self._snapshot_retry_at = 0.0  # a failed snapshot is tried again from then (monotonic)
        self._snapshot_retry_s = WRITE_RETRY_FIRST_S
        self._memory_limits = memory.find_limits()  # once: a process's limits do not change under it

    # ------------------------------------------------------------------ declarations (call from setup)
    def input(self, name: str, key: str, frame_type, handler: Callable[..., Any], *, policy: Policy = "latest",
              depth: int | None = None, raw: bool = False, decoder: Callable[..., Any] | None = None,
              check: Callable[[Frame], None] | None = None, any_robot: bool = False,
              recover: bool | None = None, cached: bool = False, attachment: bool = False) -> Input:
        """Subscribe ``handler(frame)`` to ``key`` (wildcards allowed). ``frame_type``: a Frame class, a tuple of
        them, or None for any registered type. ``raw=True`` calls ``handler(frame, payload_bytes)`` instead.
        ``decoder(payload) -> item`` replaces semloc's frame decoding (foreign payloads, e.g. ROS 2 CDR): it runs on
        zenoh's thread like ``schemas.decode`` and its ``FrameError`` counts as rejected; ``attachment=True`` calls
        ``decoder(payload, attachment)`` with the sample's attachment (bytes; None without one), e.g. the ROS 2
        publisher's GID that rmw_zenoh puts there.
        ``check(frame)`` validates a decoded frame against the worker's configuration (its limits, its classes)
        and raises :class:`schemas.FrameError` to reject it before it takes a queue slot; it runs on zenoh's
        thread, so it may only read settings fixed at setup. Before it, a frame whose header names another robot
        than the key does is refused (``robot``); ``any_robot=True`` takes every robot's. ``recover`` (default: the
        key's stream is in ``keys.RECOVERABLE_STREAMS``): frames a recoverable output sent while out of reach (a link
        gap) arrive late, in order, counted as ``recovered``, queued beyond ``depth`` and the policy (within
        RECOVER_BUDGET_BYTES, with a lossless input's live frames that arrive behind them), ahead of the live ones;
        those beyond its cache count as ``missed``. Config ``inputs.<name>`` may override key, policy, depth and
        recover."""
        override = self.config.inputs.get(name, InputOverride())
        policy = override.policy or policy
        depth = override.depth or depth or DEFAULT_DEPTH.get(policy, 2)
        entry = Input(self, name, override.key or key, frame_type, handler, policy, depth, raw, decoder, check,
                      any_robot, attachment)
        recover = next(r for r in (override.recover, recover, keys.recover_frames(entry.key) > 0) if r is not None)
        if recover:
            # The counting subscription first: from the recoverable one's declaration on every live frame reaches
            # both, so received - live is what was recovered (once delivered; one between the two counts as live).
            live = self.session.declare_subscriber(entry.key, entry._on_live)
            # a worker with a state to restore holds its frames until it knows whether to ask the caches (_restore)
            entry.history = CacheHistory(self.session, entry.key, entry._on_sample) if self._has_state else None
            entry.subscriber, missed = declare_recoverable_subscriber(self.session, entry.key, entry._on_sample,
                                                                      entry._on_missed, entry.history)
            entry.recover_handles = (missed, live) + ((entry.history,) if entry.history else ())
        elif cached:
            entry.subscriber = declare_cached_subscriber(self.session, entry.key, entry._on_sample)
        else:
            entry.subscriber = self.session.declare_subscriber(entry.key, entry._on_sample)
        self._inputs.append(entry)
        return entry

    def output(self, name: str, key: str, frame_type=None, *, bulk: bool = False) -> Output:
        """Declare a publisher on ``key`` (config ``outputs.<name>.key`` may override). ``bulk=True``: large frames a
        consumer can do without (images, heatmaps), dropped under network congestion rather than waited for, and
        sent after the others (services.bus.stream_qos; ``outputs.<name>.bulk`` may override). A stream of
        ``keys.RECOVERABLE_STREAMS`` keeps its last frames for recoverable inputs that missed them
        (``bus.recover_cache``; config ``outputs.<name>.recover`` sets how many at most, 0: none)."""
        override = self.config.outputs.get(name, OutputOverride())
        key = override.key or key
        recover = override.recover if override.recover is not None else keys.recover_frames(key)
        bulk = override.bulk if override.bulk is not None else bulk
        out = Output(self, name, key, frame_type, bulk, recover)
        self._outputs.append(out)
        return out

    def compile_kernels(self, warm_up: Callable[..., Any], *args, **kwargs) -> None:
        """Call ``warm_up(*args, **kwargs)`` - a throwaway run of the worker's numba kernels - and log its CPU time.
        For ``setup``: numba compiles a kernel on its first call (seconds on a fresh install), which must not stall
        the first real frames while the worker already reports running."""
        started = time.process_time()
        warm_up(*args, **kwargs)
        self.logger.info("kernels ready (%.1f s of CPU)", time.process_time() - started)

    def queryable(self, name: str, key: str, handler: Callable[[Any], Any], *, request=None,
                  check: Callable[[Frame], None] | None = None) -> _Queryable:
        """Answer queries on ``key`` with ``handler(request) -> Frame | list[Frame] | None``. ``request``: the
        expected request frame type (None: the query takes no payload; one with a payload is rejected).
        ``check(request)`` validates it on zenoh's thread, as an input's check does (after its robot: a request
        whose header names another robot than the key does is refused, ``robot``). A handler raising
        :class:`schemas.FrameError` rejects the request with its reason (validate before touching state)."""
        override = self.config.outputs.get(name, OutputOverride())
        entry = _Queryable(self, name, override.key or key, handler, request, check)
        entry.queryable = self.session.declare_queryable(entry.key, entry._on_query)
        self._queryables.append(entry)
        return entry

    def latest_input(self, name: str, key: str, frame_type, handler: Callable[..., Any], *,
                     query_key: str | None = None, timeout_s: float = 1.0,
                     check: Callable[[Frame], None] | None = None) -> Input:
        """Subscribe ``handler`` to a slowly changing stream (a camera model, a map) and ask for its current value (on
        ``query_key``, default the stream's key): a worker started after the publisher must not wait for the next
        publication. Unanswered at start, it is asked again until a value arrives (:meth:`_ask_until_answered`).
        The reply is checked and counted as a frame of the input."""
        entry = self.input(name, key, frame_type, handler, policy="latest", depth=1, check=check)
        entry.drives_output = False
        try:
            replies = query(self.session, query_key or entry.key, reply_type=frame_type, timeout=timeout_s)
        except (QueryError, FrameError) as error:
            self.logger.warning("%s: query on %s failed: %s", name, entry.key, error)
            replies = []
        if not replies:
            self._ask_until_answered(entry, query_key or entry.key, timeout_s)
        if replies:
            with self._wake:
                entry.received += 1
            try:
                entry.accept(replies[0])
            except FrameError as error:
                with self._wake:
                    entry.count_rejected(error)
                self._note_error(f"{name}: rejected the reply on {query_key or entry.key}: {error}")
            else:
                self._handle(entry, time.monotonic(), replies[0])
        return entry

    def _ask_until_answered(self, entry: Input, key: str, timeout_s: float) -> None:
        """Ask ``key`` again, at growing intervals, until ``entry`` has received a frame (a reply or a publication).

        A session just opened meshes with the other peers over some time (more on a loaded machine): a query sent
        before it met the publisher's process reaches no one, and a restarted worker would then go without its
        camera model until the next publication, if any. The replies arrive on zenoh's thread and are queued and
        counted as the input's frames; nothing here blocks the main thread."""
        def on_reply(reply) -> None:
            if reply.ok is not None and entry.received == 0 and not self._stopping.is_set():
                entry._on_sample(reply.ok)

        def ask_again() -> None:
            if entry.received or self.session is None or self._stopping.is_set():
                timer[1] = float("inf")  # answered (or leaving): never due again
                return
            self.session.get(key, on_reply, timeout=timeout_s)
            timer[1] = min(2 * timer[1], LATEST_ASK_MAX_S)

        timer = [time.monotonic() + LATEST_ASK_FIRST_S, LATEST_ASK_FIRST_S, ask_again]
        self._timers.append(timer)

    def journal_stream(self, name: str, source: Input | _Queryable, apply: Callable[[Any], Any]) -> None:
        """Declare a journaled stream of the frames of ``source`` (the input or queryable they arrived on): records
        written with :meth:`journal_write` are replayed after a restart by ``apply(frame)``, on top of the restored
        snapshot, in order, with outputs and rerun muted. Each record is decoded as the source's frame type and
        passes the source's boundary checks (``accept``: its robot, then its ``check``) first: a journal is a file,
        read like any input, and one copied from another robot's state folder is refused and counted there.
        ``apply`` must change the state exactly as the original handler did."""
        self._journal_streams[name] = (source, apply)

    def journal_write(self, name: str, record: Frame | bytes | bytearray | memoryview,
                      replay_s: float | None = None) -> None:
        """Journal one applied state change (a frame, or the encoded bytes received); call it once the handler has
        changed the state. ``replay_s``: how long replaying it takes, when less than the handler's time so far (the
        default), e.g. the handler extracted what it journals. A no-op without ``state_dir`` and while replaying."""
        if self._journal is None or self._replaying:
            return
        if name not in self._journal_streams:
            raise ValueError(f"journal stream {name!r} is not declared (journal_stream)")
        source = self._journal_streams[name][0]
        if isinstance(source, Input):  # the state holds it from now on, journaled or not (the next snapshot)
            header = (record.header.robot, record.header.stream, record.header.stamp_ns) \
                if isinstance(record, Frame) else peek_header(record)
            if header is not None:
                source.note_journaled(header)
        if self._journal_lost:
            return  # the state holds a change the journal lacks: records after it wait for the next snapshot
        try:
            self._journal.append(name, encode(record) if isinstance(record, Frame) else record)
        except OSError as error:
            # The handler has changed the state: it goes on (its outputs keep flowing). A record missing from the
            # journal would make a replay diverge, so none is written until a snapshot holds the state again;
            # after a crash meanwhile, the worker restarts from the snapshot and the records before this one.
            self._journal_lost = True
            self.write_failed("journal", error, "journaling stopped until a state snapshot is written")
            return
        self._persistence.journal_records += 1
        self._journal_cost_s += time.monotonic() - self._handler_started if replay_s is None else replay_s

    @property
    def replaying(self) -> bool:
        """True while journal records are replayed at start (outputs and rerun are muted)."""
        return self._replaying

    def skipped(self, why: str) -> None:
        """Count a frame this worker could not process for a reason outside it (e.g. ``no camera model yet``):
        logged at the 1st, 100th and 1000th, and the worker reports ``degraded`` with the reason until it calls
        :meth:`resumed` or has skipped nothing for ``degraded_silence_s``."""
        entry = self._skipped.setdefault(why, [0, 0.0])
        entry[0] += 1
        entry[1] = time.monotonic()
        if entry[0] in (1, 100, 1000):
            self.logger.warning("%s: %d frame(s) skipped", why, entry[0])

    def resumed(self, why: str) -> None:
        """The cause of :meth:`skipped` ``why`` is gone (e.g. the camera model arrived)."""
        entry = self._skipped.pop(why, None)
        if entry is not None:
            self.logger.info("%s no more: %d frame(s) were skipped", why, entry[0])

    def write_failed(self, what: str, error: OSError, consequence: str = "") -> None:
        """A write of ``what`` (a file the worker keeps, e.g. its trajectory) failed: a full or read-only disk, a
        file size limit. Counted (``Status.write_failures``), logged at its first failure, and the worker reports
        ``degraded`` with ``cannot write <file>: <the system's reason>`` until :meth:`write_succeeded` ``what``.
        The caller keeps serving its outputs and tries again later."""
        self.write_failures += 1
        reason = one_line(f"cannot write {error.filename or what}: {error.strerror or error}"
                          f"{f' ({consequence})' if consequence else ''}")
        first = what not in self._write_failing
        self._write_failing[what] = reason  # before logging: a log that cannot be written reports here too
        self._last_error, self._last_error_ns = reason, time.time_ns()
        if first and what != LOG_WRITES:
            self.logger.error("%s", reason)

    def write_failing(self, what: str) -> bool:
        """Whether ``what`` is reported as failing (:meth:`write_failed`, not succeeded since)."""
        return what in self._write_failing

    def write_succeeded(self, what: str) -> None:
        """``what`` was written again after :meth:`write_failed`: no longer degraded for it."""
        if self._write_failing.pop(what, None) is not None:
            self.logger.warning("%s written again (%d failed writes so far)", what, self.write_failures)

    def every(self, period_s: float, callback: Callable[[], Any]) -> None:
        """Call ``callback()`` every ``period_s`` seconds on the main thread (first call after one period)."""
        if period_s <= 0:
            raise ValueError("timer period must be positive")
        self._timers.append([time.monotonic() + period_s, float(period_s), callback])

    # ------------------------------------------------------------------ hooks
    def setup(self) -> None:
        """Declare inputs, outputs, queryables and timers here."""

    def run(self) -> None:
        """Main loop. The default dispatches events until stopped; a source worker overrides it and calls
        :meth:`sleep` between frames (which keeps queries, timers and inputs served)."""
        while not self.stopping:
            self.spin_once(0.5)

    def snapshot(self) -> State | None:
        """State to save (periodically and on stop) when ``state_dir`` is set; None = nothing to save."""
        return None

    def restore(self, state: State) -> None:
        """Called after :meth:`setup` with the last snapshot, if one exists."""

    def teardown(self) -> None:
        """Called once on the way out (after the last snapshot), before the session closes."""

    # ------------------------------------------------------------------ helpers
    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def stop(self) -> None:
        """Ask the worker to stop (thread-safe)."""
        self._stopping.set()
        with self._wake:
            self._wake.notify_all()

    def sleep(self, seconds: float) -> bool:
        """Serve events for ``seconds``; returns False if the worker is stopping."""
        deadline = time.monotonic() + max(0.0, seconds)
        while not self.stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return True
            self.spin_once(remaining)
        return False

    def sleep_until(self, deadline_monotonic: float) -> bool:
        return self.sleep(deadline_monotonic - time.monotonic())

    @property
    def state_path(self) -> Path | None:
        if not self.config.state_dir:
            return None
        return Path(self.config.state_dir) / self.robot / f"{self.name}.npz"

    @property
    def state_store_dir(self) -> Path | None:
        """A directory for state too large to snapshot whole (e.g. an append-only store the snapshot indexes); set
        aside with the snapshot when that cannot be used."""
        path = self.state_path
        return None if path is None else path.with_suffix(".store")

    def save_state_now(self) -> bool:
        """Snapshot the state immediately (atomic); the journal starts a new segment and drops the old ones.
        False when it cannot be written (a full or read-only disk: reported, see :meth:`write_failed`, the previous
        snapshot and its journal kept, tried again with a growing wait up to ``snapshot_period_s``)."""
        path = self.state_path
        if path is None:
            return True
        try:
            if self._set_aside_pending:  # never written over: the unusable snapshot goes first
                moved = set_aside(self._set_aside_pending)
                self._persistence.set_aside += [str(m) for m in moved]
                self._set_aside_pending = []
                self.logger.warning("unusable state set aside as %s", ", ".join(m.name for m in moved))
            state = self.snapshot()  # no handler runs in between: the state holds every record journaled so far
            if state is None:
                return True
            state.meta[STATE_HOLDS] = {entry.name: [[*stream, stamp] for stream, stamp in entry.journaled.items()]
                                       for entry in self._inputs if entry.journaled}
            segment = self._journal.rotate() if self._journal is not None else 0
            state.journal_segment = segment
            save_state(path, state)
        except OSError as error:  # snapshot() may flush a store, rotate() syncs the journal: fsync names no file
            self.write_failed("state", error if error.filename else OSError(error.errno, error.strerror, str(path)))
            self._snapshot_retry_at = time.monotonic() + self._snapshot_retry_s
            self._snapshot_retry_s = min(2 * self._snapshot_retry_s, self.config.snapshot_period_s or 30.0)
            return False
        self._snapshot_retry_at, self._snapshot_retry_s = 0.0, WRITE_RETRY_FIRST_S
        self.write_succeeded("state")
        if self._journal_lost:
            self._journal_lost = False  # the snapshot holds the state: journaling resumes in the new segment
            self.write_succeeded("journal")
        self._journal_cost_s = 0.0
        self._persistence.snapshots += 1
        self._persistence.journal_records = 0
        if self._journal is not None:
            self._journal.discard_before(segment)
        return True

    def _snapshot_if_due(self) -> None:
        due = self._journal_cost_s >= self.config.journal_replay_s or self._journal_lost
        if due and time.monotonic() >= self._snapshot_retry_at:
            self.save_state_now()

    def rerun_log(self, path: str, entity, *, header: Header | None = None, static: bool = False) -> None:
        """Log a rerun archetype at ``/<robot>/<worker>/<path>``; ``header`` sets the ``frame`` (seq) and
        ``capture`` (stamp) timelines. A no-op when rerun output is off."""
        if self.rerun is None or self._replaying:
            return
        if header is not None:
            self.rerun.set_time("frame", sequence=header.seq)
            self.rerun.set_time("capture", timestamp=header.stamp_ns * 1e-9)
        self.rerun.log(f"{self._rr_entity_root}/{path.strip('/')}", entity, static=static)

    def status(self) -> Status:
        inputs = {i.name: i.stats() for i in list(self._inputs)}
        inputs.update({f"query:{q.name}": q.stats() for q in list(self._queryables)})  # not in the totals below
        p50, p95 = self._latency.p50_p95()
        total = lambda attr: sum(getattr(i, attr) for i in list(self._inputs))  # noqa: E731
        reading = memory.read(self._memory_limits)
        state, reason = self.health(reading)
        busy = self._busy_fraction(time.monotonic())
        return Status(
            header=Header(robot=self.robot, stream=keys.status(self.robot, self.name), stamp_ns=time.time_ns()),
            worker=self.name, kind=self.kind or type(self).__name__, state=state, state_reason=reason,
            pid=os.getpid(), host=socket.gethostname(), started_ns=self._started_ns,
            uptime_s=max(0.0, (time.time_ns() - self._started_ns) * 1e-9),
            received=total("received"), processed=total("processed"), dropped=total("dropped"),
            overflow=total("overflow"), rejected=total("rejected"), errors=total("errors"),
            queries=self.queries_served, latency_p50_ms=p50, latency_p95_ms=p95, inputs=inputs,
            outputs={o.name: o.stats() for o in list(self._outputs)}, last_error=self._last_error,
            last_error_ns=self._last_error_ns, restarts=self._restarts, restart_reason=self._restart_reason,
            bus_transports=len(self._bus.open), bus_lost=self._bus.lost, bus_regained=self._bus.regained,
            persistence=PersistenceStats(**vars(self._persistence)) if self.config.state_dir else None,
            write_failures=self.write_failures,
            busy_fraction=busy,
            memory=MemoryStats(rss_bytes=reading.rss, peak_bytes=reading.peak, used_bytes=reading.used,
                               limit_bytes=None if reading.limit is None else reading.limit.bytes,
                               limit_source="" if reading.limit is None else one_line(reading.limit.source),
                               near_limit=self._near_limit(reading)),
            details={**SHARED_MEMORY.details(self._shared_memory), **self.status_details()},
        )

    def status_details(self) -> dict:
        """The worker's own figures for its status (flat: names to numbers or short strings); none by default."""
        return {}

    def _handler_running_s(self, now: float) -> float:
        """How long the input handler running now has run, within the last RATE_WINDOW_S (0: none runs). A call of
        seconds is part of the window's work before it returns."""
        started = self._handling
        return 0.0 if started is None else min(now - started, RATE_WINDOW_S)

    def _busy_fraction(self, now: float) -> float:
        """The share of the last RATE_WINDOW_S (of its life, if shorter) its handlers ran."""
        span = min(RATE_WINDOW_S, max(now - self._started_monotonic, 1e-3))
        return min(1.0, (sum(i.window(now)[2] for i in list(self._inputs)) + self._handler_running_s(now)) / span)

    def _falling_behind(self, now: float) -> str:
        """Why it cannot keep up with its inputs ("": it can). A lossless input that refused a frame in the last
        RATE_WINDOW_S lost what it must not; a latest one that dropped frames did so by design unless the frames that
        arrived asked for more handler time than the whole window holds (the worker's own figures, Input.demand: with
        time to spare, drops come from bursts, e.g. a key frame's long handler, and stop by themselves; a whole
        window even for a worker younger than it, whose first burst would otherwise look sustained). A latest input
        owed no output (a pose, a camera model) loses only values a newer one replaced."""
        demands = [(entry, *entry.demand(now)) for entry in list(self._inputs)]
        needed = (sum(seconds for *_, seconds in demands) + self._handler_running_s(now)) / RATE_WINDOW_S
        behind = [f"falling behind on {entry.name}: {'refused' if entry.policy == 'lossless' else 'dropped'} {lost} "
                  f"of {arrived} frames in the last {RATE_WINDOW_S:.0f} s"
                  for entry, arrived, lost, _ in demands
                  if lost and (entry.policy == "lossless" or (entry.drives_output and needed >= 1.0))]
        if not behind:
            return ""
        return one_line(f"{'; '.join(behind)} (busy {100 * self._busy_fraction(now):.0f} %, needed "
                        f"{100 * needed:.0f} %)")

    def _shared_streams(self, now: float) -> str:
        """The streams more than one publisher sends ("": none): their frames interleave, each consumer takes both."""
        shared = [stream for entry in list(self._inputs) for stream in entry.shared_streams(now)]
        if not shared:
            return ""
        return one_line(f"{', '.join(shared)} in the last {RATE_WINDOW_S:.0f} s (two workers publishing one key, "
                        f"a replay beside the worker it recorded, or an old process still running)")

    def _losing_in_transit(self, now: float) -> str:
        """The streams that lose frames on the way ("": none): the link from their publisher is the bottleneck,
        not this worker."""
        losing = [stream for entry in list(self._inputs) for stream in entry.losing_in_transit(now)]
        if not losing:
            return ""
        return one_line(f"losing frames on the way: {', '.join(losing)} sent in the last {RATE_WINDOW_S:.0f} s "
                        f"never arrived (a thin or congested link)")

    def _near_limit(self, reading: memory.Reading) -> bool:
        high, fraction = self.config.memory_high_fraction, reading.fraction
        return high is not None and fraction is not None and fraction >= high

    def health(self, reading: memory.Reading | None = None) -> tuple[str, str]:
        """(state, reason): ``running``, or ``degraded`` / ``stalled`` with the reason in one line, or the
        lifecycle state (starting, stopping, stopped). Stalled wins over degraded. ``reading``: its memory now (read
        if not given)."""
        if self._state != "running":
            return self._state, ""
        reading = memory.read(self._memory_limits) if reading is None else reading
        c, now = self.config, time.monotonic()
        busy = self._busy
        if busy is not None and now - busy[0] > c.stalled_after_s:
            return "stalled", one_line(f"{busy[1]} has not returned for {now - busy[0]:.0f} s")
        if now - self._progress > c.stalled_after_s:
            return "stalled", f"the main loop made no progress for {now - self._progress:.0f} s"
        if self._near_limit(reading):
            # first: past its limit the kernel kills it, whatever else is wrong
            return "degraded", one_line(f"memory near its limit: {memory.mb(reading.used)} of "
                                        f"{memory.mb(reading.limit.bytes)} ({100 * reading.fraction:.0f} %; "
                                        f"{reading.limit.source})", limit=1000)
        failing = list(self._write_failing.copy().values())  # copy: any thread's log may add to it
        if failing:
            # each file in full, as many as Status.state_reason holds (paths are long)
            return "degraded", one_line(f"{'; '.join(failing)} ({self.write_failures} failed writes)", limit=1000)
        if self._failures_in_a_row >= c.degraded_after_failures:
            return "degraded", one_line(f"the last {self._failures_in_a_row} handler calls failed; last: "
                                        f"{self._last_error}")
        silent_since = self._unanswered_since
        if (c.degraded_silence_s and self._outputs and silent_since is not None
                and now - silent_since > c.degraded_silence_s and now - self._last_work_input < c.degraded_silence_s):
            return "degraded", f"inputs arrive but nothing was published for {now - silent_since:.0f} s"
        window = c.degraded_silence_s or 30.0
        skipping = [(count, why) for why, (count, last) in self._skipped.items() if now - last < window]
        if skipping:
            return "degraded", one_line("; ".join(f"{why}: {count} frame(s) skipped" for count, why in skipping))
        # the streams two publishers share first: both publishers' frames are what a consumer falls behind on
        behind = self._shared_streams(now) or self._falling_behind(now) or self._losing_in_transit(now)
        if behind:
            return "degraded", behind
        cut_off = self._bus.cut_off_since
        if cut_off is not None:
            return "degraded", f"cut off the bus for {now - cut_off:.0f} s (no zenoh transport open)"
        return "running", ""

    # ------------------------------------------------------------------ event loop
    def spin_once(self, timeout: float) -> None:
        """Run due timers, then the queued frames (all of a lossless input, one of a latest input; across inputs in
        the order they arrived) and the queued queries; wait up to ``timeout`` if idle."""
        now = self._progress = time.monotonic()
        for timer in self._timers:
            if timer[0] <= now:
                timer[0] = max(timer[0] + timer[1], now)
                self._call(timer[2], None, what="timer")
        if self._idle():
            # Idle: give the worker up while waiting, so zenoh's thread may run a lossless delivery itself
            # (Input._on_sample); taken back before anything else runs here.
            self._owner.release()
            try:
                with self._wake:
                    if self._idle():
                        next_timer = min((t[0] for t in self._timers), default=now + timeout)
                        # Capped so a signal (which only sets the stop flag) is honoured quickly.
                        self._wake.wait(max(0.0, min(timeout, 0.2, next_timer - time.monotonic())))
            finally:
                self._owner.acquire()
        with self._wake:
            batch = []
            for entry in self._inputs:
                # lossless: everything queued, in order (one lock round per batch, not per frame, keeps a fast
                # stream from ping-ponging between zenoh's thread and this one); latest: the oldest kept frame.
                taken = len(entry.queue) if entry.policy == "lossless" else min(len(entry.queue), 1)
                for _ in range(taken):
                    batch.append((entry, entry.queue.popleft()))
                entry.held += taken
            queries = list(self._queries)
            self._queries.clear()
        # Across inputs in the order the frames arrived: a worker that fell behind must not see a frame before one
        # that came earlier on another input (the localizer's odometry, say, before the heatlines it precedes).
        batch.sort(key=lambda queued: queued[1][0])
        for index, (entry, (arrived, item, size)) in enumerate(batch):
            batch[index] = None  # a handled frame is freed at once, not when the whole batch is done
            entry.done(size)
            if self.stopping:
                continue  # a stopping worker finishes the frame in its handler, not its backlog
            self._handle(entry, arrived, item)
        for entry, query, request in queries:
            self._answer(entry, query, request)

    def _idle(self) -> bool:
        return not self._queries and not any(i.queue for i in self._inputs) and not self.stopping

    def _handle(self, entry: Input, arrived: float, item) -> None:
        """Run an input's handler on its decoded item (the caller owns the worker) and count it."""
        if entry.state_holds and entry.held_by_state(item[0] if entry.raw else item):
            return
        started = self._handling = time.monotonic()
        try:
            handled = self._call(entry.deliver, item, what=entry.what, entry=entry)
        finally:
            self._handling = None
        ended = time.monotonic()
        entry.timed(ended - started)
        if handled:
            entry.processed += 1
            entry.recent.append((ended, ended - started))
            if entry.drives_output:  # a pose or odometry that asks for no output would dilute the frames' latency
                self._latency.add((ended - arrived) * 1e3)

    def _call(self, function, argument, *, what: str, entry: Input | _Queryable | None = None) -> bool:
        self._handler_started = time.monotonic()
        self._busy = (self._handler_started, what)
        try:
            function() if argument is None and entry is None else function(argument)
            self._failures_in_a_row = 0
            return True
        except FrameError as error:  # the input's fault, not the worker's: neither a failure nor a success
            if entry is not None:
                with self._wake:  # zenoh's threads count this input's rejected payloads too (Input._decode)
                    entry.count_rejected(error)
            self._note_error(f"{what}: rejected: {error}", quiet=True)
        except Exception as error:  # error isolation: a failing handler never stops the worker
            if entry is not None:
                entry.errors += 1
            self._failures_in_a_row += 1
            self._note_error(f"{what}: {type(error).__name__}: {error}", details=traceback.format_exc())
        finally:
            self._busy = None
            self._progress = time.monotonic()
        return False

    def _work_arrived(self, entry: Input, arrived: float) -> None:
        """An accepted frame arrived (zenoh's thread): the silence check of :meth:`health` starts counting."""
        if entry.drives_output:
            self._last_work_input = arrived
            if self._unanswered_since is None:
                self._unanswered_since = arrived

    def _published(self) -> None:
        self._unanswered_since = None
        self._progress = time.monotonic()

    def answered(self) -> None:
        """A handler that chose to publish nothing for its frame (a loop-closure image that is no key-frame) has
        answered it all the same: the silence check of :meth:`health` stops counting."""
        self._unanswered_since = None

    def _answer(self, entry: _Queryable, query, request) -> None:
        self._busy = (time.monotonic(), f"query {entry.name}")
        try:
            result = entry.handler(request)
            frames = [] if result is None else list(result) if isinstance(result, (list, tuple)) else [result]
            for frame in frames:
                query.reply(entry.key, encode(frame))
            self.queries_served += 1
            entry.processed += 1
        except Exception as error:
            rejected = isinstance(error, FrameError)
            with self._wake:
                if rejected:
                    entry.count_rejected(error)
                else:
                    entry.errors += 1
            self._note_error(f"query {entry.name}: {type(error).__name__}: {error}", quiet=rejected)
            reason = f"FrameError({error.reason})" if rejected else type(error).__name__
            try:
                query.reply_err(f"{reason}: {error}".encode())
            except Exception:
                pass
        finally:
            query.drop()
            self._busy = None
            self._progress = time.monotonic()

    def _note_error(self, message: str, quiet: bool = False, details: str = "") -> None:
        """Remember ``message`` in one line as ``last_error``; log it with ``details`` (a traceback)."""
        self._last_error = one_line(message)
        self._last_error_ns = time.time_ns()
        self._error_count_logged += 1
        # The first errors in full, then one in a hundred: a hostile stream must not flood the log.
        if self._error_count_logged <= 10 or self._error_count_logged % 100 == 0:
            (self.logger.info if quiet else self.logger.error)("%s%s", message, f"\n{details}" if details else "")

    # ------------------------------------------------------------------ lifecycle
    def _status_loop(self, publisher, done: threading.Event) -> None:
        # From the session's opening to the end of teardown: the heartbeat the launcher watches (a worker in a long
        # setup or final snapshot is starting / stopping, not hung).
        while True:
            try:
                publisher.put(encode(self.status()))
            except Exception as error:  # never let status reporting kill the worker
                self.logger.warning("status publication failed: %s", error)
            if done.wait(self.config.status_period_s):
                return

    def _meet_started_after(self, session) -> None:
        """Wait until this session has met the workers its launcher names (``START_AFTER_ENV``: those it held this
        first start for, or those running at this restart): their liveliness tokens are seen here. Peers do not
        relay for each other, and zenoh's gossip meshes a new session with the running peers one by one after it
        opened: the first frames of a recorded source that played at once reached some of the workers it waited for
        and not others. A worker's token comes with its other declarations (its inputs' subscribers, made in its
        setup, before it ran) when the two sessions meet."""
        wanted = {}
        for name in filter(None, os.environ.get(START_AFTER_ENV, "").split(",")):
            robot, _, worker = name.partition("/")
            try:
                wanted[name] = keys.alive(robot, worker)
            except ValueError as error:  # not a worker's name: nothing to meet
                self.logger.warning("%s: %r ignored: %s", START_AFTER_ENV, name, error)
        if not wanted:
            return
        started, met = time.monotonic(), list(wanted)
        while wanted:
            for name, key in list(wanted.items()):
                if any(reply.ok is not None for reply in session.liveliness().get(key, timeout=1.0)):
                    del wanted[name]
            if not wanted:
                break
            if self.stopping:
                return
            if time.monotonic() - started >= MEET_TIMEOUT_S:
                self.logger.warning("not met %.0f s after the start, going on without them: %s", MEET_TIMEOUT_S,
                                    ", ".join(wanted))
                return
            time.sleep(0.02)  # (before the setup: no event loop to serve yet)
        self.logger.info("met %s (%s) in %.2f s", ", ".join(met),
                         "restart" if os.environ.get(RESTARTS_ENV, "0") != "0" else "start_after",
                         time.monotonic() - started)

    def _on_status_query(self, query) -> None:
        try:
            # Under the worker's own key, not the query's (a wildcard): zenoh's default consolidation keeps one
            # reply per key, so replies under one shared key would hide all workers but one.
            query.reply(keys.status(self.robot, self.name), encode(self.status()))
        except Exception as error:
            self.logger.warning("status query failed: %s", error)
        finally:
            query.drop()

    def main(self) -> int:
        """Run the worker to completion; returns the process exit code (0 after a graceful stop)."""
        retain_freed_memory()
        self._install_signal_handlers()
        self._watch_log_writes()
        self._write_config_snapshot()
        exit_code = 0
        setup_done = state_ready = False
        status_thread = None
        status_done = threading.Event()
        token = status_queryable = status_publisher = None
        with open_session(self.config.bus) as session:
            self.session = session
            self._shared_memory = uses_shared_memory(self.config.bus)
            try:
                self._bus.watch(session)
                token = session.liveliness().declare_token(keys.alive(self.robot, self.name))
                status_key = keys.status(self.robot, self.name)
                status_publisher = session.declare_publisher(status_key)
                status_queryable = session.declare_queryable(status_key, self._on_status_query)
                status_thread = threading.Thread(target=self._status_loop, args=(status_publisher, status_done),
                                                 name="semloc-status", daemon=True)
                status_thread.start()
                self._meet_started_after(session)
                self.rerun = open_recording(self.config.rerun, self.name, self.robot)
                memory.check_room(self.config.memory_needs(), self.config.memory_high_fraction or 1.0,
                                  self._memory_limits)
                self._has_state = self._state_exists()
                self.setup()
                setup_done = True
                self._check_overrides()
                self._restore()
                self._ask_history()
                state_ready = True  # only a state restored (or started empty) on purpose may be snapshotted
                if self.config.state_dir and self.config.snapshot_period_s:
                    self.every(self.config.snapshot_period_s, self.save_state_now)
                if self._journal is not None:
                    self.every(0.1, self._snapshot_if_due)
                self._progress = time.monotonic()
                self._state = "running"
                status_publisher.put(encode(self.status()))
                self.logger.info("worker %s (%s) running on robot %s", self.name, self.kind, self.robot)
                self.run()
            except (FileFormatError, ConfigError, UnusableState) as error:
                # A bad file or setting, or a state an operator must decide about: one line naming it, and an exit
                # code a launcher does not restart.
                exit_code = CONFIG_ERROR_EXIT
                self._note_error(f"worker failed: {error}")
            except Exception as error:
                exit_code = 1
                self._note_error(f"worker failed: {type(error).__name__}: {error}", details=traceback.format_exc())
            finally:
                self._state = "stopping"
                self._stopping.set()
                with self._wake:
                    self._wake.notify_all()  # wake the main loop
                if state_ready:
                    try:
                        if not self.save_state_now():
                            exit_code = exit_code or 1
                    except Exception as error:
                        exit_code = exit_code or 1
                        self._note_error(f"final state snapshot failed: {error}")
                if self._journal is not None:
                    try:
                        self._journal.close()
                    except OSError as error:
                        self._note_error(f"journal close failed: {error}")
                if setup_done:
                    try:
                        self.teardown()
                    except Exception as error:
                        self._note_error(f"teardown failed: {type(error).__name__}: {error}")
                for entry in self._inputs:
                    for handle in (entry.subscriber, *entry.recover_handles):
                        if handle is not None:
                            handle.undeclare()
                for entry in self._queryables:
                    if entry.queryable is not None:
                        entry.queryable.undeclare()
                for _, query, _ in self._queries:
                    query.reply_err(b"worker stopping")
                    query.drop()
                status_done.set()
                if status_thread is not None:
                    status_thread.join(timeout=2.0)
                self._state = "stopped"
                if status_publisher is not None:
                    try:
                        status_publisher.put(encode(self.status()))
                    except Exception:
                        pass
                if status_queryable is not None:
                    status_queryable.undeclare()
                if token is not None:
                    token.undeclare()
                self._bus.close()
                if self.rerun is not None:
                    try:
                        self.rerun.flush(timeout_sec=5.0)
                        self.rerun.disconnect()
                    except Exception as error:
                        self.logger.warning("rerun flush failed: %s", error)
        self.session = None
        self.logger.info("worker %s stopped (exit code %d)", self.name, exit_code)
        return exit_code

    def _check_overrides(self) -> None:
        # A graph file naming an input or output the worker does not declare is almost always a typo.
        declared_inputs = {i.name for i in self._inputs}
        declared_outputs = {o.name for o in self._outputs} | {q.name for q in self._queryables}
        for name in set(self.config.inputs) - declared_inputs:
            self.logger.warning("config overrides input %r, but this worker declares only %s", name,
                                sorted(declared_inputs))
        for name in set(self.config.outputs) - declared_outputs:
            self.logger.warning("config overrides output %r, but this worker declares only %s", name,
                                sorted(declared_outputs))

    def _restore(self) -> None:
        """Restore the snapshot, replay the journal after it, and open a new journal segment. A snapshot that cannot
        be used is set aside with its journal and store, never overwritten (``on_corrupt_state``)."""
        path = self.state_path
        if path is None:
            return
        journal = Journal(path.with_suffix(".journal"), self.config.journal_commit_s)
        try:
            remove_partial_writes(path)
        except OSError:
            pass  # a read-only disk: the leftovers stay beside the snapshot, which they never replace
        try:
            state = load_state(path)
            if state is not None:
                self.logger.info("restoring state from %s", path)
                holds = self._state_holds(state.meta.pop(STATE_HOLDS, {}))  # checked before anything changes
                self.restore(state)  # all or nothing: a restore that raises leaves the worker's state as it was
                for entry in self._inputs:
                    entry.journaled = holds.get(entry.name, {})
                self._persistence.restored = True
        except Exception as error:
            refused = refused_write(error)
            if refused is not None:  # a good snapshot: a disk refusing writes says nothing about it
                raise StateNotWritable(f"state snapshot {path} kept: restoring it needs a write the disk refuses "
                                       f"({refused.filename or path}: {refused.strerror}); exits to be started again"
                                       ) from error
            reason = str(error) if isinstance(error, StateError) else f"{type(error).__name__}: {error}"
            reason = reason.splitlines()[0][:300] if reason else type(error).__name__
            if self.config.on_corrupt_state == "stop":
                raise UnusableState(f"state snapshot {path} cannot be used ({reason}); left as it is: move it away "
                                    f"or set on_corrupt_state: empty to start with an empty state") from None
            unusable = [path, journal.directory, self.state_store_dir]
            try:
                moved = set_aside(unusable)
            except OSError as refusal:
                # Started empty all the same; its first snapshot sets them aside first (save_state_now), and none
                # is written until then. Their journal is not replayed: its records follow the unusable snapshot.
                self._set_aside_pending = [p for p in unusable if p is not None and p.exists()]
                self._persistence.note = one_line(f"state snapshot {path} cannot be used ({reason}); cannot be set "
                                                  f"aside yet ({refusal.strerror}); started with an empty state")
                self._note_error(self._persistence.note)
                self._journal = journal if self._journal_streams else None
                self._journal_lost = True
                self.write_failed("state", OSError(refusal.errno, refusal.strerror, refusal.filename or str(path)),
                                  "the unusable snapshot is set aside before any other is written")
                return
            self._persistence.set_aside = [str(m) for m in moved]
            self._persistence.note = one_line(f"state snapshot {path} cannot be used ({reason}); set aside as "
                                              f"{', '.join(m.name for m in moved)}; started with an empty state")
            self._note_error(self._persistence.note)
            state = None
        replayed = failed = 0
        refused: collections.Counter[str] = collections.Counter()  # records the sources' checks refused, by reason
        started = time.monotonic()
        self._replaying = True
        try:
            for stream, payload in journal.records(state.journal_segment if state is not None else 0):
                if stream not in self._journal_streams:
                    failed += 1
                    continue
                source = self._journal_streams[stream][0]
                before = collections.Counter(source.rejected_reasons)
                if self._call(lambda data: self._replay_record(stream, data), payload,
                              what=f"journal replay of {stream}", entry=source):
                    replayed += 1
                elif source.rejected_reasons != before:  # counted on the source, under its reason
                    refused.update(source.rejected_reasons - before)
                else:
                    failed += 1
        finally:
            self._replaying = False
        self._persistence.replayed = replayed
        self._persistence.journal_records = replayed
        self._journal_cost_s = time.monotonic() - started  # those records are still to replay after another crash
        if replayed or failed or journal.torn:
            self.logger.info("replayed %d journal record(s) in %.2f s (%d failed, %d torn)", replayed,
                             self._journal_cost_s, failed, journal.torn)
        if refused:
            reasons = ", ".join(f"{reason}: {count}" for reason, count in sorted(refused.items()))
            self._persistence.note = self._persistence.note or one_line(
                f"journal {journal.directory}: {sum(refused.values())} record(s) refused ({reasons}), not applied")
            self.logger.warning("journal %s: %d record(s) refused by their inputs' checks (%s), not applied",
                                journal.directory, sum(refused.values()), reasons)
        if self._journal_streams:  # a worker that journals nothing gets no journal
            self._journal = journal
            try:
                journal.open()
            except OSError as error:  # a full or read-only disk: the worker runs, its first snapshot opens one
                self._journal_lost = True
                self.write_failed("journal", error, "journaling stopped until a state snapshot is written")

    def _state_exists(self) -> bool:
        """A snapshot or journal segments to restore (read before setup: its inputs hold their frames then)."""
        path = self.state_path
        return path is not None and (path.exists() or bool(Journal(path.with_suffix(".journal")).segments()))

    def _state_holds(self, value) -> dict[str, dict[tuple[str, str], int]]:
        """A snapshot's newest stamps per input and stream (StateError if malformed: a file is untrusted)."""
        def stream(item) -> tuple[tuple[str, str], int]:
            if not (isinstance(item, list) and len(item) == 3 and isinstance(item[0], str)
                    and isinstance(item[1], str) and type(item[2]) is int and item[2] >= 0):
                raise StateError(f"{STATE_HOLDS}: expected [robot, stream, stamp_ns], got {str(item)[:60]}")
            return (item[0], item[1]), item[2]

        if not isinstance(value, dict) or not all(isinstance(v, list) for v in value.values()):
            raise StateError(f"{STATE_HOLDS}: expected a mapping of inputs to lists, got {str(value)[:60]}")
        return {str(name): dict(stream(item) for item in items[:MAX_STREAMS_PER_INPUT])
                for name, items in value.items()}

    def _ask_history(self) -> None:
        """After the restore: each recoverable input the journal records asks the publishers' caches for what its
        state does not hold (from about the newest stamp it holds of each stream), if the state holds any of it; the
        others (a worker started empty, an input whose frames the journal does not record) ask for nothing, as a
        worker never stopped."""
        journaled = {id(source) for source, _ in self._journal_streams.values()}
        for entry in self._inputs:
            if entry.history is not None:
                ask = id(entry) in journaled and bool(entry.journaled)
                entry.state_holds = dict(entry.journaled) if ask else {}
                entry.history.start(ask, entry.state_holds)

    def _replay_record(self, stream: str, payload: bytes) -> None:
        source, apply = self._journal_streams[stream]
        frame = decode(payload, expected=source.frame_type)
        source.accept(frame)
        apply(frame)
        if isinstance(source, Input):
            source.note_journaled((frame.header.robot, frame.header.stream, frame.header.stamp_ns))

    def _watch_log_writes(self) -> None:
        """A log line the disk refuses (the log is the process's stderr, a file on the same disk as the outputs)
        makes the worker ``degraded`` with ``cannot write <log file>: <reason>`` until a line is written again;
        logging's own complaint would go to the same file, so it is not printed."""
        def failed(handler, _record) -> None:
            error = sys.exc_info()[1]
            if not isinstance(error, OSError):
                return logging.StreamHandler.handleError(handler, _record)
            try:
                name = os.readlink(f"/proc/self/fd/{handler.stream.fileno()}")
            except (OSError, AttributeError, ValueError):
                name = "its log"
            self.write_failed(LOG_WRITES, OSError(error.errno, error.strerror, name))

        def flushed(handler, flush) -> None:
            flush()  # the last step of a line's emit: it got through
            if LOG_WRITES in self._write_failing:
                self.write_succeeded(LOG_WRITES)

        for handler in logging.getLogger().handlers:
            if isinstance(handler, logging.StreamHandler):
                handler.handleError = functools.partial(failed, handler)
                handler.flush = functools.partial(flushed, handler, handler.flush)

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        signals_seen = []

        def on_signal(signum, _frame):
            signals_seen.append(signum)
            if len(signals_seen) > 1:
                os._exit(128 + signum)  # second signal: the user insists
            self.logger.info("signal %s: stopping", signal.Signals(signum).name)
            self._stopping.set()
            # No lock here: the signal may interrupt a thread that holds it; waits use short timeouts.

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)

    def _write_config_snapshot(self) -> None:
        snapshot = self.config.model_dump(mode="json")
        self.logger.info("config %s", json.dumps(snapshot, sort_keys=True))
        if self.config.run_dir:
            path = Path(self.config.run_dir) / f"{self.name}.config.json"
            try:
                replace_text(path, json.dumps({"kind": self.kind, "config": snapshot}, indent=2, sort_keys=True) + "\n")
            except OSError as error:  # a record for the operator (also in the log, above): the worker runs without
                self._note_error(f"config snapshot not written: cannot write {error.filename}: {error.strerror}")
