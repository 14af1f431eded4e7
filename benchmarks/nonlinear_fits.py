"""Nonlinear fits of the diagnoses and the Schuler test, timed: the nominal fit, the refits and
the whole diagnosis of one record per rig, and the Schuler test's iterated Gauss-Newton.

Every nonlinear least-squares fit in gyrojax runs through optimistix
(``gyrojax.estimate.solve_least_squares``); this benchmark is the check that the generic path
kept the speed of the hand-written loops it replaced. The records are simulated by the
``gyrojax simulate`` command (the same ones on any commit), the timings read from
``diagnose(...).timings`` (public), the best of ``--repeat`` warm calls after one call that
compiles (reported apart).

    python benchmarks/nonlinear_fits.py [--repeat 3] [--out benchmarks/RESULTS.md]
        [--label after] [--json times.json] [--compilation-cache DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

RECORDS = {
    # rig -> (simulate arguments, diagnose keyword arguments)
    "esg": (["--scheme", "equatorial", "--latitude", "55.75", "--set", "m11=0.15",
             "--set", "mc2=-0.15", "--set", "eps2=40", "--set", "eps3=60", "--seed", "1"], {}),
    "schuler": (["--rig", "schuler", "--periods", "2", "--sample", "10", "--set",
                 "nudot2=0.05", "--seed", "2"], {}),
    "gyrotheodolite": (["--rig", "gyrotheodolite", "--set", "M_ramp=0.3", "--seed", "3"], {}),
    "imu": (["--rig", "imu", "--poses", "12", "--dwell", "10", "--set", "sax=800", "--set",
             "maxy=2", "--latitude", "45", "--seed", "4"], {"conditions": {"latitude_deg": 45.0}}),
}


def _simulate(rig: str, folder: str) -> str:
    out = os.path.join(folder, f"{rig}.nc")
    cmd = [sys.executable, "-m", "gyrojax", "simulate", *RECORDS[rig][0], "--out", out]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out


def _time_diagnose(rig, path, repeat):
    from gyrojax.diagnose import diagnose
    from gyrojax.io import load_record

    rec = load_record(path)
    kw = dict(RECORDS[rig][1])
    t0 = time.perf_counter()
    first = diagnose(rec, rig=rig, design_advice=False, **kw)
    first_s = time.perf_counter() - t0
    runs = [diagnose(rec, rig=rig, design_advice=False, **kw).timings for _ in range(repeat)]
    best = {k: min(r.get(k, 0.0) for r in runs) for k in ("nominal_fit_s", "refit_s", "total_s")}
    return dict(first_total_s=first_s, verdict=first.verdict["kind"],
                effects=list(first.verdict.get("effects") or []), **best)


def _time_fit_schuler(path, repeat):
    import numpy as np

    from gyrojax.estimate.schuler import fit_schuler
    from gyrojax.io import load_record
    from gyrojax.models.schuler import SchulerConditions, SchulerRig

    rec = load_record(path)
    c = rec.conditions
    cond = SchulerConditions.create(float(c["latitude_deg"]), g=c.get("g"), v10=float(c["v10"]),
                                    v20=float(c["v20"]),
                                    azimuth0_deg=float(c.get("azimuth0_deg", 0.0)))
    rig = SchulerRig()
    t0 = time.perf_counter()
    est = fit_schuler(rig, rec.t, rec.y, cond)
    est.values.block_until_ready()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fit_schuler(rig, rec.t, rec.y, cond).values.block_until_ready()
        times.append(time.perf_counter() - t0)
    return dict(first_s=first, best_s=min(times), converged=bool(np.all(est.converged)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--label", default="this commit")
    ap.add_argument("--json", help="write the timings here")
    ap.add_argument("--out", help="results file to write the section to "
                                  "(benchmarks/RESULTS.md); default: print only")
    ap.add_argument("--before", help="a --json file of the same benchmark on another commit: "
                                     "the table gives both and their ratio")
    ap.add_argument("--rigs", default=",".join(RECORDS),
                    help="comma-separated rigs to time (default all)")
    ap.add_argument("--merge", nargs="*", default=[],
                    help="--json files of earlier runs of this commit: each figure is the "
                         "smallest over them and this run (runs interleaved with the other "
                         "commit's take the machine's drift out of the ratio)")
    ap.add_argument("--compilation-cache", metavar="DIR",
                    help="JAX's persistent compilation cache in DIR (set directly, so any "
                         "commit can use it): a second run's first calls load what the first "
                         "compiled")
    a = ap.parse_args(argv)
    if a.compilation_cache:
        import jax

        jax.config.update("jax_compilation_cache_dir", a.compilation_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rig in a.rigs.split(","):
            path = _simulate(rig, tmp)
            out[rig] = _time_diagnose(rig, path, a.repeat)
            print(rig, out[rig], flush=True)
            if rig == "schuler":
                out["fit_schuler"] = _time_fit_schuler(path, a.repeat)
                print("fit_schuler", out["fit_schuler"], flush=True)
    for path in a.merge:
        out = _smallest(out, json.load(open(path)))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=1)
    if a.out:
        _publish(a, out)


def _smallest(a: dict, b: dict) -> dict:
    """Per workload and stage, the smaller timing of two runs (the other fields of ``a``)."""
    out = {}
    for k in set(a) | set(b):
        x, y = a.get(k), b.get(k)
        if x is None or y is None:
            out[k] = x if y is None else y
            continue
        out[k] = {f: (min(v, y[f]) if f.endswith("_s") and f in y else v) for f, v in x.items()}
    return out


def _publish(a, out):
    sys.path.insert(0, os.path.dirname(__file__))
    from _results import machine_line, publish

    before = json.load(open(a.before)) if a.before else None
    lines = ["## Nonlinear fits through optimistix (`benchmarks/nonlinear_fits.py`)", "",
             machine_line() + f" Best of {a.repeat} warm calls per process; first call "
             "(compilation included) apart. Diagnosis without design advice; one record per "
             "rig from `gyrojax simulate` (the script's RECORDS). Before and after ran "
             "interleaved (a process of each in turn, rig by rig; each figure the smallest over "
             "the rounds), which takes this machine's drift (up to 2x within minutes) out of the "
             "ratio.", ""]
    head = "| workload | stage | " + ("before s | " if before else "") + f"{a.label} s |" + (
        " after / before |" if before else "")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for rig in ("esg", "schuler", "gyrotheodolite", "imu"):
        for stage in ("nominal_fit_s", "refit_s", "total_s", "first_total_s"):
            now = out[rig][stage]
            row = f"| diagnose --rig {rig} | {stage.removesuffix('_s')} | "
            if before:
                was = before[rig][stage]
                row += f"{was:.3f} | {now:.3f} | {now / was:.2f} |"
            else:
                row += f"{now:.3f} |"
            lines.append(row)
    for stage in ("best_s", "first_s"):
        now = out["fit_schuler"][stage]
        row = f"| fit_schuler (2 periods) | {stage.removesuffix('_s')} | "
        if before:
            was = before["fit_schuler"][stage]
            row += f"{was:.3f} | {now:.3f} | {now / was:.2f} |"
        else:
            row += f"{now:.3f} |"
        lines.append(row)
    lines += ["", "Verdicts: " + ", ".join(f"{r} {out[r]['verdict']} ({', '.join(out[r]['effects'])})"
                                            for r in RECORDS) + "."]
    publish(a.out, "nonlinear_fits", lines)


if __name__ == "__main__":
    main()
