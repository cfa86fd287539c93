"""Record bus traffic to MCAP and replay it with the original timing.

MCAP layout: one channel per (key expression, frame schema); the channel's topic is the key, its schema is named
after the frame type (``semloc.Image``...) with encoding ``jsonschema`` and the exported JSON Schema as data;
messages keep the exact wire bytes (``message_encoding: semloc``, docs/wire.md). ``log_time`` is the reception
time (ns), ``publish_time`` the frame's capture stamp. Payloads that are not semloc frames are kept too, on a
schemaless channel with ``message_encoding: octet-stream``. With ``foxglove=True`` the frames Foxglove can show are
also written in Foxglove's schemas on channels of their own (services/foxglove.py), which replay skips.
"""

from __future__ import annotations

import glob
import logging
import os
import re
import struct
import threading
import time
from fnmatch import fnmatchcase
from pathlib import Path

import msgpack
import zenoh
from mcap.writer import CompressionType, Writer

from schemas import FrameError, Status, keys, lookup
from schemas.export import frame_json_schema
from services.bus import NumberedPublisher, QueryError, query
from services.cut_files import CutFileError, mcap_channels, mcap_messages

log = logging.getLogger("semloc.recording")

MESSAGE_ENCODING = "semloc"
RAW_ENCODING = "octet-stream"
DEFAULT_REPLAY_EXCLUDE = (keys.ALL_STATUS,)
LIVE_QUERY_S = 2.0  # replay asks the running workers for their outputs this long at most (a loaded machine)
DRAIN_TIMEOUT_S = 30.0  # a closing subscriber waits this long at most for its callbacks on what was queued


class DrainedSubscribers:
    """Subscribers whose :meth:`close` returns once their callbacks have run on every sample that arrived before.

    zenoh runs a callback on a thread of its own through an unbounded queue, which can still hold samples when the
    subscriber is undeclared; it calls the handler's drop function once that queue is empty. Undeclaring alone
    returns at once, so a closing recorder lost those samples and a closing collector counted on after it returned.
    """

    def __init__(self, session: zenoh.Session):
        self._session = session
        self._declared: list[tuple[zenoh.Subscriber, threading.Event]] = []

    def declare(self, key: str, callback) -> None:
        drained = threading.Event()
        subscriber = self._session.declare_subscriber(key, zenoh.handlers.Callback(callback, drained.set))
        self._declared.append((subscriber, drained))

    def close(self, timeout_s: float = DRAIN_TIMEOUT_S) -> bool:
        """Undeclare all, then wait (``timeout_s`` in all) for their queues; False if one was still busy."""
        declared, self._declared = self._declared, []
        for subscriber, drained in declared:
            try:
                subscriber.undeclare()
            except Exception:  # the session is closing: it drops the handlers itself
                drained.set()
        deadline = time.monotonic() + timeout_s
        return all(drained.wait(max(0.0, deadline - time.monotonic())) for _, drained in declared)


def _frame_identity(payload: bytes) -> tuple[str, int, int] | None:
    """(schema, version, stamp_ns) of a semloc frame, without decoding its arrays; None if it is not a frame."""
    try:
        (length,) = struct.unpack_from("<I", payload, 0)
        if length > len(payload) - 4:
            return None
        body = msgpack.unpackb(memoryview(payload)[4 : 4 + length], raw=False)
        stamp = body.get("header", {}).get("stamp_ns", 0)
        return str(body["schema"]), int(body["version"]), int(stamp) if isinstance(stamp, int) else 0
    except Exception:
        return None


class _WholeRecords:
    """A recording's file, written a batch of MCAP records at a time (the writer's chunks) without buffering: a batch
    the disk refuses is cut off again, so the file always ends with whole records."""

    def __init__(self, path: Path):
        self._file = open(path, "wb", buffering=0)  # noqa: SIM115 - closed in close()
        self._end = 0

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        try:
            written = 0
            while written < len(view):
                written += self._file.write(view[written:])
        except OSError:
            self._file.truncate(self._end)
            self._file.seek(self._end)
            raise
        self._end += len(view)
        return len(view)

    def tell(self) -> int:
        return self._end

    def flush(self) -> None:
        pass

    def close(self) -> None:
        try:
            os.fsync(self._file.fileno())  # a closed split is on the disk: a power cut after it loses only later ones
        finally:
            self._file.close()


def split_name(folder: Path, index: int) -> Path:
    """The ``index``-th split of a recording folder: ``<folder>/<folder name>_<index>.mcap`` (ros2 bag's naming)."""
    return folder / f"{folder.name}_{index}.mcap"


