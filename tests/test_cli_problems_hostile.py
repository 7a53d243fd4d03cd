"""Hostile input to the instance commands (``problems list`` / ``import`` / ``export``,
``run --instances``): each is refused with one ``error:`` line naming the option or file, exit
code 2, and nothing read is written over.

* ``export``: ``--out`` equal to DIR, inside it, holding it, or a non-empty folder no export
  wrote is refused; an earlier export's folder is updated.
* ``import``: ``--out`` equal to SRC or inside it is refused.
* stored instances with complex or string arrays, a ``q`` whose length does not fit ``P``,
  and a damaged ``manifest.json`` are refused by ``problems list`` and ``run --instances``.
* ``problems list`` of a folder without instances exits 2 like ``run --instances``.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from c3bench.bench.cli import main
from c3bench.problems.errors import InputError
from c3bench.problems.exporters import INDEX
from c3bench.problems.instance import MANIFEST, Problem, read_instances, save_problem


# --- helpers ----------------------------------------------------------------------------------
def _qp(name: str, n: int = 3) -> Problem:
    """A tiny convex QP of the generic ``qp`` family (no metadata needed)."""
    return Problem(name=name, family="qp", P=np.eye(n), q=np.arange(n, dtype=float),
                   G=np.ones((1, n)), h=np.ones(1))


def _instances(directory: Path, count: int = 2) -> Path:
    """``count`` tiny ``qp`` instances under ``directory/qp``; returns ``directory``."""
    for index in range(count):
        save_problem(_qp(f"qp-{index}"), directory / "qp")
    return directory


def _snapshot(directory: Path) -> dict[str, bytes]:
    """Every file below ``directory`` by relative path, with its bytes."""
    return {str(path.relative_to(directory)): path.read_bytes()
            for path in sorted(directory.rglob("*")) if path.is_file()}


def _error(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run ``c3bench argv``, assert exit 2 with one ``error:`` line on stderr and nothing on
    stdout; return that line."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. numpy's ComplexWarning must not be the answer
        code = main(list(argv))
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, (code, captured.err, captured.out)
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err and not captured.out.strip(), captured
    return lines[0]


def _rewrite_npz(npz: Path, **changes: Any) -> None:
    """Replace some arrays of a stored instance's ``.npz`` (the rest kept)."""
    with np.load(npz) as stored:
        arrays = {key: stored[key] for key in stored.files}
    arrays.update(changes)
    np.savez(npz, **arrays)


# --- export ----------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["same", "inside", "inside-new", "parent"])
def test_export_refuses_an_out_overlapping_dir(tmp_path: Path, where: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "parent" / "inst")
    out = {"same": source, "inside": source / "qp", "inside-new": source / "new",
           "parent": tmp_path / "parent"}[where]
    if where == "parent":
        (out / INDEX).write_text(json.dumps({"format": "qpsolvers", "instances": []}))
    before = _snapshot(source)
    line = _error(capsys, "problems", "export", str(source), "--out", str(out))
    assert "--out" in line and str(source) in line
    assert _snapshot(source) == before
    assert not (source / "new").exists()


