"""Recognised places in the localization experiment (semloc_core.experiments.localization_places): the loop-closure
features of a sequence, each frame computed once and cached by frame index, the re-entry figures of a filter
re-initialised or kidnapped, and a prior lap's places recognised by a kidnapped second traversal."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.experiments.localization_places import reentry_figures, sequence_features


class _Counting:
    """A dataset that counts the frames it renders."""

    def __init__(self, dataset):
        self.dataset = dataset
        self.camera = dataset.camera
        self.options = dataset.options
        self.rendered: list[int] = []

    def image(self, index: int):
        self.rendered.append(int(index))
        return self.dataset.image(index)

    def T_body_cam_at(self, index: int):
        return self.dataset.T_body_cam_at(index)


def _same(a, b) -> bool:
    return (np.array_equal(a.bearings, b.bearings) and np.array_equal(a.descriptors, b.descriptors)
            and np.array_equal(a.points, b.points))


def test_features_of_a_carried_back_sequence_are_each_frames_own_computed_once_and_cached(sim_scenario, tmp_path):
    from semloc_core.loopclosure import FeatureParams, extract_features

    hall = sim_scenario("hall", frames=6, camera="panorama:512x128")
    carried_back = [0, 1, 2, 3, 1, 2]  # kidnapped at 4 back by 3 positions: frames 1 and 2 again
    cache = tmp_path / "features.npz"
    counting = _Counting(hall)
    features = sequence_features(counting, carried_back, cache, lambda _: None)
    assert sorted(counting.rendered) == [0, 1, 2, 3] and cache.exists()
    fresh = {i: extract_features(hall.image(i), hall.camera, FeatureParams(), hall.T_body_cam_at(i)) for i in range(4)}
    assert len(features) == len(carried_back)
    assert all(_same(f, fresh[i]) for f, i in zip(features, carried_back))
    assert len(features[1].bearings) > 0  # a panorama of the hall has texture to match

    # a sequence of cached frames renders nothing; one with new frames renders only those and extends the cache
    again = _Counting(hall)
    assert all(_same(a, b) for a, b in zip(sequence_features(again, [3, 2, 1], cache, lambda _: None),
                                            [fresh[3], fresh[2], fresh[1]]))
    assert again.rendered == []
    more = _Counting(hall)
    extended = sequence_features(more, [4, 0, 5], cache, lambda _: None)
    assert more.rendered == [4, 5] and _same(extended[1], fresh[0])
    last = _Counting(hall)
    sequence_features(last, list(range(6)), cache, lambda _: None)
    assert last.rendered == []


def test_features_cached_for_one_look_of_a_scene_are_not_served_for_another(tmp_path):
    """A scene textured with the data folder's object crops and one with generated looks (no data folder) share
    their poses and map, not their pixels: the cache of one is not served for the other."""
    from semloc_core.sim import make_scenario

    cache = tmp_path / "features.npz"
    generated = _Counting(make_scenario("tabletop", seed=0, frames=3))
    sequence_features(generated, [0, 1], cache, lambda _: None)
    crop = np.full((40, 40, 3), 90, np.uint8)
    crop[10:30, 10:30] = 200
    textured = _Counting(make_scenario("tabletop", seed=0, frames=3, crops={"bowl": crop}))
    sequence_features(textured, [0, 1], cache, lambda _: None)
    assert textured.rendered == [0, 1]
    again = _Counting(make_scenario("tabletop", seed=0, frames=3, crops={"bowl": crop}))
    sequence_features(again, [0, 1], cache, lambda _: None)
    assert again.rendered == []


def test_reentry_counts_from_the_restart_and_from_the_first_recognised_place():
    errors = np.r_[np.full(20, 0.1), np.full(6, 9.0), np.full(3, 0.8), np.full(21, 0.2)]  # restart at 20
    figures = reentry_figures(errors, 20, recognised=[5, 23, 30], thresholds=(0.5, 1.0), hold=10)
    assert figures["start"] == 20 and figures["recognised_at"] == 23  # the places before the restart do not count
    assert figures["thresholds"]["0.5"] == {"settled_at": 29, "frames_from_start": 9, "frames_from_recognised": 6}
    assert figures["thresholds"]["1.0"] == {"settled_at": 26, "frames_from_start": 6, "frames_from_recognised": 3}
    unseen = reentry_figures(errors[:32], 20, recognised=[], thresholds=(0.5,), hold=10)
    assert unseen["recognised_at"] is None
    assert unseen["thresholds"]["0.5"] == {"settled_at": 29, "frames_from_start": 9, "frames_from_recognised": None}
    never = reentry_figures(np.full(40, 3.0), 20, recognised=[21], thresholds=(0.5,))
    assert never["thresholds"]["0.5"]["settled_at"] is None


@pytest.mark.parametrize("bad", [{"reinit": 0}, {"reinit": 12, "frames": 12}])
def test_a_reinitialisation_outside_the_sequence_is_refused(bad):
    from semloc_core.experiments.localization import LocalizationSpec

    with pytest.raises(ValueError, match="reinit"):
        LocalizationSpec(dataset="sim:hall", **bad)


@pytest.mark.parametrize("bad, message", [({"prior_lap": True}, "needs places"),
                                          ({"prior_lap": True, "places": True, "second_traversal": "small"},
                                           "camera model"),
                                          ({"prior_lap": True, "places": True, "second_traversal": "fisheye"},
                                           "camera model"),
                                          ({"prior_lap": True, "places": True, "second_traversal": "dusk"},
                                           "unknown degradation")])
def test_a_prior_lap_needs_places_and_a_second_traversal_that_keeps_the_camera(bad, message):
    from semloc_core.experiments.localization import LocalizationSpec

    with pytest.raises(ValueError, match=message):
        LocalizationSpec(dataset="sim:tabletop", **bad)


@pytest.mark.parametrize("values", [{"same_track_xy": 0.3, "same_track_theta": 0.52}, {"commit_after": 0},
                                    {"retract": False}])
def test_the_recording_rule_takes_each_of_its_settings(values):
    from semloc_core.experiments.localization import LocalizationSpec
    from semloc_core.localization.place_poses import PlacePoseConfig

    spec = LocalizationSpec(dataset="sim:tabletop", place_poses=values)
    assert PlacePoseConfig(**spec.place_poses).to_dict() == {**PlacePoseConfig().to_dict(), **values}


@pytest.mark.parametrize("bad", [{"same_track_xy": -0.3}, {"commit_after": -1}, {"keep_all": True}])
def test_a_bad_recording_setting_is_refused(bad):
    from semloc_core.experiments.localization import LocalizationSpec

    with pytest.raises(ValueError):
        LocalizationSpec(dataset="sim:tabletop", place_poses=bad)


@pytest.mark.parametrize("values, ok", [({"enabled": False}, True), ({"max_frames": 50, "steps_per_frame": 1}, True),
                                        ({"max_frames": 0}, False), ({"rule": "all"}, False)])
def test_the_backward_pass_takes_its_settings(values, ok):
    from semloc_core.experiments.localization import LocalizationSpec
    from semloc_core.localization.smoothing import SmoothingConfig

    if not ok:
        with pytest.raises(ValueError):
            LocalizationSpec(dataset="sim:tabletop", smoothing=values)
        return
    spec = LocalizationSpec(dataset="sim:tabletop", smoothing=values)
    assert SmoothingConfig(**spec.smoothing).to_dict() == {**SmoothingConfig().to_dict(), **values}


@pytest.fixture(scope="module")
def prior_lap_run():
    """A simulated table top's first 60 frames: a lap from the true pose (``lap_init``, as an operator gives a
    mapping robot its start) records its places, then the run, started globally, its images degraded as a second
    traversal (``sensor``), kidnapped at 20 by 20 frames (0.9 m) onto recorded places. Synthetic scores (§4.8.3)
    with the bearing model given, so nothing is calibrated."""
    from semloc_core.experiments.localization import LocalizationSpec, run

    spec = LocalizationSpec(dataset="sim:tabletop", frames=60, sources=["synthetic"], models=["B"], variants=["soft"],
                            init="global", lap_init="gt", kidnap=20, jump=20, places=True, prior_lap=True,
                            perception={"sigma": 3.0, "exponent": 0.18})
    return run(spec).report


def test_a_prior_lap_records_true_poses_and_a_kidnapped_second_traversal_recognises_them(prior_lap_run):
    """Against the simulator's ground truth: the lap's places hold poses within the table top's convergence
    threshold (the hybrid map); after the kidnapping the second traversal - other pixels, the same places -
    recognises them at once, every recognition of a lap frame is one seen from where the robot truly is, and the
    particles they propose bring the filter back within 0.5 m."""
    metrics = prior_lap_run["runs"]["B-soft-synthetic"]["metrics"]
    lap = metrics["places"]["prior_lap"]
    assert lap["frames"] == 60 and lap["recorded"] >= 30, lap
    assert lap["recorded_error_median_m"] < 0.1 and lap["recorded_over_0_5_m"] == 0, lap
    recognised = metrics["places"]["lap_recognised"]
    after = [s for s in recognised["steps"] if s >= 20]
    assert after and after[0] <= 25, recognised["steps"]
    assert max(recognised["true_distance_m"]) < 0.3, recognised  # never a place elsewhere on the table top
    injected = [s for s in metrics["places"]["injections"] if s >= 20]
    errors = np.asarray(metrics["errors_m"])
    assert errors[20] > 0.5 and injected, (errors[20], metrics["places"]["injections"])
    settled = metrics["reentry"]["thresholds"]["0.5"]["settled_at"]
    assert settled is not None and settled <= injected[0] + 3, (settled, injected)


def test_the_lap_starts_where_lap_init_says_and_the_measured_run_where_init_says(prior_lap_run):
    """The lap from the true pose is within the convergence threshold from its first frame; the measured run,
    started globally, is lost at first and converges later."""
    run = prior_lap_run["runs"]["B-soft-synthetic"]
    assert (prior_lap_run["init"], prior_lap_run["lap_init"]) == ("global", "gt")
    assert run["metrics"]["places"]["prior_lap"]["time_to_converge_frames"] == 0, run["metrics"]["places"]["prior_lap"]
    assert run["states"][0] == "lost" and run["metrics"]["time_to_converge_frames"] > 0, run["metrics"]


@pytest.mark.parametrize("bad, message", [({"lap_init": "gt"}, "needs prior_lap"),
                                          ({"lap_init": "operator", "prior_lap": True, "places": True}, "lap_init")])
def test_a_lap_start_needs_a_prior_lap_and_a_known_kind(bad, message):
    from semloc_core.experiments.localization import LocalizationSpec

    with pytest.raises(ValueError, match=message):
        LocalizationSpec(dataset="sim:tabletop", **bad)


def test_a_second_traversal_sees_other_pixels_of_the_same_places(sim_scenario):
    """The second traversal's features are those of its degraded images (darker, blurred, noisy, re-encoded): not
    the lap's, yet as many."""
    from semloc_core.experiments.localization_places import traversal_degradation

    tabletop = sim_scenario("tabletop", frames=3)
    lap = sequence_features(tabletop, [2], None, lambda _: None)[0]
    second = sequence_features(tabletop, [2], None, lambda _: None, traversal_degradation("sensor"))[0]
    assert not np.array_equal(lap.descriptors, second.descriptors)
    assert 0.5 < len(second.bearings) / len(lap.bearings) < 2.0