def recording_files(path: str | Path) -> list[Path]:
    """The MCAP files of a recording in the order they were written: a file alone, or the splits of a folder
    (``<name>_<N>.mcap``, by N; splits deleted by ``--keep`` leave their successors in order). [] when a folder holds
    no split."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    numbered = [(int(match.group(1)), file) for file in path.glob(f"{glob.escape(path.name)}_*.mcap")
                if (match := re.fullmatch(re.escape(path.name) + r"_(\d+)\.mcap", file.name))]
    return [file for _, file in sorted(numbered)]


class Recorder:
    """Subscribe to ``key`` and write every sample to an MCAP file until :meth:`close`.

    Split (``split_bytes`` and/or ``split_s`` set): ``path`` (a trailing ``.mcap`` dropped) is a folder of numbered
    complete MCAP files, :func:`split_name`; a split is finished (summary, fsync) and the next begun once it holds
    ``split_bytes`` or spans ``split_s`` of reception time, so a power cut loses at most the open split's unflushed
    tail. ``keep``: at most this many splits stay, the open one included (the oldest closed ones are deleted;
    ``deleted`` counts them). ``files``: the splits on disk, oldest first.

    A write the disk refuses (full, read-only) ends the recording there: the file keeps every chunk written before
    (``read_messages`` reads an unfinished file's complete chunks), ``error`` says why (``cannot write <file>:
    <reason>``) and ``lost`` counts the messages that arrived since (those of the chunk being written, up to 256 KiB,
    are in ``count`` but not in the file); nothing raises. Writing on after a failed write could leave a chunk cut
    short before the later ones."""

    def __init__(self, session: zenoh.Session, key: str, path: str | Path, compress: bool = False,
                 foxglove: bool = False, split_bytes: int | None = None, split_s: float | None = None,
                 keep: int | None = None):
        if (split_bytes is not None and split_bytes <= 0) or (split_s is not None and split_s <= 0):
            raise ValueError("a split size and duration must be positive")
        if keep is not None and (keep < 1 or (split_bytes is None and split_s is None)):
            raise ValueError("keep needs a split size or duration, and is at least 1")
        self.split_bytes, self.split_s, self.keep = split_bytes, split_s, keep
        self.splitting = split_bytes is not None or split_s is not None
        path = Path(path)
        self.folder = path.with_suffix("") if self.splitting and path.suffix == ".mcap" else path
        if self.splitting and self.folder.is_dir() and recording_files(self.folder):
            # its splits would be replayed with this recording's
            raise FileExistsError(f"{self.folder} already holds a recording ({recording_files(self.folder)[0].name})")
        if not self.splitting and path.is_dir():
            raise IsADirectoryError(f"{path} is a folder: name the file (e.g. {path / 'session.mcap'}), or split the "
                                    "recording into it (--split)")
        if not self.splitting and path.exists():  # opening it for writing would empty an earlier recording
            raise FileExistsError(f"{path} already exists: a recording is never written over (remove it, or name "
                                  "another file)")
        self.files: list[Path] = []
        self.deleted = 0
        self._compression = CompressionType.ZSTD if compress else CompressionType.NONE
        # Small chunks: a recorder killed without finishing the file loses at most the last 256 KiB of messages
        # (and a small split holds several of them, so it ends near its size).
        self._chunk_size = min(256 << 10, max(4 << 10, (split_bytes or 1 << 30) // 8))
        self._lock = threading.Lock()
        self._sequence: dict[tuple[str, str], int] = {}  # per channel, continued across splits
        self.count = 0
        self.lost = 0  # messages not recorded: they arrived after a failed write
        self.error = ""
        self.closed = False
        self.foxglove = foxglove  # Foxglove-readable copies of the frames (services/foxglove.py)
        try:
            self._open(split_name(self.folder, 0) if self.splitting else path, time.time_ns())
        except OSError as error:  # a read-only or full disk, a file where the folder goes: one line, no traceback
            where = f"{error.filename}: " if error.filename and Path(error.filename) != self.path else ""  # a folder
            raise OSError(error.errno, f"cannot write {self.path}: {where}{error.strerror or error}") from None
        # A plain callback: its queue is unbounded, which is what a recorder wants (never drop); close() waits for
        # it, so the messages that arrived before are in the file.
        self._subscribers = DrainedSubscribers(session)
        self._subscribers.declare(key, self._on_sample)

    def _open(self, path: Path, now_ns: int) -> None:
        """Begin file ``path``: schemas and channels are registered again in each (every split reads alone)."""
        self.path = path
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = _WholeRecords(self.path)
        self.files.append(self.path)
        self._writer = Writer(self._stream, chunk_size=self._chunk_size, compression=self._compression)
        self._writer.start(profile="", library="semloc")
        self._opened_ns = now_ns
        self._schemas: dict[tuple[str, int], int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._foxglove_schemas: dict[str, int] = {}  # schema ids by name
        self._foxglove_channels: dict[str, int] = {}  # channel ids by topic

    def _split_due(self, now_ns: int) -> bool:
        return self.splitting and (
            (self.split_bytes is not None and self._stream.tell() >= self.split_bytes)
            or (self.split_s is not None and now_ns - self._opened_ns >= self.split_s * 1e9))

    def _next_split(self, now_ns: int) -> None:
        """Finish the open split and begin the next; delete the oldest beyond ``keep``."""
        self._writer.finish()
        self._stream.close()
        index = int(self.path.stem.rsplit("_", 1)[1]) + 1
        self._open(split_name(self.folder, index), now_ns)
        while self.keep is not None and len(self.files) > self.keep:
            self.files.pop(0).unlink(missing_ok=True)
            self.deleted += 1

    def _schema_id(self, name: str, version: int) -> int:
        if (name, version) not in self._schemas:
            try:
                import json

                data = json.dumps(frame_json_schema(lookup(name, version))).encode()
            except Exception:
                data = b""
            self._schemas[(name, version)] = self._writer.register_schema(name=name, encoding="jsonschema", data=data)
        return self._schemas[(name, version)]

    def _on_sample(self, sample) -> None:
        received = time.time_ns()
        payload = sample.payload.to_bytes()
        topic = str(sample.key_expr)
        identity = _frame_identity(payload)
        with self._lock:
            if self.closed:
                return
            if self.error:
                self.lost += 1
                return
            try:
                if self._split_due(received):
                    self._next_split(received)
                self._write(topic, payload, identity, received)
            except OSError as error:
                self.lost += 1
                self._failed(error)

    def _failed(self, error: OSError) -> None:
        self.error = f"cannot write {self.path}: {error.strerror or error}"
        log.error("%s: the recording ends after %d messages", self.error, self.count)

    def _write(self, topic: str, payload: bytes, identity, received: int) -> None:
        if identity is None:
            channel_key = (topic, "")
            if channel_key not in self._channels:
                self._channels[channel_key] = self._writer.register_channel(topic, RAW_ENCODING, 0)
            publish_time = received
        else:
            name, version, stamp = identity
            channel_key = (topic, f"{name}.v{version}")
            if channel_key not in self._channels:
                self._channels[channel_key] = self._writer.register_channel(
                    topic, MESSAGE_ENCODING, self._schema_id(name, version))
            publish_time = stamp or received
        sequence = self._sequence.get(channel_key, 0)
        self._sequence[channel_key] = sequence + 1
        self._writer.add_message(self._channels[channel_key], log_time=received, data=payload,
                                 publish_time=publish_time, sequence=sequence)
        self.count += 1
        if self.foxglove and identity is not None:
            self._add_foxglove(topic, payload, received)

    def _add_foxglove(self, key: str, payload: bytes, received: int) -> None:
        """The frame's Foxglove messages, on their own channels (a frame that does not decode gets none)."""
        from schemas import decode
        from services.foxglove import foxglove_messages, message_encoding

        try:
            frame = decode(payload)
        except FrameError:
            return
        for topic, message in foxglove_messages(key, frame):
            if topic not in self._foxglove_channels:
                schema = message.get_schema()
                if schema.name not in self._foxglove_schemas:
                    self._foxglove_schemas[schema.name] = self._writer.register_schema(
                        name=schema.name, encoding=schema.encoding, data=bytes(schema.data))
                self._foxglove_channels[topic] = self._writer.register_channel(
                    topic, message_encoding(schema.encoding), self._foxglove_schemas[schema.name])
            self._writer.add_message(self._foxglove_channels[topic], log_time=received, data=message.encode(),
                                     publish_time=frame.header.stamp_ns or received)

    def close(self) -> None:
        if not self._subscribers.close():
            log.warning("%s: closed with messages still queued for it after %.0f s", self.path, DRAIN_TIMEOUT_S)
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                if not self.error:
                    self._writer.finish()
            except OSError as error:
                self._failed(error)
            finally:
                self._stream.close()


