"""The solver's child process: started from a forkserver, in its own process group, killed
with everything it started, dying with its parent. The plumbing of
:mod:`c3bench.solvers.isolation` (which says what runs in the child and what becomes a row).

* **Start method.** A ``forkserver`` (``spawn`` where there is none), never ``fork``: threads of
  the parent (JAX, BLAS pools, Dask's) cannot leave the child holding a lock. The forkserver
  preloads the registry, the backend modules and the solver packages (:func:`preload_solvers`,
  through :data:`PRELOAD_MODULE`) and pins BLAS to one thread, so a child starts in
  milliseconds. The parent's ``__main__`` is not re-run in the child (multiprocessing would:
  :func:`_preparation_data`). A process forked from one that started a forkserver (the local
  pool's workers) forgets it and starts its own.
* **Daemonic parents** (Dask and pool workers): the daemon flag, which makes multiprocessing
  refuse children, is lifted while the child starts (:func:`start`); cleanup is ours.
* **Process group.** The child makes itself a group leader (:func:`detach`); :func:`stop`
  kills the whole group, so a subprocess the solver started dies too.
* **Parent death.** The child arms a Linux parent-death signal (its parent is the
  forkserver, which exits when the requesting process is gone) and watches the pipe
  multiprocessing keeps to the requesting process, which reaches EOF when it dies
  (``kill -9`` included): then it kills its group.
* **Messages.** The child reports :class:`Reply` messages (``STARTED``, ``READY`` once its job
  is loaded, ``WARM`` after a warm-up, ``DONE`` or ``ERROR``); the parent adds ``TIMEOUT``
  and ``DIED`` when none comes (:func:`receive`). A child that does not start raises
  :class:`IsolationFailed`: an infrastructure fault, not the solver's.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import sys
import threading
from collections.abc import Callable
from enum import StrEnum
from multiprocessing import spawn
from multiprocessing.connection import Connection
from multiprocessing.context import ForkServerContext, SpawnContext
from multiprocessing.process import BaseProcess
from multiprocessing.reduction import ForkingPickler
from typing import Any

from threadpoolctl import ThreadpoolController

from c3bench.problems.errors import C3BenchError
from c3bench.solvers import registry
from c3bench.solvers.timing import single_thread_blas

STARTUP_SECONDS = 60.0
"""Bound on starting a child, and separately on loading the solver in it (not counted in the
time limit). Generous: the first child of a process also starts the forkserver."""

JOIN_SECONDS = 5.0
"""How long to wait for a killed child to be reaped."""

PRELOAD_MODULE = "c3bench.solvers._forkserver_preload"
"""Imported once by the forkserver (it calls :func:`preload_solvers`)."""

_PR_SET_PDEATHSIG = 1  # linux/prctl.h


class IsolationFailed(C3BenchError, RuntimeError):
    """The solver's child process could not be started: an infrastructure fault, not a
    result of the solve (store nothing; the cell is run again later)."""


class Reply(StrEnum):
    """What the child reports (``STARTED`` ... ``DONE``/``ERROR``), and what the parent
    concludes without a message (``TIMEOUT``, ``DIED``)."""

    STARTED = "started"
    READY = "ready"
    WARM = "warm"
    DONE = "done"
    ERROR = "error"
    TIMEOUT = "timeout"
    DIED = "died"


Message = tuple[Reply, Any]


# --- the forkserver -----------------------------------------------------------------------
_CONTEXT: ForkServerContext | SpawnContext | None = None

PRELOAD_EXTRA = ("qpsolvers",)
"""Packages the built-in backends import besides their own ``package`` (qpsolvers also
imports JAX: an import only, no backend, no thread)."""


def _context() -> ForkServerContext | SpawnContext:
    """The start method of every child: forkserver (preloading :data:`PRELOAD_MODULE`), or
    spawn where there is no forkserver. Never fork."""
    global _CONTEXT
    if _CONTEXT is None:
        if spawn.get_preparation_data is not _preparation_data:
            spawn.get_preparation_data = _preparation_data
        if "forkserver" in multiprocessing.get_all_start_methods():
            server = multiprocessing.get_context("forkserver")
            server.set_forkserver_preload([PRELOAD_MODULE])
            _CONTEXT = server
        else:
            _CONTEXT = multiprocessing.get_context("spawn")
    return _CONTEXT


_STDLIB_PREPARATION = spawn.get_preparation_data
_STARTING = threading.local()


def _preparation_data(name: str) -> dict[str, Any]:
    """``multiprocessing.spawn.get_preparation_data``, without the main module while this
    thread starts a solver child.

    multiprocessing re-runs the parent's ``__main__`` script in every spawn or forkserver
    child so that objects defined there can be unpickled. A solver child needs none of it
    (its job arrives pickled, backends by their module), and re-running the ``c3bench``
    script would import the whole CLI into every child (0.3 s a solve) and break scripts
    without an ``if __name__ == "__main__":`` guard. Other callers (and other threads) get
    the standard data.
    """
    data: dict[str, Any] = _STDLIB_PREPARATION(name)
    if getattr(_STARTING, "solver", False):
        data.pop("init_main_from_name", None)
        data.pop("init_main_from_path", None)
    return data


def preload_solvers() -> None:
    """Import the registry, every backend module and the packages of the built-in backends,
    then pin BLAS and OpenMP to one thread (run once in the forkserver: do not call it in a
    process that does anything else). A package that fails is skipped; a child imports it.

    Only imports, not ``Backend.require`` (CasADi's plugin loading starts a thread): nothing
    here may start a thread, since the forkserver forks its children.
    """
    packages = {backend.package for backend in registry.backends().values()
                if backend.package
                and type(backend).__module__.startswith(registry.BACKEND_PACKAGE)}
    for package in sorted(packages) + list(PRELOAD_EXTRA):
        with contextlib.suppress(Exception):
            importlib.import_module(package)
    global _BLAS
    _BLAS = ThreadpoolController()  # finds the BLAS and OpenMP libraries loaded by now
    _BLAS.limit(limits=1)  # children are forked pinned; pinned_blas keeps it so


_BLAS: ThreadpoolController | None = None


def pinned_blas() -> contextlib.AbstractContextManager[Any]:
    """BLAS and OpenMP on one thread: through the forkserver's controller when there is one
    (finding the libraries again costs a fresh child some 30 ms), else
    :func:`~c3bench.solvers.timing.single_thread_blas`."""
    if _BLAS is not None:
        limiter: contextlib.AbstractContextManager[Any] = _BLAS.limit(limits=1)
        return limiter
    return single_thread_blas()


def _forkserver_state() -> Any:
    """multiprocessing's forkserver client state (private; ``None`` where it has none)."""
    try:
        from multiprocessing import forkserver
    except ImportError:
        return None
    return getattr(forkserver, "_forkserver", None)


def _forget_inherited_forkserver() -> None:
    """After ``fork``: forget the parent's forkserver (a forked pool worker would otherwise
    ask ``waitpid`` about a process that is not its child and fail); the first solve here
    starts a forkserver of its own."""
    server = _forkserver_state()
    if server is None or getattr(server, "_forkserver_pid", None) is None:
        return
    fd = server._forkserver_alive_fd
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)
    server._forkserver_pid = None
    server._forkserver_alive_fd = None
    server._forkserver_address = None
    server._lock = threading.Lock()


