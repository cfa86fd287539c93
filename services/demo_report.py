"""The demo's results: what the workers published, evaluated against the simulator's ground truth.

Pure bookkeeping over ``semloc_core.eval`` (no bus, no processes): the collector's snapshot + the data set's ground
truth in, a JSON-ready document, a Markdown table and PNG plots out.

* Loop closure: the worker's final decisions (each frame's loops, as revised later by the banded inference) against
  the loop ground truth on the frames it processed, pairs more than ``window`` frames of the data set apart (the
  worker processes key-frames), soft pairs ignored
  (docs/evaluation.md); plus the average precision of its DP similarity scores (the retrieved candidates; pairs it
  never aligned rank last).
* Localization: every published pose against the true pose at the same capture stamp: RMSE, time to converge (error
  under ``LOCALIZATION_THRESHOLD_M`` for ``LOCALIZATION_HOLD_S``), RMSE after convergence, heading RMSE.
* Mapping: the mapper's final object map against the true one: precision / recall / F1 of objects matched within
  ``MAPPING_DISTANCE_M`` (3-D, same class), mean position error.
* Stages: frames in / out / dropped, throughput, camera -> output latency measured on the bus, and each worker's
  own handler latency (its Status).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from semloc_core.io.atomic import replace_bytes, replacing

LOCALIZATION_THRESHOLD_M = 0.25
LOCALIZATION_HOLD_S = 3.0
STATE_FAR_M, STATE_NEAR_M = 0.5, 0.1  # the localizer's state should flag frames this far off, and not these
MAPPING_DISTANCE_M = 0.10
LOOP_WINDOW = 30


def _percentiles(values) -> tuple[float | None, float | None]:
    values = np.asarray(list(values), float)
    if values.size == 0:
        return None, None
    p50, p95 = np.percentile(values, [50, 95])
    return float(p50), float(p95)


def _latencies(images: dict[int, float], outputs: dict[int, float]) -> list[float]:
    return [(arrived - images[stamp]) * 1e3 for stamp, arrived in outputs.items() if stamp in images]


# ---------------------------------------------------------------------------------------------------- loop closure
def _pairs_apart(values, gt, soft, apart) -> tuple[np.ndarray, np.ndarray]:
    """(values, labels) of the pairs [later, earlier] in ``apart``, as ``semloc_core.eval.pr.loop_pairs``: pairs
    ``soft`` but not ``gt`` are left out."""
    later, earlier = np.nonzero(apart)
    gt = np.asarray(gt, bool)[later, earlier]
    keep = np.ones(later.size, bool) if soft is None else ~(np.asarray(soft, bool)[later, earlier] & ~gt)
    return np.asarray(values, float)[later[keep], earlier[keep]], gt[keep]


def loop_closure_results(events: list, rows: list, index_of_stamp: dict[int, int], gt: np.ndarray,
                         soft: np.ndarray | None, window: int = LOOP_WINDOW, positions: np.ndarray | None = None) -> dict:
    """Decisions and similarity of the loop-closure worker, in its own frame numbering, mapped onto the data set.
    ``positions`` (the data set's camera centres): how far apart the false decisions' cameras are."""
    from semloc_core.eval.loops import frame_decisions, pair_distances
    from semloc_core.eval.pr import average_precision, max_recall_at_full_precision, pr_curve

    by_frame = {}
    for event in events:
        by_frame[int(event.frame)] = event
    if not by_frame:
        return {"available": False, "reason": "no loop-closure decisions were published"}
    n = max(by_frame) + 1
    dataset_index = np.full(n, -1)
    for frame, event in by_frame.items():
        dataset_index[frame] = index_of_stamp.get(int(event.header.stamp_ns), -1)
    known = dataset_index >= 0  # frames the collector missed (or stamps outside the data set) are left out
    loops = {frame: np.asarray(event.loops, int) for frame, event in by_frame.items()}
    for frame in sorted(by_frame):  # later events revise earlier frames' decisions: the last word wins
        for revision in by_frame[frame].revised:
            loops[int(revision.frame)] = np.asarray(revision.loops, int)
    decisions = np.zeros((n, n), bool)
    for frame, partners in loops.items():
        partners = partners[(partners >= 0) & (partners < n)]
        decisions[frame, partners] = True
    similarity = np.full((n, n), -np.inf)
    for row in rows:
        j = int(row.frame)
        if j < n and len(row.candidates):
            similarity[j, np.asarray(row.candidates, int)] = np.asarray(row.similarity, float)
    keep = np.flatnonzero(known)
    idx = dataset_index[keep]
    gt_sub = np.asarray(gt, bool)[np.ix_(idx, idx)]
    soft_sub = None if soft is None else np.asarray(soft, bool)[np.ix_(idx, idx)]
    d_sub = decisions[np.ix_(keep, keep)]
    s_sub = similarity[np.ix_(keep, keep)]
    # Pairs more than `window` frames of the data set apart: the worker processes key-frames, so its own numbering
    # skips frames (a window over its frames would be a longer stretch of the sequence).
    apart = idx[:, None] > idx[None, :] + window  # [later, earlier]
    dec, labels = _pairs_apart(d_sub.astype(float), gt_sub, soft_sub, apart)
    positives = int(labels.sum())
    predicted = int(dec.sum())
    tp = int(np.sum((dec > 0) & labels))
    out = {
        "available": True, "frames": int(n), "frames_evaluated": int(keep.size), "window": window,
        "pairs": int(labels.size), "positives": positives, "predicted": predicted, "true_positives": tp,
        "precision": tp / predicted if predicted else None,
        "recall": tp / positives if positives else None,
        # What the worker expected of its loops when it published the last frame (issue 33).
        "expected_precision": by_frame[max(by_frame)].expected_precision,
    }
    # Per frame (a place recognised or not): a frame "revisits" when it has a true partner more than ``window``
    # frames earlier; it is "recognised" when one of its reported partners is a true (or soft) one.
    hard = np.asarray(gt_sub, bool)
    soft_only = np.asarray(soft_sub, bool) & ~hard if soft_sub is not None else np.zeros_like(hard)
    out.update(frame_decisions(d_sub.T, hard.T, soft_only.T, apart.T))
    if positions is not None:
        # Near misses of the ground truth's radius, or places seen elsewhere (docs/loopclosure.md).
        out["false_decisions"] = pair_distances(d_sub & apart & ~hard & ~soft_only, np.asarray(positions)[idx])
    if positives and np.isfinite(s_sub).any():
        scores, labels_s = _pairs_apart(np.where(np.isfinite(s_sub), s_sub, -1e30), gt_sub, soft_sub, apart)
        curve = pr_curve(scores, labels_s)
        out["similarity_average_precision"] = average_precision(curve)
        out["similarity_recall_at_100_precision"] = max_recall_at_full_precision(curve)
        out["scored_pairs"] = int(np.sum(np.isfinite(s_sub)))
        out["_curve"] = curve
    out["_decisions"] = d_sub
    out["_gt"] = gt_sub
    return out


# ---------------------------------------------------------------------------------------------------- localization
def localization_results(poses: list, index_of_stamp: dict[int, int], truth2d: np.ndarray,
                         stamps_ns: np.ndarray, odometry=None) -> dict:
    """``odometry`` (the data set's, as the localizer received it): dead reckoning from the true first pose on the
    same frames is reported next to the filter, the reference a filter that uses the detections must beat."""
    from semloc_core.eval.trajectory import position_errors, rmse, trajectory_figures

    latest = {}
    for record in poses:  # one estimate per frame: the last one published for its stamp
        frame = index_of_stamp.get(record.stamp_ns)
        if frame is not None:
            latest[frame] = record
    if not latest:
        return {"available": False, "reason": "no pose estimates were published"}
    frames = np.array(sorted(latest))
    estimate = np.array([latest[f].pose for f in frames])
    figures = trajectory_figures(estimate, truth2d[frames], stamps_ns[frames], LOCALIZATION_THRESHOLD_M,
                                 LOCALIZATION_HOLD_S)
    statuses = [latest[f].status for f in frames]
    out = {
        "available": True, "frames": int(frames.size), "rmse_m": figures["rmse"],
        "median_error_m": figures["median_error"], "final_error_m": figures["final_error"],
        "converged": figures["converged"],
        "convergence_frame": None if figures["convergence_frame"] is None
        else int(frames[figures["convergence_frame"]]),
        "time_to_converge_s": figures["time_to_converge_s"],
        "rmse_after_convergence_m": figures["rmse_after_convergence"],
        "heading_rmse_deg": figures.get("heading_rmse_deg"),
        "heading_rmse_after_convergence_deg": figures.get("heading_rmse_after_convergence_deg"),
        "threshold_m": LOCALIZATION_THRESHOLD_M, "hold_s": LOCALIZATION_HOLD_S,
        "status_converged_fraction": float(np.mean([s == "converged" for s in statuses])),
        "final_status": statuses[-1],
        "_frames": frames, "_estimate": estimate, "_errors": np.asarray(figures["errors"], float),
    }
    states = [latest[f].state for f in frames]
    if all(state is not None for state in states):
        from semloc_core.localization.evaluation import state_metrics

        out["state_detection"] = state_metrics(states, out["_errors"].tolist(), STATE_FAR_M, STATE_NEAR_M)
    if odometry is not None:
        reckoned = odometry.integrate(truth2d[0])
        errors = position_errors(reckoned[frames], truth2d[frames])
        out["odometry_only_rmse_m"] = rmse(errors)
        out["_odometry_errors"] = errors
    return out


def place_results(topomap, index_of_stamp: dict[int, int], truth2d: np.ndarray) -> dict | None:
    """The hybrid map's places: how many key-frames carry a recorded pose, and how far those are from the truth."""
    if topomap is None or topomap.keyframe_poses is None:
        return None
    poses = np.asarray(topomap.keyframe_poses, float)
    known = np.isfinite(poses).all(axis=1)
    frames = np.array([index_of_stamp.get(int(s), -1) for s in topomap.keyframe_stamps_ns])
    matched = known & (frames >= 0)
    errors = np.hypot(*(poses[matched, :2] - truth2d[frames[matched], :2]).T)
    return {"nodes": int(len(poses)), "with_pose": int(known.sum()),
            "median_error_m": float(np.median(errors)) if errors.size else None}


# ---------------------------------------------------------------------------------------------------- mapping
def mapping_results(object_map, truth) -> dict:
    from semloc_core.eval.objects import compare_maps

    if object_map is None:
        return {"available": False, "reason": "the mapper published no object map"}
    from services.frames import semantic_map_from_frame

    predicted = semantic_map_from_frame(object_map)
    figures = compare_maps(predicted, truth, distance=MAPPING_DISTANCE_M, planar=False)
    return {
        "available": True, "objects": len(predicted), "true_objects": len(truth),
        "frames_integrated": int(object_map.frames), "distance_m": MAPPING_DISTANCE_M,
        "tp": figures["tp"], "fp": figures["fp"], "fn": figures["fn"], "precision": figures["precision"],
        "recall": figures["recall"], "f1": figures["f1"], "mean_position_error_m": figures["mean_position_error"],
        "per_class": {name: {k: v for k, v in c.items() if k in ("tp", "fp", "fn", "precision", "recall")}
                      for name, c in figures["per_class"].items()},
        "_predicted": predicted,
    }


# ---------------------------------------------------------------------------------------------------- stages
def stage_results(snapshot: dict, nodes: dict[str, str], duration_s: float) -> list[dict]:
    """One row per worker: frames in/out, drops, throughput over the playback, latency on the bus and in-handler."""
    status = snapshot["status"]
    images = snapshot["images"].arrivals
    outputs = {
        "camera": None,
        "detector": snapshot["heatlines"].arrivals,
        "loopclosure": snapshot["loopclosure"].get("events").arrivals if "events" in snapshot["loopclosure"] else {},
        "localizer": {r.stamp_ns: r.arrived for r in snapshot["poses"]},
        "mapper": None,
    }
    rows = []
    for role, node in nodes.items():
        s = status.get(node)
        row = {"stage": role, "node": node, "frames_in": None, "processed": None, "dropped": None,
               "throughput_fps": None, "latency_p50_ms": None, "latency_p95_ms": None,
               "handler_p50_ms": None, "handler_p95_ms": None, "sustained_fps": None, "handler_mean_ms": None,
               "capacity_fps": None, "busy_fraction": None}
        if role == "camera":
            row["processed"] = len(images)
            row["throughput_fps"] = len(images) / duration_s if duration_s > 0 else None
        elif s is not None:
            main = _main_input(role, s)
            if main is not None:
                row["frames_in"], row["processed"], row["dropped"] = main.received, main.processed, main.dropped
                row["throughput_fps"] = main.processed / duration_s if duration_s > 0 else None
            # Status's last 10 s, from the last Status with a rate on the main input: the last of all may come after
            # 10 s of waiting for a lagging stage (optional v1 fields: None from a worker without them)
            during = next((h for h in reversed(snapshot.get("status_history", {}).get(node, []))
                           if (main_of := _main_input(role, h)) is not None and main_of.rate_hz), s)
            rates = _main_input(role, during)
            if rates is not None:
                row["sustained_fps"], row["handler_mean_ms"] = rates.rate_hz, rates.handler_ms
                if rates.handler_ms:
                    row["capacity_fps"] = 1e3 / rates.handler_ms
            row["handler_p50_ms"], row["handler_p95_ms"] = s.latency_p50_ms, s.latency_p95_ms
            row["busy_fraction"] = during.busy_fraction
        if outputs.get(role):
            row["latency_p50_ms"], row["latency_p95_ms"] = _percentiles(_latencies(images, outputs[role]))
        rows.append(row)
    return rows


MAIN_INPUT = {"detector": "image", "loopclosure": "image", "localizer": "heatlines", "mapper": "heatmaps"}
POSE_CHAIN = ("camera", "detector", "localizer")  # each pose needs one frame through each of these


def pose_rate_limit(stages: list[dict], camera_rate_hz: float) -> dict:
    """Which stage limits the pose rate: the lowest of the camera's rate and each pose-chain stage's capacity (1000 /
    its mean handler time over Status's last 10 s, measured on the loaded machine). Stages off the chain (loop
    closure, mapper) slow it only by taking CPU, which shows in those capacities."""
    limits = {"camera": camera_rate_hz}
    for stage in stages:
        if stage["stage"] in POSE_CHAIN[1:] and stage["capacity_fps"] is not None:
            limits[stage["stage"]] = stage["capacity_fps"]
    limiting = min(limits, key=limits.get)
    return {"stage": limiting, "rate_hz": limits[limiting], "capacities_hz": limits}


def _main_input(role: str, status):
    name = MAIN_INPUT.get(role)
    return status.inputs.get(name) if name else None


# ---------------------------------------------------------------------------------------------------- tables
def _fmt(value, digits: int = 2, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return f"{value}{unit}"
    return f"{value:.{digits}f}{unit}"


def _false_decisions_text(false: dict | None) -> str:
    if not false or not false.get("quartiles_m"):
        return ""
    q = false["quartiles_m"]
    return f"; the false ones {_fmt(q[0])}-{_fmt(q[2])} m apart (quartiles)"


def results_markdown(doc: dict) -> str:
    lc, loc, mp = doc["loop_closure"], doc["localization"], doc["mapping"]
    w = doc["world"]
    lines = [f"# semloc demo results", "",
             f"World: `tabletop` seed {w['seed']}, {w['frames']} frames ({w['appearance']} object appearances), "
             f"{w['laps']} laps round the table ({w['path_m']} m), {w['object_count']} objects, "
             f"{w['loop_pairs']} true loop pairs. Played at {doc['run']['rate_hz']:g} Hz, "
             f"{doc['run']['playback_s']:.0f} s; whole run {doc['run']['total_s']:.0f} s.", "",
             "| capability | figure | value |", "|---|---|---|"]

    def row(capability, figure, value):
        lines.append(f"| {capability} | {figure} | {value} |")

    if lc.get("available"):
        row("loop closure", f"precision / recall of the decisions (pairs > {lc['window']} frames apart)",
            f"{_fmt(lc['precision'])} / {_fmt(lc['recall'])} ({lc['true_positives']} of {lc['predicted']} "
            f"reported, {lc['positives']} true); the worker expected precision {_fmt(lc.get('expected_precision'))}"
            + _false_decisions_text(lc.get("false_decisions")))
        if lc.get("frame_recall") is not None:
            row("loop closure", "frames revisiting a place that got a correct loop; frames with loops that are right",
                f"{lc['revisit_frames_recognised']} of {lc['revisit_frames']} ({_fmt(lc['frame_recall'])}); "
                f"{lc['frames_with_correct_loop']} of {lc['frames_with_loop']} ({_fmt(lc['frame_precision'])})")
        if lc.get("places") is not None:
            row("loop closure", "hybrid map: places whose key-frame has a recorded pose (seen while localized); "
                "their error against the truth, median", f"{lc['places']['with_pose']} of {lc['places']['nodes']}; "
                f"{_fmt(lc['places']['median_error_m'], 3, ' m')}")
        if "similarity_average_precision" in lc:
            row("loop closure", "average precision of the DP similarity", _fmt(lc["similarity_average_precision"]))
    else:
        row("loop closure", "-", lc.get("reason", "not run"))
    if loc.get("available"):
        row("localization", "position RMSE, all frames", _fmt(loc["rmse_m"], 3, " m"))
        if loc.get("odometry_only_rmse_m") is not None:
            row("localization", "(reference) odometry alone from the true start: RMSE",
                _fmt(loc["odometry_only_rmse_m"], 3, " m"))
        row("localization", f"time to converge (< {loc['threshold_m']:g} m for {loc['hold_s']:g} s)",
            _fmt(loc["time_to_converge_s"], 1, " s") if loc["converged"] else "did not converge")
        row("localization", "position RMSE after convergence", _fmt(loc["rmse_after_convergence_m"], 3, " m"))
        row("localization", "heading RMSE", _fmt(loc["heading_rmse_deg"], 1, " deg"))
        if loc.get("state_detection"):
            d = loc["state_detection"]
            counts = d["states"]
            row("localization", f"localizer state: frames localized / uncertain / lost; flagged (not localized) "
                f"when > {d['far_m']:g} m off, when < {d['near_m']:g} m",
                f"{counts['localized']} / {counts['uncertain']} / {counts['lost']}; "
                f"{_fmt(d['flagged_when_far'])} of {d['far_frames']}, {_fmt(d['flagged_when_near'])} of "
                f"{d['near_frames']}")
    else:
        row("localization", "-", loc.get("reason", "not run"))
    if mp.get("available"):
        row("mapping", f"precision / recall / F1 (same class, within {mp['distance_m']:g} m)",
            f"{_fmt(mp['precision'])} / {_fmt(mp['recall'])} / {_fmt(mp['f1'])} ({mp['tp']} of {mp['objects']} "
            f"mapped, {mp['true_objects']} true)")
        row("mapping", "mean position error of matched objects", _fmt(mp["mean_position_error_m"], 3, " m"))
    else:
        row("mapping", "-", mp.get("reason", "not run"))
    lines += ["", "| stage | frames in | processed | dropped | throughput (fps) | sustained / capacity (fps) | busy "
                  "| camera -> output p50 / p95 (ms) | handler p50 / p95 (ms) |", "|---|---|---|---|---|---|---|---|---|"]
    for s in doc["stages"]:
        busy = None if s.get("busy_fraction") is None else 100 * s["busy_fraction"]
        lines.append(f"| {s['stage']} | {_fmt(s['frames_in'])} | {_fmt(s['processed'])} | {_fmt(s['dropped'])} | "
                     f"{_fmt(s['throughput_fps'])} | {_fmt(s.get('sustained_fps'), 1)} / {_fmt(s.get('capacity_fps'), 1)} "
                     f"| {_fmt(busy, 0, ' %')} | {_fmt(s['latency_p50_ms'], 0)} / {_fmt(s['latency_p95_ms'], 0)} "
                     f"| {_fmt(s['handler_p50_ms'], 0)} / {_fmt(s['handler_p95_ms'], 0)} |")
    limit = doc.get("pose_rate")
    if limit:
        lines += ["", f"Poses: {_fmt(limit['poses_hz'], 1)} Hz over the playback; the pose rate is limited by the "
                      f"**{limit['stage']}** ({_fmt(limit['rate_hz'], 1)} fps; capacities: "
                      + ", ".join(f"{k} {_fmt(v, 1)}" for k, v in limit["capacities_hz"].items()) + ")."]
    lines += ["", f"Command: `{doc['command']}`", ""]
    return "\n".join(lines)


def public(doc: dict) -> dict:
    """The document without the private arrays (keys starting with '_') used for plots."""
    if isinstance(doc, dict):
        return {k: public(v) for k, v in doc.items() if not str(k).startswith("_")}
    if isinstance(doc, list):
        return [public(v) for v in doc]
    return doc


# ---------------------------------------------------------------------------------------------------- plots
def save_figure(figure, path: Path, **options) -> None:
    """A figure as PNG, replacing ``path`` atomically (a full disk leaves no half-written plot)."""
    with replacing(path) as stream:
        figure.savefig(stream, format="png", **{"bbox_inches": "tight", **options})


def write_plots(doc: dict, truth, truth2d: np.ndarray, stamps_ns: np.ndarray, folder: Path) -> list[Path]:
    """PNG plots: localization error, trajectories with the maps, loop-closure decisions, PR curve, latency."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from semloc_core.eval.report import error_plot_png, pr_plot_png

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    loc, lc, mp = doc["localization"], doc["loop_closure"], doc["mapping"]
    if loc.get("available"):
        times = (stamps_ns[loc["_frames"]] - stamps_ns[0]) * 1e-9
        path = folder / "localization_error.png"
        curves = {"localizer": loc["_errors"]}
        if "_odometry_errors" in loc:
            curves["odometry alone (reference)"] = loc["_odometry_errors"]
        replace_bytes(path, error_plot_png(times, curves, title="localization error vs truth",
                                           threshold=loc["threshold_m"]))
        written.append(path)
    # Top view: true path, estimated path, true objects and mapped objects.
    figure = Figure(figsize=(6.5, 6.0), dpi=100)
    ax = figure.add_subplot(1, 1, 1)
    ax.plot(truth2d[:, 0], truth2d[:, 1], color="tab:green", linewidth=1, label="true camera path")
    if loc.get("available"):
        ax.plot(loc["_estimate"][:, 0], loc["_estimate"][:, 1], ".", color="tab:blue", markersize=3,
                label="localizer estimate")
    ax.scatter(truth.positions[:, 0], truth.positions[:, 1], s=80, facecolors="none", edgecolors="k",
               label="true objects")
    for k, (x, y) in zip(truth.class_index, truth.positions[:, :2]):
        ax.annotate(truth.class_names[k], (x, y), fontsize=7, xytext=(4, 4), textcoords="offset points")
    if mp.get("available") and len(mp["_predicted"]):
        p = mp["_predicted"]
        ax.scatter(p.positions[:, 0], p.positions[:, 1], marker="x", color="tab:red", label="mapped objects")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("top view")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    path = folder / "top_view.png"
    save_figure(figure, path)
    written.append(path)
    if lc.get("available"):
        figure = Figure(figsize=(9, 4.5), dpi=100)
        for k, (matrix, title) in enumerate(((lc["_gt"], "true loops"), (lc["_decisions"], "worker's decisions"))):
            ax = figure.add_subplot(1, 2, k + 1)
            ax.imshow(np.tril(matrix, -1), cmap="gray_r", interpolation="nearest")
            ax.set_title(title)
            ax.set_xlabel("earlier frame")
            ax.set_ylabel("later frame")
        path = folder / "loop_closure.png"
        save_figure(figure, path)
        written.append(path)
        if "_curve" in lc:
            path = folder / "loop_closure_pr.png"
            replace_bytes(path, pr_plot_png({"DP similarity": lc["_curve"]},
                                            title="loop closure: PR of the similarity scores"))
            written.append(path)
    stages = [s for s in doc["stages"] if s["latency_p50_ms"] is not None or s["handler_p50_ms"] is not None]
    if stages:
        figure = Figure(figsize=(7, 3.5), dpi=100)
        ax = figure.add_subplot(1, 1, 1)
        x = np.arange(len(stages))
        for offset, key, label in ((-0.2, "latency", "camera -> output"), (0.2, "handler", "in the handler")):
            p50 = [s[f"{key}_p50_ms"] or 0 for s in stages]
            p95 = [s[f"{key}_p95_ms"] or 0 for s in stages]
            ax.bar(x + offset, p50, 0.4, label=f"{label} p50")
            ax.errorbar(x + offset, p50, yerr=[np.zeros(len(p50)), np.maximum(np.array(p95) - p50, 0)], fmt="none",
                        ecolor="k", capsize=3)
        ax.set_xticks(x, [s["stage"] for s in stages])
        ax.set_ylabel("ms (bar p50, whisker p95)")
        ax.set_title("per-stage latency")
        ax.legend(fontsize=8)
        path = folder / "latency.png"
        save_figure(figure, path)
        written.append(path)
    return written
