"""The zenoh bus: session factory, typed publish and query helpers.

Embedded default (no endpoint given): peer mode on loopback, multicast scouting off, rendezvous at the *hub*
endpoint ``tcp/127.0.0.1:7447``: the first process to start listens on it, later ones listen on a free loopback
port and connect to it; zenoh's gossip then meshes the peers directly, so the hub may go away. ``semloc up`` is
the hub of its graph. For real deployments pass ``--connect/--listen/--mode`` or a zenoh config file
(deploy/zenoh-*.json5); STACK_NOTES explains why peers behind a router must be clients or have listen endpoints.

Pitfall handled here: a process that declared a Python-callback subscriber/queryable hangs at exit unless its
session is closed, so always use ``with open_session(...) as session`` (or close it in ``finally``).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from schemas import Frame, FrameError, decode, encode

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


def _zenoh_config(bus: BusConfig, listen: list[str], connect: list[str]) -> zenoh.Config:
    config = zenoh.Config.from_file(bus.zenoh_config) if bus.zenoh_config else zenoh.Config()
    config.insert_json5("mode", json.dumps(bus.mode))
    if not bus.zenoh_config or not bus.multicast:
        config.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    if bus.shared_memory is not None:
        config.insert_json5("transport/shared_memory/enabled", json.dumps(bus.shared_memory))
    if bus.lease_ms is not None:
        config.insert_json5("transport/link/tx/lease", json.dumps(int(bus.lease_ms)))
    return config


def open_session(bus: BusConfig | None = None) -> zenoh.Session:
    """Open a zenoh session as described by ``bus`` (see the module docstring for the embedded default)."""
    bus = bus or BusConfig()
    if bus.zenoh_config:
        if not Path(bus.zenoh_config).is_file():
            raise FileNotFoundError(f"zenoh config file not found: {bus.zenoh_config}")
        return zenoh.open(_zenoh_config(bus, list(bus.listen), list(bus.connect)))
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
    return zenoh.open(_zenoh_config(bus, listen, connect))


def bus_from_env(bus: BusConfig | None = None) -> BusConfig:
    """Apply SEMLOC_CONNECT / SEMLOC_LISTEN (comma-separated), SEMLOC_MODE, SEMLOC_ZENOH_CONFIG to ``bus``."""
    bus = bus or BusConfig()
    update = {}
    for field, var in (("connect", "SEMLOC_CONNECT"), ("listen", "SEMLOC_LISTEN")):
        if os.environ.get(var):
            update[field] = [e.strip() for e in os.environ[var].split(",") if e.strip()]
    if os.environ.get("SEMLOC_MODE"):
        update["mode"] = os.environ["SEMLOC_MODE"]
    if os.environ.get("SEMLOC_ZENOH_CONFIG"):
        update["zenoh_config"] = os.environ["SEMLOC_ZENOH_CONFIG"]
    return BusConfig.model_validate({**bus.model_dump(), **update})


def add_bus_arguments(parser) -> None:
    """``--mode/--connect/--listen/--zenoh-config/--hub`` for commands that open a session."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh mode (default peer)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")
    group.add_argument("--hub", metavar="ENDPOINT", help=f"rendezvous endpoint (default {DEFAULT_HUB})")


def bus_from_args(args, base: BusConfig | None = None) -> BusConfig:
    bus = bus_from_env(base)
    update = {}
    for field in ("mode", "connect", "listen", "zenoh_config", "hub"):
        value = getattr(args, field, None)
        if value:
            update[field] = value
    return BusConfig.model_validate({**bus.model_dump(), **update})


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
) -> list[Frame]:
    """Ask every queryable matching ``key`` and return the decoded replies.

    Raises :class:`QueryError` when every answer was an error reply, :class:`schemas.FrameError` when a reply does
    not decode (or is not of ``reply_type``). No answer within ``timeout`` gives an empty list."""
    kwargs = {"timeout": float(timeout)}
    if request is not None:
        kwargs["payload"] = encode(request)
    frames = []
    errors = []
    for reply in session.get(key, **kwargs):
        if reply.ok is not None:
            frames.append(decode(reply.ok.payload.to_bytes(), expected=reply_type))
        else:
            errors.append(reply.err.payload.to_string())
    if errors and not frames:
        raise QueryError(f"query {key} failed: {'; '.join(errors)}")
    return frames


class QueryError(RuntimeError):
    """Every queryable that answered replied with an error."""


__all__ = [
    "BusConfig",
    "DEFAULT_HUB",
    "FrameError",
    "QueryError",
    "add_bus_arguments",
    "bus_from_args",
    "bus_from_env",
    "open_session",
    "publish",
    "query",
]
