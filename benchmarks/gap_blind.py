"""Blind validation of the gap diagnosis on the ESG rig (docs/diagnosis.md), with baselines.

Generates sealed cases (nulls, each library effect at noncentrality 8/16/32/64, two-effect cases,
two out-of-library effects), diagnoses them without the manifest, runs the baselines on the same
records (B1 Ljung-Box whiteness, B2 refit-all + BIC), unseals and scores. Writes the section
``gap_blind`` of RESULTS.md.

    python benchmarks/gap_blind.py        # 160 cases + 1000 nulls + 40 OOL + 60 G8 (~15 min)
    python benchmarks/gap_blind.py --cases 24 --nulls 0 --ool-cases 0 --g8-cases 0  # quick look
    python benchmarks/gap_blind.py --cases 0 --calibration-cases 400  # G4 alone (~6 min)
    python benchmarks/gap_blind.py --cases 0 --g6-cases 80  # G6, rotor tilt and diurnal line (~6 min)
    python benchmarks/gap_blind.py --cases 0 --flicker-nulls 300 --flicker-kinds gm spectral \
        --flicker-models white given reml --flicker-power 80  # G1 under flicker
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))

from _results import (  # noqa: E402
    LOCATED_WORDS,
    ORACLE_LAMBDAS,
    ORACLE_NOTE,
    calibration_line,
    crb_text,
    decay_crb_text,
    far_text,
    g6_lines,
    g9_text,
    machine_line,
    publish,
    work_dir,
)
from _results import fmt_rate as _fmt  # noqa: E402
from tqdm import tqdm  # noqa: E402

from gyrojax import units  # noqa: E402
from gyrojax.io import load_record  # noqa: E402
from gyrojax.validation import esg as bench  # noqa: E402
from gyrojax.validation._harness import (  # noqa: E402
    closed_loop_scores,
    oracle_detection_thresholds,
    separability,
)

G8_FAMILIES = ("drift_step", "drift_transient", "diurnal_line")


def g8_text(s) -> str:
    """goal G8 from a score's ``g8_*`` entries (:func:`gyrojax.validation._scoring.
    localisation_scores`)."""
    return (f"drift_step onset within 5 % of the record (1.2 h, one window of the map's finest "
            f"level) of the truth: located {_fmt(s.get('g8_step_onset_located'))}, at the "
            f"largest score {_fmt(s['g8_step_onset'])} (the onset grid: one value every 5 % of "
            f"the record over the train span, at least 8{LOCATED_WORDS}"
            f"{crb_text(s.get('g8_step_onset_crb'))}); drift_transient decay time within one "
            f"step of its grid: located {_fmt(s.get('g8_transient_decay_located'))}, at the "
            f"largest score {_fmt(s['g8_transient_decay'])}"
            f"{decay_crb_text(s.get('g8_transient_decay_crb'))}; diurnal_line on the sidereal-day line "
            f"{_fmt(s['g8_line'])} (G8: >= 0.90, >= 0.95), the other families' gaps on that "
            f"line too {_fmt(s['g8_line_other_families'])}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=160)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    ap.add_argument("--nulls", type=int, default=1000,
                    help="extra null cases for the false-alarm rate (goal G1: >= 1000; "
                         "diagnosis and B1 only)")
    ap.add_argument("--ool-cases", type=int, default=40,
                    help="extra out-of-library cases at lambda 32/64/128 for goal G9 "
                         "(diagnosis only)")
    ap.add_argument("--g8-cases", type=int, default=60,
                    help="extra drift_step / drift_transient / diurnal_line cases at lambda "
                         "32/64 for the localisation of goal G8 (diagnosis only)")
    ap.add_argument("--tau-cases", type=int, default=40,
                    help="sealed angle_random_walk cases (a noise-model effect outside the "
                         "white-noise model) for the tau band of goal G8; with --rescore "
                         "DIR run (once) and added to DIR's results")
    ap.add_argument("--calibration-cases", type=int, default=0,
                    help="sealed in-library cases (no nulls) at lambda 8-64 for the posteriors' "
                         "calibration (goal G4), section gap_blind_calibration; with "
                         "--cases 0 alone")
    ap.add_argument("--g6-cases", type=int, default=0,
                    help="design-advice closed-loop runs (goal G6): N rotor-tilt cases "
                         "(equatorial / arbitrary alpha_2 -> theta) and N sidereal-day-line "
                         "cases on 12 h records (>= 24 h -> diurnal vs ramp) over the four "
                         "schemes, each re-run on the design the advisor ranks first and "
                         "diagnosed again, sections gap_blind_g6 and gap_blind_g6_diurnal; "
                         "with --cases 0 alone")
    ap.add_argument("--g6-fractions", type=float, nargs="+", default=[1.0, 0.01],
                    help="tilt sizes of the G6 tilt run as fractions of the prior scale (10 arcmin), "
                         "in turn (default: 1, the goal's magnitude, and 0.01)")
    ap.add_argument("--flicker-nulls", type=int, default=0,
                    help="goal G1's robustness run: N sealed nulls per --flicker-arcsec "
                         "level with flicker on the gimbal angles that the white nominal noise "
                         "model omits (section gap_blind_nulls_flicker); with --cases 0 alone")
    ap.add_argument("--flicker-arcsec", type=float, nargs="+", default=[0.1, 0.2],
                    help="flicker levels (bias-instability coefficient B, arcsec; the white "
                         "noise is 1 arcsec per sample)")
    ap.add_argument("--flicker-kinds", nargs="+", default=["gm"], choices=("gm", "spectral"),
                    help="flicker generators of the --flicker-nulls run (default gm)")
    ap.add_argument("--flicker-models", nargs="+", default=["white"],
                    choices=tuple(FLICKER_MODELS),
                    help="the diagnosis' noise models on the --flicker-nulls records: white "
                         "(default), given (white + flicker at the generating B), reml")
    ap.add_argument("--flicker-power", type=int, default=0,
                    help="N cases at lambda 16 / 32: detection on white-noise records with the "
                         "REML flicker model against the white one, and on records with the "
                         "largest --flicker-arcsec level with the given-B model against the "
                         "white one (in the --flicker-nulls section)")
    ap.add_argument("--keep", help="directory to keep the cases and results in")
    ap.add_argument("--rescore", metavar="DIR",
                    help="score the results kept in DIR by an earlier --keep run (no rerun)")
    args = ap.parse_args(argv)
    if (args.calibration_cases > 0 or args.g6_cases > 0 or args.flicker_nulls > 0
            or args.flicker_power > 0):
        work = work_dir(args, "gyrojax-blind-")
        if args.calibration_cases > 0:
            calibration_run(args, os.path.join(work, "calibration"))
        if args.g6_cases > 0:
            g6_run(args, os.path.join(work, "g6"))
        if args.flicker_nulls > 0 or args.flicker_power > 0:
            flicker_null_run(args, os.path.join(work, "flicker"))
        if args.cases == 0:
            return
    design = bench.Design()
    if args.rescore:
        work = args.rescore
        with open(os.path.join(work, "results.json")) as fh:
            results = json.load(fh)
        with open(os.path.join(work, "run_meta.json")) as fh:
            meta = json.load(fh)
    else:
        work = work_dir(args, "gyrojax-blind-")
        t0 = time.perf_counter()
        bench.generate(work, args.cases, seed=args.seed, design=design, null_fraction=0.3)
        t_gen = time.perf_counter() - t0
        bar = tqdm(total=args.cases, desc="diagnosing", unit="case")
        t0 = time.perf_counter()
        results = bench.run(work, design=design, progress=lambda k, n: bar.update(1))
        bar.close()
        meta = {"cases": args.cases, "seed": args.seed, "t_generate_s": t_gen,
                "t_run_s": time.perf_counter() - t0}
        if args.nulls:
            null_dir = os.path.join(work, "nulls")
            t0 = time.perf_counter()
            bench.generate(null_dir, args.nulls, seed=args.seed + 1, design=design,
                           null_fraction=1.0)
            bar = tqdm(total=args.nulls, desc="nulls", unit="case")
            null_results = bench.run(null_dir, design=design, refit_all=False,
                                     progress=lambda k, n: bar.update(1))
            bar.close()
            ns = bench.score(null_dir, null_results)
            meta["nulls"] = {"n": args.nulls, "far": ns["far"], "b1_far": ns["b1_far"],
                             "far_plain_bh": ns.get("far_plain_bh"),
                             "level_median": ns.get("level_median"),
                             "t_s": time.perf_counter() - t0,
                             "median_diagnose_s": ns["cost"]["median_diagnose_s"]}
        if args.ool_cases:
            ool_dir = os.path.join(work, "ool")
            t0 = time.perf_counter()
            bench.generate(ool_dir, args.ool_cases, seed=args.seed + 2, design=design,
                           null_fraction=0.0, lambdas=(32.0, 64.0, 128.0),
                           families=bench.OUT_OF_LIBRARY)
            ool_results = bench.run(ool_dir, design=design, baselines=False)
            os_ = bench.score(ool_dir, ool_results)
            meta["ool"] = {"n": args.ool_cases, "t_s": time.perf_counter() - t0} | {
                k: os_[k] for k in ("ool_strong_not_confident",
                                    "ool_strong_unexplained_or_ambiguous",
                                    "ool_confident_misattribution", "out_of_library_honest",
                                    "ool_confident_remainder_max")}
        if args.g8_cases:
            g8_dir = os.path.join(work, "g8")
            t0 = time.perf_counter()
            bench.generate(g8_dir, args.g8_cases, seed=args.seed + 3, design=design,
                           null_fraction=0.0, lambdas=(32.0, 64.0), families=G8_FAMILIES)
            g8_results = bench.run(g8_dir, design=design, baselines=False)
            with open(os.path.join(g8_dir, "results.json"), "w") as fh:  # for rescoring
                json.dump(g8_results, fh)
            g8 = bench.score(g8_dir, g8_results)
            meta["g8"] = {"n": args.g8_cases, "t_s": time.perf_counter() - t0} | {
                k: v for k, v in g8.items() if k.startswith("g8_")}
        with open(os.path.join(work, "results.json"), "w") as fh:
            json.dump(results, fh)
        with open(os.path.join(work, "run_meta.json"), "w") as fh:
            json.dump(meta, fh)
    if args.tau_cases and "tau" not in meta:
        tau_dir = os.path.join(work, "tau")
        t0 = time.perf_counter()
        bench.generate(tau_dir, args.tau_cases, seed=args.seed + 4, design=design,
                       null_fraction=0.0, lambdas=(1.0, 2.0, 4.0),
                       families=("angle_random_walk",))
        ts_ = bench.score(tau_dir, bench.run(tau_dir, design=design, baselines=False))
        meta["tau"] = {"n": args.tau_cases, "t_s": time.perf_counter() - t0} | {
            k: ts_[k] for k in ("g8_tau_detected", "g8_tau_band", "g8_tau_not_attributed")}
        with open(os.path.join(work, "run_meta.json"), "w") as fh:
            json.dump(meta, fh)
    # separability of the library on this design (any record of it: the Jacobians barely depend
    # on the nominal errors), docs/goals.md: <= 0.9
    first = sorted(Path(work).glob("case_*.nc"))[0]
    sep = separability(load_record(first, channels=("alpha1", "alpha2")), "esg",
                       [design.noise_arcsec * units.ARCSEC] * 2)
    separable = sorted(e for e, v in sep.items() if v <= 0.9)
    thresholds = oracle_detection_thresholds(load_record(first, channels=("alpha1", "alpha2")),
                                             "esg", [design.noise_arcsec * units.ARCSEC] * 2,
                                             ORACLE_LAMBDAS)
    s = bench.score(work, results, separable=separable, oracle_thresholds=thresholds)
    lams = sorted((k for k in s if k.startswith("lambda=")), key=lambda k: float(k[7:]))
    lines = ["## Gap diagnosis, blind ESG suite (`benchmarks/gap_blind.py`)", "", machine_line(), "",
             f"Design: {design.scheme} scheme, {design.latitude_deg} deg N, {design.hours:g} h at "
             f"{design.sample_s:g} s, {design.noise_arcsec:g} arcsec white noise, last "
             f"{design.holdout:.0%} held out (same-design split). {meta['cases']} sealed cases (seed "
             f"{meta['seed']}), generated in {meta['t_generate_s']:.0f} s, diagnosed + baselines "
             f"in {meta['t_run_s']:.0f} s. "
             "Library: rotor_tilt, base_misalignment, drift_transient (decay-time grid), "
             "drift_ramp, drift_step (onset grid), diurnal_line. Rates ± Monte Carlo standard "
             "error (n cases).", "",
             "- Nulls: false-alarm rate (verdict not no-gap, alpha 0.05; weighted BH over map + "
             "library at the level calibrated by 499 null draws per record) "
             f"{_fmt(s['far'])}; B1 Ljung-Box {_fmt(s['b1_far'])}; B2 refit-all + BIC false "
             f"selection {_fmt(s['b2_false_selection'])}." + (
                 f" Separate null run ({meta['nulls']['n']} sealed nulls, seed {meta['seed'] + 1}, "
                 f"{meta['nulls']['t_s']:.0f} s, median {meta['nulls']['median_diagnose_s']:.2f} s "
                 f"per diagnosis): false-alarm rate {_fmt(meta['nulls']['far'])} (goal G1: "
                 "[0.03, 0.06]); B1 Ljung-Box "
                 f"{_fmt(meta['nulls']['b1_far'])}." + (
                     " Uncalibrated, weighted BH at q < 0.05 on the same nulls: "
                     f"{_fmt(meta['nulls']['far_plain_bh'])} (median calibrated level "
                     f"{meta['nulls']['level_median']:.3f})." if meta["nulls"].get("far_plain_bh")
                     else "") if meta.get("nulls") else ""), "",
             "- Separability on this design (largest projected canonical correlation with another "
             "library effect, over every pair of grid values): "
             + ", ".join(f"{e} {v:.4f}" for e, v in sorted(sep.items()))
             + f". Separable (<= 0.9): {', '.join(separable) or 'none'}.", "", ORACLE_NOTE, "",
             "| lambda | power | Bayes-oracle power | top-1 | top-1, separable families | "
             "Bayes-oracle top-1, separable | Bayes-oracle top-1 | top-1 / oracle | top-3 | "
             "90 % set coverage | mean set size | confident misattribution | "
             "B1 Ljung-Box power | B2 refit-all+BIC top-1 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k in lams:
        b = s[k]
        size = "-" if b["mean_set_size"] is None else f"{b['mean_set_size']:.2f}"
        lines.append(f"| {k.split('=')[1]} | {_fmt(b['power'])} | {_fmt(b['oracle_power'])} | "
                     f"{_fmt(b['top1'])} | "
                     f"{_fmt(b['top1_separable'])} | {_fmt(b['oracle_top1_separable'])} | "
                     f"{_fmt(b['oracle_top1'])} | "
                     f"{_fmt(b['oracle_efficiency'])} | "
                     f"{_fmt(b['top3'])} | {_fmt(b['set_coverage'])} | {size} | "
                     f"{_fmt(b['confident_misattribution'])} | {_fmt(b['b1_power'])} | "
                     f"{_fmt(b['b2_top1'])} |")
    c = s["cost"]
    med = s["heldout_reduction_median"]
    lines += ["",
              calibration_line(s.get("calibration"),
                               {k.split("=")[1]: s[k].get("calibration") for k in lams}),
              f"- Held-out gap (same-design): median reduction "
              f"{'-' if med is None else f'{med:.2f}'} over attributed/ambiguous library cases; "
              f"closure (held-out gap within the refitted model's 95 % band) "
              f"{_fmt(s['heldout_closure'])}.",
              "- Localisation (goal G8, lambda >= 32, from the screened grid values and "
              f"the gap map's frequency axis): {g8_text(s)}." + (
                  f" Localisation run ({meta['g8']['n']} more sealed "
                  f"{' / '.join(G8_FAMILIES)} cases at lambda 32/64, seed {meta['seed'] + 3}, "
                  f"{meta['g8']['t_s']:.0f} s): {g8_text(meta['g8'])}."
                  if meta.get("g8") else ""),
              f"- Out-of-library cases (2 h heater square wave, 5 h line) not confidently "
              f"attributed: {_fmt(s['out_of_library_honest'])}. Two-effect cases with both "
              f"effects named or in the set: {_fmt(s['two_effects_both_named'])}.",
              *([f"- Tau band (goal G8, noise-model effects to the correct band >= 0.90): "
                 f"{meta['tau']['n']} sealed angle_random_walk cases (a random walk on both "
                 "gimbal angles, outside the white-noise nominal model, its step set for an "
                 "expected Allan excess of 1/2/4 null s.d. at the longest band; seed "
                 f"{meta['seed'] + 4}, {meta['tau']['t_s']:.0f} s): a tau cell significant "
                 f"{_fmt(meta['tau']['g8_tau_detected'])}, of those the smallest-p tau cell at "
                 f"the longest band (where the walk's excess over white noise is largest) "
                 f"{_fmt(meta['tau']['g8_tau_band'])}; not attributed to a catalogued effect "
                 f"{_fmt(meta['tau']['g8_tau_not_attributed'])}."] if meta.get("tau") else []),
              *([f"- Out-of-library run ({meta['ool']['n']} more sealed heater_cycle / "
                 f"hvac_line cases at lambda 32/64/128, seed {meta['seed'] + 2}, "
                 f"{meta['ool']['t_s']:.0f} s): G9, on the diagnosis' grids, "
                 f"{g9_text(meta['ool'])}; "
                 f"not attributed at all {_fmt(meta['ool']['out_of_library_honest'])}."]
                if meta.get("ool") else []),
              f"- Cost per case (median): whole diagnosis {c['median_diagnose_s']:.2f} s; "
              f"screening (Jacobians + score tests) {c['median_screen_s']:.2f} s vs B2 refit-all "
              f"{c['median_refit_all_s']:.2f} s "
              f"({c['median_refit_all_s'] / c['median_screen_s']:.1f}x; with the null "
              f"calibration of the BH level, {c.get('median_calibration_s', 0.0):.2f} s more, "
              f"{c['median_refit_all_s'] / (c['median_screen_s'] + c.get('median_calibration_s', 0.0)):.1f}x)"
              " for 6 effects "
              f"({c['n_refits']} nonlinear refits: every grid value of the decay time and the "
              f"onset). Top-1 agreement of screening with the refits' answer (the same design "
              f"prior's Bayes factor with each refit's estimate in place of the one-step one) at "
              f"lambda >= 32: {_fmt(s['screen_refit_agreement'])}; on the "
              f"separable families {_fmt(s['screen_refit_agreement_separable'])}.",
              ""]
    publish(args.out, "gap_blind", lines)


def calibration_run(args, work):
    """goal G4 with enough in-library cases to read the ECE against its goal: the suite's
    76 give a calibrated forecaster an ECE of ~0.1 by sampling alone."""
    design = bench.Design()
    t0 = time.perf_counter()
    bench.generate(work, args.calibration_cases, seed=args.seed + 5, design=design,
                   null_fraction=0.0, families=bench.LIBRARY_FAMILIES)
    bar = tqdm(total=args.calibration_cases, desc="calibration", unit="case")
    results = bench.run(work, design=design, baselines=False,
                        progress=lambda k, n: bar.update(1))
    bar.close()
    with open(os.path.join(work, "results.json"), "w") as fh:  # for other priors, post hoc
        json.dump(results, fh)
    s = bench.score(work, results)
    lams = sorted((k for k in s if k.startswith("lambda=")), key=lambda k: float(k[7:]))
    top1 = ", ".join(f"lambda {k.split('=')[1]} {_fmt(s[k]['top1'])}" for k in lams)
    lines = ["## Gap diagnosis, ESG posterior calibration (`benchmarks/gap_blind.py "
             "--calibration-cases`)", "", machine_line(), "",
             f"{args.calibration_cases} sealed in-library cases on the suite's design (the six "
             f"catalogue effects, no nulls; seed {args.seed + 5}, lambda 8/16/32/64, "
             f"{time.perf_counter() - t0:.0f} s); top-1: {top1}.", "",
             calibration_line(s.get("calibration"),
                              {k.split("=")[1]: s[k].get("calibration") for k in lams}), ""]
    publish(args.out, "gap_blind_calibration", lines)


