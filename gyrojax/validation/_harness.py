"""Running and scoring a blind suite, shared by the rigs' harnesses (docs/diagnosis.md).

:func:`run_cases` diagnoses every ``case_*.nc`` of a suite (never reading ``sealed/``) and keeps
what the scorer needs; :func:`score_cases` unseals the manifest and computes the false-alarm rate,
per noncentrality the power, top-1 and "named" rates and ambiguity-set size, per family top-1,
the held-out gap reduction and closure, and out-of-library honesty, each with its Monte Carlo
standard error.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import numpy as np

from ..io import load_record
from ._scoring import (
    calibration,
    confounding_scores,
    grid_best,
    grid_localisation,
    grid_locations,
    multiplicity_fields,
    ool_scores,
    oracle_choice,
    oracle_power,
    plain_bh_far,
    projector,
    ranking_scores,
    rate,
    ratio_rate,
    refit_all_baseline,
    sha256_file,
)

__all__ = ["run_cases", "score_cases", "projector", "separability",
           "oracle_detection_thresholds", "sealed_pairs", "sealed_localisation"]


def separability(record, rig: str, sigma, split=None, **problem_kw) -> dict:
    """Largest canonical correlation of each visible catalogue effect with another on the train
    rows of ``split``, after the nominal parameters are projected out, maximised over the
    effects' grids (a transient with a decay time near the record length looks like a ramp);
    docs/goals.md calls an effect separable at <= 0.9. ``sigma``: the channels' noise (SI; only the
    ratios between channels matter); ``None``: the problem's own noise model on this record (the
    diagnosis's, e.g. the IMU's AR prewhitening). ``problem_kw``: the diagnosis' catalogue
    options (``nominal_terms``, ``per_coefficient``)."""
    from ..diagnose import canonical_correlation, nominal_basis, project_out, visible

    jn, sigs = _train_jacobians(record, rig, sigma, split, **problem_kw)
    u = nominal_basis(jn)
    vis = [s for s in sigs if visible(u, s.jac[0])]  # the diagnosis' threshold
    return {a.name: max(canonical_correlation(project_out(u, ja), project_out(u, jb))
                        for b in vis if b is not a for ja in a.jac for jb in b.jac)
            for a in vis}


def _train_jacobians(record, rig, sigma, split, **problem_kw):
    """The whitened nominal Jacobian and the catalogue's signatures on the train rows of
    ``split``, at the nominal fit of ``record`` (``sigma``: see :func:`separability`)."""
    from .. import rigs
    from ..diagnose import given_options, train_first

    prob = rigs.get(rig).problem_for(record, **given_options(dict(problem_kw, split=split)))
    params0 = prob.fit_nominal()
    if sigma is None:
        resid = (prob.y - prob.predict(params0))[: prob.n_train]
        sigma = prob.noise_level(resid)[0]
    jn, sigs = prob.jacobians(params0, sigma)
    tr = train_first(prob, params0)[: prob.n_train * len(prob.channels) + prob.block_train]
    return jn[tr], [dataclasses.replace(s, jac=s.jac[:, tr, :]) for s in sigs]


def oracle_detection_thresholds(record, rig: str, sigma, lambdas, *, split=None,
                                alpha: float = 0.05, n_draws: int = 20_000,
                                seed: int = 0, **problem_kw) -> dict:
    """Null thresholds of the Bayes-oracle detector (:func:`~gyrojax.validation._scoring.
    oracle_detect_statistic`) on the design of ``record``: per noncentrality, the ``1 - alpha``
    quantile of the statistic under the linearised null, from ``n_draws`` draws of the residual
    in the span of the library's projected signatures (its only part the scores see; drawn there
    as `gyrojax.diagnose._sup_null` does). The statistic is the Neyman-Pearson
    statistic of the generator's alternative (equal odds between the catalogue's effects
    with a signature, the diagnosis' design prior sized to expect exactly ``lambda``), so
    rejecting above the threshold is the most powerful level-``alpha`` test a diagnosis could
    run: the reference for goal G2's detection power."""
    from ..diagnose import design_log_bf, screen_designs

    jn, sigs = _train_jacobians(record, rig, sigma, split, **problem_kw)
    _, designs = screen_designs(jn, sigs, n_boot=0)
    # the effects with a signature: the others hold no posterior (_screening._posteriors)
    designs = [des for des in designs if any(b.shape[1] for b in des.bases)]
    span = np.concatenate([jt for des in designs for jt in des.jt], axis=1)
    q, s, _ = np.linalg.svd(span, full_matrices=False)
    q = q[:, s > 1e-10 * s[0]]  # the tested bases lie in this span too
    z = np.random.default_rng(seed).standard_normal((q.shape[1], n_draws))
    small = [([q.T @ jt for jt in des.jt], [q.T @ b for b in des.bases]) for des in designs]
    lambdas = [float(lam) for lam in lambdas]
    stat = np.stack([design_log_bf(jts, bases, z, lambdas) for jts, bases in small])  # (K, L, B)
    stat = np.logaddexp.reduce(stat, axis=0) - np.log(len(small))
    return {lam: float(np.quantile(st, 1 - alpha)) for lam, st in zip(lambdas, stat)}


