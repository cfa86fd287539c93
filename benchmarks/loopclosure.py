"""Loop-closure speed on the simulated `route` (rendered, real SIFT features).

(a) 300 frames: the incremental engine (retrieval + DP on candidates + banded loopy BP + incremental map) against the
    exhaustive batch pipeline of the thesis (DP on every pair, batch loopy BP, algorithm 3.1), in the same process:
    speed ratio and the difference in AP after inference (target: >= 20x, AP difference <= 0.02).
(b) The engine's per-frame latency (features -> loop decision and map update) as the map grows to 2,000 frames:
    p50/p95 over the 100 frames before 200 and before 2,000 (targets: p50 <= 50 ms, p95 at 2,000 <= 2x p95 at 200).
(c) Feature extraction (SIFT + bearings) per frame, reported separately.

Features are cached in --cache (npz), so reruns skip rendering and SIFT. The machine is shared: repeat and take
medians (--repeat).

    .venv/bin/python benchmarks/loopclosure.py [--frames-a 300] [--frames-b 2000] [--repeat 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.io.loopclosure import load_features, save_features  # noqa: E402
from semloc_core.loopclosure import EngineParams, FeatureParams, LoopClosureEngine, extract_features  # noqa: E402
from semloc_core.loopclosure.evaluation import batch_pipeline, evaluated_pairs  # noqa: E402
from semloc_core.eval.pr import average_precision, pr_curve  # noqa: E402
from semloc_core.loopclosure.mrf import IncrementalMrf  # noqa: E402


def route_features(seed: int, frames: int, max_features: int, cache: Path):
    """SIFT sequences of the `route` scenario's frames, ground truth (hard, soft) and extraction times."""
    from semloc_core.sim.scenarios import make_scenario

    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"route_s{seed}_n{frames}_f{max_features}.npz"
    gt_path = cache / f"route_s{seed}_n{frames}_gt.npz"
    scenario = None
    if path.exists() and gt_path.exists():
        sequences, meta = load_features(path)
        with np.load(gt_path, allow_pickle=False) as gt:
            hard, soft = gt["hard"], gt["soft"]
        return sequences, hard, soft, meta.get("extract_ms", [])
    scenario = make_scenario("route", seed=seed, frames=frames)
    params = FeatureParams(max_features=max_features)
    sequences, times = [], []
    for i in range(len(scenario)):
        image = scenario.image(i)
        start = time.perf_counter()
        sequences.append(extract_features(image, scenario.camera, params, scenario.T_body_cam_at(i)))
        times.append((time.perf_counter() - start) * 1e3)
        if (i + 1) % 200 == 0:
            print(f"  rendered and extracted {i + 1}/{frames} frames", flush=True)
    save_features(path, sequences, {"seed": seed, "extract_ms": times, "sift": params.__dict__})
    np.savez(gt_path, hard=scenario.loop_gt, soft=scenario.loop_gt_soft)
    return sequences, scenario.loop_gt, scenario.loop_gt_soft, times


def after_inference_ap(beliefs: np.ndarray, hard: np.ndarray, soft: np.ndarray, window: int) -> float:
    n = beliefs.shape[0]
    gt = np.triu(hard[:n, :n], 1)
    ignore = np.triu(soft[:n, :n], 1) & ~gt
    earlier, later = evaluated_pairs(n, window, ignore)
    return average_precision(pr_curve(beliefs[earlier, later], gt[earlier, later]))


