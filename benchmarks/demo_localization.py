"""The demo's localizer replayed on a demo world, over filter seeds: its error against odometry alone.

    .venv/bin/python benchmarks/demo_localization.py [--fast] [--appearance auto|real|generated] [--seeds 8]
        [--drop 0.0] [--prune] [--set KEY=VALUE ...] [--cache DIR] [--json out.json]

What `semloc demo` reports for localization is one run: one filter seed, one pattern of frames the detector dropped.
This replays the same localizer - the worker class of services/workers/localizer.py with deploy/demo.yaml's node
config and the demo's known start, on a private zenoh session with no peers - on every frame of the same world
(`semloc demo`'s cache; generated when missing), feeding its handlers directly in capture order: odometry, then the
detector's heatlines of that frame (computed once with the world's detector and cached beside the world). Per filter
seed: median and RMSE of the position error, and the ratio of that RMSE to odometry alone from the true start (the
demo's reference row); the localizer's states (localized / uncertain / lost) and the share flagged (not localized)
of the frames under 0.1 m off from the filter's first convergence on (issue 34's monitor). ``--drop P`` skips each
frame's heatlines with probability P (a loaded machine's detector), ``--set`` overrides the localizer's config
(``likelihood_exponent=0.1``, ``filter.outlier_probability=0``). ``--prune`` runs the world's detector on every
frame instead, its levels pruned by the localizer's last localized estimate (``PrunedHeatlines``), and prints each
seed's share of the exhaustive work.

An accuracy study, not a speed benchmark: its reference is odometry alone (the ratio of RMSEs), its figures medians
over filter seeds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _override(config: dict, assignment: str) -> None:
    key, _, value = assignment.partition("=")
    if not key or not _:
        raise SystemExit(f"--set wants KEY=VALUE, got {assignment!r}")
    *parents, leaf = key.split(".")
    for part in parents:
        config = config.setdefault(part, {})
    config[leaf] = yaml.safe_load(value)


def heatlines_of(world, log) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """(classes, scores (N, C, B), observed (N, B)) of the world's detector on every frame, cached in the world."""
    from semloc_core import bearing
    from semloc_core.detection.config import build_detector
    from semloc_core.detection.heatlines import HeatlineProjector
    from semloc_core.io.dataset import open_dataset

    cache = world.path / "replay_heatlines.npz"
    if cache.exists():
        stored = np.load(cache)
        return tuple(str(c) for c in stored["classes"]), stored["scores"], stored["observed"]
    dataset = open_dataset(world.dataset)
    detector = build_detector(str(world.detector))
    projector = HeatlineProjector(dataset.camera, tuple(detector.classes), bearing.BearingGrid(360))
    scores, observed = [], []
    for i in range(len(dataset)):
        heatlines = projector.project([detector.heatmaps(dataset.image(i))], T_body_cam=[None])
        scores.append(heatlines.scores)
        observed.append(heatlines.observed)
        if (i + 1) % 20 == 0 or i + 1 == len(dataset):
            log(f"  detector {i + 1}/{len(dataset)}")
    classes = tuple(heatlines.classes)
    np.savez(cache, classes=np.array(classes), scores=np.stack(scores), observed=np.stack(observed))
    return classes, np.stack(scores), np.stack(observed)


