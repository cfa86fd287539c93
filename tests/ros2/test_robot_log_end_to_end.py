"""Acceptance of issue 31, end to end: a ROS 2 bag written with rosbags' own writer (a simulated table top:
images, CameraInfo, odometry and TF, ground truth) is replayed into the graph by `semloc replay`; the detector and
the localizer run on it as on any camera; the ros2 bridge puts the estimate on amcl_pose in rmw_zenoh's form.
Decoded with rosbags, those PoseWithCovarianceStamped messages carry the right frame id and the images' stamps, and
their error against the ground truth is within what `semloc eval localization` reports on the same sequence (same
detector kind, same map and score likelihoods, the same known start).

The same run is recorded with `semloc record --foxglove`'s recorder: the file opens with the mcap reader, every
Foxglove channel's schema decodes every one of its messages (protobuf through mcap-protobuf-support, which builds
the classes from the file's own descriptors; JSON checked against its JSON Schema), and replay still reads semloc's
own channels only."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from schemas import Header, encode, keys
from schemas.mapping import ObjectMap
from semloc_core.geometry import transform_to_pose2d
from semloc_core.io.dataset import open_dataset
from services.recording import Recorder, read_messages
from services.ros2 import messages as ros
from services.ros2.wire import topic_key
from tests.ros2.robot_log import EPOCH_NS, write_ros2_bag
from tests.service.conftest import REPO_ROOT, hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
FRAMES = 60
STORE = ros.typestore("jazzy")


DEMO_LOCALIZER = yaml.safe_load((REPO_ROOT / "deploy" / "demo.yaml").read_text())["nodes"]["localizer"]["config"]


def _localizer_config(path: Path, dataset: Path, start) -> Path:
    """deploy/demo.yaml's localizer (model B, table-top filter) on deploy/local's detector calibration."""
    config = dict(DEMO_LOCALIZER)
    config.update(map=str(dataset / "semantic_map.json"),
                  score_likelihood=str(REPO_ROOT / "deploy" / "local" / "score_likelihood.json"),
                  initial_pose=[float(v) for v in start], initial_covariance=[0.0025, 0.0025, 0.003],
                  rerun_every=0, status_period_s=0.5)
    path.write_text(yaml.safe_dump(config))
    return path


def test_a_ros2_bag_is_localized_end_to_end_and_recorded_for_foxglove(tmp_path, procs, session, hub, sim_dataset):
    dataset_dir = Path(sim_dataset("tabletop", frames=FRAMES, seed=0))
    dataset = open_dataset(dataset_dir)
    bag = write_ros2_bag(dataset_dir, tmp_path / "robot_bag")
    truth = {EPOCH_NS + int(s): transform_to_pose2d(T) for s, T in zip(dataset.stamps_ns, dataset.T_world_body)}
    # The reference: `semloc eval localization` on the same sequence with the localizer's bearing spread and
    # likelihood exponent, run beside the graph.
    report = tmp_path / "eval" / "report.json"
    evaluation = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "eval", "localization", str(dataset_dir), "-o", str(report), "--quiet",
         *(a for setting in ("models=B", "variants=soft", "sources=detector", "init=gt",
                             f"calibration.file={REPO_ROOT / 'deploy' / 'local' / 'score_likelihood.json'}",
                             f"perception.sigma={DEMO_LOCALIZER['sigma_deg']}",
                             f"perception.exponent={DEMO_LOCALIZER['likelihood_exponent']}")
           for a in ("--set", setting))],
        cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=open(tmp_path / "eval.log", "wb"))  # noqa: SIM115
    common = ("--connect", hub, "--robot", "r1", "--log-level", "WARNING")
    procs.semloc("worker", "detector", *common, "--set", f"detector_file={REPO_ROOT / 'deploy/local/detector.yml'}",
                 "--set", "inputs.image.depth=1", name="detector")
    start = truth[min(truth)]
    procs.semloc("worker", "localizer", *common, "--config", str(_localizer_config(tmp_path / "localizer.yaml",
                                                                                   dataset_dir, start)),
                 name="localizer")
    # No robot here, the bridge only publishes: no ROS input is not a robot away (ros_silence_s off).
    procs.semloc("worker", "ros2", *common, "--set", "base_frame=base_footprint", "--set", "ros_silence_s=null",
                 name="ros2")
    poses = []
    pose_key = topic_key("rmw_zenoh", "/amcl_pose", ros.POSE_WITH_COVARIANCE_STAMPED,
                         STORE.hash_rihs01(ros.POSE_WITH_COVARIANCE_STAMPED))
    subscriber = session.declare_subscriber(pose_key, lambda s: poses.append(s.payload.to_bytes()))
    recorder = Recorder(session, "semloc/r1/**", tmp_path / "run.mcap", foxglove=True)
    try:
        for worker in ("detector", "localizer", "ros2"):
            wait_until(lambda w=worker: _running(session, w), 90, message=f"{worker} running\n{procs.log(worker)}")
        replay = procs.semloc("replay", str(bag), "--robot", "r1", "--speed", "0.1", "--connect", hub,
                              "--wait-for-subscribers", "10", name="replay")
        assert replay.wait(timeout=240) == 0, procs.log("replay")
        # one object map from the "mapper", for the SceneUpdate channel
        session.put(keys.mapper_objects("r1"), encode(_object_map(dataset)))
        wait_until(lambda: len(poses) >= FRAMES // 3 and _idle(session), 60, message="the last estimates")
    finally:
        subscriber.undeclare()
        recorder.close()
    assert evaluation.wait(timeout=300) == 0, (tmp_path / "eval.log").read_text()[-3000:]
    reference = json.loads(report.read_text())["runs"]["B-soft-detector"]["metrics"]["rmse_m"]

    messages = [ros.decode_cdr(STORE, p, ros.POSE_WITH_COVARIANCE_STAMPED) for p in poses]
    assert all(m.header.frame_id == "map" for m in messages)
    stamps = [ros.stamp_ns(m.header.stamp) for m in messages]
    assert set(stamps) <= set(truth), "every estimate carries an image's stamp"
    errors = [math.hypot(*(ros.transform_to_pose2d(ros.pose_matrix(m.pose.pose))[:2] - truth[s][:2]))
              for m, s in zip(messages, stamps)]
    rmse = float(np.sqrt(np.mean(np.square(errors))))
    print(f"ROS amcl_pose: {len(messages)} estimates, RMSE {rmse:.3f} m; semloc eval localization: {reference:.3f} m")
    # eval runs its detector on every frame; the graph's detector keeps only the latest image and may skip some on
    # a loaded machine (the localizer then bridges them with odometry): half as much again is the margin.
    assert rmse <= 1.5 * reference
    for m in messages:
        covariance = m.pose.covariance.reshape(6, 6)
        assert covariance[0, 0] > 0 and covariance[1, 1] > 0 and covariance[5, 5] > 0

    _check_foxglove(tmp_path / "run.mcap")


def _running(session, worker):
    from schemas import Status
    from services.bus import query

    replies = query(session, keys.status("r1", worker), reply_type=Status, timeout=0.5)
    return bool(replies) and replies[0].state == "running"


def _idle(session):
    """The localizer has handled every heatline the detector published (nothing queued)."""
    from schemas import Status
    from services.bus import query

    replies = query(session, keys.status("r1", "localizer"), reply_type=Status, timeout=0.5)
    return bool(replies) and replies[0].inputs["heatlines"].queued == 0


def _object_map(dataset) -> ObjectMap:
    m = dataset.semantic_map
    return ObjectMap(header=Header(robot="r1", stream="mapper", stamp_ns=EPOCH_NS, frame_id="world"),
                     class_names=m.class_names, class_index=m.class_index.astype(np.int32), positions=m.positions,
                     has_height=m.has_height, sizes=m.sizes, scores=m.scores, bounds=m.bounds,
                     existence=m.existence)


def _check_foxglove(path: Path) -> None:
    import jsonschema
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    decoders = DecoderFactory()
    counts: dict[str, int] = {}
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "protobuf":
                decoded = decoders.decoder_for("protobuf", schema)(message.data)
                if schema.name == "foxglove.SceneUpdate":
                    assert len(decoded.entities[0].cubes) == len(decoded.entities[0].texts) > 0
                else:
                    assert decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos >= EPOCH_NS
                if schema.name == "foxglove.RawImage":
                    assert len(decoded.data) == decoded.height * decoded.step > 0
            elif channel.message_encoding == "json":
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            else:
                continue
            counts[schema.name] = counts.get(schema.name, 0) + 1
    assert {"foxglove.RawImage", "foxglove.PoseInFrame", "foxglove.SceneUpdate", "semloc.HeatlinesPlot"} <= set(counts)
    assert counts["foxglove.RawImage"] >= FRAMES // 2, counts
    topics = {c.topic for c in summary.channels.values()}
    assert "/semloc/r1/localizer/pose" in topics and "/semloc/r1/detector/heatlines" in topics
    replayed = {topic for topic, _, _ in read_messages(path)}
    assert replayed and all(t.startswith("semloc/") for t in replayed)
