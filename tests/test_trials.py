"""Randomized closed-loop trials: the Wilson interval, Newcombe's interval for a difference of
rates (against his paper's table), the per-configuration summary, the randomization and a short
end-to-end run of ``c3bench closed-loop-trials`` through the process pool (stored, then
resumed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench.cli import main
from c3bench.bench.closed_loop import ControllerSpec
from c3bench.bench.trials import (
    TrialRanges,
    newcombe_interval,
    rate_line,
    trial_case,
    trial_cases,
    trial_summary,
    wilson_interval,
)
from c3bench.problems.config import load_config


@pytest.mark.parametrize(("successes", "trials", "low", "high"), [
    (14, 20, 0.4810, 0.8545),  # Wilson (1927); e.g. R's prop.test(14, 20, correct = FALSE)
    (0, 2, 0.0, 0.6576),
    (10, 10, 0.7225, 1.0),
    (1, 1, 0.2065, 1.0),
    (50, 100, 0.4038, 0.5962),
])
def test_wilson_interval_known_values(successes: int, trials: int, low: float,
                                      high: float) -> None:
    got = wilson_interval(successes, trials)
    assert got == pytest.approx((low, high), abs=5e-4)


def test_wilson_interval_is_symmetric_and_checked() -> None:
    low, high = wilson_interval(3, 17)
    assert wilson_interval(14, 17) == pytest.approx((1 - high, 1 - low))
    with pytest.raises(ValueError):
        wilson_interval(5, 4)
    assert rate_line("success", 14, 20) == "success 14/20 (70%, 95% CI 48-85%)"


def test_trials_are_reproducible_from_the_seed_and_differ() -> None:
    spec = ControllerSpec()
    first = trial_cases(spec, 30, seed=7)
    assert first == trial_cases(spec, 30, seed=7)
    assert first[:5] == trial_cases(spec, 5, seed=7)  # a trial does not depend on N
    assert [c.scene_changes for c in first] != [c.scene_changes for c in
                                                trial_cases(spec, 30, seed=8)]
    draws = np.array([[value for _, value in c.scene_changes] for c in first])
    offsets = np.array([c.ball_offset for c in first])
    assert len({tuple(row) for row in draws}) == 30 and len({tuple(o) for o in offsets}) == 30
    nominal = load_config().scene
    ranges = TrialRanges()
    side, mass, mu_table, mu_ball = draws.T
    assert np.all((side >= 0.28) & (side <= 0.32)) and np.ptp(side) > 0.02
    assert np.all(np.abs(mass / nominal.cube_mass - 1) <= ranges.mass)
    assert np.all(np.abs(mu_table / nominal.mu_table - 1) <= ranges.friction)
    assert np.all(np.abs(mu_ball / nominal.mu_ball - 1) <= ranges.friction)
    assert np.all(np.abs(offsets) <= 0.03) and np.abs(offsets).max() > 0.02
    assert all(c.spec == spec for c in first)  # a single-model controller is unchanged
    robust = trial_cases(ControllerSpec(controller="c3plus-robust"), 5, seed=7)
    assert len({c.spec.seed for c in robust}) == 5  # fresh sampled model sides per trial
    config = load_config()
    case = trial_case(spec, 3, seed=7)
    plant = case.plant_config(config)
    assert plant.scene.cube_side == dict(case.scene_changes)["cube_side"]
    x0 = case.initial_state(plant)
    assert x0[1] == pytest.approx(plant.scene.cube_side / 2)  # the cube rests on the table
    assert x0[3:5] == pytest.approx(np.array(nominal.ball_start) + case.ball_offset)


@pytest.mark.timeout(120)
def test_two_short_trials_end_to_end_then_resumed(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["closed-loop-trials", "--trials", "2", "--duration", "0.25", "--seed", "3",
            "--jobs", "2", "--quiet", "--results", str(tmp_path)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "success 0/2 (0%, 95% CI 0-66%)" in out  # 0.25 s runs cannot succeed
    assert "gentle success 0/2" in out and "peak angle" in out and "labels:" in out
    directory = tmp_path / "closed_loop" / "trials" / ControllerSpec().label()
    cells = sorted((directory / "cells").iterdir())
    assert len(cells) == 2
    for cell, case in zip(cells, trial_cases(ControllerSpec(), 2, seed=3, duration=0.25),
                          strict=True):
        row = json.loads((cell / "summary.json").read_text())
        assert row["case"] == case.name == cell.name and row["steps"] == 5
        assert row["cube_side"] == dict(case.scene_changes)["cube_side"]
        for key in ("peak_angle", "passed_balance", "impact_speed", "hold_time",
                    "max_table_penetration", "clipped_inputs", "plan_lcs_error_median",
                    "plan_plant_error_max", "gentle_success"):
            assert key in row
        # the stored states start from the trial's plant: its cube side and ball offset
        states = np.load(cell / "states.npy")
        assert states[0, 1] == pytest.approx(row["cube_side"] / 2)
    assert main(argv) == 0
    again = capsys.readouterr().out
    assert "2 stored" in again and "success 0/2" in again


# Newcombe (1998) Table II, method 10 (the hybrid score interval without continuity
# correction), his eight worked examples (a)-(h): (x1, n1, x2, n2, lower, upper).
NEWCOMBE_TABLE_II = [
    (56, 70, 48, 80, 0.0524, 0.3339),
    (9, 10, 3, 10, 0.1705, 0.8090),
    (6, 7, 2, 7, 0.0582, 0.8062),
    (5, 56, 0, 29, -0.0381, 0.1926),
    (0, 10, 0, 20, -0.1611, 0.2775),
    (0, 10, 0, 10, -0.2775, 0.2775),
    (10, 10, 0, 20, 0.6791, 1.0),
    (10, 10, 0, 10, 0.6075, 1.0),
]


@pytest.mark.parametrize(("x1", "n1", "x2", "n2", "low", "high"), NEWCOMBE_TABLE_II)
def test_newcombe_interval_matches_the_papers_table(x1: int, n1: int, x2: int, n2: int,
                                                   low: float, high: float) -> None:
    assert newcombe_interval(x1, n1, x2, n2) == pytest.approx((low, high), abs=6e-5)


def test_newcombe_interval_is_antisymmetric_and_empty_sides_are_uninformative() -> None:
    low, high = newcombe_interval(14, 20, 6, 20)
    assert newcombe_interval(6, 20, 14, 20) == pytest.approx((-high, -low))
    assert low < 0.4 < high  # it contains the observed difference
    assert newcombe_interval(3, 0, 1, 5) == (-1.0, 1.0)


def test_trial_summary_counts_rates_medians_and_labels() -> None:
    rows = [{"success": True, "gentle_success": True, "passed_balance": False,
             "peak_angle": 0.6, "label": "success", "error": ""},
            {"success": True, "gentle_success": False, "passed_balance": True,
             "peak_angle": 1.0, "label": "success", "error": ""},
            {"success": False, "gentle_success": False, "passed_balance": True,
             "peak_angle": 1.4, "label": "strike-topple", "error": ""},
            {"success": False, "label": "error", "error": "RuntimeError: boom",
             "peak_angle": float("nan")}]
    summary = trial_summary(rows)
    assert (summary.n, summary.successes, summary.gentle, summary.passed_balance,
            summary.errors) == (4, 2, 1, 2, 1)
    assert summary.success_interval == wilson_interval(2, 4)
    assert summary.gentle_interval == wilson_interval(1, 4)
    assert summary.rate == 0.5
    assert summary.medians["peak_angle"] == pytest.approx(1.0)  # NaN ignored
    assert np.isnan(summary.medians["impact_speed"])
    assert summary.labels == (("success", 2), ("strike-topple", 1), ("error", 1))
