"""A loop-closure worker SIGKILLed and restarted from its state_dir keeps its places' poses (docs/deploy.md, "Nothing
lost"): deploy/two-machines/ on one machine, the loop closure and the localizer at the base station, every frame
through (lossless queues), the link cut for 10 s through a relay (tests/e2e/relay.py) once 10 poses came back and
the loop closure killed 3 s into the cut. Its key-frames' poses are compared, stamp by stamp, with those of a run
never cut nor stopped on the same frames. `python -m tests.e2e.test_loopclosure_restart` measures both and a
restart without a cut (docs/results/2026-12-07-loopclosure-restart.md)."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from schemas import Status, keys
from schemas.loopclosure import TopoMap
from services.bus import free_port, query
from semloc_core.localization.place_poses import PoseRecorder
from services.state import load_state
from tests.e2e.relay import Relay
from tests.e2e.two_machines import CAMERA_RATE_HZ, REPO_ROOT, plain_launchers, run_split_graph
from tests.service.conftest import wait_until

pytestmark = pytest.mark.service

FRAMES = 120  # 30 s at the camera's 4 Hz
CUT_S = 10.0
KILL_AFTER_S = 3.0
POSES_BEFORE = 30  # the places placed before the cut: the first frames' (commit_after 10 estimates later)
LOCAL = REPO_ROOT / "deploy" / "local"


def _status(session, worker: str) -> Status | None:
    replies = query(session, keys.status("r1", worker), reply_type=Status, timeout=2.0)
    return replies[0] if replies else None


def _overrides() -> tuple[dict, dict]:
    """(base station's, robot's): the loop closure on, taking every image; the localizer's heatlines recoverable, as
    docs/deploy.md shows, so that it estimates the frames of a cut too; deploy/local/'s detector and score likelihood
    (made on this world), with which the localizer says it is localized (the places keep only such estimates)."""
    every = {"policy": "lossless", "depth": 64}
    # no snapshot in a run this short: the kill finds the whole state in the journal (as one just before a snapshot)
    journal_only = {"snapshot_period_s": 600.0, "journal_replay_s": 600.0}
    base = {"nodes": {"loopclosure": {"enabled": True, "inputs": {"image": every}, "config": journal_only},
                      "localizer": {"inputs": {"heatlines": {"recover": True}},
                                    "config": {"score_likelihood": str(LOCAL / "score_likelihood.json")}}}}
    detector = yaml.safe_load((LOCAL / "detector.yml").read_text())  # (every field of the test graph's)
    detector["templates"] = str(LOCAL / detector["templates"])
    robot = {"nodes": {"detector": {"outputs": {"heatlines": {"recover": 300}}, "config": {"detector": detector}}}}
    return base, robot


def loopclosure_run(tmp_path: Path, dataset: Path, cut: bool, restart: bool) -> dict:
    """One run of the data set: the link cut for CUT_S once POSES_BEFORE poses came back (``cut``), the loop closure
    SIGKILLed KILL_AFTER_S after that and restarted by its launcher from its state_dir (``restart``); once every frame
    went through and its pose inputs settled: its frames' stamps and poses, its input counters."""
    base_port, seen = free_port(), {}

    def then(poses, at_robot, at_base) -> None:
        wait_until(lambda: len(poses) >= POSES_BEFORE, 60, message=f"{POSES_BEFORE} poses before the cut")
        seen["cut_stamp"] = max(p.header.stamp_ns for p in poses)
        started = time.monotonic()
        if cut:
            relay.cut("refuse")
        time.sleep(KILL_AFTER_S)
        if restart:
            os.kill(base.nodes["loopclosure"].pid, signal.SIGKILL)
            wait_until(lambda: getattr(_status(at_base, "loopclosure"), "state", None) == "running", 60,
                       message="the loop closure restarted")
        if cut:
            time.sleep(max(0.0, CUT_S - KILL_AFTER_S - (time.monotonic() - started)))
            relay.restore()
        last: dict = {}

        def settled() -> bool:  # the camera played everything; the loop closure's and localizer's queues are empty
            camera, loop, localizer = (_status(at_robot, "camera"), _status(at_base, "loopclosure"),
                                       _status(at_base, "localizer"))
            if loop is None or localizer is None:
                return False
            played = camera is None or camera.outputs["image"].published >= FRAMES - 1
            state = (played, localizer.outputs["pose"].published,
                     *((loop.inputs[i].processed, loop.inputs[i].queued) for i in ("image", "pose", "odom")))
            same = state == last.get("state") and all(q == 0 for _, q in state[2:])
            last["state"] = state
            return played and same

        wait_until(settled, 120, interval=3.0, message=lambda: f"every frame through ({last})")
        seen["status"] = _status(at_base, "loopclosure")
        seen["topomap"] = query(at_base, keys.loopclosure_topomap("r1"), reply_type=TopoMap, timeout=10.0)[0]

    with Relay(base_port) as relay:
        base, robot, _, robot_port = plain_launchers(tmp_path, dataset, True, base_port=base_port,
                                                    link_port=relay.port, overrides=_overrides())
        run = run_split_graph(base, robot, base_port, robot_port, then=then,
                              base_workers=("localizer", "loopclosure"))
    topomap, status = seen["topomap"], seen["status"]
    # every frame's pose, from the snapshot the graceful stop wrote (the map published holds its places' only)
    state = load_state(tmp_path / "state" / "r1" / "loopclosure.npz")
    inputs = {name: {"processed": status.inputs[name].processed, "recovered": status.inputs[name].recovered,
                     "missed": status.inputs[name].missed, "already_held": status.inputs[name].already_held}
              for name in ("image", "pose", "odom", "past_poses") if name in status.inputs}
    return {"frames": {int(s): [float(v) for v in p] for s, p in zip(state.arrays["stamps_ns"],
                                                                       state.arrays["frame_poses"])},
            "places": len(topomap.keyframes), "inputs": inputs, "restarts": status.restarts,
            "cut_stamp": seen["cut_stamp"],
            "estimates": {int(p.header.stamp_ns): [float(p.x), float(p.y), float(p.theta), p.localized()]
                          for p in run.poses}}


