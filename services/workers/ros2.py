"""ROS 2 bridge: a ROS 2 robot's topics in, the localizer's answer out, over zenoh (rmw_zenoh or
zenoh-bridge-ros2dds; docs/ros2.md).

In (CDR, each checked at the boundary; a malformed payload is rejected with its reason and counted):
``sensor_msgs/Image`` or ``CompressedImage`` -> semloc ``Image``; ``CameraInfo`` (mounted where TF puts its frame on
the base) -> ``CameraModel``; ``nav_msgs/Odometry`` or ``tf2_msgs/TFMessage`` (``odom -> base``) -> ``Odometry``;
``/initialpose`` (RViz's "2D Pose Estimate", nav2's topic) -> the localizer's ``set_initial_pose``.
Out: the localizer's ``PoseEstimate`` -> ``geometry_msgs/PoseWithCovarianceStamped`` (covariance of the reported
hypothesis of the particle set) and the ``map -> odom`` transform on ``/tf`` (as nav2 AMCL publishes them); the
mapper's object map and the loop closure's topological map -> ``visualization_msgs/MarkerArray``; the estimates ->
``nav_msgs/Path``.
"""

from __future__ import annotations

import collections
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas import Ack, CameraModel, FrameError, Image, Odometry, Pose2D, camera_image, keys
from schemas.localization import PoseEstimate
from schemas.loopclosure import TopoMap
from schemas.mapping import ANY_OBJECT_MAP
from semloc_core.camera import forward_extrinsic
from semloc_core.geometry import invert_transform, pose2d_to_transform
from services.bus import QueryError, query
from services.frames import STREAM_RESTART_S, camera_model_frame, restarted
from services.ros2 import messages as ros
from services.ros2.wire import (QoS, RosPublisher, check_topic, endpoint_token, entity_gid, node_token,
                                parse_attachment, topic_key)
from services.runtime import Worker, WorkerConfig, one_line


class TopicSettings(BaseModel):
    """One ROS topic: its name (relative names go under ``namespace``; empty: not bridged) and QoS."""

    model_config = ConfigDict(extra="forbid")

    name: str
    reliability: Literal["reliable", "best_effort"] = "reliable"
    durability: Literal["volatile", "transient_local"] = "volatile"
    depth: int = Field(10, ge=1, le=10_000)

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        return check_topic(value) if value else value

    def qos(self) -> QoS:
        return QoS(self.reliability, self.durability, "keep_last", self.depth)


def _topic(name: str, **qos) -> Field:
    return Field(default_factory=lambda: TopicSettings(name=name, **qos))


class RosTopics(BaseModel):
    """The topic table, with nav2's names and QoS where nav2 has the topic."""

    model_config = ConfigDict(extra="forbid")

    image: TopicSettings = _topic("/camera/image_raw", reliability="best_effort", depth=5)
    camera_info: TopicSettings = _topic("/camera/camera_info", reliability="best_effort", depth=5)
    odom: TopicSettings = _topic("/odom")
    tf: TopicSettings = _topic("/tf", depth=100)
    tf_static: TopicSettings = _topic("/tf_static", durability="transient_local", depth=100)
    initialpose: TopicSettings = _topic("/initialpose", depth=1)
    pose: TopicSettings = _topic("/amcl_pose", durability="transient_local", depth=1)
    objects: TopicSettings = _topic("/semloc/objects", durability="transient_local", depth=1)
    topomap: TopicSettings = _topic("/semloc/topomap", durability="transient_local", depth=1)
    path: TopicSettings = _topic("/semloc/path", depth=1)

    @model_validator(mode="before")
    @classmethod
    def _over_role_defaults(cls, data):
        """A role given in part (``--set topics.image.name=/oak/rgb/image_raw``) keeps its role's other defaults
        (the image's best effort, depth 5), not TopicSettings' own: the QoS in its token is the robot's."""
        if not isinstance(data, dict):
            return data
        return {role: {**cls.model_fields[role].default_factory().model_dump(), **value}
                if role in cls.model_fields and isinstance(value, dict) else value for role, value in data.items()}


