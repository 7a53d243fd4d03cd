"""The ``c3bench`` command line (also ``python -m c3bench``).

Subcommands:

* ``problems generate --suite quick --out DIR``: write a suite's instances.
* ``problems list DIR``: a table of the instances below DIR by family.
* ``solvers``: the registry: every backend, its availability, version and families.
* ``run``, ``report``, ``compare``: the benchmark (``bench/commands.py``).
* ``closed-loop``, ``closed-loop-suite``, ``sweep``: C3 / C3+ driving the MuJoCo cube.
* ``perf``: control-step time of the fast paths against the reference controller.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from c3bench.problems.suites import Capture

CAPTURE_QP_BACKEND = "clarabel"
"""QP solver of the controller runs whose iterates become suite instances (exact and
deterministic; the seed's equilibrated method with its ridge is not exact)."""


def _capture_for(name: str) -> Capture | None:
    """The ADMM-iterate source behind the QP and projection families.

    ``controller`` (default): real C3+ runs (the seed's schedule, 10 iterations) at each
    sampled state; ``provisional``: the documented deterministic stand-in.
    """
    if name == "provisional":
        return None
    from c3bench.solvers.c3 import C3Options, controller_capture

    return controller_capture(C3Options(variant="c3plus", qp_backend=CAPTURE_QP_BACKEND))


def cmd_problems_generate(args: argparse.Namespace) -> int:
    from c3bench.problems.config import load_config
    from c3bench.problems.suites import SUITES, generate_suite

    if args.suite not in SUITES:
        print(f"error: unknown suite {args.suite!r}; known: {', '.join(SUITES)}",
              file=sys.stderr)
        return 2
    config = load_config(args.config)
    paths = generate_suite(args.suite, args.out, config=config,
                           capture=_capture_for(args.capture), progress=not args.quiet)
    print(f"wrote {len(paths)} instances to {args.out}")
    print(instance_table(Path(args.out)).to_string(index=False))
    return 0


def instance_table(directory: Path) -> pd.DataFrame:
    """Per family: count, variables, equality and inequality rows, bounded variables, pairs.

    Sizes that vary within a family are shown as ``min-max``.
    """
    from c3bench.problems.instance import load_instances

    rows = [p.summary() for p in load_instances(directory)]
    if not rows:
        return pd.DataFrame(columns=["family", "count", "variables", "equality_rows",
                                     "inequality_rows", "bounded_variables",
                                     "complementarity_pairs"])
    frame = pd.DataFrame(rows)
    columns = ["variables", "equality_rows", "inequality_rows", "bounded_variables",
               "complementarity_pairs"]

    def span(values: pd.Series) -> str:
        low, high = int(values.min()), int(values.max())
        return str(low) if low == high else f"{low}-{high}"

    table = frame.groupby("family", sort=True).agg(
        count=("name", "size"), **{c: (c, span) for c in columns})
    return table.reset_index()


def cmd_problems_list(args: argparse.Namespace) -> int:
    directory = Path(args.directory)
    if not directory.is_dir():
        print(f"error: {directory} is not a directory", file=sys.stderr)
        return 2
    table = instance_table(directory)
    if table.empty:
        print(f"no instances under {directory}")
        return 1
    print(table.to_string(index=False))
    return 0


def cmd_solvers(args: argparse.Namespace) -> int:
    from c3bench.solvers import registry

    rows = [{
        "solver": info.name,
        "available": "yes" if info.available else "no",
        "version": info.version,
        "families": ",".join(info.families),
        "precisions": ",".join(info.precisions),
        "note": info.reason or info.description,
    } for info in registry.available()]
    frame = pd.DataFrame(rows)
    with pd.option_context("display.max_colwidth", 70, "display.width", 200):
        print(frame.to_string(index=False))
    for module, error in registry.module_errors().items():
        print(f"warning: backend module {module} failed to load: {error}", file=sys.stderr)
    return 0


def cmd_closed_loop(args: argparse.Namespace) -> int:
    from c3bench.bench.closed_loop import (
        ControllerSpec,
        render_run,
        run_closed_loop,
        run_summary,
        write_run,
    )
    from c3bench.problems.config import load_config
    from c3bench.problems.scene import RenderUnavailable, build_scene

    config = load_config(args.config)
    spec = ControllerSpec(controller=args.controller, qp_backend=args.qp_backend,
                          projection=args.projection, rho_schedule=args.rho_schedule,
                          admm_iterations=args.iterations, model_l=args.model_l,
                          samples=args.samples, weighting=not args.no_weighting,
                          seed=args.seed, feedback=args.feedback)
    trajectory, records, outcome = run_closed_loop(spec, config, args.duration,
                                                   progress=not args.quiet)
    scene = build_scene(config=config)
    out = Path(args.out) if args.out else Path("results") / "closed_loop" / "runs" / spec.label()
    write_run(out, trajectory, records, scene, run_summary(spec, trajectory, outcome))
    print(f"controller        {spec.label()}")
    print(f"success           {'yes' if outcome.success else 'no'}")
    print(f"angle error       {outcome.angle_error:.4f} rad at t = {args.duration:g} s "
          f"(theta = {outcome.final_angle:.4f}, target {config.mpc.target_angle:g})")
    print(f"failure mode      {outcome.failure_mode} ({outcome.failure_label}): "
          f"{outcome.failure_reason}")
    print(f"control step      median {1e3 * outcome.median_step_time:.1f} ms, "
          f"p95 {1e3 * outcome.p95_step_time:.1f} ms (LCS build median "
          f"{1e3 * outcome.median_lcs_time:.1f} ms, solve "
          f"{1e3 * outcome.median_solve_time:.1f} ms)")
    print(f"fallbacks / NaNs  {outcome.fallback_count} / {outcome.nan_count}")
    print(f"records           {out}")
    if args.render:
        try:
            path = render_run(trajectory.states, scene, args.render, config.mpc.dt)
            print(f"animation         {path}")
        except RenderUnavailable as error:
            print(f"animation skipped: {error}", file=sys.stderr)
    return 0


def cmd_closed_loop_suite(args: argparse.Namespace) -> int:
    from c3bench.bench.closed_loop_suite import (
        CLOSED_LOOP_SUITES,
        RESULTS_DIR,
        run_cases,
        write_report,
    )

    if args.suite not in CLOSED_LOOP_SUITES:
        print(f"error: unknown closed-loop suite {args.suite!r}; known: "
              f"{', '.join(CLOSED_LOOP_SUITES)}", file=sys.stderr)
        return 2
    directory = Path(args.results) if args.results else RESULTS_DIR / args.suite
    run = run_cases(CLOSED_LOOP_SUITES[args.suite], directory, jobs=args.jobs,
                    scheduler=args.scheduler, rerun=args.rerun, progress=not args.quiet)
    report = write_report(run, f"suite `{args.suite}`", render=not args.no_render)
    succeeded = sum(bool(row.get("success")) for row in run.rows)
    print(f"{len(run.rows)} runs ({run.skipped} stored), {succeeded} succeeded; report: {report}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from c3bench.bench.closed_loop_suite import RESULTS_DIR, run_cases, sweep_cases, write_report

    cases = sweep_cases(args.dt, args.rho_schedule, args.q_box, args.model_l, args.qp_backend)
    directory = Path(args.results) if args.results else RESULTS_DIR / "sweep"
    run = run_cases(cases, directory, jobs=args.jobs, scheduler=args.scheduler,
                    rerun=args.rerun, progress=not args.quiet)
    report = write_report(run, "hyperparameter sweep", render=False)
    print(f"{len(run.rows)} runs ({run.skipped} stored); report: {report}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="c3bench",
        description="Benchmark solvers on the subproblems of contact-implicit MPC (C3 / C3+).")
    from c3bench import __version__

    parser.add_argument("--version", action="version", version=f"c3bench {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    problems = sub.add_parser("problems", help="generate and list subproblem instances")
    problems_sub = problems.add_subparsers(dest="problems_command", required=True)
    generate = problems_sub.add_parser("generate", help="write a suite's instances")
    generate.add_argument("--suite", default="quick", help="quick, default or full")
    generate.add_argument("--out", required=True, help="output directory")
    generate.add_argument("--config", default=None, help="task constants (TOML)")
    generate.add_argument("--capture", choices=("controller", "provisional"),
                          default="controller",
                          help="source of the ADMM iterates behind the QP families")
    generate.add_argument("--quiet", action="store_true", help="no progress bar")
    generate.set_defaults(handler=cmd_problems_generate)
    listing = problems_sub.add_parser("list", help="table of instances by family")
    listing.add_argument("directory")
    listing.set_defaults(handler=cmd_problems_list)

    solvers = sub.add_parser("solvers", help="list solver backends")
    solvers.set_defaults(handler=cmd_solvers)

    loop = sub.add_parser("closed-loop", help="drive the MuJoCo cube with C3 / C3+")
    loop.add_argument("--controller", choices=("c3", "c3plus", "c3plus-robust", "c3plus-fast",
                                               "c3plus-fast-robust"),
                      default="c3plus")
    loop.add_argument("--qp-backend", default="clarabel", help="registry name of the QP solver")
    loop.add_argument("--projection", default="scip", help="C3's MIQP projection backend")
    loop.add_argument("--rho-schedule", choices=("geometric", "adaptive", "residual_balancing"),
                      default="geometric")
    loop.add_argument("--iterations", type=int, default=10, help="ADMM iterations per step")
    loop.add_argument("--samples", type=int, default=16, help="robust variant: sampled models")
    loop.add_argument("--no-weighting", action="store_true",
                      help="robust variant: uniform sample weights")
    loop.add_argument("--feedback", action="store_true",
                      help="low-level PD tracking of the plan's ball motion between steps")
    loop.add_argument("--model-l", type=float, default=0.29, help="cube side of the model")
    loop.add_argument("--duration", type=float, default=2.0, help="seconds of simulation")
    loop.add_argument("--seed", type=int, default=0)
    loop.add_argument("--config", default=None, help="task constants (TOML)")
    loop.add_argument("--out", default=None, help="directory for the run's records")
    loop.add_argument("--render", default=None, help="write an animated GIF here")
    loop.add_argument("--quiet", action="store_true", help="no progress bar")
    loop.set_defaults(handler=cmd_closed_loop)

    loop_suite = sub.add_parser("closed-loop-suite",
                                help="closed-loop runs: backends x controllers x seeds")
    loop_suite.add_argument("--suite", default="quick", help="quick or full")
    sweep = sub.add_parser("sweep", help="failure-mode map: dt x rho schedule x Q_box x l")
    sweep.add_argument("--dt", type=float, nargs="+", default=[0.05, 0.1])
    sweep.add_argument("--rho-schedule", nargs="+", default=["geometric", "adaptive"],
                       choices=("geometric", "adaptive", "residual_balancing"))
    sweep.add_argument("--q-box", type=float, nargs="+", default=[2e4, 2e5])
    sweep.add_argument("--model-l", type=float, nargs="+", default=[0.29, 0.30])
    sweep.add_argument("--qp-backend", default="clarabel")
    for parser_ in (loop_suite, sweep):
        parser_.add_argument("--jobs", type=int, default=2, help="local worker processes")
        parser_.add_argument("--scheduler", default=None, help="Dask scheduler address")
        parser_.add_argument("--rerun", action="store_true", help="run stored cases again")
        parser_.add_argument("--results", default=None, help="output directory")
        parser_.add_argument("--quiet", action="store_true", help="no progress bar")
    loop_suite.add_argument("--no-render", action="store_true", help="skip the animation")
    loop_suite.set_defaults(handler=cmd_closed_loop_suite)
    sweep.set_defaults(handler=cmd_sweep)

    from c3bench.bench.perf import register_perf_command

    register_perf_command(sub)

    try:
        from c3bench.bench.commands import register_commands
    except ModuleNotFoundError as error:
        if error.name != "c3bench.bench.commands":
            raise
    else:
        register_commands(sub, capture=_capture_for("controller"))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
