"""The rerun viewer layout of a semloc run, declared in code once: every recording of ``semloc up``, ``semloc worker``
and ``semloc demo`` carries it (services/viz.py).

Entity paths are the workers' (docs/runtime.md: ``/<robot>/<node>/...``) plus the demo's own ``/<robot>/demo/...``:

* camera: ``camera/image``; detector: ``detector/heatmap/<class>`` (image with the class's heatmap overlaid),
  ``detector/heatlines/<class>``;
* localizer: ``localizer/map/*`` (object map), ``localizer/particles``, ``localizer/estimate/*``,
  ``localizer/ground_truth/*``;
* loop closure: ``loopclosure/**`` (its own logs, its ``graph``) and the demo's ``demo/topology`` graph (keyframes and
  loop edges) and ``demo/places`` (the places at the poses recorded while localized, in the map view);
* mapper: ``mapper/objects`` (boxes), ``mapper/hot_voxels``, ``mapper/camera`` (frustum); the demo adds the true
  objects and trajectories in ``demo/world``;
* time series: ``demo/errors/*`` (localization error against ground truth; without the demo the localizer's
  ``error_m``) and the localizer's ``state`` (0 localized, 1 uncertain, 2 lost), ``demo/latency/*`` (per stage).

The time panel follows the ``capture`` timeline (the camera's capture stamp): every worker logs on it, whereas
``frame`` is each worker's own output sequence number.
"""

from __future__ import annotations

from collections.abc import Sequence


def semloc_blueprint(robot: str, classes: Sequence[str], nodes: dict[str, str] | None = None):
    """The layout: camera and heatmaps | map and voxel objects | topological graph, errors and latency.

    ``nodes`` maps a role (camera, detector, localizer, mapper, loopclosure, demo) to its node name when a graph
    renames them."""
    import rerun.blueprint as rrb

    names = {"camera": "camera", "detector": "detector", "localizer": "localizer", "mapper": "mapper",
             "loopclosure": "loopclosure", "demo": "demo", **(nodes or {})}
    root = f"/{robot}"
    path = {role: f"{root}/{name}" for role, name in names.items()}
    heatmaps = [rrb.Spatial2DView(name=f"heatmap: {name}", origin=f"{path['detector']}/heatmap/{name}")
                for name in classes]
    camera_column = rrb.Vertical(
        rrb.Spatial2DView(name="camera", origin=f"{path['camera']}/image"),
        rrb.Tabs(*heatmaps, name="detector heatmaps") if heatmaps else
        rrb.Spatial2DView(name="detector heatmaps", origin=f"{path['detector']}/heatmap"),
        row_shares=[1, 1],
    )
    map_view = rrb.Spatial2DView(
        name="map: particles, estimate (blue), ground truth (green)",
        origin=path["localizer"],
        contents=["+ $origin/map/**", "+ $origin/particles", "+ $origin/estimate/**", "+ $origin/ground_truth/**",
                  f"+ {path['demo']}/places"],
    )
    world_view = rrb.Spatial3DView(
        name="voxel objects: mapped (boxes, hot voxels) and true (grey)",
        origin=root,
        contents=[f"+ {path['mapper']}/**", f"+ {path['demo']}/world/**"],
    )
    series_column = rrb.Vertical(
        # The demo logs its own graph and errors; a run without it shows the loop closure's and the localizer's.
        rrb.GraphView(name="topological graph (loop closure)", origin=root,
                      contents=[f"+ {path['demo']}/topology/**", f"+ {path['loopclosure']}/graph"]),
        rrb.TimeSeriesView(name="localization error vs ground truth", origin=root,
                           contents=[f"+ {path['demo']}/errors/**", f"+ {path['localizer']}/error_m",
                                     f"+ {path['localizer']}/state"]),
        rrb.TimeSeriesView(name="camera -> output latency per stage (ms)", origin=f"{path['demo']}/latency"),
        row_shares=[2, 1, 1],
    )
    return rrb.Blueprint(
        rrb.Horizontal(camera_column, rrb.Vertical(map_view, world_view), series_column, column_shares=[1, 1, 1]),
        rrb.TimePanel(timeline="capture"),
        collapse_panels=False,
    )
