"""Heatlines kept between runs of the localization experiment: one ``.npz`` per dataset and heatline source in the
spec's ``cache`` folder, keyed by what they depend on (a run whose frames are a subset of a cached run's reuses
it)."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from semloc_core.experiments.localization_detector import DETECTOR_SETTINGS, detector_heatlines


def looks(dataset) -> str:
    """What a simulated scene's appearance was made from (its options: the classes textured with real object crops,
    none when the data folder was absent, and the rest), so that a cache made with one is not served for the other;
    empty for a recorded data set."""
    options = getattr(dataset, "options", None)
    return repr(sorted(options.items())) if isinstance(options, dict) else ""


def fingerprint(dataset) -> str:
    """A digest of what a cached heatline depends on: the map, the poses, the first frame's visible boxes (a
    simulator that changed its scenes must not be served stale heatlines) and the scene's looks."""
    digest = hashlib.sha256()
    digest.update(looks(dataset).encode())
    semantic_map = dataset.semantic_map
    for array in (semantic_map.positions, semantic_map.sizes, semantic_map.class_index, np.asarray(dataset.poses2d)):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    digest.update(repr(semantic_map.class_names).encode())
    for obj in dataset.visible_objects(0):
        digest.update(repr((obj.object_index, tuple(float(v) for v in obj.visible_box))).encode())
    return digest.hexdigest()[:16]


def cached_heatlines(path: Path | None, indices, compute: Callable[[], dict], key: str = "") -> dict:
    """Heatlines per frame index, from ``path`` when it holds these frames of this ``key``, else computed (and
    stored)."""
    from semloc_core.bearing import Heatlines

    if path is not None and path.exists():
        with np.load(path, allow_pickle=False) as data:
            stored = {int(i): k for k, i in enumerate(data["indices"])}
            if str(data["key"]) == key and all(int(i) in stored for i in indices):
                classes = tuple(str(c) for c in data["classes"])
                return {int(i): Heatlines(classes, data["scores"][stored[int(i)]], data["observed"][stored[int(i)]])
                        for i in indices}
    heatlines = compute()
    if path is not None:
        first = heatlines[int(indices[0])]
        np.savez_compressed(path, indices=np.asarray(indices), key=np.asarray(key), classes=np.asarray(first.classes),
                            scores=np.stack([heatlines[int(i)].scores for i in indices]),
                            observed=np.stack([heatlines[int(i)].observed for i in indices]))
    return heatlines


def heatline_cache_name(dataset: str, scenario_seed: int, trajectory: str | None, camera: str | None,
                        what: str) -> str:
    """The file name of one dataset's heatlines of one source in a cache folder."""
    parts = [dataset.replace("/", "_").replace(":", "-"), f"s{scenario_seed}",
             *([camera.replace(":", "-")] if camera else []), Path(trajectory).stem if trajectory else "orbit", what]
    return "_".join(parts) + ".npz"


def views_key(chosen: dict | None) -> str:
    """What the chosen exemplar views add to a detector cache's key (nothing for the front views)."""
    return f" {sorted(chosen.items())}" if chosen else ""


def detector_cache_what(templates: str) -> str:
    """The detector source's part of a heatline cache name, per ``templates`` choice."""
    return "detector" if templates == "front" else f"detector_{templates}"


def cache_path(spec, what: str) -> Path | None:
    """One file per dataset of ``spec`` (a LocalizationSpec) and source; None without a cache folder."""
    if not spec.cache:
        return None
    folder = Path(spec.cache)
    folder.mkdir(parents=True, exist_ok=True)
    return folder / heatline_cache_name(spec.dataset, spec.scenario.seed, spec.scenario.trajectory,
                                        spec.scenario.camera, what)


def heatline_key(spec, dataset, preset) -> str:
    """The key a dataset's cached heatlines are stored under (empty without a cache)."""
    return f"{fingerprint(dataset)} min_box_px={preset.min_box_px}" if spec.cache else ""


def cached_detector_heatlines(spec, dataset, indices, key: str, chosen: dict | None,
                              log: Callable[[str], None]) -> dict:
    """The detector's heatlines of ``indices``: from the cache (one file per ``templates`` choice) when it holds
    them for this ``key`` and these views, else computed and stored."""
    return cached_heatlines(cache_path(spec, detector_cache_what(spec.templates)), indices,
                            lambda: detector_heatlines(dataset, indices, log, chosen),
                            f"{key} {sorted(DETECTOR_SETTINGS.items())}{views_key(chosen)}")
