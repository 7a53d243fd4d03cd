"""Instance identity across machines: provenance plus a tolerance-aware digest of the arrays.

A stored cell is *stale* when the instance it was solved on is no longer the instance in the
suite. Byte hashes of the files answer that on one machine (generation is byte-identical
there), but a suite regenerated on another machine (another BLAS, libm or MuJoCo build) has
arrays equal to about 1e-11 with different bytes, which made every stored cell stale. An
instance's identity here is therefore

1. its **provenance**: SHA-256 of what generated it: the instance header (schema version,
   name, family, array keys, the LCS table and all metadata: scene, seed, state index, ADMM
   iteration, rho, capture route, variant...; every number in it comes from the
   configuration, not from floating-point computation), without ``objective_offset`` (a
   computed number, fingerprinted with the arrays), plus the suite manifest's ``config``
   table and ``suite`` table (generator settings; ``generator_version`` too when a
   generator writes one) without the local paths ``instances_from`` and ``imported_from``,
   and without an imported instance's ``meta.source`` (the file ``problems import`` read:
   byte-identical files imported from another folder are the same instance); compared
   exactly;
2. a **fingerprint**: SHA-256 of every array rounded on a grid relative to the array's
   largest magnitude (below), compared exactly.

Rounding (documented choice)
----------------------------
Each float array ``a`` is scaled by a power of two, ``v = a * 2^(30 - e)`` with
``2^(e-1) <= max|a| < 2^e`` (``e = 0`` for an all-zero array), so the grid is one unit of
``v``: ``2^(e-30)``, between 4.7e-10 and 9.3e-10 of ``max|a|`` (relative 1e-9 of the array,
a norm-wise tolerance like the solvers' own: an exact zero carries noise of 1e-17 from some
BLAS, so no per-entry relative grid could be robust). Every rounding grid has boundaries, and
any noise, however small, flips the rounding of a value that sits close enough to one. So
each value is rounded on one of two grids offset by half a unit: the plain grid
(``round(v)``, boundaries at half-integers) unless ``v`` lies within :data:`GUARD` units of a
half-integer, then the shifted grid (``floor(v)``, boundaries at integers, which such a
value is at least ``0.5 - GUARD`` units away from). Which grid each value uses (and ``e``) is
chosen once, when the identity is first made, and stored with it; a later check on another
machine rounds *its* arrays with the stored choice. Hence:

* any perturbation below ``GUARD`` units (1.2e-10 of ``max|a|``) gives the same fingerprint:
  never stale (last-bit noise is 1e-16);
* any change of a value by one unit or more (9.3e-10 of ``max|a|``) changes it: stale;
* byte-identical files give the same fingerprint and the same ``id``: the string the rows
  store, the first 16 hex digits of SHA-256 of the provenance and of the file bytes the
  identity was first made from (kept, with its rounding choices, as long as it holds; for an
  imported instance the header's bytes are replaced by the header without its local
  ``meta.source``, so the same files imported from two folders get the same ``id``).
  Rows stored before this rule hold a plain byte hash: they are stale once, as is a suite
  whose generator config changed without changing its files.

Integer arrays (complementarity pairs) and non-finite entries are hashed exactly.

Part of the plant-free core: imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

import base64
import hashlib
import json
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.errors import InstanceFormatError
from c3bench.problems.instance import atomic_write_bytes

IDENTITY_VERSION = 1
"""Version of the identity rule (part of the provenance: a new rule re-identifies)."""
GRID_BITS = 30
"""Grid of an array: ``2^-GRID_BITS`` of the power of two above its largest magnitude."""
GUARD = 0.125
"""Values within this many grid units of a plain-grid boundary use the shifted grid."""
LOCAL_KEYS: tuple[str, ...] = ("instances_from", "imported_from")
"""Manifest suite entries that describe the local machine, not the generation: where a run
copied its instances from, and the folder ``problems import`` read (a path; the imported
arrays themselves are fingerprinted), so that re-importing a folder with one file changed
makes only that instance stale."""
LOCAL_META_KEYS: tuple[str, ...] = ("source",)
"""Metadata of an imported instance (``meta.imported``) that describes the local machine:
the file (a path) or module item ``problems import`` read; the arrays it held are
fingerprinted."""
OFFSET_KEY = "objective_offset"
"""The header's computed constant, fingerprinted as a 0-d array under this key."""