def read_messages(path: str | Path, include: tuple[str, ...] = ("**",), exclude: tuple[str, ...] = (),
                  warn: bool = True):
    """(topic, log_time_ns, payload) of every message of a recording (an MCAP file, or a folder of splits read one
    after the other: :func:`recording_files`), each file in log-time order, read as it is consumed.

    A file cut short (recorder killed, power cut: no summary) gives its complete messages in file order, with one
    warning saying where it stopped; a damaged chunk of a finished file is skipped with one warning naming it
    (services/cut_files.py; ``warn=False``: neither, for a look at the first message before the reading). Raises
    :class:`CutFileError` for a file that is not MCAP, or is cut before its first complete message, and for a folder
    holding no split."""
    files = recording_files(path)
    if not files:
        raise CutFileError(f"{path}: no recording in it (no {Path(path).name}_<N>.mcap)")
    for file in files:
        for _schema, channel, message in mcap_messages(file, on_cut=lambda cut: warn and log.warning("%s", cut)):
            # semloc's own channels only: Foxglove copies (semloc record --foxglove) are not republished
            if channel.message_encoding in (MESSAGE_ENCODING, RAW_ENCODING) and _selected(channel.topic, include,
                                                                                         exclude):
                yield channel.topic, message.log_time, message.data


def _key_match(pattern: str, topic: str) -> bool:
    """zenoh-like matching: ``*`` = exactly one chunk, ``**`` = any number of chunks (including none)."""

    def match(p: list[str], t: list[str]) -> bool:
        if not p:
            return not t
        if p[0] == "**":
            return any(match(p[1:], t[i:]) for i in range(len(t) + 1))
        return bool(t) and (p[0] == "*" or fnmatchcase(t[0], p[0])) and match(p[1:], t[1:])

    return match(pattern.split("/"), topic.split("/"))


