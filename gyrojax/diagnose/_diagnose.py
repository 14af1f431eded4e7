"""The diagnosis pipeline: one linearisation, four answers, one verdict (docs/diagnosis.md).

Stage 0 fits the nominal model on the train split and whitens its residual by the noise level
(given, or estimated from first differences of the residual, which a smooth gap barely touches).
Stage 1 maps the gap (time x channel, known lines, the largest unlisted line, test position and
condition x channel where the rig has positions, Allan tau band x channel; the Ljung-Box lag axis
is reported and never decided on). Stage 2 screens the library by efficient score tests with
posteriors and an ambiguity set. Stage 3 reports confounding (visible fraction, no-signature
directions, aliases by name) and design advice. Stage 4 refits the candidates and measures the
held-out gap before and after; where the top effect's refit leaves a localised gap, forward
selection adds effects one at a time, each by a conditional score test on the refit residual
and, where the held-out part can show it, by a lower held-out gap. Stage 5 gives the verdict.
Multiplicity: weighted Benjamini-Hochberg over every gap-map cell and every library test
together; detection = any q < alpha. The weights are fixed before the data: the library's tests
(the catalogued effects and noise-model terms, the hypotheses the diagnosis is for) hold
``library_share`` of the total weight, the gap map's many and strongly correlated cells the rest
(docs/diagnosis.md "FDR across the whole gap map and library").
With equal weights a 3-dof library test at noncentrality 16 competed with ~100-200 map cells.

Calibrated level: the map's dyadic windows are nested and the library's signatures nearly
collinear, so weighted BH (a weighted Simes test of the global null) is conservative on these
positively dependent tests (on the ESG rig its false-alarm rate is about 0.02 at alpha 0.05,
docs/decisions/0013-gap-map-and-multiplicity.md). Where the
residual's null law is the linearised Gaussian one (white noise per channel, its level given or
estimated from first differences: the ESG, Schuler and gyrotheodolite problems; the IMU's
AR-prewhitened residual; the platform supplies its own draws, centred per dwell with the level
from second differences), ``null_draws`` residuals are drawn from it (projected off the nominal
span, the noise level re-estimated per draw as on the data) and every map cell and library test
is evaluated on each; tests outside the map and the library (the IMU's noise-model rows, a
design-shift split's held-out cell) enter each draw as independent p-values from their own null
law (uniform; a row that is the Bonferroni minimum over k channels as ``min(1, k min U)``). The
BH level is lowered or raised to the ``alpha`` quantile of the draws'
smallest weighted-BH q-value. The global test "some q below that level" is then a Monte Carlo
test of exact size ``alpha`` (``(B + 1) alpha`` an integer) under the linearised null
(docs/diagnosis.md: sup-statistics and the map's multiplicity need a bootstrap). The draws are seeded
by the record's data, so a diagnosis is reproducible.
"""

from __future__ import annotations

import dataclasses
import time
import zlib

import numpy as np

from .. import rigs
from ..io import check_channel_bounds
from ..record import BenchRecord
from ._advice import _design_advice
from ._bayes import PRIORS
from ._gapmap import gap_map_cells, map_design
from ._multiplicity import _bh_weights, _calibrated_level, _outside_pvalues, bh_qvalues, rejected
from ._noise_tests import lag_cells
from ._records import Refit, Verdict
from ._report import GapReport
from ._rows import _onestep_display, candidate_record
from ._screening import ambiguity_set, screen, screen_designs
from ._signatures import (
    canonical_correlations,
    indistinguishable_classes,
)
from ._verdict import (
    _CONFOUNDED_FLAGS,
    _heldout_cell,
    _null_band,
    _refit_uncertainty,
    _shift_hidden,
    _verdict,
    _with_noise,
    earns_place,
)

__all__ = ["diagnose", "default_prior", "library"]

LABEL_CHANNELS = ("position", "amplitude")  # segment labels, not measurements


def library(rig: str, **options) -> dict:
    """The diagnosis catalogue of ``rig`` under its ``options`` (platform: ``nominal_terms``):
    effect name -> family (the registry's :meth:`~gyrojax.rigs.RigEntry.catalogue`)."""
    return rigs.get(rig).catalogue(**given_options(options))


