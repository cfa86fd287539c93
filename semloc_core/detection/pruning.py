"""Which pyramid levels can see an object where: the image rows in which an object standing on a support plane would
have the apparent size a level matches (issue 35: "prune scales by the expected object distance").

A level ``s`` of the template detector matches objects whose longer side spans about ``template_px / s`` pixels
(``TemplateDetector.level_object_px``). An object of silhouette size ``L`` (its longer side, metres) whose centre is
at depth ``z`` along the optical axis spans ``f L / z`` pixels (pinhole). Objects stand on a support plane at height
``support_z`` (a table top, the floor), so an object of height ``h`` has its centre on the plane ``support_z + h / 2``:
each pixel's ray meets that plane at one depth, which gives the apparent size of such an object centred on that
pixel. Per pixel, the sizes of every class (its range of heights and sizes), at either end of the camera's height
tolerance, give a size range; a level runs on the rows where its share of the size axis (as in ``levels_for``: up to
the geometric midpoints with its neighbours) meets that range widened by ``size_factor``. With a support polygon
(the table's outline, grown by ``polygon_margin`` for the pose's error and the lag of the pose behind the image),
only rays meeting the plane inside it count. Rays that never meet a centre plane in front of the camera see no
object of that class.

The rows are on the detector's output grid; ``TemplateDetector.heatmaps(image, rows=...)`` matches each level on
its rows (plus the template's reach), and leaves it out elsewhere: the heatmap there is the max over the other
levels, never thresholded. What this needs at run time is the camera's pose in the world - a 2-D body pose (the
localizer's), the camera's attitude (``T_body_cam``, per frame for a hand-held camera) and its height above the
floor - the support plane, and each class's size range (from an object map, ``class_shapes``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from semloc_core.camera import PinholeCamera
from semloc_core.detection.templates import level_shares
from semloc_core.geometry import inside_polygon, pose2d_to_transform

# Each class's silhouette longer side from its box extents (dx, dy, dz): seen from the side, the horizontal extent
# spans between the box's shorter side and its diagonal; the diagonal bounds it.
_SHAPE_COLUMNS = ("height_min", "height_max", "size_min", "size_max")


@dataclass(frozen=True)
class PruneParams:
    """How generous the rows are. ``size_factor``: a level runs where the expected size is within this factor of its
    share of the size axis (1.19 = half a level step of the demo's pyramid, whose levels are 1.41x apart: the object's
    size varies with the view and the pose's error; an object between two levels is matched by both). ``polygon_margin``
    (m): the support polygon grown by this much (the pose's error and its lag behind the image).
    ``camera_height_tolerance`` (m): the configured camera height is right to within this (a hand-held camera's
    height wanders that much). With a 3-D pose of the frame (``height_from_pose``), the camera's height is that pose's,
    known to within ``pose_height_tolerance`` (m: a visual-inertial odometry's height error; or 3 standard deviations
    of the pose's own, if larger) plus ``vertical_speed`` (m/s: how fast a hand-held camera moves up and down while
    walking) times the time between the pose and the image."""

    size_factor: float = 1.19
    polygon_margin: float = 0.2
    camera_height_tolerance: float = 0.1
    pose_height_tolerance: float = 0.02
    vertical_speed: float = 0.5

    def __post_init__(self) -> None:
        if not 1.0 <= self.size_factor <= 4.0:
            raise ValueError(f"size_factor must be within [1, 4], got {self.size_factor}")
        if not 0.0 <= self.polygon_margin <= 10.0 or not 0.0 <= self.camera_height_tolerance <= 5.0:
            raise ValueError("polygon_margin must be within [0, 10] m and camera_height_tolerance within [0, 5] m")
        if not 0.0 <= self.pose_height_tolerance <= 5.0 or not 0.0 <= self.vertical_speed <= 10.0:
            raise ValueError("pose_height_tolerance must be within [0, 5] m and vertical_speed within [0, 10] m/s")


def height_from_pose(T_world_body: np.ndarray, T_body_cam: np.ndarray, gap_s: float,
                     params: PruneParams = PruneParams(), height_sigma: float = 0.0) -> tuple[float, float]:
    """(camera height, tolerance) from a 3-D body pose ``gap_s`` seconds from the image: the camera centre's height
    with the image's extrinsic, within the pose's accuracy (``params.pose_height_tolerance`` or 3 ``height_sigma``,
    the pose's own standard deviation) and the vertical motion in the gap (``params.vertical_speed``)."""
    height = float((np.asarray(T_world_body, float) @ np.asarray(T_body_cam, float))[2, 3])
    accuracy = max(params.pose_height_tolerance, 3.0 * float(height_sigma))
    return height, accuracy + params.vertical_speed * abs(float(gap_s))


@dataclass(frozen=True)
class SupportScene:
    """Where objects can be: a support plane at ``support_z`` (m), optionally bounded by ``polygon`` ((n, 2) world
    x, y), and each class's ``shapes`` row (height min, height max, silhouette size min, max; metres)."""

    support_z: float
    shapes: np.ndarray
    polygon: np.ndarray | None = None

    def __post_init__(self) -> None:
        shapes = np.asarray(self.shapes, dtype=float).reshape(-1, len(_SHAPE_COLUMNS))
        if shapes.size == 0 or not np.isfinite(shapes).all() or (shapes <= 0).any() or (shapes > 100).any():
            raise ValueError("shapes must be rows of positive heights and sizes (m) up to 100 m")
        if (shapes[:, 0] > shapes[:, 1]).any() or (shapes[:, 2] > shapes[:, 3]).any():
            raise ValueError("each class's shape row must be (height min <= max, size min <= max)")
        object.__setattr__(self, "shapes", shapes)
        if not math.isfinite(self.support_z) or abs(self.support_z) > 1e4:
            raise ValueError(f"support_z must be finite and within 1e4 m, got {self.support_z}")
        if self.polygon is not None:
            polygon = np.asarray(self.polygon, dtype=float)
            if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) < 3 or not np.isfinite(polygon).all():
                raise ValueError("polygon must be at least three finite (x, y) vertices")
            object.__setattr__(self, "polygon", polygon)


def class_shapes(sizes: np.ndarray, class_index: np.ndarray, classes: int) -> np.ndarray:
    """(classes, 4) shape rows of ``SupportScene`` from an object map's box extents ``sizes`` (n, 3) and each
    object's class; a class with no object takes the range over every object (it may be anywhere in it)."""
    sizes = np.asarray(sizes, dtype=float).reshape(-1, 3)
    class_index = np.asarray(class_index, dtype=int).reshape(-1)
    if sizes.shape[0] == 0 or sizes.shape[0] != class_index.shape[0]:
        raise ValueError("class_shapes needs one class index per object and at least one object")
    horizontal = np.hypot(sizes[:, 0], sizes[:, 1])
    rows = np.stack([sizes[:, 2], sizes[:, 2], np.maximum(sizes[:, :2].min(axis=1), sizes[:, 2]),
                     np.maximum(horizontal, sizes[:, 2])], axis=1)

    def span(members: np.ndarray) -> list[float]:
        chosen = rows[members]
        return [chosen[:, 0].min(), chosen[:, 1].max(), chosen[:, 2].min(), chosen[:, 3].max()]

    everything = span(np.ones(len(rows), bool))
    return np.array([span(class_index == k) if (class_index == k).any() else everything for k in range(classes)])


def camera_in_world(pose2d, camera_height: float, T_body_cam: np.ndarray) -> np.ndarray:
    """T_world_cam of a camera ``camera_height`` m above the floor on a body at planar pose (x, y, theta)."""
    T = pose2d_to_transform(*(float(v) for v in pose2d)) @ np.asarray(T_body_cam, dtype=float)
    T[2, 3] = camera_height
    return T


def grown_polygon(polygon: np.ndarray, margin: float) -> np.ndarray:
    """The polygon with every edge moved ``margin`` outwards and the corners mitred (for a convex outline it holds
    every point within ``margin`` of the polygon; corners sharper than 30 degrees are cut at 2 x margin)."""
    polygon = np.asarray(polygon, dtype=float)
    if margin <= 0:
        return polygon
    area = 0.5 * np.sum(polygon[:, 0] * np.roll(polygon[:, 1], -1) - np.roll(polygon[:, 0], -1) * polygon[:, 1])
    edges = np.roll(polygon, -1, axis=0) - polygon
    edges /= np.maximum(np.linalg.norm(edges, axis=1, keepdims=True), 1e-12)
    outward = np.stack([edges[:, 1], -edges[:, 0]], axis=1) * (1.0 if area > 0 else -1.0)
    before = np.roll(outward, 1, axis=0)            # the normal of the edge ending at each vertex
    bisector = outward + before
    cosine = np.clip(np.sum(outward * before, axis=1, keepdims=True), -0.75, 1.0)   # cos of the turn
    return polygon + bisector * margin / (1.0 + cosine)


def sample_rays(camera: PinholeCamera, grid: tuple[int, int]) -> np.ndarray:
    """The camera-frame unit rays ``level_rows`` samples: every other row of the output grid, 12 columns with both
    edges (a level's rows, not its columns, are what is kept), (rows / 2, 12, 3)."""
    rows, cols = int(grid[0]), int(grid[1])
    u = (np.unique(np.linspace(0, cols - 1, 12).round()) + 0.5) * camera.width / cols - 0.5
    v = (np.arange(0, rows, 2) + 0.5) * camera.height / rows - 0.5
    return camera.rays_cam(*np.meshgrid(u, v))


def level_rows(camera: PinholeCamera, T_world_cam: np.ndarray, scene: SupportScene, level_px: Mapping[float, float],
               grid: tuple[int, int], params: PruneParams = PruneParams(),
               rays_cam: np.ndarray | None = None) -> dict[float, tuple[int, int]]:
    """Per level, the output-grid rows [first, last + 1) where an object of that level's size can be centred; a level
    absent from the result sees no object anywhere. ``grid`` is the detector's (rows, cols) output grid;
    ``rays_cam``: ``sample_rays(camera, grid)`` computed once (a stream's camera does not change)."""
    rows = int(grid[0])
    rays_cam = sample_rays(camera, grid) if rays_cam is None else rays_cam
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    rays = rays_cam @ T_world_cam[:3, :3].T
    focal = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    origin = T_world_cam[:3, 3]
    tolerance = params.camera_height_tolerance
    # Every (camera height, class, object height) at once: the object centres' plane above the camera's centre.
    combos = np.unique([(centre_above, size_min, size_max)
                       for camera_z in {origin[2] - tolerance, origin[2] + tolerance}
                       for height_min, height_max, size_min, size_max in scene.shapes
                       for centre_above in {scene.support_z + height_min / 2 - camera_z,
                                            scene.support_z + height_max / 2 - camera_z}], axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = combos[:, 0, None, None] / rays[None, ..., 2]   # range along each unit ray to the plane
    seen = np.isfinite(reach) & (reach > 0)
    if scene.polygon is not None:
        x, y = origin[0] + reach * rays[..., 0], origin[1] + reach * rays[..., 1]
        x, y = np.where(seen, x, origin[0]), np.where(seen, y, origin[1])
        seen &= inside_polygon(x, y, grown_polygon(scene.polygon, params.polygon_margin))
    depth = np.where(seen, reach * rays_cam[..., 2], np.inf)
    with np.errstate(divide="ignore"):
        low = np.where(seen, np.log(focal * combos[:, 1, None, None] / depth), np.inf).min(axis=0)
        high = np.where(seen, np.log(focal * combos[:, 2, None, None] / depth), -np.inf).max(axis=0)
    widen = math.log(params.size_factor)
    low, high = low - widen, high + widen
    kept = {}
    for scale, (first, last) in level_shares(level_px).items():
        answered = ((high >= first) & (low <= last)).any(axis=1)
        if answered.any():
            hits = 2 * np.flatnonzero(answered)   # sampled every other row: a row more on either side
            kept[scale] = (max(0, int(hits[0]) - 1), min(rows, int(hits[-1]) + 2))
    return kept


def work_share(rows_of_levels: Mapping[float, tuple[int, int]], scales, grid_rows: int) -> float:
    """The share of the exhaustive matching's work these rows are (a level's work ~ its pixels, scale^2)."""
    total = sum(s * s for s in scales)
    return sum(s * s * (b - a) / grid_rows for s, (a, b) in rows_of_levels.items()) / total


class LevelPruner:
    """The rows of each pyramid level of ``detector`` (a ``TemplateDetector``) for a frame, from the body's planar
    pose: what ``detector.heatmaps(image, rows=...)`` takes. One per camera stream (the rays are the camera's)."""

    def __init__(self, detector, camera: PinholeCamera, scene: SupportScene, camera_height: float,
                 params: PruneParams = PruneParams()):
        if not isinstance(camera, PinholeCamera):
            raise ValueError(f"pruning needs a pinhole camera, got {type(camera).__name__}")
        if not math.isfinite(camera_height) or not -1e4 <= camera_height <= 1e4:
            raise ValueError(f"camera_height must be finite, got {camera_height}")
        self.camera, self.scene, self.camera_height, self.params = camera, scene, float(camera_height), params
        self.level_px = detector.level_object_px()
        self.scales = tuple(detector.match.scales)
        self.grid = detector.output_shape((camera.height, camera.width))
        # what does not change from frame to frame: the rays, the polygon grown by its margin
        self._rays = sample_rays(camera, self.grid)
        self._scene = scene if scene.polygon is None else SupportScene(
            scene.support_z, scene.shapes, grown_polygon(scene.polygon, params.polygon_margin))
        self._params = replace(params, polygon_margin=0.0)

    def rows(self, pose2d, T_body_cam: np.ndarray | None = None,
             height: tuple[float, float] | None = None) -> dict[float, tuple[int, int]]:
        """{level: (first, last + 1)} for a body at ``pose2d`` (x, y, theta), the camera at its extrinsic or at
        the frame's attitude ``T_body_cam``; at ``height`` (camera height, tolerance: ``height_from_pose``) where
        it is known for the frame and tighter than the configured ``camera_height`` +- ``camera_height_tolerance``."""
        camera_height, params = self.camera_height, self._params
        if height is not None and height[1] < params.camera_height_tolerance:
            camera_height, params = height[0], replace(params, camera_height_tolerance=height[1])
        T_world_cam = camera_in_world(pose2d, camera_height,
                                      self.camera.T_body_cam if T_body_cam is None else T_body_cam)
        return level_rows(self.camera, T_world_cam, self._scene, self.level_px, self.grid, params, self._rays)

    def agrees(self, height: tuple[float, float]) -> bool:
        """Whether a frame's (camera height, tolerance) is consistent with the configured ``camera_height`` +-
        ``camera_height_tolerance``: a pose that puts the camera elsewhere is another frame's or wrong, and pruning by
        it could drop every level."""
        return abs(height[0] - self.camera_height) <= self.params.camera_height_tolerance + height[1]

    def share(self, rows: Mapping[float, tuple[int, int]]) -> float:
        """The share of the exhaustive matching's work that ``rows`` asks for (before bands are rounded)."""
        return work_share(rows, self.scales, self.grid[0])


def build_pruner(detector, camera, object_map, support_z: float, camera_height: float, support_polygon=None,
                 params: PruneParams = PruneParams()) -> LevelPruner:
    """A ``LevelPruner`` whose classes' sizes come from ``object_map`` (a ``SemanticMap``: its objects' extents);
    the detector's classes the map lacks may have any of the map's sizes."""
    names = tuple(object_map.class_names)
    shapes = class_shapes(object_map.sizes, object_map.class_index, len(names))
    everything = np.array([shapes[:, 0].min(), shapes[:, 1].max(), shapes[:, 2].min(), shapes[:, 3].max()])
    present = set(np.asarray(object_map.class_index).tolist())
    rows = [shapes[names.index(name)] if name in names and names.index(name) in present else everything
            for name in detector.classes]
    polygon = None if support_polygon is None else np.asarray(support_polygon)
    scene = SupportScene(float(support_z), np.array(rows), polygon)
    return LevelPruner(detector, camera, scene, camera_height, params)
