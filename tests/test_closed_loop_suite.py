"""Closed-loop suites through the runner's executors: storage, resume, report, sweep grid; the
suites as configurations x randomized trials, their report (intervals, l curve, claims) on
hand-made rows, and a tiny trials suite run end to end and extended."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from c3bench.bench.cli_closed_loop import suite_trials
from c3bench.bench.closed_loop import ControllerSpec
from c3bench.bench.closed_loop_configs import (
    CLOSED_LOOP_SUITES,
    L_CURVE,
    ClosedLoopSuite,
    Configuration,
    reference_ablation,
)
from c3bench.bench.closed_loop_figures import (
    distributions_figure,
    l_curve_figure,
    success_rate_figure,
)
from c3bench.bench.closed_loop_report import configuration_results
from c3bench.bench.closed_loop_suite import (
    Case,
    SuiteRun,
    run_cases,
    sweep_cases,
    sweep_grid,
    write_report,
    write_trials_report,
)
from c3bench.bench.trials import newcombe_interval, wilson_interval
from c3bench.problems.errors import InputError


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


def test_a_stored_run_of_another_backend_is_not_reused(tmp_path: Path) -> None:
    """``sweep --qp-backend osqp`` over a folder of Clarabel runs reported the Clarabel rows
    as done: a stored row whose identifying columns differ from the case's is stale."""
    clarabel = Case("same-name", "sweep", ControllerSpec(qp_backend="clarabel"), duration=0.1)
    osqp = Case("same-name", "sweep", ControllerSpec(qp_backend="osqp"), duration=0.1)
    first = run_cases([clarabel], tmp_path, jobs=1, progress=False)
    assert first.rows[0]["qp_backend"] == "clarabel" and first.rows[0]["error"] == ""
    assert run_cases([clarabel], tmp_path, jobs=1, progress=False).skipped == 1
    other = run_cases([osqp], tmp_path, jobs=1, progress=False)
    assert other.skipped == 0 and other.rows[0]["qp_backend"] == "osqp"
    stored = pd.read_parquet(tmp_path / "results.parquet")
    assert list(stored["qp_backend"]) == ["osqp"]
    grid = dict(dts=(0.1,), schedules=("geometric",), q_boxes=(2e4,), model_ls=(0.29,))
    assert sweep_cases(**grid)[0].name == "sweep-dt0.1-geometric-q20000-l0.29"
    assert sweep_cases(**grid, backend="osqp")[0].name.endswith("-osqp")


def test_sweep_grid_has_one_cell_per_combination() -> None:
    cases = sweep_cases(dts=(0.05, 0.1), schedules=("geometric",), q_boxes=(2e5,),
                        model_ls=(0.29, 0.30))
    assert len(cases) == 4 and len({c.name for c in cases}) == 4
    rows = [{"group": "sweep", "dt": c.dt, "rho_schedule": c.spec.rho_schedule,
             "q_cube_pose": c.q_cube_pose, "model_l": c.spec.model_l, "success": i % 2 == 1,
             "gentle_success": False, "label": "success" if i % 2 else "strike-topple",
             "failure_mode": i % 2, "angle_error": 0.1 * i, "error": ""}
            for i, c in enumerate(cases)]
    grid = sweep_grid(pd.DataFrame(rows))
    assert grid.count("| success (") == 2 and grid.count("strike-topple (") == 2
    assert "0.05 / geometric" in grid and "0.1 / geometric" in grid
    assert "mode" not in grid.split("\n\n", 1)[1]


def test_sweep_grid_agrees_with_the_outcomes_table() -> None:
    """The audit's sweep case: the angle ends in the band (the older end-time rule's mode 0
    would need no slip; here its mode is 1) but the cube slid 3.5 cm, so the run failed, as
    its ``success`` and ``label`` say; a run that failed to run is an error, and a success
    whose old mode said otherwise is a success."""
    case = sweep_cases(dts=(0.05,), schedules=("geometric",), q_boxes=(5e4,),
                       model_ls=(0.27, 0.29, 0.30))
    base = {"group": "sweep", "dt": 0.05, "rho_schedule": "geometric", "q_cube_pose": 5e4,
            "angle_error": 0.007, "error": ""}
    rows = [{**base, "model_l": 0.27, "success": False, "gentle_success": False,
             "label": "cube slid", "failure_mode": 0},
            {**base, "model_l": 0.29, "success": True, "gentle_success": True,
             "label": "success", "failure_mode": 1},
            {**base, "model_l": 0.30, "success": False, "label": "error", "failure_mode": -1,
             "angle_error": float("nan"), "error": "RuntimeError: boom"}]
    assert [c.spec.model_l for c in case] == [0.27, 0.29, 0.30]
    cells = sweep_grid(pd.DataFrame(rows)).splitlines()[-1].split(" | ")
    assert cells[1:] == ["cube slid (0.01)", "gentle success (0.01)", "error |"]


