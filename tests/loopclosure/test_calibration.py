"""Self-calibration from the sequence (issue 33): the match threshold follows the descriptors' noise, the static
regions are those of a fixed overlay, and the engine calibrates before it aligns anything."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.loopclosure.calibration import Calibration, CalibrationParams, calibrate
from semloc_core.loopclosure.features import l1_distances
from semloc_core.loopclosure.engine import EngineParams, LoopClosureEngine
from semloc_core.loopclosure.features import normalize_descriptors

from .synthetic import LandmarkWorld, loop_route, sift_like


def noisy_route(noise: float, seed: int = 4, frames: int = 40):
    rng = np.random.default_rng(seed)
    world = LandmarkWorld.random(300, 10.0, rng)
    poses = loop_route(10.0, 0.5)[:frames]
    return world, [world.observe(p, rng, noise=noise) for p in poses]


def true_and_chance_distances(world: LandmarkWorld, noise: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth: L1 distances between two noisy views of one landmark, and from a view to the nearest view of
    150 other landmarks (what a feature of an unrelated frame can reach)."""
    def view(d):
        return normalize_descriptors(d + noise * np.abs(rng.normal(0, 1, d.shape)) / np.sqrt(128))

    a, b = view(world.descriptors), view(world.descriptors)
    true = np.abs(a.astype(np.int32) - b.astype(np.int32)).sum(axis=1)
    others = normalize_descriptors(sift_like(150, rng))
    chance = l1_distances(a, others).min(axis=1)
    return true, chance


@pytest.mark.parametrize("noise", [0.15, 0.3])
def test_threshold_separates_true_correspondences_from_chance(noise):
    world, frames = noisy_route(noise)
    calibration = calibrate(frames)
    true, chance = true_and_chance_distances(world, noise, np.random.default_rng(1))
    t = calibration.t_match
    assert np.mean(true < t) >= 0.75
    assert np.mean(chance < t) <= 0.1
    assert calibration.repeated_threshold == t and calibration.static is None


def test_threshold_grows_with_descriptor_noise():
    low = calibrate(noisy_route(0.1)[1]).t_match
    high = calibrate(noisy_route(0.35)[1]).t_match
    assert high > low + 200


def test_too_few_frames_say_nothing():
    _, frames = noisy_route(0.1, frames=3)
    assert calibrate(frames) is None


def test_static_region_is_masked_and_only_it():
    """Features at fixed pixels (an overlay) in every frame, the rest moving: the overlay's cells are static."""
    _, frames = noisy_route(0.1, frames=30)
    rng = np.random.default_rng(5)
    overlay = normalize_descriptors(sift_like(6, rng))
    overlay_points = np.array([[10.0, 110.0], [30.0, 112.0], [50.0, 111.0], [70.0, 113.0], [90.0, 110.0],
                               [110.0, 112.0]], np.float32)
    placed = []
    for k, f in enumerate(frames):
        moving = rng.uniform([0, 0], [160, 95], (len(f), 2)).astype(np.float32)  # upper part, anywhere
        noisy = normalize_descriptors(overlay + 0.03 * np.abs(rng.normal(0, 1, overlay.shape)))
        from semloc_core.loopclosure.features import FeatureSequence

        placed.append(FeatureSequence.from_unsorted(
            np.concatenate([f.bearings, rng.uniform(-1, 1, len(overlay))]),
            np.concatenate([f.descriptors, noisy]), None, np.concatenate([moving, overlay_points])))
    calibration = calibrate(placed, image_size=(160, 120))
    assert calibration.static is not None
    kept = calibration.apply(placed[0])
    assert not np.any(kept.points[:, 1] >= 105)  # the overlay row is gone
    assert len(kept) >= 0.7 * len(frames[0])  # the moving features stay


def test_calibration_survives_its_state():
    _, frames = noisy_route(0.15)
    calibration = calibrate(frames)
    again = Calibration.from_array(calibration.to_array())
    assert again.t_match == calibration.t_match and again.frames == calibration.frames


@pytest.mark.parametrize("given_vocabulary", [False, True])
def test_engine_calibrates_first_then_aligns(given_vocabulary):
    from semloc_core.loopclosure.bow import train_vocabulary

    _, frames = noisy_route(0.15, frames=60)
    params = EngineParams(window=8, band=10, bootstrap_frames=20, bootstrap_pairs=100, vocabulary_words=100,
                          candidates=6, calibration=CalibrationParams(frames=15))
    vocabulary = train_vocabulary([f.descriptors for f in frames], words=100) if given_vocabulary else None
    engine = LoopClosureEngine(params, vocabulary)
    results = [engine.add_frame(f) for f in frames]
    assert all(r.candidates.size == 0 for r in results[:14])  # the 15th frame is aligned on the calibration
    assert engine.calibration is not None and engine.alignment.t_match == engine.calibration.t_match
    assert engine.calibration.t_match == calibrate(frames[:15], params.calibration).t_match
    assert any(r.candidates.size for r in results[16:])
    restored = LoopClosureEngine.from_state(*engine.state())
    assert restored.calibration.t_match == engine.calibration.t_match
    assert restored.decision == engine.decision