def test_export_refuses_a_folder_it_did_not_write(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst")
    out = tmp_path / "nonempty"
    out.mkdir()
    (out / "mydata.txt").write_text("mine")
    (out / "qp-0.npz").write_text("also mine")
    line = _error(capsys, "problems", "export", str(source), "--out", str(out))
    assert "--out" in line and "mydata.txt" in line
    assert sorted(p.name for p in out.iterdir()) == ["mydata.txt", "qp-0.npz"]
    assert (out / "qp-0.npz").read_text() == "also mine"


def test_export_updates_an_earlier_export(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst", count=3)
    out = tmp_path / "export"
    assert main(["problems", "export", str(source), "--out", str(out)]) == 0
    (out / "results.csv").write_text("qpbenchmark's, kept")
    for suffix in (".json", ".npz"):
        (source / "qp" / f"qp-2{suffix}").unlink()
    before = _snapshot(source)
    assert main(["problems", "export", str(source), "--out", str(out)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == [
        "c3bench_test_set.py", INDEX, "qp-0.npz", "qp-1.npz", "results.csv"]
    index = json.loads((out / INDEX).read_text())
    assert [entry["name"] for entry in index["instances"]] == ["qp-0", "qp-1"]
    assert _snapshot(source) == before


# --- import ----------------------------------------------------------------------------------
@pytest.mark.parametrize("inside", [False, True])
def test_import_refuses_an_out_in_src(tmp_path: Path, inside: bool,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "byo"
    source.mkdir()
    np.savez(source / "one.npz", P=np.eye(2), q=np.ones(2))
    before = _snapshot(source)
    out = source / "out" if inside else source
    line = _error(capsys, "problems", "import", str(source), "--out", str(out))
    assert "--out" in line and "SRC" in line
    assert _snapshot(source) == before
    assert not (source / "out").exists()


# --- stored instances ----------------------------------------------------------------------------
@pytest.mark.parametrize("key, value, words", [
    ("q", np.array([1 + 1j, 2.0, 3.0]), "complex"),
    ("P", np.eye(3).astype(complex), "complex"),
    ("h", np.array(["a"]), "not real numbers"),
])
def test_non_real_stored_arrays_are_refused(tmp_path: Path, key: str, value: np.ndarray,
                                            words: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst")
    npz = source / "qp" / "qp-1.npz"
    _rewrite_npz(npz, **{key: value})
    for argv in (["problems", "list", str(source)],
                 ["run", "--instances", str(source), "--results", str(tmp_path / "R")]):
        line = _error(capsys, *argv)
        assert str(npz) in line and repr(key) in line and words in line, line
    assert not (tmp_path / "R").exists()


def test_a_problem_refuses_complex_data() -> None:
    with pytest.raises(ValueError, match="q must be real"):
        Problem(name="c", family="qp", P=np.eye(2), q=np.array([1j, 0.0]))


def test_a_wrong_length_q_is_blamed_on_q(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="q has length 2 but P is 3 x 3"):
        Problem(name="w", family="qp", P=np.eye(3), q=np.zeros(2))
    source = _instances(tmp_path / "inst")
    _rewrite_npz(source / "qp" / "qp-0.npz", q=np.zeros(8))
    line = _error(capsys, "problems", "list", str(source))
    assert "qp-0" in line and "q has length 8 but P is 3 x 3" in line, line


@pytest.mark.parametrize("text, words", [
    ("xx", "not JSON"),
    ("", "not JSON"),
    ("[]", "a JSON list"),
    ('{"counts": {"qp": 2}}', "'suite'"),
    ('{"suite": 5}', "'suite'"),
    ('{"suite": {}, "counts": {"qp": "two"}}', "'counts'"),
    ('{"suite": {}, "instances": "qp-0"}', "'instances'"),
    ('{"suite": {}, "generator_version": "2"}', "'generator_version'"),
])
def test_a_damaged_manifest_is_refused(tmp_path: Path, text: str, words: str,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst")
    (source / MANIFEST).write_text(text)
    for argv in (["problems", "list", str(source)],
                 ["problems", "list", str(source), "--skip-bad"],
                 ["run", "--instances", str(source), "--results", str(tmp_path / "R")]):
        line = _error(capsys, *argv)
        assert str(source / MANIFEST) in line and words in line, line
    assert not (tmp_path / "R").exists()


def test_a_manifest_that_is_a_folder_is_refused(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst")
    (source / MANIFEST).mkdir()
    line = _error(capsys, "problems", "list", str(source))
    assert str(source / MANIFEST) in line


def test_a_damaged_manifest_can_be_left_to_regeneration(tmp_path: Path) -> None:
    """``check_manifest=False``: a packaged suite's stored copy, which a run regenerates."""
    source = _instances(tmp_path / "inst")
    (source / MANIFEST).write_text("xx")
    assert len(read_instances(source, check_manifest=False).problems) == 2
    with pytest.raises(InputError, match=r"manifest\.json"):
        read_instances(source, skip_bad=True)


def test_a_valid_manifest_is_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    source = _instances(tmp_path / "inst")
    (source / MANIFEST).write_text(json.dumps(
        {"suite": {"name": "mine"}, "counts": {"qp": 2}, "instances": ["qp-0", "qp-1"]}))
    assert main(["problems", "list", str(source)]) == 0
    assert "qp" in capsys.readouterr().out


def test_listing_a_folder_without_instances_exits_2(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "emptydir"
    empty.mkdir()
    line = _error(capsys, "problems", "list", str(empty))
    assert "DIR" in line and f"no instances under {empty}" in line


@pytest.mark.parametrize("body", [
    "import sys\nsys.exit(0)\n",  # at import
    "import sys\n\n\ndef qps():\n    sys.exit(3)\n    yield\n",  # while yielding
])
def test_import_module_that_exits_is_bad_input(tmp_path: Path, body: str,
                                               monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A test-set module calling ``sys.exit()`` is bad input (exit 2 naming ``--module``),
    not a silent exit with nothing written."""
    (tmp_path / "c3bench_exiting_set.py").write_text(body)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "out"
    line = _error(capsys, "problems", "import", "--module", "c3bench_exiting_set",
                  "--out", str(out))
    assert "--module c3bench_exiting_set" in line and "SystemExit" in line
    assert not out.exists()
