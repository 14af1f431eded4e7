"""``gyrojax simulate|fit|observability --rig schuler``: the platform INS Schuler test.

Record channels ``V1 V2`` (model velocities, m/s) and ``rot1 rot2 rot3`` (platform rotation since
t0 from the gimbal angles, rad); conditions as record attributes (``latitude_deg``, ``v10``,
``v20``, ``azimuth0_deg``, ``g``). Reports in deg/h, ppm, m/s^2 and arcmin.
"""

from __future__ import annotations

import numpy as np

from ._cli_base import (
    AbstractRigCommands,
    UsageError,
    emit_json,
    load,
    misfit_note,
    parse_sets,
    with_latitude,
)
from .record import sample_noise, sample_times

CHANNELS = ("V1", "V2", "rot1", "rot2", "rot3")


def _conditions(args, record=None):
    """``(conditions, latitude)``: the record's (``--latitude`` over its own), or the test's
    defaults at ``--latitude``."""
    from .models.schuler import SchulerConditions

    if record is None:
        lat = 55.57 if args.latitude is None else float(args.latitude)
        return SchulerConditions.create(lat), lat
    record = with_latitude(args, record)
    return (SchulerConditions.from_record(record),
            float(record.conditions.get("latitude_deg", 55.57)))


def _noise(args):
    from . import units

    if args.sigma_v <= 0 or args.sigma_arcmin <= 0:
        raise ValueError(f"--sigma-v {args.sigma_v} m/s and --sigma-arcmin {args.sigma_arcmin} "
                         "must be > 0")
    return args.sigma_v, args.sigma_arcmin * units.ARCMIN


def _duration(args, cond):
    if args.periods is None or not args.periods > 0:
        raise ValueError(f"--periods {args.periods} must be > 0 (test length in Schuler periods)")
    if not args.sample > 0:
        raise ValueError(f"--sample {args.sample} s must be > 0")
    return args.periods * float(cond.schuler_period)


def simulate(args):
    import jax

    from .io import record_path, save_record
    from .models.schuler import EFFECT_NAMES, PARAM_NAMES, SchulerRig, add_measurement_noise
    from .record import BenchRecord, freeze
    from .simulate import integrate

    rig = SchulerRig()
    cond, lat = _conditions(args)
    span = _duration(args, cond)
    sigma_v, sigma_theta = _noise(args)
    space = rig.param_space
    key_theta, key_noise = jax.random.split(jax.random.key(args.seed))
    if args.random_errors:  # draw theta ~ N(0, prior) (docs/rigs/schuler.md), then apply --set overrides
        draw = jax.random.normal(key_theta, (len(PARAM_NAMES),))
        given = {n: float(space[n].scale * d) for n, d in zip(PARAM_NAMES, draw, strict=True)}
    else:
        given = {}
    sets = parse_sets(args.set, space)  # the 12 errors, or an unmodelled effect's parameters
    params = space.make(given | sets)
    shown = PARAM_NAMES + tuple(n for n in EFFECT_NAMES if n in sets)
    ts = sample_times(span, args.sample, span=f"--periods {args.periods:g}",
                      sample=f"--sample {args.sample:g}")
    out = record_path(args.out)  # ValueError: exit 2
    y = add_measurement_noise(key_noise, integrate(rig, params, cond, ts), sigma_v=sigma_v,
                              sigma_theta=sigma_theta)
    attrs = {"rig": "schuler", "latitude_deg": lat, "v10": float(cond.v10),
             "v20": float(cond.v20), "azimuth0_deg": 0.0, "g": float(cond.g),
             "sigma_v": sigma_v, "sigma_arcmin": args.sigma_arcmin, "seed": args.seed}
    save_record(BenchRecord(ts, y, CHANNELS, freeze(attrs)), out, units=rig.CHANNEL_UNITS)
    print(f"wrote {out}: {ts.size} samples over {span / 60:.1f} min ({args.periods} Schuler "
          f"periods of {float(cond.schuler_period) / 60:.3f} min), latitude {lat} deg")
    print(space.table(params, names=shown))
    emit_json({"record": str(out), "samples": int(ts.size),
               "parameters": space.display_json(params, shown)}, args.json)


def _channels_text(x, first=0):
    """Per-channel levels as shown: velocities in m/s, attitude in arcmin."""
    from . import units

    return ", ".join(f"{CHANNELS[i]} {v:.3g} m/s" if i < 2 else
                     f"{CHANNELS[i]} {v / units.ARCMIN:.3g} arcmin"
                     for i, v in enumerate(x, start=first))


