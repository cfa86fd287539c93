"""Evaluation metrics and the experiment layer (sequences, ground-truth views, observed bins) on small inputs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid
from semloc_core.camera import EquirectangularCamera, PinholeCamera
from semloc_core.localization.evaluation import first_settled, localization_metrics
from semloc_core.localization.experiment import make_sequence, observed_mask, views_from_visible


def test_metrics_time_to_converge_rmse_and_recovery():
    frames = 100
    truth = np.zeros((frames, 3))
    errors = np.r_[np.linspace(3, 0.5, 20), np.full(30, 0.05), np.full(10, 2.0), np.full(40, 0.08)]
    estimates = truth.copy()
    estimates[:, 0] = errors
    estimates[:, 2] = 0.1
    metrics = localization_metrics(estimates, truth, converge_threshold=0.1, hold=10, teleports=[50],
                                   recover_threshold=0.5)
    assert metrics["time_to_converge_frames"] == 20
    assert metrics["rmse_after_convergence_m"] == pytest.approx(0.05)
    assert metrics["recoveries"] == [{"frame": 50, "frames_to_recover": 10}]
    assert metrics["heading_rmse_after_convergence_deg"] == pytest.approx(math.degrees(0.1))
    assert metrics["running_rmse_m"][0] == pytest.approx(3.0)
    assert first_settled(np.array([0.0, 1.0, 0.0, 0.0]), 0.5, hold=2) == 2
    never = localization_metrics(np.ones((5, 3)), np.zeros((5, 3)), 0.1)
    assert never["time_to_converge_frames"] is None and never["rmse_after_convergence_m"] is None


@dataclass
class _Odometry:
    steps: np.ndarray

    def increments(self):
        return self.steps


@dataclass
class _Dataset:
    n: int

    def __post_init__(self):
        steps = np.zeros((self.n, 3))
        steps[1:] = [0.1, 0.0, 0.05]  # 10 cm forward and a small turn per frame
        self.odometry = _Odometry(steps)
        self.stamps_ns = np.arange(self.n) * 100_000_000

    def __len__(self):
        return self.n


def test_sequence_composes_skipped_frames_and_splices_a_kidnapping():
    dataset = _Dataset(30)
    sequence = make_sequence(dataset, stride=2)
    assert sequence.indices.tolist() == list(range(0, 30, 2))
    # two steps of (0.1, 0, 0.05) composed: the second moves along the turned heading
    np.testing.assert_allclose(sequence.increments[1], [0.1 + 0.1 * math.cos(0.05), 0.1 * math.sin(0.05), 0.1])
    assert sequence.dts[1] == pytest.approx(0.2)
    kidnapped = make_sequence(dataset, kidnap_at=10, jump=5)
    assert kidnapped.indices[9:11].tolist() == [9, 15] and kidnapped.teleports == (10,)
    np.testing.assert_array_equal(kidnapped.increments[10], 0.0)
    with pytest.raises(ValueError, match="kidnap_at"):
        make_sequence(dataset, kidnap_at=28, jump=5)


@dataclass
class _Visible:
    class_name: str
    camera: int
    visible_box: tuple
    bearing: float


def test_views_from_visible_boxes_use_the_camera_model():
    camera = PinholeCamera.from_fov(640, 480, 60.0)
    fx = camera.K[0, 0]
    visible = [_Visible("mug", 0, (300.0, 200.0, 340.0, 260.0), 0.01),  # 40 px wide at the centre
               _Visible("mug", 0, (10.0, 10.0, 15.0, 40.0), 0.5),  # 5 px wide: dropped (< 10 px)
               _Visible("chair", 0, (100.0, 100.0, 200.0, 200.0), 0.3)]  # not a mapped class
    views = views_from_visible(visible, ("mug", "bowl"), camera)
    assert views.bearing.tolist() == [0.01]
    expected = math.atan((340 - 319.5) / fx) - math.atan((300 - 319.5) / fx)
    assert views.width[0] == pytest.approx(expected, rel=1e-6)


def test_observed_mask_of_pinhole_and_panorama():
    grid = BearingGrid(360)
    pinhole = observed_mask(PinholeCamera.from_fov(640, 480, 60.0), 360)
    assert pinhole.sum() in (60, 61)
    assert np.all(np.abs(np.degrees(grid.centers[pinhole])) <= 31)
    assert observed_mask(EquirectangularCamera(1024, 256), 360).all()


def test_calibration_detector_scores_every_class_on_every_world():
    """The thesis evaluates every class's detector on every training image (§4.8.2): a calibration world without a
    class must still give that class's p(z|d̄) negatives - the whole observed heatline, as no object of it is there."""
    from semloc_core.detection.calibration import heatline_samples
    from semloc_core.detection.evaluation import frame_objects, run_detector
    from semloc_core.sim import make_scenario
    from semloc_core.experiments.localization_detector import scene_detector

    with_cap = make_scenario("tabletop", seed=1, frames=2, instances={"bowl": 0, "cap": 1, "cereal_box": 0,
                                                                      "coffee_mug": 1, "soda_can": 0})
    without_cap = make_scenario("tabletop", seed=2, frames=2, instances={"bowl": 1, "cap": 0, "cereal_box": 0,
                                                                         "coffee_mug": 0, "soda_can": 1})
    assert "cap" not in without_cap.semantic_map.class_names
    detector = scene_detector(without_cap, with_cap)
    assert set(detector.classes) == {"bowl", "cap", "coffee_mug", "soda_can"}
    (_, heatlines, _), = run_detector(without_cap, detector, [0])
    objects = frame_objects(without_cap.visible_objects(0))
    positives, negatives = heatline_samples(heatlines, [(o.class_name, o.bearing, o.usable) for o in objects])
    assert positives["cap"].size == 0
    assert negatives["cap"].size == int(heatlines.observed.sum()) > 0
    assert np.ptp(negatives["cap"]) > 0  # real detector responses to the world's background, not a constant


