"""The benchmarks stay runnable: no test times them (they run for minutes and print ratios), so nothing else would see
one rot. Each script starts and prints its help, each helper module is imported by a benchmark, every benchmark a
page names exists, and every option a page, the README or a benchmark's own usage lines give a benchmark is one the
script takes. The benchmarks that run in one process on the core alone also run, on a tiny configuration, to their
ratio (what they print, never how fast)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((REPO_ROOT / "benchmarks").glob("*.py"))
SCRIPTS = [p for p in BENCHMARKS if 'if __name__ == "__main__":' in p.read_text()]
# A benchmark named on a page or in a docstring, and an option of a command line.
CITED = re.compile(r"benchmarks/(\w+)\.py")
OPTION = re.compile(r"(?<![\w-])--[a-z][\w-]*")
# A usage line of a benchmark's docstring: the command, then its continuation lines (indented deeper).
# The in-process benchmarks on their smallest settings (seconds each), and the ratio each must print.
TINY_RUNS = {
    "localization_health.py": (["--frames", "8"], r"\(\d+\.\d\d x the filter step\)"),
    "localization_smoothing.py": (["--frames", "60"], r"\(\d+\.\d\d x the live step"),
    "localizer.py": (["--particles", "200", "--repeats", "1", "--reference-repeats", "1", "--sweep", "200"],
                     r"filter step B .* speed-up x *\d"),
    "mapper.py": (["--frames", "1", "--reference-frames", "1", "--repeats", "1", "--downsample", "8"],
                  r"\| \d+x \| [\d.e+-]+ ok \|"),
}
USAGE = re.compile(r"^( +)(?:\w+=\S+ )*\.venv/bin/python benchmarks/(\w+)\.py(.*(?:\n\1 +\S.*)*)", re.M)


def test_every_benchmark_module_without_a_command_is_used_by_a_benchmark():
    helpers = {p.stem for p in BENCHMARKS} - {p.stem for p in SCRIPTS}
    imported = {name for p in BENCHMARKS
                for name in re.findall(r"^\s*(?:from|import) (?:benchmarks\.)?(\w+)", p.read_text(), re.M)}
    assert helpers <= imported, f"benchmarks/ modules that neither run nor are imported: {sorted(helpers - imported)}"


def cited_options(text: str, markdown: bool) -> list[tuple[str, str]]:
    """(benchmark, option) of each command line in ``text``: in a page, a command in a fenced block (its line and
    backslash continuations, up to a comment) or in an inline code span (up to the closing backtick); in a
    docstring, its usage lines."""
    if not markdown:
        return [(name, option) for match in USAGE.finditer(text) for name in [match.group(2)]
                for option in OPTION.findall(match.group(3))]
    found = []
    for match in CITED.finditer(text):
        before = text[:match.start()]
        line_start = before.rfind("\n") + 1
        if len(re.findall(r"^```", before, re.M)) % 2:  # in a fenced block
            command = re.match(r"(?:\\\n|[^\n#])*", text[match.end():]).group()
        elif before[line_start:].count("`") % 2:  # in an inline code span
            command = text[match.end():text.find("`", match.end())]
        else:
            continue
        found += [(match.group(1), option) for option in OPTION.findall(command)]
    return found


def citing_files() -> list[Path]:
    pages = sorted((REPO_ROOT / "docs").glob("*.md")) + [REPO_ROOT / "README.md", REPO_ROOT / "CONTRIBUTING.md"]
    return pages + BENCHMARKS


def test_every_benchmark_cited_exists():
    missing = sorted({f"{page.relative_to(REPO_ROOT)}: benchmarks/{name}.py" for page in citing_files()
                      for name in CITED.findall(page.read_text())
                      if not (REPO_ROOT / "benchmarks" / f"{name}.py").is_file()})
    assert not missing, f"pages cite benchmarks that are not there: {missing}"


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.name)
def test_every_benchmark_starts_and_takes_the_options_cited_for_it(path):
    result = subprocess.run([sys.executable, str(path), "--help"], cwd=REPO_ROOT, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0 and "usage:" in result.stdout, \
        f"{path.name} --help failed:\n{result.stderr[-3000:]}"
    options = set(OPTION.findall(result.stdout))
    unknown = sorted({f"{page.relative_to(REPO_ROOT)}: {option}" for page in citing_files()
                      for name, option in cited_options(page.read_text(), page.suffix == ".md")
                      if name == path.stem and option not in options})
    assert not unknown, f"options cited for {path.name} that it does not take: {unknown}"


def test_the_option_finder_reads_blocks_spans_and_usage_lines():
    page = ("Run `.venv/bin/python benchmarks/a.py --one\n--two`, then\n```bash\n"
            ".venv/bin/python benchmarks/b.py --three \\\n    --four  # --not-this\n```\n"
            "as benchmarks/c.py --nor-this says.")
    assert cited_options(page, markdown=True) == [("a", "--one"), ("a", "--two"), ("b", "--three"), ("b", "--four")]
    docstring = ("Speed.\n\n    .venv/bin/python benchmarks/d.py [--five 3]\n        [--six]\n\n"
                 "    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/e.py --seven\nProse --no.")
    assert cited_options(docstring, markdown=False) == [("d", "--five"), ("d", "--six"), ("e", "--seven")]


@pytest.mark.parametrize("name", sorted(TINY_RUNS))
def test_in_process_benchmarks_run_to_their_ratio(name):
    argv, ratio = TINY_RUNS[name]
    result = subprocess.run([sys.executable, str(REPO_ROOT / "benchmarks" / name), *argv], cwd=REPO_ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{name} {' '.join(argv)} failed:\n{result.stderr[-3000:]}"
    assert re.search(ratio, result.stdout), result.stdout
