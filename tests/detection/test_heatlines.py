"""Heatmaps -> heatlines through the camera models (§4.4.2) and the hard variant (§4.5.2)."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.camera import (CameraRig, EquirectangularCamera, PinholeCamera, column_bearings, pixel_bearings)
from semloc_core.geometry import R_BODY_CAM_FORWARD, make_transform
from semloc_core.detection.heatlines import HeatlineProjector, hard_heatlines, heatline_peaks


def _rotation(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _brute_force(heatmaps: np.ndarray, bearings: np.ndarray, grid: BearingGrid) -> np.ndarray:
    """Per-pixel heatmaps: every pixel's score into its bearing's bin, one by one."""
    out = np.zeros((heatmaps.shape[0], grid.n_bins), np.float32)
    bins = grid.index(bearings).ravel()
    for k in range(heatmaps.shape[0]):
        for b, value in zip(bins, heatmaps[k].ravel()):
            out[k, b] = max(out[k, b], value)
    return out


def test_upright_pinhole_is_the_column_maximum():
    camera = PinholeCamera.from_fov(160, 120, 60.0)
    rng = np.random.default_rng(0)
    heatmaps = rng.random((2, 120, 160)).astype(np.float32)
    heatlines = HeatlineProjector(camera, ("a", "b")).project(heatmaps)
    grid = BearingGrid()
    expected = np.zeros((2, grid.n_bins), np.float32)
    for column, b in enumerate(grid.index(column_bearings(camera))):
        expected[:, b] = np.maximum(expected[:, b], heatmaps[:, :, column].max(axis=1))
    np.testing.assert_array_equal(heatlines.scores, expected)
    assert heatlines.observed.sum() == np.unique(grid.index(column_bearings(camera))).size


@pytest.mark.parametrize("roll_deg, pitch_deg", [(0.0, 25.0), (20.0, 0.0), (15.0, -30.0)])
def test_tilted_camera_uses_the_per_frame_attitude(roll_deg, pitch_deg):
    """A hand-held camera: per-frame T_body_cam from its IMU; the heatline equals per-pixel binning through it."""
    camera = PinholeCamera.from_fov(96, 72, 70.0)
    tilt = _rotation("y", np.radians(pitch_deg)) @ _rotation("x", np.radians(roll_deg))
    T = make_transform(tilt @ R_BODY_CAM_FORWARD, (0, 0, 1.2))
    rng = np.random.default_rng(1)
    heatmaps = rng.random((1, 72, 96)).astype(np.float32)
    projector = HeatlineProjector(camera, ("a",))
    heatlines = projector.project(heatmaps, T_body_cam=T)
    expected = _brute_force(heatmaps, pixel_bearings(camera, T_body_cam=T), projector.grid)
    np.testing.assert_array_equal(heatlines.scores, expected)
    # A single hot pixel lands in exactly its own bearing's bin, not in its column's upright bearing.
    hot = np.zeros((1, 72, 96), np.float32)
    hot[0, 5, 80] = 1.0
    line = projector.project(hot, T_body_cam=T).scores[0]
    assert np.flatnonzero(line) == projector.grid.index(pixel_bearings(camera, T_body_cam=T)[5, 80])


@pytest.mark.parametrize("dist", [None, (-0.25, 0.08, 0.001, -0.001, 0.0)], ids=["pinhole", "distorted"])
def test_attitude_changing_every_frame(dist):
    """A hand-held camera's attitude changes every frame, more attitudes than the projector caches, each seen twice:
    every frame's heatline equals per-pixel binning through that frame's attitude (the cells' rays are reused)."""
    camera = PinholeCamera.from_fov(96, 72, 70.0)
    if dist is not None:
        camera = PinholeCamera(camera.width, camera.height, camera.K, dist=np.array(dist))
    rng = np.random.default_rng(2)
    attitudes = [make_transform(_rotation("z", yaw) @ _rotation("y", pitch) @ _rotation("x", roll)
                                @ R_BODY_CAM_FORWARD, (0, 0, 1.0))
                 for yaw, pitch, roll in rng.uniform([-np.pi, -0.4, -0.3], [np.pi, 0.4, 0.3], (12, 3))]
    projector = HeatlineProjector(camera, ("a", "b"), cache_size=8)
    for T in attitudes + attitudes:
        heatmaps = rng.random((2, 72, 96)).astype(np.float32)
        heatlines = projector.project(heatmaps, T_body_cam=T)
        bearings = pixel_bearings(camera, T_body_cam=T)
        np.testing.assert_array_equal(heatlines.scores, _brute_force(heatmaps, bearings, projector.grid))
        np.testing.assert_array_equal(np.flatnonzero(heatlines.observed), np.unique(projector.grid.index(bearings)))


def test_coarse_heatmap_covers_every_bin_of_the_field_of_view():
    """A heatmap much coarser than the bins (8-pixel cells of a wide panorama) still leaves no hole."""
    camera = EquirectangularCamera(1024, 256)
    heatmaps = np.ones((1, 32, 128), np.float32)
    heatlines = HeatlineProjector(camera, ("a",)).project(heatmaps)
    assert heatlines.observed.all()
    assert np.all(heatlines.scores == 1.0)


def test_panorama_column_lands_at_its_longitude():
    camera = EquirectangularCamera(720, 180)
    heatmaps = np.zeros((1, 180, 720), np.float32)
    heatmaps[0, 90, 540] = 0.8      # longitude +90 deg (to the right) -> bearing -90 deg
    heatlines = HeatlineProjector(camera, ("a",)).project(heatmaps)
    peak = heatlines.grid.centers[np.argmax(heatlines.scores[0])]
    assert np.degrees(peak) == pytest.approx(-90.0, abs=1.0)


def test_fisheye_cell_lands_at_the_true_lens_bearing():
    """A fisheye camera (as a ROS equidistant CameraInfo or an OpenCV fisheye file gives) projects its heatmaps (the
    detector refused its model with a TypeError: no heatlines at all). A hot cell 70 degrees off axis lands in the
    bin of the bearing OpenCV's fisheye model gives for it."""
    import cv2

    from semloc_core.camera import FisheyeCamera

    K = np.array([[230.0, 0, 321.3], [0, 229.0, 238.4], [0, 0, 1]])
    D = np.array([0.03, -0.012, 0.004, -0.001])
    camera = FisheyeCamera(640, 480, K, D)
    ray = np.array([np.sin(np.radians(70.0)), 0.0, np.cos(np.radians(70.0))])  # 70 deg right: bearing -70 deg
    (u, v), = cv2.fisheye.projectPoints(ray.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, D)[0].reshape(1, 2)
    heatmaps = np.zeros((1, 120, 160), np.float32)
    heatmaps[0, int(v // 4), int(u // 4)] = 0.9  # the 4x4-pixel cell holding that pixel
    heatlines = HeatlineProjector(camera, ("a",)).project(heatmaps)
    grid = heatlines.grid
    hot = np.flatnonzero(heatlines.scores[0])
    assert grid.index(np.radians(-70.0)) in hot and np.ptp(np.degrees(grid.centers[hot])) < 3.0


def test_rig_takes_the_max_across_cameras():
    rig = CameraRig.ring(5, 160, 60, 80.0)
    rng = np.random.default_rng(2)
    per_camera = [rng.random((2, 60, 160)).astype(np.float32) for _ in range(5)]
    projector = HeatlineProjector(rig, ("a", "b"))
    heatlines = projector.project(per_camera)
    assert heatlines.observed.all()   # 5 x 80 deg cover the turn
    expected = np.zeros_like(heatlines.scores)
    for camera, heatmaps in zip(rig.cameras, per_camera):
        expected = np.maximum(expected, _brute_force(heatmaps, pixel_bearings(camera), projector.grid))
    np.testing.assert_array_equal(heatlines.scores, expected)


def test_projector_rejects_mismatched_heatmaps():
    projector = HeatlineProjector(PinholeCamera.from_fov(64, 48, 60.0), ("a", "b"))
    with pytest.raises(ValueError, match="classes=2"):
        projector.project(np.zeros((3, 6, 8), np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        projector.project(np.full((2, 6, 8), np.nan, np.float32))


def test_peaks_are_greedy_nms_over_the_circle():
    scores = np.zeros(360)
    scores[[10, 12, 100, 359]] = [0.9, 0.95, 0.5, 0.7]
    observed = np.ones(360, bool)
    np.testing.assert_array_equal(heatline_peaks(scores, observed, 5, threshold=0.0), [12, 359, 100])
    np.testing.assert_array_equal(heatline_peaks(scores, observed, 5, threshold=0.6), [12, 359])
    np.testing.assert_array_equal(heatline_peaks(scores, observed, 15, threshold=0.0), [12, 100])  # 359 near 12
    np.testing.assert_array_equal(heatline_peaks(scores, observed, 5, max_peaks=2), [12, 359])
    observed[12] = False
    assert heatline_peaks(scores, observed, 5)[0] == 10


def test_hard_heatlines_are_binary_detections_of_fixed_width():
    """Fig. 4.8: threshold, non-maximum suppression, binary signal."""
    grid = BearingGrid()
    centres = np.degrees(grid.centers)
    line = np.exp(-0.5 * ((centres - 20.5) / 3) ** 2) + 0.6 * np.exp(-0.5 * ((centres + 49.5) / 3) ** 2)
    scores = np.stack([line, 0.3 * line]).astype(np.float32)
    observed = np.abs(centres) < 90
    heatlines = Heatlines(("a", "b"), scores * observed, observed)
    hard = hard_heatlines(heatlines, {"a": 0.5, "b": 0.5}, nms_deg=5.0, width_deg=3.0)
    assert set(np.unique(hard.scores)) <= {0.0, 1.0}
    ones = np.flatnonzero(hard.scores[0])
    assert len(ones) == 6   # two detections, 3 bins each
    assert set(np.round(centres[ones], 1)) == {19.5, 20.5, 21.5, -50.5, -49.5, -48.5}
    assert not hard.scores[1].any()   # class b never reaches its threshold
    np.testing.assert_array_equal(hard.observed, observed)
