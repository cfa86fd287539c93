"""A localizer restored from its state_dir (snapshot, the journal after it, killed without a last snapshot) goes on
as if it had never stopped: the same inputs give the same poses and states as an uninterrupted run, bit for bit.
In process, on the simulated table top with synthetic heatlines, no bus timing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas import Header, Odometry, decode, encode
from schemas.loopclosure import LoopClosure
from semloc_core.io.semantic_map import save_semantic_map
from semloc_core.localization import OmniDriveModel, field_of_view_mask, synthetic_scores_heatlines, visible_objects
from semloc_core.localization.motion import Odometry as OdometryIncrement
from semloc_core.sim import make_scenario
from services.frames import camera_model_frame, heatlines_frame
from services.workers.localizer import Localizer, LocalizerConfig
from tests.service.conftest import hub, session  # noqa: F401 - fixtures

FRAMES = 50
SCENARIO = make_scenario("tabletop", seed=0, frames=FRAMES)
TRUTH, STAMPS, ODOMETRY = SCENARIO.poses2d, SCENARIO.stamps_ns, SCENARIO.odometry
OBSERVED = field_of_view_mask(360, 0.0, math.radians(57))
FILTER = {"max_particles": 2000, "min_particles": 200, "converged_xy_std": 0.1, "converged_theta_std": 0.17}


def _odometry(k: int) -> Odometry:
    return Odometry(header=Header(robot="r1", stamp_ns=int(STAMPS[k])), v=float(ODOMETRY.v[k]),
                    v_lateral=float(ODOMETRY.v_lateral[k]), omega=float(ODOMETRY.omega[k]), dt=float(ODOMETRY.dt[k]))


def _heatlines(k: int):
    views = visible_objects(TRUTH[k], SCENARIO.semantic_map, OBSERVED, SCENARIO.semantic_map.class_names)
    return heatlines_frame(Header(robot="r1", stamp_ns=int(STAMPS[k]), seq=k, frame_id="body"),
                           synthetic_scores_heatlines(views, OBSERVED))


def _place_elsewhere(k: int) -> LoopClosure:
    """A confident recognised place across the table from the robot at frame ``k``."""
    pose = np.array([[-TRUTH[k][0], -TRUTH[k][1], TRUTH[k][2]]])
    return LoopClosure(header=Header(robot="r1", stamp_ns=int(STAMPS[k]) + 1), frame=k, status="loop_found",
                       loops=np.arange(1), loop_stamps_ns=np.arange(1), beliefs=np.full(1, 3.0, np.float32), node=0,
                       loop_poses=pose)


def _run(session, tmp_path, settings: dict, cut: int | None = None, journaled: int = 0,  # noqa: F811
         places=(), lost=(), model_after: int | None = None) -> list:
    """(x, y, theta, state, motion_std) after each frame's heatlines; ``cut``: a snapshot before frame ``cut``,
    ``journaled`` frames more only in the journal, then the worker dropped as a SIGKILL leaves it (no last snapshot)
    and a fresh one restored from the state_dir goes on. ``places``: frames after whose heatlines a place is
    recognised; ``lost``: frames whose odometry and heatlines never arrive (None in the list). ``model_after``: view
    geometry on, the camera model arriving after that frame's heatlines (-1: before the first; a restarted worker has it
    at setup once it came, as the query's reply), and the final particles and weights at the end of the list."""
    save_semantic_map(SCENARIO.semantic_map, tmp_path / "map.json")
    config = LocalizerConfig(**{"robot": "r1", "map": str(tmp_path / "map.json"), "motion": "omni", "seed": 0,
                                "initial_pose": [float(v) for v in TRUTH[0]],
                                "initial_covariance": [0.0025, 0.0025, 0.003], "odometry_wait_s": 30.0,
                                "state_dir": str(tmp_path / "state"), "snapshot_period_s": None, **settings})
    started = []
    model = camera_model_frame(SCENARIO.camera, Header(robot="r1", stamp_ns=1))
    model_came = model_after == -1

    def start() -> Localizer:
        worker = Localizer(config)
        worker.session = session
        worker.setup()
        if model_came:
            worker.on_camera_model(model)
        worker._restore()
        started.append(worker)
        return worker

    worker, out = start(), []
    for k in range(FRAMES):
        if k == cut:
            assert worker.save_state_now()
        if cut is not None and k == cut + journaled:
            worker = start()
        if k in lost:
            out.append(None)
            continue
        if k:
            worker.on_odometry(_odometry(k), encode(_odometry(k)))
        worker.on_heatlines(decode(encode(_heatlines(k))))
        if k == model_after:
            worker.on_camera_model(model)
            model_came = True
        if k in places:
            place = _place_elsewhere(k)
            worker.loop_stream.check(place)
            worker.on_loop(place)
        estimate = worker.last_estimate
        if estimate is None:  # nothing weighed yet
            out.append(None)
            continue
        out.append((estimate.x, estimate.y, estimate.theta, estimate.state,
                    None if estimate.motion_std is None else tuple(estimate.motion_std.tolist())))
    if model_after is not None:
        out.append((worker.filter.states.tobytes(), worker.filter.weights.tobytes()))
    for each in started:
        each._journal.close()
        for entry in each._inputs:
            entry.subscriber.undeclare()
    return out


