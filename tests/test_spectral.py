"""Allan deviation against allantools, confidence-interval coverage, IEEE noise-term fit."""

import math

import allantools
import numpy as np
import pytest

from gyrojax.analysis import spectral
from gyrojax.analysis.spectral import (
    NoiseTerms,
    allan_deviation,
    equivalent_dof,
    fit_noise_likelihood,
    fit_noise_terms,
)


def test_matches_allantools_to_1e10():
    rng = np.random.default_rng(0)
    rate = 1e-3 * rng.standard_normal(20_000) + np.cumsum(1e-6 * rng.standard_normal(20_000))
    ad = allan_deviation(rate, 100.0)
    taus, dev, _, _ = allantools.oadev(rate, rate=100.0, data_type="freq", taus=ad.tau)
    np.testing.assert_allclose(taus, ad.tau, rtol=1e-12)
    np.testing.assert_allclose(ad.adev, dev, rtol=1e-10)


def test_confidence_intervals_cover_the_truth_at_the_stated_rate():
    """White rate noise of sample std sigma: ADEV(tau) = sigma sqrt(dt / tau). Over 300 records
    the 68.3 % intervals (edf from the local slope) cover it at 0.683 +- 0.06 at every tau."""
    rng = np.random.default_rng(1)
    sigma, fs, n = 0.01, 50.0, 4096
    m = np.array([1, 4, 16, 64, 256])
    hits = np.zeros(len(m))
    for _ in range(300):
        ad = allan_deviation(sigma * rng.standard_normal(n), fs, m)
        truth = sigma * np.sqrt(1 / fs / ad.tau)
        hits += (ad.lo <= truth) & (truth <= ad.hi)
    cover = hits / 300
    assert np.all(np.abs(cover - 0.683) < 0.06), cover
    assert equivalent_dof(4097, 1, "white_fm") == pytest.approx((3 * 4096 / 2 - 2 * 4095 / 4097)
                                                                * 4 / 9)


def test_noise_terms_recover_angle_and_rate_random_walk():
    """ARW and RRW from ten 2000 s records at 100 Hz: ARW to 2 % each; RRW (seen only at the
    longest taus, edf of a few) to within its scatter: mean ratio 0.85, sd 0.18 over the ten."""
    fs, n = 100.0, 200_000
    arw, rrw = 2e-3, 2e-4  # rad/sqrt(s), rad/s^(3/2)
    ratios = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        white = arw * np.sqrt(fs) * rng.standard_normal(n)
        walk = np.cumsum(rrw / np.sqrt(fs) * rng.standard_normal(n))
        ad = allan_deviation(white + walk, fs)
        fit = fit_noise_terms(ad, terms=("angle_random_walk", "rate_random_walk"))
        ratios.append((fit.angle_random_walk / arw, fit.rate_random_walk / rrw))
    ratios = np.array(ratios)
    assert np.all(np.abs(ratios[:, 0] - 1) < 0.02)
    assert 0.7 < ratios[:, 1].mean() < 1.15
    with pytest.raises(ValueError, match="non-finite"):
        allan_deviation(np.array([1.0, np.nan] * 10), fs)
    with pytest.raises(ValueError, match="unknown noise term"):
        fit_noise_terms(ad, terms=("flicker",))


def _binned(pk, f, rate, f_max):
    band = f <= f_max
    plan = spectral._bin_plan(f[band])
    h = spectral.term_spectra(spectral._apply_bins(plan, f[band]), rate)
    return h, spectral._apply_bins(plan, pk[..., band]), plan[2]


def test_whittle_fit_reaches_the_maximum_a_bounded_quasi_newton_finds():
    """Projected Fisher scoring against scipy's L-BFGS-B on the same Whittle likelihood with
    c >= 0 (natural coefficients, six starts, the best kept): on 20 records (white, white +
    rate random walk, white + flicker) its maximum is never lower by more than 1e-6 of the
    log-likelihood."""
    from scipy import optimize, signal

    rng = np.random.default_rng(3)
    rate, n = 50.0, 30_000
    worse = []
    for r in range(20):
        x = rng.standard_normal(n)
        if r % 3 == 1:
            x = x + np.cumsum(0.01 * rng.standard_normal(n))
        elif r % 3 == 2:  # flicker-like: a sum of Gauss-Markov processes, 1-1000 s
            for tau in (1.0, 10.0, 100.0, 1000.0):
                a = np.exp(-1 / (rate * tau))
                e = rng.standard_normal(n) * 0.05 * np.sqrt(1 - a * a)
                x = x + signal.lfilter([1.0], [1.0, -a], e)
        f, pk = spectral.periodogram([x], rate)
        h, pb, w = _binned(pk, f, rate, rate / 10)
        pn = pb / (pb @ w / w.sum())
        c, nll, _ = spectral.whittle_ml(h, pn, w)
        sc = h.mean(axis=0)

        def obj(u):
            s = (h / sc) @ u
            return float((np.log(s) + pn / s) @ w) if np.all(s > 0) else 1e300

        best = np.inf
        for k in range(6):
            u0 = np.full(4, 0.25) if k == 0 else rng.uniform(0.01, 1.0, 4)
            sol = optimize.minimize(obj, u0, method="L-BFGS-B", bounds=[(0, None)] * 4,
                                    options=dict(ftol=1e-15, gtol=1e-12, maxiter=5000))
            best = min(best, sol.fun)
        worse.append(float(nll[0]) - best)
    assert max(worse) < 1e-6, worse


