"""Identification on the vibrating platform (spec platform-vibration §8-§10).

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

from ..models.platform import (
    AXES,
    COEFF_NAMES,
    drift_regressor,
    kinematic_matrix,
    platform_matrix,
    specific_force_direction,
)
from ._linalg import scaled_lstsq
from ._result import AbstractNamedEstimate

__all__ = ["amplitude_first_harmonic", "kappa_from_accelerometers", "forgetting_blend",
           "accelerometer_amplitude_error", "regression_design", "platform_regression",
           "PlatformFit", "two_amplitude_resolution", "check_sampling"]


def check_sampling(dt: float, frequency_hz: float):
    """Refuse sampling below the Nyquist rate of the vibration (the estimators need the
    fundamental in band)."""
    if dt <= 0:
        raise ValueError(f"sampling interval {dt} s must be positive")
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


def amplitude_first_harmonic(ts, acc, frequency_hz: float):
    """``a0`` (g) from the first harmonic of ``S = |f|^2`` (S19b); ``acc`` (..., n, 3) in g.

    The sums run over the longest whole number of cycles of the *sampled* sequence, where they
    are exact for a sinusoid."""
    n_use = _whole_cycles(ts, frequency_hz)
    s = jnp.sum(jnp.asarray(acc)[..., :n_use, :] ** 2, axis=-1)
    w = 2 * jnp.pi * frequency_hz * jnp.asarray(np.asarray(ts, float)[:n_use])
    c1 = 2.0 / n_use * jnp.sum(s * jnp.cos(w), axis=-1)
    s1 = 2.0 / n_use * jnp.sum(s * jnp.sin(w), axis=-1)
    return 0.5 * jnp.sqrt(c1**2 + s1**2)


def kappa_from_accelerometers(acc, ts=None, frequency_hz=None):
    """``kappa = mean |f|^2`` (S19c), exact for any zero-mean vibration over whole periods;
    ``acc`` (..., n, 3) in g. Give ``ts`` and ``frequency_hz`` to average over whole cycles of
    the sampled sequence only."""
    acc = jnp.asarray(acc)
    if ts is not None and frequency_hz is not None:
        acc = acc[..., :_whole_cycles(ts, frequency_hz), :]
    return jnp.mean(jnp.sum(acc**2, axis=-1), axis=-1)


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


@eqx.filter_jit
def _position_design(ts, angles, conditions):
    """Rows of (S22) for one position: centred ``y - h`` and centred ``F`` (n, 3) and (n, 3, 30)."""
    dt = jnp.diff(ts)

    def integrands(y):
        mk = kinematic_matrix(y[1], y[2])
        n = specific_force_direction(y, conditions.mounting)
        g = drift_regressor(n, jnp.ones_like(conditions.kappa), conditions.kappa)
        we = platform_matrix(y).T @ conditions.earth_rate_base()
        return -mk @ g, -mk @ we

    fg, fh = jax.vmap(integrands)(angles)

    def cumtrapz(f):
        inc = 0.5 * (f[1:] + f[:-1]) * dt.reshape((-1,) + (1,) * (f.ndim - 1))
        return jnp.concatenate([jnp.zeros_like(f[:1]), jnp.cumsum(inc, axis=0)])

    big_f, h = cumtrapz(fg), cumtrapz(fh)
    y = angles - h
    return y - y.mean(0), big_f - big_f.mean(0)


def regression_design(ts, angles, conditions):
    """Stack (S22) over positions: ``angles`` (P, n, 3), ``conditions`` stacked over P.
    Returns ``(b, A)`` with ``A`` (P*n*3, 30) and ``b`` (P*n*3,)."""
    y, f = jax.vmap(_position_design, in_axes=(None, 0, 0))(jnp.asarray(ts), angles, conditions)
    return y.reshape(-1), f.reshape(-1, 30)


class PlatformFit(AbstractNamedEstimate):
    """Regression estimate of the free coefficients (internal rad/s); ``noise_std`` is the angle
    residual std (rad); ``singular_values`` of the column-normalised design."""

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    noise_std: jax.Array
    singular_values: jax.Array
    n_positions: int = eqx.field(static=True)

    def full(self, fixed=None) -> dict:
        """All 30 coefficients: the free ones estimated, the others at ``fixed`` (default 0)."""
        out = {n: 0.0 for n in COEFF_NAMES} | dict(fixed or {})
        return out | self.as_dict()


def platform_regression(ts, records: Sequence, conditions: Sequence, *,
                        free: Sequence[str] = COEFF_NAMES, noise_std=None) -> PlatformFit:
    """Batch regression (S22) of the averaged model.

    **Arguments:**
    - `ts`: sample times of one dwell (s, shared by every position).
    - `records`: one array of gimbal angles per test amplitude, shape (P, n, 3) in rad.
    - `conditions`: one stacked :class:`PlatformConditions` per record (its ``kappa`` is the
      amplitude estimate the averaged model uses).
    - `free`: coefficients to estimate (e.g. all but ``D_oo_*`` for a one-amplitude fit); with a
      rank-deficient choice the solution is the minimum-norm one in scaled units.
    - `noise_std`: angle noise (rad); default estimated from the residual.
    """
    free = tuple(free)
    unknown = [n for n in free if n not in COEFF_NAMES]
    if unknown:
        raise ValueError(f"unknown coefficient(s) {unknown}; names are D_<term>_<axis>, e.g. "
                         "D_oo_x")
    if len(records) != len(conditions):
        raise ValueError(f"{len(records)} records but {len(conditions)} conditions; give one "
                         "stacked PlatformConditions per record")
    bs, As = [], []
    for ang, cond in zip(records, conditions):
        b, a = regression_design(ts, jnp.asarray(ang), cond)
        bs.append(b)
        As.append(a)
    b, a = jnp.concatenate(bs), jnp.concatenate(As)
    idx = jnp.array([COEFF_NAMES.index(n) for n in free])
    scale = jnp.array([1.0 if n.startswith(("D_f", "D_i_", "D_o_", "D_s_")) else 0.03
                       for n in free]) * (np.pi / 180 / 3600)
    a = a[:, idx] * scale
    x, cov_unit, s = scaled_lstsq(a, b)
    res = b - a @ x
    n_pos = sum(int(np.shape(r)[0]) for r in records)
    k = int(jnp.sum(s > 1e-12 * s[0]))
    dof = max(res.shape[0] - k - 3 * n_pos, 1)
    sigma2 = jnp.sum(res**2) / dof if noise_std is None else jnp.asarray(noise_std) ** 2
    cov = sigma2 * cov_unit * jnp.outer(scale, scale)
    return PlatformFit(free, x * scale, jnp.sqrt(jnp.diag(cov)), cov, jnp.sqrt(sigma2), s, n_pos)


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