def confirmed(got: dict) -> dict[int, list[float]]:
    """The frames' poses the run's own estimates (as the robot received them) give by the places' rule
    (semloc_core/localization/place_poses.py): the estimate at a frame's stamp, once it and the next ``commit_after``
    ones were localized (on a track that stays one, nothing is withdrawn)."""
    estimates = got["estimates"]
    order = sorted(estimates)
    wait = PoseRecorder().commit_after
    kept = {stamp for k, stamp in enumerate(order)
            if k + wait < len(order) and all(estimates[s][3] for s in order[k:k + wait + 1])}
    return {stamp: estimates[stamp][:3] for stamp in got["frames"] if stamp in kept}


def held(got: dict) -> dict:
    """How many of the frames :func:`confirmed` places hold that pose (``equal``: to 1e-6), and the others."""
    expected = confirmed(got)
    equal = [s for s, pose in expected.items() if np.allclose(got["frames"][s], pose, atol=1e-6)]
    return {"frames": len(got["frames"]), "confirmed": len(expected), "equal": len(equal),
            "others": {s: [expected[s], got["frames"][s]] for s in expected if s not in equal}}


def compare(reference: dict, got: dict) -> dict:
    """The frames (key-frames the gate took) both runs have: how many the reference placed, how many of those ``got``
    placed too, and how far apart (m, rad); ``unplaced``: the stamps of those ``got`` left without a pose."""
    ours, theirs = got["frames"], reference["frames"]
    common = sorted(set(theirs) & set(ours))
    placed = [s for s in common if np.isfinite(theirs[s][0])]
    both = [s for s in placed if np.isfinite(ours[s][0])]
    apart = [float(np.hypot(*np.subtract(ours[s][:2], theirs[s][:2]))) for s in both]
    turned = [abs(float(np.angle(np.exp(1j * (ours[s][2] - theirs[s][2]))))) for s in both]
    return {"frames": len(ours), "reference_frames": len(theirs), "common": len(common),
            "reference_placed": len(placed), "placed": len(both),
            "placed_total": int(sum(np.isfinite(p[0]) for p in ours.values())),
            "max_apart_m": round(max(apart, default=0.0), 4), "max_turned_rad": round(max(turned, default=0.0), 4),
            "unplaced": [s for s in placed if s not in both]}


