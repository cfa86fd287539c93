"""The layout the code keeps, checked mechanically: commands only parse, call the experiments library and report;
nothing but the `semloc` entry point reaches into them; workers stand alone and convert frames in one place; the core
(the experiments library included) stays pure and is a graph without cycles; every command line stays small; every
name imported from the project, in a function too, exists."""

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
WORKERS_DIR = REPO_ROOT / "services" / "workers"
FRAMES = REPO_ROOT / "services" / "frames.py"
# Other wires than semloc's frames keep their own converters.
OTHER_WIRES = (REPO_ROOT / "services" / "ros2", REPO_ROOT / "services" / "foxglove.py")


def python_files(*folders: str) -> list[Path]:
    return sorted(p for folder in folders for p in (REPO_ROOT / folder).rglob("*.py") if ".venv" not in p.parts)


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO_ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_froms(path: Path):
    """(line, module, names) of each ``from module import names`` in ``path``, at the top or in a function, relative
    imports resolved."""
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
            yield node.lineno, base, [alias.name for alias in node.names]


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at the top or in a function (``from a import b`` gives ``a.b`` when that is a
    module, else ``a``; relative imports resolved)."""
    names = {alias.name for node in ast.walk(ast.parse(path.read_text(), str(path)))
             if isinstance(node, ast.Import) for alias in node.names}
    for _, base, imported in import_froms(path):
        submodules = {f"{base}.{name}" for name in imported}
        modules = {name for name in submodules if _is_module(name)}
        names |= modules or {base}
        if len(modules) < len(submodules):
            names.add(base)
    return names


def _is_module(name: str) -> bool:
    path = REPO_ROOT.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def worker_modules() -> set[str]:
    return {module_name(p) for p in WORKERS_DIR.glob("*.py") if p.name != "__init__.py"}


def test_no_worker_imports_another():
    workers = worker_modules()
    offenders = {module_name(path): sorted(imported_modules(path) & (workers - {module_name(path)}))
                 for path in WORKERS_DIR.glob("*.py")}
    assert {name: others for name, others in offenders.items() if others} == {}


def test_only_the_registry_tests_and_benchmarks_import_a_worker_module():
    """A worker module is loaded by the registry (services/workers/__init__.py) by name; what two workers share
    (frame conversions, configuration, checks) lives outside them."""
    workers = worker_modules()
    registry = WORKERS_DIR / "__init__.py"
    offenders = sorted(str(path.relative_to(REPO_ROOT)) for path in python_files("semloc_core", "schemas", "services")
                       if path != registry and WORKERS_DIR not in path.parents and imported_modules(path) & workers)
    assert offenders == []


def defined_functions(path: Path) -> set[str]:
    """The module-level functions of ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    return {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}


def test_each_frame_conversion_exists_once():
    """Every conversion between frames and core objects is a function of services/frames.py: none is defined again
    elsewhere, and no worker module defines one (a function named ``*_frame``, ``*_frames`` or ``*_from_frame``)."""
    converters = defined_functions(FRAMES)
    assert {"heatlines_frame", "heatlines_from_frame", "objectmap_frame", "semantic_map_from_frame",
            "pose_estimate_frame", "camera_model_frame", "camera_from_frame", "topomap_frame"} <= converters
    offenders = {}
    for path in python_files("semloc_core", "schemas", "services", "benchmarks", "tests"):
        if path == FRAMES or any(wire == path or wire in path.parents for wire in OTHER_WIRES):
            continue
        names = defined_functions(path)
        again = names & converters
        if WORKERS_DIR in path.parents:
            again |= {n for n in names if n.endswith(("_frame", "_frames")) or "_from_frame" in n}
        if again:
            offenders[str(path.relative_to(REPO_ROOT))] = sorted(again)
    assert offenders == {}


def core_import_graph() -> dict[str, set[str]]:
    modules = {module_name(p): p for p in python_files("semloc_core")}
    return {name: {m for m in imported_modules(path) if m in modules and m != name} for name, path in modules.items()}


def cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of ``graph`` (a list of nodes, the first repeated at the end), or [] when it has none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> list[str]:
        state[node] = 1
        for successor in sorted(graph.get(node, ())):
            if state.get(successor) == 1:
                return path[path.index(successor):] + [successor]
            if successor not in state:
                found = visit(successor, path + [successor])
                if found:
                    return found
        state[node] = 2
        return []

    for start in sorted(graph):
        if start not in state:
            found = visit(start, [start])
            if found:
                return found
    return []


def test_cycle_finds_a_cycle():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []


