"""What every report figure shares: the :class:`Figure` record, panels, baseline rows and
saving.

Figures use cold-start float64 rows unless they are about precision or warm starts. A family's
rows are split into **panels** by (variant, settings profile): a backend that takes one ADMM
variant only (C3+'s closed-form projection) is then drawn on that variant's instances and
named "not run" on the other, instead of counting as a failure there or as 100 % of a
smaller set.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure as MplFigure
from matplotlib.lines import Line2D

from c3bench.bench import store
from c3bench.bench.metrics import family_label, ranked_time_label, with_variants
from c3bench.bench.palette import SolverStyle, legend_outside, palette
from c3bench.problems.names import Precision, Profile, Start

DPI = 110
SETTINGS_ORDER: tuple[str, ...] = tuple(Profile)
"""Order of the settings profiles in figures and tables."""
LEGEND_WIDTH = 2.0
"""Inches added to a figure's width for the legend beside its panels."""
DRAW_FLOOR = 1e-18
"""Log-scale axes draw smaller values (exact zeros) at this level; captions say so."""
_KEPT: list[MplFigure] | None = None


def time_label() -> str:
    """The ranked time's name for axis labels and captions (``total time``)."""
    return ranked_time_label()


@dataclass
class Figure:
    """One figure of the report.

    Attributes
    ----------
    key
        Stable identifier (also the file stem).
    title
        Heading.
    caption
        One line describing axes and what is shown.
    path
        PNG path relative to the suite directory (``None`` when there was no data).
    note
        Why the figure is missing (``""`` when drawn).
    """

    key: str
    title: str
    caption: str
    path: str | None = None
    note: str = ""


@dataclass
class Panel:
    """The rows of one panel: a family's (variant, settings) group."""

    family: str
    variant: str
    settings: str
    rows: pd.DataFrame

    @property
    def label(self) -> str:
        """``family (variant variant), settings``."""
        return f"{family_label(self.family, self.variant)}, {self.settings}"

    @property
    def instances(self) -> int:
        """Distinct instances of the panel."""
        return int(self.rows["instance"].nunique())


def preferred_settings(frame: pd.DataFrame) -> str | None:
    """``default`` when present, else the first profile of :data:`SETTINGS_ORDER` present."""
    present = set(frame["settings"])
    for name in SETTINGS_ORDER:
        if name in present:
            return name
    return min(present) if present else None


def ordered_settings(frame: pd.DataFrame) -> list[str]:
    """The settings profiles present, in :data:`SETTINGS_ORDER` (unknown ones last)."""
    present = set(frame["settings"])
    return [s for s in SETTINGS_ORDER if s in present] + sorted(present - set(SETTINGS_ORDER))


def baseline(frame: pd.DataFrame) -> pd.DataFrame:
    """The cold-start float64 rows (with a ``variant`` column)."""
    rows = frame[(frame["precision"] == Precision.FLOAT64) & (frame["start"] == Start.COLD)]
    return with_variants(rows)


def panels(rows: pd.DataFrame, settings: list[str] | None = None) -> list[Panel]:
    """The (variant, settings) panels of one family's rows, variants sorted, settings in
    :data:`SETTINGS_ORDER` (only ``settings`` when given)."""
    rows = with_variants(rows)
    out = []
    for profile in settings if settings is not None else ordered_settings(rows):
        for variant in sorted(set(rows["variant"])):
            mine = rows[(rows["variant"] == variant) & (rows["settings"] == profile)]
            if len(mine):
                out.append(Panel(str(mine["family"].iloc[0]), str(variant), profile, mine))
    return out


def not_run(panel: Panel, family_rows: pd.DataFrame) -> list[str]:
    """Solvers with rows in the family but none in the panel's variant and settings."""
    others = family_rows[family_rows["settings"] == panel.settings]
    return sorted(set(others["solver"]) - set(panel.rows["solver"]))


