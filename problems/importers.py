"""Bring your own problem: convex QPs in qpsolvers' form become ``qp`` instances.

Two sources (``c3bench problems import``):

* ``.npz`` files, one file or a directory of them (searched recursively), each recognised by
  its keys:

  - qpsolvers' ``Problem.save`` keys (``P q G h A b lb ub``; only ``P`` and ``q`` are
    required, a missing key or one stored as ``None`` means the block is absent; ``None`` is
    recognised without unpickling it): a ``qp`` instance;
  - CasADi ``conic`` names (``h g a lba uba lbx ubx``, written by
    :func:`c3bench.problems.conic.save_conic`; a lower-case ``g`` and no ``q``): converted
    by :func:`c3bench.problems.conic.conic_to_qpsolvers` into a ``qp`` instance;
  - ``F`` and ``q``: the LCP ``0 <= lam perp F lam + q >= 0`` with any square ``F``, an
    ``lcp_general`` instance (:func:`c3bench.problems.families.lcp_general`);
* a Python module (``--module``) defining qpbenchmark-style test sets, yielding
  ``qpsolvers.Problem`` objects (or ``(name, problem)`` pairs; a problem's ``name``
  attribute is used when it has one). A test set is a public object defined in the module
  (not imported into it) that is either

  - a *generator function* (its body has a ``yield``) callable without arguments, or
  - a *class* with ``__iter__`` (its own or inherited, e.g. from qpbenchmark's ``TestSet``)
    constructible without arguments: it is instantiated and iterated.

  Nothing else is called or refused: plain functions (a ``main()``, a helper returning a
  list), classes without ``__iter__``, and callables that need arguments are skipped (give
  helpers a leading ``_`` to be explicit). An exception raised by a test set (constructing,
  calling or iterating it, or reading a yielded problem's attributes) is an
  :class:`~c3bench.problems.errors.InputError` naming the module and the test set.

Each QP is checked (real numbers, at least one variable, finite matrices and right-hand
sides, no lower bound ``+inf`` and no upper bound ``-inf`` (infeasible), shapes that fit,
``P`` symmetric after ``P <- (P + P^T) / 2``, which leaves the objective unchanged, and
positive semi-definite) and becomes a :class:`~c3bench.problems.instance.Problem` of the
``qp`` family with metadata ``{"source": ..., "imported": True}`` (``source``, a local path,
is not part of the instance's identity: :mod:`c3bench.problems.identity`). A file that is not
such a problem raises :class:`~c3bench.problems.errors.InputError` naming the file and the
key (or the module and the item): among others a key of the file stored as a pickled Python
object (what ``numpy.savez`` makes of a ``scipy.sparse`` matrix; pickles are never loaded),
complex values, and, in a conic file, a key that is not a CasADi name.

Part of the plant-free core's dependencies: numpy only (neither qpsolvers nor CasADi is
imported here; a module's objects are read by their attributes).
"""

from __future__ import annotations

import importlib
import inspect
import json
import pickletools
import re
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.conic import (
    CONIC_KEYS,
    conic_to_qpsolvers,
    infeasible_side,
    is_conic,
)
from c3bench.problems.errors import InputError
from c3bench.problems.families import lcp_general
from c3bench.problems.instance import MANIFEST, Problem, atomic_write_bytes, save_problem
from c3bench.problems.instance_contract import check_real
from c3bench.problems.names import Family

QPSOLVERS_KEYS: tuple[str, ...] = ("P", "q", "G", "h", "A", "b", "lb", "ub")
"""The keys of ``qpsolvers.Problem.save`` / ``Problem.load``."""
LCP_KEYS: tuple[str, ...] = ("F", "q")
"""The keys of an ``.npz`` holding an LCP ``0 <= lam perp F lam + q >= 0``."""
PSD_TOLERANCE = 1e-9
"""Smallest eigenvalue of ``P`` allowed, relative to its largest magnitude (convexity)."""
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+]+")


