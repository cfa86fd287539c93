"""Backpressure benchmark: a slow lossless subscriber must not slow the camera or a fast subscriber next to it.

    .venv/bin/python benchmarks/backpressure.py [--seconds 20] [--depth 256] [--rate 30] [--slow-s 0.1]

Separate processes over zenoh on loopback, all joined to this process's session (the hub):

* ``camera``: the camera worker playing a folder of 640x480x3 images at ``--rate`` frames/s, looping;
* ``fast``: a sink worker, ``latest`` input (depth 2), no work per frame;
* ``slow``: a sink worker, ``lossless`` input of ``--depth`` frames, ``--slow-s`` seconds per frame (10 frames/s).

Two runs in this process: the reference (camera and fast only), then the same with the slow subscriber added.
Rates are counter deltas of the workers' own Status frames, the median over the 1 s windows of ``--seconds`` after a
warm-up (the slow queue fills first). The slow subscriber's memory is its private resident set (VmRSS less the
pages of the publisher's zenoh shared-memory pool it maps, printed apart), sampled every 0.2 s, against its own
before any frame reached it (the camera is stopped while it starts).

Prints the camera's and the fast subscriber's rates in both runs, the fast subscriber's rate against the
reference run (the ratio) and its share of the camera's rate in the reference run (target >= 0.9: a camera slowed
down by the slow subscriber fails it), the slow subscriber's rate and overflow, and its memory growth against the
bound ``depth x frame size + 50 MB``. Exit code 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from schemas import Status, keys  # noqa: E402
from services.bus import BusConfig, free_port, open_session, query  # noqa: E402

ROBOT = "bench"
SHAPE = (480, 640, 3)
MEMORY_SLACK = 50 << 20


def resident(pid: int) -> tuple[int, int]:
    """(private, shared-memory) resident bytes of a process. The shared part is the publisher's shared-memory pool
    (services.bus.SharedMemoryPool: a few of its frames) as far as this process touched it reading frames: the
    publisher's memory, mapped by every subscriber on the machine, whatever their queues."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "RssShmem"):
            fields[name] = int(value.split()[0]) << 10
    return fields["VmRSS"] - fields.get("RssShmem", 0), fields.get("RssShmem", 0)


def make_images(folder: Path, count: int = 30) -> None:
    """``count`` distinct 640x480 colour images (a gradient with noise: textured, quick to decode)."""
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 255, SHAPE[1], dtype=np.float32)[None, :, None]
    for index in range(count):
        noise = rng.normal(0, 8, SHAPE).astype(np.float32)
        pixels = np.clip(ramp + noise + index * 4, 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{index:03d}.png"), pixels)


class Graph:
    """The worker processes of one benchmark, joined to this process's hub session."""

    def __init__(self, hub: str, session, logs: Path):
        self.hub, self.session, self.logs = hub, session, logs
        self.processes: dict[str, subprocess.Popen] = {}

    def start(self, name: str, kind: str, *args: str) -> subprocess.Popen:
        env = {k: v for k, v in os.environ.items() if not k.startswith("SEMLOC__")}
        env["PYTHONPATH"] = str(REPO_ROOT)
        with open(self.logs / f"{name}.log", "ab") as log:
            process = subprocess.Popen([sys.executable, "-m", "services.cli", "worker", kind, "--connect", self.hub,
                                        "--robot", ROBOT, "--name", name, "--log-level", "WARNING", *args],
                                       cwd=REPO_ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                                       stdin=subprocess.DEVNULL, start_new_session=True)
        self.processes[name] = process
        deadline = time.monotonic() + 60
        while not ((s := self.status().get(name)) and s.state == "running"):
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"worker {name} did not start; see {self.logs / f'{name}.log'}")
            time.sleep(0.2)
        return process

    def stop(self, name: str) -> None:
        process = self.processes.pop(name)
        process.send_signal(signal.SIGINT)
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()

    def stop_all(self) -> None:
        for name in list(self.processes):
            self.stop(name)

    def status(self) -> dict[str, Status]:
        frames = query(self.session, keys.robot_statuses(ROBOT), reply_type=Status, timeout=3.0, every_reply=True)
        return {frame.worker: frame for frame in frames}


def rates(before: dict[str, Status], after: dict[str, Status]) -> dict[str, dict[str, float]]:
    """Per worker: frames/s published (camera) or received / processed / refused (sinks) between two Status."""
    out = {}
    for name, end in after.items():
        start = before.get(name)
        if start is None or start.pid != end.pid:
            continue
        seconds = (end.header.stamp_ns - start.header.stamp_ns) * 1e-9
        delta = lambda attr: (getattr(end, attr, 0) - getattr(start, attr, 0)) / seconds  # noqa: E731
        published = sum(o.published for o in end.outputs.values() if o.key.endswith("/image")) - \
            sum(o.published for o in start.outputs.values() if o.key.endswith("/image"))
        out[name] = {"published": published / seconds, "received": delta("received"),
                     "processed": delta("processed"), "overflow": delta("overflow"), "dropped": delta("dropped")}
    return out


