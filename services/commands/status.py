"""``semloc status``: every worker's health and counters, from its own Status and its launcher's view.

A worker answers for itself (Status on ``semloc/<robot>/<worker>/status``) while it can. One that cannot (killed,
stopped, hung) is known from its launcher's view (``LauncherStatus`` on ``keys.launcher_nodes``) and from its
liveliness token, and is shown down or stalled."""

from __future__ import annotations

import json
import sys
import time

from schemas import FrameError, Status, keys
from schemas.status import LauncherStatus
from services.bus import add_bus_arguments, bus_from_args, open_session, query
from services.commands import robot_or_every, robots_on_bus
from services.memory import mb

UNHEALTHY = ("down", "stalled")  # `semloc status` exits 1 when a worker is in one of these


def add_arguments(parser) -> None:
    parser.add_argument("--robot", default="*", type=robot_or_every, help="only this robot (default: all)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--wait", type=float, default=3.0, help="seconds to wait for workers to answer")
    parser.add_argument("--watch", type=float, metavar="SECONDS", help="refresh every SECONDS until Ctrl-C")
    add_bus_arguments(parser)


def _replies(session, key: str, reply_type, timeout: float) -> list:
    try:
        return query(session, key, reply_type=reply_type, timeout=timeout, every_reply=True)
    except (FrameError, RuntimeError):
        return []


def collect(session, robot: str = "*", wait: float = 3.0, settle: float = 0.75,
            launchers: dict[str, LauncherStatus] | None = None) -> dict[str, dict]:
    """``robot/worker`` -> {"alive": bool, "status": Status | None, "duplicates": [Status], "launcher": NodeHealth |
    None, "state": str, "reason": str} for every worker seen ("duplicates": other processes answering as it, later
    started) (by its token, its Status or a launcher); each launcher's view also into
    ``launchers`` (its id -> LauncherStatus) if given.

    A new session meshes with the workers' peers over a few hundred milliseconds, so one round of queries may
    miss some: poll until ``settle`` seconds have passed, two rounds in a row agree and every live worker has
    answered, or ``wait`` runs out."""
    start = time.monotonic()
    seen: dict[str, dict] = {}
    robots = set() if robot == "*" else {robot}
    previous = None
    while True:
        for reply in session.liveliness().get(keys.for_robots(keys.robot_alive, robot), timeout=0.5):
            if reply.ok is not None:
                r, w = keys.worker_of(str(reply.ok.key_expr))
                _entry(seen, f"{r}/{w}")["alive"] = True
        if robot == "*":
            robots |= robots_on_bus(session)
        # Each robot asked on its own keys (a router's access rules let a query through only within one robot's,
        # deploy/secure/). A query ends as soon as every queryable it reached has answered, so the long timeout costs
        # nothing when all answer; a worker starved of CPU (a loaded 2-core CI machine) that takes longer than a
        # short round would otherwise be missed on every round until ``wait`` runs out.
        for name in sorted(robots):
            remaining = max(0.5, wait - (time.monotonic() - start))
            # Two processes can answer as one worker (started twice with one name, an old one left running): each
            # is kept (by host, pid and start), this round's replacing the last's (a restarted worker's old self).
            this_round: dict[str, dict] = {}
            for frame in _replies(session, keys.robot_statuses(name), Status, remaining):
                process = (frame.started_ns, frame.host, frame.pid)
                this_round.setdefault(f"{frame.header.robot}/{frame.worker}", {})[process] = frame
            for worker, by_process in this_round.items():
                statuses = [by_process[process] for process in sorted(by_process)]
                _entry(seen, worker).update(status=statuses[0], duplicates=statuses[1:])
            for view in _replies(session, keys.all_launcher_nodes(name), LauncherStatus, 0.5):
                if launchers is not None:
                    launchers[view.launcher] = view
                for node in view.nodes.values():
                    _entry(seen, f"{node.robot}/{node.worker}")["launcher"] = node
        snapshot = {name: (e["alive"], e["status"] is not None, len(e["duplicates"]), e["launcher"] is not None)
                    for name, e in seen.items()}
        elapsed = time.monotonic() - start
        answered = all(e["status"] is not None for e in seen.values() if e["alive"])
        if (elapsed >= settle and snapshot == previous and answered) or elapsed >= wait:
            for entry in seen.values():
                entry["state"], entry["reason"] = judge(entry, wait)
            return dict(sorted(seen.items()))
        previous = snapshot
        time.sleep(0.15)


