"""C3+ against an independent implementation written from the papers' description (dense KKT
solve of the equality-constrained QP step, the pairwise closed-form projection in ``U``, the
scaled dual update, the geometric schedule on ``lam`` / ``eta`` with the dual rescaled, the
warm start shifting ``delta`` and restarting ``w`` at zero), closed loop on the point mass
between two soft walls (``problems/toy_lcs.py``). Nothing of the controller's code is used by
the independent one; the two must produce the same closed loop.

References: Aydinoglu & Posa, ICRA 2022 (C3); Bui et al., arXiv:2510.19974, 2025 (C3+);
Boyd et al. 2011, section 3.1.1 (scaled dual).
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.lcs import LCS
from c3bench.problems.mpc import MPC
from c3bench.problems.toy_lcs import point_mass_lcs, point_mass_mpc
from c3bench.solvers.admm.controller import C3Controller
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.lcs_simulation import simulate

U = {"x": 1000.0, "lam": 1.0, "u": 1.0, "eta": 1.0}
RHO0 = {"x": 1.0, "lam": 50.0, "u": 0.1, "eta": 50.0}
FACTOR, ITERATIONS, STEPS = 2.0, 10, 30


class IndependentC3Plus:
    """C3+ from the papers, in plain numpy (module docstring)."""

    def __init__(self, lcs: LCS, mpc: MPC) -> None:
        self.lcs, self.mpc = lcs, mpc
        self.nx, self.nl, self.nu = lcs.nx, lcs.nlam, lcs.nu
        self.ns = self.nx + 2 * self.nl + self.nu  # (x, lam, u, eta) per step
        self.delta: np.ndarray | None = None

    def weights(self, rho: dict[str, float]) -> np.ndarray:
        nx, nl, nu = self.nx, self.nl, self.nu
        return np.concatenate([np.full(nx, rho["x"]), np.full(nl, rho["lam"]),
                               np.full(nu, rho["u"]), np.full(nl, rho["eta"])])

    def qp_step(self, x0: np.ndarray, delta: np.ndarray, w: np.ndarray,
                rho: dict[str, float]) -> np.ndarray:
        lcs, mpc, T, ns = self.lcs, self.mpc, self.mpc.horizon, self.ns
        nx, nl, nu = self.nx, self.nl, self.nu
        n = T * ns + nx
        P, q, G = np.zeros((n, n)), np.zeros(n), self.weights(rho)
        rows, rhs = [], []
        for k in range(T + 1):
            o = k * ns
            cost = mpc.Q if k < T else mpc.Q_f
            P[o:o + nx, o:o + nx] += 2 * cost
            q[o:o + nx] -= 2 * cost @ mpc.x_target
            if k == T:
                break
            u = slice(o + nx + nl, o + nx + nl + nu)
            P[u, u] += 2 * mpc.R
            P[o:o + ns, o:o + ns] += 2 * np.diag(G)
            q[o:o + ns] -= 2 * G * (delta[k] - w[k])
            dynamics = np.zeros((nx, n))  # x_{k+1} = A x + D lam + B u + d
            dynamics[:, o + ns:o + ns + nx] = np.eye(nx)
            dynamics[:, o:o + nx] = -lcs.A
            dynamics[:, o + nx:o + nx + nl] = -lcs.D
            dynamics[:, u] = -lcs.B
            gap = np.zeros((nl, n))  # eta = E x + F lam + H u + c
            gap[:, o + nx + nl + nu:o + ns] = np.eye(nl)
            gap[:, o:o + nx] = -lcs.E
            gap[:, o + nx:o + nx + nl] = -lcs.F
            gap[:, u] = -lcs.H
            rows += [dynamics, gap]
            rhs += [lcs.d, lcs.c]
        start = np.zeros((nx, n))
        start[:, :nx] = np.eye(nx)
        A = np.vstack([start, *rows])
        b = np.concatenate([x0, *rhs])
        kkt = np.block([[P, A.T], [A, np.zeros((len(b), len(b)))]])
        z = np.linalg.solve(kkt, np.concatenate([-q, b]))[:T * ns]
        return z.reshape(T, ns)

    def project(self, v: np.ndarray) -> np.ndarray:
        """Each pair: ``(lam+, 0)`` or ``(0, eta+)``, whichever is nearer in ``U``."""
        out = v.copy()
        lam0, eta0 = self.nx, self.nx + self.nl + self.nu
        for k in range(v.shape[0]):
            for i in range(self.nl):
                lam, eta = v[k, lam0 + i], v[k, eta0 + i]
                keep_lam = U["eta"] * eta**2 + U["lam"] * min(lam, 0.0)**2
                keep_eta = U["lam"] * lam**2 + U["eta"] * min(eta, 0.0)**2
                out[k, lam0 + i] = max(lam, 0.0) if keep_lam <= keep_eta else 0.0
                out[k, eta0 + i] = 0.0 if keep_lam <= keep_eta else max(eta, 0.0)
        return out

    def __call__(self, x: np.ndarray) -> np.ndarray:
        T = self.mpc.horizon
        if self.delta is None:
            delta = np.zeros((T, self.ns))
            delta[:, :self.nx] = x
        else:
            delta = np.vstack([self.delta[1:], self.delta[-1:]])
        w, rho = np.zeros((T, self.ns)), dict(RHO0)
        for i in range(ITERATIONS):
            z = self.qp_step(x, delta, w, rho)
            delta = self.project(z + w)
            w = w + z - delta
            if i + 1 < ITERATIONS:
                new = {**rho, "lam": rho["lam"] * FACTOR, "eta": rho["eta"] * FACTOR}
                w = w * self.weights(rho) / self.weights(new)
                rho = new
        self.delta = delta
        u = delta[0, self.nx + self.nl:self.nx + self.nl + self.nu]
        return np.clip(u, -self.mpc.force_limit, self.mpc.force_limit)


def test_c3plus_closed_loop_equals_an_independent_implementation() -> None:
    lcs = point_mass_lcs(0.05, 1.0, 50.0, 0.5)
    mpc = point_mass_mpc(0.7, horizon=4, dt=0.05, q_position=10.0, r_input=0.01)
    ours = C3Controller(C3Options(variant="c3plus", projection_weights=U, qp_backend="clarabel",
                                  rho0=dict(RHO0), rho_factor=FACTOR,
                                  admm_iterations=ITERATIONS))
    mine = simulate(lcs, np.zeros(2), lambda x: ours.step(lcs, mpc, x).u, STEPS)
    theirs = simulate(lcs, np.zeros(2), IndependentC3Plus(lcs, mpc), STEPS)
    assert np.max(np.abs(mine.forces[:, 1])) > 0.05  # the loop reached the wall and pressed
    np.testing.assert_allclose(mine.states, theirs.states, rtol=0, atol=1e-8)
    np.testing.assert_allclose(mine.inputs, theirs.inputs, rtol=0, atol=1e-6)
