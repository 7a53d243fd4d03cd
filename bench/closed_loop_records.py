"""The records of a closed-loop run: the per-step table, the stored run directory, the
``summary.json`` of a single run and its animation.

The run itself (:func:`bench.closed_loop.run_closed_loop`) lives in :mod:`bench.closed_loop`,
which re-exports these functions.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from c3bench.bench.closed_loop import ClosedLoopOutcome, StepRecord, Trajectory
    from c3bench.bench.closed_loop_policy import ControllerSpec
    from c3bench.problems.scene import Scene

__all__ = ["records_frame", "render_run", "run_summary", "write_run"]


def records_frame(trajectory: Trajectory, records: list[StepRecord], scene: Scene
                  ) -> Any:
    """One row per control step: time, state, input, angle, timings, ok, NaNs, diagnostics
    and, when the run measured them, the contact of the step's control period at the plant's
    rate (``plant_min_gap``, ``plant_min_height``, ``plant_contact_time``,
    ``plant_away_time``, ``plant_touch_time``, ``plant_touch_speed`` and, when measured, the
    cube's height ``plant_cube_clearance``, ``plant_cube_air_time``:
    :class:`~c3bench.bench.closed_loop_metrics.PlantContact`)."""
    import pandas as pd

    plant = trajectory.plant
    rows = []
    for k, record in enumerate(records):
        row: dict[str, Any] = {"step": k, "time": record.time,
                               "cube_angle": scene.cube_angle(record.state),
                               "ball_gap": float(trajectory.ball_gap[k]),
                               "lcs_time": record.lcs_time, "solve_time": record.solve_time,
                               "ok": record.ok, "nan_count": record.nan_count,
                               "qp_failures": record.qp_failures,
                               "qp_failure": record.qp_failure,
                               "fallback_reason": record.fallback_reason}
        row.update({f"x{i}": float(v) for i, v in enumerate(record.state)})
        row.update({f"u{i}": float(v) for i, v in enumerate(record.input)})
        commanded = record.input if record.commanded is None else record.commanded
        row.update({f"commanded{i}": float(v) for i, v in enumerate(commanded)})
        plan = np.full(scene.nx, np.nan) if record.plan_next is None else record.plan_next
        lcs = np.full(scene.nx, np.nan) if record.lcs_next is None else record.lcs_next
        row["plan_lcs_error"] = float(np.linalg.norm(plan - lcs))
        row["plan_plant_error"] = float(np.linalg.norm(plan - trajectory.states[k + 1]))
        if plant is not None:
            row.update({f"plant_{name}": float(getattr(plant, name)[k])
                        for name in plant.columns})
        row.update(record.info)
        rows.append(row)
    return pd.DataFrame(rows)


def write_run(out_dir: str | Path, trajectory: Trajectory, records: list[StepRecord],
              scene: Scene, summary: dict[str, Any]) -> Path:
    """Write a run into ``out_dir``: ``steps.parquet``/``steps.csv`` (:func:`records_frame`),
    ``states.npy`` (the plant states at every control step) and, last, ``summary.json``
    (whose presence marks a finished run). Every file goes through a temporary and a rename.
    """
    import json

    from c3bench.problems.instance import atomic_write_bytes

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frame = records_frame(trajectory, records, scene)
    for name, write in (("steps.parquet", lambda p: frame.to_parquet(p, index=False)),
                        ("steps.csv", lambda p: frame.to_csv(p, index=False)),
                        ("states.npy", lambda p: np.save(p, trajectory.states))):
        temporary = out / f".{name}.tmp"
        with temporary.open("wb") as handle:
            write(handle)
        temporary.replace(out / name)
    atomic_write_bytes(out / "summary.json", (json.dumps(
        summary, indent=2, sort_keys=True, default=float) + "\n").encode())
    return out


def run_summary(spec: ControllerSpec, trajectory: Trajectory,
                outcome: ClosedLoopOutcome) -> dict[str, Any]:
    """The ``summary.json`` of a single ``c3bench closed-loop`` run (``contact_model``: the
    controller's LCS contact model, also in ``spec``)."""
    from dataclasses import asdict

    outcome_fields = {key: value for key, value in asdict(outcome).items()
                      if key != "metrics"}
    return {"spec": asdict(spec), "contact_model": spec.contact_model,
            "outcome": outcome_fields,
            "metrics": asdict(outcome.metrics) if outcome.metrics is not None else {},
            "failure_label": outcome.failure_label,
            "final_state": trajectory.states[-1].tolist()}


def render_run(states: np.ndarray, scene: Scene, path: str | Path, dt: float) -> Path:
    """Animate a run's states (one per control step) as a GIF (raises ``RenderUnavailable``
    without an off-screen GL)."""
    from c3bench.problems.scene import render_frames, save_gif

    frames = render_frames(scene, states, width=480, height=360)
    return save_gif(frames, path, dt)
