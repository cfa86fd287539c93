"""Frames published from zenoh shared memory: same bytes for every subscriber, with or without shared memory; a pool
sized from the frames a worker sends; a correct, counted fallback to plain bytes when the pool has no room, when no
pool fits (the setting, a small /dev/shm) and when /dev/shm cannot even hold a session's segment."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import services.bus as bus
from schemas import Header, Image, Status, decode, encode, keys
from services.bus import (SHM_DIR, BusConfig, FramePublisher, SharedMemoryPool, open_session, payload_bytes, query,
                          uses_shared_memory)
from services.runtime import retain_freed_memory
from tests.service.conftest import REPO_ROOT, free_port, make_image_folder, wait_until

pytestmark = pytest.mark.service


def _frame(seq: int, shape=(240, 320, 3)) -> Image:
    pixels = np.random.default_rng(seq).integers(0, 256, shape, dtype=np.uint8)
    return Image.from_pixels(Header(robot="r1", seq=seq, stamp_ns=seq + 1), pixels)


class _Collector:
    """Keeps every sample (so their shared buffers stay in use; ``hold=False``: only what they carried, as the
    runtime does) and what they carried; a payload equal to ``ignore`` (a probe) is only counted."""

    def __init__(self, ignore: bytes | None = None, hold: bool = True):
        self.samples, self.lock, self.ignore, self.ignored, self.hold = [], threading.Lock(), ignore, 0, hold

    def __call__(self, sample):
        data = payload_bytes(sample.payload)
        with self.lock:
            if data == self.ignore:
                self.ignored += 1
                return
            self.samples.append((sample if self.hold else None, data, sample.payload.as_shm() is not None))

    def payloads(self):
        with self.lock:
            return [data for _, data, _ in self.samples]


@pytest.fixture
def sessions():
    """A publisher session and two subscriber sessions: one with shared memory, one without (like a remote peer)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    with open_session(BusConfig(listen=[hub])) as publisher, \
            open_session(BusConfig(connect=[hub], listen=[f"tcp/127.0.0.1:{free_port()}"])) as local, \
            open_session(BusConfig(connect=[hub], listen=[f"tcp/127.0.0.1:{free_port()}"],
                                   shared_memory=False)) as remote:
        yield publisher, local, remote


def test_large_frames_travel_in_shared_memory_and_arrive_intact_everywhere(sessions, monkeypatch):
    publisher, local, remote = sessions
    probe = _frame(100, shape=(8, 8, 3))
    near, far = _Collector(ignore=encode(probe)), _Collector(ignore=encode(probe))
    subscribers = [local.declare_subscriber("t/img", near), remote.declare_subscriber("t/img", far)]
    monkeypatch.setattr(bus, "SHARED_MEMORY", SharedMemoryPool())  # this test's own pool, for the frames it holds
    frames = FramePublisher(publisher, "t/img", bus=BusConfig(shm_pool_frames=8))
    # Both subscriptions known to the publisher (matching says only "at least one"): a probe reaches both.
    wait_until(lambda: frames.put_frame(probe) or (near.ignored and far.ignored), 20, interval=0.1,
               message="a probe at both subscribers")
    sent = [_frame(seq) for seq in range(5)] + [_frame(9, shape=(8, 8, 3))]  # the last one is small
    for frame in sent:
        frames.put_frame(frame)
    wait_until(lambda: len(near.samples) == len(far.samples) == len(sent), 10, message="all frames delivered")
    expected = [encode(frame) for frame in sent]
    assert near.payloads() == expected and far.payloads() == expected
    assert frames.shm_frames == 5 and frames.shm_fallbacks == 0  # the small frame went as plain bytes
    assert [shm for _, _, shm in near.samples] == [True] * 5 + [False]  # handed over by reference
    assert not any(shm for _, _, shm in far.samples)  # zenoh copied them for the peer without shared memory
    decoded = decode(near.payloads()[2], expected=Image)
    np.testing.assert_array_equal(decoded.images[0].data, sent[2].images[0].data)
    for subscriber in subscribers:
        subscriber.undeclare()


@pytest.mark.parametrize("block", [False, True], ids=["drop", "block"])
def test_a_full_pool_falls_back_to_plain_bytes(sessions, monkeypatch, block):
    publisher, local, _ = sessions
    # A pool holding two frames; the subscriber keeps every sample, so no buffer ever comes back.
    monkeypatch.setattr(bus, "SHARED_MEMORY", SharedMemoryPool())
    monkeypatch.setattr(bus, "SHM_WAIT_S", 0.05)
    near = _Collector()
    subscriber = local.declare_subscriber("t/full", near)
    frames = FramePublisher(publisher, "t/full", bulk=not block, bus=BusConfig(shm_pool_frames=2))
    wait_until(lambda: frames.publisher.matching_status.matching, 10, message="subscriber matched")
    sent = [_frame(seq) for seq in range(5)]
    for frame in sent:
        frames.put_frame(frame)
        # a dropping publisher also loses a frame that finds zenoh's queue full (seen in a loaded CI run): let it
        # drain, so what is counted is the pool's fallback, not congestion
        time.sleep(0.05)
    wait_until(lambda: len(near.samples) == len(sent), 10, message="all frames delivered")
    assert near.payloads() == [encode(frame) for frame in sent]
    assert frames.shm_frames == 2 and frames.shm_fallbacks == 3
    assert bus.SHARED_MEMORY.fallbacks == {"pool full": 3}
    subscriber.undeclare()


