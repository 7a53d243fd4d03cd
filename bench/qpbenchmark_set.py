"""A qpbenchmark test set over an exported directory: run our instances in qpbenchmark.

``c3bench problems export DIR --out OUT --format qpsolvers`` writes each QP instance as
``OUT/<name>.npz`` (``qpsolvers.Problem.save``'s layout), ``OUT/index.json`` and
``OUT/c3bench_test_set.py``, a two-line file defining the class qpbenchmark's command line
looks for (``C3BenchTestSet``, the title-cased file name), so::

    qpbenchmark --results-path OUT/results.csv OUT/c3bench_test_set.py run --solver clarabel \
        --author NAME

runs the exported instances with qpbenchmark's own settings, tolerances and report (Caron et al.,
qpbenchmark). In Python, ``qpbenchmark_class()(OUT)`` (or ``C3BenchTestSet(OUT)``, resolved
lazily from this module) is the same test set; it subclasses ``qpbenchmark.TestSet`` and
yields ``qpbenchmark.Problem`` objects named after the instances, in ``index.json``'s order.

qpbenchmark is optional (``pip install qpbenchmark``; in the ``test`` extra): this module
imports without it and raises :class:`QpbenchmarkMissing` naming the package when the class
is asked for.

Objectives: qpbenchmark's objective is ``1/2 x^T P x + q^T x``; ours adds the instance's
constant, :attr:`objective_offsets` ``[name]`` (from ``index.json``).

References
----------
S. Caron, A. Zaki, P. Otta, D. Arnström, J. Carpentier, F. Yang and P.-A. Leziart,
"qpbenchmark: Benchmark for quadratic programming solvers available in Python", 2024,
https://github.com/qpsolvers/qpbenchmark.
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

from c3bench.problems.errors import C3BenchError, InputError
from c3bench.problems.exporters import INDEX, SHIM_NAME, SHIM_SOURCE

__all__ = ["SHIM_NAME", "SHIM_SOURCE", "QpbenchmarkMissing", "qpbenchmark_class", "read_index"]


class QpbenchmarkMissing(C3BenchError, ImportError):
    """qpbenchmark is not installed (``pip install qpbenchmark``)."""


def _qpbenchmark() -> Any:
    """The ``qpbenchmark`` module; :class:`QpbenchmarkMissing` when it is not installed."""
    try:
        return importlib.import_module("qpbenchmark")
    except ImportError as error:
        raise QpbenchmarkMissing(
            "the qpbenchmark test set needs the package qpbenchmark "
            f"(pip install qpbenchmark): {error}") from error


def read_index(directory: Path) -> list[dict[str, Any]]:
    """The instance entries of an export's ``index.json`` (name, family, file,
    ``objective_offset``); :class:`InputError` when ``directory`` holds no export."""
    index = directory / INDEX
    try:
        table = json.loads(index.read_text())
        entries = list(table["instances"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"{index}: not the index of `c3bench problems export --format "
                         f"qpsolvers` ({type(error).__name__}: {error})") from error
    return entries


@cache
def qpbenchmark_class() -> type[Any]:
    """The class ``C3BenchTestSet``, a ``qpbenchmark.TestSet`` over an exported directory.

    ``C3BenchTestSet(directory)`` (or a subclass setting the class attribute ``directory``,
    as the exported ``c3bench_test_set.py`` does) reads ``directory/index.json``. Its
    ``title``, ``description`` and ``sparse_only`` (``False``: our instances are dense) are
    qpbenchmark's required properties; tolerances and solver settings are qpbenchmark's
    defaults (``default``, ``low_accuracy``, ``mid_accuracy``, ``high_accuracy``).
    """
    qpbenchmark = _qpbenchmark()
    base: Any = qpbenchmark.TestSet

    class C3BenchTestSet(base):
        """The instances of a ``c3bench problems export`` directory as a qpbenchmark test
        set."""

        directory: Path | None = None

        def __init__(self, directory: str | Path | None = None) -> None:
            chosen = directory if directory is not None else type(self).directory
            if chosen is None:
                raise InputError("C3BenchTestSet needs the directory written by "
                                 "`c3bench problems export --format qpsolvers`")
            self.root = Path(chosen)
            self.entries = read_index(self.root)
            self.objective_offsets: dict[str, float] = {
                str(e["name"]): float(e.get("objective_offset", 0.0)) for e in self.entries}
            super().__init__()

        @property
        def title(self) -> str:
            return f"c3bench instances ({self.root.name})"

        @property
        def description(self) -> str:
            return (f"{len(self.entries)} c3bench instances exported from {self.root} "
                    "(convex QPs of contact-implicit MPC and imported problems; our "
                    "objective adds objective_offsets[name]).")

        @property
        def sparse_only(self) -> bool:
            return False

        def __iter__(self) -> Iterator[Any]:
            for entry in self.entries:
                problem = qpbenchmark.Problem.load(str(self.root / entry["file"]))
                problem.name = str(entry["name"])
                yield problem

    return C3BenchTestSet


def __getattr__(name: str) -> Any:
    """``C3BenchTestSet`` resolved on first use (qpbenchmark imported only then)."""
    if name == "C3BenchTestSet":
        return qpbenchmark_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
