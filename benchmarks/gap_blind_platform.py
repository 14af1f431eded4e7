"""Blind validation of the gap diagnosis on the three-gimbal platform (spec gap-diagnosis §5-6,
design D2).

One sealed suite: the 14 positions of seed 001 at a static run and two vibration amplitudes
(table 0, 9, 7 g; 100 s dwells at 40 Hz, 1 arcsec angle noise), the 27 nominal drift
coefficients drawn per case, nulls, the five catalogue effects at noncentrality 8/16/32/64, the
seed-001 structural case (hidden D_oo on a single-amplitude test) and two out-of-library pick-off
effects. Also reports how separable the catalogue is on D2 (largest projected canonical
correlation of each effect with another one). Writes the section ``gap_blind_platform`` of
RESULTS.md.

    python benchmarks/gap_blind_platform.py              # 200 cases (~8 min on 2 cores)
    python benchmarks/gap_blind_platform.py --cases 24   # quick look
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(__file__))

import numpy as np  # noqa: E402
from _results import fmt_rate as _fmt  # noqa: E402
from _results import machine_line, publish, suite_lines  # noqa: E402
from tqdm import tqdm  # noqa: E402

from gyrojax import units  # noqa: E402
from gyrojax.diagnose import bench_platform as bp  # noqa: E402
from gyrojax.diagnose._harness import separability  # noqa: E402
from gyrojax.io import load_record  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    ap.add_argument("--keep", help="directory to keep the cases and results in")
    args = ap.parse_args(argv)
    work = args.keep or tempfile.mkdtemp(prefix="gyrojax-blind-platform-")
    design = bp.PlatformDesign()
    t0 = time.perf_counter()
    paths = bp.generate(work, args.cases, seed=args.seed, design=design, null_fraction=0.3)
    t_gen = time.perf_counter() - t0
    bar = tqdm(total=args.cases, desc="platform", unit="case")
    t0 = time.perf_counter()
    results = bp.run(work, design=design, progress=lambda i, n: bar.update(1))
    bar.close()
    t_run = time.perf_counter() - t0
    with open(os.path.join(work, "results.json"), "w") as fh:
        json.dump(results, fh)
    s = bp.score(work, results)
    full = next(p for p in paths if json.loads(load_record(p).conditions["schedule_json"])[
        "table_amplitudes_g"] == list(design.table_amplitudes_g))
    sep = separability(load_record(full), "platform", np.full(3, units.ARCSEC))
    separable = sorted(e for e, v in sep.items() if v <= 0.9)
    lines = ["## Gap diagnosis, blind platform suite D2 (`benchmarks/gap_blind_platform.py`)",
             "", machine_line(), "",
             f"Design D2: {json.dumps(dataclasses.asdict(design))} (Table 1 positions). "
             f"{args.cases} sealed cases (seed {args.seed}, 30 % nulls), generated in "
             f"{t_gen:.0f} s, diagnosed in {t_run:.0f} s (median "
             f"{s['median_diagnose_s']:.2f} s per case). Records come from the ODE model with "
             "the rig's effect groups; the diagnosis works from the linear (S22) design. Rates "
             "± Monte Carlo standard error (n cases). top-1 = the verdict's first effect (or the "
             "top posterior) is the hidden one; named = the hidden effect is in the verdict or "
             "the 90 % ambiguity set.", "",
             f"- Nulls: false-alarm rate {_fmt(s['far'])}.",
             "- Structural (seed 001): hidden D_oo at its prior scale (0.03 deg/h/g^2) on a "
             "single-amplitude test left unattributed (no-gap or confounded): "
             f"{_fmt(s['structural_silent'])}; the aliases D_f + kappa D_oo, D_ii - D_oo, "
             "D_ss - D_oo are checked to 1e-6 by the tests.",
             "- Separability on D2 (largest projected canonical correlation with another "
             "catalogue effect, over every pair of grid values): "
             + ", ".join(f"{e} {v:.4f}" for e, v in sorted(sep.items()))
             + f". Separable (<= 0.9): {', '.join(separable) or 'none'}.", ""]
    lines += suite_lines(s, "readout_line, readout_step")
    publish(args.out, "gap_blind_platform", lines)


if __name__ == "__main__":
    main()
