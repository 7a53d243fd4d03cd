"""Compiled per-sample half of the batched LCS build (:mod:`c3bench.problems.linearize_batch`).

:class:`c3bench.problems.linearize_batch.BatchLinearizer` reads everything that needs MuJoCo
once per control step (smooth dynamics of the reference model, mass matrix, Jacobians, poses)
and then works out each model sample's LCS with numpy over a leading sample axis. That numpy
half is about 60 small array calls whose Python overhead, not their arithmetic, is most of the
LCS build (about 0.35 of 0.57 ms at 16 samples). :func:`sample_lcs` does the same arithmetic,
sample by sample, in one compiled call:

* ``M_j = M_ref + (I_j - I_ref) J_r^T J_r``, ``M_j^-1`` (LU, symmetrised), ``T_j = M_j^-1 M_ref``,
  ``J_*^j = T_j J_*^ref``, ``a^j = T_j a^ref``, ``d_v^j = a^j - J_q^j q_0 - J_v^j v_0 - J_u^j u``;
* the contact geometry of the module docstring of :mod:`c3bench.problems.linearize_batch`
  (bottom corners, ball-table, ball-cube in closed form with the nearest face when the ball's
  centre is inside the box), point Jacobians ``J_p(x) = J_p0 + J_r x (x - p_0)``;
* the Anitescu LCS of :func:`c3bench.problems.lcs.assemble_lcs` (formulas in
  :mod:`c3bench.problems.lcs`):
  ``A = [[I + dt^2 N J_q, dt N + dt^2 N J_v], [dt J_q, I + dt J_v]]``,
  ``B = [dt^2 N J_u; dt J_u]``, ``d = [dt^2 N d_v; dt d_v]``,
  ``D = [dt^2 N M^-1 J_c^T; dt M^-1 J_c^T]``,
  ``E = [dt J_c J_q + E_t^T J_n N^+ / dt, J_c + dt J_c J_v]``, ``F = dt J_c M^-1 J_c^T``
  (symmetrised), ``H = dt J_c J_u``, ``c = E_t^T phi / dt + dt J_c d_v - E_t^T J_n N^+ q_0 /
  dt`` with ``J_c = E_t^T J_n + mu J_t``.

The sums run in a different order from numpy's (BLAS) products, so the LCS agrees with the
numpy build to rounding (tested to 1e-12 relative), not bit for bit. Stewart-Trinkle and
the spatial scene stay on the numpy path. Pure numba: no MuJoCo here.

References: the LCS of a time-stepping contact model (Anitescu, "Optimization-based simulation
of nonsmooth rigid multibody dynamics", Math. Program. 105, 2006); rigid-body point velocity
``v_x = v_0 + omega x (x - p_0)`` (Featherstone, *Rigid Body Dynamics Algorithms*, 2008,
section 2.2).
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.jit import jit

__all__ = ["sample_lcs"]


@jit
def _matmul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out = a @ b`` (2-d), sums in index order."""
    for i in range(a.shape[0]):
        for k in range(b.shape[1]):
            total = 0.0
            for m in range(a.shape[1]):
                total += a[i, m] * b[m, k]
            out[i, k] = total


@jit
def _point_jacobian(jacp: np.ndarray, jacr: np.ndarray, point: np.ndarray,
                    origin: np.ndarray, out: np.ndarray) -> None:
    """``J_p(x) = J_p0 + J_r x (x - p_0)`` column by column (3, nv)."""
    r0, r1, r2 = point[0] - origin[0], point[1] - origin[1], point[2] - origin[2]
    for v in range(jacp.shape[1]):
        a0, a1, a2 = jacr[0, v], jacr[1, v], jacr[2, v]
        out[0, v] = jacp[0, v] + (a1 * r2 - a2 * r1)
        out[1, v] = jacp[1, v] + (a2 * r0 - a0 * r2)
        out[2, v] = jacp[2, v] + (a0 * r1 - a1 * r0)


@jit
def _ball_cube(half: float, box_pos: np.ndarray, box_rot: np.ndarray, centre: np.ndarray,
               radius: float, near: np.ndarray, normal: np.ndarray) -> float:
    """Signed ball-box distance ``phi`` (what ``mj_geomDistance`` gives for a sphere and a
    box): ``near`` the box point, ``normal`` from it to the ball centre (flipped when the centre
    is inside, where the nearest face's point is used)."""
    offset, local = np.empty(3), np.empty(3)
    inside = True
    for a in range(3):
        total = 0.0
        for b in range(3):
            total += box_rot[b, a] * (centre[b] - box_pos[b])
        offset[a] = total
        inside = inside and abs(total) < half
        local[a] = min(max(total, -half), half)
    if inside:
        face, smallest = 0, half - abs(offset[0])
        for a in range(1, 3):
            if half - abs(offset[a]) < smallest:
                face, smallest = a, half - abs(offset[a])
        for a in range(3):
            local[a] = offset[a]
        local[face] = np.sign(offset[face]) * half
    for a in range(3):
        total = 0.0
        for b in range(3):
            total += local[b] * box_rot[a, b]
        near[a] = box_pos[a] + total
    gap = np.empty(3)
    for a in range(3):
        gap[a] = centre[a] - near[a]
    norm = np.sqrt(gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2])
    sign = -1.0 if inside else 1.0
    for a in range(3):
        normal[a] = sign * gap[a] / norm
    return float(sign * norm - radius)