# ---------------------------------------------------------------------------------------------- a worker's pool
FRAME_SHAPE = (480, 640, 3)  # a VGA camera: 921,840 B a frame on the wire


def _camera(procs, hub, images: Path, *settings: str, prefix: tuple[str, ...] = ()):
    return procs.semloc("worker", "camera", "--connect", hub, "--robot", "r1", "--set", f"source={images}",
                        "--set", "rate=20", "--set", "loop=true", "--set", "wait_for_subscriber_s=20",
                        "--set", "status_period_s=0.2", *[f"--set={s}" for s in settings], name="camera",
                        prefix=prefix)


def _camera_status(session, procs, published: int) -> Status:
    """The camera's Status once it has published ``published`` frames."""

    def status():
        replies = query(session, keys.status("r1", "camera"), reply_type=Status, timeout=1.0)
        image = replies[0].outputs.get("image") if replies else None  # none before its setup declared it
        return image is not None and image.published >= published and replies[0]

    return wait_until(status, 60, interval=0.2, message=lambda: f"the camera's status\n{procs.log('camera')[-3000:]}")


def _segments_held(pid: int) -> dict[str, int]:
    """The zenoh segments a process holds open (ground truth from /proc, not its own report): path -> size."""
    held = {}
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with contextlib.suppress(OSError):
            target = os.readlink(fd)
            if target.startswith(SHM_DIR) and target.endswith(".zenoh"):
                held[target] = os.path.getsize(target)
    return held


def _receive_images(session):
    near = _Collector(hold=False)
    return near, session.declare_subscriber(keys.camera_image("r1", "front"), near)


