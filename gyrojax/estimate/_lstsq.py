"""Every nonlinear least-squares fit in gyrojax, through optimistix.

One entry point, :func:`solve_least_squares`, runs an optimistix Gauss-Newton-type solver
(:class:`ScaledLevenbergMarquardt`, Levenberg-Marquardt as a trust region in the scaled norm,
by default; ``optimistix.Dogleg`` and ``optimistix.GaussNewton`` fit
too) under :class:`StationaryStop`, and one report,
:func:`convergence_note`, turns the outcome into the line a user reads.

Two things make the generic path fit bench-test models:

- **The Jacobian in one forward pass.** optimistix linearises the residual with
  ``jax.linearize``; through a diffrax solve (a ``while_loop``) the linearised function re-runs
  the whole solve, primal included, for the Jacobian's columns. :func:`dense_jacobian` wraps the
  residual in a custom JVP that forms the Jacobian with its value in one ``jax.jacfwd`` pass (the
  ODE solved once with one tangent per column), so the linear solvers' ``as_matrix`` costs a
  matrix product.
- **A stop at the ODE solver's noise floor.** A residual computed through an adaptive ODE solve
  carries its error control's noise (~1e-9 of the cost): near the optimum a step predicted to
  lower the cost by less than that is as likely to raise it, the trust region shrinks, and
  optimistix's test on successive iterates passes late or never. :class:`StationaryStop` also
  stops when the Gauss-Newton step still to take at the accepted point is shorter than
  ``step_se_tol`` (1e-2) of its own standard errors: far below anything the data can tell.

A fit is *converged* when optimistix's own test passed, the stop above was met, or the
Gauss-Newton step left at the solution is under ``STATIONARY_SE`` of its own standard errors
(its length under the covariance ``sigma^2 (J^T J)^+``, ``sigma^2`` from the residual): the
rule of every fit in gyrojax. A fit that is not converged is returned at its last accepted point
with its reason; callers say so with :func:`convergence_note` (or raise, ``throw=True``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Union

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._linalg import tall_qr_r, value_and_jacfwd

__all__ = ["STATIONARY_SE", "CappedTrustRegion", "LeastSquaresSolution",
           "ScaledLevenbergMarquardt", "StationaryStop", "TrustRegionDescent", "convergence_note",
           "dense_jacobian", "solve_least_squares"]

# the Gauss-Newton step left at a converged solution, in its own standard errors. Along a weakly
# observable direction (the ESG equatorial scheme's m11 + 0.72 mc2 + 0.56 eps3, relative
# singular value 3e-4) the adaptive ODE's error control, not the data, keeps moving the
# iterates: of no statistical meaning, yet far above a step test on the parameters' values.
STATIONARY_SE = 1e-2

# the solvers a fit takes: gyrojax's own, or optimistix's Gauss-Newton family
GaussNewtonLike = Union["ScaledLevenbergMarquardt", optx.AbstractGaussNewton]


def dense_jacobian(fn: Callable[[Any, Any], Array]) -> Callable[[Any, Any], Array]:
    """``fn(y, args)`` with a custom JVP that materialises the Jacobian in ``y`` in one
    forward-mode pass (:func:`~gyrojax.estimate._linalg.value_and_jacfwd`): its ``jax.linearize``
    is then the value and a matrix product, not a second run of a diffrax solve. Tangents of
    ``args`` (floating-point leaves that are differentiated) add their own JVP, so derivatives
    through the fit stay exact.

    **Arguments:** `fn`: residual function of a flat ``y`` (shape ``(k,)``) and a pytree
    ``args``, returning a flat residual ``(m,)``.

    **Returns:** the wrapped function, same signature.
    """

    @eqx.filter_custom_jvp
    def wrapped(y, args):
        return fn(y, args)

    @wrapped.def_jvp
    def _jvp(primals, tangents):
        y, args = primals
        ty, targs = tangents
        value, jac = value_and_jacfwd(lambda v: fn(v, args))(y)
        out = jnp.zeros_like(value) if ty is None else jac @ ty
        if any(t is not None for t in jax.tree_util.tree_leaves(
                targs, is_leaf=lambda x: x is None)):
            dyn, static = eqx.partition(args, eqx.is_inexact_array)
            tdyn = jax.tree_util.tree_map(
                lambda a, t: jnp.zeros_like(a) if t is None else t, dyn, targs,
                is_leaf=lambda x: x is None)
            out = out + jax.jvp(lambda d: fn(y, eqx.combine(d, static)), (dyn,), (tdyn,))[1]
        return value, out

    return wrapped


class StationaryStop(optx.AbstractLeastSquaresSolver):
    """An optimistix Gauss-Newton-type ``solver`` with one more stop rule: the Gauss-Newton step
    still to take at the accepted point is shorter than ``step_se_tol`` of its own standard
    errors (``|J p|^2 / sigma^2``, ``sigma^2 = |r|^2 / (m - rank J)``: scale-free, so a
    noise-free fit stops too). The steps, the trust region and optimistix's own termination test
    are ``solver``'s.

    **Arguments:**
    - `solver`: a Gauss-Newton-type solver: :class:`ScaledLevenbergMarquardt` or an
      ``optimistix.AbstractGaussNewton`` (``optimistix.Dogleg``, ``optimistix.GaussNewton``);
      its ``rtol``/``atol`` are optimistix's test on successive iterates.
    - `step_se_tol`: the step left, in standard errors, below which the fit stops (a float,
      or a traced scalar: fits of different tolerances share one compilation).
    - `budget`: ``None``, or a (traced) number of steps after which the fit stops with
      optimistix's ``nonlinear_max_steps_reached``: fits of different budgets share one
      compilation, where ``max_steps`` is static.
    """

    solver: GaussNewtonLike
    step_se_tol: float | Float[Array, ""]
    budget: Int[Array, ""] | None
    rtol: float
    atol: float
    norm: Callable

    def __init__(self, solver: GaussNewtonLike, step_se_tol: float = 1e-2,
                 budget=None):
        self.solver = solver
        self.step_se_tol = step_se_tol
        self.budget = None if budget is None else jnp.asarray(budget)
        self.rtol, self.atol, self.norm = solver.rtol, solver.atol, solver.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self.solver.init(fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        return self.solver.step(fn, y, args, options, state, tags)

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.solver.terminate(fn, y, args, options, state, tags)
        decrement, cost, rank = _decrement(state, self.solver.descent)
        m = state.f_info.residual.shape[0]
        small = jnp.invert(state.first_step) & (
            decrement * jnp.maximum(m - rank, 1) <= self.step_se_tol**2 * cost)
        result = optx.RESULTS.where(done, result, optx.RESULTS.successful)
        if self.budget is not None:
            spent = jnp.invert(done | small) & (state.num_steps >= self.budget)
            result = optx.RESULTS.where(spent, optx.RESULTS.nonlinear_max_steps_reached, result)
            done = done | spent
        return done | small, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.solver.postprocess(fn, y, aux, args, options, state, tags, result)


def _decrement(state, descent):
    """``(|J p|^2, |r|^2, rank)`` at the accepted point of a Gauss-Newton-type solver's
    ``state``: the drop of the sum of squares the Gauss-Newton step ``p`` (minimum norm)
    predicts, the sum of squares, and the numerical rank of ``J`` (singular values above 1e-12
    of the largest). :class:`TrustRegionDescent` holds the SVD already (its query ran at that
    point); any other descent's ``J`` is factored here."""
    r = state.f_info.residual
    if isinstance(descent, TrustRegionDescent):
        d = state.descent_state
        keep = d.s2 > 0
        dec = jnp.sum(jnp.where(keep, d.sb**2 / jnp.where(keep, d.s2, 1.0), 0.0))
        return dec, jnp.sum(r**2), jnp.sum(keep)
    jac = state.f_info.jac.as_matrix()
    u, s, _ = jnp.linalg.svd(jac, full_matrices=False)
    keep = s > 1e-12 * jnp.max(s)
    proj = jnp.where(keep, u.T @ r, 0.0)
    return jnp.sum(proj**2), jnp.sum(r**2), jnp.sum(keep)


