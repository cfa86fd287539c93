"""The loop-closure experiment: precision-recall of the similarity scores and the topological map (thesis ch. 3).

For the DP score and the four baselines (M^SIFT, M^SYM, BoW TF-IDF, SeqSLAM): PR raw and after batch inference,
interpolated precision, AP, recall at 100 % precision, the decisions at the target precision (expected and measured
precision); the incremental engine on the same features; the topological map's figures; PNG plots. DATASET: a
simulated dataset (``semloc sim``), a scenario rendered on the fly (``scenario:route:seed=0,frames=300``) or an
image folder with a ground-truth loop matrix (the layout of ``rtabmap_loop_samples``). ``degrade`` runs the whole
evaluation once per named degradation of the images (``semloc_core.sim.degrade.PRESETS``: downscaling, fisheye
warp with a rim, body overlay, exposure change, ...), all in one report.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from semloc_core.experiments import loopclosure_data as data
from semloc_core.experiments.spec import DataPath, Spec
from semloc_core.loopclosure import AlignmentParams, EngineParams, FeatureParams, MrfParams
from semloc_core.loopclosure.calibration import CALIBRATION_MODES
from semloc_core.loopclosure.evaluation import SCORES
from semloc_core.loopclosure.similarity import MatchRule
from semloc_core.loopclosure.keyframes import KeyframeParams
from semloc_core.sim.degrade import PRESETS as DEGRADATIONS

Log = Callable[[str], None]
_ENGINE = EngineParams()


class FeaturesSpec(Spec):
    max_features: int = Field(500, ge=0, description="SIFT keypoints per image (0 = all)")
    calibration: Literal[CALIBRATION_MODES] = Field(
        "sequence", description="t_match, repeated texture and static regions from the sequence itself, or the "
                                "fixed constants below (the thesis preset)")
    match: MatchRule = Field("threshold_or_mutual", description="the DP's matching pairs: within t_match (thesis), "
                             "mutual ratio-test nearest neighbours, or either (default)")
    t_match: float = Field(AlignmentParams().t_match, gt=0, description="fixed calibration: L1 match threshold, "
                                                                        "VLFeat scale (thesis: 1000)")
    repeated_threshold: float | None = Field(None, ge=0, description="fixed calibration: drop features with a match "
                                                                     "inside their own frame (default: t_match)")
    upsample_below: int = Field(FeatureParams().upsample_below, ge=0, description="upsample images whose shorter "
                                                                                  "side is below this (0: never)")
    stretch_contrast: bool = Field(FeatureParams().stretch_contrast, description="stretch grey levels before SIFT")


class VocabularySpec(Spec):
    words: int = Field(1000, ge=2, description="BoW vocabulary size when it is learnt here")
    file: DataPath | None = Field(None, description="vocabulary .npz for the BoW score and the engine (default: "
                                                    "learnt on this dataset; the engine learns its own)")
    save: str | None = Field(None, description="write the vocabulary learnt here (.npz, e.g. for the worker)")


class EngineSpec(Spec):
    enabled: bool = Field(True, description="run the incremental engine on the same features")
    candidates: int = Field(_ENGINE.candidates, ge=1, description="retrieved frames")
    neighbour_candidates: int = Field(_ENGINE.neighbour_candidates, ge=0,
                                      description="also align frames this close to the previous frame's partners")
    match: MatchRule = Field(_ENGINE.alignment.match, description="the engine's match rule (default: the worker's, "
                             "the threshold through its word index; the ratio-test rules compare every feature pair "
                             "of a candidate, ~18x the CPU)")


class LoopClosureSpec(Spec):
    """``semloc eval loopclosure``."""

    dataset: DataPath | None = Field(None, description="simulated dataset, scenario:NAME[:k=v,...] or an image "
                                                       "folder with a ground-truth matrix")
    cache: str | None = Field(None, description="folder keeping the features and the full similarity matrices")
    window: int = Field(30, ge=0, description="w: pairs i < j - w are scored (thesis: 30)")
    gt_distance: float | None = Field(None, gt=0, description="metres: ground truth from poses (default: the "
                                                              "dataset's own, else its matrix)")
    features: FeaturesSpec = FeaturesSpec()
    mrf: MrfParams = Field(default_factory=MrfParams, description="the MRF and its inference "
                           "(semloc_core.loopclosure.MrfParams); its offset is the DP score's, the baselines' is 0")
    vocabulary: VocabularySpec = VocabularySpec()
    temporal_radius: int = Field(2, ge=0, description="r: frames <= r apart share a place")
    map_min_belief: float = Field(_ENGINE.map_min_belief, description="log-odds a loop needs to join places in "
                                                                      "the map (batch and engine)")
    engine: EngineSpec = EngineSpec()
    keyframes: KeyframeParams = Field(KeyframeParams(enabled=False), description="enabled: evaluate on the "
                                        "key-frames a live worker would process (the poses stand for odometry)")
    target_precision: float = Field(_ENGINE.target_precision, gt=0, le=1,
                                    description="decisions at the belief threshold expected to reach this precision")
    report_precisions: list[float] = Field([0.9], description="decisions also reported at these target precisions "
                                                              "(issue 33's acceptance reads them at 0.9)")
    decision_places: bool = Field(_ENGINE.decision_places, description="decisions (batch and engine) count near "
                                                                      "misses of a place as false")
    seqslam: bool = Field(True, description="the SeqSLAM sequence baseline (from the images)")
    batch: bool = Field(True, description="the full matrices, every score and the batch map; false: the engine "
                                          "alone (its figures at a fraction of the cost, for long sequences)")
    degrade: list[str] = Field(["none"], min_length=1, description="degradations to evaluate, each a variant: "
                                                                   + ", ".join(DEGRADATIONS))
    jobs: int | None = Field(None, ge=1, description="processes for the full matrices (default: every core)")

    @field_validator("report_precisions")
    @classmethod
    def _precisions(cls, values: list[float]) -> list[float]:
        if any(not 0 < v <= 1 for v in values):
            raise ValueError("report_precisions must lie in (0, 1]")
        return values

    @field_validator("degrade")
    @classmethod
    def _known_degradations(cls, names: list[str]) -> list[str]:
        unknown = [name for name in names if name not in DEGRADATIONS]
        if unknown:
            raise ValueError(f"unknown degradation {unknown[0]!r}: one of {', '.join(DEGRADATIONS)}")
        if len(set(names)) != len(names):
            raise ValueError("degrade names a variant twice")
        return names


@dataclass
class LoopClosureResult:
    """The report (every figure, JSON-ready), its plots as PNG bytes, the engine's topological map (None without the
    engine) and the Markdown table's rows."""

    report: dict
    pngs: dict[str, bytes]
    topomap: object | None
    rows: list[dict]
    name: str


