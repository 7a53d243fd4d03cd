"""Handlers of ``c3bench closed-loop``, ``closed-loop-trials``, ``closed-loop-suite`` and
``sweep``.

The parser of every command is assembled in one place, :func:`bench.cli.build_parser`, which
adds these commands' subparsers with :func:`add_closed_loop`; each handler here takes the
parsed namespace and returns an exit code (:mod:`bench.cli`). Every
command writes under the results root ``--results ROOT`` (:func:`bench.store.closed_loop_dir`):
``ROOT/closed_loop/runs/<controller>/`` (one run), ``ROOT/closed_loop/trials/<controller>/``
(randomized trials), ``ROOT/closed_loop/<suite>/`` and ``ROOT/closed_loop/sweep/``.

Every option is checked before anything is simulated (:mod:`bench.closed_loop_checks`,
:mod:`bench.cli_checks`): the backends exist, are available and take the controller's QP
family (and a backend option the controller does not use is not given), durations are whole
numbers of control periods and the sweep's periods whole numbers of plant steps, MuJoCo
accepts the model cube sides, counts are within their caps
(:data:`bench.cli_options.OPTION_CAPS`), and the output directory (and ``--render`` path) can
be written, so a bad path fails at once instead of after the run. A single run's records are written
before its animation is rendered: a failed render loses nothing.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from c3bench.bench import store
from c3bench.bench.cli_checks import (
    MAX_MODEL_SIDE,
    MAX_STACKED_SAMPLES,
    check_backend_options,
    check_model_side,
    check_plant_period,
    check_samples,
)
from c3bench.bench.cli_options import (
    EXIT_ERROR,
    EXIT_OK,
    add_executor,
    add_list,
    add_quiet,
    add_results,
    nonnegative_int,
    path_text,
    positive_float,
    positive_int,
)
from c3bench.bench.closed_loop_checks import (
    check_backends,
    check_render_path,
    control_steps,
    writable_directory,
)
from c3bench.problems.errors import InputError, RenderUnavailable

MAX_DURATION_S = 3600.0
"""Longest ``--duration`` of a closed-loop run or trial (s): an hour of simulated time, some
72 000 control steps at the default dt, far beyond any task (success needs 3 s)."""


def duration(text: str) -> float:
    """``--duration``: a finite number of seconds in (0, :data:`MAX_DURATION_S`]."""
    value = positive_float(text)
    if value > MAX_DURATION_S:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_DURATION_S:g} s, got {text!r}")
    return float(value)


def _missing(run: Any) -> int:
    """Exit code of a closed-loop suite: 1 (with what is missing) when infrastructure faults
    left runs without a result, else 0."""
    if not run.missing:
        return EXIT_OK
    reasons = "; ".join(run.missing_reasons)
    print(f"{run.missing} runs missing ({reasons}); run again to complete them",
          file=sys.stderr)
    return EXIT_ERROR


def metric_lines(metrics: Any) -> list[str]:
    """The physical metrics of one run (:class:`bench.closed_loop_metrics.PhysicalMetrics`),
    as printed by ``c3bench closed-loop``."""
    return [
        f"gentle success    {'yes' if metrics.gentle_success else 'no'} (peak angle "
        f"{metrics.peak_angle:.3f} rad, balance angle {metrics.balance_angle:.3f} rad"
        f"{', passed' if metrics.passed_balance else ''})",
        f"hold time         {metrics.hold_time:.2f} s in the band at the end (settled "
        + ("never" if metrics.settling_time != metrics.settling_time
           else f"at {metrics.settling_time:.2f} s")
        + f"), steady offset {metrics.steady_offset:+.3f} rad",
        "pivot slip        "
        + ("not measured" if metrics.pivot_slip != metrics.pivot_slip
           else f"{1e2 * metrics.pivot_slip:.1f} cm (the far bottom edge along the table)"),
        "contact           "
        + ("no contact" if metrics.first_touch_time != metrics.first_touch_time
           else f"first touch {metrics.first_touch_time:.2f} s at "
                f"{metrics.impact_speed:.2f} m/s")
        + f"; {metrics.contact_time:.2f} s in contact, {metrics.free_time:.2f} s out",
        f"penetration       cube {1e3 * metrics.max_cube_penetration:.1f} mm, table "
        f"{1e3 * metrics.max_table_penetration:.1f} mm; clipped inputs "
        f"{metrics.clipped_inputs} steps",
        f"plan vs LCS       angle median {metrics.plan_lcs_angle_median:.4f} rad, max "
        f"{metrics.plan_lcs_angle_max:.4f} rad (state norm median "
        f"{metrics.plan_lcs_error_median:.3g})",
        f"plan vs plant     angle median {metrics.plan_plant_angle_median:.4f} rad, max "
        f"{metrics.plan_plant_angle_max:.4f} rad (state norm median "
        f"{metrics.plan_plant_error_median:.3g})",
    ]


def contact_model_option(args: argparse.Namespace) -> str:
    """The ``--contact-model`` of ``args`` (``anitescu`` when the parser has no such option);
    :class:`ControllerSpec` checks it (one-line :class:`InputError`, exit 2, on a bad
    value)."""
    return str(getattr(args, "contact_model", None) or "anitescu")


def backend_options(args: argparse.Namespace) -> dict[str, Any]:
    """The ``qp_backend`` / ``projection`` fields of the controller: those given (the
    defaults of :class:`ControllerSpec` otherwise); one given to a controller that does not
    use it is an :class:`InputError` (:func:`bench.cli_checks.check_backend_options`)."""
    given = {"qp_backend": getattr(args, "qp_backend", None),
             "projection": getattr(args, "projection", None)}
    check_backend_options(args.controller, {f"--{key.replace('_', '-')}": value
                                            for key, value in given.items()})
    return {key: value for key, value in given.items() if value is not None}


def check_controller(spec: Any, config: Any) -> None:
    """The options of ``spec`` that only the task configuration can judge: its samples
    (:func:`bench.cli_checks.check_samples`) and model side
    (:func:`bench.cli_checks.check_model_side`)."""
    check_samples(spec.controller, spec.samples)
    check_model_side("--model-l", spec.model_l, config)


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
    spec = ControllerSpec(controller=args.controller, **backend_options(args),
                          rho_schedule=args.rho_schedule,
                          admm_iterations=args.iterations, model_l=args.model_l,
                          samples=args.samples, weighting=not args.no_weighting,
                          seed=args.seed, feedback=args.feedback,
                          qp_time_limit=args.qp_time_limit,
                          contact_model=contact_model_option(args))
    control_steps(args.duration, config.mpc.dt, "--duration")
    check_backends(spec)
    check_controller(spec, config)
    runs = writable_directory(store.closed_loop_dir(args.results, "runs"), "--results")
    if args.render:
        check_render_path(args.render)
    trajectory, records, outcome = run_closed_loop(spec, config, args.duration,
                                                   progress=not args.quiet)
    scene = build_scene(config=config)
    out = runs / spec.label()
    write_run(out, trajectory, records, scene, run_summary(spec, trajectory, outcome))
    print(f"controller        {spec.label()}")
    print(f"contact model     {spec.contact_model} (the controller's LCS)")
    print(f"success           {'yes' if outcome.success else 'no'}")
    if outcome.metrics is not None:
        for line in metric_lines(outcome.metrics):
            print(line)
    print(f"angle error       {outcome.angle_error:.4f} rad at t = {args.duration:g} s "
          f"(theta = {outcome.final_angle:.4f}, target {config.mpc.target_angle:g})")
    print(f"what happened     {outcome.label}: {outcome.label_reason}")
    print(f"failure mode      {outcome.failure_mode} ({outcome.failure_label}): "
          f"{outcome.failure_reason}")
    print(f"control step      median {1e3 * outcome.median_step_time:.1f} ms, "
          f"p95 {1e3 * outcome.p95_step_time:.1f} ms (LCS build median "
          f"{1e3 * outcome.median_lcs_time:.1f} ms, solve "
          f"{1e3 * outcome.median_solve_time:.1f} ms)")
    print(f"fallbacks / NaNs  {outcome.fallback_count} / {outcome.nan_count}")
    print(f"QP failures       {outcome.qp_failure_steps} of {outcome.steps} steps"
          + (f" (first: {outcome.qp_failure})" if outcome.qp_failure else ""))
    print(f"records           {out}")
    if args.render:
        try:
            path = render_run(trajectory.states, scene, args.render, config.mpc.dt)
            print(f"animation         {path}")
        except RenderUnavailable as error:
            print(f"animation skipped: {error}", file=sys.stderr)
        except (OSError, ValueError) as error:  # the records above are already written
            print(f"error: animation not written to {args.render}: {error}",
                  file=sys.stderr)
            return EXIT_ERROR
    return EXIT_OK


def suite_trials(args: argparse.Namespace, default: int) -> int:
    """The episodes per configuration of ``closed-loop-suite``: ``--trials N`` when given
    (an integer in [1, :data:`~bench.cli_options.MAX_TRIALS`]; :class:`InputError`
    otherwise), else the suite's ``default``."""
    from c3bench.bench.closed_loop_configs import check_trials

    trials = getattr(args, "trials", None)
    return default if trials is None else check_trials(trials)


