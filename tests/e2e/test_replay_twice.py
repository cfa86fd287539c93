"""A recorded session replayed twice into the same running workers (docs/deploy.md, "Replaying a session"): the
second pass's stamps go back in time, and the ordered peer streams (the localizer's estimates into the loop closure,
its decisions into the localizer: ``services.frames.PeerStream``) start over instead of refusing it; its frames get
recorded poses as the first pass's did, the first pass's keep theirs, and nothing is refused or dropped on the way."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from schemas import Header, decode, keys
from schemas.localization import PoseEstimate
from schemas.loopclosure import LoopClosure, TopoMapUpdate
from schemas.status import Ack
from schemas.status import Status
from schemas.motion import Pose2D
from semloc_core.geometry import transform_to_pose2d
from semloc_core.io.trajectory import read_tum
from services.bus import BusConfig, open_session, query
from services.frames import STREAM_RESTART_S
from services.recording import Recorder, replay
from tests.e2e.graph import stop, tracking_options
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.service
WORKERS = ("detector", "loopclosure", "localizer")
FRAMES = 45  # 1.5 s of the simulator's 30 Hz stamps: a pass spans more than STREAM_RESTART_S


def statuses(session) -> dict[str, Status]:
    found = {}
    for worker in WORKERS:
        replies = query(session, keys.status("r1", worker), reply_type=Status, timeout=1.0)
        if replies and replies[0].state == "running":
            found[worker] = replies[0]
    return found


def record_the_camera(dataset: Path, path: Path) -> None:
    """The data set as the camera worker publishes it, recorded on a bus of its own (no worker takes it yet)."""
    bus = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(listen=[bus])) as session:
        recorder = Recorder(session, keys.robot_all("r1"), path)
        camera = subprocess.run(
            [sys.executable, "-m", "services.cli", "worker", "camera", "--robot", "r1", "--connect", bus,
             "--set", f"source={dataset}", "--set", "source_type=dataset", "--set", "rate=10",
             "--set", f"calibration={REPO_ROOT / 'deploy' / 'local' / 'camera.yml'}"],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
        recorder.close()
    assert camera.returncode == 0, camera.stderr[-2000:]


def test_a_session_replayed_twice_is_processed_twice(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=FRAMES, seed=0))
    gt_stamps, gt_poses = read_tum(dataset / "groundtruth_body.tum")
    assert gt_stamps[-1] - gt_stamps[0] > STREAM_RESTART_S
    start = transform_to_pose2d(gt_poses[0])
    session_file = tmp_path / "session.mcap"
    hub = f"tcp/127.0.0.1:{free_port()}"
    log = open(tmp_path / "up.log", "wb")  # noqa: SIM115 - the child keeps its copy
    graph = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "up", "deploy/local.yaml", "--hub", hub,
         "--run-dir", str(tmp_path / "run"),
         *(f"--set=nodes.{node}.enabled=false" for node in ("camera", "mapper", "monitor")),
         *tracking_options(start, tmp_path / "state")],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    record_the_camera(dataset, session_file)  # while the workers start
    events: list[LoopClosure] = []
    updates: list[TopoMapUpdate] = []
    estimates: list[tuple[int, PoseEstimate]] = []  # (pass, the localizer's estimate)
    passes = []
    updates_of_first = 0  # the TopoMapUpdates published by the end of the first pass
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            wait_until(lambda: len(statuses(session)) == len(WORKERS), 180, interval=1.0,
                       message=lambda: f"every worker running (up.log: {(tmp_path / 'up.log').read_text()[-1500:]})")
            subscribers = [
                session.declare_subscriber(keys.loopclosure_events("r1"), lambda s: events.append(
                    decode(s.payload.to_bytes(), expected=LoopClosure))),
                session.declare_subscriber(keys.loopclosure_topomap("r1"), lambda s: updates.append(
                    decode(s.payload.to_bytes(), expected=TopoMapUpdate))),
                session.declare_subscriber(keys.localizer_pose("r1"), lambda s: estimates.append(
                    (len(passes), decode(s.payload.to_bytes(), expected=PoseEstimate))))]
            for run in range(2):
                if run:  # the robot is back at the session's start: the operator says so (semloc localize set-pose)
                    ack = query(session, keys.localizer_set_initial_pose("r1"), Pose2D(
                        header=Header(robot="r1"), x=start[0], y=start[1], theta=start[2],
                        covariance=np.diag([0.01, 0.01, 0.01])), reply_type=Ack, timeout=5.0)
                    assert ack and ack[0].ok, ack
                sent = replay(session, session_file, speed=2.0, wait_for_subscribers_s=10.0)
                assert sent > 3 * FRAMES

                def settled():
                    found = statuses(session)
                    if len(found) != len(WORKERS):
                        return None
                    images = found["loopclosure"].inputs["image"]
                    pose_in, pose_out = found["loopclosure"].inputs["pose"], found["localizer"].outputs["pose"]
                    heatlines = found["localizer"].inputs["heatlines"]
                    done = (images.received == (run + 1) * FRAMES and images.queued == 0
                            and heatlines.received == (run + 1) * FRAMES and heatlines.queued == 0
                            and pose_in.received == pose_out.published and pose_in.queued == 0)
                    return found if done else None

                counts = lambda: {w: (s.received, s.processed, s.rejected)  # noqa: E731
                                  for w, s in statuses(session).items()}
                passes.append(wait_until(settled, 120, interval=0.5,
                                         message=lambda: f"pass {run + 1} processed: {counts()}"))
                if not run:
                    time.sleep(0.5)  # the last pose changes on their way here
                    updates_of_first = len(updates)
            for subscriber in subscribers:
                subscriber.undeclare()
    finally:
        stop(graph)
    first, second = passes
    for name, found in (("first", first), ("second", second)):
        for worker, status in found.items():
            assert status.errors == 0 and status.overflow == 0, (name, worker, status.last_error)
            # (the latest-policy inputs - ground truth, camera model, decisions - may drop by design)
            assert all(i.dropped == 0 for i in status.inputs.values() if i.policy == "lossless"), (name, worker)
    # The localizer's estimates into the loop closure: every one of the second pass taken too (the set-pose
    # announcement is stamped at the first pass's end, so nothing near the restart is stale)
    pose_first, pose_second = first["loopclosure"].inputs["pose"], second["loopclosure"].inputs["pose"]
    assert pose_second.rejected == 0, pose_second.rejected_reasons
    assert pose_second.processed - pose_first.processed >= FRAMES
    assert second["localizer"].inputs["loops"].rejected == 0, second["localizer"].inputs["loops"].rejected_reasons
    # and the localizer tracked the second pass with its odometry, as the first (without it the track was lost);
    # judged against the ground truth, not by the state, which a short track's last frames may still be judging
    def tracking_error(run):
        return [float(np.hypot(*(np.array([e.x, e.y]) - transform_to_pose2d(
            gt_poses[np.abs(gt_stamps - e.header.stamp_ns * 1e-9).argmin()])[:2])))
            for k, e in estimates if k == run and e.status != "localizing"]

    tracking = tracking_error(0), tracking_error(1)
    print("localizer position error per pass, median (m):", *(round(float(np.median(e)), 3) for e in tracking))
    assert len(tracking[1]) >= FRAMES // 2 and np.median(tracking[1]) < 0.2, tracking[1]
    assert all(s.rejected == 0 for s in second.values()), {w: s.inputs for w, s in second.items() if s.rejected}
    # Every frame of the second pass went through the loop closure, and its places were given poses, where the
    # robot was
    frames_first = int(first["loopclosure"].details["frames"])
    frames_second = int(second["loopclosure"].details["frames"])
    # the same images and odometry, the same key-frames (give or take one: an image may come before the odometry up
    # to it); its motion since the first pass's last key-frame is not its own
    assert frames_second - frames_first >= frames_first - 1 > 0, (frames_first, frames_second)
    stamp_of = {event.frame: event.header.stamp_ns for event in events}

    def frame_poses(published):
        poses = {}
        for update in published:
            for frame, pose in zip(update.posed_frames if update.posed_frames is not None else [],
                                   update.frame_poses if update.frame_poses is not None else []):
                poses[int(frame)] = pose
        return {frame: pose for frame, pose in poses.items() if np.isfinite(pose).all()}
    posed = frame_poses(updates)
    # The first pass's places keep the poses they had (the map): the second pass's estimates, on the same stamps,
    # neither withdraw nor overwrite them (services/workers/loopclosure.py, _new_run)
    kept = frame_poses(updates[:updates_of_first])
    changed = {f: (tuple(np.round(p, 3)), tuple(np.round(posed[f], 3)) if f in posed else None)
               for f, p in kept.items() if f not in posed or not np.array_equal(p, posed[f])}
    print(f"first pass's places posed {len(kept)}, changed by the second {len(changed)}")
    assert kept and not changed, changed
    posed_first = [f for f in posed if f < frames_first]
    posed_second = [f for f in posed if f >= frames_first]
    print(f"frames {frames_first} + {frames_second - frames_first}; posed {len(posed_first)} + {len(posed_second)}; "
          f"estimates taken {pose_first.processed} then {pose_second.processed}")
    assert posed_first and len(posed_second) >= len(posed_first) - 2

    def error(frame):
        truth = transform_to_pose2d(gt_poses[np.abs(gt_stamps - stamp_of[frame] * 1e-9).argmin()])
        return float(np.hypot(*(posed[frame][:2] - truth[:2])))

    errors = [error(f) for f in posed_first], [error(f) for f in posed_second]
    print("place position errors (m):", *(np.round(e, 3).tolist() for e in errors))
    assert np.median(errors[1]) < 0.2  # as the first pass's (the short track's last estimates drift in both)
