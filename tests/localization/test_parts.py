"""Score likelihoods, motion models, resampling, free space and ground-truth observation sources."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid
from semloc_core.io.calibration import ScoreLikelihoods, save_score_likelihoods
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.localization import (DifferentialDriveModel, FreeSpace, ObjectViews, Odometry, OdometryBuffer,
                                      OmniDriveModel, RandomWalkModel, ScoreLikelihood, field_of_view_mask, load_score_likelihood,
                                      simulated_dpm_heatlines, synthetic_scores_heatlines,
                                      synthetic_scores_likelihood, visible_objects)
from semloc_core.localization.resampling import (effective_sample_size, kld_resample, kld_sample_count,
                                                 low_variance_resample, normalize_log_weights)


# ---------------------------------------------------------------------------------------------- score likelihoods
def test_synthetic_scores_likelihood_is_the_thesis_gaussians():
    likelihood = synthetic_scores_likelihood(["mug", "bowl"])
    z = np.array([[0.0, 0.25, 0.75, 1.0]] * 2)
    log_d, log_b = likelihood.log_densities(z)
    normal = lambda x, m: np.exp(-0.5 * ((x - m) / 0.25) ** 2) / (0.25 * np.sqrt(2 * np.pi))  # noqa: E731
    # tabulated on 1000 points and interpolated linearly, as the thesis samples its KDEs
    np.testing.assert_allclose(np.exp(log_d), normal(z, 0.75), rtol=1e-3)
    np.testing.assert_allclose(np.exp(log_b), normal(z, 0.25), rtol=1e-3)


def test_densities_are_floored_and_clamped_outside_the_grid():
    likelihood = ScoreLikelihood.gaussian(["mug"], 0.75, 0.05, 0.25, 0.05, floor=1e-6)
    log_d, _ = likelihood.log_densities(np.array([[-50.0, 0.0]]))
    assert np.all(np.isfinite(log_d))
    assert log_d[0, 0] == pytest.approx(math.log(1e-6))


def test_binary_likelihood_for_hard_heatlines():
    likelihood = ScoreLikelihood.binary(["mug"], hit_rate=0.8, false_alarm_rate=0.1)
    log_d, log_b = likelihood.log_densities(np.array([[0.0, 1.0]]))
    np.testing.assert_allclose(np.exp(log_d), [[0.2, 0.8]])
    np.testing.assert_allclose(np.exp(log_b), [[0.9, 0.1]])
    with pytest.raises(ValueError, match="hit_rate"):
        ScoreLikelihood.binary(["mug"], hit_rate=1.0)


def test_sampling_follows_the_densities():
    likelihood = synthetic_scores_likelihood(["mug"])
    rng = np.random.default_rng(0)
    detected = np.zeros(20000, dtype=bool)
    detected[:10000] = True
    scores = likelihood.sample(0, detected, rng)
    assert scores[:10000].mean() == pytest.approx(0.75, abs=0.01)
    assert scores[10000:].mean() == pytest.approx(0.25, abs=0.01)
    assert scores[:10000].std() == pytest.approx(0.25, abs=0.01)


def test_calibration_file_round_trip(tmp_path):
    z = np.linspace(0, 1, 101)
    pdf_d = np.stack([2 * z, np.ones_like(z)])
    pdf_not_d = np.stack([2 * (1 - z), np.ones_like(z)])
    path = save_score_likelihoods(ScoreLikelihoods(("mug", "bowl"), 0.0, 1.0, pdf_d, pdf_not_d), tmp_path / "s.json")
    likelihood = load_score_likelihood(path)
    log_d, log_b = likelihood.log_densities(np.array([[0.3], [0.3]]), [likelihood.index("mug"),
                                                                       likelihood.index("bowl")])
    np.testing.assert_allclose(np.exp(log_d[:, 0]), [0.6, 1.0], rtol=1e-9)
    np.testing.assert_allclose(np.exp(log_b[:, 0]), [1.4, 1.0], rtol=1e-9)


def test_thesis_bandwidth_keeps_the_likelihood_ratio_smooth():
    """§4.8.2's bandwidth (the robust standard deviation) against the normal-reference rule, on 20,000 scores of
    two normal classes: the fitted density's spread is sqrt(2) sigma, and log p(z|d)/p(z|not d) rises steadily
    instead of hitting the density floor a few widths away from the training scores."""
    from semloc_core.detection.calibration import fit_score_likelihoods, robust_bandwidth

    rng = np.random.default_rng(3)
    positives, negatives = rng.normal(0.6, 0.05, 20000), rng.normal(0.2, 0.05, 20000)
    assert robust_bandwidth(positives, 1e-3, "robust_std") == pytest.approx(0.05, rel=0.03)
    assert robust_bandwidth(positives, 1e-3) == pytest.approx(0.05 * (4 / 60000) ** 0.2, rel=0.03)
    with pytest.raises(ValueError):
        robust_bandwidth(positives, 1e-3, "silverman")
    wide = fit_score_likelihoods({"c": positives}, {"c": negatives}, bandwidth="robust_std")
    z = wide.z
    spread = math.sqrt(np.sum(wide.pdf_d[0] * (z - 0.6) ** 2) / np.sum(wide.pdf_d[0]))
    assert spread == pytest.approx(0.05 * math.sqrt(2), rel=0.05)
    likelihood = ScoreLikelihood.from_calibration(wide)
    log_d, log_b = likelihood.log_densities(np.linspace(0.2, 0.6, 41)[None], [0])
    assert np.all(np.diff(log_d - log_b) > 0)


# ---------------------------------------------------------------------------------------------- motion
def test_odometry_conversions_round_trip():
    odometry = Odometry.from_velocity(0.5, 0.4, 2.0)
    assert odometry.velocity == pytest.approx((0.5, 0.4))
    between = Odometry.between((1.0, 2.0, math.pi / 2), (1.0, 3.0, math.pi / 2 + 0.1), 1.0)
    assert (between.dx, between.dy, between.dtheta) == pytest.approx((1.0, 0.0, 0.1))
    with pytest.raises(ValueError):
        Odometry(float("nan"), 0, 0, 1)
    # a constant twist on a circle of radius 2 for a quarter turn: (2, 2) in the start frame, facing +y
    quarter = Odometry.from_twist(1.0, 0.0, 0.5, math.pi)
    assert (quarter.dx, quarter.dy, quarter.dtheta) == pytest.approx((2.0, 2.0, math.pi / 2))
    sideways = Odometry.from_twist(0.0, 0.3, 0.0, 2.0)
    assert (sideways.dx, sideways.dy, sideways.dtheta) == pytest.approx((0.0, 0.6, 0.0))
    # from_velocity takes v Δt for the chord: the two differ by the arc-chord gap v Δt (ωΔt)²/24 = 1.7e-6 m here
    small, midpoint = Odometry.from_twist(1.0, 0.0, 0.2, 0.1), Odometry.from_velocity(1.0, 0.2, 0.1)
    assert math.hypot(small.dx - midpoint.dx, small.dy - midpoint.dy) == pytest.approx(0.1 * 0.02 ** 2 / 24, rel=0.01)


def _pose_after(odometry):
    return (0.0, 0.0, 0.0) if odometry is None else (odometry.dx, odometry.dy, odometry.dtheta)


def test_odometry_buffer_integrates_exactly_up_to_the_observation_stamp():
    second = 1_000_000_000
    buffer = OdometryBuffer()
    # 1 m/s forward over (0, 1] s, then a quarter turn on a circle of radius 2 over (1, 1 + pi] s
    buffer.add(1 * second, 1.0, 0.0, 0.0, 1.0)
    buffer.add(int((1 + math.pi) * second), 1.0, 0.0, 0.5, math.pi)
    # a heatline captured at 0.25 s, although all the odometry up to 4.14 s has arrived: a quarter metre only
    assert _pose_after(buffer.integrate_until(second // 4)) == pytest.approx((0.25, 0.0, 0.0))
    # the next one at 1 + pi/2 s: the rest of the straight part, then half of the arc (an eighth of a turn)
    arc = Odometry.from_twist(1.0, 0.0, 0.5, math.pi / 2)
    expected = (0.75 + arc.dx, arc.dy, arc.dtheta)
    assert _pose_after(buffer.integrate_until(int((1 + math.pi / 2) * second))) == pytest.approx(expected, abs=1e-6)
    # an observation older than the last one, and one with no odometry since: no motion
    assert buffer.integrate_until(second) is None
    end = buffer.integrate_until(int((1 + math.pi) * second))
    assert _pose_after(end) == pytest.approx(_pose_after(arc), abs=1e-6)
    assert len(buffer) == 0 and buffer.integrate_until(5 * second) is None
    # odometry arriving late, partly before motion already applied: only the part after the last stamp counts
    buffer.add(6 * second, 0.0, 0.5, 0.0, 2.0)
    assert _pose_after(buffer.integrate_until(7 * second)) == pytest.approx((0.0, 0.5, 0.0))
    # a new initial pose drops the motion buffered before it
    buffer.add(8 * second, 1.0, 0.0, 0.0, 1.0)
    buffer.reset()
    assert buffer.integrate_until(9 * second) is None
    with pytest.raises(ValueError):
        buffer.add(10 * second, float("nan"), 0.0, 0.0, 1.0)


def test_differential_drive_follows_eq_4_5_on_average():
    """Mean displacement (v Δt along the mid-step heading) and a spread that grows with the noise parameters."""
    rng = np.random.default_rng(1)
    states = np.tile([1.0, 2.0, 0.3], (20000, 1))
    model = DifferentialDriveModel(alpha1=0.01, alpha2=0.0, alpha3=0.01, alpha4=0.0, min_speed_std=0.0,
                                   min_rotation_std=0.0)
    moved = model.sample(states, Odometry.from_velocity(1.0, 0.5, 0.5), 0.5, rng)
    heading = 0.3 + 0.25 / 2
    np.testing.assert_allclose(moved[:, :2].mean(0), [1 + 0.5 * math.cos(heading), 2 + 0.5 * math.sin(heading)],
                               atol=3e-3)
    assert moved[:, 2].mean() == pytest.approx(0.55, abs=2e-3)
    assert moved[:, 2].std() == pytest.approx(math.sqrt(0.01) * 0.5 * 0.5, rel=0.05)  # σ_Ω Δt = 0.1·0.5·0.5


def test_omni_model_moves_sideways_in_the_body_frame():
    rng = np.random.default_rng(2)
    states = np.tile([0.0, 0.0, math.pi / 2], (5000, 1))  # facing +y: body left is world -x
    model = OmniDriveModel(alpha1=0, alpha2=0, alpha3=0, alpha4=0, min_translation_std=1e-3, min_rotation_std=1e-3)
    moved = model.sample(states, Odometry(0.0, 0.2, 0.0, 0.1), 0.1, rng)
    np.testing.assert_allclose(moved[:, :2].mean(0), [-0.2, 0.0], atol=1e-3)


def test_random_walk_spread_grows_with_the_square_root_of_time():
    rng = np.random.default_rng(3)
    model = RandomWalkModel(translation_std=0.2, rotation_std=0.1)
    states = np.zeros((20000, 3))
    for dt in (0.25, 4.0):
        moved = model.sample(states, None, dt, rng)
        assert moved[:, 0].std() == pytest.approx(0.2 * math.sqrt(dt), rel=0.05)
        assert moved[:, 2].std() == pytest.approx(0.1 * math.sqrt(dt), rel=0.05)
    # a model with odometry falls back to its random walk when odometry drops out
    fallback = DifferentialDriveModel(fallback=RandomWalkModel(0.3, 0.0)).sample(states, None, 1.0, rng)
    assert fallback[:, 1].std() == pytest.approx(0.3, rel=0.05)


@pytest.mark.parametrize("model, odometry", [
    (OmniDriveModel(alpha1=0.05, alpha2=0.01, alpha3=0.05, alpha4=0.01, min_translation_std=0.002,
                    min_rotation_std=0.005), Odometry(0.03, -0.01, 0.04, 1 / 30)),
    (DifferentialDriveModel(alpha1=0.2, alpha2=0.2, alpha3=0.2, alpha4=0.2), Odometry.from_velocity(0.5, 0.3, 0.1)),
    (RandomWalkModel(0.2, 0.1), Odometry(0.0, 0.0, 0.0, 0.25)),
])
def test_increment_std_is_the_spread_sample_adds(model, odometry):
    """What carries a pose along the odometry outside the filter (the places' back-fill) takes the filter's own
    noise: the spread of the sampled increments, along the heading (and across it for omni and the random walk)."""
    states = np.zeros((40000, 3))
    moved = model.sample(states, None if isinstance(model, RandomWalkModel) else odometry, odometry.dt,
                         np.random.default_rng(4))
    translation_std, rotation_std = model.increment_std(odometry)
    heading = odometry.dtheta / 2 if isinstance(model, DifferentialDriveModel) else 0.0
    along = moved[:, 0] * math.cos(heading) + moved[:, 1] * math.sin(heading)
    assert along.std() == pytest.approx(translation_std, rel=0.05)
    assert moved[:, 2].std() == pytest.approx(rotation_std, rel=0.05)
    if not isinstance(model, DifferentialDriveModel):
        assert moved[:, 1].std() == pytest.approx(translation_std, rel=0.05)


# ---------------------------------------------------------------------------------------------- resampling
def test_low_variance_resampling_keeps_proportions():
    rng = np.random.default_rng(4)
    weights = np.array([0.5, 0.25, 0.125, 0.125])
    counts = np.bincount(low_variance_resample(weights, 800, rng), minlength=4)
    np.testing.assert_array_equal(counts, [400, 200, 100, 100])  # systematic: exact up to one particle


def test_effective_sample_size_and_log_weights():
    assert effective_sample_size(np.full(10, 0.1)) == pytest.approx(10)
    assert effective_sample_size(np.array([1.0, 0, 0])) == pytest.approx(1)
    weights = normalize_log_weights(np.array([-1000.0, -1000.0 + math.log(3)]))
    np.testing.assert_allclose(weights, [0.25, 0.75])
    np.testing.assert_allclose(normalize_log_weights(np.array([-np.inf, -np.inf])), [0.5, 0.5])


def test_kld_sample_count_matches_fox_2003():
    # k = 100, epsilon = 0.05, z = 2.3263: (k-1)/(2 epsilon) (1 - 2/(9(k-1)) + sqrt(2/(9(k-1))) z)^3
    # = 990 * (1 - 0.0022447 + 0.0473804 * 2.3263)^3 = 990 * 1.107979^3 = 1346.6 -> 1347
    assert kld_sample_count(100, 0.05, 2.3263) == 1347
    assert kld_sample_count(1, 0.05, 2.3263) == 1


def test_kld_resampling_adapts_to_the_spread():
    rng = np.random.default_rng(5)
    # all in one (0.5 m, 0.5 m, 10 degree) bin: KLD needs a single particle, min_particles wins
    concentrated = np.column_stack([rng.normal(0.25, 0.02, 5000), rng.normal(0.25, 0.02, 5000),
                                    rng.normal(0.05, 0.01, 5000)])
    spread = np.column_stack([rng.uniform(0, 50, 5000), rng.uniform(0, 50, 5000), rng.uniform(-3, 3, 5000)])
    weights = np.full(5000, 1 / 5000)
    small = kld_resample(concentrated, weights, rng, 100, 5000)
    large = kld_resample(spread, weights, rng, 100, 5000)
    assert small.size == 100
    assert large.size == 5000


# ---------------------------------------------------------------------------------------------- free space
def test_free_space_polygons_contain_every_sample():
    square_with_notch = np.array([[0, 0], [4, 0], [4, 4], [2, 4], [2, 2], [0, 2]])
    free = FreeSpace(np.array([[-1, -1], [5, 5]]), (square_with_notch,))
    rng = np.random.default_rng(6)
    samples = free.sample(4000, rng)
    assert free.contains(samples).all()
    assert not free.contains(np.array([[1.0, 3.0], [-0.5, 0.5]])).any()
    assert free.contains(np.array([[1.0, 1.0], [3.0, 3.0]])).all()
    # uniform: the two unit-area halves of the L shape receive equal shares
    assert (samples[:, 1] > 2).mean() == pytest.approx(1 / 3, abs=0.03)
    assert free.area(rng) == pytest.approx(12.0, rel=0.03)


def test_free_space_contains_is_the_even_odd_rule_of_its_polygons():
    """The numba test the filter uses (FreeSpace.contains, and inside sample_poses' resection) against
    geometry.inside_polygon on random concave and self-overlapping polygons, points on their vertices included."""
    from semloc_core.geometry import inside_polygon

    rng = np.random.default_rng(3)
    polygons = tuple(rng.uniform(0, 10, (n, 2)) for n in (3, 7, 12))
    free = FreeSpace(np.array([[1.0, 0.5], [9.0, 9.5]]), polygons)
    points = np.concatenate([rng.uniform(-1, 11, (20000, 2)), *polygons])
    in_bounds = np.all((points >= free.bounds[0]) & (points <= free.bounds[1]), axis=1)
    expected = in_bounds & np.any([inside_polygon(points[:, 0], points[:, 1], p) for p in polygons], axis=0)
    np.testing.assert_array_equal(free.contains(points), expected)
    assert 0.1 < expected.mean() < 0.9
    assert free.contains(points.reshape(2, -1, 2)).shape == (2, points.shape[0] // 2)


def test_free_space_from_map_and_errors():
    semantic_map = SemanticMap.from_objects([{"class": "a", "position": [1, 1]}], bounds=[[0, 0], [3, 2]])
    free = FreeSpace.from_map(semantic_map)
    poses = free.sample_poses(100, np.random.default_rng(0))
    assert poses.shape == (100, 3) and free.contains(poses[:, :2]).all()
    with pytest.raises(ValueError, match="bounds"):
        FreeSpace(np.array([[1, 1], [0, 0]]))
    with pytest.raises(ValueError, match="outside"):
        FreeSpace(np.array([[0, 0], [1, 1]]), (np.array([[5, 5], [6, 5], [6, 6]]),)).sample(3, np.random.default_rng(0))


# ---------------------------------------------------------------------------------------------- observations
def test_synthetic_scores_heatlines_follow_section_4_8_3():
    grid = BearingGrid(360)
    observed = field_of_view_mask(360, 0.0, math.radians(60))
    views = ObjectViews(("mug", "bowl"), [0, 0], [math.radians(10), math.radians(-20)],
                        [math.radians(4), math.radians(6)])
    heatlines = synthetic_scores_heatlines(views, observed)
    mug = heatlines.scores[0]
    # exp(-((θ - x_i)/w_i)²) at bin centres half a degree from each mug, max over the two mugs
    assert mug[grid.index(math.radians(10.2))] == pytest.approx(math.exp(-(0.5 / 4) ** 2), abs=1e-4)
    assert mug[grid.index(math.radians(-20.2))] == pytest.approx(math.exp(-(0.5 / 6) ** 2), abs=1e-4)
    assert mug[grid.index(math.radians(-4.0))] == pytest.approx(
        max(math.exp(-(14.5 / 4) ** 2), math.exp(-(15.5 / 6) ** 2), 0.01), abs=1e-4)
    assert heatlines.scores[1][observed].min() == pytest.approx(0.01)  # floor where no bowl is
    assert np.all(heatlines.scores[:, ~observed] == 0)


def test_simulated_dpm_heatlines_follow_eq_4_29():
    rng = np.random.default_rng(7)
    likelihood = synthetic_scores_likelihood(["mug"])
    observed = np.ones(360, dtype=bool)
    views = ObjectViews(("mug",), [0], [0.0], [math.radians(20)])
    near = np.abs(BearingGrid(360).centers) <= math.radians(20)
    scores = np.stack([simulated_dpm_heatlines(views, observed, likelihood, rng).scores[0] for _ in range(50)])
    assert scores[:, near].mean() == pytest.approx(0.75, abs=0.02)
    assert scores[:, ~near].mean() == pytest.approx(0.25, abs=0.01)


def test_visible_objects_bearings_and_widths():
    semantic_map = SemanticMap.from_objects([
        {"class": "mug", "position": [0.0, 2.0], "size": [0.2, 0.2, 0.1]},  # left of a particle facing +x
        {"class": "bowl", "position": [-3.0, 0.0]},  # behind
        {"class": "mug", "position": [50.0, 0.0]},  # too far
    ])
    observed = np.ones(360, dtype=bool)
    views = visible_objects([0, 0, 0], semantic_map, observed, max_range=10.0)
    assert views.bearing.size == 2
    mug = np.flatnonzero(np.asarray(views.class_names)[views.class_index] == "mug")[0]
    assert views.bearing[mug] == pytest.approx(math.pi / 2)
    assert views.width[mug] == pytest.approx(2 * math.atan(0.1 / 2.0))
    front = visible_objects([0, 0, 0], semantic_map, field_of_view_mask(360, 0.0, math.radians(120)), max_range=10.0)
    assert front.bearing.size == 0


def test_odometry_buffer_reports_the_time_no_message_covers():
    """The seconds of each span between observations that no odometry message covers, exactly: none when each
    message's dt is the time since the previous stamp (as the ROS bridge, the camera's data sets and the simulator
    stamp it), however irregular; a reboot's gap; the time before the first message after it and past the last."""
    second = 10**9
    buffer = OdometryBuffer(restart_after_ns=second)
    # irregular stamps (a jittered 10 Hz), each dt the float seconds since the previous: contiguous to the nanosecond
    stamps = np.cumsum(np.random.default_rng(0).integers(90_000_000, 110_000_000, 60)) + 10**18
    for previous, stamp in zip(stamps[:-1], stamps[1:]):
        buffer.add(int(stamp), 0.5, 0.0, 0.1, (int(stamp) - int(previous)) * 1e-9)
    assert buffer.uncovered_until(int(stamps[0]) + 7) == 0.0  # before anything applied: from the first message
    buffer.integrate_until(int(stamps[0]))
    for observation in np.linspace(stamps[0], stamps[-1], 23).astype(np.int64)[1:]:  # straddling stamps: split
        assert buffer.uncovered_until(int(observation)) == 0.0
        assert buffer.integrate_until(int(observation)) is not None
    end = int(stamps[-1])
    # a reboot: nothing for 3 s, the chain afresh from its first sample (the next messages cover 0.1 s each)
    for k in range(1, 6):
        buffer.add(end + 3 * second + k * second // 10, 0.5, 0.0, 0.0, 0.1)
    assert buffer.uncovered_until(end + 3 * second + second // 2) == 3.0
    assert buffer.uncovered_until(end + 3 * second + second // 4) == 3.0  # inside a message: split there
    assert buffer.uncovered_until(end + 4 * second) == 3.5  # and past the last message
    assert buffer.uncovered_until(end) == 0.0  # a stamp not after the previous call's: no span
    moved = buffer.integrate_until(end + 4 * second)
    assert moved.dt == pytest.approx(0.5) and buffer.uncovered_until(end + 4 * second) == 0.0
    # overlapping messages count their common time once; a span without any message is uncovered whole
    buffer.add(end + 5 * second, 1.0, 0.0, 0.0, 0.6)
    buffer.add(end + 5 * second - second // 10, 1.0, 0.0, 0.0, 0.6)
    assert buffer.uncovered_until(end + 5 * second) == pytest.approx(0.3, abs=1e-12)
    buffer.integrate_until(end + 5 * second)
    assert buffer.uncovered_until(end + 6 * second) == 1.0 and buffer.integrate_until(end + 6 * second) is None


@pytest.mark.parametrize("back_s, starts_over", [(0.5, False), (3.0, True)])
def test_odometry_buffer_starts_over_at_a_new_run_of_the_stream(back_s, starts_over):
    """A session replayed again into a running worker: its odometry goes back in time. Further back than
    ``restart_after_ns`` it is a new run (integrated from its own start), nearer a late re-delivery (dropped)."""
    second = 1_000_000_000
    buffer = OdometryBuffer(restart_after_ns=second)
    for k in range(1, 11):  # the first run: 1 m/s forward up to 5 s
        buffer.add(k * second // 2, 1.0, 0.0, 0.0, 0.5)
    assert _pose_after(buffer.integrate_until(5 * second)) == pytest.approx((5.0, 0.0, 0.0))
    start = 5 * second - int(back_s * second)
    for k in range(1, 5):  # again from there, 2 m/s sideways
        buffer.add(start + k * second // 2, 0.0, 2.0, 0.0, 0.5)
    moved = buffer.integrate_until(start + 2 * second)
    if starts_over:  # the whole of the new run's motion up to the stamp (the first message's span before its start)
        assert buffer.covered_until_ns == start + 2 * second
        assert _pose_after(moved) == pytest.approx((0.0, 4.0, 0.0))
    else:  # only the part after the last stamp applied
        assert _pose_after(moved) == pytest.approx((0.0, 2.0 * (2.0 - back_s), 0.0))
