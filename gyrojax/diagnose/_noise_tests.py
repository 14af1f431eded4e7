"""Tests of the noise model, reported beside the map: Allan variance forms and their moments under
white noise, the full-rate tau band of the static pieces, quantization and outlier scores, Ljung-
Box lags and cross-correlation with auxiliary channels.

Whitened quantities throughout (see :mod:`gyrojax.diagnose._signatures`)."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from ._signatures import chi2_sf, nominal_basis

__all__ = ["allan_form", "cross_correlation", "full_rate_tau_cells", "lag_cells", "lag_one_moments",
           "ljung_box", "outlier_score", "overlapping_allan_form", "overlapping_allan_forms",
           "projected_overlapping_allan_traces", "quantization_score", "tau_cell",
           "white_allan_moments", "white_overlapping_allan_moments"]


def allan_form(e: np.ndarray, m: int, csum: np.ndarray | None = None) -> np.ndarray:
    """``Q = sum_k (S_k+1 - S_k)^2 / (2 m)`` over the cluster sums ``S_k`` of ``m`` samples of
    ``e`` (``B x n x c``): ``(B, c)``; ``Q / (K - 1)`` is the non-overlapping Allan variance at
    ``tau = m tau_0`` over its white-noise value ``1 / m`` (unit noise). ``csum``: the running
    sums of ``e`` with a leading zero (``B x n+1 x c``), shared between cluster sizes."""
    if csum is None:
        csum = np.concatenate([np.zeros_like(e[:, :1]), np.cumsum(e, axis=1)], axis=1)
    edges = np.arange(e.shape[1] // m + 1) * m
    s = np.diff(csum[:, edges], axis=1)
    return np.sum(np.diff(s, axis=1) ** 2, axis=1) / (2 * m)


def white_allan_moments(k: int) -> tuple[float, float]:
    """Mean and variance of the Allan quadratic form :func:`allan_form` over ``k >= 2`` clusters
    of unit white noise: ``Q = d' d`` with ``d`` the ``k - 1`` differences of the cluster sums
    over ``sqrt(2 m)``, whose covariance ``M M'`` is the tridiagonal ``(1, -1/2)``; so
    ``E Q = k - 1`` and ``var Q = 2 tr (M M')^2 = 2 ((k - 1) + (k - 2) / 2)``."""
    return float(k - 1), 2.0 * ((k - 1) + 0.5 * (k - 2))


def overlapping_allan_form(x: np.ndarray, m: int) -> float:
    """``Q = sum_j (S_{j+m} - S_j)^2 / (2 m)`` over *every* window start ``j`` (``S_j`` the sum
    of ``x[j:j+m]``): ``Q / (n - 2m + 1)`` is the fully overlapping Allan variance at ``tau = m
    tau_0`` over its white-noise value ``1 / m`` (unit noise)."""
    cs = np.concatenate([[0.0], np.cumsum(np.asarray(x, float))])
    s = cs[m:] - cs[:-m]
    return float(np.sum((s[m:] - s[:-m]) ** 2) / (2 * m))


def overlapping_allan_forms(csum: np.ndarray, m: int) -> np.ndarray:
    """:func:`overlapping_allan_form` of every series at once from their running sums with a
    leading zero, ``csum`` (``B x n+1 x c``): ``(B, c)``."""
    s = csum[:, m:] - csum[:, :-m]
    return np.sum((s[:, m:] - s[:, :-m]) ** 2, axis=1) / (2 * m)


def white_overlapping_allan_moments(n: int, m: int) -> tuple[float, float]:
    """Mean and variance of :func:`overlapping_allan_form` on ``n`` samples of unit white noise:
    ``Q = |D z|^2`` with ``L = n - 2m + 1`` rows ``d_j`` of unit norm, whose inner products
    depend on the offset ``k = |i - j|`` alone: ``(2m - 3k) / (2m)`` below ``m``, ``-(2m - k) /
    (2m)`` from ``m`` to ``2m - 1``, 0 beyond. So ``E Q = L`` and ``var Q = 2 |D D'|_F^2 =
    2 (L + 2 sum_k (L - k) c_k^2)``."""
    big_l = n - 2 * m + 1
    if big_l < 1:
        raise ValueError(f"white_overlapping_allan_moments: n={n} < 2 m = {2 * m}")
    k = np.arange(1, min(2 * m, big_l))
    c = np.where(k < m, (2 * m - 3 * k) / (2 * m), -(2 * m - k) / (2 * m))
    return float(big_l), 2.0 * (big_l + 2.0 * float(np.sum((big_l - k) * c * c)))


class _RemovedSpan:
    """The span of the columns a least-squares fit removed from a set of pieces (coefficients
    shared over the pieces), for the white moments of :func:`overlapping_allan_form`: an
    orthonormal basis ``U`` (:func:`nominal_basis`) and the traces of
    :func:`projected_overlapping_allan_traces` per cluster size, computed once.
    :meth:`of` reuses a span already prepared when the new columns span it (the channels of one
    record often share their bias, drift and warm-up columns)."""

    def __init__(self, u: np.ndarray, sizes: list[int]):
        self.u, self.sizes, self.dim = u, sizes, u.shape[1]
        self._sums = None
        self._traces: dict[int, tuple[float, float, float]] = {}

    @classmethod
    def of(cls, columns: list, sizes: list[int], known: list[_RemovedSpan]) -> _RemovedSpan:
        mats = [np.asarray(c, float) for c in columns]
        if any(m.ndim != 2 or len(m) != n for m, n in zip(mats, sizes)) or \
                len({m.shape[1] for m in mats}) != 1:
            raise ValueError("full_rate_tau_cells: give the removed columns as one (n_i, K) "
                             "array per piece, n_i its samples, the same K for every piece; got "
                             f"shapes {[m.shape for m in mats]} for pieces of {list(sizes)}")
        x = np.concatenate(mats)
        norm = np.linalg.norm(x, axis=0)
        x = x[:, norm > 0] / norm[norm > 0]
        for span in known:  # x = U C exactly when x lies in span(U); then rank x = rank C
            if span.sizes == list(sizes) and span.dim:
                c = span.u.T @ x
                if np.linalg.norm(x - span.u @ c) <= 1e-8 * math.sqrt(x.shape[1]):
                    sv = np.linalg.svd(c, compute_uv=False)
                    if np.sum(sv > 1e-10 * sv[0]) == span.dim:
                        return span
        span = cls(nominal_basis(x) if x.shape[1] else np.zeros((len(x), 0)), list(sizes))
        known.append(span)
        return span

    def traces(self, m: int) -> tuple[float, float, float]:
        if m not in self._traces:
            if self._sums is None:
                self._sums = [np.concatenate([np.zeros((self.dim, 1)), np.cumsum(b.T, axis=1)],
                                             axis=1)
                              for b in np.split(self.u, np.cumsum(self.sizes)[:-1])]
            self._traces[m] = projected_overlapping_allan_traces(self._sums, m)
        return self._traces[m]


def projected_overlapping_allan_traces(sums: list[np.ndarray], m: int) -> tuple[float, float,
                                                                                 float]:
    """What removing the columns of an orthonormal basis ``U`` (over all pieces) takes from the
    white-noise moments of :func:`overlapping_allan_form` summed over pieces:
    ``(tr U'AU, |AU|_F^2, |U'AU|_F^2)``, ``A`` the block-diagonal form (one block per piece).
    ``sums``: per piece the running sums of its rows of ``U`` with a leading zero, ``(K, n_i +
    1)`` (shared between cluster sizes); pieces shorter than ``2 m`` are skipped.

    ``Q = |D x|^2`` per piece with ``(D x)_j = (c_{j+2m} - 2 c_{j+m} + c_j) / sqrt(2m)`` on the
    running sums ``c``; ``A U = D'(D U)``, the adjoint by one more running sum: O(n K)."""
    au2, uau = 0.0, None
    scale = 1.0 / math.sqrt(2 * m)
    for c in sums:
        k, n = c.shape[0], c.shape[1] - 1
        if n < 2 * m:
            continue
        length = n - 2 * m + 1
        d = np.empty((k, length))  # D U
        g = np.empty(n)
        for i in range(k):  # one column at a time: its running sums stay in cache
            ci, di = c[i], d[i]
            np.subtract(ci[2 * m:], ci[m:-m], out=di)
            di -= ci[m:-m]
            di += ci[: -2 * m]
            di *= scale
            # the adjoint onto the running sums c_0..c_{n-1} (c_n, the total, gets nothing:
            # the weights (1, -2, 1) of every row sum to zero), then x_l enters c_i for i > l:
            # (D'v)_l = sum_{i > l} g_i = -sum_{i <= l} g_i
            g[:length] = di
            g[length:] = 0.0
            g[m:m + length] -= 2.0 * di
            g[2 * m:] += di[: n - 2 * m]
            np.cumsum(g, out=g)
            au2 += float(g @ g) * scale * scale  # |A U|^2 = |D' D U|^2
        uau = d @ d.T if uau is None else uau + d @ d.T
    if uau is None:
        return 0.0, 0.0, 0.0
    return float(np.trace(uau)), au2, float(np.sum(uau * uau))


def full_rate_tau_cells(pieces: dict, channels: tuple[str, ...], tau0: float, *,
                        min_clusters: int = 9, overlapping: bool = True,
                        removed: dict | None = None) -> list[dict]:
    """Tau band x channel at the full sampling rate: the fully overlapping Allan variance
    (``overlapping=False``: the non-overlapping one) of residual ``pieces`` (channel index ->
    list of 1-D arrays, e.g. the static intervals of one record, sampled every ``tau0`` s) over
    its value for white noise (below), at ``tau = m tau0`` for ``m = 1, 2, 4, ...`` while the
    pieces hold ``>= min_clusters`` non-overlapping clusters. The overlapping form uses every
    window start: its equivalent dof are ~2x the non-overlapping form's (2.03x at 9 clusters),
    and a rate random walk's smallest-p cell landed within 3 octaves of the longest tau in 0.91
    of 45 static-design cases (lambda 32-128), 0.73 with the non-overlapping form.

    This is the axis that localises noise-model effects whose excess lives below a gap map's
    row spacing (quantization at the shortest tau) as well as the slow ones (bias instability,
    rate random walk at the longest). The white value is that of the pieces' own mean square
    ``s^2`` (per channel), for which the null mean and variance of ``Q / s^2`` are exact (see
    the comment below), so every cell holds its level. A term that carries much of the variance
    raises ``s^2`` and so also lowers the ratio away from its band (strong quantization: an
    excess at one sample, a deficit at long tau); the one-sided p-values see only the excess.
    (A noise-model fit's white level as the reference, tried instead, moved the smallest p of
    weak slow terms to the shortest band: that level's own error, with ~N/10 dof from the
    fitted band, outweighs a short band's sampling error.) Cells
    are reported, not decided on (``q`` None, ``decision`` False, like the lag axis): the
    decision family tests the noise-model effects themselves; these say where in tau their
    excess lies. ``rate`` is ``"full"``.

    ``removed`` (channel index -> one ``(n_i, K)`` array per piece): the columns a least-squares
    fit took out of the residual (coefficients shared over the pieces). The white reference is
    then that of white noise with those columns projected out, as the residual is: a mean fit's
    slow columns (bias, ramp, warm-up exponentials) lower the longest cells' white mean by up to
    ~20 %, which the plain reference reads as a deficit of slow noise."""
    if removed is not None and not overlapping:
        raise ValueError("full_rate_tau_cells: removed= needs the overlapping form")
    out, spans = [], []
    for ch, pcs in pieces.items():
        cols = (removed or {}).get(ch)
        if cols is not None and len(cols) != len(pcs):
            raise ValueError(f"full_rate_tau_cells: channel {ch} has {len(pcs)} pieces but "
                             f"{len(cols)} arrays of removed columns; give one per piece")
        keep = [i for i, p in enumerate(pcs) if np.size(p) >= 2]
        pcs = [np.asarray(pcs[i], float) for i in keep]
        n_all = sum(p.size for p in pcs)
        if not n_all:
            continue
        s = math.sqrt(sum(float(np.sum(p * p)) for p in pcs) / n_all)
        if s == 0.0:
            continue
        span = None if cols is None else \
            _RemovedSpan.of([cols[i] for i in keep], [p.size for p in pcs], spans)
        dim = 0 if span is None else span.dim
        m = 1
        while True:
            use = [(p, p.size // m) for p in pcs if p.size // m >= 2]
            clusters = sum(k for _, k in use)
            if clusters < min_clusters:
                break
            if overlapping:
                q = sum(overlapping_allan_form(p / s, m) for p, _ in use)
                mom = np.array([white_overlapping_allan_moments(p.size, m)
                                for p, _ in use]).sum(0)
            else:
                q = sum(float(allan_form(p[None, :, None] / s, m)[0, 0]) for p, _ in use)
                mom = np.array([white_allan_moments(k) for _, k in use]).sum(0)
            # Q / s^2 = N z'Bz / z'z over the N' = N - K dimensions the fit leaves (B = PAP,
            # P the projector off the removed columns) is independent of z'z (spherical
            # symmetry): its mean is N tr B / N' and its variance
            # N^2 2 (N' tr B^2 - (tr B)^2) / (N'^2 (N' + 2)): well below the known-level
            # 2 tr A^2 at the short bands, where Q and s^2 share their samples; and with slow
            # columns removed (a mean fit's bias, ramp, warm-up), the mean falls well below
            # tr A at the longest bands (0.80 tr A at N / 11 samples for 8 such columns)
            tr_a, tr_a2 = float(mom[0]), 0.5 * float(mom[1])
            tr_uau, au2, uau2 = (0.0, 0.0, 0.0) if span is None else span.traces(m)
            tr_b, tr_b2 = tr_a - tr_uau, tr_a2 - 2.0 * au2 + uau2
            dof = n_all - dim
            mean = n_all * tr_b / dof
            var = n_all ** 2 * 2.0 * (dof * tr_b2 - tr_b ** 2) / (dof ** 2 * (dof + 2))
            g, h = var / (2 * mean), 2 * mean ** 2 / var
            out.append(tau_cell(m * tau0, channels[ch], q / mean, mean, h,
                                float(chi2_sf(q / g, h)), clusters, rate="full", q=None,
                                significant=False, decision=False))
            m *= 2
    return out


def lag_one_moments(sizes) -> tuple[float, float]:
    """Exact mean and variance, for white noise, of the pooled lag-one autocorrelation
    :func:`quantization_score` reads: ``r = sum x_k x_{k+1} / sum x_k^2`` over pieces of
    ``sizes`` samples, each mean-removed.

    Per piece ``r`` is ``x'Ax / x'Cx`` with ``A`` the symmetric lag-one form (``1/2`` off the
    diagonal) and ``C`` the centring projector; over the pieces' ``N' = sum (n - 1)`` free
    dimensions the ratio ``w'Bw / w'w`` (``B = CAC``) has mean ``tr B / N'`` and variance
    ``2 (N' tr B^2 - (tr B)^2) / (N'^2 (N' + 2))``, with ``tr B = -(n - 1) / n`` and
    ``tr B^2 = (n - 1) / 2 - 2 (n - 3/2) / n + (n - 1)^2 / n^2`` per piece."""
    n = np.asarray(sizes, float)
    n = n[n >= 2]
    if n.size == 0:
        raise ValueError("lag_one_moments: no piece of at least 2 samples")
    dof = float(np.sum(n - 1))
    tr = float(np.sum(-(n - 1) / n))
    tr2 = float(np.sum((n - 1) / 2 - 2 * (n - 1.5) / n + (n - 1) ** 2 / n ** 2))
    return tr / dof, 2 * (dof * tr2 - tr * tr) / (dof * dof * (dof + 2))


def quantization_score(pieces, tau0: float) -> tuple[float, float, float]:
    """Score (Rao) test for quantization on white-noise residual ``pieces`` sampled every
    ``tau0`` s: returns ``(p, z, Q)``, ``z`` positive where ``r`` lies below its white mean.

    Angle quantization adds the first difference of a white angle error to the rate: white +
    quantization is an MA(1) process with a negative coefficient (lag-one autocovariance
    ``-Q^2 / tau0^2``, all else zero), and the score test of an MA(1) coefficient at zero is the
    lag-one autocorrelation ``r`` (Box-Jenkins). ``z = (r - E r) / sd r`` with the exact white
    moments of :func:`lag_one_moments`; one-sided (``p = Phi(z)``): a negative ``r`` is
    quantization; slow terms, an anti-alias roll-off and settling motion make ``r`` positive and
    the test only conservative. It uses every sample pair up to the Nyquist frequency, where
    quantization's spectrum ``4 sin^2(pi f tau0) Q^2 / tau0^2`` lives; a band-limited fit (the
    Whittle one up to ``rate / 10``) keeps a tenth of it. ``Q`` (the pieces' unit times s) is
    ``tau0 sqrt(-c1)`` from the lag-one autocovariance ``c1`` (0 when ``c1 >= 0``)."""
    pcs = [np.asarray(x, float) - np.mean(x) for x in pieces if np.size(x) >= 2]
    if not pcs:
        raise ValueError("quantization_score: no piece of at least 2 samples")
    c0 = sum(float(np.dot(x, x)) for x in pcs)
    if c0 == 0.0:
        raise ValueError("quantization_score: the pieces are constant")
    c1 = sum(float(np.dot(x[1:], x[:-1])) for x in pcs)
    mean, var = lag_one_moments([x.size for x in pcs])
    z = (c1 / c0 - mean) / math.sqrt(var)
    c1 /= sum(x.size - 1 for x in pcs)
    return float(stats.norm.cdf(z)), float(-z), tau0 * math.sqrt(max(-c1, 0.0))


def outlier_score(pieces) -> tuple[float, float, float]:
    """One-sided test for outliers (heavy tails) on white-noise residual ``pieces``: the excess
    kurtosis ``k`` of the pieces' non-overlapping first differences (the differences remove a
    slow residual; taking every other one keeps them independent), ``z = k / sqrt(24 / n)`` its
    large-sample Gaussian law on ``n`` differences; returns ``(p, z, k)``, ``p = 1 - Phi(z)``
    (a knock or a spike makes the tails heavy, ``k > 0``)."""
    d = np.concatenate([np.diff(np.asarray(x, float))[::2] for x in pieces if np.size(x) >= 2])
    if d.size < 4:
        raise ValueError("outlier_score: fewer than 4 first differences in the pieces")
    d = d - d.mean()
    m2 = float(np.mean(d ** 2))
    if m2 == 0.0:
        raise ValueError("outlier_score: the pieces are constant")
    k = float(np.mean(d ** 4)) / m2 ** 2 - 3
    z = k / math.sqrt(24.0 / d.size)
    return float(stats.norm.sf(z)), z, k


def ljung_box(x: np.ndarray, lags: int):
    """Ljung-Box portmanteau of a series ``x``: ``(Q, p, acf)`` with ``p`` from chi2(lags)."""
    x = x - x.mean()
    n = len(x)
    acf = np.array([np.sum(x[k:] * x[:-k]) for k in range(1, lags + 1)]) / max(
        float(np.sum(x * x)), 1e-300)
    q = float(n * (n + 2) * np.sum(acf ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(chi2_sf(q, lags)), acf


def lag_cells(e: np.ndarray, channels: tuple[str, ...], lags: int = 20,
              aux: dict | None = None) -> list[dict]:
    """Ljung-Box whiteness per channel of a whitened residual ``e`` (``n x c``), the ``resid``-
    style lag axis, and with ``aux`` (name -> ``n`` values of an auxiliary channel on the same
    rows) the cross-correlation of each channel with the auxiliary channel's increments at lags
    ``-L..L`` (largest ``|r| sqrt(n)``, Bonferroni over the lags against N(0, 1)): reported for
    compatibility, never a decision statistic (no q-value)."""
    n = e.shape[0]
    lags = max(1, min(lags, n // 5))
    out = []
    for ch, name in enumerate(channels):
        q, p, acf = ljung_box(e[:, ch], lags)
        out.append(dict(axis="lag", cell=f"lags 1-{lags} (Ljung-Box)", channel=name,
                        statistic=q, dof=lags, expected=float(lags), excess=q - lags, p=p,
                        acf=[float(a) for a in acf[:5]], q=None, significant=False,
                        decision=False))
    for aname, a in (aux or {}).items():
        da = np.diff(np.asarray(a, float)[:n])
        if da.size < 3 or not np.any(da != da[0]):
            continue
        for ch, name in enumerate(channels):
            r, lag = cross_correlation(e[1:, ch], da, lags)
            z = float(np.max(np.abs(r)) * np.sqrt(da.size))
            p = float(min(1.0, len(r) * 2 * stats.norm.sf(z)))
            out.append(dict(axis="lag", cell=f"CCF with d{aname} (lags -{lags}..{lags})",
                            channel=name, statistic=z, dof=len(r), expected=1.0, excess=0.0,
                            p=p, lag=int(lag[np.argmax(np.abs(r))]), q=None,
                            significant=False, decision=False))
    return out


def cross_correlation(x: np.ndarray, y: np.ndarray, lags: int):
    """Sample cross-correlation ``r_k = corr(x_t, y_{t-k})`` of two equal-length series at
    ``k = -lags..lags``: ``(r, k)``."""
    x = (x - x.mean()) / max(float(np.std(x)), 1e-300)
    y = (y - y.mean()) / max(float(np.std(y)), 1e-300)
    n = len(x)
    ks = np.arange(-lags, lags + 1)
    r = np.array([np.sum(x[k:] * y[:n - k]) if k >= 0 else np.sum(x[:n + k] * y[-k:])
                  for k in ks]) / n
    return r, ks


def tau_cell(tau_s: float, channel: str, r: float, mean: float, h: float, p: float,
             clusters: int, *, rate: str | None = None, **extra) -> dict:
    """One tau-band cell of a report's ``where``: the Allan ratio ``r`` at ``tau_s`` over its
    white-noise value (null mean ``mean`` counts, equivalent dof ``h``), its p-value and its EDF
    95 % interval. ``rate="full"`` marks the full-rate band (:func:`full_rate_tau_cells`)."""
    return dict(axis="tau", cell=f"tau {_duration(tau_s)}" + (f" ({rate} rate)" if rate else ""),
                channel=channel, statistic=r, dof=h, expected=1.0, excess=(r - 1.0) * mean,
                p=p, tau_s=tau_s, clusters=clusters,
                ci95=[r * h / float(stats.chi2.ppf(0.975, h)),
                      r * h / float(stats.chi2.ppf(0.025, h))],
                **({"rate": rate} if rate else {}), **extra)


def _duration(s: float) -> str:
    return f"{s:.3g} s" if s < 120 else f"{s / 60:.3g} min" if s < 7200 else f"{s / 3600:.3g} h"
