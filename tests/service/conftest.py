"""Service-test helpers: real worker processes over a real zenoh session on loopback.

Every test gets its own hub endpoint on a free port (xdist-safe); multicast scouting is off; every process started
here is in its own process group and is killed at the end of the test.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from schemas import decode
from services.bus import BusConfig, free_port, open_session  # noqa: F401 - free_port: the tests import it from here

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.service


def wait_until(predicate, timeout: float, interval: float = 0.05, message="condition"):
    """``predicate()``'s first truthy value within ``timeout`` s; ``message`` (or a callable giving it at the
    timeout, e.g. the state last seen) says what was awaited."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            awaited = message() if callable(message) else message
            raise AssertionError(f"timed out after {timeout} s waiting for {awaited}")
        time.sleep(interval)


def tcp_listener(port: int = 0) -> socket.socket:
    """A TCP socket listening on 127.0.0.1:``port`` (0: a free one; ``getsockname()`` tells), its port reusable at
    once after it closes (a test's server that goes down and comes back on it)."""
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", port))
    listener.listen(16)
    return listener


def limit_file_size(pid: int, size: int | None) -> None:
    """Writes of process ``pid`` (0: this one) past ``size`` bytes of a file fail with EFBIG, "File too large" (None:
    no limit): a disk that stops taking writes, without root. Python ignores SIGXFSZ, so the write fails instead of
    the process being killed."""
    _, hard = resource.prlimit(pid, resource.RLIMIT_FSIZE)
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (hard if size is None else size, hard))


@contextlib.contextmanager
def file_size_limit(size: int):
    """This process's files limited to ``size`` bytes while the block runs (:func:`limit_file_size`)."""
    limit_file_size(0, size)
    try:
        yield
    finally:
        limit_file_size(0, None)


def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class Processes:
    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.started: list[subprocess.Popen] = []

    def semloc(self, *args: str, name: str = "proc", prefix: tuple[str, ...] = ()) -> subprocess.Popen:
        """``semloc ARGS`` as a process of its own (``prefix``: a command that runs it, e.g. in a namespace)."""
        log = open(self.tmp_path / f"{name}.log", "ab")  # noqa: SIM115 - the child keeps its copy
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
        env = {k: v for k, v in env.items() if not k.startswith("SEMLOC__")}
        process = subprocess.Popen([*prefix, sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT, env=env,
                                   stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   start_new_session=True)
        log.close()
        self.started.append(process)
        return process

    def play(self, hub: str, source, rate: float) -> subprocess.Popen:
        """The camera worker (robot r1) playing ``source`` at ``rate`` into ``hub`` once a subscriber listens."""
        return self.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={source}", "--set",
                           f"rate={rate}", "--set", "wait_for_subscriber_s=20", "--log-level", "WARNING", name="camera")

    def log(self, name: str) -> str:
        path = self.tmp_path / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def cleanup(self) -> None:
        for process in self.started:
            if process.poll() is None:
                try:
                    os.killpg(process.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                process.wait()


@pytest.fixture
def procs(tmp_path):
    processes = Processes(tmp_path)
    yield processes
    processes.cleanup()


@pytest.fixture
def hub() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def session(hub):
    """The test's own zenoh session, listening on the hub endpoint (workers connect to it)."""
    with open_session(BusConfig(listen=[hub])) as zenoh_session:
        yield zenoh_session


def repack(frame, edit) -> bytes:
    """The wire bytes of ``frame`` with its msgpack header map edited by ``edit(body)`` (the data section kept):
    hostile payloads that no model would build."""
    import struct

    import msgpack

    from schemas import encode

    data = encode(frame)
    (length,) = struct.unpack_from("<I", data)
    body = msgpack.unpackb(data[4 : 4 + length])
    edit(body)
    header = msgpack.packb(body)
    data_start = 4 + length + (-(4 + length)) % 8
    return struct.pack("<I", len(header)) + header + bytes((-(4 + len(header))) % 8) + data[data_start:]


class Received:
    """Frames decoded off the bus as they arrive, a list per name (``keys_by_name``: name -> key expression).
    ``received[name]`` is a copy taken under the lock zenoh's threads append under; leaving the ``with`` block (or
    ``close()``) undeclares the subscribers."""

    def __init__(self, session, keys_by_name: dict[str, str]):
        self.frames: dict[str, list] = {name: [] for name in keys_by_name}
        self.lock = threading.Lock()

        def keep(name):
            def on_sample(sample):
                frame = decode(sample.payload.to_bytes())
                with self.lock:
                    self.frames[name].append(frame)
            return on_sample

        self.subscribers = [session.declare_subscriber(key, keep(name)) for name, key in keys_by_name.items()]

    def __getitem__(self, name: str) -> list:
        with self.lock:
            return list(self.frames[name])

    def close(self) -> None:
        for subscriber in self.subscribers:
            subscriber.undeclare()

    def __enter__(self) -> "Received":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_image_folder(path: Path, count: int, shape=(24, 32, 3)) -> list[Path]:
    """``count`` distinct PNG images named 0.png .. (count-1).png (natural order differs from lexicographic)."""
    import cv2
    import numpy as np

    path.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(count)
    files = []
    for index in range(count):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        image[0, 0] = index % 256
        file = path / f"{index}.png"
        cv2.imwrite(str(file), image)
        files.append(file)
    return files


@contextlib.contextmanager
def spinning(worker):
    """Run an in-process ``worker``'s event loop on a thread (its main thread, yielded) while the block runs."""
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            worker.spin_once(0.05)

    thread = threading.Thread(target=spin, name="worker-main")
    thread.start()
    try:
        yield thread
    finally:
        stop.set()
        thread.join(5)


@contextlib.contextmanager
def memory_cgroup(limit_bytes: int):
    """A fresh memory cgroup under this process's own, limited to ``limit_bytes`` (v1 ``memory.limit_in_bytes``
    or v2 ``memory.max``): yields the file a pid is written to (``cgroup.procs``) to put a process in it. Skips the
    test where no group can be made (no root, no memory controller). Removed at the end, even on failure: processes
    still in it are moved back to the parent first."""
    import uuid

    from services.memory import memory_groups

    groups = memory_groups(os.getpid())
    if not groups:
        pytest.skip("no memory cgroup controller here")
    version, parent = groups[0]
    group = parent / f"semloc-test-{uuid.uuid4().hex[:8]}"
    try:
        group.mkdir()
    except OSError as error:
        pytest.skip(f"cannot make a memory cgroup under {parent}: {error.strerror}")
    try:
        try:
            (group / ("memory.limit_in_bytes" if version == 1 else "memory.max")).write_text(str(limit_bytes))
        except OSError as error:
            pytest.skip(f"cannot limit memory cgroup {group}: {error.strerror}")
        yield group / "cgroup.procs"
    finally:
        for _ in range(50):
            for pid in (group / "cgroup.procs").read_text().split():
                with contextlib.suppress(OSError):  # gone meanwhile
                    (parent / "cgroup.procs").write_text(pid)
            try:
                group.rmdir()
                break
            except OSError:
                time.sleep(0.1)
