"""Estimation of the 12 instrument errors and initial misalignments from a Schuler-test record
(docs/rigs/schuler.md).

Measurements (docs/rigs/schuler.md): the model velocities ``V1 V2`` and the platform's rotation since ``t0``
(record channels ``rot1..3``, a rotation vector). Against a model trajectory the attitude residual is
(S12): $E = \\Delta R\\,\\Delta R_{model}^T = I - [\\mathbf z_\\theta\\times]$,
$\\mathbf z_\\theta = -\\mathrm{vee}(\\tfrac12(E - E^T))$.

Two estimators of $\\boldsymbol\\theta = $ (``nu1 nu2 nu3 D11 D22 df1 df2 K11 K22 alpha10 alpha20
dA0``), both with the prior $N(0, \\Sigma_\\theta)$:

- :func:`schuler_filter` — the source's single-pass linearised Kalman filter on the 17-state
  error model about the error-free reference, in square-root form under ``lax.scan``, with an RTS
  smoother. Biased for realistic scale errors (the linearisation misses the Schuler-frequency
  shift).
- :func:`fit_schuler` — the iterated Gauss-Newton on the nonlinear model, as optimistix's
  trust-region Levenberg-Marquardt: forward-mode sensitivities through diffrax, the prior as
  extra residual rows, first on the first period and then on the whole record. It reaches the
  Cramer-Rao bound.

Both run under ``jax.vmap`` over records (Monte Carlo).
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import units
from ..models.schuler import (
    PARAM_NAMES,
    SchulerConditions,
    SchulerRig,
    error_matrix,
    platform_matrix,
)
from ..rotations import matrix_to_rotvec, rotvec_to_matrix
from ..simulate import integrate, trajectory
from ._linalg import scaled_lstsq
from ._lstsq import (
    LeastSquaresSolution,
    ScaledLevenbergMarquardt,
    convergence_note,
    solve_least_squares,
)
from ._result import AbstractNamedEstimate
from .kalman import rts_smoother, square_root_filter

__all__ = ["attitude_residual", "schuler_residuals", "SchulerEstimate", "fit_schuler",
           "schuler_filter", "check_schuler_record", "check_rotation_units", "linearised_model",
           "measurement_variations", "prior_factor"]

THETA_NAMES = PARAM_NAMES


def attitude_residual(rot_meas, rot_model):
    """$\\mathbf z_\\theta = -\\mathrm{vee}(\\tfrac12(E - E^T))$ with
    $E = \\Delta R_{meas}\\Delta R_{model}^T$ (S12), from two rotation vectors (rad)."""
    e = rotvec_to_matrix(rot_meas) @ rotvec_to_matrix(rot_model).T
    return -0.5 * jnp.stack([e[2, 1] - e[1, 2], e[0, 2] - e[2, 0], e[1, 0] - e[0, 1]])


def schuler_residuals(rig: SchulerRig, conditions: SchulerConditions, ts, y, params, *,
                      adjoint=None, throw: bool = True):
    """Measured minus modelled channels, ``(N, 5)``: velocity differences (m/s) and the attitude
    residual (S12) (rad). ``throw=False``: a failed integration gives non-finite residuals
    instead of an error."""
    model = integrate(rig, params, conditions, ts, adjoint=adjoint, throw=throw)
    att = jax.vmap(attitude_residual)(y[:, 2:], model[:, 2:])
    return jnp.concatenate([y[:, :2] - model[:, :2], att], axis=1)


class SchulerEstimate(AbstractNamedEstimate):
    """Estimates of the 12 unknowns (internal units, parameter axis last).

    - ``covariance`` (12, 12) posterior covariance (prior included); ``stderr`` its root diagonal.
    - ``iterations``: optimistix steps of the fit (0 for the filter); ``residual_rms`` (5,): RMS of
      the measured minus modelled channels at the estimate (:func:`schuler_residuals`: m/s,
      rad), for either method (the filter's standardized innovations are in its extras).
    - ``method``: ``"gauss-newton"`` or ``"kalman"``.
    - ``converged``: the fit reached a solution by the rule of every fit in gyrojax
      (:mod:`gyrojax.estimate._lstsq`); True for the filter, a single pass.
    - ``last_step_se``: the Gauss-Newton step left at the estimate, in standard errors; NaN for
      the filter.
    - ``solution``: the fit's :class:`~gyrojax.estimate.LeastSquaresSolution` (``None`` for the
      filter); :meth:`note` reads it.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    iterations: jax.Array
    residual_rms: jax.Array
    method: str = eqx.field(static=True)
    converged: jax.Array | bool = True
    last_step_se: jax.Array | float = float("nan")
    solution: LeastSquaresSolution | None = None

    def note(self, what: str = "the fit") -> str | None:
        """The line a report gives a fit that did not converge (``None`` if it did, or for the
        filter): :func:`~gyrojax.estimate.convergence_note`."""
        return None if self.solution is None else convergence_note(self.solution, what)

    def correlation(self):
        s = self.stderr
        return self.covariance / (s[..., :, None] * s[..., None, :])

    def table(self, truth=None) -> str:
        """Values and standard errors in display units (deg/h, ppm, m/s^2, arcmin)."""
        space = SchulerRig().param_space
        lines = [f"{'name':8s} {'estimate':>12s} {'std error':>11s} {'unit':7s}"
                 + ("  truth" if truth is not None else "")]
        for i, n in enumerate(self.names):
            p = space[n]
            row = (f"{n:8s} {float(p.to_display(self.values[i])):12.5g} "
                   f"{float(p.to_display(self.stderr[i])):11.3g} {p.display_unit:7s}")
            if truth is not None:
                row += f"  {float(p.to_display(truth[n])):.5g}"
            lines.append(row)
        return "\n".join(lines)


