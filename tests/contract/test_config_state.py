"""Worker configuration layering and crash-safe state snapshots."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from services.cli import main
from services.state import State, StateError, load_state, save_state
from services.workers import WorkerNotFound, load_worker


def resolved(capsys, *argv: str) -> dict:
    """The config `semloc worker sink ARGV --print-config` resolves."""
    assert main(["worker", "sink", *argv, "--print-config"]) == 0
    return yaml.safe_load(capsys.readouterr().out)


def test_precedence_defaults_yaml_env_flags(tmp_path, monkeypatch, capsys):
    path = tmp_path / "sink.yaml"
    path.write_text("robot: from_yaml\ndepth: 5\nkey: semloc/yaml\nrerun: {mode: save, path: a.rrd}\n")
    for name, value in {"SEMLOC__DEPTH": "7", "SEMLOC__ROBOT": "from_env", "SEMLOC__NOT_A_FIELD": "ignored",
                        "SEMLOC__RERUN__RECORDING_ID": "run-1"}.items():
        monkeypatch.setenv(name, value)
    config = resolved(capsys, "--config", str(path), "--robot", "from_flag", "--set", "bus.connect=[tcp/1.2.3.4:1]")
    assert config["robot"] == "from_flag"  # flag beats env beats yaml
    assert config["depth"] == 7  # env beats yaml
    assert config["key"] == "semloc/yaml"  # yaml beats default
    assert config["rerun"]["mode"] == "save" and config["rerun"]["recording_id"] == "run-1"
    assert config["bus"]["connect"] == ["tcp/1.2.3.4:1"]
    assert config["policy"] == "lossless"  # default


def test_every_worker_setting_is_a_set_not_a_flag(capsys):
    config = resolved(capsys, "--set", "key=semloc/x/**", "--set", "depth=3", "--set", "policy=latest")
    assert (config["key"], config["depth"], config["policy"]) == ("semloc/x/**", 3, "latest")
    with pytest.raises(SystemExit) as exit_info:  # no per-field flags: argparse refuses the option
        main(["worker", "sink", "--depth", "3", "--print-config"])
    assert exit_info.value.code == 2


@pytest.mark.parametrize("value, source", [("0", "0"), ("'0'", "0"), ("images/", "images/")])
def test_a_device_index_is_a_camera_source_as_set_reads_it(value, source, capsys):
    # `--camera 0` and `--set nodes.camera.config.source=0` name the same device (docs/deploy.md); YAML reads an int
    assert main(["worker", "camera", "--set", f"source={value}", "--print-config"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["source"] == source


@pytest.mark.parametrize("argv, message", [
    (["--set", "depth=0"], "depth"),
    (["--set", "nonsense=1"], "nonsense"),
    (["--set", "policy=sometimes"], "policy"),
    (["--set", "noequals"], "field.path=value"),
])
def test_invalid_config_is_reported_on_one_line(argv, message, capsys, monkeypatch):
    monkeypatch.delenv("SEMLOC__DEPTH", raising=False)
    assert main(["worker", "sink", *argv, "--print-config"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("semloc worker: ") and message in error and error.count("\n") == 1


def test_unknown_worker():
    with pytest.raises(WorkerNotFound):
        load_worker("no_such_worker")


def test_state_round_trip_and_atomic_replace(tmp_path):
    path = tmp_path / "r1" / "mapper.npz"
    assert load_state(path) is None
    save_state(path, State({"votes": np.arange(6.0).reshape(2, 3)}, {"frames": 3, "classes": ["cup"]}))
    save_state(path, State({"votes": np.ones((2, 2), np.float32)}, {"frames": 4}))
    state = load_state(path)
    assert state.meta == {"frames": 4}
    np.testing.assert_array_equal(state.arrays["votes"], np.ones((2, 2), np.float32))
    assert sorted(p.name for p in path.parent.iterdir()) == ["mapper.npz"]  # no temporary file left


def test_state_refuses_objects_and_reports_corruption(tmp_path):
    with pytest.raises(ValueError, match="object"):
        save_state(tmp_path / "s.npz", State({"bad": np.array([{"a": 1}], dtype=object)}))
    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(StateError):
        load_state(tmp_path / "corrupt.npz")
