"""Confounding recall and precision of the gap diagnosis on every rig (docs/diagnosis.md,
goal G5's "practical confounding (v < 0.05)").

For each design: sealed in-library cases (no nulls; each catalogue family at noncentrality
8/16/32/64). The generator records, truth side, the hidden effect's visible fraction on the train
rows (the smallest ``1 - rho^2`` over its coefficient directions, with the Jacobians at the
generating parameters and the sealed grid value: ``bench.truth_visibility``) and the flag it
earns; the diagnosis flags every catalogue effect from its own nominal fit of the record, at the
grid value its screening chose. Recall: hidden effects confounded on the truth side (visible
fraction < 0.05, or no signature) that the diagnosis flags so; precision: flagged hidden effects
that are so on the truth side. Also G5's confident misattribution over all in-library cases
(posterior > 0.9 on another effect; goal <= 0.02). Writes the section ``gap_confounding``.

    python benchmarks/gap_confounding.py                   # 100 cases per design (~30 min)
    python benchmarks/gap_confounding.py --cases 8 --designs esg,schuler   # quick look

``--keep DIR`` keeps each design's cases and results in ``DIR/<design>``; a later run with the
same ``--keep``, seed and size reuses them (two runs with disjoint ``--designs`` on two cores,
then one with every design to publish).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(__file__))

from _results import (  # noqa: E402
    diagnose_suite,
    fmt_rate,
    machine_line,
    publish,
    reusable_cases,
    work_dir,
)

from gyrojax.validation import _scoring  # noqa: E402
from gyrojax.validation import esg as bench  # noqa: E402
from gyrojax.validation import gyrotheodolite as bench_gyrotheodolite  # noqa: E402
from gyrojax.validation import imu as bench_imu  # noqa: E402
from gyrojax.validation import platform as bench_platform  # noqa: E402
from gyrojax.validation import schuler as bench_schuler  # noqa: E402

FIRST_ORDER = ("f", "i", "o", "s")


class _Run:
    """A harness module with a design's ``run`` options fixed (the costly extras off: B2
    refit-all on ESG, every effect's refit on the platform)."""

    def __init__(self, harness, **run_kw):
        self.harness, self.run_kw = harness, run_kw

    def generate(self, *a, **kw):
        return self.harness.generate(*a, **kw)

    def run(self, work, *, design, progress=None, prior=None):
        return self.harness.run(work, design=design, progress=progress, prior=prior,
                                **self.run_kw)

    def score(self, work, results, design):
        if self.harness in (bench_platform, bench_imu):
            return self.harness.score(work, results, design=design)
        return self.harness.score(work, results)


# name -> (label, harness, design, in-library families)
DESIGNS = {
    "esg": ("ESG, vertical scheme, 24 h", _Run(bench, baselines=False), bench.Design(),
            bench.LIBRARY_FAMILIES),
    "platform": ("platform D2 (27 nominal coefficients)", _Run(bench_platform, refit_all=False),
                 bench_platform.PlatformDesign(), None),
    "platform_first_order": (
        "platform D2, first-order nominal (22 effects)", _Run(bench_platform, refit_all=False),
        bench_platform.PlatformDesign(nominal_terms=FIRST_ORDER), None),
    "imu": ("IMU 12-pose stand", _Run(bench_imu), bench_imu.IMUDesign(), None),
    "imu_per_coefficient": ("IMU 12-pose stand, per coefficient (40 effects)", _Run(bench_imu),
                            bench_imu.IMUDesign(per_coefficient=True), None),
    "schuler": ("Schuler test D5", _Run(bench_schuler), bench_schuler.SchulerDesign(),
                bench_schuler.MEAN_FAMILIES),
    "gyrotheodolite": ("gyrotheodolite, 40 min", _Run(bench_gyrotheodolite),
                       bench_gyrotheodolite.GyrotheodoliteDesign(),
                       bench_gyrotheodolite.MEAN_FAMILIES),
}


def families_of(name, design, fams):
    if fams is not None:
        return tuple(fams)
    mod = DESIGNS[name][1].harness
    return tuple(mod.mean_families(design))


def run_design(name, work, n_cases, seed):
    """Generate (or reuse) and diagnose one design's cases; returns its score and timings."""
    label, h, design, fams = DESIGNS[name]
    t_gen = None
    if reusable_cases(work, n_cases, seed, design) is None:
        t0 = time.perf_counter()
        h.generate(work, n_cases, seed=seed, design=design, null_fraction=0.0,
                   families=families_of(name, design, fams))
        t_gen = time.perf_counter() - t0
    res_path = os.path.join(work, "results.json")
    if os.path.exists(res_path) and t_gen is None:
        with open(res_path) as fh:
            results, t_run = json.load(fh), None
    else:
        results, t_run = diagnose_suite(h, work, design, name)
    return h.score(work, results, design), t_gen, t_run, results


