"""``gyrojax simulate --rig imu`` (a multi-position test record) and ``gyrojax fit --rig imu``:
multi-position calibration of a strapdown IMU on a stand.

The simulated test: ``--poses`` still poses (the six axis-up poses, then seeded random tilts;
``cube_poses``) of ``--dwell`` s each, joined by 2-s constant-rate turns, sampled every
``--sample`` s, with white gyro and accelerometer noise (``--arw`` deg/sqrt(h), ``--vrw``
m/s/sqrt(h)) and the rig's parameters from ``--set`` in display units (``bgx=10`` deg/h,
``sax=500`` ppm, ``maxy=1`` mrad, ``gsxz=5`` deg/h/g ...; the default IMU has gyro biases
10, -5, 3 deg/h and accelerometer biases 5, -3, 2 mg, and no other error). With
``--latitude`` the record carries the site and the gyros see the vertical Earth rate
(``k_earth`` 1 unless set).

The static poses are found in the record (``detect_static``); the accelerometer's biases, scale
factors and misalignments are fitted so that every pose's specific force has the local gravity's
magnitude (``calibrate_accelerometer``), checked by leaving each pose out in turn; the gyros'
scale factors and misalignments by propagating the calibrated up vector through the turns
between poses (``calibrate_gyro``), where the record has the gyro channels and such turns.
Fewer poses determine fewer terms (an x-up/x-down pair: bax and sax); the table gives those with
how far the undetermined ones could move them, and names the rest. A still record (every static
interval in one orientation) is refused with the pointer to ``gyrojax diagnose``.
"""

from __future__ import annotations

import numpy as np

from ._cli_base import AbstractRigCommands, UsageError, emit_json, load, parse_sets

ACCELEROMETERS = ("ax", "ay", "az")
GYROS = ("wx", "wy", "wz")
DEFAULT_ERRORS = {"bgx": 10.0, "bgy": -5.0, "bgz": 3.0, "bax": 5.0, "bay": -3.0, "baz": 2.0}
TURN_S = 2.0
SAME_POSE_DEG = 5.0  # static intervals whose gravity directions lie closer are one orientation


