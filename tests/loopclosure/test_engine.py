"""The incremental engine on a synthetic route: decisions against ground truth, statuses, restart."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.io.loopclosure import load_engine_state, save_engine_state
from semloc_core.loopclosure.engine import EngineParams, FrameStatus, LoopClosureEngine
from semloc_core.loopclosure.features import FeatureSequence

from .synthetic import ground_truth, synthetic_sequence

WINDOW = 8
# Scaled to the 80-frame synthetic route (window, band, bootstrap and band radius below the route's defaults).
PARAMS = EngineParams(window=WINDOW, band=10, bootstrap_frames=20, bootstrap_pairs=100, vocabulary_words=100,
                      candidates=6, neighbour_candidates=2)


@pytest.fixture(scope="module")
def route():
    poses, frames = synthetic_sequence(seed=2, spacing=1.0, landmarks=300)
    return poses, frames


def run(engine, frames):
    return [engine.add_frame(f) for f in frames]


def test_engine_finds_the_revisits(route):
    poses, frames = route
    engine = LoopClosureEngine(PARAMS)
    results = run(engine, frames)
    # Landmarks are seen from up to 6 m, so frames 8 m apart still share some: pairs within 2.5 m must be found,
    # pairs beyond 8 m (nothing much in common) must not.
    gt, near = ground_truth(poses, 2.5, WINDOW), ground_truth(poses, 8.0, WINDOW)
    decisions = engine.mrf.dense().decisions
    assert np.sum(decisions & near) / decisions.sum() >= 0.95
    assert np.sum(decisions & gt) / gt.sum() >= 0.5
    statuses = [r.status for r in results]
    assert all(s is FrameStatus.TOO_FEW_FRAMES for s in statuses[: WINDOW + 1])
    # The second and third laps (from frame 40) revisit the first.
    assert np.mean([s is FrameStatus.LOOP_FOUND for s in statuses[40:]]) > 0.9
    for r in results:
        assert np.all(r.loops < r.frame - WINDOW)
        assert np.all(np.isin(r.loops, r.candidates))
        assert r.similarity.shape == r.candidates.shape
    # The map: every frame but the last pending ones in one node, far fewer nodes than frames.
    snapshot = engine.topomap.snapshot()
    assert np.all(snapshot.frame_node[: len(frames) - PARAMS.temporal_radius] >= 0)
    assert snapshot.n_nodes <= 0.3 * len(frames)


def test_retrieval_gives_the_exhaustive_decisions(route):
    _, frames = route
    fast = LoopClosureEngine(PARAMS)
    full = LoopClosureEngine(EngineParams(**{**PARAMS.__dict__, "exhaustive": True}))
    aligned_fast = sum(r.candidates.size for r in run(fast, frames))
    aligned_full = sum(r.candidates.size for r in run(full, frames))
    a, b = fast.mrf.dense().decisions, full.mrf.dense().decisions
    assert np.sum(a & b) / np.sum(a | b) > 0.9
    assert aligned_fast < 0.5 * aligned_full


def test_restart_from_saved_state_continues_identically(route, tmp_path):
    _, frames = route
    reference = LoopClosureEngine(PARAMS)
    expected = run(reference, frames)
    engine = LoopClosureEngine(PARAMS)
    run(engine, frames[:45])
    path = tmp_path / "engine.npz"
    save_engine_state(path, *engine.state())
    restored = LoopClosureEngine.from_state(*load_engine_state(path))
    got = run(restored, frames[45:])
    for a, b in zip(expected[45:], got):
        assert a.status == b.status and a.node == b.node
        assert np.array_equal(a.candidates, b.candidates) and np.array_equal(a.loops, b.loops)
        assert np.allclose(a.similarity, b.similarity) and np.allclose(a.loop_beliefs, b.loop_beliefs)
        assert a.map_update == b.map_update


def test_featureless_frames_and_bad_input():
    engine = LoopClosureEngine(EngineParams(window=2, bootstrap_frames=1000))
    rng = np.random.default_rng(0)
    textured = FeatureSequence.from_unsorted(rng.uniform(-3, 3, 30), rng.integers(0, 60, (30, 128)).astype(np.uint8))
    for _ in range(4):
        engine.add_frame(textured)
    assert engine.add_frame(FeatureSequence.empty()).status is FrameStatus.NO_CANDIDATE
    with pytest.raises(TypeError):
        engine.add_frame(np.zeros((3, 128)))


def test_params_round_trip_through_json():
    params = EngineParams(window=12, background_samples=3)
    assert EngineParams.from_json_dict(params.to_json_dict()) == params
    with pytest.raises(ValueError):
        EngineParams(band=0)


def test_candidates_follow_the_loop_band(route):
    """Retrieval only has to find where a revisit starts: the frames next to the previous frame's loop partners
    (D) are aligned too, so the engine scores nearly every ground-truth pair of each band with 2 retrieved frames
    per frame; retrieval alone misses most of them."""
    poses, frames = route
    gt = ground_truth(poses, 2.5, WINDOW)

    def coverage(neighbours: int) -> float:
        engine = LoopClosureEngine(EngineParams(**{**PARAMS.__dict__, "candidates": 2,
                                                   "neighbour_candidates": neighbours}))
        run(engine, frames)
        rows, cols, _, _ = engine.similarity_cells()
        scored = np.zeros(gt.shape, bool)
        scored[rows, cols] = True
        near = ground_truth(poses, 8.0, WINDOW)  # landmarks are seen from 6 m: pairs beyond 8 m are not loops
        decisions = engine.mrf.dense().decisions
        assert np.sum(decisions & near) / decisions.sum() >= 0.95
        return float(np.sum(scored & gt) / gt.sum())

    assert coverage(0) < 0.5
    assert coverage(2) >= 0.95
