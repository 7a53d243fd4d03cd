"""The report of a closed-loop suite or sweep.

* :func:`write_trials_report` (``closed-loop-suite``: configurations x randomized trials):
  per configuration the success and gentle-success rates with Wilson 95 % intervals and the
  metric medians, the success-rate figure, the success-vs-``l`` curve, the metric
  distributions (:mod:`bench.closed_loop_figures`) and the claims paragraph (Newcombe's
  interval for each difference of rates).
* :func:`write_report` (``sweep``, and any list of single cases): one row per run (success,
  gentle success, peak angle, hold time, clipped inputs, plan consistency, failure labels,
  step times), the outcome map of a sweep (success or label per combination), and
  ``figures/`` (angle error bars, angle
  trajectories, step-time distributions, an animation of a successful run).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from c3bench.bench.closed_loop import render_run
from c3bench.bench.closed_loop_figures import (
    ConfigurationResult,
    plot_distributions,
    plot_l_curve,
    plot_success_rates,
)
from c3bench.bench.closed_loop_metrics import SuccessRules
from c3bench.bench.trials import TrialSummary, newcombe_interval, trial_summary
from c3bench.problems.config import Config, load_config
from c3bench.problems.errors import RenderUnavailable
from c3bench.problems.instance import atomic_write_bytes
from c3bench.problems.scene import build_scene

if TYPE_CHECKING:
    from c3bench.bench.closed_loop_suite import ClosedLoopSuite, Comparison, SuiteRun


def _fmt(value: Any, digits: int = 3) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        return f"{value:.{digits}g}"
    return str(value)


def _table(frame: pd.DataFrame, columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for _, row in frame.iterrows():
        lines.append("| " + " | ".join(_fmt(row.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


def _axes(size: tuple[float, float]) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=size)


def _save(figure: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def cell_states(directory: Path, name: str) -> np.ndarray | None:
    """The plant states (one per control step) a finished case stored, or ``None``."""
    path = directory / "cells" / name / "states.npy"
    return np.load(path) if path.exists() else None


def plot_error_bars(frame: pd.DataFrame, path: Path, target: float) -> Path:
    """Cube angle error at the end per configuration, coloured by success and annotated with
    the run's label (its failure mode ``mN`` for rows without one)."""
    figure, axis = _axes((max(6.0, 0.55 * len(frame)), 4.2))
    errors = frame["angle_error"].fillna(target).to_numpy(dtype=float)
    colours = ["tab:green" if ok else "tab:red" for ok in frame["success"].fillna(False)]
    axis.bar(range(len(frame)), errors, color=colours)
    labels = frame["label"] if "label" in frame else pd.Series([""] * len(frame))
    for index, (error, mode, label) in enumerate(zip(errors, frame["failure_mode"], labels,
                                                     strict=True)):
        text = label if isinstance(label, str) and label else \
            f"m{int(mode)}" if mode == mode else ""
        axis.text(index, error, text, ha="center", va="bottom", fontsize=6, rotation=90)
    axis.axhline(load_config().mpc.success_tolerance, color="k", linestyle="--", linewidth=0.8,
                 label="success tolerance")
    axis.set_xticks(range(len(frame)))
    axis.set_xticklabels(frame["case"], rotation=60, ha="right", fontsize=7)
    axis.set_ylabel("|theta(2 s) - theta*| (rad)")
    axis.set_title("Cube angle error after the run (green: success; text: the label)")
    axis.legend(fontsize=8)
    return _save(figure, path)


