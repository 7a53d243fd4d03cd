"""The documentation stays true: its examples run, its links and paths exist, its tables match.

* The first ``python`` code block under every ``## Adding ...`` heading of README.md and
  CONTRIBUTING.md (adding a backend, a problem family, a scene) runs, as written, in a fresh
  interpreter; the examples assert their own results.
* Every ``docs/<page>.md`` named in a Python file, the README or the docs exists, and
  docs/index.md lists every page.
* Relative links and the code paths quoted in the README, CONTRIBUTING.md and docs/ resolve.
* docs/results.md documents every column of the results table and of the committed tables.
* No file of the repository mentions the team's internal specification file.
"""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EXAMPLE_SOURCES = ("README.md", "CONTRIBUTING.md")
EXPECTED_EXAMPLES = ("Adding a backend", "Adding a problem family", "Adding a scene")
# Assembled so that this file does not contain the name it looks for.
INTERNAL_SPEC = "SPEC" + ".md"


# --- helpers ----------------------------------------------------------------------------------
def _examples() -> dict[str, str]:
    """``{heading: code}``: the first python block under each ``## Adding ...`` heading."""
    found: dict[str, str] = {}
    for name in EXAMPLE_SOURCES:
        path = ROOT / name
        if not path.exists():
            continue
        heading: str | None = None
        block: list[str] | None = None
        for line in path.read_text().splitlines():
            if block is not None:
                if line.strip() == "```":
                    assert heading is not None
                    found.setdefault(heading, "\n".join(block) + "\n")
                    block, heading = None, None
                else:
                    block.append(line)
                continue
            if line.startswith("#"):
                title = line.lstrip("#").strip()
                heading = title if line.startswith("## ") and title.startswith("Adding ") \
                    else None
            elif heading is not None and heading not in found \
                    and line.strip().startswith("```python"):
                block = []
    return found


def _repository_files() -> list[Path]:
    """Tracked files plus untracked files git does not ignore (skip when git is missing)."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        pytest.skip("git is not available or this is not a git checkout")
    paths = {ROOT / entry for entry in listed.decode().split("\0") if entry}
    return sorted(path for path in paths if path.is_file())


def _doc_pages() -> list[Path]:
    return sorted(DOCS.glob("*.md"))


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *_doc_pages()]


def _results_doc_columns(section: str | None = None) -> set[str]:
    """Backquoted names in the first cell of the table rows of docs/results.md (of one
    ``## `` section when given)."""
    text = (DOCS / "results.md").read_text()
    if section is not None:
        start = text.index(f"## {section}")
        end = text.find("\n## ", start + 1)
        text = text[start:end if end >= 0 else None]
    names: set[str] = set()
    for line in text.splitlines():
        if line.startswith("| "):
            first = line.split("|")[1]
            names.update(re.findall(r"`([A-Za-z_][A-Za-z0-9_]*)`", first))
    return names


# --- the examples -----------------------------------------------------------------------------
def test_every_extension_point_has_an_example() -> None:
    examples = _examples()
    for title in EXPECTED_EXAMPLES:
        assert title in examples, f"no python block under '## {title}' in {EXAMPLE_SOURCES}"
        assert examples[title].strip(), f"the example under '## {title}' is empty"


@pytest.mark.parametrize("title", EXPECTED_EXAMPLES)
def test_extension_example_runs(title: str, tmp_path: Path) -> None:
    """Each example runs as written, in its own interpreter (nothing leaks into the
    registry of this test process) and from an empty directory."""
    code = _examples().get(title)
    if code is None:
        pytest.fail(f"no example under '## {title}'")
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONDONTWRITEBYTECODE="1")
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (f"the example under '## {title}' failed:\n"
                                  f"{done.stdout}\n{done.stderr}")


# --- docs/ pages and paths --------------------------------------------------------------------
DOCS_PATH = re.compile(r"docs/[A-Za-z0-9_./-]*?\.md")


def test_every_named_docs_page_exists() -> None:
    """``docs/<page>.md`` named in any Python file (docstrings), the README or the docs."""
    sources = [p for p in _repository_files() if p.suffix == ".py"] + _markdown_files()
    missing: dict[str, list[str]] = {}
    for path in sources:
        if not path.exists():
            continue
        for match in set(DOCS_PATH.findall(path.read_text(errors="replace"))):
            if not (ROOT / match).is_file():
                missing.setdefault(match, []).append(str(path.relative_to(ROOT)))
    assert not missing, f"docs pages named but absent: {missing}"


def test_the_pages_named_by_the_code_exist() -> None:
    for page in ("admm", "mpc", "families", "lcs", "closed_loop", "metrics", "equilibrated",
                 "reference_study", "results", "index"):
        assert (DOCS / f"{page}.md").is_file(), f"docs/{page}.md is missing"


def test_index_lists_every_page() -> None:
    index = (DOCS / "index.md").read_text()
    for page in _doc_pages():
        if page.name != "index.md":
            assert f"({page.name})" in index, f"docs/index.md does not link {page.name}"


LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("name", ["README.md", "CONTRIBUTING.md", "docs"])
def test_relative_links_resolve(name: str) -> None:
    files = _doc_pages() if name == "docs" else [ROOT / name]
    broken = []
    for path in files:
        if not path.exists():
            continue
        for target in LINK.findall(path.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            resolved = (path.parent / target.split("#")[0]).resolve()
            if not resolved.exists():
                broken.append(f"{path.relative_to(ROOT)} -> {target}")
    assert not broken, f"broken links: {broken}"


CODE_PATH = re.compile(r"`((?:problems|solvers|bench|tests)/[A-Za-z0-9_/]+\.(?:py|toml))`")


def test_code_paths_quoted_in_the_docs_exist() -> None:
    """The source files the README, CONTRIBUTING.md and docs/ point at (files move in
    refactors; the documentation must follow)."""
    missing = []
    for path in _markdown_files():
        if not path.exists():
            continue
        for target in set(CODE_PATH.findall(path.read_text())):
            if not (ROOT / target).is_file():
                missing.append(f"{path.relative_to(ROOT)}: {target}")
    assert not missing, f"code paths quoted in the docs do not exist: {sorted(missing)}"


# --- docs/results.md against the tables -------------------------------------------------------
def test_results_table_schema_is_documented() -> None:
    from c3bench.bench import store

    documented = _results_doc_columns("The results table")
    schema = set(store.COLUMNS)
    assert documented == schema, (
        f"docs/results.md's results table differs from the schema: missing "
        f"{sorted(schema - documented)}, extra {sorted(documented - schema)}")


@pytest.mark.parametrize("table", [
    "results/quick/results.csv",
    "results/quick/summary.csv",
    "results/perf/perf.csv",
    "results/closed_loop/quick/results.csv",
    "results/closed_loop/sweep/results.csv",
])
def test_committed_table_columns_are_documented(table: str) -> None:
    path = ROOT / table
    if not path.exists():
        pytest.skip(f"{table} is not in this checkout")
    with path.open(newline="") as handle:
        header = next(csv.reader(handle))
    undocumented = sorted(set(header) - _results_doc_columns())
    assert not undocumented, f"columns of {table} missing from docs/results.md: {undocumented}"


# --- nothing points at the team's internal specification --------------------------------------
def test_no_file_mentions_the_internal_specification() -> None:
    needle = INTERNAL_SPEC.encode()
    offenders = [str(path.relative_to(ROOT)) for path in _repository_files()
                 if needle in path.read_bytes()]
    assert not offenders, f"files mentioning {INTERNAL_SPEC}: {offenders}"