def run(spec: LoopClosureSpec, log: Log = lambda _: None) -> LoopClosureResult:
    """Every variant's (``spec.degrade``) figures: every score's PR raw and after inference, its decisions at the
    target precision, the descriptor study, the batch map and the engine's run. One variant gives its report as
    it is; several give ``{"variants": {name: report}}`` with a table row per variant and score. Raises ValueError
    for a dataset it cannot use."""
    if spec.dataset is None:
        raise ValueError("no dataset given")
    sequence = data.open_loop_sequence(spec.dataset, spec.gt_distance)
    log(f"{sequence.name}: {sequence.frames} frames, {int(sequence.gt.sum())} ground-truth loop pairs")
    from semloc_core.loopclosure.evaluation import evaluated_pairs

    full = sequence
    if spec.keyframes.enabled:  # chosen once on the dataset's images, so that every variant sees the same frames
        sequence = data.keyframe_sequence(sequence, spec.keyframes, log)
    earlier, later = evaluated_pairs(sequence.frames, spec.window, sequence.ignore)
    labels = sequence.gt[earlier, later]
    if not labels.any():  # said before the costly part: precision and recall need a place seen twice
        raise ValueError(f"{sequence.name}: no loop pairs to find ({int(sequence.gt.sum())} ground-truth pairs, none "
                         f"of them among the {labels.size} pairs evaluated, more than window={spec.window} frames "
                         "apart): precision and recall are undefined")
    if sequence.camera_assumed:
        log(f"warning: {sequence.name} has no camera calibration: a {data.NOMINAL_FOV_DEG:g} deg pinhole is assumed "
            "(give a camera.json; the DP sees only the order of the bearings)")
    results = {name: _run_variant(spec, sequence, full, name, log) for name in spec.degrade}
    if len(results) == 1:
        return next(iter(results.values()))
    report = {"dataset": str(sequence.path), "name": sequence.name, "variants": {k: r.report for k, r in
                                                                                results.items()}}
    pngs = {f"{k}_{p}": png for k, r in results.items() for p, png in r.pngs.items()}
    rows = [{"variant": k, **row} for k, r in results.items() for row in r.rows]
    return LoopClosureResult(report, pngs, None, rows, sequence.name)