def _selected(topic: str, include, exclude) -> bool:
    return any(_key_match(p, topic) for p in include) and not any(_key_match(p, topic) for p in exclude)


def is_split_recording(path: str | Path) -> bool:
    """A folder of ``semloc record --split`` splits (a ROS 2 bag folder names its files the same way: its first
    file holds no semloc frame)."""
    from services.camera_sources import is_semloc_recording

    files = recording_files(path) if Path(path).is_dir() else []
    return bool(files) and is_semloc_recording(files[0])


def is_robot_log(path: str | Path) -> bool:
    """A ROS 1 bag, a ROS 2 bag (folder or .db3) or a ROS 2 MCAP file (not a ``semloc record`` session)."""
    from services.camera_sources import SourceError, classify, is_semloc_recording

    if is_split_recording(path):
        return False
    try:
        kind = classify(str(path))
    except SourceError:
        return False
    return kind == "bag" or (kind == "mcap" and not is_semloc_recording(Path(path)))


def robot_log_messages(path: str | Path, robot: str, camera: str = "front", topic: str | None = None,
                       topics=None, model_period_ns: int = 1_000_000_000):
    """(key, stamp_ns, payload) of the semloc frames a robot log becomes, in the log's image order and timing: the
    camera worker's frames of each image (image, odometry, ground truth; ``capture_frames``) and, from the log's
    CameraInfo, the CameraModel before the first image and again every ``model_period_ns`` of log time."""
    from schemas import Header, encode
    from schemas import keys as semloc_keys
    from services.camera_sources import open_source
    from services.frames import camera_model_frame, capture_frames

    keys = {"image": semloc_keys.camera_image(robot, camera), "model": semloc_keys.camera_model(robot, camera),
            "odometry": semloc_keys.odometry(robot), "groundtruth_pose": semloc_keys.groundtruth_pose(robot),
            "groundtruth_pose2d": semloc_keys.groundtruth_pose2d(robot)}
    sequence = dict.fromkeys(keys, 0)

    def header(name: str, stamp: int, frame_id: str) -> Header:
        sequence[name] += 1
        return Header(robot=robot, stream=keys[name], seq=sequence[name] - 1, stamp_ns=stamp, frame_id=frame_id)

    source = open_source(str(path), "bag" if Path(path).is_dir() else "auto", topic=topic, log=topics)
    source.on_skip = lambda _why, detail: log.warning("%s", detail)  # a recording cut short says where, once
    log.info("replaying %s", source.description)
    model_due = None
    try:
        for capture in source:
            stamp = int(capture.stamp_ns)
            if source.camera is not None and (model_due is None or stamp >= model_due):
                model = camera_model_frame(source.camera, header("model", stamp, "body"), name=camera)
                yield keys["model"], stamp, encode(model)
                model_due = stamp + model_period_ns
            for name, frame in capture_frames(capture, stamp, header, frame_id=camera):
                yield keys[name], stamp, encode(frame)
    finally:
        source.close()


