"""Where the camera worker's images come from: image folder, video file, device, network stream, ROS 1/2 bag,
MCAP file (ROS 2 messages or a ``semloc record`` session), simulated data set.

Every source yields :class:`Capture` objects: the BGR (or grey) uint8 images of one instant (one per member camera),
their timestamp when the source has one, and, for data sets, ground truth. A frame a file source cannot read (an
unreadable image in a folder, a damaged stretch of a video) is skipped, counted and reported (:meth:`Source.skip`),
and the source goes on.
"""

from __future__ import annotations

import collections
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from semloc_core.io.dataset import open_dataset
from semloc_core.io.errors import FileFormatError
from semloc_core.io.timestamps import read_timestamps

IMAGE_EXTENSIONS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp"}
VIDEO_EXTENSIONS = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"}
SOURCE_TYPES = ("auto", "folder", "video", "device", "url", "bag", "mcap", "dataset")
LIVE_KINDS = ("device", "url")  # sources that may go away and come back: the camera worker reopens them
# Failed reads in a row that end a video file short of the frame count its container declares. Why not the first:
# OpenCV's read() fails on each frame of a damaged stretch and then decodes the frames after it.
MAX_UNDECODABLE_IN_A_ROW = 50
# A network stream's bounds on FFmpeg's open and read (OpenCV's own: 30 s each): the camera worker's defaults
# (CameraConfig), and every other reader's (semloc calibrate-camera).
URL_OPEN_TIMEOUT_S = 5.0
URL_READ_TIMEOUT_S = 2.0


class SourceError(ValueError):
    """The source cannot be opened or read (the message says why); a live source (device, stream) may come back."""


class SourceFileError(SourceError, FileFormatError):
    """A source file or folder that cannot be used (restarting cannot help: the worker exits with code 2)."""


@dataclass
class Capture:
    images: list[np.ndarray]
    stamp_ns: int | None = None  # None: the source has no clock (live capture, folder without timestamps)
    T_body_cam: list[np.ndarray | None] | None = None  # per-frame attitude override, per member camera
    T_world_body: np.ndarray | None = None  # ground truth (data sets)
    odometry: tuple[float, float, float, float] | None = None  # (v, v_lateral, omega, dt) ending at this frame


class Source:
    """Iterable of captures. ``live`` sources pace themselves (no sleeping, no looping); ``camera`` is the
    calibration the source carries (data sets), else None."""

    live = False
    camera = None
    description = ""
    on_skip: Callable[[str, str], None] | None = None  # called with (why, which frame) for each frame skipped

    def __iter__(self) -> Iterator[Capture]:
        raise NotImplementedError

    @property
    def skipped(self) -> collections.Counter:
        """The frames skipped so far, per reason."""
        return self.__dict__.setdefault("_skipped", collections.Counter())

    def skip(self, why: str, detail: str) -> None:
        """Count a frame the source could not read under ``why`` (``detail`` names it); iteration goes on."""
        self.skipped[why] += 1
        if self.on_skip is not None:
            self.on_skip(why, detail)

    def close(self) -> None:
        pass


