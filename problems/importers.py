"""Bring your own problem: convex QPs in qpsolvers' form become ``qp`` instances.

Two sources (``c3bench problems import``):

* ``.npz`` files, one file or a directory of them (searched recursively), each recognised by
  its keys:

  - qpsolvers' ``Problem.save`` keys (``P q G h A b lb ub``; only ``P`` and ``q`` are
    required, a missing key or one stored as ``None`` means the block is absent): a ``qp``
    instance;
  - CasADi ``conic`` names (``h g a lba uba lbx ubx``, written by
    :func:`c3bench.problems.conic.save_conic`; a lower-case ``g`` and no ``q``): converted
    by :func:`c3bench.problems.conic.conic_to_qpsolvers` into a ``qp`` instance;
  - ``F`` and ``q``: the LCP ``0 <= lam perp F lam + q >= 0`` with any square ``F``, an
    ``lcp_general`` instance (:func:`c3bench.problems.families.lcp_general`);
* a Python module (``--module``) defining a qpbenchmark-style test set: a function, or a
  class whose instances are iterable, yielding ``qpsolvers.Problem`` objects (or
  ``(name, problem)`` pairs; a problem's ``name`` attribute is used when it has one).

Each QP is checked (finite, shapes that fit, ``P`` symmetric after
``P <- (P + P^T) / 2``, which leaves the objective unchanged, and positive semi-definite) and
becomes a :class:`~c3bench.problems.instance.Problem` of the ``qp`` family with metadata
``{"source": ..., "imported": True}``. A file that is not such a problem raises
:class:`~c3bench.problems.errors.InputError` naming the file (or the module and the item).

Part of the plant-free core's dependencies: numpy only (neither qpsolvers nor CasADi is
imported here; a module's objects are read by their attributes).
"""

from __future__ import annotations

import importlib
import inspect
import json
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.conic import conic_to_qpsolvers, is_conic
from c3bench.problems.errors import InputError
from c3bench.problems.families import lcp_general
from c3bench.problems.instance import MANIFEST, Problem, atomic_write_bytes, save_problem
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


def _optional(stored: Any, key: str) -> np.ndarray | None:
    """``stored[key]`` as an array, ``None`` when absent or saved as ``None`` (an object
    array, which ``allow_pickle=False`` refuses: qpsolvers' own reading of it)."""
    try:
        value = stored[key]
    except (KeyError, ValueError):
        return None
    if value is None:
        return None
    if hasattr(value, "toarray"):  # a scipy sparse matrix from a module's Problem
        value = value.toarray()
    array = np.asarray(value)
    if array.dtype == object and array.ndim == 0 and array.item() is None:
        return None
    return array


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


def read_npz(path: Path) -> Problem:
    """One ``.npz`` as an instance named after the file, its form told by its keys (a qpsolvers
    problem, a saved CasADi conic problem or an LCP: see the module docstring)."""
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {key: _optional(stored, key) for key in stored.files}
    except Exception as error:  # any failure to decode is a bad file
        raise InputError(f"{path}: unreadable, truncated or not an .npz "
                         f"({type(error).__name__}: {error})") from error
    name, keys = instance_name(path.stem), set(arrays)
    if "F" in keys:
        return _read_lcp(name, arrays, path)
    if is_conic(keys):
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


def _items(module: Any) -> Iterator[tuple[str, Any]]:
    """``(owner name, produced object)`` of every test-set function or class of ``module``
    (those defined in it, not imported)."""
    for attribute, value in vars(module).items():
        if attribute.startswith("_") or getattr(value, "__module__", None) != module.__name__:
            continue
        if inspect.isclass(value):
            try:
                instance = value()
            except TypeError:
                continue  # needs arguments: not a test set
            if isinstance(instance, Iterable):
                yield attribute, instance
        elif inspect.isfunction(value) and not inspect.signature(value).parameters:
            yield attribute, value()


def _as_problem(label: str, item: Any, index: int) -> tuple[str, Any]:
    """``(name, problem object)`` of one yielded item."""
    if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str):
        return item[0], item[1]
    return str(getattr(item, "name", "") or f"{label}_{index:03d}"), item


def read_module(name: str) -> list[Problem]:
    """The problems a module's test sets yield (see the module docstring).

    :class:`InputError` when the module cannot be imported, yields nothing, or yields an
    object without qpsolvers' ``P`` and ``q``.
    """
    try:
        module = importlib.import_module(name)
    except Exception as error:  # a user module may raise anything on import
        raise InputError(f"--module {name}: cannot import it ({type(error).__name__}: "
                         f"{error})") from error
    problems: list[Problem] = []
    for label, produced in _items(module):
        if not isinstance(produced, Iterable) or isinstance(produced, str | bytes | dict):
            continue
        for index, item in enumerate(produced):
            item_name, obj = _as_problem(label, item, index)
            source = f"--module {name}: {label} item {index} ({item_name})"
            if not hasattr(obj, "P") or not hasattr(obj, "q"):
                raise InputError(f"{source}: not a qpsolvers.Problem (no P and q)")
            arrays = {key: _optional({key: getattr(obj, key, None)}, key)
                      for key in QPSOLVERS_KEYS}
            problems.append(qp_problem(instance_name(item_name), arrays, source))
    if not problems:
        raise InputError(f"--module {name}: defines no function or class yielding "
                         "qpsolvers.Problem objects")
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