def _prior_std(rig, prior_std):
    space = rig.param_space
    base = {n: space[n].scale for n in THETA_NAMES}
    base.update(prior_std or {})
    return jnp.array([float(base[n]) for n in THETA_NAMES])


def check_rotation_units(y):
    """Refuse attitude channels ``rot1 rot2 rot3`` (columns 2-4 of ``y``) that cannot be a
    rotation vector in rad: its angle ``|rot|`` is at most pi (0.01 rad of noise allowed). A
    record in deg or arcmin fails the fit ("not converged", its last step 1e4 standard errors)."""
    from ..io import check_radians

    angle = np.linalg.norm(np.asarray(y, float)[:, 2:5], axis=1)[:, None]
    check_radians(angle, ("rotation angle |rot1 rot2 rot3|",), np.pi + 0.01,
                  "a rotation vector's largest angle", convert=("rot1", "rot2", "rot3"))


def check_schuler_record(ts, y, conditions: SchulerConditions, *, uniform: bool = False):
    """Validate a Schuler-test record at the boundary: ``ts`` (N,) strictly increasing, ``y``
    (N, 5) finite with the velocity and attitude channels, spanning at least half a Schuler
    period; with ``uniform`` also a constant sample interval (the filter's discretisation)."""
    ts = np.asarray(ts, dtype=float)
    y = np.asarray(y, dtype=float)
    if y.ndim != 2 or y.shape[1] != 5:
        raise ValueError(f"the record has channels of shape {y.shape[1:]}: the Schuler test needs "
                         "V1 V2 (model velocities, m/s) and rot1 rot2 rot3 (platform rotation since "
                         "t0 from the gimbal angles, rad); missing gimbal angles cannot be replaced")
    if ts.shape != (y.shape[0],) or np.any(np.diff(ts) <= 0):
        raise ValueError("t must be strictly increasing, one time per sample")
    if not np.all(np.isfinite(y)):
        bad = np.argwhere(~np.isfinite(y))[0]
        raise ValueError(f"non-finite value at t={ts[bad[0]]} s, channel {bad[1]}; remove or "
                         "interpolate the gap")
    check_rotation_units(y)
    half = 0.5 * float(conditions.schuler_period)
    if ts[-1] - ts[0] < half:
        raise ValueError(f"the record spans {ts[-1] - ts[0]:.0f} s, less than half a Schuler period "
                         f"({half:.0f} s): the errors are not separable; record 1-4 periods (t is in s: "
                         "a record in min spans 60x less)")
    if uniform:
        dt = np.diff(ts)
        if np.max(np.abs(dt - dt[0])) > 1e-6 * dt[0]:
            raise ValueError(f"inconsistent sampling: intervals from {dt.min():g} to {dt.max():g} s; "
                             "the filter needs a constant interval (resample the record)")


