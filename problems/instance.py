"""Subproblem instances' ``.npz`` + JSON storage (the ``Problem`` contract, the one
QP-with-complementarity form every family is stored in, is in
:mod:`problems.instance_contract`, re-exported here).

Storage: ``<name>.npz`` (the arrays, written with fixed zip timestamps so that regenerating
gives byte-identical files) and ``<name>.json`` (schema version, family, name, metadata and the
list of array keys, plus an ``lcs`` table when the instance has an LCS; its arrays are then
stored as ``lcs.A`` ... ``lcs.phi``). Loading a file of another schema version, or one missing a
key, raises :class:`InstanceFormatError` naming the file and the key.

Part of the plant-free core: imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.errors import InputError, InstanceFormatError
from c3bench.problems.instance_contract import (  # re-exported: the contract
    FAMILIES,
    QP_FIELDS,
    REQUIRED_META,
    SCHEMA_VERSION,
    Problem,
    check_real,
    lcp_data,
)

__all__ = [
    "FAMILIES", "MANIFEST", "QP_FIELDS", "REQUIRED_META", "SCHEMA_VERSION", "InstanceSet",
    "Problem", "atomic_write_bytes", "lcp_data", "list_instances", "load_instances",
    "load_problem", "problem_arrays", "read_instances", "read_manifest", "required_meta",
    "save_problem",
]
from c3bench.problems.lcs import LCS, LCS_MATRICES
from c3bench.problems.names import GENERIC_FAMILIES

# --- storage -------------------------------------------------------------------------------
_FIXED_TIME = (1980, 1, 1, 0, 0, 0)


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write an uncompressed ``.npz`` with fixed timestamps (byte-reproducible), atomically."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for key in sorted(arrays):
            entry = io.BytesIO()
            np.lib.format.write_array(entry, np.ascontiguousarray(arrays[key]),
                                      allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_FIXED_TIME)
            info.external_attr = 0o644 << 16
            archive.writestr(info, entry.getvalue())
    atomic_write_bytes(path, buffer.getvalue())


def atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` through a temporary file and a rename.

    An ``OSError`` of the write (disk full, read-only file system, no permission) names
    ``path`` rather than the temporary file; one creating the folder names that folder.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                             suffix=".tmp")
    except OSError as error:
        raise _naming(error, path) from error
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(payload)
            stream.flush()
            os.fsync(stream.fileno())
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException as error:
        Path(temporary).unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise _naming(error, path) from error
        raise


def _naming(error: OSError, path: Path) -> OSError:
    """``error`` as the same ``OSError`` subclass, naming ``path`` as the file at fault."""
    if error.errno is None or error.strerror is None:
        return error
    return type(error)(error.errno, error.strerror, str(path))


def problem_arrays(problem: Problem) -> dict[str, np.ndarray]:
    """All arrays of an instance under their storage keys (``P``, ``lcs.A``, ``data.x0``...)."""
    arrays: dict[str, np.ndarray] = {}
    for name in QP_FIELDS:
        value = getattr(problem, name)
        if value is not None:
            arrays[name] = value
    if problem.complementarity is not None:
        arrays["complementarity"] = problem.complementarity
    if problem.lcs is not None:
        for key, value in problem.lcs.arrays().items():
            arrays[f"lcs.{key}"] = value
    for key, value in problem.data.items():
        arrays[f"data.{key}"] = value
    return arrays


def save_problem(problem: Problem, directory: str | Path) -> Path:
    """Write ``<name>.npz`` and ``<name>.json`` into ``directory``; return the JSON path."""
    directory = Path(directory)
    arrays = problem_arrays(problem)
    header: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "name": problem.name,
        "family": problem.family,
        "objective_offset": problem.objective_offset,
        "arrays": sorted(arrays),
        "meta": problem.meta,
    }
    if problem.lcs is not None:
        header["lcs"] = {
            "dt": problem.lcs.dt,
            "contact_model": problem.lcs.contact_model,
            "n_contacts": problem.lcs.n_contacts,
            "friction_directions": problem.lcs.friction_directions,
        }
    _write_npz(directory / f"{problem.name}.npz", arrays)
    text = json.dumps(header, indent=2, sort_keys=True, allow_nan=False) + "\n"
    json_path = directory / f"{problem.name}.json"
    atomic_write_bytes(json_path, text.encode())
    return json_path


def _require(table: dict[str, Any], key: str, source: Path) -> Any:
    if key not in table:
        raise InstanceFormatError(f"{source}: missing key {key!r}")
    return table[key]


def _read_header(json_path: Path, npz_path: Path) -> dict[str, Any]:
    """The JSON header of an instance; :class:`InstanceFormatError` naming the file when it
    is missing, empty or not a JSON object."""
    try:
        text = json_path.read_text()
    except FileNotFoundError as error:
        if npz_path.exists():
            raise InstanceFormatError(f"{npz_path}: no {json_path.name} beside it (an array "
                                      "file without its instance header)") from error
        raise InstanceFormatError(f"{json_path}: no such instance file") from error
    except (OSError, UnicodeDecodeError) as error:
        raise InstanceFormatError(f"{json_path}: unreadable ({error})") from error
    try:
        header = json.loads(text)
    except json.JSONDecodeError as error:
        what = "empty file" if not text.strip() else f"not valid JSON ({error})"
        raise InstanceFormatError(f"{json_path}: {what}") from error
    if not isinstance(header, dict):
        raise InstanceFormatError(f"{json_path}: not an instance header (a JSON "
                                  f"{type(header).__name__}, expected an object)")
    return header


def _read_arrays(npz_path: Path) -> dict[str, np.ndarray]:
    """Every array of an instance's ``.npz``; :class:`InstanceFormatError` naming the file
    when it is missing, empty or truncated."""
    if not npz_path.exists():
        raise InstanceFormatError(f"{npz_path}: no such array file (the instance header "
                                  "is there, its arrays are not)")
    if npz_path.is_file() and npz_path.stat().st_size == 0:
        raise InstanceFormatError(f"{npz_path}: empty file (0 bytes)")
    try:
        with np.load(npz_path, allow_pickle=False) as stored:
            return {key: stored[key] for key in stored.files}
    except Exception as error:  # any failure to decode is a bad file
        raise InstanceFormatError(f"{npz_path}: unreadable, truncated or not an .npz "
                                  f"({type(error).__name__}: {error})") from error


def load_problem(path: str | Path) -> Problem:
    """Load an instance from its ``.json`` (or ``.npz``, or the common stem) path.

    Raises :class:`InstanceFormatError` naming the file and the problem: a header or array
    file missing, empty, truncated or of another schema version, a key missing, arrays of
    the wrong shape.
    """
    path = Path(path)
    json_path = path.with_suffix(".json") if path.suffix in (".npz", "") else path
    npz_path = json_path.with_suffix(".npz")
    header = _read_header(json_path, npz_path)
    version = _require(header, "schema_version", json_path)
    if version != SCHEMA_VERSION:
        raise InstanceFormatError(
            f"{json_path}: key 'schema_version' is {version!r}, this c3bench reads "
            f"{SCHEMA_VERSION}; regenerate the instances"
        )
    for key in ("name", "family"):
        _require(header, key, json_path)
    keys = _require(header, "arrays", json_path)
    meta = _require(header, "meta", json_path)
    if not isinstance(meta, dict) or not isinstance(keys, list):
        raise InstanceFormatError(f"{json_path}: 'meta' must be an object and 'arrays' a list")
    for key in required_meta(str(header["family"]), "lcs" in header):
        if key not in meta:
            raise InstanceFormatError(f"{json_path}: missing key 'meta.{key}'")
    arrays = _read_arrays(npz_path)
    _check_real(arrays, npz_path)
    for key in [*keys, "P", "q"]:
        if key not in arrays:
            raise InstanceFormatError(f"{npz_path}: missing key {key!r}")
    try:
        return _build_problem(header, arrays, json_path, npz_path)
    except (TypeError, ValueError) as error:
        if isinstance(error, InstanceFormatError):
            raise
        raise InstanceFormatError(f"{json_path}: {error}") from error


def _check_real(arrays: dict[str, np.ndarray], npz_path: Path) -> None:
    """Every stored array holds real numbers (:func:`check_real`): :class:`InstanceFormatError`
    naming the file and the key for complex (never cut to its real part), string or other
    data."""
    for key in sorted(arrays):
        try:
            check_real(key, arrays[key])
        except ValueError as error:
            raise InstanceFormatError(f"{npz_path}: {error}") from None


def required_meta(family: str, has_lcs: bool) -> tuple[str, ...]:
    """The metadata keys an instance must carry: :data:`REQUIRED_META` where it describes the
    cube (every instance with an LCS table, and every instance of a cube-only family), none
    for an instance of a generic family (``qp``, ``mpcc``, ``lcp``, ``lcp_general``) brought
    without an LCS."""
    return () if family in GENERIC_FAMILIES and not has_lcs else REQUIRED_META


def _build_problem(header: dict[str, Any], arrays: dict[str, np.ndarray], json_path: Path,
                   npz_path: Path) -> Problem:
    """The :class:`Problem` of a checked header and its arrays (``ValueError`` when the
    arrays do not fit together)."""
    lcs = None
    if "lcs" in header:
        lcs_header = header["lcs"]
        for key in LCS_MATRICES:
            if f"lcs.{key}" not in arrays:
                raise InstanceFormatError(f"{npz_path}: missing key 'lcs.{key}'")
        lcs = LCS(
            **{key: arrays[f"lcs.{key}"] for key in LCS_MATRICES},
            dt=float(_require(lcs_header, "dt", json_path)),
            contact_model=str(_require(lcs_header, "contact_model", json_path)),
            n_contacts=int(_require(lcs_header, "n_contacts", json_path)),
            friction_directions=int(_require(lcs_header, "friction_directions", json_path)),
            phi=arrays.get("lcs.phi", np.zeros(0)),
        )
    data = {key[5:]: value for key, value in arrays.items() if key.startswith("data.")}
    return Problem(
        name=header["name"], family=header["family"], P=arrays["P"], q=arrays["q"],
        A=arrays.get("A"), b=arrays.get("b"), G=arrays.get("G"), h=arrays.get("h"),
        lb=arrays.get("lb"), ub=arrays.get("ub"),
        complementarity=arrays.get("complementarity"),
        objective_offset=float(header.get("objective_offset", 0.0)),
        lcs=lcs, data=data, meta=header["meta"],
    )


# --- directories of instances ----------------------------------------------------------------
MANIFEST = "manifest.json"
"""The suite manifest beside the family folders (not an instance)."""
MANIFEST_HELP = ("remove it: `c3bench run --instances DIR` writes a new one, `c3bench run` "
                 "regenerates a packaged suite")
"""What to do about a damaged manifest (:func:`read_manifest`)."""


def read_manifest(directory: str | Path) -> dict[str, Any] | None:
    """The manifest of an instance directory (``directory/manifest.json``), ``None`` when it
    has none.

    Raises
    ------
    InputError
        Naming the file when it is unreadable, not JSON, or not a manifest's table: an object
        whose ``suite`` is an object, with ``counts`` (if any) mapping names to counts,
        ``instances`` (if any) a list of names and ``generator_version`` (if any) an integer.
    """
    path = Path(directory) / MANIFEST
    if not os.path.lexists(path):
        return None
    try:
        table = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        why = f"{type(error).__name__}: {error}"
        raise InputError(f"{path}: unreadable or not JSON ({why}); {MANIFEST_HELP}") from error
    why = _manifest_fault(table)
    if why:
        raise InputError(f"{path}: not an instance manifest ({why}); {MANIFEST_HELP}")
    return dict(table)


def _manifest_fault(table: Any) -> str:
    """What makes ``table`` (a parsed ``manifest.json``) no manifest, ``""`` when nothing."""
    if not isinstance(table, dict):
        return f"a JSON {type(table).__name__}, expected an object"
    if not isinstance(table.get("suite"), dict):
        return "key 'suite' must be an object"
    counts = table.get("counts", {})
    if not (isinstance(counts, dict) and all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in counts.values())):
        return "key 'counts' must map names to counts"
    names = table.get("instances", [])
    if not (isinstance(names, list) and all(isinstance(name, str) for name in names)):
        return "key 'instances' must be a list of names"
    version = table.get("generator_version", 0)
    if not isinstance(version, int) or isinstance(version, bool):
        return "key 'generator_version' must be an integer"
    return ""


def list_instances(directory: str | Path) -> list[Path]:
    """The instance files of a directory (recursively), as JSON paths sorted by path.

    Every ``.npz`` counts, and every ``.json`` in a folder named after a family or holding an
    ``.npz`` (the manifest and hidden files aside), so that a header without its arrays, or
    arrays without their header, are listed (and then fail to load) rather than ignored.
    """
    root = Path(directory)
    found: set[Path] = set()
    for path in root.rglob("*.npz"):
        if not path.name.startswith("."):
            found.add(path.with_suffix(".json"))
    for path in root.rglob("*.json"):
        if path.name.startswith(".") or path.name == MANIFEST:
            continue
        if path.parent.name in FAMILIES or path.with_suffix(".npz").exists() \
                or any(path.parent.glob("*.npz")):
            found.add(path)
    return sorted(found)


@dataclass
class InstanceSet:
    """The instances of a directory.

    Attributes
    ----------
    problems
        Every instance loaded, in path order.
    paths
        The JSON path of each of ``problems`` (same order).
    skipped
        One line per bad file left out (``skip_bad=True``): ``path: what is wrong``.
    """

    problems: list[Problem] = field(default_factory=list)
    paths: list[Path] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)


def read_instances(directory: str | Path, skip_bad: bool = False, *,
                   check_manifest: bool = True) -> InstanceSet:
    """Load every instance below ``directory``.

    A bad file (see :func:`load_problem`) or a second instance of the same name raises
    :class:`InstanceFormatError` naming the file and the problem; with ``skip_bad`` it is
    left out and listed in :attr:`InstanceSet.skipped` instead. A damaged ``manifest.json``
    (:func:`read_manifest`) raises :class:`InputError` naming it, with or without
    ``skip_bad``, unless ``check_manifest`` is false (a packaged suite's stored copy, whose
    damaged manifest a run regenerates).
    """
    if check_manifest:
        read_manifest(directory)  # a damaged manifest stops it, even with skip_bad
    out = InstanceSet()
    first: dict[str, Path] = {}
    for path in list_instances(directory):
        try:
            problem = load_problem(path)
            if problem.name in first:
                raise InstanceFormatError(f"{path}: duplicate instance name {problem.name!r} "
                                          f"(also in {first[problem.name]})")
        except InstanceFormatError as error:
            if not skip_bad:
                raise
            out.skipped.append(str(error))
            continue
        first[problem.name] = path
        out.problems.append(problem)
        out.paths.append(path)
    return out


def load_instances(directory: str | Path, families: tuple[str, ...] | None = None,
                   skip_bad: bool = False) -> list[Problem]:
    """Load every instance below ``directory`` (optionally only some families).

    Stops at the first bad file unless ``skip_bad`` (:func:`read_instances`).
    """
    problems = read_instances(directory, skip_bad).problems
    if families is not None:
        problems = [p for p in problems if p.family in families]
    return problems
