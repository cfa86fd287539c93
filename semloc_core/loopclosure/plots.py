"""Figures for loop-closure evaluation (matplotlib Figure objects; the caller saves them)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from semloc_core.loopclosure.metrics import RECALL_LEVELS, PrCurve

_COLOURS = {"dp": "tab:red", "sift": "tab:blue", "sym": "tab:green", "bow": "tab:gray", "engine": "tab:purple"}


def pr_figure(curves: dict[str, tuple[PrCurve, PrCurve | None]], title: str) -> Figure:
    """Interpolated precision-recall per score: raw (solid) and after inference (dashed), as Figure 3.4."""
    figure = Figure(figsize=(6.5, 5.0))
    axes = figure.add_subplot(1, 1, 1)
    for name, (raw, after) in curves.items():
        colour = _COLOURS.get(name)
        axes.plot(RECALL_LEVELS, raw.interpolated(), "-", color=colour, label=f"{name} raw (AP {raw.average_precision:.3f})")
        if after is not None:
            axes.plot(RECALL_LEVELS, after.interpolated(), "--", color=colour,
                      label=f"{name} + inference (AP {after.average_precision:.3f})")
    axes.set_xlabel("recall")
    axes.set_ylabel("interpolated precision")
    axes.set_xlim(0, 1)
    axes.set_ylim(0, 1.02)
    axes.grid(True, alpha=0.3)
    axes.legend(fontsize=7, loc="lower left")
    axes.set_title(title, fontsize=9)
    return figure


def matrices_figure(panels: dict[str, np.ndarray], title: str) -> Figure:
    """Side-by-side images of (n, n) matrices (similarity, decisions, ground truth); -inf shown blank."""
    figure = Figure(figsize=(4.2 * len(panels), 4.2))
    for k, (name, matrix) in enumerate(panels.items()):
        axes = figure.add_subplot(1, len(panels), k + 1)
        shown = np.where(np.isfinite(matrix), matrix, np.nan).astype(float)
        axes.imshow(shown, cmap="viridis", interpolation="nearest")
        axes.set_title(name, fontsize=9)
        axes.set_xlabel("later frame j")
        axes.set_ylabel("earlier frame i")
    figure.suptitle(title, fontsize=10)
    return figure


def topomap_figure(positions: np.ndarray, keyframes: np.ndarray, edges: np.ndarray, loop_keyframes: np.ndarray,
                   title: str) -> Figure:
    """Key-frames at their ground-truth positions with the map's edges (Figure 3.5); red = loop-closure nodes.

    ``keyframes[node]`` is node ``node``'s key-frame (node ids 0..K-1); ``edges`` holds node-id pairs.
    """
    figure = Figure(figsize=(6.0, 6.0))
    axes = figure.add_subplot(1, 1, 1)
    axes.plot(positions[:, 0], positions[:, 1], "-", color="0.85", linewidth=0.8, zorder=0)
    key_pos = positions[keyframes]
    for a, b in edges:
        pa, pb = positions[keyframes[a]], positions[keyframes[b]]
        axes.plot([pa[0], pb[0]], [pa[1], pb[1]], "-", color="tab:blue", linewidth=0.8)
    axes.scatter(key_pos[:, 0], key_pos[:, 1], s=8, color="tab:blue", zorder=2)
    if len(loop_keyframes):
        lp = positions[loop_keyframes]
        axes.scatter(lp[:, 0], lp[:, 1], s=12, color="tab:red", zorder=3)
    axes.set_aspect("equal")
    axes.set_title(title, fontsize=9)
    return figure
