"""The loop-closure experiment's data: a sequence with its loop ground truth, its features and the full
similarity matrices, each kept in the cache folder between runs."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semloc_core.camera import PinholeCamera, members
from semloc_core.loopclosure import FeatureParams
from semloc_core.loopclosure.evaluation import SCORES, descriptor_distances, distance_summary, similarity_columns
from semloc_core.sim.degrade import Degradation, degrade, fisheye_camera

Log = Callable[[str], None]
NOMINAL_FOV_DEG = 60.0
"""The horizontal field of view assumed for an image folder without a camera.json (a warning says so)."""


@dataclass
class LoopSequence:
    """What the evaluation needs from a dataset: images, camera model, ground truth (and poses when known)."""

    path: str
    name: str
    frames: int
    camera: object
    image: Callable[[int], object]
    T_body_cam: Callable[[int], object]
    gt: np.ndarray  # (n, n) bool, gt[earlier, later], strictly upper triangular: true loops
    ignore: np.ndarray  # (n, n) bool: pairs neither counted as loops nor as mistakes (soft ground truth)
    positions: np.ndarray | None  # (n, 3) camera centres (planar figures use x, y)
    gt_distance: float | None
    gt_source: str
    stamps_s: np.ndarray  # (n,) capture times
    poses2d: np.ndarray | None  # (n, 3) body x, y, theta when known
    frame_index: np.ndarray | None = None  # the dataset's index of each frame (None: all frames, in order)
    camera_assumed: bool = False  # no calibration came with the images: a nominal pinhole stands in


def _scenario(text: str):
    """``scenario:NAME[:key=value,...]``, e.g. ``scenario:route:seed=0,frames=1200`` - rendered on demand."""
    from semloc_core.sim.scenarios import make_scenario

    parts = text.split(":", 2)
    options = {}
    if len(parts) == 3 and parts[2]:
        for item in parts[2].split(","):
            key, _, value = item.partition("=")
            options[key.strip()] = json.loads(value) if value.strip()[:1] in "0123456789-[{tf" else value
    return make_scenario(parts[1], **options)


def open_loop_sequence(text: str, gt_distance: float | None) -> LoopSequence:
    """A semloc dataset folder, a rendered scenario (``scenario:route:...``) or an image folder with a
    ground-truth matrix (rtabmap_loop_samples layout; no calibration there: a nominal pinhole is assumed, which
    does not change the scores - the DP sees only the order of the bearings). ValueError when unusable."""
    from semloc_core.io.dataset import DatasetError, open_dataset

    try:
        dataset = _scenario(text) if text.startswith("scenario:") else open_dataset(text)
    except (DatasetError, ValueError, KeyError) as error:
        raise ValueError(f"cannot open {text}: {error}") from None
    if not dataset.has_images:
        raise ValueError(f"{text} has no images")
    n = len(dataset)
    settings = getattr(dataset, "loop_settings", None)
    loop_meta = dataset.metadata.get("loop", {}) if isinstance(dataset.metadata.get("loop"), dict) else {}
    distance = settings.distance if settings is not None else loop_meta.get("distance")
    positions = dataset.T_world_cam[:, :3, 3] if dataset.has_poses else None  # camera centres
    if gt_distance is not None:
        if not dataset.has_poses:
            raise ValueError(f"gt_distance needs poses, and {text} has none")
        max_angle = settings.max_angle if settings is not None else (
            np.radians(loop_meta["max_angle_deg"]) if loop_meta.get("max_angle_deg") is not None else None)
        hard, soft = dataset.loop_gt_at(gt_distance, 2 * gt_distance, max_angle)
        distance, source = gt_distance, f"poses, {gt_distance} m (soft {2 * gt_distance} m)"
    elif dataset.loop_gt is not None:
        hard = dataset.loop_gt
        soft = dataset.loop_gt_soft if dataset.loop_gt_soft is not None else hard
        source = "dataset" + (f", {distance} m" if distance else " matrix")
    else:
        raise ValueError(f"{text} has no loop ground truth: give gt_distance")
    hard = np.triu(hard | hard.T, 1)
    soft = np.triu(soft | soft.T, 1)
    return LoopSequence(text, dataset.name, n, dataset.camera, dataset.image, dataset.T_body_cam_at, hard,
                        soft & ~hard, positions, distance, source, np.asarray(dataset.stamps_ns, float) * 1e-9,
                        dataset.poses2d if dataset.has_poses else None,
                        camera_assumed=bool(dataset.metadata.get("camera_assumed")))


def keyframe_sequence(sequence: LoopSequence, params, log: Log) -> LoopSequence:
    """The key-frames of ``sequence`` (semloc_core.loopclosure.keyframes, as the worker gates a live camera: the
    poses stand for its odometry; without poses, image change alone) with their ground truth."""
    from semloc_core.loopclosure.keyframes import select_keyframes, thumbnail

    thumbs = (thumbnail(sequence.image(k)) for k in range(sequence.frames)) if params.min_change else None
    if thumbs is None:
        thumbs = (None for _ in range(sequence.frames))
    kept = select_keyframes(sequence.stamps_s, sequence.poses2d, thumbs, params)
    log(f"key-frames: {kept.size} of {sequence.frames} frames")
    image, T_body_cam = sequence.image, sequence.T_body_cam
    return LoopSequence(
        sequence.path, sequence.name, int(kept.size), sequence.camera, lambda k: image(int(kept[k])),
        lambda k: T_body_cam(int(kept[k])), sequence.gt[np.ix_(kept, kept)], sequence.ignore[np.ix_(kept, kept)],
        None if sequence.positions is None else sequence.positions[kept], sequence.gt_distance, sequence.gt_source,
        sequence.stamps_s[kept], None if sequence.poses2d is None else sequence.poses2d[kept], kept,
        sequence.camera_assumed)


def scores_on_all_frames(full: LoopSequence, kept: np.ndarray, matrices: dict, window: int) -> dict:
    """The key-frames' raw scores as a live worker answers every frame (each frame by its latest key-frame), ranked
    on the whole sequence's pairs: PR figures per score, comparable with an evaluation of every frame."""
    from semloc_core.eval.pr import pr_curve
    from semloc_core.loopclosure.evaluation import curve_summary, evaluated_pairs

    owner = np.searchsorted(kept, np.arange(full.frames), side="right") - 1
    earlier, later = evaluated_pairs(full.frames, window, full.ignore)
    labels = full.gt[earlier, later]
    return {name: curve_summary(pr_curve(M[owner[earlier], owner[later]], labels)) for name, M in matrices.items()}


