"""The one timing contract: rankings read ``total_time = setup_time + solve_time``, so where a
backend books its factorisation (setup or solve) cannot change its rank.

The fake backends here sleep known times (conversion, factorisation, iterations) and return
the exact solution; they are registered for the test only (``monkeypatch`` on the registry),
never in the package. They run through the real path of a cell: an isolated child with an
untimed warm-up and median repeats (:func:`solvers.isolation.solve_isolated`), the row filled
by :func:`bench.rows.fill_row`, the aggregates of :func:`bench.metrics.aggregate`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from c3bench.bench import store
from c3bench.bench.metrics import RANKED_TIME_COLUMN, aggregate, ranked_time
from c3bench.bench.rows import fill_row
from c3bench.problems.instance import Problem
from c3bench.problems.names import Family
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.timing import SETUP, SOLVE, Stopwatch, total_time

FACTOR_S = 0.016
"""The slow backend's factorisation (s): booked as setup by one reporting, as solve by the
other."""
ITERATE_S = {"slow": 0.004, "fast": 0.006}
"""Iterations of each backend (s): the fast one has no factorisation, so its total is lower
although its solve alone is longer than the slow one's."""


def _problem() -> Problem:
    """``min 1/2 |x|^2 - x_0`` s.t. ``x_0 + x_1 = 1``: x = (1, 0), y = 0."""
    return Problem(name="qp-timing", family=Family.QP, P=np.eye(2), q=np.array([-1.0, 0.0]),
                   A=np.array([[1.0, 1.0]]), b=np.array([1.0]))


class Sleepy(Backend):
    """Sleeps its conversion, factorisation and iterations; books the factorisation as
    ``factor_lap`` (setup under the contract, solve in the other reporting)."""

    families = (Family.QP,)

    def __init__(self, name: str, factor_s: float, iterate_s: float, factor_lap: str) -> None:
        self.name, self.factor_s, self.iterate_s = name, factor_s, iterate_s
        self.factor_lap = factor_lap

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        watch = Stopwatch()
        with watch.lap(SETUP):
            time.sleep(0.001)
        with watch.lap(self.factor_lap):
            if self.factor_s:
                time.sleep(self.factor_s)
        with watch.lap(SOLVE):
            time.sleep(self.iterate_s)
        return Result(self.name, problem.name, True, "solved", x=np.array([1.0, 0.0]),
                      y=np.array([0.0]), iterations=1, setup_time=watch.get(SETUP),
                      solve_time=watch.get(SOLVE))


def _row(problem: Problem, result: Result, solver: str) -> dict[str, Any]:
    row = store.empty_row()
    row.update({"cell_id": f"{problem.name}--{solver}", "suite": "timing",
                "instance": problem.name, "family": problem.family, "solver": solver,
                "settings": "default", "tolerance": 1e-3, "time_limit": 10.0,
                "precision": "float64", "start": "cold", "repeats": 3})
    return fill_row(row, problem, result)


@pytest.mark.timeout(120)
def test_where_the_factorisation_is_booked_does_not_change_the_ranking(
        monkeypatch: pytest.MonkeyPatch) -> None:
    problem = _problem()
    ranks: dict[str, dict[str, float]] = {}
    totals: dict[str, float] = {}
    for booking in (SETUP, SOLVE):
        fakes = [Sleepy(f"slow_{booking}", FACTOR_S, ITERATE_S["slow"], booking),
                 Sleepy(f"fast_{booking}", 0.0, ITERATE_S["fast"], booking)]
        rows = []
        for fake in fakes:
            monkeypatch.setitem(registry._BACKENDS, fake.name, fake)
            result = solve_isolated(fake.name, problem, Settings(), repeats=3, warmup=True)
            assert result.found, result.status
            assert result.total_time == pytest.approx(
                total_time(result.setup_time, result.solve_time))
            rows.append(_row(problem, result, fake.name.split("_")[0]))
        frame = store.rows_to_frame(rows)
        assert frame["success"].all()
        assert np.allclose(frame["total_time"], frame["setup_time"] + frame["solve_time"])
        slow = frame[frame["solver"] == "slow"].iloc[0]
        if booking == SOLVE:  # booked as solve: the slow one's solve holds the factorisation
            assert slow["solve_time"] >= FACTOR_S
        else:  # booked as setup: its solve alone is below the fast one's (the old trap)
            assert slow["setup_time"] >= FACTOR_S
            fast = frame[frame["solver"] == "fast"].iloc[0]
            assert slow["solve_time"] < fast["solve_time"]
        totals[booking] = float(slow["total_time"])
        table = aggregate(frame).set_index("solver")
        ranks[booking] = table["time_rel"].to_dict()
        assert list(ranked_time(frame)) == list(frame[RANKED_TIME_COLUMN])
    assert RANKED_TIME_COLUMN == "total_time"
    for booking in (SETUP, SOLVE):
        assert ranks[booking]["fast"] == 1.0  # the fast backend is best either way
        assert ranks[booking]["slow"] > 1.5
    expected = 0.001 + FACTOR_S + ITERATE_S["slow"]
    for value in totals.values():  # sleeps never end early; allow scheduling delay above
        assert expected <= value < expected + 0.05
