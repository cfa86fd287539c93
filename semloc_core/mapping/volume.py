"""The semantic voxel map: one Hough volume per class, accumulated frame by frame (thesis §5.4).

``VoxelMapper`` keeps, for every voxel, a float32 sum of back-projected heatmap values per class (the Hough
volume ``V_c`` after k frames, ``V^k``) and a float32 count of the frames that had the voxel in view (fractional at the edges of a view).

Memory. A voxel costs ``4·C + 4`` bytes (float32 per class, float32 view count): the thesis's 2 x 2 x 0.7 m at 1 cm
with 5 classes is 2.8 M voxels = 67 MB; a 6 x 5 x 2.5 m room at 5 cm is 0.6 M voxels = 14 MB. Both are dense
arrays (the default, one block). The accumulators stay float32: a float16 running sum stops growing once it
reaches ~2048 increments of its own resolution, i.e. after a few hundred frames of a 0..1 heatmap. For spaces
beyond a room (a building floor at 5 cm is tens of millions of voxels) set ``tile_size``: the grid is then cut
into columns of ``tile_size x tile_size`` voxels over the full height, allocated only when a frame's view frustum
(clipped at ``max_depth``) first reaches them, so memory follows the explored part of the space. Tiles use the
same kernel as the dense block, each with its own homography offset. ``memory_limit_mb`` bounds the total and
raises ``MapperMemoryError`` instead of swapping the machine to death.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field

from semloc_core.camera import PinholeCamera
from semloc_core.mapping.backprojection import (
    backproject_block,
    box_in_frustum,
    check_heatmaps,
    check_pose,
    downsample_heatmaps,
    remove_background,
    frustum_constraints,
    pad_heatmaps,
    slice_homography_terms,
    surface_depths,
    undistort_heatmaps,
    undistortion_maps,
)
from semloc_core.mapping.extraction import (ExtractionConfig, MappedObject, extract_with, objects_to_semantic_map,
                                            white_tophat)
from semloc_core.mapping.grid import VoxelGrid
from semloc_core.mapping.likelihood import check_llr_tables, heat_to_llr, level_surprisal
from semloc_core.mapping.scale_depth import depth_bands, reach_over_levels
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.settings import settings

SNAPSHOT_FORMAT = "semloc.voxel_map"
SNAPSHOT_VERSION = 1


def class_colors(num_classes: int) -> np.ndarray:
    """A distinct RGB colour per class (uint8, (C, 3)); cycles after ten."""
    palette = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                        [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)
    return palette[np.arange(num_classes) % len(palette)]


def hot_voxels(scores, grid: VoxelGrid, fraction: float = 0.5, max_points: int = 200_000) -> dict[str, np.ndarray]:
    """Voxels scoring at least ``fraction`` of their class's maximum (and above zero), every class together, from
    per-class score volumes ``scores`` (C, nz, ny, nx) over ``grid``.

    Returns ``points`` (N, 3) voxel centres, ``class_index`` (N,), ``score`` (N,) and ``colors`` (N, 3) uint8
    (one colour per class) - ready for ``semloc_core.io.voxel_map.save_ply`` or a rerun point cloud. The
    strongest ``max_points`` are kept.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    points, classes, values = [], [], []
    for c, score in enumerate(scores):
        score = np.asarray(score)
        if score.shape != grid.volume_shape:
            raise ValueError(f"score volume {c} is {score.shape}, the grid's volumes are {grid.volume_shape}")
        top = float(score.max()) if score.size else 0.0
        if top <= 0:
            continue
        kji = np.argwhere(score >= fraction * top)
        points.append(grid.centres(kji[:, ::-1]))
        classes.append(np.full(len(kji), c, dtype=np.int32))
        values.append(score[tuple(kji.T)])
    if not points:
        return {"points": np.zeros((0, 3)), "class_index": np.zeros(0, np.int32), "score": np.zeros(0, np.float32),
                "colors": np.zeros((0, 3), np.uint8)}
    points, classes, values = np.concatenate(points), np.concatenate(classes), np.concatenate(values)
    if len(values) > max_points:
        keep = np.argsort(-values, kind="stable")[:max_points]
        points, classes, values = points[keep], classes[keep], values[keep]
    return {"points": points, "class_index": classes, "score": values.astype(np.float32),
            "colors": class_colors(len(scores))[classes]}


