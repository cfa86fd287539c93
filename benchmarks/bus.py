"""Bus benchmark: semloc's typed frames + worker runtime vs raw zenoh put/subscribe of the same bytes, same run.

    .venv/bin/python benchmarks/bus.py [--repeats 3] [--pings 1000] [--frames 1000]

Two processes on loopback (this one and an echo worker started here):

* one-hop latency = half the round trip of a ping echoed back, p50 / p99, for a ~1 KB and a 640x480x3 Image.
  semloc path: services.bus.FramePublisher (encode, shared memory for large frames) -> the worker runtime (decode
  in zenoh's thread, bounded queue, handler on the main thread) -> the handler publishes through its runtime
  Output -> decode here.
* sustained one-way throughput of 640x480x3 frames: frames sent back to back (congestion control BLOCK), counted at
  the receiver (semloc: runtime input with a lossless queue and a handler), with the CPU time per frame of the
  receiving and the sending process (zenoh's threads included): on a shared machine the CPU figures are steadier
  than the rates.

Raw zenoh references carry the same bytes with plain callbacks, in the same run:

* ``zenoh`` (the reference of the ratios): ``put`` of the bytes; each receiver reads the payload into Python
  (``services.bus.payload_bytes``: one copy, as the runtime does; Python code cannot look at a payload in place)
  and the echo puts those bytes back;
* ``zenoh-untouched``: the payload is never read; the echo forwards zenoh's own buffer (with shared memory, a
  pointer). Shown for context: no worker can do anything useful with a frame it does not read.
* ``zenoh-shm`` (throughput only): the bytes put from a zenoh shared-memory buffer (what semloc's publisher does
  after encoding), read with ``payload_bytes``: the best raw zenoh can do from Python, for context.

Prints the median over ``--repeats`` runs of each figure, the ratio semloc / zenoh, and for throughput also the
median of the per-run ratios (the paths of one run are measured back to back, under the same background load).

``--secure``: the cost of mutual TLS (docs/security.md). This process is a router listening on plain TCP and on
mutual TLS (certificates made for the run by services/certs.py); two echo workers are its clients, one over each
link, shared memory off (the bytes cross the link, as between machines). Same latencies and throughput as above,
for the raw zenoh and the semloc paths, over TCP and over TLS in the same run, with the ratio TLS / TCP.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from schemas import Header, Image, decode, encode  # noqa: E402
from services.bus import BusConfig, FramePublisher, free_port, open_session, payload_bytes  # noqa: E402
from services.runtime import Worker, WorkerConfig  # noqa: E402

PATHS = ("zenoh-untouched", "zenoh", "semloc")  # latency
# Every session here: zenoh's own pool for messages of 3 KB or more on (semloc turns it off), so the raw zenoh
# references put the frame from zenoh's pool as zenoh's defaults do; the semloc path's frames come from its own
# pool (services.bus.SharedMemoryPool), not from zenoh's. --pool-frames sets that pool (BusConfig.shm_pool_frames).
BUS_SETTINGS = {"shm_small_frames": True}
FLOOD_PATHS = ("zenoh-untouched", "zenoh", "zenoh-shm", "semloc")  # throughput


class EchoConfig(WorkerConfig):
    prefix: str = "bench"  # of every key: one echo worker per link under --secure


def control_keys(prefix: str) -> tuple[str, str]:
    return f"{prefix}/control", f"{prefix}/done"


class BenchEcho(Worker):
    """Echoes pings and counts floods, on both the semloc runtime path and a raw zenoh path."""

    Config = EchoConfig

    def setup(self) -> None:
        self.expected = 0
        self.counts = dict.fromkeys(FLOOD_PATHS, 0)
        self.first = dict.fromkeys(FLOOD_PATHS, 0)
        self.first_cpu = dict.fromkeys(FLOOD_PATHS, 0.0)
        self.last = dict.fromkeys(FLOOD_PATHS, 0)
        self.last_cpu = dict.fromkeys(FLOOD_PATHS, 0.0)
        self.flood_start = (0, 0)
        p = self.config.prefix
        self.pong = self.output("pong", f"{p}/semloc/pong")
        self.input("ping", f"{p}/semloc/ping", Image, lambda frame: self.pong.publish(frame), policy="lossless",
                   depth=16)
        self.flood = self.input("flood", f"{p}/semloc/flood", Image, lambda _frame: self._count("semloc"),
                                policy="lossless", depth=16)
        self.every(0.05, self._semloc_flood_done)
        session = self.session
        # BLOCK as the semloc path's output does: zenoh's default (DROP) may lose a pong on a loaded machine.
        block = zenoh.CongestionControl.BLOCK
        raw_pong = session.declare_publisher(f"{p}/zenoh/pong", congestion_control=block)
        untouched_pong = session.declare_publisher(f"{p}/zenoh-untouched/pong", congestion_control=block)
        control, self.done_key = control_keys(p)
        self.raw = [
            session.declare_subscriber(f"{p}/zenoh/ping", lambda sample: raw_pong.put(payload_bytes(sample.payload))),
            session.declare_subscriber(f"{p}/zenoh-untouched/ping", lambda sample: untouched_pong.put(sample.payload)),
            session.declare_subscriber(f"{p}/zenoh/flood", lambda sample: self._count("zenoh", sample.payload)),
            session.declare_subscriber(f"{p}/zenoh-shm/flood",
                                       lambda sample: self._count("zenoh-shm", sample.payload)),
            session.declare_subscriber(f"{p}/zenoh-untouched/flood", lambda _s: self._count("zenoh-untouched")),
            session.declare_subscriber(control, self._on_control),
        ]

    def _on_control(self, sample) -> None:
        self.expected = int(sample.payload.to_string())
        self.counts = dict.fromkeys(FLOOD_PATHS, 0)
        self.flood_start = (self.flood.received, self.flood.overflow)

    def _semloc_flood_done(self) -> None:
        """The semloc path's report: a lossless queue refuses frames a flood brings faster than the worker handles
        them (its overflow), so the flood is done when every frame arrived and the queue is empty; the rate is of
        the frames handled, from the first to the last."""
        received, overflow = (now - start for now, start in zip((self.flood.received, self.flood.overflow),
                                                                 self.flood_start))
        if not self.expected or received < self.expected or self.flood.queue or self.flood.held:
            return
        handled = self.counts["semloc"]
        self.session.put(self.done_key, json.dumps({"path": "semloc", "count": handled, "overflow": overflow,
                                                    "seconds": (self.last["semloc"] - self.first["semloc"]) * 1e-9,
                                                    "cpu_seconds": self.last_cpu["semloc"] - self.first_cpu["semloc"]}))
        self.expected = 0

    def _count(self, path: str, payload=None) -> None:
        if payload is not None:
            payload_bytes(payload)
        now = time.perf_counter_ns()
        self.counts[path] += 1
        if self.counts[path] == 1:
            self.first[path] = now
            self.first_cpu[path] = time.process_time()
        self.last[path], self.last_cpu[path] = now, time.process_time()
        if self.counts[path] == self.expected and path != "semloc":
            self.session.put(self.done_key, json.dumps({"path": path, "count": self.expected,
                                               "seconds": (now - self.first[path]) * 1e-9,
                                               "cpu_seconds": time.process_time() - self.first_cpu[path]}))


def image_frame(shape) -> Image:
    pixels = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    return Image.from_pixels(Header(robot="bench", stream="bench", stamp_ns=1), pixels)


def ping_pong(session, path: str, payload: bytes, count: int, prefix: str = "bench",
              shared_memory: bool | None = None) -> np.ndarray:
    """One-hop latencies (half round trips) in microseconds."""
    arrived = threading.Event()
    if path == "zenoh-untouched":
        subscriber = session.declare_subscriber(f"{prefix}/{path}/pong", lambda _sample: arrived.set())
    elif path == "zenoh":
        def on_raw_pong(sample):
            payload_bytes(sample.payload)
            arrived.set()
        subscriber = session.declare_subscriber(f"{prefix}/{path}/pong", on_raw_pong)
    else:
        def on_pong(sample):
            decode(payload_bytes(sample.payload), expected=Image)
            arrived.set()
        subscriber = session.declare_subscriber(f"{prefix}/semloc/pong", on_pong)
    send, publisher = sender(session, f"{prefix}/{path}/ping", path, payload, shared_memory)
    samples = []
    for index in range(count + 20):
        arrived.clear()
        start = time.perf_counter_ns()
        send()
        if not arrived.wait(5.0):
            raise RuntimeError(f"{path} pong lost")
        if index >= 20:  # warm-up
            samples.append((time.perf_counter_ns() - start) / 2e3)
    subscriber.undeclare()
    publisher.undeclare()
    return np.asarray(samples)


def sender(session, key: str, path: str, payload: bytes, shared_memory: bool | None = None):
    """(send(), publisher) for one path: raw put of the bytes, raw put from shared memory, or the semloc
    publisher encoding the frame (as every worker's runtime Output does). ``shared_memory``: as zenoh's default
    when None."""
    if path in ("zenoh", "zenoh-untouched"):
        publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        return (lambda: publisher.put(payload)), publisher
    frames = FramePublisher(session, key, bus=BusConfig(shared_memory=shared_memory, **BUS_SETTINGS))
    if path == "zenoh-shm":
        return (lambda: frames.put_bytes(payload)), frames
    frame = decode(payload)
    return (lambda: frames.put_frame(frame)), frames


def flood(session, path: str, payload: bytes, count: int, prefix: str = "bench",
          shared_memory: bool | None = None) -> tuple[float, float, float, int]:
    """(frames per second received by the echo process, receiver CPU µs per frame, sender CPU µs per frame, frames
    refused by the receiver's full queue (semloc path)).

    CPU times are of the whole process (zenoh's threads included), from the first frame to the last."""
    done = threading.Event()
    result = {}

    def on_done(sample):
        message = json.loads(sample.payload.to_string())
        if message["path"] == path:
            result.update(message)
            done.set()

    control, done_key = control_keys(prefix)
    subscriber = session.declare_subscriber(done_key, on_done)
    session.put(control, str(count))
    time.sleep(0.2)
    send, publisher = sender(session, f"{prefix}/{path}/flood", path, payload, shared_memory)
    start_cpu = time.process_time()
    for _ in range(count):
        send()
    sender_cpu = time.process_time() - start_cpu
    if not done.wait(60):
        raise RuntimeError(f"{path} flood did not complete")
    subscriber.undeclare()
    publisher.undeclare()
    per_frame = 1e6 / (result["count"] - 1)
    return ((result["count"] - 1) / result["seconds"], result["cpu_seconds"] * per_frame, sender_cpu * per_frame,
            result.get("overflow", 0))


def run_echo(hub: str, prefix: str = "bench", tls: str | None = None) -> int:
    if prefix == "bench":
        bus = BusConfig(connect=[hub], **BUS_SETTINGS)
    else:  # --secure: a client of this process's router, the bytes over the link
        bus = BusConfig(mode="client", connect=[hub], tls=tls, shared_memory=False)
    config = EchoConfig(robot="bench", name=f"echo-{prefix}", prefix=prefix, bus=bus, status_period_s=5.0)
    return BenchEcho(config).main()


def start_echo(session, hub: str, prefix: str = "bench", tls: str | None = None) -> subprocess.Popen:
    """An echo worker in its own process, once it is alive."""
    command = [sys.executable, __file__, "--role", "echo", "--hub", hub, "--prefix", prefix,
               "--pool-frames", str(BUS_SETTINGS.get("shm_pool_frames", BusConfig().shm_pool_frames))]
    echo = subprocess.Popen(command + (["--tls", tls] if tls else []), stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.monotonic() + 30
    while not list(session.liveliness().get(f"semloc/bench/echo-{prefix}/alive", timeout=0.5)):
        if echo.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"echo worker {prefix} did not start")
    time.sleep(0.5)
    return echo


def stop_echo(echo: subprocess.Popen) -> None:
    echo.send_signal(signal.SIGINT)
    echo.wait(20)


def run_secure(args, small: bytes, big: bytes) -> int:
    """--secure: the same paths over plain TCP and over mutual TLS, one hop, shared memory off, same run."""
    from services.certs import write_layout

    links = ("tcp", "tls")
    paths = ("zenoh", "semloc")
    with tempfile.TemporaryDirectory() as pki:
        write_layout(pki, "bench")
        router_config = Path(pki) / "router.json"
        router_config.write_text(json.dumps({"transport": {"link": {"tls": {
            "root_ca_certificate": f"{pki}/ca.pem", "listen_certificate": f"{pki}/base-router.pem",
            "listen_private_key": f"{pki}/base-router-key.pem", "enable_mtls": True}}}}))
        endpoints = {"tcp": f"tcp/127.0.0.1:{free_port()}", "tls": f"tls/localhost:{free_port()}"}
        listen = [endpoints["tcp"], endpoints["tls"].replace("localhost", "127.0.0.1")]
        bus = BusConfig(mode="router", listen=listen, zenoh_config=str(router_config), shared_memory=False)
        latency: dict[tuple, list] = {}
        throughput: dict[tuple, list] = {}
        refused: dict[str, list[int]] = {}
        with open_session(bus) as session:
            echoes = [start_echo(session, endpoints["tcp"], "tcp"),
                      start_echo(session, endpoints["tls"], "tls", tls=f"{pki}/bench-workers")]
            try:
                for _ in range(args.repeats):
                    for label, payload, count in (("1 KB", small, args.pings), ("640x480x3", big, args.big_pings)):
                        for path in paths:
                            for link in links:
                                samples = ping_pong(session, path, payload, count, prefix=link, shared_memory=False)
                                latency.setdefault((label, path, link), []).append(
                                    (np.percentile(samples, 50), np.percentile(samples, 99)))
                    for path in paths:
                        for link in links:
                            fps, _, _, overflow = flood(session, path, big, args.frames, prefix=link,
                                                        shared_memory=False)
                            throughput.setdefault((path, link), []).append(fps)
                            if path == "semloc":
                                refused.setdefault(link, []).append(overflow)
            finally:
                for echo in echoes:
                    stop_echo(echo)
    print(f"\nmutual TLS against plain TCP, one hop through this process's router, shared memory off; median of "
          f"{args.repeats} runs; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    print(f"{'one-hop latency':18s} {'path':8s} {'link':5s} {'p50 ms':>8s} {'p99 ms':>8s} {'TLS / TCP (p50)':>16s}")
    for label in ("1 KB", "640x480x3"):
        for path in paths:
            tcp = np.median(np.asarray(latency[(label, path, "tcp")]), axis=0)
            for link in links:
                p50, p99 = np.median(np.asarray(latency[(label, path, link)]), axis=0)
                ratio = f"{p50 / tcp[0]:15.2f}x" if link == "tls" else ""
                print(f"{label:18s} {path:8s} {link:5s} {p50 / 1e3:8.3f} {p99 / 1e3:8.3f} {ratio:>16s}")
    print(f"\n{'throughput 640x480x3':22s} {'link':5s} {'frames/s':>9s} {'TCP / TLS':>10s}   runs")
    for path in paths:
        tcp = statistics.median(throughput[(path, "tcp")])
        for link in links:
            fps = statistics.median(throughput[(path, link)])
            ratio = f"{tcp / fps:9.2f}x" if link == "tls" else ""
            print(f"{path:22s} {link:5s} {fps:9.0f} {ratio:>10s}   {[round(x) for x in throughput[(path, link)]]}")
    for path in paths:
        paired = [tcp / tls for tcp, tls in zip(throughput[(path, "tcp")], throughput[(path, "tls")])]
        print(f"{path} TCP / TLS, paired by run (same moment, same load): median {statistics.median(paired):.2f}x "
              f"{[round(r, 2) for r in paired]}")
    print(f"semloc frames refused by the receiver's full lossless queue (depth 16), of {args.frames} a run: {refused}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pings", type=int, default=1000, help="round trips per latency run (1 KB)")
    parser.add_argument("--big-pings", type=int, default=200, help="round trips per latency run (640x480x3)")
    parser.add_argument("--frames", type=int, default=2000, help="frames per throughput run")
    parser.add_argument("--secure", action="store_true", help="mutual TLS against plain TCP (one hop, same run)")
    parser.add_argument("--pool-frames", type=int, default=BusConfig().shm_pool_frames,
                        help="frames a process's shared-memory pool holds (BusConfig.shm_pool_frames)")
    parser.add_argument("--role", choices=["main", "echo"], default="main", help=argparse.SUPPRESS)
    parser.add_argument("--hub", help=argparse.SUPPRESS)
    parser.add_argument("--prefix", default="bench", help=argparse.SUPPRESS)
    parser.add_argument("--tls", help=argparse.SUPPRESS)
    args = parser.parse_args()
    BUS_SETTINGS["shm_pool_frames"] = args.pool_frames
    if args.role == "echo":
        return run_echo(args.hub, args.prefix, args.tls)

    small, big = encode(image_frame((16, 21, 3))), encode(image_frame((480, 640, 3)))
    print(f"payloads: small {len(small)} B, big {len(big)} B")
    if args.secure:
        return run_secure(args, small, big)
    hub = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(listen=[hub], **BUS_SETTINGS)) as session:
        echo = start_echo(session, hub)
        try:
            latency: dict[tuple[str, str], list] = {}
            refused: list[int] = []
            throughput: dict[str, list[float]] = {path: [] for path in FLOOD_PATHS}
            cpu: dict[str, list[tuple[float, float]]] = {path: [] for path in FLOOD_PATHS}
            for _ in range(args.repeats):
                for label, payload, count in (("1 KB", small, args.pings), ("640x480x3", big, args.big_pings)):
                    for path in PATHS:
                        samples = ping_pong(session, path, payload, count)
                        latency.setdefault((label, path), []).append(
                            (np.percentile(samples, 50), np.percentile(samples, 99)))
                for path in FLOOD_PATHS:
                    fps, receiver_us, sender_us, overflow = flood(session, path, big, args.frames)
                    if path == "semloc":
                        refused.append(overflow)
                    throughput[path].append(fps)
                    cpu[path].append((receiver_us, sender_us))
        finally:
            stop_echo(echo)

    print(f"\nmedian of {args.repeats} runs (machine shared with other work: expect +-30 %); load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    print(f"{'one-hop latency':18s} {'path':16s} {'p50 ms':>8s} {'p99 ms':>8s} {'p50 / zenoh':>12s}")
    for label in ("1 KB", "640x480x3"):
        reference = np.median(np.asarray(latency[(label, "zenoh")]), axis=0)[0]
        for path in PATHS:
            p50, p99 = np.median(np.asarray(latency[(label, path)]), axis=0)
            print(f"{label:18s} {path:16s} {p50 / 1e3:8.3f} {p99 / 1e3:8.3f} {p50 / reference:11.2f}x")
    print(f"\n{'throughput 640x480x3':22s} {'frames/s':>9s} {'/ zenoh':>8s} {'CPU µs/frame: receiver':>23s} "
          f"{'sender':>7s}   runs")
    reference = statistics.median(throughput["zenoh"])
    for path in FLOOD_PATHS:
        fps = statistics.median(throughput[path])
        receiver_us, sender_us = np.median(np.asarray(cpu[path]), axis=0)
        print(f"{path:22s} {fps:9.0f} {fps / reference:7.2f}x {receiver_us:23.0f} {sender_us:7.0f}   "
              f"{[round(x) for x in throughput[path]]}")
    paired = [s / z for s, z in zip(throughput["semloc"], throughput["zenoh"])]
    print(f"semloc / zenoh, paired by run (same moment, same load): median {statistics.median(paired):.2f}x "
          f"{[round(r, 2) for r in paired]}")
    print(f"semloc frames refused by the receiver's full lossless queue (depth 16), of {args.frames} a run: {refused}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
