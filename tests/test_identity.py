"""Instance identity across machines (problems/identity.py, bench/runner.identify_instances).

* Arrays perturbed by 1e-13 relative (another machine's last-bit noise), including values
  placed exactly on a rounding boundary so that plain rounding would flip: same identity,
  the stored cells stay fresh.
* A matrix changed by 1e-6 relative, a changed seed in the metadata, a changed generator
  config in the manifest: a new identity, the cells are stale.
* Regenerating on one machine is byte-identical and gives the same identity.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from c3bench.bench import store
from c3bench.bench.runner import identify_instances
from c3bench.problems.identity import (
    GRID_BITS,
    GridChoice,
    byte_hash,
    fingerprint,
    identify,
    rounded,
)
from c3bench.problems.instance import MANIFEST, Problem, read_instances, save_problem

MANIFEST_TABLE = {"config": {"mpc": {"horizon": 7}}, "suite": {"name": "t", "seed": 0,
                                                               "instances_from": "/here"}}


def boundary_problem(seed: int = 0) -> Problem:
    """A QP whose arrays span magnitudes, with ``q`` values exactly on rounding boundaries
    (half a grid unit: where plain rounding flips under any noise)."""
    rng = np.random.default_rng(seed)
    n = 12
    M = rng.standard_normal((n, n))
    q = rng.standard_normal(n) * 1e3
    grid = np.ldexp(1.0, int(np.frexp(np.max(np.abs(q)))[1]) - GRID_BITS)
    q[:4] = (np.round(q[:4] / grid) + 0.5) * grid  # on the boundary of round()
    return Problem(name="qp-boundary", family="qp", P=M @ M.T + np.eye(n) * 1e-6, q=q,
                   A=rng.standard_normal((3, n)), b=rng.standard_normal(3),
                   G=rng.standard_normal((5, n)), h=rng.uniform(1e-9, 1.0, 5),
                   lb=np.full(n, -1.0), ub=np.full(n, np.inf), objective_offset=123.456,
                   meta={"seed": seed, "scene": "none"})


def perturbed(problem: Problem, relative: float, seed: int = 1) -> Problem:
    """Every float array and the offset times ``1 +- relative`` entrywise (random signs)."""
    rng = np.random.default_rng(seed)
    changes: dict[str, object] = {}
    for name in ("P", "q", "A", "b", "G", "h", "lb", "ub"):
        value = getattr(problem, name)
        noise = relative * rng.choice([-1.0, 1.0], size=value.shape)
        if name == "P":  # keep it symmetric
            noise = np.triu(noise) + np.triu(noise, 1).T
        changes[name] = np.where(np.isfinite(value), value * (1.0 + noise), value)
    changes["objective_offset"] = problem.objective_offset * (1.0 + relative)
    return Problem(**{**problem.__dict__, **changes})


def _write(problem: Problem, directory: Path, manifest: dict[str, object]) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / MANIFEST).write_text(json.dumps(manifest))
    return save_problem(problem, directory)


def test_last_bit_noise_keeps_the_identity(tmp_path: Path) -> None:
    problem = boundary_problem()
    path = _write(problem, tmp_path / "a", MANIFEST_TABLE)
    first = identify(path, None, MANIFEST_TABLE)
    noisy = _write(perturbed(problem, 1e-13), tmp_path / "b",
                   {**MANIFEST_TABLE, "suite": {**MANIFEST_TABLE["suite"],
                                                "instances_from": "/elsewhere"}})
    assert byte_hash(noisy) != first.id  # the bytes differ ...
    assert identify(noisy, first, MANIFEST_TABLE) == first  # ... the instance does not
    # the boundary values really flip under plain rounding: the guard is what keeps it
    plain = GridChoice(first.choices["q"].exponent)
    assert not np.array_equal(rounded(problem.q, plain),
                              rounded(perturbed(problem, 1e-13).q, plain))
    assert first.choices["q"].mask(problem.q.size)[:4].all()


def test_the_folder_an_import_read_is_not_part_of_the_identity(tmp_path: Path) -> None:
    """``problems import`` records the folder it read (``imported_from``, a local path):
    re-importing from another folder, or with another file changed, keeps the identity."""
    problem = boundary_problem()
    imported = {"suite": {"name": "mine", "imported_from": "/home/me/qps"}}
    first = identify(_write(problem, tmp_path / "a", imported), None, imported)
    moved = {"suite": {"name": "mine", "imported_from": "../elsewhere"}}
    assert identify(_write(problem, tmp_path / "b", moved), first, moved) == first
    renamed = {"suite": {"name": "yours", "imported_from": "/home/me/qps"}}
    assert identify(_write(problem, tmp_path / "c", renamed), first, renamed) != first


def test_real_changes_make_a_new_identity(tmp_path: Path) -> None:
    problem = boundary_problem()
    first = identify(_write(problem, tmp_path / "a", MANIFEST_TABLE), None, MANIFEST_TABLE)
    scaled = Problem(**{**problem.__dict__, "P": problem.P * (1.0 + 1e-6)})
    one_entry = problem.G.copy()
    one_entry[2, 3] *= 1.0 + 1e-6 * np.max(np.abs(problem.G)) / abs(one_entry[2, 3])
    changed = [
        (scaled, MANIFEST_TABLE),
        (Problem(**{**problem.__dict__, "G": one_entry}), MANIFEST_TABLE),
        (Problem(**{**problem.__dict__, "meta": {**problem.meta, "seed": 1}}),
         MANIFEST_TABLE),
        (problem, {**MANIFEST_TABLE, "config": {"mpc": {"horizon": 8}}}),
    ]
    for index, (variant, manifest) in enumerate(changed):
        path = _write(variant, tmp_path / f"c{index}", manifest)
        again = identify(path, first, manifest)
        assert again != first and again.id != first.id, index


def test_regeneration_on_one_machine_is_byte_identical(tmp_path: Path) -> None:
    problem = boundary_problem()
    one = _write(problem, tmp_path / "a", MANIFEST_TABLE)
    two = _write(boundary_problem(), tmp_path / "b", MANIFEST_TABLE)
    assert one.read_bytes() == two.read_bytes()
    assert one.with_suffix(".npz").read_bytes() == two.with_suffix(".npz").read_bytes()
    identity = identify(one, None, MANIFEST_TABLE)
    assert identify(two, None, MANIFEST_TABLE) == identity


def test_fingerprint_depends_on_every_array() -> None:
    arrays = {"P": np.eye(3), "q": np.ones(3), "pairs": np.array([[0, 1]])}
    choices = {k: GridChoice.of(v) for k, v in arrays.items() if v.dtype.kind == "f"}
    base = fingerprint(arrays, choices)
    assert fingerprint({**arrays, "pairs": np.array([[0, 2]])}, choices) != base
    assert fingerprint({**arrays, "q": np.ones(3) * (1 + 1e-8)}, choices) != base
    assert fingerprint({**arrays, "q": np.ones(3) * (1 + 1e-14)}, choices) == base


def test_runner_keeps_cells_of_a_suite_regenerated_elsewhere(tmp_path: Path) -> None:
    """identify_instances: the ids of a regenerated (noisy) suite are the recorded ones,
    those of a changed instance are new."""
    paths = store.SuitePaths.of(tmp_path, "suite")
    problem = boundary_problem()
    _write(problem, paths.instances, MANIFEST_TABLE)
    first = identify_instances(paths, read_instances(paths.instances))
    assert paths.identities.is_file()
    _write(perturbed(problem, 1e-13), paths.instances, MANIFEST_TABLE)
    assert identify_instances(paths, read_instances(paths.instances)) == first
    _write(perturbed(problem, 1e-6), paths.instances, MANIFEST_TABLE)
    assert identify_instances(paths, read_instances(paths.instances)) != first
