"""The mapper worker over zenoh on loopback: heatmaps + poses in, the object map out and on request; its state
survives a restart; rerun receives frustums, boxes and hot voxels."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import rerun as rr
import zenoh

from schemas import Header, Pose3D, encode, keys
from schemas.detection import CameraHeatmaps, Heatmaps
from schemas.mapping import ObjectMap
from semloc_core.camera import PinholeCamera
from semloc_core.geometry import invert_transform
from semloc_core.mapping.synthetic import SyntheticObject, orbit_poses, render_heatmaps
from services.bus import query
from services.camera_calibration import save_camera
from services.workers.mapper import semantic_map_from_frame
from tests.service.conftest import hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service

CLASSES = ("bowl", "soda_can")
OBJECTS = [SyntheticObject(0, np.array([0.3, 0.4, 0.08]), np.array([0.16, 0.16, 0.08])),
           SyntheticObject(1, np.array([0.7, 0.6, 0.1]), np.array([0.07, 0.07, 0.12]))]
# The camera's body frame: 20 cm behind and 10 cm below the camera (a fixed extrinsic the worker must apply).
K = np.array([[131.25, 0.0, 79.625], [0.0, 131.25, 59.625], [0.0, 0.0, 1.0]])
T_BODY_CAM = np.eye(4)
T_BODY_CAM[:3, 3] = [0.0, 0.1, -0.2]
CAMERA = PinholeCamera(160, 120, K, T_body_cam=T_BODY_CAM)


def _objects(session) -> ObjectMap | None:
    replies = query(session, keys.mapper_map("r1"), reply_type=ObjectMap, timeout=2.0)
    return replies[0] if replies else None


def _check_map(frame: ObjectMap, frames: int) -> None:
    semantic_map = semantic_map_from_frame(frame)
    assert frame.frames == frames and semantic_map.class_names == CLASSES
    assert len(semantic_map) == len(OBJECTS)
    for obj in OBJECTS:
        (index,) = semantic_map.objects_of(CLASSES[obj.class_index])
        assert np.linalg.norm(semantic_map.positions[index] - obj.centre) < 0.02


def test_mapper_worker(tmp_path, procs, session, hub):
    calibration = save_camera(CAMERA, tmp_path / "camera.yaml")
    rrd = tmp_path / "mapper.rrd"
    args = ["worker", "mapper", "--connect", hub, "--robot", "r1", "--calibration", str(calibration),
            "--state-dir", str(tmp_path / "state"), "--set", "grid_min=[0,0,0]", "--set", "grid_max=[1,1,0.3]",
            "--voxel-size", "0.02", "--publish-period-s", "0.2", "--rerun-save", str(rrd)]
    worker = procs.semloc(*args, name="mapper")
    wait_until(lambda: query(session, keys.status("r1", "mapper"), timeout=0.5), 60, message="mapper up")
    published = []
    subscriber = session.declare_subscriber(keys.mapper_objects("r1"), lambda s: published.append(s))
    poses_out = session.declare_publisher(keys.groundtruth_pose("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    heat_out = session.declare_publisher(keys.detector_heatmaps("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: poses_out.matching_status.matching and heat_out.matching_status.matching, 20,
               message="mapper subscribed")

    views = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 10)
    for seq, T_world_cam in enumerate(views):
        stamp = 1_000_000_000 + seq * 100_000_000
        T_world_body = T_world_cam @ invert_transform(T_BODY_CAM)
        values = render_heatmaps(CAMERA, T_world_cam, OBJECTS, len(CLASSES))
        quantised = np.round(values * 255).astype(np.uint8)
        heat = Heatmaps(header=Header(robot="r1", seq=seq, stamp_ns=stamp), classes=CLASSES,
                        maps=[CameraHeatmaps(image_width=160, image_height=120, scores=quantised, scale=1 / 255)])
        # Heatmaps first, pose after: the worker must hold the heatmaps until their pose arrives.
        heat_out.put(encode(heat))
        poses_out.put(encode(Pose3D.from_matrix(Header(robot="r1", seq=seq, stamp_ns=stamp, frame_id="world"),
                                                T_world_body)))
    frame = wait_until(lambda: (f := _objects(session)) and f.frames == len(views) and f, 30, message="all frames")
    _check_map(frame, len(views))
    wait_until(lambda: published, 10, message="a published ObjectMap")

    worker.send_signal(signal.SIGTERM)
    assert worker.wait(30) == 0, procs.log("mapper")
    subscriber.undeclare()
    reader = rr.chunk.RrdReader(str(rrd))
    rows: dict[str, int] = {}
    for chunk in reader.stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows.get("/r1/mapper/camera", 0) >= len(views)
    assert rows.get("/r1/mapper/objects", 0) >= 1 and rows.get("/r1/mapper/hot_voxels", 0) >= 1

    restarted = procs.semloc(*args[:-2], name="mapper2")
    frame = wait_until(lambda: _objects(session), 60, message="restored map")
    _check_map(frame, len(views))
    restarted.send_signal(signal.SIGTERM)
    assert restarted.wait(30) == 0, procs.log("mapper2")
