"""Infrastructure faults are never solver failures; runs stop cleanly; one run per directory.

Every test here makes a real fault happen: a Dask scheduler process killed mid-run, a solve
that hangs on a (daemonic) Dask worker, SIGTERM and ``kill -9`` of a running ``c3bench run``,
a solver that starts a subprocess, a pool worker that exits outside any solve, a second run
on a locked directory, an address where no scheduler listens. The runs are real ``c3bench``
processes on a tiny suite (four ``lcp`` instances) with the backends of a plugin written
below (``sleepy``: sleeps, then answers; ``spawner``: starts a grandchild, then hangs;
``hang``: hangs), loaded with ``--plugin`` in the run and in its workers.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
import pytest

from c3bench.bench import closed_loop_suite, runner, store
from c3bench.bench.closed_loop import ControllerSpec
from c3bench.bench.closed_loop_suite import Case, run_cases
from c3bench.bench.executors import DaskPool, LocalPool, SchedulerUnreachable, TaskOutcome
from c3bench.bench.lock import LOCK_NAME, DirectoryLock, read_holder
from c3bench.bench.reference import load_references
from c3bench.bench.rows import reference_task
from c3bench.problems.capture import SuiteSpec
from c3bench.problems.errors import InputError, ResultsLocked
from c3bench.problems.instance import Problem
from c3bench.problems.suites import generate_suite

ROOT = Path(__file__).resolve().parents[1]
SUITE = "faults"
SPEC = SuiteSpec(SUITE, n_states=4, admm_iterations=(0,), projection_iterations=(0,),
                 projection_steps=(0,))
PLUGIN = "c3bench_fault_plugin"
PLUGIN_SOURCE = '''
"""Backends that misbehave on purpose (tests/test_faults.py)."""
import os
import subprocess
import sys
import time
from pathlib import Path

from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result


def _note(kind):
    folder = os.environ.get("C3BENCH_FAULT_DIR")
    if folder:
        Path(folder, f"{kind}-{os.getpid()}").touch()


class Sleepy(Backend):
    name = "sleepy"
    families = ("lcp",)

    def solve(self, problem, settings, warm_start=None):
        _note("solver")
        time.sleep(float(os.environ.get("C3BENCH_SLEEP", "0.3")))
        return Result(self.name, problem.name, False, "slept")


class Sleepy2(Sleepy):
    name = "sleepy2"


class Spawner(Backend):
    name = "spawner"
    families = ("lcp",)

    def solve(self, problem, settings, warm_start=None):
        _note("solver")
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
        folder = os.environ.get("C3BENCH_FAULT_DIR")
        if folder:
            Path(folder, f"spawned-{child.pid}").touch()
        time.sleep(600)
        return Result(self.name, problem.name, False, "never")


class Hang(Backend):
    name = "hang"
    families = ("lcp",)

    def solve(self, problem, settings, warm_start=None):
        _note("solver")
        time.sleep(600)
        return Result(self.name, problem.name, False, "never")


for backend in (Sleepy(), Sleepy2(), Spawner(), Hang()):
    registry.register(backend)
'''
RUN = ["run", "--suite", SUITE, "--families", "lcp", "--settings", "default", "--precision",
       "float64", "--start", "cold", "--repeats", "1", "--quiet", "--no-report", "--plugin",
       PLUGIN]
N_INSTANCES = 4


# --- helpers ----------------------------------------------------------------------------------
@dataclass
class Bench:
    """A results root seeded with the tiny suite, and the environment of its processes."""

    results: Path
    notes: Path
    env: dict[str, str]

    @property
    def paths(self) -> store.SuitePaths:
        return store.SuitePaths.of(self.results, SUITE)

    def start(self, *args: str, **popen: Any) -> subprocess.Popen[str]:
        """``c3bench ARGS --results ROOT`` as a child process (output captured)."""
        return subprocess.Popen([sys.executable, "-m", "c3bench", *args, "--results",
                                 str(self.results)], cwd=ROOT, env=self.env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, **popen)

    def run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        process = self.start(*args)
        out, err = process.communicate(timeout=timeout)
        return subprocess.CompletedProcess(process.args, process.returncode, out, err)

    def rows(self) -> list[dict[str, Any]]:
        return store.read_cells(self.paths)

    def noted(self, kind: str) -> list[int]:
        """Pids the plugin noted (``solver`` processes, ``spawned`` grandchildren)."""
        return [int(p.name.split("-")[1]) for p in self.notes.glob(f"{kind}-*")]


@pytest.fixture(scope="module")
def instances(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fault_instances")
    generate_suite(SPEC, out, progress=False)
    assert len(list((out / "lcp").glob("*.json"))) == N_INSTANCES
    return out


@pytest.fixture(scope="module")
def plugin_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fault_plugin")
    (folder / f"{PLUGIN}.py").write_text(PLUGIN_SOURCE)
    return folder


@pytest.fixture
def bench(tmp_path: Path, instances: Path, plugin_dir: Path) -> Bench:
    import shutil

    results, notes = tmp_path / "results", tmp_path / "notes"
    notes.mkdir()
    shutil.copytree(instances, store.SuitePaths.of(results, SUITE).instances)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(plugin_dir), str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
        "C3BENCH_FAULT_DIR": str(notes), "C3BENCH_SLEEP": "0.3"}
    return Bench(results, notes, env)


def wait_until(condition: Callable[[], bool], timeout: float, what: str,
               process: subprocess.Popen[str] | None = None) -> None:
    """Poll ``condition``; fail after ``timeout`` s, or at once when ``process`` ended."""
    deadline = time.monotonic() + timeout
    while not condition():
        if process is not None and process.poll() is not None:
            _, err = process.communicate()
            raise AssertionError(f"the run ended ({process.returncode}) before {what}: {err}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def living(pids: set[int]) -> set[int]:
    """The processes of ``pids`` still running (zombies count as gone)."""
    alive = set()
    for pid in pids:
        with contextlib.suppress(psutil.NoSuchProcess):
            if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                alive.add(pid)
    return alive


def all_end(pids: Callable[[], set[int]], seconds: float) -> None:
    """Fail unless every process of ``pids()`` ends within ``seconds`` (naming those left)."""
    deadline = time.monotonic() + seconds
    while living(pids()):
        if time.monotonic() > deadline:
            left = []
            for pid in living(pids()):
                with contextlib.suppress(psutil.NoSuchProcess):
                    left.append(f"{pid}: {' '.join(psutil.Process(pid).cmdline())[:120]}")
            raise AssertionError(f"still running {seconds:g} s later: {left}")
        time.sleep(0.05)


def descendants(pid: int) -> set[int]:
    try:
        return {child.pid for child in psutil.Process(pid).children(recursive=True)}
    except psutil.NoSuchProcess:
        return set()


def plant_stale_cell(bench: Bench) -> str:
    """A stored ``sleepy`` cell (also in ``results.parquet``) whose instance has changed since
    (its hash differs): the next run deletes it. Returns that stale hash."""
    instance = sorted((bench.paths.instances / "lcp").glob("*.json"))[0].stem
    row = store.empty_row()
    row.update({"cell_id": store.cell_id(instance, "sleepy", "default", "float64", "cold"),
                "suite": SUITE, "instance": instance, "instance_hash": "0123456789stale",
                "family": "lcp", "solver": "sleepy", "settings": "default",
                "precision": "float64", "start": "cold", "status": "stale"})
    store.write_cell(bench.paths, row)
    assert len(store.consolidate(bench.paths)) == 1
    return str(row["instance_hash"])


def one_row_per_cell(rows: list[dict[str, Any]], expected: int) -> None:
    keys = [store.cell_key(row) for row in rows]
    assert len(keys) == len(set(keys)) == expected


def no_infrastructure_rows(rows: list[dict[str, Any]]) -> None:
    for row in rows:
        assert not re.search(r"cancel|scheduler|connection|worker", row["status"], re.I), row


@dataclass
class Cluster:
    address: str
    scheduler: subprocess.Popen[bytes]
    worker: subprocess.Popen[bytes]


@contextlib.contextmanager
def dask_cluster(folder: Path, env: dict[str, str]) -> Iterator[Cluster]:
    """A Dask scheduler on 127.0.0.1 and one nanny-managed (daemonic) worker, as processes."""
    pytest.importorskip("distributed")
    scheduler_file = folder / "scheduler.json"
    log = open(folder / "dask.log", "wb")  # noqa: SIM115 - closed below
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
         "--port", "0", "--no-dashboard", "--scheduler-file", str(scheduler_file)],
        env=env, stdout=log, stderr=log, start_new_session=True)
    worker: subprocess.Popen[bytes] | None = None
    try:
        wait_until(lambda: scheduler_file.exists() and scheduler_file.stat().st_size > 0, 60,
                   "the scheduler")
        address = json.loads(scheduler_file.read_text())["address"]
        worker = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
             "--nworkers", "1", "--no-dashboard", "--death-timeout", "5",
             "--local-directory", str(folder / "dask-worker")],
            env=env, stdout=log, stderr=log, start_new_session=True)
        yield Cluster(address, scheduler, worker)
    finally:
        for process in (worker, scheduler):
            if process is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                process.wait(10)
        log.close()


# --- Dask -------------------------------------------------------------------------------------
@pytest.mark.timeout(180)
def test_lost_scheduler_stores_no_rows_for_unrun_cells_and_the_next_run_completes_them(
        bench: Bench, tmp_path: Path) -> None:
    planned = 2 * N_INSTANCES
    with dask_cluster(tmp_path, bench.env) as cluster:
        run = bench.start(*RUN, "--solvers", "sleepy", "sleepy2", "--time-limit", "5",
                          "--scheduler", cluster.address)
        wait_until(lambda: len(list(bench.paths.cells.glob("*.json"))) >= 2, 120,
                   "two stored cells", run)
        cluster.scheduler.kill()
        _, err = run.communicate(timeout=60)
    rows = bench.rows()
    missing = planned - len(rows)
    assert run.returncode == 1, err
    assert 0 < missing < planned
    assert re.search(rf"\b{missing} cells? missing", err), err
    assert "Traceback" not in err
    no_infrastructure_rows(rows)
    # the consolidated table holds exactly the stored cells
    assert len(store.read_results(bench.paths.parquet)) == len(rows)

    again = bench.run(*RUN, "--solvers", "sleepy", "sleepy2", "--time-limit", "5")
    assert again.returncode == 0, again.stderr
    assert f"{len(rows)} already stored, {missing} run" in again.stdout
    one_row_per_cell(bench.rows(), planned)


@pytest.mark.timeout(180)
def test_a_hanging_solve_on_a_daemonic_dask_worker_is_killed_at_the_limit(
        bench: Bench, tmp_path: Path) -> None:
    with dask_cluster(tmp_path, bench.env) as cluster:
        started = time.monotonic()
        done = bench.run(*RUN, "--solvers", "hang", "--time-limit", "1",
                         "--scheduler", cluster.address)
        elapsed = time.monotonic() - started
        # checked while the worker still runs: the solving processes were killed, not
        # abandoned in a thread
        solvers = set(bench.noted("solver"))
        assert solvers and not living(solvers)
    assert done.returncode == 0, done.stderr
    rows = bench.rows()
    one_row_per_cell(rows, N_INSTANCES)
    for row in rows:
        assert row["failure"] == "timeout" and row["time_limit"] == 1.0
        assert "killed" in row["status"]
        assert row["solve_time"] <= 1.0 + 1e-9 or math.isnan(row["solve_time"])
    assert elapsed < 90


# --- references lost to the infrastructure ----------------------------------------------
def dying_reference(doomed: str, problem: Problem, *args: Any) -> Any:
    """``reference_task`` whose worker dies for instance ``doomed``."""
    if problem.name == doomed:
        os._exit(5)
    return reference_task(problem, *args)


@pytest.mark.timeout(180)
def test_a_reference_lost_to_a_dead_worker_is_not_cached_and_its_cells_wait(
        tmp_path: Path, instances: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    paths = store.SuitePaths.of(tmp_path, SUITE)
    shutil.copytree(instances, paths.instances)
    doomed = sorted((paths.instances / "lcp").glob("*.json"))[0].stem
    options: dict[str, Any] = dict(solvers=["pgs"], families=("lcp",), starts=("cold",),
                                   precisions=("float64",), repeats=1, time_limit=5.0,
                                   jobs=1, progress=False)
    monkeypatch.setattr(runner, "reference_task", functools.partial(dying_reference, doomed))
    first = runner.run_suite(SUITE, tmp_path, **options)  # forked workers inherit the patch
    assert (first.ran, first.missing) == (N_INSTANCES - 1, 1)
    assert first.missing_reasons == ["reference not computed: pool worker died (exit code 5) "
                                     "outside the isolated solve"]
    assert doomed not in load_references(paths.references)  # not cached as a failure
    assert doomed not in {row["instance"] for row in store.read_cells(paths)}
    monkeypatch.undo()
    second = runner.run_suite(SUITE, tmp_path, **options)
    assert (second.already_done, second.ran, second.missing) == (N_INSTANCES - 1, 1, 0)
    assert second.references_computed == 1
    assert load_references(paths.references)[doomed].available
    one_row_per_cell(store.read_cells(paths), N_INSTANCES)


def test_an_unreachable_scheduler_is_one_error_naming_it_within_the_timeout() -> None:
    pytest.importorskip("distributed")
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    started = time.monotonic()
    with pytest.raises(SchedulerUnreachable, match=re.escape(address)):
        DaskPool(address, connect_timeout=2)
    assert time.monotonic() - started < 10


def _cli_env() -> dict[str, str]:
    """The environment of a ``python -m c3bench`` child: this checkout first."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}


