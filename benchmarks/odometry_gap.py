"""The localizer through a reboot: neither odometry nor heatlines for a while, then both again, the odometry chain
restarted (its first Odometry covers one frame's interval, no twist across the reboot), so the first span after the
gap is only partly covered. Per filter seed: the error and spread of the first estimate after the gap, its state,
and the frames until the error stays under 0.1 m.

    .venv/bin/python benchmarks/odometry_gap.py [--world table|demo] [--seeds 8] [--ignore-uncovered]
        [--set KEY=VALUE ...]

``table``: the table top of tests/localization/test_localizer_worker.py (a robot circling it at 0.3 m/s, 15 Hz,
synthetic heatlines, augmented MCL on), 50 frames lost (3.3 s, 1.0 m). ``demo``: the demo localizer's replay
(benchmarks/demo_localization.py: `semloc demo`'s cached world, real appearance, deploy/demo.yaml's node config,
recovery off), frames 150-154 lost (2.0 s, 1.0 m). ``--ignore-uncovered``: the localizer as before it diffused over
the uncovered time (``OdometryBuffer.uncovered_until`` reporting none). ``--set``: a localizer config override
(``max_dt=5``, ``filter.recovery_alpha_slow=0``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def table_world():
    """(node config, truth poses (K, 3), stamps, odometry (v, v_lateral, omega, dt) per frame, heatlines(k), lost)."""
    from semloc_core.io.semantic_map import save_semantic_map
    from tests.localization.test_localizer_worker import (FILTER, RADIUS, RATE, SPEED, _heatlines_frame, _robot_pose,
                                                          _table_map)

    semantic_map, frames = _table_map(), 60 + 50 + 90
    path = Path(tempfile.gettempdir()) / "odometry_gap_table_map.json"
    save_semantic_map(semantic_map, path)
    node = {"map": str(path), "model": "B", "odom_alpha1": 0.05, "odom_alpha2": 0.05, "odom_alpha3": 0.05,
            "odom_alpha4": 0.05, "initial_pose": _robot_pose(0).tolist(), "initial_covariance": [1e-4] * 3,
            "filter": FILTER}
    truth = np.array([_robot_pose(k) for k in range(frames)])
    stamps = (np.arange(frames) / RATE * 1e9).astype(np.int64)
    odometry = np.tile([SPEED, 0.0, SPEED / RADIUS, 1 / RATE], (frames, 1))
    return node, truth, stamps, odometry, lambda k: _heatlines_frame(semantic_map, k, k), range(60, 110)


def demo_world():
    import demo_localization as demo
    from semloc_core import bearing
    from semloc_core.experiments.demo_world import ensure_world
    from semloc_core.experiments.spec import load_preset
    from services.demo_run import DemoSpec
    from services.frames import heatlines_frame
    from schemas import Header

    spec = DemoSpec.model_validate({**load_preset("demo", "full"), "seed": 0, "appearance": "real"})
    world = ensure_world(spec.world(), None)
    node, dataset = demo.localizer_node(world)
    classes, scores, observed = demo.heatlines_of(world, print)
    stamps = np.asarray(dataset.stamps_ns, np.int64)
    odometry = dataset.odometry.as_array()

    def heatlines(k):
        return heatlines_frame(Header(robot="gap", stamp_ns=int(stamps[k]), seq=k, frame_id="body"),
                               bearing.Heatlines(classes, scores[k], observed[k]))
    return node, dataset.poses2d, stamps, odometry, heatlines, range(150, 155)


def run(node: dict, truth, stamps, odometry, heatlines, lost, seed: int) -> dict:
    from schemas import Header, Odometry, encode
    from services.bus import BusConfig, open_session
    from services.workers.localizer import Localizer, LocalizerConfig

    worker = Localizer(LocalizerConfig(**{**node, "robot": "gap", "seed": seed, "odometry_wait_s": 0.0,
                                          "sample_size": 0}))
    after = []
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        worker.session = session
        worker.setup()
        for k in range(len(stamps)):
            if k in lost:
                continue
            if k > 0:
                v, v_lateral, omega, dt = (float(x) for x in odometry[k])
                frame = Odometry(header=Header(robot="gap", stamp_ns=int(stamps[k])), v=v, v_lateral=v_lateral,
                                 omega=omega, dt=dt)
                worker.on_odometry(frame, encode(frame))
            worker.on_heatlines(heatlines(k))
            estimate = worker.last_estimate
            if k > lost[-1]:
                after.append((float(np.hypot(estimate.x - truth[k, 0], estimate.y - truth[k, 1])),
                              float(np.sqrt(max(estimate.covariance[0][0], estimate.covariance[1][1]))),
                              estimate.state))
    off = [i for i, (error, _, _) in enumerate(after) if error >= 0.1]
    return {"error": after[0][0], "std": after[0][1], "state": after[0][2], "errors": [a[0] for a in after[:6]],
            "within_0.1_from": off[-1] + 1 if off else 0, "frames": len(after)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", default="table", choices=("table", "demo"))
    parser.add_argument("--seeds", type=int, default=8, help="filter seeds 0 .. N-1")
    parser.add_argument("--ignore-uncovered", action="store_true", help="the localizer before the change")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="localizer config override")
    args = parser.parse_args(argv)
    from demo_localization import _override
    if args.ignore_uncovered:
        from semloc_core.localization.motion import OdometryBuffer
        OdometryBuffer.uncovered_until = lambda self, stamp_ns: 0.0
    node, truth, stamps, odometry, heatlines, lost = table_world() if args.world == "table" else demo_world()
    for assignment in args.set:
        _override(node, assignment)
    moved = float(np.sum(np.hypot(*np.diff(truth[lost[0] - 1:lost[-1] + 2, :2], axis=0).T)))
    print(f"{args.world}: frames {lost[0]}-{lost[-1]} lost, {(stamps[lost[-1] + 1] - stamps[lost[0] - 1]) / 1e9:.2f} s,"
          f" the truth moved {moved:.2f} m")
    for seed in range(args.seeds):
        r = run(node, truth, stamps, odometry, heatlines, lost, seed)
        print(f"  seed {seed}: first after the gap: error {r['error']:.2f} m, std {r['std']:.3f} m, {r['state']}; "
              f"errors {' '.join(f'{e:.2f}' for e in r['errors'])}; under 0.1 m from frame {r['within_0.1_from']} "
              f"of {r['frames']} on", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
