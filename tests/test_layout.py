"""The layout the code keeps, checked mechanically: commands only parse, call the experiments library and report;
nothing but the `semloc` entry point reaches into them; the library stays pure; every command line stays small."""

from __future__ import annotations

import argparse
import ast
import contextlib
import io
import re
from pathlib import Path

import pytest

from services.cli import build_parser, main
from services.workers import available

REPO_ROOT = Path(__file__).resolve().parents[1]
COMMANDS_DIR = REPO_ROOT / "services" / "commands"
# The `semloc` dispatcher is the one module outside services/commands/ that imports it.
ENTRY_POINTS = {REPO_ROOT / "services" / "cli.py"}
MAX_COMMAND_LINES = 300
MAX_HELP_OPTIONS = 15


def python_files(*folders: str) -> list[Path]:
    return sorted(p for folder in folders for p in (REPO_ROOT / folder).rglob("*.py") if ".venv" not in p.parts)


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports (``from a import b`` gives ``a`` and ``a.b``)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return names


def test_nothing_outside_the_commands_imports_them():
    offenders = []
    for path in python_files("semloc_core", "schemas", "services", "tests", "benchmarks"):
        if COMMANDS_DIR in path.parents or path in ENTRY_POINTS:
            continue
        if any(name == "services.commands" or name.startswith("services.commands.") for name in imported_modules(path)):
            offenders.append(str(path.relative_to(REPO_ROOT)))
    assert offenders == []


@pytest.mark.parametrize("path", python_files("services/commands"), ids=lambda p: p.name)
def test_no_command_module_is_over_300_lines(path):
    assert len(path.read_text().splitlines()) <= MAX_COMMAND_LINES


def test_the_experiments_library_is_pure():
    """semloc_core (the experiments included) imports no bus, no viewer, no services and parses no command line."""
    forbidden = ("zenoh", "rerun", "services", "schemas", "argparse")
    offenders = {str(path.relative_to(REPO_ROOT)): sorted(name for name in imported_modules(path)
                                                          if name.split(".")[0] in forbidden)
                 for path in python_files("semloc_core")}
    assert {path: names for path, names in offenders.items() if names} == {}


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next((a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {})


def command_lines() -> list[list[str]]:
    """Every command line with its own --help: each command, each evaluation, each worker."""
    lines = []
    for name, parser in subcommands(build_parser()).items():
        kinds = subcommands(parser)
        lines += [[name, kind] for kind in kinds] if kinds else [[name]]
    return lines + [["worker", kind] for kind in available()]


def help_text(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_info:
        main([*argv, "--help"])
    assert exit_info.value.code == 0, argv
    return out.getvalue()


@pytest.mark.parametrize("argv", command_lines(), ids=" ".join)
def test_no_help_lists_more_than_15_options(argv):
    options = [line.split()[0] for line in help_text(argv).splitlines() if re.match(r"  -", line)]
    assert 0 < len(options) <= MAX_HELP_OPTIONS, options


def test_camera_means_one_thing():
    """`--camera` is a camera source (`semloc up`); a camera model or name is a spec or config field."""
    having = [" ".join(argv) for argv in command_lines() if re.search(r"^  (-\w, )?--camera\b", help_text(argv), re.M)]
    assert having == ["up"]
