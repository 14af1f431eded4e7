"""Injection-recovery of the IMU gap diagnosis on real records (real noise, real unmodelled
effects).

Each real record is diagnosed as it is, then again with one catalogued effect added at a known
size: gyro and accelerometer scale factors, misalignments, g-sensitivity, time drift or a
warm-up transient, in a random direction (seeded), sized to noncentrality ``lambda`` on the
record's train rows through the diagnosis' own whitened signature with the nominal model
projected out. The effect is added to the samples through the sensors' error model evaluated on
the measured signals less the nominal fit's biases (first order in the effect: a scale error
acts on the rate and force the sensor sees, turns included), not through the diagnosis' model
of the rows. The record's own noise and gaps stay in.

Scores, per record, effect and lambda:

- identifiable: the effect has directions the record shows (the un-injected report's
  ``identifiable``); the rates below count these cases;
- detected: the effect's library test is significant (q under the report's level); beside it,
  whether it already is on the record as it is (a large unmodelled gap lifts every test that
  overlaps it, so detection there says little);
- named: the injected effect is among the verdict's effects; beside it, whether the record as
  it is already names it (then naming says little), and the share over the cases where it
  does not; and the share over the separable cases (the effect is in no class of effects the
  record as it is cannot tell apart, ``GapReport.ambiguity["classes"]``);
- held-out closes: a refit of the record as it is brings its held-out gap into its null band;
  where none does, an effect added to the verdict must lower a held-out gap that a remainder
  no catalogued effect explains dominates, and naming is reported over the records where one
  does as well;
- top: the injected effect has the highest posterior;
- recovery: the refit of that effect alone on the injected record less the same refit on the
  record as it is, projected on the injected coefficients (1 = all of it), over the
  coefficients the rows determine.

Writes the section ``gap_inject_real`` of RESULTS.md.

    python benchmarks/gap_inject_real.py                       # 5 records x 5 effects x 6 lambda
    python benchmarks/gap_inject_real.py --records ln100_pair --lambdas 32
    python benchmarks/gap_inject_real.py --rows-out rows.json   # keep every case's scores
    python benchmarks/gap_inject_real.py --jobs 2               # two records at once
    python benchmarks/gap_inject_real.py --from-rows rows.json  # the section again, no rerun
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

from _results import fmt_rate, machine_line, publish  # noqa: E402

from gyrojax import rigs  # noqa: E402
from gyrojax.datasets import REAL_DATA_SETS  # noqa: E402
from gyrojax.diagnose import diagnose  # noqa: E402
from gyrojax.io import write_json  # noqa: E402
from gyrojax.models.imu import IMU_CHANNELS, IMURig, accel_matrix, gyro_matrix  # noqa: E402
from gyrojax.record import BenchRecord  # noqa: E402
from gyrojax.validation._scoring import orthonormal_basis, rate  # noqa: E402

RECORDS = ("ln100_pair", "mpu6050_multipos_calibration", "mpu9150_0", "xsens", "adis_1")
EFFECTS = ("scale_factor", "misalignment", "g_sensitivity", "time_drift", "warmup_transient")
LAMBDAS = (8.0, 16.0, 32.0, 64.0, 128.0, 256.0)
SPACE = IMURig().param_space


def injected_samples(record: BenchRecord, nominal: dict, coef: dict, tau_w: float):
    """``(samples, channels)``: the catalogued effect ``coef`` (SI, IMU parameter names) on
    ``record``'s samples, the sensors' error model on the measured rates and forces less the
    ``nominal`` biases (SI): ``(S_g + M_g) w + G f + d_g t + w_g exp(-t / tau_w)`` for the
    gyros, ``(S_a + M_a) f + d_a t + w_a exp(-t / tau_w)`` for the accelerometers."""
    p = {k: float(v) for k, v in SPACE.make().items()} | {"tau_w": float(tau_w)}
    p |= {k: float(v) for k, v in coef.items()}
    y = np.asarray(record.y, float)
    t = np.asarray(record.t, float)[:, None]
    ch = list(record.channels)
    w = np.stack([y[:, ch.index(f"w{a}")] - nominal[f"bg{a}"] for a in "xyz"], 1)
    f = np.stack([y[:, ch.index(f"a{a}")] - nominal[f"ba{a}"] for a in "xyz"], 1)
    vec = {pre: np.array([p[f"{pre}{a}"] for a in "xyz"]) for pre in ("dg", "wg", "da", "wa")}
    g = np.array([[p[f"gs{a}{b}"] for b in "xyz"] for a in "xyz"])
    decay = np.exp(-t / p["tau_w"])
    dw = w @ (np.asarray(gyro_matrix(p)) - np.eye(3)).T + f @ g.T + vec["dg"] * t \
        + vec["wg"] * decay
    df = f @ (np.asarray(accel_matrix(p)) - np.eye(3)).T + vec["da"] * t + vec["wa"] * decay
    out = np.zeros_like(y)
    for i, c in enumerate(IMU_CHANNELS):
        if c in ch:
            out[:, ch.index(c)] = (dw if c[0] == "w" else df)[:, "xyz".index(c[1])]
    return out


def sized_case(prob, q, sigs, effect, lam, rng):
    """A random direction of ``effect``'s coefficients scaled to noncentrality ``lam`` on the
    train rows (the diagnosis' whitened signatures ``sigs``, the nominal basis ``q`` of the
    train rows projected out): ``(coef SI, display values, decay time)``, or ``None`` where the
    record shows none of it."""
    (sig,) = [s for s in sigs if s.name == effect]
    m = prob.n_train * len(prob.channels)
    g = int(rng.integers(sig.jac.shape[0]))  # a decay time of the grid (warm-up)
    j = sig.jac[g][:m]
    jt = j - q @ (q.T @ j)
    z = rng.standard_normal(len(sig.names))
    lam0 = float(np.sum((jt @ z) ** 2))
    if lam0 <= 1e-12 * float(np.sum(j ** 2) * (z @ z)):
        return None
    z *= np.sqrt(lam / lam0)
    shown = dict(zip(sig.names, (z * sig.prior_scale).tolist()))  # display units
    coef = {n: float(SPACE[n].from_display(v)) for n, v in shown.items()}
    tau = prob.tau_grid_s[g] if sig.grid else 600.0
    return coef, shown, tau


def recovery(refit_inj, refit_0, shown) -> float | None:
    """The injected record's refit less the record's, projected on the injected display values
    over the coefficients both refits determine (finite standard errors)."""
    if refit_inj is None or refit_0 is None:
        return None
    keys = [k for k in shown if np.isfinite(refit_inj.std_errors.get(k, np.inf))
            and np.isfinite(refit_0.std_errors.get(k, np.inf))]
    if not keys:
        return None
    d = np.array([refit_inj.coefficients[k] - refit_0.coefficients[k] for k in keys])
    b = np.array([shown[k] for k in keys])
    return float(d @ b / (b @ b))


def _share(flags):
    return rate([(None, bool(f)) for f in flags], lambda _, r: r)


def _refit(rep, effect):
    return next((r for r in rep.refits if r.effects == [effect]), None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", nargs="+", default=list(RECORDS), choices=list(REAL_DATA_SETS))
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--lambdas", nargs="+", type=float, default=list(LAMBDAS))
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    ap.add_argument("--rows-out", help="also write every case's scores (JSON) to this file")
    ap.add_argument("--from-rows", help="write the section from a --rows-out file, diagnosing "
                                        "nothing")
    ap.add_argument("--jobs", type=int, default=1,
                    help="records diagnosed at once, each in its own process (default 1)")
    ap.add_argument("--worker-json", help=argparse.SUPPRESS)  # one record, rows to this file
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: give at least 1")
    if args.worker_json:
        return _worker(args)
    if args.from_rows:
        with open(args.from_rows) as fh:
            got = json.load(fh)
        args.records = list(got["record"])
        publish(args.out, "gap_inject_real", _lines(
            got["rows"], {k: tuple(v) for k, v in got["record"].items()}, args, got["total_s"]))
        return None
    # every record in a fresh process: each record's diagnoses compile programs of their own,
    # and one process holding the programs of several long records ran out of the kernel's
    # memory maps (LLVM "Cannot allocate memory", then a segfault)
    # (--jobs of them at once; each record keeps its seed, so the cases do not depend on it)
    t_all = time.perf_counter()
    done = {}  # record index -> the worker's rows and record tuple
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(args.jobs) as pool:
        futures = {pool.submit(_run_worker, args, k, name, os.path.join(tmp, f"rows{k}.json")): k
                   for k, name in enumerate(args.records)}
        for fut in as_completed(futures):
            try:
                done[futures[fut]] = fut.result()
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            rows = [r for i in sorted(done) for r in done[i]["rows"]]
            per_record = {args.records[i]: tuple(done[i]["record"]) for i in sorted(done)}
            if args.rows_out:
                write_json({"rows": rows, "record": per_record,
                            "total_s": time.perf_counter() - t_all}, args.rows_out)
            # after every record: a long run stopped early keeps what it measured
            publish(args.out, "gap_inject_real", _lines(rows, per_record, args,
                                                        time.perf_counter() - t_all))


def _run_worker(args, k, name, path) -> dict:
    """Diagnose record ``name`` (index ``k``: its seed is ``args.seed + k``) in a fresh process;
    its rows and record tuple, read back from ``path``."""
    cmd = [sys.executable, __file__, "--records", name, "--effects", *args.effects,
           "--lambdas", *map(str, args.lambdas), "--seed", str(args.seed + k),
           "--worker-json", path]
    subprocess.run(cmd, check=True)
    with open(path) as fh:
        return json.load(fh)


def _worker(args):
    """Diagnose the records of ``args`` as they are and injected; write the rows and each
    record's ``(verdict, seconds as it is, median seconds injected)`` to ``--worker-json``."""
    rng = np.random.default_rng(args.seed)
    rows, per_record = [], {}
    for name in args.records:
        rec = REAL_DATA_SETS[name]()
        t0 = time.perf_counter()
        base = diagnose(rec, rig="imu", design_advice=False, refit_all=True)
        t_base = time.perf_counter() - t0
        prob = rigs.get("imu").problem_for(rec, holdout=0.25)
        params0 = prob.fit_nominal()
        sigma = prob.noise_level(None)[0]
        jn, sigs = prob.jacobians(params0, sigma)  # once per record: every case scales by it
        q = orthonormal_basis(jn[: prob.n_train * len(prob.channels)])
        nominal = {k: float(params0[k]) for k in prob.nominal_names}
        nominal |= {k: 0.0 for k in ("bgx", "bgy", "bgz", "bax", "bay", "baz")
                    if k not in nominal}
        ident = {c.name: bool(c.identifiable) for c in base.ranking}
        named0 = set(base.verdict.effects or [])
        alike = {e for c in base.ambiguity["classes"] if len(c) > 1 for e in c}
        level0 = base.multiplicity.get("level", base.alpha)
        det0 = {c.name: bool(c.q is not None and c.q < level0) for c in base.ranking}
        # whether a refit of the record as it is brings its held-out gap into its null band:
        # where none does, the held-out veto weighs an added effect against a remainder no
        # catalogued effect explains
        closes = any(rf.closure for rf in base.refits)
        times = []
        print(f"{name}: {base.verdict.kind} {base.verdict.effects}, {t_base:.0f} s")
        for effect in args.effects:
            if effect not in ident:
                continue
            for lam in args.lambdas:
                case = sized_case(prob, q, sigs, effect, lam, rng)
                if case is None:
                    rows.append(dict(record=name, effect=effect, lam=lam, identifiable=False))
                    continue
                coef, shown, tau = case
                y = np.asarray(rec.y) + injected_samples(rec, nominal, coef, tau)
                inj = BenchRecord(rec.t, y, rec.channels, rec.attrs)
                t1 = time.perf_counter()
                rep = diagnose(inj, rig="imu", design_advice=False, refit_all=True)
                times.append(time.perf_counter() - t1)
                cand = rep.candidate(effect)
                level = rep.multiplicity.get("level", rep.alpha)
                top = max(rep.ranking, key=lambda c: c.posterior).name
                rows.append(dict(
                    record=name, effect=effect, lam=lam, identifiable=ident[effect],
                    closes=closes,
                    detected=bool(cand.q is not None and cand.q < level),
                    detected0=bool(det0[effect]),
                    named=effect in (rep.verdict.effects or []), named0=effect in named0,
                    separable=effect not in alike, top=bool(top == effect),
                    recovery=recovery(_refit(rep, effect), _refit(base, effect), shown),
                    verdict=f"{rep.verdict.kind} {rep.verdict.effects}"))
                r = rows[-1]
                print(f"  {effect} lambda {lam:g}: detected {r['detected']}, named "
                      f"{r['named']}, top {r['top']}, recovery {r['recovery']}, {r['verdict']}")
        verdict = f"{base.verdict.kind} ({', '.join(base.verdict.effects or [])})"
        per_record[name] = (verdict, t_base, float(np.median(times)) if times else float("nan"),
                            closes, _stop_text(base.conditional))
    write_json({"rows": rows, "record": per_record[name]}, args.worker_json)