class LeastSquaresSolution(eqx.Module):
    """The outcome of :func:`solve_least_squares`.

    - `value`: ``(k,)`` the last accepted point.
    - `residual`: ``(m,)`` and `jacobian`: ``(m, k)`` there.
    - `cost`: the sum of squares ``|residual|^2``.
    - `step_se`: the Gauss-Newton step left there, in its own standard errors (``sigma^2`` =
      ``cost / (m - rank)``); 0 for a noise-free exact fit.
    - `result`: optimistix's result code; `num_steps`: optimistix's steps (function and
      Jacobian evaluations, rejected trust-region trials included).
    - `converged`: optimistix's test or :class:`StationaryStop`'s passed, or `step_se` is under
      ``STATIONARY_SE``.
    - `solver_name` (static): the solver's class name, for the report.
    """

    value: Float[Array, " k"]
    residual: Float[Array, " m"]
    jacobian: Float[Array, "m k"]
    cost: Float[Array, ""]
    step_se: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    solver_name: str = eqx.field(static=True)


class _DescentState(eqx.Module):
    v: Float[Array, "k k"]  # right singular vectors of the column-scaled J
    sb: Float[Array, " k"]  # s * (U^T r): the scaled gradient's components
    s2: Float[Array, " k"]  # the squared singular values (0 where dropped)
    scale: Float[Array, " k"]  # the column scales D
    gn_norm: Float[Array, ""]  # |D p_GN|, the Gauss-Newton step's scaled length


