"""The ``c3bench`` command line (also ``python -m c3bench``): the one parser of every command.

Subcommands: ``problems generate`` / ``problems list`` (instances), ``solvers`` (the
registry), ``run`` / ``report`` / ``compare`` (the benchmark), ``perf`` (control-step time),
``closed-loop`` / ``closed-loop-suite`` / ``sweep`` (C3 / C3+ driving the MuJoCo cube; their
handlers are in :mod:`bench.cli_closed_loop`). README's "Command line" section is the synopsis
(``tests/test_cli.py`` checks it against this parser).

Conventions, the same in every command:

* a list option takes its values space or comma separated, or repeated: ``--x a b``,
  ``--x a,b`` and ``--x a --x b`` are equal (:class:`bench.cli_options.ListAction`);
* ``--results ROOT`` is the results root; each command reads and writes its own folder under
  it (:mod:`bench.store`), default ``results``;
* exit codes: 0 success, 1 error (nothing to read, a failed command, cells left missing, an
  expected fault such as a disk filling up during the work or a Dask scheduler that does not
  answer: one line ``error: ...``), 2 bad
  input (one line ``error: ...``, never a traceback: an option, a malformed scheduler address, a
  results root that cannot be written, a configuration value, a damaged input or results
  file), 130 interrupted (Ctrl-C), 143 terminated (SIGTERM, one line ``terminated
  (SIGTERM)``): :func:`main` turns SIGTERM into :class:`Terminated` around every command, so
  a terminated command cleans up (children, temporary folders) exactly as after Ctrl-C;
* every argument is checked before any work (:mod:`bench.cli_checks`); ``--debug`` (anywhere
  on the line) shows the traceback of an error instead of the one line; an unexpected
  exception (a bug) prints ``internal error`` and its traceback.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from c3bench.bench import cli_checks, perf_store, store
from c3bench.bench.cli_closed_loop import add_closed_loop
from c3bench.bench.cli_options import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    EXIT_USAGE,
    Parser,
    add_executor,
    add_list,
    add_quiet,
    add_results,
    nonnegative_int,
    parse_command,
    path_text,
    positive_float,
    positive_int,
)
from c3bench.bench.cli_problems import add_problems, add_skip_bad, capture_for, read_instance_dir
from c3bench.bench.lock import terminate_as_exception
from c3bench.bench.planning import DEFAULT_PRECISIONS, DEFAULT_SETTINGS, SEQUENCE_SCOPE, STARTS
from c3bench.problems.capture import SUITES
from c3bench.problems.errors import C3BenchError, InputError, Terminated
from c3bench.problems.names import Family, Precision, Profile, Start


def load_plugins(entries: Sequence[str]) -> None:
    """Load ``MODULE`` / ``MODULE:FUNCTION`` plugins; one that is missing or fails to load
    (whatever it raises) is an :class:`InputError`."""
    from c3bench.solvers import registry

    for entry in entries:
        try:
            registry.import_plugins([entry])
        except (Exception, SystemExit) as error:  # a plugin may raise anything, or exit
            raise InputError(f"cannot load plugin {entry!r} (--plugin): "
                             f"{type(error).__name__}: {error}") from error


# --- solvers ------------------------------------------------------------------------------------
def cmd_solvers(args: argparse.Namespace) -> int:
    """Print every registered backend: availability, version, families, precisions."""
    from c3bench.solvers import registry

    load_plugins(args.plugin)
    rows = [{
        "solver": info.name,
        "available": "yes" if info.available else "no",
        "version": info.version,
        "families": ",".join(info.families),
        "precisions": ",".join(info.precisions),
        "note": info.reason or info.description,
    } for info in registry.available()]
    with pd.option_context("display.max_colwidth", 70, "display.width", 200):
        print(pd.DataFrame(rows).to_string(index=False))
    for module, error in registry.module_errors().items():
        print(f"warning: backend module {module} failed to load: {error}", file=sys.stderr)
    return EXIT_OK


# --- run, report, compare, perf ---------------------------------------------------------------
def check_run(args: argparse.Namespace) -> None:
    """Every argument of ``run``, before any work: the results root, the suite, the plugins,
    the solvers, a selection that plans cells, and the stored instance files."""
    from c3bench.solvers import registry

    cli_checks.check_output_path("--results", args.results)
    if args.sequence_all and Start.SEQUENCE not in args.start:
        raise InputError("--sequence-all widens the sequence cells, but --start "
                         f"{','.join(args.start)} plans none (add --start sequence)")
    in_suite = _check_instances_option(args) if args.instances is not None else None
    if args.instances is None:
        cli_checks.check_suite_to_run(args.suite, args.results)
    load_plugins(args.plugin)
    available = cli_checks.check_solvers(args.solvers, registry.available())
    cli_checks.check_selection(available, args.families, args.precision,
                               in_suite if args.instances is not None
                               else cli_checks.suite_families(args.suite, args.results))
    cli_checks.check_output_path("--results", store.SuitePaths.of(args.results, args.suite).root)
    instances = store.SuitePaths.of(args.results, args.suite).instances
    if args.instances is None and instances.is_dir():  # a packaged suite's is regenerated
        read_instance_dir(instances, args.skip_bad, check_manifest=args.suite not in SUITES)


def _check_instances_option(args: argparse.Namespace) -> set[str]:
    """``run --instances DIR``: a directory of instances that load (bad files under the
    ``--skip-bad`` policy); the suite becomes its name. Returns the families it holds."""
    directory = Path(args.instances)
    if not directory.is_dir():
        raise InputError(f"--instances: {directory} is not a directory")
    if any(directory.rglob("*.npz")) and not any(directory.rglob("*.json")):
        raise InputError(f"--instances: {directory} holds .npz files but no instance headers; "
                         f"import them first: c3bench problems import {directory} --out DIR")
    problems = read_instance_dir(directory, args.skip_bad)
    if not problems:
        raise InputError(f"--instances: no instances under {directory}")
    args.suite = directory.resolve().name
    cli_checks.check_suite_name("--instances", args.suite)
    return {str(problem.family) for problem in problems}


def cmd_run(args: argparse.Namespace) -> int:
    """Run a suite (generating its instances first when missing), then write the report."""
    from c3bench.bench.report import write_report
    from c3bench.bench.runner import run_suite

    check_run(args)
    summary = run_suite(
        args.suite, results_dir=args.results, solvers=args.solvers,
        settings=args.settings, precisions=args.precision, starts=args.start,
        families=args.families, jobs=args.jobs, scheduler=args.scheduler,
        rerun=args.rerun, repeats=args.repeats, time_limit=args.time_limit,
        reference_time_limit=args.reference_time_limit,
        capture=capture_for("controller"), progress=not args.quiet,
        max_cells=args.max_cells, preload=tuple(args.plugin), skip_bad=args.skip_bad,
        instances=args.instances,
        sequence_scope=None if args.sequence_all else SEQUENCE_SCOPE)
    if summary.planned == 0:
        raise InputError("nothing to run: no solver accepts any instance of the selection "
                         "(--solvers, --families, --precision)")
    for name, reason in sorted(summary.skipped_solvers.items()):
        print(f"skipped {name}: {reason}", file=sys.stderr)
    print(f"{summary.suite}: {summary.planned} cells planned, {summary.already_done} already "
          f"stored, {summary.ran} run ({summary.failed} failed), "
          f"{summary.references_computed} references computed"
          + (f", {summary.warm_without_reference} warm cells without a reference start"
             if summary.warm_without_reference else "")
          + (f", {summary.stale_removed} stale cells of changed instances removed"
             if summary.stale_removed else "")
          + (f", {summary.adopted} rows of the stored table (no cell files) kept"
             if summary.adopted else ""))
    print(f"solver output: {store.SuitePaths(summary.root).solver_log}")
    if not args.no_report and (summary.ran or summary.already_done or not summary.missing):
        print(f"report: {write_report(summary.suite, args.results)}")
    if summary.missing:
        reasons = "; ".join(summary.missing_reasons) or "infrastructure faults"
        print(f"{summary.missing} cells missing ({reasons}); run again to complete them",
              file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    """Write ``ROOT/<suite>/report.md`` and its figures."""
    from c3bench.bench.report import write_report

    cli_checks.check_output_path("--results", args.results)
    cli_checks.check_stored_suite(args.suite, args.results)
    cli_checks.check_output_path("--results", store.SuitePaths.of(args.results, args.suite).root)
    path = write_report(args.suite, args.results, figures=not args.no_figures,
                        budget_ms=args.budget_ms)
    print(f"report: {path}")
    return EXIT_OK


def cmd_compare(args: argparse.Namespace) -> int:
    """Print who wins between two solvers, per family and settings."""
    from c3bench.bench.compare import compare

    if args.a == args.b:
        raise InputError(f"compare: A and B are both {args.a!r}; give two different solvers")
    cli_checks.check_stored_suite(args.suite, args.results)
    print(compare(args.suite, args.a, args.b, args.results), end="")
    return EXIT_OK


def cmd_perf(args: argparse.Namespace) -> int:
    """Time one C3+ control step per backend and number of samples."""
    from c3bench.bench.perf import PERF_FIGURE, PerfSettings, run_perf

    cli_checks.check_output_path("--results", args.results)
    cli_checks.check_cpu(args.cpu)
    settings = PerfSettings(samples=tuple(args.samples), backends=tuple(args.backend),
                            precisions=tuple(args.precision), device=args.device,
                            repeats=args.repeats, warmup=args.warmup,
                            iterations=args.iterations, reference_budget=args.reference_budget,
                            seed=args.seed, results_dir=Path(args.results), cpu=args.cpu,
                            weighting=args.weighting, worker_processes=args.worker_processes)
    frame = run_perf(settings)
    runs = {str(run) for run in frame["run_id"]}
    written = [*(path for path in perf_store.perf_run_files(settings.results_dir)
                 if path.stem in runs),
               *perf_store.perf_files(settings.results_dir),
               store.perf_dir(settings.results_dir) / "figures" / PERF_FIGURE]
    print("# wrote " + ", ".join(str(path) for path in written if path.exists()))
    return EXIT_OK


# --- the parser ---------------------------------------------------------------------------------
def _add_plugin(parser: argparse.ArgumentParser, loaded: str) -> None:
    """``--plugin MODULE[:FUNCTION]``."""
    add_list(parser, "--plugin", metavar="MODULE[:FUNCTION]", default=(),
             help=f"plugins that register extra backends: MODULE is imported, then "
                  f"FUNCTION called when given; loaded {loaded}", default_text="none")


def _add_benchmark(sub: Any) -> None:
    """``solvers``, ``run``, ``report`` and ``compare``."""
    solvers = sub.add_parser("solvers", help="list solver backends",
                             description="Every backend: availability, version, families.")
    _add_plugin(solvers, "before listing")
    solvers.set_defaults(handler=cmd_solvers)

    run = sub.add_parser("run", help="run a benchmark suite (resumable)",
                         description="Run every (instance, solver, settings, precision, "
                                     "start) cell of a suite; finished cells are kept and "
                                     "skipped on the next run.")
    run.add_argument("--suite", default="quick", metavar="NAME",
                     help=f"suite ({', '.join(SUITES)}, or a stored one; default: quick)")
    run.add_argument("--instances", default=None, metavar="DIR", type=path_text,
                     help="run this directory of instances (e.g. from `c3bench problems "
                          "import`) instead of a generated suite: they are copied to "
                          "ROOT/<DIR name>/instances (with a manifest written when DIR has "
                          "none) and the results go to ROOT/<DIR name>/; --suite is then "
                          "ignored")
    add_results(run, "writes ROOT/<suite>/ (with --instances: ROOT/<DIR name>/)")
    add_list(run, "--solvers", metavar="NAME", help="backends",
             default_text="every available one")
    add_list(run, "--settings", metavar="PROFILE", choices=tuple(Profile),
             default=DEFAULT_SETTINGS, help="settings profiles")
    add_list(run, "--precision", metavar="PRECISION", choices=tuple(Precision),
             default=DEFAULT_PRECISIONS, help="precisions, float32 only where a backend runs in it")
    add_list(run, "--start", metavar="START", choices=tuple(Start), default=STARTS,
             help="cold, warm and/or sequence starts (sequence: the 10 QP steps of one ADMM "
                  "run per state with the backend as QP step; C3+ bounded heads unless "
                  "--sequence-all)")
    run.add_argument("--sequence-all", action="store_true",
                     help="sequence cells for every c3plus_qp / c3_qp head (C3 and the "
                          "equality variant too; C3's enumeration projection makes them slow)")
    add_list(run, "--families", metavar="FAMILY", choices=tuple(Family),
             help="restrict to these families", default_text="all")
    add_executor(run, "cells")
    run.add_argument("--repeats", type=positive_int, default=3, metavar="N",
                     help="timed repeats after one untimed warm-up (default: 3)")
    run.add_argument("--time-limit", type=positive_float, default=10.0, metavar="S",
                     help="seconds per solve (default: 10)")
    run.add_argument("--reference-time-limit", type=positive_float, default=60.0, metavar="S",
                     help="seconds per reference solve (default: 60)")
    run.add_argument("--max-cells", type=positive_int, default=None, metavar="N",
                     help="stop after this many cells (the rest stay for a later run)")
    _add_plugin(run, "here and in every worker")
    add_skip_bad(run)
    run.add_argument("--no-report", action="store_true", help="do not write the report")
    add_quiet(run)
    run.set_defaults(handler=cmd_run)

    report = sub.add_parser("report", help="write ROOT/<suite>/report.md and figures",
                            description="Write a stored suite's report, figures and summary.")
    report.add_argument("--suite", default="quick", metavar="NAME",
                        help="stored suite (default: quick)")
    add_results(report, "reads and writes ROOT/<suite>/")
    report.add_argument("--no-figures", action="store_true", help="tables only")
    report.add_argument("--budget-ms", type=positive_float, default=None, metavar="MS",
                        help="control budget of one QP solve for the budget table, in ms "
                             "(default: control period / ADMM iterations = 50 ms / 10 = 5 ms)")
    report.set_defaults(handler=cmd_report)

    compare = sub.add_parser("compare", help="compare two solvers on a stored suite",
                             description="Who wins between A and B, per family and settings, "
                                         "on success, time and accuracy.")
    compare.add_argument("a", metavar="A", help="first solver")
    compare.add_argument("b", metavar="B", help="second solver")
    compare.add_argument("--suite", default="quick", metavar="NAME",
                         help="stored suite (default: quick)")
    add_results(compare, "reads ROOT/<suite>/")
    compare.set_defaults(handler=cmd_compare)


def _add_perf(sub: Any) -> None:
    """``perf``."""
    from c3bench.bench.perf import BACKENDS, DEFAULT_SAMPLES, DEVICES, PerfSettings

    defaults = PerfSettings()
    perf = sub.add_parser("perf", help="time one C3+ control step per backend and samples",
                          description="Time the LCS build plus the ADMM of one C3+ control "
                                      "step (bench/perf.py).")
    add_list(perf, "--samples", metavar="N", item=positive_int, default=DEFAULT_SAMPLES,
             help="numbers of model samples")
    add_list(perf, "--backend", metavar="NAME", default=BACKENDS,
             help="backends; c3-<QP backend> runs the reference controller with any registry "
                  "QP backend that takes c3plus_qp (e.g. c3-daqp, c3-proxqp_dense)")
    add_list(perf, "--precision", metavar="PRECISION", choices=tuple(Precision),
             default=defaults.precisions, help="precisions of the c3plus backends")
    perf.add_argument("--device", choices=DEVICES, default=defaults.device,
                      help="device of the JAX backend; the others run on the CPU "
                           "(default: cpu)")
    perf.add_argument("--repeats", type=positive_int, default=defaults.repeats, metavar="N",
                      help=f"timed rounds, each a block of four consecutive control steps "
                           f"per backend (the first stored cache-cold, the others warm) "
                           f"(default: {defaults.repeats})")
    perf.add_argument("--warmup", type=nonnegative_int, default=defaults.warmup, metavar="N",
                      help=f"untimed rounds first (default: {defaults.warmup})")
    perf.add_argument("--iterations", type=positive_int, default=defaults.iterations,
                      metavar="N",
                      help=f"ADMM iterations per step (default: {defaults.iterations})")
    perf.add_argument("--reference-budget", type=positive_float,
                      default=defaults.reference_budget, metavar="S",
                      help="seconds allowed per reference-controller configuration "
                           f"(default: {defaults.reference_budget:g})")
    perf.add_argument("--seed", type=nonnegative_int, default=defaults.seed, metavar="N",
                      help=f"seed of the sampled cube sides (default: {defaults.seed})")
    perf.add_argument("--weighting", action=argparse.BooleanOptionalAction,
                      default=defaults.weighting,
                      help="weight the samples of each step with n > 1 by their LCP "
                           "prediction error over the last 5 observed transitions, as the "
                           "robust closed loop does (default: on)")
    perf.add_argument("--cpu", type=nonnegative_int, default=None, metavar="CORE",
                      help="pin the process to this CPU core; XLA may otherwise use a "
                           "second core for the JAX backend")
    perf.add_argument("--same-process", dest="worker_processes", action="store_false",
                      help="measure every backend in this process instead of one worker "
                           "process each (the JAX runtime then slows the compiled step)")
    add_results(perf, "writes ROOT/perf/")
    perf.set_defaults(handler=cmd_perf)


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command (each subcommand sets ``handler``)."""
    from c3bench import __version__

    parser = Parser(prog="c3bench",
                    description="Benchmark solvers on the subproblems of contact-implicit MPC "
                                "(C3 / C3+).")
    parser.add_argument("--version", action="version", version=f"c3bench {__version__}",
                        help="print the version and exit")
    parser.add_argument("--debug", action="store_true",
                        help="on an error, show the full traceback instead of the one-line "
                             "message (also accepted after the command)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                help="the command; `c3bench COMMAND --help` for its options")
    add_problems(sub)
    _add_benchmark(sub)
    add_closed_loop(sub)
    _add_perf(sub)
    return parser


def check_common(args: argparse.Namespace) -> None:
    """The options several commands share, checked before the command's handler runs:
    ``--scheduler`` is a Dask address (before any folder is made or client started)."""
    if getattr(args, "scheduler", None) is not None:
        from c3bench.bench.executors import check_scheduler_address

        check_scheduler_address(args.scheduler)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments), run the command, return its code.

    Expected faults print one line ``error: ...`` (with ``--debug``, the traceback as well):
    bad input exits 2, other c3bench errors and ``OSError`` (a disk that fills up during the
    work) exit 1. Ctrl-C exits 130, SIGTERM (:class:`Terminated`, raised by the handler
    installed here for the whole command) 143. Anything else is a bug: ``internal error`` and
    its traceback, exit 1.
    """
    arguments = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in arguments:  # accepted anywhere on the line, parsed as the global flag
        arguments = ["--debug", *(word for word in arguments if word != "--debug")]
    try:
        args = parse_command(build_parser(), arguments)
    except SystemExit as stop:  # --help, --version, usage errors
        return stop.code if isinstance(stop.code, int) else EXIT_ERROR
    try:
        with terminate_as_exception():  # SIGTERM stops every command like Ctrl-C
            check_common(args)
            return int(args.handler(args))
    except KeyboardInterrupt as stop:  # Terminated (SIGTERM) among them
        if not getattr(stop, "__notes__", None):  # a run that said what it kept: one line
            print("terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted",
                  file=sys.stderr)
        return EXIT_TERMINATED if isinstance(stop, Terminated) else EXIT_INTERRUPTED
    except ValueError as error:  # InputError and SchemaVersionError among them
        return _fail(error, str(error), EXIT_USAGE, args.debug)
    except OSError as error:  # disk full, read-only, a path under a file, nothing to read
        return _fail(error, cli_checks.describe_os_error(error), EXIT_ERROR, args.debug)
    except C3BenchError as error:  # a failed command, a locked results directory
        return _fail(error, str(error), EXIT_ERROR, args.debug)
    except Exception as error:  # noqa: BLE001 - a bug: say so, with the traceback
        print(f"internal error: {type(error).__name__}: {error} (a bug in c3bench; please "
              "report it with the traceback below)", file=sys.stderr)
        traceback.print_exc()
        return EXIT_ERROR


def _fail(error: BaseException, message: str, code: int, debug: bool) -> int:
    """Print ``error: message`` (after the traceback with ``--debug``); return ``code``."""
    if debug:
        traceback.print_exception(error)
    line = " ".join(part.strip() for part in message.splitlines() if part.strip())
    print(f"error: {line or type(error).__name__}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