def test_null_periodograms_match_the_time_domain_law():
    """The frequency-domain draws of the tapered periodogram against the periodogram of
    simulated white records (time domain): mean ordinate within 2 %, the Hann window's
    neighbour correlation 4/9 (|rho|^2, rho = -2/3) within 0.03, in both."""
    rng = np.random.default_rng(4)
    rate, n, draws = 50.0, 8000, 600
    coef = np.array([0.0, 1 / rate, 0.0, 0.0])  # unit-variance white rate
    fd = spectral.null_periodograms([n], rate, rate / 2, coef, draws, rng)
    td = np.stack([spectral.periodogram([rng.standard_normal(n)], rate)[1]
                   for _ in range(draws)])
    assert fd.shape == td.shape
    for p in (fd, td):
        assert p.mean() == pytest.approx(1.0, rel=0.02)
        adj = np.mean([np.corrcoef(p[:, k], p[:, k + 1])[0, 1] for k in range(10, 3000, 7)])
        assert adj == pytest.approx(4 / 9, abs=0.03)


def test_null_periodograms_remove_the_fitted_columns_as_the_time_domain_fit_does():
    """Residuals of a least-squares fit of slow columns (polynomials to degree 5 and four decays,
    coefficients shared by two pieces): the mean of the two lowest tapered ordinates of each
    piece, where the fit takes out up to half the power, from the frequency-domain draws with
    ``removed`` against time-domain residuals of white records, within 10 % (Monte Carlo sd of
    the difference ~2.6 %); the draws without ``removed`` overstate the lowest by > 50 %."""
    rng = np.random.default_rng(5)
    rate, draws, lengths = 10.0, 3000, (3000, 2000)
    coef = np.array([0.0, 1 / rate, 0.0, 0.0])  # unit-variance white rate
    cols = [np.column_stack([(t / 900) ** j for j in range(6)]
                            + [np.exp(-t / tau) for tau in (3, 8, 30, 120)])
            for t in (np.arange(n) / rate for n in lengths)]
    q, _ = np.linalg.qr(np.concatenate(cols))
    td = []
    for _ in range(draws):
        r = rng.standard_normal(sum(lengths))
        r = r - q @ (q.T @ r)
        td.append(spectral.periodogram([r[:3000], r[3000:]], rate)[1])
    td = np.mean(td, axis=0)
    removed = spectral.removed_columns(cols, rate, rate / 2)
    fd = spectral.null_periodograms(lengths, rate, rate / 2, coef, draws, rng, removed).mean(0)
    raw = spectral.null_periodograms(lengths, rate, rate / 2, coef, draws, rng).mean(0)
    low = [0, 1, 1498, 1499]  # k = 2, 3 of each piece (1498 ordinates in the first)
    assert td.shape == fd.shape and td[0] < 0.6
    np.testing.assert_allclose(fd[low], td[low], rtol=0.10)
    assert raw[0] > 1.5 * td[0]
    assert fd[100:1400].mean() == pytest.approx(td[100:1400].mean(), rel=0.01)


@pytest.mark.slow
def test_bootstrap_boundary_law_holds_the_level_where_the_boundary_law_is_conservative():
    """300 white-noise records (900 s at 50 Hz): with every other term on its boundary, the
    likelihood ratios of bias instability and rate random walk are 0 more often than half the
    time and small when positive, so the boundary law (p = P(chi2_1 > LR) / 2) rejects the rate
    random walk almost never at 0.05. The bootstrap law (``null_draws=200``) rejects each within
    [0.025, 0.085] (0.05 +- 2.8 standard errors at n = 300)."""
    rng = np.random.default_rng(21)
    rate, n = 50.0, 45_000
    rej = {"boot": np.zeros(2), "boundary": np.zeros(2)}
    terms = ("bias_instability", "rate_random_walk")
    for r in range(300):
        x = rng.standard_normal(n)
        for lab, draws in (("boot", 200), ("boundary", 0)):
            fit = spectral.fit_noise_likelihood(x, rate, null_draws=draws, seed=r)
            rej[lab] += [fit.p[t] < 0.05 for t in terms]
    boot, boundary = rej["boot"] / 300, rej["boundary"] / 300
    assert np.all((boot >= 0.025) & (boot <= 0.085)), boot
    assert boundary[1] < 0.02, boundary


