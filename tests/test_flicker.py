"""White + flicker noise model (gyrojax.analysis.flicker) and the ESG diagnosis on it: the
innovations whitening against a dense Cholesky factor, the REML profile against its dense
formula and the generating level, the spectral flicker generator against the IEEE Allan floor,
and the GLS refit against the screened score."""

import jax
import numpy as np
import pytest
from scipy.signal import lfilter

from gyrojax import units
from gyrojax.analysis.flicker import (
    FLICKER_STD_PER_B,
    _profile_ll,
    _spacings,
    flicker_taus,
    reml_rho,
    rho_to_b,
    whiten,
)
from gyrojax.analysis.spectral import allan_deviation
from gyrojax.diagnose import diagnose
from gyrojax.models.imu import _flicker, flicker_spectral
from gyrojax.record import BenchRecord

DT = 60.0


def _dense_cov(t, rho):
    taus = flicker_taus(DT)
    lag = np.abs(t[:, None] - t[None, :])
    return np.eye(len(t)) + rho * sum(np.exp(-lag / tau) for tau in taus)


def test_whitening_is_the_cholesky_inverse_also_across_a_gap():
    t = np.concatenate([np.arange(300), 420 + np.arange(200)]) * DT  # a 2 h gap
    x = np.random.default_rng(0).standard_normal((len(t), 3))
    for rho in (0.0, 0.02, 1.5):
        want = np.linalg.solve(np.linalg.cholesky(_dense_cov(t, rho)), x)
        np.testing.assert_allclose(whiten(x, t, rho, DT), want, atol=1e-12)


def test_reml_profile_equals_its_dense_formula():
    rng = np.random.default_rng(1)
    n = 400
    t = np.arange(n) * DT
    x = np.stack([np.ones(n), t / t[-1], np.sin(2 * np.pi * t / 86164.0)], 1)
    u, _, _ = np.linalg.svd(x, full_matrices=False)
    r = rng.standard_normal(n)
    import jax.numpy as jnp

    for rho in (1e-4, 0.05, 2.0):
        c = _dense_cov(t, rho)
        ci = np.linalg.inv(c)
        xtx = u.T @ ci @ u
        beta = np.linalg.solve(xtx, u.T @ ci @ r)
        rss = (r - u @ beta) @ ci @ (r - u @ beta)
        p = u.shape[1]
        want = (-0.5 * (n - p) * np.log(rss / (n - p)) - 0.5 * np.linalg.slogdet(c)[1]
                - 0.5 * np.linalg.slogdet(xtx)[1])
        padded = np.concatenate([u, np.zeros((n, 5))], axis=1)
        got = float(_profile_ll(jnp.asarray(rho), jnp.asarray(r), jnp.asarray(padded),
                                jnp.asarray(np.arange(8) < 3), jnp.asarray(_spacings(t)),
                                jnp.asarray(flicker_taus(DT))))
        assert got == pytest.approx(want, abs=1e-8)


def test_reml_recovers_the_flicker_level_and_rarely_finds_one_in_white_noise():
    """40 series of 1080 one-minute samples (white 1 + GM-sum flicker), a bias, a ramp and a
    sidereal line projected out: the REML B averages to the generating one (seeded; the spread
    of one estimate is ~30 %, of the mean ~5 %); on 80 white series the likelihood-ratio test
    against no flicker rejects at about its 5 % level (the 50:50 chi2_0 / chi2_1 mixture)."""
    n = 1080
    t = np.arange(n) * DT
    x = np.stack([np.ones(n), t / t[-1], np.sin(2 * np.pi * t / 86164.0),
                  np.cos(2 * np.pi * t / 86164.0)], 1)

    def fit(y):
        r = y - x @ np.linalg.lstsq(x, y, rcond=None)[0]
        return reml_rho(r, x, t, DT)

    b_true = 0.2
    fl = np.asarray(_flicker(jax.random.key(0), n, DT, np.full(40, b_true), t0=DT))
    y = np.random.default_rng(100).standard_normal((n, 40)) + fl
    est = [rho_to_b(fit(y[:, s])[0], 1.0) for s in range(40)]
    assert np.mean(est) == pytest.approx(b_true, rel=0.15)
    white = np.random.default_rng(500).standard_normal((n, 80))
    lr = np.array([fit(white[:, s])[1] for s in range(80)])
    assert np.mean(lr > 2.71) <= 0.12


def test_spectral_flicker_has_the_ieee_allan_floor():
    """1/f by spectral synthesis (independent of the GM sum): Allan deviation 0.664 B from a
    few samples to a few thousand (one seeded 200 000-sample series; the estimate's scatter at
    tau = 1024 samples is ~5 %)."""
    b = 0.1
    x = np.asarray(flicker_spectral(jax.random.key(3), 200_000, DT, np.array([b]), span=4))[:, 0]
    ad = allan_deviation(x, 1 / DT)
    for m in (4, 16, 64, 256, 1024):
        k = int(np.argmin(np.abs(ad.tau / DT - m)))
        assert ad.adev[k] / b == pytest.approx(0.664, rel=0.1), m


