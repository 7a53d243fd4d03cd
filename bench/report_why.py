""""Why slow": one measured line per QP backend that is far slower than the fastest.

For every group of peers (family, variant, settings, precision, start; :data:`PEER_COLUMNS`)
of a convex QP family, a solver whose ranked time is more than :data:`SLOW_FACTOR` times the
fastest solver's gets one line saying where its time goes, derived from its stored rows and
the fastest solver's, never from its name:

* times are shifted geometric means (shift ``TIME_SHIFT``) of the ranked time
  (``total_time``; a failed cell charged its time limit, :func:`charged_times`), as in the
  family tables;
* **failures** first: when failed cells carry most of the solver's charged time,
  "k of n cells failed, charged the X s limit";
* otherwise the gap to the fastest, ``T - T0``, is split by the medians over the solved cells
  into a setup part ``S - S0`` and a solve part ``V - V0``; the larger part is the reason:

  - setup: "setup is p % of its time (S of T; <fastest> pays T0 in all)": conversion,
    construction and factorisation outweigh the solve (a modelling layer, a conversion
    through another package, a solver object rebuilt per call);
  - solve: "solve V vs V0 for <fastest>", followed, where iterations are reported, by
    "iterations: i vs i0" when they differ by :data:`ITERATION_FACTOR` or more, else by the
    time per iteration (against the median of the peers' iteration medians when the
    fastest reports none).

The section is Markdown for ``report.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from c3bench.bench.metrics import (
    PEER_COLUMNS,
    TIME_SHIFT,
    charged_times,
    family_label,
    shifted_geometric_mean,
    with_variants,
)
from c3bench.problems.names import QP_FAMILIES

SLOW_FACTOR = 5.0
"""A solver this many times slower than the fastest of its peers gets a line."""
ITERATION_FACTOR = 2.0
"""Iteration counts differing by this factor are named as the reason of a slow solve."""
FAILURE_SHARE = 0.5
"""Failures are the reason when their charged time is more than this share of the total."""


@dataclass(frozen=True)
class SolverTimes:
    """What one solver's rows of one peer group say about its time (seconds)."""

    solver: str
    ranked: float
    """Shifted geometric mean of the charged ranked times."""
    cells: int
    failed: int
    failure_share: float
    """Share of the charged time spent in failed cells."""
    time_limit: float
    setup: float
    """Median setup time over the solved cells (NaN when none)."""
    solve: float
    iterations: float
    """Median iterations over the solved cells (NaN when not reported)."""

    @property
    def total(self) -> float:
        """Median setup + median solve over the solved cells."""
        return self.setup + self.solve

    @classmethod
    def of(cls, solver: str, rows: pd.DataFrame) -> SolverTimes:
        charged = charged_times(rows)
        success = rows["success"].to_numpy(dtype=bool)
        solved = rows[success]
        total_charged = float(np.sum(charged))
        return cls(
            solver=solver, ranked=shifted_geometric_mean(charged, TIME_SHIFT),
            cells=len(rows), failed=int((~success).sum()),
            failure_share=(float(np.sum(charged[~success])) / total_charged
                           if total_charged > 0 else 0.0),
            time_limit=float(rows["time_limit"].max()),
            setup=_median(solved["setup_time"]), solve=_median(solved["solve_time"]),
            iterations=_median(solved["iterations"].astype("float64")))


def _median(values: pd.Series) -> float:
    array = values.to_numpy(dtype=float)
    array = array[np.isfinite(array)]
    return float(np.median(array)) if array.size else float("nan")


def _ms(seconds: float) -> str:
    """Seconds as milliseconds, 2-3 significant digits."""
    return f"{seconds * 1e3:.3g} ms"