class Ros2Config(WorkerConfig):
    convention: Literal["rmw_zenoh", "bridge"] = Field("rmw_zenoh", description="rmw_zenoh (ROS 2 on zenoh) or "
                                                       "bridge (zenoh-bridge-ros2dds next to a DDS robot)")
    distro: Literal["humble", "jazzy", "kilted"] = Field("jazzy", description="the robot's ROS 2 distribution "
                                                         "(message definitions and type hashes)")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh)")
    namespace: str = Field("", description="ROS namespace of the node and of relative topic names")
    node_name: str = Field("semloc", description="ROS node name (rmw_zenoh graph)")
    topics: RosTopics = Field(default_factory=RosTopics)
    compressed_images: bool = Field(False, description="the image topic is sensor_msgs/CompressedImage")
    odometry_from: Literal["odom", "tf", "none"] = Field("odom", description="motion from the odometry topic, from "
                                                         "TF (odom_frame -> base_frame), or none")
    map_frame: str = Field("map", description="global frame of the estimates (nav2 AMCL global_frame_id)")
    odom_frame: str = Field("odom", description="odometry frame (AMCL odom_frame_id)")
    base_frame: str = Field("base_footprint", description="robot base frame (AMCL base_frame_id)")
    publish_tf: bool = Field(True, description="publish map -> odom on /tf (AMCL tf_broadcast)")
    transform_tolerance_s: float = Field(1.0, ge=0, description="map -> odom is future-dated by this (AMCL)")
    camera: str = Field("front", description="semloc camera name of the images")
    camera_height: float = Field(0.0, description="without TF from base to camera: a level camera this high")
    model_period_s: float = Field(1.0, gt=0, description="CameraModel republication period")
    markers_period_s: float = Field(2.0, gt=0, description="object / topological map markers republication period")
    path_period_s: float = Field(1.0, gt=0, description="Path publication period")
    path_length: int = Field(10_000, ge=1, description="poses kept in the Path")
    query_timeout_s: float = Field(2.0, gt=0, description="how long /initialpose waits for the localizer")
    ros_silence_s: float | None = Field(5.0, gt=0, description="degraded when no ROS input (images, camera info, "
                                        "odometry, TF) arrived for this long: the robot, its router or the link is "
                                        "away; None: never")
    lost_variance: float = Field(100.0, gt=0, description="a lost estimate's published x, y (m²) and yaw (rad²) "
                                 "variances are at least this: consumers that gate on the covariance ignore it")


