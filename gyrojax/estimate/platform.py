"""Identification on the vibrating platform (docs/rigs/platform.md).

- vibration amplitude from the accelerometers: the first-harmonic estimator (S19b), the mean of
  ``|f|^2`` (S19c, exact for any zero-mean vibration), the forgetting-factor blend (source (18)),
  and the first-order effect of accelerometer errors (S20a-b);
- batch integral regression (S22) of the averaged model on the gimbal-angle records of a schedule
  (each position's unknown initial angles eliminated by centring), solved by QR, never normal
  equations; several records (amplitudes) stack into one joint fit, each with its own ``kappa``;
- the two-amplitude resolution (S21) of the ``D_oo = 0`` fits.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..models.platform import (
    AXES,
    COEFF_NAMES,
    drift_regressor,
    kinematic_matrix,
    platform_matrix,
    specific_force_direction,
)
from ._linalg import scaled_lstsq, value_and_jacfwd
from ._result import AbstractNamedEstimate

__all__ = ["amplitude_first_harmonic", "kappa_from_accelerometers", "record_kappas",
           "forgetting_blend",
           "accelerometer_amplitude_error", "platform_regression_design", "platform_regression",
           "PlatformFit", "two_amplitude_resolution", "check_sampling"]


def check_sampling(dt: float, frequency_hz: float):
    """Refuse sampling below the Nyquist rate of the vibration (the estimators need the
    fundamental in band)."""
    if not dt > 0:
        raise ValueError(f"sampling interval {dt} s must be positive")
    if not (np.isfinite(frequency_hz) and frequency_hz > 0):
        raise ValueError(f"vibration frequency {frequency_hz} Hz must be positive (the source "
                         "vibrates at 15 Hz; a static run is an amplitude of 0 g)")
    if 1.0 / dt <= 2.0 * frequency_hz:
        raise ValueError(f"sampling at {1 / dt:g} Hz is below the Nyquist rate of the "
                         f"{frequency_hz:g} Hz vibration ({2 * frequency_hz:g} Hz); sample faster "
                         "(the source uses 25 ms for 15 Hz)")


def _whole_cycles(ts, frequency_hz):
    """Number of leading samples that cover whole cycles of the sampled vibration sequence (at
    15 Hz and 25 ms: multiples of 8 samples = 3 cycles); all samples if there is no short period."""
    from fractions import Fraction

    ts = np.asarray(ts, float)
    n = ts.shape[-1]
    dt = float(ts[1] - ts[0])
    cyc = Fraction(frequency_hz * dt).limit_denominator(1000)
    n0 = cyc.denominator if abs(float(cyc) - frequency_hz * dt) < 1e-9 else 1
    return n - n % n0 if n >= n0 else n


def amplitude_first_harmonic(ts: Float[ArrayLike, " n"], acc: Float[ArrayLike, "*batch n 3"],
                             frequency_hz: float) -> Float[Array, "*batch"]:
    """``a0`` (g) from the first harmonic of ``S = |f|^2`` (S19b); ``acc`` (..., n, 3) in g.

    The sums run over the longest whole number of cycles of the *sampled* sequence, where they
    are exact for a sinusoid."""
    n_use = _whole_cycles(ts, frequency_hz)
    s = jnp.sum(jnp.asarray(acc)[..., :n_use, :] ** 2, axis=-1)
    w = 2 * jnp.pi * frequency_hz * jnp.asarray(np.asarray(ts, float)[:n_use])
    c1 = 2.0 / n_use * jnp.sum(s * jnp.cos(w), axis=-1)
    s1 = 2.0 / n_use * jnp.sum(s * jnp.sin(w), axis=-1)
    return 0.5 * jnp.sqrt(c1**2 + s1**2)


def kappa_from_accelerometers(acc: Float[ArrayLike, "*batch n 3"],
                              ts: Float[ArrayLike, " n"] | None = None,
                              frequency_hz: float | None = None) -> Float[Array, "*batch"]:
    """``kappa = mean |f|^2`` (S19c), exact for any zero-mean vibration over whole periods;
    ``acc`` (..., n, 3) in g. Give ``ts`` and ``frequency_hz`` to average over whole cycles of
    the sampled sequence only."""
    acc = jnp.asarray(acc)
    if ts is not None and frequency_hz is not None:
        acc = acc[..., :_whole_cycles(ts, frequency_hz), :]
    return jnp.mean(jnp.sum(acc**2, axis=-1), axis=-1)


def record_kappas(data, s) -> list[float]:
    """Each table amplitude's ``kappa`` (S19c) from a split platform record ``data`` (``(A, P,
    n, 8)``, :func:`~gyrojax.models.platform_schedule.split_record`) of schedule ``s``: the
    accelerometers (m/s^2 in the file, g here) over whole vibration cycles, averaged over the
    positions. Each must lie within a factor 2 of the schedule's ``1 + a0^2 / 2`` (``a0`` the
    table amplitude over the attenuation): a schedule in other units (m/s^2 for g) or with
    another record's amplitudes is refused, with both numbers."""
    from ..models.platform_schedule import accelerations_g, dwell_times

    ts = jnp.asarray(dwell_times(s))
    out = []
    for k, amp in enumerate(s["table_amplitudes_g"]):
        kap = float(np.mean(np.asarray(kappa_from_accelerometers(
            jnp.asarray(accelerations_g(data[k])), ts, s["frequency_hz"]))))
        want = 1.0 + 0.5 * (float(amp) / s["attenuation"]) ** 2
        if not 0.5 <= kap / want <= 2.0:
            raise ValueError(
                f"the accelerometers give kappa = mean |f|^2 = {kap:#.4g} g^2 at table "
                f"amplitude {amp:g} g, where the schedule (attenuation {s['attenuation']:g}) "
                f"implies 1 + a0^2/2 = {want:#.4g} g^2; give the schedule the record was taken with "
                "(table_amplitudes_g in g, amplitude-major dwells)")
        out.append(kap)
    return out


