"""Allan deviation against allantools, confidence-interval coverage, IEEE noise-term fit."""

import allantools
import numpy as np
import pytest

from gyrojax.analysis.spectral import allan_deviation, equivalent_dof, fit_noise_terms


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
