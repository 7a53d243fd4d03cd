"""CasADi ``conic`` problems on disk: :func:`save_conic` writes, ``problems import`` reads.

CasADi's QP interface (``casadi.conic``; inputs ``casadi.conic_in()``) states a problem as::

    minimise    1/2 x^T H x + g^T x
    subject to  lba <= A x <= uba,   lbx <= x <= ubx

(Andersson, Gillis, Horn, Rawlings and Diehl 2019). :func:`save_conic` writes an ``.npz`` whose
keys are CasADi's own input names in lower case, ``h g a lba uba lbx ubx`` (absent blocks are
left out), and ``c3bench problems import`` recognises such a file by its keys (a lower-case
``g`` and no ``q``: qpsolvers' files always hold ``q``) and converts it to qpsolvers' form
(:func:`conic_to_qpsolvers`):

* rows with ``lba_i == uba_i`` become equality rows ``A_i x = lba_i``;
* every other row gives ``A_i x <= uba_i`` where ``uba_i`` is finite and ``-A_i x <= -lba_i``
  where ``lba_i`` is finite (a row with both sides infinite constrains nothing and is dropped);
* ``lbx`` / ``ubx`` become the bounds ``lb`` / ``ub`` (``None`` when all infinite);
* ``H`` and ``g`` become ``P`` and ``q``.

No CasADi import here (the plant-free core): every argument is read with ``np.asarray``, after
``.toarray()`` for a ``scipy.sparse`` matrix or ``.full()`` for a CasADi ``DM``, so pass
``casadi.DM`` values (or ``np.array(dm)``) as they are.

References
----------
J. A. E. Andersson, J. Gillis, G. Horn, J. B. Rawlings and M. Diehl, "CasADi: a software
framework for nonlinear optimization and optimal control", Mathematical Programming
Computation 11(1), 1-36, 2019.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.instance import atomic_write_bytes

CONIC_KEYS: tuple[str, ...] = ("h", "g", "a", "lba", "uba", "lbx", "ubx")
"""The keys of a saved conic problem: CasADi's ``conic_in()`` names of a QP's data."""


def dense(value: Any, label: str = "value") -> np.ndarray:
    """``value`` as a float array: ``scipy.sparse`` via ``.toarray()``, CasADi ``DM`` via
    ``.full()``, anything else via ``np.asarray``; :class:`InputError` naming ``label`` for
    complex values (never cut to their real part)."""
    if hasattr(value, "toarray"):
        value = value.toarray()
    elif hasattr(value, "full"):
        value = value.full()
    if np.iscomplexobj(value):
        raise InputError(f"conic: {label} is complex; a QP's data are real numbers")
    return np.asarray(value, dtype=np.float64)


def is_conic(keys: set[str]) -> bool:
    """Whether an ``.npz`` with these keys is a saved conic problem (a ``g``, no ``q``)."""
    return "g" in keys and "q" not in keys


def conic_arrays(*, H: Any, g: Any, A: Any = None, lba: Any = None, uba: Any = None,
                 lbx: Any = None, ubx: Any = None) -> dict[str, np.ndarray]:
    """The checked arrays of a conic problem keyed by :data:`CONIC_KEYS` (absent ones left
    out). ``g`` is flattened to ``n``; ``A`` given without ``lba`` / ``uba`` gets CasADi's
    defaults ``-inf`` / ``+inf``.

    Raises
    ------
    InputError
        Shapes that do not fit ``n`` (or ``A``'s rows), no variable (``g`` empty), complex
        values, ``lba > uba`` or ``lbx > ubx``, a lower side ``+inf`` or an upper side
        ``-inf`` (infeasible), non-finite ``H``, ``g`` or ``A``, or ``lba`` / ``uba`` without
        ``A``.
    """
    g_vec = dense(g, "g").reshape(-1)
    n = g_vec.size
    if n == 0:
        raise InputError("conic: g is empty: a QP needs at least one variable")
    arrays: dict[str, np.ndarray] = {"g": g_vec, "h": _matrix("H", H, n, n)}
    if A is None:
        if lba is not None or uba is not None:
            raise InputError("conic: lba / uba given without A")
    else:
        a = dense(A, "A")
        a = a.reshape(1, -1) if a.ndim == 1 else a
        rows = a.shape[0]
        arrays["a"] = _matrix("A", a, rows, n)
        arrays["lba"] = _side("lba", lba, rows, -np.inf)
        arrays["uba"] = _side("uba", uba, rows, np.inf)
        _ordered("lba", arrays["lba"], "uba", arrays["uba"])
    if lbx is not None:
        arrays["lbx"] = _side("lbx", lbx, n, -np.inf)
    if ubx is not None:
        arrays["ubx"] = _side("ubx", ubx, n, np.inf)
    if lbx is not None and ubx is not None:
        _ordered("lbx", arrays["lbx"], "ubx", arrays["ubx"])
    if not all(np.all(np.isfinite(arrays[key])) for key in ("h", "g", "a") if key in arrays):
        raise InputError("conic: H, g and A must be finite")
    return arrays


def _matrix(label: str, value: Any, rows: int, cols: int) -> np.ndarray:
    """A ``rows x cols`` float matrix (``H = None`` is the zero matrix: an LP)."""
    matrix = np.zeros((rows, cols)) if value is None else dense(value, label)
    if matrix.shape != (rows, cols):
        raise InputError(f"conic: {label} must have shape ({rows}, {cols}), got {matrix.shape}")
    return matrix


def _side(label: str, value: Any, size: int, default: float) -> np.ndarray:
    """A bound vector of ``size`` entries (a scalar is broadcast; ``None`` is ``default``,
    ``-inf`` for a lower side, ``+inf`` for an upper one). A lower side ``+inf`` or an upper
    side ``-inf`` is infeasible: :class:`InputError` naming the entry."""
    vector = np.full(size, default) if value is None else dense(value, label).reshape(-1)
    if vector.size == 1 and size != 1:
        vector = np.full(size, float(vector[0]))
    if vector.shape != (size,) or np.any(np.isnan(vector)):
        raise InputError(f"conic: {label} must be {size} numbers (no NaN), got shape "
                         f"{vector.shape}")
    lower = default < 0
    index = infeasible_side(vector, lower)
    if index is not None:
        raise InputError(f"conic: {label}[{index}] = {-default:+}: an infeasible "
                         f"{'lower' if lower else 'upper'} side")
    return vector


def infeasible_side(bound: Any, lower: bool) -> int | None:
    """Index of the first entry of ``bound`` that no point satisfies, ``+inf`` in a lower
    bound or ``-inf`` in an upper one (``None`` when there is none)."""
    wrong = np.inf if lower else -np.inf
    hits = np.flatnonzero(np.asarray(bound, dtype=np.float64).reshape(-1) == wrong)
    return int(hits[0]) if hits.size else None


def _ordered(low_label: str, low: np.ndarray, high_label: str, high: np.ndarray) -> None:
    """:class:`InputError` where a lower side exceeds its upper side."""
    if np.any(low > high):
        raise InputError(f"conic: {low_label} > {high_label} at rows "
                         f"{np.flatnonzero(low > high).tolist()}")


def save_conic(path: str | Path, *, H: Any, g: Any, A: Any = None, lba: Any = None,
               uba: Any = None, lbx: Any = None, ubx: Any = None) -> Path:
    """Write the CasADi ``conic`` problem ``min 1/2 x^T H x + g^T x`` s.t.
    ``lba <= A x <= uba``, ``lbx <= x <= ubx`` as an ``.npz`` keyed by CasADi's input names
    (:data:`CONIC_KEYS`) that ``c3bench problems import`` reads.

    Parameters
    ----------
    path
        File to write (``.npz`` is appended when missing, as ``numpy.savez`` does).
    H, g, A, lba, uba, lbx, ubx
        CasADi's ``conic`` inputs ``h g a lba uba lbx ubx``: ``casadi.DM``, ``scipy.sparse``
        or anything ``np.asarray`` reads (``H = None``: an LP; ``A = None``: no rows).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    InputError
        Data that is not a QP of this form (:func:`conic_arrays`).

    Examples
    --------
    >>> save_conic("qp.npz", H=H, g=g, A=A, lba=lba, uba=uba)  # doctest: +SKIP
    """
    arrays = conic_arrays(H=H, g=g, A=A, lba=lba, uba=uba, lbx=lbx, ubx=ubx)
    target = Path(path)
    if target.suffix != ".npz":
        target = target.with_name(target.name + ".npz")
    buffer = io.BytesIO()
    cast(Any, np.savez)(buffer, **arrays)  # numpy's stubs type **kwds as allow_pickle
    atomic_write_bytes(target, buffer.getvalue())
    return target


def conic_to_qpsolvers(stored: Mapping[str, np.ndarray]) -> dict[str, np.ndarray | None]:
    """The qpsolvers arrays ``P q G h A b lb ub`` of a saved conic problem (see the module
    docstring for the rows); :class:`InputError` on data :func:`conic_arrays` refuses."""
    arrays = conic_arrays(H=stored.get("h"), g=stored["g"], A=stored.get("a"),
                          lba=stored.get("lba"), uba=stored.get("uba"),
                          lbx=stored.get("lbx"), ubx=stored.get("ubx"))
    n = arrays["g"].size
    result: dict[str, np.ndarray | None] = {"P": arrays["h"], "q": arrays["g"], "A": None,
                                            "b": None, "G": None, "h": None}
    if "a" in arrays:
        a, low, high = arrays["a"], arrays["lba"], arrays["uba"]
        equal = (low == high) & np.isfinite(low)
        upper = ~equal & np.isfinite(high)
        lower = ~equal & np.isfinite(low)
        if np.any(equal):
            result["A"], result["b"] = a[equal], low[equal]
        if np.any(upper) or np.any(lower):
            result["G"] = np.vstack([a[upper], -a[lower]]).reshape(-1, n)
            result["h"] = np.concatenate([high[upper], -low[lower]])
    for ours, theirs in (("lb", "lbx"), ("ub", "ubx")):
        bound = arrays.get(theirs)
        result[ours] = bound if bound is not None and np.any(np.isfinite(bound)) else None
    return result
