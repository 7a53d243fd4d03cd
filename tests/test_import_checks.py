"""``problems import`` refuses what is not the QP it seems to be (exit 2, one line naming the
file and the key, or the module and the test set), and runs no user code it was not asked to.

* A key stored as a pickled object (``qpsolvers.Problem.save`` of a ``scipy.sparse`` ``P``,
  ``G`` or ``A``) is refused, not read as "absent" (which turned a QP into an LP); the pickle
  is never loaded. A key stored as ``None`` still means "absent".
* A misspelled key of a CasADi conic file (``ubX``) is refused, as in qpsolvers' files.
* A lower bound ``+inf`` or an upper bound ``-inf`` (infeasible, but read as "no bound") is
  refused, in both forms.
* ``--module``: a test set that warns imports; one that raises is a one-line error naming it;
  helper functions and ``main()`` are neither called nor refused.
* The file path an import read is not part of the instance's identity.
* A QP without variables and complex data are refused.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import qpsolvers
import scipy.sparse as sp

from c3bench.bench.cli import main
from c3bench.problems.conic import conic_arrays
from c3bench.problems.errors import InputError
from c3bench.problems.identity import identify
from c3bench.problems.importers import find_test_sets, read_module, read_npz
from c3bench.problems.instance import MANIFEST, load_instances

INF = np.inf


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], path: Path,
             *words: str) -> str:
    """Import ``path``: exit 2, one line naming the file and every word; nothing written."""
    out = tmp_path / "out"
    code, _, err = _cli(capsys, "problems", "import", str(path), "--out", str(out))
    assert code == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert str(path) in err, err
    for word in words:
        assert word in err, (word, err)
    assert not out.exists()
    return err


# --- 1. keys stored as pickled objects ------------------------------------------------------

@pytest.mark.parametrize("key", ["P", "G", "A"])
@pytest.mark.parametrize("sparse", [sp.csr_matrix, sp.csc_array])
def test_sparse_key_saved_by_qpsolvers_is_refused(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str],
                                                  key: str, sparse: Any) -> None:
    blocks: dict[str, Any] = {"P": np.diag([4.0, 2.0]), "G": np.array([[1.0, 1.0]]),
                              "A": np.array([[1.0, -1.0]])}
    blocks[key] = sparse(blocks[key])
    path = tmp_path / "sparse.npz"
    qpsolvers.Problem(blocks["P"], np.ones(2), blocks["G"], np.array([1.0]), blocks["A"],
                      np.array([0.0]), lb=np.zeros(2), ub=np.ones(2)).save(str(path))
    _refused(tmp_path, capsys, path, f"key {key!r}", "pickled", "toarray", "save_conic")


def test_absent_blocks_saved_as_none_still_import(tmp_path: Path) -> None:
    path = tmp_path / "lp_free.npz"
    qpsolvers.Problem(np.diag([4.0, 2.0]), np.ones(2), lb=np.zeros(2)).save(str(path))
    problem = read_npz(path)
    assert problem.G is None and problem.A is None and problem.ub is None
    np.testing.assert_array_equal(problem.P, np.diag([4.0, 2.0]))


def test_pickled_objects_are_never_loaded(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A pickle that would run code when loaded (here: create a file) is refused unread; a
    pickled number is no more "absent" than a matrix."""
    marker = tmp_path / "unpickled"
    trap = np.empty((), dtype=object)
    trap[()] = _Trap(str(marker))
    path = tmp_path / "trap.npz"
    np.savez(path, P=np.eye(2), q=np.ones(2), lb=trap)
    _refused(tmp_path, capsys, path, "key 'lb'", "pickled")
    assert not marker.exists()
    np.savez(path, P=np.array(5.0, dtype=object), q=np.ones(2))
    _refused(tmp_path, capsys, path, "key 'P'", "pickled")