FLICKER_MODELS = {
    "white": ("the white nominal model (flicker not modelled)", {}),
    "given": ("white + flicker at the generating B (as from an Allan test)", None),
    "reml": ("white + flicker at a REML level from the record", {"noise_model": "white+flicker"}),
}


def flicker_null_run(args, work):
    """goal G1 under flicker on the gimbal angles: the same sealed nulls per level and
    generator (the GM sum the flicker model assumes, or 1/f by spectral synthesis) diagnosed
    with each noise model of ``--flicker-models``; ``--flicker-power N``: the REML model's cost,
    detection on white-noise records at lambda 16 / 32 against the white model."""
    from collections import Counter

    from gyrojax import units

    lines = ["## Gap diagnosis, ESG null run with flicker (`benchmarks/gap_blind.py "
             "--flicker-nulls`)", "", machine_line(), ""]
    for k, b in enumerate(args.flicker_arcsec if args.flicker_nulls > 0 else ()):
        for kind in args.flicker_kinds:
            design = dataclasses.replace(bench.Design(), flicker_arcsec=b, flicker_kind=kind)
            sub = os.path.join(work, f"b{k}-{kind}")
            seed = args.seed + 8 + k + (100 if kind == "spectral" else 0)
            bench.generate(sub, args.flicker_nulls, seed=seed, design=design, null_fraction=1.0)
            for model in args.flicker_models:
                what, kw = FLICKER_MODELS[model]
                kw = {"flicker_b": b * units.ARCSEC} if kw is None else kw
                t0 = time.perf_counter()
                bar = tqdm(total=args.flicker_nulls, desc=f"B={b:g} {kind} {model}",
                           unit="case")
                res = bench.run(sub, design=design, refit_all=False, noise=kw,
                                progress=lambda i, n: bar.update(1))
                bar.close()
                s = bench.score(sub, res)
                kinds = Counter(r["verdict"] for r in res if r["verdict"] != "no-gap")
                named = Counter(e for r in res if r["verdict"] != "no-gap"
                                for e in r["effects"][:1])
                lines.append(
                    f"- B = {b:g} arcsec, {'GM sum' if kind == 'gm' else 'spectral 1/f'} "
                    f"flicker (Allan floor ~{0.664 * b:.3g} arcsec), {what}: {far_text(s)}"
                    + (f"; B1 Ljung-Box {_fmt(s['b1_far'])}" if model == "white" else "")
                    + f". {args.flicker_nulls} sealed nulls, seed {seed}, "
                    f"{time.perf_counter() - t0:.0f} s. Alarms by verdict: "
                    f"{', '.join(f'{v} {n}' for v, n in kinds.most_common()) or 'none'}; "
                    f"first effect named: "
                    f"{', '.join(f'{e} {n}' for e, n in named.most_common()) or 'none'}.")
    if args.flicker_power > 0:
        def power_line(design, models, seed):
            sub = os.path.join(work, f"power-{design.flicker_arcsec:g}")
            bench.generate(sub, args.flicker_power, seed=seed, lambdas=(16.0, 32.0),
                           null_fraction=0.0, families=bench.LIBRARY_FAMILIES, design=design)
            out = []
            for model in models:
                kw = FLICKER_MODELS[model][1]
                kw = {"flicker_b": design.flicker_arcsec * units.ARCSEC} if kw is None else kw
                res = bench.run(sub, design=design, refit_all=False, baselines=False,
                                noise=kw)
                s = bench.score(sub, res)
                out.append(f"{model}: power {_fmt(s['lambda=16']['power'])} at lambda 16, "
                           f"{_fmt(s['lambda=32']['power'])} at 32")
            return "; ".join(out)

        seed = args.seed + 40
        lines.append(f"- The REML level's cost, on white-noise records with one catalogued "
                     f"effect (seed {seed}, {args.flicker_power} cases): "
                     f"{power_line(bench.Design(), ('white', 'reml'), seed)}.")
        b = max(args.flicker_arcsec)
        lines.append(
            f"- What the flicker hides: the same families and lambdas (lambda on the white "
            f"noise alone) with GM-sum flicker of B = {b:g} arcsec added (seed {seed + 1}, "
            f"{args.flicker_power} cases): "
            f"{power_line(bench.Design(flicker_arcsec=b), ('given', 'white'), seed + 1)} (the "
            f"white model's detections include its false alarms on these records).")
    lines += ["", "goal G1: FAR in [0.03, 0.06] with the correct noise model, <= 0.10 under "
              "mild misspecification (flicker present, not modelled). The design is the "
              "suite's (vertical scheme, 24 h at 60 s, 1 arcsec white noise per sample); GM-sum "
              "flicker: five Gauss-Markov processes one decade apart from one sample "
              "(`gyrojax.models.imu._flicker`, the shape the white + flicker model assumes); "
              "spectral 1/f: `gyrojax.models.imu.flicker_spectral` (PSD B^2 / (pi f) down to "
              "1/8 of the record's lowest frequency: a shape the model only approximates). The "
              "white + flicker model whitens every row (tests, refits, held-out gap) by the "
              "Kalman innovations of the GM sum (`gyrojax.analysis.flicker`)."]
    publish(args.out, "gap_blind_nulls_flicker", lines)


