"""Loaders for the real recorded data sets in ``../shared/data/real/`` (never copied into this
repository), into :class:`BenchRecord` in SI units with their conditions.

| loader | folder | format -> conversion |
|---|---|---|
| :func:`load_ucalgary` | ``ucalgary_ln100_adi`` | LN-100 raw ``<f8`` x 7; ADI 7 text columns |
| :func:`load_ucalgary_pair` | same | x down then x up as one two-position record (real times) |
| :func:`load_xsens` | ``imu_tk_xsens`` | two text files of raw counts -> nominal scales (README) |
| :func:`load_mpu9150` | ``mpu9150_mikov`` | 6 text columns, SI, 100 Hz, no timestamps |
| :func:`load_smac` | ``smac_imudata`` | ``.npz``: ADIS16405 int16 counts x LSB (deg/s, g); MTi-G gyro x |
| :func:`load_mpu6050` | ``mpu6050_unc`` | CSV with a 5-line header, counts / (16384 LSB/g, 131 LSB/(deg/s)) |

Channels ``wx wy wz`` (rad/s) and ``ax ay az`` (m/s^2), the record contract of docs/concepts.md; a record may
carry a subset (the MTi-G file is gyro x only). Conditions carry the sampling rate, latitude where
the source gives it, the nominal conversion used, and ``masked_s``: a flat tuple
``(t0, t1, t0, t1, ...)`` of disturbed spans (saturation, knocks) that fits and diagnoses exclude
(:func:`masked`); nothing is dropped from the record itself.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from . import units
from .record import BenchRecord, freeze

__all__ = ["DataFileError", "data_root", "read_float64_records", "read_text_columns",
           "load_ucalgary", "load_ucalgary_pair", "load_xsens", "load_mpu9150", "load_smac",
           "load_mpu6050", "masked", "REAL_DATA_SETS", "ADIS_KNOCK_SIGMAS"]

IMU_CHANNELS = ("wx", "wy", "wz", "ax", "ay", "az")


class DataFileError(ValueError):
    """A data file that cannot be read as documented: names the file, the place and the fix."""


def data_root(path=None) -> Path:
    """``path``, else ``$GYROJAX_REAL_DATA``, else ``../shared/data/real`` beside the project
    root; a clear error if absent."""
    if path is None:
        path = os.environ.get("GYROJAX_REAL_DATA") or \
            Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"real data not found at {root}: the data sets live in "
                                "../shared/data/real beside the project (not in this repository); "
                                "point GYROJAX_REAL_DATA at a copy elsewhere")
    return root


def read_float64_records(path, n_columns: int, *, partial: str = "error") -> np.ndarray:
    """Raw little-endian float64 records of ``n_columns`` values. A size that is not a whole
    number of records is an error (truncated file) unless ``partial="warn"``, which drops the
    trailing bytes *with a warning* naming them."""
    path = Path(path)
    raw = path.read_bytes()
    rec = 8 * n_columns
    if len(raw) < rec:
        raise DataFileError(f"{path}: {len(raw)} bytes, less than one record of {n_columns} "
                            "float64 values; the file is truncated or not this format")
    extra = len(raw) % rec
    if extra:
        msg = (f"{path}: {len(raw)} bytes is {len(raw) // rec} whole records of {n_columns} "
               f"float64 plus {extra} trailing bytes")
        if partial != "warn":
            raise DataFileError(msg + "; the file is truncated (or has another column count). "
                                "If the trailing bytes are known padding, pass partial='warn'")
        warnings.warn(msg + "; dropping the trailing bytes", stacklevel=2)
    data = np.frombuffer(raw[: len(raw) - extra], dtype="<f8").reshape(-1, n_columns)
    if not np.all(np.isfinite(data)):
        bad = int(np.argwhere(~np.isfinite(data))[0][0])
        raise DataFileError(f"{path}: record {bad} holds non-finite values; wrong format?")
    return data


def read_text_columns(path, n_columns: int, *, delimiter=None, skip: int = 0) -> np.ndarray:
    """Numeric text with exactly ``n_columns`` per row (whitespace-separated, or ``delimiter``),
    after ``skip`` header lines; errors name the file, the line and the fix."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path}: no such file; check the data folder (see its README)")
    rows = []
    with path.open() as fh:
        for k, line in enumerate(fh, start=1):
            if k <= skip:
                continue
            parts = line.split(delimiter) if delimiter else line.split()
            parts = [p.strip() for p in parts]
            if not any(parts):
                continue
            if not parts:
                continue
            if len(parts) != n_columns:
                raise DataFileError(f"{path}, line {k}: {len(parts)} columns, expected "
                                    f"{n_columns}; fix or remove the line")
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                raise DataFileError(f"{path}, line {k}: non-numeric value in {line.strip()!r}; "
                                    "fix or remove the line") from None
    if not rows:
        raise DataFileError(f"{path}: no data rows")
    return np.asarray(rows)


