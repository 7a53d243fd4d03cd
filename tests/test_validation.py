"""Validate before working, and no tracebacks for expected faults (issue 13, items 4 and 5).

Every bad argument exits 2 with one line naming the option, before any directory is made;
config files reject unknown tables; bad instance files stop with the file's name or, with
``--skip-bad``, are listed and skipped; regenerating a suite replaces it as a whole; ``perf``
keeps every run; a full disk, a read-only file system and a results path under a file are one
line, never a traceback (``--debug`` shows it).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from c3bench.bench import perf_store, store
from c3bench.bench.cli import main
from c3bench.bench.cli_checks import describe_os_error
from c3bench.problems.capture import SuiteSpec, provisional_capture
from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError, InstanceFormatError
from c3bench.problems.instance import MANIFEST, list_instances, load_problem, read_instances
from c3bench.problems.suites import generate_suite

REPO = Path(__file__).resolve().parents[1]
SMALL = SuiteSpec("small", n_states=2, admm_iterations=(0,), projection_iterations=(0,),
                  projection_steps=(0,))
"""Two states, every family: a few dozen instances, generated in about a second."""


def _env() -> dict[str, str]:
    """The environment of a ``python -m c3bench`` child: this checkout first on the path."""
    path = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    return {**os.environ, "PYTHONPATH": path}


def _cli(*argv: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """``python -m c3bench ARGV`` in a child process."""
    return subprocess.run([sys.executable, "-m", "c3bench", *argv], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def _one_line_error(captured: Any) -> str:
    """The single ``error: ...`` line of stderr (asserting there is nothing else)."""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err
    return str(lines[0])


@pytest.fixture(scope="module")
def small_suite(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The instances of :data:`SMALL` (provisional capture)."""
    out = tmp_path_factory.mktemp("small") / "instances"
    generate_suite(SMALL, out, capture=provisional_capture, progress=False)
    return out


def _stored(results: Path, instances: Path, name: str = "small") -> Path:
    """Copy the instances to ``results/<name>/instances`` (a stored suite); return it."""
    target = store.SuitePaths.of(results, name).instances
    shutil.copytree(instances, target)
    return target


# --- every bad argument: exit 2, one line naming the option, nothing created --------------------
BAD_ARGUMENTS = [
    (["run", "--suite", "nosuch"], "--suite"),
    (["run", "--suite", "../escape"], "--suite"),
    (["run", "--solvers", "osqp,nosuch"], "--solvers"),
    (["run", "--families", "banana"], "--families"),
    (["run", "--time-limit", "-1"], "--time-limit"),
    (["run", "--time-limit", "0"], "--time-limit"),
    (["run", "--time-limit", "nan"], "--time-limit"),
    (["run", "--reference-time-limit", "inf"], "--reference-time-limit"),
    (["run", "--repeats", "0"], "--repeats"),
    (["run", "--max-cells", "0"], "--max-cells"),
    (["run", "--max-cells", "-1"], "--max-cells"),
    (["run", "--jobs", "0"], "--jobs"),
    (["run", "--plugin", "c3bench_no_such_plugin_module"], "--plugin"),
    (["run", "--solvers", "osqp", "--precision", "float32"], "--precision"),
    (["run", "--solvers", "lemke", "--families", "c3plus_qp"], "--families"),
    (["report", "--suite", "../up"], "--suite"),
    (["compare", "osqp", "clarabel", "--suite", "a/b"], "--suite"),
    (["perf", "--samples", "0"], "--samples"),
    (["perf", "--backend", "nosuch"], "--backend"),
    (["perf", "--repeats", "0"], "--repeats"),
    (["perf", "--reference-budget", "0"], "--reference-budget"),
    (["perf", "--cpu", "100000"], "--cpu"),
    # a malformed Dask address: refused before a folder is made or a client started
    (["run", "--scheduler", "garbage", "--solvers", "lemke"], "--scheduler 'garbage'"),
    (["closed-loop-trials", "--scheduler", "garbage"], "--scheduler 'garbage'"),
    (["closed-loop-suite", "--scheduler", "tcp://host:99999"], "--scheduler"),
    (["sweep", "--scheduler", "nosuchscheme://host:1"], "--scheduler"),
    # a family the packaged suite does not generate: refused before generating it
    (["run", "--suite", "quick", "--families", "qp", "--solvers", "clarabel"], "--families"),
    (["compare", "clarabel", "clarabel"], "two different solvers"),
    (["closed-loop", "--duration", "1e12"], "--duration"),
    (["closed-loop-trials", "--duration", "3601"], "--duration"),
]


