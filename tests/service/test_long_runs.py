"""A robot running for weeks does not fill its disk with semloc's files: `semloc record` splits (and keeps the newest
N), node logs rotate, rerun save files rotate, each bounded and each still readable."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from mcap.reader import make_reader

from schemas import decode
from services.camera_sources import open_source
from services.recording import read_messages, recording_files
from tests.service.conftest import free_port, make_image_folder, read_jsonl, wait_until

pytestmark = pytest.mark.service

KEY = "semloc/r1/camera/front/image"
FRAMES = 120


def _splits_of(folder) -> list[list[bytes]]:
    """Each split's payloads, read with the mcap library alone: each must be a complete file (summary)."""
    splits = []
    for file in recording_files(folder):
        with open(file, "rb") as stream:
            reader = make_reader(stream)
            assert reader.get_summary() is not None, f"{file} is not a finished MCAP file"
            splits.append([m.data for _, _, m in reader.iter_messages(log_time_order=True)])
    return splits


def test_record_splits_by_size_keeps_the_newest_and_replays_the_set_in_order(tmp_path, procs, hub):
    """Two `semloc record --split 0.2MB` of one camera run (9.3 KB frames, 1.1 MB in all): every split a complete
    MCAP file named <name>_<N>.mcap, at least 3, near the split size, holding together every frame once in order;
    with --keep 2 only the two newest stay, the last frames. `semloc replay FOLDER` publishes the set as one session:
    every frame once, in order, byte for byte, its timing kept across the splits; the camera worker's source plays it
    too."""
    make_image_folder(tmp_path / "images", FRAMES, shape=(48, 64, 3))
    whole, kept = tmp_path / "whole", tmp_path / "kept.mcap"  # a trailing .mcap names the folder without it
    first = procs.semloc("record", "--listen", hub, "-k", KEY, "-o", str(whole), "--split", "0.2MB", "--count",
                         str(FRAMES), name="record")
    second = procs.semloc("record", "--connect", hub, "-k", KEY, "-o", str(kept), "--split", "0.2MB", "--keep",
                          "2", "--count", str(FRAMES), name="record_keep")
    wait_until(lambda: "recording" in procs.log("record") and "recording" in procs.log("record_keep"), 30,
               message="both recorders subscribed")
    camera = procs.play(hub, tmp_path / "images", 40)
    assert camera.wait(60) == 0, procs.log("camera")
    assert first.wait(30) == 0, procs.log("record")
    assert second.wait(30) == 0, procs.log("record_keep")

    splits = _splits_of(whole)
    names = [file.name for file in recording_files(whole)]
    assert names == [f"whole_{index}.mcap" for index in range(len(names))] and len(names) >= 3
    sizes = [file.stat().st_size for file in recording_files(whole)]
    assert all(size < 0.2e6 + (64 << 10) for size in sizes), sizes  # the size, and at most a chunk past it
    recorded = [payload for split in splits for payload in split]
    seqs = [decode(payload).header.seq for payload in recorded]
    assert seqs == list(range(FRAMES))  # every frame once, in order, across the splits
    assert [payload for _, _, payload in read_messages(whole)] == recorded
    source = open_source(str(whole))  # the camera worker plays the set too
    assert [capture.stamp_ns for capture in source] == [decode(p).header.stamp_ns for p in recorded]

    kept_folder = tmp_path / "kept"
    kept_files = recording_files(kept_folder)
    assert len(kept_files) == 2 and not (kept_folder / "kept_0.mcap").exists()
    indexes = [int(file.stem.rsplit("_", 1)[1]) for file in kept_files]
    assert indexes[1] == indexes[0] + 1 and indexes[0] >= 1
    tail = [decode(payload).header.seq for split in _splits_of(kept_folder) for payload in split]
    assert tail == list(range(FRAMES - len(tail), FRAMES)) and 0 < len(tail) < FRAMES

    sink_log = tmp_path / "sink.jsonl"
    hub2 = f"tcp/127.0.0.1:{free_port()}"
    procs.semloc("worker", "sink", "--listen", hub2, "--robot", "r1", "--set", f"key={KEY}", "--set",
                 f"log_path={sink_log}", name="sink")
    replay = procs.semloc("replay", str(whole), "--connect", hub2, "--wait-for-subscribers", "20", name="replay")
    assert replay.wait(60) == 0, procs.log("replay")
    assert f"replayed {FRAMES} messages" in procs.log("replay")
    received = wait_until(lambda: (r := read_jsonl(sink_log)) and len(r) >= FRAMES and r, 20,
                          message=f"{FRAMES} frames")
    assert [r["sha256"] for r in received] == [hashlib.sha256(p).hexdigest() for p in recorded]
    log_times = [t for _, t, _ in read_messages(whole)]
    original_span = (log_times[-1] - log_times[0]) * 1e-9
    replay_span = (received[-1]["received_ns"] - received[0]["received_ns"]) * 1e-9
    assert abs(replay_span / original_span - 1) < 0.2, (replay_span, original_span)