@pytest.mark.parametrize("persistent", [False, True])
def test_engine_state_while_calibrating_continues_identically(tmp_path, persistent):
    """Saved half-way through its calibration frames (held in memory, not yet in the storage), the engine restarts
    with them and calibrates, aligns and decides exactly as one that ran through; another version is refused."""
    from semloc_core.io.loopclosure import FileStorage

    _, frames = noisy_route(0.15, frames=50)
    params = EngineParams(window=8, band=10, bootstrap_frames=20, bootstrap_pairs=100, vocabulary_words=100,
                          candidates=6, calibration=CalibrationParams(frames=15))

    def storage(name):
        return FileStorage(tmp_path / name) if persistent else None

    reference = LoopClosureEngine(params, storage=storage("reference"))
    expected = [reference.add_frame(f) for f in frames]
    engine = LoopClosureEngine(params, storage=storage("store"))
    for f in frames[:9]:
        engine.add_frame(f)
    assert engine.calibrating and len(engine._store) == 0  # held for the calibration, nothing stored yet
    engine.flush()
    arrays, meta = engine.state()
    assert int(arrays["pending_frames"]) == 9
    restored = LoopClosureEngine.from_state(arrays, meta, storage("store"))
    assert restored.n_frames == 9 and restored.calibrating
    assert np.array_equal(restored.descriptors(4), frames[4].descriptors)
    got = [restored.add_frame(f) for f in frames[9:]]
    assert restored.calibration.t_match == reference.calibration.t_match
    for a, b in zip(expected[9:], got):
        assert a.status == b.status and np.array_equal(a.candidates, b.candidates)
        assert np.array_equal(a.loops, b.loops) and np.array_equal(a.similarity, b.similarity)
    assert restored.decision == reference.decision
    with pytest.raises(ValueError, match="version 4 cannot be read"):
        LoopClosureEngine.from_state(arrays, {**meta, "version": 4}, storage("store"))


@pytest.mark.parametrize("noise", [0.3, 0.5])
def test_threshold_ranks_revisits_as_well_as_any(noise):
    """Judged by what the DP does with it: the threshold chosen on the first 30 frames (no ground truth) ranks the
    revisits of the whole route (ground truth: poses within 2 m) as well as the best of a sweep, where too low a
    threshold loses them."""
    from semloc_core.eval.pr import average_precision, pr_curve
    from semloc_core.loopclosure.features import suppress_repeated
    from semloc_core.loopclosure.similarity import AlignmentParams, dp_similarity

    from .synthetic import ground_truth, synthetic_sequence

    poses, frames = synthetic_sequence(seed=3, noise=noise, keep=0.5, clutter=40, max_range=4.0)
    t = calibrate(frames[:30]).t_match
    poses, frames = poses[::2], frames[::2]  # every other frame: a quicker sweep
    truth = ground_truth(poses, 2.0, 4)
    first, second = np.nonzero(np.triu(np.ones(truth.shape, bool), 5))

    def ap(threshold):
        kept = [suppress_repeated(f, threshold) for f in frames]
        params = AlignmentParams(t_match=threshold)
        scores = [dp_similarity(kept[b], kept[a], params) for a, b in zip(first, second)]
        return average_precision(pr_curve(np.array(scores), truth[first, second]))

    sweep = {threshold: ap(threshold) for threshold in (800.0, 1200.0, 1600.0, 2000.0, 2400.0)}
    assert min(sweep.values()) < max(sweep.values()) - 0.3  # the threshold matters here
    assert ap(t) >= max(sweep.values()) - 0.02


@pytest.mark.parametrize("bootstrap_frames", [15, 25], ids=["same-frame", "later"])
def test_one_off_steps_prepared_ahead_give_the_same_engine(bootstrap_frames, monkeypatch):
    """The calibration and the vocabulary computed ahead (``prepare``, what the worker runs on a helper thread while
    its frames keep coming) and handed to ``add_frame``, which then computes neither: every frame's result and the
    final state are those of the engine that computed them itself; only the frames with such a step have any; work
    prepared for another frame is refused."""
    import dataclasses

    from semloc_core.loopclosure import engine as engine_module

    _, frames = noisy_route(0.15, frames=45)
    params = EngineParams(window=8, band=10, bootstrap_frames=bootstrap_frames, bootstrap_pairs=100,
                          vocabulary_words=100, candidates=6, calibration=CalibrationParams(frames=15))
    reference = LoopClosureEngine(params)
    expected = [reference.add_frame(f) for f in frames]
    engine = LoopClosureEngine(params)
    got, prepared_at = [], []
    for t, f in enumerate(frames):
        work = engine.prepare(f)
        prepared = None
        if work is not None:
            prepared_at.append(t)
            prepared = work()
            with pytest.raises(ValueError, match="prepared for frame"):
                LoopClosureEngine(params).add_frame(f, prepared)  # (a fresh engine is at frame 0)
        with monkeypatch.context() as m:
            for name in ("calibrate", "train_vocabulary"):
                m.setattr(engine_module, name, lambda *a, **k: pytest.fail("computed on the frame path"))
            got.append(engine.add_frame(f, prepared))
    assert prepared_at == sorted({14, bootstrap_frames - 1})  # the calibration's last frame, the vocabulary's
    assert engine.vocabulary is not None and engine.calibration is not None
    for a, b in zip(got, expected, strict=True):
        for field in dataclasses.fields(a):
            x, y = getattr(a, field.name), getattr(b, field.name)
            if field.name == "revised":
                assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
            elif isinstance(x, np.ndarray):
                assert np.array_equal(x, y), (a.frame, field.name)
            else:
                assert x == y, (a.frame, field.name)
    (arrays, meta), (arrays_ref, meta_ref) = engine.state(), reference.state()
    assert meta == meta_ref and arrays.keys() == arrays_ref.keys()
    assert all(np.array_equal(arrays[k], arrays_ref[k]) for k in arrays)
