"""Constant (rectified) azimuth error of the gyrotheodolite under translational vibration, and its
algorithmic compensation (docs/rigs/gyrotheodolite.md).

The products of oscillating angles in (1) — ``mgl (gamma n_X + beta n_Z)`` and, with the rig's
``roll_rate_coupling``, the kinematic ``H alpha_dot gamma`` — have a nonzero mean. Averaging the
azimuth equation over the vibration (``<alpha_dot> = <beta_dot> = 0``) gives the constant error

$$k_\\alpha\\langle\\alpha\\rangle = H\\langle\\dot\\alpha\\gamma\\rangle
  + mgl\\,\\langle\\gamma n_X + \\beta n_Z\\rangle .$$

:func:`constant_vibration_error` evaluates every mean by harmonic balance from the first-order
phasors (``<Im(P e^{jwt}) Im(Q e^{jwt})> = Re(P conj Q)/2``): exact to second order in the vibration
amplitude, vectorizable, and checked in the tests against diffrax simulations of the full nonlinear
rig. The compensation subtracts

$$\\langle\\alpha\\rangle_{\\rm est} = \\arcsin\\frac{\\langle\\hat{\\dot\\alpha}\\gamma\\rangle}
  {\\omega_3\\cos\\varphi}$$

computed with the true rate or with the observer's estimate; :func:`compensate` is the same
algorithm on recorded signals. The formula ignores the pendulous mean torque (``pendulous``); in
the model (1) that part is usually the larger one
(docs/decisions/0008-gyrotheodolite-observer-and-vibration.md).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import units
from ..estimate.observer import frequency_response
from ..models.gyrotheodolite import GyrotheodoliteConditions, GyrotheodoliteRig

__all__ = ["VibrationError", "constant_vibration_error", "compensate", "CompensationStudy",
           "compensation_monte_carlo", "FrequencyStudy", "frequency_study"]


class VibrationError(eqx.Module):
    """Constant azimuth error and its compensation (rad; ``rate_roll*`` in rad^2/s).

    - ``mean_alpha``: the constant error ``<alpha>``; ``kinematic`` and ``pendulous``: its parts
      from ``H <alpha_dot gamma>`` and ``mgl <gamma n_X + beta n_Z>``.
    - ``rate_roll``: ``<alpha_dot gamma>``; ``rate_roll_est``: ``<alpha_dot_hat gamma>`` with the
      observer's estimate.
    - ``correction_true`` / ``correction_est``: the correction with the true / estimated rate;
      ``residual_true`` / ``residual_est``: ``mean_alpha`` minus them (NaN where the arcsine's
      argument exceeds 1: the formula is then undefined).
    """

    mean_alpha: jax.Array
    kinematic: jax.Array
    pendulous: jax.Array
    rate_roll: jax.Array
    rate_roll_est: jax.Array
    correction_true: jax.Array
    correction_est: jax.Array
    residual_true: jax.Array
    residual_est: jax.Array


def _correction(rate_roll, latitude):
    return jnp.arcsin(rate_roll / (units.EARTH_RATE * jnp.cos(latitude)))


def constant_vibration_error(rig: GyrotheodoliteRig, params, conditions: GyrotheodoliteConditions,
                             gain) -> VibrationError:
    """Steady-state constant error under ``conditions``' vibration and its compensation with the
    true rate and with the observer of gain ``gain`` (shape ``(4,)``), by harmonic balance.

    Pure JAX: ``jax.vmap`` it over conditions (amplitude, frequency, direction) and parameters.
    """
    plant, observer = _unit_responses(rig, params, conditions, gain,
                                      jnp.atleast_1d(conditions.omega))
    return _vibration_error(rig, params, conditions, plant[0], observer[0])


def _unit_responses(rig, params, conditions, gain, omegas):
    """Plant ``(jwE - A)^{-1} G`` and observer ``(jwE - A + KC)^{-1} K``, each ``(F, 3)``
    (``alpha``, ``alpha_dot``, ``beta``), in one call (one Hessenberg reduction per system,
    elementwise work per frequency)."""
    a, c, g, _ = rig.state_space(params, conditions)
    k = jnp.asarray(gain, dtype=float).reshape(4)
    resp = frequency_response(jnp.stack([a, a - jnp.outer(k, c[0])]), jnp.stack([g, k]), omegas,
                              c=jnp.eye(4)[:3])
    return resp[0], resp[1]


def _vibration_error(rig, params, conditions, plant, observer) -> VibrationError:
    """Means of the products from the unit responses at ``conditions.omega`` (elementwise)."""
    w = conditions.omega
    nx = conditions.n_m * jnp.cos(conditions.eps_v + conditions.psi0)
    nz = conditions.n_m * jnp.sin(conditions.eps_v + conditions.psi0)
    x = plant * nx[..., None]  # phasors of (alpha, alpha_dot, beta, beta_dot)
    xh = observer * x[..., :1]  # the observer driven by the measured alpha
    gam = rig.roll_response(params, w) * nz

    def mean(p, q):
        return 0.5 * jnp.real(p * jnp.conj(q))

    rate_roll = mean(x[..., 1], gam)
    rate_roll_est = mean(xh[..., 1], gam)
    ka = rig.k_alpha(params, conditions)
    kin = params["H"] * rate_roll / ka if rig.roll_rate_coupling else jnp.zeros_like(rate_roll)
    pend = params["mgl"] * (mean(gam, nx) + mean(x[..., 2], nz)) / ka
    if not rig.vibration_torque:
        pend = jnp.zeros_like(pend)
    total = kin + pend
    corr_true = _correction(rate_roll, conditions.latitude)
    corr_est = _correction(rate_roll_est, conditions.latitude)
    return VibrationError(mean_alpha=total, kinematic=kin, pendulous=pend, rate_roll=rate_roll,
                          rate_roll_est=rate_roll_est, correction_true=corr_true,
                          correction_est=corr_est, residual_true=total - corr_true,
                          residual_est=total - corr_est)


def compensate(ts: Float[ArrayLike, " n"], alpha: Float[ArrayLike, " n"],
               rate: Float[ArrayLike, " n"], gamma: Float[ArrayLike, " n"], latitude_deg: float):
    """The compensation algorithm on recorded signals over one averaging window.

    ``ts`` (s), ``alpha`` (rad), ``rate`` (the true or estimated azimuth rate, rad/s), ``gamma``
    (rad), all ``(N,)``. The window should span an integer number of vibration periods and be
    long compared with the slow north-seeking mode. Returns ``(mean_alpha, correction,
    compensated)`` in rad, with ``compensated = mean_alpha - correction``.
    """
    ts = jnp.asarray(ts, dtype=float)
    span = ts[-1] - ts[0]

    def avg(f):
        return jnp.trapezoid(f, ts) / span

    mean_alpha = avg(alpha)
    corr = _correction(avg(rate * gamma), latitude_deg * units.DEG)
    return mean_alpha, corr, mean_alpha - corr


class CompensationStudy(eqx.Module):
    """Monte Carlo draws (``n_m`` in g, ``omega`` in rad/s, ``psi0`` in rad) and their
    :class:`VibrationError` (each field shape ``(N,)``)."""

    n_m: jax.Array
    omega: jax.Array
    psi0: jax.Array
    error: VibrationError
    omega0: float = eqx.field(static=True)

    def summary(self) -> dict:
        """Over the draws: the constant error (arcsec), the pendulous share of it, and the fraction
        ``|residual| / |constant error|`` left by each compensation (median and 95th percentile;
        draws where the formula is undefined are counted and left out)."""
        e = jax.tree.map(np.asarray, self.error)
        big = np.abs(e.mean_alpha)
        out = {"omega0_per_s": self.omega0, "draws": int(big.size),
               "median_constant_error_arcsec": float(np.median(big) / units.ARCSEC),
               "median_pendulous_share": float(np.median(np.abs(e.pendulous) / big))}
        for label, r in (("true_rate", e.residual_true), ("observer", e.residual_est)):
            frac = np.abs(r) / big
            out[f"median_residual_{label}"] = float(np.nanmedian(frac))
            out[f"p95_residual_{label}"] = float(np.nanquantile(frac, 0.95))
            out[f"undefined_{label}"] = int(np.sum(np.isnan(frac)))
        return out


def compensation_monte_carlo(rig: GyrotheodoliteRig, params, key, draws: int, *, omega0: float,
                             latitude_deg: float = 50.45, n_m=(1e-5, 1e-3), omega=(5.0, 200.0),
                             psi0=(0.0, 2 * np.pi), eps_v: float = 0.0) -> CompensationStudy:
    """Constant vibration error and its compensation over random vibrations.

    ``n_m`` (g) is drawn log-uniform in its range, ``omega`` (rad/s) and ``psi0`` (rad) uniform;
    the observer has all four poles at ``-omega0`` (closed-form gains, recomputed per draw under
    ``vmap``). ``key``: a ``jax.random`` key.
    """
    if draws < 1:
        raise ValueError(f"draws={draws} must be >= 1")
    for name, (lo, hi) in (("n_m", n_m), ("omega", omega)):
        if not 0 < lo <= hi:
            raise ValueError(f"{name} range ({lo}, {hi}) must satisfy 0 < low <= high")
    if not omega0 > 0:
        raise ValueError(f"omega0={omega0}: the observer pole magnitude must be > 0 (1/s)")
    k1, k2, k3 = jax.random.split(key, 3)
    amp = jnp.exp(jax.random.uniform(k1, (draws,), minval=np.log(n_m[0]), maxval=np.log(n_m[1])))
    om = jax.random.uniform(k2, (draws,), minval=omega[0], maxval=omega[1])
    ps = jax.random.uniform(k3, (draws,), minval=psi0[0], maxval=psi0[1])
    err = _batched(rig, params, jnp.asarray(latitude_deg * units.DEG, dtype=float), float(omega0),
                   amp, om, ps,
                   jnp.asarray(eps_v, dtype=float))
    return CompensationStudy(amp, om, ps, err, float(omega0))


@eqx.filter_jit
def _batched(rig, params, latitude, omega0, amp, om, ps, eps_v):
    # the plant and the observer do not change between draws: one Hessenberg reduction each,
    # then elementwise work per draw
    cond = GyrotheodoliteConditions(latitude, amp, om, jnp.broadcast_to(eps_v, om.shape), ps)
    gain = rig.observer_gains(params, cond, omega0)
    plant, observer = _unit_responses(rig, params, cond, gain, om)
    return _vibration_error(rig, params, cond, plant, observer)


class FrequencyStudy(eqx.Module):
    """Fig. 1 of the source as numbers: the plant's rate response to ``n_X`` and the observer's
    estimate of it for several ``omega0``.

    - ``omegas`` (rad/s, ``(F,)``), ``omega0s`` (1/s, ``(W,)``);
    - ``plant``: ``alpha_dot / n_X`` (rad/s per g, complex ``(F,)``), i.e. ``W_IT2``;
    - ``observer``: ``alpha_dot_hat / n_X`` (complex ``(W, F)``), i.e. ``W_HY2``;
    - ``gains`` ``(W, 4)`` and ``poles`` ``(W, 4)`` (eigenvalues of ``A - K C``);
    - ``error``: ``|W_HY2 / W_IT2 - 1|`` and ``amplitude_error``: ``| |W_HY2| / |W_IT2| - 1 |``.
    """

    omegas: jax.Array
    omega0s: jax.Array
    plant: jax.Array
    observer: jax.Array
    gains: jax.Array
    poles: jax.Array
    error: jax.Array
    amplitude_error: jax.Array

    def bandwidth(self, level: float = 0.1, *, amplitude: bool = False) -> np.ndarray:
        """For each ``omega0``, the highest grid frequency up to which the error stays below
        ``level`` from the lowest grid frequency on; NaN where it exceeds ``level`` already there."""
        err = np.asarray(self.amplitude_error if amplitude else self.error)
        w = np.asarray(self.omegas)
        out = np.full(err.shape[0], np.nan)
        for i, e in enumerate(err):
            bad = np.flatnonzero(e >= level)
            if bad.size == 0:
                out[i] = w[-1]
            elif bad[0] > 0:
                out[i] = w[bad[0] - 1]
        return out

    def table(self, level: float = 0.1) -> list[dict]:
        """One row per ``omega0``: gains (SI), poles, and the ``level`` bandwidths (rad/s)."""
        bw, bwa = self.bandwidth(level), self.bandwidth(level, amplitude=True)
        rows = []
        for i, w0 in enumerate(np.asarray(self.omega0s)):
            k = np.asarray(self.gains[i])
            p = np.asarray(self.poles[i])
            rows.append({"omega0": float(w0), "k1": float(k[0]), "k2": float(k[1]),
                         "k3": float(k[2]), "k4": float(k[3]),
                         "poles": [[float(z.real), float(z.imag)] for z in p],
                         "max_pole_offset_rel": float(np.max(np.abs(p + w0)) / w0),
                         "bandwidth": None if np.isnan(bw[i]) else float(bw[i]),
                         "amplitude_bandwidth": None if np.isnan(bwa[i]) else float(bwa[i])})
        return rows


def frequency_study(rig: GyrotheodoliteRig, params, conditions: GyrotheodoliteConditions,
                    omega0s, omegas=None) -> FrequencyStudy:
    """Plant and observer rate responses (docs/rigs/gyrotheodolite.md, (10)-(12)) on a frequency grid (default
    ``logspace(-2, 3, 1001)`` rad/s), vectorized over frequency and ``omega0``; gains are the
    closed-form (corrected) ones."""
    omega0s = jnp.atleast_1d(jnp.asarray(omega0s, dtype=float))
    if not bool(jnp.all(omega0s > 0)):
        raise ValueError(f"omega0={np.asarray(omega0s)}: observer pole magnitudes must be > 0 (1/s)")
    omegas = jnp.logspace(-2, 3, 1001) if omegas is None else jnp.asarray(omegas, dtype=float)
    gains, plant, obs, err, amp_err = _frequency_study(rig, params, conditions, omega0s, omegas)
    a, c, _, _ = (np.asarray(m) for m in rig.state_space(params, conditions))
    poles = np.stack([np.linalg.eigvals(a - np.outer(k, c[0])) for k in np.asarray(gains)])
    return FrequencyStudy(omegas=omegas, omega0s=omega0s, plant=plant, observer=obs, gains=gains,
                          poles=jnp.asarray(poles), error=err, amplitude_error=amp_err)


@eqx.filter_jit
def _frequency_study(rig, params, conditions, omega0s, omegas):
    a, c, g, _ = rig.state_space(params, conditions)
    gains = jax.vmap(lambda w0: rig.observer_gains(params, conditions, w0))(omega0s)
    systems = jnp.concatenate([a[None], a[None] - jax.vmap(lambda k: jnp.outer(k, c[0]))(gains)])
    resp = frequency_response(systems, jnp.concatenate([g[None], gains]), omegas,
                              c=jnp.eye(4)[:2])  # (1+W, F, 2): alpha and alpha_dot
    plant, obs = resp[0, :, 1], resp[1:, :, 1] * resp[0, None, :, 0]
    return gains, plant, obs, jnp.abs(obs / plant - 1), jnp.abs(jnp.abs(obs) / jnp.abs(plant) - 1)