@dataclass(frozen=True)
class GridChoice:
    """How one array is rounded: the exponent ``e`` and which values use the shifted grid
    (packed bits, zlib, base64; ``""`` when none do)."""

    exponent: int
    shifted: str = ""

    def mask(self, size: int) -> np.ndarray:
        """The shifted-grid mask as booleans of ``size``."""
        if not self.shifted:
            return np.zeros(size, dtype=bool)
        bits = np.frombuffer(zlib.decompress(base64.b64decode(self.shifted)), dtype=np.uint8)
        return np.unpackbits(bits, count=size).astype(bool)

    @classmethod
    def of(cls, values: np.ndarray) -> GridChoice:
        """The choice for ``values`` (finite float entries): ``e`` from the largest
        magnitude, the shifted grid where a value is within :data:`GUARD` of a boundary."""
        finite = values[np.isfinite(values)]
        largest = float(np.max(np.abs(finite))) if finite.size else 0.0
        exponent = int(np.frexp(largest)[1]) if largest > 0 else 0
        scaled = np.ldexp(np.where(np.isfinite(values), values, 0.0), GRID_BITS - exponent)
        near = 0.5 - np.abs(scaled - np.rint(scaled)) < GUARD
        if not near.any():
            return cls(exponent)
        packed = np.packbits(near.ravel()).tobytes()
        return cls(exponent, base64.b64encode(zlib.compress(packed, 9)).decode())


def rounded(values: np.ndarray, choice: GridChoice) -> np.ndarray:
    """The integer codes of ``values`` under ``choice``: ``2 round(v)`` on the plain grid,
    ``2 floor(v) + 1`` on the shifted one (distinct codes), with non-finite entries coded
    apart (``v = a 2^(30 - e)``, module docstring)."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    finite = np.isfinite(flat)
    scaled = np.ldexp(np.where(finite, flat, 0.0), GRID_BITS - choice.exponent)
    shifted = choice.mask(flat.size)
    codes = np.where(shifted, 2 * np.floor(scaled) + 1, 2 * np.rint(scaled))
    codes = np.where(finite, codes, 0.0)
    out: np.ndarray = codes.astype(np.int64)
    if not finite.all():  # +inf, -inf and NaN coded by position
        out = np.concatenate([out, np.flatnonzero(~finite), np.sign(flat[~finite])
                              .astype(np.int64), np.isnan(flat[~finite]).astype(np.int64)])
    return out


def fingerprint(arrays: dict[str, np.ndarray], choices: dict[str, GridChoice]) -> str:
    """SHA-256 of every array's name, shape and codes (floats rounded with ``choices``,
    anything else by its bytes), in name order."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.asarray(arrays[name])
        digest.update(f"{name}|{array.shape}|{array.dtype.kind}|".encode())
        if array.dtype.kind == "f" and name in choices:
            digest.update(rounded(array, choices[name]).tobytes())
        else:
            digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def portable_header(header: dict[str, Any]) -> dict[str, Any]:
    """``header`` without what describes the local machine: an imported instance's
    :data:`LOCAL_META_KEYS` (``header`` itself when it has none)."""
    meta = header.get("meta")
    if not (isinstance(meta, dict) and meta.get("imported") is True
            and any(key in meta for key in LOCAL_META_KEYS)):
        return header
    return {**header, "meta": {k: v for k, v in meta.items() if k not in LOCAL_META_KEYS}}


