"""Contact measured at the plant's rate (1 ms), not only at the recorded states (50 ms).

The audit's case: the fast single-model C3+ (``l = 0.29``, nominal start) strikes the cube
58 ms into the run, between the first two recorded states after the start, and the ball is off
the cube for about 0.2 s before the recorded states see it touch at 0.30 s. The metrics must
see the strike; an independent 1 ms replay of the recorded inputs (MuJoCo ``Plant.step`` and
a hand-written sphere-box distance, as the audit did) must agree with them.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench.closed_loop import (
    ContactProbe,
    ControllerSpec,
    FailureRules,
    Trajectory,
    advance,
    label_failure_mode,
    records_frame,
    run_closed_loop,
    run_signals,
    simulate,
)
from c3bench.bench.closed_loop_labels import LabelRules
from c3bench.bench.closed_loop_metrics import PlantContact, SuccessRules, physical_metrics
from c3bench.bench.closed_loop_suite import Case, _stored, case_row
from c3bench.problems.config import load_config
from c3bench.problems.scene import Plant, build_scene, home_state, target_state

CONFIG = load_config()
SCENE = build_scene(config=CONFIG)
H = float(SCENE.model.opt.timestep)
TARGET, BAND = CONFIG.mpc.target_angle, CONFIG.mpc.success_tolerance


def box_gap(x: np.ndarray, side: float, radius: float) -> float:
    """Planar sphere-box signed distance written out by hand (independent of MuJoCo's)."""
    c, s = math.cos(x[2]), math.sin(x[2])
    dx, dz = x[3] - x[0], x[4] - x[1]
    lx, lz = c * dx - s * dz, s * dx + c * dz  # ball centre in the cube frame
    qx, qz = abs(lx) - side / 2, abs(lz) - side / 2
    return math.hypot(max(qx, 0.0), max(qz, 0.0)) + min(max(qx, qz), 0.0) - radius


@pytest.fixture(scope="module")
def audited_run() -> tuple[Trajectory, list, object]:
    spec = ControllerSpec(controller="c3plus-fast", model_l=0.29)
    return run_closed_loop(spec, CONFIG, duration=1.0)


def test_strike_between_recorded_states_is_seen(audited_run) -> None:
    trajectory, records, outcome = audited_run
    m = outcome.metrics
    assert m is not None and m.contact_step == pytest.approx(H)
    # the recorded states alone see the first touch at 0.30 s and no time off the cube
    sampled = physical_metrics(replace(run_signals(trajectory, records, SCENE), plant=None),
                               TARGET, BAND)
    assert sampled.first_touch_time >= 0.25 and sampled.free_time == 0.0
    assert m.first_touch_time == pytest.approx(0.058, abs=1.5e-3)
    assert m.free_time > 0.15  # the ball bounced off the cube after the strike
    assert m.impact_speed > 3.0  # a strike, not the 0.22 m/s of the recorded state
    assert m.max_cube_penetration > sampled.max_cube_penetration + 1e-3
    assert m.contact_time + m.free_time == pytest.approx(1.0 - m.first_touch_time)


def test_metrics_agree_with_an_independent_1ms_replay(audited_run) -> None:
    trajectory, records, outcome = audited_run
    m = outcome.metrics
    radius, table = CONFIG.scene.ball_radius, CONFIG.scene.table_height
    plant = Plant(SCENE)
    plant.reset(trajectory.states[0])
    fine = [trajectory.states[0].copy()]
    per_period = round(CONFIG.mpc.dt / H)
    for u in trajectory.inputs:
        for _ in range(per_period):
            fine.append(plant.step(u, H))
    states = np.array(fine)
    np.testing.assert_array_equal(states[::per_period], trajectory.states)  # same plant
    gaps = np.array([box_gap(x, SCENE.l, radius) for x in states])
    touching = gaps <= SuccessRules().contact_gap
    first = int(np.flatnonzero(touching)[0])
    assert m.first_touch_time == pytest.approx(first * H, abs=1e-12)
    after = touching[first + 1:]
    assert m.contact_time == pytest.approx(after.sum() * H, abs=1e-9)
    assert m.free_time == pytest.approx((~after).sum() * H, abs=1e-9)
    x = states[first]
    r_x, r_z, omega = x[3] - x[0], x[4] - x[1], x[7]
    relative = (x[8] - x[5] - omega * r_z, x[9] - x[6] + omega * r_x)
    assert m.impact_speed == pytest.approx(math.hypot(*relative), rel=1e-9)
    # the audit's speed one plant step earlier (before the touch), ball alone: within 5 %
    assert m.impact_speed == pytest.approx(math.hypot(*states[first - 1, 8:10]), rel=0.05)
    assert m.max_cube_penetration == pytest.approx(max(0.0, -gaps.min()), abs=1e-6)
    heights = states[:, 4] - radius - table
    assert m.max_table_penetration == pytest.approx(max(0.0, -heights.min()), abs=1e-12)
    # per period, in the step table
    frame = records_frame(trajectory, records, SCENE)
    windows = gaps[1:].reshape(-1, per_period)
    np.testing.assert_allclose(frame["plant_min_gap"], windows.min(axis=1), atol=1e-6)
    np.testing.assert_allclose(frame["plant_contact_time"],
                               (windows <= SuccessRules().contact_gap).sum(axis=1) * H)
    np.testing.assert_allclose(frame["plant_away_time"],
                               (windows > FailureRules().contact_gap).sum(axis=1) * H)
    assert frame["plant_touch_time"].notna().sum() == (windows <= 0.002).any(axis=1).sum()
    # the cube's lowest point above the table, by hand: centre height less the half side
    # times |cos| + |sin| of the tilt
    clearance = states[:, 1] - SCENE.l / 2 * (np.abs(np.cos(states[:, 2]))
                                              + np.abs(np.sin(states[:, 2]))) - table
    lifted = clearance[1:].reshape(-1, per_period)
    np.testing.assert_allclose(frame["plant_cube_clearance"], lifted.max(axis=1), atol=1e-9)
    np.testing.assert_allclose(frame["plant_cube_air_time"],
                               (lifted > LabelRules().air_gap).sum(axis=1) * H)
    assert trajectory.plant is not None and trajectory.plant.air_gap == LabelRules().air_gap


def test_advance_steps_the_plant_as_plant_step_does() -> None:
    x0 = home_state(SCENE)
    u = np.array([12.0, -3.0])

    def law(x: np.ndarray, s: float, u0: np.ndarray) -> np.ndarray:
        return u0 + 50.0 * (0.02 - x[3:5]) - 40.0 * s  # saturates: the clip acts

    for control in (None, law):
        reference, mine = Plant(SCENE), Plant(SCENE)
        reference.reset(x0)
        mine.reset(x0)
        probe = ContactProbe(SCENE, 0.002, 0.02, LabelRules().air_gap)
        for _ in range(4):
            expected = reference.step(u, 0.05) if control is None else \
                reference.step_with(lambda x, s, c=control: c(x, s, u), 0.05)
            np.testing.assert_array_equal(advance(mine, u, 0.05, probe, control), expected)
    with pytest.raises(ValueError, match="multiple of the plant step"):
        advance(Plant(SCENE), u, 0.0505,
                ContactProbe(SCENE, 0.002, 0.02, LabelRules().air_gap))


def test_simulate_records_one_plant_contact_entry_per_period() -> None:
    trajectory, records = simulate(lambda x, t: (np.array([20.0, 0.0]), {}), CONFIG, 0.5)
    plant = trajectory.plant
    assert plant is not None and plant.min_gap.shape == (10,)
    assert plant.plant_step == H and plant.contact_gap == SuccessRules().contact_gap
    # the last plant state of a period is the next recorded state
    assert np.all(plant.min_gap <= trajectory.ball_gap[1:] + 1e-15)
    assert np.all(plant.contact_time + plant.away_time <= 0.05 + 1e-12)
    frame = records_frame(trajectory, records, SCENE)
    assert {f"plant_{name}" for name in PlantContact.COLUMNS} <= set(frame)


def test_rules_with_another_contact_gap_are_refused(audited_run) -> None:
    trajectory, records, _ = audited_run
    signals = run_signals(trajectory, records, SCENE)
    with pytest.raises(ValueError, match="contact_gap"):
        physical_metrics(signals, TARGET, BAND, SuccessRules(contact_gap=0.005))
    # run_closed_loop measures at the rules' threshold
    spec = ControllerSpec(controller="c3plus-fast", model_l=0.29)
    other, _, outcome = run_closed_loop(spec, CONFIG, 0.2,
                                        rules=SuccessRules(contact_gap=0.005))
    assert other.plant is not None and other.plant.contact_gap == 0.005
    assert outcome.metrics is not None and outcome.metrics.first_touch_time <= 0.058


def test_whack_rule_uses_the_time_away_at_the_plant_rate() -> None:
    """Failure mode 3 (ball > 2 cm from the cube for >= 0.2 s after the peak): the recorded
    states can show the ball on the face while it was away in between, and away while it
    touched in between; the plant-rate record decides."""
    angles = np.concatenate([np.linspace(0, 0.4, 10), np.linspace(0.4, 0.05, 31)])
    on_face = np.array([target_state(SCENE, a) for a in angles])
    times = np.arange(41) * CONFIG.mpc.dt
    gaps = np.zeros(41)

    def record(away: float) -> PlantContact:
        n = 40
        return PlantContact(H, 0.002, 0.02, np.zeros(n), np.full(n, 0.1), np.zeros(n),
                            np.full(n, away), np.full(n, np.nan), np.full(n, np.nan))

    sampled = Trajectory(times, on_face, np.zeros((40, 2)), gaps)
    assert label_failure_mode(sampled, SCENE, TARGET, BAND)[0] == 5  # samples: on the face
    away = replace(sampled, plant=record(0.02))  # 20 ms of every period off the cube
    mode, reason = label_failure_mode(away, SCENE, TARGET, BAND)
    assert mode == 3 and "contact lost 0.62 s" in reason  # 31 periods after the peak
    assert label_failure_mode(replace(sampled, plant=record(0.006)), SCENE, TARGET,
                              BAND)[0] == 5  # 0.19 s: not enough
    # the other way round: away at every recorded state, touching in between
    far = on_face.copy()
    far[:, 3] -= 0.5
    far_gaps = np.full(41, 0.5)
    seen_away = Trajectory(times, far, np.zeros((40, 2)), far_gaps)
    assert label_failure_mode(seen_away, SCENE, TARGET, BAND)[0] == 3
    touched = replace(seen_away, plant=record(0.0))
    assert label_failure_mode(touched, SCENE, TARGET, BAND)[0] == 5


def test_stored_rows_without_plant_rate_contact_are_run_again(tmp_path: Path) -> None:
    case = Case("c", "g", ControllerSpec())
    cell = tmp_path / "c"
    cell.mkdir()
    row = {**case_row(case), "success": True}
    (cell / "summary.json").write_text(json.dumps(row))
    assert _stored(tmp_path, case) is None  # measured at the recorded states only: stale
    judged = {**row, "contact_step": 0.001, "pivot_slip": 0.002}
    (cell / "summary.json").write_text(json.dumps(judged))
    stored = _stored(tmp_path, case)
    assert stored is not None and stored["contact_step"] == 0.001


def test_stored_rows_judged_before_the_pivot_rule_are_run_again(tmp_path: Path) -> None:
    """A row stored before success required the pivot to stay put (no ``pivot_slip``) may
    call a slid cube a success, and its labels predate ``thrown / tumbled`` and ``cube
    slid``: the case runs again."""
    case = Case("c", "g", ControllerSpec())
    cell = tmp_path / "c"
    cell.mkdir()
    row = {**case_row(case), "success": True, "label": "success", "contact_step": 0.001}
    (cell / "summary.json").write_text(json.dumps(row))
    assert _stored(tmp_path, case) is None