def test_record_splits_by_duration_and_refuses_a_folder_holding_splits(tmp_path, session):
    """Recorder(split_s=0.3) taking 40 messages over 1.2 s: at least 3 complete splits, each spanning less than 0.3 s
    of reception time, every message once in order across them; a second recorder into the same folder is refused
    (its splits would be replayed with the first's)."""
    import time

    from services.recording import Recorder

    payloads = [bytes([index]) * 1000 for index in range(40)]
    recorder = Recorder(session, "semloc/r1/**", tmp_path / "timed", split_s=0.3)
    for payload in payloads:
        session.put("semloc/r1/test/blob", payload)
        time.sleep(0.03)
    wait_until(lambda: recorder.count == len(payloads), 20, message="every message taken")
    recorder.close()
    splits = _splits_of(tmp_path / "timed")
    assert len(splits) >= 3 and [p for split in splits for p in split] == payloads
    for file in recording_files(tmp_path / "timed"):
        times = [t for _, t, _ in read_messages(file)]
        assert times[-1] - times[0] < 0.3e9, file
    with pytest.raises(FileExistsError):
        Recorder(session, "semloc/r1/**", tmp_path / "timed", split_s=0.3)


def test_a_recorder_closed_at_once_keeps_what_arrived_before(tmp_path, session):
    """zenoh hands the samples to the recorder's callback through a queue of its own: closed right after the last
    publication, the recorder still writes every message (it once lost those queued, e.g. the Foxglove test's
    object map put just before its close)."""
    from services.recording import Recorder

    payloads = [bytes([index]) * 10_000 for index in range(200)]
    recorder = Recorder(session, "semloc/r1/**", tmp_path / "at-once.mcap")
    for payload in payloads:
        session.put("semloc/r1/test/blob", payload)
    recorder.close()
    assert [payload for _, _, payload in read_messages(tmp_path / "at-once.mcap")] == payloads


def test_the_demo_collector_closed_at_once_has_counted_what_arrived_before(session):
    """The demo's collector shares the recorder's close: 200 images put, then closed at once while its display hook
    (1 ms an image, as a viewer's logging) is behind, are all counted and shown when close() returns, and none after
    (it only undeclared, and counted on while zenoh emptied the callback queue)."""
    import time

    from schemas import Header, Image, encode, keys
    from schemas.camera import camera_image
    from services.demo_collector import Collector

    pixels = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    frames = [encode(Image(header=Header(robot="r1", seq=seq, stamp_ns=(seq + 1) * 1000),
                           images=[camera_image(pixels)])) for seq in range(200)]
    shown = []
    collector = Collector(session, "r1", on_image=lambda stamp, _: (shown.append(stamp), time.sleep(0.001)))
    for frame in frames:
        session.put(keys.camera_image("r1", "front"), frame)
    collector.close()
    counted = (collector.images.count, len(collector.images.arrivals), len(shown))
    time.sleep(0.5)
    assert counted == (collector.images.count, len(collector.images.arrivals), len(shown)) == (200, 200, 200)


def test_node_logs_stay_bounded_and_keep_the_crash(tmp_path, procs, hub):
    """A node that warns 2,000 times (300 KB), writes a line straight to its fd 2 and fails, three times (a restart
    loop), under `logs: {max_mb: 0.05, keep: 2}`: its log and two rotated files stay, each within the bound (and a
    pipe read past it), no third; the last one ends with the whole traceback and the raw line; the launcher names
    the failure (what `semloc status` shows) from it."""
    import yaml

    from tests.service.chatty_worker import RAW_LINE

    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump({"name": "logs", "robot": "r1", "hub": hub, "logs": {"max_mb": 0.05, "keep": 2},
                                     "restart": {"max_restarts": 2, "backoff_s": 0.1},
                                     "nodes": {"chatty": {"worker": "tests.service.chatty_worker"}}}))
    launcher = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    assert launcher.wait(120) is not None
    logs = tmp_path / "run" / "logs"
    assert sorted(path.name for path in logs.iterdir()) == ["chatty.log", "chatty.log.1", "chatty.log.2"]
    for path in logs.iterdir():
        assert path.stat().st_size <= 50_000, path
    last = (logs / "chatty.log").read_text()
    assert "Traceback (most recent call last)" in last and last.count("RuntimeError: chatty failure after 2000 "
                                                                      "lines") >= 1
    assert RAW_LINE.decode() in last
    assert procs.log("launcher").count("RuntimeError: chatty failure after 2000 lines") >= 3  # each exit's reason


