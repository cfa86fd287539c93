"""Recoverable stream benchmark: odometry published through a recoverable output (a publisher cache, a subscriber
that asks for what it missed; docs/deploy.md "When the link drops") against the plain publisher and subscriber,
same run, same bytes:

    .venv/bin/python benchmarks/recoverable_stream.py [--repeats 5] [--pings 1000] [--messages 200000]

A router on loopback, the publisher and the subscriber each a client of it (two sessions in this process: the
bytes cross the router as between processes). Per path: the publisher's CPU per put (``put`` µs, its thread's
time), one-hop latency (half the round trip of a ping echoed back on a second stream of the same kind, p50 / p99)
and the sustained rate of encoded Odometry frames sent back to back and counted at the receiver. Prints medians over
``--repeats`` and the ratio recoverable / plain of each.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time

import zenoh

from schemas import Header, Odometry, encode, keys
from services.bus import (BusConfig, declare_recoverable_publisher, declare_recoverable_subscriber, free_port,
                          open_session)


def _publisher(session, key: str, recoverable: bool):
    if recoverable:
        return declare_recoverable_publisher(session, key, zenoh.CongestionControl.BLOCK,
                                             keys.RECOVERABLE_STREAMS[keys.odometry])
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)


def _subscriber(session, key: str, callback, recoverable: bool) -> list:
    if recoverable:
        return list(declare_recoverable_subscriber(session, key, callback, lambda count: None))
    return [session.declare_subscriber(key, callback)]


def run(a, b, recoverable: bool, pings: int, messages: int, tag: str) -> dict:
    payload = bytes(encode(Odometry(header=Header(robot="r1", stream="odom", seq=0, stamp_ns=1), v=0.5,
                                    v_lateral=0.0, omega=0.1, dt=0.1)))
    out, back = f"bench/{tag}/out", f"bench/{tag}/back"
    counted, pong = [0], threading.Event()
    done = threading.Event()

    def on_out(sample) -> None:
        counted[0] += 1
        if counted[0] == messages:
            done.set()

    echo = _publisher(b, back, recoverable)
    handles = _subscriber(b, out, lambda s: echo.put(s.payload.to_bytes()) if counted[0] < 0 else on_out(s),
                          recoverable)
    handles += _subscriber(a, back, lambda s: pong.set(), recoverable)
    publisher = _publisher(a, out, recoverable)
    time.sleep(0.5)  # routes settle
    counted[0] = -1  # ping phase: the receiver echoes
    rtts = []
    for _ in range(pings):
        pong.clear()
        started = time.perf_counter()
        publisher.put(payload)
        if not pong.wait(2.0):
            raise RuntimeError("a ping was lost")
        rtts.append(time.perf_counter() - started)
    counted[0] = 0  # throughput phase: the receiver counts
    started, cpu = time.perf_counter(), time.thread_time()
    for _ in range(messages):
        publisher.put(payload)
    put_us = 1e6 * (time.thread_time() - cpu) / messages
    if not done.wait(30.0):
        raise RuntimeError(f"{counted[0]} of {messages} arrived")
    rate = messages / (time.perf_counter() - started)
    for handle in (*handles, publisher, echo):
        handle.undeclare()
    rtts.sort()
    return {"put_us": put_us, "p50_ms": 1e3 * rtts[len(rtts) // 2] / 2, "p99_ms": 1e3 * rtts[int(len(rtts) * 0.99)] / 2,
            "rate": rate}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pings", type=int, default=1000, help="round trips per latency run")
    parser.add_argument("--messages", type=int, default=200000, help="frames per throughput run")
    args = parser.parse_args()
    port = free_port()
    results: dict[bool, list[dict]] = {False: [], True: []}
    with open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"])), \
            open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"])) as a, \
            open_session(BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"])) as b:
        for repeat in range(args.repeats):
            for recoverable in (False, True):  # back to back: the same background load
                results[recoverable].append(run(a, b, recoverable, args.pings, args.messages, f"{repeat}{recoverable}"))
    print(f"{'figure':10s} {'plain':>10s} {'recoverable':>12s} {'ratio':>6s}   (medians of {args.repeats})")
    for figure in ("put_us", "p50_ms", "p99_ms", "rate"):
        plain, recoverable = (statistics.median(r[figure] for r in results[kind]) for kind in (False, True))
        print(f"{figure:10s} {plain:10.3f} {recoverable:12.3f} {recoverable / plain:6.2f}")


if __name__ == "__main__":
    main()
