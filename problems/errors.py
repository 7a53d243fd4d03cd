"""One exception base for everything c3bench raises on purpose.

Catch :class:`C3BenchError` to handle any of them; each subclass also derives from the builtin
it refines (``ValueError``, ``RuntimeError``), so older ``except ValueError`` handlers still
work. Part of the plant-free core.
"""

from __future__ import annotations


class C3BenchError(Exception):
    """Base of every error c3bench raises on purpose."""


class InputError(C3BenchError, ValueError):
    """Bad user input: an option, a configuration key, a file. The CLI prints it on one line
    and exits with code 2."""


class InstanceFormatError(InputError):
    """An instance file is malformed, of another schema version, or misses a key."""


class SchemaVersionError(InputError):
    """A results file was written under another schema version."""


class BackendUnavailable(C3BenchError, RuntimeError):
    """A backend's package is missing or cannot load (the backend is listed as unavailable)."""


class RenderUnavailable(C3BenchError, RuntimeError):
    """No OpenGL context can be created for off-screen rendering."""


class NotPositiveDefiniteError(C3BenchError, ValueError):
    """A matrix that must be positive definite (a Cholesky factor's input) is not."""


class ResultsLocked(C3BenchError, RuntimeError):
    """Another c3bench process is working in the same results directory (its lock file names
    it)."""


class Terminated(KeyboardInterrupt):
    """The process received SIGTERM: stop like Ctrl-C (finished work is kept), exit code 143.

    A ``KeyboardInterrupt`` so that every interrupt path handles it and ``except Exception``
    cannot swallow it.
    """
