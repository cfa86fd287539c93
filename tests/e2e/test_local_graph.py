"""deploy/local.yaml runs as shipped, through `semloc up --camera`: with its example files (made from the simulated
table top, seed 0, generated looks) every worker starts and processes the camera's frames."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from schemas import decode, keys
from schemas.detection import Heatlines
from schemas.localization import PoseEstimate
from services.bus import BusConfig, open_session, query
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.service
WORKERS = ("camera", "detector", "loopclosure", "localizer", "mapper", "monitor")


def test_local_graph_runs_on_the_example_files(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    expected_map = json.loads((REPO_ROOT / "deploy" / "local" / "map.json").read_text())
    assert json.loads((dataset / "semantic_map.json").read_text())["objects"] == expected_map["objects"]
    hub = f"tcp/127.0.0.1:{free_port()}"
    log = open(tmp_path / "up.log", "wb")  # noqa: SIM115 - the child keeps its copy
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "up", "deploy/local.yaml", "--camera", str(dataset), "--hub", hub,
         "--run-dir", str(tmp_path / "run"), "--set", "nodes.camera.config.rate=4",
         # looping keeps the camera alive (and its status answering) however long a loaded machine needs
         "--set", "nodes.camera.config.loop=true",
         "--set", "nodes.camera.config.wait_for_subscriber_s=30", "--set", f"state_dir={tmp_path / 'state'}"],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    heatlines, poses = [], []
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            subscribers = [
                session.declare_subscriber(keys.detector_heatlines("r1"), lambda s: heatlines.append(
                    decode(s.payload.to_bytes(), expected=Heatlines))),
                session.declare_subscriber(keys.localizer_pose("r1"), lambda s: poses.append(
                    decode(s.payload.to_bytes(), expected=PoseEstimate))),
            ]

            def statuses():
                found = {}
                for worker in WORKERS:
                    replies = query(session, keys.status("r1", worker), timeout=1.0)
                    if replies:
                        found[worker] = replies[0]
                return found

            def all_processed():
                found = statuses()
                # A status answered while a worker is still in setup lists only the inputs declared so far.
                running = {w: s for w, s in found.items() if s.state == "running"}
                busy = {w for w, s in running.items() if s.processed > 0 or w == "camera"}
                # A worker's total counts its camera-model input too: wait for the first image itself (the loop
                # closure worker's first frame compiles its kernels and takes a while on a loaded machine).
                image = running["loopclosure"].inputs.get("image") if "loopclosure" in running else None
                images = image is not None and image.processed > 0
                # The mapper counts poses as processed at once; its first heatmap waits for a pose at its stamp.
                heatmap = running["mapper"].inputs.get("heatmaps") if "mapper" in running else None
                mapped = heatmap is not None and heatmap.processed > 0
                return found if busy == set(WORKERS) and images and mapped and len(poses) >= 3 else None

            found = wait_until(all_processed, 150, interval=1.0, message="every worker processing frames")
            for subscriber in subscribers:
                subscriber.undeclare()
    finally:
        os.killpg(process.pid, signal.SIGINT)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert set(heatlines[0].classes) == {"bowl", "cap", "cereal_box", "coffee_mug", "soda_can"}
    assert found["mapper"].inputs["heatmaps"].processed > 0 and found["mapper"].inputs["pose"].processed > 0
    assert found["loopclosure"].inputs["image"].processed > 0
    assert all(s.errors == 0 and s.rejected == 0 for s in found.values()), {
        w: (s.errors, s.rejected, s.last_error[-300:]) for w, s in found.items()}
    # The camera node took the --camera source and the calibration of deploy/local/.
    camera_config = (tmp_path / "run" / "camera.yaml").read_text()
    assert str(dataset) in camera_config and "deploy/local/camera.yml" in camera_config