def _imu_record(t, w, f, attrs, channels=IMU_CHANNELS):
    t = np.asarray(t, float)
    if np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0))
        raise DataFileError(f"{attrs.get('source', 'record')}: time is not strictly increasing at "
                            f"sample {k + 1} ({t[k]} -> {t[k + 1]} s)")
    y = np.concatenate([w, f], axis=1) if f is not None else np.asarray(w)
    return BenchRecord(np.asarray(t - t[0]), np.asarray(y), tuple(channels),
                       freeze(attrs | {"t0_s": float(t[0])}))


def masked(record: BenchRecord) -> np.ndarray:
    """Boolean mask, True where a sample lies in one of the record's ``masked_s`` spans."""
    t = np.asarray(record.t)
    spans = np.asarray(record.conditions.get("masked_s", ()), float).reshape(-1, 2)
    out = np.zeros(t.shape, bool)
    for t0, t1 in spans:
        out |= (t >= t0) & (t <= t1)
    return out


def _spans(t, bad, pad: int = 0) -> tuple:
    """Flat (t0, t1, ...) spans covering the True runs of ``bad``, widened by ``pad`` samples."""
    bad = np.asarray(bad, bool).copy()
    if pad and bad.any():
        idx = np.flatnonzero(bad)
        for k in range(-pad, pad + 1):
            bad[np.clip(idx + k, 0, len(bad) - 1)] = True
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(int), [0]])))
    out = []
    for i0, i1 in zip(edges[::2], edges[1::2]):
        out += [float(t[i0]), float(t[i1 - 1])]
    return tuple(out)


def _robust_outliers(y, k: float = 10.0, block: int = 1000):
    """Samples more than ``k`` robust sigmas (MAD of first differences) from the median of their
    ``block``-sample block (10 s at 100 Hz: long enough that a knock does not move the median)."""
    y = np.asarray(y, float)
    n = len(y)
    nb = -(-n // block)
    pad = np.concatenate([y, np.repeat(y[-1:], nb * block - n, axis=0)])
    med = np.repeat(np.median(pad.reshape(nb, block, -1), axis=1), block, axis=0)[:n]
    d = np.diff(y, axis=0)
    s = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)
    return np.any(np.abs(y - med) > k * np.maximum(s, 1e-300), axis=1)