@pytest.mark.parametrize(("address", "words"), [
    ("garbage", "missing port number in address 'garbage'"),
    ("tcp://127.0.0.1:99999", "port 99999 is not in 1-65535"),
    ("nosuch://host:1", "unknown address scheme 'nosuch'"),
])
def test_a_malformed_scheduler_address_fails_at_once_without_a_half_made_client(
        address: str, words: str) -> None:
    """No ``Client`` is made for an address Dask cannot parse: one half made waits 20 s in
    its finaliser and prints a ``TimeoutError`` traceback."""
    pytest.importorskip("distributed")
    started = time.monotonic()
    with pytest.raises(InputError, match=re.escape(f"--scheduler {address!r}: ") + ".*"
                       + re.escape(words)):
        DaskPool(address)
    gc.collect()
    assert time.monotonic() - started < 5


@pytest.mark.timeout(120)
def test_a_malformed_scheduler_address_on_the_cli_is_one_line_and_creates_nothing(
        tmp_path: Path) -> None:
    results = tmp_path / "results"
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "c3bench", "closed-loop-trials",
                           "--scheduler", "garbage", "--results", str(results)], cwd=ROOT,
                          env=_cli_env(), capture_output=True, text=True, timeout=100)
    assert done.returncode == 2, done.stderr
    # nothing after the line: no client finaliser waiting 20 s, then a TimeoutError traceback
    assert done.stderr == ("error: --scheduler 'garbage': missing port number in address "
                           "'garbage'\n"), done.stderr
    assert time.monotonic() - started < 20
    assert not results.exists()


