"""Recordings and robot logs cut short: a recorder killed, or the power cut while it wrote (the unflushed tail of
the file lost too). One reading rule per format; each takes every record intact up to the cut and says where it
stopped (:class:`Cut`), once, through its caller.

* MCAP (``semloc record`` sessions, ROS 2 ``.mcap`` logs): a file without summary is read record by record in file
  order; a chunk cut short gives the complete messages it holds (uncompressed, zstd or lz4: decompressed as far as its
  bytes go); a whole chunk whose CRC does not match ends the reading there (damage, not a cut).
* rosbag2 sqlite3 (``.db3``): a database shorter than its header says (a torn last transaction) is read row by row
  in the order written, up to the first page that is missing.

A folder ``ros2 bag record`` left without ``metadata.yaml`` (it writes it last) is read from its storage files:
services/ros2/logs.py.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

from semloc_core.io.errors import FileFormatError

CUT_SHORT = "recording cut short"  # the reason a source counts a recording cut short under (Source.skip)
DAMAGED = "recording damaged"  # ... and a damaged chunk of a finished one
MCAP_MAGIC = b"\x89MCAP0\r\n"
_HEADER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _DATA_END, _FOOTER = 0x01, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x02
_CHUNK_HEADER = struct.Struct("<QQQIL")  # start, end, uncompressed size, uncompressed crc, compression's length


class CutFileError(FileFormatError):
    """A file cut before its first complete message: nothing in it can be read."""


@dataclass
class Cut:
    """Where the reading of a file cut short stopped: ``messages`` complete messages read, ``stopped_at`` the byte
    offset of the first record not whole (None: not known by byte), ``why`` what was missing."""

    path: Path
    why: str
    messages: int = 0
    stopped_at: int | None = None

    @property
    def size(self) -> int:
        return self.path.stat().st_size

    def __str__(self) -> str:
        size = self.size
        if self.stopped_at is None:
            where = f"{size} bytes"
        elif self.stopped_at >= size:  # cut on a record's boundary: only the file's end (its summary) is missing
            where = f"it ends after a whole record, at byte {size}"
        else:
            where = f"the record at byte {self.stopped_at} of its {size} is not whole"
        return f"{self.path} was cut short ({self.why}): read its {self.messages} complete messages ({where}); " \
               "the rest is lost"


@dataclass
class Damage:
    """A chunk of a finished MCAP file that cannot be read as written (its CRC does not match, or it does not
    decompress or parse): its ``messages`` (None: not known) are skipped, the chunks after it read."""

    path: Path
    offset: int
    length: int
    why: str
    messages: int | None = None

    def __str__(self) -> str:
        count = "its messages" if self.messages is None else f"its {self.messages} messages"
        return f"{self.path} is damaged: the chunk at byte {self.offset} ({self.length} bytes) {self.why}; " \
               f"{count} skipped, the rest read"


# ----------------------------------------------------------------------------------------------------------- MCAP

def mcap_summary(path: Path):
    """The summary of an MCAP file, or None (no summary: a file cut short); raises :class:`CutFileError` for a file
    that does not start with the MCAP magic."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise CutFileError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        stream.seek(0)
        try:
            return make_reader(stream).get_summary()
        except Exception:  # the mcap reader raises several unrelated types on a file without its end
            return None


def mcap_library(path: str | Path) -> str | None:
    """The library an MCAP file's header names (``semloc`` for ``semloc record``), None without a whole header."""
    with open(path, "rb") as stream:
        data = stream.read(len(MCAP_MAGIC) + 9 + (1 << 12))
    try:
        opcode, length, profile = struct.unpack_from("<BQI", data, len(MCAP_MAGIC))
        if not data.startswith(MCAP_MAGIC) or opcode != _HEADER or length > len(data):
            return None
        at = len(MCAP_MAGIC) + 13 + profile
        (size,) = struct.unpack_from("<I", data, at)
        return data[at + 4:at + 4 + size].decode() if at + 4 + size <= len(MCAP_MAGIC) + 9 + length else None
    except (struct.error, UnicodeDecodeError):
        return None