class Ros2(Worker):
    """Bridges a ROS 2 robot: images, camera info, odometry and /initialpose in; pose, map -> odom, maps out."""

    Config = Ros2Config
    # until setup: the status may be asked before
    robot_silent, robot_silences, robot_silent_s, odometry_restarts = False, 0, 0.0, 0

    def setup(self) -> None:
        c = self.config
        self.store = ros.typestore(c.distro)
        self.tf = ros.TransformBuffer()
        self.session_id = str(self.session.zid())
        self.tokens = [] if c.convention != "rmw_zenoh" else [
            self.session.liveliness().declare_token(node_token(c.domain_id, self.session_id, 0, c.node_name,
                                                               c.namespace))]
        self.entities = 0
        self.camera_model = None
        self.last_odom: tuple[int, np.ndarray] | None = None
        self.odom_source: bytes | None = None  # the odometry publisher's GID (rmw_zenoh), once known
        self.path: collections.deque = collections.deque(maxlen=c.path_length)
        self.object_markers = self.topomap_markers = None
        self.topomap: TopoMap | None = None
        # The robot heard from: ROS samples received (rejected ones too: the robot is there), when that last grew,
        # whether it has been silent longer than ros_silence_s, how often and how long in all.
        self.ros_inputs: list = []
        self.ros_received, self.ros_heard_at = 0, time.monotonic()
        self.robot_silent = False
        self.robot_silences, self.robot_silent_s = 0, 0.0
        # semloc side
        robot = self.robot
        self.images = self.output("image", keys.camera_image(robot, c.camera), Image, bulk=True)
        self.model_out = self.output("model", keys.camera_model(robot, c.camera), CameraModel)
        self.odom_out = self.output("odometry", keys.odometry(robot), Odometry)
        self.queryable("model_query", self.model_out.key, lambda _request: self._model_frame())
        self.input("estimate", keys.localizer_pose(robot), PoseEstimate, self.on_estimate, policy="lossless")
        self.latest_input("objects", keys.mapper_objects(robot), ANY_OBJECT_MAP, self.on_objects,
                          query_key=keys.mapper_map(robot))
        self.input("topomap", keys.loopclosure_topomap(robot), TopoMap, self.on_topomap, policy="latest", depth=1)
        # ROS side
        t = c.topics
        image_type = ros.COMPRESSED_IMAGE if c.compressed_images else ros.IMAGE
        self._subscribe("ros_image", t.image, image_type, self.on_image, "latest", 2)
        self._subscribe("ros_camera_info", t.camera_info, ros.CAMERA_INFO, self.on_camera_info, "latest", 1)
        if c.odometry_from == "odom":
            self._subscribe("ros_odom", t.odom, ros.ODOMETRY, self.on_odometry, "lossless", 1024, source=True)
        self._subscribe("ros_tf", t.tf, ros.TF_MESSAGE, self.on_tf, "lossless", 1024,
                        source=c.odometry_from == "tf")
        self._subscribe("ros_tf_static", t.tf_static, ros.TF_MESSAGE, self.on_tf_static, "lossless", 64)
        self._subscribe("ros_initialpose", t.initialpose, ros.POSE_WITH_COVARIANCE_STAMPED, self.on_initial_pose,
                        "lossless", 16)
        self.pose_pub = self._advertise("ros_pose", t.pose, ros.POSE_WITH_COVARIANCE_STAMPED)
        self.tf_pub = self._advertise("ros_tf", t.tf, ros.TF_MESSAGE) if c.publish_tf else None
        self.objects_pub = self._advertise("ros_objects", t.objects, ros.MARKER_ARRAY)
        self.topomap_pub = self._advertise("ros_topomap", t.topomap, ros.MARKER_ARRAY)
        self.path_pub = self._advertise("ros_path", t.path, ros.PATH)
        self.every(c.model_period_s, self._publish_model)
        self.every(c.markers_period_s, self._publish_markers)
        self.every(c.path_period_s, self._publish_path)
        if c.ros_silence_s and self.ros_inputs:
            self.every(min(1.0, c.ros_silence_s / 4), self._watch_robot)

    # ------------------------------------------------------------------ ROS endpoints
    def _key(self, topic: TopicSettings, msgtype: str, publish: bool) -> str:
        c = self.config
        type_hash = self.store.hash_rihs01(msgtype) if publish else ""  # subscriptions accept any distribution's
        return topic_key(c.convention, topic.name, msgtype, type_hash, c.domain_id, c.namespace)

    def _token(self, kind: str, topic: TopicSettings, msgtype: str) -> str:
        c = self.config
        self.entities += 1
        return endpoint_token(kind, c.domain_id, self.session_id, 0, self.entities, c.node_name, topic.name, msgtype,
                              self.store.hash_rihs01(msgtype), topic.qos(), c.namespace)

    def _subscribe(self, name: str, topic: TopicSettings, msgtype: str, handler, policy: str, depth: int,
                   source: bool = False) -> None:
        """``source``: ``handler(msg, gid)`` with the publisher's GID from rmw_zenoh's attachment (None without one),
        which tells a rebooted robot's new publisher from the same one heard again."""
        if not topic.name:
            return
        if self.config.convention == "rmw_zenoh":
            self.tokens.append(self.session.liveliness().declare_token(self._token("MS", topic, msgtype)))
        store = self.store
        # As rmw_zenoh's transient-local subscriptions: what the robot published before this subscriber (or its
        # link) was there comes from the publishers' caches - /tf_static sent once at the robot's start.
        cached = self.config.convention == "rmw_zenoh" and topic.durability == "transient_local"

        def decoder(payload: bytes, attached: bytes | None = None):
            msg = ros.decode_cdr(store, payload, msgtype)
            return (msg, publisher_gid(attached)) if source else msg

        self.ros_inputs.append(self.input(name, self._key(topic, msgtype, publish=False), None,
                                          (lambda item: handler(*item)) if source else handler, policy=policy,
                                          depth=depth, decoder=decoder, cached=cached, attachment=source))

    def _advertise(self, name: str, topic: TopicSettings, msgtype: str) -> RosPublisher | None:
        if not topic.name:
            return None
        gid = bytes(16)
        if self.config.convention == "rmw_zenoh":
            token = self._token("MP", topic, msgtype)
            self.tokens.append(self.session.liveliness().declare_token(token))
            gid = entity_gid(token)
        publisher = RosPublisher(self.session, name, self._key(topic, msgtype, publish=True), self.config.convention,
                                 topic.qos(), gid, self.logger)
        self._outputs.append(publisher)  # counted in the status like the worker's own outputs
        return publisher

    def _put(self, publisher: RosPublisher | None, msg, msgtype: str) -> None:
        if publisher is not None:
            publisher.put(ros.encode_cdr(self.store, msg, msgtype))

    # ------------------------------------------------------------------ the robot's presence
    def _watch_robot(self) -> None:
        """Silent: no ROS sample for ``ros_silence_s`` (counted, logged); heard again: running again."""
        now, received = time.monotonic(), sum(entry.received for entry in self.ros_inputs)
        if received != self.ros_received:
            if self.robot_silent:
                self.robot_silent = False
                self.robot_silent_s += now - self.ros_heard_at
                self.logger.warning("ROS input again after %.1f s", now - self.ros_heard_at)
            self.ros_received, self.ros_heard_at = received, now
        elif not self.robot_silent and now - self.ros_heard_at > self.config.ros_silence_s:
            self.robot_silent = True
            self.robot_silences += 1
            self.logger.warning("%s", self._silence())

    def _silence(self) -> str:
        heard = "for" if self.ros_received else "since the start,"
        return (f"no ROS input {heard} {time.monotonic() - self.ros_heard_at:.0f} s: the robot, its router or the "
                f"link to it is away")

    def health(self, *args, **kwargs) -> tuple[str, str]:
        """The runtime's, and a silent robot among the reasons (degraded)."""
        state, reason = super().health(*args, **kwargs)
        if state in ("running", "degraded") and self.robot_silent:
            silence = self._silence()
            return "degraded", one_line(f"{silence}; {reason}" if reason else silence)
        return state, reason

    def status_details(self) -> dict:
        ongoing = time.monotonic() - self.ros_heard_at if self.robot_silent else 0.0
        return {"robot_silences": self.robot_silences, "robot_silent_s": round(self.robot_silent_s + ongoing, 1),
                "odometry_restarts": self.odometry_restarts}

    # ------------------------------------------------------------------ ROS -> semloc
    def on_image(self, msg) -> None:
        msgtype = ros.COMPRESSED_IMAGE if self.config.compressed_images else ros.IMAGE
        pixels = ros.image_pixels(msgtype, msg)
        stamp = ros.stamp_ns(msg.header.stamp)
        header = self.images.header(stamp_ns=stamp, frame_id=str(msg.header.frame_id)[:128])
        self.images.publish(Image(header=header, images=[camera_image(pixels)]))

    def on_camera_info(self, msg) -> None:
        c = self.config
        camera_frame = str(msg.header.frame_id).lstrip("/")
        T_body_cam = self.tf.lookup(c.base_frame, camera_frame, ros.stamp_ns(msg.header.stamp)) if camera_frame \
            else None
        camera = ros.camera_from_info(msg, forward_extrinsic(c.camera_height) if T_body_cam is None else T_body_cam)
        changed = self.camera_model is None or not _same_camera(self.camera_model, camera)
        self.camera_model = camera
        if changed:
            self.logger.info("camera model from %s: %dx%d, T_body_cam from %s", self.config.topics.camera_info.name,
                             camera.width, camera.height, "TF" if T_body_cam is not None else "camera_height")
            self._publish_model()

    def on_odometry(self, msg, source: bytes | None = None) -> None:
        c = self.config
        for frame, expected in ((msg.header.frame_id, c.odom_frame), (msg.child_frame_id, c.base_frame)):
            if str(frame).lstrip("/") != expected:
                raise FrameError(f"odometry of {msg.child_frame_id!r} in {msg.header.frame_id!r}, expected "
                                 f"{c.base_frame!r} in {c.odom_frame!r}", reason="frame_id")
        stamp = ros.stamp_ns(msg.header.stamp)
        T = ros.pose_matrix(msg.pose.pose, "odometry")
        self._odometry_source(source, stamp)
        self.tf.add(c.odom_frame, c.base_frame, stamp, T)
        self._odometry_at(stamp, T)

    def on_tf(self, msg, source: bytes | None = None) -> None:
        c = self.config
        if c.odometry_from == "tf":
            # the odometry's own transforms (odom -> the base, or the first frame on the way to it) tell its source
            chain = self.tf.edges(c.odom_frame, c.base_frame) or [c.base_frame]
            stamps = [ros.stamp_ns(t.header.stamp) for t in msg.transforms
                      if t.header.frame_id.lstrip("/") == c.odom_frame and t.child_frame_id.lstrip("/") in chain]
            if stamps:
                self._odometry_source(source, min(stamps))
        self.tf.add_message(msg)
        if c.odometry_from != "tf":
            return
        for transform in msg.transforms:
            stamp = ros.stamp_ns(transform.header.stamp)
            T = self.tf.lookup(c.odom_frame, c.base_frame, stamp)
            if T is not None:
                self._odometry_at(stamp, T)

    def on_tf_static(self, msg) -> None:
        self.tf.add_message(msg, static=True)

    def _odometry_source(self, source: bytes | None, stamp: int) -> None:
        """A restarted odometry source - another publisher GID (a rebooted robot, its odometry from zero again), or
        stamps more than STREAM_RESTART_S back (a clock restarted behind; all that zenoh-bridge-ros2dds shows) -
        starts the chain afresh at this sample: no twist across the restart (a jump the robot never made), its
        stamps taken though behind the old chain's; counted and logged."""
        known, previous = self.odom_source, self.last_odom
        self.odom_source = source or known
        if previous is None:
            return
        if source is not None and known is not None and source != known:
            why = f"a new publisher, GID {source.hex()[:8]}"
        elif restarted(previous[0], stamp):
            why = f"stamps {(previous[0] - stamp) * 1e-9:.1f} s behind the last (more than {STREAM_RESTART_S:g} s)"
        else:
            return
        c = self.config
        self.last_odom = None
        self.tf.forget(c.odom_frame, c.base_frame)
        self.odometry_restarts += 1
        n = self.odometry_restarts
        if n <= 10 or n == 10 ** (len(str(n)) - 1):
            self.logger.warning("odometry restarted (%s): no motion published across it, the odometry starts "
                                "afresh (%d restart(s) so far)", why, n)

    def _odometry_at(self, stamp: int, T_odom_base: np.ndarray) -> None:
        """semloc Odometry: the constant twist from the previous odometry pose to this one."""
        previous, self.last_odom = self.last_odom, (stamp, T_odom_base)
        if previous is None or stamp == previous[0]:
            return
        if stamp < previous[0]:
            self.last_odom = previous
            raise FrameError(f"odometry stamp {stamp} before the previous one {previous[0]}", reason="stamp")
        dt = (stamp - previous[0]) * 1e-9
        v, v_lateral, omega = ros.planar_twist(previous[1], T_odom_base, dt)
        header = self.odom_out.header(stamp_ns=stamp, frame_id="body")
        self.odom_out.publish(Odometry(header=header, v=v, v_lateral=v_lateral, omega=omega, dt=min(dt, 3600.0)))

    def on_initial_pose(self, msg) -> None:
        x, y, theta, covariance = ros.initial_pose(msg, self.config.map_frame)
        header = self.odom_out.header(stamp_ns=ros.stamp_ns(msg.header.stamp), frame_id="world")
        request = Pose2D(header=header, x=x, y=y, theta=theta, covariance=0.5 * (covariance + covariance.T))
        try:
            replies = query(self.session, keys.localizer_set_initial_pose(self.robot), request, reply_type=Ack,
                            timeout=self.config.query_timeout_s)
        except (QueryError, FrameError) as error:
            self.logger.warning("initial pose: %s", error)
            return
        if not replies:
            self.logger.warning("initial pose (%.2f, %.2f, %.2f): no localizer answered", x, y, theta)
        else:
            self.logger.info("initial pose (%.2f, %.2f, %.2f): %s", x, y, theta, replies[0].message)

    # ------------------------------------------------------------------ semloc -> ROS
    def on_estimate(self, frame: PoseEstimate) -> None:
        c = self.config
        stamp = frame.header.stamp_ns
        msg = ros.pose_with_covariance_stamped(self.store, stamp, c.map_frame, frame.x, frame.y, frame.theta,
                                               published_covariance(frame, c.lost_variance))
        self._put(self.pose_pub, msg, ros.POSE_WITH_COVARIANCE_STAMPED)
        self.path.append((stamp, frame.x, frame.y, frame.theta))
        if self.tf_pub is not None:
            T_odom_base = self.tf.lookup(c.odom_frame, c.base_frame, stamp)
            if T_odom_base is not None:
                # map -> odom = T_map_base · T_odom_base⁻¹ (what AMCL broadcasts), future-dated by the tolerance
                T_map_odom = pose2d_to_transform(frame.x, frame.y, frame.theta) @ invert_transform(T_odom_base)
                future = stamp + int(c.transform_tolerance_s * 1e9)
                self._put(self.tf_pub, ros.tf_message(self.store, [(future, c.map_frame, c.odom_frame, T_map_odom)]),
                          ros.TF_MESSAGE)

    def on_objects(self, frame) -> None:
        self.object_markers = ros.object_markers(
            self.store, frame.header.stamp_ns, self.config.map_frame, frame.class_names, frame.class_index,
            frame.positions, frame.sizes, getattr(frame, "existence", None))
        self._put(self.objects_pub, self.object_markers, ros.MARKER_ARRAY)

    def on_topomap(self, frame: TopoMap) -> None:
        self.topomap = frame
        self._topomap_markers()
        self._put(self.topomap_pub, self.topomap_markers, ros.MARKER_ARRAY)

    def _topomap_markers(self) -> None:
        """Nodes placed at the estimate nearest their key-frame's stamp (within a second)."""
        frame = self.topomap
        if frame is None or not self.path:
            return
        stamps = np.array([p[0] for p in self.path], dtype=np.int64)
        positions = {}
        for node, keyframe_stamp in enumerate(frame.keyframe_stamps_ns):
            index = int(np.argmin(np.abs(stamps - int(keyframe_stamp))))
            if abs(int(stamps[index]) - int(keyframe_stamp)) <= 1_000_000_000:
                positions[node] = self.path[index][1:3]
        self.topomap_markers = ros.topomap_markers(self.store, frame.header.stamp_ns, self.config.map_frame,
                                                   positions, frame.edges)

    def _publish_markers(self) -> None:
        if self.object_markers is not None:
            self._put(self.objects_pub, self.object_markers, ros.MARKER_ARRAY)
        self._topomap_markers()
        if self.topomap_markers is not None:
            self._put(self.topomap_pub, self.topomap_markers, ros.MARKER_ARRAY)

    def _publish_path(self) -> None:
        if self.path:
            msg = ros.path_message(self.store, self.path[-1][0], self.config.map_frame, list(self.path))
            self._put(self.path_pub, msg, ros.PATH)

    def _model_frame(self) -> CameraModel | None:
        if self.camera_model is None:
            return None
        return camera_model_frame(self.camera_model, self.model_out.header(frame_id="body"), name=self.config.camera)

    def _publish_model(self) -> None:
        frame = self._model_frame()
        if frame is not None:
            self.model_out.publish(frame)

    def teardown(self) -> None:
        for token in self.tokens:
            token.undeclare()


