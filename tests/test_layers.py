"""The layers: a plant-free core that neither MuJoCo nor CasADi leaks into, and an acyclic graph.

The core is :data:`c3bench.problems.CORE_MODULES` (the one list). Two kinds of checks:

* **run time**, in a fresh interpreter: importing the core, ``c3bench.solvers.base`` and every
  backend module leaves ``mujoco`` and ``casadi`` out of ``sys.modules``; the core's API (LCS,
  MPC, families, storage, capture) works there without them;
* **source**, with :mod:`ast` over every ``.py`` file of ``problems/``, ``solvers/`` and
  ``bench/``: module-level and function-level imports. No core module imports MuJoCo, CasADi or
  a non-core ``c3bench.problems`` module; nothing in ``c3bench.problems`` imports
  ``c3bench.solvers`` or ``c3bench.bench``; nothing in ``c3bench.solvers`` imports
  ``c3bench.bench``; the module-level imports between c3bench modules have no cycle.
  Imports under ``if TYPE_CHECKING:`` never run: they are exempt from the core boundary and
  the cycle check (they may still name neither MuJoCo nor CasADi, and the problems/solvers/bench
  direction rules apply to them too).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems import CORE_MODULES

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {"problems": "c3bench.problems", "solvers": "c3bench.solvers", "bench": "c3bench.bench"}
PLANT_PACKAGES = ("mujoco", "casadi")


# --- run time -------------------------------------------------------------------------------------
def _run(code: str) -> dict[str, object]:
    """Run ``code`` in a fresh interpreter; it prints one JSON object as its last line."""
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=300, cwd=ROOT, check=False)
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def test_core_and_solver_contract_load_without_mujoco_or_casadi() -> None:
    loaded = _run(f"""
        import importlib, json, sys
        import c3bench.solvers.base
        for name in {CORE_MODULES!r}:
            importlib.import_module(name)
        print(json.dumps({{name: name in sys.modules for name in {PLANT_PACKAGES!r}}}))
    """)
    assert loaded == dict.fromkeys(PLANT_PACKAGES, False)


def test_every_backend_module_loads_without_mujoco_or_casadi() -> None:
    """``registry.backends()`` imports every backend module: none may load MuJoCo or CasADi
    at import time (CasADi-based backends import it inside their functions)."""
    loaded = _run(f"""
        import json, sys
        import c3bench.solvers.base
        from c3bench.solvers import registry
        names = registry.backends()
        print(json.dumps({{"backends": len(names),
                          **{{name: name in sys.modules for name in {PLANT_PACKAGES!r}}}}}))
    """)
    assert loaded.pop("backends")
    assert loaded == dict.fromkeys(PLANT_PACKAGES, False)


def test_core_api_works_without_the_plant() -> None:
    """LCS, LCSBatch, MPC, every family builder, storage with and without an LCS, and the
    provisional capture: all without loading MuJoCo."""
    result = _run("""
        import json, sys, tempfile
        import numpy as np
        from c3bench.problems import families
        from c3bench.problems.capture import (
            SUITES, CaptureContext, provisional_capture, reference_rho)
        from c3bench.problems.instance import Problem, load_problem, save_problem
        from c3bench.problems.lcs import LCS, LCSBatch
        from c3bench.problems.mpc import MPC

        rng = np.random.default_rng(0)
        nx, nu, nlam, T = 4, 2, 3, 3
        J = rng.normal(size=(nlam, nx))
        lcs = LCS(A=np.eye(nx) + 0.01 * rng.normal(size=(nx, nx)), B=rng.normal(size=(nx, nu)),
                  D=rng.normal(size=(nx, nlam)), d=np.zeros(nx), E=J,
                  F=np.eye(nlam) + 0.1 * (J @ J.T), H=rng.normal(size=(nlam, nu)),
                  c=np.ones(nlam), dt=0.05)
        batch = LCSBatch.from_lcs([lcs, lcs])
        mpc = MPC(Q=np.eye(nx), R=0.1 * np.eye(nu), Q_f=2 * np.eye(nx), x_target=np.ones(nx),
                  horizon=T, dt=0.05, force_limit=10.0)
        x0, u = rng.normal(size=nx), rng.normal(size=nu)
        meta = {"scene": "planar", "l": 0.29, "dt": 0.05, "T": T, "seed": 0,
                "precision": "float64"}
        problems = [
            families.consensus_qp("c3plus_qp", "a", lcs, mpc, x0, reference_rho(1), meta=meta),
            families.consensus_qp("c3_qp", "b", lcs, mpc, x0,
                                  {k: v for k, v in reference_rho(1).items() if k != "eta"},
                                  meta=meta),
            families.mpcc("c", lcs, mpc, x0, meta=meta),
            families.lcp("d", lcs, x0, u, meta=meta),
            Problem("e", "lcp", P=np.eye(2), q=-np.ones(2), lb=np.zeros(2), meta=meta),
        ]
        context = CaptureContext(SUITES["quick"], 0, x0, u, lcs, mpc, None,
                                 np.random.default_rng(0), meta)
        captured = provisional_capture(context)
        with tempfile.TemporaryDirectory() as directory:
            loaded = [load_problem(save_problem(p, directory)) for p in problems]
        print(json.dumps({
            "batch": batch.n_samples,
            "captured": len(captured),
            "lcs": [p.lcs is not None for p in loaded],
            "same": [bool(np.array_equal(p.P, q.P) and np.array_equal(p.q, q.q))
                     for p, q in zip(problems, loaded)],
            **{name: name in sys.modules for name in ("mujoco", "casadi")},
        }))
    """)
    assert result == {"batch": 2, "captured": 4, "lcs": [True, True, True, True, False],
                      "same": [True] * 5, "mujoco": False, "casadi": False}


# --- source ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Import:
    """One import statement's target, as written in the source."""

    source: str
    """Importing module (``c3bench.problems.lcs``)."""
    target: str
    """Imported module, resolved to the most specific c3bench module when it names one."""
    line: int
    top_level: bool
    """Runs when ``source`` is imported (not inside a function)."""
    type_only: bool
    """Under ``if TYPE_CHECKING:`` (never runs)."""


