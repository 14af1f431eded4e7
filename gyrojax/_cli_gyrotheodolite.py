"""``gyrojax simulate|diagnose --rig gyrotheodolite``: a north-seeking run of the sensing element.

Record channel ``alpha`` (azimuth pick-off, rad); conditions as record attributes
(``latitude_deg``). ``--set`` takes the rig's parameters in display units: the bench-test ones
(``index_offset`` arcsec, ``alpha0`` arcmin, ``alpha_dot0`` arcsec/s) and the unmodelled effects'
(``M_tape``, ``M_tr``, ``M_step`` in nN m, ``M_ramp`` in nN m/h, ``tau_tr``, ``t_step`` in min,
``k_pick`` in ppm).
"""

from __future__ import annotations

from .record import sample_times

CHANNELS = ("alpha",)
DEFAULT_HOURS = 40 / 60


def simulate(args, parse_sets, emit_json, usage_error):
    import jax

    from . import units
    from .io import record_path, save_record
    from .models.gyrotheodolite import ODE_OPTIONS, GyrotheodoliteConditions, GyrotheodoliteRig
    from .simulate import simulate as run

    hours = DEFAULT_HOURS if args.hours is None else args.hours
    sample = 1.0 if args.sample is None else args.sample
    if not hours > 0 or not sample > 0:
        raise usage_error(f"--hours {hours} and --sample {sample} s must be > 0")
    if args.noise_arcsec < 0:
        raise usage_error(f"--noise-arcsec {args.noise_arcsec} must be >= 0")
    lat = 50.45 if args.latitude is None else args.latitude
    try:
        cond = GyrotheodoliteConditions.create(lat)
    except ValueError as exc:
        raise usage_error(str(exc)) from None
    rig = GyrotheodoliteRig()
    space = rig.param_space
    sets = parse_sets(args.set, space)
    params = rig.default_params(**sets)
    ts = sample_times(hours * 3600, sample, span=f"--hours {hours:g}",  # ValueError: exit 2
                      sample=f"--sample {sample:g}")
    out = record_path(args.out)  # ValueError: exit 2
    rec = run(rig, params, cond, ts, key=jax.random.key(args.seed),
              noise_std=args.noise_arcsec * units.ARCSEC,
              attrs={"rig": "gyrotheodolite", "latitude_deg": lat,
                     "noise_arcsec": args.noise_arcsec, "seed": args.seed}, **ODE_OPTIONS)
    save_record(rec, out)
    shown = [k for k in space.names if float(params[k]) != space[k].null or k in sets]
    print(f"wrote {out}: {ts.size} samples over {hours * 60:.1f} min, latitude {lat} deg, "
          f"pick-off noise {args.noise_arcsec} arcsec")
    if shown:
        print(space.table(params, names=shown))
    emit_json({"record": str(out), "samples": int(ts.size),
               "parameters": space.display_json(params, shown)}, args.json)
    return 0