def test_semloc_core_has_no_import_cycle():
    """Between modules (imports in functions included) and between its packages (io, detection, mapping, ...): a
    package that imports another is never imported back by it."""
    graph = core_import_graph()
    assert cycle(graph) == []

    def package(module: str) -> str:
        return ".".join(module.split(".")[:2])

    packages: dict[str, set[str]] = {}
    for module, imports in graph.items():
        packages.setdefault(package(module), set()).update(package(m) for m in imports if package(m) != package(module))
    assert cycle(packages) == []



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


# Docs are reference pages: short, undated, standing alone. The history of measurements is in docs/results/.
MAX_DOC_LINES = 300
RESULTS_DIR = REPO_ROOT / "docs" / "results"
# Files of the repository's own text (not the venv, caches or run outputs).
SKIPPED_PARTS = {".venv", ".git", "__pycache__", ".pytest_cache", "build", "dist", "out", "runs"}
DATE = re.compile(r"\b(19|20)\d\d-(0[1-9]|1[0-2])(-\d\d)?\b"
                  r"|\b(January|February|March|April|May|June|July|August|September|October|November|December)"
                  r"( \d{1,2},?)? (19|20)\d\d\b")
# A link to a dated results entry names its file, not a date of the page's own.
RESULTS_LINK = re.compile(r"results/(19|20)\d\d-\d\d-\d\d-[\w.-]+")
# Notes that live outside the repository (spelt in two parts so that this file does not cite them itself).
OUTSIDE_NOTES = re.compile("STACK" + "_NOTES|DESIGN" + r"\.md")
BESIDE_THE_REPOSITORY = ".." + "/shared"
THIS_MACHINES_DATA = "/work" + "/shared"


def repository_files(*suffixes: str) -> list[Path]:
    return sorted(p for p in REPO_ROOT.rglob("*") if p.suffix in suffixes and p.is_file()
                  and not SKIPPED_PARTS.intersection(p.relative_to(REPO_ROOT).parts))


def doc_pages() -> list[Path]:
    return sorted((REPO_ROOT / "docs").rglob("*.md"))


def undated_pages() -> list[Path]:
    """Every page but the dated results entries: docs/, the README, the contributing guide."""
    pages = [p for p in doc_pages() if RESULTS_DIR not in p.parents]
    return pages + [REPO_ROOT / "README.md", REPO_ROOT / "CONTRIBUTING.md"]


def page_id(path: Path) -> str:
    return str(path.relative_to(REPO_ROOT))


