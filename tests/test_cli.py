"""The ``c3bench`` command line: README's synopsis against the parser, list options, help,
``--version``, number checks and ``solvers --plugin``."""

from __future__ import annotations

import argparse
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from c3bench import __version__
from c3bench.bench.cli import build_parser, main
from c3bench.bench.cli_closed_loop import metric_lines
from c3bench.bench.cli_options import ListAction

README = Path(__file__).resolve().parents[1] / "README.md"
OPTION = re.compile(r"--[a-z][a-z0-9-]*")


# --- the parser as data ------------------------------------------------------------------------
def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def parser_commands() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every command that runs (leaves of the subcommand tree), plus the bare ``c3bench``."""
    root = build_parser()
    out: dict[tuple[str, ...], argparse.ArgumentParser] = {(): root}
    stack: list[tuple[tuple[str, ...], argparse.ArgumentParser]] = [((), root)]
    while stack:
        path, parser = stack.pop()
        for name, child in _subcommands(parser).items():
            if _subcommands(child):
                stack.append(((*path, name), child))
            else:
                out[(*path, name)] = child
    return out


def options_of(parser: argparse.ArgumentParser) -> set[str]:
    """The long options of one parser, ``--help`` aside."""
    return {flag for action in parser._actions for flag in action.option_strings
            if flag.startswith("--") and flag != "--help"}


def positionals_of(parser: argparse.ArgumentParser) -> list[str]:
    return [str(action.metavar or action.dest) for action in parser._actions
            if not action.option_strings and not isinstance(action,
                                                            argparse._SubParsersAction)]


# --- README's synopsis -------------------------------------------------------------------------
def readme_synopsis() -> dict[tuple[str, ...], str]:
    """The fenced block under "## Command line": command path -> the rest of its lines."""
    text = README.read_text()
    section = text.split("\n## Command line\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```", 2)[1]
    lines: list[str] = []
    for raw in block.splitlines()[1:]:
        line = raw.split("#", 1)[0].rstrip()
        if not line:
            continue
        if line[0].isspace():
            lines[-1] += " " + line.strip()
        else:
            lines.append(line)
    prefixes = {path[:i] for path in parser_commands() for i in range(len(path) + 1)}
    out: dict[tuple[str, ...], str] = {}
    for line in lines:
        words = line.split()
        assert words[0] == "c3bench", line
        path: tuple[str, ...] = ()
        for word in words[1:]:
            if (*path, word) not in prefixes:
                break
            path = (*path, word)
        assert path not in out, f"{path} twice in the synopsis"
        out[path] = " ".join(words[1 + len(path):])
    return out


def test_readme_synopsis_matches_the_parser() -> None:
    commands = parser_commands()
    synopsis = readme_synopsis()
    assert set(synopsis) == set(commands), "commands differ between README and parser"
    for path, parser in commands.items():
        shown = set(OPTION.findall(synopsis[path]))
        name = " ".join(("c3bench", *path))
        assert options_of(parser) - shown == set(), f"{name}: missing from README"
        assert shown - options_of(parser) == set(), f"{name}: not options of the parser"
        words = synopsis[path].split()
        for positional in positionals_of(parser):
            assert positional in words or f"[{positional}]" in words, \
                f"{name}: positional {positional} not in README"


# --- conventions -------------------------------------------------------------------------------
def test_every_command_and_option_has_help() -> None:
    for path, parser in parser_commands().items():
        for action in parser._actions:
            assert action.help and action.help != argparse.SUPPRESS, (path, action.dest)
    root = build_parser()
    for parser in [root, *_subcommands(root).values()]:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                assert all(choice.help for choice in action._choices_actions), parser.prog


def test_every_list_option_uses_the_one_list_action() -> None:
    for path, parser in parser_commands().items():
        for action in parser._actions:
            if action.nargs in ("+", "*"):
                assert isinstance(action, ListAction), (path, action.dest)


def test_results_is_the_results_root_everywhere() -> None:
    for path, parser in parser_commands().items():
        if path[:1] in ((), ("problems",), ("solvers",)):
            assert "--results" not in options_of(parser)
            continue
        action = next(a for a in parser._actions if "--results" in a.option_strings)
        assert (action.default, action.metavar) == ("results", "ROOT"), path
        assert "results root" in str(action.help), path


@pytest.mark.parametrize(("command", "option", "values", "expected"), [
    (["run"], "solvers", ["osqp", "clarabel"], ["osqp", "clarabel"]),
    (["run"], "settings", ["default", "high_accuracy"], ["default", "high_accuracy"]),
    (["run"], "precision", ["float32", "float64"], ["float32", "float64"]),
    (["run"], "start", ["warm", "cold"], ["warm", "cold"]),
    (["run"], "families", ["lcp", "c3_qp"], ["lcp", "c3_qp"]),
    (["run"], "plugin", ["a.b", "c:d"], ["a.b", "c:d"]),
    (["solvers"], "plugin", ["a.b:f", "c"], ["a.b:f", "c"]),
    (["perf"], "samples", ["1", "16"], [1, 16]),
    (["perf"], "backend", ["c3-osqp", "c3plus-riccati"], ["c3-osqp", "c3plus-riccati"]),
    (["perf"], "precision", ["float64", "float32"], ["float64", "float32"]),
    (["sweep"], "dt", ["0.05", "0.1"], [0.05, 0.1]),
    (["sweep"], "rho-schedule", ["adaptive", "geometric"], ["adaptive", "geometric"]),
    (["sweep"], "q-box", ["2e4", "2e5"], [2e4, 2e5]),
    (["sweep"], "model-l", ["0.29", "0.3"], [0.29, 0.30]),
])
def test_list_forms_parse_equal(command: list[str], option: str, values: list[str],
                                expected: list[object]) -> None:
    parser = build_parser()
    flag = f"--{option}"
    dest = option.replace("-", "_")
    spaced = parser.parse_args([*command, flag, *values])
    commas = parser.parse_args([*command, flag, ",".join(values)])
    repeated = parser.parse_args([*command, *(x for v in values for x in (flag, v))])
    assert getattr(spaced, dest) == getattr(commas, dest) == getattr(repeated, dest) \
        == expected


def test_perf_runs_each_backend_in_its_own_process_unless_told() -> None:
    from c3bench.bench.perf import PerfSettings

    parser = build_parser()
    assert parser.parse_args(["perf"]).worker_processes is PerfSettings().worker_processes is True
    assert parser.parse_args(["perf", "--same-process"]).worker_processes is False


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"c3bench {__version__}\n"


def test_help_of_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    for path in [*parser_commands(), ("problems",)]:
        assert main([*path, "--help"]) == 0, path
        out = capsys.readouterr().out
        assert out.startswith(f"usage: {' '.join(('c3bench', *path))}"), path


@pytest.mark.parametrize("argv", [
    ["perf", "--samples", "0"], ["perf", "--samples", "1,x"], ["run", "--jobs", "0"],
    ["run", "--time-limit", "nan"], ["sweep", "--dt", "-1"], ["run", "--start", "hot"],
    ["closed-loop", "--duration", "inf"], ["perf", "--backend", "nope"], ["nothing"],
    ["run", "--solvers"],
])
def test_bad_input_is_one_line_and_exit_code_2(argv: list[str],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("error: ") and captured.err.count("\n") == 1


def test_missing_plugin_is_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["solvers", "--plugin", "c3bench_no_such_plugin_module"]) == 2
    assert capsys.readouterr().err.startswith(
        "error: cannot load plugin 'c3bench_no_such_plugin_module'")


PLUGIN = '''
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result


class PluginBackend(Backend):
    name = "plugin_fake"
    families = ("lcp",)
    description = "registered by a test plugin"

    def solve(self, problem, settings, warm_start=None):
        return Result(self.name, problem.name, False, "never called")


def register():
    registry.register(PluginBackend())
'''


def test_solvers_plugin_registers_a_backend(tmp_path: Path) -> None:
    (tmp_path / "c3bench_test_plugin.py").write_text(PLUGIN)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    without = subprocess.run([sys.executable, "-m", "c3bench", "solvers"], env=env,
                             capture_output=True, text=True, timeout=300)
    assert without.returncode == 0, without.stderr
    assert "plugin_fake" not in without.stdout
    done = subprocess.run([sys.executable, "-m", "c3bench", "solvers", "--plugin",
                           "c3bench_test_plugin:register"], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    line = next(line for line in done.stdout.splitlines() if "plugin_fake" in line)
    assert "registered by a test plugin" in line and " yes " in f" {line} "


def _metrics(**values: float) -> SimpleNamespace:
    """The fields :func:`metric_lines` prints, zero unless given."""
    names = ("peak_angle", "balance_angle", "hold_time", "settling_time", "steady_offset",
             "pivot_slip", "first_touch_time", "impact_speed", "contact_time", "free_time",
             "max_cube_penetration", "max_table_penetration", "clipped_inputs",
             "plan_lcs_angle_median", "plan_lcs_angle_max", "plan_lcs_error_median",
             "plan_plant_angle_median", "plan_plant_angle_max", "plan_plant_error_median")
    return SimpleNamespace(gentle_success=False, passed_balance=False,
                           **{name: values.get(name, 0.0) for name in names})


def test_closed_loop_summary_says_no_contact_instead_of_nan() -> None:
    never = next(line for line in metric_lines(_metrics(
        first_touch_time=math.nan, impact_speed=math.nan, free_time=3.0))
        if line.startswith("contact"))
    assert never == "contact           no contact; 0.00 s in contact, 3.00 s out"
    touched = next(line for line in metric_lines(_metrics(
        first_touch_time=0.058, impact_speed=3.41, contact_time=1.0, free_time=2.0))
        if line.startswith("contact"))
    assert touched == ("contact           first touch 0.06 s at 3.41 m/s; 1.00 s in contact, "
                       "2.00 s out")
