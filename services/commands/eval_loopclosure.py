"""`semloc eval loopclosure DATASET --json OUT`: loop-closure precision-recall and the topological map.

For the DP score and the three baselines (M^SIFT, M^SYM, BoW TF-IDF): PR raw and after batch inference,
interpolated precision, AP, recall at 100 % precision; the incremental engine on the same features; the
topological map's figures; PNG plots next to the JSON. DATASET: a simulated dataset (``semloc sim``) or an image
folder with a ground-truth loop matrix (the layout of ``rtabmap_loop_samples``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semloc_core.camera import PinholeCamera, members
from semloc_core.io.loopclosure import (
    load_features,
    load_matrices,
    load_vocabulary,
    save_features,
    save_matrices,
    save_topomap,
    save_vocabulary,
)
from semloc_core.loopclosure import (
    AlignmentParams,
    EngineParams,
    FeatureParams,
    LoopClosureEngine,
    MrfParams,
    extract_features,
    train_vocabulary,
)
from semloc_core.loopclosure.evaluation import (
    SCORES,
    curve_summary,
    decision_quality,
    descriptor_distances,
    distance_summary,
    evaluate_score,
    evaluate_topomap,
    same_place_pairs,
    evaluated_pairs,
    similarity_columns,
)
from semloc_core.eval.pr import interpolated_precision, pr_curve
from semloc_core.eval.report import json_text, markdown_table, matrix_png, pr_plot_png
from semloc_core.loopclosure.plots import topomap_png
from semloc_core.loopclosure.mrf import COUPLINGS, POTENTIALS
from semloc_core.loopclosure.topomap import map_from_beliefs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="simulated dataset directory or image folder with a GT matrix")
    parser.add_argument("--json", required=True, help="report file (JSON); plots go next to it")
    parser.add_argument("--window", type=int, default=30, help="w: pairs i < j - w are scored (thesis: 30)")
    parser.add_argument("--gt-distance", type=float, default=None,
                        help="metres: ground truth from poses (default: the dataset's own, else its matrix)")
    parser.add_argument("--max-features", type=int, default=500, help="SIFT keypoints per image (0 = all)")
    parser.add_argument("--t-match", type=float, default=AlignmentParams().t_match,
                        help="L1 match threshold, VLFeat scale (thesis: 1000)")
    parser.add_argument("--repeated-threshold", type=float, default=None,
                        help="drop features with a match inside their own frame (default: --t-match; 0: keep all)")
    defaults = MrfParams()
    parser.add_argument("--potential", choices=POTENTIALS, default=defaults.potential, help="MRF node potential")
    parser.add_argument("--z0", type=float, default=defaults.z0, help="calibrated: even odds at z0 deviations")
    parser.add_argument("--kappa", type=float, default=defaults.kappa, help="calibrated: log-odds per deviation")
    parser.add_argument("--coupling", choices=COUPLINGS, default=defaults.coupling)
    parser.add_argument("--sigma", type=float, default=None,
                        help="edge sigma: fraction of F (thesis potential, 0.05) or deviations (calibrated, 5)")
    parser.add_argument("--alpha", type=float, default=defaults.alpha, help="edge weight alpha")
    parser.add_argument("--dp-offset", type=float, default=defaults.offset,
                        help="thesis potential: DP score mapped to phi(1) = 0 (the baselines' scores are >= 0)")
    parser.add_argument("--words", type=int, default=1000, help="BoW vocabulary size when it is learnt here")
    parser.add_argument("--vocabulary", default=None,
                        help="vocabulary .npz for the BoW score and the engine (default: learnt on this dataset for "
                             "the BoW score; the engine learns its own from its first frames, as the worker does)")
    parser.add_argument("--save-vocabulary", default=None,
                        help="write the vocabulary learnt here (.npz; e.g. for a worker's --vocabulary)")
    parser.add_argument("--temporal-radius", type=int, default=2, help="r: frames <= r apart share a place")
    parser.add_argument("--map-min-belief", type=float, default=EngineParams().map_min_belief,
                        help="log-odds a loop needs to join places in the map (batch and engine)")
    parser.add_argument("--feature-cache", default=None, help=".npz cache of the features (created if missing)")
    parser.add_argument("--matrix-cache", default=None,
                        help=".npz cache of the full similarity matrices (created if missing, reused when the features,"
                             " window, alignment and vocabulary settings match)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes for the full matrices")
    parser.add_argument("--no-engine", action="store_true", help="skip the incremental engine run")
    parser.add_argument("--candidates", type=int, default=EngineParams().candidates, help="engine: retrieved frames")
    parser.add_argument("--neighbour-candidates", type=int, default=EngineParams().neighbour_candidates,
                        help="engine: also align frames this close to the previous frame's loop partners")


# --- datasets -------------------------------------------------------------------------------------------------


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
    positions: np.ndarray | None
    gt_distance: float | None
    gt_source: str


def _scenario(spec: str):
    """``scenario:NAME[:key=value,...]``, e.g. ``scenario:route:seed=0,frames=1200`` - rendered on demand."""
    from semloc_core.sim.scenarios import make_scenario

    parts = spec.split(":", 2)
    options = {}
    if len(parts) == 3 and parts[2]:
        for item in parts[2].split(","):
            key, _, value = item.partition("=")
            options[key.strip()] = json.loads(value) if value.strip()[:1] in "0123456789-[{tf" else value
    return make_scenario(parts[1], **options)


def open_loop_sequence(spec: str, gt_distance: float | None) -> LoopSequence:
    """A semloc dataset folder, a rendered scenario (``scenario:route:...``) or an image folder with a
    ground-truth matrix (rtabmap_loop_samples layout; no calibration there: a nominal pinhole is assumed, which
    does not change the scores - the DP sees only the order of the bearings)."""
    from semloc_core.io.dataset import DatasetError, open_dataset

    try:
        dataset = _scenario(spec) if spec.startswith("scenario:") else open_dataset(spec)
    except (DatasetError, ValueError, KeyError) as error:
        raise SystemExit(f"cannot open {spec}: {error}") from None
    if not dataset.has_images:
        raise SystemExit(f"{spec} has no images")
    n = len(dataset)
    settings = getattr(dataset, "loop_settings", None)
    loop_meta = dataset.metadata.get("loop", {}) if isinstance(dataset.metadata.get("loop"), dict) else {}
    distance = settings.distance if settings is not None else loop_meta.get("distance")
    positions = dataset.T_world_cam[:, :2, 3] if dataset.has_poses else None
    if gt_distance is not None:
        if not dataset.has_poses:
            raise SystemExit(f"--gt-distance needs poses, and {spec} has none")
        max_angle = settings.max_angle if settings is not None else (
            np.radians(loop_meta["max_angle_deg"]) if loop_meta.get("max_angle_deg") is not None else None)
        hard, soft = dataset.loop_gt_at(gt_distance, 2 * gt_distance, max_angle)
        distance, source = gt_distance, f"poses, {gt_distance} m (soft {2 * gt_distance} m)"
    elif dataset.loop_gt is not None:
        hard = dataset.loop_gt
        soft = dataset.loop_gt_soft if dataset.loop_gt_soft is not None else hard
        source = "dataset" + (f", {distance} m" if distance else " matrix")
    else:
        raise SystemExit(f"{spec} has no loop ground truth: give --gt-distance")
    hard = np.triu(hard | hard.T, 1)
    soft = np.triu(soft | soft.T, 1)
    return LoopSequence(spec, dataset.name, n, dataset.camera, dataset.image, dataset.T_body_cam_at, hard,
                        soft & ~hard, positions, distance, source)


# --- features -------------------------------------------------------------------------------------------------


def _features(sequence: LoopSequence, params: FeatureParams, cache: str | None, log) -> list:
    meta = {"dataset": sequence.path, "frames": sequence.frames, "sift": params.__dict__}
    if cache and Path(cache).exists():
        frames, stored = load_features(cache)
        if stored.get("dataset") == meta["dataset"] and stored.get("sift") == meta["sift"] and len(frames) == sequence.frames:
            log(f"features: {len(frames)} frames from {cache}")
            return frames
        log(f"features: {cache} was made from other data or settings; recomputing")
    frames = []
    start = time.perf_counter()
    for k in range(sequence.frames):
        frames.append(extract_features(sequence.image(k), sequence.camera, params, sequence.T_body_cam(k)))
        if (k + 1) % 100 == 0 or k + 1 == sequence.frames:
            log(f"features: {k + 1}/{sequence.frames} ({(time.perf_counter() - start) / (k + 1) * 1e3:.0f} ms/frame)")
    if cache:
        save_features(cache, frames, meta)
    return frames


def _descriptor_distances(sequence: LoopSequence, frames, window: int, thresholds, pairs: int = 200):
    """L1 distances of verified correspondences on ground-truth loops vs nearest neighbours in unrelated frames
    (a fixed random sample of each), for pinhole cameras and rigs of them; None for panoramas."""
    if not all(isinstance(c, PinholeCamera) for c in members(sequence.camera)):
        return None
    rng = np.random.default_rng(0)
    unrelated = np.triu(~(sequence.gt | sequence.gt.T | sequence.ignore | sequence.ignore.T), window + 1)

    def sample(mask):
        found = np.argwhere(mask)
        return found[np.sort(rng.choice(len(found), min(pairs, len(found)), replace=False))]

    verified, nearest = descriptor_distances(frames, sample(np.triu(sequence.gt, window + 1)), sample(unrelated))
    return distance_summary(verified, nearest, thresholds)


# --- full similarity matrices, spread over processes ----------------------------------------------------------

_SHARED: dict = {}


def _columns_job(columns):
    s = _SHARED
    return columns, similarity_columns(s["frames"], columns, s["window"], s["alignment"], 0.8, s["bow"])


def _matrices(frames, window, alignment, bow, jobs, log) -> dict[str, np.ndarray]:
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
    for done, (columns, part) in enumerate(results, 1):
        for name, values in part.items():
            out[name][:, columns] = values
        log(f"similarity: {done}/{len(chunks)} column groups ({time.perf_counter() - start:.0f} s)")
    if jobs > 1:
        pool.shutdown()
    return out


def _fingerprint(frames) -> str:
    """SHA-1 of every frame's bearings and descriptors: what the matrices were computed from."""
    digest = hashlib.sha1()
    for f in frames:
        digest.update(np.int64(len(f)).tobytes())
        digest.update(np.ascontiguousarray(f.bearings).tobytes())
        digest.update(np.ascontiguousarray(f.descriptors).tobytes())
    return digest.hexdigest()