def instance_name(stem: str) -> str:
    """A file-safe instance name (letters, digits, ``_ . +``; runs of others become ``_``)."""
    name = _UNSAFE.sub("_", stem).strip("_.")
    return name or "problem"


PICKLED_HELP = ("save it as a dense array (e.g. P.toarray() for a scipy.sparse matrix), "
                "write the file with c3bench.problems.conic.save_conic (which densifies "
                "scipy.sparse and casadi.DM values), or import the qpsolvers.Problem from a "
                "--module test set")
"""How to store a key that was saved as a pickled object (pickles are never loaded)."""
_MEMO_OPCODES = frozenset({"MEMOIZE", "PUT", "BINPUT", "LONG_BINPUT", "FRAME"})


class _Pickled:
    """A key stored as a pickled Python object other than ``None`` (not loaded)."""


def _real(key: str, value: Any) -> np.ndarray | None:
    """``value`` as an array of real numbers, ``None`` when it is ``None`` (or a 0-d object
    array holding ``None``); ``ValueError`` naming ``key`` for complex or non-numeric data.
    A ``scipy.sparse`` matrix (from a module's Problem) is densified."""
    if value is None:
        return None
    if hasattr(value, "toarray"):  # a scipy sparse matrix from a module's Problem
        value = value.toarray()
    array = np.asarray(value)
    if array.dtype == object and array.ndim == 0 and array.item() is None:
        return None
    check_real(key, array)
    return array


def _pickled_none(stream: Any) -> bool:
    """Whether a ``.npy`` member (a stream at its start) is the 0-d object array holding
    ``None`` that ``numpy.savez`` writes for ``key=None`` (qpsolvers' absent blocks).

    Decided from the header and the pickle's opcodes (:mod:`pickletools`), which executes
    nothing: the array's object list must be exactly ``[None]``."""
    version = np.lib.format.read_magic(stream)
    shape, _, _ = (np.lib.format.read_array_header_1_0(stream) if version == (1, 0)
                   else np.lib.format.read_array_header_2_0(stream))
    if shape != ():
        return False
    names = [op.name for op, _, _ in pickletools.genops(stream.read())
             if op.name not in _MEMO_OPCODES]
    if "EMPTY_LIST" not in names:
        return False
    last = len(names) - 1 - names[::-1].index("EMPTY_LIST")
    return names[last + 1:] == ["NONE", "APPEND", "TUPLE", "BUILD", "STOP"]


def _stored(stored: Any, key: str) -> np.ndarray | _Pickled | None:
    """``stored[key]`` of an open ``.npz`` read with ``allow_pickle=False``: the array,
    ``None`` for a pickled ``None``, :class:`_Pickled` for any other pickled object."""
    member = f"{key}.npy" if f"{key}.npy" in stored.zip.namelist() else key
    with stored.zip.open(member) as stream:
        version = np.lib.format.read_magic(stream)
        header = (np.lib.format.read_array_header_1_0(stream) if version == (1, 0)
                  else np.lib.format.read_array_header_2_0(stream))
    if not header[2].hasobject:
        return np.asarray(stored[key])
    with stored.zip.open(member) as stream:
        return None if _pickled_none(stream) else _Pickled()


