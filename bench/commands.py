"""Sub-commands ``run``, ``report`` and ``compare`` for the ``c3bench`` command line.

``register_commands(subparsers)`` adds them to an ``argparse`` sub-parser set; each parser has
``handler`` set to its function, which takes the parsed namespace and returns an exit code
(0 success, 1 error, 2 bad arguments, 130 interrupted).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from c3bench.solvers.base import PRECISIONS, PROFILES

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


def _split(values: list[str] | None) -> list[str] | None:
    """Accept both ``--solvers a b`` and ``--solvers a,b``."""
    if values is None:
        return None
    return [part for value in values for part in value.split(",") if part]


def cmd_run(args: argparse.Namespace, capture: Any = None) -> int:
    """Run a suite (generating its instances first when missing), then write the report."""
    from c3bench.bench.report import write_report
    from c3bench.bench.runner import run_suite
    from c3bench.bench.store import SchemaVersionError

    try:
        summary = run_suite(
            args.suite, results_dir=args.results, solvers=_split(args.solvers),
            settings=_split(args.settings) or list(args.default_settings),
            precisions=_split(args.precision) or list(PRECISIONS),
            starts=_split(args.start) or ["cold", "warm"],
            families=_split(args.families), jobs=args.jobs, scheduler=args.scheduler,
            rerun=args.rerun, repeats=args.repeats, time_limit=args.time_limit,
            reference_time_limit=args.reference_time_limit, capture=capture,
            progress=not args.quiet, max_cells=args.max_cells,
            preload=tuple(_split(args.plugin) or ()))
    except KeyboardInterrupt:
        print("interrupted; finished cells are stored, run again to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, SchemaVersionError) as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_USAGE
    for name, reason in sorted(summary.skipped_solvers.items()):
        print(f"skipped {name}: {reason}", file=sys.stderr)
    print(f"{summary.suite}: {summary.planned} cells planned, {summary.already_done} already "
          f"stored, {summary.ran} run ({summary.failed} failed), "
          f"{summary.references_computed} references computed"
          + (f", {summary.warm_without_reference} warm cells without a reference start"
             if summary.warm_without_reference else "")
          + (f", {summary.stale_removed} stale cells of changed instances removed"
             if summary.stale_removed else ""))
    print(f"solver output: {summary.root / 'solver_output.log'}")
    if not args.no_report:
        path = write_report(summary.suite, args.results)
        print(f"report: {path}")
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    """Write ``results/<suite>/report.md`` and its figures."""
    from c3bench.bench.report import write_report
    from c3bench.bench.store import SchemaVersionError

    try:
        path = write_report(args.suite, args.results, figures=not args.no_figures)
    except (FileNotFoundError, SchemaVersionError) as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_ERROR
    print(f"report: {path}")
    return EXIT_OK


def cmd_compare(args: argparse.Namespace) -> int:
    """Print who wins between two solvers, per family and settings."""
    from c3bench.bench.compare import compare
    from c3bench.bench.store import SchemaVersionError

    try:
        text = compare(args.suite, args.a, args.b, args.results)
    except (FileNotFoundError, SchemaVersionError) as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_ERROR
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_USAGE
    print(text, end="")
    return EXIT_OK


def register_commands(subparsers: Any, capture: Any = None) -> None:
    """Add ``run``, ``report`` and ``compare`` to ``subparsers`` (from ``add_subparsers``).

    ``capture`` (optional) is passed to ``problems.suites.generate_suite`` when ``run`` has
    to generate a suite's instances.
    """
    run = subparsers.add_parser("run", help="run a benchmark suite (resumable)",
                                description="Run every (instance, solver, settings, "
                                "precision, start) cell of a suite; finished cells are kept "
                                "and skipped on the next run.")
    run.add_argument("--suite", default="quick", help="suite name (default: quick)")
    run.add_argument("--solvers", nargs="+", help="backends (default: every available one)")
    run.add_argument("--settings", nargs="+", help=f"profiles among {', '.join(PROFILES)} "
                     "(default: default)")
    run.add_argument("--precision", nargs="+", help="float64 and/or float32 (default: both, "
                     "float32 only where a backend supports it)")
    run.add_argument("--start", nargs="+", help="cold and/or warm (default: both)")
    run.add_argument("--families", nargs="+", help="restrict to these families")
    run.add_argument("--jobs", type=int, default=2, help="local worker processes (default 2)")
    run.add_argument("--scheduler", help="Dask scheduler address (runs cells on that cluster)")
    run.add_argument("--rerun", action="store_true", help="run cells even if stored")
    run.add_argument("--repeats", type=int, default=3, help="timed repeats (default 3)")
    run.add_argument("--time-limit", type=float, default=10.0, help="seconds per solve")
    run.add_argument("--reference-time-limit", type=float, default=60.0,
                     help="seconds per reference solve")
    run.add_argument("--max-cells", type=int, help="stop after this many cells")
    run.add_argument("--plugin", nargs="+", help="MODULE or MODULE:FUNCTION loaded in every "
                     "worker (to register extra backends)")
    run.add_argument("--results", default="results", help="results folder (default results)")
    run.add_argument("--no-report", action="store_true", help="do not write the report")
    run.add_argument("--quiet", action="store_true", help="no progress bars")
    run.set_defaults(handler=lambda args: cmd_run(args, capture), default_settings=("default",))

    report = subparsers.add_parser("report", help="write results/<suite>/report.md")
    report.add_argument("--suite", default="quick")
    report.add_argument("--results", default="results")
    report.add_argument("--no-figures", action="store_true", help="tables only")
    report.set_defaults(handler=cmd_report)

    comp = subparsers.add_parser("compare", help="compare two solvers on a stored suite")
    comp.add_argument("a", help="first solver")
    comp.add_argument("b", help="second solver")
    comp.add_argument("--suite", default="quick")
    comp.add_argument("--results", default="results")
    comp.set_defaults(handler=cmd_compare)
