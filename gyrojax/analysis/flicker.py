"""White + flicker measurement noise as a Gauss-Markov sum: whitening and the REML level.

The noise of a channel is ``sigma * (v_k + sqrt(rho) * sum_i x_i(t_k))``: white ``v`` of unit
variance plus :data:`FLICKER_DECADES` first-order Gauss-Markov processes ``x_i`` of unit
stationary variance with correlation times one decade apart from the sample interval up
(``dt, 10 dt, ..., 10^4 dt``) -- the standard GM-sum approximation of flicker noise, whose Allan
deviation is flat at ``FLICKER_ADEV_PER_B * B`` from ~2 to ~2000 samples (the generator's
:func:`gyrojax.models.imu._flicker` draws the same process). The bias-instability coefficient is
``B = sigma * sqrt(rho) / FLICKER_STD_PER_B``.

:func:`whiten` is the Kalman filter's innovations sequence, each innovation divided by its
standard deviation: exactly ``L^-1 x`` for the Cholesky factor ``L`` of the covariance
``I + rho K`` (time order), in linear time, so the first ``n`` whitened rows depend on the first
``n`` samples only (a held-out tail is whitened given the train part, never the reverse).
:func:`reml_rho` estimates ``rho`` by restricted maximum likelihood on a residual with the
columns of a regression (the fitted model's Jacobian) projected out, so the slow terms that the
regression absorbs do not bias the flicker level low; ``sigma`` is profiled out.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["FLICKER_DECADES", "FLICKER_ADEV_PER_B", "FLICKER_STD_PER_B", "flicker_taus",
           "innovations", "whiten", "reml_rho", "rho_to_b"]

FLICKER_DECADES = 5
FLICKER_ADEV_PER_B = 0.664  # Allan deviation floor of flicker noise per unit B (IEEE 952)
# one GM per decade at equal variances has its Allan deviation flat at ~0.75 x its standard
# deviation between ~2 and ~2000 correlation-time units (measured on 2e6 samples; tests/test_imu)
FLICKER_STD_PER_B = FLICKER_ADEV_PER_B / 0.75


def flicker_taus(t0: float) -> np.ndarray:
    """Correlation times of the GM sum, one decade apart from ``t0`` (s)."""
    return t0 * 10.0 ** np.arange(FLICKER_DECADES)


def rho_to_b(rho, sigma):
    """Bias-instability coefficient ``B`` (units of ``sigma``) of the variance ratio ``rho``."""
    return np.asarray(sigma) * np.sqrt(np.asarray(rho)) / FLICKER_STD_PER_B


@jax.jit
def innovations(x, dts, rho, taus):
    """Whitened innovations of the columns ``x`` (``n x m``) and the log-determinant of the
    covariance ``I + rho K`` at the sample spacings ``dts`` (``n``; the first, ``inf``, starts
    the filter at the stationary prior); ``taus`` the GM correlation times. Traceable (use it
    inside a jitted fit)."""
    k = taus.shape[0]
    h = jnp.ones(k)

    def step(carry, inp):
        xh, p = carry
        xk, dt = inp
        phi = jnp.exp(-dt / taus)
        # time update (the first sample: the stationary prior, dt = inf -> phi = 0)
        xh = phi[:, None] * xh
        p = phi[:, None] * p * phi[None, :] + rho * jnp.diag(1 - phi ** 2)
        s = h @ p @ h + 1.0
        g = p @ h / s
        e = xk - h @ xh
        xh = xh + g[:, None] * e[None, :]
        p = p - jnp.outer(g, g) * s
        return (xh, p), (e / jnp.sqrt(s), jnp.log(s))

    xh0 = jnp.zeros((k, x.shape[1]))
    p0 = jnp.zeros((k, k))
    _, (e, logs) = jax.lax.scan(step, (xh0, p0), (x, dts))
    return e, jnp.sum(logs)


def _spacings(t):
    t = np.asarray(t, float)
    return np.concatenate([[np.inf], np.diff(t)])


def whiten(x, t, rho, t0: float):
    """``L^-1 x`` along the first axis of ``x`` (``n`` or ``n x m``) for the unit-white +
    ``rho`` x GM-sum covariance at the sample times ``t`` (s); ``t0`` sets the GM taus."""
    x = np.asarray(x, float)
    cols = x.reshape(len(x), -1)
    e, _ = innovations(jnp.asarray(cols), jnp.asarray(_spacings(t)), jnp.asarray(float(rho)),
                        jnp.asarray(flicker_taus(t0)))
    return np.asarray(e).reshape(x.shape)


@jax.jit
def _profile_ll(rho, r, u, live, dts, taus):
    """REML profile log-likelihood of ``r`` with the orthonormal columns ``u`` projected out
    (``live`` marks them; the rest are zero padding to a fixed width), ``sigma`` profiled:
    ``-(n-p)/2 log(RSS/(n-p)) - logdet/2 - log|U_w'U_w|/2``."""
    e, logdet = innovations(jnp.concatenate([r[:, None], u], axis=1), dts, rho, taus)
    ew, uw = e[:, 0], e[:, 1:]
    q, rr = jnp.linalg.qr(uw)
    rss = ew @ ew - jnp.sum(jnp.where(live, q.T @ ew, 0.0) ** 2)
    d = jnp.abs(jnp.diag(rr))
    n, p = r.shape[0], jnp.sum(live)
    return (-0.5 * (n - p) * jnp.log(rss / (n - p)) - 0.5 * logdet
            - jnp.sum(jnp.where(live, jnp.log(jnp.where(live, d, 1.0)), 0.0)))


