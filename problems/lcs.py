"""Linear complementarity systems (LCS): the types, their one validator and the assembly formulas.

The LCS (docs/lcs.md) is

    x_{k+1} = A x_k + B u_k + D lam_k + d,
    0 <= lam_k  perp  E x_k + F lam_k + H u_k + c >= 0.

:class:`LCS` holds one system, :class:`LCSBatch` ``n`` systems of the same dimensions stacked
along a leading sample axis (the robust controller's model samples). Both check their arrays
with :func:`check_lcs_arrays`.

:func:`assemble_lcs` turns a linearised plant into the LCS matrices. With the smooth dynamics
``v' = M^-1 (tau - C v + B_u u)`` linearised as ``J_q q + J_v v + J_u u + d_v``, ``q' = N v``
(``N^+`` its pseudo-inverse) and semi-implicit Euler of step ``dt``:

* Anitescu (default): one force per contact ``i`` and friction direction ``j`` along
  ``n_i + mu_i t_ij``; ``J_c = E_t^T J_n + mu J_t``;
  ``A = [[I + dt^2 N J_q, dt N + dt^2 N J_v], [dt J_q, I + dt J_v]]``,
  ``B = [dt^2 N J_u; dt J_u]``, ``d = [dt^2 N d_v; dt d_v]``,
  ``D = [dt^2 N M^-1 J_c^T; dt M^-1 J_c^T]``,
  ``E = [dt J_c J_q + E_t^T J_n N^+ / dt, J_c + dt J_c J_v]``, ``F = dt J_c M^-1 J_c^T``,
  ``H = dt J_c J_u``, ``c = E_t^T phi / dt + dt J_c d_v - E_t^T J_n N^+ q_0 / dt``.
* Stewart-Trinkle: ``lam = [gamma; lam_n; lam_t]`` with the slack ``gamma`` per contact;
  rows: friction cone ``mu lam_n - E_t lam_t``, position-level gap
  ``phi + dt J_n v_{k+1}``, and maximum dissipation ``E_t^T gamma + J_t v_{k+1}``.

``E_t`` (contacts x directions) sums a contact's friction directions. The MuJoCo side (mass
matrix, smooth acceleration, contact frames) is in :mod:`c3bench.problems.linearize` and
:mod:`c3bench.problems.linearize_batch`.

Part of the plant-free core: pure numpy, imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

ContactModel = Literal["anitescu", "stewart_trinkle"]
CONTACT_MODELS: tuple[str, ...] = ("anitescu", "stewart_trinkle")
LCS_MATRICES: tuple[str, ...] = ("A", "B", "D", "d", "E", "F", "H", "c")

_UIDS = itertools.count(1)


def next_uid() -> int:
    """A process-wide unique integer: the identity of an LCS batch (factorisation caches)."""
    return next(_UIDS)


def check_dt(dt: float, name: str = "dt") -> float:
    """``dt`` as a float; ``ValueError`` naming ``name`` unless it is a finite number > 0."""
    if not (isinstance(dt, int | float | np.integer | np.floating) and math.isfinite(dt)
            and dt > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {dt!r}")
    return float(dt)


def check_lcs_arrays(owner: str, arrays: Mapping[str, Any], dt: float,
                     batched: bool = False) -> dict[str, np.ndarray]:
    """The one LCS validator: shapes, finiteness and ``dt`` of :class:`LCS` and :class:`LCSBatch`.

    Parameters
    ----------
    owner
        Name used in error messages (``"LCS"`` or ``"LCSBatch"``).
    arrays
        ``A, B, D, d, E, F, H, c`` (at least; other keys are ignored).
    dt
        Time step (s).
    batched
        ``True`` when every array carries a leading sample axis ``n >= 1``.

    Returns
    -------
    dict
        The matrices as arrays (non-floating ones converted to float64, floating ones kept in
        their precision).

    Raises
    ------
    ValueError
        Naming the offending matrix (``"LCS.F must have shape ..."``) or ``dt``.
    """
    checked: dict[str, np.ndarray] = {}
    for name in LCS_MATRICES:
        value = np.asarray(arrays[name])
        if not np.issubdtype(value.dtype, np.floating):
            value = value.astype(np.float64)
        checked[name] = value
    lead: tuple[int, ...] = ()
    A = checked["A"]
    if batched:
        if A.ndim != 3 or A.shape[0] < 1:
            raise ValueError(f"{owner}.A must have shape (n, nx, nx) with n >= 1, got "
                             f"{A.shape}")
        lead = (int(A.shape[0]),)
    axis = len(lead)
    nx = int(A.shape[axis]) if A.ndim > axis else 0
    nu = int(checked["B"].shape[-1]) if checked["B"].ndim == axis + 2 else 0
    nlam = int(checked["D"].shape[-1]) if checked["D"].ndim == axis + 2 else 0
    expected = {
        "A": (nx, nx), "B": (nx, nu), "D": (nx, nlam), "d": (nx,),
        "E": (nlam, nx), "F": (nlam, nlam), "H": (nlam, nu), "c": (nlam,),
    }
    for name, shape in expected.items():
        value = checked[name]
        if value.shape != lead + shape:
            raise ValueError(f"{owner}.{name} must have shape {lead + shape}, got "
                             f"{value.shape}")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{owner}.{name} has non-finite entries")
    check_dt(dt, f"{owner}.dt")
    return checked


@dataclass
class LCS:
    """A discrete-time LCS: ``x' = A x + B u + D lam + d``, ``0 <= lam perp E x + F lam + H u + c``.

    Attributes
    ----------
    A, B, D, d, E, F, H, c
        The LCS matrices (docs/lcs.md).
    dt
        Time step (s).
    contact_model
        ``"anitescu"`` or ``"stewart_trinkle"``.
    n_contacts, friction_directions
        Contacts and friction directions per contact.
    phi
        Signed distances of the contacts at the linearisation point (m).
    """

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    d: np.ndarray
    E: np.ndarray
    F: np.ndarray
    H: np.ndarray
    c: np.ndarray
    dt: float
    contact_model: str = "anitescu"
    n_contacts: int = 0
    friction_directions: int = 0
    phi: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.validate()

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.A.shape[0])

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.B.shape[1])

    @property
    def nlam(self) -> int:
        """Number of contact forces (complementarity pairs per step)."""
        return int(self.D.shape[1])

    def validate(self) -> None:
        """Check shapes and finiteness (:func:`check_lcs_arrays`); ``ValueError`` names the
        offending matrix."""
        for name, value in check_lcs_arrays("LCS", self.arrays(), self.dt).items():
            setattr(self, name, value)

    def next_state(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``A x + B u + D lam + d``."""
        out: np.ndarray = self.A @ x + self.B @ u + self.D @ lam + self.d
        return out

    def lcp_offset(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``E x + H u + c``: the ``q`` of the step's LCP ``0 <= lam perp F lam + q >= 0``."""
        out: np.ndarray = self.E @ x + self.H @ u + self.c
        return out

    def gap(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``E x + F lam + H u + c``."""
        out: np.ndarray = self.lcp_offset(x, u) + self.F @ lam
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        """The matrices by name, plus ``phi``."""
        out = {name: getattr(self, name) for name in LCS_MATRICES}
        out["phi"] = self.phi
        return out


@dataclass
class LCSBatch:
    """``n`` LCS with the same dimensions, stacked along a leading sample axis.

    ``x'_j = A_j x + B_j u + D_j lam + d_j``, ``0 <= lam perp E_j x + F_j lam + H_j u + c_j``.

    Attributes
    ----------
    A, B, D, d, E, F, H, c
        (n, ...) stacks of the LCS matrices of :class:`LCS`.
    dt
        Time step (s), common to all samples.
    contact_model, n_contacts, friction_directions
        As in :class:`LCS`.
    phi
        (n, contacts) signed distances.
    sides
        (n,) cube sides of the samples (``nan`` when unknown).
    uid
        Identity of this batch: arrays are made read-only at construction, so the same
        ``uid`` means the same data (used as the LCS key of factorisation caches).
    """

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    d: np.ndarray
    E: np.ndarray
    F: np.ndarray
    H: np.ndarray
    c: np.ndarray
    dt: float
    contact_model: str = "anitescu"
    n_contacts: int = 0
    friction_directions: int = 0
    phi: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    sides: np.ndarray | None = None
    uid: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        arrays = {name: getattr(self, name) for name in LCS_MATRICES}
        for name, value in check_lcs_arrays("LCSBatch", arrays, self.dt, batched=True).items():
            if value.flags.writeable:
                value.setflags(write=False)
            setattr(self, name, value)
        self.phi = np.asarray(self.phi, dtype=float)
        if self.sides is not None:
            self.sides = np.asarray(self.sides, dtype=float).reshape(self.n_samples)
        self.uid = next_uid()

    @property
    def n_samples(self) -> int:
        """Number of samples ``n``."""
        return int(self.A.shape[0])

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.A.shape[1])

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.B.shape[2])

    @property
    def nlam(self) -> int:
        """Number of contact forces per step."""
        return int(self.D.shape[2])

    def sample(self, j: int) -> LCS:
        """Sample ``j`` as an :class:`LCS` (float64 copies)."""
        arrays = {name: np.array(getattr(self, name)[j], dtype=np.float64)
                  for name in LCS_MATRICES}
        phi = self.phi[j].copy() if self.phi.ndim == 2 and self.phi.shape[0] else np.zeros(0)
        return LCS(**arrays, dt=self.dt, contact_model=self.contact_model,
                   n_contacts=self.n_contacts, friction_directions=self.friction_directions,
                   phi=phi)

    def samples(self) -> list[LCS]:
        """All samples as :class:`LCS` objects."""
        return [self.sample(j) for j in range(self.n_samples)]

    @classmethod
    def from_lcs(cls, systems: Sequence[LCS], sides: Sequence[float] | None = None
                 ) -> LCSBatch:
        """Stack LCS objects (same dimensions, dt and contact model) into a batch."""
        if len(systems) < 1:
            raise ValueError("need at least one LCS")
        first = systems[0]
        for lcs in systems[1:]:
            if (lcs.nx, lcs.nu, lcs.nlam) != (first.nx, first.nu, first.nlam):
                raise ValueError("all LCS must have the same dimensions")
            if lcs.dt != first.dt or lcs.contact_model != first.contact_model:
                raise ValueError("all LCS must have the same dt and contact model")
        arrays = {name: np.stack([getattr(lcs, name) for lcs in systems])
                  for name in LCS_MATRICES}
        phis = [np.asarray(lcs.phi, dtype=float) for lcs in systems]
        phi = np.stack(phis) if len({p.shape for p in phis}) == 1 else np.zeros((len(phis), 0))
        return cls(**arrays, dt=first.dt, contact_model=first.contact_model,
                   n_contacts=first.n_contacts, friction_directions=first.friction_directions,
                   phi=phi, sides=None if sides is None else np.asarray(sides, dtype=float))

    def repeat(self, n: int) -> LCSBatch:
        """A batch of ``n`` copies of sample 0 (for tests of identical samples)."""
        arrays = {name: np.repeat(getattr(self, name)[:1], n, axis=0) for name in LCS_MATRICES}
        sides = None if self.sides is None else np.repeat(self.sides[:1], n)
        phi = np.repeat(self.phi[:1], n, axis=0) if self.phi.ndim == 2 else self.phi
        return LCSBatch(**arrays, dt=self.dt, contact_model=self.contact_model,
                        n_contacts=self.n_contacts,
                        friction_directions=self.friction_directions, phi=phi, sides=sides)


def assemble_lcs(dt: float, q0: np.ndarray, N: np.ndarray, N_pinv: np.ndarray,
                 J_q: np.ndarray, J_v: np.ndarray, J_u: np.ndarray, d_v: np.ndarray,
                 M_inv: np.ndarray, phi: np.ndarray, J_n: np.ndarray, J_t: np.ndarray,
                 E_t: np.ndarray, mu: np.ndarray, contact_model: str
                 ) -> dict[str, np.ndarray]:
    """The LCS matrices (module docstring) for ``n`` models at once (leading axis ``n``).

    Shared: ``q0`` (nq), ``N`` (nq x nv), ``N_pinv`` (nv x nq), ``E_t`` (contacts x
    directions), ``mu`` (contacts). Per model: ``J_q`` (n, nv, nq), ``J_v`` (n, nv, nv),
    ``J_u`` (n, nv, nu), ``d_v`` (n, nv), ``M_inv`` (n, nv, nv), ``phi`` (n, contacts),
    ``J_n`` (n, contacts, nv), ``J_t`` (n, directions, nv). Returns ``A, B, D, d, E, F, H, c``
    stacked along the leading axis; :func:`c3bench.problems.linearize.linearize` calls it with
    ``n = 1`` and :mod:`c3bench.problems.linearize_batch` with one model per sampled cube side.
    """
    n, nv, nq = J_q.shape
    nu = J_u.shape[-1]
    Et = E_t
    eye_q = np.broadcast_to(np.eye(nq), (n, nq, nq))
    eye_v = np.broadcast_to(np.eye(nv), (n, nv, nv))
    A = np.concatenate([
        np.concatenate([eye_q + dt**2 * N @ J_q, dt * N + dt**2 * N @ J_v], axis=2),
        np.concatenate([dt * J_q, eye_v + dt * J_v], axis=2),
    ], axis=1)
    B = np.concatenate([dt**2 * N @ J_u, dt * J_u], axis=1)
    d = np.concatenate([dt**2 * d_v @ N.T, dt * d_v], axis=1)
    mu_rows = Et.T @ mu
    if contact_model == "anitescu":
        J = Et.T @ J_n + mu_rows[:, None] * J_t  # (n, nlam, nv)
        JnNp = Et.T @ J_n @ N_pinv
        E = np.concatenate([dt * J @ J_q + JnNp / dt, J + dt * J @ J_v], axis=2)
        F = dt * J @ M_inv @ np.swapaxes(J, -1, -2)
        F = 0.5 * (F + np.swapaxes(F, -1, -2))
        H = dt * J @ J_u
        c = (phi @ Et) / dt + dt * (J @ d_v[..., None])[..., 0] - (JnNp @ q0) / dt
    elif contact_model == "stewart_trinkle":
        nc, nd = Et.shape
        Jn, Jt = J_n, J_t
        J = np.concatenate([np.zeros((n, nc, nv)), Jn, Jt], axis=1)
        JnT, JtT = np.swapaxes(Jn, -1, -2), np.swapaxes(Jt, -1, -2)
        E = np.concatenate([
            np.zeros((n, nc, nq + nv)),
            np.concatenate([Jn @ N_pinv + dt**2 * Jn @ J_q, dt * Jn + dt**2 * Jn @ J_v], axis=2),
            np.concatenate([dt * Jt @ J_q, Jt + dt * Jt @ J_v], axis=2),
        ], axis=1)
        zeros_c = np.zeros((n, nc, nc))
        F = np.concatenate([
            np.concatenate([zeros_c, np.broadcast_to(np.diag(mu), (n, nc, nc)),
                            np.broadcast_to(-Et, (n, nc, nd))], axis=2),
            np.concatenate([zeros_c, dt**2 * Jn @ M_inv @ JnT, dt**2 * Jn @ M_inv @ JtT],
                           axis=2),
            np.concatenate([np.broadcast_to(Et.T, (n, nd, nc)), dt * Jt @ M_inv @ JnT,
                            dt * Jt @ M_inv @ JtT], axis=2),
        ], axis=1)
        H = np.concatenate([np.zeros((n, nc, nu)), dt**2 * Jn @ J_u, dt * Jt @ J_u], axis=1)
        c = np.concatenate([
            np.zeros((n, nc)),
            phi - (Jn @ N_pinv @ q0) + dt**2 * (Jn @ d_v[..., None])[..., 0],
            dt * (Jt @ d_v[..., None])[..., 0],
        ], axis=1)
    else:
        raise ValueError(f"contact_model must be one of {CONTACT_MODELS}, got "
                         f"{contact_model!r}")
    D = np.concatenate([dt**2 * N @ M_inv @ np.swapaxes(J, -1, -2),
                        dt * M_inv @ np.swapaxes(J, -1, -2)], axis=1)
    return {"A": A, "B": B, "D": D, "d": d, "E": E, "F": F, "H": H, "c": c}
