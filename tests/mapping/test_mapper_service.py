"""The mapper worker over zenoh on loopback: heatmaps + poses in, the object map out and on request; its state
survives a restart; rerun receives frustums, boxes and hot voxels."""

from __future__ import annotations

import json
import signal

import numpy as np
import pytest
import rerun as rr
import zenoh

from schemas import Header, Pose3D, encode, keys
from schemas.detection import CameraHeatmapLevels, CameraHeatmaps, HeatmapLevels, Heatmaps
from schemas.mapping import ObjectMap
from semloc_core.camera import PinholeCamera
from semloc_core.geometry import invert_transform
from semloc_core.mapping import ExtractionConfig, VoxelGrid, VoxelMapper
from semloc_core.mapping.existence import ExistenceCurve
from semloc_core.mapping.scale_depth import level_depths
from semloc_core.mapping.synthetic import SyntheticObject, orbit_poses, render_heatmaps, render_level_heatmaps
from services.bus import query
from semloc_core.io.camera_model import save_camera
from services.frames import semantic_map_from_frame
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
    args = ["worker", "mapper", "--connect", hub, "--robot", "r1", "--set", f"calibration={calibration}",
            "--state-dir", str(tmp_path / "state"), "--set", f"classes={list(CLASSES)}", "--set", "grid_min=[0,0,0]",
            "--set", "grid_max=[1,1,0.3]", "--set", "voxel_size=0.02", "--set", "publish_period_s=0.2",
            "--rerun-save", str(rrd)]
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

    # Restarted with an existence curve (what calibration.fit fits): the restored map's objects carry p(real).
    curve = ExistenceCurve(reference=10.0, intercept=0.5, slope=1.0)
    restarted = procs.semloc(*args[:-2], "--set", f"extraction.existence={json.dumps(curve.to_document())}", name="mapper2")
    frame = wait_until(lambda: _objects(session), 60, message="restored map")
    _check_map(frame, len(views))
    np.testing.assert_allclose(frame.existence, curve(frame.scores))
    assert np.all((frame.existence > 0.05) & (frame.existence < 0.95))
    np.testing.assert_allclose(semantic_map_from_frame(frame).existence, frame.existence)
    restarted.send_signal(signal.SIGTERM)
    assert restarted.wait(30) == 0, procs.log("mapper2")


# Scale-selected mapping: a window detector's levels (docs/mapping.md). The soda-can filter also answers on a clutter
# box, at the level of a can 60 % as far (a look-alike of the wrong size): a phantom can in a single map.
SCALES = (1.2, 0.85, 0.6, 0.42, 0.3, 0.21)
DEPTH_PER_SCALE = 0.0085  # metres per focal pixel per unit scale: levels answer 1.34 m ... 0.23 m away
CLUTTER = SyntheticObject(1, np.array([0.35, 0.75, 0.1]), np.array([0.12, 0.12, 0.12]))


def _level_frames(views):
    depths = level_depths([DEPTH_PER_SCALE] * len(CLASSES), SCALES, K[0, 0])
    world = OBJECTS + [CLUTTER]
    return [render_level_heatmaps(CAMERA, T, world, len(CLASSES), depths, depth_factor={len(world) - 1: 0.6})
            for T in views]


def test_single_maps_of_these_frames_hold_the_phantom_can():
    """What the worker test below guards against: the max over levels of the same frames, mapped without the
    levels, puts a can on the clutter box."""
    views = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 10)
    mapper = VoxelMapper(VoxelGrid.from_bounds([0, 0, 0], [1, 1, 0.3], 0.02), CLASSES)
    for T, levels in zip(views, _level_frames(views)):
        mapper.integrate(levels.max(axis=1), T, CAMERA)
    cans = [o for o in mapper.extract(ExtractionConfig()) if o.class_name == "soda_can"]
    assert any(np.linalg.norm(o.position - CLUTTER.centre) < 0.03 for o in cans)


