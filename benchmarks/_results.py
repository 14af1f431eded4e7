"""Shared writer for ``benchmarks/RESULTS.md``: each benchmark owns one marked section and
replaces only that one (atomically), so the benchmarks can be run in any order."""

from __future__ import annotations

import os
import platform
import re
import sys

import numpy as np

HEADER = "# Benchmark results\n\nRatios are gyrojax / baseline, measured side by side in one run.\n"


def machine_line() -> str:
    import jax

    dev = ", ".join(str(d) for d in jax.devices())
    return (f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python "
            f"{sys.version.split()[0]}, jax {jax.__version__}, devices: {dev}.")


def update_section(path: str, key: str, text: str) -> None:
    """Replace (or append) the section ``key`` of the results file with ``text``."""
    from gyrojax.io import atomic_write

    old = open(path).read() if os.path.exists(path) else HEADER
    block = f"<!-- section: {key} -->\n{text.rstrip()}\n<!-- end: {key} -->\n"
    pat = re.compile(rf"<!-- section: {re.escape(key)} -->.*?<!-- end: {re.escape(key)} -->\n",
                     re.S)
    new = pat.sub(lambda _: block, old) if pat.search(old) else old.rstrip() + "\n\n" + block

    def write(tmp):
        with open(tmp, "w") as fh:
            fh.write(new)

    atomic_write(path, write)


def publish(path: str, key: str, lines) -> str:
    """Join the section's lines, print them and write them as section ``key`` of ``path``."""
    text = "\n".join(lines)
    print(text)
    update_section(path, key, text)
    return text


def best_time(fn, repeat: int = 3) -> float:
    """Best of ``repeat`` wall times of ``fn()`` (blocked on JAX results), after warm-up."""
    import time

    import jax

    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return min(times)


def first_and_best(fn, repeat: int = 3):
    """``(result, first call s (compile included), best of repeat s)`` of ``fn()``."""
    import time

    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t
    return out, first, best_time(fn, repeat)


def fmt_rate(r) -> str:
    """``rate ± se (n=...)`` of a blind-suite metric, or ``-``; three decimals from n = 500 on,
    where the standard error is below 0.01 (G1's edges 0.03 and 0.06 need the third digit)."""
    if r is None:
        return "-"
    d = 3 if r["n"] >= 500 else 2
    return f"{r['rate']:.{d}f} ± {r['se']:.{d}f} (n={r['n']})"


def far_text(s) -> str:
    """The null cases' false-alarm rate, and where the BH level was calibrated by null draws
    (goal G1), what the uncalibrated weighted BH at q < 0.05 gives on the same cases."""
    far = s["far"]
    text = f"false-alarm rate {fmt_rate(far)}" + (
        "" if far is None else f" ({round(far['rate'] * far['n'])} alarms; pooled with other "
        "runs by these counts)")
    lvl = s.get("level_median")
    if s.get("far_plain_bh") and lvl is not None and abs(lvl - 0.05) > 1e-12:
        text += (f" (BH level calibrated by 499 null draws per record, median {lvl:.3f}; "
                 f"uncalibrated, q < 0.05: {fmt_rate(s['far_plain_bh'])})")
    return text


def calibration_line(pooled, by_lambda: dict) -> str:
    """One line on the posteriors' calibration (goal G4: ECE <= 0.05) from
    :func:`gyrojax.validation._scoring.calibration` results, pooled and per lambda."""
    if pooled is None:
        return "- Posterior calibration: no posteriors."
    per = ", ".join(f"lambda {k} {c['ece']:.2f} (calibrated {c['ece_calibrated_median']:.2f}, "
                    f"n={c['n']})" for k, c in by_lambda.items() if c is not None)
    return ("- Posterior calibration (goal G4: ECE <= 0.05), the posteriors renormalised over "
            f"the catalogue, in-library cases: ECE of the top posterior {pooled['ece']:.3f} "
            f"(a calibrated forecaster at these confidences and n: median "
            f"{pooled['ece_calibrated_median']:.3f}, 95 % {pooled['ece_calibrated_95']:.3f}; "
            f"mean confidence {pooled['mean_confidence']:.2f} vs top-1 "
            f"{pooled['accuracy']:.2f}), Brier {pooled['brier']:.3f}, n={pooled['n']}; ECE per "
            f"lambda: {per}.")