def test_gm_sum_at_rho_has_the_ieee_floor_of_rho_to_b():
    """``rho_to_b`` against the IEEE Allan floor, generated independently of the library's
    flicker generator: five unit-variance first-order Gauss-Markov processes at the model's
    correlation times (stationary start, scipy's lfilter), scaled by sqrt(rho), have their Allan
    deviation at 0.664 B of ``B = rho_to_b(rho, 1)`` from 4 to 2048 samples (one seeded
    400 000-sample series: 1.03-1.05 of it, asserted to 10 %)."""
    rng = np.random.default_rng(11)
    n, rho = 400_000, 0.04
    x = np.zeros(n)
    for tau in flicker_taus(1.0):
        phi = np.exp(-1.0 / tau)
        e = rng.standard_normal(n) * np.sqrt(1 - phi ** 2)
        x += lfilter([1.0], [1.0, -phi], e, zi=[phi * rng.standard_normal()])[0]
    ad = allan_deviation(np.sqrt(rho) * x, 1.0)
    b = rho_to_b(rho, 1.0)
    for m in (4, 16, 64, 256, 1024, 2048):
        k = int(np.argmin(np.abs(ad.tau - m)))
        assert ad.adev[k] / (0.664 * b) == pytest.approx(1.0, rel=0.1), m


def _esg_record_with_flicker(b_arcsec, output=None, seed=4):
    from test_diagnose import _record

    rec = _record(seed=seed, output=output)
    fl = np.asarray(_flicker(jax.random.key(seed + 50), len(rec.t), DT,
                             np.full(2, b_arcsec), t0=DT)) * units.ARCSEC
    return BenchRecord(rec.t, rec.y + fl, rec.channels, rec.attrs)


def test_given_flicker_gls_refit_drop_equals_the_screened_score():
    """With the flicker level given, the tests and the refits run on the same whitened rows: a
    refit (nonlinear Gauss-Newton on the exact model through the innovations filter) lowers the
    whitened chi-square by the screened score of the effect, and the white level comes out at
    the generating 1 arcsec although the flicker adds ~0.2 arcsec per sample."""
    from test_diagnose import TS

    from gyrojax.diagnose._esg import ESGProblem

    w = 2 * np.pi / 86164.0
    line = 3 * units.ARCSEC * np.sin(w * TS + 0.4)
    rec = _esg_record_with_flicker(0.2, output=np.stack([line, -0.5 * line], 1))
    b = 0.2 * units.ARCSEC
    rep = diagnose(rec, design_advice=False, flicker_b=b)
    assert rep.noise["model"] == "white+flicker" and rep.noise["flicker_source"] == "given"
    sigma = np.asarray(rep.noise["std"])
    np.testing.assert_allclose(sigma / units.ARCSEC, 1.0, rtol=0.08)
    prob = ESGProblem(rec, holdout=0.25, flicker_b=b)
    p0 = prob.fit_nominal()
    n = prob.n_train
    _, sigs = prob.jacobians(p0, sigma)

    def chi2(pred):
        return float(np.sum(prob.standardize(prob.y[:n] - pred[:n], sigma) ** 2))

    sig = next(s for s in sigs if s.name == "diurnal_line")
    row = rep.candidate("diurnal_line")
    assert row["score"] > 20
    drop = chi2(prob.predict(p0)) - chi2(prob.refit(p0, [(sig, 0)], sigma)[0])
    assert drop == pytest.approx(row["score"], rel=0.02)
    # the flicker model's ratio against the white part: (s_B / sigma_w)^2
    assert prob._rho == pytest.approx((FLICKER_STD_PER_B * 0.2 / 1.0) ** 2, rel=0.2)


def test_noise_model_bad_input_names_the_fix():
    from test_diagnose import _record

    rec = _record(seed=2)
    with pytest.raises(ValueError, match="white, white\\+flicker"):
        diagnose(rec, noise_model="pink")
    with pytest.raises(ValueError, match="goes with noise_model='white\\+flicker'"):
        diagnose(rec, noise_model="white", flicker_b=1e-7)
    with pytest.raises(ValueError, match="accounts for the residual's whole"):
        diagnose(rec, flicker_b=5 * units.ARCSEC)
    # and a B that leaves the white level only 3 % of the first-difference variance (under
    # the 5 % floor: the white level, and the ratio with it, would be noise)
    from gyrojax.diagnose._esg import ESGProblem
    from gyrojax.diagnose._problem import first_difference_level

    white = ESGProblem(rec, holdout=0.25)
    p = white.fit_nominal()
    fd2 = first_difference_level((white.y - white.predict(p))[: white.n_train]) ** 2
    share = np.sum(1 - np.exp(-DT / flicker_taus(DT)))
    b = np.sqrt(0.97 * fd2 / share) / FLICKER_STD_PER_B
    with pytest.raises(ValueError, match="accounts for the residual's whole"):
        ESGProblem(rec, holdout=0.25, flicker_b=b).fit_nominal()
    with pytest.raises(ValueError, match="noise_model are not for --rig platform"):
        diagnose(rec, rig="platform", noise_model="white+flicker")