def run_cases(case_dir, rig: str, holdout: float, *, split=None, refit_all: bool = False,
              progress=None, split_for=None, baselines: bool = False,
              diagnose_kw: dict | None = None, prior: str | None = None) -> list:
    """Diagnose every case blind. ``refit_all``: refit every catalogued effect alone as well
    (the scorer's oracle is then the hidden effect's own refit, goal G7). ``split_for``:
    ``(record, split) -> split`` where a record's own design decides (a one-amplitude platform
    test has no design shift). ``baselines``: also run B2 refit-all + BIC on each record
    (:func:`~gyrojax.validation._scoring.refit_all_baseline`: its answers, wall time and refit count,
    beside the screening's time). ``diagnose_kw``: more arguments of the diagnosis (e.g. the
    platform's ``nominal_terms``). ``prior``: the diagnosis' Bayes-factor prior (and B2's;
    ``None``: the diagnosis' default)."""
    from .. import rigs
    from ..diagnose import diagnose, given_options

    diagnose_kw = dict(diagnose_kw or {}) | {"prior": prior}  # None: the diagnosis' default

    results = []
    paths = sorted(Path(case_dir).glob("case_*.nc"))
    for k, path in enumerate(paths):
        rec = load_record(path)
        t0 = time.perf_counter()
        rec_split = split_for(rec, split) if split_for else split
        rep = diagnose(rec, rig=rig, holdout=holdout, design_advice=False, split=rec_split,
                       refit_all=refit_all, **diagnose_kw)
        t_diag = time.perf_counter() - t0
        v = rep.verdict
        results.append({
            "sha": sha256_file(path), "file": path.name, "verdict": v.kind, "prior": rep.prior,
            "effects": v.effects, "noise_effects": v.noise_effects,
            "ranking": [r.name for r in rep.ranking],
            "posterior": {r.name: r.posterior for r in rep.ranking},
            "flags": {r.name: r.flag for r in rep.ranking},
            "visible_fraction": {r.name: r.visible_fraction for r in rep.ranking},
            "scores": ranking_scores(rep.ranking),
            "log_bf_by_lambda": {r.name: r.log_bf_by_lambda for r in rep.ranking},
            "ambiguity": rep.ambiguity["set"],
            "heldout_gap_before": v.heldout_gap_before,
            "heldout_gap_after": v.heldout_gap_after,
            "null_band": rep.gap.get("heldout_null_band"),
            "null_band_after": next((rf.heldout_null_band_after for rf in rep.refits
                                     if rf.effects == v.effects), None),
            "single_refits": {rf.effects[0]: rf.heldout_gap_after for rf in rep.refits
                              if len(rf.effects) == 1},
            "time_diagnose_s": t_diag,
            "time_screen_s": rep.timings.get("screening_s", 0.0)
            + rep.timings.get("jacobians_s", 0.0),
            "time_calibration_s": rep.timings.get("calibration_s", 0.0),
            "time_library_scores_s": rep.timings.get("library_scores_s", 0.0)
            + rep.timings.get("jacobians_s", 0.0),
            "time_refit_all_in_report_s": rep.timings.get("refit_all_s"),
            # the effects this design cannot tell apart (docs/diagnosis.md stage 3)
            "classes": rep.ambiguity["classes"],
            # each grid effect's grid value at its largest score (onset, decay time) and the
            # record's length: goal G8's localisation
            "grid_best": grid_best(rep), "grid_located": grid_locations(rep),
            "record_s": float(rep.t[-1] - rep.t[0]),
            **multiplicity_fields(rep),
        })
        if baselines:
            options = {k: v for k, v in diagnose_kw.items() if k != "prior"}
            prob = rigs.get(rig).problem_for(rec, holdout=holdout,
                                             **given_options(options | {"split": rec_split}))
            results[-1] |= refit_all_baseline(prob, rep.ranking, np.asarray(rep.noise["std"]),
                                              prior=rep.prior)
        if progress is not None:
            progress(k + 1, len(paths))
    return results