def natural_key(name: str):
    """Sort key putting ``2.jpg`` before ``10.jpg``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


class FolderSource(Source):
    def __init__(self, path: Path, timestamps: str | None = None, grayscale: bool = False):
        self.files = sorted((p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS),
                            key=lambda p: natural_key(p.name))
        if not self.files:
            raise SourceFileError(f"no images ({', '.join(sorted(IMAGE_EXTENSIONS))}) in {path}")
        stamp_file = Path(timestamps) if timestamps else None
        if stamp_file is None and (path / "timestamps.txt").is_file():
            stamp_file = path / "timestamps.txt"
        try:
            self.stamps = read_timestamps(stamp_file, [f.name for f in self.files]) if stamp_file else None
        except FileFormatError as error:  # a source's file: a SourceError too
            raise SourceFileError(str(error)) from None
        self.flag = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR
        self.description = f"folder {path} ({len(self.files)} images)"

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self):
        read = 0
        for index, file in enumerate(self.files):
            image = cv2.imread(str(file), self.flag)
            if image is None:
                self.skip("unreadable images", f"cannot read image {file}: skipped")
                continue
            read += 1
            yield Capture([image], None if self.stamps is None else self.stamps[index])
        if not read:
            raise SourceFileError(f"none of the {len(self.files)} images in {self.files[0].parent} can be read")


class VideoSource(Source):
    """A video file (stamps from the container), a device index or an RTSP/HTTP URL (live).

    ``open_timeout_s`` / ``read_timeout_s`` bound opening and each read of a URL (FFmpeg's interrupt callback; without
    them OpenCV waits 30 s on a stream that stops sending). URLs only: OpenCV refuses to open a capture with a
    parameter its backend does not take (so do 4.14's image and MJPEG backends); the camera worker's status watches
    a device's silence instead."""

    def __init__(self, target, live: bool, grayscale: bool = False, open_timeout_s: float | None = None,
                 read_timeout_s: float | None = None):
        self.target, self.live, self.grayscale = target, live, grayscale
        self.read_timeout_s = read_timeout_s if isinstance(target, str) and live else None
        params = []
        if isinstance(target, str) and live:
            for prop, seconds in ((cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, open_timeout_s),
                                  (cv2.CAP_PROP_READ_TIMEOUT_MSEC, read_timeout_s)):
                if seconds is not None:
                    params += [prop, max(1, int(round(seconds * 1000)))]
        started = time.monotonic()
        self.capture = cv2.VideoCapture(target, cv2.CAP_ANY, params) if params else cv2.VideoCapture(target)
        if not self.capture.isOpened():
            if live:  # a device or a stream may come up later: not a bad file
                took = time.monotonic() - started
                raise SourceError(f"cannot open video source {target!r}" +
                                  (f" (no answer in {took:.1f} s)" if open_timeout_s and took >= 0.9 * open_timeout_s
                                   else ""))
            raise SourceFileError(f"{target}: not a video OpenCV can open")
        fps = self.capture.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and np.isfinite(fps) and 0 < fps < 1000 else None
        self.description = f"{'live ' if live else ''}video {target}"

    def __iter__(self):
        index = undecodable = failed = 0  # frames read, frames skipped, failed reads since the last frame read
        declared = 0 if self.live else int(max(0.0, self.capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0))
        while True:
            started = time.monotonic()
            ok, image = self.capture.read()
            if not ok:
                if self.live:
                    timeout = self.read_timeout_s
                    timed_out = timeout and time.monotonic() - started >= 0.9 * timeout
                    raise SourceError(f"no frame in {timeout:g} s" if timed_out else
                                      "the read failed (stream closed, device gone)")
                failed += 1
                if index + undecodable + failed < declared and failed < MAX_UNDECODABLE_IN_A_ROW:
                    continue  # a damaged frame: the ones after it may decode
                if index + undecodable < declared:
                    self.skip("video ended early", f"{self.target}: ended after {index + undecodable} frames of the "
                                                   f"{declared} its container declares")
                return
            for _ in range(failed):
                self.skip("undecodable video frames", f"{self.target}: frame {index + undecodable} cannot be "
                                                      f"decoded: skipped")
                undecodable += 1
            failed = 0
            if self.grayscale and image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            if self.live:
                stamp = time.time_ns()
            else:
                msec = self.capture.get(cv2.CAP_PROP_POS_MSEC)
                stamp = int(round(msec * 1e6)) if msec and msec > 0 or index == 0 else None
                if stamp is None and self.fps:
                    stamp = int(round((index + undecodable) / self.fps * 1e9))
            index += 1
            yield Capture([image], stamp)

    def close(self) -> None:
        self.capture.release()


def ros_image_to_bgr(msgtype: str, msg, grayscale: bool = False) -> np.ndarray:
    """sensor_msgs Image / CompressedImage -> uint8 BGR (or grey)."""
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
        if image is None:
            raise SourceFileError("undecodable CompressedImage")
        return image
    height, width, encoding = int(msg.height), int(msg.width), str(msg.encoding).lower()
    data = np.asarray(msg.data, dtype=np.uint8)
    channels = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4, "mono16": 2, "16uc1": 2}
    if encoding not in channels:
        raise SourceFileError(f"unsupported image encoding {encoding!r}")
    per_pixel = channels[encoding]
    step = int(msg.step) or width * per_pixel
    if data.size < step * height:
        raise SourceFileError(f"image data of {data.size} bytes is too short for {width}x{height} {encoding}")
    rows = data[: step * height].reshape(height, step)[:, : width * per_pixel]
    if per_pixel == 2:
        dtype = np.dtype(">u2") if getattr(msg, "is_bigendian", 0) else np.dtype("<u2")
        grey16 = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
        image = (grey16 >> 8).astype(np.uint8)  # keep the 8 most significant bits
    elif per_pixel == 1:
        image = rows.reshape(height, width)
    else:
        image = rows.reshape(height, width, per_pixel)
        conversion = {"rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR}.get(encoding)
        image = cv2.cvtColor(image, conversion) if conversion is not None else image.copy()
    if grayscale and image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif not grayscale and image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image)