def test_mapper_worker_maps_heatmap_levels_scale_selected(tmp_path, procs, session, hub):
    calibration = save_camera(CAMERA, tmp_path / "camera.yaml")
    scale_depth = tmp_path / "scale_depth.json"
    scale_depth.write_text(json.dumps({"detector": {"scale_depth": {
        "scales": list(SCALES), "classes": {name: {"depth_per_scale": DEPTH_PER_SCALE} for name in CLASSES}}}}))
    args = ["worker", "mapper", "--connect", hub, "--robot", "r1", "--set", f"calibration={calibration}",
            "--set", f"classes={list(CLASSES)}", "--set", "grid_min=[0,0,0]", "--set", "grid_max=[1,1,0.3]",
            "--set", "voxel_size=0.02", "--set", "publish_period_s=0.2", "--set", f"scale_depth_file={scale_depth}"]
    worker = procs.semloc(*args, name="mapper")
    wait_until(lambda: query(session, keys.status("r1", "mapper"), timeout=0.5), 60, message="mapper up")
    poses_out = session.declare_publisher(keys.groundtruth_pose("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    levels_out = session.declare_publisher(keys.detector_heatmap_levels("r1"),
                                           congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: poses_out.matching_status.matching and levels_out.matching_status.matching, 20,
               message="mapper subscribed")
    views = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 10)
    for seq, (T_world_cam, levels) in enumerate(zip(views, _level_frames(views))):
        stamp = 1_000_000_000 + seq * 100_000_000
        frame = HeatmapLevels(header=Header(robot="r1", seq=seq, stamp_ns=stamp), classes=CLASSES,
                              level_scales=SCALES, maps=[CameraHeatmapLevels(
                                  image_width=160, image_height=120, scores=levels.astype(np.float16))])
        levels_out.put(encode(frame))
        poses_out.put(encode(Pose3D.from_matrix(Header(robot="r1", seq=seq, stamp_ns=stamp, frame_id="world"),
                                                T_world_cam @ invert_transform(T_BODY_CAM))))
    # Levels of another detector (other scales): refused with the reason, counted, the worker carries on.
    other = HeatmapLevels(header=Header(robot="r1", seq=99, stamp_ns=3_000_000_000), classes=CLASSES,
                          level_scales=(1.0, 0.5), maps=[CameraHeatmapLevels(
                              image_width=160, image_height=120, scores=np.zeros((2, 2, 120, 160), np.float16))])
    levels_out.put(encode(other))
    frame = wait_until(lambda: (f := _objects(session)) and f.frames == len(views) and f, 30, message="all frames")
    _check_map(frame, len(views))  # the two objects within 2 cm and nothing else: no phantom can
    def status():
        replies = query(session, keys.status("r1", "mapper"), timeout=0.5)
        return replies[0] if replies else None

    seen = wait_until(lambda: (s := status()) and s.inputs["heatmaps"].rejected == 1 and s, 20,
                      message=lambda: f"the foreign frame rejected; status {status()}")
    assert seen.inputs["heatmaps"].processed >= len(views)
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(30) == 0, procs.log("mapper")
    assert "level scales [1.0, 0.5] differ" in procs.log("mapper")


