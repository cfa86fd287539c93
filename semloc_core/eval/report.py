"""Plots (PNG bytes, matplotlib Agg) and tables (Markdown text, JSON-ready dicts) of evaluation figures.

Nothing here touches files: callers write the returned bytes / text (``semloc eval`` puts them next to its JSON).
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import asdict, is_dataclass

import numpy as np

from semloc_core.eval.pr import RECALL_LEVELS, PRCurve, interpolated_precision


def _figure(width: float = 6.0, height: float = 4.5):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100)


def _png(figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", bbox_inches="tight", metadata={"Software": None})
    return buffer.getvalue()


def pr_plot_png(curves: dict[str, PRCurve], title: str = "precision-recall", interpolated: bool = False,
                dashed: dict[str, PRCurve] | None = None) -> bytes:
    """PR curves (raw steps, or Everingham-interpolated at r = 0, 0.01, ..., 1) with optional dashed companions
    (e.g. the same score after inference)."""
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    colours = {}
    for style, group in (("-", curves), ("--", dashed or {})):
        for label, curve in group.items():
            colour = colours.get(label)
            if interpolated:
                line, = ax.plot(RECALL_LEVELS, interpolated_precision(curve), style, color=colour,
                                label=label if style == "-" else f"{label} (dashed)")
            else:
                line, = ax.step(np.concatenate([[0.0], curve.recall]),
                                np.concatenate([[curve.precision[0]], curve.precision]), style, where="post",
                                color=colour, label=label if style == "-" else f"{label} (dashed)")
            colours.setdefault(label, line.get_color())
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("interpolated precision" if interpolated else "precision")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    return _png(fig)


def error_plot_png(times_s, errors: dict[str, np.ndarray], title: str = "localization error",
                   ylabel: str = "position error (m)", threshold: float | None = None) -> bytes:
    """Error against time for one or more runs/methods, with the convergence threshold as a dotted line."""
    fig = _figure(7.0, 3.8)
    ax = fig.add_subplot(1, 1, 1)
    t = np.asarray(times_s, float)
    for label, e in errors.items():
        ax.plot(t, np.asarray(e, float), label=label, linewidth=1.2)
    if threshold is not None:
        ax.axhline(threshold, color="k", linestyle=":", linewidth=1, label=f"threshold {threshold:g}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig)


def matrix_png(matrix, title: str = "", cmap: str = "gray_r") -> bytes:
    """A pair matrix (similarity or ground truth) as an image, row = later frame."""
    fig = _figure(5.0, 5.0)
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(np.asarray(matrix, float), cmap=cmap, interpolation="nearest")
    ax.set_xlabel("frame j")
    ax.set_ylabel("frame i")
    ax.set_title(title)
    return _png(fig)


def _cell(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if math.isnan(value):
            return "nan"
        return f"{value:.4g}"
    return str(value)


def markdown_table(rows: list[dict], columns: list[str] | None = None) -> str:
    """A Markdown table of dict rows (columns: given order, else the keys of the first row)."""
    if not rows:
        return ""
    columns = columns or list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row.get(c)) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def jsonable(value):
    """Numpy arrays and scalars, dataclasses, tuples and paths turned into plain JSON types (NaN -> None)."""
    if is_dataclass(value) and not isinstance(value, type):
        return jsonable(asdict(value))
    if isinstance(value, PRCurve):
        return value.to_dict()
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if hasattr(value, "__fspath__"):
        return str(value)
    return value


def json_text(document) -> str:
    return json.dumps(jsonable(document), indent=1, allow_nan=False)
