"""``gyrojax simulate|fit|observability|diagnose --rig esg``: the non-contact gyro in a two-axis
gyrostabilizer (the default rig).

Record channels ``alpha1 alpha2`` (gimbal angles, rad); conditions ``scheme`` and
``latitude_deg`` as record attributes or ``--scheme`` / ``--latitude``. ``--set`` takes the
rig's parameters in display units (``m11=0.15`` deg/h, ``theta1=600`` arcsec, ``eps2=60``
arcsec ...).
"""

from __future__ import annotations

import jax
import numpy as np

from ._cli_base import (
    AbstractRigCommands,
    UsageError,
    alpha0,
    emit_json,
    load,
    misfit_note,
    parse_sets,
    positive,
)

CHANNELS = ("alpha1", "alpha2")
DEFAULT_DRIFTS = {"m11": 0.15, "m12": -0.15, "m21": 0.15, "m22": -0.075, "mc1": 0.15,
                  "mc2": -0.15}  # deg/h, the simulated record's unless --set


def rig_and_conditions(args, record=None):
    """``(rig, conditions, scheme, latitude)`` from ``--scheme``/``--latitude`` or the record's
    attributes, ``--base-param`` choosing the base misalignment's parametrization."""
    from .models.esg import SCHEMES, ESGConditions, ESGRig

    conds = dict(record.conditions) if record is not None else {}
    scheme = args.scheme or conds.get("scheme")
    lat = args.latitude if args.latitude is not None else conds.get("latitude_deg")
    if scheme is None:
        raise UsageError(f"--scheme is required (one of {', '.join(SCHEMES)}); the record does "
                         "not carry it")
    if scheme not in SCHEMES:
        raise UsageError(f"--scheme {scheme!r} is unknown; use one of {', '.join(SCHEMES)}")
    if lat is None:
        raise UsageError("--latitude DEG is required; the record does not carry latitude_deg")
    lat = float(lat)
    if not -89.0 <= lat <= 89.0:
        raise UsageError(f"--latitude {lat} is outside [-89, 89] deg; give degrees North")
    base = getattr(args, "base_param", None) or "eps"
    rig = ESGRig.for_scheme(scheme, lat, base_param=base)
    return rig, ESGConditions.create(scheme, lat), scheme, lat


def parse_effects(text, rig):
    """``--effects a,b`` checked against the rig's effect groups."""
    if not text:
        return ()
    effects = tuple(e.strip() for e in text.split(",") if e.strip())
    known = rig.param_space.effects
    for e in effects:
        if e not in known:
            raise UsageError(f"--effects: unknown effect {e!r}; this rig has {', '.join(known)}")
    return effects


def sample_times(hours, sample_s):
    """The ESG commands' time grid (a ValueError is a usage error: exit 2)."""
    from .record import sample_times as grid

    return grid(hours * 3600, sample_s, span=f"--hours {hours:g}",
                sample=f"--sample {sample_s:g}")


