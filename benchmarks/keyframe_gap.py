"""The loop-closure worker's key-frame gate through a reboot: the robot drives on while its odometry and camera are
down, then both come back, the odometry chain restarted (its first message covers one frame's interval, no twist
across the reboot), so the span since the last key-frame is only partly covered.

    .venv/bin/python benchmarks/keyframe_gap.py [--dataset DIR] [--lost 5] [--every 10] [--set KEY=VALUE ...]

The worker class of services/workers/loopclosure.py with deploy/demo.yaml's key-frame settings (``min_interval_s``
0.25), on a private zenoh session with no peers, is given a data set's frames in capture order, as the camera
worker publishes them: each frame's odometry, then its image (the data set's, not a JPEG of it; the gate only: no
SIFT, no engine). The data set: `semloc demo`'s cached world (seed 0, real appearance, 3 fps; generated when
missing), or ``--dataset`` (a `semloc sim` folder with odometry). First every frame (complete odometry: the
key-frames, per reason, and a digest of their indices), then one run per reboot: ``--lost`` frames dropped
(odometry and image) from frame 20 on, every ``--every`` frames. Per run: whether the first frame after the reboot
is a key-frame (and why), and how far the robot went (ground truth) from the place it came back to before the next
key-frame. ``--set``: a ``keyframes`` override (``min_interval_s=0``).
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import statistics
import sys
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def frames_of(folder: str | None):
    """(keyframes settings of deploy/demo.yaml, stamps (N,), odometry (N, 4): v, v_lateral, omega, dt, truth
    poses (N, 3), the grey images (what the gate's thumbnail takes of a colour one)) of ``folder`` (None: the
    demo world)."""
    import cv2

    from semloc_core.io.dataset import open_dataset

    if folder is None:
        from semloc_core.experiments.demo_world import ensure_world
        from semloc_core.experiments.spec import load_preset
        from services.demo_run import DemoSpec

        spec = DemoSpec.model_validate({**load_preset("demo", "full"), "seed": 0, "appearance": "real"})
        folder = ensure_world(spec.world(), None).dataset
    dataset = open_dataset(folder)
    config = yaml.safe_load((REPO / "deploy" / "demo.yaml").read_text())["nodes"]["loopclosure"]["config"]
    images = [cv2.cvtColor(np.asarray(dataset.image(k)), cv2.COLOR_BGR2GRAY) for k in range(len(dataset))]
    return (config.get("keyframes", {}), np.asarray(dataset.stamps_ns, np.int64), dataset.odometry.as_array(),
            dataset.poses2d, images)


def gate(session, keyframes: dict, stamps, odometry, images, frames) -> list[tuple[int, str]]:
    """(frame, reason) of each key-frame a fresh worker's gate picks on ``frames`` (odometry first, then image)."""
    from schemas import Header, Odometry
    from services.workers.loopclosure import LoopClosureConfig, LoopClosureWorker

    worker = LoopClosureWorker(LoopClosureConfig(robot="gap", rerun_every=0, keyframes=keyframes))
    worker.session = session
    worker.setup()
    kept = []
    try:
        for k in frames:
            if k > 0:
                v, v_lateral, omega, dt = (float(x) for x in odometry[k])
                worker.on_odometry(Odometry(header=Header(robot="gap", stamp_ns=int(stamps[k])), v=v,
                                            v_lateral=v_lateral, omega=omega, dt=dt))
            counted = collections.Counter(worker.gated)
            if worker.is_keyframe(int(stamps[k]), images[k]):
                kept.append((k, next(iter(worker.gated - counted))))
    finally:
        worker.teardown()
        for entry in worker._inputs:
            entry.subscriber.undeclare()
    return kept


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", help="a semloc sim folder (default: the demo world)")
    parser.add_argument("--lost", type=int, default=5, help="frames lost in each reboot")
    parser.add_argument("--every", type=int, default=10, help="a reboot every this many frames (from frame 20)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="keyframes override")
    args = parser.parse_args(argv)
    from demo_localization import _override
    from services.bus import BusConfig, open_session

    keyframes, stamps, odometry, truth, images = frames_of(args.dataset)
    for assignment in args.set:
        _override(keyframes, assignment)
    n = len(stamps)
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        kept = gate(session, keyframes, stamps, odometry, images, range(n))
        reasons = collections.Counter(reason for _, reason in kept)
        digest = hashlib.sha256(np.array([k for k, _ in kept], np.int64).tobytes()).hexdigest()[:16]
        print(f"complete odometry: {len(kept)} key-frames of {n} "
              f"({', '.join(f'{r} {c}' for r, c in sorted(reasons.items()))}); indices sha256 {digest}", flush=True)
        runs = []
        for first in range(20, n - args.lost - 20, args.every):
            lost = range(first, first + args.lost)
            back = lost[-1] + 1
            kept = gate(session, keyframes, stamps, odometry, images, [k for k in range(n) if k not in lost])
            why = dict(kept).get(back)
            following = next(k for k, _ in kept if k >= back) if any(k >= back for k, _ in kept) else n - 1
            path = truth[back:following + 1, :2]
            driven = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) > 1 else 0.0
            moved = float(np.sum(np.hypot(*np.diff(truth[first - 1:back + 1, :2], axis=0).T)))
            runs.append((why, driven))
            print(f"  frames {first}-{lost[-1]} lost ({moved:.2f} m driven): frame {back} "
                  f"{'a key-frame (' + why + ')' if why else 'not a key-frame'}; next key-frame {following}, "
                  f"{driven:.2f} m on", flush=True)
    keyframed = sum(why is not None for why, _ in runs)
    driven = [d for _, d in runs]
    print(f"{len(runs)} reboots: the first frame after is a key-frame in {keyframed} "
          f"({', '.join(f'{r} {c}' for r, c in sorted(collections.Counter(w for w, _ in runs if w).items()))}); "
          f"driven from it before a key-frame: median {statistics.median(driven):.2f} m, max {max(driven):.2f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
