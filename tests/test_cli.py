"""The command line as a user meets it: `semloc --version`, and a missing or empty input is one line
``semloc <command>: ...`` on stderr with exit code 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version

import pytest

from services.cli import main
from tests.conftest import REPO_ROOT

# Every command that reads a data set, with what it needs besides it.
DATASET_COMMANDS = [
    ["eval", "loopclosure", "{data}", "-o", "{out}/r.json"],
    ["eval", "localization", "{data}", "-o", "{out}/r.json"],
    ["eval", "mapping", "{data}", "-o", "{out}/r.json"],
    ["calibrate", "{data}", "-o", "{out}/s.json"],
    ["select-templates", "{data}", "-o", "{out}/t"],
    ["train-detector", "{data}", "-o", "{out}/d"],
]


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"semloc {version('semloc')}"


@pytest.mark.parametrize("data", ["missing", "empty"])
@pytest.mark.parametrize("argv", DATASET_COMMANDS, ids=lambda argv: " ".join(argv[:2]).replace(" {data}", ""))
def test_a_missing_or_empty_dataset_is_one_line_and_exit_2(argv, data, tmp_path, capsys):
    folder = tmp_path / data
    if data == "empty":
        folder.mkdir()
    command = [part.format(data=folder, out=tmp_path / "out") for part in argv]
    assert main([*command, "--quiet"]) == 2
    captured = capsys.readouterr()
    name = " ".join(argv[:2]) if argv[0] == "eval" else argv[0]
    assert captured.err.startswith(f"semloc {name}: ") and str(folder) in captured.err, captured.err
    assert len(captured.err.splitlines()) == 1 and "Traceback" not in captured.err


@pytest.mark.parametrize("argv, message", [
    (["up", "{tmp}/nosuch.yaml"], "graph file not found"),
    (["up", "nosuch"], "built-in graphs: camera-sink, demo, local"),
    (["demo", "--graph", "nosuch", "-o", "{tmp}/demo"], "graph file not found: nosuch"),  # before building a world
    (["sim", "hall", "-o", "{tmp}/x", "--trajectory", "{tmp}/nosuch.json"], "cannot read trajectory"),
])
def test_a_missing_file_is_one_line_and_exit_2(argv, message, tmp_path, capsys):
    assert main([part.format(tmp=tmp_path) for part in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"semloc {argv[0]}: ") and message in err and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("environment, expected", [(None, "1"), ("3", "3")])
def test_a_worker_process_runs_blas_on_one_thread_unless_told(environment, expected):
    """`semloc worker` (every node the launcher starts) sets OPENBLAS_NUM_THREADS=1 before numpy loads OpenBLAS:
    a graph's workers share the cores, and a BLAS pool per process spins against the others. A value in the
    environment wins."""
    import os

    script = ("import os, sys\nfrom services.cli import main\nassert 'numpy' not in sys.modules, 'numpy loaded "
              "before the default'\nmain(['worker', '--list'])\nimport numpy\n"
              "print('BLAS', os.environ.get('OPENBLAS_NUM_THREADS'))")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if environment is not None:
        env["OPENBLAS_NUM_THREADS"] = environment
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == f"BLAS {expected}"


def test_a_reader_that_leaves_early_gets_no_traceback(tmp_path):
    """`semloc up local --dry-run | head -3`: the pipe closes before the command has printed all; it stops quietly."""
    process = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "local", "--dry-run", "--run-dir",
                                str(tmp_path / "run")], cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # before it writes: its first print meets a closed pipe
    _, err = process.communicate(timeout=60)
    assert b"Traceback" not in err and b"BrokenPipeError" not in err, err.decode()
    assert process.returncode == 1


def test_a_worker_or_command_without_robot_is_on_the_shipped_graphs_robot():
    """`semloc worker KIND` started by hand next to `semloc up local` hears it (it was robot `robot`, the graphs
    `r1`): the worker's default robot and the `--robot` defaults of export, map save and replay are the robot of
    every shipped graph."""
    import os

    import yaml

    from services.cli import build_parser
    from services.launcher import load_graph

    graphs = {load_graph(path).robot for path in sorted((REPO_ROOT / "deploy").rglob("*.yaml"))}
    env = {k: v for k, v in os.environ.items() if not k.startswith("SEMLOC__")}
    done = subprocess.run([sys.executable, "-m", "services.cli", "worker", "sink", "--print-config"], cwd=REPO_ROOT,
                          env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    worker = yaml.safe_load(done.stdout)["robot"]
    parser = build_parser()
    commands = {argv[0]: parser.parse_args(argv).robot
                for argv in (["export", "s.mcap", "-o", "out"], ["map", "save", "out"], ["replay", "s.mcap"])}
    assert len(graphs) == 1 and {worker, *commands.values()} == graphs, (graphs, worker, commands)
