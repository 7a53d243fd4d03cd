"""One fixed colour, marker and line style per solver, and the panel conventions of every
figure: legends outside the data, ``n`` in every panel, solvers not run named.

The style of a solver depends only on its name and the registry's list of backend names
(sorted), never on which solvers one figure shows or in which order: solver ``i`` of the
sorted registry list gets colour ``COLORS[i % 10]``, marker ``MARKERS[i % 9]`` and line style
``LINESTYLES[(i // 10) % 4]``. As 10 and 9 are coprime, the first 90 names all get distinct
(colour, marker) pairs (Chinese remainder theorem). A name outside the registry (a plugin
or a test backend registered later) gets index ``len(registry) + crc32(name) % 90``.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from matplotlib.axes import Axes
from matplotlib.figure import Figure as MplFigure
from matplotlib.legend import Legend
from matplotlib.lines import Line2D
from matplotlib.typing import LineStyleType, MarkerType

COLORS: tuple[str, ...] = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
                           "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
"""matplotlib's tab10 qualitative palette."""
MARKERS: tuple[MarkerType, ...] = ("o", "s", "^", "D", "v", "P", "X", "<", "*")
LINESTYLES: tuple[LineStyleType, ...] = ("-", "--", ":", "-.")
UNKNOWN_SPREAD = len(COLORS) * len(MARKERS)
LEGEND_ROWS = 24
"""Legend entries per column."""


@dataclass(frozen=True)
class SolverStyle:
    """How a solver is drawn in every figure."""

    color: str
    marker: MarkerType
    linestyle: LineStyleType


def registry_names() -> tuple[str, ...]:
    """The registry's backend names, sorted (loads the backend modules once)."""
    from c3bench.solvers import registry

    return tuple(sorted(registry.backends()))


def style_index(name: str, known: Sequence[str]) -> int:
    """Position of ``name`` in ``known``; names outside it hash past its end."""
    if name in known:
        return list(known).index(name)
    return len(known) + zlib.crc32(name.encode()) % UNKNOWN_SPREAD


def solver_style(name: str, known: Sequence[str] | None = None) -> SolverStyle:
    """The fixed style of solver ``name`` (``known`` defaults to :func:`registry_names`)."""
    index = style_index(str(name), registry_names() if known is None else known)
    return SolverStyle(COLORS[index % len(COLORS)], MARKERS[index % len(MARKERS)],
                       LINESTYLES[(index // len(COLORS)) % len(LINESTYLES)])


def palette(names: Iterable[str]) -> dict[str, SolverStyle]:
    """:func:`solver_style` of each name (the registry is read once)."""
    known = registry_names()
    return {str(name): solver_style(str(name), known) for name in names}


def solver_handles(styles: dict[str, SolverStyle], lines: bool = True) -> list[Line2D]:
    """Legend proxies, one per solver in name order (line and marker, or marker only)."""
    return [Line2D([], [], color=style.color, marker=style.marker, markersize=5,
                   linestyle=style.linestyle if lines else "none", label=name)
            for name, style in sorted(styles.items())]


def legend_outside(fig: MplFigure, handles: Sequence[Line2D], title: str | None = None
                   ) -> Legend:
    """One figure legend to the right of every panel (needs a constrained-layout figure);
    two columns past :data:`LEGEND_ROWS` entries."""
    columns = 1 if len(handles) <= LEGEND_ROWS else 2
    return fig.legend(handles=list(handles), loc="outside right upper", fontsize=7,
                      title=title, title_fontsize=7, frameon=False, ncols=columns)


def n_text(n: int, what: str = "instances") -> str:
    """``"n = 8 instances"``."""
    return f"n = {n} {what}"


def panel_title(ax: Axes, title: str, n: int, what: str = "instances",
                not_run: Iterable[str] = ()) -> None:
    """Title with ``n = ...`` on its second line and, when any, the solvers not run on the
    panel's instances on a third (so they are neither failures nor a smaller denominator)."""
    lines = [title, n_text(n, what)]
    missing = sorted(not_run)
    if missing:
        lines.append("not run: " + ", ".join(missing))
    ax.set_title("\n".join(lines), fontsize=8)
