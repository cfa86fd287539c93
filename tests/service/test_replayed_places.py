"""A walk replayed into a running loop-closure worker (docs/hybrid-localization.md, "Places carry poses"): the second
run's images, odometry and estimates carry the first run's stamps again. Its stretch of localized estimates is not
judged against the first run's, nor are the first run's last estimates committed by the second's: the frames of the
first run keep the poses they recorded (the map), and those of the second record their own.

A real worker process over zenoh on loopback, fed as the localizer and the camera would (tests/service/test_poison.py's
clean sequence, without the barrage).
"""

from __future__ import annotations

import numpy as np
import pytest

from schemas import Header, Image, encode, keys
from tests.service.conftest import Received, wait_until
from tests.service.test_poison import (SECOND, SMALL, _calibration, _estimate, _frame_poses,  # noqa: F401
                                       _odometry_of, fleet)

pytestmark = pytest.mark.service


@pytest.mark.parametrize("estimate_first", [False, True], ids=["images-first", "estimates-first"])
def test_a_replayed_walk_keeps_the_first_runs_place_poses_and_records_its_own(tmp_path, fleet, session,
                                                                             sim_scenario, estimate_first):
    """Run 1: lost for three frames, then localized at the truth. Run 2, the same stamps (the robot carried back to
    the start): uncertain for three frames, then localized at the truth, 3 m from where run 1 ended - another
    hypothesis, had the two runs been one track. The worker meets run 2's first image before its first estimate, or
    (``estimate_first``) the other way round."""
    scenario = sim_scenario("tabletop", frames=24, seed=0, fps=2.0, camera=SMALL)
    args = [a for setting in (f"calibration={_calibration(tmp_path)}", "engine.window=5", "engine.bootstrap_frames=12",
                              "engine.vocabulary_words=48", "engine.candidates=5", "engine.band=8",
                              "engine.temporal_radius=1", "image_policy=lossless", "rerun_every=0",
                              "keyframes.min_change=1e-9", "keyframes.min_distance=1e-9", "keyframes.min_turn=1e-9",
                              "place_poses.commit_after=3")
            for a in ("--set", setting)]
    fleet.running("r1", "loopclosure", fleet.start("loopclosure", "r1", *args))
    publishers = {kind: fleet.publisher(key("r1")) for kind, key in (
        ("image", keys.camera_image), ("pose", keys.localizer_pose), ("odom", keys.odometry))}
    updates = Received(session, {"r1": keys.loopclosure_topomap("r1")})
    events = Received(session, {"r1": keys.loopclosure_events("r1")})
    n = len(scenario)
    truth = scenario.poses2d
    stamps = [(k + 1) * SECOND for k in range(n)]
    odometry = _odometry_of(truth, stamps, "r1")  # each run's first from rest: the odometry sees no carrying
    after = {}
    for run, before in ((1, "lost"), (2, "uncertain")):
        for k in range(n):
            header = Header(robot="r1", seq=(run - 1) * n + k, stamp_ns=stamps[k])
            estimate = _estimate(header.model_copy(update={"frame_id": "world"}), truth[k],
                                 state=before if k < 3 else "localized")
            publishers["odom"].put(encode(odometry[k]))
            if estimate_first and run == 2 and k == 0:
                publishers["pose"].put(estimate)
                wait_until(lambda: fleet.status("r1", "loopclosure").inputs["pose"].processed == n + 1, 30,
                           message="the second run's first estimate")
            publishers["image"].put(encode(Image.from_pixels(header, scenario.image(k))))
            if not (estimate_first and run == 2 and k == 0):
                publishers["pose"].put(estimate)
        wait_until(lambda: len(events["r1"]) >= run * n, 120, message=lambda: f"{run * n} decisions\n"
                   f"{fleet.procs.log('loopclosure-r1')[-3000:]}")
        handled = wait_until(lambda: (s := fleet.status("r1", "loopclosure")).inputs["pose"].processed == run * n
                             and s.inputs["odom"].processed == run * n and s, 60,
                             message="every estimate and odometry taken")
        # every map update they made is here: the last pose changes go out as the estimates are handled
        published = handled.outputs["topomap"].published
        wait_until(lambda: len(updates["r1"]) >= published, 10,
                   message=lambda: f"{published} map updates (got {len(updates['r1'])})")
        after[run] = _frame_poses(updates["r1"])
    updates.close()
    events.close()
    first, final = after[1], after[2]
    posed_first = sorted(f for f in first if np.isfinite(first[f][0]))
    posed_second = sorted(f for f in final if f >= n and np.isfinite(final[f][0]))
    print(f"posed: first run {posed_first}, second run {posed_second}")
    # the first run's frames: committed from frame 3 (and carried back to the lost ones), all but the last three
    assert posed_first and max(posed_first) <= n - 4 and len(posed_first) >= n - 6
    for f in posed_first:  # the map stays: not withdrawn, not overwritten by the second run's estimates
        assert np.array_equal(final[f], first[f]), (f, first[f], final[f])
        assert np.hypot(*(np.array(first[f][:2]) - truth[f][:2])) < 0.05
    assert len(posed_second) >= len(posed_first)
    for f in posed_second:
        assert np.hypot(*(np.array(final[f][:2]) - truth[f - n][:2])) < 0.05, (f, final[f], truth[f - n])
    status = fleet.status("r1", "loopclosure")
    assert status.state == "running" and status.errors == 0 and status.rejected == 0
