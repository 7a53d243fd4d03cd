"""``c3bench problems generate`` / ``problems list``: the instance commands (:mod:`bench.cli`).

Also the instance helpers other commands share: :func:`capture_for` (the ADMM-iterate source
of a generation), :func:`read_instance_dir` (a directory's instances under the ``--skip-bad``
policy) and :func:`add_skip_bad`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import pandas as pd

from c3bench.bench import cli_checks
from c3bench.bench.cli_options import EXIT_ERROR, EXIT_OK, add_quiet
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


def read_instance_dir(directory: Path, skip_bad: bool) -> list[Problem]:
    """The instances below ``directory``; bad files stop it (:class:`InstanceFormatError`
    naming the file) or, with ``skip_bad``, are listed on stderr and left out."""
    from c3bench.problems.instance import read_instances

    try:
        found = read_instances(directory, skip_bad=skip_bad)
    except InstanceFormatError as error:
        raise InstanceFormatError(f"{error} (--skip-bad lists and skips bad files)") from error
    for line in found.skipped:
        print(f"skipped bad instance file {line}", file=sys.stderr)
    return found.problems


def instance_table(directory: Path, skip_bad: bool = False) -> pd.DataFrame:
    """Per family: count, variables, equality and inequality rows, bounded variables, pairs.

    Sizes that vary within a family are shown as ``min-max``.
    """
    columns = ["variables", "equality_rows", "inequality_rows", "bounded_variables",
               "complementarity_pairs"]
    rows = [p.summary() for p in read_instance_dir(directory, skip_bad)]
    if not rows:
        return pd.DataFrame(columns=["family", "count", *columns])

    def span(values: pd.Series) -> str:
        low, high = int(values.min()), int(values.max())
        return str(low) if low == high else f"{low}-{high}"

    table = pd.DataFrame(rows).groupby("family", sort=True).agg(
        count=("name", "size"), **{c: (c, span) for c in columns})
    return table.reset_index()


def cmd_problems_generate(args: argparse.Namespace) -> int:
    """Write a suite's instances and print their table."""
    from c3bench.problems.config import load_config
    from c3bench.problems.suites import check_target, generate_suite

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
        print(f"no instances under {directory}")
        return EXIT_ERROR
    print(table.to_string(index=False))
    return EXIT_OK


def add_problems(sub: Any) -> None:
    """``problems generate`` and ``problems list``."""
    problems = sub.add_parser("problems", help="generate and list subproblem instances",
                              description="Generate a suite's instances, or list instances.")
    problems_sub = problems.add_subparsers(dest="problems_command", required=True,
                                           metavar="{generate,list}",
                                           help="what to do with instances")
    generate = problems_sub.add_parser("generate", help="write a suite's instances",
                                       description="Write a suite's instances to a directory.")
    generate.add_argument("--suite", choices=tuple(SUITES), default="quick",
                          help="suite (default: quick)")
    generate.add_argument("--out", required=True, metavar="DIR",
                          help="instance directory to write (not a results root); one "
                               "holding a suite is replaced as a whole")
    generate.add_argument("--config", default=None, metavar="FILE",
                          help="task constants (TOML; default: the packaged cube_tipping.toml)")
    generate.add_argument("--capture", choices=("controller", "provisional"),
                          default="controller",
                          help="source of the ADMM iterates behind the QP and projection "
                               "families (default: controller)")
    add_quiet(generate)
    generate.set_defaults(handler=cmd_problems_generate)
    listing = problems_sub.add_parser("list", help="table of instances by family",
                                      description="Per family: count, variables, rows, pairs.")
    listing.add_argument("directory", metavar="DIR", help="directory holding instances")
    add_skip_bad(listing)
    listing.set_defaults(handler=cmd_problems_list)


def add_skip_bad(parser: argparse.ArgumentParser) -> None:
    """``--skip-bad``."""
    parser.add_argument("--skip-bad", action="store_true",
                        help="list bad instance files on stderr and leave them out (default: "
                             "stop at the first, naming it)")
