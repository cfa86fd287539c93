"""Acceptance: rerun output read back with rerun's API; MCAP record + replay keeps payloads and timing."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import rerun as rr
from mcap.reader import make_reader

from tests.service.conftest import free_port, make_image_folder, read_jsonl, wait_until

pytestmark = pytest.mark.service


def test_rerun_save_has_one_image_row_per_frame(tmp_path, procs):
    make_image_folder(tmp_path / "images", 30)
    rrd = tmp_path / "run.rrd"
    camera = procs.semloc("worker", "camera", "--hub", f"tcp/127.0.0.1:{free_port()}", "--robot", "r1",
                          "--set", f"source={tmp_path / 'images'}", "--set", "rate=200", "--rerun-save", str(rrd),
                          "--set", "rerun.recording_id=test-recording", name="camera")
    assert camera.wait(60) == 0, procs.log("camera")
    reader = rr.chunk.RrdReader(str(rrd))
    assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("semloc", "test-recording")]
    assert len(reader.blueprints()) == 1  # the viewer layout (tests/service/test_rerun_viewer.py checks its views)
    rows: dict[str, int] = {}
    for chunk in reader.stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows.get("/r1/camera/image") == 30


def test_record_and_replay_keep_payloads_and_timing(tmp_path, procs, hub):
    make_image_folder(tmp_path / "images", 200, shape=(12, 16, 3))
    session_file = tmp_path / "session.mcap"
    key = "semloc/r1/camera/front/image"
    recorder = procs.semloc("record", "--listen", hub, "-k", key, "-o", str(session_file), "--count", "200",
                            name="record")
    camera = procs.play(hub, tmp_path / "images", 50)
    assert recorder.wait(60) == 0, procs.log("record")
    assert camera.wait(30) == 0, procs.log("camera")
    with open(session_file, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert [s.name for s in summary.schemas.values()] == ["semloc.Image"]
        original = [(m.log_time, m.data) for _, _, m in reader.iter_messages(log_time_order=True)]
    assert len(original) == 200

    sink_log = tmp_path / "sink.jsonl"
    hub2 = f"tcp/127.0.0.1:{free_port()}"
    sink = procs.semloc("worker", "sink", "--listen", hub2, "--robot", "r1", "--set", f"key={key}", "--set",
                        f"log_path={sink_log}", name="sink")
    replay = procs.semloc("replay", str(session_file), "--connect", hub2, "--wait-for-subscribers", "20",
                          name="replay")
    assert replay.wait(60) == 0, procs.log("replay")
    received = wait_until(lambda: (r := read_jsonl(sink_log)) and len(r) >= 200 and r, 20, message="200 frames")
    assert sink.poll() is None
    assert [r["sha256"] for r in received] == [hashlib.sha256(data).hexdigest() for _, data in original]

    original_gaps = np.diff([t for t, _ in original]) * 1e-9
    replay_gaps = np.diff([r["received_ns"] for r in received]) * 1e-9
    assert abs(np.median(replay_gaps) / np.median(original_gaps) - 1) < 0.2
    span_ratio = replay_gaps.sum() / original_gaps.sum()
    assert abs(span_ratio - 1) < 0.2
    # Most individual gaps within 20 % too (a shared 2-core machine may delay a few).
    assert np.mean(np.abs(replay_gaps - original_gaps) <= 0.2 * np.median(original_gaps)) > 0.8


def test_a_recording_killed_and_cut_short_replays_every_frame_before_the_cut(tmp_path, procs, hub):
    """The power cut while `semloc record` writes: the recorder is SIGKILLed (no summary) and the file then loses
    its tail mid-chunk (the unflushed pages). `semloc replay` publishes every frame whole before the cut, in order,
    byte for byte, says once where the file stopped, and exits 0."""
    import signal
    import subprocess
    import sys

    from services.recording import read_messages

    make_image_folder(tmp_path / "images", 80, shape=(48, 64, 3))  # 9.3 KB frames: 256 KiB chunks of 28
    session_file = tmp_path / "session.mcap"
    key = "semloc/r1/camera/front/image"
    recorder = procs.semloc("record", "--listen", hub, "-k", key, "-o", str(session_file), name="record")
    camera = procs.play(hub, tmp_path / "images", 50)
    assert camera.wait(30) == 0, procs.log("camera")
    wait_until(lambda: session_file.stat().st_size > 512 << 10, 10, message="two chunks written")
    recorder.send_signal(signal.SIGKILL)
    recorder.wait(10)
    data = session_file.read_bytes()
    published = [payload for _, _, payload in read_messages(session_file)]  # the whole chunks a kill leaves
    assert len(published) >= 56
    cut = len(data) - (100 << 10)  # mid-chunk: the last chunk's first frames are whole, the rest lost
    session_file.write_bytes(data[:cut])
    intact = [payload for payload in published if data.find(payload) + len(payload) <= cut]
    assert 0 < len(intact) < len(published)

    sink_log = tmp_path / "sink.jsonl"
    hub2 = f"tcp/127.0.0.1:{free_port()}"
    procs.semloc("worker", "sink", "--listen", hub2, "--robot", "r1", "--set", f"key={key}", "--set",
                 f"log_path={sink_log}", name="sink")
    replay = subprocess.run([sys.executable, "-m", "services.cli", "replay", str(session_file), "--connect", hub2,
                             "--wait-for-subscribers", "20"], capture_output=True, text=True, timeout=60)
    assert replay.returncode == 0, replay.stderr
    received = wait_until(lambda: (r := read_jsonl(sink_log)) and len(r) >= len(intact) and r, 20,
                          message=f"{len(intact)} frames")
    assert [r["sha256"] for r in received] == [hashlib.sha256(p).hexdigest() for p in intact]
    warnings = [line for line in replay.stderr.splitlines() if "was cut short" in line]
    assert len(warnings) == 1 and str(session_file) in warnings[0] and f"read its {len(intact)} complete" in warnings[0]


def test_a_replay_whose_wait_for_subscribers_ends_names_the_keys_nobody_hears(tmp_path, procs, hub):
    """`--wait-for-subscribers` into a graph listening on other keys (another camera name, robot, a graph not up
    yet): once the wait is over the replay names the keys without a subscriber, once, and plays; the key that has
    one gets every frame. It once played to nobody without a word."""
    import subprocess
    import sys

    from schemas import Ack, Header, encode
    from services.bus import BusConfig, open_session
    from services.recording import Recorder

    heard, unheard = "semloc/r1/test/acks", "semloc/r1/side/acks"
    recording = tmp_path / "session.mcap"
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        recorder = Recorder(session, "semloc/**", recording)
        for seq in range(10):
            for key in (heard, unheard):
                session.put(key, encode(Ack(header=Header(robot="r1", stream=key, seq=seq), ok=True)))
        wait_until(lambda: recorder.count == 20, 10, message="20 messages recorded")
        recorder.close()
    sink_log = tmp_path / "sink.jsonl"
    procs.semloc("worker", "sink", "--listen", hub, "--robot", "r1", "--set", f"key={heard}", "--set",
                 f"log_path={sink_log}", name="sink")
    with open_session(BusConfig(connect=[hub])) as session:  # the sink listens before the replay's wait begins
        probe = session.declare_publisher(heard)
        wait_until(lambda: probe.matching_status.matching, 30, message="the sink subscribed")
        probe.undeclare()
    replay = subprocess.run([sys.executable, "-m", "services.cli", "replay", str(recording), "--connect", hub,
                             "--wait-for-subscribers", "10"], capture_output=True, text=True, timeout=60)
    assert replay.returncode == 0, replay.stderr
    wait_until(lambda: len(read_jsonl(sink_log)) >= 10, 20, message="10 frames")
    [warning] = [line for line in replay.stderr.splitlines() if "no subscriber" in line]
    assert f"no subscriber for {unheard} (1 of 2 keys) after 10 s" in warning and heard not in warning, warning


def test_a_replay_says_which_running_worker_publishes_its_keys_too(tmp_path, procs, hub):
    """`semloc record -o session.mcap && semloc replay session.mcap` next to the graph that made it: the running
    camera publishes the recorded image key itself, so its subscribers would get both runs' frames interleaved. The
    replay names the worker and the key at its start, and plays; a replay of keys no worker publishes says nothing.
    It once said nothing either way (a localizer's 'lost on the way' then counted the seq jumps between the runs)."""
    import subprocess
    import sys

    from schemas import Ack, Header, encode
    from services.bus import BusConfig, open_session
    from services.recording import Recorder

    make_image_folder(tmp_path / "images", 20)
    image, acks = "semloc/r1/camera/front/image", "semloc/r1/test/acks"
    procs.semloc("worker", "camera", "--listen", hub, "--robot", "r1", "--set", f"source={tmp_path / 'images'}",
                 "--set", "rate=20", "--set", "loop=true", "--log-level", "WARNING", name="camera")
    recording = tmp_path / "session.mcap"
    with open_session(BusConfig(connect=[hub])) as session:
        recorder = Recorder(session, "semloc/r1/**", recording)
        for seq in range(5):
            session.put(acks, encode(Ack(header=Header(robot="r1", stream=acks, seq=seq), ok=True)))
        wait_until(lambda: recorder.count >= 30, 60, message="images recorded")
        recorder.close()

    def replay(*args: str) -> list[str]:
        result = subprocess.run([sys.executable, "-m", "services.cli", "replay", str(recording), "--connect", hub,
                                 "--speed", "20", *args], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        return [line for line in result.stderr.splitlines() if "also publishes" in line]

    [warning] = replay()
    assert "r1/camera also publishes" in warning and image in warning and acks not in warning, warning
    assert replay("-k", acks) == []
