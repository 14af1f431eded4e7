"""The ``gyrojax`` command: simulate, fit, observability, montecarlo, diagnose, effects, observer,
demo.

Engineering units at this edge (deg/h, arcsec, deg); SI inside. Bad input prints one line naming
the field, the value and the fix, and exits with status 2. ``--json FILE`` writes machine-readable
output atomically; ``--json -`` prints it.

``simulate``, ``fit``, ``observability``, ``diagnose`` and ``effects`` dispatch through the rig
registry (:mod:`gyrojax.rigs`): each rig's commands class
(:class:`~gyrojax._cli_base.AbstractRigCommands`) adds its own options, in a group of its own,
and does the work; an option of another rig's is refused by name.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from . import rigs
from ._cli_base import (
    EXIT_USAGE,
    AbstractRigCommands,
    UsageError,
    check_outputs,
    emit_json,
    load,
    parse_sets,
    stage_printer,
    write_outputs,
)
from ._cli_esg import rig_and_conditions
from .io import json_writer

__all__ = ["AbstractRigCommands", "UsageError", "build_parser", "emit_json", "load", "main",
           "parse_sets"]

# the commands a rig serves through its commands class, and the rigs' own studies
DISPATCHED = ("simulate", "fit", "observability", "diagnose")
STUDIES = ("montecarlo", "demo", "observer")


def _commands(args):
    """The commands object of ``--rig`` (a usage error for an unknown rig or a command it does
    not serve, before any record is read)."""
    entry = rigs.get(args.rig)  # ValueError (exit 2): names the rigs
    commands = entry.commands_object()
    if args.command not in commands.COMMANDS:
        raise commands.refuse(args.command)
    return commands


# -- commands ------------------------------------------------------------------------------
def cmd_simulate(args):
    _commands(args).simulate(args)


def cmd_fit(args):
    _commands(args).fit(args)


def cmd_observability(args):
    _commands(args).observability(args)


def cmd_montecarlo(args):
    import jax

    from .analysis.mounting import mounting_budget_stats, mounting_error_tables
    from .io import atomic_write

    lat = args.latitude if args.latitude is not None else 55.75
    if args.study == "tables":
        tab = mounting_error_tables(lat)
        print(f"# Tables 2 and 3 (latitude {lat} deg, drifts 0.01, Euler dchi = 1', theta = 10')")
        print(tab.markdown())
        emit_json(tab.to_json(), args.json)
    else:
        if args.draws < 1:
            raise UsageError(f"--draws {args.draws} must be >= 1")
        if args.chunk_size < 1:
            raise UsageError(f"--chunk-size {args.chunk_size} must be >= 1 (draws per compiled "
                             "block; default 128)")
        if not np.isfinite(args.noise_arcsec) or args.noise_arcsec < 0:
            raise UsageError(f"--noise-arcsec {args.noise_arcsec} must be >= 0")
        scheduler = args.scheduler
        if args.processes is not None:
            if scheduler is not None:
                raise UsageError("--processes and --scheduler: give one (--scheduler local runs "
                                 "one worker per core)")
            if args.processes != "all" and (not args.processes.isdigit()
                                            or int(args.processes) < 1):
                raise UsageError(f"--processes {args.processes!r}: give a number of worker "
                                 "processes >= 1 or 'all' (one per CPU core)")
            scheduler = "local" if args.processes == "all" else f"local:{int(args.processes)}"
        bud = mounting_budget_stats(jax.random.key(args.seed), args.draws, lat,
                                    noise_arcsec=args.noise_arcsec, alpha20_deg=args.alpha20,
                                    block_size=args.chunk_size, scheduler=scheduler,
                                    resume=args.resume, progress=True)
        print(f"# Monte Carlo error budget: {args.draws} draws per scheme, dchi ~ N(0, 1'), "
              f"theta ~ N(0, 10'), noise {args.noise_arcsec}\", alpha2(0) = {args.alpha20} deg; "
              "RMS drift error ± its standard error, deg/h")
        if bud.stats.nonfinite:
            print(f"warning: {bud.stats.nonfinite} draws gave non-finite errors and are left out",
                  file=sys.stderr)
        print(bud.markdown())
        emit_json(bud.to_json(), args.json)
        if args.netcdf:
            ds = bud.to_xarray()
            atomic_write(args.netcdf, lambda tmp: ds.to_netcdf(tmp, engine="h5netcdf"))
        if args.plot:
            from .plots import plot_budget

            plot_budget(bud, args.plot)


def cmd_effects(args):
    from . import rigs

    entry = rigs.get(args.rig)  # ValueError (exit 2): names the rigs
    space = entry.model_class().param_space
    nominal = ", ".join(space.nominal_names()) or "none outside the groups below"
    print(f"rig {args.rig}: ungrouped nominal parameters: {nominal}")
    for e in space.effects:
        ps = [space[n] for n in space.effect_names(e)]
        print(f"  {e}: " + ", ".join(f"{p.name} [{p.display_unit}, null {p.to_display(p.null):g}]"
                                     for p in ps))
    lib = entry.catalogue() if entry.problem else {}
    if lib:
        print(f"diagnosis catalogue (gyrojax diagnose --rig {args.rig}): "
              + ", ".join(f"{k} ({v})" for k, v in lib.items()))
    if entry.problem and entry.problem_class.CATALOGUE_NOTE:
        print(entry.problem_class.CATALOGUE_NOTE)
    emit_json({"rig": args.rig, "nominal": list(space.nominal_names()),
                "effects": {e: list(space.effect_names(e)) for e in space.effects},
                "diagnosis_catalogue": lib}, args.json)


def cmd_demo(args):
    """Fit the built-in example record: regression, Gauss-Newton, Kalman; observability; then
    diagnose the nominal model's gap on it (the record hides a base misalignment)."""
    from .analysis.observability import observability
    from .estimate import fit
    from .io import load_record

    path = Path(__file__).parent / "data" / "esg_equatorial_24h.csv"
    meta = json.loads(path.with_suffix(".json").read_text())
    rec = load_record(path, conditions={"scheme": meta["scheme"],
                                        "latitude_deg": meta["latitude_deg"]})
    rig, cond, scheme, lat = rig_and_conditions(
        argparse.Namespace(scheme=None, latitude=None, base_param="eps"), rec)
    space = rig.param_space
    truth = {k: space[k].from_display(v["value"]) for k, v in meta["parameters"].items()}
    print(f"# gyrojax demo: built-in record {path.name} ({rec.n_samples} samples, 24 h, "
          f"scheme {scheme}, latitude {lat} deg, 1 arcsec noise)")
    effects = ("base_misalignment",)
    if args.plot:  # a bad figure name fails now, not after the fits
        from .plots import figure_format

        figure_format(args.plot)
    summary, fits = {}, {}
    for method in ("regression", "gauss-newton", "kalman"):
        rep = fits[method] = fit(rig, rec, cond, effects=effects, method=method)
        print(f"\n## {method}: residual RMS {rep.to_json()['residual_rms_arcsec']:.3f} arcsec")
        print(f"{'parameter':<10} {'estimate':>12} {'stderr':>10} {'truth':>12} {'error':>10}  unit")
        for n in rep.free:
            if n not in truth and not n.startswith("alpha"):
                continue
            p = space[n]
            tv = truth.get(n, None)
            est = float(p.to_display(rep.params[n]))
            se = rep.stderr.get(n)
            se = float(p.to_display(se)) if se is not None else float("nan")
            tvd = float(p.to_display(tv)) if tv is not None else float("nan")
            print(f"{n:<10} {est:12.5f} {se:10.2g} {tvd:12.5f} {est - tvd:10.2g}  {p.display_unit}")
        summary[method] = rep.to_json()
    rep = observability(rig, space.make(truth), cond, rec.t,
                        free=("alpha10", "alpha20", *rig.regression_names))
    print("\n## observability of drift + rotor tilt + base misalignment in this test")
    print(rep.summary())
    summary["observability"] = rep.to_json()
    from .diagnose import diagnose

    print("\n## sim-to-real diagnosis: the nominal model (drifts only) against this record")
    gap = diagnose(rec, progress=stage_printer("demo"))
    print(gap.markdown())
    summary["diagnosis"] = gap.to_json()
    v = gap.verdict
    after = v.get("heldout_gap_after")
    print(f"\ndiagnosis verdict: {v['kind']} ({', '.join(v.get('effects') or []) or '-'}); "
          f"held-out gap {v['heldout_gap_before']:.3g} -> "
          f"{'-' if after is None else f'{after:.3g}'} (0 = model and data agree)")
    head = gap.verdict.headline()
    if head:
        print(head)
    if args.json == "-":
        emit_json(summary, "-")
    outputs = [(args.json if args.json != "-" else None, json_writer(summary))]
    if args.plot:
        from .plots import figure_writer, plot_fit, plot_gap_report

        gap_plot = _gap_figure_path(args.plot)
        outputs += [(args.plot, figure_writer(plot_fit(rig, rec, cond, fits["gauss-newton"]),
                                              args.plot)),
                    (gap_plot, figure_writer(plot_gap_report(gap), gap_plot))]
    write_outputs(outputs)  # every output or none
    if args.plot:
        print(f"{gap_plot}: the diagnosis (gap map, residuals before and after, ranking)")


