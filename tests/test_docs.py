"""The reference pages say what the code does: every `semloc` command of the READMEs and docs/*.md
parses with the current command line and names presets and `--set` fields that exist, and the settings tables name
their class's fields with its defaults. A renamed option or field, or a changed default, fails here rather than on
a reader's machine."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import math
import re
import shlex
import typing
from pathlib import Path

import pydantic
import pytest

from semloc_core.experiments.spec import preset_names
from services.cli import COMMANDS, build_parser, main
from services.workers import available

REPO_ROOT = Path(__file__).resolve().parents[1]
PAGES = [REPO_ROOT / "README.md", REPO_ROOT / "deploy" / "README.md"] + sorted((REPO_ROOT / "docs").glob("*.md"))
# What a page writes where a command takes a number (`--seed S`, `--set kidnap=K`).
NUMBER_PLACEHOLDERS = {"S": "0", "K": "1", "N": "1"}


def page_id(path: Path) -> str:
    return str(path.relative_to(REPO_ROOT))


def expand(where: str, command: str, whole: bool) -> list[tuple[str, str, bool]]:
    """``command`` once per alternative of an `x|y|z` word."""
    alternatives = re.search(r"\b\w+(\|\w+)+\b", command)
    choices = alternatives.group(0).split("|") if alternatives else [None]
    return [(where, command.replace(alternatives.group(0), choice) if choice else command, whole) for choice in choices]


def documented_commands() -> list[tuple[str, str, bool]]:
    """(page:line, command, whole) of every `semloc ...` line of a shell block (```bash or plain ```; continuation
    lines joined, comments and a trailing `&` dropped, `a && b` and `a; b` split), and of every inline `semloc CMD
    ...` (whole=False: it may leave out what the command requires)."""
    found = []
    for page in PAGES:
        fence, text, start = None, "", 0  # fence: the open block's language line, None outside blocks
        for number, line in enumerate(page.read_text().splitlines(), 1):
            if line.lstrip().startswith("```"):
                fence, text = (line.strip() if fence is None else None), ""
                continue
            if fence is None:
                for span in re.findall(r"`(semloc [^`]*)`", line):
                    for part in span.split("&&"):
                        words = part.split()
                        if len(words) > 1 and words[1].split("|")[0] in COMMANDS:
                            found += expand(f"{page_id(page)}:{number}", part.strip(), False)
                continue
            if fence not in ("```", "```bash"):
                continue
            line = re.sub(r"\s+#.*$", "", line)
            text, start = (f"{text} {line.strip()}", start) if text else (line, number)
            if text.rstrip().endswith("\\"):
                text = text.rstrip()[:-1]
                continue
            for part in re.split(r"&&|;", text):
                match = re.search(r"(?:^|\s|\$)(?:\.venv/bin/)?(semloc\s.*)", part)
                if match:
                    found += expand(f"{page_id(page)}:{start}", match.group(1).strip().rstrip("&").strip(), True)
            text = ""
    return found


def fields_of(model) -> dict | None:
    """name -> annotation of a pydantic model's or a dataclass's fields (None: not a settings class)."""
    if isinstance(model, type) and issubclass(model, pydantic.BaseModel):
        return {name: field.annotation for name, field in model.model_fields.items()}
    if isinstance(model, type) and dataclasses.is_dataclass(model):
        return typing.get_type_hints(model)
    return None


def nested_settings(annotation):
    """The settings class a field holds (through Optional, unions, lists), or None (a plain value or a mapping)."""
    pending = [annotation]
    while pending:
        candidate = pending.pop()
        if fields_of(candidate) is not None:
            return candidate
        if typing.get_origin(candidate) is not dict:
            pending.extend(typing.get_args(candidate))
    return None


def unknown_field(model, path: str) -> str | None:
    """The first part of the dotted ``path`` that ``model`` has no field for (None: every part exists; below a
    mapping or a plain value anything goes)."""
    for part in path.split("."):
        fields = fields_of(model)
        if fields is None or part == "*":
            return None
        if part not in fields:
            return part
        model = nested_settings(fields[part])
    return None


def command_options(argv: list[str]) -> tuple[set[str], list[str]]:
    """The options of the deepest command ``argv`` names (`eval mapping`, `worker localizer`) and its words."""
    parser, words = build_parser(argv[0]), []
    for token in argv:
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or token not in sub.choices:
            break
        parser, words = sub.choices[token], words + [token]
    options = {option for action in parser._actions for option in action.option_strings}
    if words == ["worker"] and len(argv) > 1 and not argv[1].startswith("-"):
        # a worker parses its own options (`semloc worker KIND -h`); every worker takes the same ones
        kind = argv[1] if argv[1] in available() else "sink"  # `semloc worker KIND`, `my_pkg.my_worker`
        out = io.StringIO()
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
            main(["worker", kind, "--help"])
        options, words = set(re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", out.getvalue())), words + [argv[1]]
    return options, words


def settings_of(words: list[str]):
    """The settings class `--set` fills for this command and its presets' kind ((None, None): not checked)."""
    from semloc_core.experiments import (detector_calibration, detector_training, localization, loopclosure, mapping,
                                         template_selection)
    from services.demo_run import DemoSpec
    from services.workers import load_worker

    specs = {"calibrate": (detector_calibration.CalibrationSpec, "calibrate"),
             "select-templates": (template_selection.SelectionSpec, "select-templates"),
             "train-detector": (detector_training.TrainingSpec, "train-detector"), "demo": (DemoSpec, None),
             "eval loopclosure": (loopclosure.LoopClosureSpec, "loopclosure"),
             "eval localization": (localization.LocalizationSpec, "localization"),
             "eval mapping": (mapping.MappingSpec, "mapping")}
    if " ".join(words) in specs:
        return specs[" ".join(words)]
    if words[0] == "worker" and len(words) == 2 and words[1] in available():
        return load_worker(words[1]).Config, None
    return None, None


