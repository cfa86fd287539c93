"""A run's outputs in standard formats: what ``semloc up --save DIR``, ``semloc map save DIR`` and
``semloc export SESSION.mcap -o DIR`` write (docs/conventions.md, "Files and their frames"):

* ``trajectory.tum``: the localizer's estimates (``localizer/pose``), the planar body pose (z = 0, yaw only), one
  line per stamp;
* ``groundtruth.tum``: a data set's ground truth (``groundtruth/pose2d``), same frame and format;
* ``objects.json``: the mapper's objects in the localizer's map format (``semloc.semantic_map``), from
  ``mapper/save``, as are
* ``voxels.npz``: the mapper's score volumes (``semloc.voxel_map``), and ``voxels.ply``: its hot voxels (at least
  ``hot_fraction`` of their class's best): x y z, colour, score, class_index;
* ``topomap.json``, ``topomap.graphml``: the topological map (``loopclosure/topomap``), nodes placed at their
  key-frames' estimates.

TUM files grow a line at a time (written at once: a crash loses nothing written; a line a full disk refuses waits for
the next write that succeeds, the file never ending mid-line); the other files are replaced atomically
(semloc_core/io/atomic.py), so a reader never sees half a file and a failed write leaves the previous one whole.
The same functions write them whoever fetched the frames, so ``map save`` writes byte for byte what ``--save``
writes for the same state of the workers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from schemas import keys
from schemas.loopclosure import TopoMap
from schemas.mapping import VoxelMap
from services.bus import query

TRAJECTORY_FILE = "trajectory.tum"
GROUNDTRUTH_FILE = "groundtruth.tum"
OBJECTS_FILE = "objects.json"
VOXELS_FILE = "voxels.npz"
CLOUD_FILE = "voxels.ply"
TOPOMAP_FILES = ("topomap.json", "topomap.graphml")
MAP_FILES = (OBJECTS_FILE, VOXELS_FILE, CLOUD_FILE, *TOPOMAP_FILES)
HOT_FRACTION = 0.5  # of each class's best score: the voxels in voxels.ply


class TumStream:
    """A TUM file written a pose at a time: one line per stamp (a newer estimate of the last stamp, e.g. the pose an
    operator set, replaces its line); stamps older than the last line are skipped and counted (TUM is in time
    order). ``resume``: continue the file a crashed writer left (its complete lines kept, a line cut short dropped:
    ``cut_short`` bytes) instead of starting it afresh. Nothing is written before :meth:`write` or the first :meth:`add`.

    Every line is written as it is added. A write that fails (a full or read-only disk: ``add`` and ``write`` raise
    the ``OSError``) is cut off again, so the file always ends with a whole line; the lines not written wait, in
    order, and go out with the next write that succeeds (at most ``max_pending``: beyond, the oldest are dropped and
    counted in ``lost``)."""

    def __init__(self, path, resume: bool = False, max_pending: int = 100_000):
        from semloc_core.io.trajectory import TUM_HEADER

        self.path = Path(path)
        self.max_pending = max_pending
        self.last_stamp_ns: int | None = None
        self.lines = 0
        self.skipped = 0
        self.lost = 0
        self._file = None
        self._size = 0  # bytes of whole lines in the file
        self._last_offset = 0  # where its last pose line starts
        self._header = b""  # written with the first lines (a new file)
        self._pending: list[bytes] = []  # lines not written yet, in order
        self.cut_short = 0  # resumed: bytes of the line the crash cut short, dropped
        if resume and self.path.is_file():
            self._resume()
        else:
            self._header = (TUM_HEADER + "\n").encode()
            self._truncate = True  # a new run: the file starts afresh (at the first write)

    def _resume(self) -> None:
        from semloc_core.io.trajectory import TUM_HEADER

        data = self.path.read_bytes()
        complete = data[:data.rfind(b"\n") + 1]  # a line cut short by the crash is cut off at the first write
        self.cut_short = len(data) - len(complete)
        if not complete:  # cut within its header: started afresh, header first
            self._header, self._truncate = (TUM_HEADER + "\n").encode(), True
            return
        self._size = self._last_offset = len(complete)
        self._truncate = False
        offset = 0
        for line in complete.splitlines(keepends=True):
            fields = line.split()
            if fields and not line.startswith(b"#"):
                seconds, _, fraction = fields[0].decode().partition(".")
                self.last_stamp_ns = int(seconds) * 1_000_000_000 + int((fraction + "0" * 9)[:9])
                self._last_offset = offset
                self.lines += 1
            offset += len(line)

    def add(self, stamp_ns: int, x: float, y: float, theta: float) -> None:
        from semloc_core.io.trajectory import planar_tum_line

        stamp_ns = int(stamp_ns)
        if self.last_stamp_ns is not None and stamp_ns < self.last_stamp_ns:
            self.skipped += 1
            return
        line = (planar_tum_line(stamp_ns, x, y, theta) + "\n").encode()
        if stamp_ns == self.last_stamp_ns:
            if self._pending:
                self._pending[-1] = line
            else:  # the line in the file is rewritten
                self._size = self._last_offset
                self._pending.append(line)
        else:
            self.lines += 1
            self._pending.append(line)
            if len(self._pending) > self.max_pending:
                del self._pending[0]
                self.lost += 1
        self.last_stamp_ns = stamp_ns
        self.write()

    @property
    def pending(self) -> int:
        """Lines waiting for a write to succeed."""
        return len(self._pending)

    def write(self) -> None:
        """Write the lines waiting (with the header of a new file); raises ``OSError`` naming the file if it cannot,
        the file then ending where it did."""
        if not (self._pending or self._header or self._file is None):
            return
        data = self._header + b"".join(self._pending)
        try:
            if self._file is None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._file = open(self.path, "wb" if self._truncate else "r+b", buffering=0)  # noqa: SIM115
                self._truncate = False
            self._file.seek(self._size)
            written = 0
            while written < len(data):
                written += self._file.write(memoryview(data)[written:])
            self._file.truncate(self._size + len(data))  # a rewritten last line may be shorter
        except OSError as error:
            if self._file is not None:
                try:
                    self._file.truncate(self._size)  # no line cut short: the file ends with a whole line
                except OSError:
                    pass
            raise OSError(error.errno, error.strerror, str(self.path)) from error
        if self._pending:
            self._last_offset = self._size + len(data) - len(self._pending[-1])
        self._size += len(data)
        self._header = b""
        self._pending.clear()

    def close(self) -> None:
        """Write what waits (``OSError`` if it cannot) and close the file."""
        try:
            self.write()
        finally:
            if self._file is not None:
                self._file.close()
                self._file = None


def fetch_maps(session, robot: str, timeout: float = 5.0, mapper: bool = True,
               topomap: bool = True) -> tuple[VoxelMap | None, TopoMap | None]:
    """The mapper's whole map and the loop closure's topological map (those asked for), asked on the bus (None: no
    answer). Raises ``services.bus.QueryError`` for an error answer, ``schemas.FrameError`` for a bad one."""
    voxel_maps = query(session, keys.mapper_save(robot), reply_type=VoxelMap, timeout=timeout) if mapper else []
    topomaps = query(session, keys.loopclosure_topomap(robot), reply_type=TopoMap, timeout=timeout) if topomap else []
    return (voxel_maps[0] if voxel_maps else None), (topomaps[0] if topomaps else None)


def write_maps(folder, voxel_map: VoxelMap | None, topomap: TopoMap | None,
               hot_fraction: float = HOT_FRACTION) -> list[Path]:
    """Write the files of the maps given (see the module docstring) into ``folder``; returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    if voxel_map is not None:
        written += _write_voxel_map(folder, voxel_map, hot_fraction)
    if topomap is not None:
        written += write_topomap(folder, topomap)
    return written


