"""Service test: camera worker -> detector worker over zenoh on loopback, real processes; heatlines checked against
the known bearings of the objects in the frames, heatmaps decoded, rerun output read back."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest
import rerun as rr
import yaml

from schemas import decode, keys
from schemas.detection import Heatlines, Heatmaps
from semloc_core.bearing import BearingGrid
from semloc_core.camera import PinholeCamera, column_bearings
from services.workers.detector import heatlines_from_frame, heatmaps_from_frame
from tests.detection.synthetic import make_object, paste, textured_background
from tests.service.conftest import hub, procs, session, wait_until  # noqa: F401 - fixtures

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
    received: dict[str, list] = {"heatlines": [], "heatmaps": []}
    lock = threading.Lock()

    def collect(kind):
        def on_sample(sample):
            frame = decode(sample.payload.to_bytes())
            with lock:
                received[kind].append(frame)
        return on_sample

    subscribers = [session.declare_subscriber(keys.detector_heatlines("r1"), collect("heatlines")),
                   session.declare_subscriber(keys.detector_heatmaps("r1"), collect("heatmaps"))]
    rrd = tmp_path / "detector.rrd"
    detector = procs.semloc("worker", "detector", "--connect", hub, "--robot", "r1", "--detector-file",
                            str(detector_file), "--rerun-save", str(rrd), "--log-level", "WARNING",
                            # every frame must come out: a loaded machine's slow first frame must not drop the next
                            "--set", "inputs.image.policy=lossless", name="detector")
    camera_worker = procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--source", str(images),
                                 "--calibration", str(calibration), "--rate", "4", "--wait-for-subscriber-s", "60",
                                 "--log-level", "WARNING", name="camera")
    assert camera_worker.wait(120) == 0, procs.log("camera")
    wait_until(lambda: len(received["heatmaps"]) >= len(CLOCK_COLUMNS), 30,
               message=f"heatmaps\n{procs.log('detector')}")
    wait_until(lambda: len(received["heatlines"]) >= len(CLOCK_COLUMNS) - 1, 10, message="heatlines")
    for subscriber in subscribers:
        subscriber.undeclare()
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
    for chunk in rr.chunk.RrdReader(str(rrd)).stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows.get("/r1/detector/heatmap/clock", 0) >= len(CLOCK_COLUMNS)
    assert rows.get("/r1/detector/heatlines/machine", 0) >= len(CLOCK_COLUMNS) - 1


def _frame_index(heatlines: Heatlines, heatmaps: list[Heatmaps]) -> int:
    """Image index of a heatlines frame: heatmaps and heatlines of one image share its capture stamp."""
    stamps = sorted({f.header.stamp_ns for f in heatmaps})
    return stamps.index(heatlines.header.stamp_ns)
