"""``python -m c3bench.bench.gpu_perf``: the exported batches reload exactly and the run measures
every kernel it can (on the CPU here; the GPU rows need a GPU that JAX sees)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench import gpu_perf

pytest.importorskip("jax")
pytestmark = pytest.mark.jax


def test_export_and_run_on_the_cpu(tmp_path: Path) -> None:
    from c3bench.bench.perf import PerfSettings, perf_context
    from c3bench.bench.perf_backends import sample_sides
    from c3bench.problems.linearize_batch import BatchLinearizer

    written = gpu_perf.export(tmp_path / "batches", samples=[2], states=1)
    assert [p.name for p in written] == ["mpc.npz", "lcs-n2-s0.npz"]
    mpc, batches = gpu_perf._load(tmp_path / "batches")
    context = perf_context(PerfSettings())
    _, x, u_prev = context.states[0]
    expected = BatchLinearizer(sample_sides(2, 0), context.config).linearize(
        x, u_prev, context.config.mpc.dt)
    (lcs, x0), = batches[2]
    np.testing.assert_array_equal(lcs.F, expected.F)
    np.testing.assert_array_equal(x0, x)
    np.testing.assert_array_equal(mpc.Q, context.mpc.Q)
    out = tmp_path / "rows.jsonl"
    rows = gpu_perf.run(tmp_path / "batches", out, ["float64"], repeats=2, warmup=1,
                        cpu_samples_limit=4)
    backends = {(row["backend"], row["device"]) for row in rows}
    assert ("c3plus-compiled", "cpu") in backends and ("c3plus-jax", "cpu") in backends
    assert all(row["ok"] and row["admm_ms_median"] > 0 for row in rows)
    assert [json.loads(line) for line in out.read_text().splitlines()] == rows
