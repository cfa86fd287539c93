"""Robot logs read whole: a ROS 1 bag, a ROS 2 bag (sqlite3 or MCAP storage) or a ROS 2 MCAP file (rosbags'
AnyReader) becomes captures with everything the graph needs (docs/ros2.md):

* the images of one topic (``sensor_msgs/Image`` or ``CompressedImage``) with their header stamps;
* the camera model from the ``CameraInfo`` topic, mounted where TF puts the image's frame on the base
  (``base_frame -> header.frame_id``, static or per image);
* odometry: the odometry pose (``nav_msgs/Odometry`` topic, or TF ``odom_frame -> base_frame``) at each image,
  turned into the constant twist since the previous image (semloc's Odometry);
* ground truth, when the log has it: a ``nav_msgs/Odometry``, ``PoseStamped`` or ``PoseWithCovarianceStamped``
  topic of the base's pose in the world, interpolated at each image.

The log is read twice: once for everything but the images (small), then image by image. A log cut short (a
folder ``ros2 bag record`` left without ``metadata.yaml``, a storage file without its end: services/cut_files.py)
is read from its storage files up to the cut, and says so once (a ``recording cut short`` skip).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from schemas import FrameError
from semloc_core.camera import forward_extrinsic
from services.camera_sources import Capture, Source, SourceFileError
from services.cut_files import CUT_SHORT, DAMAGED, Cut, CutFileError, Damage, mcap_channels, mcap_messages, \
    mcap_summary, sqlite_bag_rows, sqlite_bag_topics
from services.ros2 import messages as ros

IMAGE_TYPES = (ros.IMAGE, ros.COMPRESSED_IMAGE, "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = (ros.ODOMETRY, ros.POSE_STAMPED, ros.POSE_WITH_COVARIANCE_STAMPED)
GROUND_TRUTH_NAMES = ("ground_truth", "groundtruth", "gt_pose")


class LogTopics(BaseModel):
    """Which topics and frames of a robot log to use; empty = found automatically (the only one of its type)."""

    model_config = ConfigDict(extra="forbid")

    camera_info: str = Field("", description="CameraInfo topic (default: the only one, or the image's sibling)")
    odometry: str = Field("", description="nav_msgs/Odometry topic; 'tf' for TF odom_frame -> base_frame; 'none'")
    ground_truth: str = Field("", description="ground-truth pose topic (default: one named *ground_truth*); 'none'")
    odom_frame: str = "odom"
    base_frame: str = "base_footprint"


def _pose_of(msgtype: str, msg) -> np.ndarray:
    pose = msg.pose.pose if msgtype in (ros.ODOMETRY, ros.POSE_WITH_COVARIANCE_STAMPED) else msg.pose
    return ros.pose_matrix(pose)


class RosLogSource(Source):
    """Images of one topic of a ROS log, with camera model, odometry and ground truth (see the module docstring)."""

    def __init__(self, path: Path, topic: str | None = None, grayscale: bool = False,
                 topics: LogTopics | None = None):
        self.path, self.grayscale, self.topics = Path(path), grayscale, topics or LogTopics()
        self.reader, self.cuts = _open_log(self.path)
        try:
            self._choose(topic)
            self._read_context()
        except Exception:
            self.reader.close()
            raise

    # ------------------------------------------------------------------ topics
    def _of_type(self, types) -> list:
        return [c for c in self.reader.connections if c.msgtype in types]

    def _choose(self, topic: str | None) -> None:
        t = self.topics
        images = [c for c in self._of_type(IMAGE_TYPES) if not topic or c.topic == topic]
        names = sorted({c.topic for c in images})
        if not images:
            raise SourceFileError(f"no image topic {topic or ''} in {self.path}")
        if len(names) > 1:
            raise SourceFileError(f"{self.path} has several image topics {names}: choose one with topic")
        self.image_connections, self.image_topic = images, names[0]
        infos = sorted({c.topic for c in self._of_type((ros.CAMERA_INFO,))})
        sibling = self.image_topic.rsplit("/", 1)[0] + "/camera_info"
        self.info_topic = self._pick("camera_info", t.camera_info, infos,
                                     sibling if sibling in infos else (infos[0] if len(infos) == 1 else None))
        poses = sorted({c.topic for c in self._of_type(POSE_TYPES)})
        named_truth = [p for p in poses if any(n in p.lower() for n in GROUND_TRUTH_NAMES)]
        self.truth_topic = self._pick("ground_truth", t.ground_truth, poses,
                                      named_truth[0] if len(named_truth) == 1 else None)
        odometry = sorted({c.topic for c in self._of_type((ros.ODOMETRY,))} - {self.truth_topic})
        self.odometry_topic = None if t.odometry == "tf" else self._pick(
            "odometry", t.odometry, odometry, odometry[0] if len(odometry) == 1 else None)
        self.tf_connections = [c for c in self._of_type((ros.TF_MESSAGE,)) if c.topic in ("/tf", "/tf_static")]

    def _pick(self, what: str, chosen: str, available: list[str], default: str | None) -> str | None:
        if chosen == "none":
            return None
        if chosen:
            if chosen not in available:
                raise SourceFileError(f"{self.path} has no {what} topic {chosen} (has {available})")
            return chosen
        return default

    # ------------------------------------------------------------------ everything but the images
    def _read_context(self) -> None:
        t = self.topics
        self.tf = ros.TransformBuffer(history_ns=None)
        self.truth = ros.TransformBuffer(history_ns=None)
        self.infos: list[tuple[int, object]] = []
        wanted = {self.info_topic, self.truth_topic, self.odometry_topic} - {None}
        connections = [c for c in self.reader.connections if c.topic in wanted] + self.tf_connections
        rejected = 0
        for connection, log_time, raw in self.reader.messages(connections=connections):
            try:
                msg = self.reader.deserialize(raw, connection.msgtype)
                stamp = _stamp(msg, log_time)
                if connection.msgtype == ros.TF_MESSAGE:
                    self.tf.add_message(msg, static=connection.topic == "/tf_static")
                elif connection.topic == self.info_topic:
                    self.infos.append((stamp, msg))
                elif connection.topic == self.truth_topic:
                    self.truth.add("world", "body", stamp, _pose_of(connection.msgtype, msg))
                elif connection.topic == self.odometry_topic:
                    self.tf.add(t.odom_frame, t.base_frame, stamp, _pose_of(connection.msgtype, msg))
            except (FrameError, ValueError) as error:  # one bad message does not spoil the log
                rejected += 1
                last_error = error
        if rejected:
            self.description_note = f", {rejected} unreadable messages (last: {last_error})"
        self.has_odometry = self.odometry_topic is not None or self.tf.latest_stamp(t.base_frame) is not None
        self.camera = self._camera(self.infos[0][1], self.infos[0][0]) if self.infos else None
        parts = [f"robot log {self.path} images {self.image_topic}",
                 f"camera_info {self.info_topic}" if self.infos else "no camera_info",
                 f"odometry {self.odometry_topic or 'from TF'}" if self.has_odometry else "no odometry",
                 f"ground truth {self.truth_topic}" if self.truth_topic else "no ground truth"]
        self.description = ", ".join(parts) + getattr(self, "description_note", "")

    def _mount(self, frame_id: str, stamp: int) -> np.ndarray | None:
        frame = str(frame_id).lstrip("/")
        return self.tf.lookup(self.topics.base_frame, frame, stamp) if frame else None

    def _camera(self, msg, stamp: int):
        T_body_cam = self._mount(msg.header.frame_id, stamp)
        return ros.camera_from_info(msg, forward_extrinsic() if T_body_cam is None else T_body_cam)

    # ------------------------------------------------------------------ the images
    def __iter__(self):
        t = self.topics
        previous: tuple[int, np.ndarray] | None = None
        for connection, log_time, raw in self.reader.messages(connections=self.image_connections):
            msgtype = connection.msgtype
            msg = self.reader.deserialize(raw, msgtype)
            stamp = _stamp(msg, log_time)
            try:
                pixels = ros.image_pixels(msgtype, msg, self.grayscale)
            except FrameError as error:
                raise SourceFileError(f"{self.image_topic} at {stamp} ns: {error}") from None
            mount = self._mount(msg.header.frame_id, stamp)
            odometry = None
            T_odom_base = self.tf.lookup(t.odom_frame, t.base_frame, stamp) if self.has_odometry else None
            if T_odom_base is not None:
                if previous is not None and stamp > previous[0]:
                    dt = (stamp - previous[0]) * 1e-9
                    odometry = (*ros.planar_twist(previous[1], T_odom_base, dt), dt)
                previous = (stamp, T_odom_base)
            yield Capture([pixels], stamp, T_body_cam=None if mount is None else [mount],
                          T_world_body=self.truth.lookup("world", "body", stamp), odometry=odometry)
        for cut in self.cuts.values():  # said once the images are read: a cut log's count is known then
            self.skip(DAMAGED if isinstance(cut, Damage) else CUT_SHORT, str(cut))

    def close(self) -> None:
        self.reader.close()


def _stamp(msg, log_time: int) -> int:
    """The message's header stamp (the log time when it has no header, or a zero stamp)."""
    header = getattr(msg, "header", None)
    if header is None:
        return int(log_time)
    value = ros.stamp_ns(header.stamp)
    return value if value > 0 else int(log_time)


