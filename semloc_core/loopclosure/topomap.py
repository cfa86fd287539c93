"""The topological map T = (N, E_T) built from the loop-closure decisions D (thesis §3.5).

D' = D v D^T is the graph of "same place" relations between frames. A dominating set K of D' gives the map's nodes:
each key-frame k represents the set N_k = {k} u Nb(k) of frames it dominates; nodes k and l are joined when N_k and
N_l hold two consecutive frames (the temporal assumption).

``temporal_radius`` r adds the temporal assumption to D' explicitly: frames at most r apart are the same place.
The thesis computes M and D only outside the window w, so in D' alone a stretch of route seen once is a chain of
isolated frames, each its own node; r groups such frames into nodes of up to 2r + 1 consecutive frames. r = 0 is
the thesis's D' exactly.

* :func:`dominating_set` / :func:`build_topological_map` - the batch algorithm 3.1 (greedy approximate minimum
  dominating set: repeatedly take the frame of largest degree in what is left of D', remove it and its neighbours).

Which node a frame joins when several key-frames dominate it matters for spatial distinctiveness (§3.1: frames of
different places *must not* share a node). D marks a revisit frame as a loop with a whole band of earlier frames
(the MRF smooths along the band, and views overlap for metres), so the key-frames it is linked to can lie several
metres apart; a node's members are each next to the key-frame but can be twice that far from each other. Given
the links' strengths (the max-marginal log-odds of D), a frame joins the key-frame it is most surely the same place
as - the peak of its band - rather than the first one found; on `route` this is what keeps the members of a node
at one place (docs/loopclosure.md).
* :class:`IncrementalTopoMap` - the map maintained as frames and revised decisions arrive, with stable node ids.
"""

from __future__ import annotations

from array import array
from collections import Counter
from dataclasses import dataclass, field
from xml.sax.saxutils import quoteattr

import numpy as np

TOPOMAP_FORMAT = "semloc.topomap"
TOPOMAP_VERSION = 1


def _check_pairs(n: int, pairs) -> np.ndarray:
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n):
        raise ValueError(f"loop pairs must index frames 0..{n - 1}")
    return pairs


def adjacency(n: int, loop_pairs, temporal_radius: int = 0) -> list[set[int]]:
    """Neighbour sets of D' (loops made undirected, self-loops dropped) plus links between frames <= r apart."""
    if temporal_radius < 0:
        raise ValueError("temporal_radius must be >= 0")
    neighbours: list[set[int]] = [set() for _ in range(n)]
    for a, b in _check_pairs(n, loop_pairs).tolist():
        if a != b:
            neighbours[a].add(b)
            neighbours[b].add(a)
    for offset in range(1, temporal_radius + 1):
        for a in range(n - offset):
            neighbours[a].add(a + offset)
            neighbours[a + offset].add(a)
    return neighbours


def dominating_set(neighbours: list[set[int]]) -> tuple[list[int], list[list[int]]]:
    """Algorithm 3.1: greedy approximate minimum dominating set; returns key-frames K and the sets N_k.

    Degrees are counted in what remains of the graph; ties go to the earliest frame.
    """
    n = len(neighbours)
    remaining = np.ones(n, bool)
    degree = np.array([len(s) for s in neighbours], np.int64)
    keyframes: list[int] = []
    members: list[list[int]] = []
    left = n
    while left:
        k = int(np.argmax(np.where(remaining, degree, -1)))
        group = sorted({k} | {v for v in neighbours[k] if remaining[v]})
        for u in group:
            remaining[u] = False
        for u in group:
            for v in neighbours[u]:
                if remaining[v]:
                    degree[v] -= 1
        left -= len(group)
        keyframes.append(k)
        members.append(group)
    return keyframes, members


