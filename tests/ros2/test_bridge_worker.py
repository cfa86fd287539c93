"""The ros2 bridge worker as a real process on a real zenoh session, in both conventions: ROS 2 CDR in (odometry,
camera info, image, /initialpose), semloc frames out, and the localizer's estimate out as nav2 expects it
(PoseWithCovarianceStamped on amcl_pose, map -> odom on /tf), decoded here with rosbags. rmw_zenoh: every sample
carries the attachment and the node's entities are in the liveliness graph. Hostile CDR payloads are counted."""

from __future__ import annotations

import math

import numpy as np
import zenoh
import pytest

from schemas import Ack, CameraModel, Header, Image, Odometry, Pose2D, Status, decode, encode, keys
from schemas.localization import PoseEstimate
from semloc_core.geometry import make_transform, pose2d_to_transform, rotation_about_x, rotation_about_z
from services.bus import query
from services.ros2 import messages as ros
from services.ros2.wire import entity_gid, parse_attachment, topic_key
from tests.service.conftest import hub, procs, session, wait_until  # noqa: F401 - fixtures

pytestmark = pytest.mark.service
STORE = ros.typestore("jazzy")
T = STORE.types
STAMP = 1_700_000_000_000_000_000
T_BASE_CAM = make_transform(rotation_about_z(-math.pi / 2) @ rotation_about_x(-math.pi / 2), (0.2, 0.0, 0.4))


def _start(procs, hub, convention, name="bridge", *settings):
    """The bridge worker; ``settings``: more ``field=value`` settings."""
    return procs.semloc("worker", "ros2", "--connect", hub, "--robot", "r1", "--name", name, "--set",
                        f"convention={convention}", "--set", "status_period_s=0.2", "--set", "path_period_s=0.2",
                        "--set", "topics.image.name=/cam/image_raw", "--set", "topics.camera_info.name=/cam/camera_info",
                        *[arg for setting in settings for arg in ("--set", setting)], "--log-level", "WARNING",
                        name=name)


def _status(session, procs, process, name="bridge"):
    assert process.poll() is None, procs.log(name)
    replies = query(session, keys.status("r1", name), reply_type=Status, timeout=0.5)
    return replies[0] if replies and replies[0].state == "running" else None


def _key(convention, topic, msgtype):
    return topic_key(convention, topic, msgtype, STORE.hash_rihs01(msgtype))


def _odometry(stamp, T_):
    return T[ros.ODOMETRY](
        header=ros.ros_header(STORE, stamp, "odom"), child_frame_id="base_footprint",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=ros.ros_pose(STORE, T_), covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))


