"""A short ``c3bench perf`` run: rows, phases, flops, ratios, files and report (no timing is
checked)."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from c3bench.bench.perf import PerfSettings, lcs_dimensions, perf_context, run_perf
from c3bench.bench.perf_backends import BackendUnavailable, Configuration, make_compiled
from c3bench.bench.perf_flops import admm_flops
from c3bench.bench.perf_store import PERF_COLUMNS, read_perf
from c3bench.bench.report import perf_report_section


def test_short_run_records_every_phase_and_ratio(tmp_path: Path) -> None:
    settings = PerfSettings(samples=(1, 2), backends=("c3plus-riccati", "c3-clarabel"),
                            repeats=2, warmup=1, iterations=2, results_dir=tmp_path)
    lines: list[str] = []
    frame = run_perf(settings, echo=lines.append)
    assert list(frame.columns) == list(PERF_COLUMNS)
    timed = frame[~frame["skipped"].astype(bool)]
    # two rounds of four steps each: riccati at 1 and 2 samples, clarabel at 1 only
    assert len(timed) == 2 * 4 * 2 + 2 * 4 and timed["ok"].all()
    both = timed[timed["samples"] == 1]
    assert both.groupby(["backend", "cache"]).size().to_dict() == {
        ("c3-clarabel", "cold"): 2, ("c3-clarabel", "warm"): 6,
        ("c3plus-riccati", "cold"): 2, ("c3plus-riccati", "warm"): 6}
    alone = timed[timed["samples"] == 2]  # riccati alone: its blocks follow the matmul probe
    assert list(alone["cache"]) == ["cold", "warm", "warm", "warm"] * 2
    assert list(both[both["backend"] == "c3plus-riccati"]["repeat"]) == list(range(8))
    # phases: the whole step is LCS build + weighting + QP + projection + overhead
    parts = timed["lcs_ms"] + timed["weighting_ms"] + timed["qp_ms"] + timed["proj_ms"] \
        + timed["overhead_ms"]
    np.testing.assert_allclose(parts, timed["total_ms"], rtol=1e-9)
    np.testing.assert_allclose(timed["total_no_weighting_ms"],
                               timed["total_ms"] - timed["weighting_ms"], rtol=1e-12)
    assert (timed["admm_ms"] <= timed["total_ms"]).all()
    weighted = timed[timed["samples"] == 2]
    assert weighted["weighted"].all() and (weighted["weighting_ms"] > 0).all()
    assert not timed[timed["samples"] == 1]["weighted"].any()
    # the flop model of the measured dimensions; none for the reference controller
    riccati = timed[(timed["backend"] == "c3plus-riccati") & (timed["samples"] == 2)]
    nx, nlam, nu = lcs_dimensions(perf_context(settings))
    assert (riccati["admm_mflop"] == admm_flops(nx, nlam, nu, 7, 2, 2).total / 1e6).all()
    assert (riccati["admm_mflop_executed"] == riccati["admm_mflop"]).all()
    assert timed[timed["backend"] == "c3-clarabel"]["admm_mflop"].isna().all()
    # one matmul rate per run, in every row; one through the rounds per sample count
    assert timed["matmul_gflops_f64"].nunique() == 1 and timed["matmul_gflops_f64"].gt(0).all()
    for column in ("matmul_run_gflops_f64", "matmul_run_gflops_f32"):
        per_samples = timed.groupby("samples")[column]
        assert (per_samples.nunique() == 1).all() and timed[column].gt(0).all()
    assert any(line.startswith("# dense matmul rate") for line in lines)
    summary_lines = lines[lines.index(next(x for x in lines if x.startswith("# summary"))):]
    assert any("c3-clarabel" in x and "t/riccati" in x and "load" in x for x in summary_lines)
    skipped = frame[frame["skipped"].astype(bool)]
    assert len(skipped) == 1 and "samples" in skipped["note"].iloc[0]
    assert len(read_perf(tmp_path)) == len(frame)
    assert (tmp_path / "perf" / "figures" / "perf_time_vs_samples.png").stat().st_size > 0
    section = perf_report_section(tmp_path)
    assert "| c3plus-riccati |" in section and "GFLOP/s" in section
    assert "Dense matmul rate of this run" in section
    assert "| c3plus-riccati | float64 | cpu | 1 | cold |" in section
    assert "No measurement" in perf_report_section(tmp_path / "missing")


def test_no_weighting_keeps_weighting_at_zero(tmp_path: Path) -> None:
    settings = PerfSettings(samples=(2,), backends=("c3plus-riccati",), repeats=1, warmup=0,
                            iterations=1, results_dir=tmp_path, weighting=False)
    frame = run_perf(settings, echo=None)
    assert not frame["weighted"].any() and (frame["weighting_ms"] == 0).all()


def test_compiled_backend_reports_why_it_cannot_run(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "c3bench.solvers.admm.compiled", None)
    monkeypatch.setitem(sys.modules, "c3bench.solvers.admm.compiled_solver", None)
    with pytest.raises(BackendUnavailable, match=r"^compiled kernel unavailable: "):
        make_compiled(None, Configuration("c3plus-compiled", "float64", "cpu", 1))  # type: ignore[arg-type]


def test_any_qp_backend_can_sit_inside_the_reference_controller() -> None:
    """``c3-<QP backend>``: the controller-sequence measurement (10 QP steps of one ADMM run
    through that backend, timed end to end) for any registry backend taking c3plus_qp."""
    from c3bench.bench.perf import PerfSettings
    from c3bench.bench.perf_backends import backend_spec, reference_qp
    from c3bench.problems.errors import InputError

    spec = backend_spec("c3-daqp")
    assert spec is not None and spec.reference and spec.make is backend_spec("c3-osqp").make
    assert reference_qp("c3-daqp") == "daqp" and reference_qp("c3-osqp") == "osqp"
    assert backend_spec("c3-lemke") is None  # an LCP solver cannot take the QP step
    assert backend_spec("c3-nope") is None and backend_spec("riccati") is None
    with pytest.raises(InputError, match="--backend: unknown backends"):
        PerfSettings(backends=("c3-nope",))


def _log_factory(log: Path, name: str, fail_at: int | None = None,
                 exit_at: int | None = None) -> Any:
    """A fake backend factory whose steps append ``name samples pid`` to ``log`` (the steps
    may run in a worker process), raise from step ``fail_at + 1`` on, or end the process at
    step ``exit_at + 1``."""
    from c3bench.bench.perf_backends import PreparedBackend, StepParts

    def make(context: Any, config: Configuration) -> PreparedBackend:
        count = [0]

        def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> StepParts:
            count[0] += 1
            if exit_at is not None and count[0] > exit_at:
                os._exit(3)  # the worker dies: an infrastructure failure
            with log.open("a") as handle:
                handle.write(f"{name} {config.samples} {os.getpid()}\n")
            if fail_at is not None and count[0] > fail_at:
                raise FloatingPointError("diverged")
            return StepParts(lcs=1e-4, weighting=0.0, admm=1e-4, qp=1e-4, proj=0.0, ok=True)
        return PreparedBackend(step)
    return make


def _fake_table(monkeypatch: pytest.MonkeyPatch, **factories: Any) -> None:
    from c3bench.bench import perf_backends

    table = dict(perf_backends.BACKEND_TABLE)
    for name, make in factories.items():
        table[name] = dataclasses.replace(table[name], make=make)
    monkeypatch.setattr(perf_backends, "BACKEND_TABLE", table)


@pytest.mark.parametrize("worker_processes", [True, False])
def test_backends_are_timed_interleaved_and_a_failing_one_is_skipped(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, worker_processes: bool) -> None:
    """Every backend of one sample count is warmed up, then round ``r`` runs four consecutive
    steps of each in turn (a slow phase of the machine falls on all alike; the first is
    cache-cold, the others warm); a backend that raises mid-run becomes one skipped row and
    the others keep their rows. Isolated, each configuration steps in a process of its own
    and none is left running."""
    log = tmp_path / "calls.log"
    _fake_table(monkeypatch, **{"c3plus-riccati": _log_factory(log, "a"),
                                "c3plus-compiled": _log_factory(log, "b", fail_at=5)})
    settings = PerfSettings(samples=(1, 2), backends=("c3plus-riccati", "c3plus-compiled"),
                            repeats=3, warmup=1, iterations=1, results_dir=tmp_path,
                            worker_processes=worker_processes)
    frame = run_perf(settings, echo=None)
    calls = [line.split() for line in log.read_text().splitlines()]
    # one sample count after the other; within it, a and b alternate block by block (b stops
    # at its sixth step, the second of the first timed round)
    names = [name for name, _, _ in calls]
    assert names[:22] == ["a"] * 4 + ["b"] * 4 + ["a"] * 4 + ["b"] * 2 + ["a"] * 8
    assert names[22:] == names[:22] and {n for _, n, _ in calls[22:]} == {"2"}
    processes = {(name, samples): {pid for n, s, pid in calls if (n, s) == (name, samples)}
                 for name, samples, _ in calls}
    assert all(len(pids) == 1 for pids in processes.values())
    pids = set().union(*processes.values())
    if worker_processes:  # two configurations per sample count, each in a worker of its own
        assert len(pids) == 4 and str(os.getpid()) not in pids
    else:
        assert pids == {str(os.getpid())}
    assert not multiprocessing.active_children()
    timed = frame[~frame["skipped"].astype(bool)]
    assert (timed["backend"] == "c3plus-riccati").all() and len(timed) == 2 * 3 * 4
    assert list(timed["cache"]) == ["cold", "warm", "warm", "warm"] * 6
    skipped = frame[frame["skipped"].astype(bool)]
    assert len(skipped) == 2 and skipped["note"].str.contains("FloatingPointError").all()
    assert set(frame["process"]) == {"worker" if worker_processes else "shared"}


@pytest.mark.parametrize("worker_processes", [True, False])
def test_a_backend_that_cannot_be_prepared_or_timed_is_a_skipped_row(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, worker_processes: bool) -> None:
    """In a worker or not: a factory that says it cannot run, a factory that raises and a
    backend whose compile-time query raises each become one skipped row with the reason."""
    from c3bench.bench.perf_backends import PreparedBackend, StepParts

    def unavailable(context: Any, config: Configuration) -> PreparedBackend:
        raise BackendUnavailable("no such thing here")

    def raising(context: Any, config: Configuration) -> PreparedBackend:
        raise ZeroDivisionError("bad factory")

    def bad_compile(context: Any, config: Configuration) -> PreparedBackend:
        def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> StepParts:
            return StepParts(lcs=1e-4, weighting=0.0, admm=1e-4, qp=1e-4, proj=0.0, ok=True)

        def compile_seconds() -> float:
            raise KeyError("no record")
        return PreparedBackend(step, compile_seconds=compile_seconds)

    _fake_table(monkeypatch, **{"c3plus-riccati": unavailable, "c3plus-compiled": raising,
                                "c3plus-jax": bad_compile})
    frame = run_perf(PerfSettings(samples=(1,), backends=("c3plus-riccati", "c3plus-compiled",
                                                          "c3plus-jax"),
                                  repeats=1, warmup=0, iterations=1, results_dir=tmp_path,
                                  worker_processes=worker_processes), echo=None)
    assert frame["skipped"].astype(bool).all() and len(frame) == 3
    notes = dict(zip(frame["backend"], frame["note"], strict=True))
    assert notes["c3plus-riccati"] == "no such thing here"
    assert notes["c3plus-compiled"] == "preparation failed: ZeroDivisionError: bad factory"
    assert notes["c3plus-jax"].endswith("KeyError: 'no record'")
    assert not multiprocessing.active_children()


def test_a_lost_worker_stores_nothing_for_its_configuration(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker process that dies is an infrastructure failure: its configuration gets no row
    (not even a skipped one), the run says so and the other backends keep their rows."""
    log = tmp_path / "calls.log"
    _fake_table(monkeypatch, **{"c3plus-riccati": _log_factory(log, "a"),
                                "c3plus-compiled": _log_factory(log, "b", exit_at=6)})
    lines: list[str] = []
    frame = run_perf(PerfSettings(samples=(1,), backends=("c3plus-riccati", "c3plus-compiled"),
                                  repeats=2, warmup=1, iterations=1, results_dir=tmp_path),
                     echo=lines.append)
    assert set(frame["backend"]) == {"c3plus-riccati"} and len(frame) == 2 * 4
    assert not frame["skipped"].astype(bool).any()
    assert any("c3plus-compiled" in line and "not measured" in line and "exit code 3" in line
               for line in lines)
    assert not multiprocessing.active_children()
