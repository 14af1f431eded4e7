"""The one nonlinear least-squares path (``gyrojax.estimate.solve_least_squares``): optimistix with
gyrojax's trust-region Levenberg-Marquardt, the dense-Jacobian JVP and the stop at the noise
floor, checked against scipy's ``least_squares`` (a second method), analytic optima, finite
differences of the solution, and its convergence report."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares as scipy_least_squares

from gyrojax.estimate import (
    ScaledLevenbergMarquardt,
    convergence_note,
    dense_jacobian,
    solve_least_squares,
)

T = jnp.linspace(0.0, 4.0, 60)


def _decay(y, args):
    t, data = args
    return y[0] * jnp.exp(-y[1] * t) + y[2] - data


def _data(seed=0, noise=0.01):
    rng = np.random.default_rng(seed)
    clean = 2.0 * np.exp(-1.3 * np.asarray(T)) + 0.5
    return jnp.asarray(clean + noise * rng.standard_normal(T.shape))


def test_matches_scipy_least_squares_and_reports_standard_errors():
    data = _data()
    sol = jax.jit(lambda d: solve_least_squares(_decay, jnp.array([1.0, 0.5, 0.0]), (T, d)))(data)
    ref = scipy_least_squares(lambda y: np.asarray(_decay(jnp.asarray(y), (T, data))),
                              [1.0, 0.5, 0.0], xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert bool(sol.converged) and convergence_note(sol, "the fit") is None
    # the two solutions differ by much less than a standard error (0.01 of one at most)
    j = np.asarray(sol.jacobian)
    cov = np.linalg.inv(j.T @ j) * float(sol.cost) / (len(T) - 3)
    se = np.sqrt(np.diag(cov))
    assert np.max(np.abs(np.asarray(sol.value) - ref.x) / se) < 0.01
    np.testing.assert_allclose(float(sol.cost), 2 * ref.cost, rtol=1e-8)
    assert float(sol.step_se) <= 1e-2
    sigma = np.sqrt(float(sol.cost) / (len(T) - 3))
    assert np.linalg.norm(np.asarray(sol.residual) - ref.fun) < 0.02 * sigma


def test_rosenbrock_from_the_textbook_start():
    """Rosenbrock's valley as residuals ``(10 (y1 - y0^2), 1 - y0)``: optimum (1, 1), cost 0,
    reached from (-1.2, 1) where a plain Gauss-Newton step overshoots."""
    def rosen(y, _):
        return jnp.array([10.0 * (y[1] - y[0] ** 2), 1.0 - y[0]])

    sol = solve_least_squares(rosen, jnp.array([-1.2, 1.0]), max_steps=100)
    assert bool(sol.converged)
    np.testing.assert_allclose(np.asarray(sol.value), [1.0, 1.0], atol=1e-8)
    assert float(sol.cost) < 1e-16


def test_masked_parameter_stays_and_rank_deficiency_is_safe():
    """A parameter multiplied by a 0 mask keeps its start and the others are the reduced fit's;
    two columns that are one (``a e^{-b t} + c + d``: c and d alias) get the minimum-norm split
    and the fit still converges."""
    data = _data(1)

    def masked(y, args):
        mask, d = args
        z = y * mask
        return _decay(z[:3], (T, d)) + z[3]

    y0 = jnp.array([1.0, 0.5, 0.0, 0.0])
    held = solve_least_squares(masked, y0, (jnp.array([1.0, 1.0, 1.0, 0.0]), data))
    reduced = solve_least_squares(_decay, y0[:3], (T, data))
    assert bool(held.converged)
    np.testing.assert_allclose(np.asarray(held.value[:3]), np.asarray(reduced.value), rtol=1e-7)
    assert float(held.value[3]) == 0.0
    both = solve_least_squares(masked, y0, (jnp.ones(4), data))
    assert bool(both.converged)
    c, d = float(both.value[2]), float(both.value[3])
    np.testing.assert_allclose(c + d, float(reduced.value[2]), rtol=1e-7)
    np.testing.assert_allclose(c, d, rtol=1e-6)  # minimum norm: the sum split evenly


def test_a_fit_out_of_steps_or_unevaluable_says_so():
    def rosen(y, _):
        return jnp.array([10.0 * (y[1] - y[0] ** 2), 1.0 - y[0]])

    sol = solve_least_squares(rosen, jnp.array([-1.2, 1.0]), max_steps=2)
    assert not bool(sol.converged)
    note = convergence_note(sol, "the nominal fit")
    assert note.startswith("the nominal fit: ScaledLevenbergMarquardt did not converge (it used "
                           "all 2 steps; the Gauss-Newton step left is ")
    assert note.endswith("its figures are those of the last accepted step")
    nan = solve_least_squares(lambda y, _: jnp.log(y) - 1.0, jnp.array([-1.0]))
    assert not bool(nan.converged)
    assert "could not be evaluated" in convergence_note(nan, "x")
    with pytest.raises(Exception, match="did not converge"):
        solve_least_squares(rosen, jnp.array([-1.2, 1.0]), max_steps=2, throw=True)


def test_other_optimistix_solvers_run_under_the_same_report():
    data = _data(2)
    for solver in (optx.GaussNewton(rtol=1e-10, atol=1e-12), optx.Dogleg(rtol=1e-10, atol=1e-12),
                   ScaledLevenbergMarquardt()):
        sol = solve_least_squares(_decay, jnp.array([1.5, 1.0, 0.3]), (T, data), solver=solver)
        assert bool(sol.converged), type(solver).__name__
        assert sol.solver_name == type(solver).__name__
        np.testing.assert_allclose(np.asarray(sol.value), [2.0, 1.3, 0.5], atol=0.1)


def test_dense_jacobian_jvp_and_the_solution_derivative_by_finite_differences():
    """The custom JVP gives ``jax.jacfwd``'s Jacobian in ``y`` and the exact JVP in ``args``; the
    fitted parameters are differentiable in the data (optimistix's implicit function theorem),
    equal to central finite differences of refits."""
    data = _data(3)
    fn = dense_jacobian(_decay)
    y = jnp.array([1.7, 1.1, 0.4])
    np.testing.assert_allclose(jax.jacfwd(lambda v: fn(v, (T, data)))(y),
                               jax.jacfwd(lambda v: _decay(v, (T, data)))(y), rtol=1e-14)
    np.testing.assert_allclose(jax.jacfwd(lambda d: fn(y, (T, d)))(data),
                               jax.jacfwd(lambda d: _decay(y, (T, d)))(data), rtol=1e-14)

    @jax.jit
    def fitted(d):
        return solve_least_squares(_decay, jnp.array([2.0, 1.3, 0.5]), (T, d),
                                   step_se_tol=1e-9).value

    jac = np.asarray(jax.jacfwd(fitted)(data))  # (3, 60)
    h = 1e-4  # the refits stop at 1e-10 in the parameters: 5e-7 of noise in the differences
    for i in (0, 17, 59):
        e = jnp.zeros_like(data).at[i].set(h)
        fd = (np.asarray(fitted(data + e)) - np.asarray(fitted(data - e))) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-4, atol=1e-8)


def test_vmap_over_records_equals_one_by_one():
    datas = jnp.stack([_data(s) for s in range(4)])
    run = jax.jit(jax.vmap(lambda d: solve_least_squares(_decay, jnp.array([1.0, 0.5, 0.0]),
                                                         (T, d))))
    batched = run(datas)
    assert bool(jnp.all(batched.converged))
    for i in range(4):
        one = solve_least_squares(_decay, jnp.array([1.0, 0.5, 0.0]), (T, datas[i]))
        np.testing.assert_allclose(np.asarray(batched.value[i]), np.asarray(one.value),
                                   rtol=1e-7)


def test_fewer_residuals_than_unknowns_take_the_minimum_norm_step():
    """Two residuals, three unknowns (``y0 + y1 = 1``, ``y2 = 2``): the fit converges to a
    solution, the minimum-norm one from 0 (``y0 = y1 = 0.5``)."""
    sol = solve_least_squares(lambda y, _: jnp.array([y[0] + y[1] - 1.0, y[2] - 2.0]),
                              jnp.zeros(3))
    assert bool(sol.converged)
    np.testing.assert_allclose(np.asarray(sol.value), [0.5, 0.5, 2.0], atol=1e-9)