def _run_variant(spec: LoopClosureSpec, sequence, full, variant: str, log: Log) -> LoopClosureResult:
    """One variant's report on ``sequence`` (the key-frames of ``full`` when ``spec.keyframes.enabled``)."""
    from semloc_core.eval.pr import interpolated_precision
    from semloc_core.io.loopclosure import load_vocabulary, save_vocabulary
    from semloc_core.loopclosure import train_vocabulary
    from semloc_core.loopclosure.calibration import Calibration, calibrate
    from semloc_core.loopclosure.evaluation import evaluate_score, evaluate_topomap, evaluated_pairs, same_place_pairs
    from semloc_core.loopclosure.seqslam import similarity_matrix as seqslam_matrix
    from semloc_core.loopclosure.topomap import map_from_beliefs

    if len(spec.degrade) > 1:
        log(f"--- {variant}")
    degradation, camera = data.degraded(sequence, DEGRADATIONS[variant])
    subset = "-keyframes" if spec.keyframes.enabled else ""
    f = spec.features
    feature_params = FeatureParams(max_features=f.max_features, repeated_threshold=0.0,
                                   upsample_below=f.upsample_below, stretch_contrast=f.stretch_contrast)
    t0 = time.perf_counter()
    raw, thumbnails = data.features(sequence, degradation, camera, feature_params,
                                    data.cache_file(spec, f"features-{variant}{subset}"), log)
    feature_seconds = time.perf_counter() - t0
    if f.calibration == "sequence":
        image_size = (camera.width, camera.height) if hasattr(camera, "width") else None
        calibration = calibrate(raw, image_size=image_size, alignment=AlignmentParams(match=f.match))
        if calibration is None:
            raise ValueError(f"{sequence.name} ({variant}): no correspondences between consecutive frames to "
                             "calibrate on (use features.calibration=fixed)")
    else:
        repeated = f.t_match if f.repeated_threshold is None else f.repeated_threshold
        calibration = Calibration(f.t_match, repeated, frames=len(raw), stats={"source": "fixed"})
    frames = [calibration.apply(x) for x in raw]
    c = calibration.summary()
    log(f"calibration: t_match {c['t_match']:g}, static area {c['static_area']:.3f}, band tau "
        f"{c['band_half_width_deg']:.2f} deg, L {c['band_max_log_scale']:.3f}, "
        f"{np.mean([len(x) for x in frames]):.0f} features per frame")

    alignment = AlignmentParams(match=f.match, t_match=calibration.t_match,
                                band_half_width=calibration.band_half_width,
                                band_max_log_scale=calibration.band_max_log_scale)
    dp_mrf = _dp_mrf(spec.mrf, f.match)
    if not spec.batch:
        return _engine_only(spec, sequence, variant, degradation, camera, feature_params, raw, frames, calibration,
                            alignment, feature_seconds, log)
    mrf = replace(_dp_mrf(spec.mrf, "mutual"), offset=0.0)  # the baselines count matches
    if spec.vocabulary.file:
        vocabulary, vocabulary_source = load_vocabulary(spec.vocabulary.file), str(spec.vocabulary.file)
    else:
        vocabulary = train_vocabulary([x.descriptors for x in frames if len(x)], words=spec.vocabulary.words)
        vocabulary_source = f"k-means ({spec.vocabulary.words} words) on this dataset's descriptors"
    if spec.vocabulary.save:
        save_vocabulary(spec.vocabulary.save, vocabulary)
    bow = [vocabulary.vector(x.descriptors) for x in frames]

    t0 = time.perf_counter()
    matrix_meta = {"features": data.fingerprint(frames), "window": spec.window, "alignment": alignment.__dict__,
                   "vocabulary": vocabulary_source, "ratio": 0.8}
    jobs = spec.jobs or os.cpu_count() or 1
    matrices = data.cached_matrices(data.cache_file(spec, f"matrices-{variant}{subset}"), matrix_meta,
                                    lambda: data.full_matrices(frames, spec.window, alignment, bow, jobs, log), log)
    names = list(SCORES)
    if spec.seqslam:
        matrices = {**matrices, "seqslam": seqslam_matrix(thumbnails, spec.window)}
        names.append("seqslam")
    matrix_seconds = time.perf_counter() - t0

    earlier, later = evaluated_pairs(sequence.frames, spec.window, sequence.ignore)
    labels = sequence.gt[earlier, later]
    counts = [len(x) for x in frames]
    place_radius = spec.temporal_radius if spec.decision_places else None
    evaluations = {name: evaluate_score(matrices[name], sequence.gt, spec.window, dp_mrf if name == "dp" else mrf,
                                        sequence.ignore, counts if name != "seqslam" else None,
                                        spec.target_precision, place_radius, spec.report_precisions)
                   for name in names}
    scores = {name: evaluations[name].summary() for name in names}
    for name in names:
        s = scores[name]
        for d in s["decisions_at_precision"].values():  # (the target's is decisions_at_target too)
            threshold = np.inf if d["threshold"] is None else d["threshold"]
            d.update(decision_figures(evaluations[name].inference.beliefs >= threshold, sequence, spec.window))
        log(f"{name:7s} AP raw {s['raw']['average_precision']:.3f} -> {s['after_inference']['average_precision']:.3f}"
            f"  R@90%P {s['after_inference']['recall_at_90_precision']:.3f}  decisions "
            + _decisions_at_text(s["decisions_at_precision"], spec.target_precision))

    distances = None
    if not degradation.fisheye:
        distances = data.descriptor_study(sequence, camera, frames, spec.window,
                                          [1000.0, 1300.0, 1700.0, 2100.0, calibration.t_match])

    same_place = same_place_pairs(sequence.frames, sequence.gt, sequence.positions, sequence.gt_distance,
                                  spec.temporal_radius)
    batch_map = map_from_beliefs(evaluations["dp"].inference.beliefs, spec.map_min_belief, spec.temporal_radius)
    report = {
        **_report_header(spec, sequence, variant, degradation, labels, feature_params, frames, feature_seconds,
                         calibration, alignment),
        "camera": type(camera).__name__ + (" (assumed)" if sequence.camera_assumed else ""),
        "dataset_frames": full.frames,
        "keyframes": None,
        "mrf": mrf.__dict__,
        "dp_mrf": dp_mrf.__dict__,
        "vocabulary": vocabulary_source,
        "scores": scores,
        "best_ap_after_inference": max(names, key=lambda n: scores[n]["after_inference"]["average_precision"]),
        "interpolated_precision": {
            name: {"raw": interpolated_precision(evaluations[name].raw).tolist(),
                   "after_inference": interpolated_precision(evaluations[name].after).tolist()} for name in names
        },
        "descriptor_distances": distances,
        "topomap_batch": evaluate_topomap(batch_map, same_place),
        "timing_s": {"features": feature_seconds, "full_matrices": matrix_seconds},
    }
    if spec.keyframes.enabled:
        every = data.scores_on_all_frames(full, sequence.frame_index, matrices, spec.window)
        report["keyframes"] = {**asdict(spec.keyframes), "kept": sequence.frames, "all_frames": every}
        log(f"key-frames answering all {full.frames} frames: AP raw " + "  ".join(
            f"{name} {every[name]['average_precision']:.3f}" for name in names))
    raw_curves = {name: evaluations[name].raw for name in names}
    after_curves = {name: evaluations[name].after for name in names}
    engine = engine_map = None
    if spec.engine.enabled:
        # The engine calibrates itself on its first frames (unsuppressed features in), or takes the fixed constants.
        engine_frames = raw if f.calibration == "sequence" else frames
        engine, engine_map, raw_curves["engine"], after_curves["engine"] = _run_engine(
            spec, engine_frames, alignment, vocabulary, sequence, earlier, later, labels, same_place,
            evaluations["dp"].inference.decisions, report, log)
    pngs = _plots(sequence, matrices, evaluations["dp"].inference.decisions, raw_curves, after_curves, engine,
                  engine_map)
    return LoopClosureResult(report, pngs, engine_map, _rows(report), sequence.name)


