"""Graphs as an installed semloc finds them: built-in graphs by name, relative paths read from the graph file's
folder (whatever the working directory), overrides from the working directory; generated worlds in the cache
folder ($SEMLOC_CACHE_DIR over the platform's)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import yaml

from semloc_core.experiments.demo_world import default_cache_dir
from services.config import ConfigError
from services.launcher import builtin_graphs, builtin_graphs_dir, find_graph, load_graph

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_built_in_graphs_are_found_by_name_from_anywhere(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert {"local", "demo", "camera-sink", "two-machines/base", "two-machines/robot"} <= set(builtin_graphs())
    assert find_graph("local") == builtin_graphs_dir() / "local.yaml"
    assert find_graph("two-machines/robot.yaml").samefile(REPO_ROOT / "deploy" / "two-machines" / "robot.yaml")
    graph = load_graph("local")
    # deploy/local.yaml names its files relative to itself
    assert Path(graph.nodes["localizer"].config["map"]).samefile(REPO_ROOT / "deploy" / "local" / "map.json")
    assert graph.nodes["camera"].config["source"] == "0"  # a device index, not a path
    robot = load_graph("two-machines/robot")
    assert Path(robot.hub_zenoh_config).samefile(REPO_ROOT / "deploy" / "two-machines" / "robot-router.json5")
    assert Path(robot.secure_hub_zenoh_config).samefile(REPO_ROOT / "deploy" / "secure" / "robot-router.json5")
    for name in ("nosuch", "../deploy/local", str(tmp_path / "local")):
        with pytest.raises(ConfigError, match="graph file not found"):
            find_graph(name)


def test_the_robot_router_retries_the_base_station_the_same_with_or_without_tls():
    """The radio link drops and comes back (docs/deploy.md, "When the link drops"): the robot's router under
    ``--secure`` retries the base station as often as the plain one (zenoh's router default backs off to 4 s)."""
    import zenoh

    plain = zenoh.Config.from_file(str(REPO_ROOT / "deploy" / "two-machines" / "robot-router.json5"))
    secure = zenoh.Config.from_json5((REPO_ROOT / "deploy" / "secure" / "robot-router.json5").read_text())
    retry = json.loads(plain.get_json("connect/retry"))
    assert retry["period_max_ms"] <= 1000
    assert json.loads(secure.get_json("connect/retry")) == retry


def test_paths_in_a_graph_are_read_from_its_folder_and_overrides_from_here(tmp_path, monkeypatch):
    (tmp_path / "robot" / "files").mkdir(parents=True)
    (tmp_path / "robot" / "files" / "map.json").write_text("{}")
    (tmp_path / "here").mkdir()
    (tmp_path / "here" / "mine.json").write_text("{}")
    graph_file = tmp_path / "robot" / "g.yaml"
    graph_file.write_text(yaml.safe_dump({"name": "g", "nodes": {
        "localizer": {"config": {"map": "files/map.json", "score_likelihood": "synthetic"}},
        "mapper": {"config": {"detector_file": "files/missing.yml"}}}}))
    monkeypatch.chdir(tmp_path / "here")
    graph = load_graph(graph_file, {"nodes": {"mapper": {"config": {"extraction_file": "mine.json"}}}})
    assert graph.nodes["localizer"].config == {"map": str(tmp_path / "robot" / "files" / "map.json"),
                                               "score_likelihood": "synthetic"}
    # not beside the graph: left as given (the worker names it if it is missing); overrides are read from here
    assert graph.nodes["mapper"].config == {"detector_file": "files/missing.yml", "extraction_file": "mine.json"}


def test_generated_worlds_go_to_the_cache_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("SEMLOC_CACHE_DIR", str(tmp_path / "cache"))
    assert default_cache_dir() == tmp_path / "cache"
    monkeypatch.delenv("SEMLOC_CACHE_DIR")
    if sys.platform.startswith("linux"):  # the platform's folder: XDG's on Linux
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        assert default_cache_dir() == tmp_path / "xdg" / "semloc"