def qp_problem(name: str, arrays: dict[str, np.ndarray | None], source: str) -> Problem:
    """The ``qp`` instance of qpsolvers' arrays; :class:`InputError` naming ``source``.

    One-row ``A`` / ``G`` given as vectors and scalar ``b`` / ``h`` are accepted (qpsolvers
    accepts them too).
    """
    try:
        q = arrays.get("q")
        if q is None:
            raise ValueError("missing key 'q'")
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        n = q.shape[0]
        if n == 0:
            raise ValueError("q is empty: a QP needs at least one variable")
        P = arrays.get("P")
        P = np.zeros((n, n)) if P is None else np.asarray(P, dtype=np.float64)
        if P.shape != (n, n):
            raise ValueError(f"P must have shape ({n}, {n}) to match q, got {P.shape}")
        P = 0.5 * (P + P.T)
        blocks: dict[str, np.ndarray | None] = {}
        for matrix, vector in (("A", "b"), ("G", "h")):
            M, v = arrays.get(matrix), arrays.get(vector)
            if M is not None and np.asarray(M).ndim == 1:
                M = np.asarray(M).reshape(1, -1)
            blocks[matrix] = M
            blocks[vector] = None if v is None else np.asarray(v, dtype=np.float64).reshape(-1)
        _check_convex(P)
        _check_bounds(arrays)
        problem = Problem(name=name, family=Family.QP, P=P, q=q,
                          A=blocks["A"], b=blocks["b"], G=blocks["G"], h=blocks["h"],
                          lb=arrays.get("lb"), ub=arrays.get("ub"),
                          meta={"source": source, "imported": True})
    except (TypeError, ValueError) as error:
        raise InputError(f"{source}: not a convex QP in qpsolvers' form ({error})") from error
    return problem


def _check_convex(P: np.ndarray) -> None:
    """``ValueError`` when symmetric ``P`` is not positive semi-definite (the ``qp`` family is
    convex)."""
    if not np.all(np.isfinite(P)) or P.size == 0:
        return  # Problem.validate names non-finite entries; an empty P is convex
    scale = max(1.0, float(np.max(np.abs(P))))
    smallest = float(np.linalg.eigvalsh(P)[0])
    if smallest < -PSD_TOLERANCE * scale:
        raise ValueError(f"P is not positive semi-definite (smallest eigenvalue "
                         f"{smallest:.3g}): the qp family is convex")


def _check_bounds(arrays: dict[str, np.ndarray | None]) -> None:
    """``ValueError`` naming the key and index of a lower bound ``+inf`` or an upper bound
    ``-inf`` (an infeasible constraint, which no solver would see: both are read as "no
    bound")."""
    for key, lower, relation in (("lb", True, ">="), ("ub", False, "<=")):
        bound = arrays.get(key)
        index = None if bound is None else infeasible_side(bound, lower)
        if index is not None:
            wrong = np.inf if lower else -np.inf
            raise ValueError(f"{key}[{index}] = {wrong:+}: x[{index}] {relation} {wrong:+} is "
                             "infeasible")


def read_npz(path: Path) -> Problem:
    """One ``.npz`` as an instance named after the file, its form told by its keys (a qpsolvers
    problem, a saved CasADi conic problem or an LCP: see the module docstring)."""
    try:
        with np.load(path, allow_pickle=False) as stored:
            raw = {key: _stored(stored, key) for key in stored.files}
    except Exception as error:  # any failure to decode is a bad file
        raise InputError(f"{path}: unreadable, truncated or not an .npz "
                         f"({type(error).__name__}: {error})") from error
    pickled = sorted(key for key, value in raw.items() if isinstance(value, _Pickled))
    if pickled:
        raise InputError(f"{path}: key {pickled[0]!r} is stored as a pickled Python object "
                         f"(numpy.savez pickles e.g. a scipy.sparse matrix), which is never "
                         f"loaded: {PICKLED_HELP}")
    arrays: dict[str, np.ndarray | None] = {}
    try:
        for key, value in raw.items():
            if not isinstance(value, _Pickled):  # none is left (refused above)
                arrays[key] = _real(key, value)
    except ValueError as error:
        raise InputError(f"{path}: {error}") from error
    name, keys = instance_name(path.stem), set(arrays)
    if "F" in keys:
        return _read_lcp(name, arrays, path)
    if is_conic(keys):
        unknown = sorted(keys - set(CONIC_KEYS))
        if unknown:
            raise InputError(f"{path}: keys {', '.join(unknown)} are not CasADi conic names "
                             f"({' '.join(CONIC_KEYS)}; a file with g and no q is read as "
                             f"a conic problem)")
        given = {key: value for key, value in arrays.items() if value is not None}
        try:
            qp_arrays = conic_to_qpsolvers(given)
        except InputError as error:
            raise InputError(f"{path}: not a CasADi conic QP ({error})") from error
        return qp_problem(name, qp_arrays, str(path))
    unknown = sorted(keys - set(QPSOLVERS_KEYS))
    if unknown:
        raise InputError(f"{path}: keys {', '.join(unknown)} are not qpsolvers' Problem keys "
                         f"({' '.join(QPSOLVERS_KEYS)}), CasADi conic's (h g a lba uba lbx "
                         f"ubx) or an LCP's (F q)")
    if arrays.get("q") is None:
        raise InputError(f"{path}: missing key 'q' (qpsolvers' Problem keys: "
                         f"{' '.join(QPSOLVERS_KEYS)})")
    return qp_problem(name, {key: arrays.get(key) for key in QPSOLVERS_KEYS}, str(path))


