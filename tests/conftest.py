"""Shared test fixtures (complementarity instances) and the test order (JAX tests last)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from c3bench.problems import families
from c3bench.problems.config import load_config
from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.linearize import linearize
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.mpc import MPC
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import generate_suite, sample_states, scripted_push
from c3bench.solvers.modes import enumerate_modes

SMALL_MPCC_META = {"scene": "planar", "l": 0.29, "dt": 0.05, "T": 1, "seed": 0,
                   "precision": "float64"}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the JAX tests last: once JAX has run it holds threads, and the local pool
    (``bench.executors``) forks its workers from this process, which is then unsafe. Solver
    isolation does not need this order: it starts its children from a forkserver
    (``test_isolation.py`` checks it after JAX ran)."""
    items.sort(key=lambda item: item.get_closest_marker("jax") is not None)


@pytest.fixture(scope="session")
def compiled_kernels() -> None:
    """Every compiled ADMM kernel signature compiled or loaded from numba's cache, once."""
    from c3bench.solvers.admm.compiled_solver import warm_up

    assert warm_up() >= 0.0


@pytest.fixture(scope="session")
def quick(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Problem]:
    """The quick suite's projection and mpcc instances by name."""
    out: Path = tmp_path_factory.mktemp("quick_complementarity")
    generate_suite("quick", out, progress=False)
    return {p.name: p for p in load_instances(out, ("projection", "mpcc"))}


@pytest.fixture(scope="session")
def small_mpccs() -> dict[str, Problem]:
    """MPCCs of horizon 1 (6 pairs) and 2 (12 pairs) at the quick suite's two states, keyed
    ``h<horizon>-<state position>``."""
    cfg = load_config()
    record = scripted_push(cfg, 1.5)
    scene = build_scene(l=0.29, config=cfg, ball_table=False)  # 3 contacts: enumerable
    base = build_mpc(scene, cfg.mpc)
    out: dict[str, Problem] = {}
    for position, index in enumerate(sample_states(record, 2, 0.02)):
        lcs = linearize(scene, record.states[index], record.inputs[max(index - 1, 0)],
                        cfg.mpc.dt)
        for horizon in (1, 2):
            mpc = dataclasses.replace(base, horizon=horizon)
            out[f"h{horizon}-{position}"] = families.mpcc(
                f"mpcc-h{horizon}-s{index:03d}", lcs, mpc, record.states[index],
                meta=dict(SMALL_MPCC_META, T=horizon))
    return out


def pick(instances: dict[str, Problem], prefix: str, position: int) -> Problem:
    """The ``position``-th instance (sorted by name) whose name starts with ``prefix``
    (names carry state indices that change with the suite's scripted push)."""
    names = sorted(name for name in instances if name.startswith(prefix))
    assert names, f"no instance named {prefix}*"
    return instances[names[position]]


_OPTIMA: dict[str, float] = {}


def enumerated_optimum(problem: Problem) -> float:
    """Global optimum by enumeration of the complementarity modes, cached per instance."""
    if problem.name not in _OPTIMA:
        _OPTIMA[problem.name] = enumerate_modes(problem)[1]
    return _OPTIMA[problem.name]


@pytest.fixture(autouse=True)
def _forget_plugins_loaded_by_the_test(monkeypatch: pytest.MonkeyPatch) -> None:
    """A plugin a test loads from its own temporary folder would be handed to every later
    isolated solve (whose child then cannot import it): each test starts from the plugins
    loaded before it and forgets its own."""
    from c3bench.solvers import registry

    monkeypatch.setattr(registry, "_PLUGINS_LOADED", dict(registry._PLUGINS_LOADED))


def push_batches(position: int, sizes: tuple[int, ...]) -> SimpleNamespace:
    """A contact-rich state of the scripted push (``position`` among 3 sampled states), the
    MPC, and LCS batches of each size in ``sizes`` (cube sides spread over 0.27-0.33; one
    sample: 0.29): ``mpc``, ``x0``, ``batches[n]``."""
    config = load_config()
    record = scripted_push(config)
    mpc = build_mpc(build_scene(l=0.29, config=config), config.mpc)
    index = sample_states(record, 3, 0.02)[position]
    x0, u = record.states[index], record.inputs[index]
    batches = {n: BatchLinearizer(list(np.linspace(0.27, 0.33, n)) if n > 1 else [0.29],
                                  config).linearize(x0, u, config.mpc.dt) for n in sizes}
    return SimpleNamespace(mpc=mpc, x0=x0, batches=batches)


def random_lcs_problem(n: int, seed: int) -> tuple[MPC, LCSBatch, np.ndarray]:
    """A random MPC (nx=4, nu=2, T=5) and ``n`` random LCS with nlam=3."""
    rng = np.random.default_rng(seed)
    nx, nu, nlam, T = 4, 2, 3, 5
    Q = np.diag(rng.uniform(0.5, 2.0, nx))
    mpc = MPC(Q=Q, R=np.diag(rng.uniform(0.1, 1.0, nu)), Q_f=3 * Q,
              x_target=rng.normal(size=nx), horizon=T, dt=0.05, force_limit=10.0)
    F = np.eye(nlam) + 0.1 * rng.normal(size=(n, nlam, nlam))
    lcs = LCSBatch(A=np.eye(nx) + 0.1 * rng.normal(size=(n, nx, nx)),
                   B=rng.normal(size=(n, nx, nu)), D=rng.normal(size=(n, nx, nlam)),
                   d=0.1 * rng.normal(size=(n, nx)), E=rng.normal(size=(n, nlam, nx)),
                   F=F @ np.swapaxes(F, 1, 2), H=rng.normal(size=(n, nlam, nu)),
                   c=rng.normal(size=(n, nlam)), dt=0.05)
    return mpc, lcs, rng.normal(size=nx)


def synthetic_report(tmp_path: Path, table: Any, info: dict[str, Any] | None = None,
                     budget_ms: float | None = None) -> str:
    """The report of a results ``table`` stored as a suite under ``tmp_path`` (no figures;
    the solver table, and ``info``, in its run_info.json)."""
    import json

    from c3bench.bench import store
    from c3bench.bench.report import build_report

    paths = store.SuitePaths.of(tmp_path, "synthetic")
    paths.root.mkdir(parents=True, exist_ok=True)
    store.write_frame(paths, table)
    solvers = [{"name": s, "available": True, "reason": "", "version": "-",
                "families": sorted(set(table.loc[table["solver"] == s, "family"])),
                "precisions": ["float64"]} for s in sorted(set(table["solver"]))]
    paths.run_info.write_text(json.dumps({"solver_table": solvers, **(info or {})}))
    return build_report(paths, table, figures=False, budget_ms=budget_ms)
