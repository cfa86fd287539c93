"""The localization experiment's report: every figure as JSON, the estimated trajectories as TUM files, error and
trajectory plots (PNG) and a Markdown table, next to each other."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def markdown(report: dict) -> str:
    lines = [f"# Localization: {report['dataset']}", "",
             f"preset {report['preset']['name']}, init {report['init']}, {report['frames']} frames, "
             f"view geometry {'on' if report['view'] else 'off'}", "",
             "| run | time to converge (frames) | RMSE after convergence (m) | heading RMSE (deg) | RMSE all (m) "
             "| recovery (frames) | ms/step |", "|---|---|---|---|---|---|---|"]
    fmt = lambda v, f="{:.3f}": "-" if v is None else f.format(v)  # noqa: E731
    for name, run in report["runs"].items():
        m = run["metrics"]
        recovery = ", ".join(fmt(r["frames_to_recover"], "{}") for r in m["recoveries"]) or "-"
        lines.append(f"| {name} | {fmt(m['time_to_converge_frames'], '{}')} | {fmt(m['rmse_after_convergence_m'])} "
                     f"| {fmt(m['heading_rmse_after_convergence_deg'], '{:.1f}')} | {fmt(m['rmse_m'])} | {recovery} "
                     f"| {fmt(run.get('ms_per_step'), '{:.1f}')} |")
    return "\n".join(lines) + "\n"


def _plots(report: dict, ground_truth, semantic_map, stem: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    figure, axis = plt.subplots(figsize=(9, 4.5))
    for name, run in report["runs"].items():
        errors = np.array([np.nan if e is None else e for e in run["metrics"]["errors_m"]])
        axis.plot(errors, label=name, lw=1)
    axis.axhline(report["preset"]["converge_threshold_m"], color="k", ls=":", lw=1)
    axis.set_yscale("log")
    axis.set_xlabel("frame")
    axis.set_ylabel("position error (m)")
    axis.legend(fontsize=7, ncol=2)
    axis.set_title(f"{report['dataset']}: localization error")
    figure.tight_layout()
    path = stem.with_name(stem.name + "_errors.png")
    figure.savefig(path, dpi=110)
    plt.close(figure)
    written.append(path.name)

    figure, axis = plt.subplots(figsize=(7, 7))
    positions = semantic_map.positions
    axis.scatter(positions[:, 0], positions[:, 1], c=semantic_map.class_index, cmap="tab10", marker="s", s=30,
                 label="objects")
    axis.plot(ground_truth[:, 0], ground_truth[:, 1], "k-", lw=1.5, label="ground truth")
    for name, run in report["runs"].items():
        if run["variant"] == "soft":
            estimate = np.asarray(run["estimates"])
            axis.plot(estimate[:, 0], estimate[:, 1], lw=0.8, label=name)
    span = np.ptp(ground_truth[:, :2], axis=0).max() * 0.6 + 0.5
    centre = ground_truth[:, :2].mean(axis=0)
    axis.set_xlim(centre[0] - span, centre[0] + span)
    axis.set_ylim(centre[1] - span, centre[1] + span)
    axis.set_aspect("equal")
    axis.legend(fontsize=7)
    axis.set_title(f"{report['dataset']}: trajectories (soft)")
    figure.tight_layout()
    path = stem.with_name(stem.name + "_trajectories.png")
    figure.savefig(path, dpi=110)
    plt.close(figure)
    written.append(path.name)
    return written


def write_report(result, out: Path) -> dict:
    """``out`` (JSON) and beside it ``<stem>_<run>.tum``, ``<stem>_errors.png``, ``<stem>_trajectories.png`` and
    ``<stem>.md``; returns the report as written."""
    from semloc_core.geometry import pose2d_to_transform
    from semloc_core.io.trajectory import write_tum

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.with_suffix("")
    report = result.report
    for name, run in report["runs"].items():
        tum = stem.with_name(f"{stem.name}_{name}.tum")
        write_tum(tum, result.stamps_s, np.stack([pose2d_to_transform(*p) for p in run["estimates"]]))
        run["tum"] = tum.name
    report["plots"] = _plots(report, result.ground_truth, result.semantic_map, stem)
    stem.with_name(stem.name + ".md").write_text(markdown(report))
    out.write_text(json.dumps(report, allow_nan=False))
    return report