def _read_lcp(name: str, arrays: dict[str, np.ndarray | None], path: Path) -> Problem:
    """The ``lcp_general`` instance of an ``.npz`` holding exactly ``F`` and ``q``."""
    F, q = arrays.get("F"), arrays.get("q")
    if set(arrays) != set(LCP_KEYS) or F is None or q is None:
        raise InputError(f"{path}: an LCP file holds exactly the keys F and q, got "
                         f"{' '.join(sorted(arrays))}")
    try:
        return lcp_general(name, np.asarray(F, dtype=np.float64),
                           np.asarray(q, dtype=np.float64).reshape(-1),
                           meta={"source": str(path), "imported": True})
    except (TypeError, ValueError) as error:  # InputError is a ValueError
        raise InputError(f"{path}: not an LCP 0 <= lam perp F lam + q >= 0 ({error})") \
            from error


def npz_files(source: Path) -> list[Path]:
    """The ``.npz`` files of ``source`` (itself, or those below it, sorted);
    :class:`InputError` when there is none."""
    if source.is_file():
        return [source]
    if not source.is_dir():
        raise InputError(f"SRC: {source} is neither a file nor a directory")
    found = sorted(p for p in source.rglob("*.npz") if not p.name.startswith("."))
    if not found:
        raise InputError(f"SRC: no .npz file under {source}")
    return found


def read_npz_source(source: Path) -> list[Problem]:
    """Every ``.npz`` of ``source`` as a ``qp`` instance (:func:`read_npz`)."""
    return [read_npz(path) for path in npz_files(source)]


def _takes_no_arguments(value: Any) -> bool:
    """Whether ``value`` can be called without arguments (``False`` when its signature
    cannot be read)."""
    try:
        parameters = inspect.signature(value).parameters.values()
    except (TypeError, ValueError):
        return False
    return all(p.default is not p.empty or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
               for p in parameters)


def find_test_sets(module: Any) -> list[tuple[str, Any]]:
    """``(name, object)`` of the test sets of ``module`` (module docstring): its public
    generator functions and classes with ``__iter__``, defined in it, that take no arguments.
    Nothing is called here; every other object is skipped.

    ``vars(module)`` is copied first: running a test set may add entries to it (a warning
    adds ``__warningregistry__``)."""
    found: list[tuple[str, Any]] = []
    for attribute, value in list(vars(module).items()):
        if attribute.startswith("_"):
            continue
        if inspect.isclass(value):
            iterable = any("__iter__" in vars(klass) for klass in value.__mro__
                           if klass is not object)
        elif inspect.isfunction(value):
            iterable = inspect.isgeneratorfunction(value)
        else:
            continue
        if (iterable and getattr(value, "__module__", None) == module.__name__
                and _takes_no_arguments(value)):
            found.append((attribute, value))
    return found


def _one_line(error: BaseException) -> str:
    """``Type: message`` of an exception on one line."""
    return " ".join(f"{type(error).__name__}: {error}".split())


