"""How much memory a process holds, the limits it runs under and how near it is to them (docs/runtime.md, "Memory").

A process on a 2-8 GB board or in a container (docker --memory, a Kubernetes limit, systemd MemoryMax) is killed by
the kernel when it, or its group, exceeds its limit. The limits are found once (:func:`find_limits`): the memory
cgroup of the process and each of its ancestors that has a limit (v2 ``memory.max``, v1
``memory.limit_in_bytes``), ``RLIMIT_AS`` and ``RLIMIT_DATA``, and the machine's RAM. Each is read against what
counts towards it: a cgroup's usage less its inactive file cache (what the kernel cannot just drop: the working set
``docker stats`` and Kubernetes show), the process's address space or data segment, the machine's RAM less what it
has available.

Linux reads /proc and /sys; elsewhere only the RAM and the process's peak (``resource.getrusage``) are known.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import sys
from pathlib import Path

from services.config import ConfigError

PROC = Path("/proc")
# A cgroup v1 limit this high is no limit (the kernel's "unlimited" is the largest page-aligned 64-bit value).
V1_UNLIMITED = 1 << 62


@dataclasses.dataclass(frozen=True)
class Limit:
    """One memory limit the process is under: ``bytes``, its ``source`` in words, and how to read what counts
    towards it (``group``: the cgroup folder; ``version``: 1 or 2; ``field``: a /proc/self/status field)."""

    bytes: int
    source: str
    group: Path | None = None
    version: int = 0
    field: str = ""


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


def _int(text: str | None) -> int | None:
    try:
        return int(text.strip()) if text is not None else None
    except ValueError:
        return None


def _kilobyte_fields(path: Path) -> dict[str, int]:
    """The ``Name:  123 kB`` lines of a /proc file (``status``, ``meminfo``), in bytes."""
    fields = {}
    for line in (_read(path) or "").splitlines():
        name, _, value = line.partition(":")
        if value.strip().endswith("kB"):
            fields[name] = int(value.split()[0]) * 1024
    return fields


def _status_fields() -> dict[str, int]:
    """This process's memory (``VmRSS``, ``VmHWM``, ``VmSize``, ``VmData``...), in bytes."""
    return _kilobyte_fields(PROC / "self" / "status")


def _meminfo() -> dict[str, int]:
    return _kilobyte_fields(PROC / "meminfo")


def memory_groups(pid: int | str = "self") -> list[tuple[int, Path]]:
    """(cgroup version, folder) of the memory cgroup of process ``pid`` and of each of its ancestors up to the
    mount's root, innermost first ([] where there is none: no cgroup memory controller, or not Linux). In a
    container with its own cgroup namespace /proc shows its group as ``/``: the mount is its own group."""
    text = _read(PROC / str(pid) / "cgroup")
    if text is None:
        return []
    v1 = v2 = None
    for line in text.splitlines():
        _, controllers, path = line.split(":", 2)
        if "memory" in controllers.split(","):
            v1 = path
        elif controllers == "" and line.startswith("0:"):
            v2 = path
    mounts = {}  # filesystem type (cgroup / cgroup2) -> (mount point, mount root) of the memory hierarchy
    for line in (_read(PROC / "self" / "mountinfo") or "").splitlines():
        left, _, right = line.partition(" - ")
        parts, kind = left.split(), right.split()
        if len(parts) < 5 or len(kind) < 3:
            continue
        if kind[0] == "cgroup" and "memory" in kind[2].split(","):
            mounts["cgroup"] = (Path(parts[4]), parts[3])
        elif kind[0] == "cgroup2":
            mounts.setdefault("cgroup2", (Path(parts[4]), parts[3]))
    for version, path, kind, marker in ((1, v1, "cgroup", "memory.limit_in_bytes"),
                                        (2, v2, "cgroup2", "memory.max")):
        if path is None or kind not in mounts:
            continue
        mount, root = mounts[kind]
        relative = Path(path).relative_to(root) if Path(path).is_relative_to(root) else Path(path.lstrip("/"))
        chain = [mount / relative, *(mount / parent for parent in relative.parents)]
        groups = [(version, folder) for folder in chain if folder.is_dir()]
        if version == 2 and not any((folder / marker).exists() for _, folder in groups):
            continue  # a v2 hierarchy without the memory controller (hybrid machines: v1 holds it)
        if groups:
            return groups
    return []


