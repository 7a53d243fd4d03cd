"""The report of a closed-loop suite, sweep or trials run: ``report.md`` with the outcome
table (success, gentle success, peak angle, hold time, clipped inputs, plan consistency,
failure labels, step times), the failure-mode map of a sweep, and ``figures/`` (angle error
bars, angle trajectories, step-time distributions, an animation of a successful run).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from c3bench.bench.closed_loop import render_run
from c3bench.problems.config import Config, load_config
from c3bench.problems.errors import RenderUnavailable
from c3bench.problems.instance import atomic_write_bytes
from c3bench.problems.scene import build_scene

if TYPE_CHECKING:
    from c3bench.bench.closed_loop_suite import SuiteRun


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
    """Cube angle error at the end per configuration, coloured by success."""
    figure, axis = _axes((max(6.0, 0.55 * len(frame)), 4.2))
    errors = frame["angle_error"].fillna(target).to_numpy(dtype=float)
    colours = ["tab:green" if ok else "tab:red" for ok in frame["success"].fillna(False)]
    axis.bar(range(len(frame)), errors, color=colours)
    for index, (error, mode) in enumerate(zip(errors, frame["failure_mode"], strict=True)):
        axis.text(index, error, f"m{int(mode)}" if mode == mode else "", ha="center",
                  va="bottom", fontsize=7)
    axis.axhline(load_config().mpc.success_tolerance, color="k", linestyle="--", linewidth=0.8,
                 label="success tolerance")
    axis.set_xticks(range(len(frame)))
    axis.set_xticklabels(frame["case"], rotation=60, ha="right", fontsize=7)
    axis.set_ylabel("|theta(2 s) - theta*| (rad)")
    axis.set_title("Cube angle error after the run (green: success; mN: failure mode)")
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
             "case's hold time), the ball never more than 5 mm into the cube or the table; "
             "gentle: a success that never passed the balance angle pi/4 "
             "(docs/closed_loop.md). Failure mode 0 is the older rule (angle within the "
             "tolerance at the end, no pivot slip). "
             "Control-step times are wall-clock on this machine (2 cores, one BLAS thread), "
             "LCS build included; the reference study reported 0.06 s per step "
             "(control period 0.05 s).", ""]
    columns = ["case", "success", "gentle_success", "label", "peak_angle", "hold_time",
               "clipped_inputs", "plan_lcs_angle_median", "angle_error", "final_angle",
               "failure_mode", "failure_label", "median_step_time", "p95_step_time",
               "median_lcs_time", "fallback_count", "nan_count"]
    shown = frame.copy()
    for column in ("median_step_time", "p95_step_time", "median_lcs_time"):
        if column in shown:
            shown[column] = shown[column] * 1e3
    lines += ["## Outcomes", "",
              "Times in ms; angles in rad (peak angle, plan vs LCS angle gap: median over "
              "the steps); hold time in s; failure modes: 0 angle in band at the end, "
              "1 fast sliding past the edge, 2 backing off first, 3 whack then contact lost, "
              "4 no motion, 5 unlabelled, -1 the run itself failed (see `error`).", "",
              _table(shown, [c for c in columns if c in shown]), ""]
    errors = frame[frame.get("error", pd.Series([""] * len(frame))).fillna("") != ""] \
        if "error" in frame else frame.iloc[0:0]
    if len(errors):
        lines += ["Runs that produced no trajectory:", "",
                  _table(errors, ["case", "error"]), ""]
    if "sweep" in set(frame.get("group", [])):
        lines += ["## Failure-mode map", "", sweep_grid(frame), ""]
    valid = frame[frame.get("failure_mode", -1) != -1] if "failure_mode" in frame else frame
    if len(valid):
        plot_error_bars(valid, figures / "closed_loop_error.png", target)
        plot_angles(directory, valid, figures / "closed_loop_angles.png", target)
        plot_step_times(directory, valid, figures / "closed_loop_step_time.png")
        lines += ["## Figures", "",
                  "![error](figures/closed_loop_error.png)", "",
                  "*Cube angle error at the end of each run (rad); green bars succeeded, "
                  "labels give the failure mode.*", "",
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


def sweep_grid(frame: pd.DataFrame) -> str:
    """Markdown grid of failure-mode labels: rows ``dt / rho schedule``, columns ``Q_box / l``."""
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
            if not len(match):
                cells.append("-")
                continue
            hit = match.iloc[0]
            mode = int(hit["failure_mode"])
            cells.append("success" if mode == 0 else f"mode {mode}" if mode > 0 else "error")
            if mode >= 0:
                cells[-1] += f" ({hit['angle_error']:.2f})"
        lines.append(f"| {dt:g} / {schedule} | " + " | ".join(cells) + " |")
    return ("Each cell: the failure-mode label (angle error at the end, rad).\n\n"
            + "\n".join(lines))