class McapSource(Source):
    """A ``semloc record`` session (semloc.Image frames), a file or a folder of splits played in order. ROS 2 MCAP
    files are robot logs (services.ros2.logs)."""

    def __init__(self, path: Path, topic: str | None, grayscale: bool = False):
        from services.cut_files import CutFileError, mcap_channels
        from services.recording import recording_files

        self.path, self.topic, self.grayscale = path, topic, grayscale
        self.files = recording_files(path)
        try:
            channels = [channel for file in self.files for channel in mcap_channels(file)]
        except CutFileError as error:
            raise SourceFileError(str(error)) from None
        except Exception as error:  # the mcap reader raises several unrelated types on garbage
            raise SourceFileError(f"{path}: not a readable MCAP file ({type(error).__name__}: {error})") from None
        candidates = [(channel.topic, schema.name) for channel, schema in channels
                      if schema is not None and schema.name == "semloc.Image"]
        if topic:
            candidates = [c for c in candidates if c[0] == topic]
        if not candidates:
            raise SourceFileError(f"no image channel {topic or ''} in {path}")
        if len({c[0] for c in candidates}) > 1:
            raise SourceFileError(f"{path} has several image channels {sorted({c[0] for c in candidates})}: use --topic")
        self.channel_topic, self.schema_name = candidates[0]
        self.description = f"mcap {path} channel {self.channel_topic} ({self.schema_name})"

    def __iter__(self):
        from schemas import FrameError, Image, decode
        from services.cut_files import CUT_SHORT, DAMAGED, CutFileError, mcap_messages

        messages = (message for file in self.files
                    for message in mcap_messages(file, on_cut=lambda cut: self.skip(CUT_SHORT, str(cut)),
                                                 on_damage=lambda damage: self.skip(DAMAGED, str(damage))))
        while True:
            try:
                _schema, channel, message = next(messages)
            except StopIteration:
                return
            except CutFileError as error:
                raise SourceFileError(str(error)) from None
            except Exception as error:  # a damaged chunk
                raise SourceFileError(f"{self.path}: damaged MCAP data ({type(error).__name__}: {error})") from None
            if channel.topic == self.channel_topic:
                try:
                    frame = decode(message.data, expected=Image)
                except FrameError as error:
                    raise SourceFileError(f"{self.path}: message {message.sequence} on {self.channel_topic}: "
                                          f"{error}") from None
                images = [image.bgr() for image in frame.images]
                if self.grayscale:
                    images = [cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) if i.ndim == 3 else i for i in images]
                overrides = [None if i.T_body_cam is None else np.array(i.T_body_cam) for i in frame.images]
                yield Capture(images, frame.header.stamp_ns,
                              T_body_cam=overrides if any(o is not None for o in overrides) else None)


def is_semloc_recording(path: Path) -> bool:
    """Whether an MCAP file holds semloc frames (``semloc record``, finished or cut short, even before its first
    channel: its header names semloc as the library that wrote it); else it is a ROS 2 robot log."""
    from services.cut_files import mcap_channels, mcap_library

    try:
        return mcap_library(path) == "semloc" or any(channel.message_encoding == "semloc"
                                                     for channel, _schema in mcap_channels(path))
    except Exception:  # not MCAP: not a recording
        return False


def classify(source: str) -> str:
    """The source type of a ``--source`` string (see SOURCE_TYPES)."""
    text = str(source)
    if re.fullmatch(r"\d+", text):
        return "device"
    if re.match(r"^(rtsp|rtsps|http|https|rtmp|udp|tcp)://", text):
        return "url"
    path = Path(text)
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "bag"
        if _looks_like_dataset(path):
            return "dataset"
        return "bag" if _looks_like_unfinished_bag(path) else "folder"
    suffix = path.suffix.lower()
    if suffix == ".bag" or suffix == ".db3":
        return "bag"
    if suffix == ".mcap":
        return "mcap"
    if suffix in VIDEO_EXTENSIONS:
        return "video"
    if not path.exists():
        raise SourceFileError(f"source not found: {source}")
    raise SourceFileError(f"cannot tell what kind of source {source} is; set source_type")


def _looks_like_unfinished_bag(path: Path) -> bool:
    """A ROS 2 bag folder without its ``metadata.yaml`` (``ros2 bag record`` writes it last: a killed recorder or a
    power cut leaves the storage files alone): storage files and no image."""
    suffixes = {f.suffix.lower() for f in path.iterdir()}
    return bool(suffixes & {".db3", ".mcap"}) and not suffixes & IMAGE_EXTENSIONS


