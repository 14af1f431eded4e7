"""The gap map: where the whitened residual departs from white noise, cell by cell (time x channel
windows, known lines, the largest unlisted line, positions and conditions, auxiliary bins, the
Allan tau band), each cell a test with its p-value (docs/diagnosis.md, stage 1).

Whitened quantities throughout (see :mod:`gyrojax.diagnose._signatures`)."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import special

from ._noise_tests import (
    allan_form,
    overlapping_allan_forms,
    projected_overlapping_allan_traces,
    tau_cell,
    white_allan_moments,
    white_overlapping_allan_moments,
)
from ._screening import _lm
from ._signatures import VISIBLE_MIN, chi2_sf, nominal_basis, project_out

__all__ = ["MapDesign", "fisher_g_pvalue", "gap_map_cells", "map_design", "map_statistics",
           "projected_overlapping_allan_moments", "tau_band_moments"]


def fisher_g_pvalue(g, q: int):
    """P(Fisher's g >= g) for ``q`` periodogram ordinates of white noise (exact series,
    ``sum_j (-1)^(j-1) C(q, j) (1 - j g)^(q-1)`` over ``j g < 1``); ``g`` a float or an array.

    The terms grow huge when ``g`` is far below its null typical value ``~ln(q)/q`` and the
    alternating sum then cancels to noise (it returned 0 at ``g = 0.003, q = 539``); there the
    p-value is 1 to many digits and is returned as such (largest term above ``1e6``).
    """
    scalar = np.ndim(g) == 0
    g = np.atleast_1d(np.asarray(g, float))
    if q < 2:
        p = np.ones_like(g)
        return float(p[0]) if scalar else p
    jmax = int(min(q, np.floor(1.0 / max(float(g.min()), 1.0 / q))))
    j = np.arange(1, jmax + 1, dtype=float)
    logc = special.gammaln(q + 1) - special.gammaln(j + 1) - special.gammaln(q - j + 1)
    x = 1.0 - j[None, :] * g[:, None]
    # capped at 1e7: a term beyond 1e6 makes p 1 below, so the cap changes no p-value, and an
    # uncapped exp overflowed (a RuntimeWarning on the user's terminal) once C(q, j) or a term
    # passed float64's range (q ~ 1000 and up: the Schuler test's 1-s records)
    expo = logc + (q - 1) * np.log(np.where(x > 0, x, 1.0))
    term = np.where(x > 0, np.exp(np.minimum(expo, np.log(1e7))), 0.0)
    total = np.sum(np.where(j % 2 == 1, 1.0, -1.0) * term, axis=1)
    p = np.where(term.max(axis=1) > 1e6, 1.0, np.clip(total, 0.0, 1.0))
    return float(p[0]) if scalar else p


@dataclasses.dataclass
class MapDesign:
    """The data-independent part of the gap map (:func:`map_design`): its cells, in order, and
    what each needs to be evaluated on a residual."""

    n: int
    c: int
    t: np.ndarray
    channels: tuple
    noise_dof: float
    windows: list  # (level, k, a, b, channel, expected)
    score_cells: list  # (axis, label, channel, basis J~ (n c, k), cov (k, k), dof, info dict)
    tau_cells: list  # (m, clusters, channel, mean, scale g, edf h)
    fisher: bool
    overlapping: bool = True  # the tau cells' Allan form (fully overlapping or not)
    n_extra: int = 0  # entries of a second residual block after the n c rows (score cells)

    @property
    def n_cells(self) -> int:
        return (len(self.windows) + len(self.score_cells) + len(self.tau_cells)
                + (self.c if self.fisher else 0))


def _score_cell(u, cols, *, min_visible=VISIBLE_MIN):
    """Projected basis, pseudo-inverse information and dof of a score cell with raw columns
    ``cols`` (``n c x k``): directions whose visible fraction after projecting out ``u`` is
    below ``min_visible`` are absorbed (not tested)."""
    if cols.shape[0] < u.shape[0]:  # a rows' cell: zero on the second block
        cols = np.concatenate([cols, np.zeros((u.shape[0] - cols.shape[0], cols.shape[1]))])
    jt = project_out(u, cols)
    _, dof, _, cov, _, _ = _lm(jt, np.zeros(len(cols)), float(np.max(np.sum(cols ** 2, 0))),
                               rtol=min_visible)
    return jt, cov, dof


def _channel_columns(w, ch, c):
    """Columns ``w`` (``n x k``) placed on channel ``ch`` of ``n x c`` rows, flattened."""
    cols = np.zeros((w.shape[0], c, w.shape[1]))
    cols[:, ch, :] = w
    return cols.reshape(-1, w.shape[1])


def tau_band_moments(u, n: int, c: int, ch: int, m: int):
    """Null mean and variance of the Allan quadratic form ``Q = sum_k (S_k+1 - S_k)^2 / (2 m)``
    (``S_k``: sums of ``K = n // m`` consecutive clusters of ``m`` samples of channel ``ch``) of
    a unit white residual with the span ``u`` (orthonormal, ``n c`` rows) projected out:
    ``Q = z' (I - P) M' M (I - P) z``, so ``E Q = tr T`` and ``var Q = 2 tr T^2`` with
    ``T = M (I - P) M' = M M' - (M u)(M u)'`` and ``M M'`` the tridiagonal (1, -1/2)."""
    k = n // m
    uc = u.reshape(n, c, -1)[: k * m, ch, :]
    mu = np.diff(uc.reshape(k, m, -1).sum(1), axis=0) / np.sqrt(2 * m)  # (K-1, p)
    # with A = M M' and B = (M u)(M u)': tr T = tr A - tr B and
    # tr T^2 = |A|_F^2 - 2 <A, B> + |mu' mu|_F^2, <A, B> = tr B - sum_i mu_i . mu_i+1
    tr_b = float(np.sum(mu * mu))
    ab = tr_b - float(np.sum(mu[1:] * mu[:-1]))
    tr_a, var_a = white_allan_moments(k)  # tr A and 2 |A|_F^2
    g = mu.T @ mu
    return tr_a - tr_b, var_a + 2 * (-2 * ab + float(np.sum(g * g)))


def map_design(t: np.ndarray, channels: tuple[str, ...], *, n_params: int, noise_dof: float,
               lines: dict[str, float], jn: np.ndarray, min_window: int = 16,
               levels: int = 5, segments=None, nuisance=None, min_clusters: int = 9,
               aux=None, overlapping: bool = True, block=None) -> MapDesign:
    """The cells of :func:`gap_map_cells` for ``n = len(t)`` samples of ``channels``.

    ``segments``: the record's test positions, ``[(label, condition, w)]`` with ``w``
    (``n x c``) the whitened per-channel signature of a position offset on the train rows (zero
    off the position); ``nuisance``: whitened columns (``n c x k``) fitted outside ``jn`` (the
    platform's dwell offsets), projected out with it; ``aux``: bins of the record's auxiliary
    channels, ``[(label, aux channel, w)]`` with ``w`` the whitened signature of an offset on the
    rows of one bin (e.g. a temperature range): one 1-dof cell per bin and channel and the joint
    test of one auxiliary channel's bins per channel (axis ``aux``); ``overlapping``: the tau
    cells' Allan form (fully overlapping, or the non-overlapping one of :func:`allan_form`);
    ``block``: score cells of a second residual block whose entries follow the rows' in ``jn``
    (the IMU's turns), ``[(axis, label, channel name, columns (entries, k))]``."""
    n, c = len(t), len(channels)
    n_extra = jn.shape[0] - n * c
    frac = 1.0 - n_params / max(n * c + n_extra, 1)
    windows = []
    for lev in range(levels):
        nw = n >> lev
        if nw < min_window:
            break
        for k in range(1 << lev):
            a, b = k * nw, (k + 1) * nw if k < (1 << lev) - 1 else n
            for ch in range(c):
                windows.append((lev, k, a, b, ch, (b - a) * frac))
    u = nominal_basis(jn if nuisance is None else np.concatenate([jn, nuisance], axis=1))
    score_cells = []
    for name, period in lines.items():
        w = 2 * np.pi / period
        for ch in range(c):
            cols = _channel_columns(np.stack([np.sin(w * t), np.cos(w * t)], 1), ch, c)
            jt, cov, dof = _score_cell(u, cols, min_visible=1e-10)
            score_cells.append(("frequency", f"{name} ({period / 3600:.4g} h)", ch, jt, cov,
                                dof, {"period_s": float(period)}))
    segments = list(segments or [])
    score_cells += _member_cells(u, segments, c, "position", "condition")
    conds = list(dict.fromkeys(cond for _, cond, _ in segments))
    if len(conds) > 1:
        score_cells += _group_cells(u, segments, c, "condition", "positions")
    aux = list(aux or [])
    score_cells += _member_cells(u, aux, c, "aux", "aux")
    score_cells += _group_cells(u, aux, c, "aux", "bins", suffix=" (all bins)", key="aux")
    for axis, label, channel, cols in block or ():
        jt, cov, dof = _score_cell(u, np.concatenate([np.zeros((n * c, cols.shape[1])), cols]))
        if dof:
            score_cells.append((axis, label, channel, jt, cov, dof, {}))
    tau_cells = []
    uc = u[: n * c].reshape(n, c, -1)
    sums = [np.concatenate([np.zeros((uc.shape[2], 1)), np.cumsum(uc[:, ch, :].T, axis=1)],
                           axis=1) for ch in range(c)] if overlapping else None
    m = 2
    while n // m >= min_clusters:
        for ch in range(c):
            if overlapping:
                mean, var = projected_overlapping_allan_moments(sums[ch], n, m)
            else:
                mean, var = tau_band_moments(u[: n * c], n, c, ch, m)
            if mean > 0 and var > 0:
                tau_cells.append((m, n // m, ch, mean, var / (2 * mean), 2 * mean ** 2 / var))
        m *= 2
    return MapDesign(n, c, np.asarray(t, float), tuple(channels), noise_dof, windows,
                     score_cells, tau_cells, n >= 16, overlapping, n_extra)


def projected_overlapping_allan_moments(sums: np.ndarray, n: int, m: int) -> tuple[float, float]:
    """Null mean and variance of :func:`overlapping_allan_form` of a unit white residual of
    ``n`` samples with the span of an orthonormal basis ``U`` projected out: ``Q = z'(I - P) A
    (I - P) z``, so ``E Q = tr A - tr U'AU`` and ``var Q = 2 (tr A^2 - 2 |AU|_F^2 +
    |U'AU|_F^2)`` (:func:`projected_overlapping_allan_traces`). ``sums``: the running sums of
    this channel's rows of ``U`` with a leading zero, ``(K, n + 1)``."""
    tr_a, var_a = white_overlapping_allan_moments(n, m)
    tr_uau, au2, uau2 = projected_overlapping_allan_traces([sums], m)
    return tr_a - tr_uau, var_a + 2.0 * (uau2 - 2.0 * au2)


def _member_cells(u, members, c, axis, key):
    """1-dof score cells of each member ``(label, group, w)`` per channel:
    ``(axis, label, channel, J~, cov, dof, {key: group})``."""
    out = []
    for label, group, w in members:
        for ch in range(c):
            jt, cov, dof = _score_cell(u, _channel_columns(w[:, ch:ch + 1], ch, c))
            if dof:
                out.append((axis, str(label), ch, jt, cov, dof, {key: group}))
    return out


def _group_cells(u, members, c, axis, count, *, suffix="", key=None):
    """Joint score cells of the members ``[(label, group, w)]`` that share a group, per
    channel: ``(axis, group + suffix, channel, J~, cov, dof, {count: members[, key: group]})``."""
    out = []
    for group in dict.fromkeys(g for _, g, _ in members):
        ws = [w for _, g, w in members if g == group]
        for ch in range(c):
            jt, cov, dof = _score_cell(u, _channel_columns(
                np.stack([w[:, ch] for w in ws], 1), ch, c))
            if dof:
                out.append((axis, f"{group}{suffix}", ch, jt, cov, dof,
                            {count: len(ws)} | ({key: group} if key else {})))
    return out




def map_statistics(design: MapDesign, e: np.ndarray):
    """Statistics, p-values and (for the largest-line cells) periodogram peaks of the gap map for
    residuals ``e`` (``B x n x c``, or ``B x (n c + n_extra)`` with a second block's entries
    after the rows'): arrays ``(B, cells)`` in :func:`gap_map_cells`' order."""
    bsz, n, c = e.shape[0], design.n, design.c
    flat = e.reshape(bsz, -1)
    e = flat[:, : n * c].reshape(bsz, n, c)
    stat, pv, extra = [], [], []
    cs = np.concatenate([np.zeros((bsz, 1, c)), np.cumsum(e * e, axis=1)], axis=1)
    if design.windows:
        _, _, a, b, ch, e0 = (np.array(x) for x in zip(*design.windows))
        x = cs[:, b, ch] - cs[:, a, ch]  # (B, windows)
        stat += list(x.T)
        pv += list(np.reshape(_f_sf(x / e0, e0, design.noise_dof), x.shape).T)
        extra += [np.zeros(bsz)] * x.shape[1]
    if design.score_cells:
        sc_all = flat @ np.concatenate([x[3] for x in design.score_cells], axis=1)
        i = 0
        lms, dofs = [], []
        for _, _, _, jt, cov, dof, _ in design.score_cells:
            sc = sc_all[:, i:i + jt.shape[1]]
            i += jt.shape[1]
            lms.append(np.sum(sc * (sc @ cov), axis=1))
            dofs.append(dof)
            # one tested direction: the signed Wald z (its square is the statistic)
            extra.append(sc[:, 0] * np.sqrt(cov[0, 0]) if jt.shape[1] == 1 else np.zeros(bsz))
        stat += lms
        dofs = np.array(dofs, float)[:, None]
        pv += list(np.where(dofs > 0, chi2_sf(np.array(lms), np.maximum(dofs, 1)), 1.0))
    forms = {}
    csum = np.concatenate([np.zeros((bsz, 1, c)), np.cumsum(e, axis=1)], axis=1) \
        if design.tau_cells else None
    for m, _, ch, mean, g, h in design.tau_cells:
        if m not in forms:
            forms[m] = overlapping_allan_forms(csum, m) if design.overlapping else \
                allan_form(e, m, csum)
        q = forms[m][:, ch]
        stat.append(q / mean)
        pv.append(np.reshape(_f_sf(q / (g * h), h, design.noise_dof), q.shape))
        extra.append(np.zeros(bsz))
    if design.fisher:
        x = e - e.mean(axis=1, keepdims=True)
        power = np.abs(np.fft.rfft(x, axis=1)[:, 1:(n - 1) // 2 + 1]) ** 2  # (B, q, c)
        g = power.max(axis=1) / power.sum(axis=1)
        kmax = np.argmax(power, axis=1) + 1
        q = power.shape[1]
        for ch in range(c):
            stat.append(g[:, ch])
            pv.append(fisher_g_pvalue(g[:, ch], q))
            extra.append(kmax[:, ch].astype(float))
    return np.array(stat).T, np.array(pv).T, np.array(extra).T




def gap_map_cells(e: np.ndarray, t: np.ndarray, channels: tuple[str, ...], *, n_params: int,
                  noise_dof: float, lines: dict[str, float], jn: np.ndarray,
                  min_window: int = 16, levels: int = 5, design: MapDesign | None = None,
                  segments=None, nuisance=None, aux=None, block=None) -> list[dict]:
    """The Stage-1 map of a whitened residual ``e`` (``n x c``; or flat, ``n c`` rows then a
    second block's entries, whose cells ``block`` names: :func:`map_design`).

    - time x channel: windowed sums of squares over dyadic windows, against
      ``E0 = n_w (1 - p/n)`` with an F reference when the noise level was estimated with
      ``noise_dof`` degrees of freedom (``inf``: known);
    - frequency: 2-dof score tests at the known ``lines`` (name -> period in s) per channel with
      the nominal span projected out, and Fisher's g for the largest unlisted line;
    - position x channel: 1-dof score test of each test position's offset signature (``segments``,
      see :func:`map_design`) with the nominal span projected out (the per-position mean in the
      Wald form that accounts for the fitted parameters); condition x channel: the joint test of
      one condition's positions, where the record has more than one condition;
    - aux x channel: the same for the bins of an auxiliary channel (``aux``), one cell per bin and
      the joint test of its bins;
    - tau band x channel: the fully overlapping Allan variance of the residual at
      ``tau = m tau_0`` (``m = 2, 4, ...`` while at least 9 non-overlapping clusters) over its
      null prediction, with the exact null mean and variance of the quadratic form after the
      projection and a scaled chi-square (Satterthwaite; F when the level was estimated) upper
      tail; ``ci95``: its equivalent-dof confidence interval. (``map_design(...,
      overlapping=False)``: the non-overlapping form, ~half the equivalent dof at the longest
      bands: an ESG angle random walk's smallest-p cell fell at the longest band in 0.84 of the
      detected cases against 0.96 with the overlapping form, 200 cases each.)
    Cells: dicts with axis, cell, channel, statistic, dof, expected, p. ``design``: the
    :func:`map_design` of these arguments (computed here when not given).
    """
    n, c = len(t), len(channels)
    if design is None:
        design = map_design(t, channels, n_params=n_params, noise_dof=noise_dof, lines=lines,
                            jn=jn, min_window=min_window, levels=levels, segments=segments,
                            nuisance=nuisance, aux=aux, block=block)
    stat, pv, extra = (x[0] for x in map_statistics(design, np.reshape(e, (1, -1))))
    cells = []
    i = 0
    for lev, k, a, b, ch, e0 in design.windows:
        cells.append(dict(axis="time", cell=f"{t[a] / 3600:.2f}-{t[b - 1] / 3600:.2f} h",
                          channel=channels[ch], statistic=float(stat[i]), dof=e0, expected=e0,
                          excess=float(stat[i]) - e0, p=float(pv[i]), t0=float(t[a]),
                          t1=float(t[b - 1]), level=lev))
        i += 1
    for axis, label, ch, jt, _, dof, info in design.score_cells:
        cells.append(dict(axis=axis, cell=label, channel=ch if isinstance(ch, str) else
                          channels[ch], statistic=float(stat[i]),
                          dof=dof, expected=dof, excess=float(stat[i]) - dof, p=float(pv[i]),
                          **info, **({"z": float(extra[i])} if jt.shape[1] == 1 else {})))
        i += 1
    tau0 = float(np.median(np.diff(t))) if n > 1 else 0.0
    for m, k, ch, mean, g, h in design.tau_cells:
        cells.append(tau_cell(m * tau0, channels[ch], float(stat[i]), mean, h, float(pv[i]), k))
        i += 1
    if design.fisher:
        q = (n - 1) // 2
        dt = (t[-1] - t[0]) / (n - 1)
        for ch in range(c):
            period = n * dt / extra[i]
            cells.append(dict(axis="frequency", cell=f"largest line ({period / 3600:.3g} h)",
                              channel=channels[ch], statistic=float(stat[i]), dof=q,
                              expected=1.0 / q, excess=0.0, p=float(pv[i]), period_s=period))
            i += 1
    return cells


def _f_sf(ratio, d1, d2):
    """Upper tail of the F(d1, d2) law (chi2(d1)/d1 when ``d2`` is infinite); arrays or floats."""
    if not np.isfinite(d2):
        out = chi2_sf(np.asarray(ratio) * d1, d1)
    else:
        out = special.fdtrc(d1, d2, np.maximum(ratio, 0.0))  # stats.f.sf without its overhead
    return float(out) if np.ndim(out) == 0 else out

