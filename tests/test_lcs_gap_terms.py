"""Each term of the LCS, tested so that removing it fails a test (issue 11, item 5).

``x' = A x + B u + D lam + d``, ``0 <= lam perp E x + F lam + H u + c >= 0`` (docs/lcs.md).

Two kinds of tests:

1. **Closed forms, term by term.** The planar scene is a rigid cube (``M = diag(m, m, m l^2 / 6)``
   about its centre) and a gravity-compensated point-mass ball; its contact geometry (corner
   heights, the ball's height, the sphere-box distance and nearest point) and the generalised
   contact directions ``G`` (one row per force direction, mapping ``v`` to the relative velocity
   of the contact points) are written out here from rigid-body kinematics, independently of
   ``problems/linearize.py``. Each term's contribution to the gap or to the next state is then
   compared with its closed form (Anitescu: ``G_c = G_n + mu G_t`` per direction; Stewart-Trinkle:
   the three row blocks), e.g. ``F lam = dt G_c M^-1 G_c^T lam``. Zeroing the term makes its
   contribution zero, which the same check rejects (``test_closed_form_checks_reject_a_zeroed_
   term``).
2. **Physics, with mutations.** The rollouts of ``test_lcs_rollouts.py`` (released tipped cube,
   launched and pushed cube, ball impact) rolled out again with one term zeroed (or scaled) in
   every relinearised LCS: each mutant fails at least one physical check (the cube sinks into the
   table, the ball goes into the cube, the cube does not fall back, no contact force exists),
   while the unmutated LCS passes the same check.

References: D. E. Stewart, J. C. Trinkle, Int. J. Numer. Meth. Eng. 39(15), 1996; M. Anitescu,
Math. Program. 105(1), 2006 (the two schemes and their Delassus operators); R. Featherstone,
"Rigid Body Dynamics Algorithms", Springer, 2008 (point Jacobians of a planar rigid body).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from test_lcs_rollouts import (
    CONFIG,
    DT,
    FINE_DT,
    GRAVITY,
    MODELS,
    Linearizer,
    ball_cube_distance,
    corner_heights,
    fall_back,
    impact,
    launched,
    launched_violations,
    pushed,
    pushed_violations,
)

from c3bench.problems.lcs import LCS, ContactModel
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import Scene, build_scene, target_state
from c3bench.solvers.lcs_simulation import SimulationFailed

SIDE = CONFIG.scene.cube_side


# --- an independent planar model ---------------------------------------------------------------
@dataclass
class PlanarContacts:
    """Contact geometry of the planar scene at one state, from rigid-body kinematics.

    Attributes
    ----------
    phi
        Signed distances (corners, ball-table, ball-cube), m.
    G_n
        (contacts, nv) normal rows: ``G_n v`` is the relative normal velocity.
    G_t
        (contacts * 2, nv) tangential rows, directions ``+t, -t`` per contact.
    mu
        Friction coefficient per contact.
    """

    phi: np.ndarray
    G_n: np.ndarray
    G_t: np.ndarray
    mu: np.ndarray


def _point_row(direction: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """Cube row of the velocity along ``direction`` (x, z) of the cube point at ``lever`` from
    its centre: ``e . (v + omega e_y x r) = e_x v_x + e_z v_z + omega (e_x r_z - e_z r_x)``."""
    return np.array([direction[0], direction[1],
                     direction[0] * lever[1] - direction[1] * lever[0]])


def planar_contacts(x: np.ndarray, l: float) -> PlanarContacts:
    """Corners-table, ball-table, ball-cube (in the LCS's order) at state ``x``."""
    s = CONFIG.scene
    h, r = l / 2, s.ball_radius
    centre, ball = x[[0, 1]], x[[3, 4]]
    c, si = math.cos(x[2]), math.sin(x[2])
    to_world = np.array([[c, si], [-si, c]])  # x' = x c + z s, z' = -x s + z c
    up, along = np.array([0.0, 1.0]), np.array([1.0, 0.0])
    rows_n, rows_t, phi = [], [], []
    for bx in (-h, h):
        lever = to_world @ np.array([bx, -h])
        phi.append(centre[1] + lever[1] - s.table_height)
        rows_n.append(np.concatenate([_point_row(up, lever), [0.0, 0.0]]))
        rows_t += [np.concatenate([_point_row(sign * along, lever), [0.0, 0.0]])
                   for sign in (1.0, -1.0)]
    phi.append(ball[1] - r - s.table_height)
    rows_n.append(np.array([0.0, 0.0, 0.0, 0.0, 1.0]))
    rows_t += [np.array([0.0, 0.0, 0.0, sign, 0.0]) for sign in (1.0, -1.0)]
    local = to_world.T @ (ball - centre)
    nearest_local = np.clip(local, -h, h)
    nearest = centre + to_world @ nearest_local
    normal = (ball - nearest) / np.linalg.norm(ball - nearest)
    tangent = np.array([normal[1], -normal[0]])  # (n_z, -n_x), the LCS's +t
    phi.append(float(ball_cube_distance(x[None, :], l)[0]))
    lever = nearest - centre
    rows_n.append(np.concatenate([-_point_row(normal, lever), normal]))
    rows_t += [np.concatenate([-_point_row(sign * tangent, lever), sign * tangent])
               for sign in (1.0, -1.0)]
    return PlanarContacts(phi=np.array(phi), G_n=np.array(rows_n), G_t=np.array(rows_t),
                          mu=np.array([s.mu_table] * 3 + [s.mu_ball]))


def mass_matrix(l: float) -> np.ndarray:
    """``diag(m_c, m_c, m_c l^2 / 6, m_b, m_b)``: cube about its centre, ball a point mass."""
    s = CONFIG.scene
    return np.diag([s.cube_mass, s.cube_mass, s.cube_mass * l * l / 6, s.ball_mass, s.ball_mass])


def force_directions(contacts: PlanarContacts, contact_model: ContactModel) -> np.ndarray:
    """``J`` with ``D = [dt^2 M^-1 J^T; dt M^-1 J^T]``: Anitescu's ``n + mu t_j`` per direction,
    Stewart-Trinkle's ``[0; G_n; G_t]`` (the slack ``gamma`` applies no force)."""
    per = 2
    if contact_model == "anitescu":
        generators: np.ndarray = np.repeat(contacts.G_n, per, axis=0) \
            + np.repeat(contacts.mu, per)[:, None] * contacts.G_t
        return generators
    return np.concatenate([np.zeros_like(contacts.G_n), contacts.G_n, contacts.G_t])


@dataclass
class Reference:
    """The LCS's terms at a linearisation point ``(x0, u0)``, from :class:`PlanarContacts`.

    ``gap(x, u, lam)`` and ``next_state(x, u, lam)`` are the closed forms that ``E x + F lam +
    H u + c`` and ``A x + B u + D lam + d`` must equal (docs/lcs.md with ``J_q = J_v = 0``: the
    planar scene's smooth acceleration ``(0, -g, 0, u / m_b)`` does not depend on ``x``).
    """

    x0: np.ndarray
    contacts: PlanarContacts
    M_inv: np.ndarray
    contact_model: ContactModel
    dt: float

    def velocity_after(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``v' = v + dt (a_smooth + M^-1 J^T lam)``, ``a_smooth = (0, -g, 0, u / m_b)``."""
        J = force_directions(self.contacts, self.contact_model)
        smooth = np.concatenate([[0.0, -GRAVITY, 0.0], u / CONFIG.scene.ball_mass])
        out: np.ndarray = x[5:] + self.dt * (smooth + self.M_inv @ J.T @ lam)
        return out

    def next_state(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """Semi-implicit Euler: ``v'`` from :meth:`velocity_after`, ``q' = q + dt v'``."""
        v = self.velocity_after(x, u, lam)
        return np.concatenate([x[:5] + self.dt * v, v])

    def gap(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """Anitescu: ``(phi + G_n dq) / dt + (G_n + mu G_t) v'`` per direction (m/s);
        Stewart-Trinkle: ``[mu lam_n - E_t lam_t; phi + G_n dq + dt G_n v'; E_t^T gamma +
        G_t v']``, ``dq = q - q0``."""
        k = self.contacts
        v = self.velocity_after(x, u, lam)
        distance = k.phi + k.G_n @ (x[:5] - self.x0[:5])
        if self.contact_model == "anitescu":
            out: np.ndarray = np.repeat(distance, 2) / self.dt \
                + force_directions(k, "anitescu") @ v
            return out
        nc = len(k.phi)
        gamma, lam_n, lam_t = lam[:nc], lam[nc:2 * nc], lam[2 * nc:]
        E_t = np.repeat(np.eye(nc), 2, axis=1)
        return np.concatenate([k.mu * lam_n - E_t @ lam_t, distance + self.dt * k.G_n @ v,
                               E_t.T @ gamma + k.G_t @ v])


def contact_rich_point(where: str = "touching") -> tuple[Scene, np.ndarray, np.ndarray]:
    """The cube tipped by 0.3 rad and moving, the ball moving: every contact has a non-trivial
    normal, lever arm and velocity.

    ``where``: ``"touching"`` (the ball on the near face at 3/4 height, ``phi = 0``),
    ``"penetrating"`` (the ball 2 mm into the face, the pivot corner 1 mm into the table) or
    ``"edge"`` (the ball 1 cm off the cube's top near edge, along the diagonal: the normal is
    neither a face normal nor vertical).
    """
    scene = build_scene(config=CONFIG)
    x0 = target_state(scene, 0.3)
    theta, h, r = x0[2], scene.l / 2, CONFIG.scene.ball_radius
    to_world = np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])
    if where == "penetrating":
        x0[[1, 4]] -= 0.001  # cube and ball 1 mm down, then the ball 2 mm into the face
        x0[[3, 4]] -= 0.002 * (to_world @ np.array([-1.0, 0.0]))
    elif where == "edge":
        edge = x0[[0, 1]] + to_world @ np.array([-h, h])
        x0[[3, 4]] = edge + (r + 0.01) * (to_world @ np.array([-1.0, 1.0]) / math.sqrt(2))
    elif where != "touching":
        raise ValueError(f"unknown point {where!r}")
    x0[5:] = [0.1, -0.05, 0.4, 0.2, -0.1]
    return scene, x0, np.array([5.0, -3.0])


POINTS = ("touching", "penetrating", "edge")


def reference_at(x0: np.ndarray, contact_model: ContactModel) -> Reference:
    """The closed-form LCS at ``x0`` (see :class:`Reference`)."""
    return Reference(x0=x0, contacts=planar_contacts(x0, SIDE),
                     M_inv=np.linalg.inv(mass_matrix(SIDE)), contact_model=contact_model, dt=DT)


# --- term-by-term checks (each returns what is wrong; empty when right) ------------------------
TermCheck = Callable[[LCS, Reference, np.ndarray, np.ndarray], list[str]]

PERTURBATION = np.array([0.004, -0.003, 0.02, 0.005, 0.002, 0.3, -0.2, 0.5, -0.4, 0.25])
"""A state displacement ``x1 - x0``: positions (m, rad) and velocities (m/s, rad/s)."""


def _mismatch(name: str, got: np.ndarray, expected: np.ndarray, tolerance: float) -> list[str]:
    error = float(np.abs(got - expected).max())
    scale = float(np.abs(expected).max())
    if error <= tolerance * max(1.0, scale) and scale > 0:
        return []
    return [f"{name}: off its closed form by {error:.3g} (closed form up to {scale:.3g})"]


def check_state_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``E (x1 - x0)``: how the gap moves with the state, positions (``G_n dq / dt``) and
    velocities (``G_c dv``) together."""
    lam = np.zeros(lcs.nlam)
    x1 = x0 + PERTURBATION
    return _mismatch("E dx", lcs.gap(x1, u, lam) - lcs.gap(x0, u, lam),
                     ref.gap(x1, u, lam) - ref.gap(x0, u, lam), 1e-7)


def check_position_columns(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``E[:, :nq] dq``: the geometry (a corner raised by ``dz`` opens its gap by ``dz / dt``)."""
    lam = np.zeros(lcs.nlam)
    x1 = x0.copy()
    x1[:5] += PERTURBATION[:5]
    return _mismatch("E_q dq", lcs.gap(x1, u, lam) - lcs.gap(x0, u, lam),
                     ref.gap(x1, u, lam) - ref.gap(x0, u, lam), 1e-7)


def check_force_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``F lam``: the Delassus operator, ``dt G_c M^-1 G_c^T lam`` for Anitescu."""
    lam = np.linspace(0.5, 2.0, lcs.nlam)
    return _mismatch("F lam", lcs.gap(x0, u, lam) - lcs.gap(x0, u, 0 * lam),
                     ref.gap(x0, u, lam) - ref.gap(x0, u, 0 * lam), 1e-9)


def check_input_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``H u``: the ball force closes the ball-cube gap by ``dt G_c (0, u / m_b)``."""
    lam = np.zeros(lcs.nlam)
    return _mismatch("H u", lcs.gap(x0, u, lam) - lcs.gap(x0, 0 * u, lam),
                     ref.gap(x0, u, lam) - ref.gap(x0, 0 * u, lam), 1e-7)


def check_offset_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``E x0 + c`` at the linearisation point: the distances and the free-flight velocities
    (the cube falling at ``g dt``), which ``c`` carries."""
    lam = np.zeros(lcs.nlam)
    return _mismatch("E x0 + c", lcs.gap(x0, 0 * u, lam), ref.gap(x0, 0 * u, lam), 1e-7)


def check_impulse_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``D lam``: the contact impulses ``dt M^-1 J^T lam`` in ``v'``, ``dt`` times that in
    ``q'``."""
    lam = np.linspace(0.5, 2.0, lcs.nlam)
    return _mismatch("D lam", lcs.next_state(x0, u, lam) - lcs.next_state(x0, u, 0 * lam),
                     ref.next_state(x0, u, lam) - ref.next_state(x0, u, 0 * lam), 1e-9)


def check_drift_term(lcs: LCS, ref: Reference, x0: np.ndarray, u: np.ndarray) -> list[str]:
    """``A x0 + d``: one free step, gravity ``-g dt`` on the cube's vertical speed included."""
    lam = np.zeros(lcs.nlam)
    return _mismatch("A x0 + d", lcs.next_state(x0, 0 * u, lam),
                     ref.next_state(x0, 0 * u, lam), 1e-7)


TERM_CHECKS: dict[str, tuple[TermCheck, str]] = {
    "E": (check_state_term, "E"),
    "E_q": (check_position_columns, "E"),
    "F": (check_force_term, "F"),
    "H": (check_input_term, "H"),
    "c": (check_offset_term, "c"),
    "D": (check_impulse_term, "D"),
    "d": (check_drift_term, "d"),
}
"""Check name -> (check, the LCS matrix whose removal it must detect)."""


@pytest.mark.parametrize("point", POINTS)
@pytest.mark.parametrize("contact_model", MODELS)
@pytest.mark.parametrize("name", list(TERM_CHECKS))
def test_term_matches_its_closed_form(name: str, contact_model: ContactModel,
                                      point: str) -> None:
    scene, x0, u = contact_rich_point(point)
    lcs = linearize(scene, x0, u, DT, contact_model)
    check, _ = TERM_CHECKS[name]
    assert check(lcs, reference_at(x0, contact_model), x0, u) == []


@pytest.mark.parametrize("contact_model", MODELS)
@pytest.mark.parametrize("name", list(TERM_CHECKS))
def test_closed_form_checks_reject_a_zeroed_term(name: str, contact_model: ContactModel) -> None:
    """The same check on the LCS with its term replaced by zeros fails."""
    scene, x0, u = contact_rich_point()
    check, matrix = TERM_CHECKS[name]
    lcs = linearize(scene, x0, u, DT, contact_model)
    if name == "E_q":  # only the position columns
        E = lcs.E.copy()
        E[:, :scene.nq] = 0.0
        mutant = dataclasses.replace(lcs, E=E)
    else:
        mutant = dataclasses.replace(lcs, **{matrix: np.zeros_like(getattr(lcs, matrix))})
    assert check(mutant, reference_at(x0, contact_model), x0, u) != []


@pytest.mark.parametrize(("point", "ball_cube", "pivot"),
                         [("touching", 0.0, 0.0), ("penetrating", -0.002, -0.001),
                          ("edge", 0.01, 0.0)])
def test_reference_geometry_matches_mujoco(point: str, ball_cube: float, pivot: float) -> None:
    """The independent contact geometry agrees with MuJoCo's (``phi`` to 1e-12): the closed
    forms above are about the same scene, at the distances each point is built with."""
    scene, x0, u = contact_rich_point(point)
    lcs = linearize(scene, x0, u, DT)
    np.testing.assert_allclose(planar_contacts(x0, SIDE).phi, lcs.phi, atol=1e-12)
    heights = corner_heights(x0[None, :], SIDE)[0]
    assert heights[1] == pytest.approx(pivot, abs=1e-12) and heights[0] > 0.08  # far edge
    assert lcs.phi[3] == pytest.approx(ball_cube, abs=1e-12)


# --- mutations of real rollouts ----------------------------------------------------------------
Mutation = Callable[[LCS, int], LCS]


def _zero(matrix: str) -> Mutation:
    def mutate(lcs: LCS, nq: int) -> LCS:
        return dataclasses.replace(lcs, **{matrix: np.zeros_like(getattr(lcs, matrix))})
    return mutate


def _scale(matrix: str, factor: float) -> Mutation:
    def mutate(lcs: LCS, nq: int) -> LCS:
        return dataclasses.replace(lcs, **{matrix: factor * getattr(lcs, matrix)})
    return mutate


def _zero_columns(start: bool) -> Mutation:
    """Zero the position (``start``) or the velocity columns of ``E``."""
    def mutate(lcs: LCS, nq: int) -> LCS:
        E = lcs.E.copy()
        if start:
            E[:, :nq] = 0.0
        else:
            E[:, nq:] = 0.0
        return dataclasses.replace(lcs, E=E)
    return mutate


def _diagonal_F(lcs: LCS, nq: int) -> LCS:
    return dataclasses.replace(lcs, F=np.diag(np.diag(lcs.F)))


MUTATIONS: dict[str, Mutation] = {
    "E=0": _zero("E"), "E_q=0": _zero_columns(True), "E_v=0": _zero_columns(False),
    "F=0": _zero("F"), "F*2": _scale("F", 2.0), "F diagonal": _diagonal_F,
    "H=0": _zero("H"), "H*2": _scale("H", 2.0), "c=0": _zero("c"),
    "D=0": _zero("D"), "D/2": _scale("D", 0.5), "d=0": _zero("d"),
}
"""Mutations of every relinearised LCS: a term removed, scaled or stripped of its coupling."""

Scenario = Callable[[ContactModel, Linearizer], list[str]]

SCENARIOS: dict[str, Scenario] = {
    "fall back": lambda m, lin: fall_back(0.3, DT, m, lin).violations(SIDE),
    "launched": lambda m, lin: launched_violations(launched(2.0, FINE_DT, 40, m, lin), SIDE),
    "pushed": lambda m, lin: pushed_violations(pushed(12, m, lin), SIDE),
    "impact": lambda m, lin: impact(3.0, m, lin).violations(SIDE),
}
"""The physical checks of ``test_lcs_rollouts.py``: each returns what is wrong."""

# (mutation, scenario that must catch it) and what goes wrong, measured (Anitescu;
# Stewart-Trinkle alike unless noted)
CAUGHT: list[tuple[str, str]] = [
    ("E=0", "fall back"),  # the gap sees the position q0 as a distance: the cube flies off
    ("E_q=0", "fall back"),  # no geometry: 0.28 rad off the plant
    ("E_v=0", "impact"),  # the gap ignores the ball's speed: 150 mm into the cube
    ("F=0", "fall back"),  # the gap cannot respond to forces: no contact force exists
    ("F*2", "impact"),  # half the impulse: the ball 75 mm into the cube
    ("F diagonal", "pushed"),  # no coupling between contacts: the cube tips (0.09 rad)
    ("H=0", "pushed"),  # the gap ignores the push: the ball 50 mm into the cube
    ("H*2", "pushed"),  # Anitescu: tips by 5e-4 rad; Stewart-Trinkle: travels 0.296 m
    ("c=0", "launched"),  # the resting cube sinks 151 mm into the table
    ("c=0", "impact"),  # the ball goes through the cube (150 mm in)
    ("D=0", "launched"),  # contact forces do nothing: the cube falls through the table
    ("D/2", "impact"),  # half the impulse: the ball 75 mm into the cube
    ("d=0", "fall back"),  # no gravity: the tipped cube stays tipped
    ("d=0", "launched"),  # no weight, less friction: slides 0.47 m, the plant 0.25 m
]


def _violations(scenario: str, contact_model: ContactModel,
                linearizer: Linearizer = linearize) -> list[str]:
    """The scenario's violations; a rollout that cannot continue is one."""
    try:
        return SCENARIOS[scenario](contact_model, linearizer)
    except SimulationFailed as error:
        return [f"no contact force solves a step: {error}"]


@pytest.mark.parametrize("contact_model", MODELS)
@pytest.mark.parametrize(("mutation", "scenario"), CAUGHT)
def test_mutated_lcs_fails_the_physical_check(mutation: str, scenario: str,
                                             contact_model: ContactModel) -> None:
    """The real LCS passes the scenario's check; the mutant fails it."""
    mutate = MUTATIONS[mutation]

    def mutant(scene: Scene, x: np.ndarray, u: np.ndarray, dt: float,
               model: ContactModel) -> LCS:
        return mutate(linearize(scene, x, u, dt, model), scene.nq)

    assert _violations(scenario, contact_model) == []
    assert _violations(scenario, contact_model, mutant) != []


def test_every_term_is_caught_by_a_physical_check() -> None:
    """Each of ``E, F, H, c, D, d`` has a zeroing mutation in :data:`CAUGHT`."""
    caught = {mutation.split("=")[0] for mutation, _ in CAUGHT if mutation.endswith("=0")}
    assert caught >= {"E", "F", "H", "c", "D", "d"}
