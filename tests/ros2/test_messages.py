"""ROS 2 messages: CDR bytes of every type the bridge speaks round-trip through rosbags, the conversions keep the
values (against the geometry they encode), and bytes or values that are not a message are refused with a reason."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas import FrameError
from semloc_core.geometry import make_transform, pose2d_to_transform, rotation_about_x, rotation_about_z
from services.ros2 import messages as ros

STORE = ros.typestore("jazzy")
T = STORE.types
STAMP = 1_700_000_000_123_456_789


def _roundtrip(msg, msgtype):
    data = ros.encode_cdr(STORE, msg, msgtype)
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    back = ros.decode_cdr(STORE, data, msgtype)
    assert ros.encode_cdr(STORE, back, msgtype) == data
    return back, data


def test_pose_with_covariance_stamped_round_trips_with_amcls_layout():
    covariance = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    msg = ros.pose_with_covariance_stamped(STORE, STAMP, "map", 1.5, -2.0, 2.5, covariance)
    back, data = _roundtrip(msg, ros.POSE_WITH_COVARIANCE_STAMPED)
    # CDR by hand: encapsulation 4 + stamp 8 + frame id (length 4, "map\\0" 4) + pose 7 x 8 + covariance 36 x 8
    assert len(data) == 4 + 8 + 4 + 4 + 56 + 288
    assert ros.stamp_ns(back.header.stamp) == STAMP and back.header.frame_id == "map"
    full = back.pose.covariance.reshape(6, 6)
    np.testing.assert_allclose(full[np.ix_([0, 1, 5], [0, 1, 5])], covariance)
    assert np.count_nonzero(full) == np.count_nonzero(covariance)
    x, y, theta = ros.transform_to_pose2d(ros.pose_matrix(back.pose.pose))
    assert (x, y) == pytest.approx((1.5, -2.0)) and theta == pytest.approx(2.5)


def test_initial_pose_reads_what_rviz_sends():
    covariance = np.diag([0.25, 0.25, 0.0685])
    msg = ros.pose_with_covariance_stamped(STORE, STAMP, "map", 0.3, 0.4, -1.0, covariance)
    x, y, theta, cov = ros.initial_pose(_roundtrip(msg, ros.POSE_WITH_COVARIANCE_STAMPED)[0], "map")
    assert (x, y, theta) == pytest.approx((0.3, 0.4, -1.0))
    np.testing.assert_allclose(cov, covariance)
    with pytest.raises(FrameError) as error:
        ros.initial_pose(msg, "odom")
    assert error.value.reason == "frame_id"


def test_tf_message_round_trips_and_the_buffer_chains_and_interpolates():
    T_odom_base = [pose2d_to_transform(0.0, 0.0, 0.0), pose2d_to_transform(1.0, 0.0, math.pi / 2)]
    T_base_cam = make_transform(rotation_about_x(-math.pi / 2) @ rotation_about_z(-math.pi / 2), (0.1, 0, 0.5))
    buffer = ros.TransformBuffer()
    for index, T_ in enumerate(T_odom_base):
        msg = ros.tf_message(STORE, [(STAMP + index * 10**9, "odom", "base_footprint", T_)])
        buffer.add_message(_roundtrip(msg, ros.TF_MESSAGE)[0])
    buffer.add_message(ros.tf_message(STORE, [(0, "base_footprint", "camera", T_base_cam)]), static=True)
    halfway = buffer.lookup("odom", "base_footprint", STAMP + 5 * 10**8)
    np.testing.assert_allclose(ros.transform_to_pose2d(halfway), [0.5, 0.0, math.pi / 4], atol=1e-9)
    np.testing.assert_allclose(buffer.lookup("odom", "camera", STAMP + 10**9), T_odom_base[1] @ T_base_cam,
                               atol=1e-9)
    np.testing.assert_allclose(buffer.lookup("camera", "odom", STAMP), np.linalg.inv(T_base_cam), atol=1e-9)
    assert buffer.lookup("odom", "base_footprint", STAMP + 2 * 10**9) is None  # no extrapolation
    assert buffer.lookup("odom", "map", STAMP) is None  # not connected


def test_planar_twist_is_what_the_localizers_odometry_integrates_back():
    from semloc_core.localization.motion import Odometry as Increment

    T0, T1 = pose2d_to_transform(1.0, 2.0, 0.3), pose2d_to_transform(1.4, 2.1, 0.9)
    v, v_lateral, omega = ros.planar_twist(T0, T1, 0.5)
    step = Increment.from_twist(v, v_lateral, omega, 0.5)
    c, s = math.cos(0.3), math.sin(0.3)
    np.testing.assert_allclose([1.0 + c * step.dx - s * step.dy, 2.0 + s * step.dx + c * step.dy, 0.3 + step.dtheta],
                               [1.4, 2.1, 0.9], atol=1e-12)


def test_path_and_markers_round_trip():
    poses = [(STAMP + i, 0.1 * i, -0.2 * i, 0.05 * i) for i in range(5)]
    path, _ = _roundtrip(ros.path_message(STORE, STAMP, "map", poses), ros.PATH)
    assert [ros.stamp_ns(p.header.stamp) for p in path.poses] == [p[0] for p in poses]
    assert [p.pose.position.x for p in path.poses] == pytest.approx([p[1] for p in poses])
    markers, _ = _roundtrip(ros.object_markers(STORE, STAMP, "map", ("bowl", "cap"), np.array([1, 0, 1]),
                                               np.array([[0.5, 0.2, 0.8], [1.0, 1.0, 0.8], [0, -1, 0.75]]),
                                               np.full((3, 3), 0.1), np.array([1.0, 0.5, 0.2])), ros.MARKER_ARRAY)
    Marker = T["visualization_msgs/msg/Marker"]
    assert markers.markers[0].action == Marker.DELETEALL
    cubes = [m for m in markers.markers[1:] if m.type == Marker.CUBE]
    assert [m.pose.position.y for m in cubes] == pytest.approx([0.2, 1.0, -1.0])
    assert [m.text for m in markers.markers if m.type == Marker.TEXT_VIEW_FACING] == ["cap", "bowl", "cap"]
    topo, _ = _roundtrip(ros.topomap_markers(STORE, STAMP, "map", {0: (0, 0), 2: (1, 1)}, [(0, 2), (0, 1)]),
                         ros.MARKER_ARRAY)
    assert len(topo.markers[1].points) == 2 and len(topo.markers[2].points) == 2  # edge (0, 1): node 1 unplaced


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_images_and_camera_info_convert(encoding):
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, 256, (6, 8, 3 if encoding != "mono8" else 1), dtype=np.uint8).squeeze()
    header = ros.ros_header(STORE, STAMP, "camera")
    data = pixels[..., ::-1] if encoding == "rgb8" else pixels
    msg = T[ros.IMAGE](header=header, height=6, width=8, encoding=encoding, is_bigendian=0,
                       step=8 * (1 if encoding == "mono8" else 3), data=np.ascontiguousarray(data).reshape(-1))
    image = ros.image_pixels(ros.IMAGE, _roundtrip(msg, ros.IMAGE)[0])
    np.testing.assert_array_equal(image, pixels if encoding != "mono8" else np.repeat(pixels[..., None], 3, 2))
    K = np.array([[500.0, 0, 4.0], [0, 500.0, 3.0], [0, 0, 1]])
    info = T[ros.CAMERA_INFO](header=header, height=6, width=8, distortion_model="plumb_bob",
                              d=np.array([0.1, -0.05, 0, 0, 0]), k=K.reshape(-1), r=np.eye(3).reshape(-1),
                              p=np.zeros(12), binning_x=0, binning_y=0,
                              roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                        do_rectify=False))
    camera = ros.camera_from_info(_roundtrip(info, ros.CAMERA_INFO)[0], np.eye(4))
    np.testing.assert_array_equal(camera.K, K)
    np.testing.assert_array_equal(camera.dist, [0.1, -0.05, 0, 0, 0])


def test_an_equidistant_camera_info_is_a_fisheye_camera():
    """A fisheye's CameraInfo (``equidistant``, as ROS's camera_calibration and drivers write it) gives the camera
    OpenCV's fisheye model describes (it was refused: a fisheye robot had no camera model)."""
    import cv2

    K = np.array([[230.0, 0, 321.3], [0, 229.0, 238.4], [0, 0, 1]])
    D = np.array([0.03, -0.012, 0.004, -0.001])
    info = T[ros.CAMERA_INFO](header=ros.ros_header(STORE, STAMP, "camera"), height=480, width=640,
                              distortion_model="equidistant", d=D, k=K.reshape(-1), r=np.eye(3).reshape(-1),
                              p=np.zeros(12), binning_x=0, binning_y=0,
                              roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                        do_rectify=False))
    camera = ros.camera_from_info(_roundtrip(info, ros.CAMERA_INFO)[0], np.eye(4))
    rays = np.array([[0.0, 0.0, 1.0], [math.sin(1.3), 0.0, math.cos(1.3)], [0.3, -0.4, 0.6]])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    pixels, _ = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    np.testing.assert_allclose(camera.rays_cam(*pixels.reshape(-1, 2).T), rays, atol=1e-7)


