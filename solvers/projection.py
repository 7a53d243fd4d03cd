"""C3+'s closed-form projection onto complementarity: the derivation (the one definition is
:func:`c3bench.solvers.admm.projection.make_c3plus_pairs`, re-exported here; the registry
backend ``c3plus_closed_form`` is :mod:`c3bench.solvers.backends.c3plus_closed_form`).

For one pair, with weights ``w_lam, w_eta >= 0`` and a point ``(a, b) = (v_lam, v_eta)``:

    minimise   w_lam (lam - a)^2 + w_eta (eta - b)^2
    subject to lam >= 0,  eta >= 0,  lam * eta = 0.

The feasible set is the union of the two half-axes ``{eta = 0, lam >= 0}`` and
``{lam = 0, eta >= 0}``. On the first the best point is ``(max(a, 0), 0)`` with cost
``w_lam min(a, 0)^2 + w_eta b^2``; on the second ``(0, max(b, 0))`` with cost
``w_lam a^2 + w_eta min(b, 0)^2``. Since ``t^2 - min(t, 0)^2 = max(t, 0)^2``,

    cost(keep eta) - cost(keep lam) = w_lam max(a, 0)^2 - w_eta max(b, 0)^2,

so the optimum keeps ``lam`` iff ``sqrt(w_lam) max(a, 0) >= sqrt(w_eta) max(b, 0)``, and then
``(lam, eta) = (max(a, 0), 0)``; otherwise ``(lam, eta) = (0, max(b, 0))``. Ties (equal
weighted positive parts, both branches optimal) deterministically keep ``lam``. When both
``a, b <= 0`` the answer is ``(0, 0)`` either way.

C3+'s projection ``min ||delta - v||^2_U`` with diagonal ``U`` and no coupling between
``eta`` and ``(x, lam, u)`` is separable: ``x = v_x``, ``u = v_u``, and every pair takes the
closed form above (Bui et al. 2025).

References
----------
W. Aydinoglu and M. Posa, "Real-time multi-contact model predictive control via ADMM",
IEEE International Conference on Robotics and Automation (ICRA), 2022 (C3).

Bui et al., 2025: C3+, the separable variant with the slack ``eta`` (the method of the
reference study c3bench reproduces).
"""

from __future__ import annotations

from c3bench.solvers.admm.projection import c3plus_projection

__all__ = ["c3plus_projection"]
