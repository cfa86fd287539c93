"""Service test: the detector worker prunes its pyramid levels by the localizer's pose (issue 35) over zenoh on
loopback, and keeps the heat at the simulator's objects that the exhaustive detector has there."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import yaml
import zenoh

from schemas import Header, Image, Pose3D, Status, decode, encode, keys
from schemas.camera import camera_image
from schemas.localization import PoseEstimate
from semloc_core.detection.config import build_detector
from semloc_core.detection.pruning import build_pruner, height_from_pose
from semloc_core.experiments.demo_world import DETECTOR
from semloc_core.experiments.tabletop import table_support
from semloc_core.io.dataset import open_dataset
from services.bus import query
from services.frames import heatmaps_from_frame
from tests.service.conftest import hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service

FRAMES = 4


def _put(session, key: str, payload: bytes) -> None:
    """Every frame sent is awaited: blocked for rather than dropped when the link is busy (a put's default), as a
    loaded run's image seemed to be (it never arrived; the 60 s wait ended)."""
    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def _estimate(stamp_ns: int, pose, state: str, robot: str) -> PoseEstimate:
    covariance = np.diag([0.05 ** 2, 0.05 ** 2, 0.03 ** 2])
    return PoseEstimate(header=Header(robot=robot, stream="pose", stamp_ns=stamp_ns, frame_id="world"),
                        x=float(pose[0]), y=float(pose[1]), theta=float(pose[2]), covariance=covariance,
                        status="converged", state=state, particles=500, effective_sample_size=400.0,
                        mean=np.asarray(pose, float), mean_covariance=covariance)


@pytest.mark.parametrize("height_from", ["configured", "pose"])
def test_detector_prunes_levels_by_the_pose_and_keeps_the_objects_heat(tmp_path, sim_dataset, procs, hub, session,
                                                                       height_from):  # noqa: F811
    robot = f"prune{height_from}"   # the module's workers outlive a test: one robot each
    folder = sim_dataset("tabletop", frames=FRAMES, seed=3)
    dataset = open_dataset(folder)
    camera = dataset.camera
    calibration = tmp_path / "camera.yaml"
    calibration.write_text(yaml.safe_dump({
        "model": "pinhole", "image_width": camera.width, "image_height": camera.height,
        "camera_matrix": {"rows": 3, "cols": 3, "data": camera.K.ravel().tolist()}}))
    detector_config = {**DETECTOR, "templates": str(folder / "exemplars")}
    detector_file = tmp_path / "detector.yaml"
    detector_file.write_text(yaml.safe_dump(detector_config))
    prune = {"map": str(folder / "semantic_map.json"), "support_z": table_support(dataset)[0],
             "support_polygon": table_support(dataset)[1].tolist(),
             "camera_height": float(np.median(dataset.T_world_cam[:, 2, 3]))}
    if height_from == "pose":   # the camera's height from the body's 3-D pose (ground truth), sent before the image
        prune["height_pose"] = True
    received, lock = [], threading.Lock()

    def on_heatmaps(sample):
        with lock:
            received.append(decode(sample.payload.to_bytes()))

    subscriber = session.declare_subscriber(keys.detector_heatmaps(robot), on_heatmaps)
    procs.semloc("worker", "detector", "--connect", hub, "--robot", robot, "--set", f"detector_file={detector_file}",
                 "--set", f"calibration={calibration}", "--set", f"prune={json.dumps(prune)}",
                 "--set", "heatmap_dtype=float32", "--set", "rerun_every=0", "--set", "inputs.image.policy=lossless",
                 "--set", f"inputs.image.depth={FRAMES + 1}", "--log-level", "WARNING", name="detector")

    def status() -> Status | None:
        replies = query(session, keys.status(robot, "detector"), reply_type=Status, timeout=1.0)
        return replies[0] if replies else None

    wait_until(lambda: (s := status()) is not None and s.state == "running", 120,
               message=lambda: f"detector running\n{procs.log('detector')}")
    stamps = [1_000_000_000 + 500_000_000 * i for i in range(FRAMES)]
    for i, stamp in enumerate(stamps):
        # the localizer's pose of this frame (a localized one for every frame but the first: that one runs all)
        state = "lost" if i == 0 else "localized"
        _put(session, keys.localizer_pose(robot), encode(_estimate(stamp - 1, dataset.poses2d[i], state, robot)))
        if height_from == "pose":
            header = Header(robot=robot, stream="groundtruth_pose", stamp_ns=stamp, seq=i, frame_id="world")
            _put(session, keys.groundtruth_pose(robot), encode(Pose3D.from_matrix(header, dataset.T_world_body[i])))
        wait_until(lambda: status().inputs["pose"].processed >= i + 1
                   and (height_from == "configured" or status().inputs["height_pose"].processed >= i + 1), 30,
                   message="the poses")
        image = Image(header=Header(robot=robot, stream="image", stamp_ns=stamp, seq=i, frame_id="camera"),
                      images=[camera_image(dataset.image(i), T_body_cam=dataset.T_body_cam[i])])
        _put(session, keys.camera_image(robot), encode(image))
        # the frame is processed before the next pose is sent (a pose may overtake an image on the bus)
        wait_until(lambda: status().inputs["image"].processed >= i + 1, 60,
                   message=lambda: f"frame {i}: {status().inputs['image']}")
    wait_until(lambda: len(received) >= FRAMES, 120, message=lambda: f"heatmaps\n{procs.log('detector')}")
    subscriber.undeclare()
    details = status().details
    assert details["prune_frames"] == FRAMES - 1 and details["prune_full_frames"] == 1, details
    share = float(details["prune_last"].split(":")[0].split()[1])
    assert share < 0.9, details   # a pose prunes: the rows asked are a share of the full work
    exhaustive = build_detector(detector_config)
    pruner = build_pruner(exhaustive, dataset.camera, dataset.semantic_map, prune["support_z"],
                          prune["camera_height"], prune["support_polygon"])
    last = FRAMES - 1
    rows = pruner.rows(dataset.poses2d[last], dataset.T_body_cam[last],
                       height_from_pose(dataset.T_world_body[last], dataset.T_body_cam[last], 0.0, pruner.params)
                       if height_from == "pose" else None)
    assert share == pytest.approx(pruner.share(rows), abs=0.006), details   # the frame's own height, if sent

    classes = tuple(exhaustive.classes)
    checked = 0
    for i, frame in enumerate(sorted(received, key=lambda f: f.header.stamp_ns)):
        heatmaps = heatmaps_from_frame(frame)[0]
        full = exhaustive.heatmaps(dataset.image(i))
        rows, cols = full.shape[1:]
        if i == 0:
            np.testing.assert_allclose(heatmaps, full, atol=1e-5)   # not localized: every level everywhere
            continue
        assert not np.allclose(heatmaps, full, atol=1e-3)   # some level was left out somewhere
        for seen in dataset.visible_objects(i):
            if seen.class_name not in classes or seen.occluded_fraction > 0.1 or seen.truncated:
                continue
            u0, v0, u1, v1 = seen.box
            box = (slice(int(v0 * rows / camera.height), int(np.ceil(v1 * rows / camera.height))),
                   slice(int(u0 * cols / camera.width), int(np.ceil(u1 * cols / camera.width))))
            k = classes.index(seen.class_name)
            assert heatmaps[k][box].max() >= full[k][box].max() - 0.05, (i, seen.class_name)
            checked += 1
    assert checked >= 2 * (FRAMES - 1)

    if height_from == "pose":   # a height pose 5 m above the configured camera height: not used, counted
        lifted = dataset.T_world_body[last].copy()
        lifted[2, 3] += 5.0
        stamp = stamps[-1] + 500_000_000
        header = Header(robot=robot, stream="groundtruth_pose", stamp_ns=stamp, seq=FRAMES, frame_id="world")
        _put(session, keys.groundtruth_pose(robot), encode(Pose3D.from_matrix(header, lifted)))
        wait_until(lambda: status().inputs["height_pose"].processed > FRAMES, 30, message="the lifted pose")
        image = Image(header=Header(robot=robot, stream="image", stamp_ns=stamp, seq=FRAMES, frame_id="camera"),
                      images=[camera_image(dataset.image(last), T_body_cam=dataset.T_body_cam[last])])
        _put(session, keys.camera_image(robot), encode(image))
        wait_until(lambda: status().inputs["image"].processed > FRAMES, 30, message="the last image")
        details = status().details
        assert details["prune_height_disagreed"] == 1, details
        configured = pruner.share(pruner.rows(dataset.poses2d[last], dataset.T_body_cam[last]))
        assert float(details["prune_last"].split(":")[0].split()[1]) == pytest.approx(configured, abs=0.006), details

    # a pose far from the table is another map's: rejected with its reason, counted, not used
    _put(session, keys.localizer_pose(robot), encode(_estimate(stamps[-1] + 1, (5e4, 0.0, 0.0), "localized", robot)))
    wait_until(lambda: status().inputs["pose"].rejected_reasons.get("pose_range") == 1, 30, message="pose_range")