def _engine_only(spec, sequence, variant, degradation, camera, feature_params, raw, frames, calibration, alignment,
                 feature_seconds, log: Log) -> LoopClosureResult:
    """``batch=false``: the engine's figures alone (no full matrix, score or batch map)."""
    from semloc_core.io.loopclosure import load_vocabulary
    from semloc_core.loopclosure.evaluation import evaluated_pairs, same_place_pairs

    if not spec.engine.enabled:
        raise ValueError("batch=false evaluates the engine alone: it needs engine.enabled=true")
    earlier, later = evaluated_pairs(sequence.frames, spec.window, sequence.ignore)
    labels = sequence.gt[earlier, later]
    same_place = same_place_pairs(sequence.frames, sequence.gt, sequence.positions, sequence.gt_distance,
                                  spec.temporal_radius)
    vocabulary = load_vocabulary(spec.vocabulary.file) if spec.vocabulary.file else None
    report = {**_report_header(spec, sequence, variant, degradation, labels, feature_params, frames, feature_seconds,
                               calibration, alignment),
              "dp_mrf": _dp_mrf(spec.mrf, spec.engine.match).__dict__, "scores": {}}
    engine_frames = raw if spec.features.calibration == "sequence" else frames
    engine, engine_map, raw_curve, after_curve = _run_engine(spec, engine_frames, alignment, vocabulary,
                                                             sequence, earlier, later, labels, same_place, None,
                                                             report, log)
    pngs = _plots(sequence, None, None, {"engine": raw_curve}, {"engine": after_curve}, engine, engine_map)
    return LoopClosureResult(report, pngs, engine_map, _rows(report), sequence.name)


