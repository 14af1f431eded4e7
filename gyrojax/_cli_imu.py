"""``gyrojax fit --rig imu``: multi-position calibration of a strapdown IMU on a stand.

The static poses are found in the record (``detect_static``); the accelerometer's biases, scale
factors and misalignments are fitted so that every pose's specific force has the local gravity's
magnitude (``calibrate_accelerometer``), checked by leaving each pose out in turn; the gyros'
scale factors and misalignments by propagating the calibrated up vector through the turns
between poses (``calibrate_gyro``), where the record has the gyro channels and such turns.
"""

from __future__ import annotations

import numpy as np

ACCELEROMETERS = ("ax", "ay", "az")
GYROS = ("wx", "wy", "wz")


def _rms(x):
    """RMS over the finite entries (NaN: a pose left out where the rest do not determine the
    calibration); None when there are none."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else None


def _mm(x) -> str:
    return "-" if x is None else f"{x * 1e3:.3f}"


def fit(args, load_imu, emit_json, usage_error):
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
        raise usage_error(f"--method {args.method!r}: the IMU's multi-position calibration is one "
                          "Levenberg-Marquardt fit of |f| = g (and of the turns for the gyros); "
                          "omit --method")
    rec = load_imu(args)
    missing = [c for c in ACCELEROMETERS if c not in rec.channels]
    if missing:
        raise usage_error(f"{args.record}: no {' '.join(missing)} channel; the multi-position "
                          "calibration needs all three accelerometers (ax ay az, m/s^2), and "
                          "wx wy wz (rad/s) for the gyros")
    gravity = IMUConditions.from_record(rec).gravity
    segs = detect_static(rec)
    if len(segs) < 2:
        raise usage_error(f"{args.record}: {len(segs)} static pose(s) found; the multi-position "
                          "calibration needs a record of still poses (>= 12, spread over the "
                          "sphere) joined by turns")
    means, _ = segment_means(rec, segs)
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
          f"{len(segs)} static poses, gravity {gravity:.5f} m/s^2")
    print(f"accelerometers: {acc.message}; converged: {acc.converged}")
    print(f"  |f| - g RMS over the poses: uncalibrated {_mm(_rms(raw))} mm/s^2, calibrated "
          f"{_mm(_rms(acc.residual))}, each pose left out {_mm(_rms(lopo))}")
    print(f"gyros: {gyro_note}" + ("" if gyro is None else f"; converged: {gyro.converged}; "
                                   f"turn residual median {np.median(gyro.residual_deg):.3f} "
                                   "deg"))
    print(f"{'term':6s} {'estimate':>13s} {'stderr':>11s}  unit")
    params = {}
    for cal, names in ((acc, ACCEL_NAMES), (gyro, GYRO_NAMES)):
        if cal is None:
            continue
        for n in names:
            p = space[n]
            v, se = float(p.to_display(cal.params[n])), cal.stderr[n]
            se = None if not np.isfinite(se) else float(p.to_display(se))
            params[n] = {"value": v, "stderr": se, "unit": p.display_unit}
            print(f"{n:6s} {v:13.6g} {'' if se is None else f'{se:11.3g}'}  {p.display_unit}")
    parts = [acc] + ([] if gyro is None else [gyro])
    emit_json({"rig": "imu", "method": "multi-position", "parameters": params,
               "converged": all(c.converged for c in parts),
               "determined": all(c.determined for c in parts),
               "poses": len(segs), "gravity_mps2": gravity,
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
