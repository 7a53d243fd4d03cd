"""Physical metrics of a closed-loop run: each on a synthetic run whose answer is known by
hand, and the plan-consistency metric against a hand rollout of a recorded step."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from c3bench.bench.closed_loop import (
    ControllerSpec,
    FailureRules,
    records_frame,
    run_closed_loop,
)
from c3bench.bench.closed_loop_metrics import (
    PlantContact,
    RunSignals,
    SuccessRules,
    balance_angle,
    physical_metrics,
)
from c3bench.problems.config import load_config
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import build_scene
from c3bench.solvers.lcp import lemke

DT = 0.05
TARGET, BAND = 0.5, 0.1
N = 61  # 3 s at 50 ms: states 0..60


def signals(**changes: object) -> RunSignals:
    """A 3 s run: the cube strikes to 0.9 rad, falls back into the band at t = 2 s and stays
    there (0.52 rad), its pivot (far bottom corner) at x = 0.15 m throughout; the ball touches
    at t = 0.5 s and is off the cube for states 30-39."""
    times = np.arange(N) * DT
    angles = np.concatenate([np.linspace(0.0, 0.9, 20), np.linspace(0.9, 0.7, 20),
                             np.full(21, 0.52)])
    gap = np.zeros(N)
    gap[:10] = 0.05
    gap[30:40] = 0.05
    speed = np.zeros(N)
    speed[9] = 0.7  # just before the touch
    speed[10] = 0.2
    states = np.zeros((N, 10))
    states[:, 2] = angles
    plan = states[1:].copy()
    plan[:, 2] += 0.1  # the plan predicts 0.1 rad more than the plant did
    lcs = plan.copy()
    lcs[:, 2] -= 0.3
    lcs[5, 2] -= 0.2  # one step is far off
    plan[7] = lcs[7] = np.nan  # a step without a plan
    commanded = np.zeros((N - 1, 2))
    commanded[0] = (34.0, 10.0)
    commanded[1] = (-5.0, -31.0)
    commanded[2] = (30.0, 0.0)  # at the limit: not clipped
    base = RunSignals(times=times, angles=angles, ball_gap=gap, ball_height=np.full(N, 0.1),
                      ball_speed=speed, commanded=commanded, force_limit=30.0, cube_side=0.3,
                      plan_next=plan, lcs_next=lcs, states=states, pivot_x=np.full(N, 0.15))
    return replace(base, **changes)


def test_balance_angle_is_pi_over_4_for_a_cube() -> None:
    assert balance_angle(0.3) == pytest.approx(math.pi / 4)
    assert balance_angle(0.2, 0.4) == pytest.approx(math.atan(0.5))


def test_each_metric_on_a_hand_made_run() -> None:
    m = physical_metrics(signals(), TARGET, BAND)
    assert m.peak_angle == pytest.approx(0.9) and m.passed_balance
    assert m.first_touch_time == pytest.approx(0.5)
    # states 10..59 stand for 50 periods after the touch: 10 of them (30-39) off the cube
    assert m.contact_time == pytest.approx(40 * DT) and m.free_time == pytest.approx(10 * DT)
    assert m.impact_speed == pytest.approx(0.7)
    assert m.settling_time == pytest.approx(2.0) and m.hold_time == pytest.approx(1.0)
    assert m.steady_offset == pytest.approx(0.02)
    assert m.max_cube_penetration == 0.0 and m.max_table_penetration == 0.0
    assert m.contact_step == pytest.approx(DT)  # no plant-rate record: the recorded states
    assert m.clipped_inputs == 2
    assert m.plan_plant_angle_median == pytest.approx(0.1)
    assert m.plan_plant_angle_max == pytest.approx(0.1)
    assert m.plan_lcs_angle_median == pytest.approx(0.3)
    assert m.plan_lcs_angle_max == pytest.approx(0.5)
    assert m.plan_lcs_error_max == pytest.approx(0.5)  # only the angle differs
    assert m.success and not m.gentle_success


def test_gentle_success_needs_no_pass_of_the_balance_angle() -> None:
    base = signals()
    angles = np.minimum(base.angles, 0.7)
    m = physical_metrics(replace(base, angles=angles), TARGET, BAND)
    assert m.peak_angle == pytest.approx(0.7) and not m.passed_balance
    assert m.success and m.gentle_success


def test_success_needs_the_hold_time_at_the_end() -> None:
    base = signals()
    angles = base.angles.copy()
    angles[45] = 0.65  # leaves the band at t = 2.25 s: held 0.75 s only
    m = physical_metrics(replace(base, angles=angles), TARGET, BAND)
    assert m.settling_time == pytest.approx(2.3) and m.hold_time == pytest.approx(0.7)
    assert not m.success
    assert physical_metrics(replace(base, angles=angles), TARGET, BAND,
                            SuccessRules(hold_time=0.5)).success
    angles[-1] = 0.2  # ends outside the band
    ended = physical_metrics(replace(base, angles=angles), TARGET, BAND)
    assert math.isnan(ended.settling_time) and ended.hold_time == 0.0 and not ended.success


def test_success_needs_three_seconds_and_no_deep_penetration() -> None:
    base = signals()
    short = replace(base, times=base.times * 0.9)  # a 2.7 s run
    assert not physical_metrics(short, TARGET, BAND).success
    gap = base.ball_gap.copy()
    gap[25] = -0.004
    m = physical_metrics(replace(base, ball_gap=gap), TARGET, BAND)
    assert m.max_cube_penetration == pytest.approx(0.004) and m.success
    height = base.ball_height.copy()
    height[50] = -0.006  # the ball 6 mm into the table
    m = physical_metrics(replace(base, ball_height=height), TARGET, BAND)
    assert m.max_table_penetration == pytest.approx(0.006) and not m.success


def test_success_needs_the_pivot_to_stay_put() -> None:
    """The audit's sweep case ``sweep-dt0.05-geometric-q50000-l0.27``: the cube's far bottom
    edge slid 3.5 cm along the table in the first 0.3 s, then the cube tipped to 0.49 rad and
    held there; the old rule called that a success."""
    base = signals()
    slid = base.pivot_x + np.minimum(np.arange(N), 7) * 0.005  # 3.5 cm by state 7
    m = physical_metrics(replace(base, pivot_x=slid), TARGET, BAND)
    assert m.pivot_slip == pytest.approx(0.035) and m.hold_time == pytest.approx(1.0)
    assert not m.success and not m.gentle_success
    assert physical_metrics(replace(base, pivot_x=slid), TARGET, BAND,
                            SuccessRules(pivot_slip=0.04)).success
    crept = base.pivot_x + np.minimum(np.arange(N), 7) * 0.004  # 2.8 cm: under the limit
    assert physical_metrics(replace(base, pivot_x=crept), TARGET, BAND).success
    back = slid.copy()
    back[20:] = base.pivot_x[20:]  # slid 3.5 cm and back: the largest slide counts
    assert not physical_metrics(replace(base, pivot_x=back), TARGET, BAND).success
    # a run whose pivot was not measured cannot be judged a success
    unmeasured = physical_metrics(replace(base, pivot_x=np.zeros(0)), TARGET, BAND)
    assert math.isnan(unmeasured.pivot_slip) and not unmeasured.success
    assert FailureRules().pivot_slip == SuccessRules().pivot_slip  # one threshold


def test_no_touch_and_no_plan() -> None:
    base = signals()
    nan = np.full_like(base.plan_next, np.nan)
    m = physical_metrics(replace(base, ball_gap=np.full(N, 0.05), plan_next=nan), TARGET,
                         BAND)
    assert math.isnan(m.first_touch_time) and math.isnan(m.impact_speed)
    assert m.contact_time == 0.0 and m.free_time == 0.0
    assert math.isnan(m.plan_lcs_error_median) and math.isnan(m.plan_plant_angle_max)


@pytest.mark.timeout(60)
def test_plan_consistency_equals_a_hand_rollout_of_a_recorded_step() -> None:
    config = load_config()
    spec = ControllerSpec(controller="c3plus", qp_backend="clarabel", qp_time_limit=None)
    trajectory, records, outcome = run_closed_loop(spec, config, duration=0.1)
    first = records[0]
    assert first.plan_next is not None and first.plan_input is not None
    assert first.commanded is not None
    np.testing.assert_allclose(first.plan_input, first.commanded)
    # by hand: the controller's model at the measured state and the previous input (zero)
    lcs = linearize(build_scene(l=spec.model_l, config=config), first.state, np.zeros(2),
                    config.mpc.dt)
    u = first.plan_input
    lam = lemke(lcs.F, lcs.E @ first.state + lcs.H @ u + lcs.c).z
    assert lam is not None
    hand = lcs.A @ first.state + lcs.B @ u + lcs.D @ lam + lcs.d
    np.testing.assert_allclose(first.lcs_next, hand, rtol=1e-9, atol=1e-9)
    frame = records_frame(trajectory, records, build_scene(config=config))
    assert frame["plan_lcs_error"][0] == pytest.approx(np.linalg.norm(first.plan_next - hand))
    assert frame["plan_plant_error"][0] == pytest.approx(
        np.linalg.norm(first.plan_next - trajectory.states[1]))
    errors = [np.linalg.norm(r.plan_next - r.lcs_next) for r in records
              if r.plan_next is not None and r.lcs_next is not None]
    assert outcome.metrics is not None
    assert outcome.metrics.plan_lcs_error_max == pytest.approx(max(errors))
    assert outcome.metrics.plan_lcs_error_median == pytest.approx(float(np.median(errors)))
    # the force limit is inside the controller (bounds of its QP step): the simulator's clip
    # never acts (before the limits were in the QP the first plan asked for about 34 N)
    assert outcome.metrics.clipped_inputs == 0 and np.abs(first.commanded).max() <= 30 + 1e-6
    assert not outcome.success  # 0.1 s is too short to succeed


H = 0.001  # plant step


def plant_record(**changes: object) -> PlantContact:
    """Per period (60), what the plant did between the recorded states of :func:`signals`:
    a strike at 0.058 s (plant state 58, in period 1) at 3.4 m/s, 13 ms on the cube (states
    58-70), off it until the recorded touch (period 9 ends at state 10), then as recorded:
    touching throughout periods 9-28 and 39-59, never in 29-38."""
    n = N - 1
    contact = np.zeros(n)
    contact[1] = 13 * H
    contact[9:29] = contact[39:] = 0.05
    touch = np.full(n, np.nan)
    touch[1] = 0.058
    touch[9:29] = np.arange(9, 29) * DT + H
    touch[39:] = np.arange(39, n) * DT + H
    speed = np.full(n, np.nan)
    speed[np.isfinite(touch)] = 0.1
    speed[1] = 3.4
    min_gap = np.where(np.isfinite(touch), 0.0, 0.05)
    min_gap[1] = -0.003
    base = PlantContact(plant_step=H, contact_gap=0.002, away_gap=0.02, min_gap=min_gap,
                        min_height=np.full(n, 0.1), contact_time=contact,
                        away_time=0.05 - contact, touch_time=touch, touch_speed=speed)
    return replace(base, **changes)


def test_contact_between_recorded_states_is_measured_at_the_plant_rate() -> None:
    m = physical_metrics(signals(plant=plant_record()), TARGET, BAND)
    old = physical_metrics(signals(), TARGET, BAND)
    assert old.first_touch_time == pytest.approx(0.5) and old.impact_speed == pytest.approx(0.7)
    assert m.first_touch_time == pytest.approx(0.058) and m.impact_speed == pytest.approx(3.4)
    # after state 58: 12 more in the strike, 20 + 21 full periods on the cube
    assert m.contact_time == pytest.approx((12 + 41 * 50) * H)
    assert m.free_time == pytest.approx(3.0 - 0.058 - (12 + 41 * 50) * H)
    assert m.contact_step == H
    assert m.max_cube_penetration == pytest.approx(0.003) and m.success


def test_penetration_between_recorded_states_fails_the_success_rule() -> None:
    record = plant_record()
    deep = record.min_gap.copy()
    deep[20] = -0.006  # 6 mm into the cube between two recorded states
    m = physical_metrics(signals(plant=replace(record, min_gap=deep)), TARGET, BAND)
    assert m.max_cube_penetration == pytest.approx(0.006) and not m.success
    low = record.min_height.copy()
    low[40] = -0.0055
    m = physical_metrics(signals(plant=replace(record, min_height=low)), TARGET, BAND)
    assert m.max_table_penetration == pytest.approx(0.0055) and not m.success
    assert physical_metrics(signals(), TARGET, BAND).success  # the samples saw neither


def test_plant_rate_contact_when_the_run_starts_touching() -> None:
    base = signals()
    gap = base.ball_gap.copy()
    gap[0] = 0.0
    record = plant_record()
    contact = record.contact_time.copy()
    contact[0] = 0.05
    m = physical_metrics(replace(base, ball_gap=gap, plant=replace(record, contact_time=contact)),
                         TARGET, BAND)
    assert m.first_touch_time == 0.0 and m.impact_speed == base.ball_speed[0]
    assert m.contact_time == pytest.approx((50 + 13 + 41 * 50) * H)
    assert m.contact_time + m.free_time == pytest.approx(3.0)


def test_plant_record_arrays_are_checked() -> None:
    with pytest.raises(ValueError, match="one length"):
        plant_record(min_gap=np.zeros(3))
    # the cube's height: both arrays or neither (a run stored before they were measured)
    assert plant_record().columns == PlantContact.COLUMNS
    both = plant_record(cube_clearance=np.zeros(N - 1), cube_air_time=np.zeros(N - 1))
    assert both.columns == PlantContact.COLUMNS + PlantContact.CUBE_COLUMNS
    with pytest.raises(ValueError, match="cube arrays"):
        plant_record(cube_clearance=np.zeros(N - 1))