def find_limits() -> list[Limit]:
    """Every memory limit this process is under (see the module's doc), found once at its start."""
    limits = []
    for version, group in memory_groups():
        if version == 1:
            value = _int(_read(group / "memory.limit_in_bytes"))
            if value is not None and value < V1_UNLIMITED:
                limits.append(Limit(value, f"cgroup v1 {group}/memory.limit_in_bytes", group, 1))
        else:
            value = _int(_read(group / "memory.max"))  # "max": none
            if value is not None:
                limits.append(Limit(value, f"cgroup v2 {group}/memory.max", group, 2))
    for name, field in (("RLIMIT_AS", "VmSize"), ("RLIMIT_DATA", "VmData")):
        soft, _ = resource.getrlimit(getattr(resource, name))
        if soft != resource.RLIM_INFINITY:
            limits.append(Limit(soft, name, field=field))
    ram = _meminfo().get("MemTotal")
    if ram is None:
        try:
            ram = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            ram = None
    if ram:
        limits.append(Limit(ram, "the machine's RAM"))
    return limits


def used_bytes(limit: Limit) -> int | None:
    """What counts towards ``limit`` now (None: cannot be read here)."""
    if limit.group is not None:
        usage = _int(_read(limit.group / ("memory.usage_in_bytes" if limit.version == 1 else "memory.current")))
        if usage is None:
            return None
        inactive = "total_inactive_file" if limit.version == 1 else "inactive_file"
        for line in (_read(limit.group / "memory.stat") or "").splitlines():
            name, _, value = line.partition(" ")
            if name == inactive:
                return max(0, usage - int(value))
        return usage
    if limit.field:
        return _status_fields().get(limit.field)
    info = _meminfo()
    if "MemTotal" in info and "MemAvailable" in info:
        return info["MemTotal"] - info["MemAvailable"]
    return None


@dataclasses.dataclass(frozen=True)
class Reading:
    """The process's resident memory now and at its peak, and the limit it is nearest to with what counts towards
    it (None where unknown)."""

    rss: int | None
    peak: int | None
    limit: Limit | None
    used: int | None

    @property
    def fraction(self) -> float | None:
        return None if self.limit is None or self.used is None else self.used / max(1, self.limit.bytes)


def read(limits: list[Limit]) -> Reading:
    """This process's memory against ``limits`` (:func:`find_limits`): the one nearest to be reached."""
    fields = _status_fields()
    rss, peak = fields.get("VmRSS"), fields.get("VmHWM")
    if peak is None:  # not Linux: the peak from getrusage (kilobytes on Linux and BSD, bytes on macOS)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    nearest, nearest_used = None, None
    for limit in limits:
        used = used_bytes(limit)
        if used is not None and (nearest is None or used / limit.bytes > nearest_used / nearest.bytes):
            nearest, nearest_used = limit, used
    return Reading(rss, peak, nearest, nearest_used)


def check_room(needs: dict[str, int], fraction: float, limits: list[Limit] | None = None) -> None:
    """ConfigError unless arrays of ``needs`` bytes (what, naming its settings -> bytes), allocated up front, fit
    within ``fraction`` of every limit with what counts towards it now: a configuration that would put the worker
    near its limit before its first frame (or past it: killed by the kernel, restarted, killed again) is refused at
    its start, naming the settings."""
    total = sum(needs.values())
    if total <= 0:
        return
    for limit in find_limits() if limits is None else limits:
        used = used_bytes(limit) or 0
        room = fraction * limit.bytes - used
        if total > room:
            asked = "; ".join(f"{what}: {mb(size)}" for what, size in needs.items())
            raise ConfigError(f"memory: {asked} - more than the {mb(max(0, room))} left of "
                              f"{fraction:.0%} of {mb(limit.bytes)} ({limit.source}; {mb(used)} in use): "
                              f"change these settings or give the process more memory")


def mb(size: float) -> str:
    return f"{size / 2**20:.0f} MB" if size < 10 << 30 else f"{size / 2**30:.0f} GB"


def oom_kills(group: tuple[int, Path] | None) -> int:
    """Processes the kernel's OOM killer has killed in memory cgroup ``group`` (version, folder), the innermost of
    :func:`memory_groups`: v1 ``memory.oom_control`` counts a kill in the victim's own group, v2 ``memory.events`` in
    it and every ancestor; a kernel before 4.13 counts none (0; 0 without a group)."""
    if group is None:
        return 0
    version, folder = group
    for line in (_read(folder / ("memory.oom_control" if version == 1 else "memory.events")) or "").splitlines():
        name, _, value = line.partition(" ")
        if name == "oom_kill":
            return _int(value) or 0
    return 0