def number_for_placeholder(token: str) -> str:
    token = NUMBER_PLACEHOLDERS.get(token, token)
    return re.sub(r"=([A-Z])$", lambda m: "=" + NUMBER_PLACEHOLDERS.get(m.group(1), m.group(1)), token)


COMMAND_CASES = documented_commands()


@pytest.mark.parametrize("where, command, whole", COMMAND_CASES, ids=[where for where, _, _ in COMMAND_CASES])
def test_every_documented_command_parses_and_names_what_exists(where, command, whole):
    argv = [number_for_placeholder(token) for token in shlex.split(command)[1:]]
    assert argv[0] in COMMANDS, f"{where}: `{command}`: no such command"
    elided = "..." in argv or not whole  # `semloc eval mapping W/dataset ... --set x=y`, `semloc up`
    argv = [token for token in argv if token != "..."]
    known, words = command_options(argv)
    if not elided:
        errors = io.StringIO()
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            try:
                build_parser(argv[0]).parse_args(argv)
            except SystemExit as exit_info:  # `semloc calibrate --help` exits 0
                assert exit_info.code == 0, f"{where}: `{command}`: {errors.getvalue().strip().splitlines()[-1]}"
    given = [token.split("=")[0] for token in argv[len(words):] if re.match(r"-+[a-zA-Z]", token)]
    assert set(given) <= known, f"{where}: `{command}`: semloc {' '.join(words)} has no {sorted(set(given) - known)}"
    model, kind = settings_of(words)
    for option, value in zip(argv, argv[1:]):
        if option == "--preset" and kind:
            assert value in preset_names(kind), f"{where}: `{command}`: no preset {value} of {kind}"
        if option == "--set" and model is not None:
            path = value.split("=", 1)[0]
            assert unknown_field(model, path) is None, \
                f"{where}: `{command}`: {model.__name__} has no {unknown_field(model, path)!r} (--set {path})"


# What a page writes for "some field" (`--set a.b=value`, `--set field=value`, `--set KEY=VALUE`).
FIELD_PLACEHOLDERS = {"a.b", "field", "dotted.path", "KEY"}


