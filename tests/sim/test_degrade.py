"""Image degradations (issue 33): each does what it says, and the fisheye model is the lens the warp applied."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.camera import FisheyeCamera, PinholeCamera
from semloc_core.sim.degrade import PRESETS, RIM_LEVEL, Degradation, _fisheye_maps, degrade, fisheye_camera


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(3)
    return np.clip(rng.normal(128, 40, (384, 512, 3)), 0, 255).astype(np.uint8)


def test_identity_returns_the_image(image):
    assert degrade(image, 0, 10, Degradation()) is image


def test_downscale_and_jpeg_keep_the_size_asked(image):
    out = degrade(image, 0, 10, Degradation(size=(160, 120), jpeg_quality=60))
    assert out.shape == (120, 160, 3) and out.dtype == np.uint8


def test_exposure_changes_the_second_half_only(image):
    d = Degradation(exposure=0.5)
    assert np.array_equal(degrade(image, 4, 10, d), image)
    darker = degrade(image, 5, 10, d)
    assert abs(darker.mean() - 0.5 * image.mean()) < 2


def test_noise_is_deterministic_per_frame(image):
    d = Degradation(noise_sigma=5.0, seed=1)
    a, b, c = degrade(image, 3, 10, d), degrade(image, 3, 10, d), degrade(image, 4, 10, d)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert 3 < np.std(a.astype(float) - image) < 7


def test_body_overlay_is_fixed_and_dark_along_the_bottom(image):
    d = Degradation(body=0.25)
    first, later = degrade(image, 0, 10, d), degrade(np.roll(image, 50, axis=1), 7, 10, d)
    bottom = (slice(370, 384), slice(200, 312))
    assert np.array_equal(first[bottom], later[bottom])
    assert first[bottom].mean() < 60
    assert not np.array_equal(first[:100], later[:100])


def test_fisheye_rim_is_dark_outside_the_image_circle(image):
    d = Degradation(fisheye=True)
    out = degrade(image, 0, 10, d).astype(float)
    v, u = np.mgrid[0:384, 0:512]
    r = np.hypot(u - 255.5, v - 191.5)
    radius = 0.5 * d.fisheye_circle * 384
    assert np.all(np.abs(out[r > radius + 1.5] - RIM_LEVEL) < 1)
    assert out[r < radius - 2].mean() > 80


@pytest.mark.parametrize("fov", [None, 100.0])
def test_fisheye_model_gives_the_rays_the_warp_sampled(fov):
    """Ground truth: the pixel of the fisheye image shows what the source pinhole saw along the warp's ray, so the
    fisheye model's ray must be the source camera's ray through the sampled pixel."""
    d = Degradation(fisheye=True, fisheye_fov_deg=fov, source_fov_deg=60.0)
    map_x, map_y, inside = _fisheye_maps(d, 512, 384, 512, 384)
    fisheye = fisheye_camera(d, 512, 384)
    assert isinstance(fisheye, FisheyeCamera)
    source = PinholeCamera(512, 384, np.array([[0.5 * 512 / np.tan(np.radians(30)), 0, 255.5],
                                               [0, 0.5 * 512 / np.tan(np.radians(30)), 191.5], [0, 0, 1]]))
    rng = np.random.default_rng(0)
    v, u = rng.integers(0, 384, 2000), rng.integers(0, 512, 2000)
    mx, my = map_x[v, u], map_y[v, u]
    keep = (inside[v, u] > 0.99) & (mx >= 0) & (mx <= 511) & (my >= 0) & (my <= 383)
    assert keep.sum() > 100
    rays_fisheye = fisheye.rays_cam(u[keep].astype(float), v[keep].astype(float))
    rays_source = source.rays_cam(map_x[v, u][keep], map_y[v, u][keep])
    assert np.max(np.degrees(np.arccos(np.clip(np.sum(rays_fisheye * rays_source, axis=1), -1, 1)))) < 0.05


def test_fisheye_camera_matches_opencv_and_projects_back():
    import cv2

    K = np.array([[90.0, 0, 80], [0, 90, 60], [0, 0, 1]])
    dist = np.array([0.04, -0.01, 0.003, -0.0005])
    camera = FisheyeCamera(160, 120, K, dist)
    uv = np.array([[3.0, 4.0], [80.0, 60.0], [150.0, 110.0], [40.0, 100.0]])
    rays = camera.rays_cam(uv[:, 0], uv[:, 1])
    normalized = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    expected = np.c_[normalized, np.ones(len(uv))]
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    assert np.allclose(rays, expected, atol=1e-9)
    back, inside = camera.project_cam(rays)
    assert np.allclose(back, uv, atol=1e-6) and inside.all()


@pytest.mark.parametrize("bad", [dict(size=(8, 8)), dict(body=0.7), dict(exposure=0.0), dict(jpeg_quality=101),
                                 dict(fisheye_fov_deg=-1.0)])
def test_bad_degradations_are_refused(bad):
    with pytest.raises(ValueError):
        Degradation(**bad)


def test_presets_are_valid_and_robot_has_them_all():
    robot = PRESETS["robot"]
    assert robot.size == (160, 120) and robot.fisheye and robot.body > 0 and robot.exposure != 1
    assert PRESETS["none"].is_identity
