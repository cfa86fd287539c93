"""A live run's outputs in standard formats: `semloc up deploy/local.yaml --save DIR` on a short simulated data set.

The saved trajectory compares with the data set's ground truth like with like (same frame, same TUM format): its
RMSE is the figure `semloc eval localization` computes for it; the saved object map loads into a localizer; PLY and
GraphML parse with standard readers (plyfile, networkx); `semloc map save` at the end of the run writes the files
`--save` wrote; `semloc export` of the run's recording gives back its trajectory and topological map."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import networkx
import numpy as np
import plyfile
import pytest

from schemas import decode, encode, keys
from schemas.localization import PoseEstimate
from schemas.status import LauncherStatus, Status
from semloc_core.geometry import transform_to_pose2d, wrap_angle
from semloc_core.io.semantic_map import load_semantic_map
from semloc_core.io.trajectory import read_tum
from semloc_core.io.voxel_map import load_voxel_map
from semloc_core.localization.health import HealthConfig
from semloc_core.localization.place_poses import PoseRecorder
from services.bus import BusConfig, open_session, query
from services.recording import Recorder, read_messages
from tests.e2e.graph import stop, tracking_options
from tests.service.conftest import free_port, wait_until

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.service
WORKERS = ("detector", "loopclosure", "localizer", "mapper", "saver")
MAP_FILES = ("objects.json", "voxels.npz", "voxels.ply", "topomap.json", "topomap.graphml")


def semloc(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=timeout)


def tum_rmse(ground_truth: Path, estimate: Path) -> tuple[float, int]:
    """evo_ape's figure, computed independently: each estimate's stamp associated with the ground truth's nearest
    (within 10 ms, evo's default), translation RMSE without alignment."""
    gt_stamps, gt_poses = read_tum(ground_truth)
    est_stamps, est_poses = read_tum(estimate)
    nearest = np.abs(est_stamps[:, None] - gt_stamps[None, :]).argmin(axis=1)
    close = np.abs(gt_stamps[nearest] - est_stamps) < 0.01
    errors = np.linalg.norm(est_poses[close, :3, 3] - gt_poses[nearest[close], :3, 3], axis=1)
    return float(np.sqrt(np.mean(errors ** 2))), int(close.sum())


@pytest.fixture(scope="module")
def run(tmp_path_factory, sim_dataset):
    """The graph without its camera, every worker running; then the data set played once by a camera worker of its
    own (so no frame is lost to a worker still starting) while the session is recorded; then every file settled."""
    root = tmp_path_factory.mktemp("run-outputs")
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    # tracking from the true start (a global start takes longer than 24 frames): the error says whether the saved
    # trajectory and the data set's ground truth are in one frame
    start = transform_to_pose2d(read_tum(dataset / "groundtruth_body.tum")[1][0])
    hub = f"tcp/127.0.0.1:{free_port()}"
    save, saved_by_command = root / "save", root / "map-save"
    log = open(root / "up.log", "wb")  # noqa: SIM115 - the child keeps its copy
    graph = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "up", "deploy/local.yaml", "--hub", hub, "--save", str(save),
         "--run-dir", str(root / "run"), "--set", "nodes.camera.enabled=false",
         "--set", "nodes.saver.config.period_s=1", "--set", "nodes.mapper.config.publish_period_s=1",
         *tracking_options(start, root / "state")],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    try:
        with open_session(BusConfig(connect=[hub], listen=["tcp/127.0.0.1:0"])) as session:
            def running():
                found = [query(session, keys.status("r1", w), reply_type=Status, timeout=1.0) for w in WORKERS]
                return all(replies and replies[0].state == "running" for replies in found)

            wait_until(running, 180, interval=1.0, message="every worker running")
            recorder = Recorder(session, keys.robot_all("r1"), root / "session.mcap")
            camera = semloc("worker", "camera", "--robot", "r1", "--connect", hub, "--set", f"source={dataset}",
                            "--set", "source_type=dataset", "--set", "rate=3", timeout=300)
            assert camera.returncode == 0, camera.stderr[-2000:]

            def settled(previous={}):  # noqa: B006 - the state seen at the last call
                state = {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in save.glob("*") if p.is_file()}
                stable = state == previous.get("state") and all(name in state for name in MAP_FILES)
                previous["state"] = state
                return stable

            wait_until(settled, 240, interval=6.0, message="the saved files settled")
            answer = semloc("map", "save", str(saved_by_command), "--hub", hub)
            recorder.close()
            nodes = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=2.0)
            assert nodes and all(node.restarts == 0 for node in nodes[0].nodes.values()), nodes
            # a crash of the saver: the launcher restarts it, and it continues the trajectory it had written
            before_crash = (save / "trajectory.tum").read_bytes()
            os.kill(nodes[0].nodes["saver"].pid, signal.SIGKILL)

            def restarted():
                found = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=1.0)
                node = found[0].nodes.get("saver") if found else None
                return node is not None and node.restarts == 1 and node.state == "running"

            wait_until(restarted, 120, interval=0.5, message="the saver restarted")
            after_restart = (save / "trajectory.tum").read_bytes()
    finally:
        stop(graph, timeout=60)
    return {"dataset": dataset, "save": save, "map_save": saved_by_command, "answer": answer, "root": root,
            "before_crash": before_crash, "after_restart": after_restart}


