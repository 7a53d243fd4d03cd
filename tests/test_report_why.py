"""The report's "why slow" lines (bench/report_why.py) on synthetic rows whose split is known:
a setup-bound solver, an iteration-bound one, a per-iteration-bound one and a failing one,
each > 5x the fastest, and one 3x solver that gets no line."""

from __future__ import annotations

from typing import Any

import pandas as pd

from c3bench.bench import store
from c3bench.bench.report_why import SLOW_FACTOR, why_slow_lines, why_slow_section

# solver -> (setup s, solve s, iterations, success)
SPLITS: dict[str, tuple[float, float, int, bool]] = {
    "fast": (0.1e-3, 0.2e-3, 8, True),
    "setup_heavy": (9.0e-3, 1.0e-3, 8, True),  # 10 ms: setup 90 %
    "many_iterations": (0.1e-3, 4.0e-3, 40, True),  # 4.1 ms, 5x the iterations
    "slow_iterations": (0.1e-3, 4.0e-3, 8, True),  # same iterations, 20x per iteration
    "three_times": (0.3e-3, 0.6e-3, 8, True),
    "failing": (0.1e-3, 0.2e-3, 8, False),
}


def _rows() -> pd.DataFrame:
    rows: list[dict[str, Any]] = []
    for solver, (setup, solve, iterations, success) in SPLITS.items():
        for k in range(4):
            row = store.empty_row()
            row.update({"cell_id": f"c3_qp-c3-s{k}--{solver}", "suite": "t",
                        "instance": f"c3_qp-c3-s00{k}-i00", "family": "c3_qp",
                        "solver": solver, "settings": "default", "precision": "float64",
                        "start": "cold", "tolerance": 1e-3, "time_limit": 10.0,
                        "repeats": 1, "setup_time": setup * (1 + 0.01 * k),
                        "solve_time": solve * (1 + 0.01 * k),
                        "total_time": (setup + solve) * (1 + 0.01 * k),
                        "iterations": iterations, "found": success, "success": success})
            rows.append(row)
    return pd.DataFrame(rows)


def test_each_slow_solver_gets_its_measured_reason() -> None:
    lines = {line.split("**")[1]: line for line in why_slow_lines(_rows())}
    assert set(lines) == {"setup_heavy", "many_iterations", "slow_iterations", "failing"}
    assert "setup is 90 % of its time" in lines["setup_heavy"]
    assert "fast pays 0.3" in lines["setup_heavy"]
    assert "iterations: 40 vs 8" in lines["many_iterations"]
    assert ("time per iteration 0.508 ms vs 0.0254 ms (8 vs 8 iterations)"
            in lines["slow_iterations"])
    assert "4 of 4 cells failed, each charged the 10 s limit" in lines["failing"]
    assert f"{SLOW_FACTOR:g}x" in why_slow_section(_rows())


def test_no_line_below_the_factor_and_none_for_other_families() -> None:
    frame = _rows()
    assert not why_slow_lines(frame[frame["solver"].isin(["fast", "three_times"])])
    assert not why_slow_lines(frame.assign(family="mpcc"))
    assert "No backend is that slow" in why_slow_section(frame.iloc[:0])
