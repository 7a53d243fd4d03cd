"""Suites with weight: several pushes, states chosen for a recorded reason, both QP variants."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench.cli import main
from c3bench.problems.capture import SUITES, SuiteSpec
from c3bench.problems.config import load_config
from c3bench.problems.instance import load_instances
from c3bench.problems.names import QP_VARIANTS, Family, QPVariant
from c3bench.problems.suites import (
    CONTACT_BAND,
    CONTACT_CHANGE,
    PushRecord,
    choose_states,
    contact_changes,
    generate_suite,
    scripted_push,
)

CONFIG = load_config()


def _record(touching: list[list[bool]], distance: list[float]) -> PushRecord:
    steps = len(distance)
    return PushRecord(np.zeros((steps + 1, 2)), np.zeros((steps, 1)), np.array(distance), 0.05,
                      np.array(touching))


def test_contact_changes_and_reasons() -> None:
    touching = [[True, False]] * 3 + [[True, True]] * 3 + [[False, True]] * 4
    distance = [0.1, 0.1, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.3]
    record = _record(touching, distance)
    np.testing.assert_array_equal(contact_changes(record), [3, 6])
    chosen = choose_states(record, 4, 0.02, n_changes=1)
    assert len(chosen) == 4 and [k for k, _ in chosen] == sorted(k for k, _ in chosen)
    reasons = dict(chosen)
    assert sum(r == CONTACT_CHANGE for r in reasons.values()) == 1
    assert set(reasons) - {k for k, r in reasons.items() if r == CONTACT_CHANGE} \
        <= set(range(2, 9))  # the rest in the contact band
    assert all(r in (CONTACT_BAND, CONTACT_CHANGE) for r in reasons.values())
    assert choose_states(record, 2, 0.02, n_changes=5) == [(3, CONTACT_CHANGE),
                                                           (6, CONTACT_CHANGE)]


def test_packaged_suites_have_weight() -> None:
    quick, default = SUITES["quick"], SUITES["default"]
    assert quick.qp_variants == QP_VARIANTS and QP_VARIANTS[0] == QPVariant.BOUNDED
    assert len(quick.trajectories) >= 2 and quick.n_states * len(quick.trajectories) >= 6
    assert len(default.trajectories) >= 5 and default.n_states * len(default.trajectories) >= 40
    assert max(default.admm_iterations) == 9 and default.contact_change_states > 0
    starts = {t.ball_start for t in default.trajectories}
    assert len(starts) == len(default.trajectories)
    # the quick suite's rotation still reaches the last ADMM iteration
    assert {i for j in range(6) for i in quick.iterations_at(j)} == set(quick.admm_iterations)


def test_default_suite_states_are_distinct_and_include_contact_changes() -> None:
    spec = SUITES["default"]
    reasons = []
    for trajectory in spec.trajectories:
        record = scripted_push(CONFIG, spec.duration, spec.variant, trajectory.ball_start,
                               trajectory.push_height)
        chosen = choose_states(record, spec.n_states, spec.contact_band,
                               spec.contact_change_states)
        assert len(chosen) == spec.n_states
        reasons += [r for _, r in chosen]
    assert len(reasons) >= 40
    assert reasons.count(CONTACT_CHANGE) >= len(spec.trajectories)


@pytest.fixture(scope="module")
def quick_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("quick_suite")
    generate_suite("quick", out, progress=False)
    return out


def test_quick_suite_counts_and_manifest(quick_dir: Path) -> None:
    manifest = json.loads((quick_dir / "manifest.json").read_text())
    states = manifest["states"]
    assert len(states) == 6 and len({s["trajectory"] for s in states}) == 2
    assert {tuple(s["ball_start"]) for s in states} == {(-0.30, 0.22), (-0.40, 0.12)}
    for entry in states:
        assert entry["reason"] in (CONTACT_BAND, CONTACT_CHANGE)
        assert entry["time"] == pytest.approx(entry["state_index"] * CONFIG.mpc.dt)
        assert entry["tag"] == f"s{entry['state_index']:03d}t{entry['trajectory']}"
    assert manifest["counts_by_variant"] == {  # two consecutive QP steps per state
        "c3_qp/bounded": 12, "c3_qp/equality": 12, "c3plus_qp/bounded": 12,
        "c3plus_qp/equality": 12, "lcp": 6, "mpcc/bounded": 1, "projection/c3": 12,
        "projection/c3plus": 12}
    qps = load_instances(quick_dir, families=(Family.C3PLUS_QP, Family.C3_QP))
    for problem in qps:
        assert problem.meta["variant"] in QP_VARIANTS
        assert problem.meta["state_reason"] in (CONTACT_BAND, CONTACT_CHANGE)
        assert (problem.n_bounded > 0) == (problem.meta["variant"] == QPVariant.BOUNDED)
    iterations = sorted({p.meta["admm_iteration"] for p in qps})
    assert iterations == [0, 3, 6, 9]


def test_generation_is_byte_identical(quick_dir: Path, tmp_path: Path) -> None:
    generate_suite("quick", tmp_path, progress=False)
    for path in sorted(quick_dir.rglob("*")):
        if path.is_file():
            assert path.read_bytes() == (tmp_path / path.relative_to(quick_dir)).read_bytes()


def test_list_shows_family_and_variant(quick_dir: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["problems", "list", str(quick_dir)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["family", "variant", "count"]
    rows = {tuple(line.split()[:2]): line.split() for line in lines[1:]}
    assert rows[("c3plus_qp", "bounded")][2] == "12"
    assert rows[("c3plus_qp", "bounded")][6] == "28"  # bounded variables: T (nu + 2)
    assert rows[("c3plus_qp", "equality")][6] == "0"


def test_suite_spec_rejects_bad_fields() -> None:
    with pytest.raises(ValueError, match="qp_variants"):
        SuiteSpec("x", 1, (0,), (0,), qp_variants=("boxed",))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="iterations_per_state"):
        SuiteSpec("x", 1, (0,), (0,), iterations_per_state=-1)


def test_an_out_of_date_stored_suite_is_regenerated(quick_dir: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A results folder holding instances of an older generator (or of another definition of
    the suite) is regenerated before a run; an up-to-date one is read as it is."""
    import shutil

    from c3bench.bench import store
    from c3bench.bench.runner import ensure_instances
    from c3bench.problems.suites import GENERATOR_VERSION, out_of_date

    manifest = json.loads((quick_dir / "manifest.json").read_text())
    assert manifest["generator_version"] == GENERATOR_VERSION
    assert out_of_date(SUITES["quick"], manifest) == ""
    assert "definition" in out_of_date(SUITES["default"], {**manifest, "suite": manifest["suite"]})
    paths = store.SuitePaths.of(tmp_path, "quick")
    shutil.copytree(quick_dir, paths.instances)
    stamp = (paths.instances / "manifest.json").stat().st_mtime_ns
    ensure_instances("quick", paths, progress=False)
    assert (paths.instances / "manifest.json").stat().st_mtime_ns == stamp  # up to date: kept
    old = {**manifest, "generator_version": 1}
    (paths.instances / "manifest.json").write_text(json.dumps(old))
    (paths.instances / "lcp" / "stale-leftover.json").write_text("{}")
    assert "version 1" in out_of_date(SUITES["quick"], old)
    instances = ensure_instances("quick", paths, progress=False)
    assert "regenerating the quick instances" in capsys.readouterr().err
    assert json.loads((paths.instances / "manifest.json").read_text()) == manifest
    assert not (paths.instances / "lcp" / "stale-leftover.json").exists()
    assert len(instances.problems) == sum(manifest["counts"].values())