# --- SIGTERM of every long command --------------------------------------------------------------
def _terminate(process: subprocess.Popen[str], tree: set[int]) -> str:
    """SIGTERM ``process``; check it exits 143 with the one line ``terminated (SIGTERM)``
    and that every process of ``tree`` ends; return its stderr."""
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 143, err
    assert err == "terminated (SIGTERM)\n", err
    all_end(lambda: tree, 5)
    return err


@pytest.mark.timeout(180)
def test_sigterm_of_problems_generate_leaves_no_staging_folder(tmp_path: Path) -> None:
    out = tmp_path / "G"
    process = subprocess.Popen(
        [sys.executable, "-m", "c3bench", "problems", "generate", "--suite", "default",
         "--capture", "provisional", "--quiet", "--out", str(out)], cwd=ROOT, env=_cli_env(),
        text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: any(tmp_path.glob(".G.generating-*")), 120,
                   "the staging folder", process)
        _terminate(process, descendants(process.pid))
    finally:
        process.kill()
        process.communicate()
    assert sorted(path.name for path in tmp_path.iterdir()) == []


@pytest.mark.timeout(180)
def test_sigterm_of_a_closed_loop_run_stops_it_and_its_qp_child(tmp_path: Path) -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "c3bench", "closed-loop", "--duration", "30", "--quiet",
         "--results", str(tmp_path / "results")], cwd=ROOT, env=_cli_env(), text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_until(lambda: bool(descendants(process.pid)), 120, "the QP child", process)
        time.sleep(1.0)  # some control steps, each a request to the child
        _terminate(process, descendants(process.pid))
    finally:
        process.kill()
        process.communicate()


