"""Hostile inputs to the closed-loop, sweep and perf commands and to configuration files: each
is refused up front with one line ``error: ...`` naming the option or file and exit code 2,
never a hang, an exhausted memory, a traceback or a silently accepted value.

Nothing here runs a controller: :func:`no_work` replaces the functions that would simulate,
time or enumerate the episodes with ones that fail the test at once, so an input that slips
through fails fast instead of running (or hanging).
"""

from __future__ import annotations

import argparse
import enum
import os
from pathlib import Path

import pytest

from c3bench.bench.cli import build_parser, main
from c3bench.bench.cli_checks import (
    MAX_MODEL_SIDE,
    MAX_STACKED_SAMPLES,
    check_backend_options,
    check_plant_period,
)
from c3bench.bench.cli_closed_loop import backend_options, suite_trials
from c3bench.bench.cli_options import (
    MAX_ITERATIONS,
    MAX_SAMPLES,
    MAX_TRIALS,
    path_text,
    plain_choices,
)
from c3bench.problems.config import (
    MAX_CONFIG_BYTES,
    MAX_HORIZON,
    MPCConfig,
    SceneConfig,
    load_config,
)
from c3bench.problems.errors import InputError

pytestmark = pytest.mark.timeout(60)


def _refuse(*args: object, **kwargs: object) -> None:
    raise AssertionError("bad input reached the work")


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Running, timing or enumerating anything fails the test (an internal error, exit 1)."""
    from c3bench.bench import closed_loop, closed_loop_configs, closed_loop_suite, perf, trials

    monkeypatch.setattr(closed_loop, "run_closed_loop", _refuse)
    monkeypatch.setattr(closed_loop_suite, "run_cases", _refuse)
    monkeypatch.setattr(trials, "trial_cases", _refuse)
    monkeypatch.setattr(closed_loop_configs.ClosedLoopSuite, "cases", _refuse)
    monkeypatch.setattr(perf, "run_perf", _refuse)


def _error_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``c3bench argv``: it exits 2 with one line ``error: ...`` on stderr; that line."""
    code = main(argv)
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert code == 2, captured.err
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err
    return lines[0]