def forgetting_blend(prior, running_estimates, lam: float = 0.95):
    """Source (18): ``a(n) = lam^n prior + (1 - lam^n) a_hat(n)`` per sample ``n = 1..N``."""
    est = jnp.asarray(running_estimates)
    w = lam ** jnp.arange(1, est.shape[-1] + 1)
    return w * prior + (1 - w) * est


def accelerometer_amplitude_error(n, dk, misalignment, bias, a0):
    """First-order relative errors of ``a0_hat`` and ``kappa_hat`` from accelerometer scale
    errors ``dk`` (3,), misalignment matrix (3x3, zero diagonal) and bias (3,) in g (S20a), and
    the relative error ``Delta`` of the quadratic/cross coefficients (S20b).
    Returns ``(da0_rel, dkappa_rel, Delta)``."""
    n = jnp.asarray(n)
    rho = 2.0 * n @ ((jnp.diag(jnp.asarray(dk)) + jnp.asarray(misalignment)) @ n)
    bn = jnp.asarray(bias) @ n
    kappa = 1 + 0.5 * a0**2
    da0 = rho + bn
    dkappa = rho + 2 * bn / kappa
    a0h = a0 * (1 + da0)
    delta = (a0**2 - a0h**2) / (a0h**2 + 2)
    return da0, dkappa, delta


def cumulative_trapezoid(f, ts):
    """The trapezoid rule's running integral of ``f`` (samples on the leading axis) over the
    times ``ts``, from 0 at ``ts[0]`` (scipy's ``cumulative_trapezoid(..., initial=0)``).

    A ``lax.scan`` adds the increments in time order, as ``numpy.cumsum`` does; ``jnp.cumsum``
    lowers to a ``reduce_window`` as long as the axis, which XLA's CPU backend runs ~4x slower
    on a dwell's 4,000 x 90 columns."""
    dt = jnp.diff(ts).reshape((-1,) + (1,) * (f.ndim - 1))
    inc = 0.5 * (f[1:] + f[:-1]) * dt

    def step(acc, x):
        acc = acc + x
        return acc, acc

    _, tail = jax.lax.scan(step, jnp.zeros_like(f[0]), inc)
    return jnp.concatenate([jnp.zeros_like(f[:1]), tail])


