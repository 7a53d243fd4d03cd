"""Tests of the compiled, batched Lemke and LCP sample weighting (solvers/lcp_batch.py) against
the scalar reference (solvers/lcp.py ``lemke``, solvers/c3.py ``lcp_prediction_errors``) and
against LCPs with known solutions; correctness only, never timing."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.suites import sample_states, scripted_push
from c3bench.solvers.c3 import lcp_prediction_errors, lcp_prediction_weights, lcp_step
from c3bench.solvers.lcp import lemke
from c3bench.solvers.lcp_batch import (
    LemkeStatus,
    lcp_prediction_errors_batch,
    lcp_prediction_weights_batch,
    lemke_batch,
    observation_arrays,
    prediction_weights,
)
from c3bench.solvers.residuals import relative_natural_residual

SCALAR_STATUS = {
    "solved": LemkeStatus.SOLVED,
    "trivial": LemkeStatus.TRIVIAL,
    "secondary ray": LemkeStatus.SECONDARY_RAY,
    "pivot limit": LemkeStatus.PIVOT_LIMIT,
    "check failed": LemkeStatus.NOT_A_SOLUTION,
}


def _scalar_code(status: str) -> LemkeStatus:
    for prefix, code in SCALAR_STATUS.items():
        if status.startswith(prefix):
            return code
    raise AssertionError(f"unknown scalar status {status!r}")


def _assert_matches_scalar(M: np.ndarray, q: np.ndarray, max_pivots: int | None = None,
                           tol: float = 1e-12) -> None:
    """Every problem of the batch: same status, pivots and ``z`` (to 1e-12) as the scalar."""
    result = lemke_batch(M, q, max_pivots=max_pivots, tol=tol)
    for i in range(q.shape[0]):
        reference = lemke(M[i], q[i], max_pivots=max_pivots, tol=tol)
        assert result.status[i] == _scalar_code(reference.status), (i, reference.status)
        assert result.found[i] == reference.found
        assert result.pivots[i] == reference.iterations
        if reference.z is None:
            assert np.all(np.isnan(result.z[i]))
        else:
            np.testing.assert_allclose(result.z[i], reference.z, rtol=0, atol=1e-12)
            np.testing.assert_allclose(result.w[i], M[i] @ reference.z + q[i], rtol=0,
                                       atol=1e-12 * max(1.0, float(np.abs(q[i]).max())))


def _known_solution_lcps(rng: np.random.Generator, k: int, m: int, positive_definite: bool
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``k`` LCPs with the unique solution ``z*``: ``M`` a P-matrix (``R R^T + I/10`` plus a
    skew part when not symmetric: ``x^T M x > 0``), ``z*, w* >= 0`` complementary,
    ``q = w* - M z*``."""
    R = rng.standard_normal((k, m, m))
    M = R @ np.swapaxes(R, 1, 2) + 0.1 * np.eye(m)
    if not positive_definite:
        S = rng.standard_normal((k, m, m))
        M = M + (S - np.swapaxes(S, 1, 2))
    active = rng.random((k, m)) < 0.5
    z_star = np.where(active, rng.uniform(0.1, 2.0, (k, m)), 0.0)
    w_star = np.where(active, 0.0, rng.uniform(0.1, 2.0, (k, m)))
    q = w_star - (M @ z_star[..., None])[..., 0]
    return M, q, z_star


@pytest.mark.parametrize("m", [1, 2, 5, 12])
@pytest.mark.parametrize("symmetric", [True, False])
def test_equals_scalar_lemke_on_known_solutions(m: int, symmetric: bool) -> None:
    rng = np.random.default_rng(100 * m + symmetric)
    M, q, z_star = _known_solution_lcps(rng, 40, m, symmetric)
    _assert_matches_scalar(M, q)
    result = lemke_batch(M, q)
    assert np.all(result.found)
    scale = np.maximum(1.0, np.abs(z_star).max(axis=1))
    assert np.all(np.abs(result.z - z_star).max(axis=1) <= 1e-9 * scale)
    assert np.all(result.w >= -1e-9 * scale[:, None])
    assert np.all(np.abs(result.z * result.w) <= 1e-9 * scale[:, None] ** 2)


