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
  forms above; fitted by :func:`whittle_ml` (projected Fisher scoring, coefficients >= 0). Each
  term gets a likelihood-ratio test against the model without it (p from the boundary law
  P(chi2_1 > LR)/2, or with ``null_draws`` from a parametric-bootstrap law of the fitted null,
  :func:`null_periodograms`), and its confidence interval from the observed information.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float
from scipy import optimize, stats

__all__ = ["AllanDeviation", "allan_deviation", "equivalent_dof", "NoiseTerms",
           "fit_noise_terms", "octave_clusters", "periodogram", "fit_noise_likelihood",
           "NoiseLikelihoodFit", "term_spectra", "whittle_ml", "null_periodograms",
           "removed_columns", "RemovedColumns"]

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


def allan_deviation(rate: Float[ArrayLike, " n"], rate_hz: float, m=None, *, confidence: float = 0.683,
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


def periodogram(pieces: Float[ArrayLike, " n"] | Sequence[Float[ArrayLike, " _"]], rate_hz: float,
                *, taper: bool = True):
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


LR_ZERO = 1e-6
"""Likelihood ratios below this are the fit's tolerance (:func:`whittle_ml`), read as 0."""

NULL_SELECT_LR = 1.0
"""A nuisance term whose likelihood ratio in a bootstrap null's fit is below this is set to its
boundary there (:func:`_selected_null`)."""

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


def _bin_plan(f, keep: int = 256, n_bins: int = 1500):
    """Sort order, bin starts and counts for averaging periodogram ordinates in geometrically
    growing bins above the lowest ``keep`` frequencies (``None`` for the starts: every ordinate
    its own bin). The Whittle sum over the original ordinates is ``sum count * (log S + I_bar /
    S)`` to first order, at a fraction of the cost for long records."""
    order = np.argsort(f)
    n = f.size
    if n <= keep + n_bins:
        return order, None, np.ones(n)
    edges = np.unique(np.concatenate([np.arange(keep), np.round(np.geomspace(
        keep, n, n_bins)).astype(int)]))
    edges = edges[edges < n]
    return order, edges, np.diff(np.append(edges, n)).astype(float)


def _apply_bins(plan, x):
    """Bin means of ``x[..., order]`` over the last axis (:func:`_bin_plan`)."""
    order, edges, counts = plan
    x = np.asarray(x)[..., order]
    return x if edges is None else np.add.reduceat(x, edges, axis=-1) / counts


def _whittle_nll(c, h, pn, w):
    """``sum w (log S + I / S)``, ``S = h @ c``, per row of ``c`` / ``pn``."""
    s = c @ h.T
    return (np.log(s) + pn / s) @ w


def _nnls_small(g, r):
    """``argmin c'Gc - 2 r'c`` over ``c >= 0`` for a batch of small (k <= 4) problems: the least
    squares solution on every support, the feasible one of least objective (exact: the NNLS
    solution is the unconstrained solution on its own support). ``g`` is scaled to a unit
    diagonal first; every support's system is solved in one batched call (off the support the
    matrix is the identity and the right side 0)."""
    b, k = r.shape
    d = np.sqrt(np.maximum(np.einsum("bii->bi", g), np.finfo(float).tiny))
    gs, rs = g / d[:, :, None] / d[:, None, :], r / d
    sup = _SUPPORTS[k]  # (n_sub, k) booleans
    both = sup[:, :, None] & sup[:, None, :]
    mats = np.where(both[:, None], gs[None], np.eye(k)) + 1e-13 * np.eye(k)
    cs = np.linalg.solve(mats, np.where(sup[:, None], rs[None], 0.0)[..., None])[..., 0]
    q = -np.einsum("sbi,bi->sb", cs, rs)
    q = np.where(np.all(cs >= 0, axis=2), q, np.inf)
    best = np.argmin(q, axis=0)
    out = cs[best, np.arange(b)]
    return np.where(q[best, np.arange(b)][:, None] < 0, out, 0.0) / d


_SUPPORTS = {k: np.array([[i in sub for i in range(k)] for size in range(1, k + 1)
                          for sub in itertools.combinations(range(k), size)])
             for k in range(1, 5)}


def whittle_ml(h, pn, w, c0=None, *, max_iter: int = 1000, tol: float = 1e-7):
    """Maximum Whittle likelihood of the linear spectral model ``S = h @ c``, ``c >= 0``, for
    every row of ``pn`` (ordinates, weights ``w``): returns ``c`` (rows, k), ``sum w (log S +
    I / S)`` at it, and the iterations taken.

    Projected Fisher scoring (the IRLS of a gamma model with identity link): each step
    minimises the Fisher-weighted ``sum w (I - h c)^2 / S_old^2`` over ``c >= 0`` exactly
    (:func:`_nnls_small`) and moves toward it, halving until the likelihood rises; a row stops
    when no step gains ``tol``. Terms absent from the data land exactly on their boundary (0).
    A quasi-Newton fit on log-coefficients (used before) stalled near that boundary: on white
    noise its fits without a term sat above this maximum, which inflated the likelihood
    ratios (bias instability's mean 0.36 against 0.20, docs/decisions/0012-noise-identification.md)."""
    pn = np.atleast_2d(np.asarray(pn, float))
    b, k = pn.shape[0], h.shape[1]
    sc = h.mean(axis=0)
    hs = h / sc
    outer = (hs[:, :, None] * hs[:, None, :]).reshape(len(hs), k * k)
    c = np.full((b, k), 1.0 / k) if c0 is None else \
        np.array(np.broadcast_to(np.maximum(np.asarray(c0, float) * sc, 0.0), (b, k)))
    c = np.where(np.sum(c, axis=1, keepdims=True) > 0, c, 1.0 / k)
    f = _whittle_nll(c, hs, pn, w)
    live = np.ones(b, bool)
    it = 0
    for it in range(1, max_iter + 1):
        rows = np.flatnonzero(live)
        cl, pl = c[rows], pn[rows]
        wt = w / (cl @ hs.T) ** 2
        gram = (wt @ outer).reshape(-1, k, k)
        step = _nnls_small(gram, (wt * pl) @ hs) - cl
        t = np.ones(rows.size)
        gain = np.zeros(rows.size)
        todo = np.arange(rows.size)
        for _ in range(30):
            trial = cl[todo] + t[todo, None] * step[todo]
            ft = _whittle_nll(trial, hs, pl[todo], w)
            up = ft < f[rows[todo]]
            gain[todo[up]] = f[rows[todo[up]]] - ft[up]
            c[rows[todo[up]]] = trial[up]
            f[rows[todo[up]]] = ft[up]
            todo = todo[~up]
            if todo.size == 0:
                break
            t[todo] *= 0.5
        live[rows] = gain > tol
        if not live.any():
            break
    return c / sc, f, it


def _drawn_band(n: int, rate_hz: float, f_max: float):
    """The DFT indices a null draw of a piece of ``n`` samples needs: the periodogram's band
    ``2 <= k <= min((n - 1) / 2, n f_max / rate)`` and one neighbour either side (the Hann
    kernel's taps); empty where the piece has no ordinate in the band."""
    if n < 16:
        return np.arange(0)
    k = np.arange(2, (n - 1) // 2 + 1)
    k = k[k * rate_hz / n <= f_max]
    return np.arange(k[0] - 1, k[-1] + 2) if k.size else np.arange(0)


@dataclasses.dataclass
class RemovedColumns:
    """The columns a least-squares fit removed from a set of pieces, as the null draws of
    :func:`null_periodograms` need them (:func:`removed_columns`): per piece the DFT of an
    orthonormal basis of the columns at the drawn indices (``(r, len(band))``), and the four
    terms' unit contributions to the covariance of the fit's coefficients from the DFT indices
    not drawn (``(4, r, r)``)."""

    drawn: list
    tail: np.ndarray


def removed_columns(columns, rate_hz: float, f_max: float) -> RemovedColumns:
    """Prepare ``columns`` (one ``(n_i, m)`` array per piece, the same ``m`` columns: what a
    least-squares fit with coefficients shared over the pieces removed from them, e.g. the
    mean model's bias, drift and warm-up columns at the samples) for :func:`null_periodograms`.

    The columns are orthonormalised over all pieces (``Q``, rank by SVD at 1e-10); for a
    circular process with DFT ordinates ``X_k`` the fit's coefficients are
    ``beta = sum_pieces (2 / n) Re sum_k conj(Q_k) X_k`` (``k >= 1``; the mean is removed
    anyway), so the null draws get ``beta`` from their drawn ordinates plus a Gaussian part for
    the indices not drawn, with covariance ``sum_k (2 S(f_k) / n) Re(conj(Q_k) Q_k^T)``."""
    mats = [np.asarray(c, float) for c in columns]
    if not mats or len({m.shape[1] for m in mats}) != 1 or any(m.ndim != 2 for m in mats):
        raise ValueError("removed columns: give one (n_i, m) array per piece with the same m")
    stack = np.concatenate([np.ones((sum(len(m) for m in mats), 1)),
                            np.concatenate(mats)], axis=1)
    norm = np.linalg.norm(stack, axis=0)
    stack = stack[:, norm > 0] / norm[norm > 0]
    u, sv, _ = np.linalg.svd(stack, full_matrices=False)
    q = u[:, sv > 1e-10 * sv[0]]
    drawn, tail, i0 = [], np.zeros((4, q.shape[1], q.shape[1])), 0
    for m in mats:
        n = len(m)
        qh = np.fft.rfft(q[i0:i0 + n], axis=0).T  # (r, n // 2 + 1)
        i0 += n
        band = _drawn_band(n, rate_hz, f_max)
        rest = np.setdiff1d(np.arange(1, qh.shape[1]), band)
        drawn.append(qh[:, band])
        h = term_spectra(rest * rate_hz / n, rate_hz) * (2.0 / n)  # (len(rest), 4)
        a = qh[:, rest]
        tail += np.einsum("kt,ik,jk->tij", h, a.conj(), a).real
    return RemovedColumns(drawn, tail)


def null_periodograms(lengths, rate_hz: float, f_max: float, coef, draws: int, rng,
                      removed: RemovedColumns | None = None):
    """``draws`` replicates of the pooled, band-limited (``f <= f_max``) Hann-tapered
    periodogram (:func:`periodogram`) of pieces of ``lengths`` samples of a stationary Gaussian
    rate whose per-sample spectrum is ``term_spectra(f) @ coef``; with ``removed``
    (:func:`removed_columns`), of its residual after the least-squares fit of those columns.

    Drawn in the frequency domain, as for a circular process: the untapered DFT ordinates
    ``X_k`` are independent ``CN(0, n S(f_k))``, and the (periodic) Hann window acts on them as
    ``Y_k = X_k / 2 - (X_{k-1} + X_{k+1}) / 4``, ``I_k = |Y_k|^2 / (3 n / 8)``: the neighbouring
    ordinates' correlation that :data:`HANN_DOF_FACTOR` accounts for is reproduced, at
    ``O(n f_max / rate)`` cost per draw (no FFT). A fit that removed slow columns (a drift, a
    warm-up exponential) takes out the lowest ordinates' power, which is where a rate random
    walk lives: its test's law on such residuals is far from the law on raw noise (on white
    records with a bias, a ramp and six exponentials removed, its likelihood ratio was positive
    in 4 % of 1000 records, not 25 %), so the draws remove them too: ``X_k - Q_k beta``."""
    coef = np.asarray(coef, float)
    zs, ns = [], []
    for n in lengths:
        kk = _drawn_band(n, rate_hz, f_max)
        s = term_spectra(kk * rate_hz / n, rate_hz) @ coef
        zs.append(rng.standard_normal((draws, 2 * kk.size)).view(np.complex128)
                  * np.sqrt(n * s / 2))
        ns.append(n)
    if removed is not None:
        if len(removed.drawn) != len(zs):
            raise ValueError(f"removed columns for {len(removed.drawn)} pieces, {len(zs)} given")
        cov = np.tensordot(coef, removed.tail, axes=1)
        r = cov.shape[0]
        w, v = np.linalg.eigh(cov)
        beta = rng.standard_normal((draws, r)) @ (v * np.sqrt(np.maximum(w, 0.0))).T
        for z, qd, n in zip(zs, removed.drawn, ns):
            beta += (2.0 / n) * (z @ qd.conj().T).real
        zs = [z - beta @ qd for z, qd in zip(zs, removed.drawn)]
    out = []
    for z, n in zip(zs, ns):
        if z.shape[1] < 3:
            continue
        y = 0.5 * z[:, 1:-1] - 0.25 * (z[:, :-2] + z[:, 2:])
        out.append((y.real ** 2 + y.imag ** 2) / (3 * n / 8))
    return np.concatenate(out, axis=1)


def fit_noise_likelihood(pieces: Float[ArrayLike, " n"] | Sequence[Float[ArrayLike, " _"]],
                         rate_hz: float, *, terms=LIK_TERMS,
                         start: NoiseTerms | None = None,
                         f_max: float | None = None, null_draws: int = 200,
                         bootstrap_terms=None, seed: int = 0,
                         removed=None) -> NoiseLikelihoodFit:
    """Fit the IEEE terms named in ``terms`` by maximum Whittle likelihood on the pooled
    periodogram of ``pieces`` (one record, or several static intervals of one channel), and test
    each against the model without it.

    The fit is :func:`whittle_ml` (projected Fisher scoring on the non-negative coefficients),
    started from the Allan NNLS fit (``start``, or computed from the longest piece); a term
    absent from the data lands on its boundary (0).

    p-values. A term's likelihood ratio (divided by :data:`HANN_DOF_FACTOR`) is 0 with
    probability ``pi`` under its null and, when positive, is close to ``s chi2_1``. Where the
    other terms are estimated inside their range, ``pi = 1/2``, ``s = 1`` (the boundary law, used
    with ``null_draws=0``). Where they sit on their boundary too (a white record tested for bias
    instability and rate random walk, whose low-frequency spectra overlap), both are smaller:
    on 3000 draws of 1800 s of white noise at 50 Hz, ``pi`` = 0.30 / 0.23 and ``s`` = 0.59 /
    0.27 for bias instability / rate random walk, and the boundary law's p-values are
    conservative (the rate random walk's never fell below 0.05). With ``null_draws = B > 0``
    (default 200) every term in ``bootstrap_terms`` (default: all but the white floor) whose
    ratio is positive gets ``p = pi chi2_1.sf(LR / s)`` with ``pi`` and ``s`` from batches of
    ``B`` parametric-bootstrap periodograms of its null (:func:`null_periodograms`; the fit
    without the term, weak nuisance terms set to 0 by :func:`_selected_null`), refitted with
    and without the term, until :data:`MIN_POSITIVE_DRAWS` ratios are positive (at most
    ``10 B``); ``seed`` fixes the draws. That scaled form matches the bootstrap law's
    tail to within its Monte Carlo error down to 0.005
    (docs/decisions/0012-noise-identification.md), and resolves p-values below ``1 / B``. On 500 white
    records the three terms then reject 0.048-0.050 at 0.05.

    ``f_max`` (Hz, default ``rate_hz / 10``) bounds the fitted band: most of the periodogram's
    ordinates lie in the top decade, where real sensors' anti-alias / digital low-pass filters
    bend the spectrum, and an unbounded fit lets that misfit drive the slow terms (on the ADIS16405
    records it inflated B four-fold against the Allan fit). Give ``f_max=rate_hz / 2`` for a
    sensor known to be white up to Nyquist (and to test quantization, which lives there).

    ``removed``: where the pieces are residuals of a least-squares fit (a mean model's bias,
    drift and warm-up columns), those columns at the pieces' samples, one ``(n_i, m)`` array
    per piece (coefficients shared over the pieces), or a function returning them (called only
    if a bootstrap runs): the bootstrap draws then have them removed as well
    (:func:`removed_columns`). Slow columns take out the rate random walk's power, and
    without this its test is far too conservative on such residuals (rejection 0.007 at 0.05 on
    150 white records with a ramp and six exponentials removed)."""
    bad = [t for t in (*terms, *(bootstrap_terms or ())) if t not in LIK_TERMS]
    if bad:
        raise ValueError(f"unknown noise term(s) {bad}; the likelihood fit knows "
                         f"{', '.join(LIK_TERMS)}")
    if null_draws < 0:
        raise ValueError(f"null_draws={null_draws}: give 0 (the boundary law) or a number of "
                         "bootstrap draws (200 is the default)")
    if isinstance(pieces, np.ndarray) and pieces.ndim == 1:
        pieces = [pieces]
    f_max = rate_hz / 10 if f_max is None else f_max
    f, pk = periodogram(pieces, rate_hz)
    band = f <= f_max
    if band.sum() < 16:
        raise ValueError(f"fit_noise_likelihood: only {int(band.sum())} Fourier frequencies below "
                         f"f_max = {f_max:g} Hz; record longer or raise f_max")
    plan = _bin_plan(f[band])
    wk = plan[2]
    h = term_spectra(_apply_bins(plan, f[band]), rate_hz)
    pk = _apply_bins(plan, pk[band])
    level = float(np.sum(wk * pk) / np.sum(wk))
    pn = pk / level  # coefficients are fitted relative to this level
    if start is None:
        longest = max(pieces, key=len)
        start = fit_noise_terms(allan_deviation(longest, rate_hz))
    c0 = np.array([getattr(start, t) ** 2 for t in LIK_TERMS]) / level
    idx = [LIK_TERMS.index(t) for t in terms]
    c, nll, _ = whittle_ml(h[:, idx], pn, wk, c0[idx])
    coef = np.zeros(4)
    coef[idx] = c[0]
    rng = np.random.default_rng(seed)
    boot = [t for t in LIK_TERMS if t != "angle_random_walk"] if bootstrap_terms is None \
        else list(bootstrap_terms)
    lengths = [len(x) for x in pieces]

    def checked(cols):
        if len(cols) != len(pieces) or any(len(c) != n for c, n in zip(cols, lengths)):
            raise ValueError(f"removed: one (n_i, m) array per piece with n_i its length; got "
                             f"{[np.shape(c) for c in cols]} for pieces of {lengths}")
        return cols

    @functools.cache
    def removed_law():  # prepared once, and only where a bootstrap needs it
        return removed_columns(checked(removed() if callable(removed) else removed), rate_hz,
                               f_max)

    if removed is not None and not callable(removed):
        checked(removed)  # a wrong shape is refused whatever the ratios
    lr, p, ci = {}, {}, {}
    info = _whittle_information(h[:, idx], c[0], pn[0], wk) / HANN_DOF_FACTOR
    pos = c[0] > 0
    cov = np.full((len(idx), len(idx)), np.nan)
    cov[np.ix_(pos, pos)] = np.linalg.pinv(info[np.ix_(pos, pos)])
    for j, t in enumerate(terms):
        rest = [i for i in idx if i != LIK_TERMS.index(t)]
        if rest:
            c_null, nll0, _ = whittle_ml(h[:, rest], pn, wk, coef[rest])
            lr[t] = float(nll0[0] - nll[0]) * 2 / HANN_DOF_FACTOR
            if lr[t] < LR_ZERO:
                lr[t] = 0.0
                p[t] = 1.0
            elif null_draws and t in boot:
                null = _selected_null(h, pn, wk, rest, c_null[0], nll0[0])
                share, scale = _boundary_law(lengths, rate_hz, f_max, plan, h, wk, idx, rest,
                                             null, null_draws, rng,
                                             None if removed is None else removed_law())
                p[t] = share * float(stats.chi2.sf(lr[t] / scale, 1))
            else:
                p[t] = 0.5 * float(stats.chi2.sf(lr[t], 1))
        sd = math.sqrt(max(cov[j, j], 0.0)) if pos[j] else float("nan")
        val = math.sqrt(coef[LIK_TERMS.index(t)] * level)
        # interval on the log-variance scale -> on the term (sqrt): exp(+-sd/2)
        ci[t] = (val * math.exp(-sd / 2), val * math.exp(sd / 2)) if sd < 5 else \
            (float("nan"), float("nan"))
    vals = {t: math.sqrt(coef[LIK_TERMS.index(t)] * level) for t in LIK_TERMS}
    return NoiseLikelihoodFit(NoiseTerms(vals["quantization"], vals["angle_random_walk"],
                                         vals["bias_instability"], vals["rate_random_walk"], 0.0),
                              -float(nll[0]) - float(np.sum(wk)) * math.log(level), lr, p, ci,
                              int(np.sum(wk)))


def _whittle_information(h, c, pn, w):
    """Observed information of the Whittle log-likelihood in the log-coefficients at ``c``."""
    s = h @ c
    u = h * c
    g = (w * (1 / s - pn / s ** 2)) @ u
    return (u.T * (w * (2 * pn / s ** 3 - 1 / s ** 2))) @ u + np.diag(g)


def _selected_null(h, pn, w, rest, c_rest, nll_rest):
    """The null a term's bootstrap draws from: the fit over ``rest`` with every other non-white
    term whose own likelihood ratio within it is below :data:`NULL_SELECT_LR` set to its
    boundary, 0 (moment selection in the manner of Andrews and Soares 2010).

    Why: where the tested term's ratio is positive, the null fit lets a nuisance term (bias
    instability, when testing the rate random walk) take up the same low-frequency excess,
    and a nuisance inside its range makes the bootstrap law the interior one (``pi`` 1/2,
    ``s`` 1), which makes the test conservative. Setting weak nuisances to 0 errs the other way
    where the nuisance is truly present but weak; :data:`NULL_SELECT_LR` trades the two
    (docs/decisions/0012-noise-identification.md)."""
    white = LIK_TERMS.index("angle_random_walk")
    keep = [i for j, i in enumerate(rest) if c_rest[j] > 0]
    for i in [i for i in keep if i != white]:
        others = [x for x in rest if x != i]
        _, n_wo, _ = whittle_ml(h[:, others], pn, w, c_rest[[rest.index(x) for x in others]])
        if (n_wo[0] - nll_rest) * 2 / HANN_DOF_FACTOR < NULL_SELECT_LR:
            keep.remove(i)
    null = np.zeros(h.shape[1])
    if keep == list(rest):
        null[rest] = c_rest
    else:
        null[keep] = whittle_ml(h[:, keep], pn, w, c_rest[[rest.index(x) for x in keep]])[0][0]
    return null


MIN_POSITIVE_DRAWS = 40
"""The bootstrap law draws batches of ``null_draws`` until this many ratios are positive (or
ten batches are drawn): ``s`` is their mean, shrunk by one pseudo-draw at 1, and with a handful
of positives (a rate random walk on residuals of a fit with slow columns is positive in ~4 % of
draws) that pseudo-draw would dominate and make the test conservative."""


def _boundary_law(lengths, rate_hz, f_max, plan, h, wk, idx, rest, null, draws, rng,
                  removed=None):
    """``(pi, s)`` of a term's likelihood ratio under the fitted ``null`` (coefficients over all
    four terms, the tested one 0): the share of bootstrap periodograms whose ratio is positive,
    and the positive ratios' mean (each estimate shrunk by one pseudo-draw at the regular
    boundary law, 1/2 and 1, so a small ``draws`` cannot return 0). Batches of ``draws`` until
    :data:`MIN_POSITIVE_DRAWS` ratios are positive, at most ten."""
    pos, total = [], 0
    for _ in range(10):
        pb = _apply_bins(plan, null_periodograms(lengths, rate_hz, f_max, null, draws, rng,
                                                 removed))
        pb = pb / (pb @ wk / np.sum(wk))[:, None]
        _, nf, _ = whittle_ml(h[:, idx], pb, wk, null[idx])
        _, n0, _ = whittle_ml(h[:, rest], pb, wk, null[rest])
        lr = np.maximum(0.0, (n0 - nf) * 2 / HANN_DOF_FACTOR)
        pos.append(lr[lr >= LR_ZERO])
        total += draws
        if sum(x.size for x in pos) >= MIN_POSITIVE_DRAWS:
            break
    pos = np.concatenate(pos)
    return (pos.size + 0.5) / (total + 1), (pos.sum() + 1.0) / (pos.size + 1)