def suite_lines(s: dict, ool_label: str) -> list[str]:
    """The per-lambda table and the summary lines of one suite scored by
    :func:`gyrojax.validation._harness.score_cases`."""
    lines = ["| lambda | power | Bayes-oracle power | top-1 | top-1, separable families | "
             "Bayes-oracle top-1, separable | Bayes-oracle top-1 | top-1 / oracle | named | "
             "mean set size |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for lam, b in s["by_lambda"].items():
        size = "-" if b["mean_set_size"] is None else f"{b['mean_set_size']:.2f}"
        lines.append(f"| {lam} | {fmt_rate(b['power'])} | {fmt_rate(b.get('oracle_power'))} | "
                     f"{fmt_rate(b['top1'])} | "
                     f"{fmt_rate(b['top1_separable'])} | "
                     f"{fmt_rate(b.get('oracle_top1_separable'))} | {fmt_rate(b['oracle_top1'])} | "
                     f"{fmt_rate(b['oracle_efficiency'])} | {fmt_rate(b['named'])} | {size} |")
    fam = ", ".join(f"{f} {fmt_rate(r)}" for f, r in s["by_family"].items())
    med = s["heldout_reduction_median"]
    return lines + [
        "", f"- top-1 by family (all lambdas): {fam}.",
        calibration_line(s.get("calibration"),
                         {k: b.get("calibration") for k, b in s["by_lambda"].items()}),
        f"- Held-out gap: median reduction {'-' if med is None else f'{med:.2f}'} "
        f"(mean-effect cases detected above the null band); closure "
        f"{fmt_rate(s['heldout_closure'])}.",
        f"- Out-of-library ({ool_label}) not attributed: {fmt_rate(s['out_of_library_honest'])}.",
        *([f"- G9, out-of-library: {g9_text(s)}."] if s.get("ool_remainder_from_truth")
          else []),
        ""]


def g10_text(s, refits: str) -> str:
    """goal G10 from a score's ``cost`` block and screening/refit agreement (runs with B2
    refit-all timed on every record): the library's score tests and the whole screening stage
    against refit-all, per case (median). ``refits``: what each refit is."""
    c = s["cost"]
    return (f"Cost per case (median, goal G10 with K = {c['n_effects']}): the library's "
            f"screening (Jacobians and the {c['n_effects']} score tests) "
            f"{c['median_library_scores_s'] * 1e3:.0f} ms against B2 refit-all "
            f"{c['median_refit_all_s'] * 1e3:.0f} ms ({c['n_refits']} refits, {refits}): "
            f"{c['median_refit_all_s'] / c['median_library_scores_s']:.1f}x; the whole "
            f"screening stage with the gap map {c['median_screen_s'] * 1e3:.0f} ms "
            f"({c['median_refit_all_s'] / c['median_screen_s']:.1f}x), the null calibration "
            f"of the BH level {c['median_calibration_s'] * 1e3:.0f} ms more. Top-1 agreement "
            "of screening (top posterior) with the refits' answer (the screening's Bayes "
            "factor, same prior, with each refit's estimate in place of the one-step one) at lambda "
            f">= 32: {fmt_rate(s['screen_refit_agreement'])} (G10: >= 0.98)"
            + ("" if s.get("screen_refit_agreement_classes") is None else
               f"; up to effects the design cannot tell apart (the report's classes: smallest "
               f"projected canonical correlation >= 0.98, docs/diagnosis.md stage 3) "
               f"{fmt_rate(s['screen_refit_agreement_classes'])}"))


def g9_text(s) -> str:
    """goal G9 from a score's ``ool_*`` entries (:func:`gyrojax.validation._scoring.ool_scores`):
    the strong cases, the confident misattributions and how far outside the catalogue's span
    the confidently misattributed cases reached."""
    worst = s.get("ool_confident_remainder_max")
    return ("over the cases whose remainder noncentrality after the best catalogue fit (one "
            "effect or a pair, truth side) is >= 32, not confidently attributed (attributed "
            "with posterior > 0.9) "
            f"{fmt_rate(s['ool_strong_not_confident'])}, unexplained or ambiguous "
            f"{fmt_rate(s['ool_strong_unexplained_or_ambiguous'])}; confident misattribution "
            f"over every out-of-library case {fmt_rate(s['ool_confident_misattribution'])} "
            "(G9: >= 0.80, <= 0.10)"
            + ("" if worst is None else
               f"; the confidently misattributed cases' remainder noncentrality <= {worst:.1f} "
               "(the catalogue mimics them on this record)"))


ORACLE_NOTE = ("goal G3: separable = largest projected canonical correlation with another "
               "catalogue effect <= 0.9 on the design; the Bayes oracle is the exact posterior of "
               "the linearised model with equal odds between the effects and the diagnosis' "
               "design prior sized to expect exactly the sealed lambda, read from the blind run's "
               "Bayes factors at every prior size: it knows lambda, the diagnosis assumes 32, "
               "so at lambda = 32 the two differ only where the verdict's first effect is not the "
               "top posterior. top-1 / oracle: delta-method standard error over paired cases. "
               "Bayes-oracle power (goal G2's reference): the same oracle as a detector, its "
               "likelihood ratio (mean Bayes factor over the catalogue at the sealed lambda) "
               "above its 95 % quantile under the linearised null (20,000 draws of the "
               "residual in the library's span on one record of the design): the most powerful "
               "level-0.05 test against that alternative.")

ORACLE_LAMBDAS = (8.0, 16.0, 32.0, 64.0)


def rescore(harness, work, **score_kw):
    """Score the results a suite kept in ``work`` again (e.g. with the separable families)."""
    import json

    with open(os.path.join(work, "results.json")) as fh:
        return harness.score(work, json.load(fh), **score_kw)


def blind_parser(doc: str, *, cases: int):
    """The blind scripts' shared arguments: ``--cases``, ``--seed``, ``--out``, ``--keep`` and
    ``--nulls``; the caller adds its own and parses."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--cases", type=int, default=cases, help="sealed cases (per suite)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    ap.add_argument("--keep", help="directory to keep the cases and results in")
    ap.add_argument("--nulls", type=int, default=0,
                    help="a separate run of N sealed nulls (goal G1: >= 1000 per design)")
    return ap


def work_dir(args, prefix: str) -> str:
    """``--keep``'s directory, or a temporary one removed when the script exits (a 1000-null
    run writes several GB of sealed records; left behind, they filled the disk)."""
    import atexit
    import shutil
    import tempfile

    if args.keep:
        return args.keep
    work = tempfile.mkdtemp(prefix=prefix)
    atexit.register(shutil.rmtree, work, ignore_errors=True)
    return work


def one_design_main(args, harness, design, suite, *, name: str, title: str, label: str):
    """A one-design blind script's run: the suite (``suite(args, work, design)``) when
    ``--cases`` > 0, then ``--nulls`` sealed nulls (seed + 1) as section
    ``gap_blind_<name>_nulls``, in ``--keep`` or a temporary directory."""
    work = work_dir(args, f"gyrojax-blind-{name}-")
    if args.cases > 0:
        suite(args, work, design)
    if args.nulls > 0:
        null_run(harness, os.path.join(work, "nulls"), args.nulls, seed=args.seed + 1,
                 design=design, out=args.out, key=f"gap_blind_{name}_nulls",
                 title=f"{title} (`benchmarks/gap_blind_{name}.py --nulls`)", label=label)


def reusable_cases(work, n_cases: int, seed: int, design) -> list | None:
    """The sealed cases already in ``work`` when its manifest is of this design, seed and
    number of cases (``None`` otherwise): a rerun of the diagnosis on the same records."""
    import dataclasses
    import json
    from pathlib import Path

    man = Path(work) / "sealed" / "manifest.json"
    if not man.exists():
        return None
    m = json.loads(man.read_text())
    paths = sorted(Path(work).glob("case_*.nc"))
    if (m.get("design") != json.loads(json.dumps(dataclasses.asdict(design)))
            or m.get("seed") != seed or len(m["cases"]) != n_cases or len(paths) != n_cases):
        return None
    return paths


def add_prior_arg(ap, section: str):
    """``--prior``: the diagnosis' Bayes-factor prior (default: the diagnosis' own for the
    suite's catalogue, :func:`gyrojax.diagnose.default_prior`); a suite run under the shell
    writes its own section (``section`` + ``_shell``) beside the design prior's."""
    ap.add_argument("--prior", choices=("design", "shell"), default=None,
                    help="the diagnosis' Bayes-factor prior (default: the diagnosis' own: "
                         "shell for a catalogue of single coefficients, design for effect "
                         "families; design writes section " + section + ", shell "
                         + section + "_shell)")


