"""The incremental engine on a synthetic route: decisions against ground truth, statuses, restart."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from semloc_core.io.loopclosure import FileStorage, load_engine_state, save_engine_state
from semloc_core.loopclosure import engine as engine_module
from semloc_core.loopclosure import mrf as mrf_module
from semloc_core.loopclosure.calibration import CalibrationParams
from semloc_core.loopclosure.engine import EngineParams, FrameStatus, LoopClosureEngine
from semloc_core.loopclosure import extract_features
from semloc_core.loopclosure.features import FeatureParams, FeatureSequence

from .synthetic import ground_truth, synthetic_sequence

WINDOW = 8
# Scaled to the 80-frame synthetic route (window, band, bootstrap and band radius below the route's defaults). The
# synthetic descriptors have no image behind them: the configured t_match (the calibration is tested on images).
PARAMS = EngineParams(window=WINDOW, band=10, bootstrap_frames=20, bootstrap_pairs=100, vocabulary_words=100,
                      candidates=6, neighbour_candidates=2, calibration=CalibrationParams(mode="fixed"))
# The same with the bearing-band count instead of the DP's k (its band as the sequence calibration would set it for
# this route's parallax: test_band_count.py).
BAND = dataclasses.replace(PARAMS, alignment=dataclasses.replace(PARAMS.alignment, band_half_width=0.45,
                                                                  band_max_log_scale=0.16))
# The route revisits its poses exactly# The route revisits its poses exactly, so the default engine keeps only the first visits' frames (cull_redundant;
# test_redundant.py): the tests of the whole lattice keep every frame.
EVERY_FRAME = EngineParams(**{**PARAMS.__dict__, "cull_redundant": False})


@pytest.fixture(scope="module")
def route():
    poses, frames = synthetic_sequence(seed=2, spacing=1.0, landmarks=300)
    return poses, frames


def run(engine, frames):
    return [engine.add_frame(f) for f in frames]


def test_engine_finds_the_revisits(route):
    poses, frames = route
    engine = LoopClosureEngine(EVERY_FRAME)
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
    fast = LoopClosureEngine(EVERY_FRAME)
    full = LoopClosureEngine(EngineParams(**{**EVERY_FRAME.__dict__, "exhaustive": True}))
    aligned_fast = sum(r.candidates.size for r in run(fast, frames))
    aligned_full = sum(r.candidates.size for r in run(full, frames))
    a, b = fast.mrf.dense().decisions, full.mrf.dense().decisions
    assert np.sum(a & b) / np.sum(a | b) > 0.9
    assert aligned_fast < 0.5 * aligned_full


@pytest.mark.parametrize("params", [PARAMS, BAND], ids=["dp", "band"])
def test_restart_from_saved_state_continues_identically(route, tmp_path, params):
    _, frames = route
    reference = LoopClosureEngine(params)
    expected = run(reference, frames)
    engine = LoopClosureEngine(params)
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


def _same_results(expected, got):
    assert len(expected) == len(got)
    for a, b in zip(expected, got):
        assert a.frame == b.frame and a.status == b.status and a.node == b.node
        assert np.array_equal(a.candidates, b.candidates) and np.array_equal(a.loops, b.loops)
        assert np.array_equal(a.similarity, b.similarity) and np.array_equal(a.loop_beliefs, b.loop_beliefs)
        assert a.map_update == b.map_update


@pytest.mark.parametrize("params", [PARAMS, BAND], ids=["dp", "band"])
def test_file_storage_and_archived_cells_change_nothing_and_restart_from_a_small_state(route, tmp_path, monkeypatch,
                                                                                        params):
    """The descriptors in mapped files, the lattice's final cells archived and the inverted index frozen into
    blocks every few frames: the same results as everything in memory at once; a restart from the state and the files
    continues identically, and the state holds no descriptors, no archived cells and no frozen postings."""
    _, frames = route
    monkeypatch.setattr(mrf_module, "_ARCHIVE_CELLS", 10**9)  # the reference keeps every cell live
    monkeypatch.setattr(engine_module, "INDEX_BLOCK_FRAMES", 10**9)  # and its whole index open
    reference = LoopClosureEngine(params)
    expected = run(reference, frames)
    monkeypatch.setattr(mrf_module, "_ARCHIVE_CELLS", 8)
    monkeypatch.setattr(engine_module, "INDEX_BLOCK_FRAMES", 7)
    engine = LoopClosureEngine(params, storage=FileStorage(tmp_path / "store"))
    _same_results(expected[:45], run(engine, frames[:45]))
    assert len(engine.storage.log("mrf_cells", mrf_module.ARCHIVE_DTYPE)) > 0  # cells were archived
    assert engine._index.frozen_frames >= 28  # and index blocks frozen
    engine.flush()
    arrays, meta = engine.state()
    assert "descriptors" not in arrays and not any(k.startswith("mrf_archive_") for k in arrays)
    assert arrays["index_blocks"].size == engine._index.frozen_frames // 7
    save_engine_state(tmp_path / "engine.npz", arrays, meta)
    run(engine, frames[45:52])  # written after the state: a restart from the state drops it
    restored = LoopClosureEngine.from_state(*load_engine_state(tmp_path / "engine.npz"),
                                            storage=FileStorage(tmp_path / "store"))
    _same_results(expected[45:], run(restored, frames[45:]))
    for a, b in zip(reference.similarity_cells(), restored.similarity_cells()):
        assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="persistent storage"):
        LoopClosureEngine.from_state(arrays, meta)


def test_the_band_count_through_the_word_index_is_the_count_of_every_pair(route):
    """With every word a feature's word the index compares every pair: the compiled band count over the index's
    matches scores each candidate as similarity.pair_count does over the whole match matrix (match_words = 0)."""
    _, frames = route
    every_word = dataclasses.replace(BAND, match_words=BAND.vocabulary_words)
    indexed = run(LoopClosureEngine(every_word), frames[:40])
    plain = run(LoopClosureEngine(dataclasses.replace(BAND, match_words=0)), frames[:40])
    _same_results(plain, indexed)
    dp = run(LoopClosureEngine(PARAMS), frames[:40])
    assert any(not np.array_equal(a.similarity, b.similarity) for a, b in zip(dp, plain))  # the count is not k


@pytest.mark.parametrize("damage", ["nan", "huge", "short"])
def test_a_state_with_bad_bearings_is_refused(route, damage):
    _, frames = route
    engine = LoopClosureEngine(BAND)
    run(engine, frames[:12])
    arrays, meta = engine.state()
    bearings = arrays["bearings"].copy()
    bearings[3] = {"nan": np.nan, "huge": 1e300, "short": bearings[3]}[damage]
    arrays["bearings"] = bearings[:-1] if damage == "short" else bearings
    with pytest.raises(ValueError, match="bearings"):
        LoopClosureEngine.from_state(arrays, meta)


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
        engine = LoopClosureEngine(EngineParams(**{**EVERY_FRAME.__dict__, "candidates": 2,
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


def test_the_map_updates_rebuild_the_map(route):
    """Subscribers rebuild the topological map from the engine's map updates (the worker publishes them; `semloc
    export` rebuilds the map of a recording from them): the changes of revised frames included, the frames' nodes
    and the edges rebuilt from the updates alone are the map's."""
    _, frames = route
    engine = LoopClosureEngine(PARAMS)
    frame_node: dict[int, int] = {}
    edges: set[tuple[int, int]] = set()
    revised = 0
    for result in run(engine, frames):
        update = result.map_update
        revised += len(result.revised)
        frame_node.update(update.assigned)
        edges -= set(update.edges_removed)
        edges |= set(update.edges_added)
    snapshot = engine.topomap.snapshot()
    rebuilt = np.full(engine.n_frames, -1)
    rebuilt[list(frame_node)] = list(frame_node.values())
    assert revised > 0  # the route has revisions: what this test is about
    assert np.array_equal(rebuilt, snapshot.frame_node)
    assert edges == {tuple(map(int, edge)) for edge in snapshot.edges}


def test_reported_loops_with_their_revisions_are_the_final_decisions(route):
    """What a subscriber holds after applying every frame's loops and revisions (the demo's report does) is the
    engine's final decision: every scored pair with a belief at the last decision threshold. The threshold is
    re-estimated as the lattice grows, so frames that left the band are revised too when it moves."""
    _, frames = route
    engine = LoopClosureEngine(EVERY_FRAME)
    held: dict[int, set[int]] = {}
    thresholds = set()
    for features in frames:
        result = engine.add_frame(features)
        held[result.frame] = set(result.loops.tolist())
        for frame, loops in result.revised.items():
            assert frame < result.frame
            held[frame] = set(np.asarray(loops).tolist())
        thresholds.add(engine.decision_threshold)
    assert len(thresholds) > 2  # the threshold moved while frames left the band: what this test is about
    rows, cols, _, beliefs = engine.mrf.cells()
    decided = beliefs >= engine.decision_threshold
    final = {j: set(rows[decided & (cols == j)].tolist()) for j in range(engine.n_frames)}
    assert any(final.values())
    assert held == final


@pytest.mark.parametrize("target, min_recall", [(0.9, 0.55), (0.95, 0.43)])
def test_decision_null_is_that_of_the_pairs_drawn_at_random(route, target, min_recall):
    """The engine's decisions fit their null to the background draws (a uniform sample of the pairs), not to the
    retrieved candidates (the best-looking unrelated pairs and the loops): against the route's ground truth (pairs
    within 2.5 m loops, beyond 8 m unrelated, between them left out) the precision expected is the measured one
    within 0.1 (issue 33's tolerance), at the target or above. Fitted to the lattice's lower half the recall was
    0.47 at 0.9 and 0.40 at 0.95 (results/2026-12-06-loop-decision-recall.md); now 0.61 and 0.48."""
    poses, frames = route
    engine = LoopClosureEngine(EVERY_FRAME)
    run(engine, frames)
    decision = engine.decision_at(target)
    rows, cols, _, beliefs = engine.mrf.cells()
    draws = engine._background.read()
    assert draws.size and np.all(draws["earlier"] < draws["later"] - WINDOW)
    gt, near = ground_truth(poses, 2.5, WINDOW), ground_truth(poses, 8.0, WINDOW)
    decided = beliefs >= decision.threshold
    counted = decided & (gt[rows, cols] | ~near[rows, cols])
    measured = np.sum(decided & gt[rows, cols]) / max(counted.sum(), 1)
    assert counted.sum() > 0
    assert abs(measured - decision.expected_precision) <= 0.1 and measured >= target - 0.05, (measured, decision)
    assert np.sum(decided & gt[rows, cols]) / gt.sum() >= min_recall



def test_decision_state_says_when_no_loops_can_be_reported(route):
    """The worker's status tells a lattice too small for a threshold ('waiting') from one where no threshold reaches
    the target precision ('unreachable': the engine reports no loops, whatever it aligns) and from 'reporting'."""
    poses, frames = route
    engine = LoopClosureEngine(EVERY_FRAME)
    states = [(engine.add_frame(f), engine.decision_state)[1] for f in frames]
    assert states[0] == "waiting" and states[-1] == "reporting"
    assert "unreachable" not in states[states.index("reporting"):]  # the route's revisits keep a threshold
    engine.decision = dataclasses.replace(engine.decision, threshold=np.inf, expected_precision=None, decided=0)
    assert engine.decision_state == "unreachable"


@pytest.mark.slow
def test_a_long_table_top_lap_keeps_a_decision_threshold(sim_scenario):
    """On a table top every frame sees the same objects, and the retrieved candidates look alike: a null fitted to
    them (the engine before the background draws) lost its threshold from frame 422 of this 520-frame walk
    (+inf, no loops reported, at 79 of the frames after the first revisit, and 0.63 of its reported loops were
    right; results/2026-12-06-loop-threshold-inf.md). Against the simulator's ground truth: once the engine has
    reported a true loop it keeps a threshold, and its loops are right."""
    scenario = sim_scenario("tabletop", frames=520, seed=0)
    params = EngineParams()
    truth = np.triu(scenario.loop_gt | scenario.loop_gt.T, params.window + 1)
    possible = np.triu(scenario.loop_gt_soft | scenario.loop_gt_soft.T, params.window + 1)
    engine = LoopClosureEngine(params)
    right = wrong = 0
    lost = []
    for k in range(len(scenario)):
        result = engine.add_frame(extract_features(scenario.image(k), scenario.camera, FeatureParams(),
                                                   scenario.T_body_cam_at(k)))
        if right and engine.decision_state != "reporting":
            lost.append(k)
        right += int(truth[result.loops, k].sum())
        wrong += int((~possible[result.loops, k]).sum())
    assert right >= 50 and not lost, (right, lost)
    assert right / (right + wrong) >= params.target_precision - 0.05, (right, wrong)