def _entry(seen: dict, name: str) -> dict:
    return seen.setdefault(name, {"alive": False, "status": None, "duplicates": [], "launcher": None, "state": "",
                                  "reason": ""})


def judge(entry: dict, wait: float) -> tuple[str, str]:
    """(state, reason) of one worker: its own Status if it answered, else its launcher's view, else its token."""
    status, node = entry["status"], entry["launcher"]
    if status is not None:
        return status.state, status.state_reason
    if node is not None and node.state != "running":
        return node.state, node.state_reason
    if entry["alive"] or node is not None:
        # Connected to the bus (or heard by its launcher), yet no answer to this query in `wait` seconds.
        return "stalled", f"no Status reply in {wait:.0f} s"
    return "down", ""


def render(seen: dict[str, dict]) -> str:
    if not seen:
        return "no live workers"
    head = f"{'worker':28s} {'state':9s} {'pid':>7s} {'up s':>7s} {'rst':>4s} {'recv':>7s} {'proc':>7s} " \
           f"{'drop':>6s} {'ovfl':>6s} {'rej':>6s} {'err':>5s} {'p50 ms':>7s} {'p95 ms':>7s} {'rss MB':>7s}"
    lines = [head]
    for name, entry in seen.items():
        s, node = entry["status"], entry["launcher"]
        if s is None:
            pid = "-" if node is None or node.pid is None else str(node.pid)
            restarts = "-" if node is None else str(node.restarts)
            lines.append(f"{name:28s} {_shown(entry['state']):9s} {pid:>7s} {'-':>7s} {restarts:>4s}")
            if entry["reason"]:
                lines.append(f"  ! {entry['reason']}")
            if node is not None and node.restarts:
                lines.append(f"  last restart: {node.restart_reason}")
            continue
        lines += _status_lines(name, entry["state"], entry["reason"], s, node)
        for other in entry["duplicates"]:  # each process answering as this worker, with its own figures
            lines += _status_lines(name, other.state, other.state_reason, other, None)
        if entry["duplicates"]:
            lines.append(f"  ! {duplicated(name, entry)}")
    return "\n".join(lines)


def _shown(state: str) -> str:
    return state if state in ("running", "starting", "stopping", "stopped") else state.upper()