def prior_section(section: str, prior: str | None) -> str:
    """The RESULTS.md section of a suite run under ``prior`` (:func:`add_prior_arg`; ``None``:
    the design prior): ``section`` for the design prior, ``section_<prior>`` for another."""
    return section + ("" if prior in (None, "design") else "_" + prior)


def prior_title(prior: str | None, default: str = "design") -> tuple[str, str]:
    """A section title's suffix (the prior, where not the design prior) and its command's
    option (``--prior``, where ``prior`` is not the suite's ``default``) for a suite run under
    ``prior`` (``None``: the design prior)."""
    prior = prior or "design"
    return ("" if prior == "design" else f", the {prior} prior",
            "" if prior == default else f" --prior {prior}")


def shell_note(ranking) -> str:
    """The bullet a suite run under ``prior="shell"`` adds: what the prior is and what it
    leaves alone; ``ranking``: the rows of one of the suite's reports (each effect's
    ``params``)."""
    n_one = sum(len(r["params"]) == 1 for r in ranking)
    n_other = len(ranking) - n_one
    other = (f", the design prior over the same sizes for the {n_other} other"
             + ("s" if n_other != 1 else "")) if n_other else ""
    return ("- The posteriors under `prior=\"shell\"` (the noncentrality log-uniform over 8 to "
            f"2^24: the exact noncentral chi-square factor for the {n_one} one-coefficient "
            f"effects{other}; docs/decisions/0014-posteriors-and-priors.md); p-values, power and "
            "the gap map do not depend on the prior. B2's Bayes factors, where run, follow the same prior.")