@jit
def _contact_rows(j: int, half: float, corners_local: np.ndarray, cube_origin: np.ndarray,
                  cube_rot: np.ndarray, jacp_cube: np.ndarray, jacr_cube: np.ndarray,
                  ball_origin: np.ndarray, jacp_ball: np.ndarray, jacr_ball: np.ndarray,
                  box_pos: np.ndarray, box_rot: np.ndarray, centre: np.ndarray,
                  radius: float, table_z: float, ball_table: bool, phi: np.ndarray,
                  J_n: np.ndarray, J_t: np.ndarray) -> None:
    """Sample ``j``'s gaps ``phi`` (contacts), normal rows ``J_n`` and tangent rows ``J_t``
    (two directions per contact, ``+t`` then ``-t``), in the scene's contact order: the two
    bottom corners, the ball-table contact when present, the ball-cube contact."""
    nv = jacp_cube.shape[1]
    point, jac = np.empty(3), np.empty((3, nv))
    for k in range(2):  # bottom corners: normal +z, tangent +x
        for a in range(3):
            total = 0.0
            for b in range(3):
                total += cube_rot[a, b] * corners_local[j, k, b]
            point[a] = cube_origin[a] + total
        phi[k] = point[2] - table_z
        _point_jacobian(jacp_cube, jacr_cube, point, cube_origin, jac)
        for v in range(nv):
            J_n[k, v] = jac[2, v]
            J_t[2 * k, v], J_t[2 * k + 1, v] = jac[0, v], -jac[0, v]
    contact = 2
    if ball_table:  # the ball's lowest point
        for a in range(3):
            point[a] = centre[a]
        point[2] = centre[2] - radius
        phi[contact] = point[2] - table_z
        _point_jacobian(jacp_ball, jacr_ball, point, ball_origin, jac)
        for v in range(nv):
            J_n[contact, v] = jac[2, v]
            J_t[2 * contact, v], J_t[2 * contact + 1, v] = jac[0, v], -jac[0, v]
        contact += 1
    near, normal = np.empty(3), np.empty(3)
    phi[contact] = _ball_cube(half, box_pos, box_rot, centre, radius, near, normal)
    for a in range(3):
        point[a] = centre[a] - radius * normal[a]
    jac_cube = np.empty((3, nv))
    _point_jacobian(jacp_ball, jacr_ball, point, ball_origin, jac)
    _point_jacobian(jacp_cube, jacr_cube, near, cube_origin, jac_cube)
    t_norm = np.sqrt(normal[2] * normal[2] + normal[0] * normal[0])
    tangent = (normal[2] / t_norm, 0.0, -normal[0] / t_norm)
    for v in range(nv):
        n_row, t_row = 0.0, 0.0
        for a in range(3):
            relative = jac[a, v] - jac_cube[a, v]
            n_row += normal[a] * relative
            t_row += tangent[a] * relative
        J_n[contact, v] = n_row
        J_t[2 * contact, v], J_t[2 * contact + 1, v] = t_row, -t_row


@jit
def _spd_inverse(M: np.ndarray, out: np.ndarray) -> None:
    """``out = M^-1`` of a symmetric positive definite ``M`` through ``M = L L^T`` (Golub &
    Van Loan, *Matrix Computations*, 4th ed., algorithm 4.2.1): ``L^-1`` by forward
    substitution, then ``M^-1 = L^-T L^-1``. A mass matrix is positive definite; a pivot
    that is not gives non-finite entries, which the LCS check rejects."""
    n = M.shape[0]
    L = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1):
            total = M[a, b]
            for k in range(b):
                total -= L[a, k] * L[b, k]
            L[a, b] = np.sqrt(total) if a == b else total / L[b, b]
    inverse_L = np.zeros((n, n))  # lower triangular
    for b in range(n):
        inverse_L[b, b] = 1.0 / L[b, b]
        for a in range(b + 1, n):
            total = 0.0
            for k in range(b, a):
                total -= L[a, k] * inverse_L[k, b]
            inverse_L[a, b] = total / L[a, a]
    for a in range(n):
        for b in range(n):
            total = 0.0
            for k in range(max(a, b), n):
                total += inverse_L[k, a] * inverse_L[k, b]
            out[a, b] = total