def provenance(header: dict[str, Any], manifest: dict[str, Any] | None) -> str:
    """SHA-256 of what generated the instance (module docstring, item 1)."""
    header = portable_header(header)
    manifest = manifest or {}
    suite = manifest.get("suite")
    if isinstance(suite, dict):
        suite = {k: v for k, v in suite.items() if k not in LOCAL_KEYS}
    table = {"identity_version": IDENTITY_VERSION,
             "header": {k: v for k, v in header.items() if k != OFFSET_KEY},
             "config": manifest.get("config"), "suite": suite,
             "generator_version": manifest.get("generator_version")}
    text = json.dumps(table, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def byte_hash(json_path: Path) -> str:
    """SHA-256 of the instance's ``.json`` and ``.npz`` bytes (first 16 hex digits)."""
    digest = hashlib.sha256()
    for path in (json_path, json_path.with_suffix(".npz")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _content_hash(json_path: Path, header: dict[str, Any]) -> str:
    """:func:`byte_hash`, with the header's bytes replaced by its :func:`portable_header`
    (canonical JSON) when it holds local metadata."""
    portable = portable_header(header)
    if portable is header:
        return byte_hash(json_path)
    digest = hashlib.sha256(json.dumps(portable, sort_keys=True, default=str).encode())
    digest.update(json_path.with_suffix(".npz").read_bytes())
    return digest.hexdigest()[:16]


@dataclass(frozen=True)
class InstanceIdentity:
    """What a stored cell's ``instance_hash`` stands for.

    Attributes
    ----------
    id
        The string rows store (from the provenance and the bytes of the files it was first
        made from).
    provenance
        :func:`provenance` of the instance.
    fingerprint
        :func:`fingerprint` of its arrays under ``choices``.
    choices
        Per float array, the rounding :class:`GridChoice` made when the identity was made.
    """

    id: str
    provenance: str
    fingerprint: str
    choices: dict[str, GridChoice]

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "provenance": self.provenance, "fingerprint": self.fingerprint,
                "choices": {k: [c.exponent, c.shifted] for k, c in self.choices.items()}}

    @classmethod
    def from_json(cls, table: dict[str, Any]) -> InstanceIdentity:
        choices = {k: GridChoice(int(v[0]), str(v[1])) for k, v in table["choices"].items()}
        return cls(str(table["id"]), str(table["provenance"]), str(table["fingerprint"]),
                   choices)


def _contents(json_path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and arrays of an instance (the offset as a 0-d array)."""
    try:
        header = json.loads(json_path.read_text())
        with np.load(json_path.with_suffix(".npz"), allow_pickle=False) as stored:
            arrays = {key: stored[key] for key in stored.files}
    except (OSError, ValueError) as error:
        raise InstanceFormatError(f"{json_path}: cannot identify ({error})") from error
    if not isinstance(header, dict):
        raise InstanceFormatError(f"{json_path}: not an instance header")
    arrays[OFFSET_KEY] = np.asarray(float(header.get(OFFSET_KEY, 0.0)))
    return header, arrays


def identify(json_path: str | Path, known: InstanceIdentity | None = None,
             manifest: dict[str, Any] | None = None) -> InstanceIdentity:
    """The identity of the instance at ``json_path``: ``known`` when it still holds (same
    provenance, same fingerprint under ``known``'s rounding choices), else a new one (its
    ``id`` from the provenance and the bytes of the files)."""
    json_path = Path(json_path)
    header, arrays = _contents(json_path)
    origin = provenance(header, manifest)
    floats = {k for k, a in arrays.items() if np.asarray(a).dtype.kind == "f"}
    if (known is not None and known.provenance == origin and set(known.choices) == floats
            and fingerprint(arrays, known.choices) == known.fingerprint):
        return known
    choices = {k: GridChoice.of(np.asarray(arrays[k], dtype=np.float64)) for k in floats}
    made = hashlib.sha256(f"{origin}|{_content_hash(json_path, header)}".encode()).hexdigest()[:16]
    return InstanceIdentity(made, origin, fingerprint(arrays, choices), choices)


def load_identities(path: str | Path) -> dict[str, InstanceIdentity]:
    """``instance name -> identity`` from ``path`` (empty when missing or unreadable: the
    identities are then made afresh, which only costs a rerun of cells)."""
    try:
        table = json.loads(Path(path).read_text())
        return {name: InstanceIdentity.from_json(entry)
                for name, entry in table.get("instances", {}).items()}
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return {}


def save_identities(path: str | Path, identities: dict[str, InstanceIdentity]) -> None:
    """Write ``identities`` to ``path`` atomically (JSON, sorted)."""
    table = {"identity_version": IDENTITY_VERSION,
             "instances": {name: identities[name].to_json() for name in sorted(identities)}}
    atomic_write_bytes(Path(path), (json.dumps(table, indent=1, sort_keys=True) + "\n").encode())
