"""The topological map drawn at ground-truth positions (Figure 3.5), as PNG bytes for the caller to write."""

from __future__ import annotations

import io

import numpy as np


def topomap_png(positions: np.ndarray, keyframes: np.ndarray, edges: np.ndarray, loop_keyframes: np.ndarray,
                title: str) -> bytes:
    """Key-frames at their positions with the map's edges; red = key-frames that close loops.

    ``keyframes[node]`` is node ``node``'s key-frame (node ids 0..K-1); ``edges`` holds node-id pairs.
    """
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6.0, 6.0), dpi=100)
    axes = figure.add_subplot(1, 1, 1)
    positions = np.asarray(positions, float)[:, :2]
    axes.plot(positions[:, 0], positions[:, 1], "-", color="0.85", linewidth=0.8, zorder=0)
    for a, b in np.asarray(edges, np.int64).reshape(-1, 2):
        pa, pb = positions[keyframes[a]], positions[keyframes[b]]
        axes.plot([pa[0], pb[0]], [pa[1], pb[1]], "-", color="tab:blue", linewidth=0.8)
    key_positions = positions[np.asarray(keyframes, np.int64)]
    axes.scatter(key_positions[:, 0], key_positions[:, 1], s=8, color="tab:blue", zorder=2)
    if len(loop_keyframes):
        loops = positions[np.asarray(loop_keyframes, np.int64)]
        axes.scatter(loops[:, 0], loops[:, 1], s=12, color="tab:red", zorder=3)
    axes.set_aspect("equal")
    axes.set_xlabel("x (m)")
    axes.set_ylabel("y (m)")
    axes.set_title(title, fontsize=9)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", bbox_inches="tight", metadata={"Software": None})
    return buffer.getvalue()