def test_noise_likelihood_bad_options_name_the_field():
    x = np.random.default_rng(0).standard_normal(4000)
    with pytest.raises(ValueError, match=r"unknown noise term\(s\) \['flicker'\]"):
        spectral.fit_noise_likelihood(x, 50.0, bootstrap_terms=("flicker",))
    with pytest.raises(ValueError, match="null_draws=-1"):
        spectral.fit_noise_likelihood(x, 50.0, null_draws=-1)
    with pytest.raises(ValueError, match=r"removed: one \(n_i, m\) array per piece"):
        spectral.fit_noise_likelihood(x, 50.0, removed=[np.ones((3999, 2))])


def test_each_ieee_term_is_its_own_process_allan_variance_and_spectrum():
    """The IEEE Std 952 basis, term by term, against the process each term names, simulated:
    - quantization Q: a white angle error of std Q, read as the differenced rate: its overlapping
      AVAR is exactly 3 Q^2 / tau^2 in expectation (the second difference of white noise has
      variance 6 Q^2), here the mean of 40 records to 3 %; fitted alone, Q comes back to 2 %;
    - rate ramp R: a deterministic ramp R t has AVAR R^2 tau^2 / 2 exactly, at every tau;
    - bias instability B: the flicker floor 0.664 B of IEEE 952 (sqrt(2 ln 2 / pi));
    - the per-sample spectra (``term_spectra``, the Whittle fit's basis): the mean Hann periodogram
      of the differenced white angle (4 Q^2 sin^2(pi f dt) / dt^2), of white rate noise of sample
      std sigma (sigma^2 = N^2 / dt) and of a rate random walk (K^2 dt / (4 sin^2(pi f dt))), to 5 %
      in octave bands away from the ends."""
    rng = np.random.default_rng(7)
    fs, n, q = 100.0, 20_000, 3e-6  # Hz, samples, rad
    dt = 1 / fs
    m = np.array([1, 2, 4, 16, 64, 256])
    avar = []
    for _ in range(40):
        y = np.diff(q * rng.standard_normal(n + 1)) / dt
        ad = allan_deviation(y, fs, m)
        avar.append(ad.adev ** 2)
    model = NoiseTerms(quantization=q, angle_random_walk=0.0, bias_instability=0.0,
                       rate_random_walk=0.0, rate_ramp=0.0).avar(ad.tau)
    np.testing.assert_allclose(np.mean(avar, axis=0), model, rtol=0.03)
    fit = fit_noise_terms(ad, terms=("quantization",))
    assert fit.quantization == pytest.approx(q, rel=0.02)

    r = 2e-7  # rad/s^2
    t = np.arange(5000) * dt
    ad = allan_deviation(r * t, fs, m)
    ramp = NoiseTerms(0.0, 0.0, 0.0, 0.0, rate_ramp=r).avar(ad.tau)
    np.testing.assert_allclose(ad.adev ** 2, ramp, rtol=1e-9)
    floor = NoiseTerms(0.0, 0.0, bias_instability=1.0, rate_random_walk=0.0, rate_ramp=0.0)
    assert math.sqrt(float(floor.avar(np.array([1.0]))[0])) == pytest.approx(0.664, abs=5e-4)

    n, runs = 4096, 200
    arw, k = 2e-3, 4e-4  # rad/sqrt(s), rad/s^(3/2)
    procs = {0: lambda: np.diff(q * rng.standard_normal(n + 1)) / dt,
             1: lambda: arw / math.sqrt(dt) * rng.standard_normal(n),
             3: lambda: np.cumsum(k * math.sqrt(dt) * rng.standard_normal(n))}
    coef = {0: q ** 2, 1: arw ** 2, 3: k ** 2}
    for col, draw in procs.items():
        pk = np.mean([spectral.periodogram([draw()], fs)[1] for _ in range(runs)], axis=0)
        f = spectral.periodogram([np.zeros(n)], fs)[0]
        s = spectral.term_spectra(f, fs)[:, col] * coef[col]
        edges = np.geomspace(f[8], f[-8], 9)
        for lo, hi in zip(edges[:-1], edges[1:]):
            band = (f >= lo) & (f < hi)
            assert np.mean(pk[band]) / np.mean(s[band]) == pytest.approx(1.0, abs=0.05), (col, lo)


def test_likelihood_intervals_cover_at_their_stated_rate():
    """The Whittle fit's 68 % interval of a term (the observed information of its log-variance,
    taken to the term's square root: half the width): over 300 white records (4000 samples at
    50 Hz) the interval for N covers the generating value at 0.74, inside 0.683 +- 0.12 (a
    Monte Carlo standard error is 0.027; the Hann taper's correlation of neighbouring ordinates
    is accounted for only on average)."""
    rng = np.random.default_rng(3)
    fs, n, arw = 50.0, 4000, 2e-3
    hits = []
    for _ in range(300):
        x = arw * math.sqrt(fs) * rng.standard_normal(n)
        fit = fit_noise_likelihood(x, fs, terms=("angle_random_walk",), null_draws=0, f_max=fs / 2)
        lo, hi = fit.interval["angle_random_walk"]
        hits.append(lo <= arw <= hi)
    assert abs(np.mean(hits) - 0.683) < 0.12, np.mean(hits)
