"""Isolated solves, each against a real fault: a real hanging, crashing or process-spawning
solver in a real child process, a real daemonic parent, a real ``kill -9`` of the parent."""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.errors import BackendUnavailable, InputError
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart, settings_for
from c3bench.solvers.isolation import IsolatedBackend, solve_isolated

REPO = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
GRACE = 5.0
"""Seconds a killed process may take to disappear."""


def _record(settings: Settings, *pids: int) -> None:
    """Write ``pids`` to ``settings.options["pid_file"]`` (when given): what the test kills."""
    path = settings.options.get("pid_file")
    if path:
        Path(path).write_text(" ".join(str(pid) for pid in pids))


def _spawn_sleep() -> int:
    return subprocess.Popen(["sleep", "60"]).pid


class Exact(Backend):
    """Equality QP by its KKT system; options make it misbehave on demand."""

    name = "iso_exact"
    families = ("c3_qp", "c3plus_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        _record(settings, os.getpid())
        how = settings.options.get("misbehave", "")
        if how == "hang":
            time.sleep(600)
        elif how == "segfault":
            os.kill(os.getpid(), signal.SIGSEGV)
        elif how == "exit":
            os._exit(3)
        elif how == "raise":
            raise RuntimeError("solver exploded")
        elif how == "unavailable":
            raise BackendUnavailable("licence size limit")
        n, m = problem.n, problem.n_eq
        kkt = np.block([[problem.P, problem.A.T], [problem.A, np.zeros((m, m))]])
        solution = np.linalg.solve(kkt, np.concatenate([-problem.q, problem.b]))
        return Result(self.name, problem.name, True, "solved", x=solution[:n], y=solution[n:],
                      diagnostics={"pid": float(os.getpid())})


class SpawnsThenHangs(Backend):
    name = "iso_spawns_hangs"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        _record(settings, os.getpid(), _spawn_sleep())
        time.sleep(600)
        raise AssertionError("unreachable")


class SpawnsThenReturns(Backend):
    name = "iso_spawns_returns"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        _record(settings, os.getpid(), _spawn_sleep())
        return Result(self.name, problem.name, True, "solved", x=np.zeros(problem.n))


class Unpicklable(Backend):
    name = "iso_unpicklable"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        result = Result(self.name, problem.name, True, "solved", x=np.zeros(problem.n))
        result.diagnostics["lock"] = threading.Lock()  # type: ignore[assignment]
        return result


class Configured(Backend):
    """Solves only after its plugin's setup function ran in the solving process."""

    name = "iso_configured"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        module = sys.modules.get("iso_plugin")
        if module is None or not getattr(module, "CONFIGURED", False):
            raise RuntimeError("plugin setup did not run here")
        return Result(self.name, problem.name, True, "solved", x=np.zeros(problem.n))


FAKES = (Exact(), SpawnsThenHangs(), SpawnsThenReturns(), Unpicklable(), Configured())


@pytest.fixture(autouse=True)
def fakes(monkeypatch: pytest.MonkeyPatch) -> None:
    registry.backends()
    for backend in FAKES:
        monkeypatch.setitem(registry._BACKENDS, backend.name, backend)


def equality_qp() -> Problem:
    return Problem("eq", "c3_qp", P=np.diag([2.0, 4.0, 6.0]), q=np.array([1.0, 0.0, -1.0]),
                   A=np.array([[1.0, 1.0, 1.0]]), b=np.array([1.0]))


def small_qp() -> Problem:
    """Equalities, inequalities and bounds (a real solver's whole interface)."""
    return Problem(
        name="small", family="c3_qp", P=np.eye(4), q=np.array([-1.0, -2.0, 0.0, 1.0]),
        A=np.array([[1.0, 1.0, 0.0, 0.0]]), b=np.array([1.0]),
        G=np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 1.0]]), h=np.array([-0.5, 5.0]),
        lb=np.array([-10.0, -np.inf, -np.inf, 0.0]), ub=np.array([np.inf, 0.2, np.inf, np.inf]))


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True
    return state not in ("Z", "X")