def sealed_pairs(case_dir, results) -> list:
    """``(truth, result)`` for each result, the truth unsealed from ``case_dir``'s manifest (only
    once every record is diagnosed)."""
    manifest = json.loads((Path(case_dir) / "sealed" / "manifest.json").read_text())["cases"]
    return [(manifest[r["sha"]], r) for r in results]


def sealed_localisation(case_dir, results, *, lam_min: float = 32.0, **rules) -> dict:
    """Goal G8's grid rules (:func:`~gyrojax.validation._scoring.grid_localisation` with
    ``rules``) over the sealed in-library cases at ``lambda >= lam_min`` that screened a grid."""
    strong = [(t, r) for t, r in sealed_pairs(case_dir, results)
              if t.get("lambda", 0) >= lam_min and "grid_best" in r]
    return grid_localisation(strong, **rules)


def score_cases(case_dir, results, mean_families, noise_families=(), out_of_library=(),
                structural=(), separable=None, oracle_thresholds=None) -> dict:
    """Unseal and score. top-1: the verdict's first effect (or the top posterior) is the hidden
    one (noise effects: the first significant noise-model effect); named: the hidden effect is
    in the verdict, the ambiguity set or the noise-model list. ``structural``: families with no
    signature on the design, scored by ``structural_silent`` (verdict no-gap or confounded).
    Per noncentrality also the top-1 over the ``separable`` families (goal G3), the Bayes
    oracle's top-1 on the mean families (:func:`~gyrojax.validation._scoring.oracle_choice`: the
    sealed lambda as the prior) and the ratio of the two. With the runs' ``single_refits``
    (``run_cases(refit_all=True)``): the oracle comparison of goal G7 over the detected
    cases of the ``separable`` families (default: every mean family) whose held-out gap
    exceeds its null band: the share whose reduction ``R = 1 - G_after / G_before`` reaches
    0.9 x the oracle's (the hidden effect's own refit). ``oracle_thresholds`` (``{lambda:
    threshold}``, :func:`oracle_detection_thresholds`): also the Bayes oracle's detection power
    (goal G2's reference) on the mean families."""
    rows = sealed_pairs(case_dir, results)
    nulls = [(t, r) for t, r in rows if t["family"] == "null"]
    lib = [(t, r) for t, r in rows if t["family"] in tuple(mean_families) + tuple(noise_families)]
    ool = [(t, r) for t, r in rows if t["family"] in out_of_library]

    def top(t, r):
        if t["family"] in noise_families:
            return r["noise_effects"][:1] == [t["family"]]
        eff = r["effects"] or ([max(r["posterior"], key=r["posterior"].get)]
                               if r["posterior"] else [])
        return eff[:1] == [t["family"]]

    def named(t, r):
        return t["family"] in set(r["effects"]) | set(r["ambiguity"]) | set(r["noise_effects"])

    sep = tuple(mean_families if separable is None else separable)

    def oracle(t, r):
        return oracle_choice(r, t["lambda"]) == t["family"]

    out = {"far": rate(nulls, lambda t, r: r["verdict"] != "no-gap"), **plain_bh_far(nulls),
           "by_lambda": {}}
    for lam in sorted({t["lambda"] for t, _ in lib}):
        sub = [(t, r) for t, r in lib if t["lambda"] == lam]
        sizes = [len(r["ambiguity"]) for _, r in sub if r["ambiguity"]]
        sub_mean = [(t, r) for t, r in sub if t["family"] in mean_families]
        out["by_lambda"][f"{lam:g}"] = {
            "power": rate(sub, lambda t, r: r["verdict"] != "no-gap"),
            "top1": rate(sub, top), "named": rate(sub, named),
            "mean_set_size": float(np.mean(sizes)) if sizes else None,
            # goal G3: top-1 on the separable families, and against the Bayes oracle (mean
            # effects: the oracle reads the score statistics, which noise effects do not have)
            "top1_separable": rate([(t, r) for t, r in sub if t["family"] in sep], top),
            "oracle_top1_separable": rate([(t, r) for t, r in sub_mean if t["family"] in sep],
                                           oracle),
            "oracle_top1": rate(sub_mean, oracle),
            "oracle_efficiency": ratio_rate(sub_mean, top, oracle),
            "oracle_power": oracle_power(sub_mean, lam, oracle_thresholds),
            "calibration": calibration(sub_mean),
            "b2_top1": (rate(sub_mean, lambda t, r: r["b2_choice"] == t["family"])
                        if all("b2_choice" in r for _, r in sub_mean) else None),
        }
    out["calibration"] = calibration([(t, r) for t, r in lib if t["family"] in mean_families])
    out["by_family"] = {f: rate([(t, r) for t, r in lib if t["family"] == f], top)
                        for f in sorted({t["family"] for t, _ in lib})}
    mean_lib = [(t, r) for t, r in lib if t["family"] in mean_families]
    red = [1 - r["heldout_gap_after"] / r["heldout_gap_before"] for t, r in mean_lib
           if r["heldout_gap_after"] is not None and r["null_band"] is not None
           and r["heldout_gap_before"] > r["null_band"][1]]
    out["heldout_reduction_median"] = float(np.median(red)) if red else None
    out["heldout_closure"] = rate([(t, r) for t, r in mean_lib if r["heldout_gap_after"]
                                    is not None and r["null_band_after"] is not None],
                                   lambda t, r: r["heldout_gap_after"] <= r["null_band_after"][1])
    g7 = [(t, r) for t, r in mean_lib if t["family"] in sep and r.get("single_refits")
          and r["verdict"] != "no-gap" and r["heldout_gap_after"] is not None
          and t["family"] in r["single_refits"] and r["null_band"] is not None
          and r["heldout_gap_before"] > r["null_band"][1]]

    def vs_oracle(t, r):
        g0 = r["heldout_gap_before"]
        return 1 - r["heldout_gap_after"] / g0 >= 0.9 * (1 - r["single_refits"][t["family"]] / g0)

    out["heldout_vs_oracle"] = rate(g7, vs_oracle)
    out["heldout_vs_oracle_all"] = rate(  # every mean family, confusable ones included
        [(t, r) for t, r in mean_lib if r.get("single_refits") and r["verdict"] != "no-gap"
         and r["heldout_gap_after"] is not None and t["family"] in r["single_refits"]
         and r["null_band"] is not None and r["heldout_gap_before"] > r["null_band"][1]],
        vs_oracle)
    out["heldout_oracle_reduction_median"] = (float(np.median(
        [1 - r["single_refits"][t["family"]] / r["heldout_gap_before"] for t, r in g7]))
        if g7 else None)
    out["heldout_closure_separable"] = rate(
        [(t, r) for t, r in g7 if r["null_band_after"] is not None],
        lambda t, r: r["heldout_gap_after"] <= r["null_band_after"][1])
    out["out_of_library_honest"] = rate(ool, lambda t, r: r["verdict"] in
                                         ("unexplained", "ambiguous", "no-gap"))

    out |= ool_scores(ool)  # goal G9
    out |= confounding_scores(mean_lib)  # goal G5, practical confounding
    if structural:
        out["structural_silent"] = rate([(t, r) for t, r in rows if t["family"] in structural],
                                         lambda t, r: r["verdict"] in ("no-gap", "confounded"))
    out["median_diagnose_s"] = float(np.median([r["time_diagnose_s"] for _, r in rows]))
    b2 = [r for _, r in rows if "time_refit_all_s" in r]
    if b2:  # goal G10: screening against B2 refit-all on the same records
        out["cost"] = {"median_screen_s": float(np.median([r["time_screen_s"] for r in b2])),
                       "median_library_scores_s": float(np.median(
                           [r["time_library_scores_s"] for r in b2])),
                       "median_calibration_s": float(np.median(
                           [r["time_calibration_s"] for r in b2])),
                       "median_refit_all_s": float(np.median(
                           [r["time_refit_all_s"] for r in b2])),
                       "n_refits": int(np.median([r["n_refits"] for r in b2])),
                       "n_effects": int(np.median([len(r["ranking"]) for r in b2]))}
        strong = [(t, r) for t, r in mean_lib if t["lambda"] >= 32 and r.get("b2_lr_choice")]
        out["screen_refit_agreement"] = rate(
            strong, lambda t, r: max(r["posterior"], key=r["posterior"].get)
            == r["b2_lr_choice"])

        def same_class(t, r):  # the same answer, or two effects the design cannot tell apart
            a, b = max(r["posterior"], key=r["posterior"].get), r["b2_lr_choice"]
            return a == b or any(a in c and b in c for c in r["classes"])
        out["screen_refit_agreement_classes"] = rate(
            [(t, r) for t, r in strong if "classes" in r], same_class)
    return out