def test_cli_diagnose_with_a_given_flicker_level(tmp_path, capsys):
    """``gyrojax diagnose --flicker-arcsec B``: the report's noise model is white + flicker at
    the given B, its white level the generating 1 arcsec (the flicker adds ~0.2 arcsec)."""
    import json

    from gyrojax.cli import main
    from gyrojax.io import save_record

    path = save_record(_esg_record_with_flicker(0.2, seed=6), tmp_path / "rec.nc")
    out = tmp_path / "rep.json"
    assert main(["diagnose", str(path), "--flicker-arcsec", "0.2", "--json", str(out)]) == 0
    noise = json.loads(out.read_text())["noise"]
    assert noise["model"] == "white+flicker"
    assert noise["flicker_B_arcsec"] == pytest.approx([0.2, 0.2], rel=1e-12)
    np.testing.assert_allclose(np.asarray(noise["std"]) / units.ARCSEC, 1.0, rtol=0.08)
    assert "white + flicker (GM sum) model, B = 0.2, 0.2 arcsec given" in capsys.readouterr().out


def test_given_flicker_level_takes_its_own_share_off_the_first_differences():
    """With B given and no white level, the white variance is the residual's first-difference
    level squared less the flicker's own share of it, s^2 sum_i (1 - exp(-dt / tau_i)) (each GM
    term of variance s^2 adds s^2 (1 - phi_i) to half the mean squared difference). On a record
    with 1 arcsec white noise and B = 0.2 arcsec the variance ratio is s^2 / (1 arcsec)^2 within
    the level's sampling error (10 %); the share itself checked against simulated flicker
    alone (5 %)."""
    from gyrojax.diagnose._esg import ESGProblem
    from gyrojax.diagnose._problem import first_difference_level

    b = 0.2 * units.ARCSEC
    s2 = (FLICKER_STD_PER_B * b) ** 2
    share = np.sum(1 - np.exp(-DT / flicker_taus(DT)))
    fl = np.asarray(_flicker(jax.random.key(7), 200_000, DT, np.full(1, 0.2), t0=DT))
    assert fl.shape == (200_000, 1)
    assert first_difference_level(fl)[0] ** 2 == pytest.approx(s2 / units.ARCSEC**2 * share,
                                                                rel=0.05)
    prob = ESGProblem(_esg_record_with_flicker(0.2), holdout=0.25, flicker_b=b)
    prob.fit_nominal()
    np.testing.assert_allclose(prob._rho * units.ARCSEC**2 / s2, 1.0, rtol=0.10)


def test_esg_reml_flicker_level_is_stated_against_the_reported_white_level():
    """The ESG problem's REML flicker level (``noise_model="white+flicker"``, no B given), the
    path no other test runs. On a 24 h record with 1 arcsec white noise and B = 0.2 arcsec
    flicker per channel, B is within 50 % of the generating one on each channel (one seeded
    record: 0.27, 0.26), and its likelihood ratio against no flicker exceeds a white record's
    (2.7, 2.9 against 0.02, 0.33). The ratio is turned into B against the white level that the
    diagnosis reports (the flicker-whitened residual's first differences), not against the raw
    residual's, which holds the flicker's own share too (2 % higher here)."""
    from test_diagnose import _record

    from gyrojax.diagnose._esg import ESGProblem

    fits = {}
    for name, rec in (("flicker", _esg_record_with_flicker(0.2)), ("white", _record(seed=4))):
        prob = ESGProblem(rec, holdout=0.25, noise_model="white+flicker")
        p = prob.fit_nominal()
        assert prob.noise_fit["flicker_source"] == "REML" and prob.notes == []
        white, _, _ = prob.noise_level((prob.y - prob.predict(p))[: prob.n_train])
        b = np.asarray(prob.noise_fit["flicker_B_arcsec"])
        np.testing.assert_allclose(b, rho_to_b(prob._rho, white) / units.ARCSEC, rtol=1e-3)
        fits[name] = b, np.asarray(prob.noise_fit["flicker_lr"])
    np.testing.assert_allclose(fits["flicker"][0], 0.2, rtol=0.5)
    assert np.all(fits["flicker"][1] > fits["white"][1])
    assert np.all(fits["flicker"][0] > fits["white"][0])
