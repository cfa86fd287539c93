"""deploy/: every zenoh config and graph file is valid; a router-hub graph of client nodes works (Python API)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from services.launcher import Launcher, load_graph
from tests.service.conftest import REPO_ROOT, free_port, make_image_folder, read_jsonl, wait_until

DEPLOY = REPO_ROOT / "deploy"


@pytest.mark.parametrize("path", sorted(DEPLOY.glob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_load(path):
    zenoh.Config.from_file(str(path))


@pytest.mark.parametrize("path", sorted(DEPLOY.rglob("*.yaml")), ids=lambda p: str(p.relative_to(DEPLOY)))
def test_graphs_validate(path):
    graph = load_graph(path)
    assert graph.nodes


@pytest.mark.service
def test_router_hub_with_client_nodes(tmp_path):
    make_image_folder(tmp_path / "images", 10)
    sink_log = tmp_path / "sink.jsonl"
    graph = load_graph(DEPLOY / "camera-sink.yaml", {
        "hub": f"tcp/127.0.0.1:{free_port()}",
        "hub_mode": "router",
        "nodes": {"camera": {"config": {"source": str(tmp_path / "images"), "rate": 50, "loop": False,
                                        "wait_for_subscriber_s": 20}},
                  "sink": {"config": {"log_path": str(sink_log)}}},
    })
    launcher = Launcher(graph, run_dir=tmp_path / "run")
    with launcher:
        records = wait_until(lambda: (r := read_jsonl(sink_log)) and len(r) >= 10 and r, 60, message="10 frames")
        assert [r["seq"] for r in records] == list(range(10))
        wait_until(lambda: launcher.summary()["camera"]["finished"], 20, message="camera done with its folder")
        pids = [p for p in launcher.pids().values() if p]
        config = (Path(launcher.run_dir) / "sink.yaml").read_text()
        assert "mode: client" in config
    assert launcher.summary()["camera"]["last_exit"] == 0  # the camera finished its folder
    for pid in pids:
        assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]


@pytest.mark.service
def test_config_errors_are_not_restarted(tmp_path):
    """A node whose config turned bad after the graph was checked (the file it names is gone when it starts) exits 2
    and is not restarted. (A config bad from the start fails when the graph is loaded: test_graph_check.py.)"""
    extraction = tmp_path / "extraction.json"
    extraction.write_text(json.dumps({"detector": {"normalised": {"threshold": 0.5}}}))
    graph = load_graph(DEPLOY / "camera-sink.yaml", {
        "hub": f"tcp/127.0.0.1:{free_port()}",
        "nodes": {"camera": {"enabled": False}, "sink": {"enabled": False},
                  "mapper": {"worker": "mapper", "config": {"grid_min": [0, 0, 0], "grid_max": [1, 1, 0.3],
                                                            "extraction_file": str(extraction)}}},
    })
    launcher = Launcher(graph, run_dir=tmp_path / "run")  # checked: the file is there
    extraction.unlink()
    with launcher:
        assert launcher.wait(timeout=60)
        summary = launcher.summary()["mapper"]
    assert (summary["starts"], summary["last_exit"]) == (1, 2)
    assert "extraction_file" in (tmp_path / "run" / "logs" / "mapper.log").read_text()


@pytest.mark.service
def test_a_finished_node_is_stopped_and_a_failed_one_says_why(tmp_path):
    """A node whose recorded source played to its end (exit 0, not restarted) is `stopped`, not `down` (which makes
    `semloc status` exit 1); a node that fails (exit 1: the folder of its log is a file) is down with its log's
    one-line reason, as the launcher logs it and `semloc status` shows it."""
    make_image_folder(tmp_path / "images", 5)
    (tmp_path / "a_file").write_text("")
    graph = load_graph(DEPLOY / "camera-sink.yaml", {
        "hub": f"tcp/127.0.0.1:{free_port()}",
        "nodes": {"camera": {"start_after": [], "config": {"source": str(tmp_path / "images"), "rate": 50,
                                                           "loop": False}},
                  "sink": {"enabled": False},
                  "failing": {"worker": "sink", "restart": {"policy": "never"},
                              "config": {"log_path": str(tmp_path / "a_file" / "frames.jsonl")}}},
    })
    with Launcher(graph, run_dir=tmp_path / "run") as launcher:
        assert launcher.wait(timeout=60)
        view = launcher.view().nodes
    assert (view["camera"].state, view["camera"].state_reason) == ("stopped", "finished: exit code 0")
    assert view["failing"].state == "down" and view["failing"].last_exit == 1
    assert view["failing"].state_reason == f"finished: exit code 1: FileExistsError: [Errno 17] File exists: " \
                                           f"'{tmp_path / 'a_file'}'"
