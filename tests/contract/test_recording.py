"""MCAP reading helpers of record/replay: key filters, and salvaging a recording whose recorder was killed."""

from __future__ import annotations

import shutil

import pytest
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