def run_engine(sequences, params: EngineParams):
    engine = LoopClosureEngine(params)
    latencies = []
    for features in sequences:
        start = time.perf_counter()
        engine.add_frame(features)
        latencies.append(time.perf_counter() - start)
    return engine, np.array(latencies)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames-a", type=int, default=300)
    parser.add_argument("--frames-b", type=int, default=2000)
    parser.add_argument("--max-features", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", default=".semloc-cache/loopclosure")
    parser.add_argument("--json", default=None, help="also write the figures as JSON")
    args = parser.parse_args()
    params = EngineParams()
    window = params.window
    report: dict = {"engine_params": params.to_json_dict(), "max_features": args.max_features}

    print(f"features: route seed {args.seed}, {args.frames_b} frames, <= {args.max_features} SIFT per image")
    sequences, hard, soft, extract_ms = route_features(args.seed, args.frames_b, args.max_features, Path(args.cache))
    mean_features = float(np.mean([len(s) for s in sequences]))
    if extract_ms:
        report["c_feature_extraction_ms"] = {"p50": float(np.median(extract_ms)),
                                             "p95": float(np.percentile(extract_ms, 95))}
        print(f"(c) feature extraction: p50 {np.median(extract_ms):.1f} ms/frame, p95 "
              f"{np.percentile(extract_ms, 95):.1f} ms (640x480, {mean_features:.0f} features/frame)")

    # (a) incremental engine vs exhaustive batch pipeline on the first frames.
    first = sequences[: args.frames_a]
    engine_times, batch_times = [], []
    engine = batch = None
    for _ in range(args.repeat):
        start = time.perf_counter()
        engine, _ = run_engine(first, params)
        engine_times.append(time.perf_counter() - start)
    for _ in range(max(1, args.repeat // 3)):
        start = time.perf_counter()
        batch = batch_pipeline(first, window, params.alignment, params.mrf, params.temporal_radius,
                               map_min_belief=params.map_min_belief)
        batch_times.append(time.perf_counter() - start)
    # The incremental lattice alone, on the batch's own scores and normalization: same D?
    n_a = len(first)
    lattice = IncrementalMrf(params.mrf, params.band, batch.mrf.normalization, window)
    for j in range(n_a):
        rows = np.arange(max(0, j - window))
        lattice.add_column(rows, batch.M[rows, j])
    same = lattice.dense().decisions
    mrf_agree = float(np.mean(same == batch.mrf.decisions))
    mrf_jaccard = float(np.sum(same & batch.mrf.decisions) / max(np.sum(same | batch.mrf.decisions), 1))
    ap_engine = after_inference_ap(engine.mrf.dense().beliefs, hard, soft, window)
    ap_batch = after_inference_ap(batch.mrf.beliefs, hard, soft, window)
    agree = float(np.mean(engine.mrf.dense().decisions == batch.mrf.decisions))
    t_engine, t_batch = statistics.median(engine_times), statistics.median(batch_times)
    report["a_incremental_vs_batch"] = {
        "frames": len(first), "engine_s": t_engine, "batch_s": t_batch, "speed_ratio": t_batch / t_engine,
        "ap_engine": ap_engine, "ap_batch": ap_batch, "ap_difference": ap_batch - ap_engine,
        "decision_agreement": agree,
        "incremental_vs_batch_mrf_same_scores": {"entries": mrf_agree, "positive_jaccard": mrf_jaccard,
                                                 "band": params.band},
    }
    print(f"(a) {len(first)} frames: engine {t_engine:.2f} s, exhaustive batch {t_batch:.2f} s -> "
          f"{t_batch / t_engine:.1f}x;  AP after inference engine {ap_engine:.3f} vs batch {ap_batch:.3f} "
          f"(difference {ap_batch - ap_engine:+.3f});  D agreement {agree:.4f}")
    print(f"    incremental MRF (band {params.band}) vs batch MRF on the same {n_a}-frame scores: D equal on "
          f"{mrf_agree:.2%} of entries, positives Jaccard {mrf_jaccard:.3f}")

    # (b) per-frame latency as the map grows.
    runs = []
    for _ in range(args.repeat):
        _, latencies = run_engine(sequences, params)
        runs.append(latencies * 1e3)
    latencies = np.median(np.stack(runs), axis=0)

    def window_stats(end: int) -> dict:
        part = latencies[max(0, end - 100) : end]
        return {"p50": float(np.percentile(part, 50)), "p95": float(np.percentile(part, 95))}

    at_200, at_end = window_stats(min(200, len(latencies))), window_stats(len(latencies))
    report["b_latency_ms"] = {"overall_p50": float(np.percentile(latencies, 50)),
                              "overall_p95": float(np.percentile(latencies, 95)),
                              "at_200": at_200, f"at_{len(latencies)}": at_end,
                              "p95_ratio": at_end["p95"] / at_200["p95"]}
    print(f"(b) per-frame latency (median of {args.repeat} runs): overall p50 {np.percentile(latencies, 50):.1f} ms, "
          f"p95 {np.percentile(latencies, 95):.1f} ms; frames 100-200 p50 {at_200['p50']:.1f} / p95 "
          f"{at_200['p95']:.1f} ms; frames {len(latencies) - 100}-{len(latencies)} p50 {at_end['p50']:.1f} / p95 "
          f"{at_end['p95']:.1f} ms -> p95 ratio {at_end['p95'] / at_200['p95']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