class ESGCommands(AbstractRigCommands):
    """The ESG rig's commands."""

    name = "esg"
    COMMANDS = ("simulate", "fit", "observability", "diagnose", "montecarlo", "demo")

    def add_arguments(self, command, group):
        if command in ("simulate", "fit", "observability", "diagnose"):
            group.add_argument("--scheme", help="esg: mounting scheme: polar, equatorial, "
                                                "horizontal, vertical (default: from the "
                                                "record's attributes)")
        if command in ("simulate", "fit", "observability"):
            group.add_argument("--base-param", choices=["eps", "eps_free", "rotvec", "euler"],
                               help="esg: base-misalignment parametrization (default eps: "
                                    "eps = u x dchi, normal to u, 2 components)")
        if command in ("simulate", "observability"):
            group.add_argument("--alpha0", type=alpha0,
                               help="esg: initial gimbal angles 'A1,A2' in deg (default 0,0)")
        if command == "observability":
            group.add_argument("--effects", help="esg: effects whose parameters join the drifts "
                                                 "(default rotor_tilt,base_misalignment)")
            group.add_argument("--method", choices=["regression", "trajectory"],
                               help="esg: sensitivity by the regression design A (linear "
                                    "model, the source's check; the default) or the trajectory "
                                    "Jacobian of the exact model")
            group.add_argument("--exact-tol", type=float,
                               help="esg: relative singular value below which a direction is "
                                    "unobservable (default 1e-6)")
            group.add_argument("--weak-tol", type=float,
                               help="esg: relative singular value below which it is weakly "
                                    "observable (default 1e-3)")
        if command == "diagnose":
            group.add_argument("--noise-model", choices=("white", "white+flicker"),
                               help="esg: the gimbal angles' nominal noise model (default "
                                    "white; white+flicker: flicker as a Gauss-Markov sum at "
                                    "--flicker-arcsec, or without it at a level estimated by "
                                    "REML, which costs the slow effects much of their power)")
            group.add_argument("--flicker-arcsec", type=float, metavar="B",
                               help="esg: flicker level, bias-instability coefficient B in "
                                    "arcsec (Allan deviation floor 0.664 B, from the "
                                    "instrument's Allan test); implies --noise-model "
                                    "white+flicker")

    def simulate(self, args):
        from . import units
        from .io import record_path, save_record
        from .simulate import simulate

        hours = 24.0 if args.hours is None else args.hours
        sample = 60.0 if args.sample is None else args.sample
        rig, cond, scheme, lat = rig_and_conditions(args)
        positive("--hours", hours)
        positive("--sample", sample)
        noise = 1.0 if args.noise_arcsec is None else args.noise_arcsec
        if noise < 0:
            raise UsageError(f"--noise-arcsec {noise} must be >= 0")
        ts = sample_times(hours, sample)
        space = rig.param_space
        given = {k: space[k].from_display(v) for k, v in DEFAULT_DRIFTS.items()} | \
            parse_sets(args.set, space)
        a0 = args.alpha0 or [0.0, 0.0]
        params = space.make(given | {"alpha10": a0[0] * units.DEG, "alpha20": a0[1] * units.DEG})
        out = record_path(args.out)  # ValueError: exit 2
        rec = simulate(rig, params, cond, ts, key=jax.random.key(args.seed),
                       noise_std=noise * units.ARCSEC,
                       attrs={"latitude_deg": lat, "scheme": scheme, "rig": "esg",
                              "noise_arcsec": noise, "seed": args.seed})
        if not np.all(np.isfinite(np.asarray(rec.y))):
            raise UsageError("the simulation left the model's domain (gimbal lock, cos alpha2 = "
                             "0); shorten --hours or change --alpha0/--scheme")
        save_record(rec, out, units=rig.CHANNEL_UNITS)
        print(f"wrote {out}: {ts.size} samples over {hours} h, scheme {scheme}, latitude "
              f"{lat} deg")
        print(space.table(params, names=[k for k in space.names
                                         if float(params[k]) != space[k].null]))
        emit_json({"record": str(out), "samples": int(ts.size),
                   "parameters": space.display_json(params, params)}, args.json)

    def fit(self, args):
        from . import units
        from .estimate import fit
        from .estimate.least_squares import convergence_text

        method = args.method or "gauss-newton"
        rec0 = load(args, CHANNELS)
        rig, cond, scheme, lat = rig_and_conditions(args, rec0)
        effects = parse_effects(args.effects, rig)
        report = fit(rig, rec0, cond, effects=effects, method=method,
                     noise_std=None if args.noise_arcsec is None
                     else args.noise_arcsec * units.ARCSEC)
        print(f"# fit of {args.record} ({rec0.n_samples} samples), rig esg, scheme {scheme}, "
              f"latitude {lat} deg, method {method}, effects {list(effects) or 'none'}")
        print(report.table())
        ex = report.extra
        conv = (convergence_text(report.converged, ex["num_steps"], ex["remaining_step_se"])
                if "remaining_step_se" in ex else f"converged: {report.converged}")
        rms, noise = report.to_json()["residual_rms_arcsec"], ex["sample_noise_arcsec"]
        print(f"residual RMS {rms:.4g} arcsec; {conv}")
        note = misfit_note(rms / noise, f"{noise:.3g} arcsec", "its units (SI: s, rad), --scheme "
                           "and --latitude", args.record, "esg")
        if note:
            print(note)
        if "residual_noise_arcsec" in ex and "noise_std_arcsec" in ex:
            print(f"standard errors at the given noise {ex['noise_std_arcsec']:.4g} arcsec (the "
                  f"residual's estimate: {ex['residual_noise_arcsec']:.4g} arcsec)")
        emit_json(report.to_json() | {"rig": "esg", "scheme": scheme, "latitude_deg": lat,
                                      "effects": list(effects)}, args.json)

    def observability(self, args):
        from . import units
        from .analysis.observability import observability

        hours = 24.0 if args.hours is None else args.hours
        sample = 60.0 if args.sample is None else args.sample
        rig, cond, scheme, lat = rig_and_conditions(args)
        effects = parse_effects("rotor_tilt,base_misalignment" if args.effects is None
                                else args.effects, rig)
        space = rig.param_space
        a0 = args.alpha0 or [0.0, 0.0]
        params = space.make({n: 0.01 for n in rig.drift_names} |
                            {"alpha10": a0[0] * units.DEG, "alpha20": a0[1] * units.DEG})
        ts = sample_times(hours, sample)
        method = args.method or "regression"
        if method == "regression":
            from .estimate._fit import _linear_names

            free = _linear_names(rig, effects)
        else:
            free = space.free_names(effects)
        rep = observability(rig, params, cond, ts, free=free, method=method,
                            exact_tol=1e-6 if args.exact_tol is None else args.exact_tol,
                            weak_tol=1e-3 if args.weak_tol is None else args.weak_tol)
        print(f"# observability: scheme {scheme}, latitude {lat} deg, alpha0 {a0} deg, "
              f"{hours} h, method {method}, base parameters {args.base_param or 'eps'}")
        print(rep.summary())
        emit_json(rep.to_json() | {"scheme": scheme, "latitude_deg": lat}, args.json)

    def load(self, args):
        record = load(args, CHANNELS)
        _, _, scheme, lat = rig_and_conditions(args, record)
        return record.with_conditions(scheme=scheme, latitude_deg=lat)

    def diagnose_options(self, args):
        flicker = None
        if args.flicker_arcsec is not None:
            from . import units

            if args.noise_model == "white":
                raise UsageError("--flicker-arcsec sets a white+flicker noise model; drop "
                                 "--noise-model white")
            if not args.flicker_arcsec >= 0:
                raise UsageError(f"--flicker-arcsec {args.flicker_arcsec}: give B >= 0 "
                                 "(arcsec)")
            flicker = args.flicker_arcsec * units.ARCSEC
        return {"noise_model": args.noise_model, "flicker_b": flicker}
