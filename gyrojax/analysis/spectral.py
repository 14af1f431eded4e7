"""Allan deviation with confidence intervals, and the IEEE noise terms of a gyro or accelerometer.

- :func:`allan_deviation`: overlapping Allan deviation of a *rate* record (gyro rad/s or
  accelerometer m/s^2) sampled at ``rate_hz``, at cluster sizes ``m`` (default: octaves). The rate is
  integrated to an angle (velocity) ``x_k = dt sum_{j<k} (w_j - mean w)`` (k = 0..n) and
  ``AVAR(tau) = sum (x_{i+2m} - 2 x_{i+m} + x_i)^2 / (2 tau^2 (n + 1 - 2m))``, ``tau = m dt`` —
  the estimator of IEEE Std 952 / NIST SP 1065 (and of ``allantools.oadev`` with
  ``data_type="freq"``).
- Confidence intervals from the equivalent degrees of freedom of the overlapping estimator
  (Howe, Allan and Barnes 1981; NIST SP 1065 Table 5) for the noise type that dominates at each
  tau (white PM, flicker PM, white FM, flicker FM, random-walk FM), and the chi-square quantiles.
- :func:`fit_noise_terms`: the five IEEE noise terms (quantization Q, angle random walk N, bias
  instability B, rate random walk K, rate ramp R) by non-negative weighted least squares on AVAR,
  in the units of Std 952 (continuous-time densities): for a gyro in rad/s, Q in rad, N in
  rad/s/sqrt(Hz) = rad/sqrt(s), B in rad/s, K in rad/s/sqrt(s) (= rad/s^(3/2)), R in rad/s^2.
  A discrete white-noise sample std ``sigma`` at ``rate_hz`` is ``N = sigma / sqrt(rate_hz)``.
- :func:`fit_noise_likelihood`: the same terms (Q, N, B, K) by maximum Whittle likelihood on the
  periodogram, with the exact sampled spectra of each term (``S_d(f)`` per sample, ``dt = 1/rate``):
  white ``N^2/dt``; quantization ``4 sin^2(pi f dt) Q^2/dt^2`` (a differenced white angle error);
  bias instability (flicker) ``B^2/(2 pi f dt)``; rate random walk ``K^2 dt / (4 sin^2(pi f dt))``
  — the two-sided IEEE densities divided by ``dt`` at low frequency, consistent with the Allan
  forms above. Each term gets a likelihood-ratio test against the model without it (boundary:
  p = P(chi2_1 > LR)/2), and its confidence interval from the observed information.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize, stats

__all__ = ["AllanDeviation", "allan_deviation", "equivalent_dof", "NoiseTerms",
           "fit_noise_terms", "octave_clusters", "periodogram", "fit_noise_likelihood",
           "NoiseLikelihoodFit", "term_spectra"]

NOISE_ALPHA = {"white_pm": 2, "flicker_pm": 1, "white_fm": 0, "flicker_fm": -1, "rw_fm": -2}
"""Power-law exponent of each noise type in fractional-frequency terms. For a gyro the rate is
the 'frequency': angle random walk is white FM, bias instability flicker FM, rate random walk
random-walk FM, quantization white PM."""


def octave_clusters(n: int, *, per_octave: int = 1) -> np.ndarray:
    """Cluster sizes ``m`` spaced in octaves up to ``(n - 1) / 2``."""
    top = max(1, (n - 1) // 2)
    m = np.unique(np.round(2.0 ** np.arange(0, math.log2(top) + 1e-9,
                                            1.0 / per_octave)).astype(int))
    return m[m <= top]


def equivalent_dof(n_phase: int, m: int, noise: str) -> float:
    """Equivalent degrees of freedom of the overlapping Allan variance with ``n_phase`` phase
    points at cluster size ``m`` for ``noise`` in :data:`NOISE_ALPHA`."""
    n = float(n_phase)
    if noise == "white_pm":
        return (n + 1) * (n - 2 * m) / (2 * (n - m))
    if noise == "flicker_pm":
        return math.exp(math.sqrt(math.log((n - 1) / (2 * m)) * math.log((2 * m + 1) * (n - 1) / 4)))
    if noise == "white_fm":
        return (3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5)
    if noise == "flicker_fm":
        return 2 * (n - 2) ** 2 / (2.3 * n - 4.9) if m == 1 else 5 * n * n / (4 * m * (n + 3 * m))
    if noise == "rw_fm":
        return (n - 2) / m * ((n - 1) ** 2 - 3 * m * (n - 1) + 4 * m * m) / (n - 3) ** 2
    raise ValueError(f"noise={noise!r}; use one of {', '.join(NOISE_ALPHA)}")


@dataclasses.dataclass
class AllanDeviation:
    """``tau`` (s), ``adev`` (units of the rate), ``lo``/``hi`` (confidence interval at
    ``confidence``), ``edf``, ``m`` (cluster sizes), ``noise`` (type assumed for the edf)."""

    tau: np.ndarray
    adev: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    edf: np.ndarray
    m: np.ndarray
    noise: list
    confidence: float


def _local_noise(tau, adev):
    """Dominant noise type from the local log-log slope of ADEV (mu = slope * 2)."""
    out = []
    lt, la = np.log(tau), np.log(adev)
    for i in range(len(tau)):
        j0, j1 = max(i - 1, 0), min(i + 1, len(tau) - 1)
        slope = (la[j1] - la[j0]) / (lt[j1] - lt[j0]) if j1 > j0 else -0.5
        mu = 2 * slope  # AVAR ~ tau^mu: white PM -2, white FM -1, flicker FM 0, RW FM +1
        if mu < -1.5:
            out.append("white_pm")
        elif mu < -0.5:
            out.append("white_fm")
        elif mu < 0.5:
            out.append("flicker_fm")
        else:
            out.append("rw_fm")
    return out


def allan_deviation(rate, rate_hz: float, m=None, *, confidence: float = 0.683,
                    noise: str | None = None) -> AllanDeviation:
    """Overlapping Allan deviation of a rate record with chi-square confidence intervals.

    **Arguments:**
    - `rate`: samples (1-D), e.g. a gyro axis in rad/s; NaNs are refused (mask them first).
    - `rate_hz`: sampling rate.
    - `m`: cluster sizes (default octaves); `confidence`: two-sided level of the interval.
    - `noise`: noise type for the edf at every tau (default: from the local slope).
    """
    w = np.asarray(rate, float)
    if w.ndim != 1 or w.size < 8:
        raise ValueError(f"allan_deviation: need a 1-D record of at least 8 samples, got shape "
                         f"{w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError(f"allan_deviation: {int(np.sum(~np.isfinite(w)))} non-finite samples; "
                         "mask or interpolate them first")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz={rate_hz} must be > 0")
    dt = 1.0 / rate_hz
    x = np.concatenate([[0.0], np.cumsum(w - w.mean()) * dt])
    n = x.size
    m = octave_clusters(w.size) if m is None else np.asarray(m, int)
    if np.any(m < 1) or np.any(2 * m >= n):
        raise ValueError(f"cluster sizes must be 1 <= m < {n // 2}; got {m.tolist()}")
    tau = m * dt
    avar = np.array([np.sum((x[2 * k:] - 2 * x[k:n - k] + x[:n - 2 * k]) ** 2)
                     / (2 * (k * dt) ** 2 * (n - 2 * k)) for k in m])
    adev = np.sqrt(avar)
    kinds = [noise] * len(m) if noise is not None else _local_noise(tau, adev)
    edf = np.array([max(equivalent_dof(n, int(k), kd), 1.0) for k, kd in zip(m, kinds)])
    a = (1 - confidence) / 2
    lo = np.sqrt(avar * edf / stats.chi2.ppf(1 - a, edf))
    hi = np.sqrt(avar * edf / stats.chi2.ppf(a, edf))
    return AllanDeviation(tau, adev, lo, hi, edf, m, kinds, confidence)


@dataclasses.dataclass
class NoiseTerms:
    """IEEE Std 952 noise terms (see the module docstring for units) and the fitted AVAR."""

    quantization: float
    angle_random_walk: float
    bias_instability: float
    rate_random_walk: float
    rate_ramp: float

    def avar(self, tau):
        tau = np.asarray(tau, float)
        return _basis(tau) @ np.array([self.quantization**2, self.angle_random_walk**2,
                                       self.bias_instability**2, self.rate_random_walk**2,
                                       self.rate_ramp**2])


def _basis(tau):
    b = 2 * math.log(2) / math.pi
    return np.stack([3 / tau**2, 1 / tau, np.full_like(tau, b), tau / 3, tau**2 / 2], axis=-1)


def fit_noise_terms(ad: AllanDeviation, *, terms=("quantization", "angle_random_walk",
                                                  "bias_instability", "rate_random_walk",
                                                  "rate_ramp")) -> NoiseTerms:
    """Non-negative least squares of AVAR on the IEEE basis, each tau weighted by its relative
    uncertainty ``sqrt(2/edf) * AVAR``; terms not named are held at zero."""
    names = ("quantization", "angle_random_walk", "bias_instability", "rate_random_walk",
             "rate_ramp")
    bad = [t for t in terms if t not in names]
    if bad:
        raise ValueError(f"unknown noise term(s) {bad}; use {', '.join(names)}")
    avar = ad.adev**2
    wgt = 1.0 / (avar * np.sqrt(2.0 / ad.edf))
    basis = _basis(ad.tau)[:, [names.index(t) for t in terms]]
    coef, _ = optimize.nnls(basis * wgt[:, None], avar * wgt)
    full = dict.fromkeys(names, 0.0)
    full.update({t: float(math.sqrt(c)) for t, c in zip(terms, coef)})
    return NoiseTerms(**full)


# -- likelihood (Whittle) fit of the IEEE terms -------------------------------------------------
LIK_TERMS = ("quantization", "angle_random_walk", "bias_instability", "rate_random_walk")


def periodogram(pieces, rate_hz: float, *, taper: bool = True):
    """Pooled periodogram of one or more contiguous pieces (each mean-removed): returns the
    Fourier frequencies ``f_k`` (Hz, 2 <= k < n/2) of every piece and ``I_k``, whose
    expectation is the per-sample spectrum ``S_d(f_k)`` (for white noise: its variance).

    With ``taper`` (default) a Hann window, ``I_k = |FFT(w x)|^2 / sum w^2``: IMU spectra span
    many decades (a random walk's 1/f^2 against a white floor) and the untapered periodogram's
    leakage (sidelobes falling as 1/f^2) would bias every red term; Hann's fall as 1/f^6. The
    ordinates are then correlated in neighbouring pairs (:data:`HANN_DOF_FACTOR`)."""
    fs, ps = [], []
    for x in pieces:
        x = np.asarray(x, float)
        n = x.size
        if n < 16:
            continue
        w = np.hanning(n) if taper else np.ones(n)
        spec = np.abs(np.fft.rfft((x - x.mean()) * w)) ** 2 / np.sum(w * w)
        k = np.arange(2, (n - 1) // 2 + 1)
        fs.append(k * rate_hz / n)
        ps.append(spec[k])
    if not fs:
        raise ValueError("periodogram: no piece of at least 16 samples")
    return np.concatenate(fs), np.concatenate(ps)


HANN_DOF_FACTOR = 35.0 / 18.0
"""n sum(w^4) / (sum w^2)^2 for the Hann window: the Whittle log-likelihood over the tapered
periodogram counts each independent ordinate about this many times, so likelihood-ratio
statistics are divided by it."""


def term_spectra(f, rate_hz: float):
    """``(len(f), 4)`` unit spectra of Q^2, N^2, B^2, K^2 (columns in LIK_TERMS order)."""
    dt = 1.0 / rate_hz
    s2 = np.sin(np.pi * np.asarray(f) * dt) ** 2
    return np.stack([4 * s2 / dt ** 2, np.full_like(s2, 1 / dt), 1 / (2 * np.pi * f * dt),
                     dt / (4 * s2)], axis=1)


@dataclasses.dataclass
class NoiseLikelihoodFit:
    """Maximum-Whittle-likelihood noise terms (units as :class:`NoiseTerms`), per-term
    likelihood-ratio statistics and boundary p-values, and 68 % intervals (NaN at a boundary)."""

    terms: NoiseTerms
    loglik: float
    lr: dict
    p: dict
    interval: dict
    n_freq: int

    def spectrum(self, f, rate_hz):
        """The fitted per-sample spectrum ``S_d(f)`` of the rate (not differenced)."""
        c = np.array([getattr(self.terms, t) ** 2 for t in LIK_TERMS])
        return term_spectra(f, rate_hz) @ c


def _bin(f, pk, keep: int = 256, n_bins: int = 1500):
    """Average periodogram ordinates in geometrically growing bins above the lowest ``keep``
    frequencies: returns bin frequencies (mean), mean ordinates and counts. The Whittle sum over
    the original ordinates is ``sum count * (log S + I_bar / S)`` to first order, at a fraction of
    the cost for long records."""
    order = np.argsort(f)
    f, pk = f[order], pk[order]
    n = f.size
    if n <= keep + n_bins:
        return f, pk, np.ones(n)
    edges = np.unique(np.concatenate([np.arange(keep), np.round(np.geomspace(
        keep, n, n_bins)).astype(int)]))
    edges = edges[edges < n]
    counts = np.diff(np.append(edges, n)).astype(float)
    return (np.add.reduceat(f, edges) / counts, np.add.reduceat(pk, edges) / counts, counts)


def _whittle_nll(theta, args):
    import jax.numpy as jnp

    hs, p, w = args
    sd = hs @ jnp.exp(theta)
    return jnp.sum(w * (jnp.log(sd) + p / sd)) / jnp.sum(w)


def _whittle_solve(x0, hs, p, w):
    import jax
    import optimistix as optx

    sol = optx.minimise(_whittle_nll, optx.BFGS(rtol=1e-10, atol=1e-12), x0, args=(hs, p, w),
                        max_steps=500, throw=False)
    th = sol.value
    return th, _whittle_nll(th, (hs, p, w)), jax.hessian(_whittle_nll)(th, (hs, p, w))


_WHITTLE_JIT = None


def _whittle_fit(h, pk, active, x0, w=None):
    """Maximise -sum w (log S + I/S), S = h @ exp(theta) over the active terms (optimistix BFGS
    on log-coefficients, spectra normalised to the data's mean level). One compiled solver per
    (frequencies, terms) shape."""
    global _WHITTLE_JIT
    import equinox as eqx
    import jax.numpy as jnp

    if _WHITTLE_JIT is None:
        _WHITTLE_JIT = eqx.filter_jit(_whittle_solve)
    w = np.ones(len(pk)) if w is None else np.asarray(w)
    th, nll, hess = _WHITTLE_JIT(jnp.asarray(x0, float), jnp.asarray(h[:, active]),
                                 jnp.asarray(pk), jnp.asarray(w))
    tot = float(np.sum(w))
    return np.asarray(th), -float(nll) * tot, np.asarray(hess) * tot


def fit_noise_likelihood(pieces, rate_hz: float, *, terms=LIK_TERMS,
                         start: NoiseTerms | None = None,
                         f_max: float | None = None) -> NoiseLikelihoodFit:
    """Fit the IEEE terms named in ``terms`` by maximum Whittle likelihood on the pooled
    periodogram of ``pieces`` (one record, or several static intervals of one channel), and test
    each against the model without it.

    Start values come from the Allan NNLS fit (``start``, or computed from the longest piece);
    coefficients are fitted as logs, so a term absent from the data goes to its boundary (0).

    ``f_max`` (Hz, default ``rate_hz / 10``) bounds the fitted band: most of the periodogram's
    ordinates lie in the top decade, where real sensors' anti-alias / digital low-pass filters
    bend the spectrum, and an unbounded fit lets that misfit drive the slow terms (on the ADIS16405
    records it inflated B four-fold against the Allan fit). Give ``f_max=rate_hz / 2`` for a
    sensor known to be white up to Nyquist (and to test quantization, which lives there)."""
    bad = [t for t in terms if t not in LIK_TERMS]
    if bad:
        raise ValueError(f"unknown noise term(s) {bad}; the likelihood fit knows "
                         f"{', '.join(LIK_TERMS)}")
    if isinstance(pieces, np.ndarray) and pieces.ndim == 1:
        pieces = [pieces]
    f_max = rate_hz / 10 if f_max is None else f_max
    f, pk = periodogram(pieces, rate_hz)
    band = f <= f_max
    if band.sum() < 16:
        raise ValueError(f"fit_noise_likelihood: only {int(band.sum())} Fourier frequencies below "
                         f"f_max = {f_max:g} Hz; record longer or raise f_max")
    f, pk, wk = _bin(f[band], pk[band])
    h = term_spectra(f, rate_hz)
    level = float(np.sum(wk * pk) / np.sum(wk))
    pn = pk / level  # coefficients are fitted relative to this level
    if start is None:
        longest = max(pieces, key=len)
        start = fit_noise_terms(allan_deviation(longest, rate_hz))
    c0 = np.array([getattr(start, t) ** 2 for t in LIK_TERMS]) / level
    # floor start values a few decades under the white level's share so logs are finite
    floor = np.array([np.mean(pn) / np.mean(h[:, j]) for j in range(4)]) * 1e-3
    x0 = np.log(np.maximum(c0, floor))
    idx = [LIK_TERMS.index(t) for t in terms]
    th, ll, hess = _whittle_fit(h, pn, idx, x0[idx], wk)
    coef = np.zeros(4)
    coef[idx] = np.exp(th)
    lr, p, ci = {}, {}, {}
    cov = np.linalg.pinv(hess / HANN_DOF_FACTOR)
    for j, t in enumerate(terms):
        rest = [i for i in idx if i != LIK_TERMS.index(t)]
        if rest:
            _, ll0, _ = _whittle_fit(h, pn, rest, np.array([th[idx.index(i)] for i in rest]), wk)
            lr[t] = max(0.0, 2 * (ll - ll0) / HANN_DOF_FACTOR)
            p[t] = 0.5 * float(stats.chi2.sf(lr[t], 1)) if lr[t] > 0 else 1.0
        sd = math.sqrt(max(cov[j, j], 0.0))
        val = math.sqrt(coef[LIK_TERMS.index(t)] * level)
        # interval on the log-variance scale -> on the term (sqrt): exp(+-sd/2)
        ci[t] = (val * math.exp(-sd / 2), val * math.exp(sd / 2)) if sd < 5 else \
            (float("nan"), float("nan"))
    vals = {t: math.sqrt(coef[LIK_TERMS.index(t)] * level) for t in LIK_TERMS}
    return NoiseLikelihoodFit(NoiseTerms(vals["quantization"], vals["angle_random_walk"],
                                         vals["bias_instability"], vals["rate_random_walk"], 0.0),
                              ll - float(np.sum(wk)) * math.log(level), lr, p, ci, int(np.sum(wk)))
