"""The demo's loop-closure figures over a worker that processed key-frames only: pairs are counted by how far apart
their frames are in the data set, not in the worker's own numbering."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from services.demo_report import loop_closure_results


def test_loop_pairs_are_counted_by_data_set_frames_when_the_worker_skips_frames():
    n, revisit = 100, 60  # frame i revisits frame i - 60
    gt = np.zeros((n, n), bool)
    for i in range(revisit, n):
        gt[i, i - revisit] = gt[i - revisit, i] = True
    stamps = np.arange(n, dtype=np.int64) * 1_000_000
    index_of_stamp = {int(s): i for i, s in enumerate(stamps)}
    # Key-frames: every other frame of the data set; worker frame k is data-set frame 2k, and it reports the right
    # loop (k - 30, i.e. frame 2k - 60) from k = 30 on, and one wrong loop (k - 20) at k = 45.
    events, rows = [], []
    for k in range(n // 2):
        loops = [k - 30] if k >= 30 else []
        if k == 45:
            loops.append(k - 20)
        header = SimpleNamespace(stamp_ns=int(stamps[2 * k]))
        # The worker's expected precision as its LoopClosure frames carry it (the report keeps the last frame's).
        events.append(SimpleNamespace(frame=k, header=header, loops=np.array(loops, int), revised=[],
                                      expected_precision=None if k < 30 else 0.9 + k / 1000))
        candidates = np.array([k - 30, k - 20] if k >= 30 else [], int)
        rows.append(SimpleNamespace(frame=k, candidates=candidates, similarity=np.array([0.9, 0.1][: candidates.size])))
    # Camera centres: frame i and its revisit i - 60 at the same place, 1 m between successive places.
    positions = np.stack([np.arange(n) % revisit, np.zeros(n), np.ones(n)], axis=1).astype(float)
    result = loop_closure_results(events, rows, index_of_stamp, gt, None, window=30, positions=positions)
    assert result["frames"] == 50 and result["window"] == 30
    assert result["positives"] == 20  # key-frame pairs 60 data-set frames apart (30 worker frames: counted)
    assert result["true_positives"] == 20 and result["predicted"] == 21
    assert result["revisit_frames"] == 20 and result["revisit_frames_recognised"] == 20
    assert result["similarity_average_precision"] == 1.0  # the true pairs score highest
    assert result["expected_precision"] == 0.9 + 49 / 1000
    # The wrong loop: data-set frames 90 and 50, places 30 and 50, 20 m apart; its frame has a right one too.
    assert result["false_decisions"] == {"count": 1, "quartiles_m": [20.0, 20.0, 20.0]}
    assert result["frame_precision"] == 1.0 and result["frames_with_loop"] == 20