# -- Gauss-Newton ---------------------------------------------------------------------------
class _FitOutcome(NamedTuple):
    theta: jax.Array  # internal units
    covariance: jax.Array  # posterior (prior included)
    iterations: jax.Array  # optimistix steps (rejected trust-region trials included)
    residual_rms: jax.Array  # per channel
    converged: jax.Array
    step_se: jax.Array  # the Gauss-Newton step left at the solution, in standard errors
    solution: LeastSquaresSolution


def _fit_prior(rig, conditions, ts, y, weights, sig, u0, max_iter, tol, names=THETA_NAMES,
               fixed=None, mask=None, step_se_tol=1e-2):
    """Prior-regularised least squares over ``names`` (prior sd ``sig``, start ``u0`` in prior
    units) by :func:`~gyrojax.estimate.solve_least_squares` (optimistix, trust-region
    Levenberg-Marquardt); ``fixed``: other parameters held at given values (an effect's decay
    time...); ``mask`` (per name, default all 1): a name with 0 is held at its start (its
    Jacobian column and prior row zeroed, so the damped step leaves it); ``step_se_tol``: the
    fit stops when the Gauss-Newton step left is under this many standard errors.

    ``weights`` broadcast to per-sample (N, 5), the mask and the step budget ``max_iter``
    passed as arrays before the jit boundary, so every caller (a staged first pass, refits of
    different effect sets over one superset ``names``, any ``max_iter``) reuses one compiled
    solver. ``tol``: optimistix's test
    on successive iterates (prior standard deviations).

    Returns a :class:`_FitOutcome`; ``converged`` by the rule of every fit in gyrojax
    (:mod:`gyrojax.estimate._lstsq`)."""
    y = jnp.asarray(y, dtype=float)
    weights = jnp.broadcast_to(jnp.asarray(weights, dtype=float), y.shape)
    mask = jnp.ones(len(names)) if mask is None else jnp.asarray(mask, dtype=float)
    fixed = {k: jnp.asarray(v, dtype=float) for k, v in (fixed or {}).items()}
    if not 1 <= int(max_iter) <= _MAX_STEPS:
        raise ValueError(f"max_iter={max_iter}: give 1 to {_MAX_STEPS} optimistix steps")
    return _fit_prior_jit(rig, conditions, jnp.asarray(ts, dtype=float), y, weights,
                          jnp.asarray(sig, dtype=float), jnp.asarray(u0, dtype=float),
                          jnp.asarray(int(max_iter)), jnp.asarray(float(tol)), names, fixed, mask,
                          jnp.asarray(float(step_se_tol)))


_START_SE = 0.5  # the staged first pass's stop, in standard errors of its own fit
_MAX_STEPS = 200  # the compiled bound; each call's budget is a traced max_iter below it


@eqx.filter_jit
def _fit_prior_jit(rig, conditions, ts, y, weights, sig, u0, max_iter, tol, names, fixed, mask,
                   step_se_tol):
    def resid(u, _):
        params = fixed | dict(zip(names, u * mask * sig, strict=True))
        # a trial step that leaves the solver's reach gives a non-finite cost: it is rejected
        r = schuler_residuals(rig, conditions, ts, y, params, adjoint=diffrax.ForwardMode(),
                              throw=False)
        return jnp.concatenate([(r * weights).ravel(), u * mask])

    sol = solve_least_squares(resid, u0 * mask, max_steps=_MAX_STEPS, budget=max_iter,
                              step_se_tol=step_se_tol, solver=ScaledLevenbergMarquardt(atol=tol))
    u = sol.value * mask
    _, cov, _ = scaled_lstsq(sol.jacobian, sol.residual)
    params = fixed | dict(zip(names, u * sig, strict=True))
    r = schuler_residuals(rig, conditions, ts, y, params)
    return _FitOutcome(u * sig, cov * jnp.outer(sig, sig), sol.num_steps,
                       jnp.sqrt(jnp.mean(r**2, axis=0)), sol.converged, sol.step_se, sol)


