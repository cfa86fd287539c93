"""Camera: publishes Image frames (and the CameraModel) from a folder, video, device, URL, bag, MCAP or data set."""

from __future__ import annotations

import collections
import itertools
import time

import cv2
from pydantic import Field, field_validator, model_validator

from schemas import CameraModel, Image, Odometry, Pose2D, Pose3D, keys
from semloc_core.camera import PinholeCamera, members
from semloc_core.io.camera_model import fit_to_frames, load_camera
from services.frames import camera_model_frame, capture_frames
from services.camera_sources import (LIVE_KINDS, SOURCE_TYPES, URL_OPEN_TIMEOUT_S, URL_READ_TIMEOUT_S, Capture, Source,
                                     SourceError, SourceFileError, open_source, source_kind)
from services.ros2.logs import LogTopics
from services.runtime import Worker, WorkerConfig, one_line

DEFAULT_FOLDER_RATE = 10.0
DEFAULT_FOV_DEG = 60.0  # a typical webcam's horizontal field of view


class CameraConfig(WorkerConfig):
    source: str = Field(..., description="image folder, video file, device index, rtsp/http URL, bag, .mcap, data set")
    source_type: str = Field("auto", description=f"one of {SOURCE_TYPES}")
    camera: str = Field("front", description="camera name in the keys semloc/<robot>/camera/<camera>/...")
    topic: str | None = Field(None, description="image topic of a bag / MCAP file")
    log: LogTopics = Field(default_factory=LogTopics, description="a robot log's camera_info, odometry and "
                           "ground-truth topics and frames (docs/ros2.md)")
    timestamps: str | None = Field(None, description="folder: '<seconds> [file]' per line (default timestamps.txt)")
    calibration: str | None = Field(None, description="calibration YAML (semloc_core/io/camera_model.py); at "
                                    "another resolution of the same aspect ratio it is scaled, with a warning")
    default_fov_deg: float = Field(DEFAULT_FOV_DEG, gt=0, lt=180, description="horizontal field of view of a "
                                   "source without any calibration (a distortion-free pinhole; with a warning)")
    rate: float | None = Field(None, gt=0, description="fixed publication rate in Hz; None = the source's timing")
    loop: bool = Field(False, description="start over at the end (not for live sources)")
    start: int = Field(0, ge=0, description="first frame index")
    end: int | None = Field(None, ge=0, description="stop before this frame index")
    grayscale: bool = Field(False, description="publish mono8 instead of bgr8")
    jpeg_quality: int | None = Field(None, ge=1, le=100, description="JPEG-compress images on the wire")
    stamp: str = Field("source", description="'source': the source's clock when it has one; 'wall': publish time")
    model_period_s: float = Field(1.0, gt=0, description="CameraModel republication period")
    wait_for_subscriber_s: float = Field(0.0, ge=0, description="wait up to this long for a subscriber first")
    exit_at_end: bool = Field(True, description="stop the worker when the source ends (else keep serving)")
    frame_id: str = Field("", description="frame id of the images (default: the camera name)")
    read_timeout_s: float = Field(URL_READ_TIMEOUT_S, gt=0, description="a live source (device, URL) without a frame "
                                  "for this long is lost: degraded, closed and reopened (also bounds FFmpeg's read "
                                  "of a URL)")
    open_timeout_s: float = Field(URL_OPEN_TIMEOUT_S, gt=0, description="a URL that does not answer in this long "
                                  "cannot be opened (FFmpeg's open): tried again")
    # Short waits: a failed attempt costs about nothing (a refused connection, a missing device; a stream that does
    # not answer waits open_timeout_s anyway), and the wait after the camera's return is up to the longest one.
    reopen_backoff_s: float = Field(0.25, gt=0, description="a lost or absent live source is reopened after this, "
                                    "doubled after each failed attempt")
    reopen_max_backoff_s: float = Field(1.0, gt=0, description="the longest wait between two reopening attempts")

    @field_validator("source", mode="before")
    @classmethod
    def _device_index(cls, value):
        # a YAML value (`--set source=0`, `source: 0` in a graph) makes a device index an int: it is the same source
        return str(value) if isinstance(value, int) and not isinstance(value, bool) else value

    @model_validator(mode="after")
    def _check(self):
        if self.stamp not in ("source", "wall"):
            raise ValueError("stamp must be 'source' or 'wall'")
        if self.end is not None and self.end <= self.start:
            raise ValueError("end must be greater than start")
        if self.reopen_max_backoff_s < self.reopen_backoff_s:
            raise ValueError("reopen_max_backoff_s must be at least reopen_backoff_s")
        return self