def fit(args):
    from .estimate.schuler import fit_schuler, schuler_filter
    from .models.schuler import SchulerRig, schuler_period

    rec = load(args, CHANNELS)
    rig = SchulerRig()
    cond, lat = _conditions(args, rec)
    sigma_v, sigma_theta = _noise(args)
    ts, y = np.asarray(rec.t), np.asarray(rec.y)
    if args.method == "kalman":
        est, _ = schuler_filter(rig, ts, y, cond, sigma_v=sigma_v, sigma_theta=sigma_theta)
    elif args.method == "gauss-newton":
        est = fit_schuler(rig, ts, y, cond, sigma_v=sigma_v, sigma_theta=sigma_theta)
    else:
        raise ValueError(f"--method {args.method!r}: the Schuler rig has 'gauss-newton' (iterated, "
                         "recommended) and 'kalman' (the source's single pass)")
    periods = [schuler_period(ts, y[:, i], conditions=cond) for i in (0, 1)]
    print(f"# Schuler test {args.record}: {ts.size} samples, {(ts[-1] - ts[0]) / 60:.1f} min, "
          f"latitude {lat} deg, method {args.method}")
    print(f"pass/fail: period {periods[0]['period_min']:.3f} min (V1), "
          f"{periods[1]['period_min']:.3f} min (V2); theory {periods[0]['theoretical_min']:.3f} min")
    print(est.table())
    if args.method == "gauss-newton":
        print(f"converged: {bool(est.converged)} ({int(est.iterations)} iterations; the last "
              f"step: {float(est.last_step_se):.2g} standard errors)")
    rms, noise = np.asarray(est.residual_rms), sample_noise(y)
    print(f"residual RMS {_channels_text(rms)}; the record's sample-to-sample noise "
          f"{_channels_text(noise)}")
    worst = int(np.argmax(rms / noise))
    ratio, worst_noise = float(rms[worst] / noise[worst]), _channels_text(noise[worst:worst + 1], worst)
    note = misfit_note(ratio, f"{worst_noise}, the worst channel",
                       "its units (SI: t in s, V1 V2 in m/s, rot1-3 in rad) and the latitude "
                       f"(deg; {lat:g} used)", args.record, "schuler")
    if note and args.method == "kalman":  # the single pass stops short of the fit at prior-scale
        # errors (15-20x the noise on records the iterated fit meets at 1x)
        note = (f"note: the single pass leaves a residual {ratio:.3g} times the record's "
                f"sample-to-sample noise ({worst_noise}): linearised about zero errors it stops "
                "short of the fit; --method gauss-newton iterates it, and tells a record the "
                "model does not describe")
    if note:
        print(note)
    space = rig.param_space
    emit_json({"rig": "schuler", "method": args.method, "latitude_deg": lat,
               "period_min": [p["period_min"] for p in periods],
               "theoretical_period_min": periods[0]["theoretical_min"],
               "iterations": int(est.iterations), "converged": bool(est.converged),
               "last_step_se": float(est.last_step_se),
               "residual_rms": dict(zip(CHANNELS, rms.tolist(), strict=True)),
               "sample_noise": dict(zip(CHANNELS, noise.tolist(), strict=True)),
               "residual_rms_unit": "m/s for V1 V2, rad for rot1-3",
               "parameters": {n: {"value": float(space[n].to_display(v)),
                                  "stderr": float(space[n].to_display(s)),
                                  "unit": space[n].display_unit}
                              for n, v, s in zip(est.names, est.values, est.stderr, strict=True)},
               "correlation": np.asarray(est.correlation()).tolist()}, args.json)


def observability(args):
    from .analysis.schuler import schuler_observability
    from .models.schuler import SchulerRig

    rig = SchulerRig()
    cond, lat = _conditions(args)
    span = _duration(args, cond)
    sigma_v, sigma_theta = _noise(args)
    rep = schuler_observability(rig, cond, span, dt=args.sample, sigma_v=sigma_v,
                                sigma_theta=sigma_theta, channels=args.channels)
    print(rep.table())
    print("least-informed directions (Fisher eigenvalue in prior units):")
    for w, comb in rep.weakest_directions(3):
        print(f"  {w:9.3g}  {comb}")
    space = rig.param_space
    emit_json({"rig": "schuler", "latitude_deg": lat, "duration_min": span / 60,
               "channels": args.channels, "rank": rep.rank, "condition": rep.condition,
               "crlb": {n: {"value": float(space[n].to_display(s)), "unit": space[n].display_unit}
                        for n, s in zip(rep.names, rep.crlb, strict=True)},
               "weak_pairs": [[a, b, c] for a, b, c in rep.weak_pairs()]}, args.json)


class SchulerCommands(AbstractRigCommands):
    """The Schuler test's commands."""

    name = "schuler"
    COMMANDS = ("simulate", "fit", "observability", "diagnose")
    ELSEWHERE = "gyrojax simulate, fit, observability or diagnose --rig schuler"

    def add_arguments(self, command, group):
        if command in ("simulate", "observability"):
            group.add_argument("--periods", type=float, default=1.0,
                               help="schuler: test length in Schuler periods of 84.4 min "
                                    "(default 1)")
        if command in ("simulate", "fit", "observability"):
            group.add_argument("--sigma-v", type=float, default=0.05,
                               help="schuler: model-velocity noise in m/s (default 0.05)")
            group.add_argument("--sigma-arcmin", type=float, default=1.0,
                               help="schuler: gimbal-angle noise in arcmin per axis (default 1)")
        if command == "simulate":
            group.add_argument("--random-errors", action="store_true",
                               help="schuler: draw the 12 errors from their priors (docs/rigs/schuler.md), "
                                    "then apply --set")
        if command == "observability":
            group.add_argument("--channels", default="all", choices=["all", "velocity"],
                               help="schuler: measurements used (all, or the classical test's "
                                    "velocities)")

    def simulate(self, args):
        args.sample = 1.0 if args.sample is None else args.sample
        simulate(args)

    def fit(self, args):
        args.method = args.method or "gauss-newton"
        fit(args)

    def observability(self, args):
        args.sample = 1.0 if args.sample is None else args.sample
        observability(args)

    def load(self, args):
        return with_latitude(args, load(args, CHANNELS))

    def noise_std(self, args):
        if args.noise_arcsec is not None:
            raise UsageError("--noise-arcsec is for the esg rig; the schuler rig estimates the "
                             "velocity and attitude noise from the record")
        return None