def test_degenerate_lcps_match_scalar() -> None:
    """Ties in ``q`` (the first pivot row), ``z*_i = w*_i = 0`` pairs (degenerate ratio tests),
    ``q >= 0`` (trivial), a zero ``q``, a singular PSD ``M`` and duplicated rows."""
    ones = np.ones((3, 3))
    cases = [
        (np.eye(3), np.array([-1.0, -1.0, -1.0])),
        (np.eye(3) + ones, np.array([-2.0, -2.0, 1.0])),
        (np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3)),
        (np.eye(3), np.array([0.0, 1.0, 2.0])),
        (ones, np.array([-1.0, -1.0, -1.0])),  # singular PSD, z = any split of 1
        (np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]),
         np.array([-1.0, -1.0, -4.0])),
        (np.diag([1.0, 0.0, 3.0]), np.array([-1.0, 0.0, -3.0])),
    ]
    # degenerate constructed: z*_i = w*_i = 0 on half the pairs
    rng = np.random.default_rng(7)
    M, _, _ = _known_solution_lcps(rng, 10, 6, False)
    for i in range(10):
        z_star = np.array([1.0, 0.0, 0.0, 2.0, 0.0, 0.0])
        w_star = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 1.0])
        cases.append((M[i], w_star - M[i] @ z_star))
    for Mi, qi in cases:
        _assert_matches_scalar(Mi[None], qi[None])
        result = lemke_batch(Mi[None], qi[None])
        assert result.found[0]
        assert np.all(result.z >= 0) and np.all(result.w >= -1e-12)
        assert np.all(np.abs(result.z * result.w) <= 1e-12)
    for size in (3, 6):  # the same problems in one batch
        same = [case for case in cases if case[1].size == size]
        _assert_matches_scalar(np.stack([c[0] for c in same]), np.stack([c[1] for c in same]))
    trivial = lemke_batch(cases[3][0][None], cases[3][1][None])
    assert trivial.status[0] == LemkeStatus.TRIVIAL and trivial.pivots[0] == 0


def test_lcps_without_solution_are_never_solved() -> None:
    """``F = [[0]], q = [-1]`` (``w = -1`` whatever ``z``) and ``[[2, -2], [-2, 2]]``,
    ``q = [-3, 0]`` (``w_2 >= 0`` forces ``w_1 < 0``; tests/test_lcp_backends.py): a secondary
    ray, and with a loose tie tolerance (1.5, which lets ``z0`` tie and leave at the first
    ratio test) a terminal basis with ``w_2 = -3`` that the check refuses, exactly as the
    scalar does."""
    unsolvable = [(np.array([[0.0]]), np.array([-1.0])),
                  (np.array([[2.0, -2.0], [-2.0, 2.0]]), np.array([-3.0, 0.0])),
                  (-np.eye(2), np.array([-1.0, 2.0]))]
    for M, q in unsolvable:
        for tol in (1e-12, 1.5):
            _assert_matches_scalar(M[None], q[None], tol=tol)
            result = lemke_batch(M[None], q[None], tol=tol)
            assert not result.found[0] and not lemke(M, q, tol=tol).found
    loose = lemke_batch(unsolvable[1][0][None], unsolvable[1][1][None], tol=1.5)
    assert loose.status[0] == LemkeStatus.NOT_A_SOLUTION
    assert np.min(loose.w[0]) < -1.0


# --- degeneracy: the lexicographic ratio test ----------------------------------------------------
# A feasible LCP with a symmetric PSD M of rank 3 and a pair z*_4 = w*_4 = 0 (case 1061 of 4000 of
# an audit's planted-feasible degenerate problems). At the third pivot z0 and w_4 tie for the
# minimum ratio in exact arithmetic; round-off in the small entries (2.5e-4 / 1.75e-4) made the
# ratios 1.4284038531347765 and 1.428403853136336 (relative gap 1.1e-12, outside a 1e-12 window
# on the ratios), w_4 left and z_4 entered with no positive entry: a secondary ray on a
# feasible LCP. The planted solution, as its w = M z + q (unique for a symmetric PSD M).
DEGENERATE_M = np.array([
    [6.478470459684421, -1.8992629661416072, 2.45143404821316, 0.7208072040803535,
     -1.7735529635665723],
    [-1.8992629661416072, 0.9357871647301729, -0.6874152688436439, -0.08021332464218114,
     -0.6793117354520699],
    [2.45143404821316, -0.6874152688436439, 0.9394659653817706, 0.24797641625142167,
     -0.7918661812054623],
    [0.7208072040803535, -0.08021332464218114, 0.24797641625142167, 0.26214771272484727,
     -0.5283540926982268],
    [-1.7735529635665723, -0.6793117354520699, -0.7918661812054623, -0.5283540926982268,
     4.331846803943269]])