@pytest.mark.parametrize("maps", ["heatmaps", "levels"])
def test_kernels_compiled_before_running(tmp_path, session, maps):  # noqa: F811
    """The worker compiles the back-projection kernels in setup (a throwaway mapper of its settings, one synthetic
    frame), so the first real heatmaps are not stalled by compilation on a fresh install: a real frame (single maps
    or scale-selected levels) needs no kernel that setup did not load (tests/fresh_setup.py); the worker's own map
    stays empty."""
    from services.workers.mapper import Mapper, MapperWorkerConfig
    from tests.fresh_setup import check_setup_compiles

    calibration = save_camera(CAMERA, tmp_path / "camera.yaml")
    settings = {"robot": "rwarm", "calibration": str(calibration), "classes": list(CLASSES), "grid_min": [0, 0, 0],
                "grid_max": [1, 1, 0.3], "voxel_size": 0.02}
    if maps == "levels":
        settings["scale_depth_file"] = str(tmp_path / "scale_depth.json")
        (tmp_path / "scale_depth.json").write_text(json.dumps({"detector": {"scale_depth": {
            "scales": list(SCALES), "classes": {name: {"depth_per_scale": DEPTH_PER_SCALE} for name in CLASSES}}}}))
    config = MapperWorkerConfig(**settings)
    run = """
        import numpy as np
        from schemas import Header, Pose3D
        from schemas.detection import CameraHeatmapLevels, CameraHeatmaps, HeatmapLevels, Heatmaps
        from semloc_core.geometry import invert_transform
        from semloc_core.mapping.synthetic import orbit_poses, render_heatmaps
        from tests.mapping.test_mapper_service import CAMERA, CLASSES, OBJECTS, SCALES, T_BODY_CAM, _level_frames
        header = Header(robot="rwarm", stamp_ns=1_000_000_000, frame_id="world")
        (T_world_cam,) = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 1)
        if worker.scale_depth is None:
            scores = np.round(render_heatmaps(CAMERA, T_world_cam, OBJECTS, len(CLASSES)) * 255).astype(np.uint8)
            frame = Heatmaps(header=header, classes=CLASSES, maps=[CameraHeatmaps(
                image_width=160, image_height=120, scores=scores, scale=1 / 255)])
        else:
            frame = HeatmapLevels(header=header, classes=CLASSES, level_scales=SCALES, maps=[CameraHeatmapLevels(
                image_width=160, image_height=120, scores=_level_frames([T_world_cam])[0].astype(np.float16))])
        worker.apply_heatmaps(frame)
        worker.apply_pose(Pose3D.from_matrix(header, T_world_cam @ invert_transform(T_BODY_CAM)))
        result = worker.mapper.frames
    """
    kernels = "semloc_core.mapping.backprojection"
    frames = check_setup_compiles("mapper", config, [kernels], run, expected=(f"{kernels}._backproject_slices",))
    assert frames == 1
    worker = Mapper(config)
    worker.session = session
    worker.setup()
    assert worker.mapper.frames == 0 and not worker.mapper.view_count().any()