def new_figure(panel_count: int, width: float, height: float, max_columns: int = 4,
               legend: bool = True) -> tuple[MplFigure, list[plt.Axes]]:
    """A constrained-layout figure of ``panel_count`` panels of ``width x height`` inches,
    at most ``max_columns`` per row (plus :data:`LEGEND_WIDTH` for a legend beside them);
    the axes flattened, unused ones removed."""
    columns = max(1, min(panel_count, max_columns))
    rows = -(-panel_count // columns)
    fig, axes = plt.subplots(rows, columns, squeeze=False, layout="constrained",
                             figsize=(width * columns + (LEGEND_WIDTH if legend else 0.0),
                                      height * rows))
    flat = [ax for row in axes for ax in row]
    for ax in flat[panel_count:]:
        ax.remove()
    return fig, flat[:panel_count]


@contextmanager
def keep_figures() -> Iterator[list[MplFigure]]:
    """Inside the block, :func:`save` still writes each PNG but keeps the figure open and
    appends it to the yielded list (to inspect the drawn objects); closed on exit."""
    global _KEPT
    kept: list[MplFigure] = []
    previous, _KEPT = _KEPT, kept
    try:
        yield kept
    finally:
        _KEPT = previous
        for fig in kept:
            plt.close(fig)


def save(fig: MplFigure, paths: store.SuitePaths, key: str) -> str:
    """Write ``figures/<key>.png`` under the suite and return that relative path."""
    paths.figures.mkdir(parents=True, exist_ok=True)
    relative = f"figures/{key}.png"
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(paths.root / relative, dpi=DPI, metadata={"Software": None})
    if _KEPT is not None:
        _KEPT.append(fig)
    else:
        plt.close(fig)
    return relative


PanelDrawer = Callable[[Axes, Panel, dict[str, SolverStyle], pd.DataFrame], None]
"""Draws one (variant, settings) panel: ``(axes, panel, solver styles, the family's rows)``."""


@dataclass(frozen=True)
class FamilyFigure:
    """A figure drawn once per family, one panel per (variant, settings profile), over the
    cold-start float64 rows (:func:`family_figures`).

    Attributes
    ----------
    key, title
        File-stem prefix and heading (``<key>_<family>``, ``<title>: <family>``).
    caption
        The caption of a family's figure.
    note
        Why a family has no figure when ``drawable`` says so.
    drawable
        Whether a family's rows have anything to draw.
    draw
        One panel.
    size
        Panel width and height (inches) for a family's rows.
    legend
        The handles of the legend beside the panels (``None``: no legend).
    """

    key: str
    title: str
    caption: Callable[[str], str]
    note: str
    drawable: Callable[[pd.DataFrame], bool]
    draw: PanelDrawer
    size: Callable[[pd.DataFrame], tuple[float, float]]
    legend: Callable[[dict[str, SolverStyle]], Sequence[Line2D]] | None


def family_figures(frame: pd.DataFrame, paths: store.SuitePaths,
                   spec: FamilyFigure) -> list[Figure]:
    """One :class:`Figure` per family of ``frame`` as ``spec`` describes it (a note instead of
    a file when the family has nothing to draw)."""
    out = []
    rows_all = baseline(frame)
    for family in sorted(set(frame["family"])):
        rows = rows_all[rows_all["family"] == family]
        figure = Figure(f"{spec.key}_{family}", f"{spec.title}: {family}",
                        spec.caption(family))
        out.append(figure)
        if rows.empty or not spec.drawable(rows):
            figure.note = spec.note
            continue
        groups = panels(rows)
        styles = palette(set(rows["solver"]))
        width, height = spec.size(rows)
        fig, axes = new_figure(len(groups), width, height, legend=spec.legend is not None)
        for ax, panel in zip(axes, groups, strict=True):
            spec.draw(ax, panel, styles, rows)
        if spec.legend is not None:
            legend_outside(fig, spec.legend(styles))
        figure.path = save(fig, paths, figure.key)
    return out
