"""What happened in a closed-loop run, as a label derived from its physical metrics.

A small decision table (docs/closed_loop.md), checked **in this order**; the first row that
fires is the label (thresholds in :class:`LabelRules`, the pivot slip in
:class:`~bench.closed_loop_metrics.SuccessRules`):

================  =======================================================================
label             rule
================  =======================================================================
success           the success rule of :mod:`bench.closed_loop_metrics` (gentle or not)
no motion         peak angle below ``still_angle``, the cube's far corner moved less than
                  ``still_shift`` and the ball never went over the top (below)
backing off       before the cube first tips past ``still_angle``, the ball retreats more
                  than ``back_off`` in -x from its start
thrown /          the cube turned past ``tumble_angle`` (either way; angles are unwrapped)
tumbled           or was airborne (its lowest point more than ``air_gap`` above the table)
                  for ``air_time`` or longer in all
strike-topple     the peak passed the balance angle and the run ends with the cube still
                  beyond it (fallen onto its face)
over-the-top      the ball touched the cube (a measured touch, or the cube tilted past
sliding           ``nudge_angle``) and, at some recorded state, its centre was over the top
                  face (cube frame: above the face's plane, within its extent)
cube slid         the far bottom corner (the pivot) slid ``SuccessRules.pivot_slip`` or
                  more along the table
whack, then       the peak exceeded ``whack_fraction * theta*``, the ball was off the cube
contact lost      for at least ``lost_time`` after the first touch, and the run ends at
                  least ``fall_back`` below the peak
slow drift        the run ends outside the band but within ``drift_band`` of the target,
                  without passing the balance angle
unlabelled        none of the above (never forced into a mode)
================  =======================================================================

Unlike the end-time failure modes of :func:`bench.closed_loop.label_failure_mode`, these read
the whole run: a strike that throws the cube past pi/4 and lets it fall over is a
strike-topple, however far the cube then slides, and one that sends it flying or rolling over
several faces is thrown / tumbled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c3bench.bench.closed_loop_metrics import PhysicalMetrics, RunSignals, SuccessRules

PHYSICAL_LABELS: tuple[str, ...] = (
    "success", "no motion", "backing off", "thrown / tumbled", "strike-topple",
    "over-the-top sliding", "cube slid", "whack, then contact lost", "slow drift",
    "unlabelled")
"""The labels, in the order their rules are checked."""


@dataclass(frozen=True)
class LabelRules:
    """Thresholds of the decision table (module docstring); lengths in m, angles in rad,
    times in s. The pivot slip is the success rule's
    (:attr:`~bench.closed_loop_metrics.SuccessRules.pivot_slip`), not repeated here.

    Attributes
    ----------
    nudge_angle
        0.005 rad: a cube tilted this far was touched, even when no touch was measured (the
        recorded states of a run stored without the plant-rate contact can miss a touch of a
        few milliseconds, not its effect); a cube left alone stays at 0 (1e-19 rad).
    tumble_angle
        ``pi/2 + pi/4``: a cube fallen onto its face lies at pi/2, and pi/4 further its
        centre of mass passes over the next edge, so beyond this angle it rolls onto yet
        another face: tumbled over, not tipped (nor merely toppled).
    air_gap
        2 cm: the plant's soft contact lets a resting cube sink or rise by millimetres, and a
        cube shoved along on its face hops (22 mm at one recorded state in the person-labelled
        strike-topple of ``tests/fixtures/closed_loop/``); only a lowest point higher than
        this is off the table.
    air_time
        0.15 s, in all: staying more than ``air_gap`` up that long takes a launch to at
        least ~4.8 cm (free fall spends ``2 sqrt(2 (h - air_gap) / g)`` above ``air_gap``
        when it peaks at ``h``), a throw; a 22 mm hop spends at most 0.04 s there. The
        thrown randomized trial of the audit (trial 4, seed 0, fast C3+ at ``l = 0.30``)
        spends 0.24 s above 2 cm (0.75 s above 2 mm, up to 10 cm).
    """

    still_angle: float = 0.05
    still_shift: float = 0.01
    back_off: float = 0.03
    whack_fraction: float = 0.5
    lost_time: float = 0.2
    fall_back: float = 0.1
    drift_band: float = 0.3
    nudge_angle: float = 0.005
    tumble_angle: float = 0.75 * math.pi
    air_gap: float = 0.02
    air_time: float = 0.15


def airborne(signals: RunSignals, rules: LabelRules | None = None) -> tuple[float, float]:
    """``(time, height)``: how long the cube's lowest point was more than ``rules.air_gap``
    above the table (s, in all) and the highest it got (m; NaN when not measured).

    At the plant's rate when :attr:`RunSignals.plant` measured it at that threshold, else from
    the recorded states (each but the last standing for one control period).
    """
    rules = rules or LabelRules()
    plant = signals.plant
    if plant is not None and plant.cube_air_time.size and \
            math.isclose(plant.air_gap, rules.air_gap, rel_tol=1e-12):
        time = plant.count(float(np.sum(plant.cube_air_time))) * plant.plant_step
        return time, float(np.max(plant.cube_clearance, initial=-math.inf))
    clearance = signals.cube_clearance
    if not clearance.size:
        return 0.0, math.nan
    periods = np.diff(signals.times)
    time = float(np.sum(periods[clearance[:-1] > rules.air_gap]))
    return time, float(np.max(clearance))


def _touched(metrics: PhysicalMetrics, signals: RunSignals, rules: LabelRules) -> bool:
    """Whether the ball touched the cube: a measured touch, or the cube tilted past
    ``rules.nudge_angle`` (nothing else moves it)."""
    return math.isfinite(metrics.first_touch_time) or \
        float(np.max(np.abs(signals.angles))) > rules.nudge_angle


def physical_label(metrics: PhysicalMetrics, signals: RunSignals, target: float,
                   rules: LabelRules | None = None,
                   success_rules: SuccessRules | None = None) -> tuple[str, str]:
    """``(label, reason)`` of a run from its metrics and signals (module docstring);
    ``success_rules``: the rules ``metrics`` were computed under (their pivot slip)."""
    rules = rules or LabelRules()
    slip_limit = (success_rules or SuccessRules()).pivot_slip
    angles = signals.angles
    final = float(angles[-1])
    slip = metrics.pivot_slip if math.isfinite(metrics.pivot_slip) else 0.0
    if metrics.success:
        kind = "gentle" if metrics.gentle_success else "past the balance angle"
        return "success", f"held {metrics.hold_time:.2f} s ({kind})"
    touched = _touched(metrics, signals, rules)
    over = touched and bool(np.any(signals.ball_above_top))  # over the top face, once touched
    if metrics.peak_angle < rules.still_angle and slip < rules.still_shift and not over:
        touch = "" if touched else ", ball never touched it"
        return "no motion", (f"peak {metrics.peak_angle:.3f} rad, corner moved {slip:.3f} m"
                             + touch)
    ball_x = signals.states[:, 3]
    tipped = np.flatnonzero(angles > rules.still_angle)
    before = ball_x[: int(tipped[0]) + 1 if tipped.size else len(ball_x)]
    retreat = float(ball_x[0] - np.min(before))
    if retreat > rules.back_off:
        return "backing off", f"ball retreated {retreat:.3f} m before the cube tipped"
    turned = float(np.max(np.abs(angles)))
    air, height = airborne(signals, rules)
    if turned > rules.tumble_angle or air >= rules.air_time:
        shift = float(abs(signals.states[-1, 0] - signals.states[0, 0]))
        flight = f", up to {1e3 * height:.0f} mm" if air and math.isfinite(height) else ""
        return "thrown / tumbled", (
            f"turned up to {turned:.2f} rad ({turned / (math.pi / 2):.1f} quarter turns), "
            f"airborne {air:.2f} s{flight}, cube moved {shift:.2f} m, ends at {final:.2f} rad")
    if metrics.passed_balance and final > metrics.balance_angle:
        return "strike-topple", (f"peak {metrics.peak_angle:.2f} rad past the balance angle "
                                 f"{metrics.balance_angle:.2f}, ends at {final:.2f} rad")
    if over:
        return "over-the-top sliding", ("ball over the top face of the cube it touched "
                                         f"(peak {metrics.peak_angle:.3f} rad)")
    if slip >= slip_limit:
        return "cube slid", (f"the far bottom edge slid {100 * slip:.1f} cm along the table "
                             f"(limit {100 * slip_limit:.1f} cm), ends at {final:.2f} rad")
    if metrics.peak_angle > rules.whack_fraction * target and \
            metrics.free_time >= rules.lost_time and \
            final < metrics.peak_angle - rules.fall_back:
        return "whack, then contact lost", (
            f"peak {metrics.peak_angle:.2f} rad, off the cube {metrics.free_time:.2f} s, "
            f"ends at {final:.2f} rad")
    if abs(final - target) <= rules.drift_band and not metrics.passed_balance:
        return "slow drift", f"ends {final - target:+.3f} rad from the target"
    error = final - target
    return "unlabelled", (f"ends {error:+.3f} rad from the target, peak "
                          f"{metrics.peak_angle:.2f} rad" if math.isfinite(error) else "")
