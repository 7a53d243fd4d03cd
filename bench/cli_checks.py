"""Checks of the ``c3bench`` arguments made before any work, and the one-line error messages.

Each check raises :class:`~c3bench.problems.errors.InputError` naming the option and what it
accepts (the CLI prints it on one line and exits with code 2) before a directory is created
or a solve starts. :func:`describe_error` turns an expected fault (an ``OSError`` of a full
disk, a read-only or missing path, a path under a file) into one line naming the path.
"""

from __future__ import annotations

import errno
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from c3bench.bench import store
from c3bench.problems.capture import SUITES
from c3bench.problems.errors import InputError
from c3bench.problems.instance import FAMILIES, MANIFEST

if TYPE_CHECKING:
    from c3bench.solvers.registry import BackendInfo

SUITE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
"""A suite name: a folder name under the results root (no separators, not hidden)."""


# --- paths ---------------------------------------------------------------------------------------
def check_output_path(option: str, path: str | Path) -> None:
    """``path`` is a directory or can become one: no file is in the way.

    The first of ``path`` and its parents that exists must be a directory.
    """
    path = Path(path)
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            if candidate.is_dir():
                return
            if candidate == path:
                raise InputError(f"{option}: {path} is a file, not a directory")
            raise InputError(f"{option}: {path} is under {candidate}, which is a file, not a "
                             "directory")
    return


# --- suites ------------------------------------------------------------------------------------
def check_suite_name(option: str, name: str) -> None:
    """A suite name that is one plain folder name."""
    if not SUITE_NAME.fullmatch(name):
        raise InputError(f"{option}: {name!r} is not a suite name (letters, digits, '.', '_', "
                         "'-'; no path)")


def stored_suites(results: str | Path) -> list[str]:
    """The suites under a results root: folders with instances, cells or a results table."""
    root = Path(results)
    if not root.is_dir():
        return []
    return sorted(child.name for child in root.iterdir() if child.is_dir() and (
        (child / "instances" / MANIFEST).exists() or (child / "cells").is_dir()
        or (child / "results.parquet").exists()))


def _stored_text(results: str | Path) -> str:
    names = stored_suites(results)
    return f"stored under {results}: {', '.join(names)}" if names else \
        f"none stored under {results}"


def check_suite_to_run(suite: str, results: str | Path) -> None:
    """``run --suite``: a known suite, or one whose instances are stored under the root."""
    check_suite_name("--suite", suite)
    if suite in SUITES or (store.SuitePaths.of(results, suite).instances / MANIFEST).exists():
        return
    raise InputError(f"--suite: unknown suite {suite!r}; choose one of {', '.join(SUITES)} "
                     f"or a stored suite ({_stored_text(results)})")


def check_stored_suite(suite: str, results: str | Path) -> None:
    """``report`` / ``compare --suite``: a suite stored under the results root.

    A bad name is an :class:`InputError`; a suite not stored is nothing to read, a
    ``FileNotFoundError`` (exit 1) naming the stored ones.
    """
    check_suite_name("--suite", suite)
    if (Path(results) / suite).is_dir():
        return
    raise FileNotFoundError(f"--suite: no stored suite {suite!r} ({_stored_text(results)}); "
                            f"`c3bench run --suite {suite} --results {results}` writes it")


def suite_families(suite: str, results: str | Path) -> set[str] | None:
    """The families of a stored suite's instances (its manifest), ``None`` when not stored."""
    manifest = store.SuitePaths.of(results, suite).instances / MANIFEST
    try:
        counts = json.loads(manifest.read_text()).get("counts", {})
    except (OSError, ValueError, AttributeError):
        return None
    return {family for family, count in counts.items() if count} if counts else None


# --- solvers and the selection -------------------------------------------------------------------
def check_solvers(names: Sequence[str] | None, infos: Sequence[BackendInfo]
                  ) -> list[BackendInfo]:
    """``--solvers``: known names; returns the chosen backends that are available here.

    Unknown names are an error listing the known ones; so is a choice of which none is
    available (each with its reason). Unavailable ones among others are left to the run
    (it reports them as skipped).
    """
    known = {info.name: info for info in infos}
    unknown = [name for name in names or () if name not in known]
    if unknown:
        raise InputError(f"unknown solver{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(map(repr, unknown))} (--solvers); known: "
                         f"{', '.join(known)}")
    chosen = [known[name] for name in (names or known)]
    available = [info for info in chosen if info.available]
    if not available:
        reasons = "; ".join(f"{info.name}: {info.reason}" for info in chosen)
        raise InputError(f"--solvers: none of the chosen solvers is available here ({reasons})")
    return available


def check_selection(available: Sequence[BackendInfo], families: Sequence[str] | None,
                    precisions: Sequence[str], in_suite: set[str] | None) -> None:
    """The selection plans at least one cell: some chosen family is in the suite, and some
    available chosen solver takes it in a chosen precision.

    Raises an :class:`InputError` naming the option that empties the selection.
    """
    wanted = list(families) if families else list(FAMILIES)
    if in_suite is not None:
        present = [family for family in wanted if family in in_suite]
        if not present:
            raise InputError(f"--families: the suite has no instance of "
                             f"{', '.join(wanted)} (it holds {', '.join(sorted(in_suite))})")
        wanted = present
    takes = {(str(family), str(precision)) for info in available for family in info.families
             for precision in info.precisions}
    if any((family, str(precision)) in takes for family in wanted for precision in precisions):
        return
    offered = "; ".join(f"{info.name}: {', '.join(map(str, info.families))} in "
                        f"{', '.join(map(str, info.precisions))}" for info in available)
    option = "--families" if families else "--precision"
    raise InputError(f"{option}: no chosen solver takes {', '.join(wanted)} in "
                     f"{', '.join(map(str, precisions))}, nothing to run (solvers: {offered})")


def check_cpu(core: int | None) -> None:
    """``perf --cpu``: a core this process may run on."""
    if core is None:
        return
    allowed = sorted(os.sched_getaffinity(0))
    if core not in allowed:
        raise InputError(f"--cpu: core {core} is not one this process may run on "
                         f"({', '.join(map(str, allowed))})")


# --- messages ------------------------------------------------------------------------------------
_OS_REASONS: dict[int, str] = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOTDIR: "a part of the path is a file, not a directory",
    errno.EEXIST: "exists and is not a directory",
    errno.EISDIR: "is a directory",
    errno.ENOENT: "no such file or directory",
    errno.ENAMETOOLONG: "file name too long",
}


def describe_os_error(error: OSError) -> str:
    """One line for an ``OSError``: the path at fault and what is wrong with it."""
    if error.errno is None:
        return str(error)
    reason = _OS_REASONS.get(error.errno) or error.strerror or str(error)
    if error.filename is None:
        return f"{reason} ({errno.errorcode.get(error.errno, error.errno)})"
    where = f"{error.filename}" + (f" -> {error.filename2}" if error.filename2 else "")
    return f"{where}: {reason}"