def truth_table(work, results) -> dict:
    """Per hidden family: cases, truth-side confounded, flagged by the diagnosis."""
    man = json.loads(open(os.path.join(work, "sealed", "manifest.json")).read())["cases"]
    out = {}
    for r in results:
        t = man[r["sha"]]
        if "visibility" not in t:
            continue
        row = out.setdefault(t["family"], [0, 0, 0, [], []])
        truth = t["visibility"] in _scoring.CONFOUNDED_FLAGS
        flagged = r["flags"].get(t["family"]) in _scoring.CONFOUNDED_FLAGS
        row[0] += 1
        row[1] += truth
        row[2] += flagged
        row[3].append(t["visible_fraction"])
        if truth != flagged:  # at which lambda the two sides disagree
            row[4].append(f"{t['lambda']:g}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=100, help="sealed in-library cases per design")
    ap.add_argument("--seed", type=int, default=2200)
    ap.add_argument("--designs", default=",".join(DESIGNS),
                    help=f"comma-separated subset of {', '.join(DESIGNS)}")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    ap.add_argument("--keep", help="directory to keep (and reuse) the cases and results in")
    ap.add_argument("--no-publish", action="store_true",
                    help="run and keep, but do not write the section (a partial run)")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.designs.split(",") if n.strip()]
    bad = [n for n in names if n not in DESIGNS]
    if bad:
        ap.error(f"--designs {','.join(bad)}: unknown; use some of {', '.join(DESIGNS)}")
    root = work_dir(args, "gyrojax-blind-confounding-")
    rows, detail = [], []
    for name in names:
        seed = args.seed + list(DESIGNS).index(name)  # a design's cases whatever --designs says
        work = os.path.join(root, name)
        s, t_gen, t_run, results = run_design(name, work, args.cases, seed)
        label = DESIGNS[name][0]
        tt = truth_table(work, results)
        n_truth = sum(v[1] for v in tt.values())
        n_flag = sum(v[2] for v in tt.values())
        n = sum(v[0] for v in tt.values())
        took = ("kept results" if t_run is None else
                f"{t_gen or 0:.0f} s + {t_run:.0f} s")
        rows.append(f"| {label} | {n} | {n_truth} | {n_flag} | {fmt_rate(s['confounding_recall'])}"
                    f" | {fmt_rate(s['confounding_precision'])} | "
                    f"{fmt_rate(s['confounding_agreement'])} | "
                    f"{fmt_rate(s['confident_misattribution_all'])} | {took} |")
        fams = "; ".join(
            f"{f} {v[1]}/{v[2]}/{v[0]} (v {min(v[3]):.2g}-{max(v[3]):.2g}"
            + (f"; disagree at lambda {', '.join(sorted(v[4], key=float))}" if v[4] else "")
            + ")" for f, v in sorted(tt.items()) if v[1] or v[2])
        detail.append(f"- {label} (seed {seed}): families confounded on the truth "
                      f"side / flagged / cases (truth-side visible fraction range): "
                      f"{fams or 'none confounded, none flagged'}.")
        print(rows[-1], detail[-1], sep="\n", flush=True)
    if args.no_publish:
        return
    lines = ["## Gap diagnosis: confounding recall and precision (`benchmarks/gap_confounding.py`)",
             "", machine_line(), "",
             f"{args.cases} sealed in-library cases per design (no nulls; each catalogue family "
             "at lambda 8/16/32/64). Truth side: the hidden effect's visible fraction on the train "
             "rows (the smallest 1 - rho^2 over its coefficient directions; Jacobians at the "
             "generating parameters and the sealed grid value), confounded when < 0.05 or "
             "without signature (docs/goals.md: practical confounding; structural cases are G5's "
             "`structural_silent` rows of the rig sections). Diagnosis: the flag on the hidden "
             "effect's row of the report (practically / structurally confounded, no signature), "
             "from its own nominal fit and the grid value its screening chose. Recall: truth "
             "confounded -> flagged; precision: flagged -> truth confounded (goal G5: >= 0.95 "
             "/ >= 0.90); agreement: the two flags equal, over every case; confident "
             "misattribution: posterior > 0.9 on another effect, over all in-library cases (G5: "
             "<= 0.02). Rates ± Monte Carlo standard error (n cases); '-': no case in the "
             "denominator.", "",
             "| design | cases | truth confounded | flagged | recall | precision | agreement | "
             "confident misattribution | generated + diagnosed |",
             "|---|---|---|---|---|---|---|---|---|", *rows, "", *detail]
    publish(args.out, "gap_confounding", lines)


if __name__ == "__main__":
    main()
