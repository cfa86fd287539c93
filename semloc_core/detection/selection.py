"""Choosing each class's exemplars on a training world: which single views the §4.3 templates should use.

The thesis builds a class's templates from one exemplar image and its mirror (§4.5.1) and names the limit that
follows: one view does not generalise to other viewpoints or instances (§4.5.1, §4.6). Rendering or photographing
more views is easy (``semloc sim`` writes 24 per class in ``exemplars_multiview/``), but taking the maximum over
many views is not free: every extra template also answers somewhere in the background, and a view that is a plain
grey box (the side of a payphone) answers everywhere. Measured on the station hall, matching all 24 views of every
class lost more than it won (docs/detection.md).

So the views are chosen, per class, by what they do on a *training* world with ground truth — never on the frames
evaluated: greedy forward selection of exemplars, each step adding the exemplar (with its mirror, as at run time)
whose maximum with those already chosen gives the heatline the most hits under the soft rule of the accuracy table
(``evaluation.score_soft``: for N usable objects of the class in a frame, its N strongest peaks, hit within the
tolerance). Selection stops when an exemplar adds no hit, or at ``max_per_class``. The heatline of a set of
exemplars is the per-bin maximum of their own heatlines (the class heatmap is their maximum, and the column
maximum commutes with it), so every exemplar is matched once per frame and every candidate set is scored from
those lines.

Pure: heatlines and ground truth in, a choice out; ``semloc_core.experiments.template_selection`` runs it on a dataset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semloc_core.bearing import Heatlines
from semloc_core.detection.evaluation import GroundTruthObject, score_soft


@dataclass(frozen=True)
class SelectionStep:
    """One exemplar added to a class, and what the class heatline scores on the training frames with it."""

    class_name: str
    exemplar: int        # index into the candidate exemplars
    hits: int
    misses: int
    hallucinations: int


def exemplar_of_templates(templates) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """Group a detector's templates by exemplar: (template -> exemplar index, [(class, source)] per exemplar).

    An exemplar and its mirror (§4.5.1) are one candidate: they share ``Template.source``.
    """
    keys: dict[tuple[str, str], int] = {}
    index = np.empty(len(templates), np.int64)
    for k, template in enumerate(templates):
        key = (template.class_name, template.source)
        index[k] = keys.setdefault(key, len(keys))
    return index, list(keys)


def per_exemplar(per_template: np.ndarray, exemplar_index: np.ndarray, exemplars: int) -> np.ndarray:
    """Max over each exemplar's templates: (templates, ...) -> (exemplars, ...)."""
    out = np.zeros((exemplars,) + per_template.shape[1:], np.float32)
    for k in range(exemplars):
        out[k] = per_template[exemplar_index == k].max(axis=0)
    return out


def _score(lines: np.ndarray, observed: np.ndarray, objects, class_name: str, tolerance_deg: float):
    """Soft hits, misses, hallucinations of one class heatline per frame, summed over the frames."""
    hits = misses = hallucinations = 0
    for line, seen, frame_objects in zip(lines, observed, objects):
        counts = score_soft(Heatlines((class_name,), line[None], seen), frame_objects, tolerance_deg)[class_name]
        hits, misses, hallucinations = hits + counts.hits, misses + counts.misses, hallucinations + counts.hallucinations
    return hits, misses, hallucinations


def select_exemplars(lines: np.ndarray, observed: np.ndarray, exemplar_class, objects: list[list[GroundTruthObject]],
                     max_per_class: int = 4, tolerance_deg: float = 5.0) -> dict[str, list[SelectionStep]]:
    """Greedy forward selection of exemplars per class (module docstring).

    ``lines`` (frames, exemplars, bins): each exemplar's own heatline per training frame; ``observed`` (frames,
    bins); ``exemplar_class``: the class of each exemplar; ``objects``: the ground-truth objects of each frame
    (``evaluation.frame_objects``; ``usable`` marks the ones that must be found). Returns, per class with at least
    one usable object, the steps in the order taken (ties: fewer hallucinations, then the lower index). A class
    whose objects never appear usable gets no step: the caller decides (e.g. keep its canonical exemplar).
    """
    lines = np.asarray(lines, np.float32)
    observed = np.asarray(observed, bool)
    exemplar_class = list(exemplar_class)
    if lines.ndim != 3 or lines.shape[1] != len(exemplar_class):
        raise ValueError(f"lines must be (frames, {len(exemplar_class)} exemplars, bins), got {lines.shape}")
    if observed.shape != (lines.shape[0], lines.shape[2]):
        raise ValueError(f"observed must be (frames, bins) = {(lines.shape[0], lines.shape[2])}, got {observed.shape}")
    if len(objects) != lines.shape[0]:
        raise ValueError(f"{len(objects)} frames of objects for {lines.shape[0]} frames of heatlines")
    if max_per_class < 1:
        raise ValueError("max_per_class must be >= 1")
    chosen: dict[str, list[SelectionStep]] = {}
    for class_name in dict.fromkeys(exemplar_class):
        frames = [f for f, frame in enumerate(objects) if any(o.class_name == class_name and o.usable for o in frame)]
        if not frames:
            continue
        candidates = [k for k, name in enumerate(exemplar_class) if name == class_name]
        frame_objects = [objects[f] for f in frames]
        current = np.zeros((len(frames), lines.shape[2]), np.float32)
        steps: list[SelectionStep] = []
        while len(steps) < max_per_class:
            taken = {step.exemplar for step in steps}
            best = None
            for k in candidates:
                if k in taken:
                    continue
                hits, misses, false = _score(np.maximum(current, lines[frames, k]), observed[frames], frame_objects,
                                             class_name, tolerance_deg)
                if best is None or (hits, -false) > (best.hits, -best.hallucinations):
                    best = SelectionStep(class_name, k, hits, misses, false)
            if best is None or (steps and best.hits <= steps[-1].hits):
                break
            steps.append(best)
            np.maximum(current, lines[frames, best.exemplar], out=current)
        chosen[class_name] = steps
    return chosen
