"""Export instances for other tools: ``qpsolvers.Problem.load`` reads every exported file.

``c3bench problems export DIR --out OUT --format qpsolvers`` writes one ``OUT/<name>.npz``
per instance without complementarity pairs (the families of
:data:`~c3bench.problems.names.QP_FAMILIES`), in exactly the layout of
``qpsolvers.Problem.save`` (qpsolvers 4): the eight keys ``P q G h A b lb ub``, an absent
block stored as ``None`` (an object array, which ``Problem.load`` reads back as ``None``).
The problem is ``min 1/2 x^T P x + q^T x`` s.t. ``G x <= h``, ``A x = b``, ``lb <= x <= ub``:
our instances' objective minus its constant ``objective_offset``.

``OUT/index.json`` lists each exported instance (name, family, file, ``objective_offset``,
so that ``f = 1/2 x^T P x + q^T x + objective_offset`` is our objective) and the instances
left out with the reason (complementarity pairs have no place in qpsolvers' form).

``OUT`` must be new, empty, or the folder of an earlier export (recognised by its
``index.json``; :func:`check_export_target`), which is updated (the ``.npz`` files its index
listed that this export does not write are removed; other files are left alone).

``OUT/c3bench_test_set.py`` (:data:`SHIM_NAME`) defines the qpbenchmark test set class
``C3BenchTestSet`` over ``OUT`` (:mod:`c3bench.bench.qpbenchmark_set`), so that
``qpbenchmark --results-path OUT/results.csv OUT/c3bench_test_set.py run`` benchmarks the
exported instances in qpbenchmark.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem, atomic_write_bytes
from c3bench.problems.names import QP_FAMILIES

FORMATS: tuple[str, ...] = ("qpsolvers",)
"""Export formats."""
INDEX = "index.json"
"""The export's table of contents (beside the ``.npz`` files)."""
SHIM_NAME = "c3bench_test_set.py"
"""The file an export writes beside the instances for qpbenchmark's command line
(which loads class ``C3BenchTestSet`` from a file ``c3bench_test_set.py``)."""
SHIM_SOURCE = '''"""qpbenchmark test set over this directory (written by `c3bench problems export`).

Run: qpbenchmark --results-path results.csv c3bench_test_set.py run --solver clarabel
"""

from pathlib import Path

from c3bench.bench.qpbenchmark_set import qpbenchmark_class


class C3BenchTestSet(qpbenchmark_class()):  # the class qpbenchmark loads from this file
    directory = Path(__file__).resolve().parent
'''
"""The source of :data:`SHIM_NAME`."""


@dataclass
class Export:
    """What an export wrote.

    Attributes
    ----------
    written
        The ``.npz`` paths, one per exported instance.
    skipped
        ``name -> reason`` of the instances left out.
    index
        The path of ``index.json``.
    test_set
        The path of the qpbenchmark test-set file (:data:`SHIM_NAME`).
    """

    written: list[Path] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    index: Path = Path(INDEX)
    test_set: Path = Path(SHIM_NAME)


def qpsolvers_arrays(problem: Problem) -> dict[str, Any]:
    """The arrays ``qpsolvers.Problem.save`` writes for ``problem`` (``None`` blocks kept)."""
    return {"P": problem.P, "q": problem.q, "G": problem.G, "h": problem.h,
            "A": problem.A, "b": problem.b, "lb": problem.lb, "ub": problem.ub}


def qpsolvers_npz(problem: Problem) -> bytes:
    """``problem`` as the bytes of a qpsolvers ``.npz`` (the layout of ``Problem.save``)."""
    buffer = io.BytesIO()
    a = {key: np.array(value) for key, value in qpsolvers_arrays(problem).items()}
    np.savez(buffer, P=a["P"], q=a["q"], G=a["G"], h=a["h"], A=a["A"], b=a["b"], lb=a["lb"],
             ub=a["ub"])
    return buffer.getvalue()


def exportable(problem: Problem) -> str:
    """Why ``problem`` cannot be written in qpsolvers' form, ``""`` when it can."""
    if problem.family not in QP_FAMILIES or problem.n_pairs:
        return (f"family {problem.family!r} has complementarity pairs, which qpsolvers' "
                "form cannot hold")
    return ""


def previous_files(out: Path) -> set[str] | None:
    """The ``.npz`` file names that the ``index.json`` of an earlier export into ``out``
    lists, ``None`` when ``out`` holds no export's index (none, unreadable, or not one)."""
    try:
        table = json.loads((out / INDEX).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not (isinstance(table, dict) and table.get("format") in FORMATS
            and isinstance(table.get("instances"), list)):
        return None
    files = (entry.get("file") for entry in table["instances"] if isinstance(entry, dict))
    return {name for name in files if isinstance(name, str) and name.endswith(".npz")
            and Path(name).name == name and not name.startswith(".")}


def check_export_target(out: Path) -> set[str] | None:
    """Refuse an output directory that an export must not write into: ``out`` may be absent,
    empty (hidden ``.tmp`` leftovers aside) or hold an earlier export (its ``index.json``,
    :func:`previous_files`), which is updated; anything else raises :class:`InputError`
    naming ``out`` (an export never overwrites files it did not write). Returns the earlier
    export's files (:func:`previous_files`), ``None`` when there is none."""
    if not out.is_dir():
        return None
    found = sorted(child.name for child in out.iterdir()
                   if not (child.name.startswith(".") and child.name.endswith(".tmp")))
    earlier = previous_files(out)
    if found and earlier is None:
        shown = ", ".join(found[:3]) + (", ..." if len(found) > 3 else "")
        raise InputError(f"{out}: holds files that no export wrote ({shown}; no export's "
                         f"{INDEX}); export into a new or empty directory, or one an earlier "
                         "export wrote")
    return earlier


def export_qpsolvers(problems: list[Problem], out: Path) -> Export:
    """Write ``problems`` (those :func:`exportable`) into ``out`` (see the module docstring).

    ``out`` must pass :func:`check_export_target`. An export's index is written first (so an
    interrupted export can be redone into the same folder) and last; the ``.npz`` files an
    earlier export there listed that this one does not write are removed.
    """
    earlier = check_export_target(out)
    result = Export(index=out / INDEX, test_set=out / SHIM_NAME)
    if earlier is None:  # mark the folder as an export's before writing into it
        _write_index(result.index, [], {})
    entries: list[dict[str, Any]] = []
    for problem in problems:
        reason = exportable(problem)
        if reason:
            result.skipped[problem.name] = reason
            continue
        path = out / f"{problem.name}.npz"
        atomic_write_bytes(path, qpsolvers_npz(problem))
        result.written.append(path)
        entries.append({"name": problem.name, "family": str(problem.family),
                        "file": path.name, "objective_offset": problem.objective_offset})
    _write_index(result.index, entries, result.skipped)
    atomic_write_bytes(result.test_set, SHIM_SOURCE.encode())
    for name in sorted((earlier or set()) - {path.name for path in result.written}):
        (out / name).unlink(missing_ok=True)
    return result


def _write_index(path: Path, entries: list[dict[str, Any]], skipped: dict[str, str]) -> None:
    """``index.json``: the exported instances' entries and the instances left out."""
    index = {"format": "qpsolvers", "instances": entries, "skipped": skipped}
    atomic_write_bytes(path, (json.dumps(index, indent=2, sort_keys=True) + "\n").encode())