def load_ucalgary(sensor: str = "ln100", orientation: str = "up", *, root=None,
                  adi_gyro_unit: str = "rad/s") -> BenchRecord:
    """The UCalgary x-axis up/down static records. ``sensor``: ``"ln100"`` (64 Hz, gyro deg/s)
    or ``"adi"`` (100 Hz, gyro unit uncertain: ``adi_gyro_unit`` ``"rad/s"`` (default, see the
    README) or ``"deg/s"``). Conditions: latitude 51.0784 deg, the orientation, the sensor."""
    if sensor not in ("ln100", "adi") or orientation not in ("up", "down"):
        raise ValueError(f"sensor={sensor!r}, orientation={orientation!r}: use 'ln100' or 'adi', "
                         "and 'up' or 'down'")
    folder = data_root(root) / "ucalgary_ln100_adi"
    if sensor == "ln100":
        path = folder / f"x_LN100_{orientation}.ins"
        # the folder README mentions 8 spare bytes in x_LN100_up.ins; its 1,076,152 bytes are in
        # fact exactly 19,217 records of 56 bytes, so the strict reader applies
        data = read_float64_records(path, 7)
        w = data[:, 1:4] * units.DEG
    else:
        path = folder / f"x_adi_{orientation}.txt"
        data = read_text_columns(path, 7)
        if adi_gyro_unit not in ("rad/s", "deg/s"):
            raise ValueError(f"adi_gyro_unit={adi_gyro_unit!r}; use 'rad/s' or 'deg/s'")
        w = data[:, 1:4] * (units.DEG if adi_gyro_unit == "deg/s" else 1.0)
    return _imu_record(data[:, 0], w, data[:, 4:7],
                       {"latitude_deg": 51.0784, "orientation": f"x {orientation}",
                        "sensor": sensor, "source": str(path.name)})


def load_ucalgary_pair(sensor: str = "ln100", *, root=None, **kwargs) -> BenchRecord:
    """The x-down and x-up statics as one two-position record on the real time axis (down was
    recorded first; the 35 s between them is the turn). Condition ``positions`` = ("x down",
    "x up")."""
    parts = [load_ucalgary(sensor, o, root=root, **kwargs) for o in ("down", "up")]
    t = [np.asarray(p.t) + p.conditions["t0_s"] for p in parts]
    c = parts[0].conditions
    attrs = {k: c[k] for k in ("latitude_deg", "sensor")} | {
        "positions": ("x down", "x up"), "source": "x_*_down + x_*_up"}
    if t[1][0] <= t[0][-1]:  # the ADI files share one clock origin: lay them end to end
        t[1] = t[1] - t[1][0] + t[0][-1] + 1.0
        attrs["time_note"] = "files overlap in time; the up record is placed 1 s after the down"
    y = np.concatenate([np.asarray(p.y) for p in parts])
    return _imu_record(np.concatenate(t), y[:, :3], y[:, 3:], attrs)


XSENS_ACC_PER_COUNT = 2.41e-3  # m/s^2 (README: fitted scale)
XSENS_GYRO_PER_COUNT = 1.0 / 6258.0  # rad/s (IMU-TK's initial guess)
XSENS_ZERO = 32768.0


def load_xsens(*, root=None) -> BenchRecord:
    """IMU-TK's hand-placed multi-position Xsens MTi record (raw counts). Documented nominal
    conversion: (count - 32768) x 2.41e-3 m/s^2 and x 1/6258 rad/s; the biases and scale errors
    this leaves are what a fit/diagnosis must find. The gyro's ADC rails (>= 65000 or <= 1000
    counts, the last 2 s) are masked. Gravity 9.81744 m/s^2 (IMU-TK's value for this set)."""
    folder = data_root(root) / "imu_tk_xsens"
    acc = read_text_columns(folder / "xsens_acc.mat", 4)
    gyr = read_text_columns(folder / "xsens_gyro.mat", 4)
    if acc.shape != gyr.shape or np.any(acc[:, 0] != gyr[:, 0]):
        raise DataFileError(f"{folder}: xsens_acc.mat and xsens_gyro.mat have different time "
                            "stamps; they must be the two halves of one record")
    rail = np.any((gyr[:, 1:] >= 65000) | (gyr[:, 1:] <= 1000) | (acc[:, 1:] >= 65000)
                  | (acc[:, 1:] <= 1000), axis=1)
    t = acc[:, 0]
    return _imu_record(t, (gyr[:, 1:] - XSENS_ZERO) * XSENS_GYRO_PER_COUNT,
                       (acc[:, 1:] - XSENS_ZERO) * XSENS_ACC_PER_COUNT, {
                           "sensor": "Xsens MTi (raw counts)", "source": "imu_tk xsens_*.mat",
                           "gravity_mps2": 9.81744, "rate_hz": 100.0,
                           "conversion": "(count-32768)*2.41e-3 m/s^2; (count-32768)/6258 rad/s",
                           "masked_s": _spans(t - t[0], rail, pad=10)})