def _gap_figure_path(path) -> Path:
    """The demo's diagnosis figure beside its fit figure: ``demo.png`` -> ``demo_gap.png``."""
    path = Path(path)
    return path.with_name(f"{path.stem}_gap{path.suffix}")


def cmd_observer(args):
    from .analysis.vibration import compensation_monte_carlo, frequency_study
    from .models.gyrotheodolite import GyrotheodoliteConditions, GyrotheodoliteRig

    for w0 in args.omega0:
        if not np.isfinite(w0) or w0 <= 0:
            raise UsageError(f"--omega0 {w0}: observer pole magnitudes must be > 0 (1/s)")
    rig = GyrotheodoliteRig()
    params = rig.default_params(**{"kappa": args.kappa, **parse_sets(args.set, rig.param_space)})
    cond = GyrotheodoliteConditions.create(args.latitude)
    study = frequency_study(rig, params, cond, args.omega0)
    rows = study.table(level=args.level)
    print(f"gyrotheodolite observer, all poles at -omega0; latitude {args.latitude} deg, "
          f"kappa {args.kappa:g}; gains from the corrected closed form (docs/rigs/gyrotheodolite.md)")
    print(f"{'omega0':>8} {'k1 [1/s]':>12} {'k2 [1/s^2]':>12} {'k3 [1/s]':>12} {'k4 [1/s^2]':>12}"
          f"  {'max|p+w0|/w0':>12}  {int(args.level * 100)}% band [rad/s]: rate  amplitude")
    fmt = lambda x: "   none" if x is None else f"{x:7.3g}"  # noqa: E731
    for r in rows:
        print(f"{r['omega0']:8g} {r['k1']:12.5g} {r['k2']:12.5g} {r['k3']:12.5g} {r['k4']:12.5g}"
              f"  {r['max_pole_offset_rel']:12.1e}  {fmt(r['bandwidth']):>21} "
              f"{fmt(r['amplitude_bandwidth']):>10}")
    out = {"rig": "gyrotheodolite", "latitude_deg": args.latitude, "kappa": args.kappa,
           "level": args.level, "observers": rows}
    if args.compensation:
        import jax

        out["compensation"] = {}
        print("\ncompensation of the constant vibration error (docs/rigs/gyrotheodolite.md), "
              f"{args.compensation} random vibrations: fraction of the error left (median / p95)")
        for label, r in (("model (1)", rig), ("formula's mechanism only", GyrotheodoliteRig(
                vibration_torque=False))):
            for w0 in args.omega0:
                s = compensation_monte_carlo(r, params, jax.random.key(args.seed),
                                             args.compensation, omega0=w0,
                                             latitude_deg=args.latitude).summary()
                out["compensation"].setdefault(label, []).append(s)
                print(f"  {label:18s} omega0 {w0:7g}: true rate "
                      f"{s['median_residual_true_rate']:.3g} / {s['p95_residual_true_rate']:.3g}, "
                      f"observer {s['median_residual_observer']:.3g} / "
                      f"{s['p95_residual_observer']:.3g}")
    if args.plot:
        from .plots import plot_frequency_study

        plot_frequency_study(study, args.plot)
        print(f"wrote {args.plot}")
    emit_json(out, args.json)


