"""`semloc sim` writes a dataset that `open_dataset` reads back, for every scenario it offers; bad input is
reported, not raised."""

import json

import numpy as np
import pytest

from semloc_core.io.dataset import open_dataset
from services.cli import build_parser, main

SCENARIOS = ("tabletop", "hall", "route", "aliased")


def test_these_are_the_scenarios_sim_offers():
    [sim] = [a.choices["sim"] for a in build_parser()._actions if getattr(a, "choices", None) and "sim" in a.choices]
    [scenario] = [a for a in sim._actions if a.dest == "scenario"]
    assert tuple(scenario.choices) == SCENARIOS


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_semloc_sim_writes_every_scenario_it_offers(scenario, tmp_path, capsys):
    """With its multi-view exemplars (aliased, a world without objects, crashed writing them)."""
    out = tmp_path / scenario
    assert main(["sim", scenario, "-o", str(out), "--frames", "3", "--exemplars", "none", "--quiet"]) == 0
    assert capsys.readouterr().out.strip() == f"wrote 3 frames of {scenario} (seed 0) to {out}"
    d = open_dataset(out)
    assert len(d) == 3 and d.image(2).ndim == 3 and d.poses2d.shape == (3, 3)
    if scenario == "aliased":  # corridors only: no object classes, no views
        assert d.metadata["classes"] == [] and d.multiview_dir is None
    else:
        views = d.multiview_exemplars()
        assert set(views) == set(d.metadata["classes"]) and all(views.values())


def test_eval_loopclosure_on_a_route_without_loop_pairs_says_so(tmp_path, capsys):
    out = tmp_path / "aliased"
    assert main(["sim", "aliased", "-o", str(out), "--frames", "12", "--no-multiview", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["eval", "loopclosure", str(out), "-o", str(tmp_path / "eval.json"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("semloc eval loopclosure: aliased: no loop pairs to find") and len(err.splitlines()) == 1
    assert not (tmp_path / "eval.json").exists()


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
