"""A platform test as recorded: the *schedule* (JSON: positions and table amplitudes, run as
dwells) and the record layout. A record holds every dwell one after another (time runs on,
amplitude-major), with channels ``alpha beta gamma`` (rad), ``ax ay az`` (m/s^2, SI as every
record file; the rig's model and its accelerometer terms work in g: :func:`accelerations_g`
reads them back, refusing a record written in g) and the labels
``position`` (row of the schedule) and ``amplitude`` (index into the table amplitudes); the
schedule travels as the record attribute ``schedule_json``. Used by the CLI (simulate, fit) and
by the platform gap diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .platform import DEFAULT_MOUNTING, ENU_MOUNTING, TABLE1_DEG, PlatformRig, schedule

__all__ = ["CHANNELS", "SCHEDULE_FIELDS", "load_schedule", "default_phases", "schedule_json",
           "schedule_conditions", "dwell_times", "dwell_span", "split_record", "simulate_schedule",
           "accelerations_g", "POSITION_TOLERANCE_DEG"]

CHANNELS = ("alpha", "beta", "gamma", "ax", "ay", "az", "position", "amplitude")
SCHEDULE_FIELDS = {
    "positions_deg": "rows (alpha, beta, gamma) in deg (default: Table 1)",
    "table_amplitudes_g": "table vibration amplitudes in g (default [9, 7])",
    "attenuation": "table / platform amplitude ratio of the shock mount (default 1.5)",
    "frequency_hz": "vibration frequency (default 15)",
    "dwell_s": "dwell per position in s (default 100)",
    "sample_s": "sampling interval in s (default 0.025)",
    "latitude_deg": "latitude (default 45.75)",
    "mounting": "'default' (y_b Up), 'enu' (z_b Up) or a 3x3 C_r^b",
    "phases_rad": "vibration phase of each dwell, one row of positions per amplitude, in rad "
                  "(default: drawn uniform with seed 0; a simulated record carries its phases)",
}


def load_schedule(source) -> dict:
    """Read and validate a schedule (path, JSON text or dict); fills the defaults."""
    from ..estimate.platform import check_sampling

    if isinstance(source, dict):
        raw = dict(source)
    else:
        text = str(source)
        if not text.lstrip().startswith("{"):  # a file name
            try:
                text = Path(text).read_text()
            except OSError as exc:
                raise ValueError(f"schedule file {source}: {exc.strerror}; give a JSON file "
                                 "or JSON text") from None
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"schedule {source}: not valid JSON ({exc}); see "
                             "`gyrojax simulate --help` for the fields") from None
    unknown = sorted(set(raw) - set(SCHEDULE_FIELDS))
    if unknown:
        raise ValueError(f"schedule: unknown field(s) {unknown}; allowed: "
                         + "; ".join(f"{k}: {v}" for k, v in SCHEDULE_FIELDS.items()))
    s = {"positions_deg": TABLE1_DEG.tolist(), "table_amplitudes_g": [9.0, 7.0],
         "attenuation": 1.5, "frequency_hz": 15.0, "dwell_s": 100.0, "sample_s": 0.025,
         "latitude_deg": 45.75, "mounting": "default"} | raw
    amps = [float(a) for a in s["table_amplitudes_g"]]
    if not amps or any(a < 0 for a in amps):
        raise ValueError(f"schedule: table_amplitudes_g {amps} must be one or more values >= 0")
    if len(set(amps)) < len(amps):
        raise ValueError(f"schedule: table_amplitudes_g {amps} repeats an amplitude; the "
                         "two-amplitude method needs different amplitudes")
    if s["attenuation"] <= 0 or s["dwell_s"] <= 0:
        raise ValueError("schedule: attenuation and dwell_s must be > 0")
    check_sampling(float(s["sample_s"]), float(s["frequency_hz"]))
    shape = (len(amps), len(s["positions_deg"]))
    if s.get("phases_rad") is None:
        s["phases_rad"] = default_phases(*shape).tolist()
    else:
        fix = (f"give {shape[0]} row(s) (one per table amplitude) of {shape[1]} finite phases in "
               "rad (one per position), or leave it out")
        try:
            ph = np.asarray(s["phases_rad"], float)
        except (TypeError, ValueError):
            raise ValueError(f"schedule: phases_rad {s['phases_rad']!r} is not an array of "
                             f"numbers; {fix}") from None
        if ph.shape != shape or not np.all(np.isfinite(ph)):
            raise ValueError(f"schedule: phases_rad has shape {ph.shape}"
                             f"{'' if np.all(np.isfinite(ph)) else ' and a non-finite value'}; {fix}")
        s["phases_rad"] = ph.tolist()
    m = s["mounting"]
    s["mounting_matrix"] = (DEFAULT_MOUNTING if m == "default" else ENU_MOUNTING if m == "enu"
                            else np.asarray(m, float)).tolist()
    return s


def _check_size(s):
    """Refuse a schedule whose simulated record the machine could not hold (more than
    :data:`~gyrojax.record.MAX_SAMPLES` samples)."""
    from ..record import MAX_SAMPLES

    n = ((round(s["dwell_s"] / s["sample_s"]) + 1) * len(s["positions_deg"])
         * len(s["table_amplitudes_g"]))  # dwell_times' count, without making the array
    if n > MAX_SAMPLES:
        raise ValueError(f"schedule: dwell_s {s['dwell_s']:g} at sample_s {s['sample_s']:g} over "
                         f"{len(s['positions_deg'])} positions and {len(s['table_amplitudes_g'])} "
                         f"amplitude(s) gives {n:.3g} samples; a simulated record holds at most "
                         f"{MAX_SAMPLES:,}: shorten the dwells or lengthen sample_s")


def default_phases(n_amplitudes: int, n_positions: int) -> np.ndarray:
    """The vibration phases of a schedule that names none (rad, ``n_amplitudes x n_positions``):
    uniform on [0, 2 pi) from seed 0, amplitude-major (the phases every schedule had before they
    were recorded in it)."""
    return np.random.default_rng(0).uniform(0, 2 * np.pi, (n_amplitudes, n_positions))


def schedule_json(s) -> str:
    """The record attribute ``schedule_json`` of a loaded schedule (its fields as given, the
    mounting by name or matrix, the phases included)."""
    return json.dumps({k: v for k, v in s.items() if k != "mounting_matrix"})


def schedule_conditions(s):
    """One stacked PlatformConditions per table amplitude (platform amplitude = table /
    attenuation; the schedule's vibration phases, see ``phases_rad``; each dwell's start
    ``t0`` in the test, the dwells one after another amplitude-major)."""
    pos = np.asarray(s["positions_deg"], float)
    step = dwell_span(s)
    phases = np.asarray(s["phases_rad"], float)
    return [schedule(pos, a0=a / s["attenuation"], latitude_deg=s["latitude_deg"],
                     frequency_hz=s["frequency_hz"], phases=phases[k],
                     mounting=s["mounting_matrix"], t0s=(k * len(pos) + np.arange(len(pos))) * step)
            for k, a in enumerate(s["table_amplitudes_g"])]


def dwell_times(s):
    """Sample times of one dwell (s)."""
    n = int(round(s["dwell_s"] / s["sample_s"]))
    return np.arange(n + 1) * s["sample_s"]


def dwell_span(s):
    """Test time from one dwell's start to the next's (s): its samples and one interval."""
    return float(dwell_times(s)[-1]) + float(s["sample_s"])


POSITION_TOLERANCE_DEG = 5.0
"""How far a dwell's median gimbal angles may sit from the schedule's position: the platform
drifts by its coefficients within a dwell (0.3 deg over 100 s on Table 2's), and 5 deg in a
dwell would take ~180 deg/h."""


def split_record(record, s):
    """The record's samples as (amplitudes, positions, samples per dwell, channels); a clear
    error when the record does not match the schedule: its sample count, each dwell's labels
    (``position``, ``amplitude``: the schedule's order, amplitude-major), its sample interval
    (``sample_s``: t in s) and its gimbal angles (within :data:`POSITION_TOLERANCE_DEG` of the
    schedule's position: rad, and the schedule's positions). Every reader takes the dwells in
    the schedule's order and times, so a record that disagrees would be read wrong silently."""
    y = np.asarray(record.y)
    n_pos, n_amp = len(s["positions_deg"]), len(s["table_amplitudes_g"])
    n = len(dwell_times(s))
    if y.shape[0] != n_pos * n_amp * n:
        raise ValueError(f"record has {y.shape[0]} samples; the schedule needs {n_pos} positions "
                         f"x {n_amp} amplitudes x {n} samples = {n_pos * n_amp * n}: give the "
                         "schedule the record was taken with (--schedule)")
    data = y.reshape(n_amp, n_pos, n, len(CHANNELS))
    expected = np.stack(np.meshgrid(np.arange(n_pos), np.arange(n_amp)), axis=-1)  # (A, P, 2)
    wrong = np.argwhere(np.any(data[..., 6:8] != expected[:, :, None, :], axis=(2, 3)))
    if wrong.size:
        k, p = wrong[0]
        got = np.unique(data[k, p, :, 6:8], axis=0)
        raise ValueError(f"dwell {k * n_pos + p} of the record is labelled (position, amplitude) "
                         f"{got.tolist()}, where the schedule's order (amplitude-major) puts "
                         f"position {p} at amplitude {k}: reorder the record's dwells to the "
                         "schedule's, or give the schedule it was taken with (--schedule)")
    dt = float(np.median(np.diff(np.asarray(record.t, float).reshape(n_amp, n_pos, n), axis=-1)))
    if not abs(dt - s["sample_s"]) <= 1e-3 * s["sample_s"]:
        raise ValueError(f"the record samples every {dt:.6g} (its t's median step within a dwell), "
                         f"the schedule every sample_s = {s['sample_s']:g} s: t is in s; give the "
                         "schedule the record was taken with (--schedule)")
    pos = np.radians(np.asarray(s["positions_deg"], float))  # (P, 3)
    angles = np.median(data[..., :3], axis=2)  # (A, P, 3)

    def off(a):  # each dwell's largest wrapped distance from its position (rad)
        return np.max(np.abs(np.angle(np.exp(1j * (a - pos)))), axis=-1)

    far = np.argwhere(off(angles) > np.radians(POSITION_TOLERANCE_DEG))
    if far.size:
        k, p = far[0]
        fix = ("they look like deg: convert alpha beta gamma to rad"
               if np.all(off(np.radians(angles)) <= np.radians(POSITION_TOLERANCE_DEG)) else
               "give the schedule the record was taken with (--schedule), and alpha beta gamma "
               "in rad")
        raise ValueError(f"dwell {k * n_pos + p} (position {p}, amplitude {k}): the gimbal angles' "
                         f"median {np.round(angles[k, p], 4).tolist()} lies more than "
                         f"{POSITION_TOLERANCE_DEG:g} deg from the schedule's position "
                         f"{np.round(pos[p], 4).tolist()} rad ({s['positions_deg'][p]} deg), "
                         f"where the platform drifts far less in a dwell: {fix}")
    return data


def accelerations_g(data):
    """The accelerometer channels of a split record (:func:`split_record`, ``(..., 8)``) in g, the
    rig's unit, from the file's m/s^2. The accelerometers always read gravity (1 g at rest, more
    under vibration: the mean |f|^2 is 1 + a0^2/2 g^2), so a median |f| outside 0.5-20 g means
    another unit: refused, with the fix."""
    from .. import units

    acc = np.asarray(data, float)[..., 3:6]
    mag = float(np.median(np.linalg.norm(acc, axis=-1))) / units.G0
    if not 0.5 <= mag <= 20.0:
        fix = ("they look like g (gyrojax records before December 2026 wrote them so): multiply "
               "them by 9.80665" if 0.5 <= mag * units.G0 <= 20.0 else
               "convert them to m/s^2")
        raise ValueError(f"the record's accelerometers ax ay az have median |f| {mag:.4g} g "
                         f"({mag * units.G0:.4g} in the file's units), where an accelerometer on "
                         f"the table reads gravity, 1 g or more; gyrojax records are SI: {fix}")
    return acc / units.G0


def simulate_schedule(params, s, key, *, noise_arcsec: float = 1.0, accel_noise_g: float = 1e-4,
                      rig=None):
    """The record of a whole test: every dwell of schedule ``s`` (from :func:`load_schedule`)
    integrated with ``params`` (SI, the rig's full set), white noise on the angles
    (``noise_arcsec``) and accelerometers (``accel_noise_g``) from ``key``, the dwells laid end to
    end with the labels and the schedule attribute."""
    import jax
    import jax.numpy as jnp

    from .. import units
    from ..record import BenchRecord, freeze
    from ..simulate import integrate

    _check_size(s)
    rig = rig or PlatformRig()
    ts = jnp.asarray(dwell_times(s))
    blocks, t_all, t0 = [], [], 0.0
    for k, conds in enumerate(schedule_conditions(s)):
        y = np.array(jax.vmap(lambda c: integrate(rig, params, c, ts))(conds))
        key, k1, k2 = jax.random.split(key, 3)
        y[..., :3] += noise_arcsec * units.ARCSEC * np.asarray(
            jax.random.normal(k1, y[..., :3].shape))
        y[..., 3:] += accel_noise_g * np.asarray(jax.random.normal(k2, y[..., 3:].shape))
        y[..., 3:] *= units.G0  # the record file is SI
        for p in range(y.shape[0]):
            lab = np.stack([np.full(len(ts), p), np.full(len(ts), k)], axis=1)
            blocks.append(np.concatenate([y[p], lab], axis=1))
            t_all.append(t0 + np.asarray(ts))
            t0 += dwell_span(s)
    return BenchRecord(jnp.asarray(np.concatenate(t_all)), jnp.asarray(np.concatenate(blocks)),
                       CHANNELS, freeze({"schedule_json": schedule_json(s),
                                         "latitude_deg": s["latitude_deg"]}))