def cmd_closed_loop_suite(args: argparse.Namespace) -> int:
    """Run a closed-loop suite (configurations x randomized trials, resumable) and write its
    report (:func:`bench.closed_loop_report.write_trials_report`)."""
    from c3bench.bench.closed_loop_report import write_trials_report
    from c3bench.bench.closed_loop_suite import CLOSED_LOOP_SUITES, run_cases

    suite = CLOSED_LOOP_SUITES[args.suite]
    trials = suite_trials(args, suite.trials)
    directory = writable_directory(store.closed_loop_dir(args.results, args.suite),
                                   "--results")
    cases = suite.cases(trials)
    run = run_cases(cases, directory, jobs=args.jobs, scheduler=args.scheduler,
                    rerun=args.rerun, progress=not args.quiet)
    report = write_trials_report(run, suite, trials, render=not args.no_render)
    succeeded = sum(bool(row.get("success")) for row in run.rows)
    print(f"{len(suite.configurations)} configurations x {trials} trials: {len(run.rows)} "
          f"episodes ({run.skipped} stored), {succeeded} succeeded; report: {report}")
    return _missing(run)


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run the hyperparameter sweep (resumable) and write its outcome map."""
    from c3bench.bench.closed_loop_suite import run_cases, sweep_cases, write_report
    from c3bench.problems.config import load_config

    cases = sweep_cases(args.dt, args.rho_schedule, args.q_box, args.model_l, args.qp_backend)
    if cases:
        check_backends(cases[0].spec)  # every case of the sweep has the same QP backend
    config = load_config()
    for dt in dict.fromkeys(args.dt):
        check_plant_period("--dt", dt, config)
    for side in dict.fromkeys(args.model_l):
        check_model_side("--model-l", side, config)
    for case in cases:
        try:
            control_steps(case.duration, float(case.dt or 0.0))
        except InputError:
            raise InputError(f"--dt {case.dt:g}: a sweep run lasts {case.duration:g} s, not a "
                             f"whole number of control periods of {case.dt:g} s") from None
    directory = writable_directory(store.closed_loop_dir(args.results, "sweep"), "--results")
    run = run_cases(cases, directory, jobs=args.jobs, scheduler=args.scheduler,
                    rerun=args.rerun, progress=not args.quiet)
    report = write_report(run, "hyperparameter sweep", render=False)
    print(f"{len(run.rows)} runs ({run.skipped} stored); report: {report}")
    return _missing(run)


def cmd_closed_loop_trials(args: argparse.Namespace) -> int:
    """Run randomized trials of one controller (resumable) and print their statistics."""
    from c3bench.bench.closed_loop import ControllerSpec
    from c3bench.bench.closed_loop_metrics import SuccessRules
    from c3bench.bench.closed_loop_suite import run_cases
    from c3bench.bench.trials import summary_lines, trial_cases
    from c3bench.problems.config import load_config
    from c3bench.problems.instance import atomic_write_bytes

    spec = ControllerSpec(controller=args.controller, **backend_options(args),
                          model_l=args.model_l, samples=args.samples,
                          feedback=args.feedback, contact_model=contact_model_option(args))
    config = load_config()
    control_steps(args.duration, config.mpc.dt, "--duration")
    rules = SuccessRules(hold_time=args.hold_time)
    check_backends(spec)
    check_controller(spec, config)
    directory = writable_directory(store.closed_loop_dir(args.results, "trials") / spec.label(),
                                   "--results")
    cases = trial_cases(spec, args.trials, args.seed, args.duration, rules.hold_time)
    run = run_cases(cases, directory, jobs=args.jobs, scheduler=args.scheduler,
                    rerun=args.rerun, progress=not args.quiet)
    print(f"controller      {spec.label()} (contact model {spec.contact_model})")
    print(f"trials          {args.trials} (seed {args.seed}, {args.duration:g} s each, hold "
          f"{rules.hold_time:g} s; {run.skipped} stored)")
    if args.duration < rules.min_duration:
        print(f"note            runs shorter than {rules.min_duration:g} s cannot succeed")
    lines = summary_lines(run.rows, args.trials)
    for line in lines:
        print(line)
    atomic_write_bytes(directory / "summary.txt", ("\n".join(lines) + "\n").encode())
    print(f"records         {directory} (summary.txt, results.parquet, cells/)")
    return _missing(run)


def add_controller_options(parser: argparse.ArgumentParser, spec: Any) -> None:
    """The controller choice shared by ``closed-loop`` and ``closed-loop-trials``:
    ``--controller``, ``--qp-backend``, ``--model-l``, ``--samples``, ``--feedback`` and
    ``--contact-model``, defaults from ``spec`` (a :class:`ControllerSpec`)."""
    from c3bench.bench.closed_loop import CONTROLLERS

    parser.add_argument("--controller", choices=CONTROLLERS, default=spec.controller,
                        help=f"controller (default: {spec.controller})")
    parser.add_argument("--qp-backend", default=None, metavar="NAME",
                        help=f"registry name of the QP solver (default: {spec.qp_backend}); "
                             "not for the fast controllers, which solve their QP steps "
                             "themselves")
    parser.add_argument("--model-l", type=positive_float, default=spec.model_l, metavar="L",
                        help=f"cube side of the model (m; default: {spec.model_l:g}; at "
                             f"most {MAX_MODEL_SIDE:g}, and one MuJoCo can build)")
    parser.add_argument("--samples", type=positive_int, default=spec.samples, metavar="N",
                        help=f"robust variants: sampled models, c3plus-robust at most "
                             f"{MAX_STACKED_SAMPLES} (default: {spec.samples})")
    parser.add_argument("--feedback", action="store_true",
                        help="low-level PD tracking of the plan's ball motion between steps")
    parser.add_argument("--contact-model", default="anitescu", metavar="MODEL",
                        help="contact model of the controller's LCS: anitescu (default) or "
                             "stewart-trinkle")


def add_closed_loop(sub: Any) -> None:
    """``closed-loop``, ``closed-loop-trials``, ``closed-loop-suite`` and ``sweep``."""
    from c3bench.bench.closed_loop import ControllerSpec
    from c3bench.bench.closed_loop_suite import (
        CLOSED_LOOP_SUITES,
        SWEEP_DTS,
        SWEEP_MODEL_LS,
        SWEEP_Q_BOXES,
        SWEEP_SCHEDULES,
    )
    from c3bench.problems.config import SceneConfig
    from c3bench.solvers.c3 import RHO_SCHEDULES

    spec = ControllerSpec()
    loop = sub.add_parser("closed-loop", help="drive the MuJoCo cube with C3 / C3+",
                          description="One closed-loop run: the controller replans every dt "
                                      "from the measured MuJoCo state.")
    add_controller_options(loop, spec)
    loop.add_argument("--projection", default=None, metavar="NAME",
                      help=f"C3's MIQP projection backend (default: {spec.projection}); "
                           "c3 only")
    loop.add_argument("--rho-schedule", choices=RHO_SCHEDULES,
                      default=spec.rho_schedule,
                      help=f"ADMM weight schedule (default: {spec.rho_schedule})")
    loop.add_argument("--iterations", type=positive_int, default=spec.admm_iterations,
                      metavar="N",
                      help=f"ADMM iterations per step (default: {spec.admm_iterations})")
    loop.add_argument("--no-weighting", action="store_true",
                      help="robust variants: uniform sample weights")
    loop.add_argument("--duration", type=duration, default=3.0, metavar="S",
                      help="seconds of simulation, a multiple of dt, at most "
                           f"{MAX_DURATION_S:g} (default: 3; success needs at least 3)")
    loop.add_argument("--qp-time-limit", type=positive_float, default=spec.qp_time_limit,
                      metavar="S",
                      help="seconds per QP (and C3 projection) solve, run in an isolated "
                           "child; a solve that overruns is killed and the step falls back "
                           f"(default: {spec.qp_time_limit:g})")
    loop.add_argument("--seed", type=nonnegative_int, default=spec.seed, metavar="N",
                      help=f"seed of the sampled model sides (default: {spec.seed})")
    loop.add_argument("--config", type=path_text, default=None, metavar="FILE",
                      help="task constants (TOML; default: the packaged cube_tipping.toml)")
    add_results(loop, "writes ROOT/closed_loop/runs/<controller label>/")
    loop.add_argument("--render", type=path_text, default=None, metavar="GIF",
                      help="also write an animated GIF of the run to this path")
    add_quiet(loop)
    loop.set_defaults(handler=cmd_closed_loop)

    trials = sub.add_parser("closed-loop-trials",
                            help="randomized closed-loop trials with success-rate intervals",
                            description="N closed-loop episodes of one controller with a "
                                        "randomized ball start, cube mass, friction and cube "
                                        "side (resumable); prints the success rate with its "
                                        "Wilson 95% interval and the metric medians.")
    add_controller_options(trials, spec)
    trials.add_argument("--trials", type=positive_int, default=20, metavar="N",
                        help="episodes (default: 20)")
    trials.add_argument("--seed", type=nonnegative_int, default=0, metavar="S",
                        help="seed of the randomization (default: 0)")
    trials.add_argument("--duration", type=duration, default=3.0, metavar="S",
                        help="seconds per episode, a multiple of dt, at most "
                             f"{MAX_DURATION_S:g} (default: 3; success needs at least 3)")
    trials.add_argument("--hold-time", type=positive_float, default=1.0, metavar="S",
                        help="seconds the angle must stay in the band at the end (default: 1)")
    add_executor(trials, "trials")
    add_results(trials, "writes ROOT/closed_loop/trials/<controller label>/")
    add_quiet(trials)
    trials.set_defaults(handler=cmd_closed_loop_trials)

    suite = sub.add_parser("closed-loop-suite",
                           help="closed-loop suites: configurations x randomized trials",
                           description="Run every configuration of a closed-loop suite on "
                                       "the same randomized trials (resumable) and write its "
                                       "report: success rates with Wilson 95% intervals, "
                                       "success against the model's cube side, metric "
                                       "distributions and the seed's claims tested.")
    suite.add_argument("--suite", choices=tuple(CLOSED_LOOP_SUITES), default="quick",
                       help="closed-loop suite (default: quick)")
    suite.add_argument("--trials", type=positive_int, default=None, metavar="N",
                       help="trials per configuration (default: the suite's, "
                            + ", ".join(f"{name} {s.trials}"
                                        for name, s in CLOSED_LOOP_SUITES.items())
                            + "); trial i is the same episode whatever N, so a larger N "
                              "reuses the stored trials")
    add_executor(suite, "runs")
    add_results(suite, "writes ROOT/closed_loop/<suite>/")
    suite.add_argument("--no-render", action="store_true", help="skip the animation")
    add_quiet(suite)
    suite.set_defaults(handler=cmd_closed_loop_suite)

    sweep = sub.add_parser("sweep", help="outcome map: dt x rho schedule x Q_box x l",
                           description="C3+ over a grid of hyperparameters; the report maps "
                                       "each combination to its outcome (success or label).")
    add_list(sweep, "--dt", metavar="S", item=positive_float, default=SWEEP_DTS,
             help=f"control periods (s), each a whole multiple of the plant's time step, "
                  f"{SceneConfig.plant_timestep:g} s")
    add_list(sweep, "--rho-schedule", metavar="SCHEDULE",
             choices=RHO_SCHEDULES,
             default=SWEEP_SCHEDULES, help="ADMM weight schedules")
    add_list(sweep, "--q-box", metavar="Q", item=positive_float, default=SWEEP_Q_BOXES,
             help="cube-pose weights Q_box")
    add_list(sweep, "--model-l", metavar="L", item=positive_float, default=SWEEP_MODEL_LS,
             help=f"cube sides of the model (m), each at most {MAX_MODEL_SIDE:g} and one "
                  "MuJoCo can build")
    sweep.add_argument("--qp-backend", default=spec.qp_backend, metavar="NAME",
                       help=f"registry name of the QP solver (default: {spec.qp_backend})")
    add_executor(sweep, "runs")
    add_results(sweep, "writes ROOT/closed_loop/sweep/")
    add_quiet(sweep)
    sweep.set_defaults(handler=cmd_sweep)