def test_mapper_refusing_a_fisheye_camera_says_so(tmp_path, procs, session, hub):
    """A fisheye camera feeds the detector and the localizer, but the mapper back-projects pinhole rays only: it
    refuses the model (counted) and its status says so for as long as such models come (it showed `running` while
    its map stayed empty); a pinhole model afterwards brings it back to running."""
    from semloc_core.camera import FisheyeCamera
    from schemas import Status
    from services.frames import camera_model_frame

    procs.semloc("worker", "mapper", "--connect", hub, "--robot", "r1", "--set", f"classes={list(CLASSES)}",
                 "--set", "grid_min=[0,0,0]", "--set", "grid_max=[1,1,0.3]", "--set", "voxel_size=0.02",
                 "--set", "status_period_s=0.2", name="mapper")
    def status():
        replies = query(session, keys.status("r1", "mapper"), reply_type=Status, timeout=0.5)
        return replies[0] if replies else None
    wait_until(lambda: (s := status()) and s.state == "running", 60, message="mapper running")
    fisheye = FisheyeCamera(160, 120, np.array([[60.0, 0, 79.5], [0, 60.0, 59.5], [0, 0, 1]]))

    def after(camera, state):
        def check():
            session.put(keys.camera_model("r1"), encode(camera_model_frame(camera, Header(robot="r1", stamp_ns=1))))
            return (s := status()) and s.state == state and s
        return wait_until(check, 30, interval=0.3, message=lambda: f"{state}; log:\n{procs.log('mapper')[-2000:]}")

    refused = after(fisheye, "degraded")
    assert refused.state_reason.startswith("camera model refused (the mapper needs pinhole cameras)")
    wait_until(lambda: status().inputs["camera_model"].rejected >= 1, 10, message="the refusals counted")
    assert after(CAMERA, "running").state_reason == ""


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGKILL])
def test_a_restored_mapper_maps_without_the_camera_worker(tmp_path, procs, session, hub, stop):
    """The camera model the mapper maps with is part of its state (the snapshot a graceful stop writes, the journal a
    SIGKILL leaves): restarted while no camera worker answers (a cut link), it integrates heatmaps at once instead of
    holding them until the model comes (beyond `pending`, dropping the oldest). A model from the bus replaces it: the
    frames of another camera are integrated from its arrival on, those of the old one refused ('calibration'). One
    the camera worker answers at the next start replaces the state's once that is restored as it was (the other
    camera's frame included)."""
    from schemas import Status
    from services.frames import camera_model_frame

    args = ["worker", "mapper", "--connect", hub, "--robot", "r1", "--state-dir", str(tmp_path / "state"),
            "--set", f"classes={list(CLASSES)}", "--set", "grid_min=[0,0,0]", "--set", "grid_max=[1,1,0.3]",
            "--set", "voxel_size=0.02", "--set", "publish_period_s=0.2", "--set", "status_period_s=0.2"]
    poses_out = session.declare_publisher(keys.groundtruth_pose("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    heat_out = session.declare_publisher(keys.detector_heatmaps("r1"), congestion_control=zenoh.CongestionControl.BLOCK)

    def status() -> Status | None:
        replies = query(session, keys.status("r1", "mapper"), reply_type=Status, timeout=0.5)
        return replies[0] if replies else None

    def start(name: str):
        worker = procs.semloc(*args, name=name)
        wait_until(lambda: (s := status()) and s.state in ("running", "degraded"), 60,
                   message=lambda: f"{name} up; log:\n{procs.log(name)[-2000:]}")
        wait_until(lambda: poses_out.matching_status.matching and heat_out.matching_status.matching, 20,
                   message="mapper subscribed")
        return worker

    def feed(camera, seqs) -> None:
        for seq in seqs:
            stamp = 1_000_000_000 + seq * 100_000_000
            values = render_heatmaps(camera, views[seq], OBJECTS, len(CLASSES))
            heat_out.put(encode(Heatmaps(
                header=Header(robot="r1", seq=seq, stamp_ns=stamp), classes=CLASSES,
                maps=[CameraHeatmaps(image_width=camera.width, image_height=camera.height,
                                     scores=np.round(values * 255).astype(np.uint8), scale=1 / 255)])))
            poses_out.put(encode(Pose3D.from_matrix(Header(robot="r1", seq=seq, stamp_ns=stamp, frame_id="world"),
                                                    views[seq] @ invert_transform(T_BODY_CAM))))

    def mapped(frames: int, name: str) -> ObjectMap:
        return wait_until(lambda: (f := _objects(session)) and f.frames == frames and f, 30,
                          message=lambda: f"{frames} frames mapped; inputs {(s := status()) and s.inputs}; log:\n"
                                          f"{procs.log(name)[-2000:]}")

    views = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 13)
    first = start("mapper")
    session.put(keys.camera_model("r1"), encode(camera_model_frame(CAMERA, Header(robot="r1", stamp_ns=1))))
    feed(CAMERA, range(5))
    mapped(5, "mapper")
    first.send_signal(stop)
    first.wait(30)

    # No camera worker: nothing answers the model's query, nothing publishes one.
    restarted = start("restarted")
    feed(CAMERA, range(5, 10))  # without the model they would wait (and beyond `pending`, be dropped)
    _check_map(mapped(10, "restarted"), 10)
    assert status().state_reason == ""  # not "no camera model yet: heatmaps wait"

    # Another camera now: its model from the bus replaces the restored one.
    other = PinholeCamera(80, 60, K / 2 + np.diag([0, 0, 0.5]), T_body_cam=T_BODY_CAM)
    session.put(keys.camera_model("r1"), encode(camera_model_frame(other, Header(robot="r1", stamp_ns=2))))
    wait_until(lambda: status().inputs["camera_model"].processed >= 1, 10, message="the new model taken")
    feed(CAMERA, [10])
    feed(other, [11])
    mapped(11, "restarted")
    assert status().inputs["heatmaps"].rejected_reasons == {"calibration": 1}

    # The first camera back, its worker answering: the state (the other camera's frame included) is restored as it
    # was, then the camera worker's model replaces the state's.
    answer = session.declare_queryable(keys.camera_model("r1"), lambda query: query.reply(
        keys.camera_model("r1"), encode(camera_model_frame(CAMERA, Header(robot="r1", stamp_ns=3)))))
    restarted.send_signal(stop)
    restarted.wait(30)
    start("again")
    wait_until(lambda: status().inputs["camera_model"].processed >= 1, 10, message="the camera worker's model")
    feed(CAMERA, [12])
    mapped(12, "again")
    assert status().inputs["heatmaps"].rejected_reasons == {}
    answer.undeclare()


def test_heatmaps_never_integrated_are_counted_by_reason(tmp_path, procs, session, hub):
    """A heatmap frame the mapper cannot integrate is counted in its status's details under its reason, never dropped
    silently (a cut-and-restart run ended 2 frames short of the heatmaps sent, the status saying nothing of them:
    docs/results/2026-12-07-cut-restart-flake.md): five wait with ``pending`` 3 (the two oldest dropped), the pose of
    the third comes, then one 0.3 s later (beyond ``pose_tolerance_s``: the fourth and fifth have none), and a sixth
    waits for its pose."""
    from schemas import Status

    calibration = save_camera(CAMERA, tmp_path / "camera.yaml")
    procs.semloc("worker", "mapper", "--connect", hub, "--robot", "r1", "--set", f"calibration={calibration}",
                 "--set", f"classes={list(CLASSES)}", "--set", "grid_min=[0,0,0]", "--set", "grid_max=[1,1,0.3]",
                 "--set", "voxel_size=0.02", "--set", "status_period_s=0.2", "--set", "pending=3", name="mapper")

    def status() -> Status | None:
        replies = query(session, keys.status("r1", "mapper"), reply_type=Status, timeout=0.5)
        return replies[0] if replies else None

    wait_until(lambda: (s := status()) and s.state == "running", 60, message="mapper running")
    poses_out = session.declare_publisher(keys.groundtruth_pose("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    heat_out = session.declare_publisher(keys.detector_heatmaps("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: poses_out.matching_status.matching and heat_out.matching_status.matching, 20,
               message="mapper subscribed")
    views = orbit_poses([0.5, 0.5, 0.1], 0.8, 0.5, 7)
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(7)]

    def put(heatmaps=(), poses=()) -> None:  # then wait until the mapper took them (two publishers: any order)
        for i in heatmaps:
            values = np.round(render_heatmaps(CAMERA, views[i], OBJECTS, len(CLASSES)) * 255).astype(np.uint8)
            heat_out.put(encode(Heatmaps(header=Header(robot="r1", seq=i, stamp_ns=stamps[i]), classes=CLASSES, maps=[
                CameraHeatmaps(image_width=160, image_height=120, scores=values, scale=1 / 255)])))
        for i in poses:
            poses_out.put(encode(Pose3D.from_matrix(Header(robot="r1", seq=i, stamp_ns=stamps[i], frame_id="world"),
                                                    views[i] @ invert_transform(T_BODY_CAM))))
        taken[0] += len(heatmaps)
        taken[1] += len(poses)
        wait_until(lambda: (s := status()) and (s.inputs["heatmaps"].processed, s.inputs["pose"].processed) == (
            taken[0], taken[1]), 20, message="frames taken")

    taken = [0, 0]
    put(heatmaps=(0, 1, 2, 3, 4))
    put(poses=(2,))
    put(poses=(5,))
    put(heatmaps=(6,))
    details = status().details
    assert (details["heatmaps_over_pending"], details["heatmaps_without_pose"], details["heatmaps_waiting"]) == (
        2, 2, 1), details
    assert _objects(session).frames == 1