def orientations(means, *, within_deg: float = SAME_POSE_DEG) -> int:
    """The number of distinct orientations among static poses' mean specific forces: poses are
    grouped greedily, each joining the first group whose first pose lies within ``within_deg``."""
    u = np.asarray(means, float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    heads: list = []
    for v in u:
        if not any(np.dot(v, h) >= np.cos(np.radians(within_deg)) for h in heads):
            heads.append(v)
    return len(heads)


def simulate(args):
    import jax

    from . import units
    from .io import record_path, save_record
    from .models.imu import IMUConditions, IMURig, cube_poses, simulate_imu
    from .record import MAX_SAMPLES

    if args.hours is not None:
        raise UsageError(f"--hours {args.hours:g}: an IMU record lasts --poses x (--dwell + "
                          f"{TURN_S:g} s of turn); set those instead")
    sample = 0.01 if args.sample is None else args.sample
    if args.poses < 1:
        raise UsageError(f"--poses {args.poses} must be >= 1")
    for name, v, positive in (("--dwell", args.dwell, True), ("--sample", sample, True),
                              ("--arw", args.arw, False), ("--vrw", args.vrw, False)):
        if not (np.isfinite(v) and (v > 0 if positive else v >= 0)):
            raise UsageError(f"{name} {v:g} must be {'> 0' if positive else '>= 0'}")
    rate_hz = 1.0 / sample
    shortest = min(args.dwell, TURN_S)
    if sample > shortest:
        raise UsageError(f"--sample {sample:g} s is longer than "
                          + (f"--dwell {args.dwell:g} s" if args.dwell < TURN_S
                             else f"the {TURN_S:g}-s turns between poses")
                          + f": sample at {shortest:g} s or faster")
    n = round(args.poses * (args.dwell + TURN_S) * rate_hz)
    if n > MAX_SAMPLES:
        raise UsageError(f"--poses {args.poses} x (--dwell {args.dwell:g} + {TURN_S:g} s) at "
                          f"--sample {sample:g} s gives {n:.3g} samples; a simulated record holds "
                          f"at most {MAX_SAMPLES:,}: fewer or shorter poses, or sample slower")
    lat = float("nan") if args.latitude is None else args.latitude
    IMUConditions(lat)  # ValueError (exit 2) before the work: a latitude outside [-90, 90]
    heading = args.heading  # every rig's options are on the parser (cli._rig_groups)
    if heading is not None and (np.isnan(lat) or not np.isfinite(heading)):
        raise UsageError(f"--heading {heading:g} needs --latitude (the horizontal Earth rate is "
                          "Omega cos(latitude)) and a finite angle in degrees")
    space = IMURig().param_space
    sets = parse_sets(args.set, space)
    given = {k: space[k].from_display(v) for k, v in DEFAULT_ERRORS.items()}
    if not np.isnan(lat):
        given["k_earth"] = 1.0
    params = space.make(given | sets)
    out = record_path(args.out)  # ValueError: exit 2
    poses = cube_poses(args.poses, args.dwell, seed=args.seed)
    rec = simulate_imu(params, poses, rate_hz=rate_hz, turn_s=TURN_S, latitude_deg=lat,
                       arw=args.arw * units.DEG / 60, vrw=args.vrw / 60,
                       key=jax.random.key(args.seed), heading_deg=heading)
    rec = rec.with_conditions(rig="imu", arw_deg_per_sqrt_h=args.arw,
                              vrw_mps_per_sqrt_h=args.vrw, seed=args.seed)
    save_record(rec, out, units=IMURig.CHANNEL_UNITS)
    shown = [k for k in space.names if float(params[k]) != space[k].null or k in sets]
    print(f"wrote {out}: {rec.n_samples} samples, {args.poses} poses of {args.dwell:g} s at "
          f"{rate_hz:g} Hz, ARW {args.arw:g} deg/sqrt(h), VRW {args.vrw:g} m/s/sqrt(h)"
          + ("" if np.isnan(lat) else f", latitude {lat:g} deg")
          + ("" if heading is None else f", north at {heading:g} deg from the first pose's e1"))
    print(space.table(params, names=shown))
    emit_json({"record": str(out), "samples": int(rec.n_samples), "poses": args.poses,
               "parameters": space.display_json(params, shown)}, args.json)
    return 0


def _rms(x):
    """RMS over the finite entries (NaN: a pose left out where the rest do not determine the
    calibration); None when there are none."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else None


def _mm(x) -> str:
    return "-" if x is None else f"{x * 1e3:.3f}"


def fit(args):
    from .estimate.multiposition import (
        ACCEL_NAMES,
        GYRO_NAMES,
        calibrate_accelerometer,
        calibrate_gyro,
        detect_static,
        leave_one_position_out,
        segment_means,
    )
    from .models.imu import IMUConditions, IMURig

    if args.method not in (None, "levenberg-marquardt"):
        raise UsageError(f"--method {args.method!r}: the IMU's multi-position calibration is one "
                          "Levenberg-Marquardt fit of |f| = g (and of the turns for the gyros); "
                          "omit --method")
    rec = load_imu(args)
    missing = [c for c in ACCELEROMETERS if c not in rec.channels]
    if missing:
        raise UsageError(f"{args.record}: no {' '.join(missing)} channel; the multi-position "
                          "calibration needs all three accelerometers (ax ay az, m/s^2), and "
                          "wx wy wz (rad/s) for the gyros")
    gravity = IMUConditions.from_record(rec).gravity
    segs = detect_static(rec)
    if len(segs) < 2:
        t = np.asarray(rec.t, float)
        raise UsageError(f"{args.record}: {len(segs)} static pose(s) found in {t[-1] - t[0]:.4g} "
                          f"s at {1 / np.median(np.diff(t)):.4g} Hz; the multi-position "
                          "calibration needs a record of still poses (>= 12, spread over the "
                          "sphere) joined by turns, with t in s (poses are found over 1-s "
                          "windows)")
    means, _ = segment_means(rec, segs)
    n_orient = orientations(means)
    if n_orient < 2:
        raise UsageError(f"{args.record}: its {len(segs)} static intervals all lie within "
                          f"{SAME_POSE_DEG:g} deg of one orientation (a still record, broken by "
                          "gaps or masked knocks), so no term of the calibration is determined; "
                          "the multi-position calibration needs still poses (>= 12, spread over "
                          "the sphere) joined by turns. For a still record's noise and drift: "
                          f"gyrojax diagnose {args.record} --rig imu")
    acc = calibrate_accelerometer(means, gravity)
    lopo = leave_one_position_out(means, gravity)
    gyro, gyro_note = None, "no gyro channels"
    if all(c in rec.channels for c in GYROS):
        try:
            gyro = calibrate_gyro(rec, segs, acc)
            gyro_note = gyro.message
        except ValueError as exc:  # no turns short enough between the poses
            gyro_note = str(exc)

    space = IMURig().param_space
    raw = np.linalg.norm(means, axis=1) - gravity
    print(f"# multi-position calibration of {args.record}: {rec.n_samples} samples, "
          f"{len(segs)} static poses in {n_orient} orientations, gravity {gravity:.5f} m/s^2")
    print(f"accelerometers: {acc.message}; converged: {acc.converged}")
    print(f"  |f| - g RMS over the poses: uncalibrated {_mm(_rms(raw))} mm/s^2, calibrated "
          f"{_mm(_rms(acc.residual))}, each pose left out {_mm(_rms(lopo))}")
    print(f"gyros: {gyro_note}" + ("" if gyro is None else f"; converged: {gyro.converged}; "
                                   f"turn residual median {np.median(gyro.residual_deg):.3f} "
                                   "deg"))
    params, undetermined, rows = {}, [], []
    for cal, names in ((acc, ACCEL_NAMES), (gyro, GYRO_NAMES)):
        if cal is None:
            continue
        for n in names:
            p = space[n]
            if n not in cal.determination.terms:  # arbitrary along the poses' null space: no number
                params[n] = {"value": None, "stderr": None, "unit": p.display_unit,
                             "determined": False}
                undetermined.append(n)
                continue
            v, se = float(p.to_display(cal.params[n])), cal.stderr[n]
            se = None if not np.isfinite(se) else float(p.to_display(se))
            shift = float(p.to_display(cal.determination.shift(n)))
            params[n] = {"value": v, "stderr": se, "unit": p.display_unit, "determined": True,
                         "undetermined_shift": shift}
            rows.append((n, v, se, shift, p.display_unit))
    print(f"{'term':6s} {'estimate':>13s} {'stderr':>11s}"
          + (f" {'undet.':>9s}" if undetermined else "") + "  unit")
    for n, v, se, shift, unit in rows:
        print(f"{n:6s} {v:13.6g} {'-' if se is None else f'{se:11.3g}':>11s}"
              + (f" {shift:9.2g}" if undetermined else "") + f"  {unit}")
    if undetermined:
        print(f"not determined by this record: {' '.join(undetermined)}")
        print("undet.: the most the undetermined terms, held at zero, move an estimate when "
              "they are at their prior scale (10 mg, 1000 ppm, 1 mrad) instead")
    parts = [acc] + ([] if gyro is None else [gyro])
    emit_json({"rig": "imu", "method": "multi-position", "parameters": params,
               "converged": all(c.converged for c in parts),
               "determined": all(c.determined for c in parts),
               "poses": len(segs), "orientations": n_orient, "gravity_mps2": gravity,
               "accelerometer": {"message": acc.message, "converged": acc.converged,
                                 "determined": acc.determined,
                                 "residual_rms_mps2": _rms(acc.residual),
                                 "uncalibrated_rms_mps2": _rms(raw),
                                 "leave_one_position_out_rms_mps2": _rms(lopo)},
               "gyro": None if gyro is None else {
                   "message": gyro.message, "converged": gyro.converged,
                   "determined": gyro.determined, "turns": gyro.n_turns,
                   "turn_residual_median_deg": float(np.median(gyro.residual_deg))},
               "gyro_note": gyro_note}, args.json)


def load_imu(args):
    """An IMU record: a file (any subset of wx wy wz ax ay az) or ``dataset:NAME`` for one of
    the real records (:data:`gyrojax.datasets.REAL_DATA_SETS`), with ``--latitude`` and
    ``--table-run`` as its conditions."""
    from .datasets import REAL_DATA_SETS, DataFileError
    from .models.imu import IMUConditions

    if args.latitude is not None:  # before reading the record
        IMUConditions(float(args.latitude))  # ValueError (exit 2): outside [-90, 90]
    runs = table_runs(args)  # checked before the record is read
    if args.record.startswith("dataset:"):
        name = args.record.split(":", 1)[1]
        if name not in REAL_DATA_SETS:
            raise UsageError(f"unknown data set {name!r}; known: {', '.join(REAL_DATA_SETS)}")
        try:
            record = REAL_DATA_SETS[name]()
        except (DataFileError, FileNotFoundError) as exc:
            raise UsageError(str(exc)) from None
    else:
        record = load(args, None)
    if args.latitude is not None:
        record = record.with_conditions(latitude_deg=float(args.latitude))
    if runs:
        record = record.with_conditions(table_rate_s=runs)
    return record


def table_runs(args) -> tuple:
    """``--table-run T0:T1:RATE`` options as the flat triples of ``table_rate_s``."""
    runs = []
    for text in getattr(args, "table_run", None) or ():
        try:
            t0, t1, rate = (float(x) for x in text.split(":"))
        except ValueError:
            raise UsageError(f"--table-run {text!r}: give T0:T1:RATE (s, s, deg/s), e.g. "
                             "--table-run 120:180:10") from None
        runs += [t0, t1, rate]
    return tuple(runs)


class IMUCommands(AbstractRigCommands):
    """The strapdown IMU's commands."""

    name = "imu"
    COMMANDS = ("simulate", "fit", "diagnose")
    ELSEWHERE = "gyrojax simulate, fit (multi-position calibration) or diagnose --rig imu"

    def add_arguments(self, command, group):
        if command == "simulate":
            group.add_argument("--poses", type=int, default=12,
                               help="imu: still poses, the six axis-up ones first, then seeded "
                                    "random tilts (default 12), joined by 2-s turns")
            group.add_argument("--dwell", type=float, default=10.0,
                               help="imu: seconds per pose (default 10)")
            group.add_argument("--arw", type=float, default=0.3,
                               help="imu: gyro angle random walk in deg/sqrt(h) (default 0.3)")
            group.add_argument("--vrw", type=float, default=0.05,
                               help="imu: accelerometer velocity random walk in m/s/sqrt(h) "
                                    "(default 0.05)")
            group.add_argument("--heading", type=float, metavar="DEG",
                               help="imu: with --latitude, the horizontal Earth rate too, north "
                                    "at DEG from the first pose's e1 about up, carried through "
                                    "the turns (default: the vertical part only)")
        if command == "diagnose":
            group.add_argument("--per-coefficient", action="store_true",
                               help="imu: screen every coefficient of a many-coefficient "
                                    "effect as an effect of its own (g_sensitivity:gsxy, "
                                    "misalignment:mgxy, ...; K = 40 on six channels): which "
                                    "term of the error model, not only which family")
            group.add_argument("--statics-only", action="store_true",
                               help="imu: leave out the turns between still poses (by default "
                                    "each turn's misclosure, the pose before propagated through "
                                    "the gyros against the pose after, is a residual block of "
                                    "its own)")
            group.add_argument("--table-run", action="append", metavar="T0:T1:RATE",
                               help="imu: a constant-rate table run about the vertical, from "
                                    "T0 to T1 s (from the record start) at RATE deg/s (ccw seen "
                                    "from above > 0); repeat per run (default: the record's "
                                    "table_rate_s, if any)")

    def simulate(self, args):
        simulate(args)

    def fit(self, args):
        fit(args)

    def load(self, args):
        return load_imu(args)

    def diagnose_options(self, args):
        return {"per_coefficient": True if args.per_coefficient else None,
                "turns": False if args.statics_only else None}

    def noise_std(self, args):
        if args.noise_arcsec is not None:
            raise UsageError("--noise-arcsec is for the esg rig; the imu rig estimates its noise "
                             "model (AR prewhitening) from the record")
        return None