# --- SIGTERM and kill -9 of the run -----------------------------------------------------------
@pytest.mark.timeout(180)
@pytest.mark.parametrize("stop", [
    signal.SIGTERM,
    # kill -9 leaves what SIGTERM leaves minus the cleanup; opt-in to keep the default run
    # inside CI's 15 minutes (test_bench's interrupt test resumes after a hard stop too)
    pytest.param(signal.SIGKILL, marks=pytest.mark.slow)], ids=["sigterm", "kill-9"])
def test_a_stopped_run_leaves_no_process_and_a_resume_stores_each_cell_once(
        bench: Bench, stop: signal.Signals) -> None:
    planned = 2 * N_INSTANCES
    stale_hash = plant_stale_cell(bench)
    run = bench.start(*RUN, "--solvers", "sleepy", "spawner", "--time-limit", "1",
                      "--jobs", "2")
    wait_until(lambda: bench.noted("spawned") and any(
        row["instance_hash"] != stale_hash for row in bench.rows()), 120,
               "a stored cell and a running solver's subprocess", run)
    tree = descendants(run.pid) | set(bench.noted("spawned"))
    assert len(tree) >= 3  # two workers and at least one solving child or grandchild
    os.kill(run.pid, stop)
    # within 5 s of the signal: no worker, solving child, forkserver or grandchild left
    all_end(lambda: tree | set(bench.noted("spawned")), 5)
    _, err = run.communicate(timeout=60)
    stored = bench.rows()
    assert not any(row["instance_hash"] == stale_hash for row in stored)
    # the consolidated table has no row of a deleted cell, even after kill -9: the stale
    # cell was dropped from it before any work
    table = store.read_results(bench.paths.parquet)
    assert not (table["instance_hash"] == stale_hash).any()
    if stop == signal.SIGTERM:
        assert run.returncode == 143, err
        assert re.search(rf"terminated: {len(stored)} cells stored in", err), err
        assert "Traceback" not in err and "(SIGTERM)" not in err  # one line, not two
        assert len(table) == len(stored)  # what finished is consolidated
    else:
        assert run.returncode == -signal.SIGKILL

    again = bench.run(*RUN, "--solvers", "sleepy", "spawner", "--time-limit", "1",
                      "--jobs", "2")
    assert again.returncode == 0, again.stderr
    rows = bench.rows()
    one_row_per_cell(rows, planned)
    no_infrastructure_rows(rows)
    spawner = [row for row in rows if row["solver"] == "spawner"]
    assert all(row["failure"] == "timeout" for row in spawner)
    # a solver that starts a subprocess leaves nothing behind
    assert not living(set(bench.noted("spawned")) | set(bench.noted("solver")))


