"""The gap map's position, condition, tau-band and lag axes against independent truths: Monte
Carlo moments of the Allan quadratic form, null p-value rates, the noncentrality of a planted
position offset, a random walk in the long-tau band, and the axes in the diagnosis reports."""

import numpy as np
import pytest
from scipy import stats

from gyrojax.diagnose._gapmap import (
    gap_map_cells,
    map_design,
    map_statistics,
    projected_overlapping_allan_moments,
    tau_band_moments,
)
from gyrojax.diagnose._noise_tests import (
    allan_form,
    cross_correlation,
    full_rate_tau_cells,
    lag_cells,
    lag_one_moments,
    ljung_box,
    overlapping_allan_form,
    overlapping_allan_forms,
    projected_overlapping_allan_traces,
    quantization_score,
    white_allan_moments,
    white_overlapping_allan_moments,
)
from gyrojax.diagnose._problem import first_difference_level
from gyrojax.diagnose._signatures import nominal_basis

N, C = 600, 2
T = np.arange(N) * 60.0


def _nominal():
    """A bias and a ramp per channel (the nominal span)."""
    jn = np.zeros((N, C, 2 * C))
    for ch in range(C):
        jn[:, ch, 2 * ch] = 1.0
        jn[:, ch, 2 * ch + 1] = T / T[-1]
    return jn.reshape(N * C, 2 * C)


def _segments():
    """Six positions of 100 samples, the first three at condition "a", the rest at "b"."""
    out = []
    for k in range(6):
        w = np.zeros((N, C))
        w[k * 100:(k + 1) * 100] = 1.0
        out.append((f"p{k}", "a" if k < 3 else "b", w))
    return out


def _aux():
    """Four bins of a temperature cycle's train values (quantiles), as the IMU's aux axis."""
    temp = np.sin(2 * np.pi * T / 9000.0)
    k = np.clip(np.searchsorted(np.quantile(temp, [0, 0.25, 0.5, 0.75, 1]), temp, "right") - 1,
                0, 3)
    return [(f"temp bin {b}", "temp", np.repeat((k == b).astype(float)[:, None], C, 1))
            for b in range(4)]


def _null(b, seed):
    u = nominal_basis(_nominal())
    z = np.random.default_rng(seed).standard_normal((b, N * C))
    z -= (z @ u) @ u.T
    return z.reshape(b, N, C)


def _slices(d):
    nw, ns, nt = len(d.windows), len(d.score_cells), len(d.tau_cells)
    return {"time": slice(0, nw), "score": slice(nw, nw + ns), "tau": slice(nw + ns, nw + ns + nt)}


def test_allan_form_null_moments_match_monte_carlo():
    """E Q = tr T and var Q = 2 tr T^2 after the projection, against 20,000 draws (the MC
    standard errors are 0.2 % and 1 %)."""
    u = nominal_basis(_nominal())
    z = _null(20000, 0)
    for m in (2, 8, 32):
        q = allan_form(z, m)[:, 1]
        mean, var = tau_band_moments(u, N, C, 1, m)
        assert q.mean() == pytest.approx(mean, rel=0.01)
        assert q.var() == pytest.approx(var, rel=0.05)
        # without the projection: K - 1 and the tridiagonal's 2 tr = 2 (K-1) + (K-2)
        k = N // m
        m0, v0 = tau_band_moments(np.zeros((N * C, 0)), N, C, 1, m)
        assert (m0, v0) == pytest.approx((k - 1, 2 * (k - 1) + (k - 2)))
        # the closed form against the dense T = M M' - (M u)(M u)' it stands for
        mu = np.diff(u.reshape(N, C, -1)[: k * m, 1].reshape(k, m, -1).sum(1), axis=0)
        tmat = (np.eye(k - 1) - 0.5 * (np.eye(k - 1, k=1) + np.eye(k - 1, k=-1))
                - mu @ mu.T / (2 * m))
        assert (mean, var) == pytest.approx((np.trace(tmat), 2 * np.sum(tmat * tmat)),
                                            rel=1e-12)