def has_field(model, path: str) -> bool:
    """Whether every part of the dotted ``path`` is a field, through nested settings and mappings of settings
    (`inputs.image.policy`); a path below a plain mapping (a spec's `smoothing: {...}`) is not known here."""
    parts = path.split(".")
    while parts:
        fields = fields_of(model)
        if fields is None or parts[0] not in fields:
            return False
        annotation = fields[parts.pop(0)]
        model = nested_settings(annotation)
        if model is None and parts and typing.get_origin(annotation) is dict:  # a mapping's key, then its settings
            model, parts = nested_settings(typing.get_args(annotation)[1]), parts[1:]
            if model is None:
                return False
    return True


def every_settings_class() -> list:
    """The settings of every command `--set` fills: the experiments' specs, the demo's and every worker's."""
    from services.workers import load_worker

    spec_commands = [["calibrate"], ["select-templates"], ["train-detector"], ["demo"], ["eval", "loopclosure"],
                     ["eval", "localization"], ["eval", "mapping"]]
    return [settings_of(words)[0] for words in spec_commands] + [load_worker(kind).Config for kind in available()]


def test_every_set_a_page_mentions_names_a_field():
    """`--set x.y=...` in prose too (`--set smoothing.enabled=false`): some command's settings have that field
    (graph nodes, `nodes.*`, and the simulator's keyword options, `semloc sim --set`, aside)."""
    import inspect

    from semloc_core.sim import scenarios

    classes = every_settings_class()
    simulator = {name for scenario in ("tabletop", "hall", "route", "aliased")
                 for name in inspect.signature(getattr(scenarios, scenario)).parameters}
    unknown = []
    for page in PAGES:
        for number, line in enumerate(page.read_text().splitlines(), 1):
            for path in re.findall(r"--set '?([a-zA-Z_][\w.*]*)=", line):
                if path in FIELD_PLACEHOLDERS or path.startswith("nodes.") or path in simulator:
                    continue
                if not any(has_field(model, path) for model in classes):
                    unknown.append(f"{page_id(page)}:{number}: --set {path}")
    assert not unknown, "no command has these fields: " + ", ".join(unknown)


def test_the_command_check_sees_commands_and_fields():
    commands = [command for _, command, _ in COMMAND_CASES]
    assert "semloc localize relocalize" in commands and "semloc eval mapping DATASET -o out.json" in commands
    assert "semloc worker localizer --print-config" in commands and len(commands) > 200  # inline ones too
    from services.workers import load_worker

    localizer = load_worker("localizer").Config
    assert unknown_field(localizer, "filter.max_particles") is None and unknown_field(localizer, "health.probes") is None
    assert unknown_field(localizer, "filter.max_particle") == "max_particle"
    assert unknown_field(localizer, "inputs.odom.policy") is None  # a mapping: any key
    assert has_field(localizer, "inputs.odom.policy") and has_field(localizer, "smoothing.enabled")
    assert not has_field(localizer, "inputs.odom.policies") and not has_field(localizer, "smoothing.enable")
    from semloc_core.experiments.localization import LocalizationSpec

    assert not has_field(LocalizationSpec, "smoothing.enabled")  # a plain mapping: not known from the spec


# Settings tables: (page, the table's header line, the class, whether the table lists every field). A row's first
# cell names fields (`a`, `b`), its second their defaults, in order ("0.5 m", "10° (0.1745 rad)", "0 (hall preset
# 10)"); a default written in words ("the filter's converged values") is not compared.
def _tables():
    from semloc_core.localization import FilterConfig
    from semloc_core.localization.health import HealthConfig
    from semloc_core.localization.place_poses import PlacePoseConfig
    from semloc_core.localization.proposals import PlaceProposalConfig
    from semloc_core.localization.smoothing import SmoothingConfig
    from services.demo_run import DemoSpec
    from services.workers import load_worker

    return [("docs/particle-filter.md", "| parameter | default | meaning |", FilterConfig, True),
            ("docs/hybrid-localization.md", "| `health.` | default | |", HealthConfig, True),
            ("docs/hybrid-localization.md", "| loop-closure worker `place_poses.`", PlacePoseConfig, True),
            ("docs/hybrid-localization.md", "| localizer `smoothing.`", SmoothingConfig, True),
            ("docs/hybrid-localization.md", "| `place_proposals.` | default | |", PlaceProposalConfig, True),
            ("docs/loopclosure.md", "| field | default | |", load_worker("loopclosure").Config, False),
            ("docs/demo.md", "| field | default (fast) | what |", DemoSpec, True)]