def test_eval_on_a_sim_hall_with_another_camera_calibrates_on_the_same_camera(tmp_path, capsys):
    """`scenario.camera` gives the evaluated and the calibration world the same camera and caches each camera apart; a
    fresh --cache folder is created; a calibration that misses classes of the map is a clear error, not a crash."""
    import json

    from services.cli import main

    cache = tmp_path / "fresh" / "cache"
    out = tmp_path / "hall.json"

    def command(camera: str, *sets: str) -> list[str]:
        settings = [f"scenario.camera={camera}", "frames=4", "stride=5", "models=B", "variants=soft",
                    "particles=2000", "perception.sigma=3", "perception.exponent=0.1", *sets]
        return ["eval", "localization", "sim:hall", *(a for s in settings for a in ("--set", s)),
                "--cache", str(cache), "-o", str(out), "--quiet"]

    assert main(command("panorama:512x128", "sources=synthetic")) == 0
    report = json.loads(out.read_text())
    assert report["camera"] == "panorama:512x128" and report["frames"] == 4 and set(report["runs"]) == {
        "B-soft-synthetic"}
    assert [p.name for p in cache.iterdir()] == ["sim-hall_s0_panorama-512x128_orbit_synthetic.npz"]

    capsys.readouterr()
    # two calibration frames at 512 px show objects of one class at most (positives are >= 20 px tall)
    assert main(command("panorama:512x128", "sources=detector", "calibration.frames=6")) == 2
    assert "no score likelihood of" in capsys.readouterr().err
    assert any(p.name.startswith("calibration_hall_panorama-512x128_default_s1000") for p in cache.iterdir())
    assert main(command("panorama:12", "sources=synthetic")) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err


@pytest.fixture(scope="module")
def hall_synthetic():
    """The simulated station hall's first 45 frames with synthetic-score heatlines (§4.8.3) from its ground truth."""
    from semloc_core.localization.experiment import PRESETS, frame_observations, ground_truth_heatlines
    from semloc_core.sim import make_scenario

    hall = make_scenario("hall", seed=0, frames=45)
    sequence = make_sequence(hall)
    indices = [int(i) for i in sequence.indices]
    lines = ground_truth_heatlines(frame_observations(hall, indices, hall.semantic_map.class_names, 360,
                                                      PRESETS["hall"].min_box_px), "synthetic")
    return hall, sequence, lines