def mcap_records(path: Path, cut: Cut):
    """The Schema, Channel and Message records (mcap.records) of an MCAP file without summary, in file order, up to
    the first record that is not whole; ``cut`` counts the messages and says where it stopped."""
    from mcap.records import Channel, Message, Schema

    parse = {_SCHEMA: lambda s, n: Schema.read(s), _CHANNEL: lambda s, n: Channel.read(s), _MESSAGE: Message.read}
    with open(path, "rb") as stream:
        stream.seek(len(MCAP_MAGIC))
        offset, size = len(MCAP_MAGIC), cut.size
        while True:
            head = stream.read(9)
            if len(head) < 9:
                break
            opcode, length = struct.unpack("<BQ", head)
            body = stream.read(min(length, max(0, size - offset - 9)))
            whole = len(body) == length
            if opcode == _CHUNK:
                records, whole = _chunk_records(body, whole)
            else:
                records = [(opcode, body)] if whole else []
            for inner, data in records:
                if inner in parse:
                    try:
                        record = parse[inner](_data_stream(data), len(data))
                    except Exception:  # a record of the right length but other bytes: damage ends the reading
                        whole = False
                        break
                    cut.messages += inner == _MESSAGE
                    yield record
            if not whole or opcode in (_DATA_END, _FOOTER):
                break
            offset += 9 + length
        cut.stopped_at = offset


def _data_stream(data: bytes):
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(data))


def _chunk_records(body: bytes, whole: bool) -> tuple[list[tuple[int, bytes]], bool]:
    """The whole records of a chunk's body (all of it or its beginning), and whether the chunk was whole and sound."""
    if len(body) < _CHUNK_HEADER.size:
        return [], False
    _start, _end, size, crc, name_length = _CHUNK_HEADER.unpack_from(body)
    at = _CHUNK_HEADER.size + name_length + 8
    compression = body[_CHUNK_HEADER.size:at - 8].decode(errors="replace")
    data = body[at:]
    try:
        if compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif compression == "lz4":
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif compression:
            return [], False
    except Exception:  # a compressed stream cut mid-block: what was decompressed before it is gone too
        return [], False
    if whole and (len(data) != size or (crc and zlib.crc32(data) != crc)):
        return [], False  # a chunk of the right length but other bytes: damaged, not cut
    records, position = [], 0
    while position + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, position)
        if position + 9 + length > len(data):
            return records, False
        records.append((opcode, data[position + 9:position + 9 + length]))
        position += 9 + length
    return records, whole and position == len(data)


def mcap_messages(path: str | Path, on_cut=None, on_damage=None):
    """(schema, channel, message) of every message of an MCAP file: in log-time order from a finished file, each
    chunk's CRC checked (a damaged chunk is skipped, ``on_damage(Damage)``, else ``on_cut``, said once for it); from
    a file cut short (no summary), every complete one in file order, then ``on_cut(Cut)`` once. Raises
    :class:`CutFileError` for a file that is not MCAP or is cut before its first complete message."""
    from mcap.reader import make_reader

    path = Path(path)
    summary = mcap_summary(path)
    if summary is not None and summary.chunk_indexes:
        yield from _checked_messages(path, summary, on_damage or on_cut)
        return
    if summary is not None:  # unchunked: no CRC to check
        with open(path, "rb") as stream:
            yield from make_reader(stream).iter_messages(log_time_order=True)
        return
    cut = Cut(path, "no MCAP summary")
    schemas, channels = {}, {}
    for record in mcap_records(path, cut):
        kind = type(record).__name__
        if kind == "Schema":
            schemas[record.id] = record
        elif kind == "Channel":
            channels[record.id] = record
        elif record.channel_id in channels:
            channel = channels[record.channel_id]
            yield schemas.get(channel.schema_id), channel, record
    if not cut.messages:
        raise CutFileError(f"{path} was cut short (no MCAP summary) before its first complete message, at byte "
                           f"{cut.stopped_at} of {cut.size}: nothing to read")
    if on_cut is not None:
        on_cut(cut)


