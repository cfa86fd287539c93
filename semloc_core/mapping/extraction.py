"""Objects out of Hough volumes: thresholded non-maximum suppression with a per-class bounding volume (§5.4).

The thesis: "Given an approximate bounding volume of the object, search for and record local maxima. At each
maximal location remove all responses falling within the bounding volume centred around the current candidate.
Repeat until the remaining scores fall below a threshold." Here the candidates are the volume's local maxima
(3x3x3 neighbourhood) at or above the threshold, taken in decreasing score; each accepted one suppresses the
candidates inside its bounding volume. Taking local maxima rather than re-searching the global maximum after
blanking a box keeps a broad peak's flank (just outside the box) from being reported as a second object.

Each object's position is the peak refined to sub-voxel precision by a parabola through the peak and its two
neighbours on each axis; its extent is the bounding box of the connected region around the peak scoring at least
``extent_fraction`` of the peak (searched within twice the bounding volume) - for heatmaps that cover the
object's image, that region approximates the object's visual hull. The exported map gives each object its
class's bounding volume as size unless ``export_size="extent"``: with few, similar viewing directions the
half-maximum region is stretched along them (a localizer fed those extents mispredicted occlusions: RMSE after
convergence 1.8x that with the ground-truth map, 1.1x with bounding volumes - docs/mapping.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field
from scipy import ndimage

from semloc_core.geometry import inside_polygon
from semloc_core.io.semantic_map import SemanticMap
from semloc_core.mapping.existence import ExistenceCurve
from semloc_core.mapping.grid import VoxelGrid
from semloc_core.settings import settings


@dataclass(frozen=True, eq=False)
class MappedObject:
    class_name: str
    position: np.ndarray  # (3,) world, metres
    extent: np.ndarray  # (3,) metres
    score: float


POSITIONS = ("peak", "centroid", "mode")
# A length or factor that must be positive and finite (a bounding volume's side, a score divisor, a bandwidth).
PositiveSize = Annotated[float, Field(gt=0, allow_inf_nan=False)]


Size3 = tuple[PositiveSize, PositiveSize, PositiveSize]


@settings(eq=False)
class ExtractionConfig:
    """How objects are extracted from the score volumes (§5.4). Switches are booleans, never numbers."""

    threshold: float = Field(0.5, allow_inf_nan=False, description="extraction threshold on the score volume "
                             "(see VoxelMapper.score_volume)")
    normalise: bool = Field(True, strict=True, description="score = mean heat over the frames that saw a voxel; "
                            "else sum / frames")
    min_views: int = Field(5, ge=1, description="normalisation floor: a voxel seen by fewer frames is divided by "
                           "min_views")
    object_size: Size3 = Field((0.2, 0.2, 0.2), description="default bounding volume (x, y, z), metres")
    class_sizes: dict[str, Size3] = Field(default_factory=dict, description="per-class bounding volumes (x, y, z), "
                                          "metres")
    extent_fraction: float = Field(0.5, gt=0, lt=1, description="an object's extent: the region around its peak "
                                   "scoring at least this fraction of the peak")
    max_objects_per_class: int = Field(100, ge=1)
    reject_border: bool = Field(True, strict=True, description="a peak on the grid's faces is the flank of "
                                "something outside the box")
    class_scales: dict[str, PositiveSize] = Field(default_factory=dict, description="per-class score divisors making "
                                                  "scores comparable across classes (a semloc eval mapping "
                                                  "calibration)")
    cross_class: bool = Field(False, strict=True, description="an object suppresses other classes' candidates "
                              "overlapping its core")
    tophat: float = Field(0.0, ge=0, allow_inf_nan=False, description="> 0: subtract the volume's grey opening by "
                          "this many bounding volumes (white top-hat) before NMS")
    export_size: Literal["bounding_volume", "extent"] = Field("bounding_volume", description="object size in the "
                                                              "exported map: the class's bounding volume or its extent")
    support_z: float | None = Field(None, allow_inf_nan=False, description="world height (m) of the surface the "
                                    "objects rest on, if known (the table the grid was placed on): an object's "
                                    "centre then lies within its bounding volume's height above it - peaks "
                                    "elsewhere are not objects")
    support_polygon: tuple[tuple[float, float], ...] | None = Field(
        None, description="(x, y) vertices of that surface's outline, if known: an object resting on it has its "
        "centre over it, so candidates elsewhere (a template answering on the floor or a chair beyond the table's "
        "edge) are not objects")
    resting: bool = Field(False, strict=True, description="with support_z: the objects rest on the support, so an "
                          "object's centre height is halfway between the support and the top of its score region "
                          "(the voxels above extent_fraction of the peak, connected to it) instead of the position "
                          "estimate's height. A template answering on an object's textured upper part (a cereal "
                          "box's face, a cap's crown) puts the score mass - and its centroid - above or below the "
                          "centre, while the region's top follows the object's top (docs/mapping.md)")
    position: Literal["peak", "centroid", "mode"] = Field("peak", description="an object's position: 'peak', the "
                                                          "score maximum refined by a parabola on each axis; "
                                                          "'centroid', the centre of the score mass above "
                                                          "extent_fraction of the peak in the peak's connected "
                                                          "region; 'mode', the maximum of that mass smoothed by a "
                                                          "Gaussian of mode_bandwidth metres (mean shift from the "
                                                          "peak)")
    mode_bandwidth: PositiveSize = Field(0.02, description="position 'mode': the smoothing Gaussian's standard "
                                         "deviation, metres")
    prominence: float = Field(0.0, ge=0, lt=1, description="> 0: a candidate joined to a stronger accepted object of "
                              "its class by voxels scoring at least this fraction of its own peak (within "
                              "SHOULDER_REACH bounding volumes) is that object's shoulder, not another object: seen "
                              "from few, similar directions, an object's back-projected cone holds further maxima "
                              "along the rays (scene 13's soda can: a second one 18 cm behind it, within 1.3 degrees "
                              "of it from every camera)")
    existence: ExistenceCurve | None = Field(None, description="p(real | score) of an extracted object (fitted on "
                                             "calibration scenes, semloc_core.mapping.existence): the exported "
                                             "map's existence; None: every object is certain (1)")

    def __post_init__(self) -> None:
        if self.resting and self.support_z is None:
            raise ValueError("resting needs support_z: the height of the surface the objects rest on")
        if self.support_polygon is not None:
            outline = np.asarray(self.support_polygon, dtype=float)
            if len(outline) < 3 or not np.all(np.isfinite(outline)):
                raise ValueError(f"support_polygon must be >= 3 finite (x, y) vertices, got {self.support_polygon!r}")

    def size_of(self, class_name: str) -> np.ndarray:
        return np.asarray(self.class_sizes.get(class_name, self.object_size), dtype=float)

    def scale_of(self, class_name: str) -> float:
        return float(self.class_scales.get(class_name, 1.0))


def _subvoxel_offset(score: np.ndarray, peak: tuple[int, int, int]) -> np.ndarray:
    """Parabolic peak refinement along each axis, (di, dj, dk) in voxels, each within [-0.5, 0.5]."""
    k, j, i = peak[2], peak[1], peak[0]
    offsets = np.zeros(3)
    centre = float(score[k, j, i])
    for axis, (dk, dj, di) in enumerate(((0, 0, 1), (0, 1, 0), (1, 0, 0))):
        lo = (k - dk, j - dj, i - di)
        hi = (k + dk, j + dj, i + di)
        if min(lo) < 0 or any(h >= n for h, n in zip(hi, score.shape)):
            continue
        a, b = float(score[lo]), float(score[hi])
        curvature = a - 2.0 * centre + b
        if curvature < 0:
            offsets[axis] = np.clip(0.5 * (a - b) / curvature, -0.5, 0.5)
    return offsets


def _connected_region(score: np.ndarray, peak: tuple[int, int, int], half_window: np.ndarray, level: float
                      ) -> np.ndarray:
    """(n, 3) kji indices of the voxels connected to ``peak`` (i, j, k) scoring at least ``level``, searched within
    ``half_window`` (i, j, k voxels) of it."""
    i, j, k = peak
    lo = np.maximum(np.array([k, j, i]) - half_window[::-1], 0)
    hi = np.minimum(np.array([k, j, i]) + half_window[::-1] + 1, score.shape)
    window = score[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    labels, _ = ndimage.label(window >= level)
    return np.argwhere(labels == labels[k - lo[0], j - lo[1], i - lo[2]]) + lo


def _peak_position(score: np.ndarray, peak: tuple[int, int, int], half_window: np.ndarray) -> np.ndarray:
    """Sub-voxel (i, j, k) of a peak: parabolic refinement, or the centroid of the peak's plateau when several
    connected voxels share its value (evidence clipped at the likelihood ratio's bound saturates a whole core)."""
    i, j, k = peak
    plateau = _connected_region(score, peak, half_window, score[k, j, i])
    if len(plateau) > 1:
        return plateau.mean(axis=0)[::-1]
    return np.asarray(peak, dtype=float) + _subvoxel_offset(score, peak)


def _region_centroid(score: np.ndarray, region: np.ndarray, level: float) -> np.ndarray:
    """(i, j, k) centroid of ``region`` (kji indices) weighted by each voxel's score above ``level``. The weights
    fall continuously to zero at the region's edge, so on a sampled symmetric peak the centroid stays sub-voxel
    accurate; on a flat-topped or lopsided peak it is the centre of the mass above the level, not the wandering
    maximum."""
    weights = score[tuple(region.T)].astype(float) - level
    if not np.any(weights > 0):
        return region.mean(axis=0)[::-1]
    return (weights @ region / weights.sum())[::-1]


def _mass_mode(score: np.ndarray, region: np.ndarray, level: float, start: np.ndarray, sigma: float,
               iterations: int = 100) -> np.ndarray:
    """(i, j, k) maximum of the score mass above ``level`` in ``region`` (kji indices) smoothed by an isotropic
    Gaussian of ``sigma`` voxels, climbed by mean shift from ``start`` (i, j, k).

    Its limits are the two other estimators: sigma -> 0 gives the maximum, sigma -> infinity the centroid. The
    maximum wanders over a flat-topped peak (a template answering all over a cap's crown); the centroid follows the
    mass, which on a peak seen from few, similar directions is a cone widening away from the cameras, so it lies
    behind the object. Smoothed at a few centimetres, the plateau's noise averages out while the cone's far flank,
    beyond the kernel, does not pull. In between it is not always between them: the cone's mass per unit length
    grows along it, so a wide kernel climbs down the cone past the centroid (docs/mapping.md)."""
    weights = score[tuple(region.T)].astype(float) - level
    keep = weights > 0
    if not np.any(keep):
        return np.asarray(start, dtype=float)
    points, weights = region[keep][:, ::-1].astype(float), weights[keep]
    x = np.asarray(start, dtype=float)
    for _ in range(iterations):
        kernel = weights * np.exp(-0.5 * np.sum((points - x) ** 2, axis=1) / sigma ** 2)
        total = kernel.sum()
        if total <= 0:
            break
        moved = kernel @ points / total
        if np.max(np.abs(moved - x)) < 1e-3:
            return moved
        x = moved
    return x


def _extent(region: np.ndarray, voxel_size: float) -> np.ndarray:
    span_kji = region.max(axis=0) - region.min(axis=0) + 1
    return span_kji[::-1].astype(float) * voxel_size


def white_tophat(score: np.ndarray, bounding_size, voxel_size: float, factor: float = 2.0) -> np.ndarray:
    """``score`` minus its grey opening by a box ``factor`` times the bounding volume: what rises above its
    surroundings within an object-sized window. A detector answering over a whole surface (a template matching
    the table's texture) leaves a plateau in the Hough volume, whose noise makes local maxima everywhere; the
    opening follows the plateau and the difference keeps only object-sized bumps."""
    size = np.ceil(factor * np.asarray(bounding_size, dtype=float)[::-1] / voxel_size).astype(int) | 1
    size = tuple(int(v) for v in np.maximum(size, 3))
    return score - box_filter(box_filter(score, size, "min"), size, "max")


def box_filter(volume: np.ndarray, size, kind: str) -> np.ndarray:
    """The min or max of a float (nz, ny, nx) volume over a centred box of odd ``size`` (k, j, i) voxels, the
    edges extended (scipy.ndimage's minimum_filter / maximum_filter with mode "nearest", the same values): OpenCV's
    erosion or dilation by a rectangle on each slice, then along the slices - 10x faster than scipy's on the
    mapper's volumes (its extraction every publication period: a top-hat and the local maxima of every class)."""
    kz, ky, kx = (int(v) for v in size)
    if min(kz, ky, kx) < 1 or not (kz & ky & kx & 1):
        raise ValueError(f"box sizes must be odd and positive, got {size}")
    op = cv2.erode if kind == "min" else cv2.dilate
    v = np.asarray(volume)
    v = np.ascontiguousarray(v, dtype=v.dtype if v.dtype in (np.float32, np.float64) else np.float32)
    nz, ny, nx = v.shape
    out = np.empty_like(v)
    plane = cv2.getStructuringElement(cv2.MORPH_RECT, (kx, ky))
    for k in range(nz):
        out[k] = op(v[k], plane, borderType=cv2.BORDER_REPLICATE)
    if kz > 1:  # along the slices: the (nz, ny·nx) image's columns
        out = op(out.reshape(nz, ny * nx), np.ones((kz, 1), np.uint8),
                 borderType=cv2.BORDER_REPLICATE).reshape(nz, ny, nx)
    return out


def support_band(grid: VoxelGrid, support_z: float, height: float) -> tuple[int, int]:
    """Slices ``[k0, k1)`` whose voxel centres lie at most ``height / 2`` above ``support_z``: where the centre of
    an object at most ``height`` tall (its bounding volume) resting on the support can be. Candidates are the
    maxima within the band, so an object whose score peaks a little above it (views from above favour its top)
    still gives a candidate on the band's edge; what peaks far above (a template answering on another object's
    top or rim) gives at most the weak tail of its peak there."""
    z = grid.origin[2] + (np.arange(grid.nz) + 0.5) * grid.voxel_size
    inside = np.flatnonzero((z >= support_z) & (z <= support_z + 0.5 * height))
    return (int(inside[0]), int(inside[-1]) + 1) if inside.size else (0, 0)


def support_footprint(grid: VoxelGrid, polygon) -> np.ndarray:
    """(ny, nx) mask of the grid columns whose centres lie inside the (x, y) ``polygon``."""
    x, y = grid.axis_centres(0), grid.axis_centres(1)
    return inside_polygon(x[None, :], y[:, None], polygon)


def _candidates(score: np.ndarray, threshold: float, reject_border: bool, band: tuple[int, int] | None = None,
                footprint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima (3x3x3) at or above the threshold: (kji indices (N, 3), values (N,)). With ``band`` only slices
    ``[k0, k1)`` hold candidates, and maxima are taken within it (a peak on the band's edge counts); with
    ``footprint`` ((ny, nx) mask) only those columns do."""
    if band is not None or footprint is not None:
        score = score.copy()
    if band is not None:
        score[:band[0]] = -np.inf
        score[band[1]:] = -np.inf
    if footprint is not None:
        score[:, ~footprint] = -np.inf
    candidates = (score == box_filter(score, (3, 3, 3), "max")) & (score >= threshold)
    if reject_border:
        candidates[[0, -1], :, :] = False
        candidates[:, [0, -1], :] = False
        candidates[:, :, [0, -1]] = False
    kji = np.argwhere(candidates)
    return kji, score[tuple(kji.T)]


SHOULDER_REACH = 3.0   # bounding volumes around a candidate searched for the object it is a shoulder of


def _is_shoulder(volume: np.ndarray, peak_kji: np.ndarray, stronger_kji: list, level: float,
                 half: np.ndarray) -> bool:
    """Whether voxels at or above ``level`` connect the candidate's peak to one of ``stronger_kji`` (accepted
    peaks of its class) within ``SHOULDER_REACH`` bounding volumes (``half`` = half a bounding volume, voxels)."""
    reach = np.ceil(2 * SHOULDER_REACH * half).astype(int)
    near = [p for p in stronger_kji if np.all(np.abs(p - peak_kji) <= reach)]
    if not near:
        return False
    lo = np.maximum(peak_kji - reach, 0)
    hi = np.minimum(peak_kji + reach + 1, volume.shape)
    labels, _ = ndimage.label(volume[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] >= level)
    own = labels[tuple(peak_kji - lo)]
    return any(labels[tuple(p - lo)] == own for p in near)


def extract_objects(score: np.ndarray, grid: VoxelGrid, class_name: str, bounding_size, threshold: float,
                    extent_fraction: float = 0.5, max_objects: int = 100, reject_border: bool = True
                    ) -> list[MappedObject]:
    """Objects of one class from its score volume (nz, ny, nx), strongest first."""
    return extract_all({class_name: score}, grid, {class_name: bounding_size}, threshold, extent_fraction,
                       max_objects, reject_border, cross_class=False)


def extract_all(scores: dict, grid: VoxelGrid, bounding_sizes: dict, threshold: float, extent_fraction: float = 0.5,
                max_objects: int = 100, reject_border: bool = True, cross_class: bool = False,
                support_z: float | None = None, position: str = "peak", mode_bandwidth: float = 0.02,
                support_polygon=None, resting: bool = False, prominence: float = 0.0) -> list[MappedObject]:
    """Objects of every class from their score volumes ``{class: (nz, ny, nx)}``, strongest first.

    Each accepted object suppresses the candidates of its class inside its bounding volume. With ``cross_class``,
    it also suppresses candidates of other classes whose bounding volume, at half size, overlaps its own at half
    size - two objects cannot share their cores - so a detector firing on another class's object (a bowl detector
    on a mug's rim) loses to the stronger, correctly classed peak. That needs scores comparable across classes
    (see ``ExtractionConfig.class_scales``). With ``support_z``, candidates lie within their class's bounding
    height above it (``support_band``); with ``support_polygon``, their columns lie over it (``support_footprint``).
    ``position``: "peak" (the refined maximum), "centroid" or "mode" (see ``ExtractionConfig.position``); with
    ``resting``, the height is halfway between ``support_z`` and the top of the object's region
    (``ExtractionConfig.resting``); with ``prominence`` > 0, a candidate that is a stronger accepted object's
    shoulder is not an object (``ExtractionConfig.prominence``).
    """
    if position not in POSITIONS:
        raise ValueError(f"position must be one of {POSITIONS}, got {position!r}")
    if resting and support_z is None:
        raise ValueError("resting needs support_z: the height of the surface the objects rest on")
    if position == "mode" and not mode_bandwidth > 0:
        raise ValueError(f"mode_bandwidth must be a positive length in metres, got {mode_bandwidth!r}")
    names, all_kji, all_values, all_class = list(scores), [], [], []
    volumes = {}
    footprint = None if support_polygon is None else support_footprint(grid, support_polygon)
    for c, name in enumerate(names):
        volume = np.asarray(scores[name], dtype=np.float32)
        if volume.shape != grid.volume_shape:
            raise ValueError(f"score volume of {name!r} {volume.shape} does not match the grid {grid.volume_shape}")
        volumes[name] = volume
        band = None if support_z is None else support_band(grid, support_z, float(bounding_sizes[name][2]))
        kji, values = _candidates(volume, threshold, reject_border, band, footprint)
        all_kji.append(kji)
        all_values.append(values)
        all_class.append(np.full(len(values), c))
    kji = np.concatenate(all_kji) if all_kji else np.zeros((0, 3), int)
    values = np.concatenate(all_values) if all_values else np.zeros(0)
    classes = np.concatenate(all_class) if all_class else np.zeros(0, int)
    if kji.size == 0:
        return []
    order = np.argsort(-values, kind="stable")
    kji, values, classes = kji[order], values[order], classes[order]
    # Half bounding volumes in voxels, (k, j, i) order, per class.
    half = np.array([np.asarray(bounding_sizes[n], dtype=float)[::-1] / 2.0 / grid.voxel_size for n in names])
    alive = np.ones(len(kji), dtype=bool)
    counts = np.zeros(len(names), int)
    accepted: list[list[np.ndarray]] = [[] for _ in names]  # (i, j, k) positions of each class's objects
    accepted_peaks: list[list[np.ndarray]] = [[] for _ in names]  # (k, j, i) peak voxels of each class's objects
    objects = []
    for n in range(len(kji)):
        if not alive[n]:
            continue
        c = classes[n]
        volume = volumes[names[c]]
        peak = (int(kji[n, 2]), int(kji[n, 1]), int(kji[n, 0]))
        window = np.ceil(2 * half[c][::-1]).astype(int)
        level = extent_fraction * float(volume[tuple(kji[n])])
        region = _connected_region(volume, peak, window, level)
        if position == "centroid":
            centre = _region_centroid(volume, region, level)
        elif position == "mode":
            centre = _mass_mode(volume, region, level, _peak_position(volume, peak, window),
                                mode_bandwidth / grid.voxel_size)
        else:
            centre = _peak_position(volume, peak, window)
        # The bounding volume is centred on the candidate's peak (the thesis) and, with centroid or mode positions,
        # on its position too: a flat-topped peak can hold two maxima more than half a bounding volume apart around
        # one mass centre, and a candidate whose position falls in an accepted object's volume is that object.
        for at in ((kji[n],) if position == "peak" else (kji[n], centre[::-1])):
            delta = np.abs(kji - at)
            alive[(classes == c) & np.all(delta <= half[c] + 1e-9, axis=1)] = False
            if cross_class:
                alive[(classes != c) & np.all(delta <= (half[c] + half[classes]) / 2 + 1e-9, axis=1)] = False
        if position != "peak" and any(np.all(np.abs(centre - other) <= half[c][::-1] + 1e-9)
                                            for other in accepted[c]):
            continue
        if prominence > 0 and _is_shoulder(volume, kji[n], accepted_peaks[c], prominence * float(values[n]),
                                           half[c]):
            continue
        accepted[c].append(centre)
        accepted_peaks[c].append(kji[n])
        if counts[c] >= max_objects:
            continue
        counts[c] += 1
        position_world = grid.centres(centre)
        if resting:
            top = grid.origin[2] + (region[:, 0].max() + 1) * grid.voxel_size  # upper face of the highest voxel
            position_world[2] = 0.5 * (support_z + top)
        objects.append(MappedObject(names[c], position_world, _extent(region, grid.voxel_size), float(values[n])))
    objects.sort(key=lambda o: (names.index(o.class_name), -o.score))
    return objects


def extract_with(scores: dict, grid: VoxelGrid, config: ExtractionConfig) -> list[MappedObject]:
    """``extract_all`` with every setting from ``config``, on score volumes already top-hatted and scaled as
    ``config`` says (``VoxelMapper.extract`` prepares them; a calibration sweep prepares them once for many
    configs)."""
    return extract_all(scores, grid, {name: config.size_of(name) for name in scores}, config.threshold,
                       config.extent_fraction, config.max_objects_per_class, config.reject_border, config.cross_class,
                       config.support_z, config.position, config.mode_bandwidth, config.support_polygon,
                       config.resting, config.prominence)


def calibrate_class_scales(scores: dict, grid: VoxelGrid, truth: SemanticMap, radius: float = 0.05) -> dict:
    """Per class, the median over its ground-truth objects of the highest score within ``radius`` of each one:
    the level a real object of that class reaches with this detector. Dividing by it (``class_scales``) makes
    scores comparable across classes - the detector's templates answer with class-specific strengths. Fit it on a
    calibration scene, not on the scenes evaluated. Classes without objects in ``truth`` are left out."""
    scales = {}
    reach = int(np.ceil(radius / grid.voxel_size))
    for name, volume in scores.items():
        peaks = []
        for index in truth.objects_of(name):
            (i, j, k), inside = grid.indices_of(truth.positions[index])
            if not inside:
                continue
            window = volume[max(k - reach, 0):k + reach + 1, max(j - reach, 0):j + reach + 1,
                            max(i - reach, 0):i + reach + 1]
            peaks.append(float(window.max()))
        if peaks and np.median(peaks) > 0:
            scales[name] = float(np.median(peaks))
    return scales


def objects_to_semantic_map(objects: list[MappedObject], class_names, grid: VoxelGrid, sizes: dict | None = None,
                            existence: ExistenceCurve | None = None) -> SemanticMap:
    """The object map in the localizer's format (semloc_core.io.semantic_map); bounds = the grid's floor box.

    ``sizes`` {class: (x, y, z)} replaces the measured extents (``ExtractionConfig.export_size``): the extent of a
    Hough peak reflects the viewing directions as much as the object, and the localizer uses sizes to predict
    elevation spans and occlusions. ``existence`` gives each object's probability of being real from its score
    (without it, 1).
    """
    bounds = grid.bounds[:, :2]
    documents = [{"class": o.class_name, "position": [float(v) for v in o.position],
                  "size": [float(v) for v in (o.extent if sizes is None else sizes[o.class_name])],
                  "score": float(o.score),
                  "existence": 1.0 if existence is None else float(existence(o.score))} for o in objects]
    return SemanticMap.from_objects(documents, bounds=bounds, class_names=tuple(class_names))