@pytest.mark.parametrize("init", ["gt", "global"])
def test_hall_model_b_localizes_from_synthetic_scores(hall_synthetic, init):
    """Thesis Fig. 4.6's setting with exact detections: from the true pose the filter keeps tracking, from a global
    initialisation it is within 1 m after at most 40 frames and stays there. (With the table top's outlier-frame
    prior, 0.05, a panorama's sharp likelihood flattened into a tie between all but the best particles and the
    cloud drifted off by 8 m: the hall preset's 0.001.)"""
    from semloc_core.localization import synthetic_scores_likelihood
    from semloc_core.localization.experiment import PRESETS, RunSpec, run_sequence, view_geometry

    hall, sequence, lines = hall_synthetic
    preset = PRESETS["hall"]
    views = {i: view_geometry(hall, i, 360, preset.min_box_px) for i in lines}
    spec = RunSpec("B", synthetic_scores_likelihood(hall.semantic_map.class_names), init=init, seed=1,
                   exponent=0.18, view=True)  # exponent: 1 / the synthetic scores' correlation length (5.5 bins)
    poses = run_sequence(hall, sequence, lines, preset, spec, views=views).arrays()["poses"]
    errors = np.hypot(*(poses[:, :2] - np.asarray(hall.poses2d)[sequence.indices, :2]).T)
    if init == "gt":
        assert np.median(errors) < 0.3 and errors.max() < 1.0, np.round(errors, 2)
    else:
        assert errors[40:].max() < 1.0 and np.median(errors[20:]) < 0.5, np.round(errors, 2)


def test_a_reinitialisation_restarts_the_filter_globally_mid_sequence(hall_synthetic):
    """``reinit_at`` (the evaluation's ``reinit``): the same course up to that step, then a global restart - the
    monitor's `lost` (initialising) and the filter localizing again - after which the hall's exact detections bring
    it back within 1 m. Frames on from the truth, a pose no frame has weighed: held `uncertain` for rival_frames
    frames as the localizer holds a configured or given pose, then `localized` (before: from the 5th frame)."""
    from semloc_core.localization import synthetic_scores_likelihood
    from semloc_core.localization.experiment import PRESETS, RunSpec, run_sequence, view_geometry
    from semloc_core.localization.health import GIVEN, HealthConfig

    hall, sequence, lines = hall_synthetic
    preset = PRESETS["hall"]
    views = {i: view_geometry(hall, i, 360, preset.min_box_px) for i in lines}
    spec = RunSpec("B", synthetic_scores_likelihood(hall.semantic_map.class_names), init="gt", seed=1,
                   exponent=0.18, view=True, health=HealthConfig())
    tracked = run_sequence(hall, sequence, lines, preset, spec, views=views).arrays()
    restarted = run_sequence(hall, sequence, lines, preset, spec, views=views, reinit_at=15).arrays()
    held = HealthConfig().rival_frames
    assert set(tracked["states"][:held]) == {"uncertain"} and tracked["reasons"][0] == GIVEN
    assert set(tracked["states"][held:15]) == {"localized"}
    assert np.array_equal(tracked["poses"][:15], restarted["poses"][:15])
    assert tracked["states"][14] == restarted["states"][14] == "localized"
    assert restarted["statuses"][15] == "localizing" and tracked["statuses"][15] == "converged"
    assert (restarted["states"][15], restarted["reasons"][15]) == ("lost", "initialising")
    errors = np.hypot(*(restarted["poses"][:, :2] - np.asarray(hall.poses2d)[sequence.indices, :2]).T)
    assert errors[-5:].max() < 1.0, np.round(errors, 2)