@pytest.mark.parametrize("path", doc_pages(), ids=page_id)
def test_no_docs_page_is_over_300_lines(path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_DOC_LINES, f"{page_id(path)} has {lines} lines (at most {MAX_DOC_LINES}): move history to " \
                                   "docs/results/, or split the page"


@pytest.mark.parametrize("path", undated_pages(), ids=page_id)
def test_no_date_outside_the_results(path):
    text = RESULTS_LINK.sub("results/ENTRY", path.read_text())
    dated = [f"{n}: {line.strip()[:100]}" for n, line in enumerate(text.splitlines(), 1) if DATE.search(line)]
    assert not dated, f"{page_id(path)} holds dates (a measurement's date belongs in a docs/results/ entry):\n" + \
                      "\n".join(dated)


def test_the_date_check_sees_dates():
    assert DATE.search("measured 2026-12-04") and DATE.search("in December 2026") and DATE.search("2026-11 runs")
    assert not DATE.search("4096x1024, 1,200 frames, p95 3.5 ms, eq. 4.27, RFC 2119")
    assert not DATE.search(RESULTS_LINK.sub("results/ENTRY", "[a](results/2026-12-04-tls-cost.md)"))


def test_results_entries_are_dated_files():
    names = [p.name for p in RESULTS_DIR.glob("*") if p.is_file()]
    assert names, "docs/results/ holds no entry"
    misnamed = [n for n in names if not re.fullmatch(r"20\d\d-(0[1-9]|1[0-2])-[0-3]\d-[a-z0-9][a-z0-9-]*\.md", n)]
    assert not misnamed, f"docs/results/ entries are named YYYY-MM-DD-<topic>.md: {misnamed}"


# Every text the repository holds: pages, code, configs, graphs, scripts (files without a suffix, such as .ci/run).
TEXT_SUFFIXES = [".md", ".py", ".yaml", ".yml", ".toml", ".json5", ".json", ".cfg", ".txt", ".sh", ""]


@pytest.mark.parametrize("suffix", TEXT_SUFFIXES, ids=lambda s: s or "no-suffix")
def test_nothing_cites_notes_outside_the_repository(suffix):
    citing = [f"{page_id(p)}:{n}" for p in repository_files(suffix)
              for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if OUTSIDE_NOTES.search(line)]
    assert not citing, "these cite notes that are not in the repository (write what is needed into docs/): " + \
                       ", ".join(citing)


def test_pages_and_files_name_the_real_data_folder_not_a_path_beside_the_repository():
    """Pages, graphs, configs and code (the tests, which find the data folder for themselves, apart)."""
    files = [p for p in repository_files(".md", ".yaml", ".yml", ".json5", ".toml", ".py", ".sh")
             if "tests" not in p.relative_to(REPO_ROOT).parts[:1]]
    citing = [f"{page_id(p)}:{n}" for p in files for n, line in enumerate(p.read_text().splitlines(), 1)
              if BESIDE_THE_REPOSITORY in line or THIS_MACHINES_DATA in line]
    assert not citing, f"name the real data folder (docs/datasets.md) instead of {BESIDE_THE_REPOSITORY}: " + \
                       ", ".join(citing)


def settings_classes() -> list[type]:
    """The core's settings classes (made by semloc_core.settings.settings): every module of semloc_core imported."""
    import importlib
    import inspect

    from semloc_core.settings import SETTINGS_CONFIG

    found = {}
    for name in sorted(module_name(p) for p in python_files("semloc_core")):
        for cls in vars(importlib.import_module(name)).values():
            if inspect.isclass(cls) and getattr(cls, "__pydantic_config__", None) == SETTINGS_CONFIG:
                found[cls.__qualname__] = cls
    return list(found.values())


def test_worker_configs_nest_the_core_settings_instead_of_repeating_them():
    """One source per setting: a worker's config holds a core settings class as a field (``filter``, ``volume``,
    ``extraction``, ``engine``, ``features``), never a copy of three or more of its fields."""
    from dataclasses import fields

    from services.workers import load_worker

    classes = settings_classes()
    assert {"FilterConfig", "MapperConfig", "ExtractionConfig", "EngineParams", "FeatureParams"} <= {
        c.__name__ for c in classes}
    copies = {}
    for kind in available():
        for model in models_within(load_worker(kind).Config):
            for cls in classes:
                shared = set(model.model_fields) & {f.name for f in fields(cls)}
                if len(shared) >= 3:
                    copies[f"{kind}: {model.__name__} ~ {cls.__name__}"] = sorted(shared)
    assert copies == {}


def models_within(model) -> list[type]:
    """``model`` and every pydantic model its fields hold (nested, in lists or optional), once each."""
    import typing

    from pydantic import BaseModel

    found, pending = [], [model]
    while pending:
        current = pending.pop()
        if current in found:
            continue
        found.append(current)
        for info in current.model_fields.values():
            stack = [info.annotation]
            while stack:
                kind = stack.pop()
                if isinstance(kind, type) and issubclass(kind, BaseModel):
                    pending.append(kind)
                stack.extend(typing.get_args(kind))
    return found


def test_models_within_finds_a_nested_copy():
    from pydantic import BaseModel

    class Inner(BaseModel):
        a: int = 0

    class Outer(BaseModel):
        inner: Inner | None = None
        inners: list[Inner] = []

    assert models_within(Outer) == [Outer, Inner]


PROJECT_PACKAGES = ("semloc_core", "services", "schemas")


def project_imports(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, name) of each ``from <project module> import name`` in ``path`` (:func:`import_froms`; a
    benchmark's sibling, ``from end_to_end import ...``, counted as ``benchmarks.*``)."""
    found = []
    for line, base, names in import_froms(path):
        if path.parent.name == "benchmarks" and (path.parent / f"{base.split('.')[0]}.py").is_file():
            base = f"benchmarks.{base}"
        if base.split(".")[0] in PROJECT_PACKAGES + ("benchmarks",):
            found += [(line, base, name) for name in names if name != "*"]
    return found


def test_every_name_imported_from_the_project_exists():
    """Imports inside functions run only on their own path (a benchmark's worker, an optional backend): a name
    removed from the module it came from must still fail here, not on a user's machine."""
    import importlib

    missing = []
    for path in python_files("semloc_core", "services", "schemas", "benchmarks", "tests"):
        for line, module, name in project_imports(path):
            if _is_module(f"{module}.{name}"):
                continue
            if not hasattr(importlib.import_module(module), name):
                missing.append(f"{path.relative_to(REPO_ROOT)}:{line}: {module}.{name}")
    assert missing == []
