"""The statuses qpsolvers drops: DAQP's exit flag, HiGHS's model status, quadprog's message.

``qpsolvers.solve_problem`` keeps no status of these three solvers, only ``found``, so a failed
solve read "not solved" whatever the solver had said (infeasible, unbounded, cycling, limit
reached). :class:`StatusProbe` records the solver's own answer as qpsolvers receives it: for
the duration of one call it wraps ``daqp.solve`` (its third return value is DAQP's exit flag)
or ``highspy.Highs.getModelStatus`` (read by qpsolvers right after the solve), passing every
argument and result through unchanged, and restores the original afterwards. The wrapper
costs one Python call inside the solver's timed lap (below a microsecond). Should a later
qpsolvers reach the solver another way, nothing is recorded and the status says that
qpsolvers kept none, as before. quadprog's reason is its ``ValueError``: qpsolvers warns with
its message, except for :data:`QUADPROG_INCONSISTENT`, which it drops silently, so the absence
of a warning identifies that one.

References: DAQP's exit flags, ``include/constants.h`` of DAQP (Arnström, Bemporad and
Axehill 2022); HiGHS's ``HighsModelStatus`` and ``modelStatusToString`` (Huangfu and Hall
2018).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

__all__ = ["DAQP_EXIT_FLAGS", "QUADPROG_INCONSISTENT", "StatusProbe"]

DAQP_EXIT_FLAGS = {1: "optimal", 2: "soft optimal", -1: "infeasible", -2: "cycling",
                   -3: "unbounded", -4: "iteration limit", -5: "nonconvex",
                   -6: "initial working set overdetermined"}
"""DAQP's exit flags (``include/constants.h``); positive means solved."""

QUADPROG_INCONSISTENT = "constraints are inconsistent, no solution"
"""quadprog's own message for infeasible constraints (its ``ValueError``); qpsolvers drops it
silently and warns with any other ``ValueError``'s message."""


class StatusProbe:
    """What one ``qpsolvers.solve_problem`` call of ``solver`` dropped (module docstring)."""

    def __init__(self, solver: str) -> None:
        self.solver = solver
        self.last: tuple[tuple[Any, ...], Any] | None = None
        """``(arguments, result)`` of the last recorded call (``None`` before one)."""

    @contextmanager
    def watching(self) -> Iterator[None]:
        """Record the solver's answer during the ``with`` block."""
        target = self._target()
        if target is None:
            yield
            return
        owner, attribute = target
        own = attribute in vars(owner)
        original: Callable[..., Any] = getattr(owner, attribute)

        def recorder(*arguments: Any, **keywords: Any) -> Any:
            result = original(*arguments, **keywords)
            self.last = (arguments, result)
            return result

        setattr(owner, attribute, recorder)
        try:
            yield
        finally:
            if own:
                setattr(owner, attribute, original)
            else:  # inherited: remove the wrapper, the base's method shows again
                delattr(owner, attribute)

    def _target(self) -> tuple[Any, str] | None:
        try:
            if self.solver == "daqp":
                import daqp

                return daqp, "solve"
            if self.solver == "highs":
                import highspy

                return highspy.Highs, "getModelStatus"
        except ImportError:
            return None
        return None

    def info(self) -> dict[str, Any]:
        """DAQP's ``info`` of the last recorded call (times in seconds, ``iterations``), or
        ``{}`` when none was recorded."""
        if self.solver != "daqp" or self.last is None:
            return {}
        try:
            info = self.last[1][3]
        except (IndexError, TypeError):
            return {}
        return info if isinstance(info, dict) else {}

    def status(self, found: bool, warned: Sequence[str] = ()) -> str | None:
        """The solver's own status of the last call, or ``None`` when nothing was recorded
        (``warned``: the messages qpsolvers warned with, for quadprog)."""
        if self.solver == "quadprog":
            if found:
                return None
            errors = [text for text in warned if "quadprog raised a ValueError" in text]
            return errors[0] if errors else f"quadprog: {QUADPROG_INCONSISTENT}"
        if self.last is None:
            return None
        arguments, result = self.last
        try:
            if self.solver == "daqp":
                flag = int(result[2])
                return f"daqp: {DAQP_EXIT_FLAGS.get(flag, 'unknown')} (exit flag {flag})"
            if self.solver == "highs":
                return f"HiGHS: {arguments[0].modelStatusToString(result)}"
        except (IndexError, TypeError, ValueError, AttributeError):
            return None
        return None
