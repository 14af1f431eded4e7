"""Generic scoring of blind validation suites (docs/diagnosis.md): sealing a suite's
truths (:class:`Sealer`), the truth side of each case (visible fractions, Cramér-Rao references,
remainders after the library), the B2 refit-all baseline, and the suite's metrics with Monte Carlo
standard errors (rates, calibration, the Bayes oracle's choices and power, localisation,
confounding, out-of-library honesty). Every rig's suite (:mod:`gyrojax.validation.esg`,
``.imu``, ``.platform``, ``.schuler``, ``.gyrotheodolite``) scores through these."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from pathlib import Path

import numpy as np
import scipy.linalg

from ..diagnose import (
    SHELL_DESIGN_LAMBDAS,
    mix_log_bf,
    nominal_basis,
    project_out,
    shape_log_bf_scores,
    shell_design_log_bf,
    shell_log_bf,
    signature_directions,
    visibility_flag,
    zellner_log_bf,
)
from ..io import save_record, write_json

__all__ = ["CONFOUNDED_FLAGS", "Sealer", "calibration", "confounding_scores", "confident",
           "crb_rate", "crb_spread", "grid_best", "grid_localisation", "grid_locations",
           "heldout_reduction", "localisation_fields",
           "multiplicity_fields", "onset_crb", "ool_scores", "oracle_choice",
           "oracle_detect_statistic", "oracle_power", "orthonormal_basis", "plain_bh_far",
           "projector", "ranking_scores", "rate", "ratio_rate", "refit_all_baseline",
           "remainder_after_library", "sha256_file", "tau_band_scores", "top3_effects",
           "top_effect", "truth_visibility"]


# the flags of docs/diagnosis.md stage 3 that say the nominal fit absorbs (part of) an effect: visible
# fraction < 0.05 in some direction (practically or structurally confounded, or no signature)
CONFOUNDED_FLAGS = ("practically confounded", "structurally confounded",
                    "partly structurally confounded", "no signature")


def truth_visibility(jb, jt) -> dict:
    """Truth side of docs/goals.md's confounding recall and precision: the hidden effect's visible
    fraction on the train rows (the smallest ``1 - rho^2`` over its coefficient directions,
    docs/diagnosis.md stage 3) from the whitened Jacobian ``jb`` of its coefficients at the generating
    parameters and sealed grid value, and ``jt``, the same with the nominal span projected out;
    and the flag that fraction earns. The diagnosis computes its own at its fitted nominal and
    chosen grid value, from the record."""
    jb, jt = np.asarray(jb, float), np.asarray(jt, float)
    _, _, v, null, conf = signature_directions(jb, jt)
    return {"visible_fraction": float(v),
            "visibility": visibility_flag(v, bool(null), jb.shape[1] - len(null), len(conf))}


def projector(jn):
    """``a -> (I - P) a`` with ``P`` the orthogonal projector on the columns of ``jn``: the
    generators' truth-side noncentrality has the nominal parameters projected out."""
    q, _ = np.linalg.qr(jn)
    return lambda a: a - q @ (q.T @ a)