def table_rows(page: str, header: str) -> list[list[str]]:
    lines = (REPO_ROOT / page).read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def top_level_split(text: str) -> list[str]:
    """``text`` split at the commas outside brackets."""
    parts, depth, current = [], 0, ""
    for char in text:
        if char in "([{":
            depth += 1
        elif char in ")]}":
            depth -= 1
        if char == "," and depth == 0:
            parts.append(current.strip())
            current = ""
        else:
            current += char
    return parts + [current.strip()]


PROSE = object()  # a default written in words
DEFAULT = re.compile(r"`?(?P<value>[-\w.]+)`?\s*(?P<unit>m|s|px|nats|°)?(\s*\((?P<paren>[^)]*)\))?")


def documented_default(text: str, name: str):
    """The value a table's default cell gives (`none`: None), or PROSE."""
    match = DEFAULT.fullmatch(text)
    if not match:
        return PROSE
    value, unit, paren = match.group("value"), match.group("unit"), match.group("paren") or ""
    if re.fullmatch(r"[-\d.]+ rad", paren):
        return float(paren.split()[0])
    literal = {"true": True, "false": False, "none": None}.get(value.lower(), value)
    if isinstance(literal, str):
        try:
            literal = float(value)
        except ValueError:  # a word: `front`, `latest`, `auto`; words with a note are prose
            return PROSE if paren or unit else literal
        if unit == "°" and not name.endswith("_deg"):
            literal = math.radians(literal)
    return literal


def same_default(documented, actual) -> bool:
    if documented is None or isinstance(documented, bool) or isinstance(actual, bool):
        return documented is actual
    if isinstance(documented, float) and isinstance(actual, (int, float)):
        return math.isclose(documented, actual, rel_tol=2e-3, abs_tol=1e-9)
    return documented == actual


def model_defaults(model) -> dict:
    if dataclasses.is_dataclass(model):
        return {f.name: getattr(model(), f.name) for f in dataclasses.fields(model)}
    return {name: field.get_default(call_default_factory=True) for name, field in model.model_fields.items()}


@pytest.mark.parametrize("page, header, model, complete", _tables(), ids=lambda v: v if isinstance(v, str) else "")
def test_settings_tables_name_the_fields_with_their_defaults(page, header, model, complete):
    defaults = model_defaults(model)
    named, wrong = [], []
    for row in table_rows(page, header):
        names = re.findall(r"`([a-z_][a-z0-9_]*)`", row[0])
        named += names
        values = top_level_split(row[1])
        if len(values) != len(names):
            continue
        for name, text in zip(names, values):
            documented = documented_default(text, name)
            if documented is not PROSE and name in defaults and not same_default(documented, defaults[name]):
                wrong.append(f"{name}: the page says {text}, the code {defaults[name]!r}")
    assert not set(named) - set(defaults), f"{page}: {model.__name__} has no {sorted(set(named) - set(defaults))}"
    assert not wrong, f"{page}: " + "; ".join(wrong)
    if complete:
        assert not set(defaults) - set(named), f"{page} lacks {model.__name__}'s {sorted(set(defaults) - set(named))}"


def test_the_table_check_reads_defaults():
    assert documented_default("10° (0.1745 rad)", "kld_bin_theta") == 0.1745
    assert documented_default("20°", "heading_std") == pytest.approx(math.radians(20))
    assert documented_default("0 (hall preset 10)", "history_frames") == 0.0
    assert documented_default("`front`", "camera") == "front" and documented_default("none", "calibration") is None
    assert documented_default("the filter's converged values", "max_xy_std") is PROSE
    assert top_level_split("300, 3, 0 (120, 2)") == ["300", "3", "0 (120, 2)"]
    assert not same_default(0.5, 0.05) and same_default(True, True) and not same_default(True, 1)
    assert same_default(None, None) and not same_default(None, 0.0)