def fit_schuler(rig: SchulerRig, ts: Float[ArrayLike, " n"], y: Float[ArrayLike, "n 5"],
                conditions: SchulerConditions, *, sigma_v: float = 0.05,
                sigma_theta: float = units.ARCMIN, prior_std: dict | None = None,
                max_iter: int = 40, tol: float = 1e-3, staged: bool = True,
                check: bool = True) -> SchulerEstimate:
    """Iterated Gauss-Newton on the nonlinear model (docs/rigs/schuler.md), as optimistix's trust-region
    Levenberg-Marquardt (:func:`~gyrojax.estimate.solve_least_squares`).

    **Arguments:** ``ts`` (N,) in s; ``y`` (N, 5): ``V1 V2`` (m/s) and ``rot1..3`` (rad);
    ``sigma_v`` (m/s) and ``sigma_theta`` (rad) the measurement noise; ``prior_std`` overrides the
    prior standard deviations (internal units, by name); ``max_iter``: optimistix steps per pass;
    ``tol``: its test on successive iterates (prior standard deviations); with ``staged`` and a
    record longer than 1.2 periods the first period is fitted first (a safeguard
    against the Schuler-frequency ambiguity). ``check=False`` skips the host-side validation
    (for ``jax.vmap`` over records).

    **Returns:** a :class:`SchulerEstimate`; ``converged`` False (and ``note`` says why) when
    the fit did not reach a solution.
    """
    if check:
        check_schuler_record(ts, y, conditions)
    ts = jnp.asarray(ts, dtype=float)
    y = jnp.asarray(y, dtype=float)
    sig = _prior_std(rig, prior_std)
    w = 1.0 / jnp.array([sigma_v, sigma_v, sigma_theta, sigma_theta, sigma_theta])
    # the staged first pass (the first period, later samples weighted 0) and the full fit share
    # one compiled solver (``_fit_prior`` passes the weights as arrays)
    w = jnp.broadcast_to(w, y.shape)
    u = jnp.zeros(len(THETA_NAMES))
    period = float(conditions.schuler_period)
    if staged and float(ts[-1] - ts[0]) > 1.2 * period:
        n1 = int(np.searchsorted(np.asarray(ts), float(ts[0]) + period)) + 1
        first = (jnp.arange(y.shape[0]) < n1)[:, None]
        # the first pass is the full fit's start: within half a standard error of its own
        # optimum is close enough (the full fit takes it from there)
        u = _fit_prior(rig, conditions, ts, y, w * first, sig, u, max_iter, tol,
                       step_se_tol=_START_SE).theta / sig
    gn = _fit_prior(rig, conditions, ts, y, w, sig, u, max_iter, tol)
    return SchulerEstimate(names=THETA_NAMES, values=gn.theta,
                           stderr=jnp.sqrt(jnp.diagonal(gn.covariance)),
                           covariance=gn.covariance, iterations=gn.iterations,
                           residual_rms=gn.residual_rms, method="gauss-newton",
                           converged=gn.converged, last_step_se=gn.step_se,
                           solution=gn.solution)


# -- linearised Kalman filter -------------------------------------------------------------
def _perturbed_measurement(x, state_ref, state_ref0, rot_ref):
    """The measurement (S12) of the state ``X_ref + dX(x)`` against the reference: velocity
    variations and the attitude residual, as a function of the 17-state ``x``."""
    st = state_ref + jnp.stack([x[0], x[1], -x[4], x[2], x[3], 0.0])
    st0 = state_ref0 + jnp.stack([x[14], x[15], -x[16], 0.0, 0.0, 0.0])
    rel = platform_matrix(st[0], st[1], st[2]) @ platform_matrix(st0[0], st0[1], st0[2]).T
    return jnp.concatenate([x[2:4], attitude_residual(matrix_to_rotvec(rel), rot_ref)])


def prior_factor(rig: SchulerRig, prior_std: dict | None = None):
    """Square factor ``S0`` (17, 17) of ``P0 = T Sigma_theta T^T`` (rank 12) and ``T`` (17, 12)."""
    tmat = _transfer()
    sig = _prior_std(rig, prior_std)
    return jnp.concatenate([tmat * sig[None, :], jnp.zeros((17, 5))], axis=1), tmat


def _transfer(n_theta=12):
    """``T`` (17, 12): x(t0) = T theta."""
    t = np.zeros((17, n_theta))
    t[5:, :] = np.eye(n_theta)
    t[0, 9], t[1, 10], t[4, 11] = 1.0, 1.0, 1.0
    return jnp.asarray(t)