@eqx.filter_jit
def position_design(ts, angles, conditions, acc=None):
    """Rows of (S22) for one position: centred ``y - h`` and centred ``F`` (n, 3) and (n, 3, 30).
    With ``acc`` (n, 3; g) the drift uses the measured vibration sample by sample (the original,
    non-averaged model (S10) with ``1 + A_1 = f . n``) instead of ``kappa``."""

    def integrands(y, f):
        mk = kinematic_matrix(y[1], y[2])
        n = specific_force_direction(y, conditions.mounting)
        if f is None:
            g = drift_regressor(n, jnp.ones_like(conditions.kappa), conditions.kappa)
        else:
            f1 = f @ n
            g = drift_regressor(n, f1, f1 * f1)
        we = platform_matrix(y).T @ conditions.earth_rate_base()
        return -mk @ g, -mk @ we

    fg, fh = jax.vmap(integrands)(angles, acc)
    big_f, h = cumulative_trapezoid(fg, ts), cumulative_trapezoid(fh, ts)
    y = angles - h
    return y - y.mean(0), big_f - big_f.mean(0)


def platform_regression_design(ts, angles, conditions, acc=None):
    """Stack (S22) over positions: ``angles`` (P, n, 3), ``conditions`` stacked over P (and the
    accelerometers (P, n, 3) for the non-averaged model). Returns ``(b, A)`` with ``A``
    (P*n*3, 30) and ``b`` (P*n*3,)."""
    y, f = jax.vmap(position_design, in_axes=(None, 0, 0, 0))(jnp.asarray(ts), angles,
                                                                conditions, acc)
    return y.reshape(-1), f.reshape(-1, 30)


class PlatformFit(AbstractNamedEstimate):
    """Estimate of the free coefficients (internal rad/s); ``noise_std`` is the angle residual
    std (rad); ``singular_values`` of the column-normalised design (the regression's).

    Batch Gauss-Newton (:func:`platform_gauss_newton`) also reports ``converged`` (optimistix's
    test passed, or the step left at the solution is under ``STATIONARY_SE``), ``num_steps`` and
    ``remaining_step_se`` (that step in standard errors); a regression is a direct solve: True,
    0 and 0."""

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    noise_std: jax.Array
    singular_values: jax.Array
    n_positions: int = eqx.field(static=True)
    converged: jax.Array | bool = True
    num_steps: jax.Array | int = 0
    remaining_step_se: jax.Array | float = 0.0

    def full(self, fixed=None) -> dict:
        """All 30 coefficients: the free ones estimated, the others at ``fixed`` (default 0)."""
        out = {n: 0.0 for n in COEFF_NAMES} | dict(fixed or {})
        return out | self.as_dict()


def _check_inputs(ts, records, conditions, free) -> tuple:
    """The batch fits' arguments: known coefficient names, one conditions per record, records
    of shape ``(P, len(ts), 3)``, finite angles (a NaN sample made every estimate NaN) and
    strictly increasing dwell times. Returns ``free`` as a tuple."""
    free = tuple(free)
    unknown = [n for n in free if n not in COEFF_NAMES]
    if unknown:
        raise ValueError(f"unknown coefficient(s) {unknown}; names are D_<term>_<axis>, e.g. "
                         "D_oo_x")
    if len(records) != len(conditions):
        raise ValueError(f"{len(records)} records but {len(conditions)} conditions; give one "
                         "stacked PlatformConditions per record")
    from ..io import check_times

    t = check_times(ts, source="ts (one dwell's sample times)")
    for k, r in enumerate(records):
        a = np.asarray(r, dtype=float)
        if a.ndim != 3 or a.shape[1:] != (t.size, 3):
            raise ValueError(f"records[{k}] has shape {a.shape}; give (positions, {t.size}, 3) "
                             "gimbal angles in rad, one row per sample of ts")
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            p_, i, j = (int(x) for x in bad[0])
            raise ValueError(f"records[{k}] has {len(bad)} non-finite angle(s), the first at "
                             f"position {p_}, sample {i} (t = {t[i]:g} s), angle {j}; gyrojax "
                             "does not drop samples silently: remove or interpolate them")
    return free