def load_mpu9150(unit: int = 0, *, root=None) -> BenchRecord:
    """One of the five MPU-9150 units (``unit`` 0..4): factory-scaled SI, 100 Hz, no time stamps.
    Gravity 9.81 m/s^2 (the upstream code's value); latitude not given."""
    if unit not in range(5):
        raise ValueError(f"unit={unit!r}; the mpu9150_mikov set has units 0..4")
    path = data_root(root) / "mpu9150_mikov" / f"imu{unit}.log"
    a = read_text_columns(path, 6)
    t = np.arange(len(a)) / 100.0
    return _imu_record(t, a[:, 3:], a[:, :3], {
        "sensor": f"MPU-9150 unit {unit}", "source": path.name, "rate_hz": 100.0,
        "gravity_mps2": 9.81})


ADIS_KNOCK_SIGMAS = 12.0
"""Knock threshold of the ADIS16405 records, in robust sigmas (MAD of first differences): at 20
the first disturbance the data README lists for run 4 (samples 11,711-11,899, up to 4.1 deg/s
against a 0.35 deg/s noise) stayed unmasked; at 8 every run shows dozens of single spikes (the
sensor's tails are heavier than Gaussian), which are noise, not knocks."""


def load_smac(name: str = "adis", run: int = 1, *, root=None, mask: bool = True) -> BenchRecord:
    """SMAC-Group ``imudata`` long statics. ``name="adis"``: ADIS16405 run 1..6 (2.78 h, 100 Hz,
    z axis vertical; counts x 0.05 deg/s and x 3.33 mg, g = 9.80665 m/s^2). ``name="mtig"``:
    the MTi-G gyro x error signal (5000 s, unit not stated, taken as rad/s), channel ``wx`` only.
    With ``mask``, knocks are masked in ``masked_s``: samples more than
    :data:`ADIS_KNOCK_SIGMAS` robust sigmas from their 10-s block's median on any channel, each
    widened by 0.5 s either side: in run 4 the three disturbances its data README lists and two
    more single spikes, in run 1 two start-up spikes (3.3 and 6.8 s), nothing in runs 2, 3, 5, 6.
    The MTi-G record's outliers are *not* masked, they are what the diagnosis is to find."""
    folder = data_root(root) / "smac_imudata"
    if name == "adis":
        if run not in range(1, 7):
            raise ValueError(f"run={run!r}; the ADIS16405 set has runs 1..6")
        path = folder / f"adis16405_run{run}.npz"
        z = _npz(path, ("gyro_counts", "accel_counts", "gyro_lsb_dps", "accel_lsb_g", "fs_hz"))
        fs = float(z["fs_hz"])
        w = z["gyro_counts"].astype(float) * float(z["gyro_lsb_dps"]) * units.DEG
        f = z["accel_counts"].astype(float) * float(z["accel_lsb_g"]) * units.G0
        t = np.arange(len(w)) / fs
        attrs = {"sensor": f"ADIS16405 run {run}", "source": path.name, "rate_hz": fs,
                 "conversion": "counts*0.05 deg/s; counts*3.33 mg (g = 9.80665)",
                 "gravity_mps2": units.G0}
        if mask:
            attrs["masked_s"] = _spans(t, _robust_outliers(np.concatenate([w, f], 1),
                                                           ADIS_KNOCK_SIGMAS), 50)
        return _imu_record(t, w, f, attrs)
    if name == "mtig":
        path = folder / "mtig_cont_imu1_gyrox.npz"
        z = _npz(path, ("gyro_x", "fs_hz"))
        fs = float(z["fs_hz"])
        w = np.asarray(z["gyro_x"], float)[:, None]
        return _imu_record(np.arange(len(w)) / fs, w, None, {
            "sensor": "Xsens MTi-G gyro x (bias removed)", "source": path.name, "rate_hz": fs,
            "conversion": "unit not stated, taken as rad/s"}, channels=("wx",))
    raise ValueError(f"name={name!r}; use 'adis' or 'mtig'")


