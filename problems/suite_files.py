"""A stored suite's directory: its identity and its replacement as a whole.

* identity: :data:`GENERATOR_VERSION` and :func:`out_of_date` (whether a stored suite's
  ``manifest.json`` was written by today's generator for the same suite definition);
* replacement: :func:`check_target` (which directories a generation may replace),
  :func:`check_apart` (an output that is, lies inside or holds its input is refused),
  :func:`staging_dir` (the hidden sibling folder a suite is written into) and :func:`swap_in`
  (the complete suite swapped in, so a directory never mixes two generations).

Used by :func:`problems.suites.generate_suite`, which re-exports these names.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
from pathlib import Path
from typing import Any

from c3bench.problems.capture import SuiteSpec
from c3bench.problems.errors import InputError
from c3bench.problems.instance import FAMILIES, MANIFEST

__all__ = ["GENERATOR_VERSION", "check_apart", "check_target", "out_of_date", "staging_dir",
           "swap_in"]


GENERATOR_VERSION = 2
"""Version of what :func:`problems.suites.generate_suite` writes for a given spec and
config; raised whenever the instances change (2: ball-table contact, bounded and equality
variants, several pushes). A stored suite of another version (or of another spec) is out
of date (:func:`out_of_date`)."""


def out_of_date(spec: SuiteSpec, manifest: dict[str, Any]) -> str:
    """Why a stored suite's ``manifest`` was not written by today's generator for ``spec``
    (``""`` when it was): another generator version, or another suite definition."""
    stored = manifest.get("generator_version")
    if stored != GENERATOR_VERSION:
        return f"written by suite generator version {stored} (now {GENERATOR_VERSION})"
    if json.loads(json.dumps(manifest.get("suite"))) != json.loads(json.dumps(spec.to_json())):
        return f"the definition of suite {spec.name!r} changed"
    return ""


# --- replacing a suite as a whole ----------------------------------------------------------------
def check_target(out: Path) -> None:
    """Refuse an instance directory that a generation must not replace.

    ``out`` may be absent, empty, or hold a suite (``manifest.json``, family folders and
    temporary files of an interrupted write only); a file, the current directory (or one
    above it) and a directory holding anything else raise :class:`InputError`.
    """
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    if not out.is_dir():
        return
    here, target = Path.cwd().resolve(), out.resolve()
    if target == here or target in here.parents:
        raise InputError(f"{out}: is the current directory or above it; generate into a "
                         "subdirectory")
    foreign = sorted(child.name for child in out.iterdir()
                     if not (child.name == MANIFEST
                             or (child.is_dir() and child.name in FAMILIES)
                             or (child.name.startswith(".") and child.name.endswith(".tmp"))))
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise InputError(f"{out}: holds files that are not a suite's instances ({shown}); "
                         "generate into a new or empty directory")


def check_apart(out: Path, source: Path, label: str) -> None:
    """Refuse an output directory ``out`` that is the input ``source`` (a file or directory,
    called ``label`` in the message), lies inside it or holds it: writing there would change
    what is read. Symbolic links are followed; ``out`` need not exist."""
    target, origin = out.resolve(), source.resolve()
    if target == origin:
        raise InputError(f"{out}: is {label} ({source}); write to a directory outside it")
    if origin in target.parents:
        raise InputError(f"{out}: is inside {label} ({source}); write to a directory "
                         "outside it")
    if target in origin.parents:
        raise InputError(f"{out}: holds {label} ({source}); write to a directory outside it")


def staging_dir(out: Path) -> Path:
    """A new hidden sibling folder of ``out`` to generate into (leftovers of dead processes
    removed first)."""
    parent = out.absolute().parent
    parent.mkdir(parents=True, exist_ok=True)
    for leftover in parent.glob(f".{out.name}.*-*-*"):
        kind, pid = leftover.name[len(out.name) + 2:].split("-", 2)[:2]
        if kind in ("generating", "old") and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(leftover, ignore_errors=True)
    staging = parent / f".{out.name}.generating-{os.getpid()}-{secrets.token_hex(4)}"
    staging.mkdir()
    return staging


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def swap_in(staging: Path, out: Path) -> None:
    """Make the complete suite in ``staging`` the content of ``out``.

    Absent ``out``: one rename. ``out`` holding a suite: rename it aside, rename ``staging``
    in, delete the old one (put back if the second rename fails). Empty ``out``: move the
    family folders in, the manifest last (a partial move has no manifest, so a run
    regenerates it).
    """
    if not out.exists():
        os.rename(staging, out)
        return
    if not any(out.iterdir()):
        children = sorted(staging.iterdir(), key=lambda child: child.name == MANIFEST)
        for child in children:
            os.rename(child, out / child.name)
        staging.rmdir()
        return
    old = staging.with_name(f".{out.name}.old-{os.getpid()}-{secrets.token_hex(4)}")
    os.rename(out, old)
    try:
        os.rename(staging, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
