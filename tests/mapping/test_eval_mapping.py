"""The mapping experiment (`semloc eval mapping`) end to end on a simulated table top: the report against the
simulator's ground truth."""

import json

import numpy as np
import pytest

from semloc_core.geometry import inside_polygon
from semloc_core.io.semantic_map import load_semantic_map
from semloc_core.io.voxel_map import load_voxel_snapshot
from semloc_core.mapping import VoxelMapper
from semloc_core.mapping.existence import ExistenceCurve
from semloc_core.experiments.mapping import MappingSpec, run
from semloc_core.experiments.mapping_report import calibration_path, write_report
from services.cli import main


def evaluate(out, **fields) -> dict:
    """Run the experiment of ``fields`` (a MappingSpec) and write its report to ``out``; the report."""
    result = run(MappingSpec.model_validate(fields))
    write_report(result, out)
    return json.loads(out.read_text())


ORACLE = {"dataset": "tabletop", "heatmaps": "oracle"}


@pytest.mark.parametrize("position", ["centroid", "mode"])
def test_oracle_heatmaps_map_every_object_on_the_table(tmp_path, position):
    out = tmp_path / "r.json"
    report = evaluate(out, **ORACLE, trajectories=["orbit:100"], frames=90, stride=3,
                      extraction={"support": "table", "position": position, "threshold": 0.7})
    scene = report["scenes"]["orbit100"]["sources"]["oracle"]["normalised"]
    assert scene["large_objects"] >= 8 and scene["large_found"] == scene["large_objects"]
    assert scene["fp"] == 0 and scene["max_error_3d_m"] < 0.02
    settings = scene["extraction"]
    assert settings["position"] == position and len(settings["support_polygon"]) == 4
    polygon = np.asarray(settings["support_polygon"])
    positions = np.array([p["position"] for p in scene["predicted"]])
    assert inside_polygon(positions[:, 0], positions[:, 1], polygon).all()
    assert np.all(positions[:, 2] >= settings["support_z"])
    mapped = load_semantic_map(tmp_path / "r_orbit100_oracle_objects.json")
    truth = load_semantic_map(tmp_path / "r_orbit100_truth.json")
    assert len(mapped) == scene["objects_predicted"] and len(truth) == scene["objects_truth"]
    assert (tmp_path / "r_orbit100_oracle.png").stat().st_size > 0


def test_calibration_fitted_on_one_orbit_carries_to_another(tmp_path):
    # calibration.fit fits class scales, threshold, top-hat, cross-class and resting heights on a calibration scene;
    # calibration.file applies them to another. The oracle's Gaussians peak at each object's centre: the scales are
    # the heat an object reaches (near 1), every setting finds every object, and the tie-break by position error
    # keeps centroid heights (resting heights follow the region's top, which a Gaussian narrower than the object
    # does not reach).
    common = {**ORACLE, "frames": 240, "stride": 3, "extraction": {"support": "table", "position": "centroid"}}
    evaluate(tmp_path / "cal.json", **common, trajectories=["orbit:100"], calibration={"fit": True})
    calibration = calibration_path(tmp_path / "cal.json")
    assert calibration == tmp_path / "cal_calibration.json"
    fitted = json.loads(calibration.read_text())["oracle"]["normalised"]
    assert set(fitted) >= {"threshold", "tophat", "cross_class", "resting", "class_scales", "fits", "existence"}
    curve = ExistenceCurve.from_document(fitted["existence"])  # fitted on that scene's candidates
    assert curve.reference == fitted["threshold"] and curve.samples >= curve.real >= 8
    (fit,) = fitted["fits"]
    assert fit["f1"] == 1.0 and fit["fp"] == 0 and fit["fn"] == 0 and fit["mean_error_3d_m"] < 0.01
    # the threshold: inside the gap between the candidates the best F1 rejects and keeps, which holds the sweep's
    # tied thresholds
    low, high = fit["gap"]
    assert fitted["resting"] is False and low < fitted["threshold"] < high
    assert low <= fit["plateau"][0] and fit["plateau"][-1] <= high
    assert all(0.5 < scale <= 1.2 for scale in fitted["class_scales"].values())
    out = tmp_path / "r.json"
    report = evaluate(out, **common, trajectories=["orbit:101"], calibration={"file": str(calibration)})
    scene = report["scenes"]["orbit101"]["sources"]["oracle"]["normalised"]
    settings = scene["extraction"]
    assert settings["calibrated"] and settings["threshold"] == fitted["threshold"]
    assert settings["class_scales"] == fitted["class_scales"] and settings["resting"] is False
    # each exported object carries its existence from the calibration's curve
    assert settings["existence"] == fitted["existence"]
    np.testing.assert_allclose([p["existence"] for p in scene["predicted"]],
                               curve(np.array([p["score"] for p in scene["predicted"]])))
    np.testing.assert_allclose(load_semantic_map(tmp_path / "r_orbit101_oracle_objects.json").existence,
                               [p["existence"] for p in scene["predicted"]])
    # 80 frames of another walk: a box seen from few directions may land a little over 5 cm off (a miss and a
    # false positive), not more.
    assert scene["large_objects"] >= 8 and scene["large_found"] >= scene["large_objects"] - 1 and scene["fp"] <= 1


