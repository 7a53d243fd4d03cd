"""``--contact-model`` of the closed loop (issue 11 item 1): checked, recorded, and a
Stewart-Trinkle controller runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench.cli_closed_loop import contact_model_option
from c3bench.bench.closed_loop import (
    ContactModelOption,
    ControllerSpec,
    run_closed_loop,
    run_summary,
    write_run,
)
from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import build_scene


def test_contact_model_option_is_checked() -> None:
    assert ControllerSpec().contact_model == "anitescu"
    spec = ControllerSpec(contact_model="stewart_trinkle")  # the LCS spelling is accepted
    assert spec.contact_model == ContactModelOption.STEWART_TRINKLE
    assert spec.lcs_contact_model == "stewart_trinkle"
    assert spec.label().endswith("-st") and not ControllerSpec().label().endswith("-st")
    with pytest.raises(InputError, match=r"--contact-model must be one of anitescu, "
                                         r"stewart-trinkle, got 'coulomb'"):
        ControllerSpec(contact_model="coulomb")

    class Args:
        contact_model = "stewart-trinkle"

    assert contact_model_option(Args()) == "stewart-trinkle"  # type: ignore[arg-type]
    assert contact_model_option(object()) == "anitescu"  # type: ignore[arg-type]


@pytest.mark.parametrize("controller", ["c3plus-fast", "c3plus"])
def test_stewart_trinkle_controller_runs_and_is_recorded(controller: str,
                                                         tmp_path: Path) -> None:
    config = load_config()
    spec = ControllerSpec(controller=controller, contact_model="stewart-trinkle",
                          qp_time_limit=None)
    trajectory, records, outcome = run_closed_loop(spec, config, duration=0.15)
    assert len(records) == 3 and all(r.ok for r in records)
    assert np.all(np.isfinite(trajectory.states))
    scene = build_scene(config=config)
    assert records[0].plan_next is not None and records[0].plan_next.shape == (scene.nx,)
    # the controller's LCS: gamma, lam_n per contact and lam_t per direction, 4 x (1 + 1 + 2)
    lcs = linearize(scene, trajectory.states[0], np.zeros(2), config.mpc.dt,
                    spec.lcs_contact_model)
    assert lcs.nlam == 16 and lcs.contact_model == "stewart_trinkle"
    out = write_run(tmp_path / spec.label(), trajectory, records, scene,
                    run_summary(spec, trajectory, outcome))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["contact_model"] == "stewart-trinkle"
    assert summary["spec"]["contact_model"] == "stewart-trinkle"