def cmd_diagnose(args):
    from .diagnose import diagnose
    from .diagnose._diagnose import checked_effects

    commands = _commands(args)
    if not 0 < args.alpha < 0.5:
        raise UsageError(f"--alpha {args.alpha}: give a significance level in (0, 0.5)")
    if args.max_effects < 1:
        raise UsageError(f"--max-effects {args.max_effects}: give at least 1")
    if args.null_draws != 0 and args.null_draws < int(round(1 / args.alpha)) - 1:
        raise UsageError(f"--null-draws {args.null_draws}: too few for --alpha {args.alpha}; "
                         f"give 0 (no calibration) or at least {int(round(1 / args.alpha)) - 1}"
                         " (default 499)")
    options = commands.diagnose_options(args)  # checked before the record is read
    noise = commands.noise_std(args)
    effects = None
    if args.effects:
        effects = checked_effects(e.strip() for e in args.effects.split(",") if e.strip())
    record = commands.load(args)
    report = diagnose(record, rig=args.rig, effects=effects, holdout=args.holdout,
                      alpha=args.alpha, noise_std=noise, refit_all=args.refit_all,
                      max_effects=args.max_effects, null_draws=args.null_draws, prior=args.prior,
                      progress=stage_printer("diagnose"), **options)
    print(report.markdown())
    if args.json == "-":
        emit_json(report.to_json(), "-")
    outputs = [(args.json if args.json != "-" else None, json_writer(report.to_json()))]
    if args.plot:
        from .plots import figure_writer, plot_gap_report

        outputs.append((args.plot, figure_writer(plot_gap_report(report), args.plot)))
    write_outputs(outputs)  # the report and its figure, both or neither


