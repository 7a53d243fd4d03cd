"""Checks of the ``c3bench`` arguments made before any work, and the one-line error messages.

Each check raises :class:`~c3bench.problems.errors.InputError` naming the option and what it
accepts (the CLI prints it on one line and exits with code 2) before a directory is created
or a solve starts; the closed-loop commands' model and period options are checked against
the task configuration (:func:`check_model_side`, :func:`check_plant_period`) and the
backend options against the controller that would use them (:func:`check_backend_options`).
:func:`describe_error` turns an expected fault (an ``OSError`` of a full
disk, a read-only or missing path, a path under a file) into one line naming the path.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from c3bench.bench import store
from c3bench.problems.capture import SUITES, SuiteSpec
from c3bench.problems.errors import InputError
from c3bench.problems.instance import FAMILIES, MANIFEST
from c3bench.problems.names import SUITE_FAMILIES, Family

if TYPE_CHECKING:
    from c3bench.problems.config import Config
    from c3bench.solvers.registry import BackendInfo

MAX_STACKED_SAMPLES = 32
"""Most samples of the stacked ``c3plus-robust`` controller (default 16): its dense QP has
about 165 variables per sample (16 samples: n = 2638, 97 MB pickled to the solver process),
so its memory grows with the square of the samples. Measured on the 2-core VM, one control
step with Clarabel: 32 samples 45 s and 1.6 GB resident, each QP solve within the default
10 s limit; 64 samples 5.6 GB, and every QP solve overran that limit. ``c3plus-fast-robust``
takes up to :data:`bench.cli_options.MAX_SAMPLES` (4096 samples: 5.8 s a step, 0.5 GB)."""
MAX_MODEL_SIDE = 10.0
"""Largest model cube side (m; the plant's is 0.30 and the ball's workspace 1.2 m wide)."""
SUITE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
"""A suite name: a folder name under the results root (no separators, not hidden)."""


# --- paths ---------------------------------------------------------------------------------------
def check_output_path(option: str, path: str | Path) -> None:
    """``path`` is a directory or can become one, and can be written: no file is in the way.

    The first of ``path`` and its parents that exists must be a directory in which this
    process can create a folder (tried with a hidden folder, removed at once: nothing is
    left behind), so a read-only or pseudo file system fails here, before any work.
    """
    path = Path(path)
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            if candidate.is_dir():
                _check_writable(option, path, candidate)
                return
            if candidate == path:
                raise InputError(f"{option}: {path} is a file, not a directory")
            raise InputError(f"{option}: {path} is under {candidate}, which is a file, not a "
                             "directory")
    return


def _check_writable(option: str, path: Path, existing: Path) -> None:
    """A folder can be made in ``existing`` (``path`` or its first existing parent)."""
    try:
        probe = tempfile.mkdtemp(prefix=".c3bench-write-check-", dir=existing)
    except OSError as error:
        raise InputError(f"{option}: cannot write to {path}: {os_reason(error)}") from None
    with contextlib.suppress(OSError):
        os.rmdir(probe)


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
    """The families of a suite's instances: those a packaged suite generates (known before
    it is generated; a stored copy that is out of date is regenerated by the run), else those
    of a stored suite's manifest; ``None`` when unknown."""
    if suite in SUITES:
        return packaged_families(SUITES[suite])
    manifest = store.SuitePaths.of(results, suite).instances / MANIFEST
    try:
        counts = json.loads(manifest.read_text()).get("counts", {})
    except (OSError, ValueError, AttributeError):
        return None
    return {family for family, count in counts.items() if count} if counts else None


def packaged_families(spec: SuiteSpec) -> set[str]:
    """The families ``problems generate`` writes for a packaged suite (every cube-tipping
    family, and ``lcp_general`` where the suite linearises other contact models)."""
    families = {str(family) for family in SUITE_FAMILIES}
    if spec.lcp_general_models:
        families.add(str(Family.LCP_GENERAL))
    return families


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


# --- closed loop --------------------------------------------------------------------------------
def check_model_side(option: str, side: float, config: Config) -> None:
    """A model cube side of at most :data:`MAX_MODEL_SIDE` that MuJoCo accepts: the
    controller's scene is built once here, so that a side too small for MuJoCo is an
    :class:`InputError` naming ``option``, not an error in every control step."""
    from c3bench.problems.scene import build_scene

    if side > MAX_MODEL_SIDE:
        raise InputError(f"{option} {side:g}: a model cube side is at most "
                         f"{MAX_MODEL_SIDE:g} m")

    try:
        build_scene(l=side, config=config)
    except ValueError as error:  # MuJoCo's compiler errors are ValueErrors
        reason = str(error).splitlines()[0].removeprefix("Error: ").strip()
        raise InputError(f"{option} {side:g}: MuJoCo cannot build a model cube of side "
                         f"{side:g} m ({reason})") from None


def check_plant_period(option: str, dt: float, config: Config) -> None:
    """A control period that is a whole number (>= 1) of the plant's time steps."""
    from c3bench.problems.config import whole_steps

    step = config.scene.plant_timestep
    if not whole_steps(dt, step):
        raise InputError(f"{option} {dt:g}: not a whole multiple of the plant's time step "
                         f"{step:g} s (the plant runs whole steps within a control period)")


def check_samples(controller: str, samples: int) -> None:
    """``--samples`` within what ``controller`` can hold (:data:`MAX_STACKED_SAMPLES` for the
    stacked ``c3plus-robust``; the parser caps the others)."""
    if controller == "c3plus-robust" and samples > MAX_STACKED_SAMPLES:
        raise InputError(f"--samples: the stacked c3plus-robust controller takes at most "
                         f"{MAX_STACKED_SAMPLES} samples (its dense QP grows with their "
                         f"square), got {samples}; c3plus-fast-robust takes more")


_UNUSED_REASON = {"--qp-backend": "the fast controllers solve their QP steps themselves",
                  "--projection": "only c3 has an MIQP projection"}


def check_backend_options(controller: str, options: dict[str, Any]) -> None:
    """``--qp-backend`` / ``--projection`` (``options``: the given ones, ``None`` when left
    out) are not given to a controller that does not use them; the message says whether the
    value is also unknown."""
    from c3bench.bench.closed_loop_policy import FAST_CONTROLLERS

    unused = {"--qp-backend": controller in FAST_CONTROLLERS,
              "--projection": controller != "c3"}
    for option, value in options.items():
        if value is None or not unused.get(option, False):
            continue
        from c3bench.solvers import registry

        known = value in registry.backends()
        what = f"{option} {value!r}" if known else \
            f"{option}: unknown solver {value!r}, and {option}"
        raise InputError(f"{what} does not apply to --controller {controller} "
                         f"({_UNUSED_REASON[option]}); leave it out")


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


def os_reason(error: OSError) -> str:
    """What is wrong, in words, for an ``OSError`` (without the path)."""
    if error.errno is None:
        return str(error)
    return _OS_REASONS.get(error.errno) or error.strerror or str(error)


def describe_os_error(error: OSError) -> str:
    """One line for an ``OSError``: the path at fault and what is wrong with it."""
    if error.errno is None:
        return str(error)
    reason = os_reason(error)
    if error.filename is None:
        return f"{reason} ({errno.errorcode.get(error.errno, error.errno)})"
    where = f"{error.filename}" + (f" -> {error.filename2}" if error.filename2 else "")
    return f"{where}: {reason}"