def test_the_trajectory_rmse_is_the_evaluations(run):
    save, dataset = run["save"], run["dataset"]
    rmse, matched = tum_rmse(dataset / "groundtruth_body.tum", save / "trajectory.tum")
    assert matched >= 3, (save / "trajectory.tum").read_text()
    out = run["root"] / "eval" / "estimate.json"
    result = semloc("eval", "localization", str(dataset), "--set", f"estimate={save / 'trajectory.tum'}", "-o",
                    str(out), "--json", "--quiet")
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["frames"] == matched and report["unmatched_stamps"] == 0
    figure = report["runs"]["estimate"]["metrics"]["rmse_m"]
    print(f"trajectory.tum vs groundtruth_body.tum: RMSE {rmse:.6f} m over {matched} frames; "
          f"semloc eval localization: {figure:.6f} m")
    assert figure == pytest.approx(rmse, abs=1e-3)
    assert rmse < 0.3  # the estimate tracks the ground truth: the same frame (the camera's would be 1.4 m off)
    # ... and the same rotation convention: the yaw of both TUM quaternions agrees
    est_stamps, est_poses = read_tum(save / "trajectory.tum")
    gt_stamps, gt_poses = read_tum(dataset / "groundtruth_body.tum")
    yaw = lambda poses: np.arctan2(poses[:, 1, 0], poses[:, 0, 0])  # noqa: E731
    heading = wrap_angle(yaw(est_poses) - yaw(gt_poses[np.searchsorted(gt_stamps, est_stamps)]))
    assert np.degrees(np.sqrt(np.mean(heading ** 2))) < 20
    # like with like: the ground truth the run saw on the bus is the data set's file, pose for pose
    bus_stamps, bus_poses = read_tum(save / "groundtruth.tum")
    index = np.searchsorted(gt_stamps, bus_stamps)
    assert len(bus_stamps) == 24 and np.array_equal(gt_stamps[index], bus_stamps)
    assert np.allclose(gt_poses[index], bus_poses, atol=1e-6)
    assert np.all(bus_poses[:, 2, 3] == 0) and np.all(read_tum(save / "trajectory.tum")[1][:, 2, 3] == 0)


def test_a_good_track_is_localized_to_the_end(run):
    """Started at the true pose, the localizer tracks within 0.1 m: its state says localized on every such frame
    once the start is vetted (a configured pose is held ``uncertain`` for ``rival_frames`` frames, as a given one)
    and the hysteresis has let it (a fit test learned on the first ten frames once called the last two lost)."""
    gt_stamps, gt_poses = read_tum(run["dataset"] / "groundtruth_body.tum")
    estimates = sorted((decode(payload, expected=PoseEstimate) for _topic, _time, payload in
                        read_messages(run["root"] / "session.mcap", include=(keys.localizer_pose("r1"),))),
                       key=lambda estimate: estimate.header.stamp_ns)
    near = []
    for index, estimate in enumerate(estimates):
        truth = gt_poses[np.abs(gt_stamps - estimate.header.stamp_ns * 1e-9).argmin(), :2, 3]
        if np.hypot(estimate.x - truth[0], estimate.y - truth[1]) < 0.1:
            near.append((index, estimate.state))
    vetted = [state for index, state in near if index >= HealthConfig().rival_frames]  # after the start's hold
    assert len(vetted) >= 10 and set(vetted[5:]) == {"localized"}, near


def test_a_restarted_saver_keeps_what_was_written(run):
    assert run["after_restart"] == run["before_crash"] and run["before_crash"].count(b"\n") > 3