@jit
def _smooth_sample(inertia_shift: float, M_ref: np.ndarray, jacr_cube: np.ndarray,
                   Jq_ref: np.ndarray, Jv_ref: np.ndarray, Ju_ref: np.ndarray,
                   acceleration: np.ndarray, q0: np.ndarray, v0: np.ndarray, u: np.ndarray,
                   M_inv: np.ndarray, J_q: np.ndarray, J_v: np.ndarray, J_u: np.ndarray,
                   d_v: np.ndarray) -> None:
    """One sample's ``M^-1`` and smooth dynamics (module docstring)."""
    nv = M_ref.shape[0]
    M = np.empty((nv, nv))
    for a in range(nv):
        for b in range(nv):
            rotational = 0.0
            for r in range(3):
                rotational += jacr_cube[r, a] * jacr_cube[r, b]
            M[a, b] = M_ref[a, b] + inertia_shift * rotational
    inverse = np.empty((nv, nv))
    _spd_inverse(M, inverse)
    for a in range(nv):
        for b in range(nv):
            M_inv[a, b] = 0.5 * (inverse[a, b] + inverse[b, a])
    transfer = np.empty((nv, nv))
    _matmul(M_inv, M_ref, transfer)
    _matmul(transfer, Jq_ref, J_q)
    _matmul(transfer, Jv_ref, J_v)
    _matmul(transfer, Ju_ref, J_u)
    for a in range(nv):
        total = 0.0
        for b in range(nv):
            total += transfer[a, b] * acceleration[b]
        for b in range(q0.shape[0]):
            total -= J_q[a, b] * q0[b]
        for b in range(nv):
            total -= J_v[a, b] * v0[b]
        for b in range(u.shape[0]):
            total -= J_u[a, b] * u[b]
        d_v[a] = total


@jit
def _anitescu(dt: float, q0: np.ndarray, N: np.ndarray, N_pinv: np.ndarray, J_q: np.ndarray,
              J_v: np.ndarray, J_u: np.ndarray, d_v: np.ndarray, M_inv: np.ndarray,
              phi: np.ndarray, J_n: np.ndarray, J_t: np.ndarray, E_t: np.ndarray,
              mu: np.ndarray, A: np.ndarray, B: np.ndarray, D: np.ndarray, d: np.ndarray,
              E: np.ndarray, F: np.ndarray, H: np.ndarray, c: np.ndarray) -> None:
    """One sample's Anitescu LCS (module docstring)."""
    nq, nv = N.shape
    nu = J_u.shape[1]
    nc, nlam = E_t.shape
    normal_rows, J, JnNp = np.empty((nlam, nv)), np.empty((nlam, nv)), np.empty((nlam, nq))
    NJq, NJv, NJu = np.empty((nq, nq)), np.empty((nq, nv)), np.empty((nq, nu))
    MJt, NMJt = np.empty((nv, nlam)), np.empty((nq, nlam))  # M^-1 J^T, N M^-1 J^T
    JJq, JJv, JJu = np.empty((nlam, nq)), np.empty((nlam, nv)), np.empty((nlam, nu))
    JMJt = np.empty((nlam, nlam))
    for i in range(nlam):  # E_t^T J_n, J_c = E_t^T J_n + mu J_t, E_t^T J_n N^+
        mu_row = 0.0
        for k in range(nc):
            mu_row += E_t[k, i] * mu[k]
        for v in range(nv):
            total = 0.0
            for k in range(nc):
                total += E_t[k, i] * J_n[k, v]
            normal_rows[i, v] = total
            J[i, v] = total + mu_row * J_t[i, v]
    _matmul(normal_rows, N_pinv, JnNp)
    dt2 = dt * dt
    _matmul(N, J_q, NJq)
    _matmul(N, J_v, NJv)
    _matmul(N, J_u, NJu)
    for a in range(nq):
        for b in range(nq):
            A[a, b] = (1.0 if a == b else 0.0) + dt2 * NJq[a, b]
        for b in range(nv):
            A[a, nq + b] = dt * N[a, b] + dt2 * NJv[a, b]
        for b in range(nu):
            B[a, b] = dt2 * NJu[a, b]
        total = 0.0
        for v in range(nv):
            total += N[a, v] * d_v[v]
        d[a] = dt2 * total
    for a in range(nv):
        for b in range(nq):
            A[nq + a, b] = dt * J_q[a, b]
        for b in range(nv):
            A[nq + a, nq + b] = (1.0 if a == b else 0.0) + dt * J_v[a, b]
        for b in range(nu):
            B[nq + a, b] = dt * J_u[a, b]
        d[nq + a] = dt * d_v[a]
    for a in range(nv):
        for i in range(nlam):
            total = 0.0
            for v in range(nv):
                total += M_inv[a, v] * J[i, v]
            MJt[a, i] = total
    _matmul(N, MJt, NMJt)
    for i in range(nlam):
        for a in range(nq):
            D[a, i] = dt2 * NMJt[a, i]
        for a in range(nv):
            D[nq + a, i] = dt * MJt[a, i]
    _matmul(J, J_q, JJq)
    _matmul(J, J_v, JJv)
    _matmul(J, J_u, JJu)
    _matmul(J, MJt, JMJt)
    for i in range(nlam):
        for b in range(nq):
            E[i, b] = dt * JJq[i, b] + JnNp[i, b] / dt
        for b in range(nv):
            E[i, nq + b] = J[i, b] + dt * JJv[i, b]
        for b in range(nlam):
            F[i, b] = 0.5 * (dt * JMJt[i, b] + dt * JMJt[b, i])
        for b in range(nu):
            H[i, b] = dt * JJu[i, b]
        gap, velocity, position = 0.0, 0.0, 0.0
        for k in range(nc):
            gap += phi[k] * E_t[k, i]
        for v in range(nv):
            velocity += J[i, v] * d_v[v]
        for q in range(nq):
            position += JnNp[i, q] * q0[q]
        c[i] = gap / dt + dt * velocity - position / dt


