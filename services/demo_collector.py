"""What the demo sees on the bus: every worker's outputs and status, with arrival times, for the results table.

The :class:`Collector` is a plain zenoh client of the graph (it subscribes like any other consumer and changes
nothing): images, heatlines, poses, loop-closure frames, object maps and status frames are decoded on zenoh's
threads and kept, keyed by capture stamp, together with the wall-clock time (``time.monotonic``) they arrived. The
demo evaluates these against the simulator's ground truth (services/demo_report.py), so the figures are those of
what the workers actually published.

Latency here is end-to-end on the bus: from the moment the camera's image reached the collector to the moment the
stage's output for the same capture stamp did (both seen by the same process and clock).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from schemas import FrameError, Image, Pose2D, Status, decode, keys, peek_schema
from schemas.detection import Heatlines, Heatmaps
from schemas.localization import PoseEstimate
from schemas.mapping import ObjectMap
from services.recording import DrainedSubscribers

log = logging.getLogger("semloc.demo")


@dataclass
class PoseRecord:
    stamp_ns: int
    arrived: float
    pose: np.ndarray          # (x, y, theta)
    status: str
    particles: int
    cluster_weight: float
    sample: np.ndarray | None = None   # (K, 3) weighted particle sample, for pictures
    state: str | None = None           # the localizer's judgement: localized / uncertain / lost


@dataclass
class Stream:
    """Arrival times of one output, keyed by capture stamp (first arrival wins)."""

    arrivals: dict[int, float] = field(default_factory=dict)
    count: int = 0

    def add(self, stamp_ns: int, arrived: float) -> None:
        self.count += 1
        self.arrivals.setdefault(int(stamp_ns), arrived)


class Collector:
    """Subscribes to a robot's streams on ``session``; ``on_pose`` / ``on_frame`` hooks feed live displays."""

    def __init__(self, session, robot: str, camera: str = "front",
                 on_pose: Callable[[PoseRecord], None] | None = None,
                 on_output: Callable[[str, int, float], None] | None = None,
                 on_image: Callable[[int, float], None] | None = None):
        self.robot, self.camera = robot, camera
        self.lock = threading.Lock()
        self.images = Stream()
        self.heatlines = Stream()
        self.heatmaps = Stream()
        self.last_heatmaps: Heatmaps | None = None
        self.loopclosure: dict[str, Stream] = {}
        self.loopclosure_frames: dict[str, list] = {}
        self.poses: list[PoseRecord] = []
        self.object_maps: list[tuple[float, ObjectMap]] = []
        self.status: dict[str, Status] = {}
        self.status_history: dict[str, list[tuple[float, Status]]] = {}
        self.ground_truth2d: dict[int, np.ndarray] = {}
        self.rejected = 0
        self.first_image: float | None = None
        self.last_image: float | None = None
        self._on_pose = on_pose
        self._on_output = on_output
        self._on_image = on_image
        # close() waits for the callbacks on what arrived before: none runs after it (nor counts, nor draws)
        self._subscribers = DrainedSubscribers(session)
        for key, callback in ((keys.camera_image(robot, camera), self._image),
                              (keys.detector_heatlines(robot), self._heatlines),
                              (keys.detector_heatmaps(robot), self._heatmaps),
                              (keys.localizer_pose(robot), self._pose),
                              (keys.mapper_objects(robot), self._objects),
                              (keys.loopclosure_all(robot), self._loopclosure),
                              (keys.robot_statuses(robot), self._status),
                              (keys.groundtruth_pose2d(robot), self._ground_truth)):
            self._subscribers.declare(key, callback)

    def close(self) -> None:
        if not self._subscribers.close():
            log.warning("collector: closed with samples still queued for it")

    # ------------------------------------------------------------------ zenoh callbacks (zenoh's threads)
    def _decode(self, sample, expected):
        try:
            return decode(sample.payload.to_bytes(), expected=expected)
        except FrameError as error:
            with self.lock:
                self.rejected += 1
            log.debug("collector: rejected %s: %s", sample.key_expr, error)
            return None

    def _image(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, Image)
        if frame is not None:
            with self.lock:
                self.images.add(frame.header.stamp_ns, arrived)
                self.first_image = arrived if self.first_image is None else self.first_image
                self.last_image = arrived
            if self._on_image:
                self._on_image(frame.header.stamp_ns, arrived)

    def _heatlines(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, Heatlines)
        if frame is not None:
            with self.lock:
                self.heatlines.add(frame.header.stamp_ns, arrived)
            if self._on_output:
                self._on_output("detector", frame.header.stamp_ns, arrived)

    def _heatmaps(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, Heatmaps)
        if frame is not None:
            with self.lock:
                self.heatmaps.add(frame.header.stamp_ns, arrived)
                self.last_heatmaps = frame

    def _pose(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, PoseEstimate)
        if frame is None:
            return
        record = PoseRecord(int(frame.header.stamp_ns), arrived, frame.pose(), frame.status, frame.particles,
                            float(frame.cluster_weight),
                            None if frame.sample is None else np.array(frame.sample, np.float32), frame.state)
        with self.lock:
            self.poses.append(record)
        if self._on_pose:
            self._on_pose(record)
        if self._on_output:
            self._on_output("localizer", record.stamp_ns, arrived)

    def _objects(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, ObjectMap)
        if frame is not None:
            with self.lock:
                self.object_maps.append((arrived, frame))

    def _loopclosure(self, sample) -> None:
        arrived = time.monotonic()
        frame = self._decode(sample, None)
        if frame is None:
            return
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            self.loopclosure.setdefault(name, Stream()).add(frame.header.stamp_ns, arrived)
            self.loopclosure_frames.setdefault(name, []).append((arrived, frame))
        if self._on_output:
            self._on_output(f"loopclosure/{name}", frame.header.stamp_ns, arrived)

    def _status(self, sample) -> None:
        arrived = time.monotonic()
        peeked = peek_schema(sample.payload.to_bytes())
        if peeked is None or peeked[0] != Status.schema_name:  # e.g. a loop-closure stream named "status"
            return
        frame = self._decode(sample, Status)
        if frame is not None:
            with self.lock:
                self.status[frame.worker] = frame
                self.status_history.setdefault(frame.worker, []).append((arrived, frame))

    def _ground_truth(self, sample) -> None:
        frame = self._decode(sample, Pose2D)
        if frame is not None:
            with self.lock:
                self.ground_truth2d[int(frame.header.stamp_ns)] = np.array([frame.x, frame.y, frame.theta])

    # ------------------------------------------------------------------ queries (any thread)
    def running(self, workers) -> list[str]:
        """Those of ``workers`` whose last status says running."""
        with self.lock:
            return [w for w in workers if w in self.status and self.status[w].state == "running"]

    def processed(self, main_inputs: dict[str, str] | None = None) -> dict[str, int]:
        """Frames each worker processed: on its main input when ``main_inputs`` names it, else in total."""
        main_inputs = main_inputs or {}
        with self.lock:
            out = {}
            for name, status in self.status.items():
                entry = status.inputs.get(main_inputs.get(name, ""))
                out[name] = entry.processed if entry is not None else status.processed
            return out

    def settled(self, workers, quiet_s: float) -> bool:
        """True when none of ``workers`` has processed anything for ``quiet_s`` seconds and none has a queue."""
        now = time.monotonic()
        with self.lock:
            for worker in workers:
                history = self.status_history.get(worker)
                if not history:
                    continue
                last_arrived, last = history[-1]
                if now - last_arrived > 3.0:  # no status lately: the worker is gone, nothing more to wait for
                    continue
                if any(stats.queued for stats in last.inputs.values()):
                    return False
                for arrived, earlier in reversed(history):
                    if now - arrived >= quiet_s:
                        if earlier.processed != last.processed:
                            return False
                        break
                else:
                    return False
        return True

    def snapshot(self) -> dict:
        """A consistent copy of everything collected so far (for the report)."""
        with self.lock:
            return {
                "images": Stream(dict(self.images.arrivals), self.images.count),
                "heatlines": Stream(dict(self.heatlines.arrivals), self.heatlines.count),
                "heatmaps": Stream(dict(self.heatmaps.arrivals), self.heatmaps.count),
                "last_heatmaps": self.last_heatmaps,
                "loopclosure": {k: Stream(dict(v.arrivals), v.count) for k, v in self.loopclosure.items()},
                "loopclosure_frames": {k: list(v) for k, v in self.loopclosure_frames.items()},
                "poses": list(self.poses),
                "object_maps": list(self.object_maps),
                "status": dict(self.status),
                "status_history": {w: [frame for _, frame in h] for w, h in self.status_history.items()},
                "first_image": self.first_image,
                "last_image": self.last_image,
                "rejected": self.rejected,
            }