def _first_effect(rep):
    """The verdict's first effect, or the top posterior where the verdict names none."""
    return (rep.verdict.effects or [None])[0] or max(
        rep.ranking, key=lambda r: r.posterior).name


def closed_loop(case_dir, rig: str, hidden: str, rerun, truth_coefficients, *,
                holdout: float, seed: int = 0, load=load_record, progress=None) -> list:
    """Goal G6 closed loop over the cases of ``case_dir``. Each record is diagnosed blind
    with the design advisor on; then, as an experimenter would, the same instrument is run
    again, new noise, under the design the advisor ranks first for ``hidden`` and that record is
    diagnosed blind. ``rerun(record, truth, label, key) -> record`` re-simulates the sealed
    instrument ``truth`` under the design an advice row labels (the manifest is unsealed only
    after every record has been diagnosed); ``truth_coefficients(truth) -> dict`` reads the
    hidden effect's sealed coefficients (display units). Returns per case: the verdict and first
    effect on the record's own design, every flagged effect's first advised design with its
    predicted MDE over the prior scale (alone and with the closest rival fitted too), and on the
    advised design the verdict, its effects, the first effect (or top posterior) and the refit
    coefficients of the verdict's effects with their standard errors (display units) and, where
    the verdict is the hidden effect alone, the errors in standard errors of the coefficients
    and combinations it determines (``z_advised``, :func:`refit_z`)."""
    from ..diagnose import diagnose

    paths = sorted(Path(case_dir).glob("case_*.nc"))
    first = []
    for path in paths:  # blind: the manifest is not read until every record is diagnosed
        rec = load(path)
        rep = diagnose(rec, rig=rig, holdout=holdout)
        advice = {}
        for a in rep.design_advice:  # ranked per effect: the first is the advised one
            advice.setdefault(a["effect"], a)
        first.append((path, rec, rep.verdict, _first_effect(rep),
                      {r.name: r.flag for r in rep.ranking if r.flag != "visible"},
                      advice))
    manifest = json.loads((Path(case_dir) / "sealed" / "manifest.json").read_text())["cases"]
    key = jax.random.key(seed)
    out = []
    for i, (path, rec, verdict, top, flagged, advice) in enumerate(first):
        truth = manifest[sha256_file(path)]
        row = {"file": path.name, "family": truth["family"],
               "truth": {k: v for k, v in truth.items() if isinstance(v, (str, int, float))},
               "verdict": verdict["kind"],
               "effects": verdict.get("effects") or [], "top": top,
               "flagged": flagged,
               "advised": {e: {"design": a["design"], "mde_over_prior": a["mde_over_prior"],
                               "mde_vs_closest_rival": a["mde_vs_closest_rival"],
                               "unseen_dims": a.get("unseen_dims", 0)}
                           for e, a in advice.items()}}
        if hidden in advice:
            key, sub = jax.random.split(key)
            rec2 = rerun(rec, truth, advice[hidden]["design"], sub)
            rep2 = diagnose(rec2, rig=rig, holdout=holdout, design_advice=False)
            eff = rep2.verdict.get("effects") or []
            row |= {"design_advised": advice[hidden]["design"],
                    "verdict_advised": rep2.verdict["kind"], "top_advised": _first_effect(rep2),
                    "effects_advised": eff,
                    "coefficients_advised": {}, "std_errors_advised": {}}
            rf = next((x for x in rep2.refits if x["effects"] == eff), None)
            if rf is not None:
                row |= {"coefficients_advised": rf["coefficients"],
                        "std_errors_advised": rf["std_errors"]}
            if eff == [hidden] and row["coefficients_advised"]:
                row["z_advised"] = refit_z(rf, truth_coefficients(truth))
        out.append(row)
        if progress is not None:
            progress(i + 1, len(first))
    return out