def _report_header(spec, sequence, variant, degradation, labels, feature_params, frames, feature_seconds,
                   calibration, alignment) -> dict:
    """What a variant's report says about its data, features and constants, with or without the batch."""
    return {
        "dataset": str(sequence.path),
        "name": sequence.name,
        "variant": variant,
        "degradation": degradation.__dict__,
        "frames": sequence.frames,
        "window": spec.window,
        "ground_truth": {"pairs": int(sequence.gt.sum()), "evaluated_pairs": int(labels.size),
                         "ignored_pairs": int(sequence.ignore.sum()),
                         "distance_m": sequence.gt_distance, "source": sequence.gt_source},
        "features": {"sift": feature_params.__dict__, "mean_per_frame": float(np.mean([len(x) for x in frames])),
                     "seconds_per_frame": feature_seconds / max(sequence.frames, 1)},
        "calibration": calibration.summary(),
        "alignment": alignment.__dict__,
    }


def _dp_mrf(mrf: MrfParams, match: str) -> MrfParams:
    """The DP's MRF for a match rule. M^SIFT and M^SYM count matches, whose spread grows with the features there are
    to match: they take the background deviation per feature count. So does the DP when it aligns ratio-test
    matches; with the thesis's threshold alone its count moves only the background's centre."""
    if match == "threshold" or mrf.background != "features":
        return mrf
    return replace(mrf, background="features_spread")


