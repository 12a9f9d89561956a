"""The one Levenberg-Marquardt loop (handanno_core.lm) with dense and banded solvers."""

from dataclasses import dataclass

import numpy as np
import pytest

from handanno_core.lm import (
    Marquardt,
    Nielsen,
    NormalEquations,
    levenberg_marquardt,
    solve_banded,
    solve_dense,
)

T = np.linspace(0.0, 2.0, 30)
Y = 2.5 * np.exp(-1.3 * T) + 0.5


@dataclass
class _Ev:
    r: np.ndarray
    cost: float


def _evaluate(x):
    r = x[0] * np.exp(-x[1] * T) + x[2] - Y
    return _Ev(r, float(r @ r))


def _normal(x, ev):
    e = np.exp(-x[1] * T)
    jac = np.stack([e, -x[0] * T * e, np.ones_like(T)], axis=1)
    jtj = jac.T @ jac
    return NormalEquations(jtj, jac.T @ ev.r, np.diag(jtj).copy() + 1e-9)


@pytest.mark.parametrize("damping", [Marquardt(), Nielsen()])
def test_fits_an_exponential_and_cost_never_rises(damping):
    out = levenberg_marquardt(
        _evaluate, np.array([1.0, 0.3, 0.0]), normal_equations=_normal, damping=damping,
        max_iter=100, rtol=1e-14,
    )  # fmt: skip
    np.testing.assert_allclose(out.x, [2.5, 1.3, 0.5], atol=1e-6)
    assert np.all(np.diff(out.history) <= 0)
    assert out.converged and out.iterations < 100


def test_banded_solver_gives_the_dense_step():
    rng = np.random.default_rng(0)
    n = 6
    main = rng.uniform(2.0, 3.0, n)
    off = rng.uniform(-0.5, 0.5, n - 1)
    dense = np.diag(main) + np.diag(off, 1) + np.diag(off, -1)
    ab = np.zeros((2, n))
    ab[0, 1:] = off
    ab[1] = main
    g = rng.normal(size=n)
    scale = main.copy()
    step_b = solve_banded(NormalEquations(ab, g, scale), 0.1)
    step_d = solve_dense(NormalEquations(dense, g, scale), 0.1)
    np.testing.assert_allclose(step_b, step_d, rtol=1e-10)


def test_no_descent_direction_stops_without_moving():
    x0 = np.array([2.5, 1.3, 0.5])  # the exact minimum: no step can lower the cost
    out = levenberg_marquardt(_evaluate, x0, normal_equations=_normal, max_iter=10)
    np.testing.assert_array_equal(out.x, x0)
    assert out.converged and out.iterations == 1 and out.log[0][3] == 0.0


def test_batched_rows_are_independent_and_stop_on_their_own():
    from handanno_core.lm import BatchedNormalEquations, levenberg_marquardt_batched

    @dataclass
    class _Rows:
        cost: np.ndarray
        r: np.ndarray

    def evaluate(x):
        r = x[:, :1] * np.exp(-x[:, 1:2] * T) + x[:, 2:] - Y
        return _Rows(np.sum(r * r, axis=1), r)

    def normal(x, ev):
        e = np.exp(-x[:, 1:2] * T)
        jac = np.stack([e, -x[:, :1] * T * e, np.ones_like(e)], axis=-1)
        jtj = np.einsum("mrp,mrq->mpq", jac, jac)
        return BatchedNormalEquations(jtj, np.einsum("mrp,mr->mp", jac, ev.r), np.ones((len(x), 3)))

    x0 = np.array([[1.0, 0.3, 0.0], [2.5, 1.3, 0.5]])  # the second row starts at the minimum
    out = levenberg_marquardt_batched(
        evaluate, x0, normal_equations=normal, retract=lambda x, s: x + s, max_iter=200,
        rtol=1e-12, max_lam=1e8,
    )  # fmt: skip
    np.testing.assert_allclose(out.x[0], [2.5, 1.3, 0.5], atol=1e-5)
    np.testing.assert_array_equal(out.x[1], x0[1])  # never moved: no step lowered its cost


def test_batched_active_rows_matches_all_rows_and_skips_stopped_rows():
    """``active_rows``: the same rows' results as evaluating every row, but a stopped row is
    never evaluated again and normal equations are built only for rows that moved."""
    from handanno_core.lm import BatchedNormalEquations, levenberg_marquardt_batched

    @dataclass
    class _Rows:
        cost: np.ndarray
        r: np.ndarray

    def residuals(x):
        r = x[:, :1] * np.exp(-x[:, 1:2] * T) + x[:, 2:] - Y
        return _Rows(np.sum(r * r, axis=1), r)

    built = []

    def normal(x, ev):
        built.append(len(x))
        e = np.exp(-x[:, 1:2] * T)
        jac = np.stack([e, -x[:, :1] * T * e, np.ones_like(e)], axis=-1)
        jtj = np.einsum("mrp,mrq->mpq", jac, jac)
        return BatchedNormalEquations(jtj, np.einsum("mrp,mr->mp", jac, ev.r), np.ones((len(x), 3)))

    seen = []

    def evaluate_rows(x, rows):
        seen.append(rows.copy())
        return residuals(x)

    x0 = np.array([[1.0, 0.3, 0.0], [2.5, 1.3, 0.5], [3.0, 2.0, 0.0]])  # row 1: at the minimum
    kw = dict(retract=lambda x, s: x + s, max_iter=200, rtol=1e-12, max_lam=1e8, max_rejects=3)
    ref = levenberg_marquardt_batched(residuals, x0, normal_equations=normal, **kw)
    built.clear()
    out = levenberg_marquardt_batched(
        evaluate_rows, x0, normal_equations=normal, active_rows=True, **kw
    )
    np.testing.assert_allclose(out.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.evaluation.cost, ref.evaluation.cost, rtol=0, atol=1e-20)
    np.testing.assert_allclose(out.x[0], [2.5, 1.3, 0.5], atol=1e-5)
    np.testing.assert_array_equal(out.x[1], x0[1])
    # row 1 never improves: it is dropped after max_rejects rejected trials
    assert sum(1 in r for r in seen) == 1 + 3
    # one build per accepted point (plus the start), not one per iteration
    assert sum(built) < sum(len(r) for r in seen)