def storage_files(path: Path) -> list[Path]:
    """The storage files of a bag folder ``ros2 bag record`` left without ``metadata.yaml`` (it writes it last), in
    the order written (``NAME_0.db3``, ``NAME_1.db3``...)."""
    from services.camera_sources import natural_key

    return sorted((f for f in path.iterdir() if f.suffix in (".db3", ".mcap")), key=lambda f: natural_key(f.name))


def _open_log(path: Path) -> tuple:
    """(reader, cuts): rosbags' AnyReader on the log (a folder without metadata.yaml: on its storage files); for one
    rosbags cannot open and cut short (an MCAP file without summary, a .db3), :class:`_CutLog` on its storage files.
    ``cuts``: what to say once the images are read, by file (a cut log's filled as its files are read)."""
    from rosbags.highlevel import AnyReader

    unfinished = path.is_dir() and not (path / "metadata.yaml").is_file()
    files = storage_files(path) if unfinished else [path]
    if not files:
        raise SourceFileError(f"cannot open robot log {path}: no metadata.yaml and no .db3 or .mcap file")
    try:
        reader = AnyReader(files, default_typestore=ros.typestore("jazzy"))
        reader.open()
    except Exception as error:  # rosbags raises several types on a damaged log
        files = storage_files(path) if path.is_dir() else [path]
        if not any(_cut_short(f) for f in files):  # damaged, not cut short
            raise SourceFileError(f"cannot open robot log {path}: {error}") from None
        try:
            reader = _CutLog(files)
        except CutFileError as salvage:
            raise SourceFileError(f"cannot open robot log {path}: {error}; {salvage}") from None
        return reader, reader.cuts
    if unfinished:
        return reader, {path: f"{path} has no metadata.yaml (the recorder did not finish): read from its storage "
                              f"files {', '.join(f.name for f in files)}, which end whole"}
    return reader, {}


