"""Handlers of ``c3bench closed-loop``, ``closed-loop-suite`` and ``sweep``.

The parser of every command is built in one place, :func:`bench.cli.build_parser`; each
handler here takes the parsed namespace and returns an exit code (:mod:`bench.cli`). Every
command writes under the results root ``--results ROOT`` (:func:`bench.store.closed_loop_dir`):
``ROOT/closed_loop/runs/<controller>/`` (one run), ``ROOT/closed_loop/<suite>/`` and
``ROOT/closed_loop/sweep/``.
"""

from __future__ import annotations

import argparse
import sys

from c3bench.bench import store
from c3bench.problems.errors import RenderUnavailable


def cmd_closed_loop(args: argparse.Namespace) -> int:
    """Drive the MuJoCo cube with one controller and write the run's records."""
    from c3bench.bench.closed_loop import (
        ControllerSpec,
        render_run,
        run_closed_loop,
        run_summary,
        write_run,
    )
    from c3bench.problems.config import load_config
    from c3bench.problems.scene import build_scene

    config = load_config(args.config)
    spec = ControllerSpec(controller=args.controller, qp_backend=args.qp_backend,
                          projection=args.projection, rho_schedule=args.rho_schedule,
                          admm_iterations=args.iterations, model_l=args.model_l,
                          samples=args.samples, weighting=not args.no_weighting,
                          seed=args.seed, feedback=args.feedback)
    trajectory, records, outcome = run_closed_loop(spec, config, args.duration,
                                                   progress=not args.quiet)
    scene = build_scene(config=config)
    out = store.closed_loop_dir(args.results, "runs") / spec.label()
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
    """Run a closed-loop suite (resumable) and write its report."""
    from c3bench.bench.closed_loop_suite import CLOSED_LOOP_SUITES, run_cases, write_report

    directory = store.closed_loop_dir(args.results, args.suite)
    run = run_cases(CLOSED_LOOP_SUITES[args.suite], directory, jobs=args.jobs,
                    scheduler=args.scheduler, rerun=args.rerun, progress=not args.quiet)
    report = write_report(run, f"suite `{args.suite}`", render=not args.no_render)
    succeeded = sum(bool(row.get("success")) for row in run.rows)
    print(f"{len(run.rows)} runs ({run.skipped} stored), {succeeded} succeeded; report: {report}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run the hyperparameter sweep (resumable) and write its failure-mode map."""
    from c3bench.bench.closed_loop_suite import run_cases, sweep_cases, write_report

    cases = sweep_cases(args.dt, args.rho_schedule, args.q_box, args.model_l, args.qp_backend)
    directory = store.closed_loop_dir(args.results, "sweep")
    run = run_cases(cases, directory, jobs=args.jobs, scheduler=args.scheduler,
                    rerun=args.rerun, progress=not args.quiet)
    report = write_report(run, "hyperparameter sweep", render=False)
    print(f"{len(run.rows)} runs ({run.skipped} stored); report: {report}")
    return 0