def measure(graph: Graph, warmup_s: float, seconds: float, window_s: float = 1.0) -> dict[str, dict[str, float]]:
    """Per worker, the median of each rate over the ``window_s`` windows of ``seconds`` after ``warmup_s``."""
    time.sleep(warmup_s)
    samples = [graph.status()]
    for _ in range(max(1, round(seconds / window_s))):
        time.sleep(window_s)
        samples.append(graph.status())
    windows = [rates(before, after) for before, after in zip(samples, samples[1:])]
    return {name: {what: statistics.median(w[name][what] for w in windows if name in w) for what in figures}
            for name, figures in windows[-1].items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="measurement window of each run")
    parser.add_argument("--warmup", type=float, default=8.0, help="seconds before the window (the slow queue fills)")
    parser.add_argument("--depth", type=int, default=256, help="the slow subscriber's lossless queue depth")
    parser.add_argument("--rate", type=float, default=30.0, help="camera frames per second")
    parser.add_argument("--slow-s", type=float, default=0.1, help="the slow subscriber's seconds per frame")
    args = parser.parse_args()

    frame_bytes = int(np.prod(SHAPE))
    bound = args.depth * frame_bytes + MEMORY_SLACK
    hub = f"tcp/127.0.0.1:{free_port()}"
    image_key = keys.camera_image(ROBOT)
    camera = ("camera", "--set", None, "--set", f"rate={args.rate}", "--set", "loop=true")
    with tempfile.TemporaryDirectory(prefix="semloc-backpressure-") as scratch, \
            open_session(BusConfig(listen=[hub])) as session:
        scratch = Path(scratch)
        (scratch / "images").mkdir()
        make_images(scratch / "images")
        camera = tuple(f"source={scratch / 'images'}" if a is None else a for a in camera)
        graph = Graph(hub, session, scratch)
        samples: list[tuple[int, int]] = []
        try:
            graph.start("fast", "sink", "--set", f"key={image_key}", "--set", "policy=latest", "--set", "depth=2")
            graph.start("camera", *camera)
            reference = measure(graph, args.warmup, args.seconds)
            graph.stop("camera")  # so the slow subscriber's resident set is measured before any frame reaches it
            slow = graph.start("slow", "sink", "--set", f"key={image_key}", "--set", "policy=lossless", "--set",
                               f"depth={args.depth}", "--set", f"process_delay_s={args.slow_s}")
            baseline = resident(slow.pid)[0]
            sampling = threading.Event()

            def sample_rss():
                while not sampling.wait(0.2):
                    samples.append(resident(slow.pid))

            sampler = threading.Thread(target=sample_rss, daemon=True)
            sampler.start()
            graph.start("camera", *camera)
            loaded = measure(graph, args.warmup, args.seconds)
            final = graph.status()["slow"]
            sampling.set()
            sampler.join()
        finally:
            graph.stop_all()

    camera_ref, fast_ref = reference["camera"]["published"], reference["fast"]["processed"]
    camera_rate, fast_rate = loaded["camera"]["published"], loaded["fast"]["processed"]
    slow = loaded["slow"]
    peak = max(private for private, _ in samples)
    shared = max(shared for _, shared in samples)
    share = fast_rate / camera_ref  # of the camera's own rate: a camera slowed down by a subscriber is the failure
    print(f"640x480x3 frames ({frame_bytes} B), camera at {args.rate:g} frames/s, slow subscriber lossless depth "
          f"{args.depth} at {args.slow_s:g} s/frame; rates: medians over the 1 s windows of {args.seconds:g} s after "
          f"{args.warmup:g} s; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    print(f"{'run':28s} {'camera fps':>10s} {'fast fps':>9s} {'fast / camera':>14s} {'slow fps':>9s} "
          f"{'slow overflow/s':>16s}")
    print(f"{'reference (no slow)':28s} {camera_ref:10.1f} {fast_ref:9.1f} {fast_ref / camera_ref:13.2f}x")
    print(f"{'with the slow subscriber':28s} {camera_rate:10.1f} {fast_rate:9.1f} {share:13.2f}x "
          f"{slow['processed']:9.1f} {slow['overflow']:16.1f}")
    print(f"\nfast subscriber with / without the slow one: {fast_rate / fast_ref:.2f}x; camera: "
          f"{camera_rate / camera_ref:.2f}x")
    print(f"fast subscriber keeps {share:.0%} of the camera rate of the reference run (target >= 90 %): "
          f"{'ok' if share >= 0.9 else 'FAIL'}")
    growth = peak - baseline
    print(f"slow subscriber private memory: {baseline / 2**20:.0f} MB before frames, peak {peak / 2**20:.0f} MB, "
          f"growth {growth / 2**20:.0f} MB; bound depth x frame + 50 MB = {bound / 2**20:.0f} MB: "
          f"{'ok' if growth <= bound else 'FAIL'} (plus up to {shared / 2**20:.0f} MB of the camera's shared-memory "
          f"pool mapped)")
    print(f"slow subscriber totals: received {final.received}, processed {final.processed}, overflow "
          f"{getattr(final, 'overflow', 0)}, queued {sum(i.queued for i in final.inputs.values())}")
    return 0 if share >= 0.9 and growth <= bound else 1


if __name__ == "__main__":
    sys.exit(main())