# --- the suites as configurations x randomized trials ---------------------------------------
def test_quick_suite_is_20_trials_of_distinct_configurations() -> None:
    quick, full = CLOSED_LOOP_SUITES["quick"], CLOSED_LOOP_SUITES["full"]
    assert (quick.trials, full.trials) == (20, 100)
    names = [c.name for c in quick.configurations]
    specs = [c.spec for c in quick.configurations]
    assert len(set(names)) == len(names)
    assert all(specs.count(spec) == 1 for spec in specs)  # no controller runs twice
    by_name = {c.name: c for c in quick.configurations}
    for backend in ("clarabel", "osqp"):
        spec = by_name[f"c3plus-{backend}-l0.29"].spec
        assert (spec.controller, spec.qp_backend, spec.model_l) == ("c3plus", backend, 0.29)
    assert by_name["c3plus-clarabel-l0.3"].spec.model_l == 0.30
    seed = by_name["seed-method"].spec
    assert (seed.controller, seed.samples, seed.weighting, seed.feedback) == \
        ("c3plus-fast-robust", 16, True, True)
    assert seed == dict(reference_ablation())["full"]
    uniform = by_name["robust-uniform"].spec
    assert uniform.controller == "c3plus-fast-robust" and not uniform.weighting
    assert not uniform.feedback
    # every part of the ablation runs, the ones that coincide once
    ablation = [spec for _, spec in reference_ablation()]
    assert all(spec in specs for spec in ablation)
    assert "ablation no-feedback" in by_name["robust-weighted"].also
    # the success-vs-l curve: its six sides, 0.29 and 0.30 shared with the ablation
    curve = dict(quick.l_curve)
    assert tuple(curve) == L_CURVE == (0.27, 0.28, 0.29, 0.295, 0.30, 0.31)
    assert curve[0.29] == "ablation-no-samples" and curve[0.30] == "ablation-no-shrunk-model"
    for side, name in curve.items():
        spec = by_name[name].spec
        assert (spec.controller, spec.model_l, spec.feedback) == ("c3plus-fast", side, True)
    assert len(quick.configurations) == 15
    cases = quick.cases()
    assert len(cases) == 20 * 15 and len({c.name for c in cases}) == len(cases)
    per_config = Counter(c.configuration for c in cases)
    assert set(per_config) == set(names) and set(per_config.values()) == {20}
    # trial i is the same draw for every configuration (paired episodes)
    draws = {(c.trial, c.scene_changes, c.ball_offset) for c in cases}
    assert len(draws) == 20
    assert all(c.duration >= 3.0 for c in cases)  # success needs 3 s
    # full: the same configurations, more backends, C3 with its MIQP projections
    full_names = {c.name for c in full.configurations}
    assert set(names) <= full_names
    assert {"c3-clarabel-gurobi", "c3-clarabel-scip"} <= full_names
    for suite in (quick, full):
        for comparison in suite.comparisons:
            assert {comparison.with_choice, comparison.without} <= {
                c.name for c in suite.configurations}


def test_trials_option_overrides_the_count() -> None:
    quick = CLOSED_LOOP_SUITES["quick"]
    cases = quick.cases(3)
    assert len(cases) == 3 * len(quick.configurations)
    assert cases[:len(quick.configurations)] == quick.cases(1)  # a trial does not depend on N
    assert suite_trials(argparse.Namespace(trials=None), 20) == 20
    assert suite_trials(argparse.Namespace(), 20) == 20
    assert suite_trials(argparse.Namespace(trials=4), 20) == 4
    with pytest.raises(InputError, match="--trials"):
        suite_trials(argparse.Namespace(trials=0), 20)
    with pytest.raises(InputError):
        quick.cases(0)


SYNTHETIC_SUCCESSES = {
    "c3plus-clarabel-l0.29": 19, "c3plus-clarabel-l0.3": 4,  # shrunk model: resolved
    "ablation-no-samples": 18, "ablation-no-shrunk-model": 5,
    "seed-method": 4, "robust-weighted": 18,  # feedback: worse with it
    "ablation-no-weighting": 4, "robust-uniform": 17,  # weighting: not resolved
}


def synthetic_rows(suite: ClosedLoopSuite, n: int, skip: str = "") -> list[dict[str, Any]]:
    """``n`` hand-made episode rows per configuration (none for ``skip``): the first ``k``
    succeed, half of those gently."""
    rows = []
    for index, configuration in enumerate(suite.configurations):
        if configuration.name == skip:
            continue
        k = SYNTHETIC_SUCCESSES.get(configuration.name, (3 * index) % (n + 1))
        for trial in range(n):
            ok = trial < k
            rows.append({"case": f"{configuration.name}-{trial:04d}", "config":
                         configuration.name, "trial": trial, "group": configuration.group,
                         "success": ok, "gentle_success": ok and trial % 2 == 0,
                         "passed_balance": not (ok and trial % 2 == 0),
                         "peak_angle": 0.5 + 0.05 * trial, "hold_time": 2.0 if ok else 0.0,
                         "plan_lcs_angle_median": 1e-3 * (trial + 1),
                         "plan_plant_angle_median": 0.0 if trial == 0 else 0.01,
                         "median_step_time": 0.002 * (index + 1), "load_average": 1.5,
                         "label": "success" if ok else "strike-topple", "error": ""})
    return rows