def test_eval_with_selected_views_chooses_them_on_the_calibration_world_and_renders_them_of_the_evaluated_one(
        tmp_path):
    """`templates: selected`: each class's views are chosen on the calibration world's frames (never the evaluated
    world's), cached, reported, and the evaluated world's detector matches those viewpoints of its own objects. On
    the calibration frames the chosen views find at least as many objects as the canonical view alone (greedy
    forward selection starts from the best single view), recomputed here with the detectors themselves."""
    import json

    from semloc_core.detection.evaluation import UsableCriteria, run_detector, score_soft
    from semloc_core.experiments.localization_detector import SELECTION_CRITERIA, scene_detector
    from semloc_core.experiments.tabletop import simulated_scenario
    from services.cli import main

    cache = tmp_path / "cache"
    out = tmp_path / "hall.json"
    settings = ["templates=selected", "calibration.frames=60", "frames=3", "stride=10", "sources=detector",
                "models=B", "variants=soft", "particles=1000", "perception.sigma=3", "perception.exponent=0.1"]
    assert main(["eval", "localization", "sim:hall", *(a for s in settings for a in ("--set", s)),
                 "--cache", str(cache), "-o", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    chosen = report["template_views"]
    assert report["templates"] == "selected"
    assert set(chosen) == {"clock", "trashcan", "payphone", "ticket_machine"}
    assert all(1 <= len(keys) <= 4 for keys in chosen.values())
    (record_file,) = cache.glob("*_views.json")
    record = json.loads(record_file.read_text())
    assert record["chosen"] == chosen
    assert all(record["steps"][c][-1]["hits"] >= record["front_only"][c]["hits"] for c in record["steps"])

    calibration_world = simulated_scenario("hall", 1000, 60, None, "auto")
    evaluated_world = simulated_scenario("hall", 0, None, None, "auto")
    selected = scene_detector(evaluated_world, chosen=chosen)
    assert {t.source.split("/", 1)[1] for t in selected.templates} == {k for keys in chosen.values() for k in keys}

    criteria = UsableCriteria(**SELECTION_CRITERIA)
    frames = list(range(0, 60, 3))

    def hits(detector) -> int:
        total = 0
        for _, heatlines, objects in run_detector(calibration_world, detector, frames, criteria=criteria):
            total += sum(c.hits for c in score_soft(heatlines, objects, 5.0).values())
        return total

    front = hits(scene_detector(calibration_world))
    assert hits(scene_detector(calibration_world, chosen=chosen)) >= front > 0


def test_selected_views_need_the_views_in_the_evaluated_world():
    from semloc_core.experiments.localization_detector import scene_detector
    from semloc_core.experiments.tabletop import simulated_scenario

    world = simulated_scenario("hall", 0, 2, None, "auto")
    with pytest.raises(ValueError, match="no exemplar view"):
        scene_detector(world, chosen={"clock": ["az7_el89"]})


def test_carry_rigidly_moves_each_hypothesis_by_the_motion_in_its_own_frame():
    from semloc_core.localization.evaluation import carry_rigidly

    start, end = np.array([1.0, 2.0, 0.5]), np.array([1.5, 2.8, 1.2])
    hypotheses = np.array([start, [0.0, 0.0, 0.0], [-3.0, 1.0, math.pi]])
    carried = carry_rigidly(hypotheses, start, end)
    np.testing.assert_allclose(carried[0], end, atol=1e-12)
    step = np.array([math.cos(0.5) * 0.5 + math.sin(0.5) * 0.8, -math.sin(0.5) * 0.5 + math.cos(0.5) * 0.8])
    np.testing.assert_allclose(carried[1], [step[0], step[1], 0.7], atol=1e-12)
    np.testing.assert_allclose(carried[2], [-3.0 - step[0], 1.0 - step[1], 0.7 + math.pi - 2 * math.pi], atol=1e-12)


@pytest.mark.parametrize("observation", ["truth", "flat"])
def test_information_margins_single_out_the_truth_only_when_the_observations_carry_it(observation):
    """Synthetic scores of the true view single the true pose out of 3,000 uniform hypotheses within a few frames;
    a heatline that scores every bearing alike as background never does (model B then favours poses that expect
    nothing: the all-zero case of §4.7)."""
    from semloc_core.bearing import Heatlines
    from semloc_core.localization import GenerativeScoreModel, synthetic_scores_likelihood
    from semloc_core.localization.evaluation import information_margins
    from tests.localization.worlds import CLASSES, tabletop

    world = tabletop(frames=40)
    model = GenerativeScoreModel(world.semantic_map, synthetic_scores_likelihood(CLASSES), sigma=math.radians(4.0),
                                 exponent=0.1)
    rng = np.random.default_rng(3)
    hypotheses = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(-2, 2, 3000), rng.uniform(-np.pi, np.pi, 3000)])
    if observation == "truth":
        frames = [(world.heatlines(k), None) for k in range(40)]
    else:
        flat = np.where(world.observed, 0.1, 0.0).astype(np.float32)
        frames = [(Heatlines(CLASSES, np.tile(flat, (len(CLASSES), 1)), world.observed), None)] * 40
    margins = information_margins(model, world.poses, frames, hypotheses, far=0.2)
    assert len(margins["margin"]) == 40
    if observation == "truth":
        assert margins["singled_out"] is not None and margins["singled_out"] <= 10
        assert margins["above_cumulative"][-1] == 0 and margins["margin"][-1] > margins["margin"][0] > 0
    else:
        assert margins["singled_out"] is None
        assert margins["above_cumulative"][-1] > 0.5 * 3000 * 0.9 and margins["share_above_single"][-1] > 0.5
    with pytest.raises(ValueError, match="ground_truth"):
        information_margins(model, world.poses[:5], frames, hypotheses, far=0.2)


