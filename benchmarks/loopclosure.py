"""Loop-closure speed on the simulated `route` (rendered, real SIFT features), in the worker's configuration.

(a) The incremental engine (retrieval + band following + DP on candidates + banded loopy BP + incremental map)
    against the exhaustive batch pipeline of the thesis (DP on every pair, batch loopy BP, algorithm 3.1), in the same
    process, on the first 300 frames (and on more, --frames-a, to show how the ratio grows with the map): speed ratio
    and the difference in AP after inference (targets at 300 frames: >= 20x, <= 0.02). Also: the incremental lattice
    fed the batch's own scores gives the batch's D (the 99.5 % acceptance point).
(b) The engine's per-frame latency (features -> loop decision and map update) as the map grows to 2,000 frames:
    p50/p95 over the 100 frames before 200 and before 2,000 (targets: p50 <= 50 ms, p95 at 2,000 <= 2x p95 at 200).
(c) Feature extraction (SIFT + bearings + repeated-texture suppression) per 640x480 frame, reported separately.

What the engine's time includes. The main rows run the worker with a vocabulary file (``--vocabulary``), learnt
offline - as DBoW's and FAB-MAP's vocabularies are - on another world: `route` seed --vocabulary-seed (2: other
decor, textures and fixtures than the evaluated seed), its first --vocabulary-frames frames, k-means with the
engine's word count; that learning (timed and printed) is not in the engine's time. Two more engine rows, same
process, same frames: "online vocabulary" is the worker without a vocabulary file (it learns one from its first 60
frames, included in its time), and "exhaustive matching" is the main configuration with ``match_words = 0`` (every
feature pair of a candidate pair compared, as the batch does), which shows what the direct index contributes. The
batch computes every DP score exactly (every feature pair compared) and has no vocabulary.

Times are medians of --repeat runs, wall clock and CPU time of the process; on a shared machine the wall clock
includes waiting for a core. Features are cached in --cache (npz), so reruns skip rendering and SIFT; (c) renders
its frames every run. ``--storage files``: the engine keeps its descriptors, words, final lattice cells and frozen
index blocks in files it maps (a fresh temporary directory per run), as the worker does with ``state_dir``.

    .venv/bin/python benchmarks/loopclosure.py [--frames-a [N ...]] [--frames-b 2000] [--repeat 3] [--seed 0]
                                               [--storage memory|files]

A bare ``--frames-a`` skips (a): its exhaustive batch takes hours at 1,000 frames on a shared 2-core machine, while
(b) and (c) take a minute from the cache.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semloc_core.eval.pr import average_precision, pr_curve  # noqa: E402
from semloc_core.io.loopclosure import load_features, load_vocabulary, save_features, save_vocabulary  # noqa: E402
from semloc_core.loopclosure import (  # noqa: E402
    EngineParams,
    FeatureParams,
    LoopClosureEngine,
    Vocabulary,
    extract_features,
    train_vocabulary,
)
from semloc_core.loopclosure.evaluation import batch_pipeline, evaluated_pairs  # noqa: E402
from semloc_core.loopclosure.mrf import IncrementalMrf  # noqa: E402


def route_features(seed: int, frames: int, max_features: int, cache: Path):
    """SIFT sequences of the `route` scenario's frames and its loop ground truth (hard, soft), cached."""
    from semloc_core.sim.scenarios import make_scenario

    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"route_s{seed}_n{frames}_f{max_features}.npz"
    gt_path = cache / f"route_s{seed}_n{frames}_gt.npz"
    if path.exists() and gt_path.exists():
        sequences, _ = load_features(path)
        with np.load(gt_path, allow_pickle=False) as gt:
            return sequences, gt["hard"], gt["soft"]
    scenario = make_scenario("route", seed=seed, frames=frames)
    params = FeatureParams(max_features=max_features)
    sequences = []
    for i in range(len(scenario)):
        sequences.append(extract_features(scenario.image(i), scenario.camera, params, scenario.T_body_cam_at(i)))
        if (i + 1) % 200 == 0:
            print(f"  rendered and extracted {i + 1}/{frames} frames", flush=True)
    save_features(path, sequences, {"seed": seed, "sift": params.__dict__})
    np.savez(gt_path, hard=scenario.loop_gt, soft=scenario.loop_gt_soft)
    return sequences, scenario.loop_gt, scenario.loop_gt_soft