@pytest.mark.parametrize("convention", ["rmw_zenoh", "bridge"])
def test_bridge_speaks_ros2(procs, session, hub, convention):
    process = _start(procs, hub, convention)
    wait_until(lambda: _status(session, procs, process), 60, message="bridge running")
    received: dict[str, list] = {"odom": [], "model": [], "image": [], "pose": [], "tf": [], "path": []}
    subscribers = [session.declare_subscriber(key, lambda s, n=name: received[n].append(s)) for name, key in (
        ("odom", keys.odometry("r1")), ("model", keys.camera_model("r1")), ("image", keys.camera_image("r1")),
        ("pose", _key(convention, "/amcl_pose", ros.POSE_WITH_COVARIANCE_STAMPED)),
        ("tf", _key(convention, "/tf", ros.TF_MESSAGE)), ("path", _key(convention, "/semloc/path", ros.PATH)))]
    requests = []

    def set_initial_pose(q):
        requests.append(decode(q.payload.to_bytes(), expected=Pose2D))
        q.reply(q.key_expr, encode(Ack(header=Header(robot="r1", stream="x", stamp_ns=1), ok=True, message="ok")))

    queryable = session.declare_queryable(keys.localizer_set_initial_pose("r1"), set_initial_pose)

    def put(topic, msgtype, msg, sequence=1):
        key = _key(convention, topic, msgtype)
        data = ros.encode_cdr(STORE, msg, msgtype)
        if convention == "rmw_zenoh":
            from services.ros2.wire import attachment

            session.put(key, data, attachment=attachment(sequence, STAMP, bytes(16)))
        else:
            session.put(key, data)

    # TF first (the camera's mount), then odometry, camera info and an image.
    put("/tf_static", ros.TF_MESSAGE, ros.tf_message(STORE, [(0, "base_footprint", "cam", T_BASE_CAM)]))
    odom_poses = [pose2d_to_transform(0.0, 0.0, 0.0), pose2d_to_transform(0.1, 0.02, 0.05),
                  pose2d_to_transform(0.2, 0.05, 0.1)]
    wait_until(lambda: _status(session, procs, process).inputs["ros_tf_static"].processed == 1, 20,
               message="static transform taken")
    for index, T_ in enumerate(odom_poses):
        put("/odom", ros.ODOMETRY, _odometry(STAMP + index * 100_000_000, T_), index + 1)
    K = np.array([[300.0, 0, 15.5], [0, 300.0, 11.5], [0, 0, 1]])
    header = ros.ros_header(STORE, STAMP, "cam")
    put("/cam/camera_info", ros.CAMERA_INFO, T[ros.CAMERA_INFO](
        header=header, height=24, width=32, distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(-1),
        r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
    pixels = np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    put("/cam/image_raw", ros.IMAGE, T[ros.IMAGE](header=header, height=24, width=32, encoding="bgr8",
                                                    is_bigendian=0, step=96, data=pixels.reshape(-1)))
    wait_until(lambda: len(received["odom"]) == 2 and received["model"] and received["image"], 20,
               message=lambda: f"semloc frames from ROS: { {k: len(v) for k, v in received.items()} }")
    odometry = [decode(s.payload.to_bytes(), expected=Odometry) for s in received["odom"]]
    assert [o.header.stamp_ns for o in odometry] == [STAMP + 100_000_000, STAMP + 200_000_000]
    v, v_lateral, omega = ros.planar_twist(odom_poses[1], odom_poses[2], 0.1)
    assert (odometry[1].v, odometry[1].v_lateral, odometry[1].omega, odometry[1].dt) == pytest.approx(
        (v, v_lateral, omega, 0.1))
    model = decode(received["model"][-1].payload.to_bytes(), expected=CameraModel)
    np.testing.assert_allclose(model.cameras[0].K, K)
    np.testing.assert_allclose(model.cameras[0].T_body_cam, T_BASE_CAM, atol=1e-12)  # the mount from TF
    image = decode(received["image"][0].payload.to_bytes(), expected=Image)
    np.testing.assert_array_equal(image.bgr(), pixels)
    assert image.header.stamp_ns == STAMP and image.header.frame_id == "cam"

    # The localizer's estimate at the second odometry stamp -> amcl_pose, map -> odom, path.
    covariance = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.001], [0.0, 0.001, 0.005]])
    estimate_stamp = STAMP + 150_000_000
    estimate = PoseEstimate(header=Header(robot="r1", stream="pose", stamp_ns=estimate_stamp, frame_id="world"),
                            x=3.0, y=-1.0, theta=0.7, covariance=covariance, status="converged", particles=500,
                            effective_sample_size=300.0, mean=np.array([3.0, -1.0, 0.7]), mean_covariance=covariance)
    session.put(keys.localizer_pose("r1"), encode(estimate))
    wait_until(lambda: received["pose"] and received["tf"] and received["path"], 20,
               message=lambda: f"ROS outputs: { {k: len(v) for k, v in received.items()} }")
    sample = received["pose"][0]
    pose = ros.decode_cdr(STORE, sample.payload.to_bytes(), ros.POSE_WITH_COVARIANCE_STAMPED)
    assert ros.stamp_ns(pose.header.stamp) == estimate_stamp and pose.header.frame_id == "map"
    np.testing.assert_allclose(ros.transform_to_pose2d(ros.pose_matrix(pose.pose.pose)), [3.0, -1.0, 0.7])
    np.testing.assert_allclose(pose.pose.covariance.reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])], covariance)
    tf = ros.decode_cdr(STORE, received["tf"][0].payload.to_bytes(), ros.TF_MESSAGE).transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "odom")
    assert ros.stamp_ns(tf.header.stamp) == estimate_stamp + 1_000_000_000  # AMCL's transform_tolerance
    T_odom_base = ros.interpolate(odom_poses[1], odom_poses[2], 0.5)
    np.testing.assert_allclose(ros.transform_matrix(tf.transform) @ T_odom_base,
                               pose2d_to_transform(3.0, -1.0, 0.7), atol=1e-9)
    path = ros.decode_cdr(STORE, received["path"][-1].payload.to_bytes(), ros.PATH)
    assert [ros.stamp_ns(p.header.stamp) for p in path.poses] == [estimate_stamp]

    if convention == "rmw_zenoh":
        tokens = [str(reply.ok.key_expr) for reply in session.liveliness().get("@ros2_lv/0/**", timeout=2.0)]
        pose_token = next(t for t in tokens if "/MP/" in t and "%amcl_pose" in t)
        assert pose_token.endswith(f"/%amcl_pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                                   f"{STORE.hash_rihs01(ros.POSE_WITH_COVARIANCE_STAMPED)}/:1:,1:,:,:,,")
        assert any(t.endswith("/NN/%/%/semloc") for t in tokens)
        assert any("/MS/" in t and "%odom/nav_msgs::msg::dds_::Odometry_/" in t for t in tokens)
        sequence, _, gid = parse_attachment(sample.attachment.to_bytes())
        assert sequence == 1 and gid == entity_gid(pose_token)
    else:
        assert sample.attachment is None

    # /initialpose as RViz sends it -> the localizer's set_initial_pose
    rviz = ros.pose_with_covariance_stamped(STORE, STAMP, "map", 1.0, 2.0, -0.5, np.diag([0.25, 0.25, 0.0685]))
    put("/initialpose", ros.POSE_WITH_COVARIANCE_STAMPED, rviz)
    wait_until(lambda: requests, 20, message="set_initial_pose query")
    assert (requests[0].x, requests[0].y, requests[0].theta) == pytest.approx((1.0, 2.0, -0.5))
    np.testing.assert_allclose(requests[0].covariance, np.diag([0.25, 0.25, 0.0685]))
    status = _status(session, procs, process)
    assert status.errors == 0 and status.rejected == 0, status.last_error
    for entity in subscribers + [queryable]:
        entity.undeclare()


def test_hostile_cdr_is_counted_and_the_bridge_survives(procs, session, hub):
    """1,200 payloads that are not nav_msgs/Odometry (random bytes, truncated and bit-flipped CDR, other types,
    NaN and non-unit orientations, wrong frames, stamps going back) on /odom: each rejected with its reason, none an
    error; the valid odometry sent afterwards is processed."""
    process = _start(procs, hub, "rmw_zenoh", name="victim")
    wait_until(lambda: _status(session, procs, process, "victim"), 60, message="bridge running")
    key = _key("rmw_zenoh", "/odom", ros.ODOMETRY)
    publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: publisher.matching_status.matching, 10, message="subscriber matched")
    good = ros.encode_cdr(STORE, _odometry(STAMP, pose2d_to_transform(1.0, 2.0, 0.3)), ros.ODOMETRY)
    rng = np.random.default_rng(7)

    def with_pose(**changes):
        msg = _odometry(STAMP, np.eye(4))
        for name, value in changes.items():
            setattr(msg.pose.pose.orientation if name in "xyzw" else msg.pose.pose.position, name[-1], value)
        return ros.encode_cdr(STORE, msg, ros.ODOMETRY)

    def framed(frame_id, child):
        msg = _odometry(STAMP, np.eye(4))
        msg.header.frame_id, msg.child_frame_id = frame_id, child
        return ros.encode_cdr(STORE, msg, ros.ODOMETRY)

    makers = {
        "cdr": [lambda: b"\x00\x01\x00\x00" + bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8)),
                lambda: good[: int(rng.integers(0, 40))],
                lambda: b"\x00\x07" + good[2:],  # an encapsulation semloc does not read
                lambda: ros.encode_cdr(STORE, T["std_msgs/msg/String"](data="x" * int(rng.integers(1, 9))),
                                       "std_msgs/msg/String")],
        "size": [lambda: b"\x00\x01\x00\x00" + bytes(65 << 10)],
        "invalid": [lambda: with_pose(pos_x=float("nan")), lambda: with_pose(w=float(rng.uniform(0.1, 0.9))),
                    lambda: with_pose(pos_y=float("inf"))],
        "frame_id": [lambda: framed("map", "base_footprint"), lambda: framed("odom", "camera")],
    }
    bad, expected = [], {}
    order = [(reason, maker) for reason, ms in makers.items() for maker in ms]
    for index in range(1200):
        reason, maker = order[index % len(order)]
        bad.append(maker())
        expected[reason] = expected.get(reason, 0) + 1
    for payload in bad:
        publisher.put(payload)
    publisher.put(good)
    later = ros.encode_cdr(STORE, _odometry(STAMP + 10**8, pose2d_to_transform(1.1, 2.0, 0.3)), ros.ODOMETRY)
    publisher.put(later)
    publisher.put(good)  # going back in time: rejected (stamp)
    expected["stamp"] = 1

    seen = []

    def handled():
        s = _status(session, procs, process, "victim")
        odom = s.inputs["ros_odom"] if s else None
        seen.append(odom)
        return odom if odom and odom.received == len(bad) + 3 and odom.processed + odom.rejected == odom.received \
            else None

    odom = wait_until(handled, 60, message=lambda: f"all handled; last {seen[-1]}")
    assert process.poll() is None
    assert odom.rejected == len(bad) + 1 and odom.processed == 2 and odom.errors == 0
    assert odom.rejected_reasons == expected