def _stop_text(conditional) -> str | None:
    """One line of a report's ``conditional`` entry: after which effects the forward selection
    stopped, why, and the conditional score tests left (score / dof, Bonferroni p)."""
    if not conditional:
        return None
    scores = ", ".join(f"{x['effect']} {x['score']:.1f} / {x['dof']} (p {x['p_bonferroni']:.2g})"
                       for x in conditional["scores"] if x["dof"] > 0)
    return (f"after {' + '.join(conditional['after'])}: {conditional['stopped']}; "
            f"conditional scores: {scores or 'none left'}")


def _lines(rows, per_record, args, total_s):
    lines = ["## Gap diagnosis on real records: injection-recovery "
             "(`benchmarks/gap_inject_real.py`)", "", machine_line(), "",
             f"Records {', '.join(per_record)} (of {', '.join(args.records)}); effects "
             f"{', '.join(args.effects)} at lambda "
             f"{'/'.join(f'{x:g}' for x in args.lambdas)} (seed {args.seed} + the record's "
             "index), one random "
             f"direction each, added to the samples; {len(rows)} cases in {total_s:.0f} s. "
             "Rates over the identifiable cases (the effect has directions the record shows); "
             "named = in the verdict's effects (in brackets: named by the record as it is; not "
             "separable: in a class of effects the record as it is cannot tell apart); "
             "recovery = median of the refit's change over the injected coefficients (1 = all "
             "of it); held-out closes = a refit of the record as it is brings its held-out gap "
             "into its null band (where none does, the held-out veto weighs an added effect "
             "against a remainder no catalogued effect explains).", "",
             "| record | verdict as it is | held-out closes | diagnosis s (as it is / median "
             "injected) |",
             "|---|---|---|---|"]
    for name, (verdict, t_base, t_inj, *more) in per_record.items():
        shut = "-" if not more else ("yes" if more[0] else "no")
        lines.append(f"| `{name}` | {verdict} | {shut} | {t_base:.0f} / {t_inj:.0f} |")
    stops = {name: rec[4] for name, rec in per_record.items() if len(rec) > 4 and rec[4]}
    if stops:
        lines += ["", "Where the forward selection stopped on each record as it is, and the "
                  "conditional score tests of the effects left (the injected effect joins a "
                  "verdict after these; an effect the record already carries, vetoed by the "
                  "held-out part, is set aside and the rest are tested with it as a "
                  "nuisance):", ""]
        lines += [f"- `{name}`: {text}" for name, text in stops.items()]
    lines += ["", "| record | effect | lambda | detected (as it is) | named (as it is) | top "
              "| recovery |",
              "|---|---|---|---|---|---|---|"]
    for name in per_record:
        for effect in args.effects:
            for lam in args.lambdas:
                sel = [r for r in rows if r["record"] == name and r["effect"] == effect
                       and r["lam"] == lam]
                if not sel:
                    continue
                r = sel[0]
                if not r["identifiable"]:
                    lines.append(f"| `{name}` | {effect} | {lam:g} | not identifiable | | | |")
                    continue
                rec = "-" if r["recovery"] is None else f"{r['recovery']:.2f}"
                sep = "" if r["separable"] else ", not separable"
                lines.append(f"| `{name}` | {effect} | {lam:g} | {r['detected']} "
                             f"({r['detected0']}) | {r['named']} ({r['named0']}{sep}) | "
                             f"{r['top']} | {rec} |")
    lines += ["", "| lambda | detected | not detected as it is, detected | named | not named "
              "as it is, named | separable, named | separable and not named as it is, named "
              "| held-out closes, named | top | recovery (median) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for lam in args.lambdas:
        sel = [r for r in rows if r["lam"] == lam and r["identifiable"]]
        recs = [r["recovery"] for r in sel if r["recovery"] is not None]
        fresh = [r["detected"] for r in sel if not r["detected0"]]
        med = f"{np.median(recs):.2f} (n={len(recs)})" if recs else "-"
        named = [_share(r["named"] for r in sub) for sub in (
            sel, [r for r in sel if not r["named0"]], [r for r in sel if r["separable"]],
            [r for r in sel if r["separable"] and not r["named0"]],
            [r for r in sel if r.get("closes")])]
        lines.append(f"| {lam:g} | {fmt_rate(_share(r['detected'] for r in sel))} | "
                     f"{fmt_rate(_share(fresh))} | "
                     + " | ".join(fmt_rate(x) for x in named)
                     + f" | {fmt_rate(_share(r['top'] for r in sel))} | {med} |")
    # where naming arrives on each record: the lambda real noise asks for
    lines += ["", "Named, per identifiable case and lambda (the smallest lambda from which it "
              "stays named, if any, last):", "",
              "| record | effect | named as it is | "
              + " | ".join(f"{x:g}" for x in args.lambdas) + " | named from |",
              "|---|---|---|" + "---|" * len(args.lambdas) + "---|"]
    for name in per_record:
        for effect in args.effects:
            got = {r["lam"]: r for r in rows if r["record"] == name and r["effect"] == effect
                   and r["identifiable"]}
            if not got:
                continue
            marks = [("yes" if got[x]["named"] else "no") if x in got else "" for x in args.lambdas]
            lams = [x for x in args.lambdas if x in got]
            since = next((x for i, x in enumerate(lams) if all(got[y]["named"] for y in lams[i:])),
                         None)
            lines.append(f"| `{name}` | {effect} | {next(iter(got.values()))['named0']} | "
                         + " | ".join(marks) + f" | {'-' if since is None else f'{since:g}'} |")
    return lines


if __name__ == "__main__":
    main()
