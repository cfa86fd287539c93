"""A disk that stops taking writes mid-run (full, read-only, a file size limit): real worker processes over zenoh
on loopback, the failure injected with RLIMIT_FSIZE set on the running worker (``prlimit``: no root needed; Python
ignores SIGXFSZ, so a write past the limit fails with EFBIG "File too large" as a full disk fails with ENOSPC).

The worker keeps serving, says which file it cannot write and why, never leaves a partial file in place of a whole
one, and writes again by itself once the limit is lifted."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import yaml
import zenoh

from schemas import Ack, Header, Status, encode, keys
from schemas.localization import PoseEstimate
from semloc_core.io.semantic_map import load_semantic_map
from semloc_core.io.trajectory import read_tum
from semloc_core.io.voxel_map import load_voxel_map
from services.bus import BusConfig, open_session, query
from services.journal import Journal
from tests.io.test_run_files import a_voxel_map
from tests.service.conftest import file_size_limit, limit_file_size, wait_until

pytestmark = pytest.mark.service
COUNTER = "tests.service.workers_for_tests"


def status_of(session, name: str) -> Status | None:
    frames = query(session, keys.status("r1", name), reply_type=Status, timeout=0.5)
    return frames[0] if frames else None


def wait_state(session, name: str, state: str, timeout: float = 30) -> Status:
    seen = []

    def reached():
        seen[:] = [status_of(session, name)]
        return seen[0] if seen[0] is not None and seen[0].state == state else None

    return wait_until(reached, timeout, interval=0.1,
                      message=lambda: f"{name} {state} (last: {seen[0] and (seen[0].state, seen[0].state_reason)})")


def publisher(session, key: str):
    out = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: out.matching_status.matching, 20, message=f"a subscriber on {key}")
    return out


def test_a_stateful_worker_keeps_counting_reports_and_snapshots_again(tmp_path, procs, session, hub):
    """The counter journals every frame and snapshots every second. With its files limited to 1 byte it counts and
    echoes every frame all the same, its status says it cannot write its journal (File too large), the journal ends
    with a whole record, the last good snapshot stays; lifted, the next snapshot succeeds and the status is running
    again; killed then, it comes back with every frame."""
    state = tmp_path / "state"
    args = ["worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir", str(state),
            "--set", "snapshot_period_s=1", "--set", "status_period_s=0.2"]
    echoes = []
    subscriber = session.declare_subscriber("semloc/r1/counter/echo", lambda s: echoes.append(s.payload.to_bytes()))
    worker = procs.semloc(*args, name="counter")
    wait_state(session, "counter", "running")
    frames = publisher(session, "semloc/r1/counter/in")

    def send(seqs):
        for seq in seqs:
            frames.put(encode(Ack(header=Header(robot="r1", seq=seq, stamp_ns=seq + 1), ok=True, message="")))
        wait_until(lambda: len(echoes) == seqs[-1] + 1, 20, message=f"{seqs[-1] + 1} echoes")

    send(list(range(20)))
    wait_until(lambda: (s := status_of(session, "counter")) and s.persistence.snapshots >= 1, 10,
               message="a snapshot")
    snapshot = state / "r1" / "counter.npz"
    good = snapshot.read_bytes()

    limit_file_size(worker.pid, 1)
    send(list(range(20, 40)))  # every frame counted and echoed: the worker goes on
    status = wait_state(session, "counter", "degraded")
    assert "cannot write" in status.state_reason and "File too large" in status.state_reason
    assert str(state / "r1" / "counter.journal") in status.state_reason
    assert status.errors == 0 and status.write_failures >= 1
    wait_until(lambda: "counter.npz" in (status_of(session, "counter") or status).state_reason, 10,
               message="the failed snapshot in the status")
    assert snapshot.read_bytes() == good  # the last whole snapshot, never a partial one
    assert not list(snapshot.parent.glob("*.tmp"))
    journal = Journal(state / "r1" / "counter.journal")
    list(journal.records())
    assert journal.torn == 0  # the record cut short by the limit was cut off again

    limit_file_size(worker.pid, None)
    status = wait_state(session, "counter", "running", timeout=20)
    assert status.persistence.snapshots >= 2 and status.state_reason == ""
    send(list(range(40, 50)))
    worker.send_signal(signal.SIGKILL)
    worker.wait(10)
    restarted = procs.semloc(*args, name="counter2")
    wait_until(lambda: (s := status_of(session, "counter")) and s.pid == restarted.pid and s.state == "running", 30,
               message="restarted")
    counts = query(session, "semloc/r1/counter/count", reply_type=Ack, timeout=2.0)
    assert int(counts[0].message) == 50  # the snapshot after the failure and the journal since hold every frame
    subscriber.undeclare()


def a_pose(index: int) -> PoseEstimate:
    x, y, theta = 0.1 * index, -0.05 * index, 0.01 * index
    return PoseEstimate(header=Header(robot="r1", stream="localizer/pose", seq=index, stamp_ns=(index + 1) * 10**8,
                                      frame_id="world"),
                        x=x, y=y, theta=theta, covariance=np.eye(3) * 0.01, status="converged", particles=1,
                        effective_sample_size=1.0, mean=np.array([x, y, theta]), mean_covariance=np.eye(3) * 0.01)


def test_the_saver_keeps_whole_files_and_catches_up(tmp_path, procs, session, hub):
    """The saver writes the poses and maps it is given; with its files limited to 1 byte, it says it cannot write
    trajectory.tum (File too large), the trajectory ends with its last whole line and the maps stay the earlier
    ones, whole; lifted, the poses that waited and the newer map are written and the status is running again."""
    folder = tmp_path / "save"
    maps = {"current": a_voxel_map(seed=0)}

    def answer(request) -> None:
        request.reply(keys.mapper_save("r1"), encode(maps["current"]))

    mapper = session.declare_queryable(keys.mapper_save("r1"), answer)
    saver = procs.semloc("worker", "saver", "--connect", hub, "--robot", "r1", "--set", f"folder={folder}",
                         "--set", "period_s=0.3", "--set", "status_period_s=0.2", name="saver")
    wait_state(session, "saver", "running")
    poses = publisher(session, keys.localizer_pose("r1"))
    objects = publisher(session, keys.mapper_objects("r1"))

    def trajectory_lines() -> int:
        path = folder / "trajectory.tum"
        return sum(1 for line in path.read_text().splitlines() if not line.startswith("#")) if path.exists() else 0

    for index in range(10):
        poses.put(encode(a_pose(index)))
    objects.put(encode(maps["current"]))
    wait_until(lambda: trajectory_lines() == 10 and (folder / "voxels.npz").exists(), 20, message="first files")
    map_files = ("objects.json", "voxels.npz", "voxels.ply")  # objects.json is written last
    wait_until(lambda: all((folder / name).exists() for name in map_files), 10, message="the map's files")
    earlier = {name: (folder / name).read_bytes() for name in map_files}

    limit_file_size(saver.pid, 1)
    maps["current"] = a_voxel_map(seed=1)
    objects.put(encode(maps["current"]))
    for index in range(10, 20):
        poses.put(encode(a_pose(index)))
    status = wait_state(session, "saver", "degraded")
    assert f"cannot write {folder / 'trajectory.tum'}: File too large" in status.state_reason
    wait_until(lambda: "pose(s) waiting" in (s := status_of(session, "saver") or status).state_reason
               and s.inputs["pose"].processed == 20 and "voxels.npz" in s.state_reason, 20,
               message="every pose taken and the map's failed write in the status")
    status = status_of(session, "saver")
    assert status.errors == 0 and status.write_failures >= 2
    assert (folder / "trajectory.tum").read_bytes().endswith(b"\n") and trajectory_lines() == 10
    assert {name: (folder / name).read_bytes() for name in earlier} == earlier  # the earlier maps, whole
    assert not list(folder.glob("*.tmp"))

    limit_file_size(saver.pid, None)
    wait_state(session, "saver", "running", timeout=20)
    wait_until(lambda: trajectory_lines() == 20, 10, message="the poses that waited")
    stamps, written = read_tum(folder / "trajectory.tum")
    expected = [a_pose(index) for index in range(20)]
    assert np.allclose(stamps, [pose.header.stamp_ns * 1e-9 for pose in expected])
    assert np.allclose(written[:, 0, 3], [pose.x for pose in expected])
    newer = maps["current"]
    wait_until(lambda: np.array_equal(load_voxel_map(folder / "voxels.npz")["scores"], newer.score_volumes), 10,
               message="the newer voxel map")
    assert np.allclose(load_semantic_map(folder / "objects.json").positions, newer.positions)
    mapper.undeclare()


def test_a_node_whose_log_cannot_be_opened_runs_all_the_same(tmp_path, procs, hub):
    """An unwritable log (here a folder where the file should be: refused as root too) does not keep the launcher
    from starting the node; it says so and the node's output goes to the launcher's."""
    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump({"name": "logs", "robot": "r1", "hub": hub, "nodes": {"counter": {
        "worker": COUNTER, "config": {"status_period_s": 0.2}}}}))
    (tmp_path / "run" / "logs" / "counter.log").mkdir(parents=True)
    procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    with open_session(BusConfig(connect=[hub])) as session:  # the launcher listens on the hub
        wait_state(session, "counter", "running")
    assert f"node counter: cannot write its log {tmp_path / 'run' / 'logs' / 'counter.log'}" in procs.log("launcher")


def test_a_recording_the_disk_stops_keeps_its_whole_chunks(tmp_path, session):
    """`semloc record` (the demo's --record): the disk stops taking writes (here a file size limit of this
    process, the recorder's) mid-recording. Nothing raises; the recorder says why and counts the messages it lost;
    the file reads back as the first messages published, in order, byte for byte."""
    from services.recording import Recorder, read_messages

    path = tmp_path / "session.mcap"
    payloads = [bytes([index]) * 100_000 for index in range(20)]  # about 2 MB: 256 KiB chunks
    with file_size_limit(700_000):
        recorder = Recorder(session, "semloc/r1/**", path)
        for payload in payloads:
            session.put("semloc/r1/test/blob", payload)
        wait_until(lambda: recorder.count + recorder.lost == len(payloads), 20, message="every message taken")
        recorder.close()
    assert f"cannot write {path}: File too large" == recorder.error and recorder.lost >= 1
    read = [payload for _, _, payload in read_messages(path)]
    assert 1 <= len(read) < len(payloads) and read == payloads[:len(read)]


def test_map_save_into_an_unwritable_folder_says_which_file(tmp_path, session, hub):
    """`semloc map save` whose folder cannot be made (its parent is a file: refused as root too) says so in one
    line, exit 1, no traceback."""
    import subprocess
    import sys

    from tests.service.conftest import REPO_ROOT

    mapper = session.declare_queryable(keys.mapper_save("r1"),
                                       lambda request: request.reply(keys.mapper_save("r1"), encode(a_voxel_map())))
    (tmp_path / "file").write_text("not a folder")
    done = subprocess.run([sys.executable, "-m", "services.cli", "map", "save", str(tmp_path / "file" / "maps"),
                           "--connect", hub, "--wait", "10"], cwd=REPO_ROOT, capture_output=True, text=True,
                          timeout=60)
    mapper.undeclare()
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.strip() == f"semloc map save: cannot write {tmp_path / 'file' / 'maps'}: Not a directory"


def test_a_log_the_disk_refuses_is_reported_and_comes_back(tmp_path, procs, session, hub):
    """The worker's log (its stderr, a file: `semloc up` puts it in the run folder) on a disk that stops taking
    writes: the status names the log file and the reason; once lines get through again, running."""
    procs.semloc("worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--set",
                 "status_period_s=0.2", "--set", "log_level=DEBUG", name="counter")
    worker = procs.started[-1]
    wait_state(session, "counter", "running")
    log = tmp_path / "counter.log"
    limit_file_size(worker.pid, log.stat().st_size)  # not one more line
    frames = publisher(session, "semloc/r1/counter/in")
    frames.put(encode(Ack(header=Header(robot="r1", seq=0, stamp_ns=1), ok=True, message="boom")))  # logs an error
    status = wait_state(session, "counter", "degraded")
    assert f"cannot write {log}: File too large" in status.state_reason and status.write_failures >= 1
    limit_file_size(worker.pid, None)
    frames.put(encode(Ack(header=Header(robot="r1", seq=1, stamp_ns=2), ok=True, message="boom")))
    wait_state(session, "counter", "running")