def _gone(*pids: int, within: float = GRACE) -> bool:
    deadline = time.monotonic() + within
    while any(_alive(pid) for pid in pids):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _pids(path: Path, count: int, within: float = 60.0) -> list[int]:
    """The ``count`` pids a backend wrote to ``path`` (waits for them)."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        if path.exists():
            pids = [int(word) for word in path.read_text().split()]
            if len(pids) == count:
                return pids
        time.sleep(0.05)
    raise AssertionError(f"no {count} pids in {path}")


def _options(tmp_path: Path, **extra: object) -> dict[str, object]:
    return {"pid_file": str(tmp_path / "pids"), **extra}


# --- solve_isolated ---------------------------------------------------------------------
@pytest.mark.timeout(60)
def test_a_hanging_solve_is_killed_at_the_limit(tmp_path: Path) -> None:
    settings = Settings(time_limit=0.5, options=_options(tmp_path, misbehave="hang"))
    start = time.monotonic()
    result = solve_isolated("iso_exact", equality_qp(), settings)
    elapsed = time.monotonic() - start
    assert result.failure == Failure.TIMEOUT and not result.found
    assert result.status == "time limit of 0.5 s exceeded; process killed"
    assert result.solve_time == 0.5
    assert 0.5 <= elapsed < 0.5 + 10.0  # the limit, plus starting the child
    (pid,) = _pids(tmp_path / "pids", 1)
    assert _gone(pid, within=0.5)


@pytest.mark.timeout(60)
def test_warmup_and_repeats_get_their_own_limits(tmp_path: Path) -> None:
    """The warm-up gets the limit, then n timed solves n times the limit: a hang in the
    warm-up is caught after one limit, not after (1 + n) limits."""
    settings = Settings(time_limit=0.5, options=_options(tmp_path, misbehave="hang"))
    start = time.monotonic()
    result = solve_isolated("iso_exact", equality_qp(), settings, repeats=5, warmup=True)
    assert result.failure == Failure.TIMEOUT
    assert time.monotonic() - start < 0.5 * 5  # killed in the warm-up


@pytest.mark.timeout(60)
@pytest.mark.parametrize("backend", ["iso_spawns_hangs", "iso_spawns_returns"])
def test_a_subprocess_of_the_solver_is_killed_with_it(tmp_path: Path, backend: str) -> None:
    settings = Settings(time_limit=1.0, options=_options(tmp_path))
    result = solve_isolated(backend, equality_qp(), settings)
    child, grandchild = _pids(tmp_path / "pids", 2)
    if backend == "iso_spawns_hangs":
        assert result.failure == Failure.TIMEOUT
    else:
        assert result.found, result.status
    assert _gone(child, grandchild, within=1.0)


@pytest.mark.timeout(60)
def test_a_segfault_is_a_crash_row() -> None:
    result = solve_isolated("iso_exact", equality_qp(),
                            Settings(options={"misbehave": "segfault"}))
    assert result.failure == Failure.ERROR and not result.found
    assert result.status == "solver process died (exit code -11, signal SIGSEGV)"


@pytest.mark.timeout(60)
def test_an_exiting_solver_is_a_crash_row() -> None:
    result = solve_isolated("iso_exact", equality_qp(), Settings(options={"misbehave": "exit"}))
    assert result.failure == Failure.ERROR
    assert result.status == "solver process died (exit code 3)"


@pytest.mark.timeout(60)
def test_an_unpicklable_result_says_so() -> None:
    result = solve_isolated("iso_unpicklable", equality_qp())
    assert result.failure == Failure.ERROR
    assert result.status.startswith("the solver's result could not be sent back: TypeError")
    assert "lock" in result.status


@pytest.mark.timeout(60)
def test_exceptions_are_rows_as_in_process() -> None:
    for how, failure, text in (("raise", Failure.ERROR, "RuntimeError: solver exploded"),
                               ("unavailable", Failure.UNAVAILABLE, "licence size limit")):
        settings = Settings(options={"misbehave": how})
        isolated = solve_isolated("iso_exact", equality_qp(), settings)
        local = registry.solve("iso_exact", equality_qp(), settings)
        assert isolated.failure == local.failure == failure
        assert isolated.status.startswith(text) and local.status.startswith(text)


def test_a_backend_that_cannot_be_pickled_is_an_error_row(
        monkeypatch: pytest.MonkeyPatch) -> None:
    class Local(Exact):  # defined in a function: not importable by the child
        name = "iso_local"

    monkeypatch.setitem(registry._BACKENDS, "iso_local", Local())
    result = solve_isolated("iso_local", equality_qp())
    assert result.failure == Failure.ERROR
    assert result.status.startswith("the solve could not be sent to the solver process")


def test_checks_come_first_without_a_child() -> None:
    assert solve_isolated("no_such_solver", equality_qp()).failure == Failure.UNAVAILABLE
    mpcc = Problem("m", "mpcc", P=np.eye(2), q=np.zeros(2))
    assert solve_isolated("iso_exact", mpcc).failure == Failure.UNSUPPORTED
    bad = equality_qp()
    bad.P[0, 0] = np.nan
    assert solve_isolated("iso_exact", bad).failure == Failure.INVALID_INPUT
    with pytest.raises(InputError, match="repeats must be >= 1"):
        solve_isolated("iso_exact", equality_qp(), repeats=0)


@pytest.mark.timeout(60)
def test_results_equal_the_in_process_solve() -> None:
    name = next((n for n in ("osqp", "clarabel") if registry.get(n).availability()[0]), None)
    if name is None:
        pytest.skip("neither osqp nor clarabel is installed")
    problem, settings = small_qp(), settings_for("high_accuracy")
    local = registry.solve(name, problem, settings)
    isolated = solve_isolated(name, problem, settings, repeats=3, warmup=True)
    assert local.found and isolated.found, (local.status, isolated.status)
    for field in ("x", "y", "z", "z_box"):
        np.testing.assert_allclose(getattr(isolated, field), getattr(local, field),
                                   rtol=0, atol=1e-12)
    assert isolated.objective == pytest.approx(local.objective, abs=1e-12)
    assert isolated.diagnostics["timed_repeats"] == 3.0
    assert 0 < isolated.solve_time < 1.0


@pytest.mark.timeout(60)
def test_plugins_loaded_here_are_loaded_in_the_child(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "iso_plugin.py").write_text("CONFIGURED = False\n\n\ndef setup():\n"
                                            "    global CONFIGURED\n    CONFIGURED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "iso_plugin", raising=False)
    monkeypatch.setattr(registry, "_PLUGINS_LOADED", {})
    registry.import_plugins(["iso_plugin:setup"])
    assert registry.loaded_plugins() == ("iso_plugin:setup",)
    result = solve_isolated("iso_configured", equality_qp())
    assert result.found, result.status


def _solve_and_report(connection: Connection, pid_file: str) -> None:
    """Target of a daemonic process: a hanging solve under a 0.5 s limit."""
    registry.register(Exact())
    start = time.monotonic()
    result = solve_isolated("iso_exact", equality_qp(), Settings(
        time_limit=0.5, options={"pid_file": pid_file, "misbehave": "hang"}))
    connection.send((str(result.failure), result.status, time.monotonic() - start))


@pytest.mark.timeout(120)
def test_a_daemonic_parent_can_isolate(tmp_path: Path) -> None:
    """Dask and pool workers are daemonic processes; the solve is still killed at the limit."""
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    parent = context.Process(target=_solve_and_report, args=(sender, str(tmp_path / "pids")),
                             daemon=True)
    parent.start()
    sender.close()
    try:
        assert receiver.poll(90), "the daemonic parent sent nothing"
        failure, status, elapsed = receiver.recv()
    finally:
        parent.join(10)
    assert failure == Failure.TIMEOUT, status
    assert elapsed < 0.5 + 30.0  # the limit, plus starting the parent's own forkserver
    (pid,) = _pids(tmp_path / "pids", 1)
    assert _gone(pid)
    assert parent.exitcode == 0


def _solve_in_forked_worker(connection: Connection) -> None:
    result = solve_isolated("iso_exact", equality_qp())
    connection.send((result.found, result.status, result.diagnostics.get("pid")))


@pytest.mark.timeout(120)
def test_a_forked_worker_starts_its_own_forkserver() -> None:
    """The local pool forks its workers: a worker forked after this process started its
    forkserver must not reuse (and ``waitpid``) its parent's."""
    assert solve_isolated("iso_exact", equality_qp()).found
    context = multiprocessing.get_context("fork")
    receiver, sender = context.Pipe(duplex=False)
    worker = context.Process(target=_solve_in_forked_worker, args=(sender,), daemon=True)
    worker.start()
    sender.close()
    try:
        assert receiver.poll(90), "the forked worker sent nothing"
        found, status, pid = receiver.recv()
    finally:
        worker.join(10)
    assert found, status
    assert pid not in (None, float(os.getpid()), float(worker.pid or 0))