def test_the_saved_object_map_loads_into_the_localizer(run):
    from services.workers.localizer import Localizer, LocalizerConfig

    saved = load_semantic_map(run["save"] / "objects.json")
    config = LocalizerConfig(robot="rsaved", map=str(run["save"] / "objects.json"),
                             score_likelihood=str(REPO_ROOT / "deploy" / "local" / "score_likelihood.json"))
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        localizer = Localizer(config)
        localizer.session = session
        localizer.setup()
        assert localizer.semantic_map.class_names == saved.class_names
        assert np.array_equal(localizer.semantic_map.positions, saved.positions)
    voxels = load_voxel_map(run["save"] / "voxels.npz")
    assert tuple(voxels["class_names"]) == saved.class_names and int(voxels["frames"]) > 0


def test_ply_and_graphml_parse_with_standard_readers(run):
    save = run["save"]
    cloud = plyfile.PlyData.read(str(save / "voxels.ply"))["vertex"]
    voxels = load_voxel_map(save / "voxels.npz")
    assert cloud.count > 0 and {"x", "y", "z", "score", "class_index"} <= {p.name for p in cloud.properties}
    # every point is a voxel centre of the grid, and its score that voxel's score
    ijk = np.floor((np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1) - voxels["origin"])
                   / voxels["voxel_size"]).astype(int)
    scores = voxels["scores"][cloud["class_index"].astype(int), ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    assert np.allclose(scores, cloud["score"], rtol=1e-6)
    graph = networkx.read_graphml(save / "topomap.graphml")
    document = json.loads((save / "topomap.json").read_text())
    assert graph.number_of_nodes() == len(document["nodes"]) > 0
    assert graph.number_of_edges() == len(document["edges"])
    # a node's position is the localizer's estimate at its key-frame's stamp, if that estimate was localized and
    # stayed so for place_poses.commit_after further estimates (a good track: nothing withdrawn); a node seen while
    # not localized may hold the next stretch's pose carried back along the odometry (place_poses.backfill)
    estimates = {}
    for _topic, _time, payload in read_messages(run["root"] / "session.mcap", include=(keys.localizer_pose("r1"),)):
        estimate = decode(payload, expected=PoseEstimate)
        estimates[estimate.header.stamp_ns] = estimate
    order = sorted(estimates)
    wait = PoseRecorder().commit_after
    confirmed = {stamp for k, stamp in enumerate(order)
                 if all(estimates[s].state == "localized" for s in order[k:k + wait + 1]) and k + wait < len(order)}
    localized = [node for node in document["nodes"] if estimates[node["stamp_ns"]].state == "localized"]
    placed = [node for node in localized if node["pose"] is not None]
    assert [node for node in document["nodes"] if node["stamp_ns"] in confirmed] == placed and confirmed
    assert sum(estimate.state == "localized" for estimate in estimates.values()) > len(estimates) / 2
    for node in placed:
        attributes = graph.nodes[f"n{node['id']}"]
        assert (attributes["x"], attributes["y"], attributes["theta"]) == pytest.approx(node["pose"])
        estimate = estimates[node["stamp_ns"]]
        assert [estimate.x, estimate.y, estimate.theta] == pytest.approx(node["pose"], abs=1e-9)
    # the others hold a pose carried back or from a backward pass, or none; carried from a track tracking from the
    # true start, it is where the robot was (within the acceptance's 0.5 m)
    gt_stamps, gt_poses = read_tum(run["dataset"] / "groundtruth_body.tum")
    carried = [node for node in document["nodes"] if node not in localized and node["pose"] is not None]
    for node in carried:
        truth = transform_to_pose2d(gt_poses[np.abs(gt_stamps - node["stamp_ns"] * 1e-9).argmin()])
        assert np.hypot(*(np.asarray(node["pose"][:2]) - truth[:2])) < 0.5, (node, truth)


def test_map_save_writes_what_save_wrote(run):
    assert run["answer"].returncode == 0, run["answer"].stderr
    assert run["answer"].stdout.startswith("saved 5 files"), run["answer"].stdout
    for name in MAP_FILES:
        assert (run["map_save"] / name).read_bytes() == (run["save"] / name).read_bytes(), name


def test_export_of_the_recording(run):
    out = run["root"] / "export"
    result = semloc("export", str(run["root"] / "session.mcap"), "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert (out / "trajectory.tum").read_text() == (run["save"] / "trajectory.tum").read_text()
    assert (out / "groundtruth.tum").read_text() == (run["save"] / "groundtruth.tum").read_text()
    assert json.loads((out / "topomap.json").read_text()) == json.loads((run["save"] / "topomap.json").read_text())
    # the last object map published is the one saved (the mapper published after its last frame)
    assert (out / "objects.json").read_bytes() == (run["save"] / "objects.json").read_bytes()
    assert not (out / "voxels.npz").exists()  # score volumes never travel on the bus


def test_commands_say_in_one_line_when_there_is_nothing(tmp_path):
    silent = f"tcp/127.0.0.1:{free_port()}"  # no graph there
    result = semloc("map", "save", str(tmp_path / "maps"), "--hub", silent, "--wait", "1")
    assert result.returncode == 1 and result.stderr.strip().count("\n") == 0, result.stderr
    assert result.stderr.startswith("semloc map save: nothing answered on semloc/r1/mapper/save")
    result = semloc("export", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "out"))
    assert (result.returncode, result.stderr.strip()) == (2, f"semloc export: no such recording: "
                                                              f"{tmp_path / 'missing.mcap'}")
    (tmp_path / "bad.mcap").write_bytes(b"not a recording")
    result = semloc("export", str(tmp_path / "bad.mcap"), "-o", str(tmp_path / "out"))
    assert result.returncode == 2 and result.stderr.startswith("semloc export: ") and "Traceback" not in result.stderr


def test_the_saver_rewrites_the_topomap_when_a_keyframe_is_placed_late(tmp_path):
    """A key-frame's position may reach the loop closure after the frame's map update (the localizer's estimate
    committed later, a pose carried back, a backward pass): the loop closure then publishes the pose change as a
    TopoMapUpdate of its own, and the saved topomap.json ends up with the position `semloc map save` would write.
    The loop closure is played here by a queryable."""
    from schemas import Header
    from schemas.loopclosure import TopoMap, TopoMapUpdate
    from services.workers.saver import Saver, SaverConfig
    from tests.service.conftest import spinning

    robot, stamp, place = "rsave", 5_000_000_000, (0.5, -0.25, 1.0)
    known = {"pose": (np.nan,) * 3}  # what the loop closure knows of its key-frame's position

    def topomap(header_stamp=stamp):
        return TopoMap(header=Header(robot=robot, stamp_ns=header_stamp), keyframes=np.array([0]),
                       keyframe_stamps_ns=np.array([stamp]), frame_node=np.array([0]),
                       edges=np.zeros((0, 2), np.int64), transitions=np.zeros(0, np.int64),
                       keyframe_poses=np.array([known["pose"]], np.float64))

    def answer(query_):
        query_.reply(keys.loopclosure_topomap(robot), encode(topomap()))
        query_.drop()

    def saved_position():
        path = tmp_path / "save" / "topomap.json"
        return json.loads(path.read_text())["nodes"][0]["pose"] if path.exists() else "missing"

    none = np.zeros((0, 2), np.int64)
    update = TopoMapUpdate(header=Header(robot=robot, stamp_ns=stamp), frames=1, nodes=1,
                           assigned=np.array([[0, 0]]), new_nodes=np.array([[0, 0]]), edges_added=none,
                           edges_removed=none)
    placed = TopoMapUpdate(header=Header(robot=robot, stamp_ns=stamp), frames=1, nodes=1, assigned=none,
                           new_nodes=none, edges_added=none, edges_removed=none,
                           posed_frames=np.array([0]), frame_poses=np.array([place]))
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        saver = Saver(SaverConfig(robot=robot, folder=str(tmp_path / "save"), period_s=0.2))
        saver.session = session
        saver.setup()
        queryable = session.declare_queryable(keys.loopclosure_topomap(robot), answer)
        try:
            with spinning(saver):
                session.put(keys.loopclosure_topomap(robot), encode(update))
                wait_until(lambda: saved_position() is None, 10, message="topomap.json, its key-frame unplaced")
                known["pose"] = place  # the loop closure places its key-frame now, and says so
                session.put(keys.loopclosure_topomap(robot), encode(placed))
                wait_until(lambda: saved_position() == pytest.approx(list(place)), 10,
                           message=lambda: f"topomap.json placing the key-frame: {saved_position()}")
        finally:
            queryable.undeclare()
            saver.teardown()
