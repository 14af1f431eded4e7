"""Output-error fits of a rig's trajectory: Gauss-Newton / Levenberg-Marquardt via optimistix
(:func:`gyrojax.estimate.solve_least_squares`).

The residual is ``integrate(rig, params) - record.y`` over all samples and channels; its Jacobian
comes from forward sensitivities through diffrax (``diffrax.ForwardMode`` + ``jax.jacfwd``), so the
exact nonlinear model (docs/rigs/esg.md) is fitted, free of the first-order model's
``O(m dchi)`` bias. The free parameters are optimised in scaled form (value / ``Param.scale``).
Standard errors: $\\hat\\sigma^2 (J^T J)^{+}$ from the Jacobian at the solution, computed by QR/SVD.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import ArrayLike, Float

from ..record import BenchRecord
from ..simulate import integrate
from ._linalg import scaled_lstsq
from ._lstsq import ScaledLevenbergMarquardt, solve_least_squares
from ._result import AbstractNamedEstimate

__all__ = ["FitResult", "convergence_text", "fit_trajectory", "trajectory_jacobian"]

def convergence_text(converged, num_steps, step_se) -> str:
    """One line for reports: ``converged: True (5 steps; the step left: 2.4e-04 standard
    errors)``."""
    return (f"converged: {bool(converged)} ({int(num_steps)} steps; the step left: "
            f"{float(step_se):.2g} standard errors)")


class FitResult(AbstractNamedEstimate):
    """Outcome of a fit.

    - `names`: free parameters; `params`: the full parameter dict at the solution.
    - `values`, `stderr`, `covariance`: of the free parameters (internal units).
    - `residual_rms`: RMS of the output residual; `noise_std`: its estimate ``sqrt(SSR / dof)``.
    - `remaining_step_se`: the Gauss-Newton step left at the solution, in standard errors (its
      Mahalanobis length under `covariance`).
    - `result`: an ``optimistix.RESULTS`` code; `converged`: bool, optimistix's test passed or
      `remaining_step_se` is under ``STATIONARY_SE`` (1e-2): the rule of every fit
      (:func:`~gyrojax.estimate.solve_least_squares`); `num_steps`.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    params: dict
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    residual_rms: jax.Array
    noise_std: jax.Array
    converged: jax.Array
    num_steps: jax.Array
    remaining_step_se: jax.Array
    result: optx.RESULTS


def _residual_fn(rig, space, free, base, conditions, ts, y, rtol, atol, max_steps, solver=None):
    def fn(x, args):
        p = space.unflatten(x, base, free)
        pred = integrate(rig, p, conditions, ts, solver=solver, rtol=rtol, atol=atol,
                         max_steps=max_steps, adjoint=diffrax.ForwardMode(), throw=False)
        return (pred - y).reshape(-1)

    return fn


def trajectory_jacobian(rig, params: Mapping, conditions, ts: Float[ArrayLike, " n"],
                        free: Sequence[str], *,
                        rtol: float = 1e-10, atol: float = 1e-12, max_steps: int = 100_000,
                        solver=None, directions=None):
    """Jacobian of the noise-free channels (flattened, ``n*c``) w.r.t. the free parameters in
    internal units (not scaled), by forward sensitivities through diffrax (``solver``: a diffrax
    solver, default ``Dopri8``; an implicit one such as ``Kvaerno5`` for stiff rigs).
    ``directions`` (``k x len(free)``, internal units): only the derivatives along those rows,
    ``(n*c, k)`` (the Jacobian times ``directions.T``), one tangent solve each."""
    space = rig.param_space
    free = space.check_names(free)
    fn = _residual_fn(rig, space, free, dict(params), conditions, ts,
                      jnp.zeros((len(ts), len(rig.channels))), rtol, atol, max_steps, solver)
    x0 = space.flatten(params, free)
    if directions is not None:
        scales = space.scales(free)
        return jax.vmap(lambda v: jax.jvp(lambda x: fn(x, None), (x0,), (v / scales,))[1],
                        out_axes=1)(directions)
    return jax.jacfwd(lambda x: fn(x, None))(x0) / space.scales(free)