def platform_regression(ts: Float[ArrayLike, " n"], records: Sequence[Float[ArrayLike, "p n 3"]],
                        conditions: Sequence, *,
                        free: Sequence[str] = COEFF_NAMES, noise_std=None,
                        accelerations: Sequence | None = None) -> PlatformFit:
    """Batch regression (S22) of the averaged model, or of the original model (S10) with the
    measured vibration.

    **Arguments:**
    - `ts`: sample times of one dwell (s, shared by every position).
    - `records`: one array of gimbal angles per test amplitude, shape (P, n, 3) in rad.
    - `conditions`: one stacked :class:`PlatformConditions` per record (its ``kappa`` is the
      amplitude estimate the averaged model uses).
    - `free`: coefficients to estimate (e.g. all but ``D_oo_*`` for a one-amplitude fit); with a
      rank-deficient choice the solution is the minimum-norm one in scaled units.
    - `noise_std`: angle noise (rad); default estimated from the residual.
    - `accelerations`: the accelerometer records (one (P, n, 3) array in g per record): use the
      non-averaged drift law with ``1 + A_1 = f . n^p`` at every sample instead of ``kappa``.
    """
    free = _check_inputs(ts, records, conditions, free)
    n_pos = sum(int(np.shape(r)[0]) for r in records)
    accs = (None,) * len(records) if accelerations is None else tuple(
        jnp.asarray(a) for a in accelerations)
    x, cov_unit, s, rss, m = _regression_core(jnp.asarray(ts),
                                              tuple(jnp.asarray(r) for r in records),
                                              tuple(conditions), accs, free)
    scale = _scales(free)
    k = int(jnp.sum(s > 1e-12 * s[0]))
    dof = max(m - k - 3 * n_pos, 1)
    sigma2 = rss / dof if noise_std is None else jnp.asarray(noise_std) ** 2
    cov = sigma2 * cov_unit * jnp.outer(scale, scale)
    return PlatformFit(free, x * scale, jnp.sqrt(jnp.diag(cov)), cov, jnp.sqrt(sigma2), s, n_pos)


def _scales(free):
    return jnp.array([1.0 if n.startswith(("D_f", "D_i_", "D_o_", "D_s_")) else 0.03
                      for n in free]) * (np.pi / 180 / 3600)


@eqx.filter_jit
def _regression_core(ts, records, conditions, accs, free):
    """Design of every record, column selection and scaling, and the QR/SVD solve, in one jit."""
    bs, As = [], []
    for ang, cond, acc in zip(records, conditions, accs):
        b, a = platform_regression_design(ts, ang, cond, acc)
        bs.append(b)
        As.append(a)
    b, a = jnp.concatenate(bs), jnp.concatenate(As)
    idx = np.array([COEFF_NAMES.index(n) for n in free])
    a = a[:, idx] * _scales(free)
    x, cov_unit, s = scaled_lstsq(a, b)
    res = b - a @ x
    return x, cov_unit, s, jnp.sum(res**2), b.shape[0]


def two_amplitude_resolution(fit1: dict, fit2: dict, kappa1: float, kappa2: float) -> dict:
    """(S21): all 30 coefficients from two ``D_oo = 0`` fits at ``kappa1 != kappa2`` (dicts of
    the 30 names; the other coefficients are taken from fit 1, as the source does)."""
    if abs(kappa1 - kappa2) < 1e-6 * max(kappa1, kappa2):
        raise ValueError(f"equal amplitudes (kappa {kappa1:g} and {kappa2:g}): the two-amplitude "
                         "method needs two different vibration amplitudes")
    if min(kappa1, kappa2) < 1:
        raise ValueError("kappa = 1 + a0^2/2 must be >= 1")
    out = dict(fit1)
    for ax in AXES:
        f1, f2 = fit1[f"D_f_{ax}"], fit2[f"D_f_{ax}"]
        doo = (f1 - f2) / (kappa1 - kappa2)
        out[f"D_oo_{ax}"] = doo
        out[f"D_f_{ax}"] = (kappa1 * f2 - kappa2 * f1) / (kappa1 - kappa2)
        out[f"D_ii_{ax}"] = fit1[f"D_ii_{ax}"] + doo
        out[f"D_ss_{ax}"] = fit1[f"D_ss_{ax}"] + doo
    return out


