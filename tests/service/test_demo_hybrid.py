"""The demo's figures of the hybrid localization (issue 34): the localizer's state against the error, and the
places of the topological map with the poses recorded while localized, against the truth."""

from __future__ import annotations

import numpy as np

from schemas import Header
from schemas.loopclosure import TopoMap
from services.demo_collector import PoseRecord
from services.demo_report import localization_results, place_results


def test_state_detection_and_places_against_the_truth():
    truth = np.column_stack([np.linspace(0, 1, 40), np.zeros(40), np.zeros(40)])
    stamps = np.arange(40) * 100_000_000
    index = {int(s): i for i, s in enumerate(stamps)}
    offsets = np.r_[np.full(10, 2.0), np.full(30, 0.02)]  # 10 frames 2 m off, then on the truth
    states = ["lost"] * 9 + ["localized"] + ["uncertain"] * 3 + ["localized"] * 27
    poses = [PoseRecord(int(stamps[k]), 0.0, truth[k] + [offsets[k], 0, 0], "converged", 100, 1.0, None, states[k])
             for k in range(40)]
    detection = localization_results(poses, index, truth, stamps)["state_detection"]
    assert detection["far_frames"] == 10 and detection["flagged_when_far"] == 0.9
    assert detection["near_frames"] == 30 and detection["flagged_when_near"] == 0.1
    assert detection["states"] == {"localized": 28, "uncertain": 3, "lost": 9}
    old = [PoseRecord(p.stamp_ns, 0.0, p.pose, p.status, 100, 1.0) for p in poses]  # a localizer without a state
    assert "state_detection" not in localization_results(old, index, truth, stamps)

    keyframes = np.array([0, 20, 30])
    topomap = TopoMap(header=Header(robot="r"), keyframes=keyframes, keyframe_stamps_ns=stamps[keyframes],
                      frame_node=np.repeat([0, 1, 2], [20, 10, 10]), edges=np.array([[0, 1], [1, 2]]),
                      transitions=np.array([1, 1]),
                      keyframe_poses=np.array([[np.nan] * 3, truth[20] + [0.05, 0, 0], truth[30] + [0, 0.1, 0]]))
    places = place_results(topomap, index, truth)
    assert places["nodes"] == 3 and places["with_pose"] == 2 and abs(places["median_error_m"] - 0.075) < 1e-12
    assert place_results(topomap.model_copy(update={"keyframe_poses": None}), index, truth) is None