def reason(slow: SolverTimes, fastest: SolverTimes,
           peer_iterations: float = float("nan")) -> str:
    """The one-line reason ``slow`` is slower than ``fastest`` (module docstring);
    ``peer_iterations`` is the median of the peers' median iterations (used when the fastest
    reports none)."""
    if slow.failed and (slow.failure_share > FAILURE_SHARE or not np.isfinite(slow.total)):
        return (f"{slow.failed} of {slow.cells} cells failed, each charged the "
                f"{slow.time_limit:g} s limit")
    if not np.isfinite(fastest.total):
        return f"setup {_ms(slow.setup)}, solve {_ms(slow.solve)}"
    setup_gap = slow.setup - fastest.setup
    solve_gap = slow.solve - fastest.solve
    if setup_gap >= solve_gap:
        share = 100.0 * slow.setup / slow.total if slow.total > 0 else float("nan")
        return (f"setup is {share:.0f} % of its time ({_ms(slow.setup)} of {_ms(slow.total)}; "
                f"{fastest.solver} pays {_ms(fastest.total)} in all)")
    its, its0 = slow.iterations, fastest.iterations
    solve = f"solve {_ms(slow.solve)} vs {_ms(fastest.solve)} for {fastest.solver}"
    if np.isfinite(its) and np.isfinite(its0) and its0 > 0:
        if its >= ITERATION_FACTOR * its0:
            return f"{solve}; iterations: {its:.0f} vs {its0:.0f}"
        return (f"{solve}; time per iteration {_ms(slow.solve / max(its, 1.0))} vs "
                f"{_ms(fastest.solve / max(its0, 1.0))} ({its:.0f} vs {its0:.0f} "
                f"iterations)")
    if np.isfinite(its) and np.isfinite(peer_iterations) and peer_iterations > 0:
        if its >= ITERATION_FACTOR * peer_iterations:
            return f"{solve}; iterations: {its:.0f} vs peer median {peer_iterations:.0f}"
        return (f"{solve}; time per iteration {_ms(slow.solve / max(its, 1.0))} "
                f"({its:.0f} iterations, peer median {peer_iterations:.0f})")
    return solve


def why_slow_lines(frame: pd.DataFrame) -> list[str]:
    """One Markdown bullet per slow QP backend and peer group (module docstring)."""
    if frame.empty:
        return []
    frame = with_variants(frame[frame["family"].isin([str(f) for f in QP_FAMILIES])])
    lines: list[str] = []
    for key, group in frame.groupby(list(PEER_COLUMNS), sort=True, dropna=False):
        family, variant, settings, precision, start = (str(k) for k in key)
        times = [SolverTimes.of(str(solver), rows)
                 for solver, rows in group.groupby("solver", sort=True)]
        times = [t for t in times if np.isfinite(t.ranked)]
        if len(times) < 2:
            continue
        fastest = min(times, key=lambda t: t.ranked)
        counts = [t.iterations for t in times if np.isfinite(t.iterations)]
        peer_iterations = float(np.median(counts)) if counts else float("nan")
        for slow in sorted(times, key=lambda t: -t.ranked):
            factor = slow.ranked / fastest.ranked if fastest.ranked > 0 else float("inf")
            if factor <= SLOW_FACTOR:
                continue
            lines.append(f"- {family_label(family, variant)} / {settings} / {precision} / "
                         f"{start}: **{slow.solver}** {factor:.0f}x {fastest.solver}: "
                         f"{reason(slow, fastest, peer_iterations)}")
    return lines


def why_slow_section(frame: pd.DataFrame) -> str:
    """The report's "Why slow" section."""
    lines = why_slow_lines(frame)
    intro = (f"Every QP backend more than {SLOW_FACTOR:g}x slower (ranked time, shifted "
             f"geometric mean) than the fastest of its family, variant, settings, precision "
             f"and start, with the part of its time that makes the gap, measured from the "
             f"stored rows (bench.report_why).\n")
    if not lines:
        return intro + "\nNo backend is that slow.\n"
    return intro + "\n" + "\n".join(lines) + "\n"
