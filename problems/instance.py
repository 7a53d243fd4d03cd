"""Subproblem instances: the shared ``Problem`` contract and its ``.npz`` + JSON storage.

Every family is stored in one QP-with-complementarity form, following qpsolvers' names:

    minimise    1/2 z^T P z + q^T z + objective_offset
    subject to  A z = b,   G z <= h,   lb <= z <= ub,
                0 <= z_i  perp  z_j >= 0   for every row (i, j) of ``complementarity``.

``lcs`` holds the LCS the instance came from (optional: ``None`` for an instance without one),
``data`` the family's own arrays (``x0``, ``delta``, ``w``, ``G_diag``, ``v``, ``U_diag``, ...),
``meta`` its JSON metadata.

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
import math
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.errors import InstanceFormatError
from c3bench.problems.lcs import LCS, LCS_MATRICES
from c3bench.problems.names import GENERIC_FAMILIES, Family

SCHEMA_VERSION = 1
FAMILIES: tuple[str, ...] = tuple(Family)
"""Family names in their canonical order (:class:`c3bench.problems.names.Family`)."""
QP_FIELDS: tuple[str, ...] = ("P", "q", "A", "b", "G", "h", "lb", "ub")
REQUIRED_META: tuple[str, ...] = ("scene", "l", "dt", "T", "seed", "precision")
"""Metadata describing the cube scene: required of the cube families only (the generic
families, :data:`~c3bench.problems.names.GENERIC_FAMILIES`, load without it)."""


@dataclass
class Problem:
    """One subproblem instance (see the module docstring for the form).

    Attributes
    ----------
    name
        Unique, file-safe name.
    family
        One of :data:`FAMILIES`.
    P, q
        Objective ``1/2 z^T P z + q^T z`` (P symmetric positive semi-definite, dense).
    A, b
        Equalities ``A z = b`` (``None`` when absent).
    G, h
        Inequalities ``G z <= h`` (``None`` when absent).
    lb, ub
        Bounds (``None`` when absent; entries may be infinite).
    complementarity
        Integer array (pairs x 2): ``0 <= z[i] perp z[j] >= 0``; ``None`` when absent.
    objective_offset
        Constant added to the objective, so that it equals the family's true cost.
    lcs
        The LCS the instance came from, or ``None`` (then no ``lcs.*`` arrays are stored).
    data
        Family-specific arrays.
    meta
        JSON-serialisable metadata (family, scene, l, dt, T, rho, admm_iteration,
        state_index, seed, precision, ...).
    """

    name: str
    family: str
    P: np.ndarray
    q: np.ndarray
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None
    lb: np.ndarray | None = None
    ub: np.ndarray | None = None
    complementarity: np.ndarray | None = None
    objective_offset: float = 0.0
    lcs: LCS | None = None
    data: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # --- sizes ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.q.shape[0])

    @property
    def n_eq(self) -> int:
        """Equality rows."""
        return 0 if self.A is None else int(self.A.shape[0])

    @property
    def n_ineq(self) -> int:
        """Inequality rows."""
        return 0 if self.G is None else int(self.G.shape[0])

    @property
    def n_pairs(self) -> int:
        """Complementarity pairs."""
        return 0 if self.complementarity is None else int(self.complementarity.shape[0])

    @property
    def n_bounded(self) -> int:
        """Variables with at least one finite bound."""
        finite = np.zeros(self.n, dtype=bool)
        for bound in (self.lb, self.ub):
            if bound is not None:
                finite |= np.isfinite(bound)
        return int(finite.sum())

    # --- checks ---------------------------------------------------------------------------
    def validate(self) -> None:
        """Check shapes and values; raise ``ValueError`` naming the field at fault."""
        if self.family not in FAMILIES:
            raise ValueError(f"family must be one of {FAMILIES}, got {self.family!r}")
        self.q = _as_float("q", self.q, ndim=1)
        n = self.q.shape[0]
        self.P = _as_float("P", self.P, shape=(n, n))
        if not np.all(np.isfinite(self.P)):
            raise ValueError(f"{self.name}: P has non-finite entries")
        if not np.all(np.isfinite(self.q)):
            raise ValueError(f"{self.name}: q has non-finite entries")
        scale = max(1.0, float(np.max(np.abs(self.P), initial=0.0)))
        if np.max(np.abs(self.P - self.P.T), initial=0.0) > 1e-9 * scale:
            raise ValueError(f"{self.name}: P is not symmetric")
        for matrix, vector in (("A", "b"), ("G", "h")):
            M, v = getattr(self, matrix), getattr(self, vector)
            if (M is None) != (v is None):
                raise ValueError(f"{self.name}: {matrix} and {vector} must both be given or "
                                 "both be None")
            if M is None:
                continue
            M = _as_float(matrix, M, ndim=2)
            if M.shape[1] != n:
                raise ValueError(f"{self.name}: {matrix} must have {n} columns, got {M.shape}")
            v = _as_float(vector, v, shape=(M.shape[0],))
            for label, value in ((matrix, M), (vector, v)):
                if not np.all(np.isfinite(value)):
                    raise ValueError(f"{self.name}: {label} has non-finite entries")
            setattr(self, matrix, M)
            setattr(self, vector, v)
        for bound in ("lb", "ub"):
            value = getattr(self, bound)
            if value is None:
                continue
            value = _as_float(bound, value, shape=(n,))
            if np.any(np.isnan(value)):
                raise ValueError(f"{self.name}: {bound} has NaN entries")
            setattr(self, bound, value)
        if self.lb is not None and self.ub is not None and np.any(self.lb > self.ub):
            raise ValueError(f"{self.name}: lb > ub at index "
                             f"{int(np.flatnonzero(self.lb > self.ub)[0])}")
        if self.complementarity is not None:
            pairs = np.asarray(self.complementarity)
            if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype,
                                                                           np.integer):
                raise ValueError(f"{self.name}: complementarity must be an integer array of "
                                 f"shape (pairs, 2), got {pairs.dtype} {pairs.shape}")
            if pairs.size and (pairs.min() < 0 or pairs.max() >= n):
                raise ValueError(f"{self.name}: complementarity indices outside 0..{n - 1}")
            self.complementarity = pairs.astype(np.int64)
        if not math.isfinite(self.objective_offset):
            raise ValueError(f"{self.name}: objective_offset must be finite")
        for key, value in self.data.items():
            self.data[key] = np.asarray(value)
        if self.family == Family.LCP_GENERAL:
            _check_lcp_general(self)

    # --- evaluation -----------------------------------------------------------------------
    def objective(self, z: np.ndarray) -> float:
        """``1/2 z^T P z + q^T z + objective_offset``."""
        z = np.asarray(z, dtype=float)
        return float(0.5 * z @ self.P @ z + self.q @ z + self.objective_offset)

    def summary(self) -> dict[str, Any]:
        """Sizes for listings: variables, equality and inequality rows, pairs, bounds."""
        return {"name": self.name, "family": self.family, "variables": self.n,
                "equality_rows": self.n_eq, "inequality_rows": self.n_ineq,
                "bounded_variables": self.n_bounded, "complementarity_pairs": self.n_pairs}


def lcp_data(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``(F, q)`` of the LCP ``0 <= lam perp F lam + q >= 0`` an ``lcp`` or ``lcp_general``
    instance states: ``(data["F"], h)`` for ``lcp_general`` (``F`` stored as is,
    :func:`c3bench.problems.families.lcp_general`), ``(P, q)`` for ``lcp`` (whose ``F`` is
    symmetric and is the QP's Hessian)."""
    if problem.family == Family.LCP_GENERAL:
        assert problem.h is not None  # checked by Problem.validate
        return problem.data["F"], problem.h
    return problem.P, problem.q