def given_options(options: dict) -> dict:
    """The rig options given: ``None`` means the rig's default."""
    return {k: v for k, v in options.items() if v is not None}


def _check_record(record: BenchRecord, holdout: float):
    y = np.asarray(record.y)
    t = np.asarray(record.t)
    if not 0 <= holdout < 0.9:
        raise ValueError(f"holdout={holdout}; give a fraction in [0, 0.9) of the record to hold out")
    bad = ~np.isfinite(y)
    if bad.any():
        ch, idx = np.argwhere(bad)[0][1], np.argwhere(bad)[0][0]
        raise ValueError(f"channel {record.channels[ch]!r} has {int(bad[:, ch].sum())} NaN/inf "
                         f"samples (first at t = {t[idx]:g} s); mask or interpolate them first")
    for ch, name in enumerate(record.channels):
        if name not in LABEL_CHANNELS and np.ptp(y[:, ch]) == 0:
            raise ValueError(f"channel {name!r} is constant ({y[0, ch]:g}); a stuck channel "
                             "cannot be diagnosed: check the recording")
    n_train = len(t) - int(round(holdout * len(t)))
    if n_train < 60:
        raise ValueError(f"record too short to fit: {n_train} train samples (of {len(t)}); "
                         "need at least 60 - record longer or lower --holdout")


def _conditional_scores(e, span, rows, chosen):
    """The conditional score tests of the effects not in ``chosen`` (with a signature): each
    rescored on the residual ``e`` of the refit with ``chosen``, the span of the nominal and
    chosen Jacobians (``span``) projected out. A list of screening rows, empty if none is left."""
    names = {r.sig.name for r in chosen}
    others = [r.sig for r in rows if r.sig.name not in names and r.dof > 0]
    return screen(e, span, others) if others else []


def _next_effect(resc, alpha, n_tests=None):
    """Of the conditional score tests ``resc`` (:func:`_conditional_scores`), the best, where it
    is significant after Bonferroni over ``n_tests`` tests (default: ``len(resc)``; more where
    effects refused earlier were tested in the same step) and has a signature left, else
    ``None``."""
    if not resc:
        return None
    best = max(resc, key=lambda r: r.lm)
    p_bonf = min(1.0, best.p * max(n_tests or 0, len(resc)))
    return best if p_bonf < alpha and best.flag not in ("no signature",
                                                        "structurally confounded") else None


def _conditional_record(resc, chain, stop, alpha, vetoed=()) -> dict:
    """The report's ``conditional`` entry: after the forward selection's last refit
    (``chain[-1]``), why it stopped (``stop``), the effects the held-out part refused after
    that refit (``vetoed``: ``{effect, heldout_gap_before, heldout_gap_after, band}`` each, in
    the order tried) and each remaining effect's conditional score test (statistic, dof, p,
    Bonferroni p over them), largest statistic first."""
    n = max(len(resc), 1)
    return {"after": list(chain[-1]["effects"]), "stopped": stop, "alpha": alpha,
            "vetoed": list(vetoed),
            "scores": [{"effect": r.sig.name, "score": float(r.lm), "dof": int(r.dof),
                        "p": float(r.p), "p_bonferroni": float(min(1.0, r.p * n)),
                        "visibility": r.flag}
                       for r in sorted(resc, key=lambda r: -r.lm)]}


class _StageTimes(dict):
    """Seconds per stage (``"<stage>_s"``), each passed to ``progress(stage, seconds)`` as it is
    recorded."""

    def __init__(self, progress=None):
        super().__init__()
        self._progress = progress

    def __setitem__(self, key, seconds):
        super().__setitem__(key, seconds)
        if self._progress is not None:
            self._progress(key.removesuffix("_s"), seconds)


def default_prior(rig: str = "esg", **options) -> str:
    """The Bayes-factor prior :func:`diagnose` uses when none is given: ``"shell"`` for a
    catalogue of single coefficients -- "which term of the error model" (the platform with a
    chosen ``nominal_terms``: each coefficient it leaves out is an effect; the IMU
    ``per_coefficient``) -- where the shell's factor is exact for most effects; ``"design"`` for
    a catalogue of effect families (every rig's default catalogue). The blind suites that chose
    this rule: ``benchmarks/RESULTS.md`` (the shell and design sections of each suite)."""
    entry = rigs.get(rig)
    options = given_options(options)
    entry.check_options(options)
    return "shell" if entry.problem_class.single_coefficients(**options) else "design"