def publisher_gid(attached: bytes | None) -> bytes | None:
    """The publisher's GID in rmw_zenoh's attachment (None without one: zenoh-bridge-ros2dds, a plain zenoh put);
    a malformed one is rejected (``attachment``)."""
    if attached is None:
        return None
    try:
        return parse_attachment(attached)[2]
    except ValueError as error:
        raise FrameError(str(error), reason="attachment") from None


def _same_camera(a, b) -> bool:
    return (a.width, a.height) == (b.width, b.height) and np.allclose(a.K, b.K) and a.dist.shape == b.dist.shape \
        and np.allclose(a.dist, b.dist) and np.allclose(a.T_body_cam, b.T_body_cam)



def published_covariance(frame: PoseEstimate, lost_variance: float) -> np.ndarray:
    """The covariance ROS sees, by the localizer's state (``PoseEstimate.state``): localized (or no state) - the
    reported hypothesis's; uncertain - the whole particle set's where wider (other hypotheses count); lost - that,
    with the x, y and yaw variances raised to at least ``lost_variance``."""
    covariance = np.asarray(frame.covariance, float)
    if frame.state in ("uncertain", "lost"):
        spread = np.asarray(frame.mean_covariance, float)
        if np.trace(spread[:2, :2]) > np.trace(covariance[:2, :2]):
            covariance = spread
    if frame.state == "lost":
        covariance = covariance.copy()
        diagonal = np.arange(3)
        covariance[diagonal, diagonal] = np.maximum(covariance[diagonal, diagonal], lost_variance)
    return covariance

WORKER = Ros2