def _run_engine(spec, frames, alignment, vocabulary, sequence, earlier, later, labels, same_place,
                dp_decisions, report, log: Log):
    """The incremental engine on the same features, frame by frame: its report entry, raw and inferred curves. It
    aligns by its own match rule (``engine.match``, the worker's by default), not necessarily the batch DP's."""
    from semloc_core.eval.pr import pr_curve
    from semloc_core.loopclosure import LoopClosureEngine
    from semloc_core.loopclosure.calibration import CalibrationParams
    from semloc_core.loopclosure.evaluation import curve_summary, decision_quality, evaluate_topomap

    alignment = replace(alignment, match=spec.engine.match)
    engine_params = EngineParams(window=spec.window, alignment=alignment, mrf=_dp_mrf(spec.mrf, spec.engine.match),
                                 candidates=spec.engine.candidates,
                                 neighbour_candidates=spec.engine.neighbour_candidates,
                                 temporal_radius=spec.temporal_radius, map_min_belief=spec.map_min_belief,
                                 calibration=CalibrationParams(mode=spec.features.calibration),
                                 target_precision=spec.target_precision,
                                 decision_places=spec.decision_places)
    engine = LoopClosureEngine(engine_params, vocabulary if spec.vocabulary.file else None)
    latencies = []
    statuses: dict[str, int] = {}
    aligned = 0
    reported = np.zeros((sequence.frames, sequence.frames), bool)  # the loops as a subscriber holds them
    for f in frames:
        t = time.perf_counter()
        result = engine.add_frame(f)
        latencies.append(time.perf_counter() - t)
        statuses[result.status.value] = statuses.get(result.status.value, 0) + 1
        aligned += result.candidates.size
        reported[:, result.frame] = False
        reported[result.loops, result.frame] = True
        for frame, loops in result.revised.items():
            reported[:, frame] = False
            reported[loops, frame] = True
    engine.topomap.flush()  # the sequence has ended: its last frames need not wait for a key-frame
    dense = engine.mrf.dense()
    after = pr_curve(dense.beliefs[earlier, later], labels)
    cells = engine.similarity_cells()
    engine_raw = np.full((sequence.frames, sequence.frames), -np.inf)
    engine_raw[cells[0], cells[1]] = cells[2]
    raw = pr_curve(engine_raw[earlier, later], labels)
    engine_map = engine.topomap.snapshot()
    at_target = {**decision_quality(reported[earlier, later], labels),
                 **(engine.decision.summary() if engine.decision is not None else {}),
                 **decision_figures(reported, sequence, spec.window)}
    at_precision = {f"{spec.target_precision:g}": at_target}
    for target in spec.report_precisions:  # the final lattice's decisions at other targets
        if f"{target:g}" not in at_precision:
            decision = engine.decision_at(target)
            decided = dense.beliefs >= decision.threshold
            at_precision[f"{target:g}"] = {**decision_quality(decided[earlier, later], labels), **decision.summary(),
                                           **decision_figures(decided, sequence, spec.window)}
    report["engine"] = {
        "params": engine_params.to_json_dict(),
        "raw": curve_summary(raw),
        "after_inference": curve_summary(after),
        "decisions": decision_quality(dense.decisions[earlier, later], labels),
        "decisions_at_target": at_target,
        "decisions_at_precision": dict(sorted(at_precision.items())),
        "calibration": engine.calibration.summary() if engine.calibration is not None else None,
        "agreement_with_batch_dp": None if dp_decisions is None else {
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
        "redundant_frames": engine.n_frames - engine.n_kept,  # visits of a frame holding their view (not kept)
        "topomap": evaluate_topomap(engine_map, same_place),
    }
    e = report["engine"]
    log(f"engine AP {e['after_inference']['average_precision']:.3f}  decisions "
        f"{_decisions_at_text(e['decisions_at_precision'], spec.target_precision)}"
        f"  latency p50 {e['latency_ms']['p50']:.1f} ms  nodes {e['topomap']['nodes']}  same place "
        f"{e['topomap']['same_place_fraction']:.3f}  redundant frames {e['redundant_frames']}")
    return engine, engine_map, raw, after


def decision_figures(decided: np.ndarray, sequence, window: int) -> dict:
    """What loop decisions ((n, n) bool, [earlier, later]) are beyond their pairs' precision: per frame (a frame with
    a loop right or not: ``frames``) and, with poses, how far apart the false ones' cameras are (``false_decisions``:
    near misses of the ground truth's radius or places seen elsewhere)."""
    from semloc_core.eval.loops import frame_decisions, pair_distances

    n = sequence.frames
    scored = np.triu(np.ones((n, n), bool), window + 1)
    decided = np.asarray(decided, bool) & scored
    out = {"frames": frame_decisions(decided, sequence.gt, sequence.ignore, scored)}
    if sequence.positions is not None:
        out["false_decisions"] = pair_distances(decided & ~sequence.gt & ~sequence.ignore, sequence.positions)
    return out


def _decisions_at_text(at_precision: dict, target: float) -> str:
    """The target's decisions in full, the others' precision (expected) and recall."""
    texts = [f"at {key}: " + (_decisions_text(d) if key == f"{target:g}" else
                              f"P {d['precision']:.3f} (expected {_expected_text(d)}) R {d['recall']:.3f}")
             for key, d in at_precision.items()]
    return "; ".join(texts)


def _expected_text(d: dict) -> str:
    return "-" if d.get("expected_precision") is None else f"{d['expected_precision']:.2f}"


def _decisions_text(d: dict) -> str:
    text = f"P {d['precision']:.3f} (expected {_expected_text(d)}) R {d['recall']:.3f}"
    frames = d["frames"]
    if frames["frame_precision"] is not None and frames["frame_recall"] is not None:
        text += f", frames P {frames['frame_precision']:.2f} R {frames['frame_recall']:.2f}"
    false = d.get("false_decisions")
    if false and false["quartiles_m"]:
        q = false["quartiles_m"]
        text += f", false ones {q[0]:.2f}-{q[2]:.2f} m apart"
    return text


def _plots(sequence, matrices, dp_decisions, raw_curves, after_curves, engine, engine_map) -> dict[str, bytes]:
    from semloc_core.eval.report import matrix_png, pr_plot_png
    from semloc_core.loopclosure.plots import topomap_png

    pngs = {
        "pr": pr_plot_png(raw_curves, f"{sequence.name}: raw (solid) vs after inference (dashed)", interpolated=True,
                          dashed=after_curves),
        "ground_truth": matrix_png((sequence.gt | sequence.gt.T).astype(float), "ground truth"),
    }
    if matrices is not None:  # (the batch's: not with batch=false)
        pngs["M_dp"] = matrix_png(np.where(np.isfinite(matrices["dp"]), matrices["dp"], np.nan).T,
                                  "M (DP), row = later", cmap="viridis")
        pngs["D_dp"] = matrix_png(dp_decisions.T.astype(float), "D (DP + inference)")
    if sequence.positions is not None and engine_map is not None:
        loop_keys = [k for k in engine_map.keyframes.tolist() if engine.topomap.loops_of(int(k))]
        pngs["topomap"] = topomap_png(sequence.positions, engine_map.keyframes, engine_map.edges,
                                      np.array(loop_keys, np.int64), f"{sequence.name}: topological map")
    return pngs


def _rows(report: dict) -> list[dict]:
    rows = []
    for name in list(report["scores"]) + (["engine"] if "engine" in report else []):
        entry = report["engine"] if name == "engine" else report["scores"][name]
        raw = entry["raw"]
        decided = entry["decisions_at_target"]
        others = {f"{k} at {key}": d.get(field) for key, d in entry["decisions_at_precision"].items()
                  if d is not decided  # (the target's: the columns above)
                  for k, field in (("decisions P", "precision"), ("expected P", "expected_precision"),
                                   ("decisions R", "recall"))}
        rows.append({"score": name, "AP raw": raw["average_precision"],
                     "AP after": entry["after_inference"]["average_precision"],
                     "AP101 raw": raw["interpolated_average_precision"],
                     "AP101 after": entry["after_inference"]["interpolated_average_precision"],
                     "R@100%P raw": raw["recall_at_100_precision"],
                     "R@100%P after": entry["after_inference"]["recall_at_100_precision"],
                     "P@50%R after": entry["after_inference"]["precision_at_50_recall"],
                     "R@90%P after": entry["after_inference"]["recall_at_90_precision"],
                     "decisions P": decided["precision"], "expected P": decided.get("expected_precision"),
                     "decisions R": decided["recall"], **others})
    return rows


def markdown(result: LoopClosureResult) -> str:
    """The report's table (``<stem>.md``; what ``semloc eval loopclosure`` prints)."""
    from semloc_core.eval.report import markdown_table

    return f"# {result.name}\n\n" + markdown_table(result.rows)


def write_report(result: LoopClosureResult, out) -> None:
    """``out`` (JSON) and beside it ``<stem>_<plot>.png``, the engine's map ``<stem>_topomap.json`` / ``.graphml``
    and the table ``<stem>.md``."""
    from pathlib import Path

    from semloc_core.eval.report import json_text
    from semloc_core.io.loopclosure import save_topomap

    out = Path(out)
    folder, stem = out.parent, out.stem
    folder.mkdir(parents=True, exist_ok=True)
    if result.topomap is not None:
        save_topomap(folder / f"{stem}_topomap.json", result.topomap)
        save_topomap(folder / f"{stem}_topomap.graphml", result.topomap)
    result.report["plots"] = {}
    for name, png in result.pngs.items():
        path = folder / f"{stem}_{name}.png"
        path.write_bytes(png)
        result.report["plots"][name] = str(path)
    (folder / f"{stem}.md").write_text(markdown(result) + "\n")
    out.write_text(json_text(result.report))