def degraded(sequence: LoopSequence, degradation: Degradation):
    """The degradation set for this sequence's camera (the fisheye warp needs its field of view) and the camera
    model of the degraded images: the lens that made them for a fisheye warp (OpenCV's fisheye model), the same
    camera with its intrinsics scaled for a downscale. ValueError when the camera cannot be degraded so."""
    from dataclasses import replace

    camera = sequence.camera
    if degradation.is_identity:
        return degradation, camera
    if not isinstance(camera, PinholeCamera) or camera.dist.size:
        raise ValueError("images can be degraded for a single distortion-free pinhole camera only")
    degradation = replace(degradation, source_fov_deg=float(np.degrees(camera.horizontal_fov)))
    width, height = degradation.output_size(camera.width, camera.height)
    if degradation.fisheye:
        return degradation, replace(fisheye_camera(degradation, width, height), T_body_cam=camera.T_body_cam)
    scale = np.diag([width / camera.width, height / camera.height, 1.0])
    return degradation, PinholeCamera(width, height, scale @ camera.K, T_body_cam=camera.T_body_cam)


def cache_file(spec, what: str) -> str | None:
    """One file per dataset and ``what`` (features, matrices) in the spec's cache folder."""
    if not spec.cache:
        return None
    Path(spec.cache).mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha1(spec.dataset.encode()).hexdigest()[:8]
    name = Path(spec.dataset.rstrip("/")).name.replace(":", "-") or "dataset"
    return str(Path(spec.cache) / f"{name}-{digest}_{what}.npz")