def test_a_workers_pool_holds_a_few_of_its_frames_not_64_mb(procs, hub, session, tmp_path):
    make_image_folder(tmp_path / "images", 3, shape=FRAME_SHAPE)
    near, subscriber = _receive_images(session)
    camera = _camera(procs, hub, tmp_path / "images", "bus.shm_pool_frames=3")
    status = _camera_status(session, procs, 10)
    frame_bytes = len(near.payloads()[0])
    pool = 3 * -(-frame_bytes // 4096) * 4096
    assert status.details["shared_memory"] == f"pool {pool / 2**20:.1f} MiB for frames of {frame_bytes} B"
    assert status.details["shm_frames"] >= 10 and status.details["shm_fallbacks"] == 0
    assert status.state == "running"
    held = sorted(_segments_held(camera.pid).values())
    assert pool in held, held  # what /dev/shm really holds for it
    assert sum(held) < pool + (2 << 20), held  # and nothing else large: zenoh's own 16 MiB pool is off
    assert all(shm for _, _, shm in near.samples[:5])  # the frames reached this process in shared memory
    decoded = decode(near.payloads()[0], expected=Image)
    assert decoded.images[0].data.shape == FRAME_SHAPE
    subscriber.undeclare()


def test_a_pool_too_small_for_a_frame_sends_bytes_counted_and_said(procs, hub, session, tmp_path):
    make_image_folder(tmp_path / "images", 3, shape=FRAME_SHAPE)
    near, subscriber = _receive_images(session)
    camera = _camera(procs, hub, tmp_path / "images", "bus.shm_pool_max_mb=0.5")
    status = _camera_status(session, procs, 10)
    published = status.outputs["image"].published
    assert status.state == "running"  # a working fallback, not a degraded worker
    assert status.details["shared_memory"].startswith("no pool: shm_pool_max_mb 0.5 holds no frame of 921")
    assert status.details["shm_frames"] == 0
    assert status.details["shm_fallbacks"] == status.details["shm_fallbacks: no pool"] >= published - 1
    shown = subprocess.run([sys.executable, "-m", "services.cli", "status", "--connect", hub, "--wait", "15"],
                           cwd=REPO_ROOT, capture_output=True, text=True, timeout=60).stdout
    assert "  shared memory: no pool: shm_pool_max_mb 0.5 holds no frame of 921" in shown, shown
    assert not any(size > 64 << 10 for size in _segments_held(camera.pid).values())
    wait_until(lambda: len(near.samples) >= 10, 20, message="frames as bytes")
    assert not any(shm for _, _, shm in near.samples)
    assert decode(near.payloads()[-1], expected=Image).images[0].data.shape == FRAME_SHAPE
    subscriber.undeclare()


def test_frames_under_64_kb_make_no_pool_in_zenoh_either(procs, hub, session, tmp_path):
    """zenoh's own pool for messages of 3 KB or more (16 MiB a process, committed) stays off: frames of 9 KB go as
    bytes and the worker holds no large segment."""
    make_image_folder(tmp_path / "images", 3, shape=(48, 64, 3))
    near, subscriber = _receive_images(session)
    camera = _camera(procs, hub, tmp_path / "images")
    status = _camera_status(session, procs, 10)
    assert status.details["shared_memory"] == "on, no pool (no frame of 64 KB or more sent)"
    wait_until(lambda: len(near.samples) >= 10, 20, message="frames")
    assert 3 << 10 < len(near.payloads()[0]) < 64 << 10
    assert not any(shm for _, _, shm in near.samples)
    held = _segments_held(camera.pid)
    assert not any(size > 64 << 10 for size in held.values()), held
    subscriber.undeclare()


def _small_shm(size: str) -> tuple[str, ...]:
    """A command prefix running the rest in a mount namespace of its own with a tmpfs of ``size`` on /dev/shm (as a
    container's); the test skips when that cannot be had (not root, no unshare)."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("a private /dev/shm needs root and unshare")
    mount = f"mount -t tmpfs -o size={size} tmpfs {SHM_DIR}"
    if subprocess.run(["unshare", "-m", "sh", "-c", mount], capture_output=True).returncode != 0:
        pytest.skip("unshare -m / mount tmpfs not allowed here")
    return ("unshare", "-m", "sh", "-c", f'{mount} && exec "$@"', "sh")


@pytest.mark.parametrize("size, said", [
    ("2m", "no pool: /dev/shm has 2.0 MiB free, less than a frame of {frame} B and the 4 MiB left for others"),
    ("8k", "off: zenoh could not make its session segment in /dev/shm (0.0 MiB free)"),
], ids=["no-room-for-a-pool", "no-room-for-a-session"])
def test_a_worker_with_a_small_dev_shm_sends_bytes_and_says_why(procs, hub, session, tmp_path, size, said):
    prefix = _small_shm(size)
    make_image_folder(tmp_path / "images", 3, shape=FRAME_SHAPE)
    near, subscriber = _receive_images(session)
    camera = _camera(procs, hub, tmp_path / "images", prefix=prefix)
    status = _camera_status(session, procs, 10)
    assert camera.poll() is None and status.restarts == 0
    assert status.state == "running"
    wait_until(lambda: len(near.samples) >= 10, 20, message="frames as bytes")
    assert status.details["shared_memory"] == said.format(frame=len(near.payloads()[0]))
    assert status.details["shm_frames"] == 0 and status.details["shm_fallbacks"] >= 9
    assert decode(near.payloads()[-1], expected=Image).images[0].data.shape == FRAME_SHAPE
    subscriber.undeclare()


def test_shared_memory_follows_the_bus_config(tmp_path):
    assert uses_shared_memory(BusConfig()) is True  # zenoh's default
    assert uses_shared_memory(BusConfig(shared_memory=False)) is False
    config = tmp_path / "zenoh.json5"
    config.write_text('{ transport: { shared_memory: { enabled: false } } }')
    assert uses_shared_memory(BusConfig(zenoh_config=str(config))) is False
    assert uses_shared_memory(BusConfig(zenoh_config=str(config), shared_memory=True)) is True


def test_freed_memory_is_retained_unless_the_environment_says_otherwise(monkeypatch):
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1000")
    assert retain_freed_memory() is False
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    assert retain_freed_memory() is True  # glibc (Debian) here


_FAILED_POOL = """
import json, os, numpy as np
import services.bus as bus
from schemas import Header, Image
bus._free_bytes = lambda: 1 << 30  # as if /dev/shm had room: zenoh itself is asked, and fails
with bus.open_session(bus.BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
    frames = bus.FramePublisher(session, "t/img")
    frames.put_frame(Image.from_pixels(Header(robot="r1", seq=0, stamp_ns=1), np.zeros((480, 640, 3), np.uint8)))
    left = {name: os.path.getsize(os.path.join(bus.SHM_DIR, name)) for name in os.listdir(bus.SHM_DIR)}
    print(json.dumps({"left": left, "unavailable": bus.SHARED_MEMORY.unavailable,
                      "fallbacks": bus.SHARED_MEMORY.fallbacks}))
"""


def test_a_pool_zenoh_fails_to_make_leaves_no_file_filling_dev_shm(tmp_path):
    """zenoh leaves the file of a pool it failed to make, holding what it took of /dev/shm (all of it) until the
    process ends: no session on the machine could open meanwhile. The publisher removes it."""
    prefix = _small_shm("2m")
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    run = subprocess.run([*prefix, sys.executable, "-c", _FAILED_POOL], capture_output=True, text=True, env=env,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["unavailable"].startswith("zenoh could not make a pool of ")
    assert result["unavailable"].endswith(" B in /dev/shm: Unable to create POSIX shm segment: OS error 12")
    assert result["fallbacks"] == {"no pool": 1}
    assert sum(result["left"].values()) <= 64 << 10, result["left"]  # only the session's 12 KB segment