@pytest.mark.parametrize("cut", [3, 30])  # the window filling, then full
def test_a_restored_localizer_keeps_its_history_window(tmp_path, session, cut):  # noqa: F811
    """With history-checked proposals (filter.history_frames) the window of past heatlines is part of the state:
    restored without it, the filter skipped the checks (and their draws) until it was full again, and its poses
    went off the uninterrupted run's from the first frame it weighed (0.017-0.039 m over these 50 frames)."""
    settings = {"filter": {**FILTER, "history_frames": 5}}
    uninterrupted = _run(session, tmp_path / "a", settings)
    restored = _run(session, tmp_path / "b", settings, cut=cut, journaled=2)
    assert restored == uninterrupted


def test_a_restored_localizer_keeps_the_place_seen_since_its_last_verdict(tmp_path, session):  # noqa: F811
    """A place recognised after a frame's verdict is weighed at the next one: snapshotted in between, the restored
    localizer judges that frame as the uninterrupted one does (uncertain: the place puts the robot elsewhere) and
    so every frame after it; before, it forgot the place and stayed localized."""
    uninterrupted = _run(session, tmp_path / "a", {"filter": FILTER}, places=(29,))
    restored = _run(session, tmp_path / "b", {"filter": FILTER}, cut=30, places=(29,))
    assert uninterrupted[29][3] == "localized" and uninterrupted[30][3] == "uncertain"
    assert restored == uninterrupted


@pytest.mark.parametrize("cut", [18, 22])  # the lost frames in the journal, and before the snapshot
def test_a_restored_localizer_replays_a_span_partly_without_odometry(tmp_path, session, cut):  # noqa: F811
    """Frames 20-21 lost with their odometry (a link gap beyond the publishers' cache): frame 22's span has odometry
    for its last interval only, and the particles diffuse over the rest by the random walk (its noise in
    motion_std); replayed from the journal or restored from a snapshot, draw for draw the same."""
    uninterrupted = _run(session, tmp_path / "a", {"filter": FILTER}, lost=(20, 21))
    restored = _run(session, tmp_path / "b", {"filter": FILTER}, cut=cut, journaled=4, lost=(20, 21))
    assert restored == uninterrupted
    config = LocalizerConfig(map="m.json")
    increment = OmniDriveModel().increment_std(OdometryIncrement.from_twist(
        float(ODOMETRY.v[22]), float(ODOMETRY.v_lateral[22]), float(ODOMETRY.omega[22]), float(ODOMETRY.dt[22])))
    walk = math.sqrt((STAMPS[21] - STAMPS[19]) / 1e9)  # the walk's sqrt(s) over the uncovered time
    expected = (math.hypot(increment[0], config.random_walk_translation_std * walk),
                math.hypot(increment[1], config.random_walk_rotation_std * walk))
    assert uninterrupted[22][4] == pytest.approx(expected, rel=1e-6)


VIEW = {"filter": FILTER, "view": True, "camera_height": 0.1}


def test_heatlines_before_the_camera_model_are_weighed_when_it_comes(tmp_path, session):  # noqa: F811
    """The camera model arrives after the first heatlines (the camera's query reply after its first image): those
    heatlines wait for it and are weighed when it comes, as if the model had been there from the start (before, they
    were predicted and skipped: the filter's first observation lost and every pose after it different)."""
    early = _run(session, tmp_path / "a", VIEW, model_after=-1)
    late = _run(session, tmp_path / "b", VIEW, model_after=0)
    assert early[0] is not None and late == early


