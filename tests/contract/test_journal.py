"""The journal of a stateful worker: records survive the writer, a torn or damaged record ends its segment, a
snapshot's segment boundary splits what it holds from what is replayed."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from services.journal import Journal
from semloc_core.io.atomic import remove_partial_writes
from services.state import State, StateError, load_state, save_state, set_aside
from tests.service.conftest import file_size_limit


def test_records_read_back_in_order_across_segments(tmp_path):
    journal = Journal(tmp_path / "j")
    assert journal.open() == 0
    journal.append("odom", b"a")
    journal.append("update", bytearray(b"bb" * 1000))
    second = journal.rotate()
    journal.append("odom", memoryview(b"c"))
    journal.close()
    assert second == 1 and journal.segments() == [0, 1]
    assert list(Journal(tmp_path / "j").records()) == [("odom", b"a"), ("update", b"bb" * 1000), ("odom", b"c")]
    assert list(Journal(tmp_path / "j").records(first_segment=1)) == [("odom", b"c")]
    journal = Journal(tmp_path / "j")
    assert journal.open() == 2  # a restarted writer goes on after the newest segment
    journal.discard_before(2)
    journal.close()
    assert journal.segments() == [2]


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_torn_or_damaged_record_ends_its_segment(tmp_path, damage):
    journal = Journal(tmp_path / "j")
    journal.open()
    for k in range(3):
        journal.append("s", bytes([k]) * 100)
    journal.close()
    path = tmp_path / "j" / "0000000000.journal"
    data = bytearray(path.read_bytes())
    if damage == "truncate":  # killed in the middle of the third write
        data = data[:-40]
    else:  # a flipped bit in the second record's payload
        data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    reader = Journal(tmp_path / "j")
    records = list(reader.records())
    assert records == [("s", bytes([k]) * 100) for k in range(2 if damage == "truncate" else 1)]
    assert reader.torn == 1


def test_records_outlive_the_writer_without_a_commit(tmp_path):
    """A SIGKILLed process never commits: what it wrote is in the kernel and must be read back."""
    pid = os.fork()
    if pid == 0:  # the child writes and dies without closing or syncing anything
        journal = Journal(tmp_path / "j", commit_period_s=60)
        journal.open()
        journal.append("s", b"x" * 10)
        os._exit(0)
    os.waitpid(pid, 0)
    assert list(Journal(tmp_path / "j").records()) == [("s", b"x" * 10)]


def test_snapshot_keeps_its_journal_position_and_set_aside_never_replaces(tmp_path):
    path = tmp_path / "w.npz"
    save_state(path, State({"a": np.arange(3)}, {"n": 3}, journal_segment=7))
    state = load_state(path)
    assert state.journal_segment == 7 and state.meta == {"n": 3} and set(state.arrays) == {"a"}
    with pytest.raises(ValueError, match="reserved"):
        save_state(path, State({"__journal__": np.zeros(1)}))
    first = set_aside([path, tmp_path / "missing"], stamp="T")
    assert first == [tmp_path / "w.npz.corrupt-T"] and not path.exists()
    path.write_bytes(b"garbage")
    with pytest.raises(StateError):
        load_state(path)
    second = set_aside([path], stamp="T")
    assert second == [tmp_path / "w.npz.corrupt-T-1"]
    assert load_state(first[0]).journal_segment == 7  # the first one is still there, whole


def test_partial_snapshot_writes_are_removed(tmp_path):
    path = tmp_path / "w.npz"
    save_state(path, State({"a": np.arange(3)}))
    (tmp_path / "w.npz.abc123.tmp").write_bytes(b"half")  # a process killed while writing the next snapshot
    (tmp_path / "other.npz.x.tmp").write_bytes(b"not ours")
    assert remove_partial_writes(path) == [tmp_path / "w.npz.abc123.tmp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.npz.x.tmp", "w.npz"]


def test_a_record_the_disk_refuses_leaves_the_segment_whole(tmp_path):
    """A full disk (here a file size limit) refuses a record half written: the append raises naming the segment and
    cuts off what it wrote, so the records written once the disk takes them again are read after the earlier ones."""
    journal = Journal(tmp_path / "j")
    journal.open()
    journal.append("odom", b"a" * 1000)
    with file_size_limit(2000), pytest.raises(OSError) as refused:
        journal.append("odom", b"b" * 5000)
    journal.append("odom", b"c")
    journal.close()
    reader = Journal(tmp_path / "j")
    assert list(reader.records()) == [("odom", b"a" * 1000), ("odom", b"c")] and reader.torn == 0
    assert refused.value.filename == str(tmp_path / "j" / "0000000000.journal")
    assert refused.value.errno == errno.EFBIG