class PrunedHeatlines:
    """The world's detector run on each frame with its levels pruned by the localizer's last localized estimate
    (the detector worker's ``prune``, settings from ``demo_world.pruning_settings``), the camera's height from the
    frame's true 3-D pose as the demo's detector takes it (``height_pose``): what the heatlines are when the
    detector lags the localizer by a frame. ``shares``: each frame's share of the exhaustive work."""

    def __init__(self, world):
        from semloc_core import bearing
        from semloc_core.detection.config import build_detector
        from semloc_core.detection.heatlines import HeatlineProjector
        from semloc_core.detection.pruning import build_pruner
        from semloc_core.experiments.demo_world import pruning_settings
        from semloc_core.io.dataset import open_dataset
        from semloc_core.io.semantic_map import load_semantic_map

        self.dataset = open_dataset(world.dataset)
        self.detector = build_detector(str(world.detector))
        settings = pruning_settings(world)
        self.pruner = build_pruner(self.detector, self.dataset.camera, load_semantic_map(settings["map"]),
                                   settings["support_z"], settings["camera_height"], settings["support_polygon"])
        self.projector = HeatlineProjector(self.dataset.camera, tuple(self.detector.classes),
                                          bearing.BearingGrid(360))
        self.shares = []

    def __call__(self, i: int, estimate):
        from semloc_core.detection.pruning import height_from_pose

        rows = None
        if estimate is not None and estimate.localized():
            T_body_cam = self.dataset.T_body_cam[i]
            height = height_from_pose(self.dataset.T_world_body[i], T_body_cam, 0.0, self.pruner.params)
            rows = self.pruner.rows((estimate.x, estimate.y, estimate.theta), T_body_cam, height)
        self.shares.append(1.0 if rows is None else self.pruner.share(rows))
        heatlines = self.projector.project([self.detector.heatmaps(self.dataset.image(i), rows=rows)],
                                           T_body_cam=[None])
        return heatlines.scores, heatlines.observed


def replay(world, node_config: dict, seed: int, drop: float, classes, scores,
           observed, detect=None, estimates: list | None = None) -> tuple[np.ndarray, list, list]:
    """Position errors (m) of the localizer's estimate at every frame that got one, with its status and state
    (``estimates``: each frame's PoseEstimate appended, None for a frame it skipped).
    ``detect(i, last estimate)``: (scores, observed) of frame i's heatlines instead of ``scores[i]``,
    ``observed[i]``."""
    from schemas import Header, Odometry, encode
    from semloc_core import bearing
    from semloc_core.io.dataset import open_dataset
    from services.bus import BusConfig, open_session
    from services.frames import heatlines_frame
    from services.workers.localizer import Localizer, LocalizerConfig

    dataset = open_dataset(world.dataset)
    truth, odometry = dataset.poses2d, dataset.odometry
    config = LocalizerConfig(**{**node_config, "robot": "replay", "seed": seed, "odometry_wait_s": 0.0,
                                "sample_size": 0})
    worker = Localizer(config)
    skip = np.random.default_rng(1000 + seed).random(len(dataset)) < drop
    errors, statuses, states = [], [], []
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        worker.session = session
        worker.setup()
        for i in range(len(dataset)):
            stamp = int(dataset.stamps_ns[i])
            if i > 0:
                frame = Odometry(header=Header(robot="replay", stamp_ns=stamp), v=float(odometry.v[i]),
                                 v_lateral=float(odometry.v_lateral[i]), omega=float(odometry.omega[i]),
                                 dt=float(odometry.dt[i]))
                worker.on_odometry(frame, encode(frame))   # the bytes the worker journals
            if i > 0 and skip[i]:
                if estimates is not None:
                    estimates.append(None)
                continue
            header = Header(robot="replay", stamp_ns=stamp, seq=i, frame_id="body")
            frame_scores, frame_observed = (scores[i], observed[i]) if detect is None else detect(
                i, worker.last_estimate)
            worker.on_heatlines(heatlines_frame(header, bearing.Heatlines(classes, frame_scores, frame_observed)))
            estimate = worker.last_estimate
            if estimates is not None:
                estimates.append(estimate)
            errors.append(float(np.hypot(estimate.x - truth[i, 0], estimate.y - truth[i, 1])))
            statuses.append(estimate.status)
            states.append(estimate.state)
    return np.asarray(errors), statuses, states