def checked_effects(effects) -> tuple | None:
    """``effects`` as a tuple of names, each named once (``None`` stays ``None``: the whole
    catalogue). **Raises:** `ValueError` naming an effect given twice."""
    if effects is None:
        return None
    effects = tuple(effects)
    twice = sorted({e for e in effects if effects.count(e) > 1})
    if twice:
        raise ValueError(f"effects: {', '.join(twice)} named more than once; name each effect "
                         "once")
    return effects


def diagnose(record: BenchRecord, *, rig="esg", conditions=None, effects=None,
             holdout: float = 0.25, alpha: float = 0.05, noise_std=None,
             design_advice: bool = True, max_refits: int = 3, max_effects: int = 3,
             prior: str | None = None,
             library_share: float = 0.5, refit_all: bool = False, null_draws: int = 499,
             progress=None, **options) -> GapReport:
    """Diagnose the gap between the rig's nominal model and ``record``.

    **Arguments:**
    - `record`: a BenchRecord with the rig's channels and conditions (ESG: ``scheme``,
      ``latitude_deg``).
    - `rig`: a registered rig (:mod:`gyrojax.rigs`), by name (``"esg"``) or by its model object
      (``ESGRig()``, as :func:`gyrojax.fit` takes it): its diagnosis problem
      (:class:`~gyrojax.diagnose.AbstractGapProblem`) reads the record.
    - `options`: the rig's own options, passed to its problem's constructor (``None``: the
      default; an option another rig takes is an error naming the ones this rig takes):
      ``order``, ``noise_model``, ``flicker_b`` (ESG), ``split``, ``nominal_terms`` (platform),
      ``per_coefficient`` (IMU), as below.
    - `conditions`: test conditions added to (or overriding) the record's, e.g.
      ``{"scheme": "polar", "latitude_deg": 55.75}``.
    - `effects`: the library to screen (default: the rig's whole catalogue).
    - `holdout`: fraction of the record (its end) held out for the before/after gap.
    - `alpha`: significance level after multiplicity control.
    - `noise_std`: measurement noise per channel (SI); default estimated from the residual.
    - `design_advice`: compute the design advisor for confounded, weak or ambiguous effects.
    - `order`: ESG model, ``"exact"`` (5.1) or the paper's first-order ``"first"`` (3.1).
    - `max_refits`: the most members of the ambiguity set refitted one by one, and the most
      refits in a row the held-out part may refuse in the forward selection (below).
    - `max_effects`: the most catalogued effects one verdict names together. Where the top
      effect's refit leaves significant cells, the rest of the library is rescored on its
      residual (a conditional score test, Bonferroni over the rest); the best joins the refit
      where it is significant and, where the held-out part can show it, lowers the held-out
      gap; and so on up to `max_effects`. An effect the held-out part refuses is set aside and
      the rest rescored with its signature as a nuisance; the best of them is tried next
      (``GapReport.conditional``: the refused ones and why the selection stopped). The
      verdict is ``attributed`` to the first such set
      that leaves no significant cell, ``partial`` where the set explains at least 90 % of the
      gap with cells left (``Verdict.explained``: each effect's share, ``remainder``: where the
      rest lies), else ``unexplained``.
    - `prior`: Bayes-factor prior of the posteriors: ``"design"`` (the equal mixture of the next
      two), ``"shape"`` (coefficients spread as their prior scales, sized to expect
      noncentrality 32 on this record's design), ``"zellner"`` (g-prior expecting 32),
      ``"scale"`` (the prior scales themselves) or ``"shell"`` (the noncentrality log-uniform
      over 8 to 2^24, never near 0: an effect of one coefficient gets the exact noncentral
      chi-square factor, any other the design prior over the same sizes). ``None`` (default):
      :func:`default_prior`, the shell for a catalogue of single coefficients (`nominal_terms`,
      `per_coefficient`) and the design prior for a catalogue of effect families. The report
      says which (``GapReport.prior``).
    - `library_share`: share of the weighted-BH weight held by the library's tests (the gap map
      holds the rest; ``None``: equal weights, plain BH over every test).
    - `split`: the held-out plan where a rig offers more than one (platform:
      ``"same-design"``, the default, or ``"design-shift"``: the last vibration amplitude's run
      held out whole); ``None``: the rig's default.
    - `refit_all`: also refit every other visible catalogued effect alone (at its best-scoring
      grid value), so that every candidate carries its held-out gap after and reduction; they
      join ``refits`` with ``"screened": False`` and do not change the verdict.
    - `null_draws`: residuals drawn from the linearised null to calibrate the BH level to a
      global false-alarm rate of exactly ``alpha`` (module docstring); 0 keeps the plain
      weighted-BH level ``alpha``. Tests outside the map and the library (the IMU's
      noise-model rows, the platform's design-shift held-out cell) enter the draws as
      independent p-values. ``(null_draws + 1) * alpha`` should be an integer.
    - `noise_model`: the ESG's nominal noise model of the gimbal angles: ``"white"`` (the
      default) or ``"white+flicker"``: flicker as a GM sum (:mod:`gyrojax.analysis.flicker`) at
      the level `flicker_b` or, without it, one estimated per channel by REML on the
      full-model residual; the rows (tests, refits, held-out gap) are whitened by its Kalman
      innovations. A REML level from the record itself costs the slow effects much of their
      power (flicker and they share the record's lowest frequencies); a level known from the
      instrument's Allan deviation test costs only what the flicker really hides. Other rigs
      have one noise model each (leave it ``None``).
    - `flicker_b`: the flicker's bias-instability coefficient B (rad; one, or per channel;
      Allan deviation floor 0.664 B); implies ``noise_model="white+flicker"``.
    - `nominal_terms`: platform only: the drift-law terms the nominal model carries for every
      gyro (default all but ``oo``, the source's model; e.g. ``("f", "i", "o", "s")``, the
      first-order model). Every coefficient left out is then screened as an effect of its own
      (``D_ii_y``), beside the catalogue's non-drift-law effects.
    - `per_coefficient`: IMU only: screen every coefficient of a many-coefficient catalogue
      effect as an effect of its own (``g_sensitivity:gsxy``, ``warmup_transient:wgx`` with its
      decay-time grid, ...): "which term of the error model", K = 40 on a six-channel record
      instead of "which family", K = 6. `effects` may then name single coefficients too.
    - `progress`: called as ``progress(stage, seconds)`` as each stage ends (``"nominal_fit"``,
      ``"jacobians"``, ``"library_scores"``, ``"calibration"``, ``"screening"``, ``"refit"``,
      ``"refit_all"``, ``"design_advice"``, ``"total"``), e.g. to show a long first call's
      compilation (the CLI prints them); the same seconds are in ``GapReport.timings``.

    **Returns:** a :class:`GapReport` (``.to_json()``, ``.markdown()``).
    """
    if max_effects < 1:
        raise ValueError(f"max_effects={max_effects}; give at least 1 (the most effects one "
                         "verdict names together)")
    if null_draws < 0 or (null_draws and np.floor(alpha * (null_draws + 1) + 1e-9) < 1):
        raise ValueError(f"null_draws={null_draws} with alpha={alpha}: give 0 (plain weighted "
                         f"BH) or at least {int(np.ceil(1 / alpha)) - 1} draws (default 499)")
    options = given_options(options)
    rig = rigs.get(rig).name  # a model object (ESGRig()) names its registered rig
    effects = checked_effects(effects)
    if prior is None:
        prior = default_prior(rig, **options)
    if prior not in PRIORS:
        raise ValueError(f"prior={prior!r}; use one of {', '.join(map(repr, PRIORS))} "
                         "(or None: the catalogue's default, gyrojax.diagnose.default_prior)")
    timings = _StageTimes(progress)
    t_start = time.perf_counter()
    if conditions:
        record = record.with_conditions(**dict(conditions))
    check_channel_bounds(record, rigs.get(rig).model_class.CHANNEL_BOUNDS)
    _check_record(record, holdout)
    prob = rigs.get(rig).problem_for(record, holdout=holdout, noise_std=noise_std,
                                     effects=effects, **options)
    n, c = prob.n_train, len(prob.channels)
    params0 = prob.fit_nominal()
    pred0 = prob.predict(params0)
    resid_all = prob.y - pred0
    sigma, noise_dof, noise_src = prob.noise_level(resid_all[:n])

    def standardize(resid):
        return prob.standardize(resid, sigma)

    ho_dof = prob.heldout_dof
    # the whitened residual as one vector: the rows (n c train, then held-out) and, where the
    # problem has a second block (the IMU's turns), its entries; reordered train first
    order = train_first(prob, params0)
    m_tr = n * c + prob.block_train  # train entries

    def whitened(pred, params):
        """The whitened residual of ``params`` (rows ``pred``), train entries first."""
        blk = prob.block_residual(params)
        e_rows = standardize(prob.y - pred).reshape(-1)
        return (e_rows if blk is None else np.concatenate([e_rows, blk]))[order]

    def heldout_gap(ea):
        """Held-out G, corrected for terms fitted on the held-out rows (IMU poses)."""
        m = ea[m_tr:].size
        return float(np.sum(ea[m_tr:] ** 2) / max(m - ho_dof, 1) - 1)
    timings["nominal_fit_s"] = time.perf_counter() - t_start

    t0 = time.perf_counter()
    jn_all, sigs_all = prob.jacobians(params0, sigma)
    jn_all = jn_all[order]
    sigs_all = [dataclasses.replace(s, jac=s.jac[:, order, :]) for s in sigs_all]
    rows_tr = slice(0, m_tr)
    jn = jn_all[rows_tr]
    sigs = [train_slice(s, m_tr) for s in sigs_all]
    s_full = {s.name: s for s in sigs_all}
    e_all = whitened(pred0, params0)
    e = e_all[rows_tr]
    timings["jacobians_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    designs = screen_designs(jn, sigs)
    rows = screen(e, jn, sigs, prior=prior, designs=designs)
    timings["library_scores_s"] = time.perf_counter() - t0  # the score tests alone (G10)
    nuisance = prob.nuisance_dof  # train dof of terms outside the Jacobian
    # the test positions' offset signatures and the columns fitted outside the Jacobian
    map_kw = dict(noise_dof=noise_dof, lines=prob.lines,
                  segments=prob.position_signatures(sigma),
                  nuisance=prob.nuisance_columns(sigma), aux=prob.aux_signatures(sigma),
                  block=prob.block_cells())
    mdesign = map_design(prob.t[:n], prob.channels, n_params=jn.shape[1] + nuisance, jn=jn,
                         **map_kw)
    cells = gap_map_cells(e, prob.t[:n], prob.channels,
                          n_params=jn.shape[1] + nuisance, jn=jn, design=mdesign, **map_kw)
    noise_rows = prob.noise_screen(params0)
    n_ho = len(e_all) - m_tr
    extra = prob.heldout_extra
    band = _null_band(jn_all, m_tr, n_ho, extra, noise_dof * c)
    g_nom = heldout_gap(e_all) if n_ho else float("nan")
    if n_ho and prob.design_shift:
        cells.append(_heldout_cell(g_nom, band, n_ho - ho_dof, noise_dof * c, prob.split_kind))
    p_all = np.array([x["p"] for x in cells] + [r.p for r in rows] + [x["p"] for x in noise_rows])
    weights = _bh_weights(len(cells), len(rows) + len(noise_rows), library_share)
    q_all = bh_qvalues(p_all, weights)
    multiplicity = {"method": "weighted BH", "level": alpha, "null_draws": 0}
    draw = prob.null_sampler(designs[0], n, c, bool(np.isfinite(noise_dof)))
    if null_draws and draw is not None:
        t_cal = time.perf_counter()
        outside = _outside_pvalues(cells, noise_rows, mdesign.n_cells)
        level, null_minq = _calibrated_level(designs, mdesign, weights, alpha, null_draws, draw,
                                             seed=zlib.crc32(np.ascontiguousarray(prob.y)),
                                             outside=outside)
        multiplicity = {"method": "weighted BH, level calibrated by Monte Carlo under the "
                                  "linearised null", "level": level, "null_draws": null_draws,
                        "global_p": float((1 + np.sum(null_minq <= q_all.min()))
                                          / (1 + null_draws)) if q_all.size else 1.0}
        timings["calibration_s"] = time.perf_counter() - t_cal
    level = multiplicity["level"]
    for x, q in zip(cells, q_all[: len(cells)]):
        x["q"] = float(q)
        x["significant"] = rejected(x["p"], q, level)
    for r, q in zip(rows, q_all[len(cells): len(cells) + len(rows)]):
        r.q = float(q)
    for x, q in zip(noise_rows, q_all[len(cells) + len(rows):]):
        x["q"] = float(q)
        x["significant"] = rejected(x["p"], q, level)
    q_mean = q_all[: len(cells) + len(rows)]
    cells += lag_cells(e[: n * c].reshape(n, c), prob.channels,  # reported, not decided on
                       aux=prob.aux_rows)
    cells += prob.full_rate_tau_cells(params0)  # reported, not decided on
    # excess energy of the whole-record windows (level 0), all channels
    excess = sum(max(0.0, x["excess"]) for x in cells if x["axis"] == "time" and x["level"] == 0)
    detected = bool(np.any(q_mean < level))
    amb = ambiguity_set(rows) if detected else []
    # the score tests and the map; the level's null calibration is timed apart
    timings["screening_s"] = time.perf_counter() - t0 - timings.get("calibration_s", 0.0)

    # confounding + pairwise canonical correlations of projected signatures
    pairs, contained = {}, {}  # largest and smallest canonical correlation of each pair
    for i, a in enumerate(rows):
        for b in rows[i + 1:]:
            cc = canonical_correlations(a.projected, b.projected)
            pairs[(a.sig.name, b.sig.name)] = float(cc[0])
            contained[(a.sig.name, b.sig.name)] = float(cc[-1])

    top = max(rows, key=lambda r: r.posterior) if rows else None

    # held-out gap and refits
    t0 = time.perf_counter()
    g_nom_train = float(np.mean(e ** 2) - 1)

    def run_refit(combo):
        pred, coeffs, p_refit = prob.refit(params0, [(r.sig, r.grid_index) for r in combo],
                                           sigma)
        ea = whitened(pred, p_refit)
        g_aug = heldout_gap(ea) if n_ho else float("nan")
        span = np.concatenate([jn] + [r.sig.jac[r.grid_index] for r in combo], axis=1)
        span_all = np.concatenate([jn_all] + [s_full[r.sig.name].jac[r.grid_index]
                                              for r in combo], axis=1)
        band_aug = _null_band(span_all, m_tr, n_ho, extra, noise_dof * c)
        post_cells = gap_map_cells(ea[:m_tr], prob.t[:n], prob.channels,
                                   n_params=jn.shape[1] + nuisance + sum(r.dof for r in combo),
                                   jn=span, **map_kw)
        qq = bh_qvalues(np.array([x["p"] for x in post_cells]))
        remaining = [dict(x, q=float(q)) for x, q in zip(post_cells, qq) if q < alpha]
        resid_after[tuple(r.sig.name for r in combo)] = standardize(prob.y - pred)
        std_errors, estimable = _refit_uncertainty(combo, coeffs)
        refit = Refit(effects=[r.sig.name for r in combo], coefficients=coeffs,
                      std_errors=std_errors, estimable=estimable,
                      units={nm: u for r in combo for nm, u in zip(r.sig.names, r.sig.units)},
                      nominal_after=prob.display_nominal(p_refit),
                      onestep={r.sig.name: _onestep_display(r) for r in combo},
                      gap_train_after=float(np.mean(ea[:m_tr] ** 2) - 1),
                      heldout_gap_before=g_nom, heldout_gap_after=g_aug,
                      reduction=(1 - g_aug / g_nom) if n_ho and g_nom > band[1] else None,
                      heldout_null_band_after=list(band_aug),
                      closure=bool(g_aug <= band_aug[1]) if n_ho else None,
                      remaining_cells=remaining,
                      reading=prob.refit_reading(tuple(r.sig.name for r in combo)))
        return refit, ea[:m_tr], span

    refits = []
    resid_after = {}
    second = None
    conditional = None  # the forward selection's stop and last conditional score tests
    chain = []  # the nested refits of the effects that earned their place, top effect first
    if detected:
        singles = {}
        for r in amb[:max_refits]:
            if r.dof > 0:
                singles[r.sig.name] = run_refit([r])
                refits.append(singles[r.sig.name][0])
        # forward selection: while the refit leaves a localised gap, the rest of the library
        # is rescored on its residual with the chosen effects' signatures in the span (a
        # conditional score test); the best joins where it is significant and, where the
        # held-out part can show it, lowers the held-out gap (_verdict.earns_place)
        # (after an ambiguous top, its alternatives -- the ambiguity set's other members --
        # are not candidates: they explain the same part of the gap; what joins explains more)
        if top is not None and top.sig.name in singles:
            head = chain_head(amb, {k: v[0] for k, v in singles.items()}, top)
            combo = [head]
            alternatives = [r for r in amb if r is not head] if len(amb) > 1 else []
            refit, e_post, span = singles[head.sig.name]
            chain = [refit]
            resc = None  # the conditional score tests on the chain's last refit
            refused = []  # (row, refit) the held-out part refused after that refit, in order
            while True:
                if not refit.remaining_cells:
                    stop = "no significant gap-map cell left"
                    break
                if len(combo) >= max_effects:
                    stop = f"max_effects={max_effects} effects named"
                    break
                if resc is None:
                    resc = cand = _conditional_scores(e_post, span, rows, combo + alternatives)
                found = _next_effect(cand, alpha, n_tests=len(resc))
                if found is None:
                    stop = ("no other effect significant in its conditional score test with "
                            "those as nuisance" if refused else
                            "no further effect significant in its conditional score test")
                    break
                if len(refused) == max_refits:
                    stop = f"max_refits={max_refits} refits refused in a row"
                    break
                second = second or found
                partner = next(r for r in rows if r.sig.name == found.sig.name)
                nxt = run_refit(combo + [partner])
                refits.append(nxt[0])
                if not earns_place(refit, nxt[0]):
                    # a signature the record carries that does not transfer must not block
                    # the others, nor lend them its train part: the rest are rescored with
                    # the refused signatures as a nuisance (decision 0032)
                    refused.append((partner, nxt[0]))
                    given = [r for r, _ in refused]
                    cand = _conditional_scores(
                        e_post, np.concatenate([span] + [r.sig.jac[r.grid_index] for r in given],
                                               axis=1), rows, combo + alternatives + given)
                    continue
                combo.append(partner)
                chain.append(nxt[0])
                refit, e_post, span = nxt
                resc, refused = None, []
            if resc is None:
                resc = _conditional_scores(e_post, span, rows, combo + alternatives)
            vetoed = [{"effect": r.sig.name, "heldout_gap_before": refit.heldout_gap_after,
                       "heldout_gap_after": rf.heldout_gap_after,
                       "band": float(rf.heldout_null_band_after[1])} for r, rf in refused]
            if vetoed:
                stop = f"{vetoed_text(vetoed)}; {stop}"
            conditional = _conditional_record(resc, chain, stop, alpha, vetoed)
    timings["refit_s"] = time.perf_counter() - t0

    verdict = _verdict(detected, rows, amb, refits, chain, top, level, cells, g_nom, band,
                       _shift_hidden(rows, cells, jn_all, s_full), g_train=g_nom_train)
    verdict = _with_noise(verdict, noise_rows, alpha, refits)
    if refit_all:
        t0 = time.perf_counter()
        done = {tuple(rf.effects) for rf in refits}
        for r in rows:
            if (r.sig.name,) not in done and r.dof > 0 and r.flag not in _CONFOUNDED_FLAGS:
                refits.append(dataclasses.replace(run_refit([r])[0], screened=False))
        timings["refit_all_s"] = time.perf_counter() - t0
    prob.notes += prob.verdict_notes(verdict)  # e.g. the ESG's hint at its noise model
    if prob.notes:
        verdict["notes"] = list(prob.notes)

    advice = []
    if design_advice:
        t0 = time.perf_counter()
        flagged = [r for r in rows if r.flag != "visible"]
        if verdict["kind"] == "ambiguous":
            flagged += [r for r in amb if r not in flagged]
        if flagged:
            advice = _design_advice(prob, params0, sigma, flagged)
        timings["design_advice_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    return GapReport(
        rig=rig, channels=prob.channels, n_train=n, n_heldout=len(prob.t) - n,
        nominal=prob.display_nominal(params0), nominal_units=dict(zip(prob.nominal_names,
                                                                       prob.nominal_units)),
        noise={"std": [float(s) for s in sigma], "source": noise_src, "dof": float(noise_dof),
               "shown": [prob.noise_text(ch, float(s)) for ch, s in zip(prob.channels, sigma)],
               **prob.noise_fit},
        gap={"train": g_nom_train, "heldout": g_nom, "heldout_null_band": list(band),
             "rms_train": [float(x) for x in np.sqrt(np.mean(resid_all[:n] ** 2, axis=0))],
             "rms_heldout": [float(x) for x in np.sqrt(np.mean(resid_all[n:] ** 2, axis=0))]
             if n_ho else None},
        where=cells, ranking=[candidate_record(r, prob, excess, n, c, cells) for r in
                              sorted(rows, key=lambda r: -r.posterior)],
        ambiguity={"set": [r.sig.name for r in amb],
                   "pairs": {f"{a} ~ {b}": v for (a, b), v in pairs.items()},
                   "classes": indistinguishable_classes(
                       contained, [r.sig.name for r in sorted(rows, key=lambda r: -r.posterior)
                               if r.dof > 0])},
        second=second.sig.name if second is not None else None, conditional=conditional,
        refits=refits, design_advice=advice, verdict=Verdict(**verdict), alpha=alpha,
        timings=timings,
        multiplicity=multiplicity, prior=prior,
        noise_effects=noise_rows,
        split=prob.split_kind,
        residual_all=resid_all / sigma, t=prob.t,
        residual_after=resid_after.get(tuple(verdict.get("effects") or ())))


def vetoed_text(vetoed) -> str:
    """The forward selection's refused effects (:func:`_conditional_record`'s ``vetoed``) in
    words: each passed its conditional score test but not the held-out part."""
    return "; ".join(f"{v['effect']} passed its conditional score test but not the held-out "
                     f"part (held-out gap {v['heldout_gap_before']:.3g} -> "
                     f"{v['heldout_gap_after']:.3g}, null band <= {v['band']:.3g})"
                     for v in vetoed)


def chain_head(amb, singles, top):
    """The effect the forward selection starts from: the posterior's ``top`` effect; where the
    ambiguity set ``amb`` holds several members and the record has a held-out part, the member
    whose refit (``singles``: effect name -> :class:`Refit`) leaves the lowest held-out gap. The
    members explain the same part of the train gap equally well; the one whose refit predicts
    the held-out part is the one whose residual the next effects are tested on (a member whose
    refit spoils the prediction would weigh every later effect against its own error)."""
    refitted = [r for r in amb if r.sig.name in singles]
    if len(refitted) < 2 or singles[top.sig.name].heldout_gap_after is None \
            or not np.isfinite(singles[top.sig.name].heldout_gap_after):
        return top
    return min(refitted, key=lambda r: (singles[r.sig.name].heldout_gap_after, r is not top))


def train_slice(sig, m):
    return dataclasses.replace(sig, jac=sig.jac[:, :m, :])


def train_first(prob, params) -> np.ndarray:
    """The order of a problem's whitened entries (its Jacobians' rows: the rows' ``N c``, then
    a second block's) that puts the train entries first: the train rows (``n_train c``), the
    block's train entries (``block_train``), the held-out rows, the block's held-out entries.
    Its first ``n_train c + block_train`` entries are the train part."""
    c = len(prob.channels)
    rows = np.arange(len(prob.t) * c)
    block = prob.block_residual(params)
    blk = len(rows) + np.arange(0 if block is None else len(block))
    n = prob.n_train * c
    return np.concatenate([rows[:n], blk[: prob.block_train], rows[n:],
                           blk[prob.block_train:]])