@eqx.filter_jit
def _fit(rig, free, solver_name, base, conditions, ts, y, rtol, atol, max_steps, ode_rtol, ode_atol,
         ode_max_steps, ode_solver):
    space = rig.param_space
    fn = _residual_fn(rig, space, free, base, conditions, ts, y, ode_rtol, ode_atol, ode_max_steps,
                      ode_solver)
    x0 = space.flatten(base, free)
    if solver_name == "gauss-newton":
        solver = optx.GaussNewton(rtol=rtol, atol=atol)
    else:
        solver = ScaledLevenbergMarquardt(rtol=rtol, atol=atol)
    # the step test on the parameters (rtol, atol) ends the fit, as asked; the convergence rule
    # is every fit's (the test passed, or the step left under STATIONARY_SE standard errors)
    sol = solve_least_squares(fn, x0, solver=solver, max_steps=max_steps, step_se_tol=0.0)
    x = sol.value
    _, cov_unit, s = scaled_lstsq(sol.jacobian, sol.residual)
    k = jnp.sum(s > 1e-12 * s[0])
    sigma2 = sol.cost / jnp.maximum(sol.residual.shape[0] - k, 1)
    sc = space.scales(free)
    cov = sigma2 * cov_unit * jnp.outer(sc, sc)
    values = x * sc
    return (space.unflatten(x, base, free), values, jnp.sqrt(jnp.diag(cov)), cov,
            jnp.sqrt(jnp.mean(sol.residual**2)), jnp.sqrt(sigma2), sol.result, sol.num_steps,
            sol.step_se, sol.converged)


def fit_trajectory(rig, record: BenchRecord, conditions, params0: Mapping, *,
                   free: Sequence[str], method: str = "gauss-newton", rtol: float = 1e-6,
                   atol: float = 1e-8, max_steps: int = 100, ode_rtol: float = 1e-10,
                   ode_atol: float = 1e-12, ode_max_steps: int = 100_000, ode_solver=None,
                   throw: bool = True) -> FitResult:
    """Fit the free parameters of ``rig`` to ``record`` by output-error least squares.

    **Arguments:**
    - `rig`, `record`, `conditions`: the model, the measured channels and the test conditions.
    - `params0`: full parameter dict; the starting point of the free ones and the value of the
      frozen ones (e.g. a regression estimate).
    - `free`: names of the parameters to estimate.
    - `method`: ``"gauss-newton"`` (``optimistix.GaussNewton``) or ``"levenberg-marquardt"``
      (:class:`~gyrojax.estimate.ScaledLevenbergMarquardt`), run by
      :func:`~gyrojax.estimate.solve_least_squares`.
    - `rtol`, `atol`, `max_steps`: optimiser tolerances (on the scaled parameters) and budget.
    - `ode_solver`: the diffrax solver (default ``Dopri8``); ``ode_rtol``/``ode_atol``/
      ``ode_max_steps`` its controller's tolerances and budget.
    - `throw`: raise if the optimiser did not converge; pass ``False`` under ``vmap`` and read
      ``result.converged``.

    **Returns:** a :class:`FitResult`.
    """
    if method not in ("gauss-newton", "levenberg-marquardt"):
        raise ValueError(f"method={method!r}; use 'gauss-newton' or 'levenberg-marquardt'")
    free = rig.param_space.check_names(free)
    if len(free) == 0:
        raise ValueError("fit_trajectory: no free parameters; name at least one in free=")
    base = {k: jnp.asarray(v, dtype=float) for k, v in params0.items()}
    out = _fit(rig, free, method, base, conditions, record.t, record.y, rtol, atol, max_steps,
               ode_rtol, ode_atol, ode_max_steps, ode_solver)
    params, values, se, cov, rms, sig, result, nsteps, step_se, converged = out
    if throw:
        converged_all = bool(jnp.all(converged))
        if not converged_all:
            raise RuntimeError(f"fit_trajectory ({method}) did not converge in {max_steps} steps: "
                               f"{optx.RESULTS[result] if jnp.ndim(result) == 0 else result}. "
                               "Start closer (e.g. from a regression estimate), raise max_steps, "
                               "or free fewer parameters (see gyrojax observability).")
    return FitResult(names=free, params=params, values=values, stderr=se, covariance=cov,
                     residual_rms=rms, noise_std=sig, converged=converged, num_steps=nsteps,
                     remaining_step_se=step_se,
                     result=result)