class TrustRegionDescent(optx.AbstractDescent):
    """Levenberg-Marquardt's step as a trust region in the scaled norm ``|D p|`` (Moré, 1978),
    ``D`` the Jacobian's column norms: the ``p`` minimising ``|J p + r|^2`` subject to
    ``|D p| <= step_size * |D p_GN|``, a radius relative to the Gauss-Newton step's own length.
    At ``step_size >= 1`` it is the Gauss-Newton step (minimum norm, singular values below
    1e-12 of the largest dropped), which converges along weakly observable directions at once;
    below 1 the damping ``lambda`` that meets the radius is found by bisection on the secular
    equation. Scaled, the step is invariant to the units of the parameters and the residual.

    The SVD of the column-scaled ``J`` is taken once per accepted point (:meth:`query`); each
    trial radius then costs a few vector operations. A zero column (a parameter masked out of a
    compiled superset) gets a step of 0.

    **Arguments:** `gram`: take ``V`` and ``s^2`` from the eigendecomposition of the scaled
    Gram matrix ``J~^T J~`` instead of the SVD of ``J~`` (a matrix product, several times faster
    for a tall ``J``: 9000 x 100). Singular values below 1e-7 of the largest (where ``s^2``
    meets the rounding of the product) are then dropped instead of those below 1e-12: for
    well-conditioned scaled Jacobians only (the IMU's; ``tests/test_estimate_lstsq.py``
    compares the two).
    """

    gram: bool = False

    def init(self, y, f_info_struct):
        k = y.shape[0]
        z = jnp.zeros(k)
        return _DescentState(jnp.eye(k), z, z, jnp.ones(k), jnp.zeros(()))

    def query(self, y, f_info, state):
        del y, state
        jac = f_info.jac.as_matrix()
        norms = jnp.linalg.norm(jac, axis=0)
        ok = norms > 1e-12 * jnp.max(norms)
        scale = jnp.where(ok, norms, 1.0)
        scaled = jnp.where(ok, jac / scale, 0.0)
        r = f_info.residual
        if scaled.shape[0] < scaled.shape[1]:  # fewer rows than unknowns: zero rows change nothing
            pad = scaled.shape[1] - scaled.shape[0]
            scaled, r = jnp.pad(scaled, ((0, pad), (0, 0))), jnp.pad(r, (0, pad))
        if self.gram:
            s2, v = jnp.linalg.eigh(scaled.T @ scaled)
            keep = s2 > 1e-14 * jnp.max(s2)
            s2 = jnp.where(keep, s2, 0.0)
            sb = jnp.where(keep, v.T @ (scaled.T @ r), 0.0)
        else:
            # the SVD of the scaled J from that of the R of [J r] (TSQR; its last column holds
            # Q^T r): the same factors as an SVD of the tall J, in half its time
            k = scaled.shape[1]
            rr = tall_qr_r(jnp.concatenate([scaled, r[:, None]], axis=1))
            u, sv, vt = jnp.linalg.svd(rr[:k, :k])
            keep = sv > 1e-12 * sv[0]
            sv = jnp.where(keep, sv, 0.0)
            sb = sv * (u.T @ rr[:k, k])
            s2, v = sv**2, vt.T
        gn = jnp.where(keep, sb / jnp.where(keep, s2, 1.0), 0.0)
        return _DescentState(v, sb, s2, scale, jnp.linalg.norm(gn))

    def step(self, step_size, state):
        radius = jnp.minimum(step_size, 1.0) * state.gn_norm

        def length(lam):  # |D p(lambda)|
            return jnp.linalg.norm(state.sb / jnp.maximum(state.s2 + lam, 1e-300))

        # bisection on log(lambda) over [1e-16, 1] x lambda_max; |D p| <= |g| / lambda, so the
        # radius is met at or below lambda_max = |g| / radius
        lam_max = jnp.linalg.norm(state.sb) / jnp.maximum(radius, 1e-300)

        def bisect(_, bounds):
            lo, hi = bounds
            mid = 0.5 * (lo + hi)
            longer = length(jnp.exp(mid) * lam_max) > radius
            return jnp.where(longer, mid, lo), jnp.where(longer, hi, mid)

        lo, hi = jax.lax.fori_loop(0, 60, bisect, (jnp.log(1e-16), jnp.asarray(0.0)))
        lam = jnp.where(step_size >= 1.0, 0.0, jnp.exp(hi) * lam_max)
        keep = state.s2 > 0
        coef = jnp.where(keep | (lam > 0), state.sb / jnp.maximum(state.s2 + lam, 1e-300), 0.0)
        diff = -(state.v @ coef) / state.scale
        return diff, optx.RESULTS.successful


