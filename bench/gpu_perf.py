"""GPU figures of the batched C3+ step, measured on a machine without MuJoCo.

The JAX kernel (:class:`c3bench.solvers.fast_jax.JaxC3Plus`) needs only numpy and JAX, while
the LCS build needs MuJoCo. So the measurement is split:

* ``python -m c3bench.bench.gpu_perf export DIR`` (here): the LCS batches of ``c3bench perf``'s
  first visited states of the scripted push, cube sides ``U[0.27, 0.33]`` (seeded as
  ``c3bench perf``), for each number of samples, plus the MPC, as ``.npz`` files;
* ``python -m c3bench.bench.gpu_perf run DIR --out CSV`` (on the GPU machine): one warm-started
  control step (10 ADMM iterations, geometric schedule, the one loop) per state, ``--repeats``
  times, after ``--warmup`` untimed steps (JIT compilation), for ``c3plus-jax`` on the GPU and,
  in the same run for ratios, ``c3plus-jax`` and ``c3plus-compiled`` on that machine's CPU
  (one thread for BLAS). Rows: backend, device, device kind, precision, samples, median and
  p95 ADMM milliseconds, the load average and the JAX version. Nothing is written for a
  device that is not there.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.lcs import LCS_MATRICES, LCSBatch
from c3bench.problems.mpc import MPC

MPC_FIELDS: tuple[str, ...] = ("Q", "R", "Q_f", "x_target", "horizon", "dt", "force_limit")
GPU_NUMBERS: tuple[str, ...] = ("samples", "admm_ms_median", "admm_ms_p95", "load_avg")
"""The number fields of a row of :func:`run` that the perf report reads."""
GPU_FIELDS: tuple[str, ...] = ("backend", "device", "device_kind", "precision", *GPU_NUMBERS)
"""The fields of a row of :func:`run` that the perf report reads
(:func:`bench.perf_report.gpu_rows` checks them); a row also has ``ok``, ``repeats`` and
``jax``."""


def export(out: Path, samples: Sequence[int], states: int = 4, seed: int = 0) -> list[Path]:
    """Write ``mpc.npz`` and ``lcs-n<samples>-s<state>.npz`` (arrays and ``x0``) under ``out``."""
    from c3bench.bench.perf import PerfSettings, perf_context
    from c3bench.bench.perf_backends import sample_sides
    from c3bench.problems.linearize_batch import BatchLinearizer

    context = perf_context(PerfSettings(seed=seed))
    out.mkdir(parents=True, exist_ok=True)
    mpc = context.mpc
    save: Any = np.savez  # numpy's stub types the keyword arrays as its flags
    save(out / "mpc.npz", **{name: np.asarray(getattr(mpc, name)) for name in MPC_FIELDS})
    written = [out / "mpc.npz"]
    dt = context.config.mpc.dt
    for n in samples:
        linearizer = BatchLinearizer(sample_sides(n, seed), context.config)
        for index, (_, x, u_prev) in enumerate(context.states[:states]):
            lcs = linearizer.linearize(x, u_prev, dt)
            path = out / f"lcs-n{n}-s{index}.npz"
            np.savez_compressed(path, x0=x, dt=lcs.dt,
                                **{name: getattr(lcs, name) for name in LCS_MATRICES})
            written.append(path)
    return written


def _load(directory: Path) -> tuple[MPC, dict[int, list[tuple[LCSBatch, np.ndarray]]]]:
    stored = np.load(directory / "mpc.npz")
    mpc = MPC(Q=stored["Q"], R=stored["R"], Q_f=stored["Q_f"], x_target=stored["x_target"],
              horizon=int(stored["horizon"]), dt=float(stored["dt"]),
              force_limit=float(stored["force_limit"]))
    batches: dict[int, list[tuple[LCSBatch, np.ndarray]]] = {}
    for path in sorted(directory.glob("lcs-n*-s*.npz")):
        n = int(path.stem.split("-")[1][1:])
        data = np.load(path)
        lcs = LCSBatch(**{name: data[name] for name in LCS_MATRICES}, dt=float(data["dt"]))
        batches.setdefault(n, []).append((lcs, data["x0"]))
    return mpc, batches


def _time(make: Callable[[], Any], states: list[tuple[LCSBatch, np.ndarray]], repeats: int,
          warmup: int) -> tuple[float, float, bool]:
    """Median and p95 milliseconds of warm-started steps over the states, and all ok."""
    from c3bench.solvers.fast import FastC3PlusController

    controller = FastC3PlusController(make())
    for i in range(warmup):
        lcs, x0 = states[i % len(states)]
        controller.step(lcs, x0)
    times, ok = [], True
    for i in range(repeats):
        lcs, x0 = states[i % len(states)]
        start = time.perf_counter()
        solution = controller.step(lcs, x0)
        times.append((time.perf_counter() - start) * 1e3)
        ok = ok and bool(solution.ok)
    return float(np.median(times)), float(np.percentile(times, 95)), ok


def run(directory: Path, out: Path, precisions: Sequence[str], repeats: int, warmup: int,
        cpu_samples_limit: int) -> list[dict[str, Any]]:
    """Measure (module docstring); rows also written as JSON lines to ``out``."""
    from threadpoolctl import threadpool_limits

    from c3bench.solvers.fast import fast_options
    from c3bench.solvers.fast_jax import JaxC3Plus, gpu_available, jax_modules, jax_version

    jax, _, _ = jax_modules()
    mpc, batches = _load(directory)
    options = fast_options()
    rows: list[dict[str, Any]] = []
    devices = ["gpu", "cpu"] if gpu_available() else ["cpu"]
    for n, states in sorted(batches.items()):
        for precision in precisions:
            configs: list[tuple[str, str, Callable[[], Any]]] = [
                ("c3plus-jax", device, partial(JaxC3Plus, mpc, options, precision=precision,
                                               device=device)) for device in devices]
            try:
                from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
                configs.append(("c3plus-compiled", "cpu",
                                partial(CompiledC3Plus, mpc, options, precision=precision)))
            except ImportError:
                pass
            for backend, device, make in configs:
                if device == "cpu" and n > cpu_samples_limit:
                    continue
                with threadpool_limits(1):
                    median, p95, ok = _time(make, states, repeats, warmup)
                kind = jax.devices(device)[0].device_kind if backend == "c3plus-jax" else "cpu"
                row = {"backend": backend, "device": device, "device_kind": str(kind),
                       "precision": precision, "samples": n, "admm_ms_median": median,
                       "admm_ms_p95": p95, "ok": ok, "repeats": repeats,
                       "load_avg": os.getloadavg()[0], "jax": jax_version()}
                rows.append(row)
                print(json.dumps(row), flush=True)
    out.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m c3bench.bench.gpu_perf",
                                     description=__doc__.split("\n\n")[0] if __doc__ else "")
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="write the LCS batches (needs MuJoCo)")
    exp.add_argument("out", type=Path)
    exp.add_argument("--samples", type=int, nargs="+", default=[16, 1024, 4096])
    exp.add_argument("--states", type=int, default=4)
    measure = sub.add_parser("run", help="time the JAX kernel on the GPU (and the CPU)")
    measure.add_argument("directory", type=Path)
    measure.add_argument("--out", type=Path, required=True)
    measure.add_argument("--precision", nargs="+", default=["float32", "float64"])
    measure.add_argument("--repeats", type=int, default=20)
    measure.add_argument("--warmup", type=int, default=3)
    measure.add_argument("--cpu-samples-limit", type=int, default=4096)
    args = parser.parse_args(argv)
    if args.command == "export":
        for path in export(args.out, args.samples, args.states):
            print(path)
        return 0
    run(args.directory, args.out, args.precision, args.repeats, args.warmup,
        args.cpu_samples_limit)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