def test_occlusion_takes_hidden_voxels_out_of_the_views(tmp_path):
    """mapper.occlusion integrates each frame with the simulator's depth: no voxel is seen more often than without it,
    those behind the objects and clutter are seen less, and the objects are still found."""
    views, found = {}, {}
    for label, occlusion in (("open", False), ("occlusion", True)):
        out = tmp_path / label / "r.json"
        report = evaluate(out, **ORACLE, trajectories=["orbit:100"], frames=90, stride=3, save_volumes=True,
                          extraction={"support": "table", "threshold": 0.7}, mapper={"occlusion": occlusion})
        assert report["occlusion_margin_m"] == (0.15 if occlusion else None)
        scene = report["scenes"]["orbit100"]["sources"]["oracle"]["normalised"]
        found[label] = (scene["large_found"], scene["large_objects"])
        snapshot = load_voxel_snapshot(out.with_name("r_orbit100_oracle.npz"))
        views[label] = VoxelMapper.from_snapshot(snapshot).view_count()
    assert np.all(views["occlusion"] <= views["open"] + 1e-4)
    hidden = views["open"] - views["occlusion"] > 1.0
    assert hidden.mean() > 0.05
    assert found["occlusion"][0] == found["occlusion"][1] == found["open"][1] >= 8


def test_bad_settings_are_refused_with_a_message(tmp_path, capsys):
    def refused(*argv: str) -> str:
        assert main(["eval", "mapping", *argv, "-o", str(tmp_path / "r.json")]) == 2
        error = capsys.readouterr().err
        assert error.startswith("semloc eval mapping: ") and error.count("\n") == 1
        return error

    assert "stride" in refused("tabletop", "--set", "stride=0")
    assert "calibration" in refused("tabletop", "--set", "trajectories=[orbit:100]",
                                    "--set", f"calibration.file={tmp_path / 'missing.json'}")
    assert "occlusion needs depth images" in refused(str(tmp_path), "--set", "mapper.occlusion=true")
    assert "prominence" in refused("tabletop", "--set", "extraction.prominence=1.0")
    assert "no dataset given" in refused()
    for extra, message in [(["mapper.scale_depth=true"], "kind: linear"),
                           (["mapper.scale_depth=true", "heatmaps=oracle"], "needs detector heatmaps"),
                           (["mapper.level_reach=-1"], "level_reach"),
                           (["mapper.occlusion=true", "mapper.occlusion_margin=-0.1"], "occlusion_margin"),
                           (["no_such_field=1"], "no_such_field")]:
        sets = [a for item in extra for a in ("--set", item)]
        assert message in refused("tabletop", "--set", "trajectories=[orbit:100]", *sets)


def test_closing_the_loop_reports_both_maps_and_a_random_error_reference(tmp_path, shared_data):
    poses = shared_data / "rgbd_scenes_v2_poses"
    out = tmp_path / "r.json"
    report = evaluate(out, **ORACLE, trajectories=[str(poses / "13.pose")], stride=6,
                      extraction={"support": "table", "position": "centroid", "threshold": 0.7},
                      localize={"trajectory": str(poses / "14.pose"), "frames": 200, "seeds": 1, "noise_draws": 2})
    loop = report["closing_the_loop"]
    assert set(loop["runs"]) == {f"{m}-{k}" for m in "AB" for k in ("truth", "mapped", "noise0", "noise1")}
    for model in "AB":
        truth_rmse = loop["runs"][f"{model}-truth"]["median_rmse_after_convergence_m"]
        assert truth_rmse is not None and truth_rmse < 0.10
        assert loop[f"ratio_{model}"] == loop["runs"][f"{model}-mapped"]["median_rmse_after_convergence_m"] / truth_rmse
        assert len(loop["noise_reference"][f"ratios_{model}"]) == 2
    # The reference's error is the mapped objects' planar RMS error against the ground truth.
    mapped = load_semantic_map(tmp_path / "r_13_oracle_objects.json")
    truth = load_semantic_map(tmp_path / "r_13_truth.json")
    errors = [np.min([np.linalg.norm(p[:2] - q[:2]) for q, c in zip(truth.positions, truth.class_index)
                      if truth.class_names[c] == mapped.class_names[k]]) for p, k in zip(mapped.positions,
                                                                                       mapped.class_index)]
    assert loop["noise_reference"]["planar_rms_error_m"] == pytest.approx(np.sqrt(np.mean(np.square(errors))),
                                                                          rel=1e-6)
    assert 0 < loop["noise_reference"]["planar_rms_error_m"] < 0.03