@dataclass(frozen=True, eq=False)
class TopologicalMap:
    """Nodes (stable ids, one key-frame each), the node of every frame, and the edges E_T.

    ``edges`` (E, 2) node-id pairs (smaller id first) with ``transitions`` (E,): how many consecutive-frame pairs
    cross each edge.
    """

    node_ids: np.ndarray
    keyframes: np.ndarray
    frame_node: np.ndarray
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    transitions: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        node_ids = np.asarray(self.node_ids, np.int64).reshape(-1)
        keyframes = np.asarray(self.keyframes, np.int64).reshape(-1)
        frame_node = np.asarray(self.frame_node, np.int64).reshape(-1)
        edges = np.asarray(self.edges, np.int64).reshape(-1, 2)
        transitions = np.asarray(self.transitions, np.int64).reshape(-1)
        if keyframes.shape != node_ids.shape or transitions.shape != (edges.shape[0],):
            raise ValueError("one key-frame per node and one transition count per edge")
        if np.unique(node_ids).size != node_ids.size:
            raise ValueError("node ids must be unique")
        known = set(node_ids.tolist()) | {-1}
        if not set(np.unique(frame_node).tolist()) <= known or not set(np.unique(edges).tolist()) <= known - {-1}:
            raise ValueError("frames and edges must refer to existing nodes")
        for name, value in (("node_ids", node_ids), ("keyframes", keyframes), ("frame_node", frame_node),
                            ("edges", edges), ("transitions", transitions)):
            object.__setattr__(self, name, value)

    @property
    def n_nodes(self) -> int:
        return int(self.node_ids.size)

    def members(self, node_id: int) -> np.ndarray:
        return np.flatnonzero(self.frame_node == node_id)

    def to_json_dict(self, positions=None, stamps_ns=None) -> dict:
        """The ``semloc.topomap`` document; optional per node: ``positions`` (n, 3) planar pose (x, y, theta) of its
        key-frame (NaN rows: unknown, written as null) and ``stamps_ns`` (n,) the key-frame's capture stamp."""
        positions, stamps_ns = self._node_extras(positions, stamps_ns)
        nodes = []
        for index, (node, key) in enumerate(zip(self.node_ids.tolist(), self.keyframes.tolist())):
            entry = {"id": int(node), "keyframe": int(key), "frames": self.members(int(node)).tolist()}
            if stamps_ns is not None:
                entry["stamp_ns"] = int(stamps_ns[index])
            if positions is not None:
                entry["pose"] = positions[index].tolist() if np.all(np.isfinite(positions[index])) else None
            nodes.append(entry)
        return {
            "format": TOPOMAP_FORMAT,
            "version": TOPOMAP_VERSION,
            "frames": int(self.frame_node.size),
            "nodes": nodes,
            "edges": [
                {"source": int(a), "target": int(b), "transitions": int(t)}
                for (a, b), t in zip(self.edges.tolist(), self.transitions.tolist())
            ],
        }

    def _node_extras(self, positions, stamps_ns):
        if positions is not None:
            positions = np.asarray(positions, float)
            if positions.shape != (self.n_nodes, 3):
                raise ValueError(f"positions must be ({self.n_nodes}, 3) planar poses, got {positions.shape}")
        if stamps_ns is not None:
            stamps_ns = np.asarray(stamps_ns, np.int64)
            if stamps_ns.shape != (self.n_nodes,):
                raise ValueError(f"stamps_ns must hold one stamp per node ({self.n_nodes}), got {stamps_ns.shape}")
        return positions, stamps_ns

    @classmethod
    def from_json_dict(cls, data: dict) -> "TopologicalMap":
        if data.get("format") != TOPOMAP_FORMAT or data.get("version") != TOPOMAP_VERSION:
            raise ValueError(f"not a {TOPOMAP_FORMAT} v{TOPOMAP_VERSION} document")
        frames = int(data["frames"])
        frame_node = np.full(frames, -1, np.int64)
        node_ids, keyframes = [], []
        for node in data["nodes"]:
            node_ids.append(int(node["id"]))
            keyframes.append(int(node["keyframe"]))
            members = np.asarray(node["frames"], np.int64)
            if members.size and (members.min() < 0 or members.max() >= frames):
                raise ValueError("node frames out of range")
            frame_node[members] = int(node["id"])
        edges = [(int(e["source"]), int(e["target"])) for e in data["edges"]]
        transitions = [int(e["transitions"]) for e in data["edges"]]
        return cls(np.array(node_ids, np.int64), np.array(keyframes, np.int64), frame_node,
                   np.array(edges, np.int64).reshape(-1, 2), np.array(transitions, np.int64))

    def to_graphml(self, positions=None, stamps_ns=None) -> str:
        """GraphML (yEd, Gephi, networkx.read_graphml): node attributes keyframe, size, frames, and with
        ``positions`` / ``stamps_ns`` (as in :meth:`to_json_dict`) x, y, theta (nodes of unknown pose lack them)
        and stamp_ns; edge transitions."""
        positions, stamps_ns = self._node_extras(positions, stamps_ns)
        lines = [
            '<?xml version="1.0" encoding="UTF-8"?>',
            '<graphml xmlns="http://graphml.graphdrawing.org/xmlns">',
            '  <key id="keyframe" for="node" attr.name="keyframe" attr.type="int"/>',
            '  <key id="size" for="node" attr.name="size" attr.type="int"/>',
            '  <key id="frames" for="node" attr.name="frames" attr.type="string"/>',
        ]
        if positions is not None:
            lines += [f'  <key id="{name}" for="node" attr.name="{name}" attr.type="double"/>'
                      for name in ("x", "y", "theta")]
        if stamps_ns is not None:
            lines.append('  <key id="stamp_ns" for="node" attr.name="stamp_ns" attr.type="long"/>')
        lines += [
            '  <key id="transitions" for="edge" attr.name="transitions" attr.type="int"/>',
            '  <graph id="topomap" edgedefault="undirected">',
        ]
        for index, (node, key) in enumerate(zip(self.node_ids.tolist(), self.keyframes.tolist())):
            members = self.members(node)
            lines += [
                f"    <node id={quoteattr(f'n{node}')}>",
                f'      <data key="keyframe">{key}</data>',
                f'      <data key="size">{members.size}</data>',
                f'      <data key="frames">{" ".join(map(str, members.tolist()))}</data>',
            ]
            if positions is not None and np.all(np.isfinite(positions[index])):
                lines += [f'      <data key="{name}">{value!r}</data>'
                          for name, value in zip(("x", "y", "theta"), positions[index].tolist())]
            if stamps_ns is not None:
                lines.append(f'      <data key="stamp_ns">{int(stamps_ns[index])}</data>')
            lines.append("    </node>")
        for index, ((a, b), t) in enumerate(zip(self.edges.tolist(), self.transitions.tolist())):
            lines += [
                f"    <edge id=\"e{index}\" source={quoteattr(f'n{a}')} target={quoteattr(f'n{b}')}>",
                f'      <data key="transitions">{t}</data>',
                "    </edge>",
            ]
        lines += ["  </graph>", "</graphml>", ""]
        return "\n".join(lines)


