"""Blind validation of the gap diagnosis on the strapdown IMU rig (docs/diagnosis.md).

Three sealed suites: the 12-pose multi-position design with the same-design split (last quarter
held out) and with the design-shift split (six other poses held out), and the 40-min static design
(noise-model effects, drift, warm-up). Each: nulls, the library effects at noncentrality 8/16/32/64
and the out-of-library effects. Writes the section ``gap_blind_imu`` of RESULTS.md.

    python benchmarks/gap_blind_imu.py              # 3 x 60 + 2 x 40 cases (~25 min)
    python benchmarks/gap_blind_imu.py --cases 12   # quick look
    python benchmarks/gap_blind_imu.py --cases 0 --nulls 1000 --null-suite static   # G1, one design
    python benchmarks/gap_blind_imu.py --cases 0 --calibration-cases 100   # G4 on the static design
    python benchmarks/gap_blind_imu.py --cases 0 --g6-cases 40   # G6: cw/ccw, temperature cycle
    python benchmarks/gap_blind_imu.py --cases 0 --per-coefficient-cases 160   # G10, K = 40
    python benchmarks/gap_blind_imu.py --cases 0 --per-coefficient-cases 160 --prior design
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))

from _results import (  # noqa: E402
    ORACLE_LAMBDAS,
    ORACLE_NOTE,
    add_prior_arg,
    blind_parser,
    calibration_line,
    diagnose_suite,
    far_text,
    g6_lines,
    g9_text,
    g10_text,
    machine_line,
    null_run,
    prior_section,
    prior_title,
    publish,
    shell_note,
    suite_lines,
    work_dir,
)
from _results import fmt_rate as _fmt  # noqa: E402
from tqdm import tqdm  # noqa: E402

from gyrojax.io import load_record  # noqa: E402
from gyrojax.validation import imu as bench_imu  # noqa: E402
from gyrojax.validation._harness import (  # noqa: E402
    closed_loop_scores,
    oracle_detection_thresholds,
    separability,
)
from gyrojax.validation._scoring import rate, sha256_file  # noqa: E402

SUITES = {
    "multi, same-design": bench_imu.IMUDesign(),
    "multi, design-shift": bench_imu.IMUDesign(split="design-shift"),
    "static": bench_imu.IMUDesign(kind="static"),
}
# design D4: the 12-pose stand, then ccw/cw rate-table runs (`--table-cases`, its own section)
TABLE_SUITES = {"rate table (D4)": bench_imu.IMUDesign(kind="table")}
# the multi design diagnosed per coefficient (K = 40; `--per-coefficient-cases`, its null run)
PER_COEFFICIENT = {"multi, per coefficient": bench_imu.IMUDesign(per_coefficient=True)}


def main(argv=None):
    ap = blind_parser(__doc__, cases=60)
    ap.add_argument("--ool-cases", type=int, default=40,
                    help="extra out-of-library cases per multi-position suite (goal G9)")
    ap.add_argument("--suite", action="append", choices=list(SUITES),
                    help="run only this suite (repeatable; default: all three), with its own "
                         "seeds: the same cases as in a run of all")
    ap.add_argument("--null-suite", action="append",
                    choices=list(SUITES | TABLE_SUITES | PER_COEFFICIENT),
                    help="the design(s) of the null run (repeatable; default: every suite)")
    ap.add_argument("--calibration-cases", type=int, default=0,
                    help="a separate run of N static-design time_drift / warmup_transient "
                         "cases at lambda 8-64 for the posteriors' calibration (goal G4)")
    ap.add_argument("--g8-cases", type=int, default=0,
                    help="a localisation run (goal G8): N pose_step cases on the multi "
                         "design (per-position signature) and N noise-model cases on the static "
                         "design (tau band)")
    ap.add_argument("--aux-cases", type=int, default=0,
                    help="an aux-axis run: N multi-design records with a temperature channel, "
                         "30 %% nulls, the rest a bias following the temperature (the "
                         "catalogue's temperature effect on one channel)")
    ap.add_argument("--table-cases", type=int, default=0,
                    help="a blind suite of N cases on the rate-table design D4 (the 12 poses, "
                         "then ccw/cw table runs), section gap_blind_imu_table")
    ap.add_argument("--g6-cases", type=int, default=0,
                    help="design-advice closed loop (goal G6: cw/ccw rotation -> sf vs "
                         "misalignment; a temperature cycle -> temperature vs drift): N "
                         "multi-position records per family with the gyro scale factors, "
                         "misalignments or temperature coefficients (on a temperature ramp) "
                         "hidden at their prior scale, diagnosed, run again on the advised "
                         "design and diagnosed again")
    ap.add_argument("--per-coefficient-cases", type=int, default=0,
                    help="goal G10 at K >= 20: N multi-design cases diagnosed with every "
                         "coefficient an effect of its own (K = 40), each hiding one "
                         "coefficient; B2 refit-all timed on every record; section "
                         "gap_blind_imu_per_coefficient")
    add_prior_arg(ap, "gap_blind_imu_per_coefficient")  # with --per-coefficient-cases only
    ap.add_argument("--reuse-cases", action="store_true",
                    help="null run: diagnose the sealed nulls already in --keep DIR when their "
                         "manifest has the same design, seed and number (no regeneration)")
    args = ap.parse_args(argv)
    others = {"--cases": args.cases, "--table-cases": args.table_cases,
              "--calibration-cases": args.calibration_cases, "--g8-cases": args.g8_cases,
              "--aux-cases": args.aux_cases, "--g6-cases": args.g6_cases}
    if args.prior not in (None, "design") and any(others.values()):
        ap.error(f"--prior {args.prior} runs the per-coefficient suite only (its own section); "
                 "set " + ", ".join(f"{k} 0" for k, v in others.items() if v)
                 + " or leave --prior out")
    work = work_dir(args, "gyrojax-blind-imu-")
    if args.cases > 0:
        suites(args, work, {k: SUITES[k] for k in args.suite} if args.suite else SUITES,
               args.cases)
    if args.table_cases > 0:
        suites(args, os.path.join(work, "table"), TABLE_SUITES, args.table_cases,
               "gap_blind_imu_table", "--table-cases")
    if args.calibration_cases > 0:
        static_calibration(args, os.path.join(work, "calibration"))
    if args.g8_cases > 0:
        localisation(args, os.path.join(work, "g8"))
    if args.aux_cases > 0:
        aux_localisation(args, os.path.join(work, "aux"))
    if args.g6_cases > 0:
        g6_run(args, os.path.join(work, "g6"))
    if args.per_coefficient_cases > 0:
        per_coefficient(args, os.path.join(work, "per_coefficient"))
    every = SUITES | TABLE_SUITES | PER_COEFFICIENT
    for label in (args.null_suite or list(SUITES)) if args.nulls > 0 else ():
        k = list(every).index(label)
        null_run(bench_imu, os.path.join(work, f"nulls{k}"), args.nulls, seed=args.seed + 20 + k,
                 design=every[label], out=args.out, key=f"gap_blind_imu_nulls_{k}",
                 title=f"Gap diagnosis, IMU null run: {label} (`benchmarks/gap_blind_imu.py "
                       "--nulls`)",
                 label=f"the {label} design (the IMU's nominal errors drawn per case)",
                 reuse=args.reuse_cases)


G6_WHY = {
    "scale_factor": "The nominal model of a still stand carries no Earth rate (its vertical part "
                    "is the earth_rate effect), so these gyro coefficients have no signature "
                    "there.",
    "misalignment": "As for the scale factors: no signature on a still stand.",
    "temperature": "Each record carries a `temp` channel (0.01 deg C noise) on a warm-up ramp of "
                   "2-4 deg C over the record, so Delta T is a linear function of time and a "
                   "bias following it is a time_drift (and near a slow warm-up transient).",
}


def g6_run(args, work):
    """goal G6 on the IMU: cw/ccw rotation -> scale factor vs misalignment (a still stand's
    nominal model carries no Earth rate, so the gyro triad's scale factors and misalignments
    have no signature there; the advisor's rate-table design drives them) and a temperature
    cycle instead of a ramp -> temperature vs drift."""
    design = bench_imu.IMUDesign()
    lines = ["## Gap diagnosis, IMU design advice closed loop: cw/ccw rotation -> scale factor "
             "vs misalignment; a temperature cycle -> temperature vs drift "
             "(`benchmarks/gap_blind_imu.py --g6-cases`)", "", machine_line(), ""]
    for k, hidden in enumerate(bench_imu.G6_PARAMS):
        sub = os.path.join(work, hidden)
        t0 = time.perf_counter()
        bench_imu.generate_closed_loop(sub, args.g6_cases, seed=args.seed + 60 + k,
                                       families=(hidden,))
        t_gen = time.perf_counter() - t0
        bar = tqdm(total=args.g6_cases, desc=f"G6 {hidden}", unit="case")
        rows = bench_imu.closed_loop(sub, hidden, design=design, seed=args.seed + 70 + k,
                                     progress=lambda i, n: bar.update(1))
        bar.close()
        sc = closed_loop_scores(rows, hidden)
        names = ", ".join(bench_imu.G6_PARAMS[hidden])
        unseen = sorted({a.get("unseen_dims", 0) for r in rows for e, a in r["advised"].items()
                         if e == hidden})
        body = g6_lines(sc, hidden)
        if hidden == "misalignment":  # its refit carries the directions no design sees
            body[-1] += (" A common rotation of both triads (3 directions, reported as seen by "
                         "no catalogued design: the poses absorb it) leaves each coefficient "
                         "undetermined, so these are the refit's nine determined combinations "
                         "(e.g. mgxy + mgyx, maxy + mgyx), the truth's accelerometer terms zero.")
        lines += [f"### {hidden} ({names}) hidden", "",
                  f"{args.g6_cases} sealed cases (seed {args.seed + 60 + k}; the 12-pose "
                  f"multi-position design, {design.dwell_s:g} s poses at {design.rate_hz:g} Hz, "
                  f"ARW {design.arw:g} deg/sqrt(h), VRW {design.vrw:g} m/s/sqrt(h); the nominal "
                  f"biases drawn as in the suite; {names} in a random direction with RMS the "
                  f"prior scale; generated in {t_gen:.0f} s, diagnosed, re-run and diagnosed "
                  f"again in {time.perf_counter() - t0 - t_gen:.0f} s). {G6_WHY[hidden]} "
                  "Closed loop: "
                  "the same instrument run again, new noise, on the design ranked first for "
                  f"{hidden}, diagnosed blind. Directions no catalogued design sees: "
                  f"{'/'.join(map(str, unseen))} (excluded from the MDE).", "", *body, ""]
    publish(args.out, "gap_blind_imu_g6", lines)


REFITS = ("Levenberg-Marquardt on the nominal biases, the pose terms and the effect; the warm-up "
          "transients at each of their decay times")


def per_coefficient(args, work):
    """goal G10 with K >= 20 effects and nonlinear refits: the 12-pose multi design diagnosed
    with ``per_coefficient=True`` (every coefficient of the catalogue's error model an effect
    of its own: K = 40 on six channels), each case hiding one coefficient at lambda 8-64;
    B2 refit-all (Levenberg-Marquardt over the biases, the 24 pose terms and the effect, per
    effect and decay time) timed on every record beside the screening."""
    import functools
    import types

    from gyrojax.diagnose import default_prior, diagnose

    design = PER_COEFFICIENT["multi, per coefficient"]
    # a catalogue of single coefficients: the diagnosis' default prior is the shell
    default = default_prior("imu", per_coefficient=True)
    args.prior = args.prior or default
    fams = bench_imu.mean_families(design)
    n = args.per_coefficient_cases
    t0 = time.perf_counter()
    paths = bench_imu.generate(work, n, seed=args.seed + 80, design=design, null_fraction=0.3,
                               families=fams)
    t_gen = time.perf_counter() - t0
    harness = types.SimpleNamespace(run=functools.partial(bench_imu.run, baselines=True))
    results, t_run = diagnose_suite(harness, work, design, f"imu K=40 ({len(fams)} hidden)",
                                    prior=args.prior)
    first = load_record(paths[0])
    sep = separability(first, "imu", None, per_coefficient=True)
    separable = sorted(e for e, v in sep.items() if v <= 0.9)
    s = bench_imu.score(work, results, separable=separable, design=design,
                        oracle_thresholds=oracle_detection_thresholds(
                            first, "imu", None, ORACLE_LAMBDAS, per_coefficient=True))
    rec = load_record(paths[1])  # one record diagnosed whole (design advice on), after JIT
    diagnose(rec, rig="imu", per_coefficient=True, prior=args.prior)
    t1 = time.perf_counter()
    rep = diagnose(rec, rig="imu", per_coefficient=True, prior=args.prior)
    t_ref = time.perf_counter() - t1
    b2 = ", ".join(f"{lam} {_fmt(b['b2_top1'])}" for lam, b in s["by_lambda"].items())
    title, option = prior_title(args.prior, default)
    lines = ["## Gap diagnosis, IMU per coefficient: K = "
             f"{s['cost']['n_effects']} effects" + title
             + " (`benchmarks/gap_blind_imu.py --per-coefficient-cases N" + option + "`)", "",
             machine_line(), "",
             f"The 12-pose multi design ({design.dwell_s:g} s poses at {design.rate_hz:g} Hz, "
             "last quarter held out) diagnosed with every coefficient of the catalogue's error "
             "model an effect of its own (`diagnose(..., per_coefficient=True)`, CLI "
             "`--per-coefficient`: g_sensitivity:gsxy, misalignment:mgxy, warmup_transient:wgx "
             "with its decay-time grid, ...; design D1's question, which term). "
             f"{n} sealed cases (seed {args.seed + 80}, 30 % nulls; one of the {len(fams)} "
             "coefficients a still stand can see hidden at lambda 8/16/32/64), generated in "
             f"{t_gen:.0f} s, diagnosed and B2 run in {t_run:.0f} s (median diagnosis "
             f"{s['median_diagnose_s']:.2f} s per case, B2 apart). Separability: "
             f"{len(separable)} of {len(sep)} visible effects at canonical correlation <= 0.9; "
             "the closest pairs "
             + ", ".join(f"{e} {v:.3f}" for e, v in sorted(sep.items(), key=lambda x: -x[1])[:4])
             + ".", "", f"- Nulls: {far_text(s)}.", "", ORACLE_NOTE, ""]
    lines += suite_lines(s, "none in this run")
    lines += [f"- B2 refit-all + BIC top-1 by lambda: {b2}.",
              f"- {g10_text(s, REFITS)}.",
              f"- Reference case (the record's {len(rec.channels)} channels, "
              f"{len(rep.ranking)} effects, design advice on): one record of the suite "
              f"diagnosed whole in {t_ref:.1f} s after compilation (G10: <= 60 s); verdict "
              f"{rep.verdict['kind']} {', '.join(rep.verdict.get('effects') or [])}".rstrip() + ".", ""]
    if rep.prior == "shell":
        lines.insert(-1, shell_note(rep.ranking))
    publish(args.out, prior_section("gap_blind_imu_per_coefficient", args.prior), lines)


def static_calibration(args, work):
    """goal G4 on the static design with enough in-library cases to read the ECE: the two
    mean effects it can see (time_drift, warmup_transient) at every lambda, no nulls."""
    design = SUITES["static"]
    t0 = time.perf_counter()
    bench_imu.generate(work, args.calibration_cases, seed=args.seed + 30, design=design,
                       null_fraction=0.0, families=("time_drift", "warmup_transient"))
    bar = tqdm(total=args.calibration_cases, desc="calibration", unit="case")
    results = bench_imu.run(work, design=design, progress=lambda i, n: bar.update(1))
    bar.close()
    s = bench_imu.score(work, results)
    top1 = ", ".join(f"lambda {k} {_fmt(b['top1'])}" for k, b in s["by_lambda"].items())
    lines = ["## Gap diagnosis, IMU static design: posterior calibration "
             "(`benchmarks/gap_blind_imu.py --calibration-cases`)", "", machine_line(), "",
             f"{args.calibration_cases} sealed time_drift / warmup_transient cases on the static "
             f"design (seed {args.seed + 30}, lambda 8/16/32/64, "
             f"{time.perf_counter() - t0:.0f} s); top-1: {top1}.", "",
             calibration_line(s["calibration"],
                              {k: b["calibration"] for k, b in s["by_lambda"].items()})]
    publish(args.out, "gap_blind_imu_static_calibration", lines)


def _diagnose_blind(d, design, label):
    """Diagnose every case of ``d`` blind: ``{sha: report}`` and the seconds it took."""

    from gyrojax.diagnose import diagnose

    paths = sorted(Path(d).glob("case_*.nc"))
    t0 = time.perf_counter()
    reps = {sha256_file(p): diagnose(load_record(p), rig="imu", holdout=design.holdout,
                              design_advice=False) for p in tqdm(paths, desc=label, unit="case")}
    return reps, time.perf_counter() - t0


def _share(flags):
    """``rate`` of a list of booleans."""

    return rate([(None, f) for f in flags], lambda _, f: f)


def localisation(args, work):
    """goal G8 on the IMU's new map axes: the per-position signature of an out-of-library
    pose_step (cosine of the map's per-position Wald z with its expectation on the record's own
    design) and the tau band of the static design's noise-model effects."""
    import numpy as np

    lams = (32.0, 64.0, 128.0)
    out = {}
    for kind, families in (("multi", ("pose_step",)),
                           ("static", ("rate_random_walk", "bias_instability", "quantization"))):
        design = SUITES["multi, same-design" if kind == "multi" else "static"]
        d = os.path.join(work, kind)
        bench_imu.generate(d, args.g8_cases, seed=args.seed + 40 + len(out), design=design,
                           lambdas=lams, null_fraction=0.0, families=families)
        reps, secs = _diagnose_blind(d, design, f"G8 {kind}")
        manifest = json.loads((Path(d) / "sealed" / "manifest.json").read_text())["cases"]
        rows = []
        for sha, rep in reps.items():
            truth = manifest[sha]
            if kind == "multi":
                exp = bench_imu.expected_position_z(load_record(Path(d) / truth["file"]), truth)
                rows.append((truth["lambda"], bench_imu.position_correlation(rep.where, exp),
                             truth.get("nominal_lambda", float("nan"))))
            else:
                level = rep.multiplicity.get("level", rep.alpha)
                rows.append((truth["lambda"], truth["family"],
                             bench_imu.tau_band_hit(rep.where, truth["family"], level)
                             | {"detected": rep.verdict["kind"] != "no-gap"}))
        out[kind] = (rows, secs)
    lines = ["## Gap diagnosis, IMU localisation on the position and tau axes "
             "(`benchmarks/gap_blind_imu.py --g8-cases`)", "", machine_line(), ""]
    rows, secs = out["multi"]
    seen = [r for r in rows if r[2] >= 1.0]  # a step in the held-out poses has no train signature

    def cell(sel):
        cos = [r[1] for r in sel]
        if not cos:
            return "-"
        return f"median {np.median(cos):.3f}, >= 0.9 {_fmt(_share([c >= 0.9 for c in cos]))}"
    per = "; ".join(f"nominal-projected lambda {a:g}-{b:g}: " + cell(
        [r for r in seen if a <= r[2] < b]) for a, b in ((1, 32), (32, 128), (128, np.inf)))
    lines += [f"- Per-position signature (G8: correlation >= 0.9): {len(rows)} sealed pose_step "
              f"cases on the multi design (an accelerometer bias that jumps at one pose change, "
              f"out of the catalogue; generator scale lambda 32/64/128, seed {args.seed + 40}, "
              f"{secs:.0f} s); {len(rows) - len(seen)} step only in the held-out poses (no "
              "train signature) are left out. The cosine between the map's per-position Wald z "
              "(every pose x channel cell the nominal leaves visible) and its expectation on the "
              "record's design, by the noncentrality the nominal model leaves (truth side): "
              + per + "."]
    rows, secs = out["static"]
    fam = sorted({r[1] for r in rows})
    parts = []
    for f in fam:
        sel = [r[2] for r in rows if r[1] == f]
        det = [h for h in sel if h["detected"]]
        sig = [h for h in sel if h["significant"]]
        parts.append(f"{f} ({bench_imu.NOISE_BAND[f]} band): detected (verdict not no-gap) "
                     f"{_fmt(_share([h['detected'] for h in sel]))}, of those the full-rate "
                     f"band right {_fmt(_share([h['full_hit'] for h in det]))}; on the map's "
                     f"rows a gyro tau cell significant "
                     f"{_fmt(_share([h['significant'] for h in sel]))}, of those at the right "
                     f"band {_fmt(_share([h['hit'] for h in sig]))}")
    lines += [f"- Tau band (G8: noise-model effects to the correct band >= 0.90): {len(rows)} "
              f"sealed noise-model cases on the static design (lambda 32/64/128, seed "
              f"{args.seed + 41}, {secs:.0f} s): " + "; ".join(parts) + ". Full-rate band: the "
              "fully overlapping Allan variance of the full-model residual on the static pieces "
              "over a white null at their own level with the full mean fit's columns removed "
              "as from the residual, one cell per octave of tau from one sample up (reported, "
              "not decided on); right = its smallest-p gyro cell within "
              f"{bench_imu.BAND_OCTAVES} octaves of the end the term lifts (quantization: the "
              "shortest tau; bias instability and rate random walk: the longest). The map's rows "
              "are 1.6-s block means after the AR prewhitening, which hides quantization and "
              "absorbs part of a slow coloured term."]
    publish(args.out, "gap_blind_imu_g8", lines)


def aux_localisation(args, work):
    """The aux axis and the temperature effect (the gap map's aux axis and the temperature family): records
    with a temperature channel, nulls and a bias that follows the temperature on one channel (the
    catalogue's ``temperature`` effect with one coefficient)."""
    design = SUITES["multi, same-design"]
    lams = (32.0, 64.0, 128.0)
    t0 = time.perf_counter()
    bench_imu.generate(work, args.aux_cases, seed=args.seed + 50, design=design, lambdas=lams,
                       null_fraction=0.3, families=("thermal_bias",), temperature=True)
    t_gen = time.perf_counter() - t0
    reps, secs = _diagnose_blind(work, design, "aux")
    manifest = json.loads((Path(work) / "sealed" / "manifest.json").read_text())["cases"]
    nulls, hits = [], {lam: [] for lam in lams}
    for sha, rep in reps.items():
        truth = manifest[sha]
        aux = [x for x in rep.where if x["axis"] == "aux"]
        flagged = any(x["significant"] for x in aux)
        if truth["family"] == "null":
            nulls.append((rep.kind != "no-gap", flagged))
            continue
        best = min(aux, key=lambda x: x["p"]) if aux else None
        hits[truth["lambda"]].append((
            rep.kind != "no-gap",
            bool(best and best["significant"] and best["channel"] == truth["channel"]),
            rep.kind == "attributed" and rep.verdict["effects"] == ["temperature"],
            rep.kind == "attributed" and rep.verdict["effects"] != ["temperature"]))
    per = "; ".join(
        f"lambda {lam:g}: detected {_fmt(_share([h[0] for h in v]))}, aux cell on the biased "
        f"channel smallest-p and significant {_fmt(_share([h[1] for h in v]))}, attributed to "
        f"temperature alone {_fmt(_share([h[2] for h in v]))}, to another effect "
        f"{_fmt(_share([h[3] for h in v]))}" for lam, v in hits.items() if v)
    lines = ["## Gap diagnosis, IMU aux axis: a bias following the temperature "
             "(`benchmarks/gap_blind_imu.py --aux-cases`)", "", machine_line(), "",
             f"{args.aux_cases} sealed records on the multi design, each with a `temp` channel "
             f"(25 + A sin(2 pi t / P + phi) deg C, A 1-3, P a third to a whole of the record, "
             f"0.01 deg C noise; seed {args.seed + 50}, generated in {t_gen:.0f} s, diagnosed in "
             f"{secs:.0f} s). 30 % nulls; the rest `thermal_bias`: one random channel's bias "
             "follows the temperature (the catalogue's `temperature` effect, Delta T from the "
             "temp channel, with one coefficient), scaled to noncentrality lambda after the "
             "nominal model (truth side). The aux axis: five equal-count temperature bins per "
             "channel and their joint test, in the map's BH family.", "",
             f"- Nulls: verdict not no-gap {_fmt(_share([n[0] for n in nulls]))}, an aux cell "
             f"significant {_fmt(_share([n[1] for n in nulls]))}.",
             f"- Thermal bias: {per}."]
    publish(args.out, "gap_blind_imu_aux", lines)


def suites(args, work, which, n_cases, key="gap_blind_imu", flag=""):
    scores, meta = {}, {}
    for label, design in which.items():
        k = list(SUITES | TABLE_SUITES).index(label)  # the suite's seeds, whichever run
        d = os.path.join(work, f"suite{k}")
        t0 = time.perf_counter()
        bench_imu.generate(d, n_cases, seed=args.seed + k, design=design, null_fraction=0.3)
        t_gen = time.perf_counter() - t0
        bar = tqdm(total=n_cases, desc=label, unit="case")
        t0 = time.perf_counter()
        results = bench_imu.run(d, design=design, progress=lambda i, n: bar.update(1))
        bar.close()
        meta[label] = (t_gen, time.perf_counter() - t0)
        with open(os.path.join(d, "results.json"), "w") as fh:
            json.dump(results, fh)
        # separability of the mean effects on this design (any record: the AR noise model and
        # the Jacobians barely change between cases)
        first = load_record(sorted(Path(d).glob("case_*.nc"))[0])
        sep = separability(first, "imu", None)
        meta[label + " sep"] = sep
        scores[label] = bench_imu.score(
            d, results, separable=[e for e, v in sep.items() if v <= 0.9],
            oracle_thresholds=oracle_detection_thresholds(first, "imu", None, ORACLE_LAMBDAS))
        if args.ool_cases > 0 and design.kind != "static":
            od = os.path.join(work, f"suite{k}_ool")
            t0 = time.perf_counter()
            bench_imu.generate(od, args.ool_cases, seed=args.seed + 10 + k, design=design,
                               null_fraction=0.0, families=bench_imu.OUT_OF_LIBRARY)
            res = bench_imu.run(od, design=design)
            meta[label + " ool"] = time.perf_counter() - t0
            scores[label + " ool"] = bench_imu.score(od, res)
    cmd = "benchmarks/gap_blind_imu.py" + (" " + flag if flag else "")
    lines = [f"## Gap diagnosis, blind IMU suites (`{cmd}`)", "", machine_line(), "",
             f"{n_cases} sealed cases per suite (seeds {args.seed}+k, 30 % nulls). Designs: "
             f"{json.dumps({k: dataclasses.asdict(v) for k, v in which.items()})}. Rates ± "
             "Monte Carlo standard error (n cases). top-1 = the verdict's first effect (noise "
             "effects: the first significant noise-model effect) is the hidden one; named = the "
             "hidden effect is in the verdict, the ambiguity set or the noise-model list.", "",
             ORACLE_NOTE, ""]
    k_of = {lb: i for i, lb in enumerate(SUITES | TABLE_SUITES)}
    for label, s in scores.items():
        if label.endswith(" ool"):
            continue
        t_gen, t_run = meta[label]
        sep = meta[label + " sep"]
        lines += [f"### {label}", "",
                  f"- Nulls: false-alarm rate {_fmt(s['far'])}. Generated in {t_gen:.0f} s, "
                  f"diagnosed in {t_run:.0f} s (median {s['median_diagnose_s']:.1f} s per case).",
                  "- Separability of the mean effects (largest projected canonical correlation "
                  "with another): " + ", ".join(f"{e} {v:.4f}" for e, v in sorted(sep.items()))
                  + ".", ""] + suite_lines(s, "pose_step, thermal_cycle")
        o = scores.get(label + " ool")
        if o is not None:
            lines += [f"- Out-of-library run ({args.ool_cases} more sealed pose_step / "
                      f"thermal_cycle cases, seed {args.seed + 10 + k_of[label]}, "
                      f"{meta[label + ' ool']:.0f} s): G9, {g9_text(o)}; "
                      f"not attributed at all {_fmt(o['out_of_library_honest'])}.", ""]
    publish(args.out, key, lines)


if __name__ == "__main__":
    main()