class Camera(Worker):
    """Publishes images (and calibration, and ground truth for data sets) with native or fixed timing."""

    Config = CameraConfig

    def __init__(self, config: CameraConfig):
        super().__init__(config)
        # Before setup: the status thread reports them from the start, and the first frame is read in setup
        self.frames_published = 0
        self.frames_skipped: collections.Counter[str] = collections.Counter()
        # A live source going away and coming back (written by the main thread, read by the status thread's health)
        self._live = False
        self._last_frame: float | None = None  # monotonic time of the last frame read from a live source
        self._lost: tuple[str, int] | None = None  # (why, reopening attempt to come) while a live source is lost
        self._finished = False
        self.reconnects = 0  # times a lost live source gave frames again
        self.lost_s = 0.0  # the time without frames of the losses ended, last frame to first frame again

    def setup(self) -> None:
        c = self.config
        self._live = source_kind(c.source, c.source_type) in LIVE_KINDS
        self.source: Source | None = None
        self._first: Capture | None = None
        try:
            self.source = self._open()
            self.logger.info("source: %s", self.source.description)
            # The first frame tells the source's image size: the calibration must fit it (docs/camera.md).
            self._captures = iter(self.source)
            self._first = next(self._captures, None)
        except SourceError as error:
            if not self._live or isinstance(error, SourceFileError):
                raise
            self._lose(str(error))  # not there yet (a camera still booting): run() waits for it
        if self._live and self._first is not None:
            self._last_frame = time.monotonic()
        # A live source absent at start: the calibration is fitted to its first frame, when it comes (run)
        self._unfitted = self._live and self._first is None
        self.camera_model = None if self._unfitted else self._fitted_model(self._first)
        self.frame_id = c.frame_id or c.camera
        self.images = self.output("image", keys.camera_image(self.robot, c.camera), Image, bulk=True)
        self.model_out = self.output("model", keys.camera_model(self.robot, c.camera), CameraModel)
        self.pose_out = self.output("groundtruth_pose", keys.groundtruth_pose(self.robot), Pose3D)
        self.pose2d_out = self.output("groundtruth_pose2d", keys.groundtruth_pose2d(self.robot), Pose2D)
        self.odom_out = self.output("odometry", keys.odometry(self.robot), Odometry)
        if self.camera_model is not None or self._unfitted:
            self.queryable("model_query", self.model_out.key, lambda _request: self._model_frame())
            self.every(c.model_period_s, self._publish_model)
        self._sizes = None if self.camera_model is None else [(m.width, m.height) for m in members(self.camera_model)]

    def _open(self) -> Source:
        c = self.config
        source = open_source(c.source, c.source_type, topic=c.topic, timestamps=c.timestamps, grayscale=c.grayscale,
                             log=c.log, open_timeout_s=c.open_timeout_s, read_timeout_s=c.read_timeout_s)
        source.on_skip = self._skip
        return source

    def _lose(self, why: str) -> None:
        """The live source cannot be opened or read: closed, to be reopened (:meth:`_next_live`); degraded meanwhile."""
        if self.source is not None:
            self.source.close()
            self.source = None
        attempt = 1 if self._lost is None else self._lost[1] + 1
        self._lost = (why, attempt)
        if attempt in (1, 10, 100) or attempt % 1000 == 0:
            self.logger.warning("%s", self._lost_reason(time.monotonic()))

    def _found(self) -> None:
        """A frame from the live source: a loss (or the wait for it at start) ends, counted."""
        now = time.monotonic()
        if self._lost is not None:
            attempts = self._lost[1] - 1
            if self._last_frame is None:
                self.logger.info("camera %s open after %d failed attempt(s)", self.config.source, attempts)
            else:
                self.reconnects += 1
                self.lost_s += now - self._last_frame
                self.logger.warning("camera %s back after %.1f s without frames (%d failed attempt(s); reconnect %d)",
                                    self.config.source, now - self._last_frame, attempts, self.reconnects)
            self._lost = None
        self._last_frame = now

    def _lost_reason(self, now: float) -> str:
        """Why the live source gives no frames ("": it does). From the status thread too: a read that has not
        returned for ``read_timeout_s`` (a backend that ignores the timeout) is reported while it blocks."""
        lost, last = self._lost, self._last_frame
        if not self._live or self._finished:
            return ""
        if lost is None:
            if last is None or now - last <= self.config.read_timeout_s:
                return ""
            return f"camera {self.config.source} lost: no frame read for {now - last:.0f} s"
        why, attempt = lost
        if last is None:
            return f"waiting for camera {self.config.source}: {why}; attempt {attempt}, no frame yet"
        return (f"camera {self.config.source} lost: {why}; reopening, attempt {attempt}, last frame "
                f"{now - last:.0f} s ago")

    def _next_live(self) -> Capture | None:
        """The live source's next frame, reopening it (backing off) while it is lost; None when stopping."""
        c = self.config
        while not self.stopping:
            try:
                if self.source is None:
                    self.source = self._open()
                    self._captures = iter(self.source)
                capture = next(self._captures, None)
                if capture is not None:
                    self._found()
                    return capture
                why = "the stream ended"
            except SourceFileError:
                raise
            except SourceError as error:
                why = str(error)
            self._lose(why)
            if not self.sleep(min(c.reopen_backoff_s * 2 ** min(self._lost[1] - 1, 30), c.reopen_max_backoff_s)):
                return None
        return None

    def health(self, *args, **kwargs) -> tuple[str, str]:
        """The runtime's, and a live source lost first among the reasons (degraded)."""
        state, reason = super().health(*args, **kwargs)
        lost = self._lost_reason(time.monotonic()) if state in ("running", "degraded") else ""
        if lost:
            return "degraded", one_line(f"{lost}; {reason}" if reason else lost)
        return state, reason

    def _skip(self, why: str, detail: str) -> None:
        """A frame not published (the source could not read it, or it does not fit the camera model): counted in
        the status (degraded while it goes on), each of the first ten logged; the stream goes on."""
        self.frames_skipped[why] += 1
        if self.frames_skipped[why] <= 10:
            self.logger.warning("%s", detail)
        self.skipped(why)

    def status_details(self) -> dict:
        details = {"frames_published": self.frames_published, "frames_skipped": sum(self.frames_skipped.values()),
                   **{f"skipped: {why}": count for why, count in self.frames_skipped.items()}}
        if self._live:
            lost, last = self._lost, self._last_frame
            ongoing = time.monotonic() - last if lost is not None and last is not None else 0.0
            details.update(reconnects=self.reconnects, time_lost_s=round(self.lost_s + ongoing, 1))
        return details

    def _fitted_model(self, first: Capture | None):
        """The calibration (the config's, else the source's) made to fit the first frame's size: scaled at the same
        aspect ratio (warning), CalibrationError otherwise (exit 2); without any, a pinhole of ``default_fov_deg``."""
        c = self.config
        model = load_camera(c.calibration) if c.calibration else self.source.camera if self.source else None
        if first is None:
            return model
        sizes = [(image.shape[1], image.shape[0]) for image in first.images]
        if model is None:
            if len(sizes) > 1:
                self.logger.warning("no calibration for a %d-camera source: CameraModel is not published",
                                    len(sizes))
                return None
            self.logger.warning("no calibration: assuming a distortion-free pinhole camera with a %g° horizontal "
                                "field of view for the %dx%d frames (set calibration; semloc calibrate-camera)",
                                c.default_fov_deg, *sizes[0])
            return PinholeCamera.from_fov(*sizes[0], c.default_fov_deg)
        model, warnings = fit_to_frames(model, sizes, c.calibration or f"of {self.source.description}")
        for warning in warnings:
            self.logger.warning("%s", warning)
        return model

    def _model_frame(self) -> CameraModel | None:
        if self.camera_model is None:
            return None  # no reply: a live source not seen yet
        header = self.model_out.header(frame_id="body")
        return camera_model_frame(self.camera_model, header, name=self.config.camera)

    def _publish_model(self) -> None:
        if self.camera_model is not None:  # None: a live source not seen yet
            self.model_out.publish(self._model_frame())

    def _wait_for_subscriber(self) -> None:
        deadline = time.monotonic() + self.config.wait_for_subscriber_s
        while time.monotonic() < deadline and not self.stopping:
            if self.images.publisher.matching_status.matching:
                return
            self.sleep(0.02)
        if not self.stopping and self.config.wait_for_subscriber_s:
            self.logger.warning("no subscriber after %.1f s; publishing anyway", self.config.wait_for_subscriber_s)

    def run(self) -> None:
        if self.camera_model is not None:
            self._publish_model()
        self._wait_for_subscriber()
        if not (self._play_live() if self._live else self._play_files()):
            return  # stopping
        self._finished = True
        skipped = ", ".join(f"{count} {why}" for why, count in self.frames_skipped.items())
        self.logger.info("source finished after %d frames%s", self.frames_published,
                         f"; skipped: {skipped}" if skipped else "")
        if not self.config.exit_at_end:
            super().run()

    def _play_live(self) -> bool:
        """Publish a device's or a stream's frames as they come, stamped on arrival; a lost source is reopened
        (:meth:`_next_live`). False when stopping, True at ``end``."""
        c = self.config
        pending, self._first = self._first, None
        for index in itertools.count():
            if c.end is not None and index >= c.end:
                return True
            capture = pending if pending is not None else self._next_live()
            pending = None
            if capture is None:
                return False
            if self._unfitted:  # absent at start: its first frame fits the calibration, as at start
                self.camera_model = self._fitted_model(capture)
                self._sizes = [(m.width, m.height) for m in members(self.camera_model)]
                self._unfitted = False
                self._publish_model()
            if index >= c.start:
                self._publish(capture, time.time_ns())
            self.spin_once(0)  # timers (the camera model) and queries: a live source never sleeps between frames
        return True

    def _play_files(self) -> bool:
        """Play a file source at its own timing (or ``rate``), looping if asked. False when stopping."""
        c = self.config
        period = 1.0 / c.rate if c.rate else (1.0 / self.source.fps if getattr(self.source, "fps", None) else None)
        period_if_no_stamp = 1.0 / DEFAULT_FOLDER_RATE if period is None else period
        stamp_offset = 0
        for loop_index in itertools.count():
            captures = (itertools.chain([self._first], self._captures) if self._first is not None else
                        self._captures) if loop_index == 0 else iter(self._reopen())
            t0 = time.monotonic()
            first_stamp = last_stamp = None
            for index, capture in enumerate(itertools.islice(captures, c.start, c.end)):
                if self.stopping:
                    return False
                if capture.stamp_ns is not None:  # the lap's span, whatever paces the playback
                    first_stamp = capture.stamp_ns if first_stamp is None else first_stamp
                    last_stamp = capture.stamp_ns
                if c.rate is None and capture.stamp_ns is not None:
                    deadline = t0 + (capture.stamp_ns - first_stamp) * 1e-9
                else:
                    deadline = t0 + index * period_if_no_stamp
                if not self.sleep_until(deadline):
                    return False
                use_source_clock = c.stamp == "source" and capture.stamp_ns is not None
                stamp = capture.stamp_ns + stamp_offset if use_source_clock else time.time_ns()
                self._publish(capture, stamp)
            if not c.loop or self.stopping:
                return not self.stopping
            if first_stamp is not None and last_stamp is not None:
                # Keep the source clock increasing across loops: one more frame period after the last stamp.
                stamp_offset += last_stamp - first_stamp + int(period_if_no_stamp * 1e9)
        return True

    def _reopen(self) -> Source:
        self.source.close()
        self.source = self._open()
        return self.source

    def _publish(self, capture: Capture, stamp: int) -> None:
        sizes = [(image.shape[1], image.shape[0]) for image in capture.images]
        if self._sizes is not None and sizes != self._sizes:
            # Every worker would refuse it against the model (or map it with the wrong geometry): not on the wire.
            self._skip(f"frames not {'/'.join('%dx%d' % size for size in self._sizes)} like the camera model",
                       f"frame {self.frames_published + sum(self.frames_skipped.values())} is "
                       f"{'/'.join('%dx%d' % size for size in sizes)}, the camera model "
                       f"{'/'.join('%dx%d' % size for size in self._sizes)}: skipped")
            return
        outputs = {"image": self.images, "groundtruth_pose": self.pose_out, "groundtruth_pose2d": self.pose2d_out,
                   "odometry": self.odom_out}
        frames = capture_frames(capture, stamp, lambda name, s, frame_id: outputs[name].header(s, frame_id),
                                jpeg_quality=self.config.jpeg_quality, frame_id=self.frame_id)
        for name, frame in frames:
            outputs[name].publish(frame)
        self.frames_published += 1
        if self.rerun is not None:
            self._log_images(frames[-1][1].header, capture.images)

    def _log_images(self, header, images) -> None:
        import rerun as rr

        quality = self.config.rerun.jpeg_quality
        for index, pixels in enumerate(images):
            path = "image" if len(images) == 1 else f"image/{index}"
            if quality is not None:
                ok, buffer = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, quality])
                entity = rr.EncodedImage(contents=buffer.tobytes(), media_type="image/jpeg")
            else:
                entity = rr.Image(pixels, color_model="BGR" if pixels.ndim == 3 else "L")
            self.rerun_log(path, entity, header=header)

    def teardown(self) -> None:
        if self.source is not None:
            self.source.close()


WORKER = Camera