class PlatformKalman(eqx.Module):
    """Outcome of :func:`platform_kalman`: final estimates and standard errors of the free
    coefficients (rad/s), and their history at the end of every dwell (``history``, ``(R*P, k)``)
    and every ``stride`` samples (``trace``, ``(R*P*n/stride, k)``) for identification curves."""

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    history: jax.Array
    trace: jax.Array
    trace_t: jax.Array

    def as_dict(self) -> dict:
        return dict(zip(self.names, self.values))

    def stderr_dict(self) -> dict:
        return dict(zip(self.names, self.stderr))


@eqx.filter_jit
def _kalman_scan(angles, conds, p_d, noise_std, q_coeff, dt, free, stride):
    from ..models.platform import PlatformRig

    rig = PlatformRig()
    base = rig.param_space.make()
    idx = np.array([COEFF_NAMES.index(n) for n in free])
    k = len(free)
    r = noise_std**2 * jnp.eye(3)
    h = jnp.concatenate([jnp.eye(3), jnp.zeros((3, k))], axis=1)
    q = jnp.zeros((3 + k, 3 + k)).at[3:, 3:].set(q_coeff * dt * jnp.eye(k))
    eye = jnp.eye(3 + k)

    def step_fn(cond):
        def f(x):
            ang, d = x[:3], x[3:]
            p = base | dict(zip(COEFF_NAMES, jnp.zeros(30).at[idx].set(d)))
            k1 = rig.vector_field(0.0, ang, p, cond)
            k2 = rig.vector_field(0.0, ang + dt * k1, p, cond)
            return jnp.concatenate([ang + 0.5 * dt * (k1 + k2), d])

        return f

    def dwell(carry, inp):
        d, pd = carry
        ang, cond = inp
        x = jnp.concatenate([ang[0], d])
        pmat = jnp.zeros((3 + k, 3 + k)).at[:3, :3].set(r).at[3:, 3:].set(pd)
        f = step_fn(cond)

        def sample(c, z):
            x, pm = c
            fx, jac = value_and_jacfwd(f)(x)
            pm = jac @ pm @ jac.T + q
            s = h @ pm @ h.T + r
            gain = jnp.linalg.solve(s, h @ pm).T
            x = fx + gain @ (z - fx[:3])
            a = eye - gain @ h
            pm = a @ pm @ a.T + gain @ r @ gain.T  # Joseph form
            return (x, pm), x[3:]

        (x, pm), xs = jax.lax.scan(sample, (x, pmat), ang[1:])
        return (x[3:], pm[3:, 3:]), (x[3:], xs[::stride])

    (d, pd), (hist, trace) = jax.lax.scan(dwell, (jnp.zeros(k), p_d), (angles, conds))
    return d, pd, hist, trace


def platform_kalman(ts: Float[ArrayLike, " n"], records: Sequence[Float[ArrayLike, "p n 3"]],
                    conditions: Sequence, *,
                    free: Sequence[str] = COEFF_NAMES, noise_std: float = 4.84813681109536e-06,
                    prior_std=None, q_coeff: float = 0.0, stride: int = 100) -> PlatformKalman:
    """The source's identification (docs/rigs/platform.md (a)): an extended Kalman filter on the averaged
    model with state ``(alpha, beta, gamma, D_free)`` over every dwell of every record in turn
    (``lax.scan``). The angle states restart at each dwell from its first sample; ``D`` and its
    covariance carry over. Transition: one Heun step of (S12)-(S14) per sample, linearised by
    autodiff; measurement: the three angles with white noise ``noise_std`` (rad).

    ``prior_std``: initial standard deviation of the coefficients (default 10x their scales);
    ``q_coeff``: random-walk PSD of the coefficients ((rad/s)^2/s; 0 = constants).
    """
    from ..models.platform import PlatformRig

    space = PlatformRig().param_space
    free = tuple(free)
    k = len(free)
    ts = jnp.asarray(ts)
    dt = float(ts[1] - ts[0])
    scales = space.scales(free)
    p_d = jnp.diag(jnp.asarray((10 * scales if prior_std is None
                                else np.broadcast_to(prior_std, (k,))) ** 2))
    angles = jnp.concatenate([jnp.asarray(a) for a in records])
    conds = jax.tree.map(lambda *c: jnp.concatenate(c), *conditions)
    d, pd, hist, trace = _kalman_scan(angles, conds, p_d, jnp.asarray(noise_std),
                                      jnp.asarray(q_coeff), dt, free, stride)
    n_dw = angles.shape[0]
    t_tr = (jnp.arange(n_dw)[:, None] * (ts[-1] + dt) + ts[1::stride][None, :trace.shape[1]])
    return PlatformKalman(free, d, jnp.sqrt(jnp.diag(pd)), hist, trace.reshape(-1, k),
                          t_tr.reshape(-1))


