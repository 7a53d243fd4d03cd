"""What the report counts (bench/report.py): unverified cells are neither failures nor
claimed-but-wrong cells, and the header's timing comes from the stored rows, not from the
last run's ``run_info.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from conftest import synthetic_report
from synthetic_results import frame as make_frame
from synthetic_results import row

from c3bench.bench.accuracy import claimed_but_wrong
from c3bench.bench.metrics import unverified_cells


def _section(text: str, heading: str) -> str:
    return text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]


def _projection(count: int, **values: Any) -> list[dict[str, Any]]:
    """``count`` projection cells without a reference optimum (unverified when feasible)."""
    return [row(instance=f"projection-c3plus-s000-i00-k{k}", family="projection",
                solver="c3plus_closed_form", **values) for k in range(count)]


# --- A: unverified cells are counted apart -------------------------------------------------------
def test_unverified_cells_are_not_failures(tmp_path: Path) -> None:
    table = make_frame(_projection(3))
    assert unverified_cells(table).all() and not table["success"].any()
    assert claimed_but_wrong(table) == []
    text = synthetic_report(tmp_path, table)
    failures = _section(text, "Failures")
    assert "inaccurate" not in failures and "| c3plus_closed_form |" not in failures
    assert "Every cell succeeded" not in failures
    assert "3 *unverified* cells" in failures and "projection / c3plus_closed_form (3)" in failures
    claimed = _section(text, "Claimed success but wrong")
    assert "(every found=True cell succeeded)" not in claimed
    assert "3 found=True cells passed every residual check" in claimed


def test_failures_table_counts_only_the_real_failures(tmp_path: Path) -> None:
    rows = [*_projection(2), row(instance="projection-c3plus-s000-i00-k9", family="projection",
                                 solver="c3plus_closed_form", primal_residual_relative=1.0)]
    rows += [row(instance="c3_qp-s000-i00", solver="alpha", dual_residual_relative=1.0)]
    text = synthetic_report(tmp_path, make_frame(rows))
    failures = _section(text, "Failures")
    table = {line.split("|")[2].strip(): line for line in failures.splitlines()
             if line.startswith("| ") and "---" not in line and "failed cells" not in line}
    assert set(table) == {"c3plus_closed_form", "alpha"}
    assert "| 1 | inaccurate (1) |" in table["c3plus_closed_form"]
    assert "2 *unverified* cells" in failures
    claimed = _section(text, "Claimed success but wrong")
    assert "2 found=True cells passed every residual check" in claimed
    assert "wrong / claimed" in claimed  # the table of the two wrong cells is still there


def test_no_unverified_cells_keeps_the_old_sentences(tmp_path: Path) -> None:
    text = synthetic_report(tmp_path, make_frame([row()]))
    assert _section(text, "Failures").strip() == "Every cell succeeded."
    assert "(every found=True cell succeeded)" in _section(text, "Claimed success but wrong")


# --- B: the header's timing is that of the stored rows -------------------------------------------
LAST_RUN = {"date": "2025-06-01T00:00:00+00:00", "jobs": 7, "repeats": 1, "time_limit": 2.0}


def _timed_rows(finished: str) -> list[dict[str, Any]]:
    return [row(instance=f"c3_qp-s000-i{i:02d}", repeats=3, finished_at=finished,
                time_limit=10.0 if i < 3 else 100.0) for i in range(4)]


def _header(text: str) -> dict[str, str]:
    block = _section(text, "Machine and versions")
    return {cells[1].strip(): cells[2].strip() for cells in
            (line.split("|") for line in block.splitlines() if line.startswith("| "))}


def test_header_timing_is_read_from_the_rows(tmp_path: Path) -> None:
    """A later run that stored nothing (repeats 1, limit 2 s) does not describe the rows."""
    rows = make_frame(_timed_rows("2025-01-01T00:00:00+00:00"))
    header = _header(synthetic_report(tmp_path, rows, LAST_RUN))
    assert header["timing"].startswith("3 timed repeats")
    assert "time limit 10 s (3 cells), 100 s (1 cells) per solve" in header["timing"]
    assert "2 s" not in header["timing"] and "1 timed" not in header["timing"]
    assert header["executor"] == ("local process pool, 7 workers (the last run's: 0 of the 4 "
                                  "stored cells finished in it)")
    assert header["cells stored"] == "4"


def test_header_executor_is_attributed_when_the_last_run_made_every_row(tmp_path: Path) -> None:
    rows = make_frame(_timed_rows("2025-06-01T00:00:05+00:00"))
    header = _header(synthetic_report(tmp_path, rows, LAST_RUN))
    assert header["executor"] == "local process pool, 7 workers"


def test_header_lists_sequence_limits_apart(tmp_path: Path) -> None:
    rows = [row(instance="c3_qp-s000-i00", repeats=3, time_limit=10.0),
            row(instance="c3_qp-s000-i00", repeats=1, time_limit=100.0, start="sequence")]
    timing = _header(synthetic_report(tmp_path, make_frame(rows)))["timing"]
    assert timing == ("1 (1 cells), 3 (1 cells) timed repeats after 1 untimed warm-up, median; "
                      "time limit 10 s per solve; sequence cells: 100 s per ADMM run")
