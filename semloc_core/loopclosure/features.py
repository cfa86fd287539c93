"""Bearing-sorted SIFT feature sequences (thesis §3.3.1).

Each image becomes a sequence of SIFT descriptors ordered by the bearing of their keypoints: the keypoint's ray in
the body frame (through the camera model) has its elevation dropped and only its azimuth kept. A camera rig's
members are processed separately and merged into one sequence, as the thesis did with the Ladybug's lateral
cameras.

Descriptor scale. The thesis's ``t_match = 1000`` is an L1 distance between VLFeat descriptors: uint8 vectors that
are the unit SIFT vector times 512, saturated at 255 (so their L2 norm is about 512). OpenCV's SIFT produces the
same quantisation (``SIFT_INT_DESCR_FCTR = 512`` then ``saturate_cast<uchar>``: on 20 rtabmap samples, integer
values, L2 norms 510.5-513.5, median 512, maximum 229). :func:`normalize_descriptors` puts any SIFT-like descriptor on that
scale (L2 norm 512, rounded, saturated, uint8), so a threshold means the same for both: ``t_match / 512`` is the L1
distance in units of the descriptor's L2 norm. On our images the thesis's 1000 accepts only half to two thirds of
the verified correspondences between revisits, 1700 about 90 % (and 3-5 % of chance nearest neighbours);
docs/loopclosure.md has the measured distances (``semloc eval loopclosure`` reports them) behind the default of 1700
(with repeated-texture features suppressed at the same threshold).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from pydantic import Field

from semloc_core.camera import CameraRig, EquirectangularCamera, PinholeCamera, members, rays_body
from semloc_core.geometry import wrap_angle
from semloc_core.settings import settings

DESCRIPTOR_SCALE = 512.0
"""L2 norm of a descriptor on VLFeat's (and OpenCV's) uint8 scale; ``t_match`` is expressed on this scale."""

DESCRIPTOR_SIZE = 128


def normalize_descriptors(descriptors) -> np.ndarray:
    """SIFT-like descriptors (any positive scale) -> uint8 on VLFeat's scale (L2 norm 512, saturated at 255)."""
    d = np.asarray(descriptors, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_SIZE:
        raise ValueError(f"descriptors must have shape (n, {DESCRIPTOR_SIZE}), got {d.shape}")
    if not np.all(np.isfinite(d)) or np.any(d < 0):
        raise ValueError("descriptors must be finite and non-negative (SIFT histograms)")
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    scaled = np.where(norms > 0, d * (DESCRIPTOR_SCALE / np.maximum(norms, 1e-12)), 0.0)
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


@settings
class FeatureParams:
    """SIFT settings. ``max_features`` caps the keypoints per camera image (strongest first; 0 keeps all).

    ``repeated_threshold``: features with another feature of the same frame closer than this (L1, VLFeat scale)
    are dropped - repeated texture (bricks, tiles, ceiling panels) that matches anywhere (§3.6.4); 0 keeps all.

    Small and low-contrast images (issue 33): an image whose shorter side is below ``upsample_below`` pixels is
    upsampled by the integer factor that lifts it above (bicubic; the keypoints are mapped back), so SIFT's finest
    octaves see structure a 160x120 frame holds only a few pixels of; ``stretch_contrast`` maps the grey levels'
    1st..99th percentiles to 0..255 first, which scales SIFT's contrast threshold with the image's own range (a
    darker second traversal is detected like the first; the descriptors are normalised anyway). Lowering the
    threshold further until a number of keypoints is found was measured and left out: the extra weak features raise
    the ratio-test counts' AP but lower the DP's (docs/loopclosure.md).
    """

    max_features: int = Field(500, ge=0, le=20000, description="SIFT keypoints per camera image, strongest first "
                              "(0 = all)")
    contrast_threshold: float = Field(0.04, gt=0, description="SIFT contrast threshold")
    edge_threshold: float = Field(10.0, gt=0, description="SIFT edge threshold")
    sigma: float = Field(1.6, gt=0, description="SIFT's Gaussian at octave 0")
    octave_layers: int = Field(3, ge=1, description="SIFT layers per octave")
    repeated_threshold: float = Field(1700.0, ge=0, description="drop features matching another one of their own "
                                      "frame within this L1 distance (VLFeat scale; 0 keeps them)")
    upsample_below: int = Field(240, ge=0, le=4096, description="upsample images whose shorter side is below this "
                                "many pixels, by an integer factor (0: never)")
    stretch_contrast: bool = Field(True, description="stretch the grey levels' 1st..99th percentiles to 0..255 "
                                   "before SIFT")


@dataclass(frozen=True, eq=False)
class FeatureSequence:
    """One frame's features sorted by bearing.

    ``bearings`` (n,) float64 radians in [-pi, pi), ascending; ``descriptors`` (n, 128) uint8 on VLFeat's scale;
    ``camera_index`` (n,) int16, the rig member each feature came from (0 for a single camera); ``points`` (n, 2)
    float32 pixel coordinates in that member's image (for display).
    """

    bearings: np.ndarray
    descriptors: np.ndarray
    camera_index: np.ndarray = field(default=None)  # type: ignore[assignment]
    points: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        bearings = np.asarray(self.bearings, dtype=np.float64).reshape(-1)
        descriptors = np.asarray(self.descriptors)
        n = bearings.size
        if descriptors.dtype != np.uint8 or descriptors.shape != (n, DESCRIPTOR_SIZE):
            raise ValueError(
                f"descriptors must be uint8 of shape ({n}, {DESCRIPTOR_SIZE}) on VLFeat's scale "
                f"(use normalize_descriptors), got {descriptors.dtype} {descriptors.shape}"
            )
        if not np.all(np.isfinite(bearings)) or np.any(bearings < -np.pi) or np.any(bearings >= np.pi):
            raise ValueError("bearings must be finite and in [-pi, pi)")
        if n > 1 and np.any(np.diff(bearings) < 0):
            raise ValueError("bearings must be sorted ascending (use FeatureSequence.from_unsorted)")
        camera_index = np.zeros(n, np.int16) if self.camera_index is None else np.asarray(self.camera_index)
        points = np.zeros((n, 2), np.float32) if self.points is None else np.asarray(self.points, np.float32)
        if camera_index.shape != (n,) or points.shape != (n, 2):
            raise ValueError(f"camera_index must be ({n},) and points ({n}, 2)")
        object.__setattr__(self, "bearings", bearings)
        object.__setattr__(self, "descriptors", np.ascontiguousarray(descriptors))
        object.__setattr__(self, "camera_index", camera_index.astype(np.int16))
        object.__setattr__(self, "points", points)

    @classmethod
    def from_unsorted(cls, bearings, descriptors, camera_index=None, points=None) -> "FeatureSequence":
        """Sort features by bearing (stable, so equal bearings keep their input order)."""
        bearings = wrap_angle(np.asarray(bearings, dtype=np.float64).reshape(-1))
        order = np.argsort(bearings, kind="stable")
        pick = (lambda a: None if a is None else np.asarray(a)[order])
        return cls(bearings[order], np.asarray(descriptors)[order], pick(camera_index), pick(points))

    @classmethod
    def empty(cls) -> "FeatureSequence":
        return cls(np.zeros(0), np.zeros((0, DESCRIPTOR_SIZE), np.uint8))

    def __len__(self) -> int:
        return int(self.bearings.size)

    def subset(self, keep) -> "FeatureSequence":
        """The features selected by a boolean mask or index array (order kept)."""
        return FeatureSequence(self.bearings[keep], self.descriptors[keep], self.camera_index[keep], self.points[keep])

    def rotated(self, angle: float) -> "FeatureSequence":
        """The same features seen after turning the body by ``-angle`` (every bearing shifted by ``angle``)."""
        return FeatureSequence.from_unsorted(self.bearings + angle, self.descriptors, self.camera_index, self.points)


@njit(cache=True, nogil=True)
def l1_match_matrix(query: np.ndarray, reference: np.ndarray, t_match: float) -> np.ndarray:
    """match[i, j] = |q_i - r_j|_1 < t_match, on uint8 descriptors. A pair is compared in full only when the L1
    distance of its sums over groups of 4 dimensions (a lower bound of its L1 distance, :func:`_group_sums`) is
    below ``t_match``: 99 % of the pairs of two of the demo's key-frames are ruled out at its 1150, and 500 x 500
    features take 0.7 ms instead of 6 (the engine aligns every earlier frame this way until it has its vocabulary:
    the demo's slowest frames). The result is the full comparison's, bit for bit."""
    n, m, dims = query.shape[0], reference.shape[0], query.shape[1]
    match = np.zeros((n, m), np.bool_)
    if n == 0 or m == 0:
        return match
    own, other = _group_sums(query), _group_sums(reference)
    bound = np.empty(m, np.int16)
    for i in range(n):
        bound[:] = 0  # summed group by group in int16 (at most 32,640 for 128 dimensions): it vectorises
        for g in range(other.shape[0]):
            mine = own[g, i]
            row = other[g]
            for k in range(m):
                x = np.int16(mine - row[k])
                bound[k] += np.int16(max(x, -x))
        for j in range(m):
            if bound[j] >= t_match:
                continue
            total = 0
            for d in range(dims):
                total += abs(np.int32(query[i, d]) - np.int32(reference[j, d]))
            match[i, j] = total < t_match
    return match


@njit(cache=True, nogil=True)
def _group_sums(descriptors: np.ndarray) -> np.ndarray:
    """(groups, n) int16 sums of each descriptor's groups of 4 dimensions (at most 4 x 255 each): the L1 distance of
    two features' sums is a lower bound of theirs (triangle inequality per group) at a quarter of the work."""
    n, dims = descriptors.shape
    sums = np.zeros(((dims + 3) // 4, n), np.int16)
    for i in range(n):
        for d in range(dims):
            sums[d // 4, i] += descriptors[i, d]
    return sums


@njit(cache=True, nogil=True)
def l1_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) L1 distances between uint8 descriptor sets (C-contiguous)."""
    n, m, dims = a.shape[0], b.shape[0], a.shape[1]
    out = np.empty((n, m), np.int32)
    for i in range(n):
        for j in range(m):
            total = 0
            for k in range(dims):
                total += abs(np.int32(a[i, k]) - np.int32(b[j, k]))
            out[i, j] = total
    return out


@njit(cache=True, nogil=True)
def match_and_squared_l2(query: np.ndarray, reference: np.ndarray, t_match: float):
    """One pass over all pairs of uint8 descriptors: the L1 match matrix (distance below ``t_match``) and the exact
    squared L2 distances."""
    n, m, dims = query.shape[0], reference.shape[0], query.shape[1]
    match = np.empty((n, m), np.bool_)
    d2 = np.empty((n, m), np.int32)
    for i in range(n):
        for j in range(m):
            l1 = 0
            l2 = 0
            for d in range(dims):
                x = np.int32(query[i, d]) - np.int32(reference[j, d])
                l1 += abs(x)
                l2 += x * x
            match[i, j] = l1 < t_match
            d2[i, j] = l2
    return match, d2


def suppress_repeated(sequence: FeatureSequence, threshold: float) -> FeatureSequence:
    """Drop every feature that has another feature of the same frame within L1 distance ``threshold``.

    Such features come from repeated texture; they match equally well anywhere the texture appears, which is the
    perceptual aliasing of §3.6.4 (the same idea as discounting "bursty" visual words, Jegou et al. 2009).
    """
    if threshold <= 0 or len(sequence) < 2:
        return sequence
    repeated = _repeated(np.ascontiguousarray(sequence.descriptors), float(threshold))
    return sequence.subset(~repeated) if repeated.any() else sequence


@njit(cache=True, nogil=True)
def _repeated(descriptors: np.ndarray, threshold: float) -> np.ndarray:
    """repeated[i]: another feature of the set lies within L1 ``threshold`` of feature i - what the full
    :func:`l1_match_matrix` of the set with itself tells, from each pair once. A pair is compared in full only when
    the L1 distance of its sums over groups of 4 dimensions, a lower bound of its L1 distance (triangle inequality
    per group) at a quarter of the work, is below the threshold: on SIFT that rules out 96-99 % of the pairs at
    thresholds 1200-1700 (route frames). The bounds of one feature against all later ones are summed group by group
    in int16 (a group's sum is at most 4 x 255, 128 dimensions' bound at most 32,640), which vectorises: a third
    less time than one pair at a time."""
    n, dims = descriptors.shape
    sums = _group_sums(descriptors)
    bound = np.empty(n, np.int16)
    repeated = np.zeros(n, np.bool_)
    for i in range(n):
        later = bound[i + 1:]  # (indexed from 0, so no index can be negative: the loops vectorise)
        later[:] = 0
        for g in range(sums.shape[0]):
            own = sums[g, i]
            row = sums[g, i + 1:]
            for k in range(row.size):
                x = np.int16(own - row[k])
                later[k] += np.int16(max(x, -x))
        for k in range(later.size):
            if later[k] >= threshold:
                continue
            j = i + 1 + k
            total = 0
            for d in range(dims):
                total += abs(np.int32(descriptors[i, d]) - np.int32(descriptors[j, d]))
            if total < threshold:
                repeated[i] = True
                repeated[j] = True
    return repeated


def _sift(params: FeatureParams):
    return cv2.SIFT_create(
        nfeatures=params.max_features,
        nOctaveLayers=params.octave_layers,
        contrastThreshold=params.contrast_threshold,
        edgeThreshold=params.edge_threshold,
        sigma=params.sigma,
    )


def detect(grey: np.ndarray, params: FeatureParams) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints (pixel coordinates of ``grey``) and descriptors, with the small/low-contrast adaptations of
    :class:`FeatureParams`."""
    short = min(grey.shape)
    small = params.upsample_below and short < params.upsample_below
    factor = int(np.ceil(params.upsample_below / short)) if small else 1
    image = grey
    if params.stretch_contrast:
        low, high = np.percentile(grey, (1, 99))
        if high - low >= 8:  # an almost uniform image has nothing to stretch (and noise to amplify)
            image = cv2.convertScaleAbs(grey, alpha=255.0 / (high - low), beta=-255.0 * low / (high - low))
    if factor > 1:
        image = cv2.resize(image, (grey.shape[1] * factor, grey.shape[0] * factor), interpolation=cv2.INTER_CUBIC)
    keypoints, descriptors = _sift(params).detectAndCompute(image, None)
    if not keypoints:
        return np.zeros((0, 2)), None
    # Pixel centres at integers: a pixel's centre x maps to factor * x + (factor - 1) / 2 in the upsampled image.
    uv = (np.array([kp.pt for kp in keypoints], dtype=np.float64) - (factor - 1) / 2) / factor
    return uv, descriptors


def _grey(image: np.ndarray, camera, index: int) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image {index} must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"image {index} must be (H, W) grey or (H, W, 3) BGR, got shape {image.shape}")
    if image.shape != (camera.height, camera.width):
        raise ValueError(
            f"image {index} is {image.shape[1]}x{image.shape[0]} but its camera model is {camera.width}x{camera.height}"
        )
    return image


def extract_features(
    images,
    camera: PinholeCamera | EquirectangularCamera | CameraRig,
    params: FeatureParams = FeatureParams(),
    T_body_cam: np.ndarray | None = None,
) -> FeatureSequence:
    """SIFT features of one frame as a bearing-sorted sequence (§3.3.1).

    ``images``: one image for a single camera, or one per rig member (in the rig's order). ``T_body_cam`` overrides a
    single camera's extrinsic for this frame (e.g. the pitch and roll of a hand-held camera). For an
    equirectangular panorama the bearing wraps at the seam, which is why sequences are aligned cyclically.
    """
    cams = members(camera)
    if isinstance(camera, CameraRig):
        if T_body_cam is not None:
            raise ValueError("a per-frame T_body_cam override applies to single cameras, not rigs")
        if isinstance(images, np.ndarray) or len(images) != len(cams):
            raise ValueError(f"a rig of {len(cams)} cameras needs a sequence of {len(cams)} images")
        image_list = list(images)
    else:
        image_list = [images]
    bearings, descriptors, camera_index, points = [], [], [], []
    for index, (image, cam) in enumerate(zip(image_list, cams)):
        uv, desc = detect(_grey(image, cam, index), params)
        if desc is None:
            continue
        rays = rays_body(cam, uv[:, 0], uv[:, 1], T_body_cam=T_body_cam)
        # Elevation is dropped: only the azimuth of the ray in the body frame orders the sequence.
        bearings.append(np.arctan2(rays[:, 1], rays[:, 0]))
        descriptors.append(normalize_descriptors(desc))
        camera_index.append(np.full(len(uv), index, np.int16))
        points.append(uv.astype(np.float32))
    if not bearings:
        return FeatureSequence.empty()
    merged = FeatureSequence.from_unsorted(
        np.concatenate(bearings), np.concatenate(descriptors), np.concatenate(camera_index), np.concatenate(points)
    )
    return suppress_repeated(merged, params.repeated_threshold)