# --- one run per results directory ------------------------------------------------------------
@pytest.mark.timeout(120)
def test_a_second_run_on_the_same_directory_refuses_naming_the_first(bench: Bench) -> None:
    bench.env["C3BENCH_SLEEP"] = "1.0"
    first = bench.start(*RUN, "--solvers", "sleepy", "--time-limit", "5")
    try:
        wait_until(lambda: read_holder(bench.paths.root) is not None, 60,
                   "the first run's lock", first)
        second = bench.run(*RUN, "--solvers", "sleepy", "--time-limit", "5")
        assert second.returncode == 1
        message = second.stderr.strip()
        assert message.count("\n") == 0, message
        assert re.fullmatch(
            rf"error: results directory {re.escape(str(bench.paths.root))} is in use by pid "
            rf"{first.pid} on \S+ since \S+ \(command .*c3bench.* run .*\)", message), message
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    assert first.returncode == 143
    assert not (bench.paths.root / LOCK_NAME).exists()


LOCKER = """
import sys, time
from c3bench.bench.lock import DirectoryLock
with DirectoryLock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(60)
"""


@pytest.mark.timeout(60)
def test_a_closed_loop_suite_refuses_a_locked_directory_and_the_lock_dies_with_its_holder(
        tmp_path: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", LOCKER, str(tmp_path)], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        case = Case("c", "backends", ControllerSpec(controller="c3plus"))
        with pytest.raises(ResultsLocked, match=rf"in use by pid {holder.pid} on "):
            run_cases([case], tmp_path, jobs=1, progress=False)
        assert not (tmp_path / "cells").exists()  # nothing was started
    finally:
        holder.kill()
        holder.wait(10)
    with DirectoryLock(tmp_path):  # kill -9 released it
        pass


# --- a worker that dies outside a solve -------------------------------------------------------
def die_once(marker: str) -> str:
    path = Path(marker)
    if not path.exists():
        path.write_text("died once")
        os._exit(3)
    return "second attempt"


def always_die() -> None:
    os._exit(4)


def raise_error() -> None:
    raise RuntimeError("broken task")


def unpicklable() -> Any:
    return lambda: None


def test_a_worker_dying_outside_a_solve_is_retried_then_reported_never_a_value(
        tmp_path: Path) -> None:
    pool = LocalPool(2)
    marker = tmp_path / "marker"
    results = {r.key: r for r in pool.run([
        ("once", die_once, (str(marker),), 30.0), ("always", always_die, (), 30.0),
        ("raises", raise_error, (), 30.0), ("lambda", unpicklable, (), 30.0),
        ("fine", pow, (2, 5), 30.0)])}
    assert results["fine"].ok and results["fine"].value == 32
    assert results["once"].ok and results["once"].value == "second attempt"
    assert results["once"].attempts == 2
    dead = results["always"]
    assert dead.outcome == TaskOutcome.WORKER_DIED and dead.attempts == 2
    assert "exit code 4" in dead.reason
    assert results["raises"].outcome == TaskOutcome.TASK_RAISED
    assert "RuntimeError: broken task" in results["raises"].reason
    assert results["lambda"].outcome == TaskOutcome.TASK_RAISED
    assert "cannot be sent back" in results["lambda"].reason
    assert pool.workers == []


def dying_case(case: Case, cell_dir: str) -> dict[str, Any]:
    """A closed-loop case task whose worker dies for case ``die``; others answer a row."""
    if case.name == "die":
        os._exit(9)
    return {"case": case.name, "success": True, "error": ""}


def test_a_closed_loop_worker_death_is_not_a_row(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(closed_loop_suite, "run_case", dying_case)  # forked workers inherit it
    spec = ControllerSpec(controller="c3plus")
    run = run_cases([Case("ok", "backends", spec), Case("die", "backends", spec)], tmp_path,
                    jobs=2, progress=False)
    assert [row["case"] for row in run.rows] == ["ok"]
    assert run.missing == 1
    assert run.missing_reasons == ["pool worker died (exit code 9) outside the isolated solve"]
    import pandas as pd

    assert list(pd.read_parquet(tmp_path / "results.parquet")["case"]) == ["ok"]
    assert not (tmp_path / LOCK_NAME).exists()
