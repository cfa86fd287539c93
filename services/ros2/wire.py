"""How ROS 2 topics sit on zenoh, in the two conventions semloc speaks (docs/ros2.md):

* ``rmw_zenoh`` - the middleware itself (ros2/rmw_zenoh, docs/design.md): a topic's key expression is
  ``<domain_id>/<fully qualified name without leading slash>/<DDS type name>/<type hash>``; every sample carries an
  attachment (sequence number and source timestamp as little-endian int64, then the 16-byte publisher GID with its
  length, zenoh's serializer layout; before Jazzy's 0.2.4, each field after its name); every node, publisher and
  subscription declares a liveliness token under ``@ros2_lv`` that the graph cache of ``ros2 topic list`` reads;
  the GID is XXH3-128 of the entity's token.
* ``bridge`` - zenoh-bridge-ros2dds: the key is the topic name without its leading slash (plus the bridge's own
  namespace, if it has one); the payload is the CDR sample as DDS carried it; no attachment, no tokens (the bridge
  discovers DDS readers and writers itself).

Payloads are CDR with the encapsulation header in both.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Literal

ADMIN_SPACE = "@ros2_lv"
CONVENTIONS = ("rmw_zenoh", "bridge")
Convention = Literal["rmw_zenoh", "bridge"]
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
# rmw_zenoh before ros2/rmw_zenoh#605 (Jazzy's 0.2.4) wrote each field after its name, a string in the same layout
FIELD_NAMES = tuple(bytes([len(name)]) + name for name in (b"sequence_number", b"source_timestamp", b"source_gid"))

# rmw/types.h enum values, and rmw_zenoh's defaults (rmw_zenoh_cpp/src/detail/qos.cpp): a QoS field equal to the
# default is left empty in the token.
RELIABILITY = {"reliable": 1, "best_effort": 2}
DURABILITY = {"transient_local": 1, "volatile": 2}
HISTORY = {"keep_last": 1, "keep_all": 2}
DEFAULT_QOS = {"reliability": "reliable", "durability": "volatile", "history": "keep_last", "depth": 42}
_NAME_RE = re.compile(r"^/?[A-Za-z_~{][A-Za-z0-9_/{}~]*$")


@dataclass(frozen=True)
class QoS:
    """The QoS of one endpoint (the part rmw_zenoh puts in its token; deadline, lifespan and liveliness stay at
    their defaults)."""

    reliability: Literal["reliable", "best_effort"] = "reliable"
    durability: Literal["volatile", "transient_local"] = "volatile"
    history: Literal["keep_last", "keep_all"] = "keep_last"
    depth: int = 10

    def keyexpr(self) -> str:
        """rmw_zenoh's ``qos_to_keyexpr``: ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:
        <lifespan s>,<ns>:<liveliness>,<lease s>,<ns>``, each field empty when it is rmw_zenoh's default."""
        def field(name: str, table: dict) -> str:
            value = getattr(self, name)
            return "" if value == DEFAULT_QOS[name] else str(table[value])

        depth = "" if self.depth == DEFAULT_QOS["depth"] else str(int(self.depth))
        return (f"{field('reliability', RELIABILITY)}:{field('durability', DURABILITY)}:"
                f"{field('history', HISTORY)},{depth}:,:,:,,")


def check_topic(name: str) -> str:
    """A ROS topic name (``/a/b`` or relative ``a/b``); ValueError otherwise."""
    if not _NAME_RE.match(name) or "//" in name or name.endswith("/"):
        raise ValueError(f"not a ROS topic name: {name!r}")
    return name


def qualified_name(topic: str, namespace: str = "") -> str:
    """The fully qualified name of ``topic``: absolute names stay, relative ones go under ``namespace``."""
    check_topic(topic)
    if topic.startswith("/"):
        return topic
    namespace = namespace.strip("/")
    return f"/{namespace}/{topic}" if namespace else f"/{topic}"