def _check_lcp_general(problem: Problem) -> None:
    """An ``lcp_general`` instance is exactly the form of
    :func:`c3bench.problems.families.lcp_general`: ``data["F"]`` square of size ``n`` and
    finite, ``P = 0``, ``q = 0``, ``G = -F``, ``h`` (the LCP's ``q``) given, ``lb = 0``,
    nothing else; ``ValueError`` naming the field at fault."""
    n, name = problem.n, problem.name
    if "F" not in problem.data:
        raise ValueError(f"{name}: an lcp_general instance stores its matrix as data['F']; "
                         "build it with c3bench.problems.families.lcp_general")
    F = _as_float("data['F']", problem.data["F"], shape=(n, n))
    if not np.all(np.isfinite(F)):
        raise ValueError(f"{name}: data['F'] has non-finite entries")
    problem.data["F"] = F
    expected = (("P", problem.P, np.zeros((n, n))), ("q", problem.q, np.zeros(n)),
                ("G", problem.G, -F), ("lb", problem.lb, np.zeros(n)))
    for label, value, form in expected:
        if value is None or value.shape != form.shape or not np.array_equal(value, form):
            raise ValueError(f"{name}: an lcp_general instance needs {label} of its stored "
                             "form (P = 0, q = 0, G = -F, h = the LCP's q, lb = 0; "
                             "c3bench.problems.families.lcp_general)")
    extra = [label for label, value in (("A", problem.A), ("complementarity",
                                                          problem.complementarity))
             if value is not None]
    if problem.ub is not None and np.any(np.isfinite(problem.ub)):
        extra.append("ub")
    if extra:
        raise ValueError(f"{name}: an lcp_general instance takes no {', '.join(extra)}")


def _as_float(name: str, value: Any, ndim: int | None = None,
              shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be numeric: {error}") from error
    if ndim is not None and array.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {array.shape}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


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
    for key in [*keys, "P", "q"]:
        if key not in arrays:
            raise InstanceFormatError(f"{npz_path}: missing key {key!r}")
    try:
        return _build_problem(header, arrays, json_path, npz_path)
    except (TypeError, ValueError) as error:
        if isinstance(error, InstanceFormatError):
            raise
        raise InstanceFormatError(f"{json_path}: {error}") from error


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


def read_instances(directory: str | Path, skip_bad: bool = False) -> InstanceSet:
    """Load every instance below ``directory``.

    A bad file (see :func:`load_problem`) or a second instance of the same name raises
    :class:`InstanceFormatError` naming the file and the problem; with ``skip_bad`` it is
    left out and listed in :attr:`InstanceSet.skipped` instead.
    """
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
