"""Summaries, ratios and the stored layout of ``c3bench perf`` (no timing is checked)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from c3bench.bench import perf_store, store
from c3bench.bench.perf_summary import add_ratios, format_line, summarize
from c3bench.problems.errors import SchemaVersionError


def _rows(run: str, backend: str, samples: int, totals: list[float], admm: list[float],
          precision: str = "float64", mflop: float = math.nan,
          executed: float | None = None, cache: str = "warm") -> list[dict[str, object]]:
    rows = []
    for repeat, (total, step_admm) in enumerate(zip(totals, admm, strict=True)):
        row: dict[str, object] = {name: math.nan for name in perf_store.PERF_COLUMNS}
        row.update(schema_version=store.SCHEMA_VERSION, run_id=run, host="h", backend=backend,
                   precision=precision, device="cpu", samples=samples, repeat=repeat,
                   state_index=repeat, total_ms=total, admm_ms=step_admm, ok=True,
                   skipped=False, note="", weighted=samples > 1, weighting_ms=1.0,
                   total_no_weighting_ms=total - 1.0, admm_mflop=mflop,
                   admm_mflop_executed=mflop if executed is None else executed,
                   matmul_gflops_f64=10.0, matmul_gflops_f32=20.0,
                   matmul_run_gflops_f64=8.0, matmul_run_gflops_f32=16.0, load_avg=0.5,
                   iterations=10, horizon=7, cache_hits=-1, cache_misses=-1,
                   blas_threads=1, affinity="0", perf_schema_version=5, cache=cache)
        rows.append(row)
    return rows


def _frame() -> pd.DataFrame:
    rows = (_rows("r1", "c3plus-riccati", 16, [10.0, 12.0, 14.0], [4.0, 5.0, 6.0], mflop=20.0)
            + _rows("r1", "c3plus-riccati", 1, [2.0, 2.0, 2.0], [1.0, 1.0, 1.0], mflop=1.0)
            + _rows("r1", "c3-osqp", 16, [1000.0, 1200.0], [900.0, 1000.0])
            # a kernel that executes fewer flops than the model counts: its rate is its own
            + _rows("r1", "c3plus-compiled", 16, [3.0, 3.0], [1.0, 1.0], mflop=20.0,
                    executed=8.0)
            + _rows("r1", "c3plus-riccati", 16, [6.0, 6.0, 6.0], [2.0, 2.0, 2.0],
                    precision="float32", mflop=20.0)
            # another run: its riccati time must not be the denominator of run r1's rows
            + _rows("r2", "c3plus-riccati", 16, [100.0], [100.0], mflop=20.0))
    return pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS))


def test_ratios_are_within_one_run_and_the_same_samples() -> None:
    summary = summarize(_frame()).set_index(["run_id", "backend", "precision", "samples"])
    riccati = summary.loc[("r1", "c3plus-riccati", "float64", 16)]
    assert riccati["median_ms"] == 12.0 and riccati["ratio_riccati"] == 1.0
    assert riccati["ratio_osqp"] == pytest.approx(12.0 / 1100.0)
    assert riccati["admm_ratio_osqp"] == pytest.approx(5.0 / 950.0)
    single = summary.loc[("r1", "c3plus-riccati", "float64", 1)]
    assert math.isnan(single["ratio_osqp"]) and single["ratio_riccati"] == 1.0
    f32 = summary.loc[("r1", "c3plus-riccati", "float32", 16)]
    assert f32["ratio_riccati"] == pytest.approx(0.5)
    assert f32["admm_ratio_riccati"] == pytest.approx(2.0 / 5.0)
    assert summary.loc[("r2", "c3plus-riccati", "float64", 16)]["ratio_riccati"] == 1.0
    assert math.isnan(summary.loc[("r2", "c3plus-riccati", "float64", 16)]["ratio_osqp"])
    # GFLOP/s = MFLOP / ms, share of the row precision's matmul rate: the best at the start
    # and the median through the run
    assert riccati["gflops"] == pytest.approx(20.0 / 5.0)
    assert riccati["rate_share"] == pytest.approx(0.4)
    assert riccati["rate_share_run"] == pytest.approx(4.0 / 8.0)
    assert f32["rate_share"] == pytest.approx(10.0 / 20.0)
    assert f32["rate_share_run"] == pytest.approx(10.0 / 16.0)
    assert math.isnan(summary.loc[("r1", "c3-osqp", "float64", 16)]["gflops"])
    compiled = summary.loc[("r1", "c3plus-compiled", "float64", 16)]
    assert compiled["gflops"] == pytest.approx(8.0) and compiled["admm_mflop"] == 20.0


def test_cold_and_warm_steps_are_summarised_and_compared_apart() -> None:
    """A cold step is compared with the reference's cold steps, a warm one with its warm
    ones: the compiled kernel is 4x riccati warm and 2x cold here, never 8x or 1x."""
    rows = (_rows("r", "c3plus-riccati", 16, [8.0, 8.0], [8.0, 8.0])
            + _rows("r", "c3plus-riccati", 16, [10.0, 10.0], [10.0, 10.0], cache="cold")
            + _rows("r", "c3plus-compiled", 16, [2.0, 2.0], [2.0, 2.0])
            + _rows("r", "c3plus-compiled", 16, [5.0, 5.0], [5.0, 5.0], cache="cold"))
    summary = summarize(pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS)))
    compiled = summary[summary["backend"] == "c3plus-compiled"].set_index("cache")
    assert compiled.loc["warm", "ratio_riccati"] == pytest.approx(0.25)
    assert compiled.loc["cold", "admm_ratio_riccati"] == pytest.approx(0.5)
    assert (summary["repeats"] == 2).all() and len(summary) == 4
    from c3bench.bench.perf_report import target_lines

    lines = target_lines(summary)
    assert [line.split(",")[0] for line in lines] == [
        "- warm cache", "- warm cache", "- cold cache", "- cold cache"]
    assert "ADMM at 16: 4x riccati" in lines[1] and "ADMM at 16: 2x riccati" in lines[3]


def test_layout_three_rows_get_their_cache_state(tmp_path: Path) -> None:
    """Before layout 4 every step of a run that timed several configurations at a sample
    count followed another configuration's step (cold); a lone configuration's steps are
    warm; skipped rows have none."""
    frame = _frame().drop(columns=["cache"]).assign(perf_schema_version=3)
    skipped = frame.iloc[:1].assign(skipped=True, samples=64, backend="c3-osqp")
    frame = pd.concat([frame, skipped], ignore_index=True)
    read = perf_store.upgrade_perf_frame(frame, tmp_path / "x.parquet")
    keys = zip(read["run_id"], read["samples"], read["skipped"], strict=True)
    states = dict(zip(keys, read["cache"], strict=True))
    assert states[("r1", 16, False)] == "cold"  # riccati f64/f32, compiled and osqp at 16
    assert states[("r1", 1, False)] == "warm"  # riccati alone at one sample
    assert states[("r2", 16, False)] == "warm" and states[("r1", 64, True)] == ""


def test_rows_before_layout_six_ran_in_one_process(tmp_path: Path) -> None:
    """Every run before layout 6 measured all its configurations in the run's process."""
    frame = _frame().assign(perf_schema_version=5)
    if "process" in frame.columns:
        frame = frame.drop(columns=["process"])
    read = perf_store.upgrade_perf_frame(frame, tmp_path / "x.parquet")
    assert (read["process"] == perf_store.ProcessMode.SHARED.value).all()