def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%`` (an empty name becomes ``%``)."""
    return name.replace("/", "%") if name else "%"


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the name DDS and rmw_zenoh use)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(convention: Convention, topic: str, msgtype: str = "", type_hash: str = "", domain_id: int = 0,
              namespace: str = "") -> str:
    """The zenoh key expression of a topic. rmw_zenoh: ``<domain>/<name>/<type>/<hash>`` (``*`` for an empty hash:
    a subscription that accepts every distribution's definition); bridge: the name without its leading slash."""
    name = qualified_name(topic, namespace).strip("/")
    if convention == "bridge":
        return name
    if convention != "rmw_zenoh":
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    return f"{int(domain_id)}/{name}/{dds_type_name(msgtype)}/{type_hash or '*'}"


def node_token(domain_id: int, session_id: str, node_id: int, node_name: str, namespace: str = "",
               enclave: str = "") -> str:
    """Liveliness token of a node: ``@ros2_lv/<domain>/<session>/<node id>/<node id>/NN/<enclave>/<namespace>/
    <name>`` (mangled names)."""
    return "/".join([ADMIN_SPACE, str(int(domain_id)), session_id, str(node_id), str(node_id), "NN", mangle(enclave),
                     mangle(_namespace(namespace)), mangle(node_name)])


def endpoint_token(kind: Literal["MP", "MS"], domain_id: int, session_id: str, node_id: int, entity_id: int,
                   node_name: str, topic: str, msgtype: str, type_hash: str, qos: QoS, namespace: str = "",
                   enclave: str = "") -> str:
    """Liveliness token of a publisher (``MP``) or subscription (``MS``): the node's fields, then the mangled fully
    qualified topic name, the DDS type name, the type hash and the QoS."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"endpoint kind must be MP or MS, got {kind!r}")
    return "/".join([ADMIN_SPACE, str(int(domain_id)), session_id, str(node_id), str(entity_id), kind,
                     mangle(enclave), mangle(_namespace(namespace)), mangle(node_name),
                     mangle(qualified_name(topic, namespace)), dds_type_name(msgtype), type_hash, qos.keyexpr()])


def _namespace(namespace: str) -> str:
    namespace = namespace.strip("/")
    return f"/{namespace}" if namespace else ""


def entity_gid(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives an entity: XXH3-128 of its liveliness token, low 64 bits then high 64 bits,
    each little-endian (``Entity::Entity`` in liveliness_utils.cpp)."""
    import xxhash

    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's publication attachment: sequence number and source timestamp (int64 little-endian), then the
    GID as a byte sequence (its length as one LEB128 byte, 16, then the bytes) - zenoh's serializer layout."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", int(sequence_number), int(source_timestamp_ns), GID_SIZE) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment, or of one of its earlier releases
    (each field after its name); ValueError if malformed."""
    data = _without_names(bytes(data))
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    sequence, stamp = struct.unpack_from("<qq", data)
    return sequence, stamp, bytes(data[17:])


def _without_names(data: bytes) -> bytes:
    """The fields of an attachment in the earlier layout without their names; any other ``data`` as it is."""
    fields, at = [], 0
    for name, size in zip(FIELD_NAMES, (8, 8, 1 + GID_SIZE)):
        if data[at:at + len(name)] != name:
            return data
        fields.append(data[at + len(name):at + len(name) + size])
        at += len(name) + size
    return b"".join(fields) if at == len(data) else data


class RosPublisher:
    """One ROS topic published on zenoh in either convention. rmw_zenoh: each sample carries the attachment, and a
    ``transient_local`` topic keeps its last ``depth`` samples for late subscribers (zenoh's advanced publisher,
    as rmw_zenoh does; it needs ``timestamping`` on in the zenoh config, else the topic is published volatile and a
    warning logged). ``reliable`` blocks under congestion, ``best_effort`` drops. Counters like a worker output."""

    def __init__(self, session, name: str, key: str, convention: Convention, qos: QoS, gid: bytes = bytes(16),
                 logger=None):
        import zenoh
        import zenoh.ext

        self.name, self.key, self.convention, self.qos, self.gid = name, key, convention, qos, gid
        congestion = (zenoh.CongestionControl.BLOCK if qos.reliability == "reliable"
                      else zenoh.CongestionControl.DROP)
        self.publisher = None
        if convention == "rmw_zenoh" and qos.durability == "transient_local":
            try:
                self.publisher = zenoh.ext.declare_advanced_publisher(
                    session, key, congestion_control=congestion, publisher_detection=True,
                    cache=zenoh.ext.CacheConfig(max_samples=max(1, qos.depth)))
            except zenoh.ZError as error:
                if logger is not None:
                    logger.warning("%s: published volatile (no history for late subscribers): %s", name, error)
        if self.publisher is None:
            self.publisher = session.declare_publisher(key, congestion_control=congestion)
        self.sequence = 0
        self.published = 0

    def put(self, payload: bytes) -> None:
        import time

        self.sequence += 1
        if self.convention == "rmw_zenoh":
            self.publisher.put(payload, attachment=attachment(self.sequence, time.time_ns(), self.gid))
        else:
            self.publisher.put(payload)
        self.published += 1

    def stats(self):
        from schemas import OutputStats

        return OutputStats(key=self.key, published=self.published)

    def undeclare(self) -> None:
        self.publisher.undeclare()