def plot_angles(directory: Path, frame: pd.DataFrame, path: Path, target: float) -> Path:
    """Cube angle against time for every case (from the stored states)."""
    figure, axis = _axes((8, 4.5))
    scene = build_scene()
    for row in frame.itertuples():
        states = cell_states(directory, row.case)
        if states is None:
            continue
        times = np.arange(len(states)) * float(row.dt)
        axis.plot(times, [scene.cube_angle(x) for x in states], linewidth=1.2,
                  label=row.case)
    axis.axhline(target, color="k", linestyle="--", linewidth=0.8, label="target")
    axis.set_xlabel("time (s)")
    axis.set_ylabel("cube angle theta (rad)")
    axis.set_title("Cube angle trajectories")
    axis.legend(fontsize=6, ncol=2)
    return _save(figure, path)


def plot_step_times(directory: Path, frame: pd.DataFrame, path: Path) -> Path:
    """Distribution of the control-step wall time per case (log scale)."""
    data, labels = [], []
    for name in frame["case"]:
        steps_path = directory / "cells" / name / "steps.parquet"
        if not steps_path.exists():
            continue
        steps = pd.read_parquet(steps_path)
        data.append(1e3 * steps["wall_time"].to_numpy())
        labels.append(name)
    figure, axis = _axes((max(6.0, 0.55 * len(labels)), 4.2))
    if data:
        axis.boxplot(data, showfliers=True)
        axis.set_xticks(range(1, len(labels) + 1))
        axis.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    axis.set_yscale("log")
    axis.axhline(60.0, color="tab:red", linestyle="--", linewidth=0.8,
                 label="seed: 60 ms per step")
    axis.axhline(50.0, color="k", linestyle=":", linewidth=0.8, label="control period 50 ms")
    axis.set_ylabel("control-step wall time (ms)")
    axis.set_title("Control-step time (LCS build + controller), one BLAS thread")
    axis.legend(fontsize=8)
    return _save(figure, path)


def _pivot_clause() -> str:
    """The pivot-slip part of the success rule, as both reports state it."""
    return ("the cube's far bottom edge (the pivot) slid less than "
            f"{100 * SuccessRules().pivot_slip:g} cm along the table")


def write_report(run: SuiteRun, title: str, render: bool = True) -> Path:
    """``report.md`` and ``figures/*.png`` of a closed-loop suite or sweep."""
    directory = run.directory
    figures = directory / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    frame = pd.DataFrame(run.rows)
    config = load_config()
    target = config.mpc.target_angle
    lines = [f"# c3bench closed loop: {title}", "",
             f"Plant: MuJoCo, true cube l = {config.scene.cube_side} m, target angle "
             f"{target} rad. Success: a run of at least 3 s whose angle stayed within "
             f"{config.mpc.success_tolerance} rad of the target for its last second (the "
             f"case's hold time), {_pivot_clause()}, the ball never more "
             "than 5 mm into the cube or the table; gentle: a success that never passed "
             "the balance angle pi/4 (docs/closed_loop.md). Failure mode 0 is the older "
             "rule (angle within the tolerance at the end, no pivot slip). "
             "Control-step times are wall-clock on this machine (2 cores, one BLAS thread), "
             "LCS build included; the reference study reported 0.06 s per step "
             "(control period 0.05 s).", ""]
    columns = ["case", "success", "gentle_success", "label", "peak_angle", "hold_time",
               "pivot_slip", "clipped_inputs", "plan_lcs_angle_median", "angle_error",
               "final_angle", "failure_mode", "failure_label", "median_step_time", "p95_step_time",
               "median_lcs_time", "fallback_count", "nan_count"]
    shown = frame.copy()
    for column in ("median_step_time", "p95_step_time", "median_lcs_time"):
        if column in shown:
            shown[column] = shown[column] * 1e3
    lines += ["## Outcomes", "",
              "Times in ms; angles in rad (peak angle, plan vs LCS angle gap: median over "
              "the steps); hold time in s; pivot slip in m; failure modes (the older "
              "end-time rule): 0 angle in band at the end, "
              "1 fast sliding past the edge, 2 backing off first, 3 whack then contact lost, "
              "4 no motion, 5 unlabelled, -1 the run itself failed (see `error`).", "",
              _table(shown, [c for c in columns if c in shown]), ""]
    errors = frame[frame.get("error", pd.Series([""] * len(frame))).fillna("") != ""] \
        if "error" in frame else frame.iloc[0:0]
    if len(errors):
        lines += ["Runs that produced no trajectory:", "",
                  _table(errors, ["case", "error"]), ""]
    if "sweep" in set(frame.get("group", [])):
        lines += ["## Outcome map", "", sweep_grid(frame), ""]
    valid = frame[frame.get("failure_mode", -1) != -1] if "failure_mode" in frame else frame
    if len(valid):
        plot_error_bars(valid, figures / "closed_loop_error.png", target)
        plot_angles(directory, valid, figures / "closed_loop_angles.png", target)
        plot_step_times(directory, valid, figures / "closed_loop_step_time.png")
        lines += ["## Figures", "",
                  "![error](figures/closed_loop_error.png)", "",
                  "*Cube angle error at the end of each run (rad); green bars succeeded, "
                  "the text gives the run's label.*", "",
                  "![angles](figures/closed_loop_angles.png)", "",
                  "*Cube angle (rad) against time (s) for every run; dashed: the target.*", "",
                  "![times](figures/closed_loop_step_time.png)", "",
                  "*Control-step wall time (ms, log scale) per run: LCS build plus the "
                  "controller's ADMM; dashed lines: the reference study's 60 ms and the "
                  "50 ms period.*", ""]
    if render:
        lines += _animation_section(directory, valid, config)
    path = directory / "report.md"
    atomic_write_bytes(path, ("\n".join(lines).rstrip() + "\n").encode())
    return path