class _Trap:
    """Unpickling it creates ``path``."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return (_touch, (self.path, "x"))


def _touch(path: str, _: str) -> None:
    Path(path).write_text("unpickled\n")


# --- 2. unknown keys of a conic file ---------------------------------------------------------

def test_misspelled_conic_key_is_refused(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "typo.npz"
    np.savez(path, h=np.eye(2), g=-10.0 * np.ones(2), lbx=np.zeros(2), ubX=np.ones(2))
    _refused(tmp_path, capsys, path, "ubX", "CasADi conic")


# --- 3. infeasible infinite bounds ------------------------------------------------------------

@pytest.mark.parametrize(("arrays", "words"), [
    ({"P": np.eye(2), "q": np.ones(2), "lb": np.array([0.0, INF])}, ("lb[1]", "+inf")),
    ({"P": np.eye(2), "q": np.ones(2), "ub": np.array([-INF, 0.0])}, ("ub[0]", "-inf")),
    ({"h": np.eye(2), "g": np.ones(2), "a": np.eye(2), "lba": np.array([0.0, INF]),
      "uba": np.array([1.0, INF])}, ("lba[1]", "+inf")),
    ({"h": np.eye(2), "g": np.ones(2), "a": np.eye(2), "lba": np.array([-INF, 0.0]),
      "uba": np.array([-INF, 1.0])}, ("uba[0]", "-inf")),
    ({"h": np.eye(2), "g": np.ones(2), "lbx": np.array([INF, 0.0])}, ("lbx[0]", "+inf")),
    ({"h": np.eye(2), "g": np.ones(2), "ubx": np.array([1.0, -INF])}, ("ubx[1]", "-inf")),
])
def test_infeasible_infinite_bound_is_refused(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str],
                                              arrays: dict[str, np.ndarray],
                                              words: tuple[str, ...]) -> None:
    path = tmp_path / "inf_bound.npz"
    np.savez(path, **arrays)
    _refused(tmp_path, capsys, path, *words)


def test_save_conic_refuses_an_infeasible_side() -> None:
    with pytest.raises(InputError, match=r"lba\[0\] = \+inf"):
        conic_arrays(H=np.eye(1), g=np.ones(1), A=np.ones((1, 1)), lba=[INF], uba=[INF])


# --- 6. and 7. no variable, complex data ------------------------------------------------------

@pytest.mark.parametrize(("arrays", "words"), [
    ({"P": np.zeros((0, 0)), "q": np.zeros(0)}, ("q is empty",)),
    ({"h": np.zeros((0, 0)), "g": np.zeros(0)}, ("g is empty",)),
    ({"P": np.array([[1.0, 1j], [-1j, 1.0]]), "q": np.ones(2)}, ("key 'P'", "complex")),
    ({"P": np.eye(2), "q": np.ones(2) + 0j}, ("key 'q'", "complex")),
    ({"h": np.eye(2) * (1 + 1j), "g": np.ones(2)}, ("key 'h'", "complex")),
    ({"F": np.eye(2) + 0j, "q": np.ones(2)}, ("key 'F'", "complex")),
    ({"P": np.eye(2), "q": np.array(["1", "2"])}, ("key 'q'", "not real numbers")),
])
def test_empty_or_complex_problem_is_refused(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str],
                                             arrays: dict[str, np.ndarray],
                                             words: tuple[str, ...]) -> None:
    path = tmp_path / "odd.npz"
    np.savez(path, **arrays)
    _refused(tmp_path, capsys, path, *words)


def test_save_conic_refuses_complex_values() -> None:
    with pytest.raises(InputError, match="H is complex"):
        conic_arrays(H=np.eye(2) * 1j, g=np.ones(2))


# --- 4. --module ---------------------------------------------------------------------------

def _module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, text: str) -> str:
    (tmp_path / f"{name}.py").write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def test_module_whose_test_set_warns_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A warning adds ``__warningregistry__`` to the module while its test set runs."""
    name = _module(tmp_path, monkeypatch, "byo_warns",
                   "import warnings\nimport numpy as np\nfrom qpsolvers import Problem\n\n"
                   "class WarnSet:\n"
                   "    def __iter__(self):\n"
                   "        warnings.warn('loading data the old way')\n"
                   "        yield 'warned', Problem(np.eye(2), np.ones(2))\n")
    out = tmp_path / "instances"
    code, _, err = _cli(capsys, "problems", "import", "--module", name, "--out", str(out))
    assert code == 0, err
    assert [p.name for p in load_instances(out)] == ["warned"]
    # the user's warning is one line on stderr, naming the module and where it was raised
    assert err.splitlines() == [f"warning: --module {name}: UserWarning: loading data the old "
                                f"way ({name}.py:7)"]