def refit_z(refit: dict, truth: dict) -> dict:
    """A refit's errors against ``truth`` (display units, by coefficient name) in its reported
    standard errors: each coefficient it determines, and each combination it determines of the
    coefficients it does not (``refit["estimable"]``, keyed by its text) whose terms all have a
    truth. A coefficient determined only in combination (infinite standard error) has no z of
    its own: a 0 there would flatter the calibration."""
    se, coef = refit["std_errors"], refit["coefficients"]
    z = {k: (coef[k] - v) / se[k] for k, v in truth.items() if math.isfinite(se[k])}
    for c in refit.get("estimable", []):
        if c["terms"].keys() <= truth.keys():
            z[c["combination"]] = (c["value"] - sum(x * truth[k] for k, x in c["terms"].items())
                                   ) / c["std_error"]
    return z


def _resolves(advice_row) -> bool:
    """The design predicts the effect's MDE within its prior scale with the closest rival effect
    fitted too (the advisor's ranking key)."""
    return advice_row["mde_vs_closest_rival"] <= 1.0


def closed_loop_scores(rows, hidden: str) -> dict:
    """G6's rates. Over every flagged effect of every case: whether the design the advisor ranks
    first resolves it, i.e. predicts an MDE within the prior scale with the closest rival effect
    fitted too (the advisor's ranking key, so where any catalogued design resolves it the first
    one does), per effect; for ``hidden``, on the record's own design and, over the re-run
    cases, on its advised design (same instrument, new noise): the share whose first effect is
    ``hidden`` (class-level top-1) and the share attributed to it alone, and the top-1 over
    the re-run cases whose advised design resolves ``hidden`` (G6 asks it of those); and every
    refit coefficient's error in its standard errors where it was (``z_advised``)."""
    pairs = [(e, row["advised"][e]) for row in rows for e in row["flagged"]
             if e in row["advised"]]
    resolved = lambda _, a: _resolves(a)  # noqa: E731
    looped = [(None, r) for r in rows if "top_advised" in r]
    return {"resolved": rate(pairs, resolved),
            "resolved_by_effect": {e: rate([x for x in pairs if x[0] == e], resolved)
                                   for e in sorted({x for x, _ in pairs})},
            "hidden_flagged": rate([(None, r) for r in rows], lambda _, r: hidden in r["flagged"]),
            "advised_designs": sorted({r["advised"][hidden]["design"] for r in rows
                                       if hidden in r["advised"]}),
            "max_mde_hidden": max((r["advised"][hidden]["mde_vs_closest_rival"] for r in rows
                                   if hidden in r["advised"]), default=float("nan")),
            "top1_own": rate([(None, r) for r in rows], lambda _, r: r["top"] == hidden),
            "attributed_own": rate([(None, r) for r in rows],
                                    lambda _, r: r["verdict"] == "attributed"
                                    and r["effects"] == [hidden]),
            "top1_advised": rate(looped, lambda _, r: r["top_advised"] == hidden),
            "top1_advised_resolving": rate(
                [(None, r) for _, r in looped if _resolves(r["advised"][hidden])],
                lambda _, r: r["top_advised"] == hidden),
            "attributed_advised": rate(looped, lambda _, r: r["verdict_advised"] == "attributed"
                                        and r["effects_advised"] == [hidden]),
            "z_advised": [z for r in rows for z in r.get("z_advised", {}).values()]}