# -- parser --------------------------------------------------------------------------------
_RECORD_HELP = ("record file (.nc or .csv; t in s, channels in SI: alpha1 alpha2 in rad for esg, "
                "wx..az for imu, alpha beta gamma ax ay az position amplitude for platform, alpha "
                "in rad for gyrotheodolite); for --rig imu also dataset:NAME (a real record, e.g. "
                "dataset:ln100_pair)")


def _rig_option(p, default="esg"):
    p.add_argument("--rig", default=default,
                   help="rig: " + "; ".join(f"{n} ({rigs.get(n).summary})" for n in rigs.names())
                        + f" (default {default})")


def _rig_groups(p, command) -> dict:
    """Each rig's own options of ``command``, in a group per rig: ``{dest: {rigs}}``, the rigs
    whose option each is."""
    owners: dict = {}
    for name in rigs.names():
        entry = rigs.get(name)
        if entry.commands is None:
            continue
        before = {a.dest for a in p._actions}
        group = p.add_argument_group(f"{name} options")
        entry.commands_object().add_arguments(command, group)
        for action in p._actions:
            if action.dest not in before:
                owners.setdefault(action.dest, set()).add(name)
    return owners


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    ap = argparse.ArgumentParser(prog="gyrojax", description=__doc__.split("\n\n")[0])
    ap.add_argument("--version", action="version", version=f"gyrojax {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    owners = {}

    p = sub.add_parser("demo", help="fit and diagnose the built-in example record (the main job)")
    p.add_argument("--plot", metavar="FILE",
                   help="save the fit's trajectory/residual figure (.png, .pdf or .svg) and "
                        "the diagnosis' figure beside it (FILE_gap: gap map, residuals before "
                        "and after, ranking)")
    p.add_argument("--json", metavar="FILE", help="write the fits, observability and diagnosis")
    p.set_defaults(func=cmd_demo, rig="esg")

    p = sub.add_parser("simulate", help="simulate a bench test to a record file")
    _rig_option(p)
    p.add_argument("--out", required=True, help="output record (.nc or .csv)")
    p.add_argument("--latitude", type=float,
                   help="test-site latitude in degrees North (default: the rig's)")
    p.add_argument("--hours", type=float,
                   help="test length in h (default 24 for esg, 0.667 for gyrotheodolite)")
    p.add_argument("--sample", type=float,
                   help="sampling interval in s (default 60 for esg, 1 for schuler and "
                        "gyrotheodolite, 0.01 for imu)")
    p.add_argument("--noise-arcsec", type=float,
                   help="white angle-noise std in arcsec (default 1)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="parameter in display units, repeatable (m11=0.15 deg/h, theta1=600 arcsec,"
                        " eps2=60 arcsec ...; imu: sax=500 ppm, maxy=1 mrad, bgx=10 deg/h ...); "
                        "defaults: esg drifts of +-0.15 deg/h, imu biases of 3-10 deg/h and "
                        "2-5 mg")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed for the noise (default 0)")
    p.add_argument("--json", metavar="FILE", help="write machine-readable output ('-' = stdout)")
    owners["simulate"] = _rig_groups(p, "simulate")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("fit", help="identify drift (and effects) from a record; calibrate an IMU")
    p.add_argument("record", help=_RECORD_HELP)
    _rig_option(p)
    p.add_argument("--latitude", type=float,
                   help="test-site latitude in degrees North (default: from the record)")
    p.add_argument("--effects", default="",
                   help="comma-separated effects to estimate: rotor_tilt, base_misalignment, "
                        "drift_transient (default none)")
    p.add_argument("--method", default=None,
                   choices=["regression", "gauss-newton", "levenberg-marquardt", "kalman", "joint",
                            "s21"],
                   help="estimator (esg and schuler: default gauss-newton; platform: joint "
                        "regression of all amplitudes (default), s21 (the source's two-amplitude "
                        "resolution), kalman (the source's EKF) or gauss-newton; imu: the "
                        "multi-position calibration, a Levenberg-Marquardt fit of |f| = g over "
                        "the record's static poses and of the turns between them for the gyros; "
                        "RECORD may be dataset:NAME)")
    p.add_argument("--noise-arcsec", type=float,
                   help="the known angle noise (esg): the filter's measurement noise with "
                        "--method kalman; with gauss-newton / levenberg-marquardt the standard "
                        "errors are taken at it instead of at the residual's estimate (both are "
                        "in the JSON); not used by --method regression (default: estimated)")
    p.add_argument("--json", metavar="FILE", help="write machine-readable output ('-' = stdout)")
    owners["fit"] = _rig_groups(p, "fit")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("observability", help="which parameters a test design can identify")
    _rig_option(p)
    p.add_argument("--latitude", type=float,
                   help="test-site latitude in degrees North (default: the rig's)")
    p.add_argument("--hours", type=float, help="test length in h (default 24; esg)")
    p.add_argument("--sample", type=float,
                   help="sampling interval in s (default 60 for esg, 1 for schuler)")
    p.add_argument("--json", metavar="FILE", help="write machine-readable output ('-' = stdout)")
    owners["observability"] = _rig_groups(p, "observability")
    p.set_defaults(func=cmd_observability)

    p = sub.add_parser("montecarlo", help="mounting-error tables and Monte Carlo error budgets")
    p.add_argument("--rig", default="esg", help="rig name (default esg)")
    p.add_argument("--study", default="tables", choices=["tables", "budget"],
                   help="tables: the paper's Tables 2-3; budget: random mounting errors")
    p.add_argument("--latitude", type=float, help="latitude in deg North (default 55.75)")
    p.add_argument("--draws", type=int, default=1000, help="draws per scheme (budget)")
    p.add_argument("--noise-arcsec", type=float, default=1.0, help="angle noise (budget)")
    p.add_argument("--alpha20", type=float, default=30.0,
                   help="initial alpha2 in deg (budget; default 30, where all parameters are "
                        "observable in the equatorial scheme)")
    p.add_argument("--chunk-size", type=int, default=128,
                   help="draws per compiled block, the unit of work (budget; default 128)")
    p.add_argument("--scheduler", metavar="ADDRESS|local",
                   help="run the budget's blocks on Dask: 'local' starts one worker process per "
                        "CPU core, an address (tcp://...) uses a running cluster (default: this "
                        "process only); the statistics are the same bit for bit")
    p.add_argument("--processes", metavar="N|all",
                   help="a local Dask cluster of N worker processes ('all': one per CPU core)")
    p.add_argument("--resume", metavar="FILE",
                   help="keep each finished block's statistics in FILE and skip those already "
                        "there (an interrupted budget resumes)")
    p.add_argument("--netcdf", metavar="FILE",
                   help="write the statistics as a NetCDF dataset (fit x scheme x parameter)")
    p.add_argument("--plot", metavar="FILE", help="save the budget's bar chart (.png, .pdf, .svg)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed")
    p.add_argument("--json", metavar="FILE", help="write results ('-' = stdout)")
    p.set_defaults(func=cmd_montecarlo)

    p = sub.add_parser("observer", help="observer gains, poles and bandwidths (gyrotheodolite)")
    p.add_argument("--rig", default="gyrotheodolite", help="rig name (default gyrotheodolite)")
    p.add_argument("--omega0", type=float, nargs="+", default=[1.0, 10.0, 100.0, 1000.0],
                   help="observer pole magnitudes in 1/s (default 1 10 100 1000)")
    p.add_argument("--latitude", type=float, default=50.45, help="latitude in deg (default 50.45)")
    p.add_argument("--kappa", type=float, default=0.0, help="relative compensation gain (default 0)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="rig parameter in SI (H=0.1, J_y=1e-3 ...), repeatable; defaults: the "
                        "assumed set of docs/rigs/gyrotheodolite.md")
    p.add_argument("--level", type=float, default=0.1,
                   help="relative rate-estimate error defining the bandwidth (default 0.1)")
    p.add_argument("--compensation", type=int, default=0, metavar="DRAWS",
                   help="also run the vibration-compensation Monte Carlo with DRAWS draws")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed (compensation)")
    p.add_argument("--plot", metavar="FILE", help="save the Fig. 1 comparison (.png, .pdf or .svg)")
    p.add_argument("--json", metavar="FILE", help="write results ('-' = stdout)")
    p.set_defaults(func=cmd_observer)

    p = sub.add_parser("diagnose", help="sim-to-real gap: where, which effect, how much")
    p.add_argument("record", help=_RECORD_HELP)
    _rig_option(p)
    p.add_argument("--latitude", type=float,
                   help="test-site latitude in degrees North (default: from the record)")
    p.add_argument("--effects", default="",
                   help="comma-separated library to screen (default: the rig's whole catalogue, "
                        "as gyrojax effects --rig NAME lists it; imu with --per-coefficient also "
                        "single coefficients, e.g. g_sensitivity:gsxy; platform with "
                        "--nominal-terms: every coefficient left out, e.g. D_ii_y, instead of "
                        "anisoelastic_oo)")
    p.add_argument("--holdout", type=float, default=0.25,
                   help="fraction of the record (its end) held out for the before/after gap "
                        "(default 0.25)")
    p.add_argument("--max-effects", type=int, default=3,
                   help="the most catalogued effects one verdict names together, each added "
                        "by its score test after the ones before it are refitted (default 3; "
                        "1: the top effect alone)")
    p.add_argument("--refit-all", action="store_true",
                   help="also refit every other catalogued effect, so each candidate carries "
                        "its held-out gap after and reduction (the verdict is unchanged)")
    p.add_argument("--noise-arcsec", type=float,
                   help="angle noise std in arcsec (default: estimated from the residual)")
    p.add_argument("--alpha", type=float, default=0.05,
                   help="significance level after Benjamini-Hochberg control (default 0.05)")
    p.add_argument("--prior", choices=("design", "shell", "shape", "zellner", "scale"),
                   default=None,
                   help="Bayes-factor prior of the posteriors (default: shell for a catalogue "
                        "of single coefficients (--nominal-terms, --per-coefficient), design "
                        "for effect families; design: Gaussian coefficients expecting "
                        "noncentrality 32; shell: the noncentrality log-uniform over 8 to "
                        "2^24 and never near 0, exact for one-coefficient effects; see "
                        "benchmarks/RESULTS.md)")
    p.add_argument("--null-draws", type=int, default=499,
                   help="residuals drawn from the linearised null to calibrate the BH level to "
                        "a false-alarm rate of exactly --alpha (default 499; 0: plain weighted "
                        "BH at --alpha)")
    p.add_argument("--plot", metavar="FILE",
                   help="gap map, residuals before/after, ranking (.png, .pdf or .svg)")
    p.add_argument("--json", metavar="FILE", help="write machine-readable output ('-' = stdout)")
    owners["diagnose"] = _rig_groups(p, "diagnose")
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("effects", help="list a rig's catalogue of effects")
    _rig_option(p)
    p.add_argument("--json", metavar="FILE", help="write the catalogue")
    p.set_defaults(func=cmd_effects)
    ap.set_defaults(_owners=owners)
    return ap


def _foreign_options(parser, args) -> None:
    """A usage error for a rig option given with another ``--rig``: ``--split is for the
    platform rig; leave it out for --rig esg``."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    command_parser = sub.choices[args.command]
    for dest, owners in args._owners.get(args.command, {}).items():
        if args.rig in owners:
            continue
        if getattr(args, dest) != command_parser.get_default(dest):
            flag = next(a.option_strings[0] for a in command_parser._actions if a.dest == dest)
            raise UsageError(f"{flag} is for the {' and '.join(sorted(owners))} rig; leave it "
                             f"out for --rig {args.rig}")


def main(argv=None) -> int:
    from ._cache import enable_compilation_cache

    enable_compilation_cache()  # a later run loads its compiled fits ($GYROJAX_COMPILATION_CACHE)
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the command whose options they are not, with its usage
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        sub.choices[args.command].error(f"unrecognized arguments: {' '.join(extra)} (see "
                                        f"gyrojax {args.command} --help)")
    try:
        if args.command in DISPATCHED + STUDIES:  # before any record is read
            commands = rigs.get(args.rig).commands_object()
            if args.command not in commands.COMMANDS:
                raise commands.refuse(args.command)
            _foreign_options(parser, args)
        elif args.command == "effects":
            rigs.get(args.rig)
        if getattr(args, "plot", None):  # before the work the figure would show
            from .plots import figure_format

            try:
                figure_format(args.plot)
            except ValueError:
                raise UsageError(f"--plot {args.plot!r}: use a .png, .pdf or .svg file "
                                 "name") from None
        derived = ([("--plot", _gap_figure_path(args.plot))]
                   if args.command == "demo" and args.plot else [])
        check_outputs(args, derived)  # before the work, not after it
        args.func(args)
    except UsageError as exc:
        print(f"gyrojax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as exc:  # validation errors from the library name the field and the fix
        print(f"gyrojax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # output piped into `head` & co.: stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