def _module_files() -> dict[str, Path]:
    """Every module of the three packages by its installed name."""
    modules: dict[str, Path] = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


MODULES = _module_files()


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


class _Collector(ast.NodeVisitor):
    """Imports of one module with where they sit (function body, ``TYPE_CHECKING`` block)."""

    def __init__(self, module: str, is_package: bool) -> None:
        self.module = module
        self.package = module if is_package else module.rpartition(".")[0]
        self.found: list[Import] = []
        self._functions = 0
        self._type_checking = 0

    def _add(self, target: str, node: ast.stmt) -> None:
        self.found.append(Import(self.module, target, node.lineno, self._functions == 0,
                                 self._type_checking > 0))

    def _nested(self, node: ast.AST) -> None:
        self._functions += 1
        self.generic_visit(node)
        self._functions -= 1

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        self._nested(node)

    def visit_AsyncFunctionDef(self, node: ast.AsyncFunctionDef) -> None:
        self._nested(node)

    def visit_Lambda(self, node: ast.Lambda) -> None:
        self._nested(node)

    def visit_If(self, node: ast.If) -> None:
        if _is_type_checking(node.test):
            self._type_checking += 1
            for child in node.body:
                self.visit(child)
            self._type_checking -= 1
            for child in node.orelse:
                self.visit(child)
        else:
            self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(alias.name, node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            base = self.package.split(".")
            base = base[: len(base) - (node.level - 1)]
            prefix = ".".join(base + ([node.module] if node.module else []))
        else:
            prefix = node.module or ""
        for alias in node.names:
            candidate = f"{prefix}.{alias.name}"
            self._add(candidate if candidate in MODULES else prefix, node)


def _imports() -> list[Import]:
    found: list[Import] = []
    for module, path in MODULES.items():
        collector = _Collector(module, path.name == "__init__.py")
        collector.visit(ast.parse(path.read_text(), filename=str(path)))
        found.extend(collector.found)
    return found


IMPORTS = _imports()


def _within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def _describe(found: Iterable[Import]) -> list[str]:
    return [f"{i.source}:{i.line} imports {i.target}" for i in found]


def _core_violations(imports: Iterable[Import]) -> list[str]:
    """Imports by core modules of MuJoCo, CasADi or a non-core c3bench module (run-time
    imports), or of MuJoCo or CasADi (type-only imports)."""
    wrong: list[Import] = []
    for i in imports:
        if i.source not in CORE_MODULES:
            continue
        plant = any(_within(i.target, p) for p in PLANT_PACKAGES)
        outside = _within(i.target, "c3bench") and i.target not in CORE_MODULES
        if plant or (outside and not i.type_only):
            wrong.append(i)
    return _describe(wrong)


def test_core_list_names_existing_modules() -> None:
    assert set(CORE_MODULES) <= set(MODULES)
    assert all(_within(name, "c3bench.problems") for name in CORE_MODULES)


def test_core_imports_only_the_core() -> None:
    assert not _core_violations(IMPORTS)


@pytest.mark.parametrize(("package", "forbidden"), [
    ("c3bench.problems", ("c3bench.solvers", "c3bench.bench")),
    ("c3bench.solvers", ("c3bench.bench",)),
])
def test_layers_point_one_way(package: str, forbidden: tuple[str, ...]) -> None:
    wrong = (i for i in IMPORTS if _within(i.source, package)
             and any(_within(i.target, f) for f in forbidden))
    assert not _describe(wrong)


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` (its nodes, the first repeated at the end), or ``None``."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_module_level_imports_have_no_cycle() -> None:
    graph: dict[str, set[str]] = {name: set() for name in MODULES}
    for i in IMPORTS:
        if i.top_level and not i.type_only and i.target in MODULES and i.target != i.source:
            graph[i.source].add(i.target)
    cycle = _find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


@pytest.mark.parametrize("source", [
    "import mujoco\n",
    "import numpy\n\ndef f() -> None:\n    import casadi\n",
    "from c3bench.problems.scene import Scene\n",
    "from c3bench.problems import suites\n",
    "from . import linearize\n",
    "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import mujoco\n",
])
def test_the_core_check_sees_a_plant_import(source: str) -> None:
    """The source check catches MuJoCo, CasADi or a plant-side module in a core module."""
    collector = _Collector("c3bench.problems.instance", False)
    collector.visit(ast.parse(source))
    assert _core_violations(collector.found)


# --- the one LCS validator ------------------------------------------------------------------------
def test_lcs_and_batch_share_the_validator() -> None:
    from c3bench.problems.lcs import LCS, LCSBatch

    nx, nu, nlam = 3, 1, 2
    arrays = {"A": np.eye(nx), "B": np.ones((nx, nu)), "D": np.ones((nx, nlam)),
              "d": np.zeros(nx), "E": np.ones((nlam, nx)), "F": np.eye(nlam),
              "H": np.ones((nlam, nu)), "c": np.zeros(nlam)}
    lcs = LCS(**arrays, dt=0.1)
    batch = LCSBatch.from_lcs([lcs, lcs])
    assert batch.sample(1).F.tolist() == lcs.F.tolist()
    bad = dict(arrays, H=np.ones((nlam, nu + 1)))
    with pytest.raises(ValueError, match=r"LCS\.H must have shape \(2, 1\)"):
        LCS(**bad, dt=0.1)
    with pytest.raises(ValueError, match=r"LCSBatch\.H must have shape \(1, 2, 1\)"):
        LCSBatch(**{k: v[None] for k, v in bad.items()}, dt=0.1)
    with pytest.raises(ValueError, match=r"LCS\.dt"):
        LCS(**arrays, dt=0.0)
    with pytest.raises(ValueError, match=r"LCSBatch\.dt"):
        LCSBatch(**{k: v[None] for k, v in arrays.items()}, dt=float("nan"))
    with pytest.raises(ValueError, match=r"LCS\.c has non-finite"):
        LCS(**dict(arrays, c=np.array([0.0, np.inf])), dt=0.1)