def features(sequence: LoopSequence, degradation: Degradation, camera, params: FeatureParams, cache: str | None,
             log: Log) -> tuple[list, np.ndarray]:
    """Every frame's features and SeqSLAM thumbnail, of the images degraded so (``camera``: their model), from
    ``cache`` when it was made from this data with these settings."""
    from semloc_core.io.loopclosure import load_features, save_features
    from semloc_core.loopclosure import extract_features
    from semloc_core.loopclosure.seqslam import thumbnail

    meta = {"dataset": sequence.path, "frames": sequence.frames, "sift": params.__dict__,
            "frame_index": None if sequence.frame_index is None else sequence.frame_index.tolist(),
            "degradation": {k: list(v) if isinstance(v, tuple) else v for k, v in degradation.__dict__.items()}}
    thumbs_cache = cache and str(Path(cache).with_name(Path(cache).stem + "_seqslam.npy"))
    if cache and Path(cache).exists() and Path(thumbs_cache).exists():
        frames, stored = load_features(cache)
        if {k: stored.get(k) for k in meta} == meta and len(frames) == sequence.frames:
            thumbnails = np.load(thumbs_cache, allow_pickle=False)
            if len(thumbnails) == sequence.frames:
                log(f"features: {len(frames)} frames from {cache}")
                return frames, thumbnails
        log(f"features: {cache} was made from other data or settings; recomputing")
    frames, thumbnails = [], []
    start = time.perf_counter()
    for k in range(sequence.frames):
        image = degrade(sequence.image(k), k, sequence.frames, degradation)
        frames.append(extract_features(image, camera, params, sequence.T_body_cam(k)))
        thumbnails.append(thumbnail(image))
        if (k + 1) % 100 == 0 or k + 1 == sequence.frames:
            log(f"features: {k + 1}/{sequence.frames} ({(time.perf_counter() - start) / (k + 1) * 1e3:.0f} ms/frame)")
    thumbnails = np.stack(thumbnails) if thumbnails else np.zeros((0, 1, 1), np.float32)
    if cache:
        save_features(cache, frames, meta)
        np.save(thumbs_cache, thumbnails, allow_pickle=False)
    return frames, thumbnails


def descriptor_study(sequence: LoopSequence, camera, frames, window: int, thresholds, pairs: int = 200):
    """L1 distances of verified correspondences on ground-truth loops vs nearest neighbours in unrelated frames
    (a fixed random sample of each), for pinhole cameras and rigs of them; None for other lenses."""
    if not all(isinstance(c, PinholeCamera) for c in members(camera)):
        return None
    rng = np.random.default_rng(0)
    unrelated = np.triu(~(sequence.gt | sequence.gt.T | sequence.ignore | sequence.ignore.T), window + 1)

    def sample(mask):
        found = np.argwhere(mask)
        return found[np.sort(rng.choice(len(found), min(pairs, len(found)), replace=False))]

    verified, nearest = descriptor_distances(frames, sample(np.triu(sequence.gt, window + 1)), sample(unrelated))
    return distance_summary(verified, nearest, thresholds)


# Full similarity matrices, spread over forked processes that read the features from this module's global.
_SHARED: dict = {}


def _columns_job(columns):
    s = _SHARED
    return columns, similarity_columns(s["frames"], columns, s["window"], s["alignment"], 0.8, s["bow"])


def full_matrices(frames, window, alignment, bow, jobs, log: Log) -> dict[str, np.ndarray]:
    n = len(frames)
    # Interleave columns so every job gets a similar share of the (triangular) work.
    chunks = [list(range(start, n, max(jobs, 1) * 4)) for start in range(max(jobs, 1) * 4)]
    chunks = [c for c in chunks if c]
    out = {name: np.full((n, n), -np.inf) for name in SCORES}
    _SHARED.update(frames=frames, window=window, alignment=alignment, bow=bow)
    start = time.perf_counter()
    if jobs <= 1:
        results = map(_columns_job, chunks)
    else:
        import multiprocessing

        pool = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork"))
        results = pool.map(_columns_job, chunks)
    try:
        for done, (columns, part) in enumerate(results, 1):
            for name, values in part.items():
                out[name][:, columns] = values
            log(f"similarity: {done}/{len(chunks)} column groups ({time.perf_counter() - start:.0f} s)")
    finally:
        _SHARED.clear()
        if jobs > 1:
            pool.shutdown()
    return out


def fingerprint(frames) -> str:
    """SHA-1 of every frame's bearings and descriptors: what the matrices were computed from."""
    digest = hashlib.sha1()
    for f in frames:
        digest.update(np.int64(len(f)).tobytes())
        digest.update(np.ascontiguousarray(f.bearings).tobytes())
        digest.update(np.ascontiguousarray(f.descriptors).tobytes())
    return digest.hexdigest()


def cached_matrices(cache: str | None, meta: dict, compute, log: Log) -> dict[str, np.ndarray]:
    from semloc_core.io.loopclosure import load_matrices, save_matrices

    if cache and Path(cache).exists():
        matrices, stored = load_matrices(cache)
        if {k: stored.get(k) for k in meta} == meta and set(matrices) == set(SCORES):
            log(f"similarity: matrices from {cache}")
            return matrices
        log(f"similarity: {cache} was made from other features or settings; recomputing")
    matrices = compute()
    if cache:
        save_matrices(cache, matrices, meta)
    return matrices