def test_filter_overrides_apply_and_refuse_bad_settings():
    from pydantic import ValidationError

    from semloc_core.experiments.localization import LocalizationSpec, filter_with
    from semloc_core.localization import FilterConfig
    from services.config import from_sets

    # as `--set filter.KEY=VALUE` gives them
    spec = LocalizationSpec.model_validate(from_sets(["dataset=sim:hall", "filter.history_frames=12",
                                                      "filter.recovery_track_mean=true", "filter.history_margin=5"]))
    config = filter_with(FilterConfig(), spec.filter)
    assert (config.history_frames, config.recovery_track_mean, config.history_margin) == (12, True, 5.0)
    assert isinstance(config.history_frames, int)
    for bad in ({"no_such": 1}, {"history_margin": "abc"}, {"history_frames": -1}):
        with pytest.raises(ValidationError):
            LocalizationSpec(dataset="sim:hall", filter=bad)


def test_information_benchmark_after_a_kidnapping_takes_the_frames_the_kidnapped_run_continues_with(tmp_path, capsys):
    """`benchmarks/localization_information.py --set kidnap=K` bounds the recovery: it weighs the frames after the
    teleport (the evaluation's own sequence), not the first ones; an impossible kidnapping is a clear error."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "localization_information.py"
    spec = importlib.util.spec_from_file_location("localization_information", path)
    benchmark = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(benchmark)
    common = ["sim:hall", "--set", "scenario.camera=panorama:512x128", "--set", "frames=12", "--source", "synthetic",
              "--set", "perception.sigma=3", "--set", "perception.exponent=0.1", "--hypotheses", "2000", "--far", "2",
              "--every", "1", "--cache", str(tmp_path), "--quiet"]

    def rows(out):  # the table's rows: frame | share above on the frame | above summed | margin
        return [line for line in out.splitlines() if line[:5].strip().isdigit()]

    assert benchmark.main([*common, "--set", "kidnap=3"]) == 0
    out = capsys.readouterr().out
    # positions 0..11, jump 12 // 3 = 4: the kidnapped run continues with frames 7..11, five of them
    assert "5 frames after the kidnapping at 3 (frame 7 on)" in out
    after = rows(out)
    assert [row.split("|")[0].strip() for row in after] == ["0", "1", "2", "3", "4"]
    # the same hypotheses on the first five frames instead give other margins
    assert benchmark.main([a if a != "frames=12" else "frames=5" for a in common]) == 0
    first = rows(capsys.readouterr().out)
    assert len(first) == 5 and first != after
    assert benchmark.main([*common, "--set", "kidnap=9"]) == 2
    assert "kidnap" in capsys.readouterr().err