DEGENERATE_Q = np.array([4.6452119761092545, -0.373485516028428, 1.2469902030684086,
                         0.48596470657330787, -2.6229464545757804])


def test_degenerate_psd_example_is_solved() -> None:
    M, q = DEGENERATE_M, DEGENERATE_Q
    assert np.linalg.matrix_rank(M) == 3
    _assert_matches_scalar(M[None], q[None])
    reference = lemke(M, q)
    assert reference.found and reference.z is not None, reference.status
    assert relative_natural_residual(M, q, reference.z) <= 1e-12
    result = lemke_batch(M[None], q[None])
    assert result.status[0] == LemkeStatus.SOLVED
    assert np.all(result.z[0] >= 0) and np.all(result.w[0] >= -1e-12)
    planted_z = np.array([0.0, 2.34437672, 1.42840385, 0.0, 1.23425735])
    np.testing.assert_allclose(result.w[0], M @ planted_z + q, atol=1e-7)


def _planted_degenerate_lcps(rng: np.random.Generator, k: int, m: int, kind: str
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``k`` feasible degenerate LCPs ``q = w* - M z*`` with one or two pairs
    ``z*_i = w*_i = 0``: ``kind`` "psd" (``G G^T``, ``G`` m x (m - 2), rank-deficient),
    "p" (``G G^T + I/10`` plus a skew part: a P-matrix), "psd-int" and "p-int" (the same with
    small integers, so that ties in the ratio test are exact)."""
    integer = kind.endswith("-int")

    def draw(*shape: int) -> np.ndarray:
        if integer:
            return rng.integers(-2, 3, size=shape).astype(float)
        return rng.standard_normal(shape)

    if kind.startswith("psd"):
        G = draw(k, m, max(1, m - 2))
        M = G @ np.swapaxes(G, 1, 2)
    else:
        G, S = draw(k, m, m), draw(k, m, m)
        M = G @ np.swapaxes(G, 1, 2) + (1.0 if integer else 0.1) * np.eye(m)
        M = M + S - np.swapaxes(S, 1, 2)
    active = rng.random((k, m)) < 0.5
    low, high = (1, 4) if integer else (0.1, 3.0)
    values = rng.integers(low, high, (2, k, m)) if integer else rng.uniform(low, high, (2, k, m))
    z_star = np.where(active, values[0], 0.0)
    w_star = np.where(active, 0.0, values[1])
    for i in range(k):
        both_zero = rng.choice(m, size=min(m, int(rng.integers(1, 3))), replace=False)
        z_star[i, both_zero] = 0.0
        w_star[i, both_zero] = 0.0
    q = w_star - (M @ z_star[..., None])[..., 0]
    return M, q, w_star


@pytest.mark.parametrize("kind", ["psd", "p", "psd-int", "p-int"])
def test_degenerate_planted_lcps_are_solved(kind: str) -> None:
    """Feasible degenerate PSD and P-matrix LCPs (pairs with ``z* = w* = 0``, rank-deficient
    PSD ``M``, exact ties with integer data): Lemke with the lexicographic ratio test solves
    every one (Cottle, Pang and Stone 1992, section 4.4), and the batch equals the scalar.
    ``w = M z + q`` is the planted ``w*`` (unique for P-matrices and symmetric PSD ``M``)."""
    rng = np.random.default_rng(["psd", "p", "psd-int", "p-int"].index(kind))
    for m in range(2, 10):
        M, q, w_star = _planted_degenerate_lcps(rng, 30, m, kind)
        _assert_matches_scalar(M, q)
        result = lemke_batch(M, q)
        assert np.all(result.found), [lemke(M[i], q[i]).status for i in
                                      np.flatnonzero(~result.found)]
        for i in range(q.shape[0]):
            assert relative_natural_residual(M[i], q[i], result.z[i]) <= 1e-10
        scale = np.maximum(1.0, np.abs(q).max(axis=1))
        assert np.all(np.abs(result.w - w_star).max(axis=1) <= 1e-8 * scale)


def test_infeasible_lcps_end_in_a_ray() -> None:
    """``M`` symmetric PSD with ``M n = 0`` for an ``n > 0`` and ``n^T q = -1``: ``n^T w =
    -1 < 0`` for every ``z``, so no ``w >= 0`` exists; Lemke (copositive-plus ``M``) ends in a
    secondary ray, reported as not found, in the batch as in the scalar."""
    rng = np.random.default_rng(21)
    for m in range(2, 9):
        n = rng.uniform(0.5, 2.0, (40, m))
        P = np.eye(m) - n[:, :, None] * n[:, None, :] / (n * n).sum(axis=1)[:, None, None]
        G = rng.standard_normal((40, m, m))
        M = P @ G @ np.swapaxes(G, 1, 2) @ P
        q = rng.standard_normal((40, m))
        q -= n * (((n * q).sum(axis=1) + 1.0) / (n * n).sum(axis=1))[:, None]
        _assert_matches_scalar(M, q)
        result = lemke_batch(M, q)
        assert not np.any(result.found)
        assert np.all(result.status == LemkeStatus.SECONDARY_RAY)
        assert np.all(np.isnan(result.z))


def test_nan_in_the_ratio_test_is_not_a_solution() -> None:
    """A NaN reaching the ratio test (here from ``q``) leaves no comparison: "check failed"
    in the scalar (which used to raise an IndexError there), ``NOT_A_SOLUTION`` with a NaN
    ``z`` in the batch."""
    M, q = np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([np.nan, -1.0])
    reference = lemke(M, q)
    assert not reference.found and reference.z is None
    assert reference.status.startswith("check failed: non-finite"), reference.status
    _assert_matches_scalar(M[None], q[None])
    assert lemke_batch(M[None], q[None]).status[0] == LemkeStatus.NOT_A_SOLUTION


def test_never_solved_with_negative_w_on_random_lcps() -> None:
    """Random indefinite ``M`` (many without a solution): whatever the status, a problem
    reported found has ``z >= 0``, ``w >= 0`` and complementarity to the check tolerance, and
    every status equals the scalar's."""
    rng = np.random.default_rng(11)
    M = rng.standard_normal((300, 4, 4))
    q = rng.standard_normal((300, 4))
    _assert_matches_scalar(M, q)
    result = lemke_batch(M, q)
    found = result.found
    assert 0 < found.sum() < found.size
    scale = np.maximum(1.0, np.maximum(np.abs(result.w - q).max(axis=1), np.abs(q).max(axis=1)))
    assert np.all(result.z[found] >= 0)
    assert np.all(result.w[found] >= -1e-9 * scale[found, None])
    assert np.all(np.abs(np.minimum(result.z, result.w))[found].max(axis=1)
                  <= 1e-9 * scale[found])


def test_pivot_limit_and_shapes() -> None:
    rng = np.random.default_rng(3)
    M, q, _ = _known_solution_lcps(rng, 20, 8, False)
    _assert_matches_scalar(M, q, max_pivots=1)
    assert np.any(lemke_batch(M, q, max_pivots=1).status == LemkeStatus.PIVOT_LIMIT)
    empty = lemke_batch(np.zeros((0, 3, 3)), np.zeros((0, 3)))
    assert empty.z.shape == (0, 3) and empty.status.shape == (0,)
    with pytest.raises(InputError):
        lemke_batch(np.zeros((2, 3, 3)), np.zeros((2, 4)))


# --- the LCP sample weighting on real cube models ------------------------------------------------
@pytest.fixture(scope="module")
def cube() -> SimpleNamespace:
    """16 cube-side samples linearised at three contact-rich states of the scripted push, each
    with the five transitions before it (the closed loop's ``history[-5:]``)."""
    config = load_config()
    record = scripted_push(config)
    linearizer = BatchLinearizer(np.linspace(0.24, 0.36, 16), config)
    cases = []
    for index in sample_states(record, 3, 0.02):
        start = max(index - 5, 0)
        observations = [(record.states[t], record.inputs[t], record.states[t + 1])
                        for t in range(start, index)]
        batch = linearizer.linearize(record.states[index], record.inputs[max(index - 1, 0)],
                                     config.mpc.dt)
        cases.append(SimpleNamespace(batch=batch, observations=observations))
    return SimpleNamespace(cases=cases)


def _errors_close(batched: np.ndarray, scalar: np.ndarray) -> None:
    assert np.array_equal(np.isinf(batched), np.isinf(scalar))
    finite = np.isfinite(scalar)
    np.testing.assert_allclose(batched[finite], scalar[finite], rtol=1e-10, atol=1e-14)


def test_prediction_errors_equal_scalar_on_cube_samples(cube: SimpleNamespace) -> None:
    seen_finite = False
    for case in cube.cases:
        batch: LCSBatch = case.batch
        samples = batch.samples()
        scalar = lcp_prediction_errors(samples, case.observations)
        xs, us, x_next = observation_arrays(case.observations, batch.nx, batch.nu)
        _errors_close(lcp_prediction_errors_batch(batch, xs, us, x_next), scalar)
        _errors_close(lcp_prediction_errors_batch(samples, xs, us, x_next), scalar)
        seen_finite |= bool(np.any(np.isfinite(scalar) & (scalar > 0)))
        weights = lcp_prediction_weights_batch(batch, case.observations)
        np.testing.assert_allclose(weights, prediction_weights(scalar), rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(weights, lcp_prediction_weights(samples, case.observations),
                                   rtol=1e-9, atol=1e-15)
    assert seen_finite


def test_prediction_errors_per_observation_and_failure(cube: SimpleNamespace) -> None:
    """Each observation alone equals the scalar; a transition whose LCP Lemke cannot solve
    (``c`` shifted so that ``F lam + q >= 0`` is infeasible for sample 0) makes that sample's
    error infinite, in both implementations, and its weight 0."""
    case = cube.cases[0]
    batch: LCSBatch = case.batch
    samples = batch.samples()
    for observation in case.observations:
        xs, us, x_next = observation_arrays([observation], batch.nx, batch.nu)
        _errors_close(lcp_prediction_errors_batch(batch, xs, us, x_next),
                      lcp_prediction_errors(samples, [observation]))
    broken = samples[0]
    broken.F = -np.eye(broken.nlam)
    broken.c = broken.c - 1e3
    x, u, _ = case.observations[0]
    assert lcp_step(broken, x, u) is None
    scalar = lcp_prediction_errors(samples, case.observations)
    xs, us, x_next = observation_arrays(case.observations, batch.nx, batch.nu)
    batched = lcp_prediction_errors_batch(samples, xs, us, x_next)
    assert np.isinf(scalar[0]) and np.isinf(batched[0])
    _errors_close(batched, scalar)
    weights = lcp_prediction_weights_batch(samples, case.observations)
    assert weights[0] == 0.0
    np.testing.assert_allclose(weights, lcp_prediction_weights(samples, case.observations),
                               rtol=1e-9, atol=1e-15)


def test_prediction_weights_rule() -> None:
    """``exp(-(e - min e) / T)`` normalised; median temperature; inf -> 0; all inf -> uniform."""
    errors = np.array([1.0, 2.0, np.inf, 4.0])
    expected = np.exp(-(errors[[0, 1, 3]] - 1.0) / 2.0)
    weights = prediction_weights(errors)
    np.testing.assert_allclose(weights[[0, 1, 3]], expected / expected.sum(), rtol=1e-14)
    assert weights[2] == 0.0
    np.testing.assert_array_equal(prediction_weights(np.full(3, np.inf)), np.full(3, 1 / 3))
    with pytest.raises(InputError):
        prediction_weights(errors, temperature=0.0)


def test_weights_without_observations_are_uniform(cube: SimpleNamespace) -> None:
    batch = cube.cases[0].batch
    np.testing.assert_array_equal(lcp_prediction_weights_batch(batch, []), np.full(16, 1 / 16))
    with pytest.raises(InputError):
        lcp_prediction_weights_batch([], [])