class _CappedTrustRegionState(eqx.Module):
    inner: Any


class CappedTrustRegion(optx.AbstractSearch):
    """optimistix's classical trust-region update, tuned to a radius relative to the
    Gauss-Newton step (:class:`TrustRegionDescent`): a trial whose actual drop of the sum of
    squares is under 1 % of the predicted one is rejected and the radius quartered; one over a
    quarter of it grows the radius 4x, capped at the Gauss-Newton step (step size 1), so a fit
    returns to whole Gauss-Newton steps one good step after an overshoot. (optimistix's
    defaults grow only above 99 % of the predicted drop, 3.5x: a refit that overshot once then
    crept at a quarter of the Gauss-Newton step for six steps where whole steps converge in two.)
    """

    inner: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion(
        high_cutoff=0.25, low_cutoff=0.01, high_constant=4.0, low_constant=0.5)

    def init(self, y, f_info_struct):
        return _CappedTrustRegionState(self.inner.init(y, f_info_struct))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        size, accept, result, inner = self.inner.step(first_step, y, y_eval, f_info,
                                                      f_eval_info, state.inner)
        size = jnp.minimum(size, 1.0)
        inner = eqx.tree_at(lambda s: s.step_size, inner, size)
        return size, accept, result, _CappedTrustRegionState(inner)


