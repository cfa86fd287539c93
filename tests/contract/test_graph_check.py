"""A graph's node configs are checked when the graph is loaded (`semloc up`, `--dry-run` included), as each worker
will build its config: a misspelt field or a bad value fails there with the node and the field, not when the
worker starts."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from services.cli import main

REPO_ROOT = Path(__file__).resolve().parents[2]


def graph(tmp_path: Path, sink_config: dict, env: dict | None = None) -> Path:
    path = tmp_path / "graph.yaml"
    node = {"worker": "sink", "config": sink_config, **({"env": env} if env else {})}
    path.write_text(yaml.safe_dump({"name": "check", "robot": "r1", "nodes": {"counter": node}}))
    return path


def dry_run(tmp_path: Path, path: Path, capsys) -> tuple[int, str, str]:
    code = main(["up", str(path), "--dry-run", "--run-dir", str(tmp_path / "run")])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_valid_graph_passes_and_prints_its_commands(tmp_path, capsys):
    code, out, _ = dry_run(tmp_path, graph(tmp_path, {"key": "semloc/r1/**", "depth": 4}), capsys)
    assert code == 0 and out.startswith("counter: ") and "worker sink --config" in out
    assert yaml.safe_load((tmp_path / "run" / "counter.yaml").read_text())["depth"] == 4


@pytest.mark.parametrize("config, env, field", [
    ({"kye": "semloc/r1/**"}, None, "kye"),                    # a misspelt field
    ({"depth": 0}, None, "depth"),                            # a value out of range
    ({"policy": "sometimes"}, None, "policy"),
    ({}, {"SEMLOC__DEPTH": "-3"}, "depth"),                   # the node's environment is a layer too
])
def test_a_bad_node_config_fails_at_load_naming_node_and_field(tmp_path, capsys, config, env, field):
    code, out, err = dry_run(tmp_path, graph(tmp_path, config, env), capsys)
    assert code == 2 and out == ""
    assert err.startswith("semloc up: node counter: invalid SinkConfig: ") and field in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("name", ["camera-sink", "local", "two-machines/base", "two-machines/robot"])
def test_the_shipped_graphs_pass(tmp_path, capsys, name):
    code, out, err = dry_run(tmp_path, REPO_ROOT / "deploy" / f"{name}.yaml", capsys)
    assert code == 0, err
    assert out.count(" worker ") >= 2


def waiting_graph(tmp_path: Path, start_after: dict[str, list[str]], disabled: tuple[str, ...] = ()) -> Path:
    """Sink nodes, each waiting for the nodes ``start_after`` lists (start_after, deploy/README.md)."""
    path = tmp_path / "graph.yaml"
    nodes = {name: {"worker": "sink", "start_after": after, "enabled": name not in disabled}
             for name, after in start_after.items()}
    path.write_text(yaml.safe_dump({"name": "check", "robot": "r1", "nodes": nodes}))
    return path


@pytest.mark.parametrize("start_after, error", [
    ({"a": ["ghost"], "b": []}, "node a: start_after names ghost, not a node of this graph (nodes: a, b)"),
    ({"a": ["a"]}, "start_after makes a cycle: a -> a"),
    ({"a": ["b"], "b": ["a"]}, "start_after makes a cycle: a -> b -> a"),
    ({"a": [], "b": ["c"], "c": ["d"], "d": ["b", "a"]}, "start_after makes a cycle: b -> c -> d -> b"),
])
def test_start_after_names_nodes_of_the_graph_and_makes_no_cycle(tmp_path, capsys, start_after, error):
    code, out, err = dry_run(tmp_path, waiting_graph(tmp_path, start_after), capsys)
    assert code == 2 and out == ""
    assert error in err and err.count("\n") == 1


@pytest.mark.parametrize("disabled, waits", [((), "b, c"), (("c",), "b")])
def test_start_after_waits_for_the_launched_nodes(tmp_path, capsys, disabled, waits):
    code, out, err = dry_run(tmp_path, waiting_graph(tmp_path, {"a": ["b", "c"], "b": ["c"], "c": []}, disabled),
                             capsys)
    assert code == 0, err
    assert f"worker sink --config {tmp_path / 'run' / 'a.yaml'}  (starts after {waits} run)" in out


def test_save_makes_the_waiting_camera_wait_for_the_saver_too(tmp_path, capsys):
    code = main(["up", "local", "--dry-run", "--save", str(tmp_path / "out"), "--run-dir", str(tmp_path / "run")])
    out = capsys.readouterr().out
    assert code == 0
    camera = next(line for line in out.splitlines() if line.startswith("camera: "))
    assert camera.endswith("(starts after detector, loopclosure, localizer, mapper, monitor, saver run)")
