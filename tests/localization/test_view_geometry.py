"""ViewGeometry.from_camera against ground truth: per bearing bin, the elevations the image covers, for a pinhole
camera (level, and tilted by a frame's attitude), a wide panorama and a rig, from coarse to fine bins.

The reference is computed the other way round, independently of the rays through pixels that ``from_camera``
follows: directions (bearing, elevation) on a dense grid are *projected* into each camera (``project_cam``), and
where a bearing's meridian enters and leaves the image is refined by bisection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera, forward_extrinsic, members
from semloc_core.geometry import make_transform, rotation_about_x, rotation_about_y
from semloc_core.localization import ViewGeometry

PIXEL = 1.0 / PinholeCamera.from_fov(640, 480, 60.0).K[1, 1]  # the pinhole's pixel, radians at its centre
TILT = make_transform(rotation_about_x(math.radians(8.0)) @ rotation_about_y(math.radians(25.0)),
                      (0, 0, 0)) @ forward_extrinsic()  # pitched down 25 degrees, rolled 8

CAMERAS = {
    "pinhole": (PinholeCamera.from_fov(640, 480, 60.0), None),
    "tilted pinhole": (PinholeCamera.from_fov(640, 480, 60.0), TILT),  # the attitude as a frame's override
    "hall panorama": (EquirectangularCamera(4096, 1024), None),
    "rig": (CameraRig.ring(3, 640, 480, 90.0), None),  # three 90-degree cameras: gaps between them
}


def _directions(bearing, elevation):
    bearing, elevation = np.broadcast_arrays(bearing, elevation)
    return np.stack([np.cos(elevation) * np.cos(bearing), np.cos(elevation) * np.sin(bearing), np.sin(elevation)], -1)


def _reference_spans(camera, attitude, n_bins: int, per_bin: int, n_elevations: int = 361):
    """(low, high, covered) at ``per_bin`` + 1 bearings across each bin (its edges included): the lowest and highest
    elevations whose direction projects inside an image, and whether each sampled bearing reaches one."""
    bearings = (-np.pi + 2 * np.pi / n_bins * np.arange(n_bins)[:, None]
                + 2 * np.pi / n_bins * np.linspace(0, 1, per_bin + 1)[None, :]).reshape(-1)
    grid = np.linspace(-np.pi / 2, np.pi / 2, n_elevations)
    low = np.full(bearings.size, np.inf)
    high = np.full(bearings.size, -np.inf)
    for member in members(camera):
        R = (member.T_body_cam if attitude is None else attitude)[:3, :3]

        def inside(bearing, elevation):
            return member.project_cam(_directions(bearing, elevation) @ R)[1]

        hits = inside(bearings[:, None], grid[None, :])
        found = hits.any(axis=1)
        rows = np.flatnonzero(found)
        first = hits[rows].argmax(axis=1)
        last = n_elevations - 1 - hits[rows, ::-1].argmax(axis=1)
        for index, outward, extreme in ((first, -1, low), (last, 1, high)):
            # bisection between the last grid elevation outside and the first inside (the grid's end: it is the pole)
            a = grid[index]
            b = grid[np.clip(index + outward, 0, n_elevations - 1)]
            for _ in range(40):
                middle = 0.5 * (a + b)
                keep = inside(bearings[rows], middle)
                a, b = np.where(keep, middle, a), np.where(keep, b, middle)
            if extreme is low:
                low[rows] = np.minimum(low[rows], a)
            else:
                high[rows] = np.maximum(high[rows], a)
    covered = np.isfinite(low)
    shape = (n_bins, per_bin + 1)
    return low.reshape(shape), high.reshape(shape), covered.reshape(shape)


@pytest.mark.parametrize("n_bins", [72, 360, 1440])
@pytest.mark.parametrize("name", list(CAMERAS))
def test_every_bin_the_camera_covers_has_its_elevation_span(name, n_bins):
    camera, attitude = CAMERAS[name]
    view = ViewGeometry.from_camera(camera, n_bins, camera_height=1.0, T_body_cam=attitude)
    low, high, covered = _reference_spans(camera, attitude, n_bins, per_bin=max(6, 2880 // n_bins))
    has_span = view.elevation_low <= view.elevation_high
    reached = covered.any(axis=1)
    whole = covered.all(axis=1)
    # a bin the image reaches at any of its sampled bearings has a span that holds what the image shows there
    assert has_span[reached].all(), f"bins without a span: {np.flatnonzero(reached & ~has_span)}"
    tolerance = 0.05 * PIXEL  # a twentieth of a pixel
    ref_low = np.where(covered, low, np.inf).min(axis=1)
    ref_high = np.where(covered, high, -np.inf).max(axis=1)
    assert np.all(view.elevation_low[reached] <= ref_low[reached] + tolerance)
    assert np.all(view.elevation_high[reached] >= ref_high[reached] - tolerance)
    # a bin the image covers across its width: the span is the reference's (between sampled bearings the elevation
    # of the border moves by less than a pixel)
    np.testing.assert_allclose(view.elevation_low[whole], ref_low[whole], atol=0.5 * PIXEL)
    np.testing.assert_allclose(view.elevation_high[whole], ref_high[whole], atol=0.5 * PIXEL)
    # bins the image does not reach, nor their neighbours (a sliver between sampled bearings), stay empty
    far = ~(reached | np.roll(reached, 1) | np.roll(reached, -1))
    assert not has_span[far].any(), f"bins out of view with a span: {np.flatnonzero(far & has_span)}"
    if name == "hall panorama":
        assert whole.all()
        np.testing.assert_allclose(view.elevation_high, camera.lat_top, atol=1e-12)  # the top row's upper edge
        np.testing.assert_allclose(view.elevation_low, camera.lat_bottom, atol=1e-12)
    elif name == "pinhole":  # a level pinhole reaches its horizontal field of view, whatever the bins' width
        fov = camera.horizontal_fov
        centres = -np.pi + 2 * np.pi / n_bins * (np.arange(n_bins) + 0.5)
        np.testing.assert_array_equal(has_span[np.abs(centres) < 0.5 * fov - 2 * np.pi / n_bins], True)
        assert not has_span[np.abs(centres) > 0.5 * fov + 2 * np.pi / n_bins].any()
    else:
        assert not whole.all() and whole.any()  # parts of the circle in view, parts not


def test_a_pole_in_the_image_reaches_every_bearing():
    """A camera looking straight up sees the zenith: every bearing's meridian ends in its image."""
    up = make_transform(rotation_about_y(math.radians(-90.0)), (0, 0, 0)) @ forward_extrinsic()
    camera = PinholeCamera.from_fov(640, 480, 60.0, T_body_cam=up)
    view = ViewGeometry.from_camera(camera, 360, camera_height=1.0)
    np.testing.assert_array_equal(view.elevation_high, np.pi / 2)
    low, _, covered = _reference_spans(camera, None, 360, per_bin=4)
    assert covered.all()
    np.testing.assert_allclose(view.elevation_low, low.min(axis=1), atol=0.5 * PIXEL)
