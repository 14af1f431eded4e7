import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import DRIFTS, TS_24H, deg_h, design

import gyrojax as gj
from gyrojax import units
from gyrojax.estimate import esg_augmented_filter, integral_regression, rts_smoother
from gyrojax.estimate.kalman import square_root_filter

MSTAR = dict(zip(DRIFTS, (0.01, -0.01, 0.01, -0.01, 0.01, -0.01)))


def test_square_root_filter_equals_covariance_filter_and_smoother_equals_batch():
    """Second method: a plain covariance Kalman filter in numpy on a random LTV system; and the RTS
    smoother's first state equals the batch (joint Gaussian) posterior."""
    rng = np.random.default_rng(0)
    d, m, n = 4, 2, 30
    phis = np.eye(d) + 0.1 * rng.normal(size=(n - 1, d, d))
    gammas = 0.1 * rng.normal(size=(n - 1, d))
    lq = 0.05 * np.tril(rng.normal(size=(n - 1, d, d)))
    h = rng.normal(size=(m, d))
    lr = 0.2 * np.eye(m)
    ys = rng.normal(size=(n, m))
    x0, s0 = np.zeros(d), np.eye(d)
    res = square_root_filter(*map(jnp.asarray, (x0, s0, phis, gammas, lq, h, lr, ys)))
    x, p = x0.copy(), s0 @ s0.T
    ll = 0.0
    for j in range(n):
        if j:
            x = phis[j - 1] @ x + gammas[j - 1]
            p = phis[j - 1] @ p @ phis[j - 1].T + lq[j - 1] @ lq[j - 1].T
        s = h @ p @ h.T + lr @ lr.T
        k = p @ h.T @ np.linalg.inv(s)
        e = ys[j] - h @ x
        ll += -0.5 * (e @ np.linalg.solve(s, e) + np.log(np.linalg.det(2 * np.pi * s)))
        x = x + k @ e
        p = (np.eye(d) - k @ h) @ p
        np.testing.assert_allclose(res.x_filt[j], x, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(res.p_filt[j], p, rtol=1e-8, atol=1e-10)
    assert float(res.log_likelihood) == pytest.approx(ll, rel=1e-10)
    # smoother vs batch posterior of x_0 for a noise-free transition (joint Gaussian, dense)
    zero_q = jnp.zeros_like(jnp.asarray(lq))
    res0 = square_root_filter(*map(jnp.asarray, (x0, s0, phis, gammas, zero_q, h, lr, ys)))
    xs, ps = rts_smoother(res0, jnp.asarray(phis))
    maps = [np.eye(d)]
    offs = [np.zeros(d)]
    for j in range(n - 1):
        maps.append(phis[j] @ maps[-1])
        offs.append(phis[j] @ offs[-1] + gammas[j])
    a = np.concatenate([h @ mj for mj in maps])
    b = np.concatenate([ys[j] - h @ offs[j] for j in range(n)])
    w = np.linalg.inv(lr @ lr.T)[0, 0]
    info = np.eye(d) + w * a.T @ a
    x0_batch = np.linalg.solve(info, w * a.T @ b)
    np.testing.assert_allclose(xs[0], x0_batch, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(ps[0], np.linalg.inv(info), rtol=1e-7, atol=1e-12)


@pytest.fixture(scope="module")
def transient_case():
    """docs/rigs/esg.md check: equatorial, alpha2(0) = 30 deg, m* = (+-0.01), m0 - m* = 0.02, k = 3,
    dchi2 = dchi3 = 1' (eps2 = -1', eps3 = 1'), 1-min samples, 1 arcsec noise."""
    rig, cond, p = design("equatorial", alpha0_deg=(0, 30), drift=0.0,
                          **MSTAR, eps2=-units.ARCMIN, eps3=units.ARCMIN, k_tr=3.0,
                          **{f"d{n}_0": 0.02 for n in DRIFTS})
    rec = gj.simulate(rig, p, cond, TS_24H, key=jax.random.key(0), noise_std=units.ARCSEC)
    return rig, cond, p, rec


def _max_drift_err(values):
    return max(abs(deg_h(float(values[n]) - MSTAR[n])) for n in DRIFTS)


@pytest.mark.slow  # the transient-state filter's long compile (~20 s)
def test_filter_with_transient_states_recovers_settled_drift(transient_case):
    """Regression and a constant-parameter filter fail by units of deg/h (reference: 3.8, 2.3); the
    filter with the (7.4) transient states reaches 4e-3 deg/h (limited by the O(m dchi) bias)."""
    rig, cond, p, rec = transient_case
    reg = integral_regression(rig, rec, cond)
    const = esg_augmented_filter(rig, rec, cond, noise_std=units.ARCSEC)
    trans = esg_augmented_filter(rig, rec, cond, noise_std=units.ARCSEC, transient_k=3.0)
    e_reg, e_const, e_tr = (_max_drift_err(r.as_dict()) for r in (reg, const, trans))
    assert e_reg > 1.0 and e_const > 1.0
    assert e_tr < 1e-2
    assert e_reg / e_tr > 300
    innov = np.asarray(trans.filter.innovations[20:])
    np.testing.assert_allclose(innov.std(axis=0), 1.0, atol=0.1)


@pytest.mark.slow  # moved out of the default suite (compile-heavy; CI runs it)
def test_normalised_filter_errors_have_unit_rms():
    """On data from the first-order model with theta = 0 (where (6.1) is exact) the filter is
    consistent: estimation errors divided by the reported standard errors have RMS near 1."""
    rig = gj.ESGRig.for_scheme("vertical", 55.75, order="first")
    cond = gj.ESGConditions.from_scheme("vertical", 55.75)
    p = rig.param_space.make({n: 0.01 for n in DRIFTS} | {"eps1": units.ARCMIN,
                                                          "eps2": -units.ARCMIN})
    names = (*DRIFTS, "eps1", "eps2")
    keys = jax.random.split(jax.random.key(7), 40)

    def one(k):
        rec = gj.simulate(rig, p, cond, TS_24H, key=k, noise_std=units.ARCSEC)
        kf = esg_augmented_filter(rig, rec, cond, noise_std=units.ARCSEC, names=names)
        return kf.values, kf.stderr

    vals, ses = jax.vmap(one)(keys)
    truth = jnp.array([p[n] for n in names])
    z = np.asarray((vals - truth) / ses)
    assert np.sqrt(np.mean(z**2)) == pytest.approx(1.0, abs=0.15)


def test_filter_bad_input(transient_case):
    rig, cond, p, rec = transient_case
    with pytest.raises(ValueError, match="noise_std=0"):
        esg_augmented_filter(rig, rec, cond, noise_std=0)
    with pytest.raises(ValueError, match="transient_k=-1"):
        esg_augmented_filter(rig, rec, cond, noise_std=1e-5, transient_k=-1)
