"""Closed-loop suites through the runner's executors: storage, resume, report, sweep grid."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from c3bench.bench.closed_loop import ControllerSpec
from c3bench.bench.closed_loop_suite import Case, run_cases, sweep_cases, sweep_grid, write_report


def short_cases() -> list[Case]:
    spec = ControllerSpec(qp_backend="clarabel")
    return [Case("nominal", "backends", spec, duration=0.25),
            Case("jittered", "backends", spec, seed=1, duration=0.25),
            Case("broken", "backends", ControllerSpec(qp_backend="no_such_solver"),
                 duration=0.25)]


def test_suite_runs_stores_resumes_and_reports(tmp_path: Path) -> None:
    first = run_cases(short_cases(), tmp_path, jobs=2, progress=False)
    assert [row["case"] for row in first.rows] == ["nominal", "jittered", "broken"]
    assert first.skipped == 0
    rows = {row["case"]: row for row in first.rows}
    assert rows["nominal"]["steps"] == 5 and rows["nominal"]["error"] == ""
    # an unknown QP backend is refused before the run: an error row, no cell stored
    assert rows["broken"]["failure_mode"] == -1
    assert "unknown solver 'no_such_solver'" in rows["broken"]["error"]
    assert not (tmp_path / "cells" / "broken").exists()
    from c3bench.problems.config import load_config

    config = load_config()
    nominal, jittered = short_cases()[0], short_cases()[1]
    offset = jittered.initial_state(config) - nominal.initial_state(config)
    assert 0 < abs(offset[3]) <= 0.01 and 0 < abs(offset[4]) <= 0.01
    assert abs(offset[:3]).max() == 0 and abs(offset[5:]).max() == 0
    stored = pd.read_parquet(tmp_path / "results.parquet")
    assert list(stored["case"]) == ["nominal", "jittered", "broken"]
    again = run_cases(short_cases(), tmp_path, jobs=2, progress=False)
    assert again.skipped == 2  # the error row is not stored: tried again
    assert [r.get("final_angle") for r in again.rows] == \
        [r.get("final_angle") for r in first.rows]
    report = write_report(again, "test", render=False)
    text = report.read_text()
    assert "nominal" in text and "![error](figures/closed_loop_error.png)" in text
    assert (tmp_path / "figures" / "closed_loop_angles.png").stat().st_size > 0


def test_sweep_grid_has_one_cell_per_combination() -> None:
    cases = sweep_cases(dts=(0.05, 0.1), schedules=("geometric",), q_boxes=(2e5,),
                        model_ls=(0.29, 0.30))
    assert len(cases) == 4 and len({c.name for c in cases}) == 4
    rows = [{"group": "sweep", "dt": c.dt, "rho_schedule": c.spec.rho_schedule,
             "q_cube_pose": c.q_cube_pose, "model_l": c.spec.model_l,
             "failure_mode": i % 2, "angle_error": 0.1 * i} for i, c in enumerate(cases)]
    grid = sweep_grid(pd.DataFrame(rows))
    assert grid.count("success") == 2 and grid.count("mode 1") == 2
    assert "0.05 / geometric" in grid and "0.1 / geometric" in grid
