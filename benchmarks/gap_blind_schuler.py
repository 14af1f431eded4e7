"""Blind validation of the gap diagnosis on the Schuler test (docs/diagnosis.md, design D5).

One sealed suite: D5's 4 h (~2.84 Schuler periods) at 10 s, the 12 nominal errors drawn from
the prior, nulls, the six visible catalogue effects at noncentrality 8/16/32/64 and two
out-of-library effects.
Also reports how separable the catalogue is on this design (largest projected canonical
correlation of each effect with another one, docs/goals.md "separable": <= 0.9). Writes the section
``gap_blind_schuler`` of RESULTS.md.

    python benchmarks/gap_blind_schuler.py              # 60 cases + 60 G8 cases
    python benchmarks/gap_blind_schuler.py --cases 12   # quick look
    python benchmarks/gap_blind_schuler.py --cases 0 --nulls 1000   # G1 null run (~25 min)
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

from _results import (  # noqa: E402
    ORACLE_LAMBDAS,
    ORACLE_NOTE,
    blind_parser,
    blind_suite,
    far_text,
    g8_line,
    g8_suite,
    machine_line,
    one_design_main,
    onset_text,
    publish,
    rescore,
    suite_lines,
)

from gyrojax.io import load_record  # noqa: E402
from gyrojax.validation import schuler as bench_schuler  # noqa: E402
from gyrojax.validation._harness import (  # noqa: E402
    oracle_detection_thresholds,
    separability,
)


def main(argv=None):
    ap = blind_parser(__doc__, cases=60)
    ap.add_argument("--g8-cases", type=int, default=60,
                    help="extra drift_step / drift_transient cases at lambda 32/64 for the "
                         "localisation of goal G8 (onset, decay time)")
    ap.add_argument("--g8-periods", type=float, nargs="*", default=[],
                    help="also localise drift steps on records of these many Schuler periods "
                         "(D5's 4 h are ~2.84): --g8-cases / 2 drift_step cases each, same seed")
    one_design_main(ap.parse_args(argv), bench_schuler, bench_schuler.SchulerDesign(), suite,
                    name="schuler", title="Gap diagnosis, Schuler-test D5 null run",
                    label="design D5 (the 12 nominal errors drawn from the prior per case)")


def suite(args, work, design):
    paths, s, t_gen, t_run = blind_suite(bench_schuler, work, args.cases, seed=args.seed,
                                         design=design, desc="schuler")
    # separability of the catalogue on this design (any record of it: the Jacobians barely
    # depend on the errors)
    sep = separability(load_record(paths[0]), "schuler", design.sigma)
    separable = sorted(e for e, v in sep.items() if v <= 0.9)
    s = rescore(bench_schuler, work, separable=separable,
                oracle_thresholds=oracle_detection_thresholds(
                    load_record(paths[0]), "schuler", design.sigma, ORACLE_LAMBDAS))
    lines = ["## Gap diagnosis, blind Schuler-test suite (`benchmarks/gap_blind_schuler.py`)", "",
             machine_line(), "",
             f"Design D5: {json.dumps(dataclasses.asdict(design))}. {args.cases} sealed cases "
             f"(seed {args.seed}, 30 % nulls), generated in {t_gen:.0f} s, diagnosed in "
             f"{t_run:.0f} s (median {s['median_diagnose_s']:.1f} s per case; the first cases "
             "compile each effect's refit). Rates ± Monte Carlo standard error (n cases). top-1 = "
             "the verdict's first effect (or the top posterior) is the hidden one; named = the "
             "hidden effect is in the verdict or the 90 % ambiguity set.", "",
             f"- Nulls: {far_text(s)}.",
             "- Separability on D5 (largest projected canonical correlation with another "
             "catalogue effect, over every pair of grid values): "
             + ", ".join(f"{e} {v:.4f}" for e, v in sorted(sep.items()))
             + f". Separable (<= 0.9): {', '.join(separable) or 'none'}.", "", ORACLE_NOTE, ""]
    lines += suite_lines(s, "velocity_line, attitude_step")
    if args.g8_cases:
        lines.insert(-1, g8_line(bench_schuler, args, work, design, step="drift_step",
                                 decay_grid="8 values, 0.25-3 h"))
        for periods in args.g8_periods:
            lines.insert(-1, g8_periods_line(args, work, design, periods))
    publish(args.out, "gap_blind_schuler", lines)


def g8_periods_line(args, work, design, periods: float) -> str:
    """G8's drift-step onset on a longer (or shorter) record than D5's: ``args.g8_cases / 2``
    sealed drift steps at lambda 32/64 (the other settings of D5 unchanged)."""
    longer = design.with_periods(periods)
    n = args.g8_cases // 2
    g8, secs = g8_suite(bench_schuler, os.path.join(work, f"periods_{periods:g}"), n,
                        seed=args.seed + 3, design=longer, families=("drift_step",))
    return (f"- Localisation on {periods:g} Schuler periods ({n} sealed drift_step cases at lambda "
            f"32/64, seed {args.seed + 3}, {secs:.0f} s): "
            f"{onset_text(g8, longer.ts, longer.n_train)}.")


if __name__ == "__main__":
    main()
