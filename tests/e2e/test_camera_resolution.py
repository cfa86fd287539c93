"""Any camera works out of the box: `semloc up deploy/local.yaml --camera VIDEO` with a video at another
resolution than deploy/local/camera.yml's 640x480. At the same aspect ratio the camera scales the intrinsics (with a
warning) and the graph produces heatlines and poses with no frame rejected; at another aspect ratio `semloc up`
exits 2 with one line naming the calibration file and both sizes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from schemas import decode, keys
from schemas.detection import Heatlines
from schemas.localization import PoseEstimate
from semloc_core.io.dataset import open_dataset
from services.bus import BusConfig, open_session, query
from tests.e2e.graph import stop
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
CALIBRATION = REPO_ROOT / "deploy" / "local" / "camera.yml"  # graph-relative paths resolve to it
pytestmark = pytest.mark.service


def write_video(dataset: Path, path: Path, size: tuple[int, int]) -> Path:
    """The data set's frames resized to ``size`` (cv2.resize maps pixel centres as the camera's scaling does)."""
    frames = open_dataset(dataset)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 4.0, size)
    for index in range(len(frames)):
        writer.write(cv2.resize(frames.image(index), size, interpolation=cv2.INTER_AREA))
    writer.release()
    return path


def start_up(tmp_path: Path, video: Path, hub: str) -> subprocess.Popen:
    log = open(tmp_path / "up.log", "wb")  # noqa: SIM115 - the child keeps its copy
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "up", "deploy/local.yaml", "--camera", str(video), "--hub", hub,
         "--run-dir", str(tmp_path / "run"), "--set", "nodes.camera.config.rate=4",
         "--set", "nodes.camera.config.loop=true", "--set", "nodes.camera.config.wait_for_subscriber_s=30",
         "--set", f"state_dir={tmp_path / 'state'}"],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    return process


def test_same_aspect_ratio_is_scaled_and_runs(tmp_path, sim_dataset):
    video = write_video(Path(sim_dataset("tabletop", frames=24, seed=0)), tmp_path / "walk.avi", (512, 384))
    hub = f"tcp/127.0.0.1:{free_port()}"
    process = start_up(tmp_path, video, hub)
    heatlines, poses = [], []
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            subscribers = [
                session.declare_subscriber(keys.detector_heatlines("r1"), lambda s: heatlines.append(
                    decode(s.payload.to_bytes(), expected=Heatlines))),
                session.declare_subscriber(keys.localizer_pose("r1"), lambda s: poses.append(
                    decode(s.payload.to_bytes(), expected=PoseEstimate))),
            ]
            wait_until(lambda: len(heatlines) >= 3 and len(poses) >= 3, 150, interval=0.5,
                       message=lambda: f"heatlines and poses ({len(heatlines)}, {len(poses)} so far)")

            def status(worker):
                replies = query(session, keys.status("r1", worker), timeout=2.0)
                return replies[0] if replies else None

            found = {worker: status(worker) for worker in ("detector", "loopclosure", "localizer")}
            [model] = query(session, keys.camera_model("r1", "front"), timeout=2.0)
            for subscriber in subscribers:
                subscriber.undeclare()
    finally:
        stop(process)
    # deploy/local/camera.yml (fx = fy = 525, principal point at the centre) scaled by 0.8 about pixel centres
    camera = model.cameras[0]
    assert (camera.width, camera.height) == (512, 384)
    assert np.allclose(camera.K, [[420, 0, 255.5], [0, 420, 191.5], [0, 0, 1]])
    assert all(s is not None and s.rejected == 0 for s in found.values()), {
        w: s and (s.rejected, s.last_error[-300:]) for w, s in found.items()}
    camera_log = (tmp_path / "run" / "logs" / "camera.log").read_text()
    assert (f"the source's frames are 512x384, the calibration {CALIBRATION} is 640x480: intrinsics scaled by 0.8"
            in camera_log)


def test_other_aspect_ratio_exits_2_with_one_line(tmp_path, sim_dataset):
    video = write_video(Path(sim_dataset("tabletop", frames=24, seed=0)), tmp_path / "wide.avi", (640, 360))
    process = start_up(tmp_path, video, f"tcp/127.0.0.1:{free_port()}")
    try:
        code = process.wait(timeout=180)
    finally:
        stop(process)
    last = (tmp_path / "up.log").read_text().strip().splitlines()[-1]
    assert code == 2, last
    assert last.startswith(f"semloc up: node camera: the calibration {CALIBRATION} is for 640x480 images, the source "
                           "gives 640x360 (another aspect ratio)"), last