def blind_suite(harness, work, n_cases: int, *, seed: int, design, desc: str,
                null_fraction: float = 0.3, reuse: bool = False, prior: str | None = None,
                **generate_kw):
    """Generate ``n_cases`` sealed cases of a rig's harness module (``generate``/``run``/
    ``score``) into ``work``, diagnose them with a progress bar, keep ``results.json`` and score.
    ``generate_kw``: more arguments of ``generate`` (``lambdas``, ``families``). ``reuse``:
    diagnose the cases already in ``work`` when its manifest has this design, seed and size
    (:func:`reusable_cases`; then ``t_generate_s`` is ``None``); ``prior``: the diagnosis'
    Bayes-factor prior (:func:`add_prior_arg`).
    Returns ``(paths, score, t_generate_s, t_diagnose_s)``."""
    import time

    paths = reusable_cases(work, n_cases, seed, design) if reuse else None
    t_gen = None
    if paths is None:
        t0 = time.perf_counter()
        paths = harness.generate(work, n_cases, seed=seed, design=design,
                                 null_fraction=null_fraction, **generate_kw)
        t_gen = time.perf_counter() - t0
    results, t_run = diagnose_suite(harness, work, design, desc, prior=prior)
    return paths, harness.score(work, results), t_gen, t_run


def null_run(harness, work, n_nulls: int, *, seed: int, design, out: str, key: str, title: str,
             label: str, reuse: bool = False) -> dict:
    """A separate run of ``n_nulls`` sealed nulls of a rig's harness (goal G1 asks for the
    false-alarm rate over >= 1000 nulls per design), published as section ``key`` of ``out``.
    ``label`` names the design and what each case draws; ``reuse``: see :func:`blind_suite`.
    Returns the score."""
    _, s, t_gen, t_run = blind_suite(harness, work, n_nulls, seed=seed, design=design,
                                     desc="nulls", null_fraction=1.0, reuse=reuse)
    gen = (f"generated in {t_gen:.0f} s" if t_gen is not None
           else "the cases of an earlier run with this seed, kept and reused")
    lines = [f"## {title}", "", machine_line(), "",
             f"{n_nulls} sealed nulls on {label} (seed {seed}), {gen}, "
             f"diagnosed in {t_run:.0f} s (median {s['median_diagnose_s']:.2f} s per case): "
             "verdict not no-gap at alpha 0.05 (weighted BH over map + library): "
             f"{far_text(s)}; goal G1: [0.03, 0.06]."]
    publish(out, key, lines)
    return s