def _animation_section(directory: Path, frame: pd.DataFrame, config: Config) -> list[str]:
    successes = frame[frame.get("success", False) == True]  # noqa: E712 - pandas mask
    if not len(successes):
        return ["## Animation", "", "No successful run to animate.", ""]
    name = str(successes.iloc[0]["case"])
    states = cell_states(directory, name)
    if states is None:
        return ["## Animation", "", f"No stored states for `{name}`.", ""]
    dt = float(successes.iloc[0].get("dt") or config.mpc.dt)
    try:
        render_run(states, build_scene(config=config),
                   directory / "figures" / "closed_loop_success.gif", dt)
    except RenderUnavailable as error:
        return ["## Animation", "", f"Not rendered: {error}", ""]
    return ["## Animation", "", "![run](figures/closed_loop_success.gif)", "",
            f"*`{name}`: one successful run, one frame per control step ({dt:g} s).*", ""]


def _outcome_cell(row: pd.Series) -> str:
    """A run's outcome as the outcomes table gives it: ``success`` (``gentle success``) when
    :mod:`bench.closed_loop_metrics`' rule holds, else its label (:mod:`bench.closed_loop_labels`;
    ``error`` when the run itself failed), with the angle error at the end."""
    error, label = row.get("error", ""), row.get("label", "")
    if (isinstance(error, str) and error) or label == "error":
        return "error"
    success = row.get("success", False)
    if isinstance(success, bool | np.bool_) and bool(success):
        text = "gentle success" if bool(row.get("gentle_success", False)) else "success"
    else:
        text = label if isinstance(label, str) and label else "failure"
    angle = row.get("angle_error", math.nan)
    if isinstance(angle, int | float) and math.isfinite(angle):
        text += f" ({angle:.2f})"
    return text