@eqx.filter_jit
def _gn_solve(ts, angles, conds, x0, free, rtol, atol, max_steps, noise_var):
    import diffrax
    import optimistix as optx

    from ..models.platform import PlatformRig
    from ..simulate import integrate
    from ._lstsq import solve_least_squares

    rig = PlatformRig()
    base = rig.param_space.make()
    k = len(free)
    scale = _scales(free)
    off_scale = np.pi / 180 / 3600  # arcsec

    def residual(x, args):
        p = base | dict(zip(free, x[:k] * scale))
        c0 = eqx.tree_at(lambda c: c.angles0, conds,
                         angles[:, 0, :] + x[k:].reshape(-1, 3) * off_scale)
        pred = jax.vmap(lambda c: integrate(rig, p, c, ts, adjoint=diffrax.ForwardMode(),
                                            throw=False))(c0)[..., :3]
        return (pred - angles).reshape(-1)

    sol = solve_least_squares(residual, x0, solver=optx.GaussNewton(rtol=rtol, atol=atol),
                              max_steps=max_steps, step_se_tol=0.0)
    _, cov_unit, _ = scaled_lstsq(sol.jacobian, sol.residual)
    # the noise given (> 0), or the residual's with the fit's dof
    sigma2 = jnp.where(noise_var > 0, noise_var,
                       sol.cost / max(sol.residual.shape[0] - x0.shape[0], 1))
    return sol.value, cov_unit, sigma2, sol.converged, sol.num_steps, sol.step_se


def platform_gauss_newton(ts: Float[ArrayLike, " n"],
                          records: Sequence[Float[ArrayLike, "p n 3"]], conditions: Sequence, *,
                          free: Sequence[str] = COEFF_NAMES, start: dict | None = None,
                          noise_std=None, rtol: float = 1e-8, atol: float = 1e-10,
                          max_steps: int = 20) -> PlatformFit:
    """Batch Gauss-Newton (optimistix, forward sensitivities through diffrax) of the averaged ODE
    model on the gimbal-angle records: unknowns the free coefficients and the initial angles of
    every dwell; started from ``start`` (e.g. the regression estimate) or zero. ``noise_std``
    (rad): the angle noise for the covariance (default: the residual's). The result's
    ``converged`` says whether the fit ended at a solution within ``max_steps``; it does not
    raise when not."""
    free = _check_inputs(ts, records, conditions, free)
    angles = jnp.concatenate([jnp.asarray(a) for a in records])
    conds = jax.tree.map(lambda *c: jnp.concatenate(c), *conditions)
    scale = _scales(free)
    d0 = jnp.array([float((start or {}).get(n, 0.0)) for n in free]) / scale
    x0 = jnp.concatenate([d0, jnp.zeros(3 * angles.shape[0])])
    noise_var = jnp.asarray(-1.0 if noise_std is None else float(noise_std) ** 2)
    x, cov_unit, sigma2, converged, steps, step_se = _gn_solve(
        jnp.asarray(ts), angles, conds, x0, free, rtol, atol, max_steps, noise_var)
    k = len(free)
    cov = sigma2 * cov_unit[:k, :k] * jnp.outer(scale, scale)
    return PlatformFit(free, x[:k] * scale, jnp.sqrt(jnp.diag(cov)), cov, jnp.sqrt(sigma2),
                       jnp.zeros(0), int(angles.shape[0]), converged, steps, step_se)