def test_ratios_are_nan_without_the_reference() -> None:
    summary = pd.DataFrame({"run_id": ["a"], "host": ["h"], "backend": ["x"],
                            "precision": ["float64"], "samples": [4], "cache": ["warm"],
                            "repeats": [3],
                            "median_ms": [2.0], "admm_ms": [1.0]})
    out = add_ratios(summary)
    assert out[["ratio_riccati", "ratio_osqp", "admm_ratio_riccati"]].isna().all().all()


def test_printed_lines_carry_ratios_rate_and_load() -> None:
    text = format_line(_frame()[lambda f: f["run_id"] == "r1"])
    line = next(t for t in text.splitlines() if "float32" in t)
    assert "t/riccati 0.5" in line
    assert "GFLOP/s (62.5 % of matmul through the run, 50.0 % of its best)" in line
    assert "load 0.50" in line and "weighting 1.00" in line
    # a layout-4 row has the best at the start only
    old = _frame()[lambda f: f["run_id"] == "r1"].assign(matmul_run_gflops_f32=math.nan)
    line = next(t for t in format_line(old).splitlines() if "float32" in t)
    assert "GFLOP/s (50.0 % of matmul)" in line


def test_layout_one_files_are_read_with_nan_columns(tmp_path: Path) -> None:
    frame = _frame()
    old = frame.drop(columns=list(perf_store.PERF_V2_COLUMNS))
    runs = store.perf_dir(tmp_path) / store.PERF_RUNS
    runs.mkdir(parents=True)
    (runs / "old.parquet").write_bytes(store.parquet_bytes(old))  # as the layout-1 writer did
    perf_store.consolidate_perf(tmp_path)
    read = perf_store.read_perf(tmp_path)
    assert list(read.columns) == list(perf_store.PERF_COLUMNS)
    assert (read["perf_schema_version"] == 1).all() and not read["weighted"].any()
    assert read["admm_ms"].isna().all() and read["matmul_gflops_f64"].isna().all()
    assert set(read["cache"]) == {"cold", "warm"}
    np.testing.assert_array_equal(read["total_ms"], frame["total_ms"])
    csv = perf_store.perf_files(tmp_path)[1]
    (store.perf_dir(tmp_path) / "perf.parquet").unlink()
    old.to_csv(csv, index=False)
    assert perf_store.read_perf(tmp_path)["admm_mflop"].isna().all()


