"""Acceptance (issue 28): a bad file ends the worker, or the command, with exit code 2 and ONE line naming the file,
the field and what is wrong - no traceback - and the launcher does not restart a worker that stopped so, saying why.
`semloc replay` on a file that is not MCAP, or holds no complete message, exits non-zero."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
import yaml

from tests.service.conftest import REPO_ROOT, wait_until

pytestmark = pytest.mark.service

MAP = {"format": "semloc.semantic_map", "version": 1, "bounds": {"min": [-2.0, -2.0], "max": [2.0, 2.0]},
       "objects": [{"class": "bowl", "position": [0.1, 0.2, 0.8]}, {"class": "cap", "position": [0.3, 0.25, 0.8]}]}
CAMERA = {"model": "pinhole", "image_width": 160, "image_height": 120,
          "camera_matrix": {"rows": 3, "cols": 3, "data": [140.0, 0, 79.5, 0, 140.0, 59.5, 0, 0, 1]}}


def _semloc(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def _semloc_here(capsys, *args: str) -> tuple[int, str]:
    """``semloc ARGS`` in this process (what the command's exit code would be, and its output): the worker cases
    run here, not in a process each. The worker's signal handlers are put back afterwards."""
    from services.cli import main

    handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        code = main(list(args))
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def _bad_map_truncated(tmp_path):
    text = json.dumps(MAP, indent=2)
    path = tmp_path / "map.json"
    path.write_text(text[: len(text) // 2])
    return path, ["localizer", "--set", f"map={path}"], ["not valid json", "line"]


def _bad_map_infinite(tmp_path):
    path = tmp_path / "map.json"
    path.write_text(json.dumps(MAP).replace("0.25", "1e999"))  # json reads 1e999 as infinity
    return path, ["localizer", "--set", f"map={path}"], ["objects[1].position[1]", "finite number", "inf"]


def _bad_camera_yaml(tmp_path):
    camera = json.loads(json.dumps(CAMERA))
    camera["camera_matrix"]["data"] = camera["camera_matrix"]["data"][:8]
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(camera))
    return path, ["mapper", "--set", "classes=[bowl]", "--set", f"calibration={path}"], [
        "camera_matrix", "needs 9 values, has 8"]


def _bad_camera_yaml_syntax(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("model: pinhole\nimage_width: [640\n")
    return path, ["loopclosure", "--set", f"calibration={path}"], ["not valid YAML"]


def _missing_templates(tmp_path):
    path = tmp_path / "detector.yaml"
    path.write_text(yaml.safe_dump({"kind": "templates", "templates": "no_such_library"}))
    return path, ["detector", "--set", f"detector_file={path}"], ["templates:", "no_such_library", "is not a folder"]


def _unreadable_template(tmp_path):
    (tmp_path / "library" / "bowl").mkdir(parents=True)
    (tmp_path / "library" / "bowl" / "0.png").write_bytes(b"\x89PNG not really")
    path = tmp_path / "detector.yaml"
    path.write_text(yaml.safe_dump({"kind": "templates", "templates": "library"}))
    return path, ["detector", "--set", f"detector_file={path}"], ["templates:", "0.png", "not a readable image"]


def _garbage_mcap_source(tmp_path):
    path = tmp_path / "session.mcap"
    path.write_bytes(bytes(range(256)) * 40)
    return path, ["camera", "--set", f"source={path}"], ["cannot open robot log", "magic is invalid"]


def _mcap_source_with_bad_magic_body(tmp_path):
    path = tmp_path / "session.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 40)  # the magic, then garbage
    return path, ["camera", "--set", f"source={path}"], ["cannot open robot log", "record"]


def _bad_detector_config(tmp_path):
    path = tmp_path / "detector.yaml"
    path.write_text(yaml.safe_dump({"kind": "templates", "templates": "library", "cell": -3}))
    return path, ["detector", "--set", f"detector_file={path}"], ["invalid detector configuration", "cell"]


@pytest.mark.parametrize("case", [_bad_map_truncated, _bad_map_infinite, _bad_camera_yaml, _bad_camera_yaml_syntax,
                                  _missing_templates, _unreadable_template, _garbage_mcap_source,
                                  _mcap_source_with_bad_magic_body, _bad_detector_config],
                         ids=lambda case: case.__name__.strip("_"))
def test_a_worker_with_a_bad_file_exits_2_with_one_line(tmp_path, capsys, case):
    path, args, phrases = case(tmp_path)
    code, output = _semloc_here(capsys, "worker", *args, "--listen", "tcp/127.0.0.1:0", "--log-level", "WARNING")
    assert code == 2, output
    assert "Traceback" not in output, output
    [line] = [line for line in output.splitlines() if "worker failed:" in line]
    reason = line.split("worker failed: ", 1)[1]
    assert str(path) in reason, line
    for phrase in phrases:
        assert phrase in reason, (phrase, line)


def test_replay_of_a_file_that_is_not_a_recording_fails(tmp_path):
    """Garbage, and a recording cut before its first complete message: exit 2, one line; a file with nothing on the
    keys asked for: exit 1."""
    from services.bus import BusConfig, open_session
    from services.recording import Recorder
    from schemas import Ack, Header, encode

    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(bytes(range(256)) * 40)
    recording = tmp_path / "session.mcap"
    with open_session(BusConfig(listen=["tcp/127.0.0.1:0"])) as session:
        recorder = Recorder(session, "semloc/**", recording)
        publisher = session.declare_publisher("semloc/r1/test/acks")
        for seq in range(20):
            publisher.put(encode(Ack(header=Header(robot="r1", seq=seq), ok=True)))
        wait_until(lambda: recorder.count == 20, 10, message="20 messages recorded")
        recorder.close()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(recording.read_bytes()[:40])  # the magic, the header and a few bytes of the first chunk
    # garbage is read as a robot log (docs/ros2.md), which cannot be opened; the truncated file's header names semloc
    # as its writer: said to be the recording cut short it is, not a robot log
    for path, phrase in ((garbage, "magic is invalid"), (truncated, "before its first complete message")):
        result = _semloc("replay", str(path), "--listen", "tcp/127.0.0.1:0")
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr
        [line] = result.stderr.strip().splitlines()
        assert line.startswith("semloc replay: ") and str(path) in line and phrase in line, line
    result = _semloc("replay", str(recording), "--listen", "tcp/127.0.0.1:0", "--key", "semloc/nobody/**")
    assert result.returncode == 1 and "nothing to replay" in result.stderr, result.stderr


def test_record_into_a_place_it_cannot_write_exits_2_with_one_line_and_keeps_an_earlier_recording(tmp_path):
    """`semloc record -o` naming a folder, an earlier recording (once emptied without a word) or a file below a
    file (the disk refusing to make it, as a read-only one does): exit 2, one line naming the place and why."""
    folder, earlier, not_a_folder = tmp_path / "folder", tmp_path / "earlier.mcap", tmp_path / "file"
    folder.mkdir()
    earlier.write_bytes(b"an earlier session")
    not_a_folder.write_text("")
    for path, phrase in ((folder, "is a folder"), (earlier, "already exists"),
                         (not_a_folder / "session.mcap", "cannot write")):
        result = _semloc("record", "-o", str(path), "--duration", "0.1", "--listen", "tcp/127.0.0.1:0")
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        [line] = result.stderr.strip().splitlines()
        assert line.startswith("semloc record: ") and str(path) in line and phrase in line, line
    assert earlier.read_bytes() == b"an earlier session"


def test_a_command_with_a_bad_file_exits_2_with_one_line(tmp_path):
    (tmp_path / "dataset").mkdir()
    result = _semloc("eval", "localization", str(tmp_path / "dataset"), "-o", str(tmp_path / "out.json"))
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    [line] = result.stderr.strip().splitlines()
    assert line.startswith("semloc eval") and str(tmp_path / "dataset") in line, line


def test_the_launcher_does_not_restart_a_worker_with_a_bad_file_and_says_why(tmp_path, procs, hub):
    bad_map = tmp_path / "map.json"
    bad_map.write_text(json.dumps(MAP).replace("0.25", "1e999"))
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((8, 8, 3), np.uint8))
    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump({
        "name": "bad", "robot": "r1", "hub": hub, "restart": {"policy": "on-failure", "backoff_s": 0.1},
        "nodes": {"localizer": {"worker": "localizer", "config": {"map": str(bad_map)}},
                  "sink": {"worker": "sink", "config": {"key": "semloc/r1/**"}}}}))
    launcher = procs.semloc("up", str(graph), "--run-dir", str(tmp_path / "run"), name="launcher")
    wait_until(lambda: "not restarted" in procs.log("launcher"), 60, message=lambda: procs.log("launcher"))
    time.sleep(1.0)  # a restart would come within the 0.1 s back-off
    log = procs.log("launcher")
    [line] = [line for line in log.splitlines() if "not restarted" in line]
    assert "node localizer stopped" in line and str(bad_map) in line and "objects[1].position[1]" in line, line
    assert log.count("node localizer started") == 1, log
    assert launcher.poll() is None  # the rest of the graph runs on
    launcher.send_signal(2)
    assert launcher.wait(30) == 0