@pytest.mark.parametrize("cut", [0, 1])  # the snapshot before the first frame, and while it waits for the model
def test_a_restored_localizer_replays_the_heatlines_before_the_camera_model(tmp_path, session, cut):  # noqa: F811
    """Frames 0 and 1 before the camera model: frame 0 predicted only (a newer one came), frame 1 weighed when the
    model comes. Replayed from the journal by a worker that has the model at once, each as it was applied: the same
    particles and poses as the uninterrupted run (before, the record of a skipped frame was replayed as a whole
    update once the model was there)."""
    uninterrupted = _run(session, tmp_path / "a", VIEW, model_after=1)
    restored = _run(session, tmp_path / "b", VIEW, cut=cut, journaled=4, model_after=1)
    assert uninterrupted[0] is None and uninterrupted[1] is not None
    assert restored == uninterrupted


def test_a_snapshot_restores_into_a_shorter_window_and_is_checked(tmp_path, session):  # noqa: F811
    """A window snapshotted longer than the configured one restores its newest frames (none with history off)
    instead of making the snapshot unusable; a snapshot's window and pending place are checked as a file is
    (StateError, nothing changed)."""
    from services.state import State, StateError

    save_semantic_map(SCENARIO.semantic_map, tmp_path / "map.json")

    def worker(history_frames: int) -> Localizer:
        made = Localizer(LocalizerConfig(robot="r1", map=str(tmp_path / "map.json"), motion="omni", seed=0,
                                         initial_pose=[float(v) for v in TRUTH[0]], odometry_wait_s=0,
                                         filter={**FILTER, "history_frames": history_frames}))
        made.session = session
        made.setup()
        return made

    first = worker(5)
    for k in range(8):
        if k:
            first.on_odometry(_odometry(k), encode(_odometry(k)))
        first.on_heatlines(_heatlines(k))
    state = first.snapshot()
    assert len(state.meta["history"]) == 5
    shorter, off = worker(3), worker(0)
    shorter.restore(state)
    off.restore(state)
    assert [h.scores.tobytes() for h, _, _ in shorter.filter.history] == [
        h.scores.tobytes() for h, _, _ in first.filter.history[-3:]]
    assert off.filter.history == []
    for meta in ({**state.meta, "health": {**state.meta["health"], "place_poses": [[0.0, float("nan"), 0.0]]}},
                 {**state.meta, "history": [*state.meta["history"][:-1],
                                            {**state.meta["history"][-1], "motion": [0.0, 1.0]}]}):
        with pytest.raises(StateError):
            shorter.restore(State(arrays=state.arrays, meta=meta))
    assert [h.scores.tobytes() for h, _, _ in shorter.filter.history] == [
        h.scores.tobytes() for h, _, _ in first.filter.history[-3:]]
    for each in (first, shorter, off):
        for entry in each._inputs:
            entry.subscriber.undeclare()


if __name__ == "__main__":  # figures: docs/results/2026-12-07-localizer-restore.md
    import json
    import tempfile
    from pathlib import Path

    from services.bus import BusConfig, free_port, open_session

    variants = {  # name: (settings, cuts, frames journaled after the snapshot, places)
        "as the e2e graph": ({"filter": {"max_particles": 2000, "min_particles": 200, "recovery_alpha_slow": 0.0}},
                             (3, 25, 40), (0, 3), ()),
        "history_frames 5": ({"filter": {**FILTER, "history_frames": 5}}, (3, 25, 40), (0, 3), ()),
        "a place before the cut": ({"filter": FILTER}, (30,), (0,), (29,)),
        "global start, backward passes": ({"initial_pose": None, "smoothing": {"steps_per_frame": 1},
                                           "filter": {**FILTER, "max_particles": 4000, "min_particles": 300}},
                                          (8, 28, 33), (0, 2), ()),
    }
    root = Path(tempfile.mkdtemp(prefix="localizer-restore-"))
    with open_session(BusConfig(listen=[f"tcp/127.0.0.1:{free_port()}"])) as bus:
        for number, (name, (settings, cuts, journals, places)) in enumerate(variants.items()):
            (root / f"{number}").mkdir()
            reference = _run(bus, root / f"{number}", settings, places=places)
            for cut in cuts:
                for journaled in journals:
                    folder = root / f"{number}-{cut}-{journaled}"
                    folder.mkdir()
                    got = _run(bus, folder, settings, cut=cut, journaled=journaled, places=places)
                    apart = [math.hypot(a[0] - b[0], a[1] - b[1]) for a, b in zip(reference, got)]
                    differing = [k for k, (a, b) in enumerate(zip(reference, got)) if a != b]
                    print(json.dumps({"variant": name, "cut": cut, "journaled": journaled,
                                      "first_differing_frame": differing[0] if differing else None,
                                      "max_apart_m": round(max(apart), 4),
                                      "states_differing": sum(a[3] != b[3] for a, b in zip(reference, got))}),
                          flush=True)