def localizer_node(world) -> tuple[dict, object]:
    """(the demo localizer's node config for ``world``, with its known start; the world's data set)."""
    from semloc_core.io.dataset import open_dataset

    node = yaml.safe_load((REPO / "deploy" / "demo.yaml").read_text())["nodes"]["localizer"]["config"]
    dataset = open_dataset(world.dataset)
    node.update(map=str(world.semantic_map), score_likelihood=str(world.score_likelihood),
                initial_pose=[float(v) for v in dataset.poses2d[0]])  # the demo's known start
    return node, dataset


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fast", action="store_true", help="the world of `semloc demo --fast`")
    parser.add_argument("--appearance", default="auto", choices=("auto", "real", "generated"))
    parser.add_argument("--seed", type=int, default=0, help="the world's seed (`semloc demo --seed`)")
    parser.add_argument("--seeds", type=int, default=8, help="filter seeds to replay (0 .. N-1)")
    parser.add_argument("--drop", type=float, default=0.0, help="probability that a frame's heatlines are skipped")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="localizer config override")
    parser.add_argument("--cache", help="demo world cache (semloc demo --cache; default: its default)")
    parser.add_argument("--prune", action="store_true",
                        help="detect on every frame with the levels pruned by the localizer's last localized "
                             "estimate (the detector worker's prune) instead of the cached heatlines")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args(argv)
    if not 0 <= args.drop < 1 or args.seeds < 1:
        parser.error("--drop must be in [0, 1) and --seeds >= 1")

    from semloc_core.eval.trajectory import position_errors, rmse
    from semloc_core.experiments.demo_world import ensure_world
    from semloc_core.experiments.spec import load_preset
    from services.demo_run import DemoSpec

    spec = DemoSpec.model_validate({**load_preset("demo", "fast" if args.fast else "full"), "seed": args.seed,
                                    "appearance": args.appearance})
    world = ensure_world(spec.world(), Path(args.cache) if args.cache else None)
    node, dataset = localizer_node(world)
    for assignment in args.set:
        _override(node, assignment)
    classes, scores, observed = heatlines_of(world, print)
    reference = rmse(position_errors(dataset.odometry.integrate(dataset.poses2d[0]), dataset.poses2d))
    print(f"world {world.path.name}: {len(dataset)} frames; odometry alone from the true start: RMSE {reference:.3f} m")
    runs = []
    for seed in range(args.seeds):
        detect = PrunedHeatlines(world) if args.prune else None
        errors, statuses, states = replay(world, node, seed, args.drop, classes, scores, observed, detect)
        converged = next((k for k, status in enumerate(statuses) if status == "converged"), len(statuses))
        near = [state != "localized" for state, error in zip(states[converged:], errors[converged:]) if error < 0.1]
        run = {"seed": seed, "median_m": float(np.median(errors)), "rmse_m": rmse(errors),
               "max_m": float(errors.max()), "frames": int(errors.size),
               "states": {state: states.count(state) for state in ("localized", "uncertain", "lost")},
               "near_frames": len(near), "flagged_when_near": float(np.mean(near)) if near else None}
        run["rmse_over_odometry"] = run["rmse_m"] / reference
        if detect is not None:
            run["work_share"] = {"median": float(np.median(detect.shares)), "mean": float(np.mean(detect.shares)),
                                 "pruned_frames": int(sum(share < 1.0 for share in detect.shares))}
        runs.append(run)
        flagged = "-" if run["flagged_when_near"] is None else f"{run['flagged_when_near']:.3f}"
        print(f"  filter seed {seed}: median {run['median_m']:.3f} m, RMSE {run['rmse_m']:.3f} m "
              f"({run['rmse_over_odometry']:.2f}x odometry), max {run['max_m']:.2f} m; states "
              f"{'/'.join(str(v) for v in run['states'].values())} (localized/uncertain/lost), flagged {flagged} of "
              f"{run['near_frames']} frames < 0.1 m after convergence"
              + ("" if detect is None else f"; pruned {run['work_share']['pruned_frames']} frames, work share "
                 f"median {run['work_share']['median']:.2f}, mean {run['work_share']['mean']:.2f}"), flush=True)
    summary = {name: statistics.median(r[name] for r in runs) for name in ("median_m", "rmse_m", "max_m",
                                                                          "rmse_over_odometry")}
    print(f"median over {len(runs)} seeds: median error {summary['median_m']:.3f} m, RMSE {summary['rmse_m']:.3f} m "
          f"= {summary['rmse_over_odometry']:.2f}x odometry alone, worst frame {summary['max_m']:.2f} m "
          f"(medians per seed {min(r['median_m'] for r in runs):.3f}-{max(r['median_m'] for r in runs):.3f} m)")
    if args.json:
        Path(args.json).write_text(json.dumps({"world": str(world.path), "drop": args.drop, "overrides": args.set,
                                               "odometry_rmse_m": reference, "runs": runs, "median": summary},
                                              indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
