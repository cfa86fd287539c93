"""The mapper worker's ``extraction_file``: the extraction `semloc eval mapping` fits (or a demo world)
fitted, applied as it was fitted and checked as ExtractionConfig checks its fields; a bad file is refused with the
reason."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from semloc_core.experiments.demo_world import MAPPER_SETTINGS
from semloc_core.experiments.mapping_fits import merge_extraction_fits
from semloc_core.experiments.tabletop import TABLETOP_SIZES
from services.workers.mapper import MapperWorkerConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


def _fit(threshold: float, tophat: float, cross_class: bool, resting: bool, scale: float) -> dict:
    return {"threshold": threshold, "tophat": tophat, "cross_class": cross_class, "resting": resting,
            "class_scales": {"bowl": scale, "cap": 2 * scale},
            "class_sizes": {name: list(size) for name, size in TABLETOP_SIZES.items()}}


def _write(path: Path, document) -> Path:
    path.write_text(json.dumps(document))
    return path


def test_the_worker_applies_the_merged_fit(tmp_path):
    # Three calibration scenes, as calibration.fit merges them: majority top-hat, medians of the scenes that chose
    # it, majority cross-class and resting heights.
    merged = merge_extraction_fits([_fit(0.7, 2.0, True, False, 4.0), _fit(0.8, 2.0, True, True, 6.0),
                                    _fit(0.5, 0.0, False, True, 9.0)])
    path = _write(tmp_path / "calibration.json", {"detector": {"normalised": merged, "sum": {"threshold": 0.3}}})
    config = MapperWorkerConfig(extraction_file=str(path), extraction={"support_z": 0.75, "threshold": 3.0,
                                                                       "tophat": 0.0})
    extraction = config.extraction
    assert extraction.threshold == pytest.approx(0.75) and extraction.tophat == 2.0
    assert extraction.cross_class is True and extraction.resting is False
    assert extraction.class_scales == {"bowl": 5.0, "cap": 10.0}
    assert tuple(extraction.size_of("soda_can")) == TABLETOP_SIZES["soda_can"]
    # Resting heights need the surface they rest on.
    with pytest.raises(ValidationError, match="fitted with resting heights: give extraction.support_z"):
        MapperWorkerConfig(extraction_file=str(_write(tmp_path / "resting.json", {"detector": {"normalised": {
            "threshold": 0.7, "resting": True}}})))
    # The score mode picks the entry: sum scores have their own fit.
    assert MapperWorkerConfig(extraction_file=str(path), extraction={"normalise": False}).extraction.threshold == 0.3
    assert extraction.existence is None  # a calibration without an existence curve: objects certain


def test_the_worker_gives_objects_the_existence_the_calibration_fitted(tmp_path):
    curve = {"reference": 0.65, "intercept": 1.06, "slope": 9.5, "samples": 69, "real": 57}
    path = _write(tmp_path / "calibration.json", {"detector": {"normalised": {"threshold": 0.65, "existence": curve}}})
    extraction = MapperWorkerConfig(extraction_file=str(path)).extraction
    assert extraction.existence.to_document() == curve
    assert extraction.existence(0.71)[()] < extraction.existence(1.2)[()] < 1.0


def test_a_top_hat_tie_goes_to_the_better_fitting_scenes_whatever_their_order():
    def fit(tophat, f1, threshold):
        return {**_fit(threshold, tophat, True, False, 4.0), "f1": f1}

    fits = [fit(0.0, 1.0, 0.8), fit(2.0, 1.0, 0.7), fit(0.0, 1.0, 0.8), fit(2.0, 0.9, 0.65), fit(0.0, 1.0, 0.65),
            fit(2.0, 0.95, 0.55)]
    for order in (fits, fits[::-1], fits[1:] + fits[:1]):
        merged = merge_extraction_fits(order)
        assert merged["tophat"] == 0.0 and merged["threshold"] == 0.8
    # equal fits too: the smaller factor (less taken away from the volumes)
    even = [fit(2.0, 1.0, 0.7), fit(0.0, 1.0, 0.8)]
    assert merge_extraction_fits(even)["tophat"] == merge_extraction_fits(even[::-1])["tophat"] == 0.0


@pytest.mark.parametrize("document, reason", [
    (None, "cannot read"),
    ("not json", "cannot read"),
    ({"oracle": {"normalised": {"threshold": 0.5}}}, "no 'detector' -> 'normalised' entry"),
    ({"detector": [0.7]}, "no 'detector' -> 'normalised' entry"),
    ({"detector": {"normalised": {"tophat": 2.0}}}, "has no threshold"),
    ({"detector": {"normalised": {"threshold": "high"}}}, "normalised.threshold"),
    ({"detector": {"normalised": {"threshold": float("nan")}}}, "normalised.threshold"),
    ({"detector": {"normalised": {"threshold": 0.7, "cross_class": 1}}}, "normalised.cross_class"),
    ({"detector": {"normalised": {"threshold": 0.7, "class_scales": [1, 2]}}}, "normalised.class_scales"),
    ({"detector": {"normalised": {"threshold": 0.7, "class_scales": {"bowl": -1.0}}}},
     "normalised.class_scales.bowl: Input should be greater than 0"),
    ({"detector": {"normalised": {"threshold": 0.7, "class_sizes": {"bowl": [0.1, 0.1]}}}},
     r"normalised.class_sizes.bowl\[2\]: Field required"),
    ({"detector": {"normalised": {"threshold": 0.7, "existence": {"reference": 0.7, "intercept": 1.0}}}},
     "normalised.existence"),
    ({"detector": {"normalised": {"threshold": 0.7, "existence": {"reference": 0.7, "intercept": 1.0,
                                                                 "slope": -2.0}}}},
     "normalised.existence.slope: Input should be greater than or equal to 0"),
], ids=["missing", "not-json", "no-detector-entry", "detector-not-a-dict", "no-threshold", "text", "nan", "int-for-bool", "list-for-dict",
        "negative-scale", "two-sided-size", "existence-incomplete", "existence-falling"])
def test_a_bad_extraction_file_is_refused_with_the_reason(tmp_path, document, reason):
    path = tmp_path / "calibration.json"
    if document == "not json":
        path.write_text("{threshold: 0.7")
    elif document is not None:
        path.write_text(json.dumps(document))
    with pytest.raises(ValidationError, match=reason):
        MapperWorkerConfig(extraction_file=str(path))


def test_the_demo_mapper_runs_with_the_settings_its_extraction_is_fitted_with():
    graph = yaml.safe_load((REPO_ROOT / "deploy" / "demo.yaml").read_text())
    mapper = graph["nodes"]["mapper"]["config"]
    set_in_graph = {"voxel_size": mapper["voxel_size"], "heatmap_background": mapper["volume"]["heatmap_background"],
                    "min_views": mapper["extraction"]["min_views"], "position": mapper["extraction"]["position"]}
    assert set_in_graph == MAPPER_SETTINGS
    assert mapper["extraction_file"].endswith("mapper_extraction.json")


def test_the_scale_depth_file_of_a_calibration_is_read(tmp_path):
    """``scale_depth_file``: the depth per scale `semloc eval mapping` fitted with mapper.scale_depth (the
    same calibration file can also be the extraction_file)."""
    fit = {"scales": [1.2, 0.85], "classes": {"bowl": {"depth_per_scale": 0.0047, "log_spread": 0.12,
                                                       "samples": 687}, "cap": {"depth_per_scale": 0.0092}}}
    path = _write(tmp_path / "calibration.json", {"detector": {"scale_depth": fit, "normalised": {"threshold": 0.65}}})
    config = MapperWorkerConfig(scale_depth_file=str(path), extraction_file=str(path), volume={"level_reach": 1})
    assert config.scale_depth() == {"scales": [1.2, 0.85], "classes": {"bowl": 0.0047, "cap": 0.0092}}
    assert config.volume.level_reach == 1 and config.extraction.threshold == 0.65
    assert MapperWorkerConfig().scale_depth() is None


@pytest.mark.parametrize("document, reason", [
    ("not json", "cannot read"),
    ({"detector": {"normalised": {"threshold": 0.5}}}, "no 'detector' -> 'scale_depth' entry"),
    ({"detector": {"scale_depth": {"scales": [], "classes": {"bowl": {"depth_per_scale": 0.01}}}}}, "scales"),
    ({"detector": {"scale_depth": {"scales": [1.0, -0.5], "classes": {"bowl": {"depth_per_scale": 0.01}}}}}, "scales"),
    ({"detector": {"scale_depth": {"scales": [1.0], "classes": {}}}}, "classes"),
    ({"detector": {"scale_depth": {"scales": [1.0], "classes": {"bowl": {"depth_per_scale": 0}}}}},
     "bowl.depth_per_scale"),
    ({"detector": {"scale_depth": {"scales": [1.0], "classes": {"bowl": 0.01}}}}, "bowl.depth_per_scale"),
])
def test_a_bad_scale_depth_file_is_refused_with_the_reason(tmp_path, document, reason):
    path = tmp_path / "scale_depth.json"
    path.write_text(document if isinstance(document, str) else json.dumps(document))
    with pytest.raises(ValidationError, match=reason):
        MapperWorkerConfig(scale_depth_file=str(path))


def test_scale_depth_and_likelihood_ratios_are_refused_together(tmp_path):
    path = _write(tmp_path / "sd.json", {"detector": {"scale_depth": {"scales": [1.0], "classes": {
        "bowl": {"depth_per_scale": 0.01}}}}})
    with pytest.raises(ValidationError, match="do not combine"):
        MapperWorkerConfig(scale_depth_file=str(path), volume={"heatmap_llr": {"bowl": [-1.0, 1.0]}})