def test_a_rotated_log_reads_by_offset_across_its_files(tmp_path):
    """`semloc logs` asks by offset: after rotations, any offset still kept reads exactly the bytes written from
    there (across the files), an older one from the oldest byte kept; the files never hold more than keep + 1."""
    from services.node_logs import LogPolicy, NodeLog

    (tmp_path / "n.log").write_bytes(b"an earlier launcher's line\n")
    node_log = NodeLog(tmp_path / "n.log", LogPolicy(max_mb=0.001, keep=2))
    written = b"an earlier launcher's line\n"
    rng = np.random.default_rng(3)
    for index in range(300):
        data = b"".join(b"line %d.%d\n" % (index, part) for part in range(int(rng.integers(1, 12))))
        node_log.write(data)
        written += data
    assert node_log.end == len(written)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["n.log", "n.log.1", "n.log.2"]
    kept = sum(path.stat().st_size for path in tmp_path.iterdir())
    assert all(path.read_bytes().endswith(b"\n") for path in tmp_path.iterdir())  # rotated at a line's end
    first, data = node_log.read(0, node_log.end)
    assert first == len(written) - kept and data == written[first:]
    for start in (first, first + 1, len(written) - 500, len(written) - 1):
        assert node_log.read(start, start + 300) == (start, written[start:start + 300])
    assert node_log.read(len(written), len(written) + 10) == (len(written), b"")


def _rrd_contents(path):
    """(recording ids, blueprints, {entity: non-static rows}, static entity paths) of an .rrd read with rerun (the
    recording's properties, its start time among them, are the static entity ``/__properties``)."""
    import rerun as rr

    reader = rr.chunk.RrdReader(str(path))
    rows, static = {}, set()
    for chunk in reader.stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
        else:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return [r.recording_id for r in reader.recordings()], len(reader.blueprints()), rows, static


def _start_time(path) -> int | None:
    """The recording's start time (ns) in an .rrd's properties, the last one sent; None when it has none."""
    import rerun as rr

    started = None
    for chunk in rr.chunk.RrdReader(str(path)).stream():
        if chunk.entity_path == "/__properties" and "RecordingInfo:start_time" in chunk.to_record_batch().schema.names:
            started = chunk.to_record_batch().column("RecordingInfo:start_time").to_pylist()[-1][0]
    return started


def test_rerun_save_rotates_within_its_budget_each_file_whole(tmp_path, procs):
    """The camera worker saving to rerun with `rerun.max_mb=0.9` in 3 files (JPEG frames of 58 KB, 7 MB in all):
    <worker>.rrd, <worker>.1.rrd ...: 3 stay, each within its share, a frame and the layout; each has the run's
    recording id and the layout; together they hold the last frames, each once."""
    make_image_folder(tmp_path / "images", FRAMES, shape=(240, 320, 3))
    folder = tmp_path / "rrd"
    camera = procs.semloc("worker", "camera", "--hub", f"tcp/127.0.0.1:{free_port()}", "--robot", "r1",
                          "--set", f"source={tmp_path / 'images'}", "--set", "rate=100", "--rerun-save", str(folder),
                          "--set", "rerun.recording_id=long-run", "--set", "rerun.max_mb=0.9", "--set",
                          "rerun.files=3", name="camera")
    assert camera.wait(60) == 0, procs.log("camera")
    files = sorted(folder.iterdir(), key=lambda p: int(p.name.split(".")[1]) if p.name.count(".") == 2 else 0)
    assert len(files) == 3 and files[-1].name.startswith("camera.") and not (folder / "camera.rrd").exists()
    for file in files:  # its third of the budget, one frame past it (58 KB of JPEG noise) and the layout (60 KB)
        assert file.stat().st_size < 0.3e6 + 70_000 + 70_000, file
    images = 0
    for file in files:
        recordings, blueprints, rows, _static = _rrd_contents(file)
        assert recordings == ["long-run"] and blueprints == 1, file
        assert rows.get("/r1/camera/image", 0) > 0, file
        images += rows["/r1/camera/image"]
    assert 0 < images < FRAMES


def test_rerun_rotation_logs_the_static_entities_again_in_every_file(tmp_path):
    """rerun sends a static entity once, to the file open then: after rotation each file still has the map (its last
    value), the layout and the recording's properties (its start time), and the frames logged while it was open (60
    frames of 8 KB in files of 50 KB: all kept)."""
    import time

    import rerun as rr

    from services.viz import RerunConfig, open_recording

    config = RerunConfig(mode="save", path=str(tmp_path), recording_id="statics", max_mb=0.5, files=10)
    stream = open_recording(config, "localizer", "r1")
    stream.log("/r1/localizer/map/bounds", rr.Boxes2D(mins=[0, 0], sizes=[1, 1]), static=True)
    rng = np.random.default_rng(0)
    for frame in range(60):
        stream.set_time("frame", sequence=frame)
        stream.log("/r1/localizer/particles", rr.Points2D(rng.random((1000, 2))))
        if frame == 30:
            stream.log("/r1/localizer/map/bounds", rr.Boxes2D(mins=[0, 0], sizes=[2, 2]), static=True)
    stream.flush(timeout_sec=5.0)
    stream.disconnect()
    files = sorted(tmp_path.iterdir())
    assert len(files) >= 3
    frames = 0
    for file in files:
        recordings, blueprints, rows, static = _rrd_contents(file)
        assert recordings == ["statics"] and blueprints == 1, file
        assert {"/r1/localizer/map/bounds", "/__properties"} <= static, (file, static)
        frames += rows.get("/r1/localizer/particles", 0)
    assert frames == 60
    started = {_start_time(file) for file in files}  # each file says when the run began, the same time
    assert len(started) == 1 and abs(started.pop() - time.time_ns()) < 120e9, started
