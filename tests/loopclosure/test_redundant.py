"""A camera going over the same route again: the map keeps each view once (cull_redundant), its decisions still name
the right places. Real SIFT on the simulator's route images, ground truth from its poses."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.io.loopclosure import FileStorage, load_engine_state, save_engine_state
from semloc_core.loopclosure import EngineParams, FeatureParams, LoopClosureEngine, extract_features
from semloc_core.loopclosure.engine import FrameStatus
from semloc_core.loopclosure.mrf import ARCHIVE_DTYPE

LAP = 48  # route frames 0.6 m apart: a stretch of corridor
LAPS = 4
PARAMS = EngineParams(window=12)  # the demo's window; every other setting the worker's default


@pytest.fixture(scope="module")
def stretch(sim_scenario):
    scenario = sim_scenario("route", frames=LAP, seed=0)
    features = [extract_features(scenario.image(i), scenario.camera, FeatureParams(repeated_threshold=0),
                                 scenario.T_body_cam_at(i)) for i in range(LAP)]
    positions = scenario.T_world_body[:, :2, 3]
    return features, positions


def _laps(seed: int = 1) -> list[int]:
    """The images played: the stretch once, then again and again with about a third of the images dropped (a
    worker taking the latest image drops what it cannot take, a different third each time)."""
    rng = np.random.default_rng(seed)
    order = list(range(LAP))
    for _ in range(LAPS - 1):
        order += [i for i in range(LAP) if rng.random() > 1 / 3]
    return order


def test_a_route_seen_again_adds_no_frame_and_its_loops_still_name_the_place(stretch, tmp_path):
    features, positions = stretch
    order = _laps()
    engine = LoopClosureEngine(PARAMS, storage=FileStorage(tmp_path / "store"))
    archive = engine.storage.log("mrf_cells", ARCHIVE_DTYPE)
    kept_after_lap, nodes_after_lap, archived_after_lap = [], [], []
    results = []
    for k, image in enumerate(order):
        results.append(engine.add_frame(features[image]))
        if k + 1 == LAP or (k + 1 > LAP and (k + 1 - LAP) % ((len(order) - LAP) // (LAPS - 1)) == 0):
            kept_after_lap.append(engine.n_kept)
            nodes_after_lap.append(engine.topomap.n_nodes)
            archived_after_lap.append(len(archive))
    first, repeats = results[:LAP], results[LAP:]
    # The first pass shows distinct views: every frame is kept.
    assert all(r.redundant_with < 0 for r in first) and kept_after_lap[0] == LAP
    # Again over the same images: nothing new for the map - no frame, no place, no descriptor, no archived cell.
    assert kept_after_lap == [LAP] * len(kept_after_lap)
    assert nodes_after_lap[1:] == [nodes_after_lap[0]] * (len(nodes_after_lap) - 1)
    assert archived_after_lap[-1] == archived_after_lap[-2]
    culled = [r for r in repeats if r.redundant_with >= 0]
    assert len(culled) >= 0.9 * len(repeats)
    for r in culled:
        image = order[r.frame]
        # The frame holding its view shows the same place: the same image, or the next one on the route.
        assert np.linalg.norm(positions[order[r.redundant_with]] - positions[image]) <= 0.61
        assert r.node == engine.topomap.node_of(r.redundant_with)  # recorded at that place
        assert len(engine.descriptors(r.frame)) == 0
    # Its decisions name the right places: each repeated frame finds the place it shows (its strongest loop: the
    # same image or the next), and it names no more far frames (beyond the simulator's 2.5 m) than an engine
    # keeping every frame does (a stretch of corridor looks alike for metres: both name some).
    reference = LoopClosureEngine(EngineParams(**{**PARAMS.__dict__, "cull_redundant": False}))
    every = [reference.add_frame(features[image]) for image in order]
    assert reference.n_kept == len(order)  # the map grows with every lap

    def far_loops(result) -> int:
        distance = np.linalg.norm(positions[[order[f] for f in result.loops.tolist()]] - positions[order[result.frame]],
                                  axis=1)
        return int(np.sum(distance > 2.5))

    for r in repeats:
        assert r.status is FrameStatus.LOOP_FOUND
        strongest = r.loops[np.argmax(r.loop_beliefs)]
        assert np.linalg.norm(positions[order[strongest]] - positions[order[r.frame]]) <= 0.61
    assert sum(far_loops(r) for r in repeats) <= sum(far_loops(r) for r in every[LAP:])
    for r in repeats:
        assert not np.any(r.candidates >= LAP)  # no dropped frame is aligned again
    # A restart from the state and the store continues the same way.
    engine.flush()
    save_engine_state(tmp_path / "engine.npz", *engine.state())
    restored = LoopClosureEngine.from_state(*load_engine_state(tmp_path / "engine.npz"),
                                            storage=FileStorage(tmp_path / "store"))
    for image in order[LAP: 2 * LAP]:
        a, b = engine.add_frame(features[image]), restored.add_frame(features[image])
        assert (a.redundant_with, a.node, a.status) == (b.redundant_with, b.node, b.status)
        assert np.array_equal(a.loops, b.loops) and np.array_equal(a.candidates, b.candidates)
    assert restored.n_kept == LAP
