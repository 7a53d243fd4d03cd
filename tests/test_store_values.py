"""Bad values in a stored results table (bench/store.read_results, normalise_row): a bool
column stored as text, a non-numeric float, a NaN integer and a repeated cell are rejected on
one line naming the file and the column (or the cell), and the CLI exits 2 without a
traceback; well-formed Parquet and CSV tables still read the same.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from synthetic_results import frame as make_frame
from synthetic_results import row

from c3bench.bench import store
from c3bench.bench.cli import main
from c3bench.problems.errors import InputError, SchemaVersionError

SUITE = "quick"


def _table() -> pd.DataFrame:
    """Four cells, one of them failed."""
    return make_frame([row(instance=f"c3_qp-s000-i{i:02d}", solver=solver,
                           primal_residual_relative=1.0 if (i, solver) == (1, "beta") else 1e-12)
                       for i in range(2) for solver in ("alpha", "beta")])


def _store(tmp_path: Path, table: pd.DataFrame) -> store.SuitePaths:
    """``table`` as the stored ``results.parquet`` of suite ``quick`` (no cell files)."""
    paths = store.SuitePaths.of(tmp_path, SUITE)
    paths.root.mkdir(parents=True, exist_ok=True)
    paths.parquet.write_bytes(store.parquet_bytes(table))
    return paths


def _success_as_text(table: pd.DataFrame) -> pd.DataFrame:
    return table.assign(success=table["success"].astype(str))


def _float_as_text(table: pd.DataFrame) -> pd.DataFrame:
    out = table.assign(total_time=table["total_time"].astype(str))
    out.loc[0, "total_time"] = "abc"
    return out


def _int_nan(table: pd.DataFrame) -> pd.DataFrame:
    out = table.assign(n_variables=table["n_variables"].astype(float))
    out.loc[0, "n_variables"] = np.nan
    return out


def _success_null(table: pd.DataFrame) -> pd.DataFrame:
    out = table.assign(success=table["success"].astype(object))
    out.loc[~table["success"], "success"] = None
    return out


@pytest.mark.parametrize(("damage", "column"), [
    (_success_as_text, "success"),
    (_float_as_text, "total_time"),
    (_int_nan, "n_variables"),
    (_success_null, "success"),
])
def test_a_bad_value_is_rejected_naming_file_and_column(
        tmp_path: Path, damage: Callable[[pd.DataFrame], pd.DataFrame], column: str) -> None:
    paths = _store(tmp_path, damage(_table()))
    with pytest.raises(SchemaVersionError) as caught:
        store.read_results(paths.root)
    message = str(caught.value)
    assert str(paths.parquet) in message and repr(column) in message
    assert "\n" not in message


def test_text_booleans_are_not_read_as_true(tmp_path: Path) -> None:
    """``bool('False')`` is True: the old reader said every cell succeeded."""
    paths = _store(tmp_path, _success_as_text(_table()))
    with pytest.raises(InputError, match="'success'"):
        store.read_results(paths.parquet)


def test_a_repeated_cell_is_rejected_naming_its_key(tmp_path: Path) -> None:
    table = _table()
    paths = _store(tmp_path, pd.concat([table, table.iloc[:1]], ignore_index=True))
    with pytest.raises(SchemaVersionError, match="1 rows repeat a cell") as caught:
        store.read_results(paths.root)
    assert str(paths.parquet) in str(caught.value)
    assert "'instance': 'c3_qp-s000-i00'" in str(caught.value)


def test_a_repeated_cell_in_the_csv_is_rejected(tmp_path: Path) -> None:
    table = _table()
    path = tmp_path / "results.csv"
    path.write_text(pd.concat([table, table.iloc[1:2]]).to_csv(index=False))
    with pytest.raises(SchemaVersionError, match="repeat a cell"):
        store.read_results(path)


def test_a_cell_file_with_a_text_boolean_is_rejected(tmp_path: Path) -> None:
    paths = store.SuitePaths.of(tmp_path, SUITE)
    good = _table().to_dict("records")[0]
    cell = store.write_cell(paths, good)
    payload = json.loads(cell.read_text())
    payload["success"] = "False"
    cell.write_text(json.dumps(payload))
    with pytest.raises(SchemaVersionError, match="'success'") as caught:
        store.read_results(paths.root)
    assert str(cell) in str(caught.value)


def test_normalise_row_names_the_column() -> None:
    good = _table().to_dict("records")[0]
    with pytest.raises(ValueError, match="'found'"):
        store.normalise_row({**good, "found": "True"})
    with pytest.raises(ValueError, match="'repeats'"):
        store.normalise_row({**good, "repeats": 2.5})
    with pytest.raises(ValueError, match="'iterations'"):
        store.normalise_row({**good, "iterations": "many"})
    assert store.normalise_row({**good, "iterations": math.nan})["iterations"] is None
    assert store.normalise_row({**good, "found": np.bool_(False)})["found"] is False
    # a missing verdict is never a given one: NaN (pandas' missing float) reads as False
    for missing in (math.nan, np.float32("nan"), None):
        assert store.normalise_row({**good, "verified": missing})["verified"] is False


def test_well_formed_tables_read_as_before(tmp_path: Path) -> None:
    """Parquet and CSV (booleans as pandas ``to_csv`` writes them) give the same frame."""
    table = _table()
    paths = store.SuitePaths.of(tmp_path, SUITE)
    paths.root.mkdir(parents=True)
    store.write_frame(paths, table)
    from_parquet = store.read_results(paths.parquet)
    from_csv = store.read_results(paths.csv)
    pd.testing.assert_frame_equal(from_parquet, table)
    pd.testing.assert_frame_equal(from_csv, table)
    assert from_csv["success"].tolist() == [True, True, True, False]
    empty = store.rows_to_frame([])
    store.write_frame(paths, empty)
    assert store.read_results(paths.csv).empty and store.read_results(paths.parquet).empty


@pytest.mark.parametrize("damage", [_success_as_text, _float_as_text, _int_nan])
def test_the_cli_exits_2_on_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     damage: Callable[[pd.DataFrame], pd.DataFrame]) -> None:
    paths = _store(tmp_path, damage(_table()))
    assert main(["report", "--no-figures", "--results", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert str(paths.parquet) in err


def test_a_found_row_needs_finite_times() -> None:
    """A stored cell that found a solution with a NaN or negative time is damaged (it would
    change every time ratio silently); a row that found nothing may keep NaN laps."""
    good = _table().to_dict("records")[0]
    assert good["found"]
    for name in ("setup_time", "solve_time", "total_time"):
        for bad in (math.nan, math.inf, -1e-3):
            with pytest.raises(ValueError, match=f"'{name}'"):
                store.normalise_row({**good, name: bad})
    lost = store.normalise_row({**good, "found": False, "total_time": math.nan})
    assert math.isnan(lost["total_time"])


def test_a_success_never_costs_more_than_the_time_limit() -> None:
    """Failures are charged the time limit in every time aggregate, so an answer that took
    longer than the limit (a limit below what the child's kill can enforce) is no success."""
    from c3bench.bench.metrics import judge

    within = row(family="lcp", setup_time=0.0, solve_time=2e-4, time_limit=1e-3)
    assert judge(within)[0]
    over = row(family="lcp", setup_time=0.0, solve_time=2.4e-4, time_limit=1e-9)
    success, verdict = judge(over)
    assert not success and "time_limit" in verdict