def _checked_messages(path: Path, summary, on_damage):
    """The messages of a finished MCAP file in log-time order, as the mcap reader gives them, but each chunk's CRC
    checked: bytes flipped on a disk or in a copy would otherwise replay as frames nobody can tell from the real."""
    from mcap.data_stream import ReadDataStream
    from mcap.reader import breakup_chunk, make_message_queue
    from mcap.records import Chunk, ChunkIndex, Message

    queue = make_message_queue(log_time_order=True, reverse=False)
    for chunk_index in summary.chunk_indexes:
        queue.push(chunk_index)
    with open(path, "rb") as stream:
        while queue:
            item = queue.pop()
            if not isinstance(item, ChunkIndex):
                yield item[0]
                continue
            try:
                stream.seek(item.chunk_start_offset)
                if stream.read(1) != bytes([_CHUNK]):
                    raise ValueError("is not a chunk")
                stream.seek(8, 1)
                records = breakup_chunk(Chunk.read(ReadDataStream(stream)), validate_crc=True)
            except Exception as error:  # CRC, decompression, a length past the end: one chunk lost, not the file
                why = "does not match its CRC" if "crc" in type(error).__name__.lower() else f"cannot be read ({error})"
                if on_damage is not None:
                    on_damage(Damage(path, item.chunk_start_offset, item.chunk_length, why,
                                     _indexed_messages(stream, item)))
                continue
            for index, record in enumerate(records):
                if isinstance(record, Message) and record.channel_id in summary.channels:
                    channel = summary.channels[record.channel_id]
                    queue.push(((summary.schemas.get(channel.schema_id), channel, record), item.chunk_start_offset,
                                index))


def _indexed_messages(stream, chunk_index) -> int | None:
    """How many messages a chunk holds, from its message indexes (None: they cannot be read either)."""
    try:
        count = 0
        for offset in chunk_index.message_index_offsets.values():
            stream.seek(offset)
            opcode, _length, _channel, entries = struct.unpack("<BQHI", stream.read(15))
            if opcode != 0x07:
                return None
            count += entries // 16
        return count
    except (OSError, struct.error):
        return None


def mcap_channels(path: str | Path):
    """(channel, schema or None) of every channel of an MCAP file, as a generator (stop early to read less of a long
    file cut short): its summary's, or those a file cut short declares before the cut, as the file declares them."""
    path = Path(path)
    summary = mcap_summary(path)
    if summary is not None:
        yield from ((channel, summary.schemas.get(channel.schema_id)) for channel in summary.channels.values())
        return
    schemas = {}
    for record in mcap_records(path, Cut(path, "no MCAP summary")):
        if type(record).__name__ == "Schema":
            schemas[record.id] = record
        elif type(record).__name__ == "Channel":
            yield record, schemas.get(record.schema_id)


# ----------------------------------------------------------------------------------------------- rosbag2 sqlite3

def sqlite_bag_rows(path: str | Path, cut: Cut):
    """(topic_id, timestamp_ns, data) of the messages of a rosbag2 ``.db3``, in the order written, up to the first
    page a cut lost; ``cut.messages`` counts them, and ``cut.why`` says where a database that ends early ended."""
    import sqlite3

    connection = _open_sqlite(Path(path))
    try:
        rows = connection.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id")
        while True:
            try:
                row = next(rows)
            except StopIteration:
                return
            except sqlite3.DatabaseError as error:
                cut.why = f"sqlite: {error} after its message {cut.messages}"
                return
            cut.messages += 1
            yield row
    finally:
        connection.close()


def sqlite_bag_topics(path: str | Path) -> list[tuple[int, str, str]]:
    """(id, name, type) of the topics of a rosbag2 ``.db3``; :class:`CutFileError` when they cannot be read."""
    import sqlite3

    connection = _open_sqlite(Path(path))
    try:
        return [tuple(row) for row in connection.execute("SELECT id, name, type FROM topics ORDER BY id")]
    except sqlite3.DatabaseError as error:
        raise CutFileError(f"{path}: cannot read its topics ({error})") from None
    finally:
        connection.close()


def _open_sqlite(path: Path):
    import sqlite3

    try:
        connection = sqlite3.connect(f"{path.resolve().as_uri()}?immutable=1", uri=True)
        # Read only (immutable), so nothing is written; writable_schema makes SQLite take a file shorter than its
        # header's page count (a cut) instead of calling the whole database malformed.
        connection.execute("PRAGMA writable_schema=ON")
    except sqlite3.DatabaseError as error:
        raise CutFileError(f"{path}: not a database SQLite can open ({error})") from None
    return connection