def write_objects(folder: Path, frame) -> Path:
    """``objects.json`` of an ObjectMap (or VoxelMap) frame."""
    from semloc_core.io.semantic_map import save_semantic_map
    from services.frames import semantic_map_from_frame

    path = folder / OBJECTS_FILE
    save_semantic_map(semantic_map_from_frame(frame), path)  # atomically
    return path


def _write_voxel_map(folder: Path, frame: VoxelMap, hot_fraction: float) -> list[Path]:
    from semloc_core.io.voxel_map import save_ply, save_voxel_map
    from semloc_core.mapping.volume import hot_voxels
    from services.frames import grid_of

    scores = np.asarray(frame.score_volumes)
    grid = grid_of(frame)
    save_voxel_map(folder / VOXELS_FILE, frame.class_names, frame.origin, frame.voxel_size, scores, frame.views,
                   frame.frames)
    cloud = hot_voxels(scores, grid, hot_fraction)
    save_ply(folder / CLOUD_FILE, cloud["points"], cloud["colors"],
             {"score": cloud["score"], "class_index": cloud["class_index"]})
    return [write_objects(folder, frame), folder / VOXELS_FILE, folder / CLOUD_FILE]


def write_topomap(folder: Path, frame: TopoMap) -> list[Path]:
    from semloc_core.io.loopclosure import save_topomap
    from services.frames import topological_map_from_frame

    topomap, poses = topological_map_from_frame(frame)
    paths = [folder / name for name in TOPOMAP_FILES]
    for path in paths:
        save_topomap(path, topomap, poses, frame.keyframe_stamps_ns)
    return paths