def _item_arrays(label: str, item: Any, index: int) -> tuple[str, dict[str, np.ndarray | None]]:
    """``(name, qpsolvers arrays)`` of one yielded item: a problem or a ``(name, problem)``
    pair (``ValueError`` for what is not a qpsolvers.Problem or holds non-real data)."""
    if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str):
        item_name, obj = item
    else:
        item_name, obj = str(getattr(item, "name", "") or f"{label}_{index:03d}"), item
    if not hasattr(obj, "P") or not hasattr(obj, "q"):
        raise ValueError(f"({item_name}): not a qpsolvers.Problem (no P and q)")
    try:
        arrays = {key: _real(key, getattr(obj, key, None)) for key in QPSOLVERS_KEYS}
    except ValueError as error:
        raise ValueError(f"({item_name}): {error}") from error
    return item_name, arrays


def read_module(name: str) -> list[Problem]:
    """The problems a module's test sets yield (:func:`find_test_sets`, module docstring).

    :class:`InputError` when the module cannot be imported, has no test set, a test set
    raises, yields nothing, or yields an object that is not a convex QP in qpsolvers' form.
    """
    try:
        module = importlib.import_module(name)
    except (Exception, SystemExit) as error:  # a user module may raise or exit
        raise InputError(f"--module {name}: cannot import it ({_one_line(error)})") from error
    sets = find_test_sets(module)
    if not sets:
        raise InputError(f"--module {name}: defines no test set (a public generator function "
                         "or class with __iter__, defined in the module and callable without "
                         "arguments, yielding qpsolvers.Problem objects; plain functions are "
                         "not called)")
    problems: list[Problem] = []
    for label, test_set in sets:
        where = f"--module {name}: {label}"
        try:
            iterator = iter(test_set())
        except (Exception, SystemExit) as error:  # user code (sys.exit too)
            raise InputError(f"{where}: raised {_one_line(error)}") from error
        index = 0
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                break
            except (Exception, SystemExit) as error:  # user code (sys.exit too)
                raise InputError(f"{where}: raised {_one_line(error)} while yielding item "
                                 f"{index}") from error
            try:
                item_name, arrays = _item_arrays(label, item, index)
            except ValueError as error:
                raise InputError(f"{where} item {index} {error}") from error
            except (Exception, SystemExit) as error:  # a user property
                raise InputError(f"{where} item {index}: reading it raised "
                                 f"{_one_line(error)}") from error
            source = f"{where} item {index} ({item_name})"
            problems.append(qp_problem(instance_name(item_name), arrays, source))
            index += 1
    if not problems:
        raise InputError(f"--module {name}: its test sets ({', '.join(l for l, _ in sets)}) "
                         "yield no problem")
    return problems


def write_imported(problems: list[Problem], out: Path, source: str,
                   name: str | None = None) -> list[Path]:
    """Save ``problems`` under ``out/<family>/`` with a manifest (suite ``name``, default
    ``out``'s name); names must be unique (:class:`InputError` naming both sources
    otherwise). Returns the JSON paths."""
    seen: dict[str, str] = {}
    for problem in problems:
        origin = str(problem.meta.get("source", ""))
        if problem.name in seen:
            raise InputError(f"{origin}: instance name {problem.name!r} also given by "
                             f"{seen[problem.name]}; rename one")
        seen[problem.name] = origin
    written = [save_problem(problem, out / problem.family) for problem in problems]
    write_manifest(out, problems, {"name": name or out.name, "imported_from": source})
    return written


def write_manifest(out: Path, problems: list[Problem], suite: dict[str, Any]) -> Path:
    """``out/manifest.json`` for a directory of ``problems`` that no generator wrote: the
    suite table given, the counts per family, and the instance names."""
    counts: dict[str, int] = {}
    for problem in problems:
        counts[problem.family] = counts.get(problem.family, 0) + 1
    manifest = {"suite": suite, "counts": dict(sorted(counts.items())),
                "instances": sorted(problem.name for problem in problems)}
    path = out / MANIFEST
    atomic_write_bytes(path, (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode())
    return path