def duplicated(name: str, entry: dict) -> str:
    """The line naming the processes that answer as one worker ("" if one does): where each runs and since when, to
    find the one that should not."""
    statuses = [entry["status"], *entry["duplicates"]] if entry["status"] is not None else []
    if len(statuses) < 2:
        return ""
    started = lambda s: time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(s.started_ns // 10**9))  # noqa: E731
    return f"{len(statuses)} workers answer as {name}: " + ", ".join(
        f"pid {s.pid} on {s.host or '?'} (started {started(s)})" for s in statuses)


def _status_lines(name: str, state: str, reason: str, s: Status, node) -> list[str]:
    """One process's row and what it says of itself (``node``: its launcher's view, None if none)."""
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    rss = "-" if s.memory is None or s.memory.rss_bytes is None else f"{s.memory.rss_bytes / 2**20:.0f}"
    lines = [f"{name:28s} {_shown(state):9s} {s.pid:7d} {s.uptime_s:7.0f} {s.restarts:4d} {s.received:7d} "
             f"{s.processed:7d} {s.dropped:6d} {s.overflow:6d} {s.rejected:6d} {s.errors:5d} "
             f"{fmt(s.latency_p50_ms):>7s} {fmt(s.latency_p95_ms):>7s} {rss:>7s}"]
    if reason:
        lines.append(f"  ! {reason}")
    if s.restarts:
        lines.append(f"  last restart: {s.restart_reason}")
    if node is not None and node.oom_kills:
        lines.append(f"  killed by the kernel for want of memory: {node.oom_kills}x")
    m = s.memory
    if m is not None and m.limit_bytes and m.used_bytes is not None:
        peak = "" if m.peak_bytes is None else f" (peak {mb(m.peak_bytes)})"
        lines.append(f"  memory: rss {mb(m.rss_bytes or 0)}{peak}; {mb(m.used_bytes)} of {mb(m.limit_bytes)} "
                     f"used ({100 * m.used_bytes / m.limit_bytes:.0f} %; {m.limit_source})")
    for input_name, stats in s.inputs.items():
        rate = "" if stats.rate_hz is None else f" | {stats.rate_hz:.1f} Hz"
        handler = "" if stats.handler_ms is None else f", handler {stats.handler_ms:.1f} ms"
        gap = f" recovered {stats.recovered} missed {stats.missed}" if stats.recovered or stats.missed else ""
        gap += f" already held {stats.already_held}" if stats.already_held else ""
        gap += f" lost on the way {stats.lost_in_transit}" if stats.lost_in_transit else ""
        lines.append(f"  <- {input_name}: {stats.key} [{stats.policy}] recv {stats.received} proc "
                     f"{stats.processed} drop {stats.dropped} overflow {stats.overflow} rej {stats.rejected} "
                     f"queued {stats.queued}{gap}{rate}{handler}")
    if s.busy_fraction is not None:
        lines.append(f"  busy {100 * s.busy_fraction:.0f} % of the last 10 s")
    for output_name, stats in s.outputs.items():
        lines.append(f"  -> {output_name}: {stats.key} published {stats.published}")
    if s.persistence is not None and s.persistence.restored:
        # Not a fresh start: a graph started again from the same state_dir goes on with the last run's state
        # (a snapshot set aside as unreadable shows in last_error).
        lines.append(f"  state: restored from its snapshot, {s.persistence.replayed} journal record(s) replayed")
    if s.details.get("shm_fallbacks"):  # a working fallback, not a degraded worker: said here
        lines.append(f"  shared memory: {s.details.get('shared_memory')}; {s.details['shm_fallbacks']} large "
                     f"frame(s) sent as bytes")
    if s.bus_lost:
        lines.append(f"  bus lost {s.bus_lost}x, regained {s.bus_regained}x; {s.bus_transports} transports open")
    if s.last_error:
        lines.append(f"  last error: {s.last_error[:160]}")
    return lines


def link_down(view: LauncherStatus) -> bool:
    """Whether a launcher's router has no link to the other machine's router it has or had one with."""
    return view.router_link_down_s is not None


def render_links(launchers: dict[str, LauncherStatus]) -> str:
    """One line per launcher whose hub is a router: its links to other routers (the link between machines)."""
    lines = []
    for view in sorted(launchers.values(), key=lambda v: v.launcher):
        if view.router_links is None:
            continue
        counts = f"lost {view.router_links_lost}x, regained {view.router_links_regained}x"
        if link_down(view):
            lines.append(f"launcher {view.graph} on {view.host}: ROUTER LINK DOWN for {view.router_link_down_s:.0f} "
                         f"s ({counts}): the other machine's workers are out of reach")
        elif view.router_links or view.router_links_lost:
            lines.append(f"launcher {view.graph} on {view.host}: {view.router_links} router link(s) ({counts})")
    return "\n".join(lines)


def as_json(seen: dict[str, dict], launchers: dict[str, LauncherStatus]) -> str:
    """``workers``: robot/worker -> its state, reason, Status and launcher's node view, and the Status of each other
    process answering as it (``duplicates``) with the line naming them (``duplicate``); ``launchers``: launcher id ->
    its graph, host, pid and router links (``link_down``: what the text shows as ROUTER LINK DOWN)."""
    dump = lambda frame: None if frame is None else frame.model_dump(mode="json")  # noqa: E731
    return json.dumps({
        "workers": {name: {"alive": e["alive"], "state": e["state"], "reason": e["reason"],
                           "status": dump(e["status"]), "launcher": dump(e["launcher"]),
                           "duplicates": [dump(s) for s in e["duplicates"]], "duplicate": duplicated(name, e)}
                    for name, e in seen.items()},
        "launchers": {name: {**view.model_dump(mode="json", exclude={"header", "nodes"}), "link_down": link_down(view)}
                      for name, view in sorted(launchers.items())}}, indent=2)


def run(args) -> int:
    with open_session(bus_from_args(args)) as session:
        while True:
            launchers: dict[str, LauncherStatus] = {}
            seen = collect(session, args.robot, args.wait, launchers=launchers)
            links = render_links(launchers)
            print(as_json(seen, launchers) if args.json else "\n".join(filter(None, [render(seen), links])), flush=True)
            if not args.watch:
                healthy = seen and not any(e["state"] in UNHEALTHY for e in seen.values())
                return 0 if healthy and not any(link_down(v) for v in launchers.values()) else 1
            try:
                time.sleep(args.watch)
            except KeyboardInterrupt:
                return 0
            print(file=sys.stdout)