# --- item: caps on counts (samples, iterations, trials) ------------------------------------------
@pytest.mark.parametrize(("argv", "words"), [
    (["perf", "--samples", "100000000"], ["--samples", f"at most {MAX_SAMPLES}"]),
    (["perf", "--samples", "1,16,5000"], ["--samples", f"at most {MAX_SAMPLES}"]),
    (["perf", "--iterations", "100000"], ["--iterations", f"at most {MAX_ITERATIONS}"]),
    (["closed-loop", "--controller", "c3plus-fast-robust", "--samples", "1000000"],
     ["--samples", f"at most {MAX_SAMPLES}"]),
    (["closed-loop", "--controller", "c3plus-robust", "--samples", str(MAX_STACKED_SAMPLES + 1)],
     ["--samples", f"at most {MAX_STACKED_SAMPLES}"]),
    (["closed-loop", "--iterations", "1000000"], ["--iterations", f"at most {MAX_ITERATIONS}"]),
    (["closed-loop-trials", "--trials", "100000000"], ["--trials", f"at most {MAX_TRIALS}"]),
    (["closed-loop-trials", "--controller", "c3plus-fast-robust", "--samples", "5000"],
     ["--samples", f"at most {MAX_SAMPLES}"]),
    (["closed-loop-suite", "--trials", str(MAX_TRIALS + 1)], ["--trials", f"at most {MAX_TRIALS}"]),
])
def test_huge_counts_are_refused(argv: list[str], words: list[str], no_work: None,
                                 tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = _error_line([*argv, "--results", str(tmp_path / "r")], capsys)
    assert all(word in line for word in words), line
    assert not (tmp_path / "r").exists()


def test_counts_at_their_caps_parse() -> None:
    parser = build_parser()
    perf = parser.parse_args(["perf", "--samples", f"1,{MAX_SAMPLES}", "--iterations",
                              str(MAX_ITERATIONS)])
    assert perf.samples == [1, MAX_SAMPLES] and perf.iterations == MAX_ITERATIONS
    trials = parser.parse_args(["closed-loop-trials", "--trials", str(MAX_TRIALS)])
    assert trials.trials == MAX_TRIALS


def test_caps_are_in_the_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["perf", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert f"each at most {MAX_SAMPLES}" in out and f"at most {MAX_ITERATIONS}" in out
    assert main(["closed-loop-trials", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert f"at most {MAX_TRIALS}" in out and f"at most {MAX_STACKED_SAMPLES}" in out


def test_suite_trials_are_capped_outside_the_parser() -> None:
    from c3bench.bench.closed_loop_configs import CLOSED_LOOP_SUITES

    with pytest.raises(InputError, match=f"--trials must be an integer in \\[1, {MAX_TRIALS}\\]"):
        suite_trials(argparse.Namespace(trials=MAX_TRIALS + 1), 20)
    with pytest.raises(InputError, match="--trials"):
        CLOSED_LOOP_SUITES["quick"].cases(MAX_TRIALS + 1)


# --- item: configuration files (size, kind, horizon, periods) -----------------------------------
def _config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "task.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("text", "words"), [
    ("[mpc]\nhorizon = 100000000\n", f"[mpc] T (horizon) must be an integer in [1, {MAX_HORIZON}]"),
    ("[mpc]\ndt = 0.0505\n", "[mpc] dt = 0.0505 is not a whole multiple of [scene] plant_timestep"),
    ("[scene]\nplant_timestep = 1e-9\n", "[scene] plant_timestep must be at least"),
])
def test_config_values_that_would_hang_are_refused(text: str, words: str, tmp_path: Path
                                                   ) -> None:
    path = _config(tmp_path, text)
    with pytest.raises(InputError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: ") and words in str(caught.value)


def test_config_limits_keep_the_sane_values(tmp_path: Path) -> None:
    assert MPCConfig(horizon=MAX_HORIZON).horizon == MAX_HORIZON
    with pytest.raises(ValueError, match="horizon"):
        MPCConfig(horizon=MAX_HORIZON + 1)
    with pytest.raises(ValueError, match="plant_timestep"):
        SceneConfig(plant_timestep=1e-7)
    loaded = load_config(_config(tmp_path, "[mpc]\ndt = 0.003\nhorizon = 40\n"))
    assert (loaded.mpc.dt, loaded.mpc.horizon) == (0.003, 40)


def test_config_that_is_not_a_regular_file_is_refused_before_reading() -> None:
    with pytest.raises(InputError, match="/dev/null: not a regular file"):
        load_config("/dev/null")  # was read as an empty file: the defaults, silently


def test_config_larger_than_the_cap_is_refused_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "huge.toml"
    with path.open("wb") as handle:  # sparse: nothing is written, and nothing should be read
        handle.truncate(MAX_CONFIG_BYTES + 1)
    with pytest.raises(InputError, match=f"{MAX_CONFIG_BYTES + 1} bytes; a configuration file"):
        load_config(path)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_config_that_is_a_pipe_is_refused_without_blocking(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str],
                                                           no_work: None) -> None:
    pipe = tmp_path / "task.toml"
    os.mkfifo(pipe)  # opening it to read would block until a writer comes
    line = _error_line(["closed-loop", "--config", str(pipe), "--results",
                        str(tmp_path / "r")], capsys)
    assert f"{pipe}: not a regular file" in line


# --- item: sweep and model sides checked against the plant and MuJoCo --------------------------
@pytest.mark.parametrize(("argv", "words"), [
    (["--dt", "0.0001"], "--dt 0.0001: not a whole multiple of the plant's time step 0.001 s"),
    (["--dt", "1e-9"], "--dt 1e-09: not a whole multiple"),
    (["--dt", "0.05,0.0505"], "--dt 0.0505: not a whole multiple"),
    (["--model-l", "1e-9"], "--model-l 1e-09: MuJoCo cannot build a model cube"),
    (["--model-l", "0.29,1e300"], f"--model-l 1e+300: a model cube side is at most "
                                  f"{MAX_MODEL_SIDE:g} m"),
])
def test_sweep_refuses_periods_and_sides_before_running(argv: list[str], words: str,
                                                        no_work: None, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    line = _error_line(["sweep", "--quiet", "--results", str(tmp_path), "--rho-schedule",
                        "geometric", "--q-box", "2e4", *argv], capsys)
    assert words in line, line
    assert "mjMINVAL" not in line or "--model-l" in line
    assert not (tmp_path / "closed_loop").exists()


@pytest.mark.parametrize("command", ["closed-loop", "closed-loop-trials"])
def test_model_side_mujoco_rejects_names_the_option(command: str, no_work: None,
                                                    tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    line = _error_line([command, "--model-l", "1e-9", "--duration", "0.1", "--quiet",
                        "--results", str(tmp_path)], capsys)
    assert line.startswith("error: --model-l 1e-09: MuJoCo cannot build"), line
    assert not (tmp_path / "closed_loop").exists()


def test_plant_periods_that_are_whole_steps_pass() -> None:
    config = load_config()
    for dt in (0.001, 0.003, 0.05, 0.1, 0.35):
        check_plant_period("--dt", dt, config)
    with pytest.raises(InputError, match=r"--dt 0\.0015"):
        check_plant_period("--dt", 0.0015, config)


# --- item: backend options the controller does not use ------------------------------------------
@pytest.mark.parametrize(("argv", "words"), [
    (["closed-loop", "--controller", "c3plus-fast", "--qp-backend", "bogus"],
     "--qp-backend: unknown solver 'bogus', and --qp-backend does not apply to --controller "
     "c3plus-fast"),
    (["closed-loop", "--controller", "c3plus-fast-robust", "--qp-backend", "clarabel"],
     "--qp-backend 'clarabel' does not apply to --controller c3plus-fast-robust"),
    (["closed-loop", "--controller", "c3plus", "--projection", "bogus"],
     "--projection: unknown solver 'bogus', and --projection does not apply to --controller "
     "c3plus"),
    (["closed-loop", "--controller", "c3plus-fast", "--projection", "scip"],
     "--projection 'scip' does not apply to --controller c3plus-fast"),
    (["closed-loop-trials", "--controller", "c3plus-fast", "--qp-backend", "lemke"],
     "--qp-backend 'lemke' does not apply to --controller c3plus-fast"),
])
def test_backend_options_the_controller_does_not_use_are_refused(
        argv: list[str], words: str, no_work: None, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    line = _error_line([*argv, "--duration", "0.1", "--quiet", "--results", str(tmp_path)],
                       capsys)
    assert words in line, line
    assert not (tmp_path / "closed_loop").exists()


def test_backend_options_default_when_left_out() -> None:
    args = build_parser().parse_args(["closed-loop", "--controller", "c3plus-fast"])
    assert backend_options(args) == {}
    args = build_parser().parse_args(["closed-loop", "--controller", "c3", "--projection",
                                      "gurobi", "--qp-backend", "osqp"])
    assert backend_options(args) == {"qp_backend": "osqp", "projection": "gurobi"}
    check_backend_options("c3plus", {"--qp-backend": "osqp", "--projection": None})


# --- item: choices listed as plain values ---------------------------------------------------------
@pytest.mark.parametrize("command", [["closed-loop"], ["sweep"]])
def test_bad_rho_schedule_lists_plain_values(command: list[str], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    line = _error_line([*command, "--rho-schedule", "bogus", "--results", str(tmp_path)],
                       capsys)
    assert "--rho-schedule" in line and "geometric" in line and "adaptive" in line
    assert "<" not in line and "RhoScheduleName" not in line, line


def test_enum_choices_become_their_values() -> None:
    class Colour(enum.StrEnum):
        RED = "red"

    assert plain_choices(tuple(Colour)) == ("red",)
    assert plain_choices(("a", "b")) == ("a", "b")
    assert plain_choices(None) is None


# --- item: empty paths ---------------------------------------------------------------------------
@pytest.mark.parametrize(("argv", "option"), [
    (["closed-loop", "--results", ""], "--results"),
    (["closed-loop", "--render", ""], "--render"),
    (["closed-loop", "--config", ""], "--config"),
    (["closed-loop-trials", "--results", ""], "--results"),
    (["closed-loop-suite", "--results", ""], "--results"),
    (["sweep", "--results", ""], "--results"),
    (["perf", "--results", " "], "--results"),
    (["run", "--results", ""], "--results"),
    (["report", "--results", ""], "--results"),
])
def test_empty_paths_are_refused(argv: list[str], option: str, no_work: None,
                                 tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)  # an empty path meant the current directory
    line = _error_line(argv, capsys)
    assert f"argument {option}: expected a path, got an empty one" in line, line
    assert not any(tmp_path.iterdir())


def test_empty_path_text_and_config_path() -> None:
    assert path_text("out") == "out"
    with pytest.raises(argparse.ArgumentTypeError, match="empty"):
        path_text("")
    with pytest.raises(InputError, match="path is empty"):
        load_config("")
