"""``plots/overview.png``: a still of what the viewer shows at the end of a demo, drawn with matplotlib.

A rerun viewer cannot be screenshotted on a headless machine, so this is *not* a screenshot: it draws, in the
blueprint's arrangement (services/blueprint.py), the same things the workers and the demo logged - the last camera
frame with the detector's heatmaps overlaid, the particles, estimate and ground truth on the object map, the mapped
and true objects in 3-D, the topological graph, and the error and latency time series - from the frames the demo
received and the data set's ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

CLASS_COLOURS = ["tab:red", "tab:orange", "tab:olive", "tab:purple", "tab:cyan", "tab:brown", "tab:pink"]


def _camera_panel(ax, dataset, index_of_stamp, heatmaps) -> None:
    import cv2

    if heatmaps is None or int(heatmaps.header.stamp_ns) not in index_of_stamp:
        ax.set_axis_off()
        ax.set_title("camera (no heatmaps received)")
        return
    frame = index_of_stamp[int(heatmaps.header.stamp_ns)]
    image = dataset.image(frame)
    image = image[0] if isinstance(image, (tuple, list)) else image
    entry = sorted(heatmaps.maps, key=lambda e: e.camera)[0]
    values = entry.values()
    strongest = values.max(axis=0)
    heat = cv2.resize(strongest, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_LINEAR)
    colour = cv2.applyColorMap(np.clip(heat * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    blended = cv2.addWeighted(image, 0.55, colour, 0.45, 0)
    ax.imshow(cv2.cvtColor(blended, cv2.COLOR_BGR2RGB))
    # The strongest class per heatmap cell above half of its maximum, labelled once.
    for k, name in enumerate(heatmaps.classes):
        r, c = np.unravel_index(int(np.argmax(values[k])), values[k].shape)
        if values[k, r, c] >= 0.3:
            u = (c + 0.5) * image.shape[1] / values.shape[2]
            v = (r + 0.5) * image.shape[0] / values.shape[1]
            ax.annotate(f"{name} {values[k, r, c]:.2f}", (u, v), color="white", fontsize=6,
                        bbox={"facecolor": "black", "alpha": 0.5, "pad": 1})
    ax.set_title(f"camera frame {frame} + detector heatmaps (max over classes)", fontsize=8)
    ax.set_axis_off()


def _map_panel(ax, truth, truth2d, loc, last_pose, index_of_stamp) -> None:
    for k, name in enumerate(truth.class_names):
        sel = truth.class_index == k
        ax.scatter(truth.positions[sel, 0], truth.positions[sel, 1], s=40, color=CLASS_COLOURS[k % 7],
                   label=name, zorder=3)
    if last_pose is not None and last_pose.sample is not None:
        ax.scatter(last_pose.sample[:, 0], last_pose.sample[:, 1], s=2, color="tab:red", alpha=0.5,
                   label="particles", zorder=2)
    if loc.get("available"):
        ax.plot(loc["_estimate"][:, 0], loc["_estimate"][:, 1], color="tab:blue", linewidth=0.8,
                label="estimate", zorder=2)
    ax.plot(truth2d[:, 0], truth2d[:, 1], color="tab:green", linewidth=0.8, label="ground truth", zorder=1)
    if last_pose is not None and last_pose.stamp_ns in index_of_stamp:
        x, y, theta = last_pose.pose
        ax.arrow(x, y, 0.3 * np.cos(theta), 0.3 * np.sin(theta), color="tab:blue", width=0.02, zorder=4)
        tx, ty, tt = truth2d[index_of_stamp[last_pose.stamp_ns]]
        ax.arrow(tx, ty, 0.3 * np.cos(tt), 0.3 * np.sin(tt), color="tab:green", width=0.02, zorder=4)
    ax.set_aspect("equal")
    ax.set_title("map: objects, particles, estimate (blue), ground truth (green)", fontsize=8)
    ax.legend(fontsize=5, loc="upper right", ncol=2)
    ax.tick_params(labelsize=6)


def _box_edges(centre, size):
    c, h = np.asarray(centre, float), np.maximum(np.asarray(size, float), 0.02) / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h + c
    pairs = [(0, 1), (0, 2), (0, 4), (1, 3), (1, 5), (2, 3), (2, 6), (3, 7), (4, 5), (4, 6), (5, 7), (6, 7)]
    return [(corners[a], corners[b]) for a, b in pairs]


def _objects_panel(ax, truth, mapped) -> None:
    for centre, size in zip(truth.positions, truth.sizes):
        for a, b in _box_edges(centre, size):
            ax.plot(*zip(a, b), color="grey", linewidth=0.6)
    if mapped is not None:
        for k, centre, size in zip(mapped.class_index, mapped.positions, mapped.sizes):
            for a, b in _box_edges(centre, size):
                ax.plot(*zip(a, b), color=CLASS_COLOURS[int(k) % 7], linewidth=1.0)
            ax.text(*centre, mapped.class_names[int(k)], fontsize=5)
    ax.set_title("voxel map: mapped objects (colour) vs true (grey)", fontsize=8)
    ax.tick_params(labelsize=5)
    ax.set_box_aspect((1, 1, 0.35))
    ax.view_init(elev=35, azim=-60)


def _graph_panel(ax, topomap, index_of_stamp, truth2d) -> None:
    if topomap is None or len(topomap.keyframes) == 0:
        ax.set_title("topological graph (none received)", fontsize=8)
        ax.set_axis_off()
        return
    frames = np.array([index_of_stamp.get(int(s), -1) for s in topomap.keyframe_stamps_ns])
    xy = np.where(frames[:, None] >= 0, truth2d[np.maximum(frames, 0), :2], np.nan)
    for a, b in np.asarray(topomap.edges):
        ax.plot(xy[[a, b], 0], xy[[a, b], 1], color="tab:gray", linewidth=0.6)
    ax.scatter(xy[:, 0], xy[:, 1], s=12, color="tab:blue", zorder=3)
    ax.set_aspect("equal")
    ax.set_title(f"topological graph: {len(frames)} places, {len(topomap.edges)} edges (at true positions)",
                 fontsize=8)
    ax.tick_params(labelsize=6)


def overview_png(path: Path, doc: dict, snapshot: dict, dataset, topomap) -> Path:
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    stamps = np.asarray(dataset.stamps_ns, np.int64)
    index_of_stamp = {int(s): i for i, s in enumerate(stamps)}
    truth2d = np.asarray(dataset.poses2d, float)
    truth = dataset.semantic_map
    loc, mp = doc["localization"], doc["mapping"]
    figure = Figure(figsize=(15, 8.5), dpi=100)
    grid = figure.add_gridspec(3, 3, height_ratios=[1.3, 1.2, 0.7])
    _camera_panel(figure.add_subplot(grid[0, 0]), dataset, index_of_stamp, snapshot.get("last_heatmaps"))
    poses = snapshot["poses"]
    _map_panel(figure.add_subplot(grid[0, 1]), truth, truth2d, loc, poses[-1] if poses else None, index_of_stamp)
    _graph_panel(figure.add_subplot(grid[0, 2]), topomap, index_of_stamp, truth2d)
    _objects_panel(figure.add_subplot(grid[1, 0:2], projection="3d"), truth,
                   mp.get("_predicted") if mp.get("available") else None)
    ax = figure.add_subplot(grid[1, 2])
    if loc.get("available"):
        t = (stamps[loc["_frames"]] - stamps[0]) * 1e-9
        ax.plot(t, loc["_errors"], color="tab:blue", linewidth=0.8, label="position error (m)")
    ax.set_title("localization error vs ground truth", fontsize=8)
    ax.set_xlabel("capture time (s)", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.grid(True, alpha=0.3)
    ax = figure.add_subplot(grid[2, :])
    images = snapshot["images"].arrivals
    series = {"detector": snapshot["heatlines"].arrivals,
              "localizer": {r.stamp_ns: r.arrived for r in poses},
              "loopclosure": snapshot["loopclosure"]["events"].arrivals if "events" in snapshot["loopclosure"]
              else {}}
    for name, arrivals in series.items():
        points = sorted((index_of_stamp[s], (a - images[s]) * 1e3) for s, a in arrivals.items()
                        if s in images and s in index_of_stamp)
        if points:
            frames, ms = zip(*points)
            ax.plot((stamps[list(frames)] - stamps[0]) * 1e-9, ms, linewidth=0.8, label=name)
    ax.set_yscale("log")  # a worker's one-off stall (e.g. learning a vocabulary) would flatten everything else
    ax.set_title("camera -> output latency per stage (ms, log scale)", fontsize=8)
    ax.set_xlabel("capture time (s)", fontsize=7)
    ax.legend(fontsize=6)
    ax.grid(True, alpha=0.3)
    ax.tick_params(labelsize=6)
    figure.suptitle("semloc demo - a still drawn from the logged data in the viewer's layout (not a screenshot)",
                    fontsize=10)
    figure.tight_layout()
    from services.demo_report import save_figure

    save_figure(figure, path, bbox_inches=None)
    return path
