"""`semloc eval mapping` end to end on a simulated table top: the report against the simulator's ground truth."""

import json

import numpy as np
import pytest

from semloc_core.geometry import inside_polygon
from semloc_core.io.semantic_map import load_semantic_map
from services.commands.eval_mapping import main


@pytest.mark.parametrize("position", ["centroid", "mode"])
def test_oracle_heatmaps_map_every_object_on_the_table(tmp_path, position):
    out = tmp_path / "r.json"
    code = main(["tabletop", "--trajectory", "orbit:100", "--frames", "90", "--stride", "3", "--heatmaps", "oracle",
                 "--support", "table", "--position", position, "--threshold", "0.7", "--json", str(out)])
    assert code == 0
    report = json.loads(out.read_text())
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


def test_bad_options_are_refused_with_a_message(tmp_path, capsys):
    assert main(["tabletop", "--stride", "0", "--json", str(tmp_path / "r.json")]) == 2
    assert "--stride" in capsys.readouterr().err
    assert main(["tabletop", "--trajectory", "orbit:100", "--calibration", str(tmp_path / "missing.json"),
                 "--json", str(tmp_path / "r.json")]) == 2
    assert "calibration" in capsys.readouterr().err
