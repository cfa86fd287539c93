"""Saver: a live run's outputs in standard formats, written while it runs (``semloc up --save DIR`` adds it).

The localizer's estimates go to ``trajectory.tum`` and a data set's ground truth to ``groundtruth.tum`` as they
arrive (one flushed line per stamp; a saver restarted after a crash continues them); when the mapper publishes a new object map or the loop closure changes its
topological map, the whole map is asked for (``mapper/save``, ``loopclosure/topomap``: what ``semloc map save``
asks) and its files are replaced atomically, at most once per ``period_s``. Files and frames: services/saving.py,
docs/conventions.md.

A file it cannot write (a full or read-only disk) makes it ``degraded`` with the file and the system's reason; the
poses wait in memory and the maps are asked for again, and both are written as soon as the disk takes them (tried
with each pose and every ``period_s``), the status then back to ``running``. A map file is never replaced by a
partial one.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from schemas import Pose2D, keys
from schemas.localization import PoseEstimate
from schemas.loopclosure import TopoMapUpdate
from schemas.mapping import ANY_OBJECT_MAP
from semloc_core.io.atomic import remove_partial_writes
from services.bus import QueryError
from services.runtime import Worker, WorkerConfig
from services.saving import (GROUNDTRUTH_FILE, HOT_FRACTION, MAP_FILES, TRAJECTORY_FILE, TumStream, fetch_maps,
                             pose_of, write_maps)


class SaverConfig(WorkerConfig):
    folder: str = Field(description="where the files go (created)")
    period_s: float = Field(2.0, gt=0, description="changed maps are asked for and rewritten at most this often")
    hot_fraction: float = Field(HOT_FRACTION, gt=0, le=1,
                                description="voxels.ply: voxels scoring at least this fraction of their class's best")
    query_timeout_s: float = Field(2.5, gt=0, description="how long to wait for a map's answer (under the "
                                                          "heartbeat's stalled_after_s: the wait blocks the worker)")


class Saver(Worker):
    """Writes the pose stream as it comes and the maps when they change."""

    Config = SaverConfig

    def setup(self) -> None:
        c = self.config
        self.folder = Path(c.folder)
        # restarted after a crash: continue the files the crashed process wrote (a new run starts them afresh)
        self.resume = self._restarts > 0
        for name in MAP_FILES:  # the temporary files a process killed mid-write left
            try:
                remove_partial_writes(self.folder / name)
            except OSError:
                pass  # a read-only folder: they stay, beside whole files
        self.trajectory = TumStream(self.folder / TRAJECTORY_FILE, resume=self.resume)
        if self.trajectory.cut_short:
            self.logger.warning("%s ended in a line cut short (%d bytes): dropped; continuing after its %d poses",
                                self.trajectory.path, self.trajectory.cut_short, self.trajectory.lines)
        self._write(self.trajectory)
        self.groundtruth: TumStream | None = None  # opened with the first ground-truth pose
        self.mapper_changed = self.topomap_changed = False
        self.input("pose", keys.localizer_pose(self.robot), PoseEstimate, self.on_pose, policy="lossless", depth=1024)
        self.input("groundtruth", keys.groundtruth_pose2d(self.robot), Pose2D, self.on_groundtruth,
                   policy="lossless", depth=1024)
        self.input("objects", keys.mapper_objects(self.robot), ANY_OBJECT_MAP, self.on_objects, policy="latest",
                   depth=1)
        self.input("topomap", keys.loopclosure_topomap(self.robot), TopoMapUpdate, self.on_topomap, policy="latest",
                   depth=1)
        self.every(c.period_s, self.save_maps)
        self.logger.info("saving to %s", self.folder)

    def on_pose(self, frame: PoseEstimate) -> None:
        self._write(self.trajectory, pose_of(frame))

    def on_groundtruth(self, frame: Pose2D) -> None:
        if self.groundtruth is None:
            self.groundtruth = TumStream(self.folder / GROUNDTRUTH_FILE, resume=self.resume)
        self._write(self.groundtruth, pose_of(frame))

    def _write(self, stream: TumStream, pose=None) -> None:
        """Add ``pose`` to ``stream`` (none: write what waits), reporting a write that fails."""
        try:
            stream.add(*pose) if pose is not None else stream.write()
        except OSError as error:
            self.write_failed(stream.path.name, error, f"{stream.pending} pose(s) waiting")
        else:
            self.write_succeeded(stream.path.name)

    def on_objects(self, _frame) -> None:
        self.mapper_changed = True

    def on_topomap(self, _frame: TopoMapUpdate) -> None:
        self.topomap_changed = True  # places, edges or the frames' poses changed

    def save_maps(self) -> None:
        """Ask for the maps that changed since the last save and replace their files; write the poses waiting."""
        for stream in (self.trajectory, self.groundtruth):
            if stream is not None and stream.pending:
                self._write(stream)
        if not (self.mapper_changed or self.topomap_changed):
            return
        wanted = (self.mapper_changed, self.topomap_changed)
        self.mapper_changed = self.topomap_changed = False
        try:
            voxel_map, topomap = fetch_maps(self.session, self.robot, self.config.query_timeout_s, *wanted)
        except QueryError as error:
            self.mapper_changed, self.topomap_changed = wanted  # try again next period
            raise RuntimeError(f"asking for the maps failed: {error}") from None
        # A map asked for and not answered is asked for again next period.
        self.mapper_changed |= wanted[0] and voxel_map is None
        self.topomap_changed |= wanted[1] and topomap is None
        try:
            write_maps(self.folder, voxel_map, topomap, self.config.hot_fraction)
        except OSError as error:  # the files written before it are whole; all are written again next period
            self.mapper_changed |= voxel_map is not None
            self.topomap_changed |= topomap is not None
            self.write_failed("maps", error)
        else:
            self.write_succeeded("maps")

    def teardown(self) -> None:
        for stream in (self.trajectory, self.groundtruth):
            if stream is not None:
                try:
                    stream.close()
                except OSError as error:
                    self.write_failed(stream.path.name, error, f"{stream.pending} pose(s) lost")


WORKER = Saver
