"""`semloc sim` writes a dataset that `open_dataset` reads back; bad input is reported, not raised."""

import json

import numpy as np

from semloc_core.io.dataset import open_dataset
from services.cli import main


def test_semloc_sim_writes_a_readable_dataset(tmp_path, capsys):
    out = tmp_path / "hall"
    assert main(["sim", "hall", "-o", str(out), "--frames", "3", "--seed", "4", "--no-multiview",
                 "--set", "counts={clock: 2}"]) == 0
    d = open_dataset(out)
    assert len(d) == 3 and d.image(2).shape == (256, 1024, 3)
    assert d.metadata["scenario"] == "hall" and d.metadata["seed"] == 4
    assert sum(1 for k in d.semantic_map.class_index if d.semantic_map.class_names[k] == "clock") == 2
    assert "3/3 frames" in capsys.readouterr().err


def test_semloc_sim_follows_a_trajectory_file(tmp_path):
    nodes = tmp_path / "nodes.json"
    nodes.write_text(json.dumps([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]]))
    out = tmp_path / "route"
    assert main(["sim", "route", "-o", str(out), "--frames", "4", "--trajectory", str(nodes), "--no-multiview",
                 "--set", "realism=false", "--set", "blocks=[2,2]"]) == 0
    d = open_dataset(out)
    np.testing.assert_allclose(d.poses2d[0, :2], [0.0, -0.45], atol=0.3)  # starts at node (0, 0), keeps right


def test_semloc_sim_reports_bad_options(tmp_path, capsys):
    assert main(["sim", "hall", "-o", str(tmp_path / "x"), "--set", "colour=1"]) == 2
    assert "no option" in capsys.readouterr().err
    assert main(["sim", "tabletop", "-o", str(tmp_path / "y"), "--trajectory", str(tmp_path / "missing.pose")]) == 2
    assert main(["sim", "hall", "-o", str(tmp_path / "z"), "--set", "novalue"]) == 2
    assert "expects field.path=value" in capsys.readouterr().err