@pytest.mark.parametrize(("text", "words"), [
    ("def items():\n    raise RuntimeError('boom in generator')\n    yield 1\n",
     ("items: raised RuntimeError: boom in generator", "item 0")),
    ("class Set:\n    def __init__(self):\n        raise ValueError('needs\\ndata file')\n"
     "    def __iter__(self):\n        return iter(())\n",
     ("Set: raised ValueError: needs data file",)),
    ("import numpy as np\nfrom qpsolvers import Problem\n"
     "def items():\n    yield Problem(np.eye(2), np.ones(2))\n    raise KeyError('second')\n",
     ("items: raised KeyError", "item 1")),
    ("class Odd:\n    @property\n    def P(self):\n        raise OSError('gone')\n    q = 1.0\n"
     "def items():\n    yield Odd()\n", ("items item 0: reading it raised OSError: gone",)),
    ("import numpy as np\nfrom qpsolvers import Problem\n"
     "def items():\n    yield Problem(np.eye(2) * 1j, np.ones(2))\n",
     ("items item 0", "key 'P' is complex")),
])
def test_module_test_set_that_raises_is_one_line(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch,
                                                 text: str, words: tuple[str, ...]) -> None:
    """Through the installed CLI: exit 2 and one line naming the module and the test set,
    no traceback."""
    (tmp_path / "byo_raises.py").write_text(text)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    done = subprocess.run([sys.executable, "-m", "c3bench.bench.cli", "problems", "import",
                           "--module", "byo_raises", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, env=env, timeout=120, check=False)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: --module byo_raises: "), done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
    for word in words:
        assert word in done.stderr, (word, done.stderr)


def test_module_helpers_are_neither_called_nor_refused(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    marker = tmp_path / "main_was_called"
    name = _module(tmp_path, monkeypatch, "byo_mixed",
                   "import numpy as np\nfrom qpsolvers import Problem, Problem as Imported\n\n"
                   "def default_sizes():\n    return [2, 3]\n\n"
                   "def main():\n"
                   f"    open({str(marker)!r}, 'w').write('side effect')\n\n"
                   "def scaled(k):\n    yield Problem(np.eye(2) * k, np.ones(2))\n\n"
                   "class Config:\n    sizes = [2, 3]\n\n"
                   "class MySet:\n"
                   "    def __iter__(self):\n"
                   "        yield Problem(np.eye(2), np.ones(2))\n\n"
                   "def more():\n"
                   "    yield 'more', Problem(np.eye(3), np.ones(3))\n\n"
                   "def _private():\n    yield 42\n")
    module = __import__(name)
    assert [label for label, _ in find_test_sets(module)] == ["MySet", "more"]
    problems = read_module(name)
    assert [p.name for p in problems] == ["MySet_000", "more"]
    assert not marker.exists()
    assert problems[1].meta["source"] == f"--module {name}: more item 0 (more)"


def test_module_without_test_set_is_refused(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    name = _module(tmp_path, monkeypatch, "byo_plain",
                   "def problems():\n    return []\n")
    with pytest.raises(InputError, match=r"defines no test set.*plain functions are not called"):
        read_module(name)


# --- 5. identity without the import path ------------------------------------------------------

def test_same_files_from_two_folders_have_the_same_identity(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    for folder in ("a", "b/deeper"):
        (tmp_path / folder).mkdir(parents=True)
        for index in range(2):
            np.savez(tmp_path / folder / f"p{index}.npz", P=np.eye(2), q=np.ones(2) * index,
                     lb=np.zeros(2))
    identities = []
    for folder, out in (("a", "one/instances"), ("b/deeper", "two/instances")):
        target = tmp_path / out
        code, _, err = _cli(capsys, "problems", "import", str(tmp_path / folder), "--out",
                            str(target))
        assert code == 0, err
        manifest = json.loads((target / MANIFEST).read_text())
        paths = sorted((target / "qp").glob("*.json"))
        assert [json.loads(p.read_text())["meta"]["source"] for p in paths] == [
            str(tmp_path / folder / f"p{i}.npz") for i in range(2)]  # the path is kept ...
        identities.append([identify(path, None, manifest) for path in paths])
    assert identities[0] == identities[1]  # ... but is not the instance
    assert identities[0][0] != identities[0][1]
