"""deploy/local.yaml runs as shipped, through `semloc up --camera`, as its comment says: with its example files (made
from the simulated table top, seed 0, generated looks) a data set played at its own rate reaches every worker, none
of its frames published before the workers ran (the camera's start_after), and every worker processes them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from schemas import decode, keys
from schemas.detection import Heatlines
from schemas.status import LauncherStatus
from semloc_core.io.dataset import open_dataset
from services.bus import BusConfig, open_session, query
from tests.e2e.graph import stop
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.service
CONSUMERS = ("detector", "loopclosure", "localizer", "mapper", "monitor")


def test_local_graph_runs_on_the_example_files(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    expected_map = json.loads((REPO_ROOT / "deploy" / "local" / "map.json").read_text())
    assert json.loads((dataset / "semantic_map.json").read_text())["objects"] == expected_map["objects"]
    # What the camera publishes once per frame (odometry: from the second frame on, a motion ending there).
    recorded = open_dataset(dataset)
    frames = len(recorded)
    camera_published = {keys.camera_image("r1"): frames, keys.groundtruth_pose("r1"): frames,
                        keys.odometry("r1"): int((recorded.odometry.as_array()[:, 3] > 0).sum())}
    hub = f"tcp/127.0.0.1:{free_port()}"
    log = open(tmp_path / "up.log", "wb")  # noqa: SIM115 - the child keeps its copy
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "up", "local", "--camera", str(dataset), "--hub", hub,
         "--run-dir", str(tmp_path / "run"), "--set", f"state_dir={tmp_path / 'state'}"],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    heatlines = []
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            subscriber = session.declare_subscriber(keys.detector_heatlines("r1"), lambda s: heatlines.append(
                decode(s.payload.to_bytes(), expected=Heatlines)))

            def camera_done():
                views = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=1.0)
                camera = views[0].nodes.get("camera") if views else None
                return camera is not None and camera.finished and camera.last_exit == 0

            def statuses():
                found = {}
                for worker in CONSUMERS:
                    replies = query(session, keys.status("r1", worker), timeout=1.0)
                    if replies and replies[0].state == "running":
                        found[worker] = replies[0]
                return found

            missing = {}

            def every_frame_arrived():
                """The statuses once every input has received all its stream published (the camera's whole data
                set, the other workers' outputs so far) and each worker processed some."""
                found = statuses()
                if set(found) != set(CONSUMERS):
                    missing.update(not_running=sorted(set(CONSUMERS) - set(found)))
                    return None
                published = {**{o.key: o.published for s in found.values() for o in s.outputs.values()},
                             **camera_published}
                missing.clear()
                missing.update({f"{w}.{name}": f"{i.received} of {published[i.key]}" for w, s in found.items()
                                for name, i in s.inputs.items()  # a queryable answers under its output's key
                                if i.key in published and not name.startswith("query:")
                                and i.received != published[i.key]})
                arrived = not missing
                heatmaps, localized = found["mapper"].inputs["heatmaps"], found["localizer"].outputs["pose"]
                return found if arrived and heatmaps.processed > 0 and localized.published > 0 and heatlines else None

            wait_until(camera_done, 150, interval=1.0, message="the camera's data set played to its end")
            found = wait_until(every_frame_arrived, 60, interval=1.0,
                               message=lambda: f"every frame at every worker; short: {missing}")
            subscriber.undeclare()
    finally:
        stop(process)
    for key in camera_published:  # each stream of the camera is read by some worker (and arrived whole, above)
        assert any(i.key == key for s in found.values() for i in s.inputs.values()), key
    assert found["detector"].inputs["image"].received == frames
    assert set(heatlines[0].classes) == {"bowl", "cap", "cereal_box", "coffee_mug", "soda_can"}
    assert found["mapper"].inputs["heatmaps"].processed > 0 and found["mapper"].inputs["pose"].processed == frames
    assert found["loopclosure"].inputs["image"].processed > 0
    assert all(s.errors == 0 and s.rejected == 0 for s in found.values()), {
        w: (s.errors, s.rejected, s.last_error[-300:]) for w, s in found.items()}
    # The camera node took the --camera source and the calibration of deploy/local/.
    camera_config = (tmp_path / "run" / "camera.yaml").read_text()
    assert str(dataset) in camera_config and "deploy/local/camera.yml" in camera_config