def _npz(path, keys):
    if not Path(path).is_file():
        raise DataFileError(f"{path}: no such file; check the data folder (see its README)")
    try:
        z = np.load(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a file error here
        raise DataFileError(f"{path}: cannot be read as .npz ({type(exc).__name__}: {exc}); "
                            "is the file complete?") from None
    missing = [k for k in keys if k not in z.files]
    if missing:
        raise DataFileError(f"{path}: lacks the key(s) {missing}; it holds {z.files}")
    return {k: z[k] for k in keys}


MPU6050_LSB_PER_G = 16384.0
MPU6050_LSB_PER_DPS = 131.0
MPU6050_FILES = ("multipos_calibration", "static_tinit_7min", "rot_90deg_x", "static_test_100s")


def load_mpu6050(name: str = "multipos_calibration", *, root=None) -> BenchRecord:
    """The small MPU-6050 set (``name`` one of MPU6050_FILES): CSV of raw counts after a 5-line
    header (``Fs,<hz>`` ... ``ax,ay,az,gx,gy,gz``); ±2 g (16384 LSB/g) and ±250 deg/s (131 LSB per
    deg/s), g = 9.80665 m/s^2."""
    if name not in MPU6050_FILES:
        raise ValueError(f"name={name!r}; the mpu6050_unc files are {MPU6050_FILES}")
    path = data_root(root) / "mpu6050_unc" / f"{name}.csv"
    head = _csv_header(path)
    a = read_text_columns(path, 6, delimiter=",", skip=5)
    t = np.arange(len(a)) / head["fs"]
    return _imu_record(t, a[:, 3:] / MPU6050_LSB_PER_DPS * units.DEG,
                       a[:, :3] / MPU6050_LSB_PER_G * units.G0, {
                           "sensor": "MPU-6050", "source": path.name, "rate_hz": head["fs"],
                           "conversion": "counts/16384 g; counts/131 deg/s",
                           "gravity_mps2": units.G0})


def _csv_header(path):
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path}: no such file; check the data folder (see its README)")
    with path.open() as fh:
        lines = [fh.readline().strip() for _ in range(5)]
    key, _, val = lines[0].partition(",")
    if key != "Fs":
        raise DataFileError(f"{path}, line 1: {lines[0]!r}; expected 'Fs,<sampling rate in Hz>'")
    try:
        fs = float(val)
    except ValueError:
        raise DataFileError(f"{path}, line 1: sampling rate {val!r} is not a number") from None
    cols = [c.strip() for c in lines[4].split(",")]
    if cols != ["ax", "ay", "az", "gx", "gy", "gz"]:
        raise DataFileError(f"{path}, line 5: columns {cols}; expected ax,ay,az,gx,gy,gz in raw "
                            "counts (other units or orders are not this format: convert first)")
    return {"fs": fs}


REAL_DATA_SETS = {
    "ln100_pair": lambda root=None: load_ucalgary_pair("ln100", root=root),
    "adi_pair": lambda root=None: load_ucalgary_pair("adi", root=root),
    "xsens": lambda root=None: load_xsens(root=root),
    **{f"mpu9150_{u}": (lambda root=None, u=u: load_mpu9150(u, root=root)) for u in range(5)},
    **{f"adis_{r}": (lambda root=None, r=r: load_smac("adis", r, root=root)) for r in range(1, 7)},
    "mtig": lambda root=None: load_smac("mtig", root=root),
    **{f"mpu6050_{n}": (lambda root=None, n=n: load_mpu6050(n, root=root))
       for n in MPU6050_FILES},
}
"""Name -> loader of every real record (the names ``gyrojax diagnose --dataset`` accepts)."""
