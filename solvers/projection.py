"""C3+'s closed-form projection onto complementarity (the maths; the registry backend
``c3plus_closed_form`` is :mod:`c3bench.solvers.backends.c3plus_closed_form`).

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

import numpy as np


def c3plus_projection(v_lam: np.ndarray, v_eta: np.ndarray, w_lam: np.ndarray | float,
                      w_eta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Project every pair ``(v_lam_i, v_eta_i)`` onto ``{lam, eta >= 0, lam eta = 0}``.

    The norm is ``w_lam (lam - v_lam)^2 + w_eta (eta - v_eta)^2`` per pair; the member with
    the larger ``sqrt(w) max(v, 0)`` is kept (clipped at 0), the other set to 0; ties keep
    ``lam`` (see the module docstring for the derivation).

    Parameters
    ----------
    v_lam, v_eta
        Points to project (same shape, any number of dimensions).
    w_lam, w_eta
        Non-negative weights, broadcastable to ``v_lam``.

    Returns
    -------
    lam, eta
        The projection, arrays of ``v_lam``'s shape, in the inputs' floating type
        (``float32`` stays ``float32``; integers become ``float64``).
    """
    dtype = np.result_type(np.asarray(v_lam), np.asarray(v_eta), np.float32)
    a = np.asarray(v_lam, dtype=dtype)
    b = np.asarray(v_eta, dtype=dtype)
    if a.shape != b.shape:
        raise ValueError(f"v_lam and v_eta must have the same shape, got {a.shape} and "
                         f"{b.shape}")
    wl = np.broadcast_to(np.asarray(w_lam, dtype=dtype), a.shape)
    we = np.broadcast_to(np.asarray(w_eta, dtype=dtype), a.shape)
    if np.any(wl < 0) or np.any(we < 0):
        raise ValueError("weights must be >= 0")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))
            and np.all(np.isfinite(wl)) and np.all(np.isfinite(we))):
        raise ValueError("points and weights must be finite")
    zero = dtype.type(0)
    a_plus = np.maximum(a, zero)
    b_plus = np.maximum(b, zero)
    keep_lam = np.sqrt(wl) * a_plus >= np.sqrt(we) * b_plus
    lam = np.where(keep_lam, a_plus, zero)
    eta = np.where(keep_lam, zero, b_plus)
    return lam, eta