def test_new_files_round_trip_and_carry_the_layout(tmp_path: Path) -> None:
    frame = _frame()
    parquet, _ = perf_store.write_perf(frame, tmp_path)
    pd.testing.assert_frame_equal(perf_store.read_perf(tmp_path), frame, check_dtype=False)
    metadata = pq.read_table(parquet).schema.metadata
    assert metadata[perf_store.PERF_METADATA_KEY] == str(perf_store.PERF_SCHEMA_VERSION).encode()
    assert metadata[store.PARQUET_METADATA_KEY] == str(store.SCHEMA_VERSION).encode()
    assert len(perf_store.perf_run_files(tmp_path)) == 2  # one file per run id
    newer = frame.assign(perf_schema_version=perf_store.PERF_SCHEMA_VERSION + 1)
    with pytest.raises(SchemaVersionError, match="layout"):
        perf_store.upgrade_perf_frame(newer, parquet)


def test_gpu_lines_show_ratios_to_the_compiled_cpu_kernel(tmp_path: Path) -> None:
    import json

    from c3bench.bench.perf_report import gpu_lines

    rows = [{"backend": "c3plus-compiled", "device": "cpu", "device_kind": "cpu",
             "precision": "float64", "samples": 16, "admm_ms_median": 4.0,
             "admm_ms_p95": 5.0, "load_avg": 0.5},
            {"backend": "c3plus-jax", "device": "gpu", "device_kind": "NVIDIA H200",
             "precision": "float64", "samples": 16, "admm_ms_median": 2.0,
             "admm_ms_p95": 2.5, "load_avg": 0.5}]
    (tmp_path / "run.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    text = "\n".join(gpu_lines(tmp_path))
    assert "| c3plus-jax | gpu | NVIDIA H200 | float64 | 16 | 2 | 2.5 | 0.5 | 0.50 |" in text
    assert gpu_lines(tmp_path / "absent") == []


@pytest.mark.parametrize(("text", "reason"), [
    ('{"backend": "c3plus-jax", "device": "gpu"', "line 1 damaged"),
    ('[1, 2]\n', "missing or not a number: backend"),
    ('{"backend": "c3plus-jax", "device": "gpu", "device_kind": "H200", "precision": '
     '"float64", "samples": 16, "admm_ms_median": "fast", "admm_ms_p95": 1.0, '
     '"load_avg": 0.1}\n', "not a number: admm_ms_median"),
])
def test_a_damaged_gpu_run_is_a_one_line_error_naming_the_file(tmp_path: Path, text: str,
                                                                reason: str) -> None:
    from c3bench.bench.perf_report import gpu_lines

    (tmp_path / "run.jsonl").write_text(text)
    with pytest.raises(SchemaVersionError, match=reason) as raised:
        gpu_lines(tmp_path)
    assert "run.jsonl" in str(raised.value) and "\n" not in str(raised.value)


def test_the_figure_legend_counts_steps_per_cache_state() -> None:
    from c3bench.bench.plots_perf import _counts

    group = pd.DataFrame({"cache": ["cold", "warm"], "repeats": [12, 36]})
    assert _counts(group) == "12 cold, 36 warm"
    assert _counts(group[group["cache"] == "warm"]) == "36 warm"


def test_history_counts_the_targets_met_over_a_machines_recent_runs() -> None:
    """Three runs of the compiled backend (shares of the 8 GFLOP/s run rate 30, 20 and 26 %;
    one run's one-sample ADMM only 8x): each target is counted over the runs, and a run that
    did not time the compiled backend at 16 samples is left out."""
    from c3bench.bench.perf_report import history_lines

    rows = []
    for run, executed, single in (("r1", 2.4, 0.25), ("r2", 1.6, 0.1), ("r3", 2.08, 0.1)):
        rows += (_rows(run, "c3plus-riccati", 16, [20.0], [8.0])
                 + _rows(run, "c3plus-riccati", 1, [3.0], [2.0])
                 + _rows(run, "c3plus-compiled", 16, [4.0], [1.0], executed=executed)
                 + _rows(run, "c3plus-compiled", 1, [1.0], [single]))
    rows += _rows("r4", "c3plus-riccati", 16, [20.0], [8.0])  # no compiled row: left out
    stored = pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS))
    lines = history_lines(stored, "h")
    table = [line for line in lines if line.startswith("| r") and not line.startswith("| run")]
    assert [line.split(" | ")[0] for line in table] == ["| r1", "| r2", "| r3"]
    assert table[0] == "| r1 | - | 0.50 | 8.0x | 5.0x | 8.0x | 30.0 |"
    summary = lines[-2]
    assert "ADMM at 16 >= 6x in 3 of 3" in summary
    assert "whole step at 16 >= 4x in 3 of 3" in summary
    assert "ADMM at 1 >= 10x in 2 of 3" in summary and "% matmul >= 25 % in 2 of 3" in summary
    assert len([line for line in history_lines(stored, "h", runs=2)
                if line.startswith("| r") and not line.startswith("| run")]) == 2
    assert history_lines(stored[stored["run_id"] == "r1"], "h") == []  # one run: nothing
    assert history_lines(stored, "other host") == []
