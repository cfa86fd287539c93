"""What a decompression bomb costs a detector worker, against a clean frame of the same declared size, same run.

    .venv/bin/python benchmarks/decompression_bomb.py [--frames 3]

A detector worker (a small template library, a 640x480 calibration) is started here on loopback. It gets
``--frames`` clean 640x480 PNG images, then as many bombs: a 12000x12000 black PNG (~430 KB on the wire, 432 MB
decoded) declared 640x480, one at a time (each counted by the worker before the next is sent). For each phase: the
median over its frames of the worker's CPU time a frame (its threads' run time, from /proc), its peak RSS (VmHWM) before
and after, and how the frames were counted (processed, rejected per reason, errors). Prints both, the ratio bomb /
clean of the median CPU a frame and the load average. Before the compressed header was checked (issue 28) a bomb was
decoded: ~3 s of CPU and +840 MB of peak RSS each; now it is rejected on decode (``image_header``).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import yaml
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from schemas import Header, Image, Status, encode, keys  # noqa: E402
from schemas.camera import CameraImage  # noqa: E402
from semloc_core.camera import PinholeCamera  # noqa: E402
from services.bus import BusConfig, free_port, open_session, query  # noqa: E402
from semloc_core.io.camera_model import save_camera  # noqa: E402


def _figures(pid: int) -> tuple[float, float]:
    """(CPU seconds, peak RSS in MB) of a process. CPU: the nanosecond run times of its threads (schedstat), since
    /proc's utime + stime count 10 ms ticks, as long as a clean frame."""
    cpu = 0.0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(FileNotFoundError):  # a thread that ended meanwhile
            cpu += int((task / "schedstat").read_text().split()[0]) * 1e-9
    peak = next(int(line.split()[1]) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                if line.startswith("VmHWM"))
    return cpu, peak / 1024


def _frame(seq: int, data: np.ndarray) -> bytes:
    """A one-camera Image declaring 640x480 with these PNG bytes, built without validation (as an attacker would)."""
    image = CameraImage.model_construct(camera=0, width=640, height=480, encoding="bgr8", compression="png",
                                        data=data, T_body_cam=None)
    return encode(Image.model_construct(header=Header(robot="bench", seq=seq, stamp_ns=seq), images=[image]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3, help="clean frames, then as many bombs")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="semloc-bomb-"))
    rng = np.random.default_rng(0)
    for name in ("box", "disc"):
        (folder / "library" / name).mkdir(parents=True)
        exemplar = np.full((60, 60, 3), 255, np.uint8)
        cv2.rectangle(exemplar, (10, 10), (50, 50), (0, 0, 200), -1) if name == "box" else cv2.circle(
            exemplar, (30, 30), 20, (200, 0, 0), -1)
        cv2.imwrite(str(folder / "library" / name / "0.png"), exemplar)
    (folder / "detector.yaml").write_text(yaml.safe_dump({"kind": "templates", "templates": "library",
                                                          "scales": [1.0]}))
    calibration = save_camera(PinholeCamera.from_fov(640, 480, 60.0), folder / "camera.yaml")
    hub = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(BusConfig(listen=[hub]))
    worker = subprocess.Popen([sys.executable, "-m", "services.cli", "worker", "detector", "--connect", hub,
                               "--robot", "bench", "--set", f"detector_file={folder / 'detector.yaml'}", "--set",
                               f"calibration={calibration}", "--log-level", "ERROR",
                               "--set", "inputs.image.policy=lossless"],
                              cwd=ROOT, stdin=subprocess.DEVNULL)
    try:
        def status() -> Status | None:
            replies = query(session, keys.status("bench", "detector"), reply_type=Status, timeout=1.0)
            return replies[0] if replies else None

        deadline = time.monotonic() + 120
        while status() is None:
            if worker.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the detector worker did not start")
            time.sleep(0.2)
        publisher = session.declare_publisher(keys.camera_image("bench"),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        while not publisher.matching_status.matching:
            time.sleep(0.05)
        clean = cv2.imencode(".png", rng.integers(0, 256, (480, 640, 3), dtype=np.uint8))[1].reshape(-1)
        bomb = cv2.imencode(".png", np.zeros((12000, 12000, 3), np.uint8))[1].reshape(-1)
        results = {}
        sent = 0
        for phase, data in (("clean", clean), ("bomb", bomb)):
            peak0 = _figures(worker.pid)[1]
            cpu = []
            for _ in range(args.frames):
                cpu0 = _figures(worker.pid)[0]
                publisher.put(_frame(sent, data))
                sent += 1
                while (s := status()) is None or s.processed + s.rejected + s.errors < sent:
                    time.sleep(0.05)
                cpu.append(_figures(worker.pid)[0] - cpu0)
            peak1 = _figures(worker.pid)[1]
            entry = s.inputs["image"]
            results[phase] = statistics.median(cpu)
            print(f"{phase:5s}: {len(_frame(0, data)) / 1024:6.0f} KB a frame, CPU {1e3 * results[phase]:.2f} ms a "
                  f"frame (median of {args.frames}), peak RSS {peak0:.0f} -> {peak1:.0f} MB; so far processed "
                  f"{entry.processed}, rejected {entry.rejected_reasons}, errors {entry.errors}")
        print(f"bomb / clean CPU a frame (medians): {results['bomb'] / max(results['clean'], 1e-9):.2f}; load average "
              f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    finally:
        worker.terminate()
        worker.wait(30)
        session.close()


if __name__ == "__main__":
    main()