def _published_live(session: zenoh.Session, topics) -> dict[str, list[str]]:
    """The keys of ``topics`` each running worker publishes itself (its Status lists its outputs), by worker."""
    try:
        statuses = query(session, keys.ALL_STATUS, reply_type=Status, timeout=LIVE_QUERY_S, every_reply=True)
    except (QueryError, FrameError):  # a worker that answers badly is not ours to judge here
        return {}
    live = {}
    for status in statuses:
        if status.state not in ("stopping", "stopped") and (
                clashing := sorted({o.key for o in status.outputs.values()} & set(topics))):
            live[f"{status.header.robot}/{status.worker}"] = clashing
    return live


def replay(session: zenoh.Session, path: str | Path, *, speed: float = 1.0, include: tuple[str, ...] = ("**",),
           exclude: tuple[str, ...] = DEFAULT_REPLAY_EXCLUDE, wait_for_subscribers_s: float = 0.0,
           stop: threading.Event | None = None, loop: bool = False, robot_log: dict | None = None) -> int:
    """Republish the messages of ``path`` with their original spacing divided by ``speed``; returns the count.
    ``robot_log``: ``path`` is a ROS log, replayed as the semloc frames of :func:`robot_log_messages` (called with
    these arguments), read as it plays."""
    if speed <= 0:
        raise ValueError("speed must be positive")
    stop = stop or threading.Event()
    # numbered: a subscriber tells two replays of one key (or a replay and a worker) apart
    publishers: dict[str, NumberedPublisher] = {}
    declare = lambda topic: NumberedPublisher(  # noqa: E731
        session.declare_publisher(topic, congestion_control=zenoh.CongestionControl.BLOCK))
    if robot_log is None:
        # Read as it plays, a split at a time: a long recording set need not fit in memory.
        first = next(read_messages(path, include, exclude, warn=False), None)  # the reading below says what it lost
        recorded = [first] if first else []
        topics = {channel.topic for file in recording_files(path) for channel, _schema in mcap_channels(file)
                  if channel.message_encoding in (MESSAGE_ENCODING, RAW_ENCODING)
                  and _selected(channel.topic, include, exclude)}
        messages = lambda: read_messages(path, include, exclude)  # noqa: E731
    else:
        first = next(robot_log_messages(path, **robot_log), None)
        recorded = [first] if first else []
        topics = {first[0]} if first else set()
        messages = lambda: (m for m in robot_log_messages(path, **robot_log)  # noqa: E731
                            if _selected(m[0], include, exclude))
    if not recorded:
        log.warning("nothing to replay in %s", path)
        return 0
    for topic in topics:
        publishers[topic] = declare(topic)
    for worker, clashing in _published_live(session, topics).items():
        # two publishers on a stream: its subscribers see both runs' frames interleaved, out of order
        log.warning("%s also publishes %s now: the replayed frames and its own will interleave (replay only what no "
                    "running worker publishes: -k, --exclude)", worker, ", ".join(clashing))
    deadline = time.monotonic() + wait_for_subscribers_s
    while wait_for_subscribers_s and time.monotonic() < deadline and not stop.is_set():
        if all(p.publisher.matching_status.matching for p in publishers.values()):
            break
        time.sleep(0.02)
    if wait_for_subscribers_s and not stop.is_set() and (
            unheard := sorted(topic for topic, p in publishers.items() if not p.publisher.matching_status.matching)):
        # a graph with other key names (another camera or robot), or not up yet: its frames reach nobody
        log.warning("no subscriber for %s (%d of %d keys) after %g s: replaying anyway, what is sent on %s reaches "
                    "nobody", ", ".join(unheard), len(unheard), len(publishers), wait_for_subscribers_s,
                    "it" if len(unheard) == 1 else "them")
    sent = 0
    while not stop.is_set():
        first = recorded[0][1]
        start = time.monotonic()
        for topic, log_time, payload in messages():
            if topic not in publishers:
                publishers[topic] = declare(topic)
            target = start + (log_time - first) * 1e-9 / speed
            while True:
                remaining = target - time.monotonic()
                if remaining <= 0 or stop.is_set():
                    break
                # Sleep most of the wait, spin the last millisecond: the VM's timer slack is ~0.6 ms.
                time.sleep(remaining - 0.001 if remaining > 0.002 else 0)
            if stop.is_set():
                break
            publishers[topic].put(payload)
            sent += 1
        if not loop:
            break
    for numbered in publishers.values():
        numbered.publisher.undeclare()
    return sent
