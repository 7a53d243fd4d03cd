"""Synthetic rows of the results table for the report, accuracy, compare and plot tests.

:func:`row` fills every column of :data:`bench.store.SCHEMA` with a neutral default, applies
the given values (``total_time`` is ``setup_time + solve_time`` unless given) and judges the
row with :func:`bench.metrics.judge` (unless ``success`` is given), so a test states only
what it is about.
"""

from __future__ import annotations

import math
from typing import Any

import pandas as pd

from c3bench.bench import store
from c3bench.bench.metrics import judge

_DEFAULTS: dict[str, Any] = {
    "schema_version": store.SCHEMA_VERSION, "suite": "synthetic", "instance": "c3_qp-s000-i00",
    "instance_hash": "hash", "family": "c3_qp", "solver": "alpha", "solver_version": "-",
    "settings": "default", "tolerance": 1e-3, "time_limit": 10.0, "precision": "float64",
    "start": "cold", "repeats": 1, "state_index": 0, "admm_iteration": None,
    "n_variables": 10, "n_constraints": 5, "found": True, "verified": True, "failure": "",
    "status": "solved",
    "iterations": 5, "setup_time": 0.0, "solve_time": 1e-3, "objective": 1.0,
    "primal_residual_relative": 1e-12, "dual_residual_relative": 1e-12,
    "duality_gap_relative": 1e-12, "complementarity_violation": 0.0,
    "reference_solver": "", "trace_file": "", "host": "test",
    "finished_at": "2025-01-01T00:00:00+00:00",
}


def row(**values: Any) -> dict[str, Any]:
    """A complete, judged row (see the module doc)."""
    out: dict[str, Any] = {}
    for column in store.SCHEMA:
        out[column.name] = _DEFAULTS.get(column.name, "" if column.dtype == "str" else math.nan)
    out.update(values)
    if "total_time" not in values:
        out["total_time"] = out["setup_time"] + out["solve_time"]
    for absolute in ("primal_residual", "dual_residual", "duality_gap"):
        if absolute not in values:
            out[absolute] = out[f"{absolute}_relative"]
    out["cell_id"] = "--".join(str(out[k]) for k in ("instance", "solver", "settings",
                                                      "precision", "start"))
    if "success" not in values:
        out["success"], out["verdict"] = judge(out)
    elif "verdict" not in values:
        out["verdict"] = "" if out["success"] else "planted failure"
    return out


def frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """The rows as a results table (schema dtypes, canonical order)."""
    return store.rows_to_frame(rows)