def pose_of(frame) -> tuple[int, float, float, float]:
    """(stamp_ns, x, y, theta) of a PoseEstimate or Pose2D."""
    return int(frame.header.stamp_ns), float(frame.x), float(frame.y), float(frame.theta)


def export_recording(path, folder, robot: str) -> dict[str, int]:
    """The files of a recorded session (``semloc record``): the trajectory and ground truth as they were published,
    the last object map, and the topological map rebuilt from its updates, with the key-frames' poses they carry
    (recordings made before updates carried poses: none).
    The score volumes never travel on the bus, so a recording has no ``voxels.*`` (``semloc map save`` during the
    run writes them). Returns counts of what was read and written; raises ``CutFileError`` for a bad file (services/cut_files.py)."""
    from schemas import FrameError, Header, Pose2D, decode
    from schemas.localization import PoseEstimate
    from schemas.loopclosure import LoopClosure, TopoMapUpdate
    from schemas.mapping import ANY_OBJECT_MAP
    from semloc_core.loopclosure.topomap import edges_from_frames
    from services.recording import read_messages

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {keys.localizer_pose(robot): PoseEstimate, keys.groundtruth_pose2d(robot): Pose2D,
              keys.mapper_objects(robot): ANY_OBJECT_MAP, keys.loopclosure_events(robot): LoopClosure,
              keys.loopclosure_topomap(robot): TopoMapUpdate}
    streams: dict[str, TumStream] = {}
    counts = {"messages": 0, "rejected": 0}
    objects = None
    frame_stamps: dict[int, int] = {}
    frame_node: dict[int, int] = {}
    keyframes: dict[int, int] = {}
    poses: dict[int, tuple[float, float, float]] = {}  # frame -> pose (NaN: withdrawn)
    frames_seen = 0  # the map's frames, pending ones included (no update assigns a frame while it is pending)
    try:
        for topic, _time, payload in read_messages(path, include=tuple(wanted)):
            try:
                frame = decode(payload, expected=wanted[topic])
            except FrameError:
                counts["rejected"] += 1
                continue
            counts["messages"] += 1
            if isinstance(frame, PoseEstimate) or topic == keys.groundtruth_pose2d(robot):
                name = TRAJECTORY_FILE if isinstance(frame, PoseEstimate) else GROUNDTRUTH_FILE
                if name not in streams:
                    streams[name] = TumStream(folder / name)
                streams[name].add(*pose_of(frame))
            elif isinstance(frame, ANY_OBJECT_MAP):
                objects = frame
            elif isinstance(frame, LoopClosure):
                frame_stamps[frame.frame] = int(frame.header.stamp_ns)
                frames_seen = max(frames_seen, frame.frame + 1)
            else:  # TopoMapUpdate: (frame, node) assignments and new nodes with their key-frames
                frames_seen = max(frames_seen, int(frame.frames))
                frame_node.update({int(f): int(n) for f, n in np.asarray(frame.assigned).tolist()})
                keyframes.update({int(n): int(k) for n, k in np.asarray(frame.new_nodes).tolist()})
                if frame.posed_frames is not None:  # the frames' poses as the places keep them, changes in order
                    poses.update(zip(frame.posed_frames.tolist(), map(tuple, frame.frame_poses.tolist())))
    finally:
        for stream in streams.values():
            stream.close()
    counts.update({name: stream.lines for name, stream in streams.items()})
    if objects is not None:
        write_objects(folder, objects)
        counts[OBJECTS_FILE] = len(objects.class_index)
    if keyframes and sorted(keyframes) != list(range(len(keyframes))):
        counts["topomap_incomplete"] = 1  # the recording started after the first places were made
    elif keyframes:
        frames = max(max(frame_node, default=-1) + 1, max(keyframes.values()) + 1, frames_seen)
        nodes = np.full(frames, -1, np.int64)
        nodes[list(frame_node)] = list(frame_node.values())
        order = sorted(keyframes)
        keyframe_of = np.array([keyframes[n] for n in order], np.int64)
        stamps = np.array([frame_stamps.get(int(k), -1) for k in keyframe_of], np.int64)  # -1: not recorded
        edges, transitions = edges_from_frames(nodes)
        header = Header(robot=robot, stream="loopclosure/topomap", stamp_ns=max(frame_stamps.values(), default=0))
        topomap = TopoMap(header=header, keyframes=keyframe_of, keyframe_stamps_ns=stamps, frame_node=nodes,
                          edges=edges, transitions=transitions,
                          keyframe_poses=np.array([poses.get(int(k), (np.nan,) * 3) for k in keyframe_of], np.float64))
        write_topomap(folder, topomap)
        counts["topomap_nodes"] = len(keyframe_of)
    return counts
