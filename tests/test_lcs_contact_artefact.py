"""Anitescu's friction-cone artefact, measured (issue 11 item 1): a loaded sliding contact
separates at ``mu |v_t'|`` under Anitescu's relaxation and stays closed under
Stewart-Trinkle; both match the closed-form step of a sliding point mass."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from c3bench.bench.contact_artefact import measure_artefact, plot_artefact, separation_slope

SPEEDS = np.array([0.0, 0.3, 0.9, 1.5, 2.5])


def test_anitescu_separates_at_mu_times_tangential_speed() -> None:
    m = measure_artefact(SPEEDS, press=10.0)
    decel = m.dt * m.mu * m.press / m.mass  # Coulomb's speed loss in one step: 0.8 m/s
    sliding = decel < SPEEDS
    assert sliding.sum() == 3 and (~sliding).sum() == 2
    # Anitescu: v_n' = mu |v_t'|, so the gap after the step is dt mu |v_t'| ...
    np.testing.assert_allclose(m.normal["anitescu"], m.mu * m.tangential["anitescu"],
                               atol=1e-9)
    np.testing.assert_allclose(m.gap["anitescu"], m.dt * m.mu * m.tangential["anitescu"],
                               atol=1e-9)
    # ... with the sliding speed of the closed form (v_t - dt mu F / m) / (1 + mu^2)
    expected = np.where(sliding, (SPEEDS - decel) / (1 + m.mu**2), 0.0)
    np.testing.assert_allclose(m.tangential["anitescu"], expected, atol=1e-9)
    assert m.gap["anitescu"][-1] > 0.02  # 2.5 m/s: the contact opens by centimetres
    # Stewart-Trinkle: the contact stays closed and slides as Coulomb says
    np.testing.assert_allclose(m.gap["stewart_trinkle"], 0.0, atol=1e-9)
    np.testing.assert_allclose(m.normal["stewart_trinkle"], 0.0, atol=1e-9)
    np.testing.assert_allclose(m.tangential["stewart_trinkle"],
                               np.maximum(SPEEDS - decel, 0.0), atol=1e-9)
    assert abs(separation_slope(m, "anitescu") - m.mu) < 1e-9
    assert abs(separation_slope(m, "stewart_trinkle")) < 1e-9


def test_artefact_figure_is_written(tmp_path: Path) -> None:
    path = plot_artefact(measure_artefact(SPEEDS[:3]), tmp_path / "artefact.png")
    assert path.stat().st_size > 10_000
