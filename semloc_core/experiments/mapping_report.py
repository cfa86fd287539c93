"""The mapping experiment's report, next to its JSON ``<stem>.json``: ``<stem>.md`` (the table), per scene the
ground truth ``<stem>_<scene>_truth.json``, per scene and heatmap source the extracted objects
``<stem>_<scene>_<source>_objects.json`` and a top view ``<stem>_<scene>_<source>.png`` (and with ``save_volumes``
the voxel map ``.npz`` and its hot voxels ``_hot.ply``), and with ``calibration.fit`` the fitted calibration
``<stem>_calibration.json``."""

from __future__ import annotations

import json
from pathlib import Path

TABLE_COLUMNS = ["scene", "heatmaps", "score", "large found", "FP", "precision", "recall", "mean err 3-D (cm)"]


def top_view_png(mapper, truth, predicted, title: str) -> bytes:
    """Per class: max over height of the score volume, ground truth (circles) and extracted objects (crosses)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classes = mapper.class_names
    fig, axes = plt.subplots(1, len(classes), figsize=(3.2 * len(classes), 3.4), squeeze=False)
    lo, hi = mapper.grid.bounds
    for c, (name, ax) in enumerate(zip(classes, axes[0])):
        score = mapper.score_volume(c, normalise=True, min_views=10).max(axis=0)
        ax.imshow(score, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="magma")
        gt = truth.positions[truth.class_index == truth.class_names.index(name)] if name in truth.class_names else []
        for p in gt:
            ax.add_patch(plt.Circle(p[:2], 0.05, fill=False, color="cyan", lw=1.2))
        for o in predicted:
            if o["class"] == name:
                ax.plot(*o["position"][:2], "x", color="lime" if o["match"] >= 0 else "red", ms=8, mew=2)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()


def markdown(result) -> str:
    from semloc_core.eval.report import markdown_table

    return markdown_table(result.rows, TABLE_COLUMNS)


def calibration_path(out: Path) -> Path:
    """Where the fitted calibration of a report ``out`` goes."""
    out = Path(out)
    return out.with_name(f"{out.with_suffix('').name}_calibration.json")


def write_report(result, out: Path) -> None:
    from semloc_core.eval.report import json_text
    from semloc_core.io.semantic_map import save_semantic_map

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("").name
    spec = result.spec
    for name in dict.fromkeys(s.name for s in result.scenes):
        scene = next(s for s in result.scenes if s.name == name)
        save_semantic_map(scene.dataset.semantic_map, out.with_name(f"{stem}_{name}_truth.json"))
    mode = result.report["primary_mode"]
    for scene in result.scenes:
        name, source = scene.name, scene.source
        save_semantic_map(scene.predicted_map, out.with_name(f"{stem}_{name}_{source}_objects.json"))
        out.with_name(f"{stem}_{name}_{source}.png").write_bytes(
            top_view_png(scene.mapper, scene.dataset.semantic_map, scene.predicted,
                         f"{name}, {source} heatmaps ({mode})"))
        if spec.save_volumes:
            from semloc_core.io.voxel_map import save_ply, save_voxel_snapshot

            save_voxel_snapshot(out.with_name(f"{stem}_{name}_{source}.npz"), scene.mapper.snapshot())
            cloud = scene.mapper.hot_voxels(0.5, min_views=spec.extraction.min_views)
            save_ply(out.with_name(f"{stem}_{name}_{source}_hot.ply"), cloud["points"], cloud["colors"],
                     {"score": cloud["score"], "class_index": cloud["class_index"]})
    if result.calibration is not None:
        calibration_path(out).write_text(json.dumps(result.calibration, indent=2) + "\n")
    out.write_text(json_text(result.report))
    out.with_suffix(".md").write_text(markdown(result) + "\n")