def test_a_loop_closure_restarted_during_a_cut_keeps_its_places_poses(tmp_path, sim_dataset):
    """Killed 3 s into a 10 s cut and restarted from its state (its journal: no snapshot yet), the loop closure's
    frames hold the poses the run's own estimates give them (the estimate at the frame's stamp, once the localizer
    stayed localized for ``commit_after`` more), those placed before the kill too, and those the uninterrupted run
    placed; the estimates its journal held, which the localizer's cache sends again, are dropped (``already_held``).
    Before, every pose placed before the kill was lost with the estimates and odometry that placed it: 6 of 11
    frames held theirs, none of the 5 placed before the kill (docs/results/2026-12-07-loopclosure-restart.md)."""
    dataset = Path(sim_dataset("tabletop", frames=FRAMES, seed=0))
    reference = loopclosure_run(tmp_path / "reference", dataset, cut=False, restart=False)
    got = loopclosure_run(tmp_path / "restart", dataset, cut=True, restart=True)
    compared, own = compare(reference, got), held(got)
    inputs = got["inputs"]
    before = [s for s in confirmed(got) if s <= got["cut_stamp"]]  # placed before the kill
    figures = json.dumps({"own": own, "before_cut": len(before), "compared": compared, "inputs": inputs,
                          "restarts": got["restarts"]}, default=int)
    assert got["restarts"] == 1 and held(reference)["equal"] == held(reference)["confirmed"] >= 10, figures
    assert own["equal"] == own["confirmed"] and len(before) >= 3, figures
    # the uninterrupted run at the frames both have (the gate's key-frames differ run to run, and the localizer's
    # estimates may, docs/results/2026-12-07-restart-during-cut.md: hence 0.15 m)
    assert compared["placed"] == compared["reference_placed"] >= 1 and compared["max_apart_m"] < 0.15, figures
    # both caches were asked; the camera's may be asked during the cut while its token is still heard, and answers
    # nothing then: it is asked again once heard (services/bus.py CacheHistory; before, 1 of 5 runs lost the gap)
    assert inputs["odom"]["recovered"] >= 0.5 * CUT_S * CAMERA_RATE_HZ and inputs["odom"]["missed"] == 0, figures
    assert inputs["odom"]["already_held"] >= 1 and inputs["pose"]["already_held"] >= 1, figures


if __name__ == "__main__":
    import tempfile

    from semloc_core.sim import make_scenario

    root = Path(tempfile.mkdtemp(prefix="loopclosure-restart-"))
    data = make_scenario("tabletop", frames=FRAMES, seed=0).write(root / "data", multiview=False)
    runs = {"reference": (False, False), "restart": (False, True), "cut-restart": (True, True)}
    if "--cut-only" in sys.argv:
        runs = {"reference": (False, False), "cut-restart": (True, True)}
    results = {}
    for label, (cut, restart) in runs.items():
        results[label] = loopclosure_run(root / label, Path(data), cut, restart)
        print(label, json.dumps({k: v for k, v in results[label].items() if k not in ("frames", "estimates")}
                                | {"frames": len(results[label]["frames"]),
                                   "localized": sum(e[3] for e in results[label]["estimates"].values())},
                                default=int), flush=True)
        print(label, "own estimates", json.dumps(held(results[label]), default=float), flush=True)
        if label != "reference":
            print(label, "vs reference", json.dumps(compare(results["reference"], results[label]), default=int),
                  flush=True)
    (root / "results.json").write_text(json.dumps(results, default=int))
    print("results in", root / "results.json")