def _strength_table(pairs: np.ndarray, strengths: np.ndarray) -> dict[tuple[int, int], float]:
    table: dict[tuple[int, int], float] = {}
    for (a, b), value in zip(pairs.tolist(), strengths.tolist()):
        if a != b:
            key = (min(a, b), max(a, b))
            table[key] = max(value, table.get(key, -np.inf))
    return table


def edges_from_frames(frame_node: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = frame_node[:-1], frame_node[1:]
    keep = (a != b) & (a >= 0) & (b >= 0)
    pairs = np.sort(np.stack([a[keep], b[keep]], axis=1), axis=1)
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    unique, counts = np.unique(pairs, axis=0, return_counts=True)
    return unique, counts


def build_topological_map(n: int, loop_pairs, temporal_radius: int = 0, strengths=None) -> TopologicalMap:
    """Batch map (§3.5): D' from the loop pairs (+ temporal links), algorithm 3.1, edges between consecutive frames.

    Node ids are 0..K-1 in the order algorithm 3.1 picks the key-frames. Without ``strengths`` a frame belongs to
    the first key-frame that dominates it (algorithm 3.1's N_k); with them (one per loop pair, e.g. the belief), to
    the key-frame it has the strongest loop with, else the nearest key-frame in time (the same key-frames K).
    """
    neighbours = adjacency(n, loop_pairs, temporal_radius)
    keyframes, members = dominating_set(neighbours)
    frame_node = np.full(n, -1, np.int64)
    for node, group in enumerate(members):
        frame_node[group] = node
    if strengths is not None:
        pairs = _check_pairs(n, loop_pairs)
        strengths = np.asarray(strengths, np.float64).reshape(-1)
        if strengths.shape != (pairs.shape[0],):
            raise ValueError("one strength per loop pair")
        strength = _strength_table(pairs, strengths)
        key_node = {k: node for node, k in enumerate(keyframes)}
        for frame in range(n):
            if frame in key_node:
                continue
            linked = [k for k in neighbours[frame] if k in key_node and (min(k, frame), max(k, frame)) in strength]
            if linked:
                best = max(linked, key=lambda k: (strength[(min(k, frame), max(k, frame))], -key_node[k]))
            else:
                best = min((k for k in neighbours[frame] if k in key_node), key=lambda k: (abs(k - frame), -k))
            frame_node[frame] = key_node[best]
    edges, transitions = edges_from_frames(frame_node)
    return TopologicalMap(np.arange(len(keyframes)), np.array(keyframes, np.int64), frame_node, edges, transitions)


def map_from_beliefs(beliefs, min_belief: float | None = None, temporal_radius: int = 0) -> TopologicalMap:
    """The batch map from an (n, n) matrix of max-marginal log-odds (earlier frame as row): D' holds the loops of
    D (belief > 0; ``min_belief`` None) or those at least ``min_belief`` sure, and each frame joins the key-frame
    of its strongest loop - the engine's rule."""
    beliefs = np.asarray(beliefs, dtype=np.float64)
    if beliefs.ndim != 2 or beliefs.shape[0] != beliefs.shape[1]:
        raise ValueError(f"beliefs must be a square matrix, got shape {beliefs.shape}")
    earlier, later = np.nonzero(beliefs > 0 if min_belief is None else beliefs >= min_belief)
    return build_topological_map(beliefs.shape[0], np.stack([earlier, later], axis=1), temporal_radius,
                                 strengths=beliefs[earlier, later])


@dataclass
class TopoMapUpdate:
    """What one call changed: frames (re)assigned to nodes, new nodes, edges added and removed."""

    assigned: list[tuple[int, int]] = field(default_factory=list)
    new_nodes: list[tuple[int, int]] = field(default_factory=list)
    edges_added: list[tuple[int, int]] = field(default_factory=list)
    edges_removed: list[tuple[int, int]] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.assigned or self.new_nodes or self.edges_added or self.edges_removed)

    def then(self, later: "TopoMapUpdate") -> "TopoMapUpdate":
        """The net change of this update followed by ``later``: a frame's last assignment, the new nodes of both, and
        the edges' net change (an edge added then removed, or removed then added, is no change)."""
        assigned = dict(self.assigned)
        assigned.update(later.assigned)
        added, removed = dict.fromkeys(self.edges_added), dict.fromkeys(self.edges_removed)
        for edge in later.edges_removed:
            if edge in added:
                del added[edge]
            else:
                removed[edge] = None
        for edge in later.edges_added:
            if edge in removed:
                del removed[edge]
            else:
                added[edge] = None
        return TopoMapUpdate(list(assigned.items()), self.new_nodes + later.new_nodes, list(added), list(removed))