@pytest.mark.parametrize("extension", [".png", ".jpg"])
def test_compressed_image_converts(extension):
    import cv2

    pixels = np.zeros((16, 24, 3), np.uint8)
    pixels[4:12, 4:12] = (0, 0, 255)
    data = cv2.imencode(extension, pixels)[1].reshape(-1)
    assert ros.encoded_size(data.tobytes()) == (24, 16)
    msg = T[ros.COMPRESSED_IMAGE](header=ros.ros_header(STORE, STAMP, "camera"), format=extension[1:], data=data)
    decoded = ros.image_pixels(ros.COMPRESSED_IMAGE, _roundtrip(msg, ros.COMPRESSED_IMAGE)[0])
    if extension == ".png":
        np.testing.assert_array_equal(decoded, pixels)
    else:
        assert decoded.shape == pixels.shape and np.abs(decoded.astype(int) - pixels).mean() < 8


def test_a_compressed_image_claiming_gigapixels_is_refused_before_decoding():
    import cv2

    png = bytearray(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes())
    png[16:24] = (60000).to_bytes(4, "big") * 2
    msg = T[ros.COMPRESSED_IMAGE](header=ros.ros_header(STORE, STAMP, "camera"), format="png",
                                  data=np.frombuffer(bytes(png), np.uint8))
    with pytest.raises(FrameError, match="60000x60000") as error:
        ros.image_pixels(ros.COMPRESSED_IMAGE, msg)
    assert error.value.reason == "invalid"