def sweep_grid(frame: pd.DataFrame) -> str:
    """Markdown grid of the runs' outcomes (``success`` and ``label``, as in the outcomes
    table): rows ``dt / rho schedule``, columns ``Q_box / l``."""
    sweep = frame[frame["group"] == "sweep"]
    rows = sorted({(r.dt, r.rho_schedule) for r in sweep.itertuples()})
    cols = sorted({(r.q_cube_pose, r.model_l) for r in sweep.itertuples()})
    header = "| dt / rho schedule | " + " | ".join(f"Q_box {q:g}, l {side:g}"
                                                   for q, side in cols) + " |"
    lines = [header, "|" + "---|" * (len(cols) + 1)]
    for dt, schedule in rows:
        cells = []
        for q, side in cols:
            match = sweep[(sweep.dt == dt) & (sweep.rho_schedule == schedule)
                          & (sweep.q_cube_pose == q) & (sweep.model_l == side)]
            cells.append(_outcome_cell(match.iloc[0]) if len(match) else "-")
        lines.append(f"| {dt:g} / {schedule} | " + " | ".join(cells) + " |")
    return ("Each cell: the run's outcome, success (gentle or not) or what happened instead "
            "(the label of docs/closed_loop.md), with the angle error at the end (rad).\n\n"
            + "\n".join(lines))


# --- randomized-trial suites: outcomes per configuration with intervals ----------------------
def _percent(low: float, high: float) -> str:
    return f"{100 * low:.0f}-{100 * high:.0f} %"


def _rate_cell(successes: int, n: int, interval: tuple[float, float]) -> str:
    """``14/20 (70 %; 48-85 %)``: count, share and Wilson 95 % interval."""
    if not n:
        return "0/0"
    return f"{successes}/{n} ({100 * successes / n:.0f} %; {_percent(*interval)})"


def configuration_results(frame: pd.DataFrame, suite: ClosedLoopSuite
                          ) -> list[ConfigurationResult]:
    """One :class:`ConfigurationResult` per configuration of ``suite``, in its order (an
    unrun configuration has ``n = 0``)."""
    out = []
    for configuration in suite.configurations:
        rows = frame[frame["config"] == configuration.name] if "config" in frame \
            else frame.iloc[0:0]
        title = configuration.title + "".join(f" = {also}" for also in configuration.also)
        out.append(ConfigurationResult(configuration.name, title, str(configuration.group),
                                       trial_summary(rows.to_dict("records")), rows))
    return out


def _median_cell(summary: TrialSummary, column: str, scale: float = 1.0,
                 digits: str = ".3g") -> str:
    value = summary.medians.get(column, math.nan)
    return "-" if math.isnan(value) else format(scale * value, digits)


def _load_cell(rows: pd.DataFrame) -> str:
    loads = pd.to_numeric(rows.get("load_average", pd.Series(dtype=float)), errors="coerce")
    loads = loads[np.isfinite(loads)]
    return f"{loads.median():.1f}" if len(loads) else "-"