def diagnose_suite(harness, work, design, desc: str, name: str = "results.json",
                   prior: str | None = None):
    """Diagnose the sealed cases in ``work`` under ``design`` (a progress bar) with the
    Bayes-factor ``prior``, keep the results as ``name``; returns ``(results, seconds)``."""
    import json
    import time
    from pathlib import Path

    from tqdm import tqdm

    n = len(list(Path(work).glob("case_*.nc")))
    bar = tqdm(total=n, desc=desc, unit="case")
    t0 = time.perf_counter()
    results = harness.run(work, design=design, progress=lambda i, n: bar.update(1), prior=prior)
    bar.close()
    t_run = time.perf_counter() - t0
    with open(os.path.join(work, name), "w") as fh:
        json.dump(results, fh)
    return results, t_run


LOCATED_WORDS = ("; located: the centre of the window of one grid step either side holding the "
                 "most posterior mass, the Bayes decision for G8's within-one-window rule")


def crb_text(r) -> str:
    """The Cramér-Rao reference of a G8 onset rate (``g8_step_onset_crb``), or nothing."""
    if not r:
        return ""
    return (f"; an efficient estimator's rate on the same cases, from each onset's Cramér-Rao "
            f"deviation (truth side; the nominal parameters and the step's sizes as nuisance) "
            f"{r['rate']:.2f} (n={r['n']}): a local bound, blind to errors far from the truth")


def decay_crb_text(r) -> str:
    """What the record says of a decay time at all (``g8_transient_decay_crb``), or nothing."""
    if not r:
        return ""
    return (f" (the truth side's Cramér-Rao deviation of the decay time, in log time, within one "
            f"grid step in {r['resolved']:.2f} of the cases, median {r['median_ratio']:.2g} "
            f"steps, n={r['n']}" + (": mostly the record does not place a decay time to one "
                                     "step, and the rate is held up by the grid's range"
                                     if r["resolved"] < 0.5 else "") + ")")


def onset_text(g8: dict, ts, n_train: int, digits: int = 1) -> str:
    """G8's onset rate in words: the tolerance (5 % of the record ``ts``, in minutes), the rate,
    the onset grid's size and the Cramér-Rao reference."""
    from gyrojax.diagnose._signatures import onset_grid

    minutes = (ts[-1] - ts[0]) / 60
    return (f"onset within 5 % of the record ({0.05 * minutes:.{digits}f} min) of the truth: "
            f"located {fmt_rate(g8.get('g8_step_onset_located'))}, at the largest score "
            f"{fmt_rate(g8['g8_step_onset'])} (onset grid: one value every 5 % of the record over "
            f"the train span, {len(onset_grid(ts, n_train))} values{LOCATED_WORDS}"
            f"{crb_text(g8.get('g8_step_onset_crb'))})")


