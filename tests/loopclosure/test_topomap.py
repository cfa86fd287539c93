"""Dominating-set topological map: algorithm 3.1, the incremental map's invariants, export."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from semloc_core.loopclosure.topomap import (
    IncrementalTopoMap,
    TopologicalMap,
    adjacency,
    build_topological_map,
    dominating_set,
)


def test_algorithm_3_1_on_a_small_graph():
    # Star centred on 2 (neighbours 0, 1, 3, 4) and a path 5-6-7: greedy takes 2 first, then 6.
    neighbours = adjacency(8, [(0, 2), (1, 2), (2, 3), (2, 4), (5, 6), (6, 7)])
    keyframes, members = dominating_set(neighbours)
    assert keyframes == [2, 6]
    assert members == [[0, 1, 2, 3, 4], [5, 6, 7]]


def test_isolated_frames_are_their_own_nodes_without_temporal_links():
    topomap = build_topological_map(6, [], temporal_radius=0)
    assert topomap.n_nodes == 6 and np.array_equal(topomap.frame_node, np.arange(6))
    assert topomap.edges.tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]]


def check_map(topomap: TopologicalMap, n: int, loop_pairs, radius: int, allow_pending: int = 0):
    neighbours = adjacency(n, loop_pairs, radius)
    assigned = topomap.frame_node >= 0
    assert assigned[: n - allow_pending].all()  # every frame (but the pending tail) in exactly one node
    for node, key in zip(topomap.node_ids, topomap.keyframes):
        assert topomap.frame_node[key] == node
        for member in topomap.members(int(node)):
            assert member == key or member in neighbours[key]  # K dominates its sets
    expected = {}
    for a, b in zip(topomap.frame_node[:-1], topomap.frame_node[1:]):
        if a != b and a >= 0 and b >= 0:
            key = (min(a, b), max(a, b))
            expected[key] = expected.get(key, 0) + 1
    got = {tuple(e): int(t) for e, t in zip(topomap.edges.tolist(), topomap.transitions.tolist())}
    assert got == expected


def random_loops(n: int, rng: np.random.Generator, count: int) -> list[tuple[int, int]]:
    later = rng.integers(10, n, count)
    earlier = (later - rng.integers(8, 40, count)).clip(0)
    return sorted({(int(a), int(b)) for a, b in zip(earlier, later) if a < b})


@pytest.mark.parametrize("radius", [0, 2])
def test_batch_map_invariants(radius):
    rng = np.random.default_rng(0)
    loops = random_loops(150, rng, 120)
    topomap = build_topological_map(150, loops, radius)
    check_map(topomap, 150, loops, radius)


@pytest.mark.parametrize("radius", [0, 1, 2, 3])
def test_incremental_map_on_a_route_seen_once(radius):
    topomap = IncrementalTopoMap(radius)
    for _ in range(60):
        topomap.add_frame([])
    snapshot = topomap.snapshot()
    check_map(snapshot, 60, [], radius, allow_pending=radius)
    # Key-frames every 2r + 1 frames, like algorithm 3.1 on a path.
    assert snapshot.n_nodes == pytest.approx(60 / (2 * radius + 1), abs=1)
    assert snapshot.n_nodes <= build_topological_map(60, [], radius).n_nodes + 1


def test_a_revisit_reuses_the_nodes_it_revisits():
    topomap = IncrementalTopoMap(2)
    for _ in range(50):
        topomap.add_frame([])
    nodes_first_pass = topomap.n_nodes
    for frame in range(50, 100):
        # The second pass sees the first pass's frames 0..49 again, each closing loops with three of them.
        centre = frame - 50
        topomap.add_frame([f for f in (centre - 1, centre, centre + 1) if 0 <= f < 50])
    snapshot = topomap.snapshot()
    # A revisit frame joins a first-pass node when one of its partners is that node's key-frame (3 frames in 5);
    # the others are dominated by a new key-frame among the revisit frames.
    reused = np.isin(snapshot.frame_node[50:98], snapshot.frame_node[:50])
    assert reused.mean() >= 0.55
    assert topomap.n_nodes <= nodes_first_pass + 12
    assert topomap.n_nodes <= 0.3 * 100
    check_map(snapshot, 100, [(a, b) for b in range(100) for a in topomap.loops_of(b) if a < b], 2, 2)


@pytest.mark.parametrize("seed", range(4))
def test_incremental_invariants_and_stable_ids_under_revisions(seed):
    rng = np.random.default_rng(seed)
    radius = int(rng.integers(0, 3))
    topomap = IncrementalTopoMap(radius)
    keyframes_seen: dict[int, int] = {}
    for frame in range(120):
        partners = rng.choice(frame, size=min(frame, int(rng.integers(0, 3))), replace=False) if frame > 5 else []
        update = topomap.add_frame(partners)
        for node, key in update.new_nodes:
            keyframes_seen[node] = key
        if frame > 10 and rng.random() < 0.3:
            # Revise a recent frame's loops, as the MRF band does.
            target = int(rng.integers(max(1, frame - 10), frame + 1))
            new = rng.choice(target, size=min(target, int(rng.integers(0, 3))), replace=False)
            update = topomap.revise(target, new)
            for node, key in update.new_nodes:
                keyframes_seen[node] = key
        snapshot = topomap.snapshot()
        loops = [(a, b) for b in range(frame + 1) for a in topomap.loops_of(b) if a < b]
        check_map(snapshot, frame + 1, loops, radius, allow_pending=radius)
        # Node ids are stable: a node keeps its key-frame for ever.
        assert {n: k for n, k in zip(snapshot.node_ids.tolist(), snapshot.keyframes.tolist())} == keyframes_seen


def test_updates_report_what_changed():
    topomap = IncrementalTopoMap(0)
    first = topomap.add_frame([])
    assert first.new_nodes == [(0, 0)] and first.assigned == [(0, 0)] and first.edges_added == []
    second = topomap.add_frame([])
    assert second.new_nodes == [(1, 1)] and second.edges_added == [(0, 1)]
    third = topomap.add_frame([0])
    assert third.assigned == [(2, 0)] and third.new_nodes == []
    assert topomap.snapshot().transitions.tolist() == [2]  # 0->1 and 1->0


def test_json_and_graphml_export():
    rng = np.random.default_rng(5)
    loops = random_loops(80, rng, 40)
    topomap = build_topological_map(80, loops, 1)
    data = json.loads(json.dumps(topomap.to_json_dict()))
    again = TopologicalMap.from_json_dict(data)
    assert np.array_equal(again.frame_node, topomap.frame_node)
    assert np.array_equal(again.edges, topomap.edges) and np.array_equal(again.transitions, topomap.transitions)
    root = ET.fromstring(topomap.to_graphml())
    ns = {"g": "http://graphml.graphdrawing.org/xmlns"}
    assert len(root.findall(".//g:node", ns)) == topomap.n_nodes
    assert len(root.findall(".//g:edge", ns)) == len(topomap.edges)
    sizes = sorted(int(d.text) for d in root.findall(".//g:node/g:data[@key='size']", ns))
    assert sum(sizes) == 80


def test_state_round_trip():
    rng = np.random.default_rng(6)
    a = IncrementalTopoMap(2)
    for frame in range(60):
        a.add_frame(rng.choice(frame, size=min(frame, 1), replace=False) if frame > 20 else [])
    b = IncrementalTopoMap.from_state(a.state(), 2)
    for frame in range(60, 90):
        partners = rng.choice(frame, size=1, replace=False)
        ua, ub = a.add_frame(partners), b.add_frame(partners)
        assert ua == ub
    sa, sb = a.snapshot(), b.snapshot()
    assert np.array_equal(sa.frame_node, sb.frame_node) and np.array_equal(sa.edges, sb.edges)


def test_bad_partners_raise():
    topomap = IncrementalTopoMap(1)
    topomap.add_frame([])
    with pytest.raises(ValueError, match="earlier"):
        topomap.add_frame([1])
