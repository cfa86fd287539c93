"""The launcher: a dataflow graph file -> one OS process per node, restarted on crash, stopped cleanly.

Graph file (YAML; deploy/README.md documents every field)::

    name: local
    robot: r1
    hub: tcp/127.0.0.1:7447          # the launcher listens here, nodes connect to it (null: no hub, use `bus`)
    rerun: {mode: off}               # given to every node, with one recording id per run
    state_dir: runs/state            # crash-safe snapshots of stateful nodes
    restart: {policy: on-failure, backoff_s: 0.1, max_backoff_s: 10}
    heartbeat: {stalled_after_s: 3, restart_after_s: 10}   # hung nodes: shown stalled, then restarted
    nodes:
      camera:
        worker: camera               # services/workers/camera.py (default: the node name)
        config: {source: images/, rate: 10}
        outputs: {image: {key: semloc/r1/camera/front/image}}      # keys written (overrides)
      detector:
        worker: detector
        optional: true               # skipped with a warning while the worker does not exist
        inputs: {image: {key: semloc/r1/camera/front/image, policy: latest, depth: 2}}   # keys read, queues

Python API (the demo uses it)::

    with Launcher(load_graph("deploy/local.yaml"), run_dir="runs/x") as launcher:
        launcher.wait(timeout=60)        # until every node has finished, or the timeout

Every node runs in its own session (process group): the launcher stops each group with SIGTERM, then SIGKILL after
``stop_timeout_s``; children also get SIGTERM if the launcher dies (Linux ``PR_SET_PDEATHSIG``).

Supervision: a node's heartbeat is its periodic ``Status``. A node that stops sending it (SIGSTOPped, hung below
Python, deadlocked) or reports itself stalled is shown ``stalled`` and, after ``heartbeat.restart_after_s`` (of the
time it could run: a node the machine starves of CPU is slow, not hung), killed and restarted; the restart count and
the reason reach the new process (``services.runtime.RESTARTS_ENV``). The launcher publishes its view of its nodes
(``LauncherStatus`` on ``keys.launcher_nodes``): ``semloc status`` shows from it the nodes that cannot answer for
themselves.
"""

from __future__ import annotations

import ctypes
import importlib.resources
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Literal

import yaml
import zenoh
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from schemas import FrameError, Header, Status, decode, encode, keys
from schemas.status import Ack, LauncherStatus, LogChunk, LogRequest, LogTail, NodeHealth
from services import memory
from services.bus import DEFAULT_HUB, BusConfig, open_session, payload_bytes
from services.config import CONFIG_ERROR_EXIT, ConfigError, deep_merge
from services.node_logs import LogPolicy, NodeLog, pump
from services.runtime import (RESTART_REASON_ENV, RESTARTS_ENV, START_AFTER_ENV, BusWatch, InputOverride,
                              OutputOverride, WorkerConfig, one_line)
from services.security import listed_endpoints
from services.viz import RerunConfig, grpc_url, layout, serve
from services.workers import check_node_config
from services.workers import exists as worker_exists

log = logging.getLogger("semloc.launcher")

# The folder holding the code (services/, schemas/, semloc_core/): nodes import it from there.
CODE_ROOT = Path(__file__).resolve().parents[1]
LAUNCHER_STATUS_PERIOD_S = 1.0
LOG_ANSWER_BYTES = 4 << 20  # at most this much log per answer, shared by the nodes (`semloc logs -f` asks again)
# A node whose heartbeat is late has its threads' CPU wait read this often (Starvation): often enough that a wait
# still in progress is seen within this, seldom enough to cost nothing.
STARVATION_SAMPLE_S = 0.25
# Added to each node's OOM score adjustment (the launcher's own + this, at most 1000): when their memory cgroup (a
# container) or the machine runs out, the kernel's OOM killer takes a node, which is restarted, not the launcher, whose
# death stops the whole graph. Sizes alone do not decide it: an idle node is about the launcher's size (~80 MB), and
# right after an OOM kill the kernel may kill a second process before the first one's memory is freed (seen: the
# launcher, 8 ms after its grower node, in a 400 MiB group). The kernel adds adj/1000 of the group's limit to a
# process's size: 500 outweighs the launcher's 80 MB in any group from 160 MB.
NODE_OOM_SCORE_ADJ = 500
OPERATOR_RESTART = "operator"  # the restart reason of a node restarted by `semloc restart` (Launcher.restart)
OPERATOR_STOP = "stopped by the operator to restart"  # its process's exit, then
OPERATOR_KILL = "killed by the operator's restart: still running stop_timeout_s after SIGTERM"


class RestartPolicy(BaseModel):
    model_config = ConfigDict(extra="forbid")

    policy: Literal["always", "on-failure", "never"] = "on-failure"
    # Small first: a crashed stateful worker's state is back as soon as its process is (issue 28: < 2 s); a crash
    # loop still backs off (0.1, 0.2, 0.4 ... max_backoff_s while runs stay shorter than reset_after_s).
    backoff_s: float = Field(0.1, ge=0, description="delay before the first restart; doubles per quick failure")
    max_backoff_s: float = Field(10.0, ge=0)
    reset_after_s: float = Field(10.0, ge=0, description="a run this long resets the backoff")
    max_restarts: int | None = Field(None, ge=0, description="give up after this many restarts (None: never); "
                                                             "`semloc restart` counts them afresh")


class HeartbeatPolicy(BaseModel):
    """How the launcher judges a running node by its heartbeat (the periodic ``Status`` of the worker)."""

    model_config = ConfigDict(extra="forbid")

    stalled_after_s: float = Field(3.0, gt=0, description="no Status for this long: the node is shown stalled "
                                                          "(must exceed the node's status_period_s)")
    restart_after_s: float | None = Field(10.0, gt=0, description="silent this long, less the time it waited for a "
                                                                  "CPU meanwhile, or reporting itself stalled this "
                                                                  "long: killed and restarted (None: never)")
    start_timeout_s: float = Field(60.0, gt=0, description="no running Status this long after the start, less the "
                                                          "time it waited for a CPU: stalled")


class NodeSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    worker: str | None = Field(None, description="worker kind (module under services/workers); default: node name")
    config: dict[str, Any] = Field(default_factory=dict, description="the worker's config fields")
    inputs: dict[str, InputOverride] = Field(default_factory=dict, description="keys read: key/policy/depth")
    outputs: dict[str, OutputOverride] = Field(default_factory=dict, description="keys written")
    restart: RestartPolicy | None = None
    heartbeat: HeartbeatPolicy | None = None
    optional: bool = Field(False, description="skip (with a warning) when the worker does not exist")
    enabled: bool = True
    env: dict[str, str] = Field(default_factory=dict)
    start_after: list[str] = Field(default_factory=list, description="nodes of this graph whose Status must say "
                                   "running before this node's first start (restarts do not wait)")
    start_after_timeout_s: float | None = Field(
        120.0, gt=0, description="start anyway, with a warning, when they do not all run this long after the launch "
                                 "(None: wait as long as it takes)")


