"""HOGE and HQC block features (§4.3.1, §4.3.2) against their definitions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.detection.features import FeatureParams, fit_to_cells, hoge, hqc, quantise_colours
from tests.detection.reference import hoge_reference, hqc_reference
from tests.detection.synthetic import make_object, paste, textured_background


@pytest.fixture(scope="module")
def scene() -> np.ndarray:
    image = textured_background(240, 320, seed=3)
    paste(image, make_object("clock"), (100, 120), 90)
    paste(image, make_object("machine"), (240, 110), 120)
    return image


@pytest.mark.parametrize("gain, offset", [(1.0, 40.0), (0.4, 0.0), (1.8, -60.0), (0.25, 100.0)])
def test_hoge_invariant_to_brightness(scene, gain, offset):
    """§4.3.1: band-pass filtering removes an additive bias, the normalisation a multiplicative one."""
    grey = cv2.cvtColor(scene, cv2.COLOR_BGR2GRAY).astype(np.float32)
    params = FeatureParams()
    original = hoge(grey, params)
    changed = hoge(grey * np.float32(gain) + np.float32(offset), params)
    assert np.abs(changed - original).max() <= 1e-3


def test_hoge_is_a_histogram_with_a_no_structure_bin(scene):
    params = FeatureParams()
    histogram = hoge(scene, params)
    assert histogram.shape == (240 // 8, 320 // 8, params.orientations + 1)
    assert np.all(histogram >= 0)
    np.testing.assert_allclose(histogram.sum(axis=-1), 1.0, atol=1e-5)
    flat = hoge(np.full((64, 64), 128, np.uint8), params)
    np.testing.assert_allclose(flat[..., -1], 1.0, atol=1e-6)  # no structure at all: everything in the epsilon bin


@pytest.mark.parametrize("angle_deg", [0.0, 45.0, 90.0, 135.0])
def test_hoge_dominant_orientation_follows_the_pattern(angle_deg):
    """A grating whose intensity varies along direction theta puts its energy in the theta bin."""
    params = FeatureParams()
    v, u = np.mgrid[0:128, 0:128].astype(np.float64)
    theta = np.radians(angle_deg)
    grating = 128 + 100 * np.sin(2 * np.pi * (u * np.cos(theta) + v * np.sin(theta)) / 7.0)
    histogram = hoge(grating.astype(np.float32), params)
    expected_bin = int(round(angle_deg / (180.0 / params.orientations))) % params.orientations
    inner = histogram[2:-2, 2:-2, :-1]
    assert np.all(inner.argmax(axis=-1) == expected_bin)


def test_hoge_fast_equals_reference(scene):
    params = FeatureParams(cell=6, sigma=1.3)
    image = fit_to_cells(scene, 1.0, params.cell)
    np.testing.assert_allclose(hoge(image, params), hoge_reference(image, params), atol=1e-5)


@pytest.mark.parametrize("shape, dtype", [((4, 4), np.uint8), ((8, 4), np.float32), ((4, 12), np.uint8),
                                          ((12, 20), np.float32), ((36, 28), np.uint8)])
def test_hoge_at_borders_and_on_images_smaller_than_the_filter(shape, dtype):
    """The filtering keeps a ring of the image rows in reach and reflects at the borders as OpenCV does (101), also
    where the filter is longer than the image (reflected more than once)."""
    params = FeatureParams(cell=4)
    image = (np.random.default_rng(shape[0]).uniform(0, 255, shape)).astype(dtype)
    np.testing.assert_allclose(hoge(image, params), hoge_reference(image, params), atol=1e-5)


def test_hqc_maps_to_nearest_palette_colour_and_counts_blocks(scene):
    params = FeatureParams()
    levels = params.color_levels
    palette = np.linspace(0, 255, levels)
    values = np.array([0, 42, 43, 127, 128, 212, 213, 255], np.uint8)
    pixel = np.stack(np.meshgrid(values, values, values, indexing="ij"), axis=-1).reshape(1, -1, 3)
    index = quantise_colours(pixel, levels)[0]
    nearest = np.abs(pixel[0, :, :, None].astype(float) - palette).argmin(axis=-1)
    np.testing.assert_array_equal(index, (nearest[:, 0] * levels + nearest[:, 1]) * levels + nearest[:, 2])
    np.testing.assert_allclose(hqc(scene, params), hqc_reference(scene, params), atol=1e-6)


def test_hsv_colours_ignore_brightness_and_match_the_reference(scene):
    params = FeatureParams(color_space="hsv")
    assert params.hqc_bins == 8 + 6 * 4
    np.testing.assert_allclose(hqc(scene, params), hqc_reference(scene, params), atol=1e-6)
    paint = np.zeros((8, 8, 3), np.uint8)
    paint[:] = (40, 160, 60)                       # a saturated green ...
    dimmer = (paint * 0.6).astype(np.uint8)        # ... under 60 % of the light
    np.testing.assert_allclose(hqc(paint, params), hqc(dimmer, params), atol=0.02)
    assert not np.array_equal(hqc(paint, FeatureParams()), hqc(dimmer, FeatureParams()))   # rgb changes bin
    # Red on both sides of the hue circle's seam (OpenCV hue 2 and 178) shares the red bin's weight.
    left, right = np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8, 3), np.uint8)
    left[:] = cv2.cvtColor(np.uint8([[[2, 200, 200]]]), cv2.COLOR_HSV2BGR)[0, 0]
    right[:] = cv2.cvtColor(np.uint8([[[178, 200, 200]]]), cv2.COLOR_HSV2BGR)[0, 0]
    overlap = np.sqrt(hqc(left, params) * hqc(right, params)).sum()   # Bhattacharyya coefficient of one block
    assert overlap > 0.85


def test_hqc_mask_counts_object_pixels_only():
    params = FeatureParams(cell=4)
    image = np.zeros((8, 8, 3), np.uint8)
    image[:, :, 2] = 255                      # red everywhere ...
    image[:2, :2] = (255, 0, 0)               # ... but a blue corner in the first block
    mask = np.ones((8, 8), bool)
    mask[:2, :2] = False                      # which the mask excludes
    mask[4:, 4:] = False                      # and an empty block
    histogram = hqc(image, params, mask=mask)
    red = (0 * 4 + 0) * 4 + 3
    assert histogram[0, 0, red] == pytest.approx(1.0)
    assert histogram[1, 1].sum() == 0.0
    unmasked = hqc(image, params)
    blue = (3 * 4 + 0) * 4 + 0
    assert unmasked[0, 0, blue] == pytest.approx(4 / 16)


@pytest.mark.parametrize("bad", [np.zeros((10, 16), np.uint8), np.zeros((16, 16, 2), np.uint8)])
def test_features_reject_bad_input(bad):
    with pytest.raises(ValueError):
        hoge(bad, FeatureParams())
    with pytest.raises(ValueError):
        hqc(bad, FeatureParams())