@pytest.mark.parametrize("payload, reason", [
    (b"", "cdr"), (b"\x00\x01\x00\x00", "cdr"), (b"\x00\x07\x00\x00" + bytes(64), "cdr"),
    (b"\x00\x01\x00\x00" + bytes(3), "cdr"), (b"\x00\x01\x00\x00" + bytes(70 << 10), "size"),
])
def test_bytes_that_are_not_the_message_are_refused(payload, reason):
    with pytest.raises(FrameError) as error:
        ros.decode_cdr(STORE, payload, ros.ODOMETRY)
    assert error.value.reason == reason


def test_values_out_of_range_are_refused():
    pose = ros.ros_pose(STORE, np.eye(4))
    pose.orientation.w = 0.5
    with pytest.raises(FrameError, match="unit quaternion"):
        ros.pose_matrix(pose)
    pose.orientation.w, pose.position.x = 1.0, float("nan")
    with pytest.raises(FrameError, match="not finite"):
        ros.pose_matrix(pose)
    bad = T[ros.IMAGE](header=ros.ros_header(STORE, 1, "c"), height=4, width=4, encoding="rgb8", is_bigendian=0,
                       step=12, data=np.zeros(10, np.uint8))
    with pytest.raises(FrameError) as error:
        ros.image_pixels(ros.IMAGE, bad)
    assert error.value.reason == "encoding"


@pytest.mark.parametrize("state, expected_xx", [(None, 0.01), ("localized", 0.01), ("uncertain", 0.25),
                                                ("lost", 100.0)])
def test_published_covariance_follows_the_localizer_state(state, expected_xx):
    """What ROS consumers gating on the covariance see: the hypothesis's when localized, the whole particle set's
    (other hypotheses included) when uncertain, at least the lost variance when lost; positive semi-definite."""
    from schemas import Header
    from schemas.localization import PoseEstimate
    from services.workers.ros2 import published_covariance

    frame = PoseEstimate(header=Header(robot="r"), x=1.0, y=2.0, theta=0.1, covariance=np.diag([0.01, 0.02, 0.003]),
                         status="converged", state=state, particles=100, effective_sample_size=50.0,
                         mean=np.array([1.0, 2.0, 0.1]), mean_covariance=np.diag([0.25, 0.36, 0.5]))
    covariance = published_covariance(frame, lost_variance=100.0)
    assert covariance[0, 0] == pytest.approx(expected_xx)
    assert np.linalg.eigvalsh(covariance).min() >= 0
    msg = ros.pose_with_covariance_stamped(STORE, STAMP, "map", frame.x, frame.y, frame.theta, covariance)
    assert msg.pose.covariance[0] == pytest.approx(expected_xx)
