"""Loop-closure frames (thesis ch. 3): per-frame decisions, similarity rows, the topological map and its updates.

Frames are numbered by the loop-closure worker in the order it processed them (``frame``, from 0); ``stamp_ns``
arrays give the capture stamps of the frames referred to, so a peer can match them with its own data.

* ``LoopFeatures`` - one frame's bearing-sorted SIFT sequence (an optional input: a separate feature extractor).
* ``LoopClosure`` - the decision for one frame: status, the earlier frames it closes a loop with (D = 1) and their
  max-marginal log-odds, its node in the map, earlier frames whose decisions the banded inference revised, and
  the poses at which those earlier frames were seen while the localizer was localized (the hybrid map).
* ``SimilarityRow`` - the frame's row of M: the retrieved candidates, their retrieval (TF-IDF) scores and DP scores.
* ``TopoMapUpdate`` - what changed in the map: frames (re)assigned, new nodes, edges added and removed.
* ``TopoMap`` - the whole map (the reply to a map query): node ids, key-frames, every frame's node, edges.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from schemas.base import Array, Frame, FrameError, Sub
from schemas.camera import MAX_CAMERAS, MAX_SIDE
from schemas.limits import MAX_COORDINATE

MAX_REVISIONS = 10_000  # earlier frames whose loops one LoopClosure revises (more wait for the next)
MAX_FEATURES = 200_000
# L2 norms a descriptor on VLFeat's scale may have: the unit SIFT vector times 512, rounded and saturated at 255
# (OpenCV's and VLFeat's: 510-514 measured; saturation of a spiky one can lower it, never to half)
DESCRIPTOR_NORMS = (0.45 * 512, 1.05 * 512)
MAX_FRAMES = 10_000_000
MAX_CANDIDATES = 100_000
Status = Literal["loop_found", "too_few_frames", "no_candidate", "rejected"]
FrameIndex = Annotated[int, Field(ge=0, lt=MAX_FRAMES)]


def _same_length(model, *names: str) -> None:
    lengths = {name: len(getattr(model, name)) for name in names}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"arrays must have the same length, got {lengths}")


def _check_poses(poses: np.ndarray, what: str) -> None:
    """Planar poses (k, 3): each row finite, or NaN throughout (unknown), within the coordinate limit."""
    finite = np.isfinite(poses)
    if np.any(~finite & ~np.isnan(poses)) or np.any(finite.any(axis=1) & ~finite.all(axis=1)):
        raise FrameError(f"{what}: a pose is finite, or NaN throughout (unknown)", reason="nonfinite")
    known = poses[finite.all(axis=1)]
    if known.size and np.abs(known).max() > MAX_COORDINATE:
        raise FrameError(f"{what} beyond {MAX_COORDINATE} m", reason="range")


def _frames_in_range(values: np.ndarray, limit: int, what: str) -> None:
    if values.size and (values.min() < 0 or values.max() >= limit):
        raise ValueError(f"{what} must lie in [0, {limit})")


class LoopFeatures(Frame, schema="semloc.LoopFeatures", version=1, max_bytes=64 << 20):
    """Bearing-sorted SIFT features of one frame (bearings ascending in [-pi, pi), uint8 descriptors on VLFeat's
    scale: L2 norm ~512, within DESCRIPTOR_NORMS)."""

    bearings: Array("float64", ndim=1, finite=True, max_elements=MAX_FEATURES)
    descriptors: Array("uint8", shape=(None, 128), max_elements=128 * MAX_FEATURES,
                       description=f"each row's L2 norm in [{DESCRIPTOR_NORMS[0]:.0f}, {DESCRIPTOR_NORMS[1]:.0f}]")
    points: Array("float32", shape=(None, 2), finite=True, max_elements=2 * MAX_FEATURES,
                  bounds=(-1.0, float(MAX_SIDE))) | None = Field(
        None, description="each feature's pixel (u, v) in its camera's image: features at the same pixel in most "
                          "frames (a lens rim, the robot's body) are masked by the engine's calibration")
    camera_index: Array("int16", ndim=1, max_elements=MAX_FEATURES, bounds=(0, MAX_CAMERAS - 1)) | None = Field(
        None, description="the rig member each feature came from (default: all from camera 0)")

    @model_validator(mode="after")
    def _consistent(self):
        n = self.bearings.shape[0]
        if self.descriptors.shape[0] != n:
            raise ValueError(f"{self.descriptors.shape[0]} descriptors for {n} bearings")
        for name in ("points", "camera_index"):
            value = getattr(self, name)
            if value is not None and value.shape[0] != n:
                raise ValueError(f"{value.shape[0]} {name} for {n} bearings")
        b = self.bearings
        if b.size and (b.min() < -np.pi or b.max() >= np.pi):
            raise FrameError(f"bearings span [{b.min():.6g}, {b.max():.6g}], outside [-pi, pi)", reason="range")
        if np.any(np.diff(b) < 0):
            raise ValueError("bearings must be ascending")
        if self.descriptors.size:
            norms = np.sqrt(np.einsum("ij,ij->i", self.descriptors, self.descriptors, dtype=np.float64))
            low, high = float(norms.min()), float(norms.max())
            if low < DESCRIPTOR_NORMS[0] or high > DESCRIPTOR_NORMS[1]:
                raise FrameError(f"descriptor L2 norms span [{low:.1f}, {high:.1f}], not VLFeat's scale "
                                 f"[{DESCRIPTOR_NORMS[0]:.0f}, {DESCRIPTOR_NORMS[1]:.0f}]", reason="range")
        return self


class Revision(Sub):
    """An earlier frame whose loop partners changed when the banded inference ran again."""

    frame: FrameIndex
    loops: Array("int64", ndim=1, max_elements=MAX_CANDIDATES)


class LoopClosure(Frame, schema="semloc.LoopClosure", version=1, max_bytes=16 << 20):
    """The loop-closure decision for one frame (``header.stamp_ns`` = the frame's capture stamp)."""

    frame: FrameIndex
    status: Status
    loops: Array("int64", ndim=1, max_elements=MAX_CANDIDATES)
    loop_stamps_ns: Array("int64", ndim=1, max_elements=MAX_CANDIDATES, bounds=(0, 2 ** 63 - 1))
    beliefs: Array("float32", ndim=1, finite=True, max_elements=MAX_CANDIDATES)
    node: Annotated[int, Field(ge=-1, lt=MAX_FRAMES)]
    revised: list[Revision] = Field(default_factory=list, max_length=MAX_REVISIONS)
    expected_precision: Annotated[float, Field(ge=0, le=1)] | None = Field(
        None, description="precision the worker expects of its loops (None: it cannot tell a threshold yet)")
    decision_threshold: Annotated[float, Field(allow_inf_nan=False)] | None = Field(
        None, description="loops are pairs whose belief (max-marginal log-odds) is at least this")
    loop_poses: Array("float64", shape=(None, 3), max_elements=3 * MAX_CANDIDATES,
                      description="the pose (x, y, theta) at which each loop's earlier frame was seen while the "
                                  "localizer was localized; NaN rows: not recorded") | None = None

    @model_validator(mode="after")
    def _consistent(self):
        _same_length(self, "loops", "loop_stamps_ns", "beliefs")
        if self.loop_poses is not None:
            _same_length(self, "loops", "loop_poses")
            _check_poses(self.loop_poses, "loop poses")
        _frames_in_range(self.loops, self.frame, "loops (earlier frames)")
        if np.unique(self.loops).size != self.loops.size:
            raise ValueError("each earlier frame is a loop at most once")
        if (self.status == "loop_found") != (len(self.loops) > 0):
            raise ValueError("status 'loop_found' if and only if there are loops")
        for revision in self.revised:
            _frames_in_range(revision.loops, revision.frame, "revised loops")
        return self


class SimilarityRow(Frame, schema="semloc.SimilarityRow", version=1, max_bytes=16 << 20):
    """Frame ``frame``'s row of the similarity matrix M: DP scores against the candidates it was aligned with."""

    frame: FrameIndex
    candidates: Array("int64", ndim=1, max_elements=MAX_CANDIDATES)
    retrieval_scores: Array("float32", ndim=1, finite=True, max_elements=MAX_CANDIDATES)
    similarity: Array("float32", ndim=1, finite=True, max_elements=MAX_CANDIDATES)
    features: Annotated[int, Field(ge=0, le=MAX_FEATURES)] = 0

    @model_validator(mode="after")
    def _consistent(self):
        _same_length(self, "candidates", "retrieval_scores", "similarity")
        _frames_in_range(self.candidates, self.frame, "candidates (earlier frames)")
        return self


class TopoMapUpdate(Frame, schema="semloc.TopoMapUpdate", version=1, max_bytes=16 << 20):
    """Changes to the topological map after one frame (or after poses alone changed). ``assigned`` (k, 2): (frame,
    node) - node -1 = pending; ``new_nodes`` (k, 2): (node, key-frame); ``edges_added`` / ``edges_removed`` (k, 2):
    node pairs; ``posed_frames`` (k,) and ``frame_poses`` (k, 3): frames whose pose (x, y, theta, as the places keep
    the localizer's estimates) changed, NaN rows withdrawn - replayed in order they give every frame's pose."""

    frames: Annotated[int, Field(ge=0, le=MAX_FRAMES)]
    nodes: Annotated[int, Field(ge=0, le=MAX_FRAMES)]
    assigned: Array("int64", shape=(None, 2), max_elements=2 * MAX_CANDIDATES)
    new_nodes: Array("int64", shape=(None, 2), max_elements=2 * MAX_CANDIDATES)
    edges_added: Array("int64", shape=(None, 2), max_elements=2 * MAX_CANDIDATES)
    edges_removed: Array("int64", shape=(None, 2), max_elements=2 * MAX_CANDIDATES)
    posed_frames: Array("int64", ndim=1, max_elements=MAX_FRAMES) | None = None
    frame_poses: Array("float64", shape=(None, 3), max_elements=3 * MAX_FRAMES) | None = None

    @model_validator(mode="after")
    def _consistent(self):
        if (self.posed_frames is None) != (self.frame_poses is None):
            raise ValueError("posed_frames and frame_poses come together")
        if self.posed_frames is not None:
            _same_length(self, "posed_frames", "frame_poses")
            _frames_in_range(self.posed_frames, self.frames, "posed frames")
            _check_poses(self.frame_poses, "frame poses")
        _frames_in_range(self.assigned[:, 0], self.frames, "assigned frames")
        if self.assigned.size and (self.assigned[:, 1].min() < -1 or self.assigned[:, 1].max() >= self.nodes):
            raise ValueError(f"assigned nodes must lie in [-1, {self.nodes})")
        _frames_in_range(self.new_nodes[:, 0], self.nodes, "new node ids")
        _frames_in_range(self.new_nodes[:, 1], self.frames, "new key-frames")
        for name in ("edges_added", "edges_removed"):
            _frames_in_range(getattr(self, name), self.nodes, name)
        return self


class TopoMap(Frame, schema="semloc.TopoMap", version=1, max_bytes=128 << 20):
    """The whole topological map: node ``k`` has key-frame ``keyframes[k]``; ``frame_node[f]`` is frame f's node
    (-1 while pending); ``edges`` (E, 2) node pairs with ``transitions`` consecutive-frame crossings each."""

    keyframes: Array("int64", ndim=1, max_elements=MAX_FRAMES)
    keyframe_stamps_ns: Array("int64", ndim=1, max_elements=MAX_FRAMES)
    frame_node: Array("int64", ndim=1, max_elements=MAX_FRAMES)
    edges: Array("int64", shape=(None, 2), max_elements=2 * MAX_FRAMES)
    transitions: Array("int64", ndim=1, max_elements=MAX_FRAMES)
    keyframe_poses: Array("float64", shape=(None, 3), max_elements=3 * MAX_FRAMES,
                          description="each node's key-frame pose (x, y, theta), as the localizer estimated it; NaN "
                                      "rows: unknown") | None = None

    @model_validator(mode="after")
    def _consistent(self):
        _same_length(self, "keyframes", "keyframe_stamps_ns")
        if self.keyframe_poses is not None:
            _same_length(self, "keyframes", "keyframe_poses")
            _check_poses(self.keyframe_poses, "key-frame poses")
        if len(self.transitions) != len(self.edges):
            raise ValueError("one transition count per edge")
        nodes, frames = len(self.keyframes), len(self.frame_node)
        _frames_in_range(self.keyframes, frames, "key-frames")
        if self.frame_node.size and (self.frame_node.min() < -1 or self.frame_node.max() >= nodes):
            raise ValueError(f"frame_node must lie in [-1, {nodes})")
        _frames_in_range(self.edges, nodes, "edges")
        if nodes and np.any(self.frame_node[self.keyframes] != np.arange(nodes)):
            raise ValueError("every key-frame belongs to its own node")
        return self
