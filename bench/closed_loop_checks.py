"""Up-front checks of the closed-loop commands' options, made before anything is simulated.

A closed-loop run takes seconds to minutes; an option that can only fail at its end (an
output path under a file, a render path that is a directory) or that makes every control
step fail (a QP backend that does not exist or does not take the controller's QP family)
is refused at once instead, with one line naming the option and what is allowed: an
:class:`~c3bench.problems.errors.InputError` (``c3bench`` exit code 2).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from c3bench.bench.closed_loop_policy import FAST_CONTROLLERS, ControllerSpec
from c3bench.problems.errors import InputError
from c3bench.problems.names import Family

DURATION_TOLERANCE = 1e-9
"""How far (s) a duration may be from a whole number of control periods."""


def control_steps(duration: float, dt: float, option: str = "duration") -> int:
    """The number of control steps of ``duration`` seconds at period ``dt``.

    Raises
    ------
    InputError
        ``duration`` is not a positive (finite) multiple of ``dt``; the message names
        ``option``.
    """
    if not (duration > 0 and dt > 0 and duration < float("inf")):
        raise InputError(f"{option} must be a positive multiple of dt = {dt:g} s, got "
                         f"{duration:g}")
    steps = round(duration / dt)
    if steps < 1 or abs(steps * dt - duration) > DURATION_TOLERANCE:
        raise InputError(f"{option} must be a positive multiple of dt = {dt:g} s, got "
                         f"{duration:g}")
    return steps


def _takers(family: Family) -> str:
    """Names of the available backends that take ``family`` (comma separated)."""
    from c3bench.solvers import registry

    names = [name for name, backend in registry.backends().items()
             if family in backend.families and backend.availability()[0]]
    return ", ".join(names) or "none"


def check_backend(option: str, name: str, family: Family, role: str) -> None:
    """``name`` is a registered, available backend that takes ``family``.

    Parameters
    ----------
    option
        The command-line option that chose it (named in the message).
    name
        Registry name.
    family
        The family the controller will give it.
    role
        What it does, for the message (e.g. ``"the C3+ QP step"``).
    """
    from c3bench.solvers import registry

    known = registry.backends()
    if name not in known:
        raise InputError(f"{option}: unknown solver {name!r}; solvers that take {family} "
                         f"({role}) here: {_takers(family)}")
    backend = known[name]
    available, reason = backend.availability()
    if not available:
        raise InputError(f"{option}: solver {name!r} is not available here ({reason}); "
                         f"solvers that take {family} ({role}) here: {_takers(family)}")
    if family not in backend.families:
        raise InputError(f"{option}: solver {name!r} does not take {family} ({role}); "
                         f"solvers that do here: {_takers(family)}")


def check_backends(spec: ControllerSpec) -> None:
    """The QP backend (and C3's projection backend) of ``spec`` can serve its controller.

    The fast controllers solve their QP steps themselves and ignore both: nothing is
    checked. C3 gives its QP backend the ``c3_qp`` family and its projection backend the
    ``projection`` family; every C3+ variant gives its QP backend ``c3plus_qp``.
    """
    if spec.controller in FAST_CONTROLLERS:
        return
    if spec.controller == "c3":
        check_backend("--qp-backend", spec.qp_backend, Family.C3_QP, "the C3 QP step")
        check_backend("--projection", spec.projection, Family.PROJECTION,
                      "C3's MIQP projection")
        return
    check_backend("--qp-backend", spec.qp_backend, Family.C3PLUS_QP, "the C3+ QP step")


def writable_directory(path: str | Path, option: str) -> Path:
    """Create ``path`` (and its parents) and check that a file can be written in it.

    Raises
    ------
    InputError
        It cannot be created (a parent is a file, no permission) or written to; the message
        names ``option`` and the path.
    """
    directory = Path(path)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as error:
        raise InputError(f"{option}: cannot write to {directory}: "
                         f"{error.strerror or error}") from None
    return directory


def check_render_path(path: str | Path, option: str = "--render") -> Path:
    """A ``.gif`` path that is not a directory, in a directory that can be written."""
    target = Path(path)
    if target.suffix.lower() != ".gif":
        raise InputError(f"{option}: expected a path ending in .gif, got {str(target)!r}")
    if target.is_dir():
        raise InputError(f"{option}: {target} is a directory, expected a .gif file path")
    writable_directory(target.parent, option)
    return target
