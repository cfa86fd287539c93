"""``semloc status``: live workers (liveliness tokens) and their counters (Status frames)."""

from __future__ import annotations

import json
import sys
import time

from schemas import FrameError, Status, keys
from services.bus import add_bus_arguments, bus_from_args, open_session, query


def add_arguments(parser) -> None:
    parser.add_argument("--robot", default="*", help="only this robot (default: all)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--wait", type=float, default=3.0, help="seconds to wait for workers to answer")
    parser.add_argument("--watch", type=float, metavar="SECONDS", help="refresh every SECONDS until Ctrl-C")
    add_bus_arguments(parser)


def collect(session, robot: str = "*", wait: float = 3.0, settle: float = 0.75) -> dict[str, dict]:
    """``robot/worker`` -> {"alive": bool, "status": Status | None} for every worker seen.

    A new session meshes with the workers' peers over a few hundred milliseconds, so one round of queries may
    miss some: poll until ``settle`` seconds have passed and two rounds in a row agree, or ``wait`` runs out."""
    start = time.monotonic()
    seen: dict[str, dict] = {}
    previous = None
    while True:
        for reply in session.liveliness().get(f"{keys.PREFIX}/{robot}/*/alive", timeout=0.5):
            if reply.ok is not None:
                r, w = keys.worker_of(str(reply.ok.key_expr))
                seen.setdefault(f"{r}/{w}", {"alive": True, "status": None})["alive"] = True
        try:
            # A query ends as soon as every queryable it reached has answered, so the long timeout costs nothing
            # when all answer; a worker starved of CPU (a loaded 2-core CI machine) that takes longer than a short
            # round would otherwise be missed on every round until ``wait`` runs out.
            remaining = max(0.5, wait - (time.monotonic() - start))
            frames = query(session, f"{keys.PREFIX}/{robot}/*/status", reply_type=Status, timeout=remaining)
        except (FrameError, RuntimeError):
            frames = []
        for frame in frames:
            entry = seen.setdefault(f"{frame.header.robot}/{frame.worker}", {"alive": False, "status": None})
            entry["status"] = frame
        snapshot = {name: entry["status"] is not None for name, entry in seen.items()}
        elapsed = time.monotonic() - start
        settled = elapsed >= settle and snapshot == previous and all(snapshot.values())
        if settled or elapsed >= wait:
            return dict(sorted(seen.items()))
        previous = snapshot
        time.sleep(0.15)


def render(seen: dict[str, dict]) -> str:
    if not seen:
        return "no live workers"
    head = f"{'worker':28s} {'state':8s} {'pid':>7s} {'up s':>7s} {'recv':>7s} {'proc':>7s} {'drop':>6s} " \
           f"{'rej':>6s} {'err':>5s} {'p50 ms':>7s} {'p95 ms':>7s}"
    lines = [head]
    for name, entry in seen.items():
        s = entry["status"]
        if s is None:
            lines.append(f"{name:28s} {'alive':8s} (no status)")
            continue
        fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        lines.append(f"{name:28s} {s.state:8s} {s.pid:7d} {s.uptime_s:7.0f} {s.received:7d} {s.processed:7d} "
                     f"{s.dropped:6d} {s.rejected:6d} {s.errors:5d} {fmt(s.latency_p50_ms):>7s} "
                     f"{fmt(s.latency_p95_ms):>7s}")
        for input_name, stats in s.inputs.items():
            lines.append(f"  <- {input_name}: {stats.key} [{stats.policy}] recv {stats.received} proc "
                         f"{stats.processed} drop {stats.dropped} rej {stats.rejected} queued {stats.queued}")
        for output_name, stats in s.outputs.items():
            lines.append(f"  -> {output_name}: {stats.key} published {stats.published}")
        if s.last_error:
            lines.append(f"  last error: {s.last_error.splitlines()[0][:160]}")
    return "\n".join(lines)


def as_json(seen: dict[str, dict]) -> str:
    return json.dumps({name: {"alive": e["alive"],
                              "status": None if e["status"] is None else e["status"].model_dump(mode="json")}
                       for name, e in seen.items()}, indent=2)


def run(args) -> int:
    with open_session(bus_from_args(args)) as session:
        while True:
            seen = collect(session, args.robot, args.wait)
            print(as_json(seen) if args.json else render(seen), flush=True)
            if not args.watch:
                return 0 if seen else 1
            try:
                time.sleep(args.watch)
            except KeyboardInterrupt:
                return 0
            print(file=sys.stdout)