class IncrementalTopoMap:
    """The topological map kept up to date frame by frame, with stable node ids.

    Invariants after every call: every frame except at most the last r (still pending) belongs to exactly one node;
    every member of a node is its key-frame or adjacent to it in D' (so K stays a dominating set); node ids are
    never reused or renumbered. Rules:

    * A frame joins a node whose key-frame it is adjacent to, preferring loop-closure links (a revisit is mapped
      onto the place it revisits: the key-frame with the strongest link, see the module docstring) over temporal
      links (the most recent key-frame).
    * A frame with no adjacent key-frame waits (at most r frames); when the oldest waiting frame would fall out of
      the temporal radius, the latest waiting frame becomes a key-frame and takes every waiting frame, so on a
      route seen once key-frames are 2r + 1 frames apart, as algorithm 3.1 would place them.
    * When revised decisions remove the link a member relied on, the member moves to another adjacent key-frame or
      becomes a key-frame itself; added links never move an assigned frame (stability over compactness).
    * A visit (:meth:`add_visit`: a frame whose view an earlier frame already holds, which the engine does not
      keep) joins that frame's node and stays there: it is never a key-frame, keeps no loops and is not a member
      the repairs move (the exception to the second invariant). It counts in the node's transitions as any frame.
    """

    def __init__(self, temporal_radius: int = 2) -> None:
        if temporal_radius < 0:
            raise ValueError("temporal_radius must be >= 0")
        self.temporal_radius = int(temporal_radius)
        # Loops of D', kept compact (a long run revisiting its places holds hundreds of thousands): each frame's
        # earlier partners (ascending) with the loops' strengths, and its later partners; () until it has any.
        self._earlier: list = []
        self._earlier_strength: list = []
        self._later: list = []
        self._node_of: list[int] = []
        self._visit = bytearray()  # 1: the frame is a visit
        self._keyframes: list[int] = []
        self._members: list[set[int]] = []  # frames each node's repairs may move: all but the visits
        self._pending: list[int] = []
        self._edges: Counter = Counter()
        self._update = TopoMapUpdate()

    # --- queries --------------------------------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        return len(self._node_of)

    @property
    def n_nodes(self) -> int:
        return len(self._keyframes)

    def node_of(self, frame: int) -> int:
        return self._node_of[frame]

    def loops_of(self, frame: int) -> set[int]:
        return set(self._earlier[frame]) | set(self._later[frame])

    def snapshot(self) -> TopologicalMap:
        edges = sorted(self._edges.items())
        return TopologicalMap(
            np.arange(self.n_nodes, dtype=np.int64),
            np.array(self._keyframes, np.int64),
            np.array(self._node_of, np.int64),
            np.array([e for e, _ in edges], np.int64).reshape(-1, 2),
            np.array([c for _, c in edges], np.int64),
        )

    # --- updates --------------------------------------------------------------------------------------------

    def add_frame(self, loop_partners=(), strengths=None) -> TopoMapUpdate:
        """Append the next frame with the earlier frames it closes a loop with (its column of D) and, optionally,
        how sure each loop is (e.g. its max-marginal log-odds; default: all equal)."""
        frame = self.n_frames
        partners = self._check_partners(frame, loop_partners, strengths)
        self._update = TopoMapUpdate()
        self._append_frame()
        self._set_earlier(frame, partners)
        for p in partners:
            self._add_later(p, frame)
        if not self._resolve(frame):
            self._pending.append(frame)
        self._promote_pending(frame)
        return self._take_update()

    def add_visit(self, place: int, loop_partners=(), strengths=None) -> TopoMapUpdate:
        """Append the next frame as a visit of earlier frame ``place``, which holds its view: it joins place's node
        for good, keeping none of its loops. While ``place`` waits for a key-frame (only with a window shorter than
        the temporal radius), the frame is added as any other, with its loops."""
        frame = self.n_frames
        if not 0 <= place < frame:
            raise ValueError(f"the place of visit {frame} must be an earlier frame, got {place}")
        node = self._node_of[place]
        if node < 0:
            return self.add_frame(loop_partners, strengths)
        self._update = TopoMapUpdate()
        self._append_frame()
        self._visit[frame] = 1
        self._assign(frame, node)
        self._promote_pending(frame)
        return self._take_update()

    def is_visit(self, frame: int) -> bool:
        return bool(self._visit[frame])

    def _append_frame(self) -> None:
        self._earlier.append(())
        self._earlier_strength.append(())
        self._later.append(())
        self._node_of.append(-1)
        self._visit.append(0)

    def revise(self, frame: int, loop_partners, strengths=None) -> TopoMapUpdate:
        """Replace the earlier loop partners of ``frame`` (a revised column of D) and repair the map (a visit
        keeps no loops: nothing changes)."""
        if not 0 <= frame < self.n_frames:
            raise IndexError(f"frame {frame} out of range")
        if self._visit[frame]:
            return TopoMapUpdate()
        strength_of = self._check_partners(frame, loop_partners, strengths)
        partners = set(strength_of)
        self._update = TopoMapUpdate()
        old = set(self._earlier[frame])
        removed, added = old - partners, partners - old
        for p in removed:
            later = self._later[p]
            del later[later.index(frame)]
        for p in sorted(added):
            self._add_later(p, frame)
        self._set_earlier(frame, strength_of)
        touched = sorted({frame} | removed | added)
        for f in touched:
            self._repair(f)
        for f in sorted(self._pending):
            if self._node_of[f] < 0 and self._resolve(f):
                self._pending.remove(f)
        return self._take_update()

    def _check_partners(self, frame: int, partners, strengths=None) -> dict[int, float]:
        """{earlier frame: strength}, sorted by frame."""
        partners = np.asarray(partners, dtype=np.int64).reshape(-1)
        values = (np.zeros(partners.size) if strengths is None
                  else np.asarray(strengths, dtype=np.float64).reshape(-1))
        if values.shape != partners.shape:
            raise ValueError(f"frame {frame}: one strength per loop partner")
        if np.any(np.isnan(values)):
            raise ValueError(f"frame {frame}: loop strengths contain NaN")
        if partners.size and (partners.min() < 0 or partners.max() >= frame):
            raise ValueError(f"loop partners of frame {frame} must be earlier frames")
        out: dict[int, float] = {}
        for p, value in sorted(zip(partners.tolist(), values.tolist())):
            out[p] = max(value, out.get(p, -np.inf))
        return out

    def _set_earlier(self, frame: int, strength_of: dict[int, float]) -> None:
        """Frame's earlier partners and their strengths (``strength_of`` sorted by partner)."""
        if strength_of:
            self._earlier[frame] = array("i", strength_of)
            self._earlier_strength[frame] = array("d", strength_of.values())
        else:
            self._earlier[frame] = self._earlier_strength[frame] = ()

    def _add_later(self, frame: int, partner: int) -> None:
        later = self._later[frame]
        if not later:
            self._later[frame] = later = array("i")
        later.append(partner)

    def strength(self, a: int, b: int) -> float:
        """How sure the loop between frames a and b is (KeyError when there is none)."""
        earlier, later = min(a, b), max(a, b)
        try:
            return self._earlier_strength[later][self._earlier[later].index(earlier)]
        except ValueError:
            raise KeyError((earlier, later)) from None

    def _adjacent(self, a: int, b: int) -> bool:
        return abs(a - b) <= self.temporal_radius or b in (self._later[a] if b > a else self._earlier[a])

    def _resolve(self, frame: int) -> bool:
        """Join the best adjacent key-frame's node; False when there is none."""
        keys = [g for partners in (self._earlier[frame], self._later[frame]) for g in partners if self._is_key(g)]
        if keys:
            # The strongest loop (ties: the oldest node) - see the module docstring.
            best = max(keys, key=lambda g: (self.strength(g, frame), -self._node_of[g]))
            self._assign(frame, self._node_of[best])
            return True
        r = self.temporal_radius
        for g in range(min(self.n_frames - 1, frame + r), max(-1, frame - r - 1), -1):
            if g != frame and self._is_key(g):
                self._assign(frame, self._node_of[g])
                return True
        return False

    def _is_key(self, frame: int) -> bool:
        node = self._node_of[frame]
        return node >= 0 and self._keyframes[node] == frame

    def flush(self) -> TopoMapUpdate:
        """The sequence has ended: the frames still waiting for a key-frame get one now (the latest of them), so
        every frame belongs to exactly one node. Frames added later are handled as usual."""
        self._update = TopoMapUpdate()
        self._promote_pending(self.n_frames - 1, force=True)
        return self._take_update()

    def _promote_pending(self, newest: int, force: bool = False) -> None:
        """When the oldest waiting frame could no longer be dominated by a future frame, make the latest waiting
        frame a key-frame: it is within r of every waiting frame (they span at most r frames), and frames that
        already joined a node keep it."""
        if self._pending and (force or newest - self._pending[0] >= self.temporal_radius):
            key = self._pending[-1]
            self._make_key(key)
            for f in self._pending[:-1]:
                self._assign(f, self._node_of[key])
            self._pending.clear()

    def _make_key(self, frame: int) -> None:
        if self._node_of[frame] >= 0:
            self._unassign(frame)
        node = len(self._keyframes)
        self._keyframes.append(frame)
        self._members.append(set())
        self._update.new_nodes.append((node, frame))
        self._assign(frame, node)

    def _repair(self, frame: int) -> None:
        node = self._node_of[frame]
        if node < 0 or self._visit[frame]:
            return
        if self._is_key(frame):
            for member in sorted(self._members[node]):
                if member != frame and not self._adjacent(member, frame):
                    self._reassign(member)
        elif not self._adjacent(frame, self._keyframes[node]):
            self._reassign(frame)

    def _reassign(self, frame: int) -> None:
        self._unassign(frame)
        if self._resolve(frame):
            return
        if self.n_frames - 1 - frame < self.temporal_radius:
            self._pending.append(frame)
            self._pending.sort()
        else:
            self._make_key(frame)

    def _assign(self, frame: int, node: int) -> None:
        self._node_of[frame] = node
        if not self._visit[frame]:
            self._members[node].add(frame)
        self._update.assigned.append((frame, node))
        self._edge_change(frame, +1)

    def _unassign(self, frame: int) -> None:
        self._edge_change(frame, -1)
        self._members[self._node_of[frame]].discard(frame)
        self._node_of[frame] = -1

    def _edge_change(self, frame: int, sign: int) -> None:
        node = self._node_of[frame]
        for other in (frame - 1, frame + 1):
            if 0 <= other < self.n_frames:
                o = self._node_of[other]
                if o >= 0 and o != node:
                    key = (min(o, node), max(o, node))
                    before = self._edges[key]
                    self._edges[key] = before + sign
                    if self._edges[key] <= 0:
                        del self._edges[key]
                        self._update.edges_removed.append(key)
                    elif before == 0:
                        self._update.edges_added.append(key)

    def _take_update(self) -> TopoMapUpdate:
        update = self._update
        # Report each frame's final node and net edge changes only.
        final = {}
        for frame, _ in update.assigned:
            final[frame] = self._node_of[frame]
        added = [e for e in dict.fromkeys(update.edges_added) if e in self._edges]
        removed = [e for e in dict.fromkeys(update.edges_removed) if e not in self._edges]
        self._update = TopoMapUpdate()
        return TopoMapUpdate(sorted(final.items()), update.new_nodes, added, removed)

    # --- state ----------------------------------------------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        earlier = [np.frombuffer(e, np.int32) for e in self._earlier if e]
        strengths = [np.frombuffer(v, np.float64) for v in self._earlier_strength if v]
        return {
            "node_of": np.array(self._node_of, np.int64),
            "keyframes": np.array(self._keyframes, np.int64),
            # each frame's earlier loop partners (ascending), frame after frame, and how many each frame has
            "loop_counts": np.array([len(e) for e in self._earlier], np.int32),
            "loop_partners": np.concatenate(earlier) if earlier else np.zeros(0, np.int32),
            "loop_strengths": np.concatenate(strengths) if strengths else np.zeros(0, np.float64),
            "pending": np.array(self._pending, np.int64),
            "visits": np.packbits(np.frombuffer(self._visit, np.uint8)),
        }

    @classmethod
    def from_state(cls, state: dict, temporal_radius: int) -> "IncrementalTopoMap":
        topo = cls(temporal_radius)
        node_of = np.asarray(state["node_of"], np.int64).reshape(-1)
        keyframes = np.asarray(state["keyframes"], np.int64).reshape(-1)
        n = node_of.size
        counts = np.asarray(state["loop_counts"], np.int64).reshape(-1)
        partners = np.asarray(state["loop_partners"], np.int64).reshape(-1)
        if counts.shape != (n,) or np.any(counts < 0) or counts.sum() != partners.size:
            raise ValueError("topological map state: one count of loop partners per frame")
        later_frames = np.repeat(np.arange(n, dtype=np.int64), counts)
        if partners.size and (partners.min() < 0 or np.any(partners >= later_frames)
                              or np.any(np.diff(later_frames * (n + 1) + partners) <= 0)):
            raise ValueError("topological map state: each frame's loop partners must be earlier frames, ascending")
        if node_of.size and (node_of.max() >= keyframes.size or node_of.min() < -1):
            raise ValueError("topological map state: frame refers to a missing node")
        if keyframes.size and (keyframes.min() < 0 or keyframes.max() >= n or np.any(node_of[keyframes] != np.arange(keyframes.size))):
            raise ValueError("topological map state: inconsistent key-frames")
        strengths = np.asarray(state["loop_strengths"], np.float64).reshape(-1)
        if strengths.shape != partners.shape or np.any(np.isnan(strengths)):
            raise ValueError("topological map state: one strength per loop pair")
        topo._earlier, topo._earlier_strength, topo._later = [()] * n, [()] * n, [()] * n
        ends = np.cumsum(counts)
        partner_list, strength_list = partners.tolist(), strengths.tolist()
        for frame, start, end in zip(np.flatnonzero(counts).tolist(), (ends - counts)[counts > 0].tolist(),
                                     ends[counts > 0].tolist()):
            topo._earlier[frame] = array("i", partner_list[start:end])
            topo._earlier_strength[frame] = array("d", strength_list[start:end])
        order = np.argsort(partners, kind="stable")  # by partner, each partner's later frames ascending
        by_partner, later = partners[order], later_frames[order].tolist()
        first = np.flatnonzero(np.r_[True, np.diff(by_partner) != 0]) if by_partner.size else np.zeros(0, np.int64)
        for start, end in zip(first.tolist(), np.r_[first[1:], by_partner.size].tolist()):
            topo._later[int(by_partner[start])] = array("i", later[start:end])
        visits = np.unpackbits(np.asarray(state["visits"], np.uint8), count=n)
        if visits.size != n or np.any(visits.astype(bool) & ((counts > 0) | (node_of < 0))) \
                or np.any(np.isin(keyframes, np.flatnonzero(visits))):
            raise ValueError("topological map state: a visit has a node, no loops and is no key-frame")
        topo._visit = bytearray(visits.tobytes())
        nodes = node_of.tolist()  # one int object per node id, as the map builds them
        ids = list(range(keyframes.size))
        topo._node_of = [ids[node] if node >= 0 else -1 for node in nodes]
        topo._keyframes = keyframes.tolist()
        topo._members = [set() for _ in range(keyframes.size)]
        for frame in np.flatnonzero((node_of >= 0) & (visits == 0)).tolist():
            topo._members[topo._node_of[frame]].add(frame)
        topo._pending = sorted(np.asarray(state["pending"], np.int64).reshape(-1).tolist())
        edges, counts = edges_from_frames(node_of)
        topo._edges = Counter({(int(a), int(b)): int(c) for (a, b), c in zip(edges.tolist(), counts.tolist())})
        return topo
