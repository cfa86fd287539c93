"""Service test: camera worker -> detector worker over zenoh on loopback, real processes; heatlines checked against
the known bearings of the objects in the frames, heatmaps decoded, rerun output read back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import rerun as rr
import yaml

from schemas import keys
from schemas.detection import HeatmapLevels, Heatlines, Heatmaps
from semloc_core.bearing import BearingGrid
from semloc_core.camera import PinholeCamera, column_bearings
from services.frames import heatlines_from_frame, heatmaps_from_frame
from tests.detection.synthetic import make_object, paste, textured_background
from tests.service.conftest import Received, hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service

WIDTH, HEIGHT, FOV = 320, 240, 60.0
CLOCK_COLUMNS = [60, 110, 160, 210, 260, 140]


def _dataset(tmp_path):
    images = tmp_path / "images"
    images.mkdir()
    for index, column in enumerate(CLOCK_COLUMNS):
        scene = textured_background(HEIGHT, WIDTH, seed=index)
        paste(scene, make_object("clock", 120), (column, 100), 70)
        paste(scene, make_object("machine", 120), ((column + 160) % WIDTH, 130), 90)
        cv2.imwrite(str(images / f"{index:03d}.png"), scene)
    camera = PinholeCamera.from_fov(WIDTH, HEIGHT, FOV)
    calibration = tmp_path / "camera.yaml"
    calibration.write_text(yaml.safe_dump({
        "model": "pinhole", "image_width": WIDTH, "image_height": HEIGHT,
        "camera_matrix": {"rows": 3, "cols": 3, "data": camera.K.ravel().tolist()}}))
    library = tmp_path / "library"
    for kind in ("clock", "machine"):
        (library / kind).mkdir(parents=True)
        cv2.imwrite(str(library / kind / f"{kind}.png"), make_object(kind, 120))
    detector = tmp_path / "detector.yaml"
    detector.write_text(yaml.safe_dump({"kind": "templates", "templates": "library", "scales": [1.0, 0.75]}))
    return images, calibration, detector, camera


def test_camera_to_detector_heatlines_peak_at_the_objects(tmp_path, procs, hub, session):  # noqa: F811
    images, calibration, detector_file, camera = _dataset(tmp_path)
    received = Received(session, {"heatlines": keys.detector_heatlines("r1"), "heatmaps": keys.detector_heatmaps("r1")})
    rrd = tmp_path / "detector.rrd"
    detector = procs.semloc("worker", "detector", "--connect", hub, "--robot", "r1", "--set",
                            f"detector_file={detector_file}", "--rerun-save", str(rrd), "--log-level", "WARNING",
                            # every frame must come out: a loaded machine's slow first frame must not drop the next
                            # and a queue as long as the data set (a frame refused by a full queue never comes back)
                            "--set", "inputs.image.policy=lossless", "--set",
                            f"inputs.image.depth={len(CLOCK_COLUMNS)}",
                            "--set", f"overlay_width={WIDTH // 2}", name="detector")
    camera_worker = procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={images}",
                                 "--set", f"calibration={calibration}", "--set", "rate=4",
                                 "--set", "wait_for_subscriber_s=60",
                                 "--log-level", "WARNING", name="camera")
    assert camera_worker.wait(120) == 0, procs.log("camera")
    wait_until(lambda: len(received["heatmaps"]) >= len(CLOCK_COLUMNS), 30,
               message=f"heatmaps\n{procs.log('detector')}")
    wait_until(lambda: len(received["heatlines"]) >= len(CLOCK_COLUMNS) - 1, 10, message="heatlines")
    received.close()
    detector.send_signal(2)
    assert detector.wait(30) == 0, procs.log("detector")

    heatmaps = received["heatmaps"]
    assert all(isinstance(f, Heatmaps) and f.classes == ("clock", "machine") for f in heatmaps)
    assert heatmaps_from_frame(heatmaps[0])[0].shape == (2, HEIGHT // 8, WIDTH // 8)
    grid = BearingGrid()
    expected = column_bearings(camera)
    for frame in received["heatlines"]:
        assert isinstance(frame, Heatlines) and frame.header.frame_id == "body"
        lines = heatlines_from_frame(frame)
        column = CLOCK_COLUMNS[_frame_index(frame, heatmaps)]
        peak = grid.centers[np.argmax(lines.scores[0])]
        assert abs(np.degrees(peak - expected[column])) <= 2.0
        assert lines.observed.sum() in (60, 61)

    rows: dict[str, int] = {}
    overlay_shapes = set()
    for chunk in rr.chunk.RrdReader(str(rrd)).stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
            if chunk.entity_path == "/r1/detector/heatmap/clock":
                for blobs in chunk.to_record_batch().column("EncodedImage:blob").to_pylist():
                    overlay = cv2.imdecode(np.asarray(blobs[0], np.uint8), cv2.IMREAD_COLOR)
                    overlay_shapes.add(overlay.shape)
    assert rows.get("/r1/detector/heatmap/clock", 0) >= len(CLOCK_COLUMNS)
    assert overlay_shapes == {(HEIGHT // 2, WIDTH // 2, 3)}  # overlay_width: logged at half the image's width
    assert rows.get("/r1/detector/heatlines/machine", 0) >= len(CLOCK_COLUMNS) - 1


def test_an_image_that_came_before_the_camera_model_gets_its_heatlines_when_the_model_comes(tmp_path, procs, hub,
                                                                                             session):  # noqa: F811
    """The camera publishes its model before its first image, but on another key: a detector that met the camera
    after the model went out gets it after the first image. That image's heatlines come with the model (before, it
    was skipped: the localizer had no observation of the first frame); of two such images, the older is skipped and
    said so, the newer gets its heatlines."""
    import zenoh

    from schemas import Header, Image, encode
    from schemas.camera import camera_image
    from services.frames import camera_model_frame

    images, _calibration, detector_file, camera = _dataset(tmp_path)
    pictures = sorted(images.iterdir())
    received = Received(session, {"heatlines": keys.detector_heatlines("r1"), "heatmaps": keys.detector_heatmaps("r1")})
    procs.semloc("worker", "detector", "--connect", hub, "--robot", "r1", "--set", f"detector_file={detector_file}",
                 "--set", "inputs.image.policy=lossless", name="detector")
    publisher = session.declare_publisher(keys.camera_image("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 60, message=lambda: f"detector\n{procs.log('detector')}")
    stamps = [10**9, 2 * 10**9]
    for index, stamp in enumerate(stamps):  # each handled (its heatmaps out) before the next: no model yet
        publisher.put(encode(Image(header=Header(robot="r1", seq=index, stamp_ns=stamp),
                                   images=[camera_image(cv2.imread(str(pictures[index])))])))
        wait_until(lambda: len(received["heatmaps"]) > index, 60, message=lambda: f"heatmaps\n{procs.log('detector')}")
    assert received["heatlines"] == []
    session.put(keys.camera_model("r1"), encode(camera_model_frame(camera, Header(robot="r1", seq=0, stamp_ns=1))))
    wait_until(lambda: received["heatlines"], 30, message=lambda: f"heatlines\n{procs.log('detector')}")
    received.close()
    heatlines = received["heatlines"]
    assert [frame.header.stamp_ns for frame in heatlines] == [stamps[1]]
    peak = BearingGrid().centers[np.argmax(heatlines_from_frame(heatlines[0]).scores[0])]
    assert abs(np.degrees(peak - column_bearings(camera)[CLOCK_COLUMNS[1]])) <= 2.0
    assert "no camera model yet: no heatlines: 1 frame(s) skipped" in procs.log("detector")


def _frame_index(heatlines: Heatlines, heatmaps: list[Heatmaps]) -> int:
    """Image index of a heatlines frame: heatmaps and heatlines of one image share its capture stamp."""
    stamps = sorted({f.header.stamp_ns for f in heatmaps})
    return stamps.index(heatlines.header.stamp_ns)


def test_a_window_detector_publishes_its_levels_beside_the_heatmaps(tmp_path, procs, hub, session):  # noqa: F811
    """``publish_levels``: a trained window detector's per-level maps (HeatmapLevels) for every image, whose max
    over levels is that image's Heatmaps frame, in the model's level order; at each object's centre the level
    whose window fits the object's size answers, the level of the most different size does not."""
    from semloc_core.detection.linear import best_level, train_linear_model
    from semloc_core.io.detector_models import save_linear_model
    from tests.detection.test_linear import KINDS, PARAMS, SCALES, scene

    model = train_linear_model([scene(seed)[:2] for seed in range(16)], KINDS, PARAMS, SCALES, window_cells=9,
                               random_negatives=30, hard_negatives=10, rounds=1, seed=0)
    save_linear_model(tmp_path / "model.npz", model)
    (tmp_path / "detector.yaml").write_text("kind: linear\nmodel: model.npz\n")
    images = tmp_path / "images"
    images.mkdir()
    truth = []
    for index in range(4):
        image, objects, _ = scene(500 + index, decoy=False)
        cv2.imwrite(str(images / f"{index:03d}.png"), image)
        truth.append(objects)
    received = Received(session, {"heatmaps": keys.detector_heatmaps("r1"),
                                  "levels": keys.detector_heatmap_levels("r1")})
    detector = procs.semloc("worker", "detector", "--connect", hub, "--robot", "r1", "--set",
                            f"detector_file={tmp_path / 'detector.yaml'}", "--log-level", "WARNING",
                            "--set", "publish_levels=true",
                            # every frame: a queue as long as the data set (a frame refused by a full queue never comes back)
                            "--set", "inputs.image.policy=lossless", "--set",
                            f"inputs.image.depth={len(CLOCK_COLUMNS)}", name="detector")
    camera_worker = procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={images}",
                                 "--set", "rate=4", "--set", "wait_for_subscriber_s=60", "--log-level", "WARNING",
                                 name="camera")
    assert camera_worker.wait(120) == 0, procs.log("camera")
    wait_until(lambda: len(received["levels"]) >= len(truth) and len(received["heatmaps"]) >= len(truth), 30,
               message=f"heatmaps and levels\n{procs.log('detector')}")
    received.close()
    detector.send_signal(2)
    assert detector.wait(30) == 0, procs.log("detector")

    heatmaps = {f.header.stamp_ns: f for f in received["heatmaps"]}
    stamps = sorted(heatmaps)
    checked_far = 0
    for frame in received["levels"]:
        assert isinstance(frame, HeatmapLevels) and frame.classes == KINDS and frame.level_scales == SCALES
        (levels,) = frame.maps
        single = heatmaps[frame.header.stamp_ns].maps[0]
        assert levels.scores.dtype == single.scores.dtype == np.uint8
        np.testing.assert_array_equal(levels.scores.max(axis=1), single.scores)
        rows, cols = levels.scores.shape[2:]
        for obj in truth[stamps.index(frame.header.stamp_ns)]:
            u, v = obj.centre
            at = levels.values()[obj.class_index, :, int(v * rows / HEIGHT), int(u * cols / WIDTH)]
            fits = best_level(obj.size, model.weights[obj.class_index].shape[:2], SCALES, PARAMS.cell)
            # (neighbouring levels, sqrt(2) apart, both answer for sizes between them; two steps off do not)
            far = [level for level in range(len(SCALES)) if abs(level - fits) >= 2]
            assert at.max() > 0.5 and abs(int(np.argmax(at)) - fits) <= 1 and np.all(at[far] < 0.5 * at.max())
            checked_far += len(far)
    assert checked_far >= 2