def test_projected_overlapping_allan_moments_match_monte_carlo():
    """The map's tau cells (fully overlapping form): E Q and var Q of a unit white residual with
    the nominal span projected out, against 20,000 draws (MC standard errors 0.2-0.5 % and
    1-3 %), and against the dense ``(I - P) A (I - P)`` they stand for."""
    u = nominal_basis(_nominal())
    z = _null(20000, 30)
    csum = np.concatenate([np.zeros((len(z), 1, C)), np.cumsum(z, axis=1)], axis=1)
    uc = u.reshape(N, C, -1)[:, 1, :]
    sums = np.concatenate([np.zeros((uc.shape[1], 1)), np.cumsum(uc.T, axis=1)], axis=1)
    for m in (2, 8, 32, 64):
        q = overlapping_allan_forms(csum, m)[:, 1]
        mean, var = projected_overlapping_allan_moments(sums, N, m)
        assert q.mean() == pytest.approx(mean, rel=0.01)
        assert q.var() == pytest.approx(var, rel=0.06)
        assert q[0] == pytest.approx(overlapping_allan_form(z[0, :, 1], m), rel=1e-12)
        d = np.zeros((N - 2 * m + 1, N))
        for j in range(N - 2 * m + 1):
            d[j, j:j + m], d[j, j + m:j + 2 * m] = -1.0, 1.0
        proj = np.eye(N) - uc @ uc.T  # channel y's rows of the projector (the span is per channel)
        b = proj @ (d.T @ d / (2 * m)) @ proj
        assert (mean, var) == pytest.approx((np.trace(b), 2 * np.sum(b * b)), rel=1e-10)


def test_position_condition_tau_cells_hold_their_null_rates():
    """Known noise: every position, condition, aux and tau cell rejects 5 % of 8,000 null draws
    (binomial s.e. 0.24 %, pooled over the axis' cells); the condition cells test the three
    positions of a condition jointly (3 dof), the aux joint cell the four temperature bins less
    the direction the bias absorbs (3 dof); no cell where the nominal absorbs it."""
    d = map_design(T, ("x", "y"), n_params=4, noise_dof=np.inf, lines={}, jn=_nominal(),
                   segments=_segments(), aux=_aux())
    axes = [x[0] for x in d.score_cells]
    assert axes.count("position") == 12 and axes.count("condition") == 4
    assert {x[5] for x in d.score_cells if x[0] == "condition"} == {3}
    assert axes.count("aux") == 8 + 2
    assert [x[5] for x in d.score_cells if x[1] == "temp (all bins)"] == [3, 3]
    assert [x[0] for x in d.tau_cells] == [2, 2, 4, 4, 8, 8, 16, 16, 32, 32, 64, 64]
    _, p, _ = map_statistics(d, _null(8000, 1))
    sl = _slices(d)
    for axis in ("score", "tau"):
        rate = float(np.mean(p[:, sl[axis]] < 0.05))
        assert rate == pytest.approx(0.05, abs=0.006), (axis, rate)
        rate1 = float(np.mean(p[:, sl[axis]] < 0.01))
        assert rate1 == pytest.approx(0.01, abs=0.003), (axis, rate1)
    # the same map with the level estimated from first differences (F reference): no cell is
    # liberal (the short-tau cells share the estimate's information: conservative)
    d2 = map_design(T, ("x", "y"), n_params=4, noise_dof=2 * (N - 1) / 3, lines={},
                    jn=_nominal(), segments=_segments(), aux=_aux())
    z = _null(8000, 2)
    _, p2, _ = map_statistics(d2, z / first_difference_level(z)[:, None, :])
    assert np.all(np.mean(p2[:, _slices(d2)["tau"]] < 0.05, axis=0) < 0.058)
    assert np.all(np.mean(p2[:, _slices(d2)["score"]] < 0.05, axis=0) < 0.058)