_profile_grid = jax.jit(jax.vmap(_profile_ll, in_axes=(0, None, None, None, None, None)))


def reml_rho(r, x, t, t0: float, *, log10_range=(-8.0, 1.0), points: int = 13):
    """REML estimate of ``rho`` for the residual ``r`` (``n``) of a regression on the columns
    ``x`` (``n x m``; rank-deficient columns are fine) at sample times ``t``.

    Returns ``(rho, lr)``: the estimate (0 where the likelihood peaks at the lower end of
    ``log10_range``, i.e. no flicker visible) and the likelihood-ratio statistic against
    ``rho = 0`` (compare with the 50:50 mixture of chi2_0 and chi2_1). A grid of ``points`` in
    ``log10 rho``, then a finer one across the best point's neighbours."""
    r = np.asarray(r, float)
    x = np.asarray(x, float).reshape(len(r), -1)
    rank, basis = 0, np.zeros((len(r), 0))
    if x.shape[1]:
        uu, s, _ = np.linalg.svd(x, full_matrices=False)
        if s[0] > 0:
            rank = int(np.sum(s > s[0] * 1e-10))
            basis = uu[:, :rank]
    width = 8 * max(1, -(-rank // 8))  # padded to a multiple of 8: few compilations
    u = np.zeros((len(r), width))
    u[:, :rank] = basis
    live = np.arange(width) < rank
    args = (jnp.asarray(r), jnp.asarray(u), jnp.asarray(live), jnp.asarray(_spacings(t)),
            jnp.asarray(flicker_taus(t0)))
    ll0 = float(_profile_ll(jnp.asarray(0.0), *args))
    grid = np.linspace(*log10_range, points)
    ll = np.asarray(_profile_grid(jnp.asarray(10.0 ** grid), *args))
    i = int(np.argmax(ll))
    step = grid[1] - grid[0]
    fine = np.linspace(grid[i] - step, grid[i] + step, 9)
    llf = np.asarray(_profile_grid(jnp.asarray(10.0 ** fine), *args))
    j = int(np.argmax(llf))
    best, ll_best = fine[j], float(llf[j])
    if ll_best <= ll0 or best <= log10_range[0]:
        return 0.0, 0.0
    return float(10.0 ** best), 2 * (ll_best - ll0)