def _python(code: str, tmp_path: Path) -> subprocess.Popen[bytes]:
    """A Python process running ``code`` with this checkout and the test modules importable."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(HERE)]))
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


@pytest.mark.timeout(120)
def test_killing_the_parent_kills_the_solver_and_its_subprocess(tmp_path: Path) -> None:
    """``kill -9`` of the process waiting for a solve: the solving child and the process it
    started are gone within 5 s (the child's watcher of its parent's pipe, backed by the
    parent-death signal)."""
    pid_file = tmp_path / "pids"
    parent = _python(f"""
        from c3bench.solvers import registry
        from c3bench.solvers.base import Settings
        from c3bench.solvers.isolation import solve_isolated
        from test_isolation import SpawnsThenHangs, equality_qp
        registry.register(SpawnsThenHangs())
        solve_isolated("iso_spawns_hangs", equality_qp(),
                       Settings(time_limit=300, options={{"pid_file": {str(pid_file)!r}}}))
        """, tmp_path)
    try:
        child, grandchild = _pids(pid_file, 2, within=90)
        assert _alive(child) and _alive(grandchild)
        parent.kill()
        parent.wait(10)
        assert _gone(child, grandchild, within=5.0)
    finally:
        parent.kill()
        parent.communicate()


@pytest.mark.timeout(120)
def test_a_parent_gone_mid_message_ends_the_persistent_child_quietly(tmp_path: Path) -> None:
    """The closed loop's persistent child whose parent stops in the middle of sending a
    request (SIGTERM of ``c3bench closed-loop``): the pipe ends within a message, and the child
    exits 0 without printing ``OSError: got end of file during message``."""
    parent = _python("""
        import struct
        from c3bench.solvers.base import Settings
        from c3bench.solvers.isolation import IsolatedBackend
        from test_isolation import Exact, equality_qp
        backend = IsolatedBackend(Exact(), time_limit=30)
        assert backend.solve(equality_qp(), Settings()).found
        child = backend._child
        connection, process = child.connection, child.process
        connection._send(struct.pack("!i", 1 << 20) + b"x" * 16)  # a cut-off request
        connection.close()
        process.join(30)
        print("exit", process.exitcode)
        """, tmp_path)
    out, err = parent.communicate(timeout=100)
    assert parent.returncode == 0, err.decode()
    assert out.decode().split() == ["exit", "0"], (out.decode(), err.decode())
    assert "Traceback" not in err.decode() and "end of file" not in err.decode(), err.decode()


@pytest.mark.timeout(120)
def test_a_script_without_a_main_guard_is_not_rerun(tmp_path: Path) -> None:
    """A child does not re-run the parent's ``__main__`` (multiprocessing would, and this
    script would then solve again in every child); a backend defined there is refused with
    the reason."""
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent("""
        import numpy as np
        from c3bench.solvers import registry
        from c3bench.solvers.base import Backend, Result
        from c3bench.solvers.isolation import solve_isolated
        from test_isolation import Exact, equality_qp

        class InMain(Backend):
            name = "iso_in_main"
            families = ("c3_qp",)

            def solve(self, problem, settings, warm_start=None):
                return Result(self.name, problem.name, True, "solved", x=np.zeros(problem.n))

        registry.register(Exact())
        registry.register(InMain())
        print("ran")
        print(solve_isolated("iso_exact", equality_qp()).found)
        print(solve_isolated("iso_in_main", equality_qp()).status)
        """))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(HERE)]))
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=100)
    assert done.returncode == 0, done.stderr
    ran, found, status = done.stdout.splitlines()
    assert (ran, found) == ("ran", "True")
    assert status.startswith("backend class InMain is defined in __main__, which an isolated "
                             "solver process cannot import")


@pytest.mark.timeout(120)
def test_isolation_is_safe_after_jax_ran_in_the_parent(tmp_path: Path) -> None:
    """JAX started its threads in the parent; a child still starts, solves and is killed."""
    pytest.importorskip("jax")
    process = _python("""
        import jax.numpy as jnp
        from c3bench.solvers import registry
        from c3bench.solvers.base import Settings
        from c3bench.solvers.isolation import solve_isolated
        from test_isolation import Exact, equality_qp
        assert float(jnp.sum(jnp.ones(8)).block_until_ready()) == 8.0
        registry.register(Exact())
        good = solve_isolated("iso_exact", equality_qp(), repeats=3, warmup=True)
        hung = solve_isolated("iso_exact", equality_qp(),
                              Settings(time_limit=0.5, options={"misbehave": "hang"}))
        print(good.found, hung.failure)
        """, tmp_path)
    out, err = process.communicate(timeout=100)
    assert process.returncode == 0, err.decode()
    assert out.decode().split() == ["True", "timeout"]


# --- IsolatedBackend --------------------------------------------------------------------
@pytest.fixture
def isolated() -> Iterator[IsolatedBackend]:
    with IsolatedBackend(Exact(), time_limit=1.0) as backend:
        yield backend


@pytest.mark.timeout(60)
def test_isolated_backend_keeps_one_child(isolated: IsolatedBackend) -> None:
    problem = equality_qp()
    local = Exact().solve(problem, Settings())
    first = isolated.solve(problem, Settings())
    second = isolated.solve(problem, Settings())
    assert first.found and second.found
    np.testing.assert_allclose(first.x, local.x, rtol=0, atol=0)
    child = first.diagnostics["pid"]
    assert second.diagnostics["pid"] == child == float(isolated.pid or 0)
    assert child != float(os.getpid())
    isolated.close()
    assert isolated.pid is None and _gone(int(child))


@pytest.mark.timeout(60)
def test_isolated_backend_kills_an_overrun_and_restarts(isolated: IsolatedBackend,
                                                        tmp_path: Path) -> None:
    problem = equality_qp()
    start = time.monotonic()
    hung = isolated.solve(problem, Settings(options=_options(tmp_path, misbehave="hang")))
    elapsed = time.monotonic() - start
    assert hung.failure == Failure.TIMEOUT
    assert hung.status == "time limit of 1 s exceeded; process killed"
    assert 1.0 <= elapsed < 1.0 + 10.0
    (pid,) = _pids(tmp_path / "pids", 1)
    assert isolated.pid is None and _gone(pid, within=0.5)
    again = isolated.solve(problem, Settings())
    assert again.found and again.diagnostics["pid"] != pid


@pytest.mark.timeout(60)
def test_isolated_backend_survives_a_crash(isolated: IsolatedBackend) -> None:
    crashed = isolated.solve(equality_qp(), Settings(options={"misbehave": "segfault"}))
    assert crashed.failure == Failure.ERROR
    assert crashed.status == "solver process died (exit code -11, signal SIGSEGV)"
    assert isolated.solve(equality_qp(), Settings()).found


@pytest.mark.timeout(60)
def test_isolated_backend_returns_exceptions_as_failures(isolated: IsolatedBackend) -> None:
    raised = isolated.solve(equality_qp(), Settings(options={"misbehave": "raise"}))
    assert raised.failure == Failure.ERROR
    assert raised.status.startswith("RuntimeError: solver exploded")
    missing = isolated.solve(equality_qp(), Settings(options={"misbehave": "unavailable"}))
    assert missing.failure == Failure.UNAVAILABLE
    pid = isolated.pid
    assert pid is not None and isolated.solve(equality_qp(), Settings()).found
    assert isolated.pid == pid  # an exception does not cost the child


@pytest.mark.timeout(60)
def test_isolated_backend_kills_a_subprocess_of_an_overrun(tmp_path: Path) -> None:
    with IsolatedBackend(SpawnsThenHangs(), time_limit=0.5) as backend:
        result = backend.solve(equality_qp(), Settings(options=_options(tmp_path)))
    assert result.failure == Failure.TIMEOUT
    assert _gone(*_pids(tmp_path / "pids", 2), within=1.0)


@pytest.mark.timeout(60)
def test_isolated_backend_pickles_as_a_fresh_wrapper(isolated: IsolatedBackend) -> None:
    assert isolated.solve(equality_qp(), Settings()).found
    copy = pickle.loads(pickle.dumps(isolated))
    assert (copy.name, copy.time_limit, copy.pid) == (isolated.name, 1.0, None)
    with copy:
        assert copy.solve(equality_qp(), Settings()).found
        assert copy.pid not in (None, isolated.pid)


def test_isolated_backend_delegates_and_checks_its_limit() -> None:
    inner = Exact()
    backend = IsolatedBackend(inner, time_limit=2)
    assert (backend.name, backend.families, backend.precisions) == (
        inner.name, inner.families, inner.precisions)
    assert backend.accepts(equality_qp()) == (True, "")
    assert backend.accepts(Problem("m", "mpcc", P=np.eye(2), q=np.zeros(2)))[0] is False
    assert backend.pid is None  # started on the first solve only
    for bad in (0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="time limit must be a finite number > 0"):
            IsolatedBackend(inner, time_limit=bad)


def test_large_sparse_matrices_travel_compact_and_arrive_exact() -> None:
    """The persistent child gets a robust controller's big, sparse QP as nonzeros: the
    problem it solves is bit for bit the one sent, and the wire is much smaller."""
    import pickle

    from c3bench.solvers.isolation import compact, expand

    rng = np.random.default_rng(3)
    n = 600
    P = np.zeros((n, n))
    P[np.arange(n), np.arange(n)] = rng.uniform(1.0, 2.0, n)
    P[rng.integers(0, n, 200), rng.integers(0, n, 200)] = rng.standard_normal(200)
    P = P + P.T + 10 * np.eye(n)
    A = np.zeros((n // 2, n))
    A[np.arange(n // 2), 2 * np.arange(n // 2)] = 1.0
    problem = Problem("big", "c3plus_qp", P=P, q=rng.standard_normal(n), A=A,
                      b=rng.standard_normal(n // 2))
    small = pickle.dumps(compact(problem))
    assert len(small) < 0.1 * len(pickle.dumps(problem))
    back = expand(pickle.loads(small))
    for name in ("P", "q", "A", "b"):
        assert np.array_equal(getattr(back, name), getattr(problem, name))
        assert getattr(back, name).dtype == getattr(problem, name).dtype
    assert problem.P is P  # the caller's problem is untouched
