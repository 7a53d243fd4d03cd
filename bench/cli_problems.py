"""``c3bench problems generate`` / ``list`` / ``import`` / ``export``: the instance commands
(:mod:`bench.cli`).

``import`` turns the user's own problems (qpsolvers' ``.npz`` files, CasADi ``conic`` problems
saved by :func:`c3bench.problems.conic.save_conic`, LCPs as ``F``/``q`` ``.npz`` files, or a
module yielding ``qpsolvers.Problem`` objects) into a directory of ``qp`` / ``lcp_general``
instances with a manifest (:mod:`c3bench.problems.importers`); ``export`` writes instances in
qpsolvers' format with a qpbenchmark test set (:mod:`c3bench.problems.exporters`).

Also the instance helpers other commands share: :func:`capture_for` (the ADMM-iterate source
of a generation), :func:`read_instance_dir` (a directory's instances under the ``--skip-bad``
policy) and :func:`add_skip_bad`.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import cli_checks
from c3bench.bench.cli_options import EXIT_ERROR, EXIT_OK, add_quiet, path_text
from c3bench.problems.capture import SUITES, Capture
from c3bench.problems.errors import InputError, InstanceFormatError
from c3bench.problems.instance import Problem
from c3bench.problems.names import Variant

CAPTURE_QP_BACKEND = "clarabel"
"""QP solver of the controller runs whose iterates become suite instances (exact and
deterministic; the reference study's equilibrated method with its ridge is not exact)."""


def capture_for(name: str) -> Capture | None:
    """The ADMM-iterate source behind the QP and projection families.

    ``controller`` (default): real C3+ runs (the reference study's schedule, 10 iterations) at each
    sampled state; ``provisional``: the documented deterministic stand-in (``None``).
    """
    if name == "provisional":
        return None
    from c3bench.solvers.c3 import C3Options, controller_capture

    return controller_capture(C3Options(variant=Variant.C3PLUS, qp_backend=CAPTURE_QP_BACKEND))


def read_instance_dir(directory: Path, skip_bad: bool, *,
                      check_manifest: bool = True) -> list[Problem]:
    """The instances below ``directory``; bad files stop it (:class:`InstanceFormatError`
    naming the file) or, with ``skip_bad``, are listed on stderr and left out. A damaged
    ``manifest.json`` stops it (:class:`InputError` naming it) unless ``check_manifest`` is
    false (:func:`c3bench.problems.instance.read_instances`)."""
    from c3bench.problems.instance import read_instances

    try:
        found = read_instances(directory, skip_bad=skip_bad, check_manifest=check_manifest)
    except InstanceFormatError as error:
        raise InstanceFormatError(f"{error} (--skip-bad lists and skips bad files)") from error
    for line in found.skipped:
        print(f"skipped bad instance file {line}", file=sys.stderr)
    return found.problems


INEQUALITIES_HELP = ("inequalities = inequality rows + finite bound entries (lb and ub "
                     "counted separately)")
"""What the ``inequalities`` column of ``problems list`` counts."""


def inequality_count(problem: Problem) -> int:
    """Inequalities of ``problem`` in any form: ``G`` rows plus finite entries of ``lb`` and of
    ``ub`` (a variable bounded on both sides counts twice), i.e. the rows of
    ``[G; I; -I] z <= [h; ub; -lb]`` after dropping infinite sides."""
    finite = sum(int(np.isfinite(bound).sum()) for bound in (problem.lb, problem.ub)
                 if bound is not None)
    return problem.n_ineq + finite


def instance_table(directory: Path, skip_bad: bool = False) -> pd.DataFrame:
    """Per family and variant: count, variables, equality and inequality rows, bounded
    variables, pairs, and ``inequalities`` (:func:`inequality_count`: inequality rows plus
    finite bound entries, so the bounded variants, which keep their limits as bounds, show
    them).

    The variant is ``meta["variant"]`` (``bounded`` / ``equality`` for the QP steps, ``c3`` /
    ``c3plus`` for projections, ``bounded`` for an mpcc built with limits; ``-`` where an
    instance has none). Sizes that vary within a group are shown as ``min-max``.
    """
    columns = ["variables", "equality_rows", "inequality_rows", "bounded_variables",
               "complementarity_pairs", "inequalities"]
    rows = [dict(p.summary(), variant=str(p.meta.get("variant", "-")),
                 inequalities=inequality_count(p))
            for p in read_instance_dir(directory, skip_bad)]
    if not rows:
        return pd.DataFrame(columns=["family", "variant", "count", *columns])

    def span(values: pd.Series) -> str:
        low, high = int(values.min()), int(values.max())
        return str(low) if low == high else f"{low}-{high}"

    table = pd.DataFrame(rows).groupby(["family", "variant"], sort=True).agg(
        count=("name", "size"), **{c: (c, span) for c in columns})
    return table.reset_index()


def cmd_problems_generate(args: argparse.Namespace) -> int:
    """Write a suite's instances and print their table."""
    from c3bench.problems.config import load_config
    from c3bench.problems.suite_files import check_target
    from c3bench.problems.suites import generate_suite

    cli_checks.check_output_path("--out", args.out)
    try:
        check_target(Path(args.out))
    except InputError as error:
        raise InputError(f"--out: {error}") from error
    config = load_config(args.config)
    paths = generate_suite(args.suite, args.out, config=config,
                           capture=capture_for(args.capture), progress=not args.quiet)
    print(f"wrote {len(paths)} instances to {args.out}")
    print(instance_table(Path(args.out)).to_string(index=False))
    return EXIT_OK


def cmd_problems_list(args: argparse.Namespace) -> int:
    """Print the table of the instances below a directory."""
    directory = Path(args.directory)
    if not directory.is_dir():
        raise InputError(f"DIR: {directory} is not a directory")
    table = instance_table(directory, args.skip_bad)
    if table.empty:
        raise InputError(f"DIR: no instances under {directory}")
    print(table.to_string(index=False))
    return EXIT_OK


def cmd_problems_import(args: argparse.Namespace) -> int:
    """Import the user's problems into ``--out`` as ``qp`` (``lcp_general`` for an LCP file)
    instances and print their table."""
    from c3bench.problems.importers import read_module, read_npz_source, write_imported
    from c3bench.problems.suite_files import check_apart, check_target, staging_dir, swap_in

    if (args.source is None) == (args.module is None):
        raise InputError("give either SRC (an .npz file or a directory of them) or "
                         "--module MODULE, not both and not neither")
    cli_checks.check_output_path("--out", args.out)
    out = Path(args.out)
    try:
        if args.source is not None:
            check_apart(out, Path(args.source), "SRC")
        check_target(out)
    except InputError as error:
        raise InputError(f"--out: {error}") from error
    if args.module is not None:
        caught: list[warnings.WarningMessage] = []
        try:
            with warnings.catch_warnings(record=True) as caught:  # the user's code may warn
                problems = read_module(args.module)
        finally:  # also when it raises: the warnings may say why
            for warning in caught:
                message = " ".join(str(warning.message).split())
                print(f"warning: --module {args.module}: {warning.category.__name__}: "
                      f"{message} ({Path(warning.filename).name}:{warning.lineno})",
                      file=sys.stderr)
        source = f"module {args.module}"
    else:
        problems, source = read_npz_source(Path(args.source)), str(args.source)
    staging = staging_dir(out)
    try:
        write_imported(problems, staging, source, name=out.name)
        swap_in(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    print(f"imported {len(problems)} instances to {out}")
    print(instance_table(out).to_string(index=False))
    return EXIT_OK


def cmd_problems_export(args: argparse.Namespace) -> int:
    """Write the instances of ``DIR`` in another tool's format (qpsolvers)."""
    from c3bench.problems.exporters import check_export_target, export_qpsolvers
    from c3bench.problems.suite_files import check_apart

    directory, out = Path(args.directory), Path(args.out)
    if not directory.is_dir():
        raise InputError(f"DIR: {directory} is not a directory")
    cli_checks.check_output_path("--out", args.out)
    try:  # the instances read are never written over
        check_apart(out, directory, "DIR")
        check_export_target(out)
    except InputError as error:
        raise InputError(f"--out: {error}") from error
    problems = read_instance_dir(directory, args.skip_bad)
    if not problems:
        raise InputError(f"DIR: no instances under {directory}")
    export = export_qpsolvers(problems, out)
    for name, reason in sorted(export.skipped.items()):
        print(f"left out {name}: {reason}", file=sys.stderr)
    print(f"exported {len(export.written)} instances to {args.out} (qpsolvers.Problem.load "
          f"reads each .npz; {export.index.name} lists them with their objective offsets; "
          f"{export.test_set.name} is their qpbenchmark test set)")
    return EXIT_OK if export.written else EXIT_ERROR


def _add_import_export(problems_sub: Any) -> None:
    """``problems import`` and ``problems export``."""
    from c3bench.problems.exporters import FORMATS

    imports = problems_sub.add_parser(
        "import", help="bring your own convex QPs (qpsolvers' form) as qp instances",
        description="Read .npz files with qpsolvers' Problem keys (P q G h A b lb ub), "
                    "CasADi conic names (h g a lba uba lbx ubx, as written by "
                    "c3bench.problems.conic.save_conic) or an LCP's F and q, or a "
                    "module whose test sets (generator functions, or classes with __iter__, "
                    "callable without arguments) yield qpsolvers.Problem objects, and "
                    "write them as instances of the qp family (lcp_general for an LCP; with "
                    "a manifest) that `c3bench run --instances DIR` runs.")
    imports.add_argument("source", nargs="?", default=None, metavar="SRC", type=path_text,
                         help="an .npz file or a directory of them (searched recursively)")
    imports.add_argument("--module", default=None, metavar="MODULE",
                         help="instead of SRC: an importable Python module defining test "
                              "sets: generator functions or classes with __iter__, callable "
                              "without arguments, yielding qpsolvers.Problem objects (nothing "
                              "else in the module is called)")
    imports.add_argument("--out", required=True, metavar="DIR", type=path_text,
                         help="instance directory to write (new, empty, or one written by "
                              "import or generate, which is replaced as a whole; not SRC or "
                              "inside it)")
    imports.set_defaults(handler=cmd_problems_import)
    export = problems_sub.add_parser(
        "export", help="write instances for other tools (qpsolvers.Problem.load)",
        description="Write each instance without complementarity pairs as OUT/<name>.npz in "
                    "qpsolvers' Problem.save layout, OUT/index.json with each one's "
                    "objective offset, and OUT/c3bench_test_set.py, the qpbenchmark test set "
                    "over them (qpbenchmark --results-path R.csv OUT/c3bench_test_set.py run "
                    "--author NAME).")
    export.add_argument("directory", metavar="DIR", type=path_text,
                        help="directory holding instances")
    export.add_argument("--out", required=True, metavar="OUT", type=path_text,
                        help="directory to write (new, empty, or one an earlier export wrote, "
                             "which is updated; not DIR or inside it)")
    export.add_argument("--format", choices=FORMATS, default=FORMATS[0],
                        help=f"output format (default: {FORMATS[0]})")
    add_skip_bad(export)
    export.set_defaults(handler=cmd_problems_export)


def add_problems(sub: Any) -> None:
    """``problems generate``, ``list``, ``import`` and ``export``."""
    problems = sub.add_parser("problems", help="generate, list, import and export instances",
                              description="Generate a suite's instances, list instances, "
                                          "import your own QPs or export instances.")
    problems_sub = problems.add_subparsers(dest="problems_command", required=True,
                                           metavar="{generate,list,import,export}",
                                           help="what to do with instances")
    generate = problems_sub.add_parser("generate", help="write a suite's instances",
                                       description="Write a suite's instances to a directory.")
    generate.add_argument("--suite", choices=tuple(SUITES), default="quick",
                          help="suite (default: quick)")
    generate.add_argument("--out", required=True, metavar="DIR", type=path_text,
                          help="instance directory to write (not a results root); one "
                               "holding a suite is replaced as a whole")
    generate.add_argument("--config", default=None, metavar="FILE", type=path_text,
                          help="task constants (TOML; default: the packaged cube_tipping.toml)")
    generate.add_argument("--capture", choices=("controller", "provisional"),
                          default="controller",
                          help="source of the ADMM iterates behind the QP and projection "
                               "families (default: controller)")
    add_quiet(generate)
    generate.set_defaults(handler=cmd_problems_generate)
    listing = problems_sub.add_parser(
        "list", help="table of instances by family and variant",
        description="Per family and variant: count, variables, equality and inequality rows, "
                    "bounded variables, pairs, and " + INEQUALITIES_HELP + ".")
    listing.add_argument("directory", metavar="DIR", type=path_text,
                         help="directory holding instances")
    add_skip_bad(listing)
    listing.set_defaults(handler=cmd_problems_list)
    _add_import_export(problems_sub)


def add_skip_bad(parser: argparse.ArgumentParser) -> None:
    """``--skip-bad``."""
    parser.add_argument("--skip-bad", action="store_true",
                        help="list bad instance files on stderr and leave them out (default: "
                             "stop at the first, naming it)")