@pytest.mark.parametrize(("argv", "option"), BAD_ARGUMENTS,
                         ids=[" ".join(argv) for argv, _ in BAD_ARGUMENTS])
def test_bad_argument_is_exit_2_naming_the_option(argv: list[str], option: str, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    results = tmp_path / "results"
    assert main([*argv, "--results", str(results)]) == 2
    assert option in _one_line_error(capsys.readouterr())
    assert not results.exists(), "a directory was created before the arguments were checked"


def test_bad_problems_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["problems", "generate", "--suite", "nosuch", "--out", str(out)]) == 2
    assert "--suite" in _one_line_error(capsys.readouterr())
    assert main(["problems", "list", str(tmp_path / "absent")]) == 2
    assert "not a directory" in _one_line_error(capsys.readouterr())
    assert not out.exists()


def test_plugin_whose_import_raises_is_bad_input(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "c3bench_broken_plugin.py").write_text("raise RuntimeError('broken on import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["solvers", "--plugin", "c3bench_broken_plugin"]) == 2
    line = _one_line_error(capsys.readouterr())
    assert "--plugin" in line and "RuntimeError: broken on import" in line


def test_plugin_that_exits_is_bad_input(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A plugin calling ``sys.exit()`` (at import, or as its FUNCTION) is bad input, not a
    silent exit 0."""
    (tmp_path / "c3bench_exiting_plugin.py").write_text("import sys\nsys.exit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["solvers", "--plugin", "c3bench_exiting_plugin"]) == 2
    assert "--plugin" in _one_line_error(capsys.readouterr())
    assert main(["solvers", "--plugin", "sys:exit"]) == 2
    assert "SystemExit" in _one_line_error(capsys.readouterr())


UNAVAILABLE_PLUGIN = '''
from c3bench.problems.errors import BackendUnavailable
from c3bench.solvers import registry
from c3bench.solvers.base import Backend


class Missing(Backend):
    name = "c3bench_test_missing"
    families = ("lcp",)
    description = "a backend whose package is not installed"

    def require(self):
        raise BackendUnavailable("package c3bench-test-missing is not installed")

    def solve(self, problem, settings, warm_start=None):
        raise AssertionError("never called")


registry.register(Missing())
'''


def test_only_unavailable_solvers_is_bad_input(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "c3bench_missing_plugin.py").write_text(UNAVAILABLE_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    results = tmp_path / "results"
    assert main(["run", "--solvers", "c3bench_test_missing", "--plugin",
                 "c3bench_missing_plugin", "--results", str(results)]) == 2
    line = _one_line_error(capsys.readouterr())
    assert "--solvers" in line and "c3bench-test-missing is not installed" in line
    assert not results.exists()


def test_family_missing_from_a_stored_suite(small_suite: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    instances = _stored(tmp_path, small_suite)
    manifest = json.loads((instances / MANIFEST).read_text())
    manifest["counts"] = {"lcp": manifest["counts"]["lcp"]}
    (instances / MANIFEST).write_text(json.dumps(manifest))
    for family in ("c3plus_qp", "c3_qp", "projection", "mpcc"):
        shutil.rmtree(instances / family)
    assert main(["run", "--suite", "small", "--results", str(tmp_path), "--families",
                 "mpcc"]) == 2
    line = _one_line_error(capsys.readouterr())
    assert "--families" in line and "no instance of mpcc" in line
    assert sorted(p.name for p in (tmp_path / "small").iterdir()) == ["instances"]


def test_bad_input_in_a_real_process_has_no_traceback(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    for argv, words in [
        (["run", "--time-limit", "nan"], "--time-limit"),
        (["run", "--results", "a_file/sub"], "a_file"),
    ]:
        done = _cli(*argv, cwd=tmp_path)
        assert done.returncode == 2, (argv, done.stderr)
        assert "Traceback" not in done.stderr and done.stderr.startswith("error: "), done.stderr
        assert words in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_report_of_a_suite_never_run_is_one_line(small_suite: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    _stored(tmp_path, small_suite)
    for argv in (["report"], ["compare", "osqp", "clarabel"]):
        assert main([*argv, "--suite", "nosuch", "--results", str(tmp_path)]) == 1
        line = _one_line_error(capsys.readouterr())
        assert "--suite: no stored suite 'nosuch'" in line and ": small)" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small"]


# --- --debug and internal errors ----------------------------------------------------------------
@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_the_traceback(where: str, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["report", "--suite", "../up", "--results", str(tmp_path)]
    argv = ["--debug", *argv] if where == "before" else [*argv, "--debug"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "InputError" in err
    assert err.strip().splitlines()[-1].startswith("error: --suite")


BUGGY_PLUGIN = '''
from c3bench.solvers import registry
from c3bench.solvers.base import Backend


class Buggy(Backend):
    name = "c3bench_test_buggy"
    families = None  # a bug: not a tuple of families
    description = "a backend with a bug"

    def solve(self, problem, settings, warm_start=None):
        raise AssertionError("never called")


registry.register(Buggy())
'''


def test_a_bug_says_internal_error_with_its_traceback(tmp_path: Path) -> None:
    (tmp_path / "c3bench_buggy_plugin.py").write_text(BUGGY_PLUGIN)
    env = _env()
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env["PYTHONPATH"]])
    done = subprocess.run([sys.executable, "-m", "c3bench", "solvers", "--plugin",
                           "c3bench_buggy_plugin"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert done.stderr.startswith("internal error: TypeError")
    assert "Traceback (most recent call last)" in done.stderr


# --- configuration files ------------------------------------------------------------------------
@pytest.mark.parametrize(("text", "words"), [
    ("[mcp]\ndt = 0.04\n", "unknown table(s) [mcp]"),
    ("dt = 0.04\n", "dt (outside a table)"),
    ("[mpc]\nhorizon_length = 3\n", "unknown key(s) ['horizon_length'] in [mpc]"),
    ("[mpc]\ndt = -1.0\n", "[mpc] dt must be"),
    ("[mpc\ndt = 0.04\n", "not valid TOML"),
    ("mpc = 3\n", "mpc must be a table"),
    ("[scene]\nball_start = [1.0]\n", "[scene] ball_start must be a list of 2 finite numbers"),
    ("[scene]\nball_start = \"x\"\n", "[scene] ball_start must be a list of 2"),
    ("[scene]\nball_start = [1.0, \"a\"]\n", "[scene] ball_start must be a list of 2"),
    ("[scene]\nball_start = [1.0, nan]\n", "[scene] ball_start must be a list of 2"),
    ("[scene]\ncontact_solref = [0.004]\n", "[scene] contact_solref must be a list of 2"),
    ("[scene]\nmu_table = \"x\"\n", "[scene] mu_table must be a finite number"),
    ("[scene]\ntable_height = nan\n", "[scene] table_height must be a finite number"),
    ("[mpc]\nhorizon = 7.5\n", "[mpc] horizon must be an integer"),
    ("[limits]\nball_x = [0.1, 0.2, 0.3]\n", "[limits] ball_x must be a list of 2"),
])
def test_config_errors_name_the_file_and_the_table(text: str, words: str,
                                                   tmp_path: Path) -> None:
    path = tmp_path / "task.toml"
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: ") and words in str(caught.value)


def test_config_file_missing_or_misspelled_table_on_the_cli(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["problems", "generate", "--out", str(out), "--config",
                 str(tmp_path / "absent.toml")]) == 2
    assert "absent.toml: no such configuration file" in _one_line_error(capsys.readouterr())
    bad = tmp_path / "bad.toml"
    bad.write_text("[mcp]\ndt = 0.04\n")
    assert main(["problems", "generate", "--out", str(out), "--config", str(bad)]) == 2
    assert "[mcp]" in _one_line_error(capsys.readouterr())
    assert not out.exists()
    bad.write_text("[scene]\nball_start = [1.0]\n")
    assert main(["problems", "generate", "--out", str(out), "--config", str(bad),
                 "--capture", "provisional"]) == 2
    line = _one_line_error(capsys.readouterr())
    assert f"{bad}: [scene] ball_start must be" in line, line
    assert not out.exists()


# --- instance files -----------------------------------------------------------------------------
def _copy(small_suite: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of the small suite and the JSON path of one of its lcp instances."""
    directory = tmp_path / "instances"
    shutil.copytree(small_suite, directory)
    return directory, sorted((directory / "lcp").glob("*.json"))[0]


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _duplicate(path: Path) -> None:
    twin = path.parent.parent / "mpcc" / f"copy-{path.name}"
    shutil.copy(path, twin)
    shutil.copy(path.with_suffix(".npz"), twin.with_suffix(".npz"))


FAULTS = {
    "empty npz": (lambda p: p.with_suffix(".npz").write_bytes(b""), ".npz: empty file"),
    "truncated npz": (lambda p: _truncate(p.with_suffix(".npz")), ".npz: unreadable, truncated"),
    "json without npz": (lambda p: p.with_suffix(".npz").unlink(), ".npz: no such array file"),
    "npz without json": (lambda p: p.unlink(), ".npz: no "),
    "invalid json": (lambda p: p.write_text("{not json"), ".json: not valid JSON"),
    "empty json": (lambda p: p.write_text(""), ".json: empty file"),
    "json list": (lambda p: p.write_text("[]"), "not an instance header"),
    "duplicate name": (_duplicate, "duplicate instance name"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_bad_instance_file_is_named_or_skipped(fault: str, small_suite: Path,
                                               tmp_path: Path) -> None:
    directory, victim = _copy(small_suite, tmp_path)
    damage, words = FAULTS[fault]
    damage(victim)
    total = len(list_instances(directory))
    with pytest.raises(InstanceFormatError) as caught:
        read_instances(directory)
    assert words in str(caught.value) and victim.stem in str(caught.value)
    found = read_instances(directory, skip_bad=True)
    assert len(found.skipped) == 1 and words in found.skipped[0]
    assert len(found.problems) == total - 1
    assert len({p.name for p in found.problems}) == len(found.problems)


def test_problems_list_stops_or_skips(small_suite: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    directory, victim = _copy(small_suite, tmp_path)
    victim.with_suffix(".npz").write_bytes(b"")
    assert main(["problems", "list", str(directory)]) == 2
    line = _one_line_error(capsys.readouterr())
    assert f"{victim.stem}.npz: empty file" in line and "--skip-bad" in line
    assert main(["problems", "list", str(directory), "--skip-bad"]) == 0
    captured = capsys.readouterr()
    assert f"skipped bad instance file {victim.with_suffix('.npz')}" in captured.err
    assert "lcp" in captured.out


def test_run_stops_at_a_bad_instance_before_any_work(small_suite: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    instances = _stored(tmp_path, small_suite)
    victim = sorted((instances / "lcp").glob("*.npz"))[0]
    victim.write_bytes(b"")
    assert main(["run", "--suite", "small", "--results", str(tmp_path), "--solvers", "lemke",
                 "--families", "lcp", "--quiet"]) == 2
    assert f"{victim}: empty file" in _one_line_error(capsys.readouterr())
    assert sorted(p.name for p in (tmp_path / "small").iterdir()) == ["instances"]


def test_run_skip_bad_lists_and_runs_the_rest(small_suite: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    instances = _stored(tmp_path, small_suite)
    victim = sorted((instances / "lcp").glob("*.npz"))[0]
    victim.write_bytes(b"")
    assert main(["run", "--suite", "small", "--results", str(tmp_path), "--solvers", "lemke",
                 "--families", "lcp", "--repeats", "1", "--jobs", "1", "--no-report",
                 "--quiet", "--skip-bad"]) == 0
    captured = capsys.readouterr()
    assert f"skipped bad instance file {victim}" in captured.err
    frame = store.read_results(tmp_path / "small")
    assert len(frame) == 1 and victim.stem not in set(frame["instance"])


# --- regenerating a suite -----------------------------------------------------------------------
def _instance_files(directory: Path) -> set[str]:
    return {str(p.relative_to(directory)) for p in directory.rglob("*") if p.is_file()}


def test_regeneration_replaces_the_suite_as_a_whole(small_suite: Path, tmp_path: Path) -> None:
    out = tmp_path / "suite"
    shutil.copytree(small_suite, out)  # dt 0.05
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / f".suite.generating-{dead}-0000").mkdir()  # left by a killed generation
    faster = load_config().with_mpc(dt=0.04)
    fresh = tmp_path / "fresh"
    generate_suite(SMALL, fresh, config=faster, capture=provisional_capture, progress=False)
    assert _instance_files(fresh) != _instance_files(out), "the test needs other file names"
    paths = generate_suite(SMALL, out, config=faster, capture=provisional_capture,
                           progress=False)
    assert _instance_files(out) == _instance_files(fresh)
    assert {load_problem(p).meta["dt"] for p in list_instances(out)} == {0.04}
    assert all(path.is_relative_to(out) and path.exists() for path in paths)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh", "suite"], "leftovers"


class _Failing:
    """A capture that works for one state, then fails (a generation dying midway)."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, context: Any) -> Any:
        self.calls += 1
        if self.calls > 1:
            raise KeyboardInterrupt
        return provisional_capture(context)


def test_interrupted_generation_leaves_the_old_suite(small_suite: Path, tmp_path: Path) -> None:
    out = tmp_path / "suite"
    shutil.copytree(small_suite, out)
    before = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    faster = load_config().with_mpc(dt=0.04)
    with pytest.raises(KeyboardInterrupt):
        generate_suite(SMALL, out, config=faster, capture=_Failing(), progress=False)
    after = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["suite"], "leftovers"


def test_generation_refuses_a_directory_of_other_files(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not a suite's instances"):
        generate_suite(SMALL, tmp_path, capture=provisional_capture, progress=False)
    assert main(["problems", "generate", "--out", str(tmp_path), "--capture",
                 "provisional", "--quiet"]) == 2
    assert "--out" in _one_line_error(capsys.readouterr())
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


# --- paths under a file, read-only, disk full ---------------------------------------------------
def test_results_path_under_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("")
    for argv in (["run"], ["perf"], ["report"], ["problems", "generate", "--out"]):
        target = str(blocker / "sub")
        full = [*argv, target] if argv[-1] == "--out" else [*argv, "--results", target]
        assert main(full) == 2, full
        line = _one_line_error(capsys.readouterr())
        assert "is under" in line and "blocker, which is a file" in line, line


def test_os_error_of_a_real_full_device_is_one_line() -> None:
    with pytest.raises(OSError) as caught, open("/dev/full", "wb", buffering=0) as device:
        device.write(b"x")
    assert caught.value.errno == errno.ENOSPC
    assert describe_os_error(caught.value) == "no space left on the device (ENOSPC)"
    named = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/results/quick/cells/c.json")
    assert describe_os_error(named) == \
        "/results/quick/cells/c.json: no space left on the device"


def _namespaces_work(tmp_path: Path) -> bool:
    """Whether ``unshare -rm`` can mount a tmpfs here (a user and mount namespace)."""
    if shutil.which("unshare") is None:
        return False
    probe = tmp_path / "probe"
    probe.mkdir()
    done = subprocess.run(["unshare", "-rm", "sh", "-c",
                           f"mount -t tmpfs -o size=64k tmpfs {probe}"],
                          capture_output=True, timeout=30)
    return done.returncode == 0


@pytest.fixture
def small_mount(tmp_path: Path) -> Iterator[Path]:
    """An empty mount point for a 64 KiB tmpfs (skips where namespaces are not allowed)."""
    if not _namespaces_work(tmp_path):
        pytest.skip("no user and mount namespaces (unshare -rm) for a small file system")
    point = tmp_path / "mnt"
    point.mkdir()
    yield point


def _in_namespace(mount: str, point: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    """``python -m c3bench ARGV`` with a 64 KiB tmpfs on ``point`` (``mount`` then its
    options), in a private mount namespace."""
    script = f"mount -t tmpfs -o size=64k tmpfs {point} && {mount} exec \"$@\""
    return subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", sys.executable, "-m",
                           "c3bench", *argv], cwd=point.parent, env=_env(),
                          capture_output=True, text=True, timeout=180)


def test_disk_full_is_one_line_naming_the_file(small_mount: Path) -> None:
    done = _in_namespace("", small_mount, "problems", "generate", "--capture", "provisional",
                         "--quiet", "--out", str(small_mount / "suite"))
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(f"error: {small_mount / 'suite'}/")
    assert done.stderr.rstrip().endswith(": no space left on the device")


def test_read_only_results_is_one_line_naming_the_path(small_mount: Path) -> None:
    read_only = f"mount -o remount,ro {small_mount} &&"
    done = _in_namespace(read_only, small_mount, "run", "--suite", "quick", "--solvers",
                         "lemke", "--families", "lcp", "--results", str(small_mount / "r"))
    assert done.returncode == 2, done.stderr  # bad input, found before any work
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr == \
        f"error: --results: cannot write to {small_mount / 'r'}: read-only file system\n"


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_unwritable_results_is_one_line(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    try:
        assert main(["run", "--solvers", "lemke", "--families", "lcp", "--results",
                     str(locked / "r"), "--quiet"]) == 2
        line = _one_line_error(capsys.readouterr())
        assert "--results: cannot write to" in line and "permission denied" in line
    finally:
        locked.chmod(0o755)


UNWRITABLE = Path("/proc/c3bench-test")
"""A results root that cannot be created (even by root): under /proc."""


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("argv", [
    ["run", "--suite", "quick", "--solvers", "lemke", "--families", "lcp", "--quiet"],
    ["perf", "--samples", "1", "--backend", "c3plus-riccati", "--repeats", "1", "--warmup",
     "0", "--iterations", "1"],
    ["closed-loop", "--quiet"], ["closed-loop-trials", "--trials", "1", "--quiet"],
    ["sweep", "--dt", "0.05", "--rho-schedule", "adaptive", "--q-box", "2e5", "--model-l",
     "0.29", "--quiet"],
], ids=lambda argv: argv[0])
def test_unwritable_results_is_bad_input_before_any_work(
        argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*argv, "--results", str(UNWRITABLE)]) == 2
    line = _one_line_error(capsys.readouterr())
    assert line.startswith(f"error: --results: cannot write to {UNWRITABLE}"), line


# --- damaged results files ----------------------------------------------------------------------
def _reported_suite(tmp_path: Path) -> store.SuitePaths:
    """A stored suite with one (synthetic) cell and a run_info.json."""
    from synthetic_results import row

    paths = store.SuitePaths.of(tmp_path, "damaged")
    paths.cells.mkdir(parents=True)
    store.write_json(paths.cells / "one.json", row(cell_id="one"))
    store.write_json(paths.run_info, {"date": "2025-01-01", "packages": {}})
    return paths


@pytest.mark.parametrize(("which", "damage", "words"), [
    ("run_info", lambda text: text[:10], "not a c3bench run_info.json"),
    ("run_info", lambda text: "[1, 2]", "a JSON list, expected an object"),
    ("run_info", lambda text: '{"packages": [1]}', "packages is not an object"),
    ("run_info", lambda text: '{"solver_table": [1]}', "solver_table"),
    ("cell", lambda text: "[1, 2]", "a JSON list, expected an object"),
    ("cell", lambda text: text[:10], "not a c3bench cell file"),
    ("cell", lambda text: "\udcff", "damaged"),
], ids=["run_info-truncated", "run_info-list", "run_info-packages", "run_info-table",
        "cell-list", "cell-truncated", "cell-not-utf8"])
def test_a_damaged_results_file_is_one_line_naming_it(
        which: str, damage: Any, words: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    paths = _reported_suite(tmp_path)
    target = paths.run_info if which == "run_info" else paths.cells / "one.json"
    damaged = damage(target.read_text())
    target.write_bytes(damaged.encode("utf-8", "surrogateescape"))
    assert main(["report", "--suite", "damaged", "--results", str(tmp_path),
                 "--no-figures"]) == 2
    line = _one_line_error(capsys.readouterr())
    assert line.startswith(f"error: {target}: damaged") and words in line, line
    assert not paths.report.exists()


# --- perf keeps every run -----------------------------------------------------------------------
PERF = ["perf", "--samples", "1", "--backend", "c3plus-riccati", "--repeats", "1",
        "--warmup", "0", "--iterations", "1"]


def test_perf_keeps_every_run_and_reports_the_latest(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    from c3bench.bench.report import perf_report_section

    history = REPO / "results" / "perf" / "perf.parquet"
    perf = store.perf_dir(tmp_path)
    perf.mkdir(parents=True)
    shutil.copy(history, perf / "perf.parquet")  # the committed table, before per-run files
    committed = perf_store.read_perf(tmp_path)
    assert main([*PERF, "--results", str(tmp_path)]) == 0
    assert main([*PERF, "--results", str(tmp_path)]) == 0
    capsys.readouterr()
    stored = perf_store.read_perf(tmp_path)
    new_runs = sorted(set(stored["run_id"]) - set(committed["run_id"]))
    assert len(new_runs) == 2, "each perf run is kept under its own id"
    kept = stored[stored["run_id"].isin(set(committed["run_id"]))].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept, committed, check_dtype=False)
    assert len(perf_store.perf_run_files(tmp_path)) == committed["run_id"].nunique() + 2
    latest = perf_store.latest_perf_runs(stored)
    this_host = latest[latest["run_id"] == new_runs[-1]]
    assert len(this_host) == 4 and (this_host["backend"] == "c3plus-riccati").all()  # 1 round
    # only the round's matmul probe ran before its first step
    assert list(this_host["cache"]) == ["cold", "warm", "warm", "warm"]
    section = perf_report_section(tmp_path)
    assert "earlier run(s) are kept" in section and new_runs[-1] in section
    csv = pd.read_csv(perf_store.perf_files(tmp_path)[1])
    assert len(csv) == len(stored)
    assert np.array_equal(np.sort(csv["run_id"].astype(str).unique()),
                          np.sort(stored["run_id"].astype(str).unique()))


def test_sequence_all_without_sequence_cells_is_bad_input(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--sequence-all`` with starts that plan no sequence cell would change nothing."""
    assert main(["run", "--results", str(tmp_path), "--start", "cold", "--sequence-all",
                 "--quiet"]) == 2
    line = _one_line_error(capsys.readouterr())
    assert "--sequence-all" in line and "--start" in line
    assert not any(tmp_path.iterdir())


def test_an_unknown_argument_points_at_its_command_help(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--bogus"]) == 2
    assert "(see `c3bench run --help`)" in _one_line_error(capsys.readouterr())
    assert main(["problems", "list", "somewhere", "--bogus"]) == 2
    assert "(see `c3bench problems list --help`)" in _one_line_error(capsys.readouterr())
