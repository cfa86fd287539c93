"""MCAP reading helpers of record/replay: key filters, and salvaging a recording whose recorder was killed."""

from __future__ import annotations

import shutil

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from services.recording import _key_match, read_messages


@pytest.mark.parametrize("pattern, topic, expected", [
    ("**", "semloc/r1/camera/front/image", True),
    ("semloc/*/camera/*/image", "semloc/r1/camera/front/image", True),
    ("semloc/*/image", "semloc/r1/camera/front/image", False),
    ("semloc/**", "semloc/r1/odom", True),
    ("semloc/*/*/status", "semloc/r1/camera/status", True),
    ("semloc/*/*/status", "semloc/r1/camera/front/status", False),
])
def test_key_match(pattern, topic, expected):
    assert _key_match(pattern, topic) is expected


def test_unfinished_recording_is_salvaged(tmp_path):
    path, copy = tmp_path / "full.mcap", tmp_path / "killed.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=64)
        writer.start()
        channel = writer.register_channel("semloc/r1/odom", "semloc", writer.register_schema("s", "jsonschema", b""))
        for index in range(20):
            writer.add_message(channel, log_time=index, data=b"%03d" % index * 10, publish_time=index)
        stream.flush()
        shutil.copy(path, copy)  # what a SIGKILLed recorder leaves: no summary, no footer
        writer.finish()
    full = list(read_messages(path))
    salvaged = list(read_messages(copy))
    assert len(full) == 20
    assert 10 <= len(salvaged) < 20 and salvaged == full[: len(salvaged)]
    assert list(read_messages(path, exclude=("semloc/*/odom",))) == []


def _recording(path, compression: str, count: int = 40):
    """A recording as `semloc record` writes it (the mcap writer, 64 KiB chunks here): ``count`` semloc Image frames
    of distinct random pixels; returns their wire bytes in order."""
    import numpy as np
    from mcap.writer import CompressionType

    from schemas import Header, Image, camera_image, encode

    rng = np.random.default_rng(7)
    payloads = [encode(Image(header=Header(robot="r1", seq=index, stamp_ns=10**9 + index),
                             images=[camera_image(rng.integers(0, 256, (40, 60, 3), dtype=np.uint8))]))
                for index in range(count)]
    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=64 << 10, compression=CompressionType[compression.upper()])
        writer.start(profile="", library="semloc")
        channel = writer.register_channel("semloc/r1/camera/front/image", "semloc",
                                          writer.register_schema("semloc.Image", "jsonschema", b"{}"))
        for index, payload in enumerate(payloads):
            writer.add_message(channel, log_time=index, data=payload, publish_time=index)
        writer.finish()
    return payloads


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_a_recording_cut_anywhere_gives_every_message_before_the_cut(tmp_path, compression, caplog):
    """A power cut loses the file's unflushed tail: the file cut at 9 offsets (in the header, inside chunks, inside
    the summary). Replay reads exactly the messages whole before the cut (uncompressed: every message whose bytes
    all precede the cut, the cut chunk's too; compressed: at least those of the whole chunks), in order, byte for
    byte, with one warning naming the file; the camera worker's source plays the same frames and counts the cut
    once."""
    import logging

    from services.camera_sources import open_source
    from services.cut_files import CUT_SHORT, CutFileError

    path = tmp_path / "full.mcap"
    payloads = _recording(path, compression)
    data = path.read_bytes()
    message_ends = [data.find(payload) + len(payload) for payload in payloads]  # uncompressed: in the clear
    with open(path, "rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    assert len(chunks) >= 4
    for fraction in (0.004, 0.05, 0.2, 0.37, 0.5, 0.66, 0.81, 0.93, 0.99):
        cut = int(len(data) * fraction)
        copy = tmp_path / f"cut{cut}.mcap"
        copy.write_bytes(data[:cut])
        caplog.clear()
        try:
            read = [payload for _, _, payload in read_messages(copy)]
        except CutFileError as error:
            read = []
            assert "before its first complete message" in str(error) and str(copy) in str(error)
        assert read == payloads[:len(read)]
        if compression == "none":
            assert len(read) == sum(end <= cut for end in message_ends), fraction
        else:  # log_time = index: the messages of the chunks whole before the cut, at least
            whole = [c.message_end_time + 1 for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
            begun = [c.message_end_time + 1 for c in chunks if c.chunk_start_offset < cut]
            assert max(whole, default=0) <= len(read) <= max(begun, default=0), fraction
        if read:
            assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
                f"{copy} was cut short (no MCAP summary): read its {len(read)} complete messages (the record at byte "
                f"{caplog.records[-1].getMessage().split('byte ')[1].split(' ')[0]} of its {cut} is not whole); "
                "the rest is lost"]
            source = open_source(str(copy))
            frames = [capture.stamp_ns for capture in source]
            assert frames == [10**9 + index for index in range(len(read))]
            assert source.skipped == {CUT_SHORT: 1}


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_damaged_chunk_of_a_finished_recording_is_skipped_and_said(tmp_path, compression, caplog):
    """Bytes flipped inside one chunk of a finished recording (a bad disk block, a bad copy): replay reads every
    other chunk's messages, in order, byte for byte, and says once which chunk it skipped and how many messages it
    held; the camera worker's source plays the same frames and counts it once. Unchecked, the flipped frame
    replayed as if recorded."""
    import logging

    from services.camera_sources import open_source
    from services.cut_files import DAMAGED

    path = tmp_path / "full.mcap"
    payloads = _recording(path, compression)
    with open(path, "rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    damaged = chunks[1]
    data = bytearray(path.read_bytes())
    middle = damaged.chunk_start_offset + damaged.chunk_length // 2
    data[middle:middle + 4] = bytes(b ^ 0xFF for b in data[middle:middle + 4])
    path.write_bytes(bytes(data))
    lost = range(damaged.message_start_time, damaged.message_end_time + 1)  # log_time = index
    kept = [payload for index, payload in enumerate(payloads) if index not in lost]
    caplog.clear()
    assert [payload for _, _, payload in read_messages(path)] == kept
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{path} is damaged: the chunk at byte {damaged.chunk_start_offset} ({damaged.chunk_length} bytes) does not "
        f"match its CRC; its {len(lost)} messages skipped, the rest read"]
    source = open_source(str(path))
    assert [capture.stamp_ns for capture in source] == [10**9 + i for i in range(len(payloads)) if i not in lost]
    assert source.skipped == {DAMAGED: 1}


def test_a_recording_cut_on_a_record_boundary_says_only_its_end_is_missing(tmp_path, caplog):
    """A file that ends right after a whole record (the recorder killed between two chunks) has no partial record:
    the warning says the file ends there, not that a record at its last byte is not whole."""
    import logging

    path = tmp_path / "full.mcap"
    payloads = _recording(path, "none")
    with open(path, "rb") as stream:
        second_chunk = make_reader(stream).get_summary().chunk_indexes[1].chunk_start_offset
    copy = tmp_path / "cut.mcap"
    copy.write_bytes(path.read_bytes()[:second_chunk])
    read = [payload for _, _, payload in read_messages(copy)]
    assert read == payloads[:len(read)] and read
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{copy} was cut short (no MCAP summary): read its {len(read)} complete messages (it ends after a whole "
        f"record, at byte {second_chunk}); the rest is lost"]
