"""Deterministic Markdown tables for the report and ``compare``.

Numbers are formatted with fixed rules (:func:`fmt`) so that a regenerated report diffs well.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from c3bench.bench.metrics import LOG_FLOOR

NOT_RUN = "not run"
"""Cell text of a solver that was not run on a group (never a failure, never a success)."""


def fmt(value: Any, kind: str) -> str:
    """Deterministic cell text: ``-`` for missing values; fixed formats per kind.

    Kinds: ``text``, ``int``, ``percent``, ``ms`` (seconds shown in ms), ``us`` (seconds
    shown in us), ``rel`` (ratios), ``num``, ``res`` (an accuracy mean: ``0`` within a
    factor 2 of :data:`bench.metrics.LOG_FLOOR`, i.e. every value was an exact zero; else like
    ``sci``) and ``sci``.
    """
    if kind == "text":
        return str(value).replace("|", "\\|").replace("\n", " ")
    try:
        number = float(value)
    except (TypeError, ValueError):
        return "-"
    if math.isnan(number):
        return "-"
    if math.isinf(number):
        return "inf" if number > 0 else "-inf"
    if kind == "int":
        return str(int(number))
    if kind == "percent":
        return f"{100.0 * number:.1f}%"
    if kind == "ms":
        return f"{1e3 * number:.3g}"
    if kind == "us":
        return f"{1e6 * number:.3g}"
    if kind == "rel":
        return f"{number:.2f}" if 0.01 <= abs(number) < 100 else f"{number:.3g}"
    if kind == "num":
        return f"{number:.4g}"
    if kind == "res" and 0.0 <= number <= 2.0 * LOG_FLOOR:
        return "0"
    return f"{number:.1e}"


def fmt_accuracy(value: Any, tolerance: float) -> str:
    """An accuracy figure as :func:`fmt` ``res``, in bold when above ``tolerance``."""
    text = fmt(value, "res")
    try:
        above = float(value) > tolerance
    except (TypeError, ValueError):
        above = False
    return f"**{text}**" if above else text


def fraction(part: int, whole: int) -> str:
    """``"87.5% (7/8)"``; ``-`` when ``whole`` is 0."""
    return f"{fmt(part / whole, 'percent')} ({part}/{whole})" if whole else "-"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]],
                   align: str | None = None) -> str:
    """A Markdown table; ``align`` has one letter per column, ``l`` or ``r`` (default: first
    column left, the others right)."""
    align = align or "l" + "r" * (len(headers) - 1)
    marks = {"l": ":---", "r": "---:"}
    lines = ["| " + " | ".join(headers) + " |",
             "|" + "|".join(marks[a] for a in align) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