def outcome_table(results: Sequence[ConfigurationResult]) -> str:
    """The per-configuration table of a trials suite (markdown)."""
    header = ["configuration", "group", "n", "success (95 % CI)", "gentle (95 % CI)",
              "median peak angle (rad)", "passed balance", "median hold (s)",
              "median step (ms)", "load", "labels"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for result in results:
        s = result.summary
        unavailable = s.n and s.errors == s.n
        labels = ", ".join(f"{label} {count}" for label, count in s.labels)
        if unavailable:
            labels = "unavailable: " + str(result.rows["error"].iloc[0]).replace("|", "/")
        lines.append("| " + " | ".join([
            result.title, result.group, str(s.n),
            _rate_cell(s.successes, s.n, s.success_interval),
            _rate_cell(s.gentle, s.n, s.gentle_interval),
            _median_cell(s, "peak_angle", digits=".2f"),
            f"{100 * s.passed_balance / s.n:.0f} %" if s.n else "-",
            _median_cell(s, "hold_time", digits=".2f"),
            _median_cell(s, "median_step_time", 1e3, ".3g"),
            _load_cell(result.rows), labels]) + " |")
    return "\n".join(lines)


def _l_curve_lines(results: Sequence[ConfigurationResult], suite: ClosedLoopSuite,
                   figures: Path, true_side: float) -> list[str]:
    by_name = {r.name: r for r in results}
    points = [(side, by_name[name].summary) for side, name in suite.l_curve
              if name in by_name and by_name[name].summary.n]
    if not points:
        return ["## Success against the model's cube side", "",
                "No episode of the curve's configurations was run.", ""]
    plot_l_curve(points, figures / "closed_loop_l_curve.png", true_side,
                 "fast C3+, one model, feedback")
    rows = ["| model l (m) | success (95 % CI) |", "|---|---|"]
    rows += [f"| {side:g} | {_rate_cell(s.successes, s.n, s.success_interval)} |"
             for side, s in points]
    return ["## Success against the model's cube side", "",
            "Fast C3+ with one model and low-level feedback (the ablation's `no-samples`), "
            "its model's side `l` varied; the plants' sides are drawn from U[0.28, 0.32] m.",
            "", *rows, "", "![l curve](figures/closed_loop_l_curve.png)", "",
            "*Success rate (dots, `k/n` above) against the model's cube side (m), Wilson 95 % "
            "band shaded; dashed: the nominal true side.*", ""]


def _verdict(interval: tuple[float, float]) -> str:
    if interval[0] > 0:
        return "better with the choice"
    if interval[1] < 0:
        return "worse with the choice"
    return "no difference resolved"


def _overlap(a: TrialSummary, b: TrialSummary) -> bool:
    return not (a.success_interval[0] > b.success_interval[1]
                or b.success_interval[0] > a.success_interval[1])


def claims_lines(results: Sequence[ConfigurationResult],
                 comparisons: Sequence[Comparison]) -> list[str]:
    """The auto-written claims paragraph: each comparison's success rates, the difference
    with Newcombe's hybrid score 95 % interval, whether the two Wilson intervals overlap, and
    per claim a verdict (it survives when every comparison's interval lies above 0)."""
    by_name = {r.name: r.summary for r in results}
    lines = ["## The seed's claims under randomized trials", "",
             "Each claim is tested on pairs of configurations that differ in that choice "
             "alone. The test is Newcombe's hybrid score 95 % interval for the difference of "
             "the two success rates (R. G. Newcombe, Stat. Med. 17 (1998) 873-890, method "
             "10): a difference is resolved when its interval excludes 0. Overlapping Wilson "
             "intervals are reported too, but they are not the test (two rates can differ "
             "significantly although their intervals overlap). Both configurations of a "
             "pair run the same trial draws; the interval treats them as independent "
             "samples, which is conservative for paired episodes.", ""]
    verdicts: dict[str, list[str]] = {}
    for comparison in comparisons:
        a, b = by_name.get(comparison.with_choice), by_name.get(comparison.without)
        if a is None or b is None or not a.n or not b.n:
            continue
        interval = newcombe_interval(a.successes, a.n, b.successes, b.n)
        verdict = _verdict(interval)
        verdicts.setdefault(str(comparison.claim), []).append(verdict)
        lines.append(
            f"* **{comparison.claim}** ({comparison.setting}): "
            f"{_rate_cell(a.successes, a.n, a.success_interval)} vs "
            f"{_rate_cell(b.successes, b.n, b.success_interval)}; difference "
            f"{100 * (a.rate - b.rate):+.0f} points, 95 % CI {100 * interval[0]:+.0f} to "
            f"{100 * interval[1]:+.0f}: {verdict} (Wilson intervals "
            f"{'overlap' if _overlap(a, b) else 'do not overlap'}).")
    if not verdicts:
        return [*lines, "No comparison has episodes on both sides.", ""]
    lines.append("")
    for claim, found in verdicts.items():
        if all(v == "better with the choice" for v in found):
            summary = "survives: better in every comparison"
        elif "worse with the choice" in found:
            summary = "contradicted: worse in at least one comparison"
        elif "better with the choice" in found:
            summary = "partly: better in some comparisons, unresolved in others"
        else:
            summary = "not resolved at this number of trials"
        lines.append(f"* {claim}: {summary}.")
    return [*lines, ""]


def _load_sentence(frame: pd.DataFrame) -> str:
    loads = pd.to_numeric(frame.get("load_average", pd.Series(dtype=float)), errors="coerce")
    loads = loads[np.isfinite(loads)]
    cores = os.cpu_count() or 0
    if not len(loads):
        return f"Load average not recorded ({cores} cores here)."
    return (f"Step times are wall-clock; the 1-minute load average at the end of the "
            f"episodes was {loads.median():.1f} (median; {loads.min():.1f}-{loads.max():.1f}) "
            f"on {cores} cores: compare configurations run under similar load only.")


def write_trials_report(run: SuiteRun, suite: ClosedLoopSuite, trials: int,
                        render: bool = True) -> Path:
    """``report.md`` and figures of a randomized-trials suite (:class:`ClosedLoopSuite`):
    the per-configuration table with Wilson intervals, the success-rate figure, the
    success-vs-``l`` curve, the metric distributions and the claims paragraph."""
    directory = run.directory
    figures = directory / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    frame = pd.DataFrame(run.rows)
    config = load_config()
    results = configuration_results(frame, suite)
    drawn = [r for r in results if r.summary.n]
    lines = [f"# c3bench closed loop: suite `{suite.name}`", "",
             f"{len(suite.configurations)} configurations x {trials} randomized trials "
             f"(seed {suite.seed}; {suite.duration:g} s episodes): ball start +-3 cm, cube "
             "mass +-20 %, friction +-25 %, plant cube side U[0.28, 0.32] m, a fresh model "
             "seed per trial for the robust controllers (docs/closed_loop.md). Success: the "
             f"angle within {config.mpc.success_tolerance} rad of the target "
             f"{config.mpc.target_angle} rad for the last {suite.hold_time:g} s, "
             f"{_pivot_clause()}, and no "
             "penetration deeper than 5 mm; gentle: a success that never passed the balance "
             "angle pi/4. Rates with Wilson score 95 % intervals (E. B. Wilson, JASA 22 "
             "(1927) 209-212). " + _load_sentence(frame), ""]
    if run.missing:
        lines += [f"**{run.missing} episodes missing** ({'; '.join(run.missing_reasons)}): "
                  "run the suite again to complete them.", ""]
    lines += ["## Outcomes per configuration", "", outcome_table(results), "",
              "Peak angle, hold time and step time: medians over the episodes; passed "
              "balance: share of episodes whose peak passed pi/4; load: median load average "
              "at the end of the episodes; `a = b` in a name: one controller playing two "
              "roles, run once.", ""]
    if drawn:
        plot_success_rates(drawn, figures / "closed_loop_success_rates.png")
        plot_distributions(drawn, figures / "closed_loop_distributions.png")
        lines += ["![success rates](figures/closed_loop_success_rates.png)", "",
                  "*Success rate per configuration with its Wilson 95 % interval, coloured by "
                  "group; `k/n` at the right.*", ""]
    lines += _l_curve_lines(results, suite, figures, config.scene.cube_side)
    if drawn:
        lines += ["## Metric distributions", "",
                  "![distributions](figures/closed_loop_distributions.png)", "",
                  "*Per configuration, one point per episode and its box plot (quartiles, "
                  "whiskers to 1.5 IQR): peak angle, hold time at the end, the plan's "
                  "predicted next angle against the LCS rollout and against the plant "
                  "(medians over the steps; log axis, values below 1e-6 rad drawn at 1e-6 and "
                  "above 10 rad, a diverged plan, at 10), "
                  "and the median control-step time (ms, log axis).*",
                  ""]
    lines += claims_lines(results, suite.comparisons)
    if render and "success" in frame:
        lines += _animation_section(directory, frame, config)
    path = directory / "report.md"
    atomic_write_bytes(path, ("\n".join(lines).rstrip() + "\n").encode())
    return path
