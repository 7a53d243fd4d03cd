"""Accuracy you can see, budgets and denominators per variant (bench/metrics, accuracy,
budgets, compare, report), on synthetic results tables whose answers are computed by hand.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import synthetic_report
from synthetic_results import frame as make_frame
from synthetic_results import row

from c3bench.bench import metrics
from c3bench.bench.accuracy import accuracy_profile, claimed_but_wrong, pareto_front, pareto_points
from c3bench.bench.budgets import DEFAULT_BUDGET_S, budget_seconds, budget_table
from c3bench.bench.compare import compare_frame, format_comparison
from c3bench.bench.metrics import TIME_SHIFT, aggregate, worst_residual
from c3bench.problems.errors import InputError


def _gm(values: list[float]) -> float:
    """Geometric mean by hand, zeros raised to 1e-300 only."""
    return math.exp(sum(math.log(max(v, 1e-300)) for v in values) / len(values))


def _sgm(values: list[float], shift: float) -> float:
    return math.exp(sum(math.log(v + shift) for v in values) / len(values)) - shift


def _table(text: str, heading: str) -> dict[str, dict[str, str]]:
    """Rows of the first Markdown table after ``heading``, keyed by their first cell."""
    block = text.split(heading, 1)[1].split("\n### ", 1)[0].split("\n## ", 1)[0]
    block = block.split("\n**", 1)[0] if heading.startswith("**") else block
    lines = [line for line in block.splitlines() if line.startswith("|")]
    headers = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return {cells[0]: dict(zip(headers, cells, strict=True))
            for cells in ([c.strip() for c in line.strip("|").split("|")] for line in lines[2:])}


# --- geometric means without a floor ------------------------------------------------------------
PRIMAL = {"alpha": [1e-16, 1e-10, 3e-5, 0.0], "beta": [2e-4, 5e-2, 1e-8, 7e-7]}
DUAL = {"alpha": [1e-14, 1e-14, 1e-13, 1e-15], "beta": [5e-3, 4e-2, 6e-2, 2e-3]}


def _accuracy_rows() -> list[dict[str, Any]]:
    return [row(instance=f"c3_qp-s000-i{i:02d}", solver=solver,
                primal_residual_relative=PRIMAL[solver][i],
                dual_residual_relative=DUAL[solver][i], duality_gap_relative=1e-17,
                solve_time=1e-3 * (i + 1))
            for solver in PRIMAL for i in range(4)]


def test_accuracy_columns_are_geometric_means_of_the_actual_values(tmp_path: Path) -> None:
    table = make_frame(_accuracy_rows())
    summary = aggregate(table).set_index("solver")
    for solver in PRIMAL:
        worst = [max(p, d, 1e-17, 0.0) for p, d in zip(PRIMAL[solver], DUAL[solver],
                                                         strict=True)]
        assert summary.loc[solver, "primal_sgm"] == pytest.approx(_gm(PRIMAL[solver]),
                                                                  rel=1e-12)
        assert summary.loc[solver, "dual_sgm"] == pytest.approx(_gm(DUAL[solver]), rel=1e-12)
        assert summary.loc[solver, "worst_sgm"] == pytest.approx(_gm(worst), rel=1e-12)
        assert summary.loc[solver, "complementarity_sgm"] == pytest.approx(1e-300, rel=1e-9)
    # below the tolerance nothing is floored: alpha's mean is far under 1e-3
    assert summary.loc["alpha", "primal_sgm"] < 1e-3 * 1e-40
    assert summary.loc["alpha", "dual_rel"] == 1.0
    assert summary.loc["beta", "dual_rel"] == pytest.approx(
        _gm(DUAL["beta"]) / _gm(DUAL["alpha"]), rel=1e-12)
    text = synthetic_report(tmp_path, table)
    shown = _table(text, "### c3_qp / default / float64 / cold")
    assert shown["alpha"]["primal (rel.)"] == f"{_gm(PRIMAL['alpha']):.1e}"
    assert shown["alpha"]["dual (rel.)"] == f"{_gm(DUAL['alpha']):.1e}"
    assert shown["beta"]["dual (rel.)"] == f"**{_gm(DUAL['beta']):.1e}**"  # above 1e-3
    assert shown["alpha"]["compl."] == "0"
    assert "1e-300" in text and "not floored at the tolerance" in text


def test_time_columns_read_the_one_ranked_time_column(monkeypatch: pytest.MonkeyPatch) -> None:
    rows = [row(instance=f"c3_qp-s000-i{i:02d}", solve_time=1e-3 * (i + 1),
                setup_time=2e-3 * (i + 1)) for i in range(3)]
    rows.append(row(instance="c3_qp-s000-i03", primal_residual_relative=1.0, solve_time=1e-4,
                    setup_time=1e-4))  # failed: charged at the 10 s limit
    table = make_frame(rows)
    total = [3e-3, 6e-3, 9e-3, 10.0]  # setup + solve, the default ranked time
    assert aggregate(table)["time_sgm"].iloc[0] == pytest.approx(_sgm(total, TIME_SHIFT))
    monkeypatch.setattr(metrics, "RANKED_TIME_COLUMN", "setup_time")
    build = [2e-3, 4e-3, 6e-3, 10.0]
    assert aggregate(table)["time_sgm"].iloc[0] == pytest.approx(_sgm(build, TIME_SHIFT))
    counts = budget_table(table, 5e-3)
    assert [c.within for c in counts] == [2]  # 2 and 4 ms build times; the failure never


# --- compare ranks accuracy ---------------------------------------------------------------------
def test_compare_ranks_accuracy_on_the_cells_both_solved() -> None:
    alpha = [1e-14, 1e-13, 1e-12, 1e-6, 1e-14, 1e-14]
    beta = [1e-8, 1e-9, 1.5e-12, 1e-9, 1e-8, 5e-1]  # the last one fails
    rows = [row(instance=f"c3_qp-s000-i{i:02d}", solver=name, primal_residual_relative=value,
                dual_residual_relative=1e-20, duality_gap_relative=1e-20)
            for name, values in (("alpha", alpha), ("beta", beta))
            for i, value in enumerate(values)]
    table = make_frame(rows)
    [result] = compare_frame(table, "alpha", "beta")
    assert result.accuracy_basis == "both solved" and result.accuracy_cells == 5
    assert result.accuracy_ratio == pytest.approx(_gm(alpha[:5]) / _gm(beta[:5]), rel=1e-12)
    # cells: alpha more accurate by > 2x on 0, 1, 4; beta on 3; cell 2 (1.5x) is a tie
    assert (result.accuracy_wins_a, result.accuracy_wins_b) == (3, 1)
    assert result.accuracy_winner == "alpha"
    [reverse] = compare_frame(table, "beta", "alpha")
    assert reverse.accuracy_winner == "alpha"
    assert reverse.accuracy_ratio == pytest.approx(1 / result.accuracy_ratio, rel=1e-12)
    assert (reverse.accuracy_wins_a, reverse.accuracy_wins_b) == (1, 3)
    text = format_comparison([result], "alpha", "beta")
    assert f"| {result.accuracy_ratio:.1e} | both solved (5) | 3 / 1 | alpha |" in text
    same = make_frame([row(instance=f"c3_qp-s000-i{i:02d}", solver=name)
                       for name in ("alpha", "beta") for i in range(3)])
    assert compare_frame(same, "alpha", "beta")[0].accuracy_winner == "tie"


# --- accuracy profiles --------------------------------------------------------------------------
def test_accuracy_profile_is_the_counted_fraction() -> None:
    rng = np.random.default_rng(7)
    rows, expected_cells = [], []
    for solver in ("alpha", "beta", "gamma"):
        for i in range(10):
            if solver == "gamma" and i >= 6:
                continue  # gamma ran 6 of the 10 instances: the denominator stays 10
            value = float(10.0 ** rng.uniform(-16, -1))
            found = not (solver == "beta" and i in (2, 5))  # not claimed: never solved
            primal = math.nan if (solver == "alpha" and i == 3) else value
            rows.append(row(instance=f"c3_qp-s000-i{i:02d}", solver=solver,
                            primal_residual_relative=primal, dual_residual_relative=value / 3,
                            duality_gap_relative=value / 7, found=found,
                            failure="" if found else "error"))
            expected_cells.append((solver, found, primal))
    table = make_frame(rows)
    thresholds = np.logspace(-17, 0, 60)
    profile = accuracy_profile(table, thresholds, instances=10)
    for solver in ("alpha", "beta", "gamma"):
        mine = [(found, value) for name, found, value in expected_cells if name == solver]
        counted = [sum(1 for found, value in mine if found and value <= eps) / 10
                   for eps in thresholds]
        assert profile[solver].tolist() == pytest.approx(counted, abs=0)
    # at the tolerance the profile is the success rate (no reference here)
    at_tol = accuracy_profile(table, np.array([1e-3]), instances=10)
    for solver, group in table.groupby("solver"):
        assert at_tol[solver][0] == group["success"].sum() / 10


# --- Pareto front -------------------------------------------------------------------------------
def _brute_front(points: list[tuple[float, float]]) -> list[bool]:
    out = []
    for i, (t, r) in enumerate(points):
        beaten = any(j != i and u <= t and s <= r and (u, s) != (t, r)
                     for j, (u, s) in enumerate(points))
        out.append(not beaten)
    return out


def test_pareto_front_is_the_brute_force_non_dominated_set() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        points = [(float(rng.integers(1, 6)), float(rng.integers(1, 6))) for _ in range(n)]
        assert pareto_front(points) == _brute_front(points)  # ties and duplicates included
    assert pareto_front([(1.0, math.nan), (2.0, 1.0)]) == [False, True]


def test_pareto_points_use_median_charged_time_and_mean_residual() -> None:
    spec = {"alpha": (1e-3, 1e-14), "beta": (1e-4, 1e-8), "gamma": (2e-3, 1e-10),
            "delta": (1e-4, 1e-6)}
    rows = [row(instance=f"c3_qp-s000-i{i:02d}", solver=name, solve_time=time,
                primal_residual_relative=res, dual_residual_relative=res / 10,
                duality_gap_relative=res / 10)
            for name, (time, res) in spec.items() for i in range(5)]
    # fast but failing on 3 of 5: median charged time is the 10 s limit
    rows += [row(instance=f"c3_qp-s000-i{i:02d}", solver="eps", solve_time=1e-5,
                 primal_residual_relative=1e-16 if i < 2 else 1.0) for i in range(5)]
    points = {p.solver: p for p in pareto_points(make_frame(rows))}
    assert {s for s, p in points.items() if p.on_front} == {"alpha", "beta"}
    assert points["eps"].time == 10.0
    assert points["alpha"].time == pytest.approx(1e-3)
    assert points["gamma"].residual == pytest.approx(1e-10, rel=1e-12)


# --- claimed success but wrong ------------------------------------------------------------------
def test_claimed_but_wrong_finds_exactly_the_planted_rows(tmp_path: Path) -> None:
    planted = {
        ("c3_qp-s000-i02", "alpha"): {"primal_residual_relative": 5e-2},
        ("c3_qp-s000-i03", "alpha"): {"dual_residual_relative": 2e-3},
        ("c3_qp-s000-i01", "beta"): {"found": False, "failure": "error",
                                     "primal_residual_relative": math.nan},
        ("lcp-s001", "gamma"): {"dual_residual_relative": math.nan},
    }
    cells = [(f"c3_qp-s000-i{i:02d}", "c3_qp", s) for s in ("alpha", "beta") for i in range(5)]
    cells += [(f"lcp-s{i:03d}", "lcp", "gamma") for i in range(3)]
    rows = [row(instance=name, family=family, solver=solver,
                **planted.get((name, solver), {})) for name, family, solver in cells]
    table = make_frame(rows)
    found = {(g.family, g.solver): g for g in claimed_but_wrong(table)}
    assert set(found) == {("c3_qp", "alpha"), ("lcp", "gamma")}  # beta's was not claimed
    alpha, gamma = found["c3_qp", "alpha"], found["lcp", "gamma"]
    assert (alpha.cells, alpha.claimed, alpha.wrong) == (5, 5, 2)
    assert (alpha.instance, alpha.figure, alpha.value) == ("c3_qp-s000-i02",
                                                           "primal_residual_relative", 5e-2)
    assert (gamma.wrong, gamma.instance, gamma.figure) == (1, "lcp-s001",
                                                           "dual_residual_relative")
    assert math.isnan(gamma.value)
    shown = _table(synthetic_report(tmp_path, table), "## Claimed success but wrong")
    assert shown["c3_qp"]["wrong / claimed"] == "40.0% (2/5)"
    assert shown["lcp"]["value"] == "unavailable"


# --- budgets ------------------------------------------------------------------------------------
def test_budget_counts_successes_within_the_control_budget(tmp_path: Path) -> None:
    times = [1e-3, 4e-3, 6e-3, 2e-3]
    rows = [row(instance=f"c3_qp-s000-i{i:02d}", solve_time=t,
                primal_residual_relative=1.0 if i == 3 else 1e-12)  # i03 fast but failed
            for i, t in enumerate(times)]
    rows += [row(instance=f"lcp-s{i:03d}", family="lcp", solve_time=9e-3) for i in range(2)]
    rows += [row(instance="mpcc-s000", family="mpcc", solve_time=1e-4,
                 dual_residual_relative=math.nan)]
    table = make_frame(rows)
    assert abs(DEFAULT_BUDGET_S - 0.05 / 10) < 1e-15
    assert budget_seconds(None) == DEFAULT_BUDGET_S and budget_seconds(7.0) == 7e-3
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InputError):
            budget_seconds(bad)
    default = {c.family: (c.within, c.cells) for c in budget_table(table, DEFAULT_BUDGET_S)}
    assert default == {"c3_qp": (2, 4), "lcp": (0, 2)}  # mpcc is not a QP family
    wider = {c.family: (c.within, c.cells) for c in budget_table(table, 1e-2)}
    assert wider == {"c3_qp": (3, 4), "lcp": (2, 2)}
    text = synthetic_report(tmp_path, table)
    assert "b = dt / N = 50 ms / 10 = 5 ms" in text
    assert _table(text, "**c3_qp** (within b")["alpha"]["default / float64 / cold"] == \
        "50.0% (2/4)"
    text = synthetic_report(tmp_path, table, budget_ms=10.0)
    assert "b = 10 ms (set for this report)" in text and "time limit 10 s" in text
    assert _table(text, "**lcp** (within b")["alpha"]["default / float64 / cold"] == \
        "100.0% (2/2)"


# --- denominators per variant -------------------------------------------------------------------
def test_a_solver_of_one_variant_is_not_run_on_the_other(tmp_path: Path) -> None:
    rows = []
    verified = {"family": "projection", "reference_solver": "scip",
                "reference_objective": 1.0, "reference_spread": 0.0, "cost_error": 0.0}
    for variant in ("c3", "c3plus"):
        for i in range(3):
            name = f"projection-{variant}-s000-i00-k{i}"
            rows.append(row(instance=name, solver="scip", **verified))
            if variant == "c3plus":
                rows.append(row(instance=name, solver="c3plus_closed_form", **verified))
    table = make_frame(rows)
    summary = aggregate(table)
    closed = summary[summary["solver"] == "c3plus_closed_form"]
    assert closed["variant"].tolist() == ["c3plus"] and closed["cells"].tolist() == [3]
    assert summary.loc[summary["solver"] == "scip", "cells"].tolist() == [3, 3]
    assert worst_residual(table).tolist() == pytest.approx([1e-12] * len(table))
    text = synthetic_report(tmp_path, table)
    overview = _table(text, "**projection (c3 variant)** (success rate")
    assert overview["c3plus_closed_form"]["default"] == "not run"
    assert _table(text, "**projection (c3plus variant)** (success rate")[
        "c3plus_closed_form"]["default"] == "100.0%"
    c3 = _table(text, "### projection (c3 variant) / default / float64 / cold")
    assert c3["c3plus_closed_form"]["cells"] == "not run"
    assert c3["scip"]["cells"] == "3"
