"""A stateful worker restarted on a disk that refuses writes keeps its state: real worker processes over zenoh on
loopback, the state folder made read-only (as ``errors=remount-ro`` does after an I/O error) in the worker's own
mount namespace (``unshare -m``: the folder bind-mounted on itself, then read-only) and writable again from outside
(``nsenter``). Skipped where mount namespaces cannot be made (not root, no util-linux)."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import subprocess
import threading

import numpy as np
import pytest

from schemas import Header, decode, encode, keys
from schemas.loopclosure import LoopClosure, TopoMap
from services.bus import query
from services.frames import loop_features_frame
from services.state import load_state
from tests.loopclosure.test_worker import HEIGHT, STEP, WIDTH, _wall
from tests.service.conftest import wait_until
from tests.service.test_disk_full import publisher, status_of, wait_state

pytestmark = pytest.mark.service

COUNTER = "tests.service.workers_for_tests"
READ_ONLY = 'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" && exec "$@"'


def read_only(folder) -> tuple[str, ...]:
    """A command prefix running its command with ``folder`` read-only (in a mount namespace of its own)."""
    return ("unshare", "-m", "sh", "-c", READ_ONLY, str(folder))


def make_writable(pid: int, folder) -> None:
    subprocess.run(["nsenter", f"--mount=/proc/{pid}/ns/mnt", "mount", "-o", "remount,bind,rw", str(folder)],
                   check=True, capture_output=True)


@pytest.fixture
def namespaces(tmp_path):
    if shutil.which("unshare") is None or shutil.which("nsenter") is None:
        pytest.skip("no unshare / nsenter")
    probe = tmp_path / "probe"
    probe.mkdir()
    done = subprocess.run([*read_only(probe), "sh", "-c", 'touch "$0/file"', str(probe)], capture_output=True)
    if b"Read-only file system" not in done.stderr:
        pytest.skip(f"no read-only bind mount in a mount namespace here: {done.stderr.decode().strip()}")


def test_loop_closure_restarted_read_only_keeps_its_map_and_goes_on_once_writable(tmp_path, procs, session, hub,
                                                                                  namespaces):
    """A snapshot of 14 frames and 6 journaled after it; restarted with its state folder read-only, the worker
    restores all of it (the map of the snapshot answers, the journal's 6 frames wait for the store), sets nothing
    aside and says ``degraded``, naming its store and the reason; once the folder is writable again it adds the
    6 frames as before (the same map), snapshots, journals new frames, and a restart brings back every frame."""
    from semloc_core.camera import PinholeCamera
    from semloc_core.loopclosure import extract_features
    from services.workers.loopclosure import LoopClosureConfig

    state = tmp_path / "state"
    wall, camera = _wall(), PinholeCamera.from_fov(WIDTH, HEIGHT, 60.0)
    features = [extract_features(np.ascontiguousarray(wall[:, STEP * k: STEP * k + WIDTH]), camera,
                                 LoopClosureConfig().features) for k in range(22)]
    events: list[int] = []
    lock = threading.Lock()

    def on_event(sample):
        with lock:
            events.append(decode(sample.payload.to_bytes(), expected=LoopClosure).frame)

    subscriber = session.declare_subscriber(keys.loopclosure_events("r1"), on_event)
    args = ["worker", "loopclosure", "--connect", hub, "--robot", "r1", "--state-dir", str(state),
            "--set", "engine.window=5", "--set", "engine.bootstrap_frames=12", "--set", "engine.vocabulary_words=48",
            "--set", "engine.candidates=5", "--set", "engine.band=8", "--set", "engine.temporal_radius=1",
            "--set", "engine.cull_redundant=false", "--set", "rerun_every=0", "--set", "status_period_s=0.2",
            "--set", "snapshot_period_s=3600", "--set", "journal_replay_s=1000", "--log-level", "INFO"]

    def send(frames):
        out = publisher(session, keys.loopclosure_features("r1"))
        for k in frames:
            out.put(encode(loop_features_frame(Header(robot="r1", stamp_ns=(k + 1) * 10**9, frame_id="world"),
                                               features[k])))
        wait_until(lambda: set(frames) <= set(events), 60, message=f"events of frames {frames}: {events}")
        out.undeclare()

    def topomap() -> TopoMap:
        return query(session, keys.loopclosure_topomap("r1"), reply_type=TopoMap, timeout=10)[0]

    def same_map(a: TopoMap, b: TopoMap) -> bool:
        return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("keyframes", "frame_node", "edges"))

    first = procs.semloc(*args, name="first")
    wait_state(session, "loopclosure", "running")
    send(range(14))
    snapshot_map = topomap()
    first.send_signal(signal.SIGINT)
    assert first.wait(60) == 0, procs.log("first")
    second = procs.semloc(*args, name="second")
    wait_state(session, "loopclosure", "running")
    send(range(14, 20))
    journaled_map = topomap()
    second.send_signal(signal.SIGKILL)
    second.wait(10)
    assert load_state(state / "r1" / "loopclosure.npz").meta["frames"] == 14 and journaled_map.frame_node.size == 20

    events.clear()
    third = procs.semloc(*args, name="third", prefix=read_only(state))
    status = wait_state(session, "loopclosure", "degraded")
    store = state / "r1" / "loopclosure.store"
    assert f"cannot write {store}/" in status.state_reason and "Read-only file system" in status.state_reason, \
        status.state_reason
    assert status.persistence.restored and status.persistence.replayed == 6 and not status.persistence.set_aside
    assert same_map(topomap(), snapshot_map)  # the snapshot's map answers; the journal's frames wait
    assert events == [] and not [p for p in state.rglob("*") if ".corrupt-" in p.name]

    make_writable(third.pid, state)
    wait_until(lambda: set(range(14, 20)) <= set(events), 30, message=f"the journal's frames: {events}")
    assert same_map(topomap(), journaled_map)
    wait_until(lambda: (s := status_of(session, "loopclosure")) is not None and s.state == "running"
               and s.persistence.snapshots >= 1, 30, message=lambda: status_of(session, "loopclosure"))
    send([20, 21])
    third.send_signal(signal.SIGKILL)
    third.wait(10)

    fourth = procs.semloc(*args, name="fourth")
    status = wait_state(session, "loopclosure", "running")
    assert status.persistence.restored and status.persistence.replayed == 2
    restored = topomap()
    assert restored.frame_node.size == 22 and np.array_equal(restored.frame_node[:20], journaled_map.frame_node)
    fourth.send_signal(signal.SIGINT)
    assert fourth.wait(60) == 0, procs.log("fourth")
    subscriber.undeclare()


def test_an_unusable_snapshot_on_a_read_only_disk_waits_to_be_set_aside(tmp_path, procs, session, hub, namespaces):
    """An unreadable snapshot the disk will not let rename: the worker starts empty all the same (not in a crash
    loop), says so, writes no snapshot over it; writable again, it sets it aside first, then snapshots."""
    state = tmp_path / "state"
    (state / "r1").mkdir(parents=True)
    garbage = b"PK\x03\x04 not a snapshot"
    (state / "r1" / "counter.npz").write_bytes(garbage)
    worker = procs.semloc("worker", COUNTER, "--connect", hub, "--robot", "r1", "--name", "counter", "--state-dir",
                          str(state), "--set", "status_period_s=0.2", "--set", "snapshot_period_s=1", name="counter",
                          prefix=read_only(state))
    status = wait_state(session, "counter", "degraded")
    assert f"cannot write {state / 'r1'}" in status.state_reason and "Read-only file system" in status.state_reason
    assert "cannot be set aside yet" in status.persistence.note and not status.persistence.restored
    assert sorted(p.name for p in (state / "r1").iterdir()) == ["counter.npz"]
    make_writable(worker.pid, state)
    status = wait_until(lambda: (s := status_of(session, "counter")) is not None and s.state == "running"
                        and s.persistence.snapshots >= 1 and s, 30, message=lambda: status_of(session, "counter"))
    moved = [p for p in (state / "r1").iterdir() if p.name.startswith("counter.npz.corrupt-")]
    assert len(moved) == 1 and moved[0].read_bytes() == garbage and status.persistence.set_aside == [str(moved[0])]
    assert load_state(state / "r1" / "counter.npz").meta["count"] == 0
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(20) == 0, procs.log("counter")


def test_a_restore_the_disk_refuses_keeps_the_snapshot(tmp_path):
    """A restore that raises because the disk refuses a write says nothing about the snapshot: it is kept as it is
    (not set aside, not replaced by an empty state) and the worker exits to be started again."""
    from services.state import State, save_state
    from tests.service.workers_for_tests import Counter, CounterConfig

    class Refused(Counter):
        def restore(self, state):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(tmp_path / "r1" / "counter.store"))

    path = save_state(tmp_path / "r1" / "counter.npz", State(arrays={"seen": np.arange(3)}, meta={"count": 3}))
    worker = Refused(CounterConfig(robot="r1", name="counter", state_dir=str(tmp_path)))
    with pytest.raises(RuntimeError, match="kept: restoring it needs a write the disk refuses"):
        worker._restore()
    assert sorted(p.name for p in path.parent.iterdir()) == ["counter.npz"]
    assert load_state(path).meta == {"count": 3}