def test_closing_the_loop_with_the_detectors_heatlines(tmp_path, shared_data):
    # The loop as a robot runs it: the localizer observes the template detector's heatlines, with score
    # likelihoods and bearing model fitted on other worlds (here two short ones, 06 and 11: every class of 13's
    # world), and localizes with the mapped and the ground-truth maps.
    poses = shared_data / "rgbd_scenes_v2_poses"
    calibration = []
    for scene in ("06", "11"):
        short = tmp_path / f"{scene}.pose"
        short.write_text("\n".join((poses / f"{scene}.pose").read_text().splitlines()[:300]) + "\n")
        calibration.append(str(short))
    cache = tmp_path / "cache"
    fields = {**ORACLE, "trajectories": [str(poses / "13.pose")], "stride": 6, "cache": str(cache),
              "extraction": {"support": "table", "position": "centroid", "threshold": 0.7},
              "localize": {"trajectory": str(poses / "14.pose"), "frames": 120, "seeds": 1,
                           "observations": "detector", "calibration_trajectories": calibration}}
    loop = evaluate(tmp_path / "r.json", **fields)["closing_the_loop"]
    assert "error" not in loop and loop["observations"].startswith("template detector heatlines")
    assert loop["frames"] == 60 and set(loop["runs"]) == {f"{m}-{k}" for m in "AB" for k in ("truth", "mapped")}
    for name, run in loop["runs"].items():
        assert len(run["per_seed"]) == 1 and np.isfinite(run["median_rmse_m"]), name
    # Model B weighs the detector's heatlines with the bearing model fitted on the calibration worlds: a tempered
    # likelihood (exponent = 1 / correlated bins, below 1; the synthetic heatlines' is 1) and a fitted sigma.
    bearing = loop["bearing_model"]
    assert 0 < bearing["exponent_model_b"] < 1 and 0 < bearing["sigma_deg"] < 20
    # The detector's heatlines of the localized frames are kept: a second run reads them back identically.
    (kept,) = cache.glob("loop_14_in_13_*_detector_heatlines.npz")
    with np.load(kept, allow_pickle=False) as data:
        assert len(data["indices"]) == 60 and np.isfinite(data["scores"]).all()
    assert evaluate(tmp_path / "again.json", **fields)["closing_the_loop"]["runs"] == loop["runs"]


def test_closing_the_loop_with_the_detector_needs_its_calibration_worlds(tmp_path, shared_data, capsys):
    poses = shared_data / "rgbd_scenes_v2_poses"
    code = main(["eval", "mapping", "tabletop", "--set", f"trajectories=[{poses / '13.pose'}]", "--set",
                 "heatmaps=oracle", "--set", f"localize.trajectory={poses / '14.pose'}", "--set",
                 "localize.observations=detector", "--set",
                 f"localize.calibration_trajectories=[{tmp_path / 'missing.pose'}]", "-o", str(tmp_path / "r.json")])
    assert code == 2 and "missing.pose" in capsys.readouterr().err


def test_a_false_positive_of_a_class_the_scene_lacks_counts_in_its_class():
    from semloc_core.io.semantic_map import SemanticMap
    from semloc_core.mapping import ExtractionConfig, VoxelGrid, VoxelMapper
    from semloc_core.mapping.extraction import MappedObject
    from semloc_core.experiments.mapping_scene import score_scene

    grid = VoxelGrid.from_bounds([0, 0, 0], [1, 1, 0.4], 0.02)
    mapper = VoxelMapper(grid, ("bowl", "cereal_box"))
    truth = SemanticMap.from_objects([{"class": "bowl", "position": [0.3, 0.3, 0.05], "size": [0.18, 0.18, 0.08]}])
    objects = [MappedObject("bowl", np.array([0.31, 0.3, 0.05]), np.full(3, 0.1), 1.0),
               MappedObject("cereal_box", np.array([0.7, 0.7, 0.15]), np.full(3, 0.1), 0.8)]
    scene = score_scene(mapper, truth, ExtractionConfig(), 0.05, 0.10, objects)
    assert scene["fp"] == 1 and scene["per_class"]["cereal_box"]["fp"] == 1
    assert scene["per_class"]["cereal_box"]["large_objects"] == 0
    assert sum(c["fp"] or 0 for c in scene["per_class"].values()) == scene["fp"]