class Graph(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = "graph"
    robot: str = keys.DEFAULT_ROBOT
    hub: str | None = DEFAULT_HUB
    hub_mode: Literal["peer", "router"] = Field("peer", description="router: the launcher routes for client nodes")
    hub_zenoh_config: str | None = Field(None, description="zenoh config file of the hub session (TLS, ACL...)")
    secure_hub_zenoh_config: str | None = Field(
        None, description="the hub's config under `semloc up --secure DIR` (deploy/secure/: mutual TLS, access control)")
    bus: BusConfig | None = Field(None, description="nodes' bus config (default: connect to the hub)")
    rerun: RerunConfig = Field(default_factory=RerunConfig)
    state_dir: str | None = None
    restart: RestartPolicy = Field(default_factory=RestartPolicy)
    heartbeat: HeartbeatPolicy = Field(default_factory=HeartbeatPolicy)
    logs: LogPolicy = Field(default_factory=LogPolicy)
    stop_timeout_s: float = Field(5.0, gt=0)
    env: dict[str, str] = Field(default_factory=dict)
    nodes: dict[str, NodeSpec]

    @model_validator(mode="after")
    def _check_start_after(self):
        for name, spec in self.nodes.items():
            unknown = [other for other in spec.start_after if other not in self.nodes]
            if unknown:
                raise ValueError(f"node {name}: start_after names {', '.join(unknown)}, not a node of this graph "
                                 f"(nodes: {', '.join(self.nodes)})")
        cycle = start_after_cycle({name: spec.start_after for name, spec in self.nodes.items()})
        if cycle:
            raise ValueError(f"start_after makes a cycle: {' -> '.join(cycle)} (no node of it could ever start)")
        return self


def start_after_cycle(after: dict[str, list[str]]) -> list[str]:
    """A cycle of the start_after relation (node -> the nodes it waits for), as the path round it, or []."""
    done: set[str] = set()
    path: list[str] = []

    def visit(name: str) -> list[str]:
        if name in path:
            return path[path.index(name):] + [name]
        if name in done:
            return []
        path.append(name)
        for other in after.get(name, ()):
            found = visit(other)
            if found:
                return found
        path.pop()
        done.add(name)
        return []

    for name in after:
        found = visit(name)
        if found:
            return found
    return []


def builtin_graphs_dir() -> Path:
    """deploy/: the built-in graphs and the files they read (the installed package ``semloc_deploy``; in a checkout
    that is not installed, the folder beside the code)."""
    try:
        return Path(str(importlib.resources.files("semloc_deploy")))
    except ModuleNotFoundError:
        return CODE_ROOT / "deploy"


def builtin_graphs() -> list[str]:
    """The names ``semloc up NAME`` accepts: ``local``, ``demo``, ``two-machines/robot``, ..."""
    folder = builtin_graphs_dir()
    return sorted(str(p.relative_to(folder).with_suffix("")) for p in folder.rglob("*.yaml") if _is_graph(p))


def _is_graph(path: Path) -> bool:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and "nodes" in data


def find_graph(graph: str | Path) -> Path:
    """A graph file: ``graph`` as a path if it names a file, else the built-in graph of that name (``local`` is
    deploy/local.yaml, shipped with semloc). ConfigError naming the built-in graphs otherwise."""
    path = Path(graph)
    if path.is_file():
        return path
    name = str(graph).removesuffix(".yaml")
    builtin = builtin_graphs_dir() / f"{name}.yaml"
    if ".." not in Path(name).parts and not path.is_absolute() and builtin.is_file():
        return builtin
    raise ConfigError(f"graph file not found: {graph} (built-in graphs: {', '.join(builtin_graphs())})")


def resolve_beside(data: dict, folder: Path) -> dict:
    """The graph ``data`` read from a file in ``folder`` with its relative paths read from there: a hub's zenoh
    config, and every string of a node's ``config`` that names a file or folder beside the graph, become absolute.
    Other strings (a device index, a URL, a name, a path to write such as a log) are left as given; nodes run in
    the launcher's working directory."""
    def beside(value):
        if not isinstance(value, str) or not value or "://" in value or Path(value).is_absolute():
            return value
        candidate = folder / value
        return str(candidate.resolve()) if candidate.exists() else value

    data = dict(data)
    for field in ("hub_zenoh_config", "secure_hub_zenoh_config"):
        if field in data:
            data[field] = beside(data[field])
    nodes = data.get("nodes")
    if isinstance(nodes, dict):
        data["nodes"] = {name: {**node, "config": {k: beside(v) for k, v in node["config"].items()}}
                         if isinstance(node, dict) and isinstance(node.get("config"), dict) else node
                         for name, node in nodes.items()}
    return data


def load_graph(path: str | Path, overrides: dict | None = None) -> Graph:
    """Read and validate a graph file (a path or a built-in graph's name, :func:`find_graph`); relative paths in
    the file are read from its folder (:func:`resolve_beside`), those in ``overrides`` (deep-merged over it, e.g.
    ``{"robot": "r2"}``) from the working directory."""
    path = find_graph(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a graph file is a mapping")
    data = deep_merge(resolve_beside(data, path.resolve().parent), overrides or {})
    try:
        return Graph.model_validate(data)
    except ValidationError as error:
        # A check across nodes (start_after) has no field to name: its message names the nodes.
        lines = [f"  {'.'.join(map(str, e['loc'])) or 'nodes'}: {e['msg']}" for e in error.errors(include_url=False)]
        raise ConfigError(f"{path}: invalid graph:\n" + "\n".join(lines)) from None


def describe_exit(code: int) -> str:
    """A process's exit code in words (negative: the signal that killed it)."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _node_oom_score_adj() -> int | None:
    """The OOM score adjustment a node is started with: the launcher's own plus NODE_OOM_SCORE_ADJ (None: not
    Linux, nothing to adjust)."""
    try:
        return min(1000, int(Path("/proc/self/oom_score_adj").read_text()) + NODE_OOM_SCORE_ADJ)
    except (OSError, ValueError):
        return None


def _node_preexec(oom_score_adj: int | None):
    """preexec_fn of a node: SIGTERM it when the launcher dies, and raise its OOM score to ``oom_score_adj`` (Linux
    only; harmless elsewhere). Raising needs no privilege."""

    def preexec() -> None:
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        except OSError:
            pass
        if oom_score_adj is not None:
            try:
                fd = os.open("/proc/self/oom_score_adj", os.O_WRONLY)
                try:
                    os.write(fd, str(oom_score_adj).encode())
                finally:
                    os.close(fd)
            except OSError:
                pass

    return preexec


def _schedstat(path: str) -> tuple[int, int] | None:
    """(ns on a CPU, ns runnable but waiting for one) of the thread whose /proc folder is ``path`` (Linux
    schedstat), or None where it cannot be read. The wait grows when the thread gets a CPU, not while it waits."""
    try:
        with open(f"{path}/schedstat") as stat:
            ran, waited = stat.read().split()[:2]
        return int(ran), int(waited)
    except (OSError, ValueError):
        return None


def cpu_wait_s(pid: int) -> float:
    """Seconds the process's main thread has spent runnable but waiting for a CPU (Linux schedstat; 0 elsewhere).
    A worker sets up on its main thread: on a machine whose cores other software keeps busy, that wait is what
    makes a start slow without the worker being stuck."""
    times = _schedstat(f"/proc/{pid}")
    return 0.0 if times is None else times[1] * 1e-9


def thread_times(pid: int) -> dict[int, tuple[str, int, int]]:
    """Each thread of the process: (its state letter, R for runnable; ns on a CPU; ns waiting for one), from /proc
    (Linux; empty elsewhere)."""
    threads = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return threads
    for tid in tids:
        path = f"/proc/{pid}/task/{tid}"
        try:
            with open(f"{path}/stat") as stat:
                state = stat.read().rsplit(")", 1)[1].split()[0]  # after the name, which may hold anything
        except (OSError, IndexError):
            continue
        times = _schedstat(path)
        if times is not None:
            threads[int(tid)] = (state, *times)
    return threads


def _failure_line(node_log: NodeLog | None, start: int = 0) -> str | None:
    """The one line a failed worker ends its log with (`semloc worker: ...` or `... worker failed: ...`), written
    from offset ``start`` on (where its process began: an earlier process's failure is not this one's), or None."""
    if node_log is None:
        return None
    _first, data = node_log.read(max(start, node_log.end - 16384), node_log.end)
    lines = data.decode(errors="replace").splitlines()
    for line in reversed(lines):
        if "worker failed: " in line:
            return line.split("worker failed: ", 1)[1].strip()
        if line.startswith("semloc worker"):
            return line.strip()
    return None


class Heartbeat:
    """The last Status of a node's current process, as the launcher received it."""

    def __init__(self, arrived: float, status: Status):
        self.arrived, self.pid, self.state, self.reason = arrived, status.pid, status.state, status.state_reason
        self.memory = status.memory


class Starvation:
    """How long a silent node waited for a CPU since its last heartbeat: over each STARVATION_SAMPLE_S, the longest
    wait of any of its threads (a SIGSTOPped or deadlocked node waits for none: it is not runnable). A thread still
    runnable that got no CPU since the last sample waited all of it: schedstat adds a wait only when it ends, and a
    node the machine starves may wait seconds on end."""

    def __init__(self, beat: Heartbeat | None = None):
        self.beat, self.waited_s = beat, 0.0
        self.last: tuple[float, dict] | None = None

    def sample(self, pid: int, now: float) -> None:
        threads = thread_times(pid)
        if self.last is not None:
            then, before = self.last
            span, longest = now - then, 0.0
            for tid, (state, ran, waited) in threads.items():
                if tid not in before:
                    continue
                was, ran_before, waited_before = before[tid]
                wait = span if state == was == "R" and ran == ran_before else (waited - waited_before) * 1e-9
                longest = max(longest, min(span, wait))
            self.waited_s += longest
        self.last = (now, threads)


class Node:
    """A running (or waiting-to-restart) node. ``pid`` changes across restarts."""

    def __init__(self, name: str, spec: NodeSpec, restart: RestartPolicy, command: list[str], env: dict, log_path,
                 heartbeat: HeartbeatPolicy | None = None, robot: str = keys.DEFAULT_ROBOT, worker: str | None = None,
                 status_period_s: float = 1.0, log_policy: LogPolicy | None = None):
        self.name, self.spec, self.restart_policy = name, spec, restart
        self.heartbeat_policy = heartbeat or HeartbeatPolicy()
        self.status_period_s = status_period_s  # its heartbeat's period: later than this, it is late
        self.robot, self.worker = robot, worker or name  # where its Status comes from: semloc/<robot>/<worker>/status
        self.command, self.env, self.log_path = command, env, log_path
        self.log_policy = log_policy or LogPolicy()
        self.log: NodeLog | None = None  # its log, opened at its first start (None: unwritable, or the console's)
        self._pump: threading.Thread | None = None  # copies the current process's output into the log
        self.process: subprocess.Popen | None = None
        self.starts = 0
        self.quick_failures = 0
        self.started_at = 0.0
        self.next_start: float | None = time.monotonic()
        self.last_exit: int | None = None
        self.finished = False
        self.restart_reason = ""  # why the current process was started again ("" for the first start)
        self.exit_reason = ""  # why the last process ended
        self.log_start = 0  # where the current process's lines begin in its log
        self.config_error = ""  # the line of a node stopped for good by a bad configuration or file (exit 2)
        self.heartbeat: Heartbeat | None = None  # of the current process
        self.starvation = Starvation()  # its wait for a CPU since its heartbeat, while that is late
        self.stalled_since: float | None = None  # the current process reports itself stalled since
        self.kill_reason = ""  # set when the launcher kills a hung process
        self.shown_state = ""  # the state last logged
        self.start_after: list[str] = []  # launched nodes its first start waits for (Launcher._prepare)
        self.waiting_for: list[str] = []  # those of them not running yet, while its first start waits
        # robot/name of the workers its next process meets before its setup: those of start_after that ran (a
        # first start), the nodes running then (a restart: Launcher._running)
        self.met: list[str] = []
        self.ran = False  # a process of it has reported running (or degraded, stalled): past its setup
        self.memory_group: tuple[int, Path] | None = None  # the current process's memory cgroup (innermost)
        self.oom_kills = 0  # processes of it the kernel killed for want of memory
        self.automatic_restarts = 0  # restarts by its policy since the operator's last (counted by max_restarts)
        self.operator_stop_at: float | None = None  # SIGTERM sent for `semloc restart`: started again once it exits

    @property
    def kind(self) -> str:
        return self.spec.worker or self.name

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None and self.process.poll() is None else None

    def drain(self, timeout_s: float = 2.0) -> None:
        """Wait until the exited process's last output is in the log (its children may hold the pipe: not long)."""
        if self._pump is not None:
            self._pump.join(timeout_s)

    @property
    def restarts(self) -> int:
        return max(0, self.starts - 1)

    def spawn(self) -> None:
        if self.log_path and self.log is None:
            try:
                self.log = NodeLog(self.log_path, self.log_policy)
            except OSError as error:
                # An unwritable log folder (read-only, removed) must not keep a node from (re)starting: its output
                # goes to the launcher's own instead.
                log.error("node %s: cannot write its log %s: %s; its output goes to the launcher's", self.name,
                          self.log_path, error.strerror)
        self.log_start = self.log.end if self.log is not None else 0  # this process's lines
        env = {**self.env, RESTARTS_ENV: str(self.starts), RESTART_REASON_ENV: self.restart_reason,
               START_AFTER_ENV: ",".join(self.met)}
        piped = subprocess.PIPE if self.log is not None else None  # node_logs.py says why a pipe
        self.process = subprocess.Popen(
            self.command, env=env, start_new_session=True, preexec_fn=_node_preexec(_node_oom_score_adj()),
            stdin=subprocess.DEVNULL, stdout=piped, stderr=subprocess.STDOUT if piped else None,
        )
        if self.log is not None:
            self._pump = pump(self.process.stdout, self.log)
        groups = memory.memory_groups(self.process.pid)  # read now: a dead process's /proc entry is gone
        self.memory_group = groups[0] if groups else None
        self.starts += 1
        self.started_at = time.monotonic()
        self.next_start = None
        self.heartbeat = self.stalled_since = None
        self.kill_reason = ""
        log.info("node %s started (pid %d%s)", self.name, self.process.pid,
                 f", restart {self.restarts}: {self.restart_reason}" if self.restarts else "")

    def health(self, now: float) -> tuple[str, str]:
        """(state, reason) of the node as the launcher sees it (see ``NodeHealth``)."""
        if self.operator_stop_at is not None and self.pid is not None:
            return "stopping", "restarting at the operator's word (semloc restart)"
        if self.process is None and self.waiting_for and not self.finished:
            return "starting", one_line(f"waiting for {', '.join(self.waiting_for)} to run (start_after)")
        if self.process is None or self.process.poll() is not None:
            if self.finished:
                # Exit 0 and not restarted: its work is done (a recorded source played to its end), not a failure.
                state = "stopped" if self.last_exit == 0 else "down"
                return state, one_line(f"finished: {self.exit_reason or 'not started'}")
            if self.next_start is not None and self.starts:
                return "down", one_line(f"{self.exit_reason}; restarts in {max(0.0, self.next_start - now):.1f} s")
            return "down", one_line(self.exit_reason or "not started yet")
        policy, beat = self.heartbeat_policy, self.heartbeat
        if beat is None or beat.state == "starting":
            # A start is judged by the time it could run: one the machine starves (numba compiling its kernels
            # while other software takes the cores) is slow, not stuck, and killing it would start it over.
            since_start = now - self.started_at
            waited = cpu_wait_s(self.process.pid)
            if since_start - waited > policy.start_timeout_s:
                return "stalled", one_line(f"not running {since_start:.0f} s after its start "
                                           f"({waited:.0f} s of it waiting for a CPU)")
            return "starting", ""
        silent = now - beat.arrived
        if silent > policy.stalled_after_s:
            waited = self.starved_s(beat)
            return "stalled", f"no heartbeat for {silent:.1f} s" + (
                f" ({waited:.1f} s of it waiting for a CPU)" if waited >= 0.05 else "")
        return beat.state, beat.reason

    def starved_s(self, beat: Heartbeat) -> float:
        """Seconds the node waited for a CPU since heartbeat ``beat`` (0 before it was late, or without schedstat)."""
        return self.starvation.waited_s if self.starvation.beat is beat else 0.0

    def watch_starvation(self, now: float) -> None:
        """Sample the threads' CPU wait of a node whose heartbeat is late, from its last heartbeat on."""
        beat = self.heartbeat
        if beat is None or self.pid is None or now - beat.arrived <= self.status_period_s:
            return
        if self.starvation.beat is not beat:
            self.starvation = Starvation(beat)
        last = self.starvation.last
        if last is None or now - last[0] >= STARVATION_SAMPLE_S:
            self.starvation.sample(self.pid, now)

    def hang(self, now: float) -> str | None:
        """Why the current process must be killed as hung now (None: it need not): silent for
        ``restart_after_s`` since its last heartbeat, less the time it waited for a CPU meanwhile (a node the machine
        starves is slow, not hung), reporting itself stalled for that long, or not running ``start_timeout_s`` after
        its start."""
        policy, beat = self.heartbeat_policy, self.heartbeat
        state, reason = self.health(now)
        if state != "stalled" or policy.restart_after_s is None:
            return None
        if beat is None or beat.state == "starting":
            return reason
        if now - beat.arrived <= policy.stalled_after_s:  # it speaks, and says it is stalled
            return reason if now - (self.stalled_since or now) >= policy.restart_after_s else None
        return reason if now - beat.arrived - self.starved_s(beat) >= policy.restart_after_s else None

    def out_of_memory(self, group_kill: bool) -> str:
        """Why the current process, killed by a SIGKILL its launcher did not send, ran out of memory ("": no sign
        of it): ``group_kill``, an OOM kill its memory cgroup counted that no other node's death took, or its last
        Status near its limit (the kernel's OOM killer sends SIGKILL)."""
        if group_kill:
            return f"the kernel's OOM killer, in its memory cgroup {self.memory_group[1]}"
        seen = self.heartbeat.memory if self.heartbeat is not None else None
        if seen is not None and seen.near_limit:
            return (f"its last status: {memory.mb(seen.used_bytes)} of {memory.mb(seen.limit_bytes)}, "
                    f"{seen.limit_source}")
        return ""

    def signal_group(self, signum: int) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.kill_leftovers(signum)

    def kill_leftovers(self, signum: int = signal.SIGKILL) -> None:
        """Signal the process's group even when the process has exited: grandchildren it left still hold what it
        held (a camera device, a port) from the next process."""
        if self.process is None:
            return
        try:
            os.killpg(self.process.pid, signum)
        except (ProcessLookupError, PermissionError):
            pass


class Launcher:
    def __init__(self, graph: Graph, run_dir: str | Path | None = None, console: bool = False,
                 python: str = sys.executable):
        self.graph = graph
        self.run_id = f"{graph.name}-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        self.run_dir = Path(run_dir) if run_dir else Path("runs") / self.run_id
        self.console = console
        self.python = python
        self.host = socket.gethostname()
        self.recording_id = graph.rerun.recording_id or self.run_id
        self.viewer = None  # rerun mode serve: the recording whose gRPC server the nodes stream to
        self.web_viewer_url: str | None = None
        # Its name on the bus (keys.launcher_nodes): the run id made a valid key chunk.
        self.launcher_id = re.sub(r"[^A-Za-z0-9_.-]", "_", self.run_id)
        self.nodes: dict[str, Node] = {}
        self.skipped: list[str] = []
        self._session = None
        self._links: BusWatch | None = None  # a router hub's links to other routers (the other machine's)
        self._link_quiet_s = 0.0  # the hub's lease: a link nothing crossed for that long is silent
        self._next_probe = 0.0
        self._declared: list = []  # the session's subscribers, queryables, liveliness token and publisher
        self._status_publisher = None
        self._stop = threading.Event()
        self._stopped = threading.Event()
        self.stop_requested = threading.Event()  # `semloc stop` asked (keys.launcher_stop): the run is over
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._started_at = time.monotonic()  # start(): the launch, from which start_after_timeout_s counts
        # Memory cgroup of nodes -> the OOM kills counted there that are accounted for: before the launch, or a node's
        # death each. Nodes sharing a group (a container) take one each: an operator's kill -9 of another node after
        # an OOM kill is not an OOM kill.
        self._oom_kills_seen: dict[tuple[int, Path], int] = {}
        self._prepare()

    # ------------------------------------------------------------------ preparation
    def _node_config(self, name: str, spec: NodeSpec) -> dict:
        g = self.graph
        if g.bus is not None:
            bus = g.bus.model_dump()
        elif g.hub:
            bus = {"connect": [g.hub.replace("0.0.0.0", "127.0.0.1")], "listen": ["tcp/127.0.0.1:0"]}
            if g.hub_mode == "router":
                bus = {"mode": "client", "connect": bus["connect"]}
        else:
            raise ConfigError("a graph without a hub needs a `bus` section telling nodes where to connect")
        rerun = g.rerun.model_dump()
        rerun["recording_id"] = self.recording_id
        rerun["nodes"] = {**self._layout_roles(), **rerun["nodes"]}
        if rerun["mode"] == "serve":
            # The launcher hosts the server (start()); its nodes stream to it.
            rerun.update(mode="grpc", url=grpc_url(g.rerun.grpc_port))
        if rerun["mode"] == "save" and not rerun.get("path"):
            rerun["path"] = str(self.run_dir / "rerun")
        base = {"robot": g.robot, "name": name, "bus": bus, "rerun": rerun, "run_dir": str(self.run_dir)}
        if g.state_dir:
            base["state_dir"] = g.state_dir
        config = deep_merge(base, spec.config)
        if spec.inputs:
            config["inputs"] = {k: v.model_dump(exclude_none=True) for k, v in spec.inputs.items()}
        if spec.outputs:
            config["outputs"] = {k: v.model_dump(exclude_none=True) for k, v in spec.outputs.items()}
        return config

    def _layout_roles(self) -> dict[str, str]:
        """The viewer layout's roles (camera, detector, ...) -> the first node running that worker."""
        roles: dict[str, str] = {}
        for name, spec in self.graph.nodes.items():
            roles.setdefault(spec.worker or name, name)
        return roles

    def _prepare(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "logs").mkdir(exist_ok=True)
        base_env = {**os.environ, **self.graph.env}
        if (CODE_ROOT / "pyproject.toml").is_file():  # a checkout: nodes import its code even if not installed
            base_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(CODE_ROOT), base_env.get("PYTHONPATH", "")]))
        for name, spec in self.graph.nodes.items():
            if not spec.enabled:
                continue
            kind = spec.worker or name
            if not worker_exists(kind):
                if spec.optional:
                    log.warning("node %s skipped: worker %r does not exist yet", name, kind)
                    self.skipped.append(name)
                    continue
                raise ConfigError(f"node {name}: no worker {kind!r} in services/workers")
            config = self._node_config(name, spec)
            heartbeat = spec.heartbeat or self.graph.heartbeat
            status_period = float(config.get("status_period_s", WorkerConfig.model_fields["status_period_s"].default))
            if heartbeat.stalled_after_s <= status_period:
                raise ConfigError(f"node {name}: heartbeat.stalled_after_s ({heartbeat.stalled_after_s}) must exceed "
                                  f"its status_period_s ({status_period}), the period of its heartbeat")
            config_path = self.run_dir / f"{name}.yaml"
            config_path.write_text(yaml.safe_dump(check_node_config(name, kind, config, {**base_env, **spec.env}),
                                                   sort_keys=False))
            command = [self.python, "-m", "services.cli", "worker", kind, "--config", str(config_path)]
            log_path = None if self.console else self.run_dir / "logs" / f"{name}.log"
            self.nodes[name] = Node(name, spec, spec.restart or self.graph.restart, command,
                                    {**base_env, **spec.env}, log_path, heartbeat=heartbeat,
                                    robot=str(config["robot"]), worker=str(config.get("name") or name),
                                    status_period_s=status_period, log_policy=self.graph.logs)
        for name, node in self.nodes.items():
            # A disabled or skipped node never runs: nothing waits for it.
            node.start_after = [other for other in node.spec.start_after if other in self.nodes]
            node.waiting_for = list(node.start_after)
            if node.start_after:
                node.next_start = None  # held until they run (_hold)
            left_out = [other for other in node.spec.start_after if other not in self.nodes]
            if left_out:
                log.info("node %s does not wait for %s: not launched (disabled or skipped)", name,
                         ", ".join(left_out))
        (self.run_dir / "graph.json").write_text(json.dumps(self.graph.model_dump(mode="json"), indent=2) + "\n")

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "Launcher":
        if self.graph.rerun.mode == "serve" and self.viewer is None:
            import rerun as rr

            self.viewer = rr.RecordingStream("semloc", recording_id=self.recording_id)
            config = self.graph.rerun.model_copy(update={"nodes": {**self._layout_roles(), **self.graph.rerun.nodes}})
            self.web_viewer_url = serve(self.viewer, config, layout(config, self.graph.robot))
            log.info("rerun web viewer: %s", self.web_viewer_url)
        if self.graph.hub:
            hub = BusConfig(mode=self.graph.hub_mode, listen=[self.graph.hub], zenoh_config=self.graph.hub_zenoh_config)
            self._link_quiet_s = hub.lease_ms / 1000
            self._session = open_session(hub)
        elif self.graph.bus is not None:
            # No hub: join the nodes' bus to hear their heartbeats (listening where they connect is theirs to do).
            self._session = open_session(self.graph.bus.model_copy(update={"listen": []}))
        if self._session is not None:
            self._watch_heartbeats(self._session)
        if self.graph.hub and self.graph.hub_mode == "router":
            self._watch_router_links(self._session)
        self._started_at = time.monotonic()
        self._thread = threading.Thread(target=self._monitor, name="semloc-launcher", daemon=True)
        self._thread.start()
        return self

    def _monitor(self) -> None:
        # Every spawn happens on this thread: PR_SET_PDEATHSIG fires when the spawning *thread* exits.
        next_publication = 0.0
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                with self._lock:
                    for node in self.nodes.values():
                        self._supervise(node, now)
                        self._watch(node, now)
                if now >= next_publication:
                    next_publication = now + LAUNCHER_STATUS_PERIOD_S
                    self._publish_view()
                self._probe_links(now)
                self._stop.wait(0.05)
        finally:
            self._terminate_all()
            self._stopped.set()

    # ------------------------------------------------------------------ heartbeats and the launcher's view
    def _watch_heartbeats(self, session) -> None:
        robot = self.graph.robot
        key = keys.launcher_nodes(robot, self.launcher_id)
        self._status_publisher = session.declare_publisher(key)
        # One subscriber per robot of its nodes, within each robot's keys: a router's access control
        # (deploy/secure/) lets a declaration through only inside a rule's key expressions (semloc/<robot>/**).
        self._declared = [
            *(session.declare_subscriber(keys.robot_statuses(r), self._on_status)
              for r in sorted({node.robot for node in self.nodes.values()})),
            session.declare_queryable(key, self._on_view_query),
            session.declare_queryable(keys.launcher_logs(robot, self.launcher_id), self._on_logs_query),
            session.declare_queryable(keys.launcher_stop(robot, self.launcher_id), self._on_stop_query),
            session.declare_queryable(keys.launcher_restart(robot, self.launcher_id), self._on_restart_query),
            session.liveliness().declare_token(keys.launcher_alive(robot, self.launcher_id)),
            self._status_publisher,
        ]

    def _watch_router_links(self, session) -> None:
        """Count the hub's links to other routers: the link between the machines (docs/deploy.md, "When the link
        drops"), down from the start for a hub that connects to one (until it answers)."""
        self._links = BusWatch(log, kinds=frozenset({"router"}), what="router link")
        self._links.watch(session)
        config = self.graph.hub_zenoh_config
        if config and listed_endpoints(zenoh.Config.from_file(config), "connect/endpoints"):
            self._links.expect()

    def _probe_links(self, now: float) -> None:
        """Ask the other machine's launchers for their view four times a lease (zenoh's keep-alive rate): a reply
        from the router at the other end of a link (a hub launcher's session is its router) says the link carried
        from when the probe was sent, and a link that answered no probe sent in the last lease is silent (BusWatch).
        zenoh's own lease counts what its router reads, and a router behind with lossless messages reads what crossed
        before the silence for seconds into it. The routers' admin space would need no launcher at the other end, but
        zenoh 1.10 answers it only where `adminspace` is enabled, and a --secure router's access control denies it; a
        far end that never answers (no launcher of this robot) leaves the link to zenoh's events."""
        if self._links is None or not self._links.open or now < self._next_probe:
            return
        self._next_probe = now + self._link_quiet_s / 4
        self._links.check_silence(self._link_quiet_s)
        try:
            # The reply takes the query's: DROP never waits for room on a silent link (neither this thread, which
            # supervises the nodes, nor the far router's); INTERACTIVE_HIGH goes ahead of the streams on a busy link.
            self._session.get(keys.all_launcher_nodes(self.graph.robot), lambda reply: self._on_probe_reply(reply, now),
                              allowed_destination=zenoh.Locality.REMOTE, timeout=self._link_quiet_s,
                              congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.INTERACTIVE_HIGH,
                              consolidation=zenoh.ConsolidationMode.NONE)
        except zenoh.ZError as error:
            log.warning("router link probe failed: %s", error)

    def _on_probe_reply(self, reply, sent: float) -> None:
        replier = reply.replier_id
        if self._links is not None and replier is not None:
            self._links.heard(str(replier.zid), sent)

    def _on_status(self, sample) -> None:
        arrived = time.monotonic()
        try:
            status = decode(payload_bytes(sample.payload), expected=Status)
        except FrameError:
            return  # not a Status (e.g. a stream of that name): not a heartbeat
        node = next((n for n in self.nodes.values() if (n.robot, n.worker) == (status.header.robot, status.worker)),
                    None)
        process = node.process if node is not None else None
        if process is None or process.pid != status.pid or status.host != self.host:
            return  # another launcher's node, or a previous process of this one
        node.heartbeat = Heartbeat(arrived, status)
        if status.state in ("running", "degraded", "stalled"):
            node.ran = True

    def _watch(self, node: Node, now: float) -> None:
        """Notice a node that reports itself stalled, and kill a hung one (its exit then restarts it)."""
        beat = node.heartbeat
        if beat is not None and beat.state == "stalled":
            node.stalled_since = node.stalled_since or beat.arrived
        elif beat is not None:
            node.stalled_since = None
        if node.kill_reason or node.pid is None:
            return
        node.watch_starvation(now)
        state, why = node.health(now)
        if state != node.shown_state and state in ("running", "degraded", "stalled"):
            if state != "running" or node.shown_state in ("degraded", "stalled"):
                log.log(logging.INFO if state == "running" else logging.WARNING, "node %s %s%s", node.name, state,
                        f": {why}" if why else " again")
            node.shown_state = state
        reason = node.hang(now)
        if reason is not None:
            node.kill_reason = one_line(f"hung: {reason}")
            log.warning("node %s (pid %d) %s: killed", node.name, node.pid, node.kill_reason)
            node.signal_group(signal.SIGKILL)  # SIGTERM would wait: a stopped or hung process cannot act on it

    def view(self) -> LauncherStatus:
        """This launcher's view of its nodes."""
        now = time.monotonic()
        nodes = {}
        with self._lock:
            for name, node in self.nodes.items():
                state, reason = node.health(now)
                nodes[name] = NodeHealth(
                    worker=node.worker, robot=node.robot, kind=node.kind, state=state, state_reason=reason,
                    pid=node.pid, restarts=node.restarts, restart_reason=node.restart_reason, last_exit=node.last_exit,
                    heartbeat_age_s=None if node.heartbeat is None else max(0.0, now - node.heartbeat.arrived),
                    finished=node.finished, oom_kills=node.oom_kills)
        robot = self.graph.robot
        header = Header(robot=robot, stream=keys.launcher_nodes(robot, self.launcher_id), stamp_ns=time.time_ns())
        links = {}
        if self._links is not None:
            down = self._links.cut_off_since
            links = dict(router_links=len(self._links.up), router_links_lost=self._links.lost,
                         router_links_regained=self._links.regained,
                         router_link_down_s=None if down is None else max(0.0, now - down))
        return LauncherStatus(header=header, launcher=self.launcher_id, graph=self.graph.name, pid=os.getpid(),
                              host=self.host, nodes=nodes, **links)

    def _publish_view(self) -> None:
        if self._status_publisher is None:
            return
        try:
            self._status_publisher.put(encode(self.view()))
        except Exception as error:  # never let reporting stop the supervision
            log.warning("launcher status publication failed: %s", error)

    def _on_view_query(self, query) -> None:
        try:
            query.reply(keys.launcher_nodes(self.graph.robot, self.launcher_id), encode(self.view()))
        except Exception as error:
            log.warning("launcher status query failed: %s", error)
        finally:
            query.drop()

    def logs(self, request: LogRequest) -> LogTail:
        """The piece of each node's log ``request`` asks for (see LogRequest)."""
        logs = {}
        budget = max(4096, LOG_ANSWER_BYTES // max(1, len(self.nodes)))
        for name, node in self.nodes.items():
            if (request.node and name != request.node) or node.log is None:
                continue
            size = node.log.end  # offsets never go back: rotation moves bytes to older files, or drops them
            start = min(request.offsets.get(name, max(0, size - request.tail_bytes)), size)
            start, data = node.log.read(start, min(size, start + budget))
            logs[name] = LogChunk(start=start, end=start + len(data), text=data.decode(errors="replace"))
        robot = self.graph.robot
        header = Header(robot=robot, stream=keys.launcher_logs(robot, self.launcher_id), stamp_ns=time.time_ns())
        return LogTail(header=header, launcher=self.launcher_id, graph=self.graph.name, logs=logs)

    def _on_logs_query(self, query) -> None:
        key = keys.launcher_logs(self.graph.robot, self.launcher_id)
        try:
            request = decode(payload_bytes(query.payload), expected=LogRequest) if query.payload else LogRequest(
                header=Header(robot=self.graph.robot, stream=key))
            if request.node and request.node not in self.nodes:
                query.reply_err(self._no_node(request.node))
                return
            query.reply(key, encode(self.logs(request)))
        except FrameError as error:  # an untrusted request: refused, the launcher goes on
            query.reply_err(f"bad log request: {error}")
        except Exception as error:
            log.warning("log query failed: %s", error)
        finally:
            query.drop()

    def _on_stop_query(self, query) -> None:
        """Acknowledge, then stop: ``semloc up`` sees :meth:`finished` and stops every node."""
        robot = self.graph.robot
        header = Header(robot=robot, stream=keys.launcher_stop(robot, self.launcher_id), stamp_ns=time.time_ns())
        try:
            log.info("stop requested over the bus")
            query.reply(keys.launcher_stop(robot, self.launcher_id), encode(Ack(
                header=header, ok=True, message=f"stopping graph {self.graph.name} (nodes: {', '.join(self.nodes) or 'none'})")))
        except Exception as error:
            log.warning("stop query failed: %s", error)
        finally:
            query.drop()
            self.stop_requested.set()

    def _no_node(self, name: str) -> str:
        """A request's node is none of this graph's (a name off the bus: cut short)."""
        return f"no node {name[:128]!r} in graph {self.graph.name} (nodes: {', '.join(self.nodes) or 'none'})"

    def restart(self, name: str) -> tuple[bool, str]:
        """Restart node ``name`` at the operator's word (``semloc restart``), whatever its restart policy: a running
        process gets SIGTERM (SIGKILL after ``stop_timeout_s``, as when the graph stops) and the node starts again as
        soon as it has exited; a node not running - given up (``max_restarts``), finished, stopped by a bad file,
        waiting for a restart or for its ``start_after`` - starts at once. Counted as a restart with the reason
        ``operator``, not as a failure: no backoff, and its automatic restarts count from 0 again towards
        ``max_restarts``. (accepted, the answer's line)."""
        graph = f"graph {self.graph.name}"
        with self._lock:
            node = self.nodes.get(name)
            if node is None:
                if name in self.graph.nodes:  # in the file, not launched: nothing to restart, or to start it with
                    why = "disabled (enabled: false)" if not self.graph.nodes[name].enabled else \
                        "skipped: its worker does not exist"
                    return False, f"node {name} of {graph} is {why}; change the graph and start it again"
                return False, self._no_node(name)
            pid = node.pid
            if pid is not None:
                if node.operator_stop_at is None:
                    log.info("node %s (pid %d) restarts: asked over the bus", name, pid)
                    node.operator_stop_at = time.monotonic()
                    node.kill_reason = OPERATOR_STOP
                    node.signal_group(signal.SIGTERM)
                return True, (f"restarting node {name} of {graph} (pid {pid}: SIGTERM, SIGKILL after "
                              f"{self.graph.stop_timeout_s:g} s)")
            if node.waiting_for:
                was = f"waiting for {', '.join(node.waiting_for)} to run (start_after)"
            elif node.finished:
                was = f"it had {node.exit_reason or 'finished'}" if not node.config_error else \
                    f"stopped by a bad configuration or file: {node.config_error}"
            elif node.starts:
                was = f"{node.exit_reason}; it was to restart by its policy"
            else:
                was = "not started yet"
            log.info("node %s starts: asked over the bus (%s)", name, was)
            self._restart_now(node, time.monotonic())
            node.waiting_for = []
            return True, one_line(f"starting node {name} of {graph} ({was})")

    def _restart_now(self, node: Node, now: float) -> None:
        node.finished, node.config_error = False, ""
        node.next_start, node.restart_reason = now, OPERATOR_RESTART
        node.quick_failures = node.automatic_restarts = 0
        node.operator_stop_at = None

    def _on_restart_query(self, query) -> None:
        name, robot = keys.restarted_node(query.key_expr), self.graph.robot
        try:
            ok, message = self.restart(name)
            if not ok:
                log.warning("restart refused: %s", message)
            # A reply names a key within the query's: the node's, or any node's for a name off the bus that is none
            # of the graph's (it may be no name, or too long for a header).
            try:
                key = keys.launcher_restart(robot, self.launcher_id, name if name in self.graph.nodes else "*")
            except ValueError:
                key = keys.launcher_restart(robot, self.launcher_id)
            header = Header(robot=robot, stream=key, stamp_ns=time.time_ns())
            query.reply(key, encode(Ack(header=header, ok=ok, message=message)))
        except Exception as error:
            log.warning("restart query failed: %s", error)
        finally:
            query.drop()

    def _hold(self, node: Node, now: float) -> None:
        """Release a node's first start once the nodes of its ``start_after`` have run (their Status said running),
        have stopped for good (a warning: they never will), or ``start_after_timeout_s`` after the launch (a warning
        naming those that still do not run)."""
        gone = [name for name in node.waiting_for if self.nodes[name].finished and not self.nodes[name].ran]
        node.waiting_for = [name for name in node.waiting_for if not self.nodes[name].ran and name not in gone]
        if gone:
            log.warning("node %s does not wait for %s: stopped without running", node.name, ", ".join(gone))
        timeout = node.spec.start_after_timeout_s
        waited = now - self._started_at
        if node.waiting_for and timeout is not None and waited >= timeout:
            log.warning("node %s starts without %s: not running %.0f s after the launch (start_after_timeout_s)",
                        node.name, ", ".join(node.waiting_for), waited)
            node.waiting_for = []
        elif not node.waiting_for:
            log.info("node %s starts (start_after: %s; %.1f s after the launch)", node.name,
                     ", ".join(node.start_after), waited)
        if not node.waiting_for:
            node.next_start = now
            node.met = [f"{self.nodes[name].robot}/{self.nodes[name].worker}" for name in node.start_after
                        if self.nodes[name].ran]

    def _running(self, node: Node) -> list[str]:
        """robot/name of the other nodes whose process runs now (said so: past its setup, its inputs subscribed), not
        being stopped: a restart of ``node`` meets them, its consumers among them, before its setup. Not those that
        stopped (each would hold it for MEET_TIMEOUT_S), nor those starting (each meets the running ones itself)."""
        return [f"{other.robot}/{other.worker}" for other in self.nodes.values()
                if other is not node and other.pid is not None and other.heartbeat is not None
                and other.heartbeat.state in ("running", "degraded", "stalled") and not other.kill_reason
                and other.operator_stop_at is None]

    def _take_oom_kill(self, group: tuple[int, Path] | None) -> bool:
        """Whether memory cgroup ``group`` counted an OOM kill no node's death took yet (taking it)."""
        if group is None or memory.oom_kills(group) <= self._oom_kills_seen[group]:
            return False
        self._oom_kills_seen[group] += 1
        return True

    def _supervise(self, node: Node, now: float) -> None:
        if node.finished:
            return
        if node.process is None and node.waiting_for:
            self._hold(node, now)
        if node.process is None or node.next_start is not None:
            if node.next_start is not None and now >= node.next_start:
                if node.starts:
                    node.met = self._running(node)
                try:
                    node.spawn()
                    if node.memory_group is not None:
                        self._oom_kills_seen.setdefault(node.memory_group, memory.oom_kills(node.memory_group))
                except OSError as error:
                    log.error("node %s cannot start: %s", node.name, error)
                    node.finished = True
            return
        code = node.process.poll()
        if code is None:
            asked = node.operator_stop_at
            if asked is not None and now - asked >= self.graph.stop_timeout_s and node.kill_reason == OPERATOR_STOP:
                log.warning("node %s did not stop in time: SIGKILL", node.name)
                node.kill_reason = OPERATOR_KILL
                node.signal_group(signal.SIGKILL)
            return
        node.last_exit = code
        policy = node.restart_policy
        ran_for = now - node.started_at
        failed = code != 0
        # Why it failed, from its log (`... worker failed: FileNotFoundError: ...`): the operator
        # sees it here and in `semloc status` (the restart reason) without opening the log.
        node.drain()
        why = _failure_line(node.log, node.log_start) if failed and not node.kill_reason else None
        described = node.kill_reason or describe_exit(code)
        if code == -signal.SIGKILL and not node.kill_reason:
            # Not the launcher's: the kernel's OOM killer, or another process (an operator's kill -9).
            oom = node.out_of_memory(self._take_oom_kill(node.memory_group))
            node.oom_kills += bool(oom)
            described += f": out of memory ({oom})" if oom else " (not sent by its launcher)"
        node.exit_reason = one_line(f"{described}{f': {why}' if why else ''}")
        log.log(logging.WARNING if failed and node.operator_stop_at is None else logging.INFO,
                "node %s exited after %.1f s: %s", node.name, ran_for, node.exit_reason)
        if node.operator_stop_at is not None:
            node.kill_leftovers()
            self._restart_now(node, now)
            return
        if code == CONFIG_ERROR_EXIT:
            # `semloc worker` exits 2 on a bad config, a bad file or an unknown worker: restarting cannot help.
            node.config_error = why or node.exit_reason
            log.error("node %s stopped, not restarted (exit %d: a bad configuration or file): %s", node.name, code,
                      why or f"see {node.log_path or 'its output'}")
            node.finished = True
            return
        wants_restart = policy.policy == "always" or (policy.policy == "on-failure" and failed)
        if policy.max_restarts is not None and node.automatic_restarts >= policy.max_restarts:
            wants_restart = False
        if not wants_restart:
            node.finished = True
            return
        node.automatic_restarts += 1
        node.quick_failures = 0 if ran_for >= policy.reset_after_s else node.quick_failures + 1
        delay = min(policy.backoff_s * 2 ** max(0, node.quick_failures - 1), policy.max_backoff_s)
        node.next_start = now + delay
        node.restart_reason = node.exit_reason  # told to the next process
        log.info("node %s restarts in %.2f s", node.name, delay)

    def _terminate_all(self) -> None:
        for declared in self._declared:
            declared.undeclare()
        self._declared, self._status_publisher = [], None
        running = [n for n in self.nodes.values() if n.process is not None and n.process.poll() is None]
        for node in running:
            node.signal_group(signal.SIGTERM)
        deadline = time.monotonic() + self.graph.stop_timeout_s
        for node in running:
            try:
                node.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("node %s did not stop in time: SIGKILL", node.name)
        for node in running:
            node.kill_leftovers()  # including grandchildren of a worker that already exited
            node.last_exit = node.process.wait()
            node.drain()
        if self._links is not None:
            self._links.close()
        if self._session is not None:
            self._session.close()
            self._session = None

    def finished(self) -> bool:
        """True when no node runs or waits for a restart, or a stop was asked over the bus (`semloc stop`)."""
        if self.stop_requested.is_set():
            return True
        with self._lock:
            return all(n.finished for n in self.nodes.values())

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every node finished (True), the launcher was stopped, or ``timeout`` passed (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._stop.is_set():
            if self.finished():
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
            self._stop.wait(0.1)
        return self.finished()

    def stop(self) -> None:
        """Stop every node (SIGTERM, then SIGKILL after ``stop_timeout_s``) and close the hub. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._stopped.wait()
            self._thread.join()
            self._thread = None

    def config_errors(self) -> dict[str, str]:
        """Node -> why, for the nodes stopped for good by a bad configuration or file (not restarted)."""
        with self._lock:
            return {name: n.config_error for name, n in self.nodes.items() if n.config_error}

    def pids(self) -> dict[str, int | None]:
        with self._lock:
            return {name: node.pid for name, node in self.nodes.items()}

    def summary(self) -> dict[str, dict]:
        with self._lock:
            return {name: {"pid": n.pid, "starts": n.starts, "last_exit": n.last_exit, "finished": n.finished,
                           "restart_reason": n.restart_reason}
                    for name, n in self.nodes.items()}

    def __enter__(self) -> "Launcher":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