def _looks_like_dataset(path: Path) -> bool:
    """A ``semloc sim`` folder. (An image folder with loop ground truth is a data set too, but plays as a plain
    folder unless ``source_type: dataset`` is given.)"""
    return (path / "dataset.json").is_file()


def source_kind(source: str, source_type: str = "auto") -> str:
    """One of SOURCE_TYPES but auto: what ``source`` is (``source_type`` unless auto)."""
    kind = classify(source) if source_type == "auto" else source_type
    if kind not in SOURCE_TYPES:
        raise SourceFileError(f"source_type must be one of {SOURCE_TYPES}, got {kind!r}")
    return kind


def open_source(source: str, source_type: str = "auto", *, topic: str | None = None, timestamps: str | None = None,
                grayscale: bool = False, log=None, open_timeout_s: float | None = URL_OPEN_TIMEOUT_S,
                read_timeout_s: float | None = URL_READ_TIMEOUT_S) -> Source:
    """The source of a ``--source`` string; ``log``: which topics of a robot log to use (services.ros2.logs.LogTopics,
    default: found automatically); the timeouts: a network stream's (VideoSource)."""
    kind = source_kind(source, source_type)
    if kind == "device":
        return VideoSource(int(source), live=True, grayscale=grayscale)
    if kind == "url":
        return VideoSource(str(source), live=True, grayscale=grayscale, open_timeout_s=open_timeout_s,
                           read_timeout_s=read_timeout_s)
    path = Path(source)
    if not path.exists():
        raise SourceFileError(f"source not found: {source}")
    if kind == "folder":
        return FolderSource(path, timestamps, grayscale)
    if kind == "video":
        return VideoSource(str(path), live=False, grayscale=grayscale)
    from services.recording import is_split_recording

    if (kind == "mcap" and is_semloc_recording(path)) or (kind == "bag" and is_split_recording(path)):
        return McapSource(path, topic, grayscale)
    if kind in ("bag", "mcap"):
        from services.ros2.logs import RosLogSource

        # a .db3 of a bag folder: the whole bag (its metadata.yaml lists the split files); alone, the file
        whole_bag = path.suffix == ".db3" and (path.parent / "metadata.yaml").is_file()
        return RosLogSource(path.parent if whole_bag else path, topic, grayscale, log)
    if kind == "dataset":
        return DatasetSource(path, grayscale)
    raise SourceFileError(f"unsupported source type {kind!r}")


class DatasetSource(Source):
    """A data set opened by ``semloc_core.io.dataset.open_dataset`` (a ``semloc sim`` folder, an image folder with
    loop ground truth...): images with the data set's stamps, its camera model, per-frame ``T_body_cam``, and
    ground-truth poses and odometry when it has them."""

    def __init__(self, path_or_dataset, grayscale: bool = False):
        if isinstance(path_or_dataset, (str, Path)):
            try:
                self.dataset = open_dataset(path_or_dataset)
            except ValueError as error:
                raise SourceFileError(f"cannot open data set {path_or_dataset}: {error}") from None
        else:
            self.dataset = path_or_dataset
        if not self.dataset.has_images:
            raise SourceFileError(f"data set {self.dataset.name} has no images")
        self.grayscale = grayscale
        self.camera = self.dataset.camera
        self.description = f"data set {self.dataset.name} ({len(self.dataset)} frames)"

    def __len__(self) -> int:
        return len(self.dataset)

    def __iter__(self):
        dataset = self.dataset
        odometry = dataset.odometry.as_array() if dataset.odometry is not None else None
        for index in range(len(dataset)):
            image = dataset.image(index)
            images = list(image) if isinstance(image, (tuple, list)) else [image]
            if self.grayscale:
                images = [cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) if i.ndim == 3 else i for i in images]
            overrides = None
            if dataset.T_body_cam is not None and len(images) == 1:
                overrides = [np.asarray(dataset.T_body_cam[index])]
            odometry_row = None
            if odometry is not None and odometry[index, 3] > 0:  # row 0 (no motion yet) has dt = 0
                v, v_lateral, omega, dt = (float(x) for x in odometry[index])
                odometry_row = (v, v_lateral, omega, dt)
            yield Capture(images, int(dataset.stamps_ns[index]), T_body_cam=overrides,
                          T_world_body=None if dataset.T_world_body is None else dataset.T_world_body[index],
                          odometry=odometry_row)