def test_planted_position_offset_is_found_with_its_noncentrality():
    """An offset of 0.6 sigma on position 3, channel y: its position cell's mean statistic is
    1 + lambda with lambda = delta^2 |(I - P) w|^2 (the noncentral chi-square, 2,000 draws),
    it is the smallest-p cell of the map in >= 95 % of draws, and the cells of the other
    positions keep their null rate."""
    segs = _segments()
    d = map_design(T, ("x", "y"), n_params=4, noise_dof=np.inf, lines={}, jn=_nominal(),
                   segments=segs)
    delta = 0.6
    w = np.zeros((N, C))
    w[300:400, 1] = 1.0
    u = nominal_basis(_nominal())
    wf = w.reshape(-1)
    lam = delta ** 2 * float(np.sum((wf - u @ (u.T @ wf)) ** 2))
    z = _null(2000, 3) + delta * (w - (u @ (u.T @ wf)).reshape(N, C))[None]
    st, p, _ = map_statistics(d, z)
    cells = [(x[0], x[1], x[2]) for x in d.score_cells]
    i = len(d.windows) + cells.index(("position", "p3", 1))
    assert st[:, i].mean() == pytest.approx(1 + lam, rel=0.06)
    # the smallest p of the map is the position's own cell or its condition's
    j = len(d.windows) + cells.index(("condition", "b", 1))
    assert np.mean(np.isin(np.argmin(p, axis=1), [i, j])) >= 0.95
    pos = [len(d.windows) + k for k, c in enumerate(cells) if c[0] == "position"]
    assert np.mean(np.argmin(p[:, pos], axis=1) == pos.index(i)) >= 0.95
    others = [len(d.windows) + k for k, c in enumerate(cells) if c[0] == "position"
              and c[1] not in ("p3",) and c[2] == 0]
    assert float(np.mean(p[:, others] < 0.05)) == pytest.approx(0.05, abs=0.015)
    # the condition cell of the planted position's condition sees it too
    assert np.median(p[:, j]) < 1e-3