class MapperMemoryError(MemoryError):
    """Allocating the voxel volumes would exceed the configured memory limit."""


@settings
class MapperConfig:
    """How heatmaps accumulate in the voxel volumes (§5.4)."""

    heatmap_downsample: int = Field(1, ge=1, description="area-average heatmaps by this integer factor before "
                                    "back-projection")
    min_depth: float = Field(0.05, gt=0, allow_inf_nan=False, description="metres along the optical axis; closer "
                             "voxels are not updated")
    max_depth: float = Field(math.inf, gt=0, description="metres along the optical axis; farther voxels are not "
                             "updated (inf: unlimited; set it when tiling large spaces)")
    tile_size: int | None = Field(None, ge=1, description="None: one dense block; else lazily allocated columns of "
                                  "tile_size² voxels (large spaces)")
    memory_limit_mb: float = Field(4096.0, gt=0, description="the volumes may take at most this much memory")
    heatmap_background: Literal["none", "median", "surprisal"] = Field(
        "none", description="how each frame's background heat is discounted before back-projection: 'median' "
        "subtracts each class's per-frame median (negatives clipped); 'surprisal' replaces heat by -log of the "
        "fraction of the frame's cells at least as hot (semloc_core.mapping.likelihood.heat_surprisal)")
    heatmap_llr: dict[str, list[float]] = Field(default_factory=dict, description="per-class heat log-likelihood "
                                                "ratios over scores 0..1 (semloc_core.mapping.likelihood): "
                                                "accumulate evidence, not heat")
    level_reach: int = Field(0, ge=0, description="scale-selected back-projection (integrate(..., level_depths=...)):"
                             " a voxel in level l's depth band takes the max over the levels within this many steps "
                             "of l (0: its own level only). Objects of one class differ in size, so an object's "
                             "strongest level may be a neighbour of the one its depth stands for; reaching for it "
                             "also lets look-alikes of the wrong size back in (1 found one more object and 5 more "
                             "false ones on the real trajectories, docs/mapping.md)")
    occlusion_margin: float = Field(0.15, ge=0, allow_inf_nan=False, description="integrate(..., depth=...): a voxel"
                                    " more than this far (m) behind the surface the depth image shows through its "
                                    "pixel is hidden from the frame - no view, no heat - so an object hidden behind "
                                    "another in some frames is not scored down by them. Deep enough to keep the "
                                    "voxels of an object behind its own visible face")

    def __post_init__(self) -> None:
        if self.heatmap_llr and self.heatmap_background != "none":
            raise ValueError("heatmap_llr replaces background removal: the ratios are fitted on raw scores")
        if not self.max_depth > self.min_depth:
            raise ValueError(f"max_depth ({self.max_depth}) must exceed min_depth ({self.min_depth})")

    def to_document(self) -> dict:
        document = asdict(self)
        document["max_depth"] = None if math.isinf(self.max_depth) else self.max_depth
        return document

    @classmethod
    def from_document(cls, document: dict) -> "MapperConfig":
        document = dict(document)
        if document.get("max_depth") is None:
            document["max_depth"] = math.inf
        return cls(**document)


def first_allocation_bytes(grid: VoxelGrid, num_classes: int, config: MapperConfig) -> int:
    """Bytes the volumes take as soon as a VoxelMapper exists: the whole grid's (one dense block), or its first
    tile's (``tile_size``: the others come as the camera explores)."""
    tile = config.tile_size
    columns = grid.nx * grid.ny if tile is None else min(tile, grid.nx) * min(tile, grid.ny)
    return columns * grid.nz * grid.bytes_per_voxel(num_classes)


