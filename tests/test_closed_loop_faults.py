"""Closed-loop faults, each real: bad options refused before anything is simulated, and QP
backends that hang, crash or return NaN inside the loop counted per step with their reason.

The misbehaving backends are module-level classes registered for one test at a time (the
per-step time limit runs them in a child process, which imports this module to unpickle
them); their names start with ``test_`` so they never clash with a real backend.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.instance import Problem
from c3bench.problems.names import Family
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart

QP_FAMILIES = (Family.C3PLUS_QP, Family.C3_QP)


class HangingQP(Backend):
    """A QP backend whose solve never returns."""

    name = "test_hanging_qp"
    families = QP_FAMILIES

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        time.sleep(3600)
        raise AssertionError("a hanging solve returned")


class NaNQP(Backend):
    """A QP backend that claims success with a NaN solution."""

    name = "test_nan_qp"
    families = QP_FAMILIES

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        return Result(self.name, problem.name, True, "solved", x=np.full(problem.n, np.nan))


class CrashingQP(Backend):
    """A QP backend that kills the process solving it (a segfault's effect)."""

    name = "test_crashing_qp"
    families = QP_FAMILIES

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        os._exit(11)


class MissingQP(Backend):
    """A QP backend whose package is not installed."""

    name = "test_missing_qp"
    families = QP_FAMILIES
    package = "c3bench_no_such_package"

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        raise AssertionError("an unavailable backend was called")


@pytest.fixture
def faulty(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register the misbehaving backends for one test."""
    registry.backends()  # load the real ones first
    for backend in (HangingQP(), NaNQP(), CrashingQP(), MissingQP()):
        monkeypatch.setitem(registry._BACKENDS, backend.name, backend)


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, float]:
    """Run ``c3bench argv`` in this process: exit code, stderr and wall time."""
    from c3bench.bench.cli import main

    start = time.perf_counter()
    code = main(argv)
    elapsed = time.perf_counter() - start
    return code, capsys.readouterr().err, elapsed


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


# --- bad options: exit 2 before anything is simulated -----------------------------------------
@pytest.mark.parametrize(("argv", "expected"), [
    (["--qp-backend", "nosuch"], "--qp-backend: unknown solver 'nosuch'"),
    (["--qp-backend", "lemke"], "--qp-backend: solver 'lemke' does not take c3plus_qp"),
    (["--controller", "c3", "--qp-backend", "lemke"],
     "--qp-backend: solver 'lemke' does not take c3_qp"),
    (["--controller", "c3", "--projection", "osqp"],
     "--projection: solver 'osqp' does not take projection"),
    (["--controller", "c3", "--projection", "nosuch"], "--projection: unknown solver"),
    (["--qp-backend", "test_missing_qp"],
     "--qp-backend: solver 'test_missing_qp' is not available here"),
    (["--duration", "0.07"], "--duration must be a positive multiple of dt = 0.05 s"),
    (["--render", "animation.png"], "--render: expected a path ending in .gif"),
])
def test_bad_closed_loop_option_exits_2_at_once(argv: list[str], expected: str, faulty: None,
                                                tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    code, err, elapsed = _cli(["closed-loop", "--quiet", "--results", str(tmp_path / "out"),
                               *argv], capsys)
    assert code == 2
    assert expected in _one_error_line(err)
    assert elapsed < 5.0  # refused up front: a 2 s run takes longer than this
    assert not (tmp_path / "out" / "closed_loop" / "runs").exists() or not any(
        (tmp_path / "out" / "closed_loop" / "runs").iterdir())


def test_fast_controller_refuses_a_qp_backend(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The fast path has no QP backend: naming one is bad input (it would be ignored), before
    anything is simulated or written."""
    code, err, _ = _cli(["closed-loop", "--controller", "c3plus-fast", "--qp-backend",
                         "nosuch", "--duration", "0.1", "--quiet", "--results",
                         str(tmp_path / "results")], capsys)
    assert code == 2 and "does not apply" in err and "--qp-backend" in err, err
    assert not (tmp_path / "results").exists()


def test_results_under_a_file_fails_before_simulating(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory\n")
    root = blocker / "results"
    code, err, elapsed = _cli(["closed-loop", "--quiet", "--results", str(root)], capsys)
    line = _one_error_line(err)
    assert code == 2
    assert "--results" in line and str(root / "closed_loop" / "runs") in line
    assert elapsed < 5.0
    assert blocker.read_text() == "not a directory\n"


def test_render_path_that_is_a_directory_fails_before_simulating(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "movie.gif"
    target.mkdir()
    code, err, elapsed = _cli(["closed-loop", "--quiet", "--results", str(tmp_path),
                               "--render", str(target)], capsys)
    assert code == 2 and f"--render: {target} is a directory" in _one_error_line(err)
    assert elapsed < 5.0


@pytest.mark.parametrize(("argv", "expected"), [
    (["--qp-backend", "nosuch"], "--qp-backend: unknown solver 'nosuch'"),
    (["--qp-backend", "scip"], "--qp-backend: solver 'scip' does not take c3plus_qp"),
    (["--dt", "0.4"], "--dt 0.4: a sweep run lasts 3 s"),
])
def test_bad_sweep_option_exits_2_at_once(argv: list[str], expected: str, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    code, err, elapsed = _cli(["sweep", "--quiet", "--results", str(tmp_path), *argv],
                              capsys)
    assert code == 2 and expected in _one_error_line(err)
    assert elapsed < 5.0
    assert not (tmp_path / "closed_loop").exists()


def test_suite_results_under_a_file_fails_before_running(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    code, err, elapsed = _cli(["closed-loop-suite", "--quiet", "--results",
                               str(blocker / "results")], capsys)
    assert code == 2 and "--results: cannot write to" in _one_error_line(err)
    assert elapsed < 5.0


# --- misbehaving backends inside the loop: counted per step, with the reason ------------------
def _children() -> set[int]:
    """Live descendants of this process, except multiprocessing's own helpers (the forkserver
    and the resource tracker: direct children running ``multiprocessing``'s code, which stay
    for the session). A solver's child is forked by the forkserver: a grandchild, counted."""
    import psutil

    me = psutil.Process()
    found = set()
    for child in me.children(recursive=True):
        try:
            helper = child.ppid() == me.pid and "multiprocessing" in " ".join(child.cmdline())
            if not helper and child.status() != psutil.STATUS_ZOMBIE:
                found.add(child.pid)
        except psutil.NoSuchProcess:
            continue
    return found


@pytest.mark.timeout(60)
def test_hanging_qp_backend_is_killed_at_the_step_limit(
        faulty: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two control steps, each with a QP solve that never returns: the loop finishes, each
    step is counted with its reason, and no solving process is left."""
    import pandas as pd

    from c3bench.bench.cli import build_parser
    from c3bench.bench.cli_closed_loop import cmd_closed_loop

    before = _children()
    args = build_parser().parse_args(["closed-loop", "--qp-backend", HangingQP.name,
                                      "--duration", "0.1", "--quiet", "--results",
                                      str(tmp_path)])
    args.qp_time_limit = 0.5
    start = time.perf_counter()
    assert cmd_closed_loop(args) == 0
    elapsed = time.perf_counter() - start
    out = capsys.readouterr().out
    assert "QP failures       2 of 2 steps (first: test_hanging_qp returned no solution" in out
    assert elapsed < 20.0
    run = next((tmp_path / "closed_loop" / "runs").iterdir())
    for steps in (pd.read_csv(run / "steps.csv", keep_default_na=False),
                  pd.read_parquet(run / "steps.parquet")):
        assert list(steps["qp_failures"]) == [1, 1]
        assert all("time limit of 0.5 s exceeded; process killed" in reason
                   for reason in steps["qp_failure"])
        assert all(reason.startswith("QP failed at iteration 0: ")
                   for reason in steps["fallback_reason"])
        assert not steps["ok"].any()
    assert _children() <= before  # the killed solver and the wrapper's child are gone


@pytest.mark.timeout(60)
def test_nan_and_crashing_qp_backends_are_counted(faulty: None) -> None:
    from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop
    from c3bench.problems.config import load_config

    config = load_config()
    for name, reason in ((NaNQP.name, "returned non-finite values"),
                         (CrashingQP.name, "returned no solution")):
        trajectory, records, outcome = run_closed_loop(
            ControllerSpec(qp_backend=name, qp_time_limit=2.0), config, duration=0.1)
        assert [r.qp_failures for r in records] == [1, 1]
        assert all(reason in r.qp_failure and not r.ok for r in records)
        assert outcome.qp_failure_steps == 2 and outcome.fallback_count == 2
        assert reason in outcome.qp_failure
        assert outcome.nan_count == 0  # the NaN never reached the plant
        assert np.all(np.isfinite(trajectory.states))


@pytest.mark.timeout(60)
def test_in_process_nan_backend_is_counted_without_a_time_limit(faulty: None) -> None:
    """``qp_time_limit=None`` calls the backend in this process: the same records."""
    from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop
    from c3bench.problems.config import load_config

    _, records, outcome = run_closed_loop(
        ControllerSpec(qp_backend=NaNQP.name, qp_time_limit=None), load_config(),
        duration=0.1)
    assert [r.qp_failures for r in records] == [1, 1]
    assert "non-finite" in outcome.qp_failure


@pytest.mark.timeout(120)
def test_suite_case_with_a_hanging_backend_is_a_row_with_counted_failures(
        faulty: None, tmp_path: Path) -> None:
    """In a suite the pool worker runs the loop and the time-limited QP under it: the case
    finishes as an ordinary row whose steps count the killed solves."""
    import pandas as pd

    from c3bench.bench.closed_loop import ControllerSpec
    from c3bench.bench.closed_loop_suite import Case, run_cases

    spec = ControllerSpec(qp_backend=HangingQP.name, qp_time_limit=0.5)
    run = run_cases([Case("hanging", "backends", spec, duration=0.1)], tmp_path, jobs=1,
                    progress=False)
    (row,) = run.rows
    assert row["error"] == "" and row["steps"] == 2 and row["fallback_count"] == 2
    assert row["qp_failure_steps"] == 2 and "process killed" in row["qp_failure"]
    assert row["qp_time_limit"] == 0.5
    stored = pd.read_parquet(tmp_path / "results.parquet")
    assert list(stored["qp_failure_steps"]) == [2]
    steps = pd.read_parquet(tmp_path / "cells" / "hanging" / "steps.parquet")
    assert list(steps["qp_failures"]) == [1, 1]


def test_a_healthy_run_records_no_qp_failure() -> None:
    from c3bench.bench.closed_loop import ControllerSpec, records_frame, run_closed_loop
    from c3bench.problems.config import load_config
    from c3bench.problems.scene import build_scene

    config = load_config()
    trajectory, records, outcome = run_closed_loop(ControllerSpec(qp_backend="clarabel"),
                                                   config, duration=0.1)
    frame = records_frame(trajectory, records, build_scene(config=config))
    assert list(frame["qp_failures"]) == [0, 0]
    assert list(frame["qp_failure"]) == ["", ""] and list(frame["fallback_reason"]) == ["", ""]
    assert outcome.qp_failure_steps == 0 and outcome.qp_failure == ""


@pytest.mark.parametrize(("changes", "expected"), [
    ({"samples": 0}, "--samples must be an integer >= 1"),
    ({"admm_iterations": 0}, "--iterations must be an integer >= 1"),
    ({"model_l": float("nan")}, "--model-l must be a finite number > 0"),
    ({"qp_time_limit": 0.0}, "--qp-time-limit must be a finite number > 0"),
    ({"qp_time_limit": float("inf")}, "--qp-time-limit must be a finite number > 0"),
    ({"rho_schedule": "banana"}, "--rho-schedule must be one of"),
    ({"controller": "c4"}, "--controller must be one of"),
])
def test_controller_spec_rejects_bad_values(changes: dict[str, object], expected: str) -> None:
    from c3bench.bench.closed_loop import ControllerSpec
    from c3bench.problems.errors import InputError

    with pytest.raises(InputError, match=expected):
        ControllerSpec(**changes)  # type: ignore[arg-type]
