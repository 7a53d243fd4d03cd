"""The report's figures follow one convention (bench/palette, bench/figure_base): one fixed
colour and marker per solver across every figure, legends beside the panels, ``n = ...`` in
every panel, and solvers of one variant named "not run" on the other. The drawn matplotlib
objects are inspected (:func:`bench.figure_base.keep_figures`), not the PNGs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from matplotlib.figure import Figure as MplFigure
from synthetic_results import frame as make_frame
from synthetic_results import row

from c3bench.bench import store
from c3bench.bench.figure_base import keep_figures
from c3bench.bench.palette import COLORS, MARKERS, palette, registry_names, solver_style
from c3bench.bench.plots import all_figures


def _synthetic_suite(root: Path) -> tuple[pd.DataFrame, store.SuitePaths]:
    """Rows for every figure: QP families with float32, warm starts, cond(S) and a trace;
    an LCP with a different solver subset; both projection variants (the closed form on
    c3plus only) and an mpcc with reference optima."""
    paths = store.SuitePaths.of(root, "synthetic")
    paths.root.mkdir(parents=True)
    trace = "traces/alpha.json"
    (paths.root / "traces").mkdir()
    (paths.root / trace).write_text(json.dumps({
        "schema_version": store.SCHEMA_VERSION, "cell_id": "alpha",
        "trace": {"primal_residual": [1.0, 1e-3, 1e-8]}}))
    rows: list[dict[str, Any]] = []
    for i in range(4):
        for solver, scale in (("alpha", 1.0), ("beta", 3.0), ("gamma", 9.0)):
            for precision in ("float64", "float32") if solver == "alpha" else ("float64",):
                for start in ("cold", "warm"):
                    rows.append(row(
                        instance=f"c3_qp-s000-i{i:02d}", solver=solver, precision=precision,
                        start=start, solve_time=scale * 1e-3 * (i + 1), admm_iteration=i,
                        primal_residual_relative=scale * 1e-12 * (i + 1),
                        cond_schur_raw=1e8 * (i + 1), cond_schur_equilibrated=1e3,
                        trace_file=trace if (solver, precision, start, i) == (
                            "alpha", "float64", "cold", 0) else ""))
    for i in range(3):
        for solver in ("beta", "delta"):
            rows.append(row(instance=f"lcp-s{i:03d}", family="lcp", solver=solver,
                            solve_time=2e-4 * (i + 1), primal_residual_relative=1e-10))
    for family, names in (("projection", [f"projection-{v}-s000-i00-k{k}"
                                          for v in ("c3", "c3plus") for k in range(2)]),
                          ("mpcc", ["mpcc-s000", "mpcc-s001"])):
        for name in names:
            for solver in ("scip", "gurobi", "c3plus_closed_form"):
                if solver == "c3plus_closed_form" and "-c3plus-" not in name:
                    continue
                rows.append(row(instance=name, family=family, solver=solver, objective=1.5,
                                reference_solver="scip", reference_objective=1.5,
                                cost_error=0.0, violation_before_projection=1e-3,
                                violation_after_projection=1e-12))
    return make_frame(rows), paths


@pytest.fixture(scope="module")
def drawn(tmp_path_factory: pytest.TempPathFactory) -> dict[str, MplFigure]:
    """Every figure of the synthetic suite, kept open, by key."""
    table, paths = _synthetic_suite(tmp_path_factory.mktemp("plots"))
    with keep_figures() as kept:
        records = all_figures(table, paths)
        drawn = [r for r in records if r.path is not None]
        assert len(drawn) == len(kept)
        figures = {r.key: fig for r, fig in zip(drawn, kept, strict=True)}
        for fig in kept:
            fig.canvas.draw()
        yield figures


def test_every_figure_kind_is_drawn(drawn: dict[str, MplFigure]) -> None:
    expected = {"profile_c3_qp", "profile_lcp", "profile_projection", "times_c3_qp",
                "accuracy_profiles", "pareto_c3_qp", "pareto_projection", "traces_c3_qp",
                "conditioning_admm", "precision_accuracy", "miqp_gap"}
    assert expected <= set(drawn)


def test_every_panel_prints_n(drawn: dict[str, MplFigure]) -> None:
    for key, fig in drawn.items():
        assert fig.axes, key
        for ax in fig.axes:
            texts = [ax.get_title(), *(t.get_text() for t in ax.texts)]
            assert any("n = " in text for text in texts), f"{key}: panel {texts[0]!r}"


def test_legends_sit_outside_the_data(drawn: dict[str, MplFigure]) -> None:
    legends = 0
    for key, fig in drawn.items():
        renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
        assert all(ax.get_legend() is None for ax in fig.axes), f"{key}: legend on a panel"
        for legend in fig.legends:
            legends += 1
            box = legend.get_window_extent(renderer)
            for ax in fig.axes:
                assert not box.overlaps(ax.get_window_extent(renderer)), key
    assert legends >= 6


def _line_colors(fig: MplFigure, label: str) -> set[str]:
    return {str(line.get_color()) for ax in fig.axes for line in ax.get_lines()
            if line.get_label() == label}


def test_a_solver_keeps_its_colour_across_figures_with_other_solvers(
        drawn: dict[str, MplFigure]) -> None:
    # beta is drawn beside alpha and gamma (c3_qp) and beside delta (lcp)
    in_qp = _line_colors(drawn["profile_c3_qp"], "beta")
    in_lcp = _line_colors(drawn["profile_lcp"], "beta")
    assert in_qp == in_lcp == {solver_style("beta").color}
    assert _line_colors(drawn["profile_lcp"], "delta") != in_lcp
    legend_colors = {handle.get_label(): handle.get_color()
                     for fig in (drawn["profile_c3_qp"], drawn["profile_lcp"])
                     for handle in fig.legends[0].legend_handles}  # type: ignore[union-attr]
    assert legend_colors["beta"] == solver_style("beta").color
    assert palette(["beta"]) == {"beta": palette(["alpha", "beta", "gamma"])["beta"]}


def test_registry_solvers_have_distinct_colour_marker_pairs() -> None:
    names = registry_names()
    pairs = {(solver_style(n).color, solver_style(n).marker) for n in names}
    assert len(pairs) == len(names)
    assert len(names) <= len(COLORS) * len(MARKERS)
    assert solver_style("not-a-backend") == solver_style("not-a-backend")


def test_the_closed_form_is_not_run_on_the_c3_variant(drawn: dict[str, MplFigure]) -> None:
    titles = [ax.get_title() for ax in drawn["profile_projection"].axes]
    [c3] = [t for t in titles if "(c3 variant)" in t]
    [c3plus] = [t for t in titles if "(c3plus variant)" in t]
    assert "not run: c3plus_closed_form" in c3 and "n = 2 instances" in c3
    assert "not run" not in c3plus and "n = 2 instances" in c3plus
    closed = solver_style("c3plus_closed_form").color
    [c3_axes] = [ax for ax in drawn["profile_projection"].axes if "(c3 variant)" in
                 ax.get_title()]
    assert closed not in {str(line.get_color()) for line in c3_axes.get_lines()}