class _ScaledLMState(eqx.Module):
    """:class:`ScaledLevenbergMarquardt`'s state; the fields :class:`StationaryStop` reads are
    named as in optimistix's Gauss-Newton state."""

    first_step: Bool[Array, ""]
    y_eval: Any  # the next trial point
    search_state: Any
    f_info: Any  # FunctionInfo.ResidualJac at the accepted point (its Jacobian a matrix)
    aux: Any
    descent_state: _DescentState
    terminate: Bool[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    num_accepted_steps: Int[Array, ""]


class ScaledLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """Levenberg-Marquardt as a trust region in the scaled norm (:class:`TrustRegionDescent`,
    :class:`CappedTrustRegion`): gyrojax's default nonlinear least-squares solver, an
    ``optimistix.AbstractLeastSquaresSolver`` (run it by ``optimistix.least_squares`` or
    :func:`solve_least_squares`). From a good start it takes Gauss-Newton steps; a trial that
    does not lower the sum of squares as predicted shrinks the radius by 4, a good one grows it
    by 4 up to the Gauss-Newton step (:class:`CappedTrustRegion`).

    A trial point costs one evaluation of the residual; the Jacobian (one forward-mode pass,
    :func:`~gyrojax.estimate._linalg.value_and_jacfwd`) is formed only where a trial is
    accepted. optimistix's ``AbstractGaussNewton`` linearises at every trial, which through a
    diffrax solve makes a rejected trial cost a whole Jacobian (the Schuler refits 1.3x slower).

    **Arguments:** `rtol`, `atol`: optimistix's termination test on successive iterates (in
    the fitted coordinates); `gram`: :class:`TrustRegionDescent`'s.
    """

    rtol: float
    atol: float
    norm: Callable
    descent: TrustRegionDescent
    search: CappedTrustRegion

    def __init__(self, rtol: float = 0.0, atol: float = 1e-10, *, gram: bool = False):
        self.rtol = rtol
        self.atol = atol
        self.norm = optx.max_norm
        self.descent = TrustRegionDescent(gram)
        self.search = CappedTrustRegion()

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        zeros = lambda s: jnp.zeros(s.shape, s.dtype)  # noqa: E731
        f0 = zeros(f_struct)
        jac = lx.MatrixLinearOperator(jnp.zeros(f0.shape + y.shape, f0.dtype))
        f_info = optx.FunctionInfo.ResidualJac(f0, jac)
        return _ScaledLMState(
            first_step=jnp.array(True), y_eval=y, search_state=self.search.init(y, f_info),
            f_info=f_info, aux=jax.tree_util.tree_map(zeros, aux_struct),
            descent_state=self.descent.init(y, f_info), terminate=jnp.array(False),
            result=optx.RESULTS.successful, num_steps=jnp.array(0),
            num_accepted_steps=jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        del options, tags
        # the trial's residual (the search reads no more: its predicted drop uses the accepted
        # point's Jacobian); the first trial, the start, is accepted whatever its value
        f_eval = jax.lax.cond(state.first_step, lambda: state.f_info.residual,
                              lambda: fn(state.y_eval, args)[0])
        trial = optx.FunctionInfo.ResidualJac(f_eval, state.f_info.jac)
        step_size, accept, search_result, search_state = self.search.step(
            state.first_step, y, state.y_eval, state.f_info, trial, state.search_state)

        def accepted(descent_state):
            (value, aux_eval), jac = value_and_jacfwd(lambda v: fn(v, args),
                                                      has_aux=True)(state.y_eval)
            f_info = optx.FunctionInfo.ResidualJac(value, lx.MatrixLinearOperator(jac))
            descent_state = self.descent.query(state.y_eval, f_info, descent_state)
            y_scale = self.atol + self.rtol * jnp.abs(state.y_eval)
            f_scale = self.atol + self.rtol * jnp.abs(value)
            terminate = (self.norm(jnp.abs(state.y_eval - y) / y_scale) < 1) & (
                self.norm(jnp.abs(value - state.f_info.residual) / f_scale) < 1)
            return state.y_eval, f_info, aux_eval, descent_state, terminate

        def rejected(descent_state):
            return y, state.f_info, state.aux, descent_state, jnp.array(False)

        y, f_info, aux, descent_state, terminate = jax.lax.cond(
            accept, accepted, rejected, state.descent_state)
        y_descent, descent_result = self.descent.step(step_size, descent_state)
        result = optx.RESULTS.where(search_result == optx.RESULTS.successful, descent_result,
                                    search_result)
        prev_aux = jax.tree_util.tree_map(
            lambda a, b: jnp.where(state.first_step, a, b), aux, state.aux)
        return y, _ScaledLMState(
            first_step=jnp.array(False), y_eval=y + y_descent, search_state=search_state,
            f_info=f_info, aux=aux, descent_state=descent_state, terminate=terminate,
            result=result, num_steps=state.num_steps + 1,
            num_accepted_steps=state.num_accepted_steps + jnp.where(accept, 1, 0)), prev_aux

    def terminate(self, fn, y, args, options, state, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def default_solver(rtol: float = 0.0, atol: float = 1e-10) -> ScaledLevenbergMarquardt:
    """:class:`ScaledLevenbergMarquardt` at these tolerances."""
    return ScaledLevenbergMarquardt(rtol=rtol, atol=atol)


def solve_least_squares(fn: Callable[[Any, Any], Array], y0: Float[Array, " k"], args: Any = None,
                        *, solver: GaussNewtonLike | None = None, max_steps: int = 50,
                        step_se_tol: float = 1e-2, budget=None,
                        throw: bool = False) -> LeastSquaresSolution:
    """Minimise ``|fn(y, args)|^2`` over ``y`` from ``y0`` by an optimistix solver.

    Call it inside ``jax.jit`` (or ``eqx.filter_jit``): it is one compiled loop. The residual is
    differentiated by :func:`dense_jacobian` (one forward pass per evaluation); pass a residual
    in whitened units (unit noise) for `step_se` to read in standard errors.

    **Arguments:**
    - `fn`: ``(y, args) -> (m,)`` residual, ``y`` flat ``(k,)``. A parameter held fixed in a
      compiled superset is best multiplied by a 0/1 mask inside ``fn``: its column is zero and
      the damped step leaves it.
    - `y0`: the start, ``(k,)``, float64.
    - `args`: arrays ``fn`` reads (the record, weights, masks...).
    - `solver`: :class:`ScaledLevenbergMarquardt` or an ``optimistix.AbstractGaussNewton``; default
      :class:`ScaledLevenbergMarquardt` ``(rtol=1e-8, atol=1e-10)``.
    - `max_steps`: optimistix's step budget.
    - `step_se_tol`: :class:`StationaryStop`'s step left, in standard errors.
    - `budget`: a traced step budget (at most `max_steps`): calls with different budgets share
      one compilation. ``budget=1`` evaluates the residual and its Jacobian at `y0` (the
      solution's `residual` and `jacobian`) and stops.
    - `throw`: raise (``equinox.EquinoxRuntimeError``) if not converged; under ``vmap`` keep
      ``False`` and read ``converged``.

    **Returns:** a :class:`LeastSquaresSolution`.
    """
    inner = default_solver() if solver is None else solver
    wrapped = dense_jacobian(fn)
    sol = optx.least_squares(wrapped, StationaryStop(inner, step_se_tol, budget), y0, args,
                             max_steps=max_steps, throw=False)
    f_info = sol.state.f_info
    decrement, cost, rank = _decrement(sol.state, inner.descent)
    m = f_info.residual.shape[0]
    sigma2 = cost / jnp.maximum(m - rank, 1)
    tiny = jnp.finfo(jnp.result_type(float)).tiny
    step_se = jnp.where(cost > tiny, jnp.sqrt(decrement / jnp.maximum(sigma2, tiny)), 0.0)
    finite = jnp.isfinite(cost)
    converged = finite & ((sol.result == optx.RESULTS.successful)
                          | (step_se <= STATIONARY_SE))
    if throw:
        converged = eqx.error_if(converged, ~converged,
                                 "the least-squares fit did not converge: start closer, raise "
                                 "max_steps, or free fewer parameters")
    return LeastSquaresSolution(
        value=sol.value, residual=f_info.residual, jacobian=f_info.jac.as_matrix(), cost=cost,
        step_se=step_se, result=sol.result, num_steps=sol.stats["num_steps"],
        converged=converged, solver_name=type(inner).__name__)


_RESULT_TEXT = (
    (optx.RESULTS.nonlinear_max_steps_reached, "it used all {steps} steps"),
    (optx.RESULTS.max_steps_reached, "it used all {steps} steps"),
    (optx.RESULTS.nonlinear_divergence, "the iterates diverged"),
    (optx.RESULTS.nonfinite, "the model gave non-finite values"),
    (optx.RESULTS.singular, "the linear solve of a step was singular"),
)


def convergence_note(sol: LeastSquaresSolution, what: str) -> str | None:
    """The line a report gives a fit that did not converge, or ``None`` for one that did:
    ``"the nominal fit: LevenbergMarquardt did not converge (it used all 20 steps; the
    Gauss-Newton step left is 3.2e+02 standard errors); its figures are those of the last
    accepted step"``. A non-finite cost says so (the model could not be evaluated there)."""
    if bool(sol.converged):
        return None
    if not bool(jnp.isfinite(sol.cost)):
        why = "the model could not be evaluated at the start or the steps left its reach"
    else:
        code = sol.result
        msg = optx.RESULTS[code]
        why = next((t.format(steps=int(sol.num_steps)) for r, t in _RESULT_TEXT
                    if msg == optx.RESULTS[r]), "it stopped without meeting its tests")
        why += f"; the Gauss-Newton step left is {float(sol.step_se):.2g} standard errors"
    return (f"{what}: {sol.solver_name} did not converge ({why}); its figures are those of the "
            "last accepted step")