def _cut_short(file: Path) -> bool:
    """Whether a storage file rosbags cannot open may have been cut short: a .db3, an MCAP file without summary."""
    try:
        return file.suffix == ".db3" or mcap_summary(file) is None
    except CutFileError:  # not MCAP at all
        return False


class _Connection(NamedTuple):
    id: tuple[int, int]  # (storage file, channel or topic id)
    topic: str
    msgtype: str


class _CutLog:
    """What RosLogSource uses of rosbags' AnyReader, over storage files cut short (.mcap, .db3) read up to the cut
    (services/cut_files.py); ``cuts``: where each stopped, from the last reading."""

    def __init__(self, files: list[Path]):
        self.files = files
        self.typestore = ros.typestore("jazzy")
        self.cuts: dict[Path, Cut] = {}  # where each file read stopped
        self.connections: list[_Connection] = []
        for index, file in enumerate(files):
            if file.suffix == ".db3":
                self.connections += [_Connection((index, tid), name, msgtype)
                                     for tid, name, msgtype in sqlite_bag_topics(file)]
            else:
                self.connections += [_Connection((index, channel.id), channel.topic, schema.name)
                                     for channel, schema in mcap_channels(file) if schema is not None]
        if not self.connections:
            raise CutFileError(f"{files[0]}: cut before its first topic")

    def messages(self, connections):
        wanted = {c.id: c for c in connections}
        for index, file in enumerate(self.files):
            if file.suffix == ".db3":
                cut = Cut(file, "")
                for tid, stamp, data in sqlite_bag_rows(file, cut):
                    if (connection := wanted.get((index, tid))) is not None:
                        yield connection, stamp, data
                if cut.why:
                    self.cuts[file] = cut
            else:
                for _schema, channel, message in mcap_messages(
                        file, on_cut=lambda c, f=file: self.cuts.update({f: c}),
                        on_damage=lambda d: self.cuts.update({(d.path, d.offset): d})):
                    if (connection := wanted.get((index, channel.id))) is not None:
                        yield connection, message.log_time, message.data

    def deserialize(self, raw: bytes, msgtype: str):
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        pass