def _cached_matrices(cache: str | None, meta: dict, compute, log) -> dict[str, np.ndarray]:
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


# --- the run --------------------------------------------------------------------------------------------------


@dataclass
class _Logger:
    quiet: bool = False

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(message, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    log = _Logger()
    sequence = open_loop_sequence(args.dataset, args.gt_distance)
    out_json = Path(args.json)
    plot_dir = out_json.parent
    plot_dir.mkdir(parents=True, exist_ok=True)
    stem = out_json.stem
    log(f"{sequence.name}: {sequence.frames} frames, {int(sequence.gt.sum())} ground-truth loop pairs")

    repeated = args.t_match if args.repeated_threshold is None else args.repeated_threshold
    feature_params = FeatureParams(max_features=args.max_features, repeated_threshold=repeated)
    t0 = time.perf_counter()
    frames = _features(sequence, feature_params, args.feature_cache, log)
    feature_seconds = time.perf_counter() - t0

    alignment = AlignmentParams(t_match=args.t_match)
    common = dict(potential=args.potential, z0=args.z0, kappa=args.kappa, sigma=args.sigma, alpha=args.alpha,
                  coupling=args.coupling)
    mrf = MrfParams(**common)
    dp_mrf = MrfParams(**common, offset=args.dp_offset)
    if args.vocabulary:
        vocabulary, vocabulary_source = load_vocabulary(args.vocabulary), str(args.vocabulary)
    else:
        vocabulary = train_vocabulary([f.descriptors for f in frames if len(f)], words=args.words)
        vocabulary_source = f"k-means ({args.words} words) on this dataset's descriptors"
    if args.save_vocabulary:
        save_vocabulary(args.save_vocabulary, vocabulary)
    bow = [vocabulary.vector(f.descriptors) for f in frames]

    t0 = time.perf_counter()
    matrix_meta = {"features": _fingerprint(frames), "window": args.window, "alignment": alignment.__dict__,
                   "vocabulary": vocabulary_source, "ratio": 0.8}
    matrices = _cached_matrices(args.matrix_cache, matrix_meta,
                                lambda: _matrices(frames, args.window, alignment, bow, args.jobs, log), log)
    matrix_seconds = time.perf_counter() - t0

    earlier, later = evaluated_pairs(sequence.frames, args.window, sequence.ignore)
    labels = sequence.gt[earlier, later]
    counts = [len(f) for f in frames]
    evaluations = {name: evaluate_score(matrices[name], sequence.gt, args.window, dp_mrf if name == "dp" else mrf,
                                        sequence.ignore, counts) for name in SCORES}
    scores = {name: evaluations[name].summary() for name in SCORES}
    for name in SCORES:
        s = scores[name]
        log(f"{name:5s} AP raw {s['raw']['average_precision']:.3f} -> {s['after_inference']['average_precision']:.3f}"
            f"  R@100%P {s['raw']['recall_at_100_precision']:.3f} -> {s['after_inference']['recall_at_100_precision']:.3f}"
            f"  P@50%R {s['raw']['precision_at_50_recall']:.3f} -> {s['after_inference']['precision_at_50_recall']:.3f}"
            f"  D: P {s['decisions']['precision']:.3f} R {s['decisions']['recall']:.3f}")

    distances = _descriptor_distances(sequence, frames, args.window, [1000.0, 1300.0, 1700.0, 2100.0, args.t_match])
    if distances is not None:
        accepted = {a["t_match"]: a for a in distances["accepted"]}
        log(f"descriptors: {distances['verified_correspondences']['count']} verified correspondences; t_match 1000 "
            f"accepts {accepted[1000.0]['verified']:.2f} of them, {args.t_match:g} accepts "
            f"{accepted[float(args.t_match)]['verified']:.2f} (and {accepted[float(args.t_match)]['unrelated']:.3f} "
            f"of nearest neighbours in unrelated frames)")

    same_place = same_place_pairs(sequence.frames, sequence.gt, sequence.positions, sequence.gt_distance,
                                  args.temporal_radius)
    dp_decisions = evaluations["dp"].inference.decisions
    batch_map = map_from_beliefs(evaluations["dp"].inference.beliefs, args.map_min_belief, args.temporal_radius)
    report = {
        "dataset": str(sequence.path),
        "name": sequence.name,
        "frames": sequence.frames,
        "window": args.window,
        "ground_truth": {"pairs": int(sequence.gt.sum()), "evaluated_pairs": int(labels.size),
                         "ignored_pairs": int(sequence.ignore.sum()),
                         "distance_m": sequence.gt_distance, "source": sequence.gt_source},
        "features": {"sift": feature_params.__dict__, "mean_per_frame": float(np.mean([len(f) for f in frames])),
                     "seconds_per_frame": feature_seconds / max(sequence.frames, 1)},
        "alignment": alignment.__dict__,
        "mrf": mrf.__dict__,
        "dp_mrf": dp_mrf.__dict__,
        "vocabulary": vocabulary_source,
        "scores": scores,
        "interpolated_precision": {
            name: {"raw": interpolated_precision(evaluations[name].raw).tolist(),
                   "after_inference": interpolated_precision(evaluations[name].after).tolist()} for name in SCORES
        },
        "descriptor_distances": distances,
        "topomap_batch": evaluate_topomap(batch_map, same_place),
        "timing_s": {"features": feature_seconds, "full_matrices": matrix_seconds},
    }

    raw_curves = {name: evaluations[name].raw for name in SCORES}
    after_curves = {name: evaluations[name].after for name in SCORES}
    engine_map = engine = None
    if not args.no_engine:
        engine_params = EngineParams(window=args.window, alignment=alignment, mrf=dp_mrf, candidates=args.candidates,
                                     neighbour_candidates=args.neighbour_candidates,
                                     temporal_radius=args.temporal_radius, map_min_belief=args.map_min_belief)
        engine = LoopClosureEngine(engine_params, vocabulary if args.vocabulary else None)
        latencies = []
        statuses: dict[str, int] = {}
        aligned = 0
        for f in frames:
            t = time.perf_counter()
            result = engine.add_frame(f)
            latencies.append(time.perf_counter() - t)
            statuses[result.status.value] = statuses.get(result.status.value, 0) + 1
            aligned += result.candidates.size
        engine.topomap.flush()  # the sequence has ended: its last frames need not wait for a key-frame
        dense = engine.mrf.dense()
        after = pr_curve(dense.beliefs[earlier, later], labels)
        cells = engine.similarity_cells()
        engine_raw = np.full((sequence.frames, sequence.frames), -np.inf)
        engine_raw[cells[0], cells[1]] = cells[2]
        engine_map = engine.topomap.snapshot()
        raw_curves["engine"], after_curves["engine"] = pr_curve(engine_raw[earlier, later], labels), after
        report["engine"] = {
            "params": engine_params.to_json_dict(),
            "raw": curve_summary(raw_curves["engine"]),
            "after_inference": curve_summary(after),
            "decisions": decision_quality(dense.decisions[earlier, later], labels),
            "agreement_with_batch_dp": {
                "entries": float(np.mean(dense.decisions == dp_decisions)),
                "positive_jaccard": float(np.sum(dense.decisions & dp_decisions)
                                          / max(np.sum(dense.decisions | dp_decisions), 1)),
            },
            "live_cells": int(cells[0].size),
            "aligned_pairs": aligned,
            "ground_truth_pairs_aligned": float(np.mean(np.isfinite(engine_raw[earlier, later][labels]))),
            "latency_ms": {"p50": float(np.percentile(latencies, 50) * 1e3),
                           "p95": float(np.percentile(latencies, 95) * 1e3)},
            "statuses": statuses,
            "topomap": evaluate_topomap(engine_map, same_place),
        }
        save_topomap(plot_dir / f"{stem}_topomap.json", engine_map)
        save_topomap(plot_dir / f"{stem}_topomap.graphml", engine_map)
        e = report["engine"]
        log(f"engine AP {e['after_inference']['average_precision']:.3f}  D: P {e['decisions']['precision']:.3f} "
            f"R {e['decisions']['recall']:.3f}  latency p50 {e['latency_ms']['p50']:.1f} ms  "
            f"nodes {e['topomap']['nodes']}  same place {e['topomap']['same_place_fraction']:.3f}")

    pngs = {
        "pr": pr_plot_png(raw_curves, f"{sequence.name}: raw (solid) vs after inference (dashed)", interpolated=True,
                          dashed=after_curves),
        "M_dp": matrix_png(np.where(np.isfinite(matrices["dp"]), matrices["dp"], np.nan).T, "M (DP), row = later",
                           cmap="viridis"),
        "D_dp": matrix_png(dp_decisions.T.astype(float), "D (DP + inference)"),
        "ground_truth": matrix_png((sequence.gt | sequence.gt.T).astype(float), "ground truth"),
    }
    if sequence.positions is not None and engine_map is not None:
        loop_keys = [k for k in engine_map.keyframes.tolist() if engine.topomap.loops_of(int(k))]
        pngs["topomap"] = topomap_png(sequence.positions, engine_map.keyframes, engine_map.edges,
                                      np.array(loop_keys, np.int64), f"{sequence.name}: topological map")
    report["plots"] = {}
    for name, data in pngs.items():
        path = plot_dir / f"{stem}_{name}.png"
        path.write_bytes(data)
        report["plots"][name] = str(path)
    rows = []
    for name in list(SCORES) + (["engine"] if "engine" in report else []):
        entry = report["engine"] if name == "engine" else scores[name]
        raw = entry["raw"]
        rows.append({"score": name, "AP raw": raw["average_precision"],
                     "AP after": entry["after_inference"]["average_precision"],
                     "AP101 raw": raw["interpolated_average_precision"],
                     "AP101 after": entry["after_inference"]["interpolated_average_precision"],
                     "R@100%P raw": raw["recall_at_100_precision"],
                     "R@100%P after": entry["after_inference"]["recall_at_100_precision"],
                     "P@50%R after": entry["after_inference"]["precision_at_50_recall"],
                     "D precision": entry["decisions"]["precision"], "D recall": entry["decisions"]["recall"]})
    (plot_dir / f"{stem}.md").write_text(f"# {sequence.name}\n\n" + markdown_table(rows) + "\n")
    out_json.write_text(json_text(report))
    log(f"wrote {out_json}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="semloc eval loopclosure", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