def test_kernels_compiled_before_running(tmp_path, session):  # noqa: F811
    """The worker compiles its detector's numba kernels in setup (its detector on a synthetic scene, exhaustive and
    on bands of rows, and a throwaway heatline projector), so the first real frames are not stalled by compilation
    on a fresh install: a real image through the worker, then matched on bands of rows, needs no kernel that setup
    did not load (tests/fresh_setup.py); the worker's detector answers as a fresh one."""
    from semloc_core.detection.config import build_detector
    from semloc_core.io.semantic_map import SemanticMap, save_semantic_map
    from services.workers.detector import Detector, DetectorConfig
    from tests.fresh_setup import check_setup_compiles

    images, calibration, detector_file, _ = _dataset(tmp_path)
    objects = [{"class": kind, "position": [1.0, 0.3 * k, 0.8], "size": [0.2, 0.2, 0.3]}
               for k, kind in enumerate(("clock", "machine"))]
    save_semantic_map(SemanticMap.from_objects(objects, bounds=[[-2, -2], [2, 2]]), tmp_path / "map.json")
    config = DetectorConfig(robot="rwarm", detector_file=str(detector_file), calibration=str(calibration),
                            prune={"map": str(tmp_path / "map.json"), "support_z": 0.75, "camera_height": 1.2})
    run = """
        import cv2
        from schemas import Header, Image
        from schemas.camera import camera_image
        bgr = cv2.imread(args[0])
        worker.on_image(Image(header=Header(robot="rwarm", stamp_ns=1, frame_id="camera"), images=[camera_image(bgr)]))
        rows = worker.detector.output_shape(bgr.shape)[0]
        worker.detector.heatmaps(bgr, rows={s: (rows // 3, rows // 2) for s in worker.detector.match.scales})
        result = worker.frames
    """
    kernels = "semloc_core.detection._kernels"
    frames = check_setup_compiles("detector", config, [kernels], run, str(images / "000.png"),
                                  expected=(f"{kernels}.lerp_rows_max", f"{kernels}.scatter_max"))
    assert frames == 1
    worker = Detector(config)
    worker.session = session
    worker.setup()
    bgr = cv2.imread(str(images / "000.png"))
    np.testing.assert_array_equal(worker.detector.heatmaps(bgr), build_detector(str(detector_file)).heatmaps(bgr))