def test_static_transforms_from_before_the_bridge(procs, session, hub, tmp_path):
    """/tf_static sent once at the robot's start, before the bridge (or its link) was there: the bridge gets it from
    the publisher's cache as rmw_zenoh's transient-local subscriptions do, and mounts the camera with it."""
    import json

    import zenoh.ext

    from services.bus import BusConfig, open_session
    from services.ros2.wire import attachment

    config = tmp_path / "robot.json5"
    config.write_text(json.dumps({"timestamping": {"enabled": True}}))  # rmw_zenoh's session config has it
    with open_session(BusConfig(connect=[hub], zenoh_config=str(config))) as robot:
        static = zenoh.ext.declare_advanced_publisher(robot, _key("rmw_zenoh", "/tf_static", ros.TF_MESSAGE),
                                                      cache=zenoh.ext.CacheConfig(max_samples=1),
                                                      publisher_detection=True)
        static.put(ros.encode_cdr(STORE, ros.tf_message(STORE, [(0, "base_footprint", "cam", T_BASE_CAM)]),
                                  ros.TF_MESSAGE), attachment=attachment(1, STAMP, bytes(16)))
        process = _start(procs, hub, "rmw_zenoh")
        wait_until(lambda: _status(session, procs, process), 60, message="bridge running")
        static_taken = lambda: [s.inputs["ros_tf_static"].processed for s in query(  # noqa: E731
            session, keys.status("r1", "bridge"), reply_type=Status, timeout=0.5)] == [1]
        wait_until(static_taken, 10, message="the static transform from the robot's cache")
        models = []
        subscriber = session.declare_subscriber(keys.camera_model("r1"), models.append)
        K = np.array([[300.0, 0, 15.5], [0, 300.0, 11.5], [0, 0, 1]])
        info = T[ros.CAMERA_INFO](
            header=ros.ros_header(STORE, STAMP, "cam"), height=24, width=32, distortion_model="plumb_bob",
            d=np.zeros(5), k=K.reshape(-1), r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        robot.put(_key("rmw_zenoh", "/cam/camera_info", ros.CAMERA_INFO), ros.encode_cdr(STORE, info, ros.CAMERA_INFO),
                  attachment=attachment(1, STAMP, bytes(16)))
        wait_until(lambda: models, 10, message="the camera model")
        model = decode(models[-1].payload.to_bytes(), expected=CameraModel)
        np.testing.assert_allclose(model.cameras[0].T_body_cam, T_BASE_CAM, atol=1e-12)  # the mount from TF
        subscriber.undeclare()
        static.undeclare()