@eqx.filter_jit
def linearised_model(rig: SchulerRig, conditions: SchulerConditions, ts, ref):
    """The discrete linear model of the single-pass filter about the trajectory with errors ``ref`` on the
    uniform sample times ``ts``: ``Phi_k = expm(A(t_{k+1/2}) dt)`` (N-1, 17, 17), ``H_k`` (N, 5, 17) the
    autodiff Jacobian of (S12), the reference states (N, 6) and rotation vectors (N, 3)."""
    dt = ts[1] - ts[0]
    mids = 0.5 * (ts[1:] + ts[:-1])
    t_all = jnp.concatenate([jnp.stack([ts[:-1], mids], axis=1).ravel(), ts[-1:]])
    states = trajectory(rig, ref, conditions, t_all)
    x_ref, x_mid = states[::2], states[1::2]
    phis = jax.vmap(lambda s: jax.scipy.linalg.expm(error_matrix(rig, ref, conditions, s) * dt))(
        x_mid)
    rot_ref = jax.vmap(lambda s: rig.observe(0.0, s, ref, conditions)[2:])(x_ref)
    hs = jax.vmap(lambda s, r: jax.jacfwd(_perturbed_measurement)(jnp.zeros(17), s, x_ref[0], r))(
        x_ref, rot_ref)
    return phis, hs, x_ref, rot_ref


def measurement_variations(y, x_ref, rot_ref):
    """The measurements ``z`` (N, 5): measured minus reference velocities and the attitude residual (S12)."""
    return jnp.concatenate([y[:, :2] - x_ref[:, 3:5],
                            jax.vmap(attitude_residual)(y[:, 2:], rot_ref)], axis=1)


@eqx.filter_jit
def _filter(rig, conditions, ts, y, ref, sqrt_r, s0, x0, smooth):
    phis, hs, x_ref, rot_ref = linearised_model(rig, conditions, ts, ref)
    z = measurement_variations(y, x_ref, rot_ref)
    n = ts.shape[0]
    res = square_root_filter(x0, s0, phis, jnp.zeros((n - 1, 17)), jnp.zeros((n - 1, 17, 17)),
                             hs, sqrt_r, z)
    smoothed = rts_smoother(res, phis)[0] if smooth else res.x_filt
    return res.x_filt[-1], res.p_filt[-1], res.innovations, smoothed


def schuler_filter(rig: SchulerRig, ts: Float[ArrayLike, " n"], y: Float[ArrayLike, "n 5"],
                   conditions: SchulerConditions, *,
                   sigma_v: float = 0.05, sigma_theta: float = units.ARCMIN,
                   prior_std: dict | None = None, params_ref=None, smooth: bool = False,
                   check: bool = True):
    """The source's single-pass linearised Kalman filter (docs/rigs/schuler.md), square-root form.

    The reference is the error-free trajectory (or ``params_ref``, e.g. a previous estimate:
    the prior mean of the correction is then ``-theta_ref``, and one pass is one Gauss-Newton
    step). ``Phi_k = expm(A(t_{k+1/2}) dt)``, ``H_k`` the autodiff Jacobian of (S12), ``Q = 0``.
    With ``Q = 0`` the constants' final filtered values are also their smoothed values.

    **Returns:** ``(estimate, extras)``: a :class:`SchulerEstimate` (``values`` = reference +
    correction) and a dict with the standardized ``innovations`` (N, 5) and the 17 ``states``
    (N, 17) (RTS-smoothed when ``smooth``).
    """
    if check:
        check_schuler_record(ts, y, conditions, uniform=True)
    ts = jnp.asarray(ts, dtype=float)
    y = jnp.asarray(y, dtype=float)
    # the full parameter dict with float arrays: one compiled filter with or without params_ref
    ref = rig.param_space.make(params_ref)
    theta_ref = jnp.array([ref[n] for n in THETA_NAMES])
    s0, tmat = prior_factor(rig, prior_std)
    x0 = tmat @ (-theta_ref)
    sqrt_r = jnp.diag(jnp.array([sigma_v, sigma_v, sigma_theta, sigma_theta, sigma_theta]))
    xf, pf, innov, states = _filter(rig, conditions, ts, y, ref, sqrt_r, s0, x0, smooth)
    theta = theta_ref + xf[5:]
    cov = pf[5:, 5:]
    # the output residual at the estimate, as Gauss-Newton reports it (one more integration)
    r = schuler_residuals(rig, conditions, ts, y, ref | dict(zip(THETA_NAMES, theta, strict=True)),
                          throw=False)
    est = SchulerEstimate(names=THETA_NAMES, values=theta, stderr=jnp.sqrt(jnp.diagonal(cov)),
                          covariance=cov, iterations=jnp.asarray(0),
                          residual_rms=jnp.sqrt(jnp.mean(r**2, axis=0)), method="kalman")
    return est, {"innovations": innov, "states": states}
