"""Helpers of the end-to-end tests that run a graph (`semloc up`) as a process group."""

from __future__ import annotations

import os
import signal
import subprocess


def stop(process: subprocess.Popen, timeout: float = 30) -> None:
    """The graph's launcher and its workers interrupted, killed after ``timeout`` s."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGINT)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()


def tracking_options(start, state_dir) -> list[str]:
    """`semloc up deploy/local.yaml` settings: every frame through every worker, however loaded the machine (latest
    queues drop frames there: the key-frames' stamps could then have no pose estimate), and the localizer tracking
    from the true ``start`` (x, y, theta; a global start takes longer than a short data set); the workers' state in
    ``state_dir``."""
    return [*(f"--set=nodes.{node}.inputs.{name}={{policy: lossless, depth: 64}}"
              for node, name in (("detector", "image"), ("loopclosure", "image"), ("localizer", "heatlines"))),
            "--set", f"nodes.localizer.config.initial_pose=[{start[0]}, {start[1]}, {start[2]}]",
            "--set", "nodes.localizer.config.initial_covariance=[0.01, 0.01, 0.01]",
            "--set", f"state_dir={state_dir}"]