def sha256_file(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class Sealer:
    """Writes the case records ``case_<index>.nc`` and, on :meth:`close`, the sealed manifest
    keyed by each file's SHA-256 (so the truth travels with the exact bytes diagnosed)."""

    def __init__(self, out_dir, seed: int):
        self.out = Path(out_dir)
        (self.out / "sealed").mkdir(parents=True, exist_ok=True)
        self.manifest, self.paths = {}, []
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def draw(self, i: int, families, lambdas, null_fraction: float):
        """Case ``i``'s family (a null with probability ``null_fraction``, else the families in
        turn) and its noncentrality."""
        family = "null" if self.rng.uniform() < null_fraction else families[i % len(families)]
        return family, float(self.rng.choice(lambdas))

    def add(self, rec, truth: dict):
        path = self.out / f"case_{len(self.paths):04d}.nc"
        save_record(rec, path)
        self.manifest[sha256_file(path)] = truth | {"file": path.name}
        self.paths.append(path)

    def close(self, design) -> list[Path]:
        write_json({"design": dataclasses.asdict(design), "seed": self.seed,
                    "cases": self.manifest},
                   self.out / "sealed" / "manifest.json")
        return self.paths


def refit_all_baseline(prob, ranking, sigma, prior: str = "design") -> dict:
    """Baseline B2 (docs/goals.md) on one record: refit every catalogued effect alone (a grid effect at every
    grid value, keeping the best: refit-all has no score to pick a decay time or onset, and the
    grid value counts as one more parameter) from the same nominal fit as the diagnosis, on its
    whitened train rows. Returns the BIC choice (``b2_choice``, ``"none"`` when the nominal wins),
    the choice by the screening's own Bayes factor with each refit's estimate in place of the
    one-step one (``b2_lr_choice``: the answer screening approximates, goal G10), their log
    Bayes factors, the refits' wall time and count. ``ranking``: the report's rows (the dof each
    effect was screened on); ``sigma``: the report's noise level; ``prior``: the screening's
    (``"design"`` or ``"shell"``, :func:`~gyrojax.diagnose._screening.screen`)."""
    if prior not in ("design", "shell"):
        raise ValueError(f"prior={prior!r}: B2's Bayes factors follow 'design' or 'shell'")
    params0 = prob.fit_nominal()
    n = prob.n_train

    def standardize(resid):
        return prob.standardize(resid, sigma)

    def chi2(pred):  # on the diagnosis' whitened rows
        return float(np.sum(standardize(prob.y[:n] - pred[:n]) ** 2))

    rss0 = chi2(prob.predict(params0))
    m = n * len(prob.channels)
    jn, sigs = prob.jacobians(params0, sigma)
    rows = slice(0, m)  # the train rows the refits fit
    u = nominal_basis(jn[rows])
    screened_dof = {r["name"]: int(r["dof"]) for r in ranking}
    t0 = time.perf_counter()  # both answers start from the same nominal fit
    n_refits = 0
    bic = {"none": m * math.log(rss0 / m)}
    lr_bf = {}
    for sig in sigs:
        rss, blocks = [], []
        for g in range(max(len(sig.grid), 1)):
            pred, coeffs, _ = prob.refit(params0, [(sig, g)], sigma)
            n_refits += 1
            rss.append(chi2(pred))
            # the screening's Bayes factor with the refit in place of the one-step estimate
            # (shape part: score = I b^; g-prior part: the likelihood-ratio drop for the score
            # statistic, on the dof the screening tested)
            jt = project_out(u, sig.jac[g][rows])
            b_hat = np.array([coeffs[nm] for nm in sig.names]) / sig.prior_scale
            blocks.append((jt.T @ jt, jt.T @ jt @ b_hat))
        k = len(sig.names) + (1 if sig.grid else 0)
        bic[sig.name] = m * math.log(min(rss) / m) + k * math.log(m)
        drops = [max(rss0 - r, 0.0) for r in rss]
        dof = screened_dof[sig.name]
        if prior == "shell" and len(sig.names) == 1:  # one coefficient: the exact shell factor
            v = shell_log_bf(drops) if dof > 0 else np.zeros(len(drops))
            lr_bf[sig.name] = float(np.logaddexp.reduce(v) - math.log(len(v)))
            continue
        lams = SHELL_DESIGN_LAMBDAS if prior == "shell" else np.array([32.0])
        shape = shape_log_bf_scores(blocks, lams)
        zell = zellner_log_bf(drops, [dof] * len(rss), lams)
        lr_bf[sig.name] = float(shell_design_log_bf(shape, zell) if prior == "shell"
                                else mix_log_bf(shape, zell)[0])
    return {"b2_choice": min(bic, key=bic.get),
            "b2_lr_choice": max(lr_bf, key=lr_bf.get) if lr_bf else None,
            "b2_lr_log_bf": lr_bf, "time_refit_all_s": time.perf_counter() - t0,
            "n_refits": n_refits}


def grid_best(rep) -> dict:
    """Each grid effect's grid value at its largest score (onset, decay time) in a report."""
    return {r["name"]: r["grid"]["best"] for r in rep.ranking if r.get("grid")}


def grid_locations(rep) -> dict:
    """Each grid effect's located value in a report: the centre of the one-step window of most
    posterior mass (:func:`gyrojax.diagnose._report.grid_located`)."""
    return {r["name"]: r["grid"]["located"] for r in rep.ranking if r.get("grid")}


def grid_localisation(strong, *, step, transient, decay_grid, record_length,
                      truth_scale: float = 1.0, crb_key: str | None = None,
                      decay_crb_key: str | None = None) -> dict:
    """Goal G8's onset and decay-time rules over (truth, result) pairs with ``grid_best``:
    ``step`` and ``transient`` are ``(family, truth key)``; an onset counts within 5 % of the
    record (``record_length(result)``, in the grid's unit) of the truth, a decay time within one
    step of the geometric ``decay_grid``. ``truth_scale`` converts the truth's display unit to the
    grid's (e.g. 1/60 for minutes against a grid in hours). ``crb_key``: the truth's Cramér-Rao
    standard deviation of the onset (same unit), for an efficient estimator's rate on the same
    cases (``g8_step_onset_crb``, :func:`crb_rate`); ``decay_crb_key``: the decay time's
    deviation in log time, summarised against the one-step tolerance (``g8_transient_decay_crb``,
    :func:`crb_spread`). The rates are scored twice where the
    results carry ``grid_located`` (the reports' located values, :func:`grid_locations`):
    ``g8_step_onset`` and ``g8_transient_decay`` at the largest score, the ``_located`` ones
    at the located value."""
    (fs, ks), (ft, kt) = step, transient
    ratio = math.log(decay_grid[1] / decay_grid[0])
    steps = [(t, r) for t, r in strong if t["family"] == fs]
    transients = [(t, r) for t, r in strong if t["family"] == ft]

    def rates(key):
        if not all(key in r for _, r in steps + transients):
            return None, None
        return (rate(steps, lambda t, r: abs(r[key][fs] - truth_scale * t[ks])
                      <= 0.05 * record_length(r)),
                rate(transients, lambda t, r: abs(math.log(r[key][ft] / (truth_scale * t[kt])))
                      <= ratio))

    best, located = rates("grid_best"), rates("grid_located")
    return {
        "g8_step_onset": best[0], "g8_transient_decay": best[1],
        "g8_step_onset_located": located[0], "g8_transient_decay_located": located[1],
        # a local reference on the same cases: the truth side's Cramér-Rao deviations
        "g8_step_onset_crb": crb_rate(steps, crb_key, lambda r: 0.05 * record_length(r),
                                      truth_scale) if crb_key else None,
        "g8_transient_decay_crb": crb_spread(transients, decay_crb_key, ratio)
        if decay_crb_key else None,
    }


def onset_crb(j_nuisance, j_onset) -> float:
    """Cramér-Rao standard deviation of an onset (in its Jacobian's unit) from whitened columns:
    ``1 / |(I - P) j_onset|`` with ``P`` the projector on the span of the nuisance columns (the
    nominal parameters and the effect's sizes, estimated jointly with the onset; rank-revealing,
    so a structurally unidentifiable nominal direction costs nothing). Any other grid value
    the same way, e.g. a decay time with ``j_onset`` its column in log time."""
    q = nominal_basis(np.asarray(j_nuisance))
    r = np.asarray(j_onset) - q @ (q.T @ np.asarray(j_onset))
    return float(1.0 / np.sqrt(r @ r))


def crb_rate(pairs, key: str, tol, truth_scale: float = 1.0):
    """An efficient estimator's expected share within ``tol(result)`` of the truth, the mean of
    ``erf(tol / (sqrt 2 sigma))`` over the pairs whose truth has the Cramér-Rao standard
    deviation ``key`` (times ``truth_scale``, to ``tol``'s unit); ``None`` when none has. A local
    reference: it counts only errors near the truth, not the far ones of the threshold regime
    (another onset fitting the absorbed remainder better), so it is no bound at low lambda."""
    vals = [math.erf(tol(r) / (math.sqrt(2) * truth_scale * t[key])) for t, r in pairs
            if key in t]
    return {"rate": float(np.mean(vals)), "n": len(vals)} if vals else None


def crb_spread(pairs, key: str, tol: float):
    """How well the record can place a grid parameter at all: over the pairs whose truth has
    the Cramér-Rao deviation ``key``, the median of deviation / ``tol`` and the share with a
    deviation <= ``tol`` (``None`` when none has). For a decay time (deviation in log time,
    ``tol`` the grid's log ratio) :func:`crb_rate` would mislead: where the deviation exceeds the
    grid's whole span, a Gaussian efficient estimator does worse than any guess inside the
    grid, so the rate a diagnosis reaches there comes from the grid's range, not the record."""
    r = np.array([t[key] / tol for t, _ in pairs if key in t])
    return ({"median_ratio": float(np.median(r)), "resolved": float(np.mean(r <= 1.0)),
             "n": int(r.size)} if r.size else None)


def localisation_fields(rep) -> dict:
    """What goal G8 scores from a report: each grid effect's screened grid value (onset,
    decay time; ``grid_best``) and located value (``grid_located``), the frequency cell of
    smallest p (``top_line``, its p) and the record's length in hours."""
    lines = [x for x in rep.where if x["axis"] == "frequency"]
    top = min(lines, key=lambda x: x["p"]) if lines else None
    taus = [x for x in rep.where if x["axis"] == "tau" and x.get("rate") != "full"]  # decided
    top_tau = min(taus, key=lambda x: x["p"]) if taus else None
    t = np.asarray(rep.t)
    return {"grid_best": grid_best(rep), "grid_located": grid_locations(rep),
            "top_line": top["cell"] if top else None, "top_line_p": top["p"] if top else None,
            "top_tau_s": top_tau["tau_s"] if top_tau else None,
            "top_tau_significant": bool(top_tau and top_tau["significant"]),
            "longest_tau_s": max(x["tau_s"] for x in taus) if taus else None,
            "record_hours": float((t[-1] - t[0]) / 3600)}


def tau_band_scores(pairs) -> dict:
    """Goal G8 for noise-model effects over (truth, result) pairs of ``angle_random_walk``
    cases: the share whose tau axis has a significant cell, and of those the share whose
    smallest-p tau cell is the longest band (where a random walk's Allan excess over white
    noise, growing as tau^2, is largest)."""
    rw = [(t, r) for t, r in pairs if t["family"] == "angle_random_walk"]
    sig = [(t, r) for t, r in rw if r.get("top_tau_significant")]
    return {"g8_tau_detected": rate(rw, lambda t, r: r.get("top_tau_significant")),
            "g8_tau_band": rate(sig, lambda t, r: r["top_tau_s"] == r["longest_tau_s"]),
            "g8_tau_not_attributed": rate(rw, lambda t, r: r["verdict"] != "attributed")}


def multiplicity_fields(rep) -> dict:
    """What a blind result keeps of the multiplicity decision: the smallest weighted-BH q over
    the map and the library, and the level it was held to (calibrated or ``alpha``)."""
    qs = [x["q"] for x in rep.where if x.get("q") is not None] + [r["q"] for r in rep.ranking]
    return {"min_q": min(qs, default=1.0),
            "level": rep.multiplicity.get("level", rep.alpha)}


def plain_bh_far(nulls) -> dict:
    """On the null cases ``(truth, result)``: the false-alarm rate weighted BH would have at the
    uncalibrated level 0.05 (smallest q < 0.05), and the median calibrated level."""
    nulls = [(t, r) for t, r in nulls if "min_q" in r]
    if not nulls:
        return {}
    levels = sorted(r["level"] for _, r in nulls)
    return {"far_plain_bh": rate(nulls, lambda t, r: r["min_q"] < 0.05),
            "level_median": levels[len(levels) // 2]}


def _se(p, n):
    return math.sqrt(max(p * (1 - p), 1e-12) / max(n, 1))


def rate(pairs, fn):
    """Share of (truth, result) pairs where ``fn`` holds, its Monte Carlo standard error and n."""
    pairs = list(pairs)
    if not pairs:
        return None
    k = sum(bool(fn(t, r)) for t, r in pairs)
    p = k / len(pairs)
    return {"rate": p, "se": _se(p, len(pairs)), "n": len(pairs)}


def orthonormal_basis(j):
    """Orthonormal basis of the column span of ``j`` (rank-revealing QR: column pivoting, so a
    dependent or zero column does not turn a later column's direction)."""
    q, r, _ = scipy.linalg.qr(j, mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    return q[:, : int(np.sum(d > 1e-10 * d[0]))] if d.size and d[0] > 0 else q[:, :0]


def remainder_after_library(d, jn, cols) -> dict:
    """Truth side of goal G9: the noncentrality of a whitened out-of-library term ``d``
    (train rows) left after the nominal parameters (columns ``jn``) and the best catalogue fit
    of one effect or a pair are fitted (the diagnosis' forward selection can name up to
    ``max_effects`` = 3; the truth side stops at pairs, so a three-effect mimic counts
    here as outside the catalogue).
    ``cols``: family -> list of column blocks (one per grid value). Returns the
    nominal-projected lambda, the remainder after the best fit (one effect or a pair), after
    the best single effect, and that effect.

    Every fit below projects ``d`` on ``jn`` and a few blocks: all are taken in the coordinates
    of one QR of ``[jn, every block, d]`` (an isometry of their span), so each fit is a small
    dense problem instead of a QR over every train row (the same numbers to rounding)."""
    blocks = [b for fam in cols for b in cols[fam]]
    m = np.concatenate([jn] + blocks + [np.asarray(d)[:, None]], axis=1)
    if m.shape[0] > m.shape[1]:
        r = np.linalg.qr(m, mode="r")
        edges = np.cumsum([jn.shape[1]] + [b.shape[1] for b in blocks])
        jn, d, in_r, at = r[:, :edges[0]], r[:, -1], {}, 0
        for fam, fam_blocks in cols.items():
            in_r[fam] = [r[:, edges[at + i]:edges[at + i + 1]] for i in range(len(fam_blocks))]
            at += len(fam_blocks)
        cols = in_r

    def left(extra):
        q = orthonormal_basis(np.concatenate([jn] + list(extra), axis=1))
        r = d - q @ (q.T @ d)
        return float(r @ r)

    fams = list(cols)
    single = min(((a, left([ca])) for a in fams for ca in cols[a]), key=lambda x: x[1])
    pair = min(left([ca, cb]) for i, a in enumerate(fams) for b in fams[i + 1:]
               for ca in cols[a] for cb in cols[b])
    return {"nominal_lambda": left([]), "remainder_lambda": min(single[1], pair),
            "remainder_single_lambda": single[1], "closest_effect": single[0]}


def confident(r) -> bool:
    """Attributed with posterior > 0.9 (an effect without a posterior, e.g. a noise-model term,
    counts as confident)."""
    return r["verdict"] == "attributed" and bool(r["effects"]) and max(
        r["posterior"].get(e, 1.0) for e in r["effects"]) > 0.9


def ool_scores(ool) -> dict:
    """Goal G9 over out-of-library (truth, result) pairs: over the cases whose remainder
    noncentrality after the best library fit (truth side, ``remainder_lambda``; else the
    case's lambda) is >= 32, the share not confidently attributed and the share unexplained or
    ambiguous; over every case, the confident misattributions."""
    strong = [(t, r) for t, r in ool if t.get("remainder_lambda", t["lambda"]) >= 32]
    return {
        "ool_strong_not_confident": rate(strong, lambda t, r: not confident(r)),
        "ool_strong_unexplained_or_ambiguous": rate(
            strong, lambda t, r: r["verdict"] in ("unexplained", "ambiguous")),
        "ool_confident_misattribution": rate(ool, lambda t, r: confident(r)),
        # how far outside the catalogue's span the confidently misattributed cases reached: a
        # remainder near zero means the library mimics the effect on this record (no test on it
        # can tell them apart; only a design shift can)
        "ool_confident_remainder_max": max(
            (t["remainder_lambda"] for t, r in ool if confident(r) and "remainder_lambda" in t),
            default=None),
        "ool_remainder_from_truth": bool(ool) and all("remainder_lambda" in t for t, _ in ool),
    }


def ranking_scores(ranking) -> dict:
    """What the oracle needs from a blind run: each effect's score statistic and dof at every
    grid value (``{name: [scores, dofs]}``)."""
    return {r["name"]: [r["score_grid"], r["dof_grid"]] for r in ranking}


def oracle_choice(r, lam: float):
    """The Bayes-oracle answer (docs/goals.md) for a case of noncentrality ``lam``: the effect of
    largest posterior under the linearised model with equal prior odds between the catalogue
    effects and the diagnosis' design prior sized to expect exactly ``lam``
    (:func:`~gyrojax.diagnose._bayes.design_log_bf`), averaged over each effect's grid. It
    reads the blind run's design-prior factors at every prior size (``r["log_bf_by_lambda"]``)
    at the sealed ``lam``, which the diagnosis does not know (it assumes ``lambda0 = 32``)."""
    lbf = _oracle_log_bfs(r, lam)
    return max(lbf, key=lbf.get) if lbf else None


def _oracle_log_bfs(r, lam: float) -> dict:
    """Each effect's design-prior log Bayes factor at prior size ``lam`` (the effects with a
    signature) from the run's recorded curve (``log_bf_by_lambda``, powers of 2 from 1 to
    1024: every suite's lambda is one); a ``lam`` between two recorded sizes is interpolated
    linearly in ``log lambda``."""
    curves = r.get("log_bf_by_lambda") or {}
    scores = r.get("scores") or {}
    out = {}
    for k, c in curves.items():
        if k in scores and not any(scores[k][1]):
            continue  # no signature: no posterior (as the diagnosis', _screening._posteriors)
        sizes = sorted(c, key=float)
        x = np.log([float(v) for v in sizes])
        if not x[0] - 1e-12 <= math.log(lam) <= x[-1] + 1e-12:
            raise KeyError(f"the run's design-prior factors cover lambda {sizes[0]}-{sizes[-1]}, "
                           f"not {lam:g}")
        out[k] = float(np.interp(math.log(lam), x, [c[v] for v in sizes]))
    return out


def oracle_detect_statistic(r, lam: float) -> float:
    """The Bayes oracle's detection statistic for a case of noncentrality ``lam``: the log of
    the mean over the catalogue of the design-prior Bayes factors expecting exactly ``lam``
    (:func:`oracle_choice`'s prior), i.e. the likelihood ratio of the generator's alternative
    against the null in the linearised model (Neyman-Pearson: the most powerful detector)."""
    lbf = list(_oracle_log_bfs(r, lam).values())
    return float(np.logaddexp.reduce(lbf) - math.log(len(lbf)))


def oracle_power(pairs, lam: float, thresholds):
    """Detection power of the Bayes oracle on ``pairs`` of noncentrality ``lam``: its statistic
    above the level-alpha threshold ``thresholds[lam]`` (from
    :func:`gyrojax.validation._harness.oracle_detection_thresholds`); ``None`` without one."""
    if not thresholds or float(lam) not in thresholds:
        return None
    return rate([(t, r) for t, r in pairs if r.get("log_bf_by_lambda")],
                 lambda t, r: oracle_detect_statistic(r, lam) > thresholds[float(lam)])


def calibration(pairs, n_bins: int = 10):
    """The set calibration (docs/goals.md) of the posteriors over in-library (truth, result) pairs, with
    each result's posteriors renormalised over the catalogue (an effect is present): expected
    calibration error of the top posterior (``n_bins`` equal-width bins; ``|accuracy -
    confidence|`` weighted by the bin's share) and the multi-class Brier score. ``None``
    without posteriors."""
    conf, hit, brier = [], [], []
    for t, r in pairs:
        post = r.get("posterior") or {}
        total = sum(post.values())
        if total <= 0:
            continue
        p = {k: v / total for k, v in post.items()}
        top = max(p, key=p.get)
        conf.append(p[top])
        hit.append(float(top == t["family"]))
        brier.append(sum((v - (k == t["family"])) ** 2 for k, v in p.items())
                     + (0.0 if t["family"] in p else 1.0))
    if not conf:
        return None
    conf, hit = np.asarray(conf), np.asarray(hit)
    bins = np.minimum((conf * n_bins).astype(int), n_bins - 1)

    def ece(h):
        return sum(abs(h[bins == b].mean() - conf[bins == b].mean()) * np.mean(bins == b)
                   for b in range(n_bins) if np.any(bins == b))

    # the ECE a perfectly calibrated forecaster shows with these confidences and this n (the
    # binned ECE is biased upwards at small n): outcomes drawn as Bernoulli(confidence)
    rng = np.random.default_rng(0)
    null = [ece((rng.uniform(size=conf.size) < conf).astype(float)) for _ in range(1000)]
    return {"ece": float(ece(hit)), "ece_calibrated_median": float(np.median(null)),
            "ece_calibrated_95": float(np.quantile(null, 0.95)), "brier": float(np.mean(brier)),
            "n": len(conf), "mean_confidence": float(conf.mean()), "accuracy": float(hit.mean())}


def ratio_rate(pairs, num, den):
    """Ratio of two rates on the same cases (e.g. top-1 / oracle top-1) with its delta-method
    standard error for paired indicators: ``se = sd(x - R y) / (sqrt(n) mean(y))``."""
    pairs = list(pairs)
    if not pairs:
        return None
    x = np.array([bool(num(t, r)) for t, r in pairs], float)
    y = np.array([bool(den(t, r)) for t, r in pairs], float)
    if y.sum() == 0:
        return None
    ratio = x.mean() / y.mean()
    se = float(np.std(x - ratio * y) / (math.sqrt(len(x)) * y.mean()))
    return {"rate": float(ratio), "se": se, "n": len(x)}


def confounding_scores(lib) -> dict:
    """The metrics of docs/goals.md / goal G5 over the in-library cases ``lib`` ((truth, result) pairs):
    confounding recall (hidden effects whose truth-side visible fraction is < 0.05, or which have no
    signature, that the diagnosis flags so: :data:`CONFOUNDED_FLAGS` on that effect's row) and
    precision (flagged hidden effects that are so on the truth side), the agreement of the two
    flags over every case, and the confident misattribution over all in-library cases
    (posterior > 0.9 on another effect)."""
    known = [(t, r) for t, r in lib if "visibility" in t and "flags" in r]

    def flagged(t, r):
        return r["flags"].get(t["family"]) in CONFOUNDED_FLAGS

    def truth(t, r):
        return t["visibility"] in CONFOUNDED_FLAGS

    return {"confounding_recall": rate([x for x in known if truth(*x)], flagged),
            "confounding_precision": rate([x for x in known if flagged(*x)], truth),
            "confounding_agreement": rate(known, lambda t, r: flagged(t, r) == truth(t, r)),
            "confident_misattribution_all": rate(
                lib, lambda t, r: bool(r["posterior"]) and max(r["posterior"].values()) > 0.9
                and top_effect(r) != t["family"])}


def top_effect(r):
    return max(r["posterior"], key=r["posterior"].get) if r["posterior"] else None


def top3_effects(r):
    return sorted(r["posterior"], key=lambda k: -r["posterior"][k])[:3]


def heldout_reduction(r):
    g0, g1 = r["heldout_gap_before"], r["heldout_gap_after"]
    if g0 is None or g1 is None or g0 <= r["null_band"][1]:
        return None
    return 1 - g1 / g0