def g6_run(args, work):
    """goal G6 on the ESG: the advisor's first design, closed loop, for the rotor tilt
    (equatorial / arbitrary alpha_2 -> theta; 24 h records) and the sidereal-day line on 12 h
    records (>= 24 h -> diurnal vs ramp)."""
    runs = [("rotor_tilt", bench.Design(), tuple(args.g6_fractions), "gap_blind_g6",
             "rotor tilt", "theta in a random direction, its size a fraction of the prior scale "
             "10 arcmin", "To first order theta is absorbed into mc on the polar and vertical "
             "schemes and has no signature on the equatorial one (docs/rigs/esg.md): what the "
             "records show of it is second order (O(m theta)) or from the large gimbal angles."),
            ("diurnal_line", bench.Design(hours=12.0), (1.0,), "gap_blind_g6_diurnal",
             "sidereal-day line on 12 h records", "the line's four coefficients (sin, cos on "
             "each gimbal angle) in a random direction, their RMS a fraction of the prior scale "
             "5 arcsec", "Half a sidereal day of a line is near a ramp or a transient of the "
             "drift, and the gimbal angles' own Earth-rate terms absorb much of it.")]
    for k, (hidden, design, fracs, key, title, size, why) in enumerate(runs):
        sub_dir = os.path.join(work, hidden)
        t0 = time.perf_counter()
        bench.generate_closed_loop(sub_dir, args.g6_cases, hidden, seed=args.seed + 6 + 10 * k,
                                   design=design, fractions=fracs)
        t_gen = time.perf_counter() - t0
        bar = tqdm(total=args.g6_cases, desc=f"G6 {hidden}", unit="case")
        rows = bench.closed_loop(sub_dir, hidden, design=design, seed=args.seed + 7 + 10 * k,
                                 progress=lambda i, n: bar.update(1))
        bar.close()
        lines = [f"## Gap diagnosis, ESG design advice closed loop: {title} (`benchmarks/"
                 "gap_blind.py --g6-cases`)", "", machine_line(), "",
                 f"{args.g6_cases} sealed {hidden} cases (seed {args.seed + 6 + 10 * k}; the four "
                 f"schemes in turn, {design.hours:.0f} h, {design.sample_s:.0f} s samples, "
                 f"{design.noise_arcsec:g} arcsec noise; the nominal drift and initial angles "
                 f"drawn as in the suite; {size}: {', '.join(f'{f:g}' for f in fracs)} in turn; "
                 f"generated in {t_gen:.0f} s, diagnosed, re-run and diagnosed again in "
                 f"{time.perf_counter() - t0 - t_gen:.0f} s). {why} Each record is diagnosed "
                 "blind with the design advisor on (designs: each other scheme, the record "
                 "doubled (and four times as long under a day), and both), ranked by the "
                 "predicted MDE with the closest rival effect "
                 "fitted too, then alone. Closed loop: the same instrument (every sealed "
                 f"parameter) run again, new noise, on the design ranked first for {hidden}, "
                 "diagnosed blind.", ""]
        for f in fracs:
            sub = [r for r in rows if r["truth"]["fraction_of_prior"] == f]
            by = []
            for scheme in dict.fromkeys(r["truth"]["scheme"] for r in sub):
                sc = closed_loop_scores([r for r in sub if r["truth"]["scheme"] == scheme],
                                        hidden)
                by.append(f"{scheme} {_fmt(sc['top1_own'])} -> {_fmt(sc['top1_advised'])}")
            head = "the goal's magnitude" if f == 1.0 else "below the goal's magnitude"
            lines += [f"{f:g} x the prior scale ({head}):", "",
                      *g6_lines(closed_loop_scores(sub, hidden), hidden),
                      f"- By the record's scheme, first effect {hidden} on the own design -> on "
                      f"the advised one: {'; '.join(by)}.", ""]
        publish(args.out, key, lines)


if __name__ == "__main__":
    main()
