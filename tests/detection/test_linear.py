"""The trained linear window detector: its correlation against direct window sums, training on scenes with known
objects (heat peaks on the objects' centres, not on a look-alike), the model file and the configuration."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semloc_core.detection.config import build_detector, load_linear_model
from semloc_core.detection.features import FeatureParams
from semloc_core.detection.linear import (LinearWindowDetector, LinearWindowModel, TrainingObject, cell_features,
                                          feature_dim, fit_logistic, ignored_cells, train_linear_model, window_at,
                                          window_shape)
from semloc_core.io.detector_models import DetectorModelError, save_linear_model
from tests.detection.synthetic import make_object, paste, textured_background

PARAMS = FeatureParams(cell=4, color_space="hsv")
SCALES = (1.0, 0.7, 0.5)
KINDS = ("clock", "can")


def scene(seed: int, decoy: bool = True):
    """320x240 clutter with a clock and a red can at random places and sizes (40-64 px tall), and a decoy: a plain
    red block as large as the can (the can's colour without its shape)."""
    rng = np.random.default_rng(seed)
    image = textured_background(240, 320, seed=seed)
    objects, boxes = [], []
    for k, kind in enumerate(KINDS):
        while True:
            height = int(rng.integers(40, 65))
            centre = (float(rng.uniform(40, 280)), float(rng.uniform(40, 200)))
            if all(abs(centre[0] - b[0]) > 70 or abs(centre[1] - b[1]) > 70 for b in boxes):
                break
        x, y, w, h = paste(image, make_object(kind, 96), centre, height)
        boxes.append(centre)
        objects.append(TrainingObject(k, (x + w / 2 - 0.5, y + h / 2 - 0.5), (w, h)))
    if decoy:
        while True:
            centre = (float(rng.uniform(30, 290)), float(rng.uniform(30, 210)))
            if all(abs(centre[0] - b[0]) > 60 or abs(centre[1] - b[1]) > 60 for b in boxes):
                break
        x0, y0 = int(centre[0] - 13), int(centre[1] - 26)
        image[max(y0, 0):y0 + 52, max(x0, 0):x0 + 26] = (30, 30, 220)
        return image, objects, centre
    return image, objects, None


@pytest.fixture(scope="module")
def trained() -> LinearWindowModel:
    frames = [scene(seed)[:2] for seed in range(40)]
    return train_linear_model(frames, KINDS, PARAMS, SCALES, window_cells=9, random_negatives=30,
                              hard_negatives=10, rounds=2, seed=0)


def test_scores_equal_the_window_sums_they_stand_for():
    rng = np.random.default_rng(3)
    dim = feature_dim(PARAMS)
    weights = [rng.normal(size=(5, 9, dim)).astype(np.float32), rng.normal(size=(9, 5, dim)).astype(np.float32)]
    model = LinearWindowModel(("a", "b"), weights, [0.5, -1.0], PARAMS, (1.0,))
    detector = LinearWindowDetector(model)
    image, _, _ = scene(7)
    features = cell_features(image, PARAMS)
    scores = detector.feature_scores(features)
    for row, col in [(0, 0), (3, 77), (30, 40), (59, 79), (10, 2)]:
        for c, w in enumerate(weights):
            direct = float(np.sum(window_at(features, row, col, w.shape[:2]) * w) + model.biases[c])
            assert scores[c, row, col] == pytest.approx(direct, abs=1e-3 * max(1.0, abs(direct)))


@pytest.mark.parametrize("aspect, cells, expected", [(1.0, 9, (9, 9)), (2.0, 9, (9, 5)), (0.45, 9, (5, 9)),
                                                     (0.2, 9, (1, 9)), (1.4, 7, (7, 5))])
def test_window_shapes_are_odd_with_the_longer_side_given(aspect, cells, expected):
    assert window_shape(aspect, cells) == expected


def test_logistic_regression_separates_separable_points():
    rng = np.random.default_rng(0)
    positives = rng.normal(1.5, 0.5, (200, 4)).astype(np.float32)
    negatives = rng.normal(-1.5, 0.5, (2000, 4)).astype(np.float32)
    w, b = fit_logistic(positives, negatives, l2=1e-4)
    assert np.mean(positives @ w + b > 0) > 0.99 and np.mean(negatives @ w + b < 0) > 0.99


def test_trained_heat_peaks_on_each_objects_centre_not_on_a_lookalike(trained):
    detector = LinearWindowDetector(trained)
    centred = decoy_wins = 0
    trials = range(100, 120)
    for seed in trials:   # frames never trained on
        image, objects, decoy = scene(seed)
        heat = detector.heatmaps(image)
        assert heat.shape == (2, 60, 80) and heat.dtype == np.float32 and 0 <= heat.min() <= heat.max() <= 1
        for obj in objects:
            row, col = np.unravel_index(np.argmax(heat[obj.class_index]), heat.shape[1:])
            # output cell (row, col) covers pixels [4 col, 4 col + 4): its centre is 4 col + 1.5 in pixel centres
            offset = np.hypot(4 * col + 1.5 - obj.centre[0], 4 * row + 1.5 - obj.centre[1])
            centred += offset <= 6.0
        can = KINDS.index("can")
        at_decoy = heat[can, int(decoy[1] // 4), int(decoy[0] // 4)]
        at_can = heat[can].max()
        decoy_wins += at_decoy >= at_can
    assert centred >= 0.9 * 2 * len(trials), centred
    assert decoy_wins == 0


def test_model_file_round_trips_and_configures_the_detector(trained, tmp_path):
    path = save_linear_model(tmp_path / "model.npz", trained)
    loaded = load_linear_model(path)
    assert loaded.classes == trained.classes and loaded.scales == trained.scales and loaded.params == trained.params
    for a, b in zip(loaded.weights, trained.weights):
        assert np.array_equal(a, b)
    assert np.array_equal(loaded.biases, trained.biases)
    with np.load(path, allow_pickle=False) as data:   # no pickle inside
        assert set(data.files) == {"meta", "biases", "weights_0", "weights_1"}
    (tmp_path / "detector.yaml").write_text("kind: linear\nmodel: model.npz\nclasses: [can]\n")
    detector = build_detector(tmp_path / "detector.yaml")
    image, _, _ = scene(123)
    expected = LinearWindowDetector(trained).heatmaps(image)[1]
    assert detector.classes == ("can",)
    assert np.allclose(detector.heatmaps(image)[0], expected, atol=1e-6)   # FFT sizes differ with one class


def _rewrite(path, **changes):
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    meta = json.loads(arrays["meta"].tobytes().decode())
    for key, value in changes.items():
        if key in meta:
            meta[key] = value
        else:
            arrays[key] = value
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)


@pytest.mark.parametrize("change, message", [
    ({"format": "something-else"}, "not a semloc-linear-window-detector"),
    ({"version": 99}, "model version 99"),
    ({"weights_1": np.zeros((4, 9, 3), np.float32)}, "filter of 'can'"),
    ({"biases": np.array([np.nan, 0.0], np.float32)}, "finite bias"),
    ({"scales": []}, "scales"),
])
def test_a_damaged_model_file_is_refused_with_the_reason(trained, tmp_path, change, message):
    path = save_linear_model(tmp_path / "model.npz", trained)
    _rewrite(path, **change)
    with pytest.raises(DetectorModelError, match=message):
        load_linear_model(path)


def test_a_file_that_is_no_model_is_refused(tmp_path):
    path = tmp_path / "model.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(DetectorModelError, match="not a readable linear detector model"):
        load_linear_model(path)
    (tmp_path / "bad.yaml").write_text("kind: linear\nmodel: model.npz\n")
    with pytest.raises(DetectorModelError):
        build_detector(tmp_path / "bad.yaml")


@pytest.mark.parametrize("radius, ignored_offsets", [(0.25, range(6)), (0.1, range(3)), (0.04, range(1))])
def test_windows_within_the_radius_of_a_centre_are_neither_positive_nor_negative(radius, ignored_offsets):
    # an 80 x 40 px box centred on cell (10, 12)'s centre, 4 px cells: radius x 80 px reaches 20 px = 5 cells at
    # 0.25, 2 cells at 0.1 and less than one at 0.04 (only the centre's own cell: the positive)
    centre = (12 * 4 + 1.5, 10 * 4 + 1.5)
    objects = [TrainingObject(0, centre, (80.0, 40.0)), TrainingObject(1, (0.0, 0.0), (400.0, 400.0))]
    mask = ignored_cells(objects, 0, (120, 160), (30, 40), 4, radius)
    offsets = {q - 12 for q in range(40) if mask[10, q]}
    assert offsets == {o for d in ignored_offsets for o in (d, -d)}
    assert not mask[0, 0]          # the other class's object keeps nothing out of this class's negatives


def test_training_without_an_example_of_a_class_says_which():
    image, objects, _ = scene(1, decoy=False)
    with pytest.raises(ValueError, match="no positive example of \\['bottle'\\]"):
        train_linear_model([(image, objects)], KINDS + ("bottle",), PARAMS, SCALES, random_negatives=2, rounds=0)


def test_train_detector_command_writes_a_model_the_evaluation_can_use(tmp_path, capsys):
    from services.cli import main

    out = tmp_path / "model"
    settings = ["trajectories=[orbit:100]", "frames=40", "stride=8", "rounds=1", "random_negatives=10",
                "hard_negatives=5"]
    code = main(["train-detector", "tabletop", "-o", str(out), "--quiet", *(a for s in settings for a in ("--set", s))])
    assert code == 0
    info = json.loads((out / "training.json").read_text())
    assert set(info["classes"]) == {"bowl", "cap", "cereal_box", "coffee_mug", "soda_can"}
    assert all(stats["positives"] > 0 for stats in info["classes"].values())
    detector = build_detector(out / "detector.yaml")
    heat = detector.heatmaps(np.zeros((480, 640, 3), np.uint8))
    assert heat.shape == (5, 120, 160) and np.isfinite(heat).all()
    for setting, message in [("stride=0", "stride: Input should be greater than or equal to 1"),
                             ("l2=0", "l2: Input should be greater than 0"), ("rounds=-1", "rounds"),
                             ("max_occluded=2", "max_occluded"), ("clutter=-1", "clutter"),
                             ("ignore_radius=-0.1", "ignore_radius"), ("no_such=1", "no_such")]:
        assert main(["train-detector", "tabletop", "-o", str(tmp_path / "x"), "--set", setting]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_heatmap_caches_of_two_trained_models_do_not_collide(trained, tmp_path):
    from semloc_core.experiments.heatmap_sources import detector_cache_name

    names = []
    for folder, bias in (("a", 0.0), ("b", 1.0)):
        model = LinearWindowModel(trained.classes, trained.weights, trained.biases + bias, trained.params,
                                  trained.scales)
        save_linear_model(tmp_path / folder / "model.npz", model)
        (tmp_path / folder / "detector.yaml").write_text("kind: linear\nmodel: model.npz\n")
        names.append(detector_cache_name(str(tmp_path / folder / "detector.yaml")))
    assert names[0] != names[1] and all(n.startswith("detector-") for n in names)
    assert detector_cache_name(str(tmp_path / "a" / "detector.yaml")) == names[0]
    assert detector_cache_name("templates-hsv") == "templates-hsv"


def test_the_heatmap_is_the_max_of_the_level_heatmaps(trained):
    detector = LinearWindowDetector(trained)
    image, _, _ = scene(5)
    levels = detector.level_heatmaps(image)
    assert levels.shape == (len(trained.classes), len(trained.scales)) + detector.output_shape(image.shape)
    np.testing.assert_array_equal(detector.heatmaps(image), levels.max(axis=1))
    assert levels.min() >= 0 and levels.max() <= 1