def g8_suite(harness, work, n_cases: int, *, seed: int, design, families,
             prior: str | None = None):
    """goal G8 on ``n_cases`` more sealed cases of ``families`` (no nulls, lambda 32/64) in
    ``work/g8``: generated, diagnosed (with the Bayes-factor ``prior``) and scored by
    ``harness.localisation_scores``. Returns ``(scores, seconds)``."""
    import time

    g8_dir = os.path.join(work, "g8")
    t0 = time.perf_counter()
    harness.generate(g8_dir, n_cases, seed=seed, design=design, null_fraction=0.0,
                     lambdas=(32.0, 64.0), families=families)
    results, _ = diagnose_suite(harness, g8_dir, design, "g8", prior=prior)
    return harness.localisation_scores(g8_dir, results), time.perf_counter() - t0


def g8_line(harness, args, work, design, *, step: str, decay_grid: str, digits: int = 1) -> str:
    """goal G8 on ``args.g8_cases`` more sealed cases (the ``step`` family and the drift
    transient at lambda 32/64, :func:`g8_suite`): onset and decay time at the largest score
    against the truth. ``decay_grid``: the transient's grid in words."""
    g8, secs = g8_suite(harness, work, args.g8_cases, seed=args.seed + 3, design=design,
                        families=(step, "drift_transient"),
                        prior=getattr(args, "prior", None))
    return (f"- Localisation (goal G8: onsets within 5 % of the record in >= 0.90 at lambda "
            f">= 32; {args.g8_cases} more sealed cases, {step} and drift_transient at "
            f"lambda 32/64, seed {args.seed + 3}, generated and diagnosed in {secs:.0f} s): "
            f"{step} {onset_text(g8, design.ts, design.n_train, digits)}; drift_transient decay "
            f"time within one step of its grid ({decay_grid}): located "
            f"{fmt_rate(g8.get('g8_transient_decay_located'))}, at the largest score "
            f"{fmt_rate(g8['g8_transient_decay'])}"
            f"{decay_crb_text(g8.get('g8_transient_decay_crb'))}.")


def g6_lines(s: dict, hidden: str) -> list[str]:
    """The closed-loop bullets of goal G6 from :func:`gyrojax.validation._harness.
    closed_loop_scores` (``hidden``: how the text names the hidden effect)."""
    by = "; ".join(f"{e} {fmt_rate(r)}" for e, r in s["resolved_by_effect"].items())
    return [f"- {hidden} flagged (not visible on the record's own design): "
            f"{fmt_rate(s['hidden_flagged'])}; advised design(s) for it: "
            f"{' / '.join(s['advised_designs'])}; the largest predicted MDE there, with the "
            f"closest rival fitted: {s['max_mde_hidden']:.3g} of the prior scale.",
            f"- goal G6 (>= 0.90 of flagged effects with a resolving design get an advised "
            f"design with MDE <= prior scale): flagged effects whose first-ranked design "
            f"resolves them (MDE with the closest rival <= prior scale) "
            f"{fmt_rate(s['resolved'])}; by effect: {by}. The ranking puts a resolving design "
            "first wherever the catalogue has one: a case left unresolved has none among these "
            "designs (so over the flagged effects that have one, the goal's rate is 1.00).",
            f"- Closed loop (G6: class-level top-1 >= 0.90 at prior-scale magnitude): on the "
            f"record's own design the first effect is {hidden} {fmt_rate(s['top1_own'])} "
            f"(attributed to it alone {fmt_rate(s['attributed_own'])}); on the advised design "
            f"{fmt_rate(s['top1_advised'])} (attributed to it alone "
            f"{fmt_rate(s['attributed_advised'])}); over the cases whose advised design "
            f"resolves it (the goal's cases) {fmt_rate(s['top1_advised_resolving'])}.",
            z_line(s["z_advised"], f"{hidden}'s refit coefficients on the advised design")]


def z_line(z, what: str) -> str:
    """How well reported standard errors match the errors against the sealed truth."""
    z = np.asarray(z, dtype=float)
    if z.size == 0:
        return f"- {what}: none refitted."
    return (f"- {what}, error against the sealed truth in reported standard errors (n={z.size} "
            f"coefficients): RMS {np.sqrt(np.mean(z ** 2)):.2f}, |z| < 2 in "
            f"{np.mean(np.abs(z) < 2):.2f} (a calibrated error: RMS 1, 0.95).")
