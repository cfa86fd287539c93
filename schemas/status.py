"""Runtime frames: ``Status`` (a worker's periodic counters) and ``Ack`` (a generic reply to a command query)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from schemas.base import Frame, Sub

Count = Annotated[int, Field(ge=0)]
WorkerState = Literal["starting", "running", "stopping", "stopped"]


class InputStats(Sub):
    key: str
    policy: Literal["latest", "lossless"]
    received: Count = 0
    processed: Count = 0
    dropped: Count = 0
    rejected: Count = 0
    rejected_reasons: dict[str, Count] = Field(default_factory=dict, description="rejected, per FrameError.reason")
    errors: Count = 0
    queued: Count = 0


class OutputStats(Sub):
    key: str
    published: Count = 0


class Status(Frame, schema="semloc.Status", version=1, max_bytes=1 << 20):
    """Counters of one worker since it started. ``received`` = payloads that arrived; ``rejected`` = payloads
    that failed decoding or validation (``schemas.FrameError``); ``dropped`` = frames discarded by a full
    ``latest`` queue; ``errors`` = exceptions raised by the worker's handlers; ``processed`` = handler calls that
    returned. Latency = time from arrival to the end of the handler, over the last 1,000 frames."""

    worker: str
    kind: str
    state: WorkerState
    pid: Count
    host: str = ""
    started_ns: Count
    uptime_s: Annotated[float, Field(ge=0)]
    received: Count = 0
    processed: Count = 0
    dropped: Count = 0
    rejected: Count = 0
    errors: Count = 0
    queries: Count = 0
    latency_p50_ms: float | None = None
    latency_p95_ms: float | None = None
    inputs: dict[str, InputStats] = Field(default_factory=dict)
    outputs: dict[str, OutputStats] = Field(default_factory=dict)
    last_error: Annotated[str, Field(max_length=4096)] = ""


class Ack(Frame, schema="semloc.Ack", version=1, max_bytes=64 << 10):
    """A reply to a command query (e.g. relocalize): whether it was accepted, and why not."""

    ok: bool
    message: Annotated[str, Field(max_length=4096)] = ""
