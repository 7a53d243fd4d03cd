"""One run per results directory, and stopping a run cleanly on SIGTERM.

:class:`DirectoryLock` holds ``<directory>/c3bench.lock`` with ``fcntl.flock`` for as long as
a command works in a results directory (``c3bench run`` in ``ROOT/<suite>/``, the closed-loop
suites in ``ROOT/closed_loop/<name>/``). The file names the holder (pid, host, command line,
start time); a second command on the same directory fails at once with
:class:`~c3bench.problems.errors.ResultsLocked` naming it. The kernel releases a ``flock``
when its last descriptor closes, so a holder killed with ``kill -9`` never leaves a stale
lock; pool workers forked while the lock is held close their copy
(:func:`close_inherited_locks`) so that they cannot keep it either. Read-only commands
(``report``, ``compare``) take no lock.

:func:`terminate_as_exception` turns SIGTERM into
:class:`~c3bench.problems.errors.Terminated` (a ``KeyboardInterrupt``), so a terminated run
stops its workers and keeps what finished exactly as after Ctrl-C. The CLI
(:func:`bench.cli.main`) holds it around every command; nested uses (:func:`exclusive_run`)
then do nothing.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import sys
import threading
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from types import FrameType, TracebackType

from c3bench.bench.machine import hostname, utc_now
from c3bench.problems.errors import ResultsLocked, Terminated

LOCK_NAME = "c3bench.lock"
"""File name of the lock in a results directory."""

_HELD: set[int] = set()
"""Descriptors of the locks this process holds (closed, never unlocked, in forked children)."""
_TERMINATE_ACTIVE = False
"""Whether a :func:`terminate_as_exception` block is active in this process."""


@dataclass(frozen=True)
class LockHolder:
    """Who holds a results directory (the content of its lock file)."""

    pid: int
    host: str
    command: str
    since: str

    @classmethod
    def current(cls) -> LockHolder:
        """This process."""
        return cls(os.getpid(), hostname(), " ".join(sys.argv) or sys.executable, utc_now())

    @classmethod
    def parse(cls, text: str) -> LockHolder | None:
        """The holder written in a lock file (``None`` when it is empty or unreadable)."""
        try:
            payload = json.loads(text)
            return cls(int(payload["pid"]), str(payload["host"]), str(payload["command"]),
                       str(payload["since"]))
        except (ValueError, KeyError, TypeError):
            return None


def _locked_message(directory: Path, holder: LockHolder | None) -> str:
    if holder is None:
        return (f"results directory {directory} is in use by another c3bench process (its "
                f"lock file {directory / LOCK_NAME} is being written)")
    return (f"results directory {directory} is in use by pid {holder.pid} on {holder.host} "
            f"since {holder.since} (command {holder.command})")


class DirectoryLock:
    """An exclusive lock on a results directory (a context manager).

    Parameters
    ----------
    directory
        The results directory (created when missing).

    Raises
    ------
    ResultsLocked
        From :meth:`acquire` when another process holds the directory.
    """

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self.descriptor: int | None = None

    def acquire(self) -> LockHolder:
        """Take the lock (never waits) and write this process into the lock file."""
        if self.descriptor is not None:
            raise ResultsLocked(_locked_message(self.directory, LockHolder.current()))
        self.directory.mkdir(parents=True, exist_ok=True)
        while True:
            descriptor = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = LockHolder.parse(os.pread(descriptor, 65536, 0).decode(
                    errors="replace"))
                os.close(descriptor)
                raise ResultsLocked(_locked_message(self.directory, holder)) from None
            except BaseException:
                os.close(descriptor)
                raise
            if self._still_linked(descriptor):
                break
            os.close(descriptor)  # the previous holder removed the file meanwhile: again
        holder = LockHolder.current()
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, (json.dumps(asdict(holder)) + "\n").encode(), 0)
        self.descriptor = descriptor
        _HELD.add(descriptor)
        return holder

    def _still_linked(self, descriptor: int) -> bool:
        """Whether the locked file is still the one at :attr:`path`."""
        try:
            return os.fstat(descriptor).st_ino == os.stat(self.path).st_ino
        except FileNotFoundError:
            return False

    def release(self) -> None:
        """Remove the lock file and release the lock (idempotent)."""
        if self.descriptor is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink(missing_ok=True)
        _HELD.discard(self.descriptor)
        os.close(self.descriptor)
        self.descriptor = None

    def __enter__(self) -> DirectoryLock:
        self.acquire()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.release()


def read_holder(directory: str | Path) -> LockHolder | None:
    """The holder named in ``directory``'s lock file, or ``None`` (no file or unreadable)."""
    try:
        return LockHolder.parse((Path(directory) / LOCK_NAME).read_text())
    except OSError:
        return None


def close_inherited_locks() -> None:
    """In a forked child: close the lock descriptors inherited from the parent.

    Closing (never ``LOCK_UN``, which would release the parent's lock too) drops this
    process's reference, so only the parent keeps the directory locked.
    """
    for descriptor in list(_HELD):
        with contextlib.suppress(OSError):
            os.close(descriptor)
    _HELD.clear()


@contextlib.contextmanager
def terminate_as_exception() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`~c3bench.problems.errors.Terminated`.

    Only the first SIGTERM raises; later ones are ignored while the interrupted work cleans
    up (stops its workers, consolidates what finished). The previous handler is restored on
    exit. Outside the main thread (where handlers cannot be set) this does nothing; nested in
    another such block (the CLI installs one around every command) it does nothing either, so
    a SIGTERM raises once per process, never again in the cleanup of an outer block.
    """
    global _TERMINATE_ACTIVE
    if _TERMINATE_ACTIVE or threading.current_thread() is not threading.main_thread():
        yield
        return
    raised = False

    def handler(signum: int, frame: FrameType | None) -> None:
        nonlocal raised
        if not raised:
            raised = True
            raise Terminated("received SIGTERM")

    previous = signal.signal(signal.SIGTERM, handler)
    _TERMINATE_ACTIVE = True
    try:
        yield
    finally:
        _TERMINATE_ACTIVE = False
        signal.signal(signal.SIGTERM, previous)


def stopped_message(stop: KeyboardInterrupt, stored: str, where: Path,
                    rerun: bool = False) -> str:
    """What an interrupted (Ctrl-C) or terminated (SIGTERM) run kept, on one line:
    ``terminated: 12 cells stored in DIR; run again to resume``; after ``--rerun`` (whose
    unfinished cells still hold the earlier run's rows, which a plain run keeps): ``...;
    the others are the earlier run's: run again with --rerun to redo them all``."""
    what = "terminated" if isinstance(stop, Terminated) else "interrupted"
    then = ("the others are the earlier run's: run again with --rerun to redo them all"
            if rerun else "run again to resume")
    return f"{what}: {stored} stored in {where}; {then}"


def report_stopped(stop: KeyboardInterrupt, stored: str, where: Path,
                   rerun: bool = False) -> None:
    """Print :func:`stopped_message` on stderr and add it to ``stop``'s notes, so that the
    command line's handler (:func:`c3bench.bench.cli.main`) prints no second line."""
    message = stopped_message(stop, stored, where, rerun)
    print("\n" + message, file=sys.stderr)
    stop.add_note(message)


@contextlib.contextmanager
def exclusive_run(directory: str | Path) -> Iterator[DirectoryLock]:
    """Hold ``directory``'s lock with SIGTERM raising :class:`Terminated` (see above)."""
    with terminate_as_exception(), DirectoryLock(directory) as lock:
        yield lock