def _rate(k: int, n: int, interval: tuple[float, float]) -> str:
    return f"{k}/{n} ({100 * k / n:.0f} %; {100 * interval[0]:.0f}-{100 * interval[1]:.0f} %)"


def test_trials_report_on_synthetic_rows(tmp_path: Path) -> None:
    quick = CLOSED_LOOP_SUITES["quick"]
    n = 20
    rows = synthetic_rows(quick, n, skip="fast-l0.31")
    report = write_trials_report(SuiteRun(tmp_path, rows=rows), quick, n, render=False)
    text = report.read_text()
    lines = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines()
             if line.startswith("| ")}
    for configuration in quick.configurations:
        line = next(v for k, v in lines.items() if k.startswith(configuration.title))
        mine = [r for r in rows if r["config"] == configuration.name]
        if not mine:  # not run: n = 0, no interval
            assert " | 0 | 0/0 | " in line
            continue
        k = sum(r["success"] for r in mine)
        gentle = sum(r["gentle_success"] for r in mine)
        assert f" | {n} | {_rate(k, n, wilson_interval(k, n))} | " \
               f"{_rate(gentle, n, wilson_interval(gentle, n))} | " in line
        assert "step (ms)" in text and f"| {1e3 * mine[0]['median_step_time']:.3g} |" in line
    # the success-vs-l curve: the points that ran, its figure written, n in its panel
    for side, name in quick.l_curve[:-1]:
        k = SYNTHETIC_SUCCESSES.get(name, sum(r["success"] for r in rows
                                              if r["config"] == name))
        assert f"| {side:g} | {_rate(k, n, wilson_interval(k, n))} |" in text
    assert "| 0.31 |" not in text
    for figure in ("closed_loop_l_curve", "closed_loop_success_rates",
                   "closed_loop_distributions"):
        assert (tmp_path / "figures" / f"{figure}.png").stat().st_size > 0
        assert f"figures/{figure}.png" in text
    # the claims: Newcombe's interval, verdict per claim
    shrunk = newcombe_interval(19, n, 4, n)
    assert f"95 % CI {100 * shrunk[0]:+.0f} to {100 * shrunk[1]:+.0f}: better with the " \
           "choice (Wilson intervals do not overlap)" in text
    assert "* shrunk model: survives" in text
    assert "* low-level feedback: contradicted" in text
    assert "* LCP weighting: not resolved" in text
    assert "Newcombe" in text and "load average" in text


def test_trial_figures_print_n_in_their_panels() -> None:
    quick = CLOSED_LOOP_SUITES["quick"]
    rows = pd.DataFrame(synthetic_rows(quick, 12))
    results = configuration_results(rows, quick)
    assert all(r.summary.n == 12 for r in results)
    figure = success_rate_figure(results)
    assert "n = 12 episodes per configuration" in figure.axes[0].get_title()
    points = [(side, next(r.summary for r in results if r.name == name))
              for side, name in quick.l_curve]
    figure = l_curve_figure(points, 0.30, "test")
    assert "n = 12 episodes per point" in figure.axes[0].get_title()
    rates = np.asarray(figure.axes[0].lines[0].get_ydata(), dtype=float)
    assert rates.tolist() == pytest.approx([s.rate for _, s in points])
    figure = distributions_figure(results)
    titles = [ax.get_title() for ax in figure.axes]
    assert len(titles) == 5 and all(f"n = {12 * len(results)} episodes" in t for t in titles)
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.mark.timeout(120)
def test_a_tiny_trials_suite_runs_reports_and_extends(tmp_path: Path) -> None:
    no_samples = dict(reference_ablation())["no-samples"]
    suite = ClosedLoopSuite("tiny", (Configuration("fast-l0.29", "l-curve", no_samples,
                                                   "fast C3+, l 0.29"),),
                            trials=2, duration=0.25)
    first = run_cases(suite.cases(), tmp_path, jobs=2, progress=False)
    assert sorted(r["case"] for r in first.rows) == ["fast-l0.29-0000", "fast-l0.29-0001"]
    assert all(r["config"] == "fast-l0.29" and r["error"] == "" for r in first.rows)
    assert [r["trial"] for r in first.rows] == [0, 1]
    assert all(r["load_average"] >= 0 for r in first.rows)
    text = write_trials_report(first, suite, 2, render=False).read_text()
    assert "| 0.29 | 0/2 (0 %; 0-66 %) |" in text  # 0.25 s episodes cannot succeed
    more = run_cases(suite.cases(3), tmp_path, jobs=2, progress=False)
    assert more.skipped == 2 and len(more.rows) == 3
    text = write_trials_report(more, suite, 3, render=False).read_text()
    assert "| 0.29 | 0/3 (0 %; 0-56 %) |" in text
    stored = pd.read_parquet(tmp_path / "results.parquet")
    assert list(stored["trial"]) == [0, 1, 2]
