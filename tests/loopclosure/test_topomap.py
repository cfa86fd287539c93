"""Dominating-set topological map: algorithm 3.1, the incremental map's invariants, export."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from semloc_core.loopclosure.topomap import (
    IncrementalTopoMap,
    TopologicalMap,
    TopoMapUpdate,
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
    # The end of the sequence: the waiting frames get a key-frame, and the map goes on as usual afterwards.
    topomap.flush()
    check_map(topomap.snapshot(), 60, [], radius)
    topomap.add_frame([])
    check_map(topomap.snapshot(), 61, [], radius, allow_pending=1)


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


# --- loop strengths: a frame joins the key-frame it is most surely the same place as ---------------------------

# Two stars, centred on 2 (0, 1, 3 and 10) and on 6 (4, 5, 7 and 10): algorithm 3.1 takes 2 first (ties go to the
# earliest frame), so frame 10, dominated by both, is in 2's set N_2; 8, 9, 11 are isolated.
STARS = [(0, 2), (1, 2), (2, 3), (2, 10), (4, 6), (5, 6), (6, 7), (6, 10)]


def test_batch_map_joins_the_strongest_key_frame():
    plain = build_topological_map(12, STARS, 0)
    assert plain.keyframes[:2].tolist() == [2, 6] and plain.frame_node[10] == 0  # algorithm 3.1's N_2
    strengths = [5.0, 5.0, 5.0, 3.0, 5.0, 5.0, 5.0, 9.0]  # 10 is surer to be where 6 is
    strong = build_topological_map(12, STARS, 0, strengths=strengths)
    assert np.array_equal(strong.keyframes, plain.keyframes)  # the same K, only N_k changes
    assert strong.frame_node[10] == 1
    assert np.array_equal(np.delete(strong.frame_node, 10), np.delete(plain.frame_node, 10))
    check_map(strong, 12, STARS, 0)
    # Equal strengths: the older node, as without strengths.
    assert build_topological_map(12, STARS, 0, strengths=np.full(8, 4.0)).frame_node[10] == 0
    # A pair listed twice keeps its strongest value.
    twice = build_topological_map(12, STARS + [(10, 2)], 0, strengths=strengths + [12.0])
    assert twice.frame_node[10] == 0


@pytest.mark.parametrize("radius", [0, 2])
def test_batch_map_prefers_the_strongest_loop_then_the_nearest_key_frame_in_time(radius):
    rng = np.random.default_rng(radius)
    loops = random_loops(150, rng, 120)
    strengths = rng.uniform(0.0, 30.0, len(loops))
    topomap = build_topological_map(150, loops, radius, strengths=strengths)
    plain = build_topological_map(150, loops, radius)
    assert np.array_equal(topomap.keyframes, plain.keyframes)
    check_map(topomap, 150, loops, radius)
    strength = {pair: s for pair, s in zip(loops, strengths)}
    node_of_key = {int(k): int(n) for n, k in zip(topomap.node_ids, topomap.keyframes)}
    moved = 0
    for frame in set(range(150)) - set(node_of_key):
        linked = {k: strength[(min(k, frame), max(k, frame))] for k in node_of_key
                  if (min(k, frame), max(k, frame)) in strength}
        if linked:
            best = max(linked.values())
            assert linked[int(topomap.keyframes[topomap.frame_node[frame]])] == best
        else:
            key = int(topomap.keyframes[topomap.frame_node[frame]])
            assert abs(key - frame) == min(abs(k - frame) for k in node_of_key if abs(k - frame) <= radius)
        moved += topomap.frame_node[frame] != plain.frame_node[frame]
    assert moved > 0


def test_batch_strengths_must_match_the_pairs():
    with pytest.raises(ValueError, match="one strength per loop pair"):
        build_topological_map(12, STARS, 0, strengths=[1.0, 2.0])


def incremental_stars(strengths=None) -> IncrementalTopoMap:
    topomap = IncrementalTopoMap(0)
    for _ in range(10):
        topomap.add_frame([])  # r = 0: every frame is its own key-frame
    topomap.add_frame([2, 6], strengths)
    return topomap


def test_incremental_map_joins_the_strongest_loop():
    assert incremental_stars().node_of(10) == incremental_stars().node_of(2)  # equal: the older node
    assert incremental_stars([3.0, 9.0]).node_of(10) == 6
    assert incremental_stars([9.0, 3.0]).node_of(10) == 2
    topomap = incremental_stars([3.0, 9.0])
    assert topomap.strength(6, 10) == 9.0 and topomap.strength(10, 2) == 3.0
    with pytest.raises(KeyError):
        topomap.strength(5, 10)


def test_revisions_keep_strengths_and_move_a_frame_that_lost_its_link():
    topomap = incremental_stars([3.0, 9.0])
    # The link to 6 is revised away: frame 10 moves to the node it still has a loop with.
    update = topomap.revise(10, [2], [4.0])
    assert topomap.node_of(10) == 2 and (10, 2) in update.assigned
    assert topomap.strength(2, 10) == 4.0
    # An added, stronger link does not move an assigned frame (stability over compactness) but is recorded.
    update = topomap.revise(10, [2, 6], [4.0, 20.0])
    assert topomap.node_of(10) == 2 and not update.assigned
    assert topomap.strength(6, 10) == 20.0
    # The strengths live in the state: a restored map chooses as the original does.
    restored = IncrementalTopoMap.from_state(topomap.state(), 0)
    assert restored.strength(6, 10) == 20.0 and restored.strength(2, 10) == 4.0
    for partners, strengths in (([2, 6], [1.0, 5.0]), ([6, 2], [1.0, 5.0])):
        assert topomap.add_frame(partners, strengths) == restored.add_frame(partners, strengths)


def test_bad_strengths_raise():
    topomap = IncrementalTopoMap(0)
    for _ in range(3):
        topomap.add_frame([])
    with pytest.raises(ValueError, match="one strength per loop partner"):
        topomap.add_frame([0, 1], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        topomap.add_frame([0], [np.nan])


def test_strengths_keep_the_nodes_of_the_simulated_route_at_one_place(sim_scenario):
    """The route's ground truth (600 frames: a loop, the same loop again, the loop reversed, crossings). Loops are
    drawn from the true geometry as D draws them: every pair of frames up to ~3.5 m apart looking the same way,
    surer the closer the two frames (belief 12 at 3 m, +8 per metre closer, noise 1.5). A node's members are then
    each near the key-frame but can be far apart; joining the strongest loop keeps >= 95 % of the frame pairs that
    share a node within the 2.5 m ground-truth distance in the incremental map, and helps the batch map too."""
    scenario = sim_scenario("route", frames=600, seed=0)
    T = scenario.T_world_body
    xy, heading = T[:, :2, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])
    n = len(xy)
    distance = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    turn = np.abs(np.angle(np.exp(1j * (heading[:, None] - heading[None, :]))))
    belief = 12.0 + 8.0 * (3.0 - distance) + np.random.default_rng(0).normal(0.0, 1.5, distance.shape)
    pairs = np.argwhere(np.triu((belief >= 12.0) & (turn < np.radians(45)), 31))
    strengths = belief[pairs[:, 0], pairs[:, 1]]
    assert distance[pairs[:, 0], pairs[:, 1]].max() > 3.0  # links longer than the ground truth's threshold
    same_place = distance < 2.5

    def fraction(topomap: TopologicalMap) -> float:
        node = topomap.frame_node
        assert np.all(node >= 0)  # every frame in exactly one node
        shared = np.triu(node[:, None] == node[None, :], 1)
        return float(np.sum(shared & same_place) / np.sum(shared))

    def incremental(use_strengths: bool) -> TopologicalMap:
        topomap = IncrementalTopoMap(2)
        for j in range(n):
            rows = pairs[pairs[:, 1] == j, 0]
            topomap.add_frame(rows, belief[rows, j] if use_strengths else None)
        topomap.flush()
        return topomap.snapshot()

    strong, plain = incremental(True), incremental(False)
    assert fraction(strong) >= 0.95 and fraction(strong) > fraction(plain) + 0.03
    assert strong.n_nodes <= 0.3 * n
    batch_strong = build_topological_map(n, pairs, 2, strengths=strengths)
    batch_plain = build_topological_map(n, pairs, 2)
    assert fraction(batch_strong) > fraction(batch_plain) + 0.03


def test_a_visit_joins_the_place_holding_its_view_and_stays():
    """A frame the engine does not keep (its view is held by an earlier frame) is a visit of that frame's place: it
    joins that node whatever its loops, is never a key-frame and keeps no loops (revising them changes nothing);
    the pass counts in the node's transitions; the state round-trips."""
    topomap = IncrementalTopoMap(2)
    for _ in range(50):
        topomap.add_frame([])
    nodes = topomap.n_nodes
    for frame in range(50, 100):
        centre = frame - 50  # the second pass shows frames 0..49 again; none is kept
        partners = [f for f in (centre - 1, centre, centre + 1) if 0 <= f < 50]
        update = topomap.add_visit(centre, partners, np.full(len(partners), 20.0))
        assert topomap.is_visit(frame) and update.assigned[-1] == (frame, topomap.node_of(centre))
        assert not update.new_nodes and topomap.loops_of(frame) == set()
    assert topomap.n_nodes == nodes
    snapshot = topomap.snapshot()
    assert np.array_equal(snapshot.frame_node[50:], snapshot.frame_node[:50])
    assert snapshot.transitions.sum() == 2 * (nodes - 1) + 1  # each pass crosses the same edges; one edge back
    assert topomap.revise(70, [5]) == TopoMapUpdate()
    restored = IncrementalTopoMap.from_state(topomap.state(), 2)
    assert restored.is_visit(75) and not restored.is_visit(25)
    for topo in (topomap, restored):
        topo.add_visit(10)
        topo.add_frame([11])
    assert np.array_equal(topomap.snapshot().frame_node, restored.snapshot().frame_node)
    with pytest.raises(ValueError, match="earlier frame"):
        topomap.add_visit(topomap.n_frames)
