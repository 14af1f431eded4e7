"""``gyrojax simulate|diagnose --rig gyrotheodolite``: a north-seeking run of the sensing element.

Record channel ``alpha`` (azimuth pick-off, rad); conditions as record attributes
(``latitude_deg``). ``--set`` takes the rig's parameters in display units: the bench-test ones
(``index_offset`` arcsec, ``alpha0`` arcmin, ``alpha_dot0`` arcsec/s) and the unmodelled effects'
(``M_tape``, ``M_tr``, ``M_step`` in nN m, ``M_ramp`` in nN m/h, ``tau_tr``, ``t_step`` in min,
``k_pick`` in ppm).
"""

from __future__ import annotations

from ._cli_base import (
    AbstractRigCommands,
    UsageError,
    emit_json,
    load,
    parse_sets,
    with_latitude,
)
from .record import sample_times

CHANNELS = ("alpha",)
DEFAULT_HOURS = 40 / 60


def simulate(args):
    import jax

    from . import units
    from .io import record_path, save_record
    from .models.gyrotheodolite import ODE_OPTIONS, GyrotheodoliteConditions, GyrotheodoliteRig
    from .simulate import simulate as run

    hours = DEFAULT_HOURS if args.hours is None else args.hours
    sample = 1.0 if args.sample is None else args.sample
    if not hours > 0 or not sample > 0:
        raise UsageError(f"--hours {hours} and --sample {sample} s must be > 0")
    noise = 1.0 if args.noise_arcsec is None else args.noise_arcsec
    if noise < 0:
        raise UsageError(f"--noise-arcsec {noise} must be >= 0")
    lat = 50.45 if args.latitude is None else args.latitude
    try:
        cond = GyrotheodoliteConditions.create(lat)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    rig = GyrotheodoliteRig()
    space = rig.param_space
    sets = parse_sets(args.set, space)
    params = rig.default_params(**sets)
    ts = sample_times(hours * 3600, sample, span=f"--hours {hours:g}",  # ValueError: exit 2
                      sample=f"--sample {sample:g}")
    out = record_path(args.out)  # ValueError: exit 2
    rec = run(rig, params, cond, ts, key=jax.random.key(args.seed),
              noise_std=noise * units.ARCSEC,
              attrs={"rig": "gyrotheodolite", "latitude_deg": lat,
                     "noise_arcsec": noise, "seed": args.seed}, **ODE_OPTIONS)
    save_record(rec, out, units=rig.CHANNEL_UNITS)
    shown = [k for k in space.names if float(params[k]) != space[k].null or k in sets]
    print(f"wrote {out}: {ts.size} samples over {hours * 60:.1f} min, latitude {lat} deg, "
          f"pick-off noise {noise} arcsec")
    if shown:
        print(space.table(params, names=shown))
    emit_json({"record": str(out), "samples": int(ts.size),
               "parameters": space.display_json(params, shown)}, args.json)


class GyrotheodoliteCommands(AbstractRigCommands):
    """The gyrotheodolite's commands (``gyrojax observer`` is its observer study)."""

    name = "gyrotheodolite"
    COMMANDS = ("simulate", "diagnose", "observer")
    ELSEWHERE = ("gyrojax observer (observer gains, poles, bandwidths), gyrojax simulate or "
                 "diagnose --rig gyrotheodolite")

    def simulate(self, args):
        simulate(args)

    def load(self, args):
        return with_latitude(args, load(args, CHANNELS))