def _random_walk_tau_cells(seed, overlapping):
    """Channel x's tau cells of white noise plus a random walk (step s.d. 0.06 sigma)."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((N, C)) + np.cumsum(0.06 * rng.standard_normal((N, C)), axis=0)
    e -= e.mean(0)
    jn = np.repeat(np.eye(C)[None], N, 0).reshape(N * C, C)
    d = map_design(T, ("x", "y"), n_params=2, noise_dof=np.inf, lines={}, jn=jn,
                   overlapping=overlapping)
    cells = gap_map_cells(e, T, ("x", "y"), n_params=2, noise_dof=np.inf, lines={}, jn=jn,
                          design=d)
    return [x for x in cells if x["axis"] == "tau" and x["channel"] == "x"]


def test_random_walk_shows_in_the_long_tau_band():
    """White noise plus a random walk (step s.d. q = 0.06 sigma) in 60 realisations: the AVAR
    ratio grows with tau as 1 + q^2 (2 m^2 + 1) / 6 (the discrete random walk's Allan variance
    over white's, 1 / m), so the longest-tau cell is significant (p < 1e-3) and the smallest p of
    the axis, and its 95 % EDF interval holds that ratio, in most realisations; the shortest
    cell (ratio 1.005) keeps about its null rate. The fully overlapping form (the default)
    detects the walk more often than the non-overlapping one on the same records (measured on
    100: 0.93 against 0.77; smallest p at the longest band 0.97 against 0.92)."""
    rows = {}
    for overlapping in (True, False):
        out = []
        for seed in range(60):
            tau = _random_walk_tau_cells(seed, overlapping)
            m = tau[-1]["tau_s"] / 60.0
            expected = 1 + 0.06 ** 2 * (2 * m * m + 1) / 6
            lo, hi = tau[-1]["ci95"]
            ps = [x["p"] for x in tau]
            out.append((ps[-1] < 1e-3, int(np.argmin(ps)) == len(ps) - 1, lo < expected < hi,
                        ps[0] < 0.01))
        rows[overlapping] = np.mean(out, axis=0)
    assert [x["tau_s"] for x in tau] == [120.0 * 2 ** k for k in range(len(tau))]
    detect, longest, covered, short = rows[True]
    assert detect >= 0.85 and longest >= 0.9 and covered >= 0.85 and short <= 0.05
    assert detect > rows[False][0] + 0.05


def test_lag_axis_is_ljung_box_and_reported_only():
    rng = np.random.default_rng(5)
    e = rng.standard_normal((500, 2))
    e[:, 1] = np.convolve(rng.standard_normal(501), [1.0, 0.8], "valid")  # MA(1)
    cells = lag_cells(e, ("x", "y"))
    assert [x["axis"] for x in cells] == ["lag", "lag"]
    assert all(x["q"] is None and not x["significant"] and not x["decision"] for x in cells)
    assert cells[0]["p"] > 0.01 and cells[1]["p"] < 1e-10
    # the statistic by hand: n (n + 2) sum acf_k^2 / (n - k)
    x = e[:, 0] - e[:, 0].mean()
    acf = [np.sum(x[k:] * x[:-k]) / np.sum(x * x) for k in range(1, 21)]
    q = 500 * 502 * sum(a * a / (500 - k) for k, a in enumerate(acf, 1))
    assert cells[0]["statistic"] == pytest.approx(q, rel=1e-12)
    assert ljung_box(e[:, 0], 20)[1] == pytest.approx(stats.chi2.sf(q, 20), rel=1e-12)
    # the CCF with an auxiliary channel's increments: y follows them two rows late
    temp = np.cumsum(rng.standard_normal(500))
    e[1:, 1] += 0.5 * np.roll(np.diff(temp), 2)
    ccf = lag_cells(e, ("x", "y"), aux={"temp": temp})[2:]
    assert [x["cell"] for x in ccf] == ["CCF with dtemp (lags -20..20)"] * 2
    assert all(x["q"] is None and not x["decision"] for x in ccf)
    assert ccf[1]["lag"] == 2 and ccf[1]["p"] < 1e-6 and ccf[0]["p"] > 0.01
    r, k = cross_correlation(e[1:, 1], np.diff(temp), 3)
    a, b = e[1:, 1] - e[1:, 1].mean(), np.diff(temp) - np.diff(temp).mean()
    assert r[k == 2][0] == pytest.approx(np.sum(a[2:] * b[:-2]) / 499 / a.std() / b.std())


def test_angle_random_walk_generator_sets_the_longest_band_excess():
    """The ESG harness' noise-model case: its random-walk step gives the longest tau band an
    expected Allan excess of z null standard deviations (no projection), by 4,000 draws."""
    from gyrojax.validation import esg as bench

    design = bench.Design()
    rng = np.random.default_rng(6)
    walk, truth = bench._angle_random_walk(rng, design, 3.0)
    n = len(design.ts) - int(round(design.holdout * len(design.ts)))
    m = int(round(truth["band_s"] / (design.ts[1] - design.ts[0])))
    k = n // m
    assert k >= 9 and n // (2 * m) < 9  # the map's longest band
    q = truth["step_arcsec"] / design.noise_arcsec
    z = rng.standard_normal((4000, n, 1)) + np.cumsum(q * rng.standard_normal((4000, n, 1)), 1)
    excess = allan_form(z, m)[:, 0].mean() - (k - 1)
    sd0 = np.sqrt(2 * (k - 1) + (k - 2))
    assert excess / sd0 == pytest.approx(3.0, rel=0.08)


def test_white_allan_moments_match_monte_carlo():
    """The exact null mean and variance of the Allan quadratic form of unit white noise against
    20,000 simulated records (k = 12 clusters of m = 3 samples)."""
    k, m = 12, 3
    e = np.random.default_rng(11).standard_normal((20_000, k * m, 1))
    q = allan_form(e, m)[:, 0]
    mean, var = white_allan_moments(k)
    assert np.mean(q) == pytest.approx(mean, rel=0.01)
    assert np.var(q) == pytest.approx(var, rel=0.04)


def test_white_overlapping_allan_moments_match_monte_carlo():
    """The exact null mean and variance of the fully overlapping Allan quadratic form of unit
    white noise against 20,000 simulated records (n = 64 samples; m = 3, 16 and 32: window
    offsets below m, from m to 2m - 1, and a single window pair)."""
    e = np.random.default_rng(14).standard_normal((20_000, 64))
    for m in (3, 16, 32):
        q = np.array([overlapping_allan_form(x, m) for x in e])
        mean, var = white_overlapping_allan_moments(64, m)
        assert np.mean(q) == pytest.approx(mean, rel=0.015)
        assert np.var(q) == pytest.approx(var, rel=0.05)
    # one window pair is one squared difference of two sums of m: chi^2_1, variance 2
    assert white_overlapping_allan_moments(64, 32) == (1.0, 2.0)


def test_full_rate_tau_cells_null_rate_and_localisation():
    """Full-rate tau band on static pieces of unequal length: under white noise the cells hold
    their level (pooled rejection rate at 0.05, mean ratio 1); a quantization-like term (the
    first difference of a white sequence: Allan excess ~ 1 / tau^2) is localised at the
    shortest band, a rate random walk within the three longest octaves, with the shortest band
    not significant."""
    rng = np.random.default_rng(12)
    sizes = (4000, 3000, 2500)
    p_all, r_all = [], []
    for _ in range(300):
        cells = full_rate_tau_cells({0: [rng.standard_normal(n) for n in sizes]}, ("wx",), 0.02)
        p_all += [x["p"] for x in cells]
        r_all += [x["statistic"] for x in cells]
    assert [x["tau_s"] for x in cells] == pytest.approx([0.02 * 2 ** j for j in range(len(cells))])
    assert all(x["q"] is None and not x["decision"] and x["rate"] == "full" for x in cells)
    assert np.mean(np.array(p_all) < 0.05) == pytest.approx(0.05, abs=0.01)
    assert np.mean(r_all) == pytest.approx(1.0, abs=0.01)

    def pieces(extra):
        return {0: [rng.standard_normal(n) + extra(n) for n in sizes]}

    quant = full_rate_tau_cells(pieces(lambda n: 0.4 * np.diff(rng.standard_normal(n + 1))),
                                ("wx",), 0.02)
    best = min(quant, key=lambda x: x["p"])
    assert best["tau_s"] == quant[0]["tau_s"] and best["p"] < 1e-6
    # the ratio is over the pieces' own mean square (1 + 2 * 0.16): (1 + 3 * 0.16) / 1.32 at
    # one sample (the term's Allan variance there is 3 * 0.16), -> 1 / 1.32 at longer tau
    assert quant[0]["statistic"] == pytest.approx(1.48 / 1.32, rel=0.01)
    mid = [x["statistic"] for x in quant if 8 <= x["tau_s"] / 0.02 <= 32]  # >= 290 clusters
    assert np.mean(mid) == pytest.approx(1 / 1.32, rel=0.1)
    rrw = full_rate_tau_cells(pieces(lambda n: np.cumsum(0.01 * rng.standard_normal(n))),
                              ("wx",), 0.02)
    best = min(rrw, key=lambda x: x["p"])
    assert best["tau_s"] >= rrw[-1]["tau_s"] / 8 and best["p"] < 1e-3
    assert rrw[0]["p"] > 0.01


def _slow_columns(n, offset=0.0):
    """A mean fit's slow columns on ``n`` samples at 50 Hz: bias, ramp, six exponentials."""
    t = np.arange(n) / 50.0 + offset
    taus = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
    return np.stack([np.ones(n), t] + [np.exp(-t / tau) for tau in taus], axis=1)


def test_projected_overlapping_allan_traces_match_the_dense_form():
    """The traces the removed columns take from the overlapping Allan form's white moments
    (``tr U'AU``, ``|AU|^2``, ``|U'AU|^2``), through running sums, against the dense block form
    ``A = D'D / (2m)`` built row by row, on two pieces and four cluster sizes (one too long for
    the short piece)."""
    rng = np.random.default_rng(21)
    sizes = (300, 170)
    u, _ = np.linalg.qr(rng.standard_normal((sum(sizes), 4)) + np.concatenate(
        [_slow_columns(n)[:, :4] for n in sizes]))
    basis = np.split(u, [sizes[0]])
    sums = [np.concatenate([np.zeros((4, 1)), np.cumsum(b.T, axis=1)], axis=1) for b in basis]
    for m in (1, 7, 40, 100):
        a = np.zeros((sum(sizes), sum(sizes)))
        i0 = 0
        for n in sizes:
            if n >= 2 * m:
                d = np.zeros((n - 2 * m + 1, n))
                for j in range(n - 2 * m + 1):
                    d[j, j:j + m], d[j, j + m:j + 2 * m] = -1.0, 1.0
                a[i0:i0 + n, i0:i0 + n] = d.T @ d / (2 * m)
            i0 += n
        uau = u.T @ a @ u
        exact = (np.trace(uau), np.sum((a @ u) ** 2), np.sum(uau ** 2))
        assert projected_overlapping_allan_traces(sums, m) == pytest.approx(exact, rel=1e-10)


@pytest.mark.slow  # ~22 s: Allan moments of many full-rate null draws
def test_full_rate_tau_cells_hold_their_level_with_the_fit_columns_removed():
    """White pieces whose slow columns a mean fit removed (bias, ramp, warm-up exponentials,
    coefficients shared over two pieces): against the plain white reference the longest cells'
    mean ratio sits ~5-15 % low (a slow noise term's excess there is under-read); with the
    columns given (``removed=``) every cell's mean ratio is 1 and the pooled rejection rate at
    0.05 holds, within Monte Carlo error (400 sets)."""
    rng = np.random.default_rng(22)
    sizes = (4000, 2600)
    cols = [_slow_columns(sizes[0]), _slow_columns(sizes[1], offset=100.0)]
    q, _ = np.linalg.qr(np.concatenate(cols))
    plain, fixed, p_fixed = [], [], []
    for _ in range(400):
        z = rng.standard_normal(sum(sizes))
        pcs = np.split(z - q @ (q.T @ z), [sizes[0]])
        a = full_rate_tau_cells({0: pcs}, ("wx",), 0.02)
        b = full_rate_tau_cells({0: pcs}, ("wx",), 0.02, removed={0: cols})
        plain.append([x["statistic"] for x in a])
        fixed.append([x["statistic"] for x in b])
        p_fixed += [x["p"] for x in b]
    plain, fixed = np.array(plain), np.array(fixed)
    se = fixed.std(0) / np.sqrt(len(fixed))
    assert np.all(np.abs(fixed.mean(0) - 1.0) < 3 * se + 1e-3)
    assert plain[:, -1].mean() < 0.92 and plain[:, -2].mean() < 0.99
    assert np.mean(np.array(p_fixed) < 0.05) == pytest.approx(0.05, abs=0.012)
    # a second channel whose columns span the same space (mixed, one repeated) reuses the
    # first channel's traces, with the cells it gets alone
    mixed = [np.concatenate([c @ rng.standard_normal((8, 8)), c[:, :1]], axis=1) for c in cols]
    two = full_rate_tau_cells({0: pcs, 1: pcs}, ("wx", "wy"), 0.02, removed={0: cols, 1: mixed})
    alone = full_rate_tau_cells({1: pcs}, ("wx", "wy"), 0.02, removed={1: mixed})
    assert [x["p"] for x in two if x["channel"] == "wy"] == pytest.approx(
        [x["p"] for x in alone], rel=1e-9)
    with pytest.raises(ValueError, match="one \\(n_i, K\\) array per piece"):
        full_rate_tau_cells({0: pcs}, ("wx",), 0.02, removed={0: [c[:-1] for c in cols]})


def test_lag_one_moments_match_monte_carlo():
    """The exact white-noise mean and variance of the pooled lag-one autocorrelation of
    mean-removed pieces (7, 20 and 150 samples) against 200,000 simulated sets."""
    rng = np.random.default_rng(13)
    sizes = (7, 20, 150)
    xs = [rng.standard_normal((200_000, n)) for n in sizes]
    xs = [x - x.mean(1, keepdims=True) for x in xs]
    r = sum((x[:, 1:] * x[:, :-1]).sum(1) for x in xs) / sum((x * x).sum(1) for x in xs)
    mean, var = lag_one_moments(sizes)
    assert mean == pytest.approx(-0.016095, rel=1e-4)  # -sum (n - 1) / n / sum (n - 1)
    assert np.mean(r) == pytest.approx(mean, abs=4 * np.sqrt(var / r.size))
    assert np.var(r) == pytest.approx(var, rel=0.015)


def test_quantization_score_level_power_and_estimate():
    """The MA(1) score test for quantization: under white noise on unequal pieces its one-sided
    p holds its level (rejection at 0.05 over 3,000 sets); white + the first difference of a
    white angle error of Q = 0.3 tau0 (unit white rate; local noncentrality N Q^4 / tau0^4 = 16)
    rejects at the normal-theory rate of its lag-one autocorrelation -0.09 / 1.18 (the term's
    own variance 2 Q^2 / tau0^2 dilutes it): Phi(0.0763 sqrt(N) - 1.645) = 0.96, and estimates
    Q within 5 %; a
    low-passed (moving-average) white noise, an anti-alias filter's signature, is never taken
    for quantization."""
    rng = np.random.default_rng(14)
    tau0 = 0.02
    p = [quantization_score([rng.standard_normal(n) for n in (900, 600, 64)], tau0)[0]
         for _ in range(3000)]
    assert np.mean(np.array(p) < 0.05) == pytest.approx(0.05, abs=0.012)
    n = 1975  # 16 / 0.3^4
    hits, q_hat = [], []
    for _ in range(400):
        y = rng.standard_normal(n) + 0.3 * np.diff(rng.standard_normal(n + 1))
        pv, z, q = quantization_score([y], tau0)
        hits.append(pv < 0.05)
        q_hat.append(q)
    assert np.mean(hits) == pytest.approx(0.96, abs=0.03)
    big = rng.standard_normal(400_000) + 0.3 * np.diff(rng.standard_normal(400_001))
    assert quantization_score([big], tau0)[2] == pytest.approx(0.3 * tau0, rel=0.05)
    lp = [np.convolve(rng.standard_normal(5000), np.ones(3) / 3, "valid") for _ in range(20)]
    assert min(quantization_score([x], tau0)[0] for x in lp) > 0.5


def test_indistinguishable_classes_are_connected_components():
    """docs/diagnosis.md stage 3: pairs at canonical correlation >= 0.98 merge (transitively) into
    classes; a pair below it, or with an effect not listed (untested), does not."""
    from gyrojax.diagnose._signatures import indistinguishable_classes

    pairs = {("a", "b"): 0.99, ("b", "c"): 0.981, ("c", "d"): 0.979, ("e", "f"): 1.0,
             ("d", "x"): 1.0}
    assert indistinguishable_classes(pairs, "abcdef") == [["a", "b", "c"], ["e", "f"]]
    assert indistinguishable_classes({}, "ab") == []


def test_truth_visibility_is_one_minus_squared_cosine_and_flags_it():
    """The harness' truth side of docs/goals.md confounding: for a one-column nominal span, an
    effect direction at angle phi to it keeps the visible fraction sin^2(phi) = 1 - cos^2(phi);
    the smallest over the effect's directions sets the flag (< 0.05 practically confounded,
    < 1e-6 structurally, a zero column no signature in that direction)."""
    from gyrojax.validation._scoring import projector, truth_visibility

    rng = np.random.default_rng(7)
    q, _ = np.linalg.qr(rng.standard_normal((200, 3)))
    x, y, z = q.T  # orthonormal
    jn = 3.0 * x[:, None]
    for cos2, flag in [(0.5, "visible"), (0.9, "weakly identifiable"),
                       (0.98, "practically confounded")]:
        a = np.sqrt(cos2) * x + np.sqrt(1 - cos2) * y
        jb = np.stack([2.0 * a, 5.0 * z], 1)  # the second direction fully visible
        got = truth_visibility(jb, projector(jn)(jb))
        assert got["visible_fraction"] == pytest.approx(1 - cos2, rel=1e-9)
        assert got["visibility"] == flag
    both = np.stack([4.0 * x, z], 1)
    absorbed = truth_visibility(both, projector(jn)(both))
    assert absorbed["visible_fraction"] < 1e-12
    assert absorbed["visibility"] == "partly structurally confounded"
    blind = np.stack([np.zeros(200), z], 1)
    assert truth_visibility(blind, projector(jn)(blind))["visibility"] == "partly no signature"


def test_confounding_scores_count_recall_precision_and_misattribution():
    from gyrojax.validation._scoring import confounding_scores

    def case(truth_flag, diag_flag, post):
        return ({"family": "a", "visibility": truth_flag},
                {"flags": {"a": diag_flag, "b": "visible"}, "posterior": post})

    pc, vis = "practically confounded", "visible"
    lib = [case(pc, pc, {"a": 0.6, "b": 0.4}), case(pc, vis, {"a": 0.95, "b": 0.05}),
           case(vis, pc, {"a": 0.05, "b": 0.95}), case(vis, vis, {"a": 0.5, "b": 0.5}),
           case("structurally confounded", "no signature", {"a": 0.2, "b": 0.8})]
    s = confounding_scores(lib)
    assert (s["confounding_recall"]["rate"], s["confounding_recall"]["n"]) == (2 / 3, 3)
    assert (s["confounding_precision"]["rate"], s["confounding_precision"]["n"]) == (2 / 3, 3)
    assert s["confounding_agreement"]["rate"] == 3 / 5
    assert s["confident_misattribution_all"]["rate"] == 1 / 5  # 0.95 on b; 0.8 is not > 0.9