@dataclass
class FrameStats:
    voxels_in_view: float = 0.0  # summed coverage
    blocks_updated: int = 0


@dataclass
class _Block:
    start: tuple[int, int]  # (i0, j0) of the block's first voxel
    acc: np.ndarray  # (C, nz, by, bx) float32
    views: np.ndarray  # (nz, by, bx) float32, summed coverage


@dataclass(eq=False)
class VoxelMapper:
    """Hough volumes over ``grid`` for ``class_names``, updated by ``integrate`` (one frame at a time)."""

    grid: VoxelGrid
    class_names: tuple[str, ...]
    config: MapperConfig = field(default_factory=MapperConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.grid, VoxelGrid):
            raise TypeError(f"grid must be a VoxelGrid, got {type(self.grid).__name__}")
        names = tuple(self.class_names)
        if not names or any(not isinstance(n, str) or not n for n in names) or len(set(names)) != len(names):
            raise ValueError(f"class_names must be distinct non-empty strings, got {self.class_names!r}")
        self.class_names = names
        self.frames = 0
        self._llr = check_llr_tables(self.config.heatmap_llr, names) if self.config.heatmap_llr else None
        self._blocks: dict[tuple[int, int], _Block] = {}
        self._undistort_cache: dict[tuple, tuple] = {}
        tile = self.config.tile_size
        self._tile = (self.grid.nx, self.grid.ny) if tile is None else (int(tile), int(tile))
        self._tiles_shape = (-(-self.grid.nx // self._tile[0]), -(-self.grid.ny // self._tile[1]))
        if tile is None:
            self._allocate((0, 0))

    # ---- memory ---------------------------------------------------------------------------------------------
    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def memory_bytes(self) -> int:
        return sum(b.acc.nbytes + b.views.nbytes for b in self._blocks.values())

    @property
    def allocated_fraction(self) -> float:
        """Fraction of the grid's voxels that have storage."""
        return sum(b.views.size for b in self._blocks.values()) / self.grid.num_voxels

    def _block_extent(self, key: tuple[int, int]) -> tuple[int, int, int, int]:
        i0, j0 = key[0] * self._tile[0], key[1] * self._tile[1]
        return i0, j0, min(i0 + self._tile[0], self.grid.nx), min(j0 + self._tile[1], self.grid.ny)

    def _allocate(self, key: tuple[int, int]) -> _Block:
        i0, j0, i1, j1 = self._block_extent(key)
        shape = (self.grid.nz, j1 - j0, i1 - i0)
        needed = self.memory_bytes + int(np.prod(shape)) * self.grid.bytes_per_voxel(self.num_classes)
        if needed > self.config.memory_limit_mb * 2**20:
            raise MapperMemoryError(
                f"voxel map would need {needed / 2**20:.0f} MB (> memory_limit_mb={self.config.memory_limit_mb:g}) "
                f"for {self.grid} with {self.num_classes} classes; use larger voxels, a smaller box, or tile_size "
                f"with max_depth so that only the explored part is allocated")
        block = _Block((i0, j0), np.zeros((self.num_classes,) + shape, np.float32), np.zeros(shape, np.float32))
        self._blocks[key] = block
        return block

    # ---- integration ----------------------------------------------------------------------------------------
    def _prepare(self, heatmaps, camera: PinholeCamera, levels: int | None = None, depth=None):
        """Background removal, downsampling and undistortion; returns (padded maps, camera of the maps, padded
        surface depths or None). ``levels``: the heatmaps are (classes, levels, H, W) per-level maps, padded as
        classes·levels channels (class c's level l at channel c·levels + l). ``depth``: see ``integrate``."""
        if not isinstance(camera, PinholeCamera):
            raise TypeError(f"the voxel mapper needs a PinholeCamera (plane-to-image homographies), got "
                            f"{type(camera).__name__}")
        stack = np.asarray(heatmaps)
        if levels is not None and (stack.ndim != 4 or stack.shape[:2] != (self.num_classes, levels)):
            raise ValueError(f"per-level heatmaps must be ({self.num_classes} classes, {levels} levels, height, "
                             f"width), got shape {stack.shape}")
        if levels is not None:
            stack = stack.reshape((-1,) + stack.shape[2:])
        surprisal = self.config.heatmap_background == "surprisal"
        # Surprisal needs only the order of a frame's heat: a detector's quantised codes are counted as they are
        # (level_surprisal), without casting them first.
        h = check_heatmaps(stack, None if levels is not None else self.num_classes, codes=surprisal)
        if surprisal:
            h = level_surprisal(h, levels or 1)
        if self.config.heatmap_background == "median":
            h = remove_background(h)  # per level: each level's own floor
        if self._llr is not None:
            if levels is not None:
                raise ValueError("heatmap_llr ratios are fitted on single heatmaps; per-level maps take heat")
            h = heat_to_llr(h, self._llr)
        h, cam = downsample_heatmaps(h, camera, self.config.heatmap_downsample)
        maps = None
        if np.any(cam.dist != 0):
            # Slices map to the image by homographies only without lens distortion: resample the heatmaps onto
            # an ideal pinhole canvas first (maps cached per camera).
            key = (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes())
            cached = self._undistort_cache.get(key)
            if cached is None:
                if len(self._undistort_cache) >= 4:
                    self._undistort_cache.clear()
                cached = self._undistort_cache[key] = undistortion_maps(cam)
            ideal, maps = cached
            h = undistort_heatmaps(h, maps)
        surface = None
        if depth is not None:
            z = np.asarray(depth)
            if z.shape != (camera.height, camera.width) or not np.issubdtype(z.dtype, np.floating):
                raise ValueError(f"depth must be a float ({camera.height}, {camera.width}) image of the camera, in "
                                 f"metres along the optical axis, got {z.dtype} {z.shape}")
            surface = surface_depths(z, cam.height, cam.width, maps)
        if maps is not None:
            cam = ideal
        return pad_heatmaps(h), cam, surface

    def integrate(self, heatmaps, T_world_cam, camera: PinholeCamera, level_depths=None, depth=None) -> FrameStats:
        """Back-project one frame's per-class heatmaps (C, H, W) seen from camera pose ``T_world_cam``.

        ``camera`` supplies the intrinsics and distortion of the image the heatmaps cover (any heatmap resolution:
        the intrinsics are rescaled to it); its ``T_body_cam`` is not used - the pose is the camera's own.
        Adds the frame to every class's Hough volume (the cumulative sum of §5.4) and to the view counts.

        ``level_depths`` (C, L), metres: scale-selected back-projection (semloc_core.mapping.scale_depth). The
        heatmaps are then a window detector's per-level maps (C, L, H, W), level ``l`` of class ``c`` answering
        for objects at depth ``level_depths[c, l]``; each voxel takes the level whose depth band holds its depth.
        The background is judged on the max over levels (the single-map heatmap), so both paths share a scale.

        ``depth`` (camera.height, camera.width) float, metres along the optical axis (NaN, inf or <= 0: no return):
        the frame's depth image. Voxels more than ``occlusion_margin`` behind the surface it shows are hidden from
        this frame (no view, no heat); without it every voxel in the frustum counts as seen (§5.4).
        """
        T = check_pose(T_world_cam)
        cfg = self.config
        bands = None
        if level_depths is not None:
            depths = np.asarray(level_depths, dtype=float)
            if depths.ndim != 2 or depths.shape[0] != self.num_classes or not np.all(np.isfinite(depths)):
                raise ValueError(f"level_depths must be finite ({self.num_classes} classes, levels), got shape "
                                 f"{depths.shape}")
            bands = depth_bands(depths, cfg.min_depth, cfg.max_depth)
            heatmaps = reach_over_levels(heatmaps, depths, cfg.level_reach)
            padded, cam, surface = self._prepare(heatmaps, camera, levels=depths.shape[1], depth=depth)
        else:
            padded, cam, surface = self._prepare(heatmaps, camera, depth=depth)
        G, h = frustum_constraints(cam.K, T, cam.width, cam.height, cfg.min_depth, cfg.max_depth)
        stats = FrameStats()
        grid = self.grid
        for key in self._candidate_blocks():
            i0, j0, i1, j1 = self._block_extent(key)
            lo = grid.origin + (np.array([i0, j0, 0]) + 0.5) * grid.voxel_size
            hi = grid.origin + (np.array([i1, j1, grid.nz]) - 0.5) * grid.voxel_size
            if not box_in_frustum(G, h, lo, hi):
                continue
            block = self._blocks.get(key)
            if block is None:
                block = self._allocate(key)
            A, d = slice_homography_terms(grid, cam.K, T, offset=(i0, j0, 0))
            stats.voxels_in_view += backproject_block(block.acc, block.views, padded, A, d, cfg.min_depth,
                                                      cfg.max_depth, cam.width, cam.height, level_bands=bands,
                                                      surface=surface, occlusion_margin=cfg.occlusion_margin)
            stats.blocks_updated += 1
        self.frames += 1
        return stats

    def _candidate_blocks(self):
        if self.config.tile_size is None:
            return list(self._blocks)
        return [(a, b) for a in range(self._tiles_shape[0]) for b in range(self._tiles_shape[1])]

    # ---- volumes --------------------------------------------------------------------------------------------
    def class_index(self, class_name: str | int) -> int:
        if isinstance(class_name, (int, np.integer)):
            if not 0 <= int(class_name) < self.num_classes:
                raise IndexError(f"class index {class_name} out of range for {self.num_classes} classes")
            return int(class_name)
        if class_name not in self.class_names:
            raise KeyError(f"unknown class {class_name!r}; the map has {list(self.class_names)}")
        return self.class_names.index(class_name)

    def hough_volume(self, class_name: str | int) -> np.ndarray:
        """The class's cumulative sum (nz, ny, nx) float32 - a fresh array (zeros where nothing is allocated)."""
        c = self.class_index(class_name)
        out = np.zeros(self.grid.volume_shape, np.float32)
        for key, block in self._blocks.items():
            i0, j0, i1, j1 = self._block_extent(key)
            out[:, j0:j1, i0:i1] = block.acc[c]
        return out

    def view_count(self) -> np.ndarray:
        """How many integrated frames had each voxel in view, (nz, ny, nx) float32 - fractional along the edges
        of a view, where the voxel's sample is partly off the image (see backprojection)."""
        out = np.zeros(self.grid.volume_shape, np.float32)
        for key, block in self._blocks.items():
            i0, j0, i1, j1 = self._block_extent(key)
            out[:, j0:j1, i0:i1] = block.views
        return out

    def score_volume(self, class_name: str | int, normalise: bool = True, min_views: int = 1) -> np.ndarray:
        """Score per voxel, (nz, ny, nx) float32.

        ``normalise=True``: the mean heat over the frames that saw the voxel, ``V_c / max(views, min_views)`` -
        voxels seen rarely are damped by ``min_views`` instead of trusted. ``normalise=False``: the thesis's plain
        cumulative sum divided by the number of frames (a constant, so thresholds do not depend on run length).
        """
        volume = self.hough_volume(class_name)
        if normalise:
            views = np.maximum(self.view_count(), np.float32(max(int(min_views), 1)))
            return volume / views
        return volume / np.float32(max(self.frames, 1))

    # ---- extraction -----------------------------------------------------------------------------------------
    def extract(self, config: ExtractionConfig | None = None) -> list[MappedObject]:
        """Objects of every class (thresholded NMS over each class's score volume, divided by the class's
        ``class_scales`` entry), strongest first per class."""
        config = config or ExtractionConfig()
        sizes = {name: config.size_of(name) for name in self.class_names}
        scores = {}
        for name in self.class_names:
            score = self.score_volume(name, normalise=config.normalise, min_views=config.min_views)
            if config.tophat > 0:
                score = white_tophat(score, sizes[name], self.grid.voxel_size, config.tophat)
            scores[name] = score / np.float32(config.scale_of(name))
        return extract_with(scores, self.grid, config)

    def semantic_map(self, config: ExtractionConfig | None = None) -> SemanticMap:
        """The extracted objects as the localizer's object map."""
        config = config or ExtractionConfig()
        sizes = ({name: config.size_of(name) for name in self.class_names}
                 if config.export_size == "bounding_volume" else None)
        return objects_to_semantic_map(self.extract(config), self.class_names, self.grid, sizes, config.existence)

    def hot_voxels(self, fraction: float = 0.5, normalise: bool = True, min_views: int = 5,
                   max_points: int = 200_000) -> dict[str, np.ndarray]:
        """:func:`hot_voxels` of this mapper's score volumes."""
        scores = [self.score_volume(c, normalise=normalise, min_views=min_views) for c in range(self.num_classes)]
        return hot_voxels(scores, self.grid, fraction, max_points)

    def score_volumes(self, normalise: bool = True, min_views: int = 5) -> np.ndarray:
        """Every class's :meth:`score_volume`, (C, nz, ny, nx) float32."""
        return np.stack([self.score_volume(c, normalise=normalise, min_views=min_views)
                         for c in range(self.num_classes)]).astype(np.float32, copy=False)

    # ---- snapshot -------------------------------------------------------------------------------------------
    def snapshot(self) -> dict[str, np.ndarray]:
        """The whole state as named arrays (no objects, no pickle): ``semloc_core.io.voxel_map`` writes it."""
        meta = {
            "format": SNAPSHOT_FORMAT,
            "version": SNAPSHOT_VERSION,
            "grid": self.grid.to_document(),
            "class_names": list(self.class_names),
            "config": self.config.to_document(),
            "frames": self.frames,
            "blocks": [list(key) for key in self._blocks],
        }
        arrays = {"meta": np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8).copy()}
        for n, block in enumerate(self._blocks.values()):
            arrays[f"acc_{n}"] = block.acc
            arrays[f"views_{n}"] = block.views
        return arrays

    @classmethod
    def from_snapshot(cls, arrays) -> "VoxelMapper":
        """Rebuild a mapper from ``snapshot()``'s arrays; ValueError if they are inconsistent."""
        try:
            meta = json.loads(bytes(np.asarray(arrays["meta"], dtype=np.uint8)).decode())
        except (KeyError, ValueError, UnicodeDecodeError) as error:
            raise ValueError(f"not a voxel map snapshot: {error}") from None
        if not isinstance(meta, dict) or meta.get("format") != SNAPSHOT_FORMAT:
            raise ValueError(f"not a voxel map snapshot (format {meta.get('format') if isinstance(meta, dict) else meta!r})")
        if meta.get("version") != SNAPSHOT_VERSION:
            raise ValueError(f"unsupported voxel map snapshot version {meta.get('version')!r}")
        try:
            mapper = cls(VoxelGrid.from_document(meta["grid"]), tuple(meta["class_names"]),
                         MapperConfig.from_document(meta["config"]))
            frames = int(meta["frames"])
            keys = [tuple(int(v) for v in key) for key in meta["blocks"]]
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"invalid voxel map snapshot metadata: {error}") from None
        mapper._blocks.clear()
        for n, key in enumerate(keys):
            if not (0 <= key[0] < mapper._tiles_shape[0] and 0 <= key[1] < mapper._tiles_shape[1]):
                raise ValueError(f"snapshot block {key} lies outside the grid")
            block = mapper._allocate(key)
            for name, target in ((f"acc_{n}", block.acc), (f"views_{n}", block.views)):
                if name not in arrays:
                    raise ValueError(f"voxel map snapshot lacks array {name!r}")
                source = np.asarray(arrays[name])
                if source.shape != target.shape or source.dtype != target.dtype:
                    raise ValueError(f"snapshot array {name!r} is {source.dtype}{source.shape}, expected "
                                     f"{target.dtype}{target.shape}")
                target[...] = source
        mapper.frames = frames
        return mapper
