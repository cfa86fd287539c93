"""Worker configuration layering and crash-safe state snapshots."""

from __future__ import annotations

import numpy as np
import pytest

from services.commands.worker import build_config
from services.config import ConfigError
from services.state import State, StateError, load_state, save_state
from services.workers import WorkerNotFound, load_worker

Sink = load_worker("sink")


def test_precedence_defaults_yaml_env_flags(tmp_path):
    path = tmp_path / "sink.yaml"
    path.write_text("robot: from_yaml\ndepth: 5\nkey: semloc/yaml\nrerun: {mode: save, path: a.rrd}\n")
    env = {"SEMLOC__DEPTH": "7", "SEMLOC__ROBOT": "from_env", "SEMLOC__NOT_A_FIELD": "ignored",
           "SEMLOC__RERUN__RECORDING_ID": "run-1"}
    config = build_config(Sink, ["--config", str(path), "--robot", "from_flag", "--set", "bus.connect=[tcp/1.2.3.4:1]"],
                          environ=env)
    assert config.robot == "from_flag"  # flag beats env beats yaml
    assert config.depth == 7  # env beats yaml
    assert config.key == "semloc/yaml"  # yaml beats default
    assert config.rerun.mode == "save" and config.rerun.recording_id == "run-1"
    assert config.bus.connect == ["tcp/1.2.3.4:1"]
    assert config.policy == "lossless"  # default


def test_generated_field_flags(tmp_path):
    config = build_config(Sink, ["--key", "semloc/x/**", "--depth", "3", "--policy", "latest"], environ={})
    assert (config.key, config.depth, config.policy) == ("semloc/x/**", 3, "latest")


@pytest.mark.parametrize("argv, message", [
    (["--depth", "0"], "depth"),
    (["--set", "nonsense=1"], "nonsense"),
    (["--policy", "sometimes"], "policy"),
    (["--set", "noequals"], "field.path=value"),
])
def test_invalid_config_is_reported(argv, message):
    with pytest.raises(ConfigError, match=message):
        build_config(Sink, argv, environ={})


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
