"""The demo's own rerun entities (``/<robot>/demo/...``): ground truth, errors, latencies, the topological graph.

The workers log what they compute; this adds what only the demo knows - the simulator's ground truth and the
comparison with it - live, from the collector's callbacks (zenoh threads: rerun's time is per thread, so every
log call sets its own time first).
"""

from __future__ import annotations

import threading

import numpy as np

GREY = [150, 150, 150]
GREEN = [0, 200, 0]
BLUE = [0, 120, 255]


class DemoViz:
    def __init__(self, stream, robot: str, stamps_ns: np.ndarray, truth2d: np.ndarray):
        self.rec = stream
        self.root = f"/{robot}/demo"
        self.index = {int(s): i for i, s in enumerate(stamps_ns)}
        self.truth2d = np.asarray(truth2d, float)
        self.lock = threading.Lock()
        self.estimates: list[np.ndarray] = []
        self.image_arrivals: dict[int, float] = {}

    def _time(self, stamp_ns: int) -> int | None:
        frame = self.index.get(int(stamp_ns))
        self.rec.set_time("capture", timestamp=int(stamp_ns) * 1e-9)
        if frame is not None:
            self.rec.set_time("frame", sequence=frame)
        return frame

    def log_world(self, semantic_map, T_world_cam: np.ndarray) -> None:
        """Static: the true objects (grey boxes with class labels) and the camera's true path."""
        import rerun as rr

        names = [semantic_map.class_names[k] for k in semantic_map.class_index]
        self.rec.log(f"{self.root}/world/truth/objects",
                     rr.Boxes3D(centers=semantic_map.positions, sizes=np.maximum(semantic_map.sizes, 0.02),
                                labels=[f"{n} (true)" for n in names], colors=GREY), static=True)
        self.rec.log(f"{self.root}/world/truth/camera_path",
                     rr.LineStrips3D([T_world_cam[:, :3, 3]], colors=[GREEN], radii=0.003), static=True)
        self.rec.log(f"{self.root}/errors/position_m", rr.SeriesLines(colors=[BLUE], names=["position error (m)"]),
                     static=True)
        self.rec.log(f"{self.root}/errors/heading_rad", rr.SeriesLines(colors=[[255, 140, 0]],
                                                                      names=["heading error (rad)"]), static=True)

    def on_pose(self, record) -> None:
        import rerun as rr

        from semloc_core.geometry import wrap_angle

        with self.lock:
            frame = self._time(record.stamp_ns)
            if frame is None:
                return
            truth = self.truth2d[frame]
            error = float(np.hypot(*(record.pose[:2] - truth[:2])))
            heading = float(abs(wrap_angle(record.pose[2] - truth[2])))
            self.rec.log(f"{self.root}/errors/position_m", rr.Scalars(error))
            self.rec.log(f"{self.root}/errors/heading_rad", rr.Scalars(heading))
            self.estimates.append(np.array([record.pose[0], record.pose[1]]))
            if len(self.estimates) >= 2:
                path = np.array(self.estimates)
                z = np.full((len(path), 1), 0.02)
                self.rec.log(f"{self.root}/world/estimate/path", rr.LineStrips3D([np.hstack([path, z])],
                                                                                 colors=[BLUE], radii=0.004))

    def on_output(self, stage: str, stamp_ns: int, arrived: float) -> None:
        import rerun as rr

        with self.lock:
            sent = self.image_arrivals.get(int(stamp_ns))
            if sent is None:
                return
            self._time(stamp_ns)
            self.rec.log(f"{self.root}/latency/{stage.replace('/', '_')}", rr.Scalars((arrived - sent) * 1e3))

    def on_image(self, stamp_ns: int, arrived: float) -> None:
        with self.lock:
            self.image_arrivals[int(stamp_ns)] = arrived

    def log_places(self, stamp_ns: int, poses) -> None:
        """The hybrid map's places (node ids) at the poses their key-frames were seen at while the localizer was
        localized (NaN rows: none recorded), drawn in the localizer's map view."""
        import rerun as rr

        poses = np.asarray(poses, float).reshape(-1, 3)
        known = np.flatnonzero(np.isfinite(poses).all(axis=1))
        with self.lock:
            self._time(stamp_ns)
            self.rec.log(f"{self.root}/places", rr.Points2D(poses[known, :2], radii=0.03, colors=[[255, 160, 0]],
                                                           labels=[str(k) for k in known]))

    def log_topology(self, stamp_ns: int, keyframes, positions, edges, loop_edges) -> None:
        """A topological map: keyframe nodes at their true positions, path edges and loop-closure edges."""
        import rerun as rr

        with self.lock:
            self._time(stamp_ns)
            ids = [str(k) for k in keyframes]
            xy = np.asarray(positions, float).reshape(-1, 2) * np.array([100.0, -100.0])  # graph view: y down
            self.rec.log(f"{self.root}/topology", rr.GraphNodes(ids, positions=xy, labels=ids))
            all_edges = [(str(a), str(b)) for a, b in list(edges) + list(loop_edges)]
            self.rec.log(f"{self.root}/topology", rr.GraphEdges(all_edges, graph_type="undirected"))