@jit
def sample_lcs(dt: float, q0: np.ndarray, v0: np.ndarray, u: np.ndarray, N: np.ndarray,
               N_pinv: np.ndarray, Jq_ref: np.ndarray, Jv_ref: np.ndarray,
               Ju_ref: np.ndarray, acceleration: np.ndarray, M_ref: np.ndarray,
               inertia_shift: np.ndarray, half: np.ndarray, corners_local: np.ndarray,
               cube_origin: np.ndarray, cube_rot: np.ndarray, jacp_cube: np.ndarray,
               jacr_cube: np.ndarray, ball_origin: np.ndarray, jacp_ball: np.ndarray,
               jacr_ball: np.ndarray, box_pos: np.ndarray, box_rot: np.ndarray,
               centre: np.ndarray, radius: float, table_z: float, ball_table: bool,
               E_t: np.ndarray, mu: np.ndarray, A: np.ndarray, B: np.ndarray, D: np.ndarray,
               d: np.ndarray, E: np.ndarray, F: np.ndarray, H: np.ndarray, c: np.ndarray,
               phi: np.ndarray) -> None:
    """Every sample's Anitescu LCS (module docstring) into the preallocated ``A`` ... ``c``
    (n, ...) and ``phi`` (n, contacts).

    Shared (from MuJoCo, once per control step): ``q0, v0, u``, ``N`` (nq, nv), ``N_pinv``,
    the reference model's smooth dynamics ``Jq_ref, Jv_ref, Ju_ref, acceleration`` and mass
    matrix ``M_ref``, poses and origin Jacobians of the cube and the ball, the cube geom's
    pose ``box_pos, box_rot``, the ball centre ``centre`` and ``radius``, ``table_z``,
    ``E_t`` (contacts, directions), ``mu`` (contacts). Per sample ``j``: ``inertia_shift[j] =
    I_j - I_ref``, ``half[j] = l_j / 2`` and the bottom corners in the cube frame
    ``corners_local[j]`` (2, 3).
    """
    n = half.shape[0]
    nq, nv = N.shape
    nu = u.shape[0]
    nc, nlam = E_t.shape
    M_inv, J_q = np.empty((nv, nv)), np.empty((nv, nq))
    J_v, J_u, d_v = np.empty((nv, nv)), np.empty((nv, nu)), np.empty(nv)
    J_n, J_t = np.empty((nc, nv)), np.empty((nlam, nv))
    for j in range(n):
        _smooth_sample(inertia_shift[j], M_ref, jacr_cube, Jq_ref, Jv_ref, Ju_ref,
                       acceleration, q0, v0, u, M_inv, J_q, J_v, J_u, d_v)
        _contact_rows(j, half[j], corners_local, cube_origin, cube_rot, jacp_cube, jacr_cube,
                      ball_origin, jacp_ball, jacr_ball, box_pos, box_rot, centre, radius,
                      table_z, ball_table, phi[j], J_n, J_t)
        _anitescu(dt, q0, N, N_pinv, J_q, J_v, J_u, d_v, M_inv, phi[j], J_n, J_t, E_t, mu,
                  A[j], B[j], D[j], d[j], E[j], F[j], H[j], c[j])
