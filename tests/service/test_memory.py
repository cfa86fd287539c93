"""Memory on small machines and in containers (docs/runtime.md, "Memory"): a worker's status carries its memory and
limit, and says degraded near it; a node the kernel kills for memory is named out of memory by its launcher; a
configuration whose up-front arrays cannot fit is refused at its start."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

from schemas import Ack, Header, Status, keys
from schemas.status import LauncherStatus
from services.bus import BusConfig, QueryError, open_session, query
from services.config import ConfigError
from services import memory
from services.memory import Limit, check_room
from services.workers.mapper import MapperWorkerConfig
from tests.service.conftest import REPO_ROOT, memory_cgroup, wait_until

GROWER = "tests.service.memory_worker"
SHARED_MEMORY = Path("/dev/shm")
MiB = 1 << 20


def _status(session, name: str = "grower") -> Status | None:
    frames = query(session, keys.status("r1", name), reply_type=Status, timeout=2.0)
    return frames[0] if frames else None


def _grow(session, mib: int, timeout: float = 20.0) -> None:
    request = Ack(header=Header(robot="r1"), ok=True, message=str(mib))
    assert query(session, "semloc/r1/grower/grow", request, reply_type=Ack, timeout=timeout)


def _proc_status(pid: int) -> dict[str, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if value.strip().endswith("kB"):
            fields[name] = int(value.split()[0]) * 1024
    return fields


def _view(session) -> LauncherStatus | None:
    views = query(session, keys.all_launcher_nodes("r1"), reply_type=LauncherStatus, timeout=2.0)
    return views[0] if views else None


def _up_in_group(tmp_path: Path, procs, hub: str, cgroup_procs: Path, names: list[str],
                 backoff_s: float = 0.1) -> subprocess.Popen:
    """`semloc up` of a graph of grower nodes ``names`` (restarted ``backoff_s`` after a failure), its launcher put in
    the memory cgroup whose ``cgroup.procs`` is given before it starts (its nodes with it): a container."""
    node = {"worker": GROWER, "config": {"status_period_s": 0.2}}
    graph = {"name": "memory", "robot": "r1", "hub": hub, "restart": {"policy": "on-failure", "backoff_s": backoff_s},
             "nodes": {name: dict(node) for name in names}}
    (tmp_path / "graph.yaml").write_text(yaml.safe_dump(graph))
    return procs.semloc("up", str(tmp_path / "graph.yaml"), "--run-dir", str(tmp_path / "run"), name="launcher",
                        prefix=_into_group(cgroup_procs))


def _into_group(cgroup_procs: Path) -> tuple[str, ...]:
    """A command prefix that runs the command in the memory cgroup whose ``cgroup.procs`` is given."""
    return ("sh", "-c", f'echo $$ > {cgroup_procs} && exec "$@"', "sh")


def _group(process: subprocess.Popen) -> tuple[int, Path]:
    """(cgroup version, folder) of the memory cgroup ``process`` runs in."""
    return memory.memory_groups(process.pid)[0]


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_a_workers_status_carries_its_resident_memory_and_peak(procs, session, hub):
    procs.semloc("worker", GROWER, "--connect", hub, "--robot", "r1", "--name", "grower", "--set",
                 "status_period_s=0.2", name="grower")
    first = wait_until(lambda: (s := _status(session)) and s.state == "running" and s, 30, message="grower running")
    _grow(session, 200)
    # a status made after the 200 MiB were touched, next to /proc's figures for that pid read at once
    grown = wait_until(lambda: (s := _status(session)) and s.memory.rss_bytes > first.memory.rss_bytes + 190 * MiB
                       and s, 10, message="a status with the 200 MiB")
    proc = _proc_status(grown.pid)
    assert abs(grown.memory.rss_bytes - proc["VmRSS"]) < 8 * MiB, (grown.memory, proc)
    assert grown.memory.peak_bytes <= proc["VmHWM"] and proc["VmHWM"] - grown.memory.peak_bytes < 8 * MiB
    assert grown.memory.peak_bytes >= grown.memory.rss_bytes
    limit = grown.memory
    assert limit.limit_bytes and limit.limit_source and limit.used_bytes is not None
    assert limit.near_limit == (limit.used_bytes >= 0.9 * limit.limit_bytes)  # memory_high_fraction's default


def test_a_node_the_kernel_kills_for_memory_is_named_out_of_memory_and_restarted(tmp_path, procs, hub):
    """The launcher (and so its node) in a fresh memory cgroup of 400 MiB: the node's status shows that limit, says
    degraded near it, and once the kernel's OOM killer kills it its launcher says out of memory (log, node view,
    `semloc status`) and starts it again."""
    limit = 400 * MiB
    with memory_cgroup(limit) as cgroup_procs:
        launcher = _up_in_group(tmp_path, procs, hub, cgroup_procs, ["grower", "other"])
        try:
            with open_session(BusConfig(connect=[hub])) as session:
                first = wait_until(lambda: (s := _status(session)) and s.state == "running" and s, 60,
                                   message=lambda: f"grower running; launcher log:\n{procs.log('launcher')[-3000:]}")
                assert first.memory.limit_bytes == limit and first.memory.limit_source.endswith(
                    ("memory.limit_in_bytes", "memory.max")), first.memory
                assert str(cgroup_procs.parent) in first.memory.limit_source and not first.memory.near_limit

                # near its limit: degraded, saying so (the group's working set: the launcher's and the node's)
                for _ in range(40):
                    _grow(session, 8)
                    seen = wait_until(lambda: (s := _status(session)) and s.header.stamp_ns > first.header.stamp_ns
                                      and s, 5, message="a status")
                    first = seen
                    if seen.state == "degraded":
                        break
                assert seen.state == "degraded" and seen.state_reason.startswith("memory near its limit: "), seen
                assert seen.memory.near_limit and 0.9 * limit <= seen.memory.used_bytes <= limit, seen.memory

                # past it: the kernel kills it; its launcher says out of memory, and starts it again
                with pytest.raises((QueryError, AssertionError)):
                    _grow(session, 400, timeout=10.0)
                again = wait_until(lambda: (s := _status(session)) and s.pid != seen.pid and s.state == "running"
                                   and s, 60, message="the grower started again")
                assert again.restarts == 1 and again.restart_reason == "killed by SIGKILL: out of memory (the " \
                    f"kernel's OOM killer, in its memory cgroup {cgroup_procs.parent})", again.restart_reason
                # The kernel may kill a second process of the group before the grower's memory is freed: the other
                # node (never the launcher: NODE_OOM_SCORE_ADJ). Its count is the kernel's, taken once the launcher
                # has seen every kill.
                kernel_kills = memory.oom_kills(_group(launcher))
                view = wait_until(lambda: (v := _view(session)) and v.nodes["grower"].oom_kills
                                  + v.nodes["other"].oom_kills == kernel_kills and v, 30,
                                  message=lambda: f"the launcher's view of the kernel's {kernel_kills} OOM kills: "
                                                  f"{_view(session)}")
                assert view.nodes["grower"].oom_kills == 1 and view.nodes["grower"].last_exit == -signal.SIGKILL
                # another node of the group (a container) killed by someone afterwards: no OOM kill of its own
                other = wait_until(lambda: (s := _status(session, "other")) and s.state == "running" and s, 60,
                                   message="the other node's status")
                os.kill(other.pid, signal.SIGKILL)
                other = wait_until(lambda: (s := _status(session, "other")) and s.pid != other.pid and s, 60,
                                   message="the other node started again")
                assert other.restart_reason == "killed by SIGKILL (not sent by its launcher)", other.restart_reason
                view = _view(session)
                assert view.nodes["other"].oom_kills == kernel_kills - 1 and memory.oom_kills(
                    _group(launcher)) == kernel_kills
                assert "exited after" in procs.log("launcher") and "out of memory (the kernel's OOM killer" in \
                    procs.log("launcher")
            command = [sys.executable, "-m", "services.cli", "status", "--connect", hub, "--wait", "15"]
            status = [subprocess.run(command + flag, cwd=REPO_ROOT, capture_output=True, text=True, timeout=60).stdout
                      for flag in (["--json"], [])]
            report = json.loads(status[0])["workers"]["r1/grower"]
            assert report["launcher"]["oom_kills"] == 1 and "out of memory" in report["status"]["restart_reason"]
            assert "killed by the kernel for want of memory: 1x" in status[1] and "memory: rss " in status[1], status
        finally:
            launcher.send_signal(signal.SIGINT)
            launcher.wait(30)


@pytest.mark.skipif(not SHARED_MEMORY.is_dir(), reason="needs a tmpfs at /dev/shm")
def test_the_kernel_kills_a_node_for_memory_never_its_launcher(tmp_path, procs, hub):
    """A graph in a 400 MiB memory cgroup (a container) whose memory fills with a file in shared memory written by a
    process of the group (tmpfs: no process holds its pages, so the OOM killer cannot free them by taking the
    writer, itself small): it must choose between the launcher and its two idle nodes, of about its size. It takes
    a node, which the launcher names out of memory and starts again; the launcher lives on (the kernel took it, a
    little larger, while its nodes' OOM score was not raised above its own, and the graph was gone)."""
    limit = 400 * MiB
    with memory_cgroup(limit) as cgroup_procs:
        # restarted only once the fill is over and freed: a node started again at once takes its memory back while
        # the group is still full, and the kernel's next choice (our CI: the third kill) was the launcher
        launcher = _up_in_group(tmp_path, procs, hub, cgroup_procs, ["a", "b"], backoff_s=10.0)
        try:
            with open_session(BusConfig(connect=[hub])) as session:
                first = {name: wait_until(lambda n=name: (s := _status(session, n)) and s.state == "running" and s,
                                          60, message=f"{name} running") for name in ("a", "b")}
                group = _group(launcher)
                assert group[1] == cgroup_procs.parent and memory.oom_kills(group) == 0
                room = limit - memory.used_bytes(Limit(limit, "", group[1], group[0]))
                shared = Path(tempfile.mkdtemp(dir=SHARED_MEMORY))
                # MiB after MiB until the kernel has killed once (a fixed overfill could ask for more than two idle
                # nodes free: much of their memory is the libraries' pages, shared, and the third kill, in our CI,
                # was the launcher's); at most 256 MiB past the room
                fill = (f"import sys; from pathlib import Path; from services.memory import oom_kills\n"
                        f"group, out = ({group[0]}, Path({str(group[1])!r})), open({str(shared / 'fill')!r}, 'wb')\n"
                        f"for _ in range({(room >> 20) + 256}):\n"
                        f"    out.write(bytes(1 << 20)); out.flush()\n"
                        f"    if oom_kills(group): sys.exit(0)\n"
                        f"sys.exit('no OOM kill')")
                try:
                    writer = subprocess.run([*_into_group(cgroup_procs), sys.executable, "-c", fill],
                                            capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
                finally:
                    shutil.rmtree(shared)  # its pages, charged to the group, freed
                assert writer.returncode == 0, writer.stderr  # it wrote until the kernel killed for room
                kills = memory.oom_kills(group)
                assert kills >= 1 and launcher.poll() is None, (kills, procs.log("launcher")[-3000:])
                view = wait_until(lambda: (v := _view(session)) and sum(n.oom_kills for n in v.nodes.values())
                                  == kills and v, 30, message=lambda: f"{kills} OOM kills in {_view(session)}")
                killed = [name for name, node in view.nodes.items() if node.oom_kills]
                for name in killed:
                    again = wait_until(lambda n=name: (s := _status(session, n)) and s.pid != first[n].pid
                                       and s.state == "running" and s, 60, message=f"{name} started again")
                    assert again.restart_reason.startswith("killed by SIGKILL: out of memory (the kernel's OOM "
                                                           "killer, in its memory cgroup "), again.restart_reason
                assert launcher.poll() is None and "out of memory (the kernel's OOM killer" in procs.log("launcher")
        finally:
            launcher.send_signal(signal.SIGINT)
            launcher.wait(30)


def _container(folder: Path, limit: int, used: int) -> list[Limit]:
    """A cgroup v1 group's files as the kernel shows them: ``used`` bytes in use, 1 MiB of it inactive file cache."""
    folder.mkdir()
    (folder / "memory.usage_in_bytes").write_text(f"{used + MiB}\n")
    (folder / "memory.stat").write_text(f"cache {2 * MiB}\ntotal_inactive_file {MiB}\n")
    return [Limit(limit, f"cgroup v1 {folder}/memory.limit_in_bytes", folder, 1)]


def test_a_voxel_grid_that_cannot_fit_is_refused_naming_its_settings(tmp_path):
    board = _container(tmp_path / "robot", 2 << 30, 100 * MiB)  # a 2 GiB container, 100 MiB in use
    default = MapperWorkerConfig(classes=["cup", "bowl", "cap"])
    check_room(default.memory_needs(), 0.9, board)  # 200 x 200 x 70 voxels x 4 float32: 45 MB
    huge = MapperWorkerConfig(classes=["cup", "bowl", "cap"], grid_max=[20.0, 20.0, 3.0])  # 2100 x 2100 x 300
    with pytest.raises(ConfigError) as refused:
        check_room(huge.memory_needs(), 0.9, board)
    message = str(refused.value)
    assert "2100 x 2100 x 300 voxels x 3 classes" in message and "grid_max, voxel_size" in message
    assert ": 20 GB - more than the 1743 MB left of 90% of 2048 MB" in message and "memory.limit_in_bytes" in message
    # tiled: only the first tile is allocated up front
    tiled = MapperWorkerConfig(classes=["cup", "bowl", "cap"], grid_max=[20.0, 20.0, 3.0], volume={"tile_size": 64})
    check_room(tiled.memory_needs(), 0.9, board)


def test_particles_that_cannot_fit_are_refused_naming_the_setting(tmp_path):
    from services.workers.localizer import LocalizerConfig

    board = _container(tmp_path / "robot", 2 << 30, 100 * MiB)
    check_room(LocalizerConfig().memory_needs(), 0.9, board)  # 10,000 particles
    with pytest.raises(ConfigError, match=r"the particle filter's 100000000 particles at least "
                                          r"\(filter.max_particles\): 3147 MB - more than"):
        check_room(LocalizerConfig(filter={"max_particles": 10**8}).memory_needs(), 0.9, board)


def test_a_voxel_grid_over_the_mappers_own_limit_stops_it_not_restarted(procs, hub):
    """volume.memory_limit_mb refused the grid with a MemoryError: exit 1, so its launcher started it again and again."""
    mapper = procs.semloc("worker", "mapper", "--connect", hub, "--robot", "r1", "--set", "classes=[cup]", "--set",
                          "volume.memory_limit_mb=10", name="mapper")  # 200 x 200 x 70 voxels x 2 float32: 21 MB
    assert mapper.wait(60) == 2, procs.log("mapper")
    assert "voxel map would need 21 MB (> memory_limit_mb=10)" in procs.log("mapper")


def _fake_machine(root: Path, cgroup: str, mounts: list[str]) -> Path:
    """A /proc whose process is in ``cgroup`` (its /proc/self/cgroup text) with these mountinfo lines."""
    proc = root / "proc" / "self"
    proc.mkdir(parents=True)
    (proc / "cgroup").write_text(cgroup)
    (proc / "mountinfo").write_text("".join(f"{line}\n" for line in mounts))
    (proc / "status").write_text("VmRSS:\t  1024 kB\nVmHWM:\t  2048 kB\n")
    (root / "proc" / "meminfo").write_text("MemTotal:  8388608 kB\nMemAvailable:  6291456 kB\n")
    return root / "proc"


def test_cgroup_v2_limits_usage_and_oom_kills_are_read_from_the_process_group(tmp_path, monkeypatch):
    """A systemd service with MemoryMax (v2): the limit of its group and of an ancestor, the working set (current less
    inactive file cache), the OOM kill count; a group at "max" has none. On a hybrid machine the v2 mount without the
    memory controller is passed over for v1's."""
    mount = tmp_path / "cgroup"
    service = mount / "robot.slice" / "semloc.service"
    service.mkdir(parents=True)
    for folder, limit in ((service, "max"), (service.parent, str(3 << 30))):
        (folder / "memory.max").write_text(f"{limit}\n")
    (service / "memory.current").write_text(f"{500 * MiB}\n")
    (service / "memory.stat").write_text(f"anon {300 * MiB}\ninactive_file {120 * MiB}\n")
    (service / "memory.events").write_text("low 0\nhigh 0\nmax 7\noom 2\noom_kill 2\n")
    (service.parent / "memory.current").write_text(f"{900 * MiB}\n")
    monkeypatch.setattr(memory, "PROC", _fake_machine(tmp_path, "0::/robot.slice/semloc.service\n", [
        f"30 1 0:26 / {mount} rw,nosuid - cgroup2 cgroup2 rw,nsdelegate"]))
    groups = memory.memory_groups()
    assert groups[:2] == [(2, service), (2, service.parent)]
    limits = memory.find_limits()
    assert [(limit.bytes, limit.source) for limit in limits] == [
        (3 << 30, f"cgroup v2 {service.parent}/memory.max"), (8 << 30, "the machine's RAM")]
    reading = memory.read(limits)
    assert (reading.rss, reading.peak, reading.limit, reading.used) == (MiB, 2 * MiB, limits[0], 900 * MiB)
    assert memory.used_bytes(memory.Limit(1 << 30, "", service, 2)) == 380 * MiB  # current less inactive file
    assert memory.oom_kills(groups[0]) == 2

    # hybrid: v1 holds the memory controller (its limit in bytes; "unlimited" is a huge number), v2 has none
    v1 = tmp_path / "v1"
    (v1 / "docker" / "abc").mkdir(parents=True)
    (v1 / "docker" / "abc" / "memory.limit_in_bytes").write_text(f"{2 << 30}\n")
    (v1 / "docker" / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    (v1 / "docker" / "abc" / "memory.oom_control").write_text("oom_kill_disable 0\nunder_oom 0\noom_kill 4\n")
    unified = tmp_path / "unified"
    unified.mkdir()
    monkeypatch.setattr(memory, "PROC", _fake_machine(tmp_path / "hybrid", "4:memory:/docker/abc\n0::/\n", [
        f"31 23 0:28 / {unified} rw - cgroup2 cgroup2 rw",
        f"32 23 0:29 / {v1} rw,relatime - cgroup cgroup rw,memory"]))
    assert memory.memory_groups()[:2] == [(1, v1 / "docker" / "abc"), (1, v1 / "docker")]
    assert [limit.bytes for limit in memory.find_limits()] == [2 << 30, 8 << 30]
    assert memory.oom_kills(memory.memory_groups()[0]) == 4


def test_without_a_cgroup_count_a_sigkill_after_a_status_near_the_limit_is_out_of_memory():
    """No memory cgroup (a board's RAM, an rlimit): the node's last Status near its limit is the evidence."""
    from schemas import MemoryStats
    from services.launcher import Heartbeat, Node, NodeSpec, RestartPolicy

    node = Node("grower", NodeSpec(), RestartPolicy(), [], {}, None)
    near = MemoryStats(used_bytes=950 * MiB, limit_bytes=1024 * MiB, limit_source="the machine's RAM", near_limit=True)
    for memory, expected in ((None, ""), (near.model_copy(update={"near_limit": False}), ""),
                             (near, "its last status: 950 MB of 1024 MB, the machine's RAM")):
        node.heartbeat = Heartbeat(0.0, Status(header=Header(robot="r1"), worker="grower", kind="grower",
                                               state="running", pid=1, started_ns=0, uptime_s=1.0, memory=memory))
        assert node.out_of_memory(group_kill=False) == expected