os.register_at_fork(after_in_child=_forget_inherited_forkserver)


# --- the child side -----------------------------------------------------------------------
def _kill_own_group() -> None:
    """Kill this child and everything it started (its own process group)."""
    if os.getpgrp() == os.getpid():
        os.killpg(os.getpid(), signal.SIGKILL)
    os.kill(os.getpid(), signal.SIGKILL)


def _libc() -> ctypes.CDLL | None:
    """The C library (Linux only: for ``prctl``)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


_LIBC = _libc()


def _arm_parent_death_signal() -> None:
    """``SIGKILL`` this process when its parent dies (Linux ``prctl``; a no-op elsewhere)."""
    if _LIBC is not None:
        with contextlib.suppress(AttributeError):
            _LIBC.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)


def _release_forkserver() -> None:
    """Close the forkserver's 'alive' pipe end a forkserver child inherits: holding it would
    keep the forkserver (this child's parent) running after the requesting process died, and
    the parent-death signal would never come."""
    server = _forkserver_state()
    fd = getattr(server, "_forkserver_alive_fd", None)
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)
        server._forkserver_alive_fd = None


def _watch_requester() -> None:
    """Kill the group when the requesting process dies: the pipe multiprocessing keeps to it
    (the parent sentinel) reaches EOF then, ``kill -9`` included."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return
    sentinel = parent.sentinel

    def watch() -> None:
        try:
            multiprocessing.connection.wait([sentinel])
        except (OSError, ValueError):
            return  # cannot watch; the parent-death signal still holds
        _kill_own_group()

    threading.Thread(target=watch, name="c3bench-watch-parent", daemon=True).start()


def detach() -> None:
    """Child side: own process group; die with the parent."""
    parent = os.getppid()
    os.setpgrp()
    _release_forkserver()
    _arm_parent_death_signal()
    if os.getppid() != parent:  # the parent died before the signal was armed
        _kill_own_group()
    _watch_requester()


def send(connection: Connection, message: Message) -> None:
    """Send ``message``; one that cannot be pickled is replaced by an error saying so."""
    try:
        data = bytes(ForkingPickler.dumps(message))
    except Exception as error:  # noqa: BLE001 - any pickling error is reported
        data = bytes(ForkingPickler.dumps((
            Reply.ERROR, f"the solver's result could not be sent back: "
                         f"{type(error).__name__}: {error}")))
    connection.send_bytes(data)


def load(connection: Connection, plugins: tuple[str, ...], payload: bytes) -> Any:
    """The parent's plugins loaded, then ``payload`` unpickled; ``None`` (and the error
    sent) when either fails."""
    try:
        registry.import_plugins(plugins)
        return pickle.loads(payload)
    except Exception as error:  # noqa: BLE001 - reported to the parent
        send(connection, (Reply.ERROR, f"the solver process could not load the solver: "
                                       f"{type(error).__name__}: {error}"))
        return None


# --- the parent side ----------------------------------------------------------------------
_START_LOCK = threading.Lock()


def start(process: BaseProcess) -> None:
    """Start ``process``, from a daemonic process too; :class:`IsolationFailed` when it
    cannot be started."""
    current = multiprocessing.current_process()
    with _START_LOCK:
        daemonic = bool(current.daemon)
        try:
            if daemonic:  # multiprocessing refuses children of daemons; cleanup is ours
                current.daemon = False
            _STARTING.solver = True
            process.start()
        except Exception as error:
            raise IsolationFailed(f"cannot start a solver process: "
                                  f"{type(error).__name__}: {error}") from error
        finally:
            _STARTING.solver = False
            if daemonic:
                current.daemon = True


def stop(process: BaseProcess) -> None:
    """Kill the child's process group (the child and whatever it started), reap the child and
    release its handles."""
    if process.pid is not None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(process.pid, signal.SIGKILL)
        with contextlib.suppress(OSError, ValueError):
            process.kill()  # not yet its own group leader
        process.join(JOIN_SECONDS)
    with contextlib.suppress(ValueError):
        process.close()


def receive(connection: Connection, seconds: float) -> Message:
    """The child's next message within ``seconds``; ``TIMEOUT`` or ``DIED`` when none."""
    if not connection.poll(max(seconds, 0.0)):
        return Reply.TIMEOUT, None
    try:
        kind, payload = connection.recv()
    except (EOFError, OSError):
        return Reply.DIED, None
    except Exception as error:  # noqa: BLE001 - e.g. a class the parent cannot import
        return Reply.ERROR, (f"the solver's result could not be read: "
                             f"{type(error).__name__}: {error}")
    return Reply(kind), payload


def died(process: BaseProcess) -> str:
    """The reason of a child that died: "solver process died (exit code N[, signal NAME])"."""
    process.join(JOIN_SECONDS)
    code = process.exitcode
    if code is not None and code < 0:
        with contextlib.suppress(ValueError):
            return f"solver process died (exit code {code}, signal {signal.Signals(-code).name})"
    return f"solver process died (exit code {code})"


def launch(target: Callable[[Connection, tuple[str, ...], bytes], None], payload: bytes,
           duplex: bool) -> tuple[BaseProcess, Connection, Message]:
    """Start a child running ``target`` and wait until it has loaded ``payload``.

    Returns the process, our end of the pipe and the last message: ``READY``, or what ended
    the loading (an ``ERROR`` message, ``DIED``, ``TIMEOUT``). The caller stops the process.
    Raises :class:`IsolationFailed` when the child does not start.
    """
    context = _context()
    ours, theirs = context.Pipe(duplex=duplex)
    process = context.Process(target=target, args=(theirs, registry.loaded_plugins(), payload),
                              name="c3bench-solver", daemon=True)
    try:
        start(process)
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    try:
        kind, _ = receive(ours, STARTUP_SECONDS)
        if kind != Reply.STARTED:
            why = (died(process) if kind == Reply.DIED
                   else f"no sign of life within {STARTUP_SECONDS:g} s")
            raise IsolationFailed(f"the solver process did not start: {why}")
        message = receive(ours, STARTUP_SECONDS)
        if message[0] == Reply.TIMEOUT:
            message = (Reply.ERROR, f"loading the solver took over {STARTUP_SECONDS:g} s; "
                                    f"process killed")
        return process, ours, message
    except BaseException:
        ours.close()
        stop(process)
        raise