def extraction_times(seed: int, count: int, max_features: int, repeat: int) -> tuple[np.ndarray, np.ndarray]:
    """(wall, CPU) ms per frame of extract_features on ``count`` route frames spread over 1,200 (median of runs)."""
    from semloc_core.sim.scenarios import make_scenario

    scenario = make_scenario("route", seed=seed, frames=1200)
    picks = np.linspace(0, len(scenario) - 1, count).astype(int)
    images = [scenario.image(int(i)) for i in picks]
    params = FeatureParams(max_features=max_features)
    wall, cpu = np.zeros((repeat, count)), np.zeros((repeat, count))
    for r in range(repeat):
        for k, i in enumerate(picks):
            w, c = time.perf_counter(), time.process_time()
            extract_features(images[k], scenario.camera, params, scenario.T_body_cam_at(int(i)))
            wall[r, k], cpu[r, k] = (time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3
    return np.median(wall, axis=0), np.median(cpu, axis=0)


def scored_pairs(n: int, hard: np.ndarray, soft: np.ndarray, window: int):
    """(earlier, later, truth) of the pairs of the first ``n`` frames that the AP scores."""
    gt = np.triu(hard[:n, :n], 1)
    ignore = np.triu(soft[:n, :n], 1) & ~gt
    earlier, later = evaluated_pairs(n, window, ignore)
    return earlier, later, gt[earlier, later]


def after_inference_ap(beliefs: np.ndarray, hard: np.ndarray, soft: np.ndarray, window: int) -> float:
    earlier, later, truth = scored_pairs(beliefs.shape[0], hard, soft, window)
    return average_precision(pr_curve(beliefs[earlier, later], truth))


def offline_vocabulary(seed: int, frames: int, max_features: int, words: int, cache: Path) -> tuple[Vocabulary, dict]:
    """A vocabulary learnt on another world's frames (k-means), cached; and how it was made."""
    path = cache / f"vocabulary_route_s{seed}_n{frames}_f{max_features}_w{words}.npz"
    info = {"world": f"route seed {seed}", "frames": frames, "words": words, "file": str(path)}
    if path.exists():
        return load_vocabulary(path), {**info, "learnt_s": None}
    sequences, _, _ = route_features(seed, frames, max_features, cache)
    w, c = time.perf_counter(), time.process_time()
    vocabulary = train_vocabulary([f.descriptors for f in sequences if len(f)], words=words)
    info.update(learnt_wall_s=time.perf_counter() - w, learnt_cpu_s=time.process_time() - c)
    save_vocabulary(path, vocabulary)
    return vocabulary, info


STORAGE = "memory"  # --storage


def run_engine(sequences, params: EngineParams, vocabulary: Vocabulary | None = None):
    """The engine over the frames: (engine, per-frame wall s, per-frame CPU s, alignments, total wall s, CPU s)."""
    storage = None
    if STORAGE == "files":
        import atexit
        import shutil
        import tempfile

        from semloc_core.io.loopclosure import FileStorage

        directory = tempfile.mkdtemp(prefix="semloc-bench-")
        atexit.register(shutil.rmtree, directory, True)
        storage = FileStorage(directory)
    engine = LoopClosureEngine(params, vocabulary, storage)
    wall, cpu = np.zeros(len(sequences)), np.zeros(len(sequences))
    aligned = 0
    w0, c0 = time.perf_counter(), time.process_time()
    for k, features in enumerate(sequences):
        w, c = time.perf_counter(), time.process_time()
        aligned += engine.add_frame(features).candidates.size
        wall[k], cpu[k] = time.perf_counter() - w, time.process_time() - c
    return engine, wall, cpu, aligned, time.perf_counter() - w0, time.process_time() - c0


def timed(function):
    w, c = time.perf_counter(), time.process_time()
    result = function()
    return result, time.perf_counter() - w, time.process_time() - c


def engine_row(sequences, params: EngineParams, vocabulary, repeat: int, hard, soft) -> tuple[dict, LoopClosureEngine]:
    runs = [run_engine(sequences, params, vocabulary) for _ in range(repeat)]
    engine = runs[-1][0]
    return {"wall_s": statistics.median(r[4] for r in runs), "cpu_s": statistics.median(r[5] for r in runs),
            "alignments": runs[-1][3],
            "ap": after_inference_ap(engine.mrf.dense().beliefs, hard, soft, params.window)}, engine


def compare_with_batch(sequences, hard, soft, params: EngineParams, vocabulary: Vocabulary, repeat: int) -> dict:
    """(a) on these frames: the engine (median of runs; three configurations) vs the exhaustive batch pipeline."""
    window = params.window
    rows = {}
    rows["engine"], engine = engine_row(sequences, params, vocabulary, repeat, hard, soft)
    rows["engine_online_vocabulary"], online = engine_row(sequences, params, None, repeat, hard, soft)
    exact = replace(params, match_words=0)
    rows["engine_exhaustive_matching"], _ = engine_row(sequences, exact, vocabulary, repeat, hard, soft)
    batches = [timed(lambda: batch_pipeline(sequences, window, params.alignment, params.mrf, params.temporal_radius,
                                            map_min_belief=params.map_min_belief))
               for _ in range(max(1, repeat // 3))]
    batch = batches[-1][0]
    batch_wall = statistics.median(b[1] for b in batches)
    batch_cpu = statistics.median(b[2] for b in batches)
    n = len(sequences)
    ap_batch = after_inference_ap(batch.mrf.beliefs, hard, soft, window)
    for row in rows.values():
        row.update(speed_ratio_wall=batch_wall / row["wall_s"], speed_ratio_cpu=batch_cpu / row["cpu_s"],
                   ap_difference=ap_batch - row["ap"])
    for name, e in (("engine", engine), ("engine_online_vocabulary", online)):
        rows[name]["decision_agreement"] = float(np.mean(e.mrf.dense().decisions == batch.mrf.decisions))
    # The direct index's scores against the exhaustive ones on the pairs the engine aligned.
    r, c, scores, _ = engine.mrf.cells()
    exact_scores = batch.M[r, c]
    fidelity = {"pairs": int(r.size), "correlation": float(np.corrcoef(scores, exact_scores)[0, 1]),
                "mean_exact_minus_indexed": float(np.mean(exact_scores - scores)),
                "equal": float(np.mean(exact_scores == scores))}
    # The incremental lattice alone, on the batch's own scores and normalization: the same D?
    lattice = IncrementalMrf(params.mrf, params.band, batch.mrf.normalization, window)
    for j in range(n):
        cells = np.arange(max(0, j - window))
        lattice.add_column(cells, batch.M[cells, j], count=len(sequences[j]))
    same = lattice.dense().decisions
    return {
        "frames": n,
        "batch_alignments": int(np.isfinite(batch.M).sum()),
        "batch_wall_s": batch_wall, "batch_cpu_s": batch_cpu, "ap_batch": ap_batch,
        **rows,
        "indexed_scores_vs_exhaustive": fidelity,
        "incremental_vs_batch_mrf_same_scores": {
            "entries": float(np.mean(same == batch.mrf.decisions)),
            "positive_jaccard": float(np.sum(same & batch.mrf.decisions) / max(np.sum(same | batch.mrf.decisions), 1)),
            "band": params.band},
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames-a", type=int, nargs="*", default=[300, 1000],
                        help="(a) at these frame counts; none (a bare --frames-a) skips (a) and its exhaustive batch")
    parser.add_argument("--frames-b", type=int, default=2000)
    parser.add_argument("--max-features", type=int, default=FeatureParams().max_features)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--extract-frames", type=int, default=60, help="(c): frames timed")
    parser.add_argument("--vocabulary-seed", type=int, default=2, help="route world the vocabulary is learnt on")
    parser.add_argument("--vocabulary-frames", type=int, default=300, help="frames of it the vocabulary is learnt on")
    parser.add_argument("--cache", default=".semloc-cache/loopclosure")
    parser.add_argument("--json", default=None, help="also write the figures as JSON")
    parser.add_argument("--storage", choices=("memory", "files"), default="memory",
                        help="where the engine keeps what grows with the map (files: as the worker with state_dir)")
    args = parser.parse_args()
    global STORAGE
    STORAGE = args.storage
    params = EngineParams()
    cache = Path(args.cache)
    report: dict = {"engine_params": params.to_json_dict(), "max_features": args.max_features}

    if args.vocabulary_seed == args.seed:
        parser.error("the vocabulary must be learnt on another world than the one evaluated")
    print(f"features: route seed {args.seed}, {args.frames_b} frames, <= {args.max_features} SIFT per image")
    sequences, hard, soft = route_features(args.seed, max([args.frames_b, *args.frames_a]), args.max_features, cache)
    for n in args.frames_a:  # (a) scores the loop closures found: without one its AP is undefined
        if not scored_pairs(n, hard, soft, params.window)[2].any():
            parser.error(f"--frames-a {n}: the route's first {n} frames revisit no place (more frames)")
    mean_features = float(np.mean([len(s) for s in sequences]))
    vocabulary, report["vocabulary"] = offline_vocabulary(args.vocabulary_seed, args.vocabulary_frames,
                                                          args.max_features, params.vocabulary_words, cache)
    learnt = (f"learnt in {report['vocabulary']['learnt_cpu_s']:.1f} s CPU" if report["vocabulary"].get("learnt_cpu_s")
              else "cached")
    print(f"vocabulary: {params.vocabulary_words} words learnt offline on {report['vocabulary']['world']}, first "
          f"{args.vocabulary_frames} frames ({learnt}; not in the engine's time)")

    wall, cpu = extraction_times(args.seed, args.extract_frames, args.max_features, args.repeat)
    report["c_feature_extraction_ms"] = {"frames": args.extract_frames, "wall_p50": float(np.median(wall)),
                                         "wall_p95": float(np.percentile(wall, 95)), "cpu_p50": float(np.median(cpu)),
                                         "cpu_p95": float(np.percentile(cpu, 95)),
                                         "features_per_frame": mean_features}
    print(f"(c) feature extraction (640x480, {args.extract_frames} frames): wall p50 {np.median(wall):.1f} / p95 "
          f"{np.percentile(wall, 95):.1f} ms, CPU p50 {np.median(cpu):.1f} / p95 {np.percentile(cpu, 95):.1f} ms; "
          f"{mean_features:.0f} features kept per frame")

    report["a_incremental_vs_batch"] = []
    labels = {"engine": "engine (offline vocabulary)", "engine_online_vocabulary": "engine, online vocabulary",
              "engine_exhaustive_matching": "engine, exhaustive matching"}
    for n in args.frames_a:
        a = compare_with_batch(sequences[:n], hard, soft, params, vocabulary, args.repeat)
        report["a_incremental_vs_batch"].append(a)
        print(f"(a) {n} frames: exhaustive batch {a['batch_wall_s']:.2f} s wall / {a['batch_cpu_s']:.2f} s CPU "
              f"({a['batch_alignments']} alignments), AP after inference {a['ap_batch']:.3f}")
        for key, label in labels.items():
            e = a[key]
            agreement = f"; D agreement {e['decision_agreement']:.4f}" if "decision_agreement" in e else ""
            print(f"    {label:30s} {e['wall_s']:.2f} s wall / {e['cpu_s']:.2f} s CPU ({e['alignments']} alignments)"
                  f" -> {e['speed_ratio_wall']:.1f}x wall, {e['speed_ratio_cpu']:.1f}x CPU; AP {e['ap']:.3f} "
                  f"(difference {e['ap_difference']:+.3f}){agreement}")
        fid = a["indexed_scores_vs_exhaustive"]
        print(f"    indexed DP scores vs exhaustive on the engine's {fid['pairs']} pairs: correlation "
              f"{fid['correlation']:.4f}, equal {fid['equal']:.1%}, mean shortfall {fid['mean_exact_minus_indexed']:.2f}")
        same = a["incremental_vs_batch_mrf_same_scores"]
        print(f"    incremental MRF (band {same['band']}) on the batch's scores: D equal on {same['entries']:.2%} of "
              f"entries, positives Jaccard {same['positive_jaccard']:.3f}")

    # (b) per-frame latency as the map grows.
    runs = [run_engine(sequences[: args.frames_b], params, vocabulary) for _ in range(args.repeat)]
    latencies = np.median(np.stack([r[1] for r in runs]), axis=0) * 1e3
    cpu_ms = np.median(np.stack([r[2] for r in runs]), axis=0) * 1e3

    def window_stats(values: np.ndarray, end: int) -> dict:
        part = values[max(0, end - 100) : end]
        return {"p50": float(np.percentile(part, 50)), "p95": float(np.percentile(part, 95))}

    end = len(latencies)
    at_200, at_end = window_stats(latencies, min(200, end)), window_stats(latencies, end)
    report["b_latency_ms"] = {"frames": end, "overall_p50": float(np.percentile(latencies, 50)),
                              "overall_p95": float(np.percentile(latencies, 95)),
                              "at_200": at_200, f"at_{end}": at_end, "p95_ratio": at_end["p95"] / at_200["p95"],
                              "cpu": {"overall_p50": float(np.percentile(cpu_ms, 50)),
                                      "overall_p95": float(np.percentile(cpu_ms, 95)),
                                      "at_200": window_stats(cpu_ms, min(200, end)),
                                      f"at_{end}": window_stats(cpu_ms, end)},
                              "alignments_per_frame": runs[-1][3] / end}
    cpu_200, cpu_end = window_stats(cpu_ms, min(200, end)), window_stats(cpu_ms, end)
    print(f"(b) per-frame latency (median of {args.repeat} runs): overall p50 {np.percentile(latencies, 50):.1f} ms, "
          f"p95 {np.percentile(latencies, 95):.1f} ms; frames 100-200 p50 {at_200['p50']:.1f} / p95 "
          f"{at_200['p95']:.1f} ms; frames {end - 100}-{end} p50 {at_end['p50']:.1f} / p95 {at_end['p95']:.1f} ms "
          f"-> p95 ratio {at_end['p95'] / at_200['p95']:.2f}")
    print(f"    CPU: frames 100-200 p50 {cpu_200['p50']:.2f} / p95 {cpu_200['p95']:.2f} ms; frames {end - 100}-{end} "
          f"p50 {cpu_end['p50']:.2f} / p95 {cpu_end['p95']:.2f} ms; {runs[-1][3] / end:.1f} alignments per frame")
    growth = {stop: window_stats(cpu_ms, stop) for stop in range(200, end + 1, 200)}
    report["b_latency_ms"]["cpu"]["every_200"] = growth
    print("    CPU as the map grows (p50 / p95 of the 100 frames before): " +
          ", ".join(f"{stop}: {g['p50']:.2f} / {g['p95']:.2f}" for stop, g in growth.items()) +
          f"; whole run median {statistics.median(r[5] for r in runs):.2f} s CPU")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
