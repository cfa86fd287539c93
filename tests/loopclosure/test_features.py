"""Bearing-sorted SIFT sequences: descriptor scale, bearings through each camera model, rig merging."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera
from semloc_core.geometry import angle_diff
from semloc_core.loopclosure.features import (
    DESCRIPTOR_SCALE,
    FeatureParams,
    FeatureSequence,
    extract_features,
    l1_match_matrix,
    normalize_descriptors,
    suppress_repeated,
)
from semloc_core.loopclosure.similarity import dp_similarity, ratio_test_matches
from semloc_core.loopclosure.warmup import synthetic_wall


def test_normalize_descriptors_puts_any_scale_on_vlfeat_scale():
    rng = np.random.default_rng(0)
    unit = rng.random((20, 128))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    a = normalize_descriptors(unit)
    b = normalize_descriptors(unit * 37.0)
    assert a.dtype == np.uint8 and np.array_equal(a, b)
    assert np.allclose(np.linalg.norm(a.astype(float), axis=1), DESCRIPTOR_SCALE, rtol=0.01)


@pytest.mark.parametrize("bad", [np.zeros((3, 64)), -np.ones((2, 128)), np.full((1, 128), np.nan)])
def test_normalize_descriptors_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        normalize_descriptors(bad)


def test_opencv_descriptors_are_already_on_the_thesis_scale():
    _, desc = cv2.SIFT_create().detectAndCompute(cv2.cvtColor(synthetic_wall(160, 120, 1), cv2.COLOR_BGR2GRAY), None)
    assert desc is not None and len(desc) > 20
    assert np.allclose(np.linalg.norm(desc, axis=1), DESCRIPTOR_SCALE, rtol=0.01)
    assert np.array_equal(desc, np.rint(desc)) and desc.max() <= 255
    assert np.array_equal(normalize_descriptors(desc), desc.astype(np.uint8))


def test_pinhole_bearings_follow_the_columns():
    camera = PinholeCamera.from_fov(160, 120, 70.0)
    seq = extract_features(synthetic_wall(160, 120, 2), camera)
    assert len(seq) > 20
    assert np.all(np.diff(seq.bearings) >= 0)
    # Level camera along body x: bearing = -atan((u - cx) / fx); right of centre is negative.
    expected = -np.arctan2(seq.points[:, 0] - camera.K[0, 2], camera.K[0, 0])
    assert np.allclose(seq.bearings, expected, atol=1e-6)
    assert np.all(np.abs(seq.bearings) <= camera.horizontal_fov / 2 + 1e-6)


def test_rig_merges_members_in_bearing():
    rig = CameraRig.ring(4, 120, 90, 80.0)
    images = [synthetic_wall(120, 90, 10 + k) for k in range(4)]
    params = FeatureParams(repeated_threshold=0)
    seq = extract_features(images, rig, params)
    assert set(np.unique(seq.camera_index).tolist()) == {0, 1, 2, 3}
    assert np.all(np.diff(seq.bearings) >= 0)
    for k in range(4):
        own = seq.bearings[seq.camera_index == k]
        # Camera k looks along yaw 2*pi*k/4: its features lie within its half field of view of that yaw.
        assert np.all(np.abs(angle_diff(own, 2 * np.pi * k / 4)) <= np.radians(40) + 1e-6)
        alone = extract_features(images[k], rig.cameras[k], params)
        assert len(alone) == len(own)


def test_equirectangular_roll_shifts_bearings_and_keeps_the_dp_score():
    camera = EquirectangularCamera(256, 64)
    panorama = synthetic_wall(256, 64, 5)
    shift = 64  # a quarter turn
    a = extract_features(panorama, camera)
    b = extract_features(np.roll(panorama, shift, axis=1), camera)
    assert len(a) > 30
    # Rolling the panorama right by s columns moves every feature right, i.e. by -s/W * 2 pi in bearing.
    match = ratio_test_matches(a, b, 0.7)
    hits = match >= 0
    assert hits.sum() > 0.5 * len(a)
    error = angle_diff(b.bearings[match[hits]], a.bearings[hits] - 2 * np.pi * shift / 256)
    assert np.mean(np.abs(error) < 0.01) > 0.9
    assert dp_similarity(b, a) >= 0.8 * dp_similarity(a, a)


@pytest.mark.parametrize(
    "image, message",
    [(np.zeros((100, 160, 3), np.uint8), "camera model is"), (np.zeros((120, 160), np.float32), "uint8")],
)
def test_bad_images_raise(image, message):
    with pytest.raises(ValueError, match=message):
        extract_features(image, PinholeCamera.from_fov(160, 120, 60.0))


def test_rig_needs_one_image_per_member():
    rig = CameraRig.ring(3, 64, 48, 90.0)
    with pytest.raises(ValueError, match="3 images"):
        extract_features([synthetic_wall(64, 48, 0)] * 2, rig)


def test_max_features_caps_each_image():
    seq = extract_features(synthetic_wall(160, 120, 3), PinholeCamera.from_fov(160, 120, 60.0), FeatureParams(max_features=15))
    assert 0 < len(seq) <= 15 + 3  # OpenCV keeps ties at the cut


def test_sequence_validation():
    with pytest.raises(ValueError, match="uint8"):
        FeatureSequence(np.zeros(2), np.zeros((2, 128)))
    with pytest.raises(ValueError, match="sorted"):
        FeatureSequence(np.array([0.5, 0.1]), np.zeros((2, 128), np.uint8))
    seq = FeatureSequence.from_unsorted([0.5, 0.1, 4.0], np.eye(3, 128, dtype=np.uint8))
    assert np.all(np.diff(seq.bearings) >= 0) and np.all(seq.bearings < np.pi)


def test_repeated_features_are_suppressed():
    rng = np.random.default_rng(4)
    unique = normalize_descriptors(rng.gamma(0.6, 1.0, (20, 128)))
    repeated = np.repeat(normalize_descriptors(rng.gamma(0.6, 1.0, (3, 128))), 4, axis=0)  # 3 textures x 4
    seq = FeatureSequence.from_unsorted(rng.uniform(-3, 3, 32), np.concatenate([unique, repeated]))
    kept = suppress_repeated(seq, 1000.0)
    assert len(kept) == 20
    assert {tuple(d) for d in kept.descriptors} == {tuple(d) for d in unique}
    assert len(suppress_repeated(seq, 0.0)) == 32


@pytest.mark.parametrize("threshold", [1000.0, 1700.0, 3000.0, 6000.0])
def test_repeated_texture_test_is_the_full_match_matrix(threshold):
    """The pairwise test with its lower bound drops exactly the features the full L1 match matrix finds a second
    match for: textures repeated with noise of several sizes, so pairs fall on both sides of each threshold."""
    rng = np.random.default_rng(int(threshold))
    textures = normalize_descriptors(rng.gamma(0.6, 1.0, (12, 128)))
    noisy = [np.clip(t.astype(np.int32) + rng.integers(-s, s + 1, 128), 0, 255)
             for t, s in zip(np.repeat(textures, 3, axis=0), np.tile([2, 8, 20, 40, 60, 90], 6))]
    descriptors = np.concatenate([normalize_descriptors(rng.gamma(0.6, 1.0, (40, 128))),
                                  np.array(noisy, np.uint8)])
    seq = FeatureSequence.from_unsorted(rng.uniform(-3, 3, len(descriptors)), descriptors)
    full = l1_match_matrix(seq.descriptors, seq.descriptors, threshold).sum(axis=1) > 1
    kept = suppress_repeated(seq, threshold)
    assert full.any()
    assert np.array_equal(kept.descriptors, seq.descriptors[~full])
