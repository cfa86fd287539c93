"""A ROS 2 robot log of a simulated data set, written with rosbags' own writer: what a robot running the camera,
its driver and a wheel odometry would have recorded with `ros2 bag record`.

Topics: ``/camera/image_raw`` (sensor_msgs/Image, rgb8), ``/camera/camera_info`` (plumb_bob, no distortion),
``/odom`` (nav_msgs/Odometry of the data set's noisy odometry integrated from the origin), ``/tf`` (``odom ->
base_footprint`` from the same odometry, and ``base_footprint -> camera_optical``: the hand-held camera's attitude
at each image), ``/ground_truth/odom`` (the true base pose in ``map``). Stamps: the data set's, shifted to a
plausible epoch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from semloc_core.geometry import make_transform, rotation_about_z
from semloc_core.io.dataset import open_dataset
from services.ros2 import messages as ros

EPOCH_NS = 1_700_000_000_000_000_000
CAMERA_FRAME = "camera_optical"


def odometry_poses(dataset) -> np.ndarray:
    """(N, 4, 4) odom -> base poses: the data set's odometry increments chained from the origin."""
    poses = dataset.odometry.integrate((0.0, 0.0, 0.0))
    return np.stack([make_transform(rotation_about_z(t), (x, y, 0.0)) for x, y, t in poses])


def write_ros2_bag(dataset_dir: Path, out: Path, distro: str = "jazzy", storage: str = "sqlite3") -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = ros.typestore(distro)
    types = store.types
    dataset = open_dataset(dataset_dir)
    camera = dataset.camera
    stamps = [EPOCH_NS + int(s) for s in dataset.stamps_ns]
    odom = odometry_poses(dataset)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        def connection(topic, msgtype):
            return writer.add_connection(topic, msgtype, typestore=store)

        image_c, info_c = connection("/camera/image_raw", ros.IMAGE), connection("/camera/camera_info", ros.CAMERA_INFO)
        odom_c, tf_c = connection("/odom", ros.ODOMETRY), connection("/tf", ros.TF_MESSAGE)
        truth_c = connection("/ground_truth/odom", ros.ODOMETRY)

        def write(conn, stamp, msg, msgtype):
            writer.write(conn, stamp, ros.encode_cdr(store, msg, msgtype))

        def odometry_msg(stamp, frame, child, T):
            pose = types["geometry_msgs/msg/PoseWithCovariance"](pose=ros.ros_pose(store, T),
                                                                 covariance=np.zeros(36))
            twist = types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                       angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36))
            return types[ros.ODOMETRY](header=ros.ros_header(store, stamp, frame), child_frame_id=child, pose=pose,
                                       twist=twist)

        for index, stamp in enumerate(stamps):
            T_body_cam = dataset.T_body_cam[index] if dataset.T_body_cam is not None else camera.T_body_cam
            write(tf_c, stamp, ros.tf_message(store, [(stamp, "odom", "base_footprint", odom[index]),
                                                      (stamp, "base_footprint", CAMERA_FRAME, T_body_cam)]),
                  ros.TF_MESSAGE)
            write(odom_c, stamp, odometry_msg(stamp, "odom", "base_footprint", odom[index]), ros.ODOMETRY)
            write(truth_c, stamp, odometry_msg(stamp, "map", "base_footprint", dataset.T_world_body[index]),
                  ros.ODOMETRY)
            rgb = np.ascontiguousarray(dataset.image(index)[..., ::-1])
            header = ros.ros_header(store, stamp, CAMERA_FRAME)
            write(image_c, stamp, types[ros.IMAGE](header=header, height=rgb.shape[0], width=rgb.shape[1],
                                                   encoding="rgb8", is_bigendian=0, step=rgb.shape[1] * 3,
                                                   data=rgb.reshape(-1)), ros.IMAGE)
            info = types[ros.CAMERA_INFO](
                header=header, height=camera.height, width=camera.width, distortion_model="plumb_bob",
                d=np.zeros(5), k=camera.K.reshape(-1), r=np.eye(3).reshape(-1),
                p=np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1), binning_x=0, binning_y=0,
                roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                              do_rectify=False))
            write(info_c, stamp, info, ros.CAMERA_INFO)
    return out
