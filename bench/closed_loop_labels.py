"""What happened in a closed-loop run, as a label derived from its physical metrics.

A small decision table (docs/closed_loop.md), checked **in this order**; the first row that
fires is the label (thresholds in :class:`LabelRules`):

================  =======================================================================
label             rule
================  =======================================================================
success           the success rule of :mod:`bench.closed_loop_metrics` (gentle or not)
no motion         peak angle below ``still_angle``, the cube's far corner moved less than
                  ``still_shift`` and the ball never rose above the cube's top face
backing off       before the cube first tips past ``still_angle``, the ball retreats more
                  than ``back_off`` in -x from its start
strike-topple     the peak passed the balance angle and the run ends with the cube still
                  beyond it (fallen onto its face)
over-the-top      the ball rose above the cube's top face (cube frame), or the far corner
sliding           slipped ``pivot_slip`` or more
whack, then       the peak exceeded ``whack_fraction * theta*``, the ball was off the cube
contact lost      for at least ``lost_time`` after the first touch, and the run ends at
                  least ``fall_back`` below the peak
slow drift        the run ends outside the band but within ``drift_band`` of the target,
                  without passing the balance angle
unlabelled        none of the above (never forced into a mode)
================  =======================================================================

Unlike the end-time failure modes of :func:`bench.closed_loop.label_failure_mode`, these read
the whole run: a strike that throws the cube past pi/4 and lets it fall over is a
strike-topple, however far the cube then slides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from c3bench.bench.closed_loop_metrics import PhysicalMetrics, RunSignals

PHYSICAL_LABELS: tuple[str, ...] = (
    "success", "no motion", "backing off", "strike-topple", "over-the-top sliding",
    "whack, then contact lost", "slow drift", "unlabelled")
"""The labels, in the order their rules are checked."""


@dataclass(frozen=True)
class LabelRules:
    """Thresholds of the decision table (module docstring); lengths in m, angles in rad,
    times in s."""

    still_angle: float = 0.05
    still_shift: float = 0.01
    back_off: float = 0.03
    pivot_slip: float = 0.03
    whack_fraction: float = 0.5
    lost_time: float = 0.2
    fall_back: float = 0.1
    drift_band: float = 0.3


def physical_label(metrics: PhysicalMetrics, signals: RunSignals, target: float,
                   rules: LabelRules | None = None) -> tuple[str, str]:
    """``(label, reason)`` of a run from its metrics and signals (module docstring)."""
    rules = rules or LabelRules()
    angles = signals.angles
    final = float(angles[-1])
    pivot = signals.pivot_x
    slip = float(np.max(np.abs(pivot - pivot[0]))) if pivot.size else 0.0
    if metrics.success:
        kind = "gentle" if metrics.gentle_success else "past the balance angle"
        return "success", f"held {metrics.hold_time:.2f} s ({kind})"
    above = bool(np.any(signals.ball_above_top)) if signals.ball_above_top.size else False
    if metrics.peak_angle < rules.still_angle and slip < rules.still_shift and not above:
        return "no motion", f"peak {metrics.peak_angle:.3f} rad, corner moved {slip:.3f} m"
    ball_x = signals.states[:, 3]
    tipped = np.flatnonzero(angles > rules.still_angle)
    before = ball_x[: int(tipped[0]) + 1 if tipped.size else len(ball_x)]
    retreat = float(ball_x[0] - np.min(before))
    if retreat > rules.back_off:
        return "backing off", f"ball retreated {retreat:.3f} m before the cube tipped"
    if metrics.passed_balance and final > metrics.balance_angle:
        return "strike-topple", (f"peak {metrics.peak_angle:.2f} rad past the balance angle "
                                 f"{metrics.balance_angle:.2f}, ends at {final:.2f} rad")
    if above or slip >= rules.pivot_slip:
        return "over-the-top sliding", ("ball above the top face" if above
                                         else f"far corner slipped {slip:.3f} m")
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
